"""Instruments for the stretch regressors from the identified model re-simulated (IDIM-IV).

The stretch x_c = l_c(α) − l_c0 + ρ·θ (eq. 27) takes α from the camera: 1° of noise on α_IP makes
the regressors x_c, x_c·t_c, ẋ_c noisy and least squares biased (errors in variables). An
instrument must follow x_c without sharing that noise, and without being the measured tension
either: t_c = f − friction − inertia is the fitted quantity, and on the prototype the forces are
open-loop current commands, so its errors (torque constants, ripple, friction the model lacks)
are in both the instrument and the residual and the estimate is biased as much as with no
instrument at all. This module therefore simulates the neck with the model being identified,
driven by the motor encoders only: at every identification instant, α_sim solves the neck's
equation (32) with the cable tensions of the cable model,

    Z(α)·t(x(α, θ)) = g(α),   x = l_c(α) − l_c0 + ρ·θ,   t = k·x/(1 − λ·x) ≥ 0,

θ the (filtered) encoder angles (quasi-static: the excitation is slow, f_99 ≈ 0.4 Hz). The
instruments are x_sim, x_sim·t_sim, ẋ_sim: functions of the encoders and the model, free of
camera noise and of force errors. They depend on the estimate (k, λ), so the estimation is
iterated to a fixed point (BIRDy's IDIM-IV: Janot, Vandanjon & Gautier, IEEE TCST 2014, where
the instruments come from the identified model simulated on the same inputs). Pure functions.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from twin.identification.processing import Processed
from twin.model import dynamics
from twin.model.numeric import Model

FloatArray = NDArray[np.float64]

NEWTON_STEPS = 20  # chord steps converge linearly; a slow one refreshes its Jacobian (below)
NEWTON_TOL_RAD = 1e-7  # rad, ≈ 1/1000 of an encoder count at the joint
FD_STEP_RAD = 1e-6
CHORD_MIN_CONTRACTION = 0.25  # a step not below this fraction of the last one gets a fresh Jacobian


def _stretch(m: Model, alpha: FloatArray, theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """x (m) of eq. 27 at α and θ, with Z and g there (:func:`dynamics.statics`)."""
    l_c, Z, g = dynamics.statics(m, alpha)
    return l_c - m.l_c0 + m.rho * theta, Z, g


def _residual(m: Model, alpha: FloatArray, theta: FloatArray, k: FloatArray, lam: FloatArray,
              inertial: FloatArray) -> tuple[FloatArray, FloatArray]:
    x, Z, g = _stretch(m, alpha, theta)
    t = np.maximum(dynamics.cable_tension_law(k, lam, 0.0, x, 0.0), 0.0)
    return np.einsum("nij,nj->ni", Z, t) - g - inertial, x


def neck_equilibrium(m: Model, theta: FloatArray, k: FloatArray, lam: FloatArray, alpha0: FloatArray,
                     inertial: FloatArray | None = None, jacobian0: FloatArray | None = None,
                     ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """α (n, N) solving Z·t(x(α, θ)) = g(α) + ``inertial`` at every instant, from ``alpha0``, each
    instant until its step is below ``NEWTON_TOL_RAD``; returns (α, x, the Jacobians (n, N, N)).

    Batched chord iterations: an instant keeps its Jacobian (finite differences, N evaluations of
    the model) while its steps shrink at least fourfold, and gets a fresh one where they do not.
    ``jacobian0``: the Jacobians of an earlier solve at nearby α and (k, λ) (the IV iteration's
    previous simulation), used from the first step. Why: the Jacobian cost three quarters of the
    evaluations, and a warm start's root moves by little. The same roots to the tolerance
    (tests/test_identification_uncertainty.py); `auto` on a robot-truth campaign 2.7 → 1.7 s with
    the IV's warm starts (benchmarks/identification.py)."""
    alpha = np.array(alpha0, dtype=float)
    inertial = np.zeros_like(alpha) if inertial is None else inertial
    n, N = alpha.shape
    J = np.empty((n, N, N))
    fresh = np.ones(n, dtype=bool)
    if jacobian0 is not None and np.shape(jacobian0) == (n, N, N) and np.all(np.isfinite(jacobian0)):
        J[:] = jacobian0
        fresh[:] = False
    last = np.full(n, np.inf)
    active = np.arange(n)  # instants still iterating: one converged stops costing evaluations
    for _ in range(NEWTON_STEPS):
        a, th, ine = alpha[active], theta[active], inertial[active]
        F, _ = _residual(m, a, th, k, lam, ine)
        new = fresh[active]
        if np.any(new):
            idx = active[new]
            for i in range(N):
                da = np.zeros(N)
                da[i] = FD_STEP_RAD
                J[idx, :, i] = (_residual(m, a[new] + da, th[new], k, lam, ine[new])[0] - F[new]) / FD_STEP_RAD
            fresh[idx] = False
        try:
            step = np.linalg.solve(J[active], -F[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # pragma: no cover
            step = np.stack([np.linalg.lstsq(J[i], -f, rcond=None)[0] for i, f in zip(active, F, strict=True)])
        step = np.clip(step, -0.05, 0.05)  # rad: a Newton step never jumps across the workspace
        alpha[active] += step
        size = np.max(np.abs(step), axis=1)
        fresh[active] = size > CHORD_MIN_CONTRACTION * last[active]
        last[active] = size
        active = active[size >= NEWTON_TOL_RAD]
        if not len(active):
            break
    return alpha, _stretch(m, alpha, theta)[0], J


class Simulated(NamedTuple):
    """The neck re-simulated on the encoders: α (n, N), stretch x, ẋ and tension t (n, n_cables);
    ``jacobian`` (n, N, N) the equilibrium's, for the next solve to start from."""

    alpha: FloatArray
    x: FloatArray
    x_dot: FloatArray
    t: FloatArray
    jacobian: FloatArray | None = None


def simulated_stretch(m: Model, proc: Processed, k: FloatArray, lam: FloatArray,
                      alpha0: FloatArray | None = None, jacobian0: FloatArray | None = None) -> Simulated:
    """The stretch the model (k, λ) predicts on the recorded encoder angles, quasi-static (the
    inertial terms M·α̈ + c of a second pass moved k and λ by less than 0.05 σ on the twin, at
    twice the cost). ``alpha0``: where Newton starts (default: the camera's α, which only seeds
    the root it converges to); ``jacobian0``: an earlier solve's Jacobians (:func:`neck_equilibrium`),
    with that solve's α as ``alpha0``."""
    alpha, x, J = neck_equilibrium(m, proc.theta, k, lam, proc.alpha if alpha0 is None else alpha0,
                                   jacobian0=jacobian0)
    t = np.maximum(dynamics.cable_tension_law(k, lam, 0.0, x, 0.0), 0.0)
    return Simulated(alpha, x, np.gradient(x, 1.0 / proc.rate_hz, axis=0), t, J)
