"""Identification of friction and cable stiffness (3-X paper §5), as pure functions on arrays.

Pipeline (every function takes and returns arrays in SI units; θ at the motor shaft in rad)::

    data = CampaignData(t_s, theta_rad, force_N, t_ip_s, alpha_ip_rad)   # checked on creation
    proc = preprocess(data, params)                  # §5.2.1: filter, differentiate, decimate
    fric = identify_friction(proc, params)           # eqs. 38 (rigid cables) -> f_s
    comp = identify_complete(proc, params)           # eqs. 43-45, W = 100 -> k, c_a, f_s
    var = identify_variable(proc, params, fric.values)   # eqs. 54-57 -> k, λ, c_a (friction-alone f_s)
    est = {"friction": fric, "complete": comp, "variable": var}   # or identify_all(proc, params)
    new_params, report, prov = identified_params(params, est, provenance)   # prov: + kept_base
    val = validate(data, proc, new_params, est)   # eqs. 51-53, 42, 33, 35 (Figs. 4-8)

twin.identification.record.identify_record runs it on an MCAP archive (xneck identify, the console).

Signs. We use the physical stretch x_c = l_c − l_c0 + (r_d/R)·θ (docs/model.md), so in our
sign eq. 32 reads M·α̈ + c + g = Z(f − f_friction − I_a(R/r_d)²·ẍ_c) and the joint rows of
eqs. 38/44 become  Z·diag(a)·f_s = Z(f − I_a(R/r_d)²ẍ_c) − M·α̈ − c − g  with
a = (2/π)·arctan(c_s·θ̇) (eq. 37). Eqs. 41/42/54-57 are written in θ̈ and t_c and do not change.

Eqs. 46-47 as extracted (y = f − (R/r_d)I_a·θ̈, D = diag(a)) cannot identify friction: y is the
cable tension plus friction, ~30 N against f_s ~15 N. The paper calls it "the model without cable
elasticity", i.e. the joint rows of eq. 38 with ẍ_c = 0; that is what :func:`identify_friction`
solves (three rows per sample, four parameters).

Least squares (eqs. 48-50): v = W⁺Y through the SVD; σ_ρ² = ‖Y − Wv‖²/(r − n_p),
C_X = σ_ρ²(WᵀW)⁻¹, σ_i = √C_X(i,i), relative σ_i = σ_i/|v_i|. A parameter whose relative σ
exceeds ``threshold`` (10 % by default), or whose value is physically impossible (k ≤ 0; f_s, λ,
c_a < 0), is *badly identified*: it is flagged in the :class:`Estimate`, and
:func:`identified_params` keeps the base value for it (the paper's damping).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twin.model import dynamics
from twin.model.numeric import CableModelName, build
from twin.model.params import Params, params_from_dict

__all__ = [
    "DECIMATION",
    "DEFAULT_THRESHOLD",
    "W_JOINT",
    "AlphaHat",
    "CampaignData",
    "Estimate",
    "IdentificationError",
    "ParameterReport",
    "Processed",
    "Provenance",
    "Validation",
    "cutoff_rule",
    "identified_params",
    "identify_complete",
    "identify_friction",
    "identify_variable",
    "least_squares",
    "preprocess",
    "validate",
    "write_identified",
]

FloatArray = NDArray[np.float64]

DECIMATION = 16  # 500 Hz -> 31.25 Hz, "the value closest to 30 Hz" (§5.2.1)
W_JOINT = 100.0  # weight of the joint rows of eq. 44 (§5.1.3)
DEFAULT_THRESHOLD = 0.10  # relative σ above which a parameter is badly identified
MIN_SAMPLES = 64  # decimated samples (≈ 2 s at 31.25 Hz) below which nothing is identified
MIN_TENSION_N = 2.0  # tension rows of a cable below this (N) are dropped: a slack cable obeys no eq. 54
# Cutoff rule (see cutoff_rule): f_c = CUTOFF_FACTOR · f_99 clipped to [CUTOFF_MIN_HZ, 0.8·f_Nyquist].
CUTOFF_FACTOR = 4.0
CUTOFF_MIN_HZ = 0.5
RANK_TOL = 1e-7  # relative singular value below which the (column-scaled) regressor is rank-deficient


class IdentificationError(ValueError):
    """The data cannot give a trustworthy identification; the message says why and what to fix."""


# --- campaign data ------------------------------------------------------------------------------


def _as_matrix(name: str, x: Any, cols: int | None) -> FloatArray:
    try:
        arr = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise IdentificationError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim != 2 or (cols is not None and arr.shape[1] != cols):
        want = f"(T, {cols})" if cols is not None else "(T, n)"
        raise IdentificationError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def _check_finite(name: str, arr: FloatArray, t: FloatArray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        rows = np.flatnonzero(bad.reshape(len(arr), -1).any(axis=1))
        raise IdentificationError(
            f"{name} has {bad.sum()} NaN/inf value(s), first at sample {rows[0]} (t = {t[rows[0]]:.4f} s); "
            "remove or repair them before identifying"
        )


def _check_times(name: str, t: FloatArray) -> None:
    if t.ndim != 1:
        raise IdentificationError(f"{name} must be a 1-D array of times (s), got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise IdentificationError(f"{name} has NaN/inf times")
    d = np.diff(t)
    if np.any(d <= 0):
        k = int(np.flatnonzero(d <= 0)[0])
        raise IdentificationError(f"{name} must increase strictly: t[{k}] = {t[k]} s, t[{k + 1}] = {t[k + 1]} s")


@dataclass(frozen=True, eq=False)
class CampaignData:
    """One identification campaign, as recorded (SI units).

    t_s (T,): encoder/force sample times at the control rate (500 Hz), s.
    theta_rad (T, n_cables): encoder angles at the motor shaft, rad (θ = 0 at the straight,
        unloaded neck, eq. 20).
    force_N (T, n_cables): motor forces applied over each period, N.
    t_ip_s (K,): capture times of the camera frames (same clock as ``t_s``), s.
    alpha_ip_rad (K, n_joints): α_IP from image processing, rad.
    campaign: id or path, kept for provenance.
    excitation_alpha_rad (N, n_joints) or None: the excitation trajectory α^d, rad, sampled at the
        encoder rate, when known (a campaign archive records its trajectory). Only its spectrum is
        used, to set the filter cutoff (:func:`cutoff_rule`), so it need not be aligned with t_s.

    Raises :class:`IdentificationError` on wrong shapes, NaNs, non-increasing times, too few
    samples, or camera frames that do not cover the encoder record.
    """

    t_s: FloatArray
    theta_rad: FloatArray
    force_N: FloatArray
    t_ip_s: FloatArray
    alpha_ip_rad: FloatArray
    campaign: str = "unnamed"
    excitation_alpha_rad: FloatArray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=float)
        t_ip = np.asarray(self.t_ip_s, dtype=float)
        _check_times("t_s", t)
        _check_times("t_ip_s", t_ip)
        theta = _as_matrix("theta_rad", self.theta_rad, None)
        force = _as_matrix("force_N", self.force_N, theta.shape[1])
        alpha = _as_matrix("alpha_ip_rad", self.alpha_ip_rad, None)
        for name, arr, times in (("theta_rad", theta, t), ("force_N", force, t), ("alpha_ip_rad", alpha, t_ip)):
            if len(arr) != len(times):
                tname = "t_ip_s" if name == "alpha_ip_rad" else "t_s"
                raise IdentificationError(f"{name} has {len(arr)} rows but {tname} has {len(times)} times")
        _check_finite("theta_rad", theta, t)
        _check_finite("force_N", force, t)
        _check_finite("alpha_ip_rad", alpha, t_ip)
        need = MIN_SAMPLES * DECIMATION
        if len(t) < need:
            raise IdentificationError(
                f"too few encoder samples: {len(t)} ({t[-1] - t[0] if len(t) > 1 else 0:.2f} s); identification "
                f"needs at least {need} (about {need / 500:.1f} s at 500 Hz), a full excitation trajectory is ~100 s"
            )
        if len(t_ip) < MIN_SAMPLES:
            raise IdentificationError(f"too few camera frames: {len(t_ip)}, need at least {MIN_SAMPLES}")
        overlap = min(t[-1], t_ip[-1]) - max(t[0], t_ip[0])
        if overlap < 0.5 * (t[-1] - t[0]):
            raise IdentificationError(
                f"camera frames ({t_ip[0]:.2f}-{t_ip[-1]:.2f} s) cover less than half of the encoder record "
                f"({t[0]:.2f}-{t[-1]:.2f} s): are both on the same clock?"
            )
        if self.excitation_alpha_rad is not None:
            exc = _as_matrix("excitation_alpha_rad", self.excitation_alpha_rad, alpha.shape[1])
            if len(exc) < MIN_SAMPLES or not np.all(np.isfinite(exc)):
                raise IdentificationError(f"excitation_alpha_rad must hold at least {MIN_SAMPLES} finite rows, "
                                          f"got {len(exc)} rows, {int((~np.isfinite(exc)).sum())} non-finite values")
            object.__setattr__(self, "excitation_alpha_rad", exc)
        for name, arr in (("t_s", t), ("theta_rad", theta), ("force_N", force), ("t_ip_s", t_ip), ("alpha_ip_rad", alpha)):
            object.__setattr__(self, name, arr)

    @property
    def n_cables(self) -> int:
        return int(self.theta_rad.shape[1])

    @property
    def n_joints(self) -> int:
        return int(self.alpha_ip_rad.shape[1])

    @property
    def rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.t_s)))


# --- processing (§5.2.1) ----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Processed:
    """Filtered, differentiated, decimated signals on the identification instants ``t_s``.

    Arrays are (n,) or (n, ·) at 31.25 Hz: θ, θ̇, θ̈ (rad, rad/s, rad/s²) and f (N) from the
    encoders (filtered at 500 Hz, then decimated by 16); α, α̇, α̈ from α_IP (filtered at the
    camera rate, linearly interpolated to ``t_s``, central differences); x_c, ẋ_c, ẍ_c (m, m/s,
    m/s²) from eq. 27 (our sign); the model terms Z, M, c, g at (α, α̇).
    ``fast_*``: the 500 Hz record (raw θ, filtered θ̇, f) for the 2 ms estimators of eqs. 35/58.
    """

    t_s: FloatArray
    theta: FloatArray
    theta_dot: FloatArray
    theta_ddot: FloatArray
    force: FloatArray
    alpha: FloatArray
    alpha_dot: FloatArray
    alpha_ddot: FloatArray
    x_c: FloatArray
    x_c_dot: FloatArray
    x_c_ddot: FloatArray
    Z: FloatArray
    M: FloatArray
    c: FloatArray
    g: FloatArray
    cutoff_hz: float
    f_99_hz: float
    rate_hz: float
    bandwidth_from: str  # "alpha_d" (the excitation trajectory), "theta_dot" (the encoders) or "given"
    fast_t_s: FloatArray
    fast_theta: FloatArray
    fast_theta_dot: FloatArray
    fast_force: FloatArray

    @property
    def n(self) -> int:
        return len(self.t_s)


def cutoff_rule(velocity: FloatArray, rate_hz: float, nyquist_hz: float) -> tuple[float, float]:
    """Cutoff (Hz) of the zero-phase Butterworth filter, and the motion bandwidth f_99 (Hz).

    Rule (after Pham, Gautier & Poignet 2001, ref. [37]: the cutoff sits a few times above the
    bandwidth of the motion, so that the filter removes noise and leaves the dynamics alone, and
    both sides of the linear model are filtered alike): f_99 is the frequency below which 99 % of
    the energy of ``velocity`` lies; f_c = 4·f_99, at least 0.5 Hz and at most 0.8 of the Nyquist
    frequency of the slowest stream (the camera, 15 Hz). :func:`preprocess` passes the velocity of
    the excitation trajectory α̇^d when the campaign records it (f_99 = 0.40 Hz on the §5.2.2
    trajectory, f_c = 1.6 Hz), else the motor velocities θ̇. θ̇ is a fallback: it also carries the
    motor-cable mode (≈ 18 kg of reflected motor inertia on a 5-8 kN/m cable, ≈ 3 Hz), which rings
    when the cable damping is small and then holds ~1 % of the θ̇ energy: enough to move f_99 from
    0.43 to 1.7 Hz, hence f_c from 1.7 to 6.8 Hz, which lets α_IP noise into x_c and, twice
    differentiated, into ẍ_c (the Γ_rf error of eq. 52 grows fifteenfold on the twin).
    Why 4 and not the usual 5-10: α_IP carries 1° of white noise up to 15 Hz that enters the
    regressor x_c; the friction regressor arctan(c_s·θ̇) is nonlinear, so a too-low cutoff rounds
    its sign changes (f_s is 2 % low at 0.9 Hz, 0.1 % at 1.7 Hz on the twin).
    """
    v = velocity - velocity.mean(axis=0)
    spec = np.abs(np.fft.rfft(v, axis=0)) ** 2
    power = spec.sum(axis=1)
    cum = np.cumsum(power)
    freqs = np.fft.rfftfreq(len(v), 1.0 / rate_hz)
    if cum[-1] <= 0.0:
        f_99 = CUTOFF_MIN_HZ
    else:
        f_99 = float(freqs[min(np.searchsorted(cum, 0.99 * cum[-1]), len(freqs) - 1)])
    return float(np.clip(CUTOFF_FACTOR * f_99, CUTOFF_MIN_HZ, 0.8 * nyquist_hz)), f_99


def _uniform(t: FloatArray, x: FloatArray, what: str, max_gap: float = 5.0) -> tuple[FloatArray, FloatArray, float]:
    """Samples on a uniform grid at the median rate (linear interpolation of jittered stamps).
    A gap longer than ``max_gap`` periods is lost data, not jitter: refuse it."""
    dt = float(np.median(np.diff(t)))
    gaps = np.diff(t) > max_gap * dt
    if gaps.any():
        k = int(np.flatnonzero(gaps)[0])
        raise IdentificationError(
            f"{what}: {gaps.sum()} gap(s) in the record, the first {t[k + 1] - t[k]:.3f} s long at t = {t[k]:.3f} s "
            f"(sampling period {dt * 1e3:.2f} ms); split the campaign or recover the data"
        )
    n = int(math.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
    grid = t[0] + dt * np.arange(n)
    # Length first: with a missed sample the grid is longer than the stamps and cannot be compared.
    if n == len(t) and np.allclose(grid, t, atol=1e-3 * dt, rtol=0.0):
        return t, x, dt
    return grid, np.column_stack([np.interp(grid, t, x[:, j]) for j in range(x.shape[1])]), dt


def _butter(x: FloatArray, cutoff_hz: float, rate_hz: float, order: int = 4) -> FloatArray:
    sos = signal.butter(order, cutoff_hz, fs=rate_hz, output="sos")
    return signal.sosfiltfilt(sos, x, axis=0)


def preprocess(data: CampaignData, params: Params, cutoff_hz: float | None = None) -> Processed:
    """§5.2.1: zero-phase Butterworth (order 4, :func:`cutoff_rule` unless ``cutoff_hz``) on θ,
    f and α_IP; central differences; θ and f decimated from 500 Hz to 31.25 Hz (anti-aliased,
    zero phase); α_IP interpolated linearly to the same instants; x_c from eq. 27 (our sign).

    Edge samples spoiled by the filters (two cutoff periods, at least 1 s, at each end) and
    instants outside the camera record are dropped.
    """
    m = build(params)
    if data.n_cables != m.n_cables or data.n_joints != m.n_joints:
        raise IdentificationError(
            f"campaign has {data.n_cables} motors and {data.n_joints} camera angles, the parameter set "
            f"{params.name!r} has {m.n_cables} cables and {m.n_joints} joints"
        )
    t, enc, dt = _uniform(data.t_s, np.hstack([data.theta_rad, data.force_N]), "encoder/force record")
    rate = 1.0 / dt
    t_ip, a_ip, dt_ip = _uniform(data.t_ip_s, data.alpha_ip_rad, "camera record")
    nc = m.n_cables
    raw_theta = enc[:, :nc]
    nyquist = 0.5 * min(rate / DECIMATION, 1.0 / dt_ip)
    if cutoff_hz is not None:
        fc, f_99, source = float(cutoff_hz), float("nan"), "given"
    elif data.excitation_alpha_rad is not None:
        fc, f_99 = cutoff_rule(np.gradient(data.excitation_alpha_rad, dt, axis=0), rate, nyquist)
        source = "alpha_d"
    else:
        fc, f_99 = cutoff_rule(np.gradient(raw_theta, dt, axis=0), rate, nyquist)
        source = "theta_dot"
    if not (0.0 < fc < nyquist):
        raise IdentificationError(f"cutoff {fc} Hz must be in (0, {nyquist:.2f}) Hz (Nyquist of the decimated/camera data)")

    filt = _butter(enc, fc, rate)
    theta_f, force_f = filt[:, :nc], filt[:, nc:]
    theta_dot = np.gradient(theta_f, dt, axis=0)
    theta_ddot = np.gradient(theta_dot, dt, axis=0)
    # Anti-aliased, zero-phase decimation (FIR: an order-8 IIR is unstable for a factor > 13).
    stack = np.hstack([theta_f, theta_dot, theta_ddot, force_f])
    dec = signal.decimate(stack, DECIMATION, ftype="fir", axis=0, zero_phase=True)
    t_dec = t[:: DECIMATION][: len(dec)]

    alpha_f = _butter(a_ip, fc, 1.0 / dt_ip)
    edge = max(1.0, 2.0 / fc)
    keep = (t_dec >= max(t[0], t_ip[0]) + edge) & (t_dec <= min(t[-1], t_ip[-1]) - edge)
    if keep.sum() < MIN_SAMPLES:
        raise IdentificationError(
            f"only {keep.sum()} identification instants remain after dropping {edge:.1f} s of filter edges "
            f"at each end; need at least {MIN_SAMPLES}"
        )
    t_dec, dec = t_dec[keep], dec[keep]
    theta_d, theta_dot_d, theta_ddot_d, force_d = np.split(dec, 4, axis=1)
    alpha = np.column_stack([np.interp(t_dec, t_ip, alpha_f[:, i]) for i in range(m.n_joints)])
    h = DECIMATION * dt
    alpha_dot = np.gradient(alpha, h, axis=0)
    alpha_ddot = np.gradient(alpha_dot, h, axis=0)
    terms = dynamics.evaluate(m, alpha, alpha_dot)
    x_c = terms.l_c - m.l_c0 + m.rho * theta_d  # eq. 27, physical stretch
    x_c_dot = np.gradient(x_c, h, axis=0)
    x_c_ddot = np.gradient(x_c_dot, h, axis=0)
    return Processed(
        t_s=t_dec, theta=theta_d, theta_dot=theta_dot_d, theta_ddot=theta_ddot_d, force=force_d,
        alpha=alpha, alpha_dot=alpha_dot, alpha_ddot=alpha_ddot,
        x_c=x_c, x_c_dot=x_c_dot, x_c_ddot=x_c_ddot,
        Z=terms.Z, M=terms.M, c=terms.c, g=terms.g,
        cutoff_hz=fc, f_99_hz=f_99, rate_hz=1.0 / h, bandwidth_from=source,
        fast_t_s=t, fast_theta=raw_theta, fast_theta_dot=theta_dot, fast_force=enc[:, nc:],
    )


# --- least squares (eqs. 48-50) -----------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Estimate:
    """Least-squares estimate of one identification model (eqs. 48-50).

    names: parameter names like ``"f_s(1)"``, ``"k(2)"``, ``"lambda(3)"``, ``"c_a(4)"``;
    values, sigma: SI units of each parameter; relative_sigma: σ_i/|v_i| (fraction, eq. 50);
    condition_number: of the observation matrix W; residual_norm: ‖Y − Wv‖ (units of Y);
    n_rows: r, rows of W; n_samples: identification instants used.
    """

    method: str
    equations: str
    names: tuple[str, ...]
    values: FloatArray
    sigma: FloatArray
    relative_sigma: FloatArray
    condition_number: float
    residual_norm: float
    n_rows: int
    n_samples: int
    threshold: float = DEFAULT_THRESHOLD
    estimator: str = "least squares"

    @property
    def out_of_range(self) -> NDArray[np.bool_]:
        """Values no physical cable or motor can have: k ≤ 0, or f_s, λ, c_a < 0. A model that
        does not fit (the linear one on variable-stiffness cables) buys its fit with such values,
        often with a small σ: Table 1's c_a(3) = −218 N·s/m is one."""
        symbols = np.array([n.split("(")[0] for n in self.names])
        return np.where(symbols == "k", self.values <= 0.0, self.values < 0.0)

    @property
    def badly_identified(self) -> NDArray[np.bool_]:
        """Relative σ above the threshold (or not finite), or out of physical range: never used
        silently."""
        r = self.relative_sigma
        return ~np.isfinite(r) | (r > self.threshold) | self.out_of_range

    def reason(self, i: int) -> str:
        """Why parameter ``i`` is badly identified ("" if it is not)."""
        r = self.relative_sigma[i]
        if not np.isfinite(r) or r > self.threshold:
            return f"badly identified, relative σ {100 * r:.1f} % > {100 * self.threshold:g} %"
        if self.out_of_range[i]:
            return "outside its physical range"
        return ""

    def vector(self, symbol: str) -> FloatArray:
        """Values of one symbol in cable order, e.g. ``vector("k")`` -> (n_cables,)."""
        idx = [i for i, n in enumerate(self.names) if n.split("(")[0] == symbol]
        if not idx:
            raise KeyError(f"{self.method} estimate has no parameter {symbol!r} (has {sorted({n.split('(')[0] for n in self.names})})")
        return self.values[idx]

    def flags(self, symbol: str) -> NDArray[np.bool_]:
        idx = [i for i, n in enumerate(self.names) if n.split("(")[0] == symbol]
        return self.badly_identified[idx]

    def rows(self) -> list[dict[str, Any]]:
        """One dict per parameter: name, value, sigma, relative_sigma, badly_identified, reason."""
        return [
            {"name": n, "value": float(v), "sigma": float(s), "relative_sigma": float(r), "badly_identified": bool(b),
             "reason": self.reason(i)}
            for i, (n, v, s, r, b) in enumerate(zip(self.names, self.values, self.sigma, self.relative_sigma,
                                                    self.badly_identified))
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method, "equations": self.equations, "parameters": self.rows(),
            "condition_number": self.condition_number, "residual_norm": self.residual_norm,
            "n_rows": self.n_rows, "n_samples": self.n_samples, "threshold": self.threshold,
            "estimator": self.estimator,
        }


def least_squares(
    W: FloatArray, Y: FloatArray, names: tuple[str, ...], *, method: str, equations: str,
    n_samples: int, threshold: float = DEFAULT_THRESHOLD, instruments: FloatArray | None = None,
) -> Estimate:
    """Solve W·v + ρ = Y (eq. 48) by v = W⁺Y (eq. 49) with σ's from eq. 50.

    With ``instruments`` Φ (same shape as W) the instrumental-variable solution
    v = (ΦᵀW)⁻¹ΦᵀY is returned instead, with C_X = σ_ρ²(ΦᵀW)⁻¹ΦᵀΦ(ΦᵀW)⁻ᵀ (eq. 50's IV form).
    Raises :class:`IdentificationError` when r ≤ n_p, W or Y is not finite, or W is
    rank-deficient (a parameter, or a combination, that the trajectory does not excite); the
    message names the parameters involved.
    """
    r, n_p = W.shape
    if r <= n_p:
        raise IdentificationError(f"{method}: {r} equations for {n_p} parameters; need r > n_p (eq. 48)")
    if not (np.all(np.isfinite(W)) and np.all(np.isfinite(Y))):
        raise IdentificationError(f"{method}: the observation matrix or vector has NaN/inf entries")
    scale = np.linalg.norm(W, axis=0)
    dead = scale <= 1e-300
    if dead.any():
        raise IdentificationError(
            f"{method}: regressor is rank-deficient, {', '.join(np.array(names)[dead])} never excited "
            "(zero column: did the motors move / were the cables stretched?)"
        )
    # Rank on the column-scaled matrix: the raw W mixes metres and newtons.
    _, s_scaled, Vt_scaled = np.linalg.svd(W / scale, full_matrices=False)
    if s_scaled[-1] < RANK_TOL * s_scaled[0]:
        weak = np.abs(Vt_scaled[-1])
        involved = np.array(names)[weak > 0.3 * weak.max()]
        raise IdentificationError(
            f"{method}: regressor is rank-deficient (scaled condition number "
            f"{s_scaled[0] / max(s_scaled[-1], 1e-300):.3g}); the trajectory does not excite {', '.join(involved)}"
        )
    U, s, Vt = np.linalg.svd(W, full_matrices=False)
    if instruments is None:
        v = Vt.T @ ((U.T @ Y) / s)
        res = Y - W @ v
        cov_unit = (Vt.T / s**2) @ Vt  # (WᵀW)⁻¹ through the SVD
    else:
        Phi = instruments
        A = Phi.T @ W
        try:
            A_inv = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            raise IdentificationError(f"{method}: instruments are uncorrelated with the regressor (ΦᵀW singular)") from None
        v = A_inv @ (Phi.T @ Y)
        res = Y - W @ v
        cov_unit = A_inv @ (Phi.T @ Phi) @ A_inv.T
    sigma_rho2 = float(res @ res) / (r - n_p)
    sigma = np.sqrt(np.abs(np.diag(cov_unit)) * sigma_rho2)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = sigma / np.abs(v)
    return Estimate(
        method=method, equations=equations, names=names, values=v, sigma=sigma, relative_sigma=rel,
        condition_number=float(s[0] / s[-1]), residual_norm=float(np.sqrt(res @ res)),
        n_rows=r, n_samples=n_samples, threshold=threshold,
        estimator="least squares" if instruments is None else "instrumental variables",
    )


def _names(symbol: str, n: int) -> tuple[str, ...]:
    return tuple(f"{symbol}({j + 1})" for j in range(n))


MIN_MOVING = 16  # decimated samples (≈ 0.5 s) a motor must turn in each direction to excite f_s


def _check_friction_excitation(proc: Processed, params: Params) -> None:
    """f_s(j) needs motor j to turn both ways at speeds where eq. 37 is near saturation
    (|θ̇| > 1/c_s, a > 0.5); below that its regressor column is numerically, not exactly, zero."""
    v = proc.theta_dot * params.friction.c_s
    poor = [j for j in range(v.shape[1]) if min((v[:, j] > 1).sum(), (v[:, j] < -1).sum()) < MIN_MOVING]
    if poor:
        names = ", ".join(f"f_s({j + 1})" for j in poor)
        raise IdentificationError(
            f"regressor is rank-deficient in practice: {names} not excited (motor(s) "
            f"{', '.join(str(j + 1) for j in poor)} turned faster than {1 / params.friction.c_s:.1f} rad/s in each "
            f"direction for less than {MIN_MOVING} samples); run the identification trajectory"
        )


def _friction_shape(proc: Processed, params: Params) -> FloatArray:
    """a = (2/π)·arctan(c_s·θ̇) (eq. 37), or sign(θ̇) for the eq. 36 model, (n, n_cables)."""
    return dynamics.friction_shape(params.friction.c_s, params.friction.model == "sign", proc.theta_dot)


def _ia_over_rho(params: Params) -> float:
    g = params.geometry
    return params.motors.I_a * g.R / g.r_d  # (R/r_d)·I_a: N per rad/s² of θ̈


def _joint_rows(proc: Processed, params: Params, elastic: bool) -> tuple[FloatArray, FloatArray]:
    """Joint rows of eqs. 38/44 (our sign): D = Z·diag(a) (n, N, nc), y = Z(f − I_a(R/r_d)²ẍ_c) − Mα̈ − c − g."""
    a = _friction_shape(proc, params)
    D = proc.Z * a[:, None, :]
    g = params.geometry
    drive = proc.force - (params.motors.I_a * (g.R / g.r_d) ** 2 * proc.x_c_ddot if elastic else 0.0)
    y = (np.einsum("nij,nj->ni", proc.Z, drive) - np.einsum("nij,nj->ni", proc.M, proc.alpha_ddot) - proc.c - proc.g)
    return D, y


def _tension_mask(t_c: FloatArray) -> NDArray[np.bool_]:
    return t_c >= MIN_TENSION_N


def identify_friction(proc: Processed, params: Params, *, threshold: float = DEFAULT_THRESHOLD) -> Estimate:
    """Dry friction f_s (N) alone, with rigid cables: eq. 38 with ẍ_c = 0 (the paper's eqs. 46-47
    "model without cable elasticity", see the module docstring). Rows: N per sample."""
    _check_friction_excitation(proc, params)
    D, y = _joint_rows(proc, params, elastic=False)
    nc = D.shape[-1]
    return least_squares(
        D.reshape(-1, nc), y.reshape(-1), _names("f_s", nc), method="friction",
        equations="eq. 38, rigid cables (eqs. 46-47)", n_samples=proc.n, threshold=threshold,
    )


def _instrument_dot(x: FloatArray, proc: Processed) -> FloatArray:
    return np.gradient(x, 1.0 / proc.rate_hz, axis=0)


def identify_complete(
    proc: Processed, params: Params, *, weight: float = W_JOINT, threshold: float = DEFAULT_THRESHOLD,
    estimator: str = "iv",
) -> Estimate:
    """Friction and linear cables together, eqs. 43-45: v = (k, c_a, f_s), 3·n_cables parameters.

    Per sample: n_cables tension rows (eq. 42) diag(x_c)k + diag(ẋ_c)c_a + diag(a)f_s =
    f − (R/r_d)I_a·θ̈, and N joint rows (eq. 38, our sign) weighted by W = ``weight``.
    Tension rows of a cable whose tension from the forces is below 2 N are dropped (slack).
    ``estimator``: ``"iv"`` (default, see :func:`identify_variable`: the instruments of x_c, ẋ_c
    are y = f − (R/r_d)I_a·θ̈ and ẏ) or ``"ls"`` (eq. 49 as printed).
    """
    _check_friction_excitation(proc, params)
    n, nc = proc.n, params.n_cables
    a = _friction_shape(proc, params)
    y_t = proc.force - _ia_over_rho(params) * proc.theta_ddot
    D_j, y_j = _joint_rows(proc, params, elastic=True)
    N = D_j.shape[1]
    eye = np.eye(nc)

    def tension_rows(x: FloatArray, x_dot: FloatArray) -> FloatArray:
        return np.concatenate([x[:, :, None] * eye, x_dot[:, :, None] * eye, a[:, :, None] * eye], axis=2)

    bottom = np.concatenate([np.zeros((n, N, 2 * nc)), weight * D_j], axis=2).reshape(-1, 3 * nc)
    mask = _tension_mask(y_t - a * np.asarray(params.friction.f_s))
    W = np.concatenate([tension_rows(proc.x_c, proc.x_c_dot)[mask], bottom])
    Y = np.concatenate([y_t[mask], weight * y_j.reshape(-1)])
    Phi = None
    if _check_estimator(estimator) == "iv":
        Phi = np.concatenate([tension_rows(y_t, _instrument_dot(y_t, proc))[mask], bottom])
    return least_squares(
        W, Y, _names("k", nc) + _names("c_a", nc) + _names("f_s", nc), method="complete",
        equations=f"eqs. 43-45, W = {weight:g}", n_samples=n, threshold=threshold, instruments=Phi,
    )


def _check_estimator(estimator: str) -> str:
    if estimator not in ("iv", "ls"):
        raise ValueError(f"estimator must be 'iv' or 'ls', got {estimator!r}")
    return estimator


def cable_tension(proc: Processed, params: Params, f_s: FloatArray) -> FloatArray:
    """Eq. 41/55: t_c = f − diag(a)f_s − (R/r_d)I_a·θ̈ (N), (n, n_cables)."""
    return proc.force - _friction_shape(proc, params) * np.asarray(f_s) - _ia_over_rho(params) * proc.theta_ddot


def identify_variable(
    proc: Processed, params: Params, f_s: FloatArray, *, threshold: float = DEFAULT_THRESHOLD, estimator: str = "iv"
) -> Estimate:
    """Variable stiffness, eqs. 54-57: t_c = k·x_c + λ·x_c·t_c + c_a·ẋ_c with t_c from eq. 55
    using the friction ``f_s`` (N) identified before; v = (k, λ, c_a).

    Why instrumental variables by default: x_c comes from α_IP (1° of camera noise, ≈ 0.2-0.4 mm
    of stretch after filtering, against a stretch of a few mm), so the regressors x_c, x_c·t_c and
    ẋ_c are noisy and plain least squares is biased towards zero (errors in variables: −15 % on
    k(4), +20 % on λ(3), damping halved on the twin). The tension t_c, computed from the forces and
    the encoders, is independent of the camera noise and strongly correlated with the stretch, so
    Φ = (diag(t_c), diag(t_c²), diag(ṫ_c)) are valid instruments (Janot, Vandanjon & Gautier,
    "A generic instrumental variable approach for industrial robot identification", IEEE TCST
    2014). ``estimator="ls"`` gives eq. 49 as printed.
    """
    nc = params.n_cables
    f_s = np.asarray(f_s, dtype=float)
    if f_s.shape != (nc,) or not np.all(np.isfinite(f_s)):
        raise IdentificationError(f"f_s must be {nc} finite values (N), got {f_s}")
    t_c = cable_tension(proc, params, f_s)
    eye = np.eye(nc)

    def rows(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
        return np.concatenate([a[:, :, None] * eye, b[:, :, None] * eye, c[:, :, None] * eye], axis=2)

    mask = _tension_mask(t_c)
    W = rows(proc.x_c, proc.x_c * t_c, proc.x_c_dot)[mask]
    Phi = rows(t_c, t_c**2, _instrument_dot(t_c, proc))[mask] if _check_estimator(estimator) == "iv" else None
    return least_squares(
        W, t_c[mask], _names("k", nc) + _names("lambda", nc) + _names("c_a", nc), method="variable",
        equations="eqs. 54-57", n_samples=proc.n, threshold=threshold, instruments=Phi,
    )


def identify_all(
    proc: Processed, params: Params, *, threshold: float = DEFAULT_THRESHOLD, estimator: str = "iv"
) -> dict[str, Estimate]:
    """The three estimations of §5 in order: friction alone, complete (Table 1), variable (Table 2,
    with the f_s of the friction-alone estimate: it does not depend on the cable model, while the
    complete model's f_s absorbs the misfit of linear cables when the cables stiffen with tension)."""
    fric = identify_friction(proc, params, threshold=threshold)
    comp = identify_complete(proc, params, threshold=threshold, estimator=estimator)
    var = identify_variable(proc, params, fric.values, threshold=threshold, estimator=estimator)
    return {"friction": fric, "complete": comp, "variable": var}


# --- identified parameter set with provenance ---------------------------------------------------


class Provenance(msgspec.Struct, frozen=True, kw_only=True):
    """Where an identified parameter set comes from. Written as ``<name>.provenance.json`` next to
    the TOML (and summarised in the TOML's header comments)."""

    campaign: str
    date: str
    method: str
    base_parameter_set: str = ""
    cutoff_hz: float = float("nan")
    threshold: float = DEFAULT_THRESHOLD
    software_version: str = ""
    parameters: list[dict[str, Any]] = msgspec.field(default_factory=list)  # per-parameter flags
    kept_base: list[str] = msgspec.field(default_factory=list)  # names of the parameters not used


@dataclass(frozen=True)
class ParameterReport:
    """What :func:`identified_params` did with each estimate.

    used: parameter key (``"cables.variable.k(2)"``) -> value written; kept_base: key ->
    (base value kept, estimate refused, reason)."""

    used: dict[str, float] = field(default_factory=dict)
    kept_base: dict[str, tuple[float, float, str]] = field(default_factory=dict)

    def lines(self) -> list[str]:
        out = [f"kept base {k} = {b:g} (estimate {e:g}: {why})" for k, (b, e, why) in self.kept_base.items()]
        return out or ["every identified parameter was used"]


# (estimate method, symbol) -> (params section path, key in that section)
_TARGETS = (
    ("friction", "f_s", ("friction",), "f_s"),
    ("complete", "k", ("cables", "linear"), "k"),
    ("complete", "c_a", ("cables", "linear"), "c_a"),
    ("variable", "k", ("cables", "variable"), "k"),
    ("variable", "lambda", ("cables", "variable"), "lambda"),
    ("variable", "c_a", ("cables", "variable"), "c_a"),
)


def identified_params(
    base: Params, estimates: Mapping[str, Estimate], provenance: Provenance
) -> tuple[Params, ParameterReport, Provenance]:
    """A new parameter set: friction.f_s (friction-alone estimate), cables.linear k/c_a (complete
    model), cables.variable k/lambda/c_a (variable model) replaced by their estimates.

    A badly identified parameter (relative σ above the estimate's threshold), or one outside its
    physical range (k ≤ 0, λ < 0, f_s < 0, c_a < 0), is NOT used: the base value stays and the
    parameter is listed in the report and in the returned provenance (``kept_base``).
    """
    data = base.to_dict()
    report = ParameterReport()
    rows: list[dict[str, Any]] = []
    for method, symbol, path, key in _TARGETS:
        est = estimates.get(method)
        if est is None:
            continue
        section = data
        for part in path:
            section = section[part]
        values = list(section[key])
        new = est.vector(symbol)
        idx = [i for i, n in enumerate(est.names) if n.split("(")[0] == symbol]
        for j, (value, i) in enumerate(zip(new, idx)):
            name = f"{'.'.join(path)}.{key}({j + 1})"
            reason = est.reason(i)
            if reason:
                report.kept_base[name] = (float(values[j]), float(value), reason)
            else:
                values[j] = float(value)
                report.used[name] = float(value)
            rows.append({
                "name": name, "estimate": float(value), "relative_sigma": float(est.relative_sigma[i]),
                "method": method, "used": not reason, "reason": reason,
            })
        section[key] = values
    data["name"] = f"{base.name}-identified"
    params = params_from_dict(data, f"identified from {provenance.campaign}")
    prov = msgspec.structs.replace(
        provenance, parameters=rows, kept_base=list(report.kept_base), base_parameter_set=base.name
    )
    return params, report, prov


def make_provenance(campaign: str, proc: Processed, *, method: str = "", threshold: float = DEFAULT_THRESHOLD) -> Provenance:
    """Provenance for a campaign processed now (ISO date in UTC)."""
    try:
        from importlib.metadata import version

        sw = version("xneck")
    except Exception:  # noqa: BLE001 - not installed: an editable checkout
        sw = "unknown"
    return Provenance(
        campaign=campaign,
        date=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        method=method or (
            f"3-X paper §5: Butterworth filtfilt {proc.cutoff_hz:.2f} Hz, decimation to {proc.rate_hz:.2f} Hz; "
            "f_s by eq. 38 (rigid cables); linear cables by eqs. 43-45 (W = 100); variable cables by eqs. 54-57; "
            "instrumental variables for the stretch regressors"
        ),
        cutoff_hz=proc.cutoff_hz, threshold=threshold, software_version=sw,
    )


def write_identified(path: str | Path, params: Params, provenance: Provenance) -> tuple[Path, Path]:
    """Write ``path`` (TOML, loadable by :func:`twin.model.params.load_params`, with a comment header
    naming the campaign, date, method and the parameters kept at their base value) and
    ``<stem>.provenance.json`` next to it. Returns both paths."""
    path = Path(path)
    prov_path = path.with_name(path.stem + ".provenance.json")
    header = [
        f"# Identified parameter set (3-X paper §5) from campaign {provenance.campaign}",
        f"# date {provenance.date}, software {provenance.software_version}, base {provenance.base_parameter_set}",
        f"# method: {provenance.method}",
        f"# parameters kept at their base value (badly identified): {', '.join(provenance.kept_base) or 'none'}",
        f"# full provenance and per-parameter relative σ: {prov_path.name}",
    ]
    path.write_text("\n".join(header) + "\n" + params.to_toml())
    prov_path.write_text(json.dumps(msgspec.to_builtins(provenance), indent=2) + "\n")
    return path, prov_path


# --- validation (§5.3-5.5) ----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class AlphaHat:
    """α̂ (rad) at the camera instants ``t_s`` for one method and cable model, and its mean
    absolute error against α_IP (deg, over joints and frames)."""

    method: str  # "eq33" or "eq35"
    cable_model: str  # "rigid", "linear", "variable"
    t_s: FloatArray
    alpha_hat: FloatArray
    mean_error_deg: float


@dataclass(frozen=True, eq=False)
class Validation:
    """Checks of the identified models (Figs. 4-8).

    Torques (N·m/rad) at the identification instants: Γ_m = Z·f, Γ_rf and Γ_r (eqs. 51-53, our
    sign) and the mean absolute errors |Γ_m − Γ_rf|, |Γ_m − Γ_r|. Tension (N), both sides of
    eq. 42: ``tension_force[model]`` from the forces (RHS) and ``tension_stiffness[model]`` from
    the cable model (LHS, eq. 39 or 54), for "linear" and "variable", with mean absolute errors
    over non-slack samples. α̂ by eqs. 33 and 35 for the rigid, linear and variable cable models
    against α_IP (Fig. 8); ``t_ip_s``/``alpha_ip`` are the frames compared.
    """

    t_s: FloatArray
    gamma_m: FloatArray
    gamma_rf: FloatArray
    gamma_r: FloatArray
    gamma_rf_error: float
    gamma_r_error: float
    tension_force: dict[str, FloatArray]
    tension_stiffness: dict[str, FloatArray]
    tension_error: dict[str, float]
    alpha_hat: dict[tuple[str, str], AlphaHat]
    t_ip_s: FloatArray
    alpha_ip: FloatArray

    def alpha_errors_deg(self) -> dict[str, float]:
        return {f"{m}/{c}": a.mean_error_deg for (m, c), a in self.alpha_hat.items()}

    def summary(self) -> dict[str, Any]:
        return {
            "gamma_rf_mean_error": self.gamma_rf_error, "gamma_r_mean_error": self.gamma_r_error,
            "tension_mean_error_N": dict(self.tension_error), "alpha_hat_mean_error_deg": self.alpha_errors_deg(),
        }


def _alpha_hat_all(data: CampaignData, proc: Processed, params: Params, models: tuple[CableModelName, ...]) -> tuple[dict, FloatArray, FloatArray]:
    """α̂ by eqs. 33 and 35 (twin.model.estimation) on the 500 Hz record, compared at the camera
    frames inside it. The estimators start at α̂ = 0, x_c = 0 with the first encoder reading: the
    campaign starts straight and at rest (§5.2.2)."""
    from twin.model.estimation import PseudoInverseEstimator, alpha_hat_3

    t, theta, force, theta_dot = proc.fast_t_s, proc.fast_theta, proc.fast_force, proc.fast_theta_dot
    inside = (data.t_ip_s >= t[0]) & (data.t_ip_s <= t[-1])
    t_ip, a_ip = data.t_ip_s[inside], data.alpha_ip_rad[inside]
    k_ip = np.clip(np.searchsorted(t, t_ip - 1e-9), 0, len(t) - 1)  # the tick of each capture
    out: dict[tuple[str, str], AlphaHat] = {}
    for name in models:
        m = build(params, name)
        est = PseudoInverseEstimator(m, float(np.median(np.diff(t))))
        est.reset(theta=theta[0])
        a35 = np.empty((len(k_ip), m.n_joints))
        a33 = np.empty_like(a35)
        j = 0
        guess = np.zeros(m.n_joints)
        ah = est.alpha_hat
        for k in range(len(t)):
            if k > 0:
                ah = est.update(theta[k], force[k], theta_dot[k])
            while j < len(k_ip) and k_ip[j] == k:
                a35[j] = ah
                guess = a33[j] = alpha_hat_3(m, theta[k], est.x_c, guess)
                j += 1
        for meth, arr in (("eq33", a33), ("eq35", a35)):
            err = float(np.degrees(np.mean(np.abs(arr - a_ip))))
            out[(meth, name)] = AlphaHat(meth, name, t_ip, arr, err)
    return out, t_ip, a_ip


def validate(
    data: CampaignData, proc: Processed, identified: Params, estimates: Mapping[str, Estimate],
    *, alpha_hat: bool = True,
) -> Validation:
    """Figs. 4-8 and their mean errors for the ``identified`` parameter set and ``estimates``.

    Γ_rf uses the identified f_s; the tension both ways (Figs. 5-7) uses each cable model's
    least-squares fit (eq. 49; "linear" with its own f_s, "variable" with the friction-alone f_s),
    badly identified damping included: this compares how well the two model forms fit. α̂ uses ``identified`` (so a
    badly identified damping is replaced by its base value there, as the controller would run).
    """
    g = identified.geometry
    iar2 = identified.motors.I_a * (g.R / g.r_d) ** 2
    a = _friction_shape(proc, identified)
    f_s = np.asarray(identified.friction.f_s)
    Zx = np.einsum("nij,nj->ni", proc.Z, -iar2 * proc.x_c_ddot)
    rigid_part = Zx + np.einsum("nij,nj->ni", proc.M, proc.alpha_ddot) + proc.c + proc.g
    gamma_m = np.einsum("nij,nj->ni", proc.Z, proc.force)
    gamma_rf = np.einsum("nij,nj->ni", proc.Z, a * f_s) + rigid_part
    gamma_r = rigid_part

    tf: dict[str, FloatArray] = {}
    ts: dict[str, FloatArray] = {}
    te: dict[str, float] = {}
    comp, var, fric = estimates.get("complete"), estimates.get("variable"), estimates.get("friction")
    # Figs. 5-7 compare how well each cable model FITS the tension: use each model's least-squares
    # fit (eq. 49), as the paper does. The instrumental-variable estimates in the tables are closer
    # to the truth under camera noise in x_c but, by construction, do not minimise this residual.
    fs_var = fric.values if fric is not None else f_s
    if comp is not None:
        comp = identify_complete(proc, identified, estimator="ls")
        tf["linear"] = cable_tension(proc, identified, comp.vector("f_s"))
        ts["linear"] = dynamics.cable_tension_law(comp.vector("k"), 0.0, comp.vector("c_a"), proc.x_c, proc.x_c_dot)
    if var is not None:
        var = identify_variable(proc, identified, fs_var, estimator="ls")
        tf["variable"] = cable_tension(proc, identified, fs_var)
        k, lam, c_a = var.vector("k"), var.vector("lambda"), var.vector("c_a")
        ts["variable"] = dynamics.cable_tension_law(k, lam, c_a, proc.x_c, proc.x_c_dot)
    for name in tf:
        mask = _tension_mask(tf[name])
        te[name] = float(np.mean(np.abs(tf[name] - ts[name])[mask]))

    if alpha_hat:
        ah, t_ip, a_ip = _alpha_hat_all(data, proc, identified, ("rigid", "linear", "variable"))
    else:
        ah, t_ip, a_ip = {}, np.zeros(0), np.zeros((0, data.n_joints))
    return Validation(
        t_s=proc.t_s, gamma_m=gamma_m, gamma_rf=gamma_rf, gamma_r=gamma_r,
        gamma_rf_error=float(np.mean(np.abs(gamma_m - gamma_rf))), gamma_r_error=float(np.mean(np.abs(gamma_m - gamma_r))),
        tension_force=tf, tension_stiffness=ts, tension_error=te, alpha_hat=ah, t_ip_s=t_ip, alpha_ip=a_ip,
    )
