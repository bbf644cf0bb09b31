"""Regressors of the identification models (3-X paper eqs. 37-45, 54-57): the observation matrix W
and vector Y of each model, built from :class:`Processed` signals. Pure functions on arrays.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from twin.identification.processing import IdentificationError, Processed
from twin.model import dynamics
from twin.model.params import Params

FloatArray = NDArray[np.float64]

W_JOINT = 100.0  # weight of the joint rows of eq. 44 (§5.1.3)
MIN_TENSION_N = 2.0  # tension rows of a cable below this (N) are dropped: a slack cable obeys no eq. 54


def param_names(symbol: str, n: int) -> tuple[str, ...]:
    return tuple(f"{symbol}({j + 1})" for j in range(n))


MIN_MOVING = 16  # decimated samples (≈ 0.5 s) a motor must turn in each direction to excite f_s


def check_friction_excitation(proc: Processed, params: Params) -> None:
    """f_s(j) needs motor j to turn both ways at speeds where eq. 37 is near saturation
    (|θ̇| > 1/c_s, a > 0.5); below that its regressor column is numerically, not exactly, zero."""
    v = proc.theta_dot[proc.fitted] * params.friction.c_s
    poor = [j for j in range(v.shape[1]) if min((v[:, j] > 1).sum(), (v[:, j] < -1).sum()) < MIN_MOVING]
    if poor:
        names = ", ".join(f"f_s({j + 1})" for j in poor)
        raise IdentificationError(
            f"regressor is rank-deficient in practice: {names} not excited (motor(s) "
            f"{', '.join(str(j + 1) for j in poor)} turned faster than {1 / params.friction.c_s:.1f} rad/s in each "
            f"direction for less than {MIN_MOVING} samples); run the identification trajectory"
            + "".join(f" (counted on the instants fitted: {note})" for note in proc.notes)
        )


def friction_shape(proc: Processed, params: Params) -> FloatArray:
    """a = (2/π)·arctan(c_s·θ̇) (eq. 37), or sign(θ̇) for the eq. 36 model, (n, n_cables)."""
    return dynamics.friction_shapes(params.friction.c_s, params.friction.model == "sign", proc.theta_dot)


def ia_over_rho(params: Params) -> float:
    g = params.geometry
    return params.motors.I_a * g.R / g.r_d  # (R/r_d)·I_a: N per rad/s² of θ̈


def joint_rows(proc: Processed, params: Params, elastic: bool) -> tuple[FloatArray, FloatArray]:
    """Joint rows of eqs. 38/44 (our sign): D = Z·diag(a) (n, N, nc), y = Z(f − I_a(R/r_d)²ẍ_c) − Mα̈ − c − g."""
    a = friction_shape(proc, params)
    D = proc.Z * a[:, None, :]
    g = params.geometry
    drive = proc.force - (params.motors.I_a * (g.R / g.r_d) ** 2 * proc.x_c_ddot if elastic else 0.0)
    y = (np.einsum("nij,nj->ni", proc.Z, drive) - np.einsum("nij,nj->ni", proc.M, proc.alpha_ddot) - proc.c - proc.g)
    return D, y


def tension_mask(t_c: FloatArray) -> NDArray[np.bool_]:
    return t_c >= MIN_TENSION_N


def moving_mask(proc: Processed, params: Params) -> NDArray[np.bool_]:
    """(n, n_cables): motor j turns at |θ̇| ≥ 1/c_s, where eq. 37's arctan is at least half
    saturated. Slower, the friction is what the model guesses it to be: a real motor there sticks
    or follows a Stribeck curve, its friction anywhere within ±(static level), so the tension of
    eq. 55 (t_c = f − a·f_s − …) is unknown by up to ~f_s. Tension rows keep moving motors only:
    on the robot truth (set-valued stiction) this alone takes k from 21-37 % low to 7-18 % low;
    on a truth with eq. 37's friction it changes k and λ by less than their σ. Instants not fitted
    (``Processed.fitted``: a gap in the record) are False."""
    return (np.abs(proc.theta_dot) * params.friction.c_s >= 1.0) & proc.fitted[:, None]


def cable_tension(proc: Processed, params: Params, f_s: FloatArray) -> FloatArray:
    """Eq. 41/55: t_c = f − diag(a)f_s − (R/r_d)I_a·θ̈ (N), (n, n_cables)."""
    return proc.force - friction_shape(proc, params) * np.asarray(f_s) - ia_over_rho(params) * proc.theta_ddot


def stacked_rows(fitted: NDArray[np.bool_], per_sample: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(instant, equation) of each row of an (n, per_sample, ·) block's ``fitted`` instants reshaped
    to rows (``block[fitted].reshape(-1, ·)``)."""
    instants = np.flatnonzero(fitted).astype(np.int64)
    return np.repeat(instants, per_sample), np.tile(np.arange(per_sample, dtype=np.int64), len(instants))


def masked_rows(mask: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(instant, cable) of each row of ``block[mask]`` for an (n, n_cables) ``mask``."""
    i, j = np.nonzero(mask)
    return i.astype(np.int64), j.astype(np.int64)
