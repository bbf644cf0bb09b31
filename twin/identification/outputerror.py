"""Table 2's k and λ by the neck's output error from the encoders, forces and pose together (issue 16).

The force fits (eq. 55's IDIM-IV, twin.identification.loadfriction) take the cable tension from
the motor force less a friction model, so whatever that model lacks biases k and λ: on the robot
truth the friction's direction asymmetry (a value without a source) pulls λ(3) 8-25 % low
(docs/identification-coverage.md, "What biases λ(3)"). The neck's pose does not see the friction:
friction acts upstream of the encoders, and at every identification instant α solves the neck's
quasi-static equilibrium (eq. 32) on the motor angles θ alone::

    Z(α)·t = g(α; s),   t = k·x'/(1 − λ·x')  (eq. 54),   x' = l_c(α) − l_c0 + ρ·θ − c   (eq. 27, m)
    τ·ċ = β·x'/(1 − λ·x') − c                       the line's Kelvin creep (loadfriction's)

g holds the lateral springs, whose rates s_i (left and right of each joint, as factors of the
parameter file's) are free, and so is the pulleys' radius r + δr (eq. 20's l_c; the line's own
radius moves the contact, and a 0.1 mm error moved λ(3), λ(4) by 3-4 % when held). A spring rate
is known to ±10 % (DIN EN 13906-2 grade 2), and the tension that balances the springs scales with
them, so with the file's rates the pose alone gives k 6-11 % off on the robot truth (docs/identification/static_output_error.py). The force
gives the tension's scale instead: on the rows where a motor turns fast (loadfriction.fit_rows),
with a = sign θ̇ and the gear's meshing losses g_f, g_b held (loadfriction.gear_losses),

    f − (R/r_d)·I_a·θ̈ = ((1 + a·μ)·t + a·F₀ − g_b·a⁻·t) / (1 − g_f·a⁺)   (N)

with the same t, simulated. One least-squares fit (scipy.optimize.least_squares, bounded) of
(k, λ, μ, F₀ per cable; β, τ; s per spring; δr) to both: α_sim − α_IP (rad, weighted by 1/σ_α) and
the force rows (N, by 1/σ_f), σ_α and σ_f the residual scales of a first pass. Everything the fit
compares is simulated from the encoders, so the camera's noise is in the residual, not in a
regressor (no errors-in-variables bias, no instruments needed). σ: the Newey-West HAC sandwich
of the linearised estimator over the identification instants (twin.identification.uncertainty),
plus a type-B part (GUM) for what the fit holds and no residual of the record shows: the
structure at the file's (the springs' free lengths, the bar masses: :func:`structure_models`) and
each motor's force scale (the torque constant and the current loop's gain, ``FORCE_SCALE_TOLERANCE``),
which sets the tension's scale, hence k's (the pose takes a part of it through the springs). With
the HAC part alone the ±2σ covered 45/80 on law 1's held-out campaigns, the errors repeating from
seed to seed (docs/identification-coverage.md).

What it assumes instead: a light cable damping (the equilibrium is quasi-static: with the paper's
c_a = 3000 N·s/m the pose is off by c_a·ẋ and λ comes out 30-80 % high, 5-9 % at 300 N·s/m; a real
line's, 40 N·s/m, changes nothing; `auto` checks it, twin.identification.model_choice.damping_check),
c_a is held at 0; the bar masses and the springs' free lengths of the file
(their errors go into s); a friction of a turning motor that is a sign (loadfriction's c_f at
its bound, as on the robot truth). The fit's Jacobian is exact, from the simulation's solution by
the implicit function theorem (twin.identification.neck_sensitivity), and it takes every fourth
instant (:func:`decimated`): about 1 s per campaign, against 40 s by finite differences on every
instant. Coverage on the twin: docs/identification-coverage.md, "The pulleys' radius fitted".
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from twin.identification import uncertainty
from twin.identification.estimators import DEFAULT_THRESHOLD, Estimate
from twin.identification.instruments import neck_equilibrium
from twin.identification.loadfriction import (
    BETA_BOUNDS,
    F0_BOUNDS_N,
    HAC_MIN_LAG_PERIODS,
    MIN_ROWS,
    MIN_SPEED_RAD_S,
    MIN_STRETCH_FACTOR,
    MU_BOUNDS,
    fit_rows,
    gear_losses,
)
from twin.identification.neck_sensitivity import PULLEY_STEP_M, Layout, Pass, creep_stretch_kernel, sensitivities
from twin.identification.options import check_sigma
from twin.identification.processing import Processed
from twin.identification.regressors import param_names
from twin.model.compiled import kernel_array
from twin.model.numeric import Model, build
from twin.model.params import Params

FloatArray = NDArray[np.float64]

NAME = "outputerror"
EDGE_S = 5.0  # s dropped at each end of the α rows: the zero-phase filter's edges
CREEP_PASSES = 3  # the creep moves the equilibrium by ~5 % of the stretch: a fixed point in a few passes
START_K_N_M, START_LAMBDA_PER_M = 4000.0, 80.0  # no prior: Table 2 spans 1900-6200 N/m and 53-121 /m
LOG_RANGE = 3.0  # k, λ within e^±3 of the start
SPRING_LOG_RANGE = 0.3  # spring rates within e^±0.3 (±35 %) of the file's: three times their tolerance
TAU_BOUNDS_S = (0.2, 20.0)
PASSES = 2  # fits: the second weighted by the first's residual scales
SAMPLES_PER_CUTOFF = 4.0  # the fit's instants per period of the filter's cutoff (:func:`decimated`)
# The structure the fit holds at the parameter file's, as half-widths of uniform tolerances, for σ's
# type-B part (:func:`structure_models`): what the spring rates cannot absorb.
L0_TOLERANCE_M = 0.5e-3  # spring free length and hook positions: about ±0.5 mm on 46 mm (DIN EN 13906-2)
MASS_TOLERANCE = 0.10  # bar masses and inertias: CAD estimates (prototype_3x.toml [bars]), ±10 %
DELTA_R_BOUNDS_M = (-0.5e-3, 0.5e-3)  # the pulleys' radius error δr, fitted: printed/turned pulleys and the line
# Each motor's force scale: the EC-max 40's torque constant falls about 0.1 %/K with the magnet's
# temperature (NdFeB) and the datasheet gives no unit tolerance; the ESCON's current set value comes
# through an uncalibrated PWM input. About ±5 %: a physics estimate, not a measurement (a bench
# calibration of f against a load cell would replace it).
FORCE_SCALE_TOLERANCE = 0.05


def creep_stretch(x_total: FloatArray, lam: FloatArray, beta: float, tau_s: float, h: float) -> FloatArray:
    """c (m, (n, n_cables)): the Kelvin creep of each cable at each sample, relaxing towards
    β·x'/(1 − λx') with x' = ``x_total`` − c (loadfriction._creep_tension's element: its drive
    β·t_e/k is the same), at its equilibrium at the first sample; ``h`` the sample step (s)."""
    gain = 1.0 - np.exp(-h / tau_s)
    return creep_stretch_kernel(kernel_array(x_total), kernel_array(lam),
                                float(beta), float(gain), MIN_STRETCH_FACTOR)


@dataclass
class _Neck:
    """The neck re-simulated on the encoders for a parameter vector, the last solve kept as the next
    one's start (its α and Jacobians), and a small cache (the fit's Jacobian comes at the point its
    residual was just computed; the structure's type-B shifts are not cached)."""

    params: Params
    m: Model
    proc: Processed
    alpha: FloatArray
    jacobian: FloatArray | None = None

    def __post_init__(self) -> None:
        self.cache: dict[bytes, tuple[FloatArray, FloatArray, list[Pass]]] = {}
        self._pulley: dict[float, tuple[float, FloatArray]] = {}

    def simulate(self, k: FloatArray, lam: FloatArray, beta: float, tau_s: float, springs: FloatArray,
                 delta_r_m: float = 0.0, base: Model | None = None) -> tuple[FloatArray, FloatArray]:
        """(α (n, N) rad, t (n, n_cables) N) at equilibrium on the recorded θ, the pulleys' radius
        off the file's by ``delta_r_m``; ``base``: another structure than the parameter file's (not cached)."""
        key = np.r_[k, lam, beta, tau_s, springs, delta_r_m].tobytes()
        if base is None and key in self.cache:
            return self.cache[key][:2]
        m = self.model(springs, delta_r_m, base)
        c = np.zeros_like(self.proc.theta)
        passes: list[Pass] = []
        for _ in range(CREEP_PASSES if beta > 0 else 1):
            # the creep lengthens a cable as unwinding its motor would: it enters as θ − c/ρ
            alpha, x, self.jacobian = neck_equilibrium(m, self.proc.theta - c / m.rho, k, lam, self.alpha,
                                                       jacobian0=self.jacobian)
            self.alpha = alpha
            passes.append(Pass(alpha, c, x + c))
            if beta <= 0:
                break
            c = creep_stretch(x + c, lam, beta, tau_s, 1.0 / self.proc.rate_hz)
        t = np.maximum(k * x / np.maximum(1 - lam * x, MIN_STRETCH_FACTOR), 0.0)
        if base is not None:
            return alpha, t
        if len(self.cache) > 8:
            self.cache.clear()
        self.cache[key] = (alpha, t, passes)
        return alpha, t

    def derivatives(self, k: FloatArray, lam: FloatArray, beta: float, tau_s: float, springs: FloatArray,
                    delta_r_m: float = 0.0) -> tuple[FloatArray, FloatArray]:
        """(dα/dq (n, N, P) rad, dt/dq (n, n_cables, P) N) at these parameters, q the neck's
        (twin.identification.neck_sensitivity.Layout): exact for the simulation :meth:`simulate` runs."""
        self.simulate(k, lam, beta, tau_s, springs, delta_r_m)
        passes = self.cache[np.r_[k, lam, beta, tau_s, springs, delta_r_m].tobytes()][2]
        pulleys = (self.model(springs, delta_r_m + PULLEY_STEP_M), self.model(springs, delta_r_m - PULLEY_STEP_M))
        return sensitivities(self.model(springs, delta_r_m), pulleys,
                             self.proc.theta, k, lam, beta, tau_s, springs, passes, 1.0 / self.proc.rate_hz,
                             MIN_STRETCH_FACTOR)

    def model(self, springs: FloatArray, delta_r_m: float, base: Model | None = None) -> Model:
        """The variable-cable model (``base``, else the file's) with the springs' rates ×``springs`` and
        the pulleys' radius off by ``delta_r_m``."""
        m0 = self.m if base is None else base
        N = m0.n_joints
        r, l_c0 = self._pulleys(delta_r_m)
        return m0._replace(k_left=m0.k_left * springs[:N], k_right=m0.k_right * springs[N:], r=r, l_c0=l_c0)

    def _pulleys(self, delta_r_m: float) -> tuple[float, FloatArray]:
        """The pulley radius (m) and the cables' lengths at α = 0 (eq. 20, m) with δr."""
        if delta_r_m == 0.0:
            return self.m.r, self.m.l_c0
        if delta_r_m not in self._pulley:
            geometry = msgspec.structs.replace(self.params.geometry, r=self.params.geometry.r + delta_r_m)
            m = build(msgspec.structs.replace(self.params, geometry=geometry), "variable")
            if len(self._pulley) > 8:
                self._pulley.clear()
            self._pulley[delta_r_m] = (m.r, m.l_c0)
        return self._pulley[delta_r_m]


def fit_output_error(proc: Processed, params: Params, *, threshold: float = DEFAULT_THRESHOLD,
                     sigma: str = "hac", start: tuple[FloatArray, FloatArray] | None = None) -> Estimate:
    """Fit the model of the module docstring. The Estimate holds k(j), lambda(j), c_a(j) (held at 0)
    in Table 2's layout, then mu(j), F_0(j), beta, tau (s) and the spring-rate factors
    s_left(i), s_right(i), with HAC σ (or eq. 50's with ``sigma="white"``) and the held structure's
    type-B part (:func:`structure_models`). ``start``: (k (N/m), λ (1/m)) per cable to start from (e.g.
    the load-friction fit's, as `auto` does; it saves iterations, the minimum is the same), else
    START_K_N_M, START_LAMBDA_PER_M (no prior). Raises ValueError when a
    cable has fewer than loadfriction.MIN_ROWS fast-motor rows, or for an unknown ``sigma``."""
    check_sigma(sigma)
    nc, N = params.n_cables, params.n_joints
    y, rows = fit_rows(proc, params)
    counts = rows.sum(axis=0)
    if np.any(counts < MIN_ROWS):
        poor = [f"{j + 1} ({int(counts[j])} rows)" for j in range(nc) if counts[j] < MIN_ROWS]
        raise ValueError(f"{NAME}: cable(s) {', '.join(poor)} have fewer than {MIN_ROWS} instants with the motor "
                         f"faster than {MIN_SPEED_RAD_S:g} rad/s and a force above 2 N; run the identification trajectory")
    edge = int(EDGE_S * proc.rate_hz)
    if proc.n <= 2 * edge + MIN_ROWS:
        raise ValueError(f"{NAME}: {proc.n} instants: the record is too short for the pose rows ({2 * EDGE_S:g} s of "
                         "filter edges and more)")
    # the checks above speak of the record's instants, as the user knows it; the fit runs on fewer
    proc = decimated(proc)[0]
    y, rows = fit_rows(proc, params)
    edge = int(EDGE_S * proc.rate_hz)
    inner = np.zeros(proc.n, dtype=bool)
    inner[edge:proc.n - edge] = True
    keep = np.flatnonzero(inner & proc.fitted)  # the pose rows' instants: not a record gap's either
    a = np.sign(proc.theta_dot)
    g_f, g_b = gear_losses(params)
    neck = _Neck(params, build(params, "variable"), proc, np.array(proc.alpha, dtype=float))
    # q: log(k/k0), log(λ/λ0) per cable; β; log τ; log s per spring; δr (mm); μ, F₀ per cable
    i_beta, i_tau, i_s, i_r, i_mu = _layout(nc, N)
    i_f0 = i_mu + nc
    lo = np.r_[np.full(2 * nc, -LOG_RANGE), BETA_BOUNDS[0], np.log(TAU_BOUNDS_S[0]), np.full(2 * N, -SPRING_LOG_RANGE),
               1e3 * DELTA_R_BOUNDS_M[0], np.full(nc, MU_BOUNDS[0]), np.full(nc, F0_BOUNDS_N[0])]
    hi = np.r_[np.full(2 * nc, LOG_RANGE), BETA_BOUNDS[1], np.log(TAU_BOUNDS_S[1]), np.full(2 * N, SPRING_LOG_RANGE),
               1e3 * DELTA_R_BOUNDS_M[1], np.full(nc, MU_BOUNDS[1]), np.full(nc, F0_BOUNDS_N[1])]
    q = np.r_[np.zeros(2 * nc), 0.02, 0.0, np.zeros(2 * N), 0.0, np.full(nc, 0.1), np.full(nc, 10.0)]
    if start is not None:
        k0, lam0 = (np.asarray(v, dtype=float) for v in start)
        if (k0.shape != (nc,) or lam0.shape != (nc,) or not np.all(np.isfinite(np.r_[k0, lam0]))
                or np.any(k0 <= 0) or np.any(lam0 < 0)):
            raise ValueError(f"{NAME}: start must be (k > 0, λ ≥ 0) for {nc} cables, finite, got {k0!r}, {lam0!r}")
        with np.errstate(divide="ignore"):
            q[:2 * nc] = np.clip(np.log(np.r_[k0 / START_K_N_M, lam0 / START_LAMBDA_PER_M]), 0.9 * lo[:2 * nc],
                                 0.9 * hi[:2 * nc])

    def unpack(q: FloatArray):
        return (START_K_N_M * np.exp(q[:nc]), START_LAMBDA_PER_M * np.exp(q[nc:2 * nc]), float(q[i_beta]),
                float(np.exp(q[i_tau])), np.exp(q[i_s:i_r]), 1e-3 * float(q[i_r]), q[i_mu:i_f0], q[i_f0:])

    def parts(q: FloatArray, base: Model | None = None) -> tuple[FloatArray, FloatArray]:
        k, lam, beta, tau, springs, delta_r, mu, f0 = unpack(q)
        alpha, t = neck.simulate(k, lam, beta, tau, springs, delta_r, base)
        model = ((1 + a * mu) * t + a * f0 - g_b * np.maximum(-a, 0) * t) / (1 - g_f * np.maximum(a, 0))
        return (alpha - proc.alpha)[keep], (model - y)[rows]

    motor = np.nonzero(rows)[1]
    winding = 1 - g_f * np.maximum(a, 0)

    def jacobians(q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """d(α rows)/dq and d(force rows)/dq, exact (twin.identification.neck_sensitivity)."""
        k, lam, beta, tau, springs, delta_r, mu, _ = unpack(q)
        d_alpha, d_t = neck.derivatives(k, lam, beta, tau, springs, delta_r)
        t = neck.simulate(k, lam, beta, tau, springs, delta_r)[1]
        ja = np.zeros((N * len(keep), len(q)))
        ja[:, :i_mu] = d_alpha[keep].reshape(-1, i_mu)
        jf = np.zeros((len(motor), len(q)))
        jf[:, :i_mu] = (((1 + a * mu - g_b * np.maximum(-a, 0)) / winding)[:, :, None] * d_t)[rows]
        jf[np.arange(len(motor)), i_mu + motor] = (a * t / winding)[rows]
        jf[np.arange(len(motor)), i_f0 + motor] = (a / winding)[rows]
        return ja, jf

    scale_a, scale_f = np.radians(0.1), 2.0  # rad, N: the first pass's weights, of the order of the twin's
    sol, used = None, (scale_a, scale_f)
    for _ in range(PASSES):
        used = (scale_a, scale_f)

        def residual(q: FloatArray, sa: float = scale_a, sf: float = scale_f) -> FloatArray:
            ra, rf = parts(q)
            return np.concatenate([ra.ravel() / sa, rf / sf])

        def jacobian(q: FloatArray, sa: float = scale_a, sf: float = scale_f) -> FloatArray:
            ja, jf = jacobians(q)
            return np.vstack([ja / sa, jf / sf])

        jac: Any = jacobian  # scipy's annotations infer jac's type from its default, a string
        sol = optimize.least_squares(residual, q, jac=jac, bounds=(lo, hi), xtol=1e-8, x_scale="jac")
        q = sol.x
        ra, rf = parts(q)
        scale_a, scale_f = float(np.sqrt(np.mean(ra ** 2))), float(np.sqrt(np.mean(rf ** 2)))
    assert sol is not None
    # the last solve's residual, at its own weights, for each structure held at the file's moved by one σ
    shifts = [np.concatenate([ra.ravel() / used[0], rf / used[1]]) - sol.fun
              for ra, rf in (parts(q, m) for m in structure_models(params))]
    # and each motor's force scale moved by one σ: the recorded force is off by that share of itself
    for j in range(nc):
        d = np.zeros_like(sol.fun)
        d[len(sol.fun) - len(motor):] = np.where(motor == j, y[rows] * FORCE_SCALE_TOLERANCE / np.sqrt(3.0), 0.0) / used[1]
        shifts.append(d)
    return _estimate(proc, params, sol, q, unpack, rows, keep, threshold, sigma, lo, hi, shifts)


def decimated(proc: Processed) -> tuple[Processed, int]:
    """``proc`` on every ``step``-th instant, ``step`` the largest that keeps SAMPLES_PER_CUTOFF samples
    per period of the filter's cutoff: the signals are low-passed there (processing.cutoff_rule), so
    the instants in between carry no more information, only cost (each is a Newton solve of the
    neck per residual evaluation). The 500 Hz record (``fast_*``) is kept whole."""
    step = max(1, int(proc.rate_hz / (SAMPLES_PER_CUTOFF * proc.cutoff_hz)))
    if step == 1:
        return proc, 1
    fields = ("t_s", "theta", "theta_dot", "theta_ddot", "force", "alpha", "alpha_dot", "alpha_ddot", "x_c", "x_c_dot",
              "x_c_ddot", "Z", "M", "c", "g", "fitted")
    return dataclasses.replace(proc, rate_hz=proc.rate_hz / step,
                               **{f: np.ascontiguousarray(getattr(proc, f)[::step]) for f in fields}), step


def _layout(nc: int, N: int) -> tuple[int, int, int, int, int]:
    """Indices into q of β, log τ, the first log s, δr (mm) and the first μ."""
    lay = Layout(nc, N)  # the neck's parameters first, then μ and F₀ per cable
    return lay.i_beta, lay.i_tau, lay.i_s, lay.i_r, lay.size


def structure_models(params: Params) -> list[Model]:
    """The variable-cable model with one held structure value moved by one σ of its tolerance
    (uniform: half-width/√3): each joint's spring free length, each joint's bar masses and
    inertias. Their effect on the estimate is σ's type-B part (GUM): the record
    cannot show it, since the fit holds them (:func:`_estimate`)."""
    base = build(params, "variable")
    out = []
    for i in range(params.n_joints):
        l0 = base.l0.copy()
        l0[i] += L0_TOLERANCE_M / np.sqrt(3.0)
        out.append(base._replace(l0=l0))
    for i in range(params.n_joints):
        f = np.ones((params.n_joints, 1))
        f[i] += MASS_TOLERANCE / np.sqrt(3.0)
        out.append(base._replace(m_body=base.m_body * f, I_body=base.I_body * f))
    return out


def _estimate(proc: Processed, params: Params, sol, q: FloatArray, unpack, rows: NDArray[np.bool_], keep: NDArray[np.int64],
              threshold: float, sigma: str, lo: FloatArray, hi: FloatArray, shifts: list[FloatArray]) -> Estimate:
    """The Estimate: values in SI, σ of the linearised estimator q − q_true ≈ −(JᵀJ)⁻¹Jᵀρ by the HAC
    sandwich over the instants (each instant's α rows and force rows summed), mapped to the
    parameters through the exponential of the log-parametrised ones."""
    nc, N = params.n_cables, params.n_joints
    J, res = np.asarray(sol.jac, dtype=float), np.asarray(sol.fun, dtype=float)
    n_alpha = N * len(keep)
    # each row's instant: the α rows instant by instant (joints within), then the force rows as
    # (model - y)[rows] orders them (row-major: instant, then cable)
    idx = np.concatenate([np.repeat(keep, N), np.nonzero(rows)[0]]).astype(np.int64)
    free = (q > lo + 1e-9 * (hi - lo)) & (q < hi - 1e-9 * (hi - lo))
    cov = np.zeros((len(q), len(q)))
    lag = 0
    Jf = J[:, free]
    try:
        B = np.linalg.solve(Jf.T @ Jf, Jf.T)
    except np.linalg.LinAlgError:
        B = np.linalg.pinv(Jf.T @ Jf) @ Jf.T
    if sigma == "hac":
        min_lag = int(np.ceil(HAC_MIN_LAG_PERIODS * proc.rate_hz / proc.cutoff_hz))
        c_free, lag = uncertainty.hac_covariance(B, res, idx, proc.n, min_lag=min_lag, n_used=int(proc.fitted.sum()))
    else:
        c_free = uncertainty.white_covariance(B, res)
    # type B: each held structure value moved by its σ shifts the estimate by −B·Δρ (uncorrelated)
    for d in shifts:
        dq = B @ d
        c_free = c_free + np.outer(dq, dq)
    cov[np.ix_(free, free)] = c_free
    sd_q = np.sqrt(np.abs(np.diag(cov)))
    k, lam, beta, tau, springs, delta_r, mu, f0 = unpack(q)
    i_beta, i_tau, i_s, i_r, i_mu = _layout(nc, N)
    values = np.r_[k, lam, np.zeros(nc), mu, f0, beta, tau, springs, delta_r]
    # σ of a log-parametrised value v: v·σ(log v)
    sd = np.r_[np.r_[k, lam] * sd_q[:2 * nc], np.zeros(nc), sd_q[i_mu:i_mu + nc], sd_q[i_mu + nc:i_mu + 2 * nc],
               sd_q[i_beta], tau * sd_q[i_tau], springs * sd_q[i_s:i_r], 1e-3 * sd_q[i_r]]
    names = (param_names("k", nc) + param_names("lambda", nc) + param_names("c_a", nc) + param_names("mu", nc)
             + param_names("F_0", nc) + ("beta", "tau") + param_names("s_left", N) + param_names("s_right", N)
             + ("delta_r",))
    q_names = (names[:2 * nc] + ("beta", "tau") + param_names("s_left", N) + param_names("s_right", N)
               + ("delta_r",) + param_names("mu", nc) + param_names("F_0", nc))
    active = tuple(q_names[i] for i in np.flatnonzero(~free))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = sd / np.abs(values)
    est = Estimate(
        method="variable", equations="eq. 32's equilibrium on the encoders (α rows) and eqs. 54-55 with load friction",
        names=names, values=values, sigma=sd, relative_sigma=rel,
        condition_number=float(np.linalg.cond(J[:, free])), residual_norm=float(np.linalg.norm(res)),
        n_rows=len(res), n_samples=int(proc.fitted.sum()), threshold=threshold,
        sigma_method=(f"HAC (Newey-West, Bartlett, {lag} lags)" if sigma == "hac" else "eq. 50 (white residuals)")
        + f" + what the fit holds (type B, {len(shifts)} values: free lengths, bar masses, force scales)",
        hac_lag=lag, active_bounds=active,
    )
    return dataclasses.replace(est, estimator=(
        f"output error from the encoders at {proc.rate_hz:.3g} Hz: the neck's equilibrium against α_IP ({n_alpha} rows) and the motor "
        f"forces where |θ̇| ≥ {MIN_SPEED_RAD_S:g} rad/s ({int(rows.sum())} rows); spring rates ×"
        f"{', '.join(f'{v:.3f}' for v in springs)} (left, right per joint); pulley radius δr = "
        f"{1e3 * delta_r:+.3f} mm; Kelvin creep β = {beta:.3f}, "
        f"τ = {tau:.2g} s; c_a held at 0 (quasi-static)"))
