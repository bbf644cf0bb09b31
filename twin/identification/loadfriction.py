"""Table 2's k and λ with load-dependent motor friction and cable creep (issues 16, 17).

Eq. 55 takes the cable tension as the motor force less eq. 37's friction, a function of θ̇ alone.
On the robot truth (twin/sim/robot_truth.toml) the friction of a turning motor grows with the
load it carries (pulley and gear losses), and the cables creep; eq. 54 fitted on that tension
comes out 8-25 % low in k (docs/identification-coverage.md, "Where the error comes from").
This estimator fits, per cable j, the force of its motor where it turns fast (|θ̇| ≥ 5 rad/s,
where a Stribeck excess has died out)::

    y = f − (R/r_d)·I_a·θ̈ = ((1 + a·μ)·t + a·F₀ − g_b·a⁻·t) / (1 − g_f·a⁺)            (N)
    a = (2/π)·arctan(c_f·θ̇), a⁺ = max(a, 0), a⁻ = max(−a, 0)   eq. 37's shape
    t = (k·x' + c_a·ẋ) / (1 − λ·x')                     eq. 54 solved for t    (N)
    x' = x_c − c,  τ·ċ = β·t_e/k − c,  t_e = k·x'/(1 − λ·x')   Kelvin creep element  (m)

x_c, ẋ_c (m, m/s) from α_IP (eq. 27), f (N) the applied force, θ̇ (rad/s), θ̈ (rad/s²);
k (N/m), λ (1/m), c_a (N·s/m); μ (dimensionless: friction per newton of tension), F₀ (N);
g_f, g_b (dimensionless) the gear's meshing loss, of the motor force when winding and of the
tension when back-driven, held at the parameter file's (:func:`gear_losses`);
β (dimensionless creep ratio), τ (s) the line's creep time constant (:func:`_tension`);
c_f (s/rad) the slope of the friction's shape. The paper's arctan (c_s = 0.5 s/rad, §5.1.1) is
far from a sign at these speeds: 0.76 of its level at 5 rad/s, 0.94 at 20. A sign (F₀ constant)
made the damping-only truth's λ(3) 13 % low on law 1's campaigns; with c_f fitted it is 6 % low,
and c_f comes out 0.48-0.58 there, and at its bound of 100 (a sign) on the robot truth, whose
friction is flat above its Stribeck velocity. At that bound c_f is held for the IV and the σ
(:func:`_hold_flat_shape`).
One μ serves both directions, so that the scale k/(1 ± μ) of the tension rows cannot trade μ
against k; β ≥ 0 (creep only lengthens a loaded cable), λ, c_a ≥ 0.

Estimation, per cable: (1) bounded nonlinear least squares (scipy.optimize.least_squares, trust
region) in (k, λ, c_a, μ, F₀, β, c_f) on the camera's stretch, for each τ of a grid; (2) IDIM-IV as
pipeline.identify_variable does it: x_c comes from α_IP, whose noise (0.15-0.35 mm of stretch
on the twin's camera, against 0.7-1.4 mm of motion) biases least squares, so Zᵀρ(p) = 0 is
solved with Z the model's Jacobian on the stretch re-simulated from the encoders
(twin.identification.instruments), iterated to a fixed point, for every τ; τ is then picked per
cable as IDIM-IV estimates the rest, at the root of its instrument's moment (:func:`_iv_taus`;
where the moment does not change sign on the grid, by the camera residual, :func:`refine_tau`), or
held at a value measured apart (:func:`creep_taus`). σ: the Newey-West HAC sandwich (twin.identification.uncertainty) of the
linearised estimator B = (ZᵀJ)⁻¹Zᵀ at the solution, τ counted as estimated (its column ∂ρ/∂τ in
J and Z): held at the grid's τ, the σ of k(4) and λ(4) missed how far they move with τ.

The start is not the parameter file: on the twin the file's k and λ are the truth. It is the
model without creep made linear (:func:`linear_start`, no prior), and any (k, λ) the caller gives
is tried beside it (the lower residual kept): the solution does not depend on the start
(tests/test_identification_loadfriction.py). Coverage on the twin: docs/identification-coverage.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy import optimize

from twin.identification import uncertainty
from twin.identification.estimators import DEFAULT_THRESHOLD, Estimate
from twin.identification.instruments import Simulated, simulated_stretch
from twin.identification.options import check_creep_time, check_sigma
from twin.identification.processing import Processed
from twin.identification.regressors import ia_over_rho, param_names
from twin.model.compiled import kernel_array
from twin.model.numeric import build
from twin.model.params import Params

FloatArray = NDArray[np.float64]

NAME = "loadfriction"
MIN_SPEED_RAD_S = 5.0  # rows: the robot's Stribeck excess (v_s = 2 rad/s) is below 2 % there
MIN_FORCE_N = 2.0  # rows: a slack cable obeys no eq. 54 (regressors.MIN_TENSION_N)
MIN_ROWS = 50  # rows a cable needs: six parameters and residuals correlated over ~10 instants
TAUS_S = (0.5, 1.0, 2.0, 4.0, 8.0)  # creep time constants tried (s): the robot truth's is within
MIN_STRETCH_FACTOR = 0.05  # 1 − λx is kept above this: a start far off must not divide by zero
HAC_MIN_LAG_PERIODS = 3.0  # as pipeline.HAC_MIN_LAG_PERIODS: residuals share the filter's memory
# Bounds of (μ, F₀ (N), β): wide against the robot truth's μ 0.08-0.34, F₀ 5-15 N, β 0.05.
# μ may be negative (a friction that falls with the load) but not below -0.5 (a motor pulling itself).
MU_BOUNDS = (-0.5, 0.9)
F0_BOUNDS_N = (-40.0, 60.0)
BETA_BOUNDS = (0.0, 0.5)  # creep only lengthens a loaded cable: β ≥ 0
# c_f (s/rad): the paper's c_s is 0.5 (§5.1.1); at 100 the shape is a sign above 0.1 rad/s.
C_F_BOUNDS = (0.05, 100.0)
SYMBOLS = ("k", "lambda", "c_a", "mu", "F_0", "beta", "c_f")
IV_MAX_ITERATIONS = 10
# How τ is chosen per cable (:func:`_iv_taus`): "iv", the root of its instrument's moment; "residual",
# the camera residual's minimum (until 2026-11-26; docs/identification/estimator_variants.py
# ``residual-tau``).
TAU_CHOICE = "iv"
IV_TOLERANCE = 1e-3  # relative change of k and λ at which the IV iteration has converged (pipeline's)


@dataclass(frozen=True, eq=False)
class LoadFrictionFit:
    """The fit of one campaign: ``estimate`` holds k(j), lambda(j), c_a(j) (Table 2's layout)
    then mu(j), F_0(j), beta(j), c_f(j), with HAC σ; ``tau_s`` (s) the creep time constant chosen per
    cable; ``start`` the (k, λ) the fit began from; ``rows`` the rows used per cable."""

    estimate: Estimate
    tau_s: FloatArray
    start: tuple[FloatArray, FloatArray]
    rows: NDArray[np.int64]


@njit(cache=True)
def _creep_tension(k: float, lam: float, c_a: float, beta: float, x: FloatArray, xd: FloatArray, gain: float,
                   floor: float) -> FloatArray:
    """t (N) per sample, the creep stretch c (m) relaxing towards β·t_e/k at ``gain`` = 1 − e^(−h/τ)
    per step, t_e = k·x'/(1 − λx') the elastic tension of x' = x − c; c at its equilibrium at the
    first sample (the robot waited at rest under its pretension before the campaign)."""
    n = x.shape[0]
    out = np.empty(n)
    c = 0.0
    for _ in range(50):  # a contraction: β·t'/k < 1 on any cable that is not near λx = 1
        xx = x[0] - c
        c = beta * max(k * xx / max(1.0 - lam * xx, floor), 0.0) / k
    for i in range(n):
        xx = x[i] - c
        out[i] = max((k * xx + c_a * xd[i]) / max(1.0 - lam * xx, floor), 0.0)
        c += (beta * max(k * xx / max(1.0 - lam * xx, floor), 0.0) / k - c) * gain
    return out


@njit(cache=True)
def _creep_tension_jacobian(k: float, lam: float, c_a: float, beta: float, x: FloatArray, xd: FloatArray,
                            gain: float, floor: float) -> tuple[FloatArray, FloatArray]:
    """:func:`_creep_tension` and its exact derivatives ∂t/∂(k, λ, c_a, β) ((n,), (n, 4)), carried
    forward through the creep recursion. The creep's drive β·t_e/k = β·x'/(1 − λx') does not depend
    on k, so neither does c; c's derivatives at the first sample are iterated with its equilibrium
    (a contraction, so they converge to the implicit ones)."""
    n = x.shape[0]
    out = np.empty(n)
    dt = np.zeros((n, 4))
    c, dc_lam, dc_beta = 0.0, 0.0, 0.0

    def drive(xx, lam, beta):  # (g, ∂g/∂x', ∂g/∂λ, ∂g/∂β) of g = β·max(x'/(1 − λx'), 0) (clipped at floor)
        q = 1.0 - lam * xx
        if xx <= 0.0:
            return 0.0, 0.0, 0.0, 0.0
        if q > floor:
            return beta * xx / q, beta / (q * q), beta * xx * xx / (q * q), xx / q
        return beta * xx / floor, beta / floor, 0.0, xx / floor

    for _ in range(50):
        g, g_x, g_lam, g_beta = drive(x[0] - c, lam, beta)
        dc_lam = g_x * -dc_lam + g_lam
        dc_beta = g_x * -dc_beta + g_beta
        c = g
    for i in range(n):
        xx = x[i] - c
        q = 1.0 - lam * xx
        num = k * xx + c_a * xd[i]
        if q > floor:
            t = num / q
            if t > 0.0:
                # ∂x'/∂p = −∂c/∂p; ∂q/∂λ = −x' − λ·∂x'/∂λ, ∂q/∂β = −λ·∂x'/∂β
                dt[i, 0] = xx / q
                dt[i, 1] = (-k * dc_lam * q - num * (-xx + lam * dc_lam)) / (q * q)
                dt[i, 2] = xd[i] / q
                dt[i, 3] = (-k * dc_beta * q - num * (lam * dc_beta)) / (q * q)
        else:
            t = num / floor
            if t > 0.0:
                dt[i, 0] = xx / floor
                dt[i, 1] = -k * dc_lam / floor
                dt[i, 2] = xd[i] / floor
                dt[i, 3] = -k * dc_beta / floor
        out[i] = max(t, 0.0)
        g, g_x, g_lam, g_beta = drive(xx, lam, beta)
        dc_lam += (g_x * -dc_lam + g_lam - dc_lam) * gain
        dc_beta += (g_x * -dc_beta + g_beta - dc_beta) * gain
        c += (g - c) * gain
    return out, dt


def _tension(p: FloatArray, x: FloatArray, xd: FloatArray, tau_s: float, h: float) -> FloatArray:
    """t (N) of the model for p = (k, λ, c_a, μ, F₀, β, c_f) on the whole record (x (m), ẋ (m/s),
    step h (s)): eq. 54 on the stretch less the creep, the creep element driven by the tension it
    leaves, as a Kelvin element in series with the line is (twin/sim/integrator.py
    ``creep_update``), so that τ is the line's creep time, measurable on a bench
    (:func:`creep_taus`). (Until 2026-11-26 it was driven by the elastic tension of the whole
    stretch, k·x/(1 − λx): its τ was then shorter than the line's by 1 + β/(1 − λx)².)
    The drive is the elastic part k·x'/(1 − λx') of that tension, without c_a·ẋ': the fitted c_a
    absorbs more than the line's damping (the paper's 3000 N·s/m), and a creep fed by it went
    wrong with a heavy damping (docs/identification-coverage.md, "The creep driven by the tension it
    leaves"); with a real line's damping (40 N·s/m) the two drives give the same fit."""
    return _creep_tension(float(p[0]), float(p[1]), float(p[2]), float(p[5]), kernel_array(x),
                          kernel_array(xd), float(1.0 - np.exp(-h / tau_s)), MIN_STRETCH_FACTOR)


def _shape(c_f: float, theta_dot: FloatArray) -> FloatArray:
    """Eq. 37's friction shape (2/π)·arctan(c_f·θ̇): a sign for c_f → ∞."""
    return (2.0 / np.pi) * np.arctan(c_f * theta_dot)


def _residual(p: FloatArray, x: FloatArray, xd: FloatArray, theta_dot: FloatArray, y: FloatArray,
              rows: NDArray[np.bool_], tau_s: float, h: float, g_f: float = 0.0, g_b: float = 0.0) -> FloatArray:
    """Model force less the measured one (N) on the fit's rows: (1 + a·μ)·t + a·F₀ with the gear's
    meshing loss, g_f of the motor force when winding (a > 0), g_b of the tension when back-driven."""
    mu, f0, a = p[3], p[4], _shape(p[6], theta_dot[rows])
    t = _tension(p, x, xd, tau_s, h)[rows]
    return ((1 + a * mu) * t + a * f0 - g_b * np.maximum(-a, 0.0) * t) / (1 - g_f * np.maximum(a, 0.0)) - y[rows]


def fit_rows(proc: Processed, params: Params) -> tuple[FloatArray, NDArray[np.bool_]]:
    """y = f − (R/r_d)I_a·θ̈ (N, (n, n_cables)) and the rows the fit uses: motor faster than
    5 rad/s and y above 2 N, at an instant the fit uses (``Processed.fitted``: not a record gap's)."""
    y = proc.force - ia_over_rho(params) * proc.theta_ddot
    return y, (np.abs(proc.theta_dot) >= MIN_SPEED_RAD_S) & (y > MIN_FORCE_N) & proc.fitted[:, None]


def linear_start(proc: Processed, params: Params) -> tuple[FloatArray, FloatArray]:
    """(k, λ) per cable with no prior: without creep (β = 0) the model multiplied by 1 − λx is
    linear, y = k·x + λ·x·y + c_a·ẋ + (μk − F₀λ)·s·x + μc_a·s·ẋ + F₀·s, solved by least squares
    on the fit's rows (biased by the noise of x·y, but only a start); k ≤ 0 or λ < 0 are replaced
    by a tenth of the row's scale and 0."""
    y, rows = fit_rows(proc, params)
    s = np.sign(proc.theta_dot)
    k, lam = np.zeros(params.n_cables), np.zeros(params.n_cables)
    for j in range(params.n_cables):
        r = rows[:, j]
        x, xd, sj, yj = proc.x_c[r, j], proc.x_c_dot[r, j], s[r, j], y[r, j]
        A = np.column_stack([x, x * yj, xd, sj * x, sj * xd, sj])
        col = np.linalg.norm(A, axis=0)
        c = np.linalg.lstsq(A / np.maximum(col, 1e-300), yj, rcond=None)[0] / np.maximum(col, 1e-300)
        k_floor = 0.1 * float(np.mean(np.abs(yj)) / max(float(np.mean(np.abs(x))), 1e-9))
        k[j], lam[j] = (c[0] if c[0] > 0 else k_floor), max(c[1], 0.0)
    return k, lam


def _jacobian(p: FloatArray, scale: FloatArray, free: NDArray[np.bool_], x: FloatArray, xd: FloatArray,
              theta_dot: FloatArray, y: FloatArray, rows: NDArray[np.bool_], tau_s: float, h: float,
              g_f: float = 0.0, g_b: float = 0.0) -> FloatArray:
    """∂r/∂p (rows, free parameters) of :func:`_residual`, exact: the tension's derivatives carried
    through the creep recursion (:func:`_creep_tension_jacobian`), the friction's in closed form.
    ``scale`` is unused (the signature of :func:`_fd_jacobian`, which variants that replace
    :func:`_residual` put in its place). Central differences cost 14 residuals per Jacobian and
    were a third of the robot-truth fit's time (benchmarks/identification.py)."""
    t_all, dt_all = _creep_tension_jacobian(
        float(p[0]), float(p[1]), float(p[2]), float(p[5]), kernel_array(x),
        kernel_array(xd), float(1.0 - np.exp(-h / tau_s)), MIN_STRETCH_FACTOR)
    t, dt = t_all[rows], dt_all[rows]
    mu, f0, w = p[3], p[4], theta_dot[rows]
    a = _shape(p[6], w)
    winding, back = a > 0.0, a < 0.0
    den = 1 - g_f * np.where(winding, a, 0.0)
    num = (1 + a * mu) * t + a * f0 - g_b * np.where(back, -a, 0.0) * t
    gain = (1 + a * mu - g_b * np.where(back, -a, 0.0)) / den  # ∂r/∂t
    # ∂r/∂a: ∂num/∂a = μt + F₀ + g_b·t where back-driven; ∂den/∂a = −g_f where winding
    r_a = (mu * t + f0 + g_b * t * back) / den + num * g_f * winding / den**2
    a_cf = (2.0 / np.pi) * w / (1.0 + (p[6] * w) ** 2)
    J = np.column_stack([gain * dt[:, 0], gain * dt[:, 1], gain * dt[:, 2], a * t / den, a / den,
                         gain * dt[:, 3], r_a * a_cf])
    return J[:, free]


def _fd_jacobian(p: FloatArray, scale: FloatArray, free: NDArray[np.bool_], *args) -> FloatArray:
    """∂r/∂p (rows, free parameters) by central differences of :func:`_residual`, steps of 1e-6 of
    each scale: for variants of the residual without their own Jacobian, and to check :func:`_jacobian`."""
    cols = []
    for i in np.flatnonzero(free):
        d = np.zeros_like(p)
        d[i] = 1e-6 * scale[i]
        cols.append((_residual(p + d, *args) - _residual(p - d, *args)) / (2 * d[i]))
    return np.column_stack(cols)


@dataclass
class _Cable:
    """One cable's fit: its data arguments of :func:`_residual` (but τ), scales and bounds."""

    x: FloatArray
    x_dot: FloatArray
    theta_dot: FloatArray  # rad/s, the motor speed of eq. 37's friction shape
    y: FloatArray
    rows: NDArray[np.bool_]
    h: float
    scale: FloatArray
    lo: FloatArray
    hi: FloatArray
    gear: tuple[float, float] = (0.0, 0.0)  # (g_f, g_b): the gear's meshing losses, held (:func:`gear_losses`)

    def args(self, tau_s: float, x: FloatArray | None = None, x_dot: FloatArray | None = None) -> tuple:
        """:func:`_residual`'s arguments; ``x``, ``x_dot``: another stretch than the camera's."""
        return (self.x if x is None else x, self.x_dot if x_dot is None else x_dot, self.theta_dot, self.y, self.rows,
                tau_s, self.h, *self.gear)

    def solve(self, fun, p0: FloatArray, free: NDArray[np.bool_] | None = None, jac=None) -> FloatArray:
        """Bounded least squares of ``fun`` from ``p0``, over the ``free`` parameters only (the
        others held at ``p0``: an IV system has one equation per free parameter); ``jac``: p ↦
        ∂fun/∂p over all parameters, else finite differences."""
        idx = np.arange(len(p0)) if free is None else np.flatnonzero(free)

        def full(q: FloatArray) -> FloatArray:
            p = p0.copy()
            p[idx] = q
            return p

        out = p0.copy()
        # Any: scipy's annotations infer jac's type from its default, a string
        jac_of: Any = "2-point" if jac is None else (lambda q: jac(full(q))[:, idx])
        out[idx] = optimize.least_squares(lambda q: fun(full(q)), p0[idx], jac=jac_of,
                                          bounds=(self.lo[idx], self.hi[idx]), x_scale=self.scale[idx],
                                          method="trf", xtol=1e-10, ftol=1e-10, gtol=1e-10).x
        return out

    def jacobian(self, tau_s: float, x: FloatArray | None = None, x_dot: FloatArray | None = None):
        """p ↦ ∂r/∂p over all parameters (:func:`_jacobian`), on the camera's stretch or ``x``."""
        every = np.ones(len(self.scale), dtype=bool)
        return lambda p: _jacobian(p, self.scale, every, *self.args(tau_s, x, x_dot))


def gear_losses(params: Params) -> tuple[float, float]:
    """(g_f, g_b), the gear's meshing losses the fit holds: the parameter file's
    ``motors.gear_loss_forward`` and ``motors.gear_loss_backward`` (physics estimates there).

    Why held and not fitted: the forward loss divides the winding rows, the backward one scales
    the back-driven rows, and together with μ their mean is a scale on the tension, which no
    record separates from k (fitted on law 1's campaigns, g_f went to its bound and k 11-33 % low,
    docs/identification-coverage.md). Without them the fit takes the winding rows' steeper slope
    as curvature: on law 1's campaigns λ(3) came out 10-21 % low. The loss divides the winding
    rows' friction offset too (the meshing loss is a fraction of the whole motor force), which is
    what corrects λ(3): with the offset left undivided the fit gained nothing there
    (docs/identification-coverage.md, "The gear's meshing loss")."""
    return float(params.motors.gear_loss_forward), float(params.motors.gear_loss_backward)


def _cables(proc: Processed, params: Params, k0: FloatArray, lam0: FloatArray, damping: bool,
            gear: tuple[float, float]) -> list[_Cable]:
    y, rows = fit_rows(proc, params)
    out = []
    for j in range(params.n_cables):
        # Scales: k and λ from the start (a start of λ = 0 still needs one), c_a like a few hundred
        # N·s/m, μ, F₀, β like the robot's; the solver works on p / scale.
        k_s, lam_s = max(abs(k0[j]), 100.0), max(abs(lam0[j]), 10.0)
        # c_a held at 0 without damping: least_squares needs lo < hi, so a 1e-12 sliver
        lo = np.array([1e-3 * k_s, 0.0, 0.0 if damping else -1e-12, MU_BOUNDS[0], F0_BOUNDS_N[0], BETA_BOUNDS[0],
                       C_F_BOUNDS[0]])
        hi = np.array([np.inf, np.inf, np.inf if damping else 0.0, MU_BOUNDS[1], F0_BOUNDS_N[1], BETA_BOUNDS[1],
                       C_F_BOUNDS[1]])
        out.append(_Cable(proc.x_c[:, j], proc.x_c_dot[:, j], proc.theta_dot[:, j], y[:, j], rows[:, j],
                          1.0 / proc.rate_hz, np.array([k_s, lam_s, 1000.0, 0.1, 10.0, 0.05, 1.0]), lo, hi, gear))
    return out


def _least_squares(c: _Cable, starts: list[FloatArray], taus_s: tuple[float, ...],
                   free: NDArray[np.bool_] | None = None) -> tuple[FloatArray, float]:
    """Stage 1: least squares on the camera's stretch from every start and τ; the lowest residual."""
    best: tuple[float, FloatArray, float] | None = None
    for tau in taus_s:
        for p0 in starts:
            p = c.solve(lambda q, a=c.args(tau): _residual(q, *a), p0, free, c.jacobian(tau))
            cost = float(np.sum(_residual(p, *c.args(tau)) ** 2))
            if best is None or cost < best[0]:
                best = (cost, p, tau)
    assert best is not None
    return best[1], best[2]


def _instrumental(proc: Processed, params: Params, cables: list[_Cable], values: FloatArray, taus: FloatArray,
                  frees: list[NDArray[np.bool_]], first: dict | None = None, start: Simulated | None = None,
                  ) -> tuple[FloatArray, list[FloatArray], int, bool, Simulated]:
    """Stage 2, IDIM-IV: Zᵀρ(p) = 0 per cable, Z the model's Jacobian on the stretch the model
    (k, λ) predicts from the encoders (twin.identification.instruments: free of camera noise),
    re-simulated with each new (k, λ) until they change by less than IV_TOLERANCE. Returns the
    values, the instruments, the iterations, whether they converged and the last simulation
    (:class:`Simulated`: the stretch x (m), ẋ (m/s) the instruments were computed on). ``first``: a
    cache of first simulations by (k, λ), shared by the calls of one fit (every τ of the grid starts
    from the same least-squares values, hence the same first simulation). ``start``: a simulation
    at nearby values (another τ's) the first one starts from, instead of the camera's α."""
    m = build(params, "variable")
    vals, zs, prev, it = values.copy(), [np.zeros(0)] * len(cables), None, 0
    while it < IV_MAX_ITERATIONS:
        it += 1
        k, lam = vals[:, 0].copy(), vals[:, 1].copy()
        key = (k.tobytes(), lam.tobytes())
        if prev is None and first is not None and key in first:
            sim = first[key]
        else:
            warm = prev if prev is not None else start
            sim = simulated_stretch(m, proc, k, lam, *((None, None) if warm is None else (warm.alpha, warm.jacobian)))
            if prev is None and first is not None:
                first[key] = sim
        prev = sim
        for j, c in enumerate(cables):
            Z = _jacobian(vals[j], c.scale, frees[j], *c.args(taus[j], sim.x[:, j], sim.x_dot[:, j]))
            Q, _ = np.linalg.qr(Z / np.maximum(np.linalg.norm(Z, axis=0), 1e-300))
            zs[j] = Z
            jac = c.jacobian(taus[j])
            vals[j] = c.solve(lambda q, a=c.args(taus[j]), Q=Q: Q.T @ _residual(q, *a), vals[j], frees[j],
                              lambda q, Q=Q, jac=jac: Q.T @ jac(q))
        change = max(np.max(np.abs(vals[:, 0] / k - 1)), np.max(np.abs(vals[:, 1] - lam) / np.maximum(lam, 1.0)))
        if change < IV_TOLERANCE:
            return vals, zs, it, True, sim
    return vals, zs, it, False, sim


def fit_load_friction(proc: Processed, params: Params, start: tuple[FloatArray, FloatArray] | None = None, *,
                      threshold: float = DEFAULT_THRESHOLD, sigma: str = "hac", damping: bool = True,
                      instruments: bool = True, taus_s: tuple[float, ...] = TAUS_S,
                      creep_ratio: float | None = None, gear: tuple[float, float] | None = None) -> LoadFrictionFit:
    """Fit the model of the module docstring per cable.

    ``start``: (k (N/m), λ (1/m)) per cable, tried beside :func:`linear_start`. ``damping`` False
    holds c_a at 0 (the diagnosis script's candidate). ``instruments`` (default): after the
    least-squares fit, IDIM-IV (:func:`_instrumental`) for each τ of the grid, τ picked per cable
    by the camera residual; False: least squares alone (consistent only with a noise-free
    stretch). ``taus_s``: the creep time constants tried (:func:`creep_taus`); ``creep_ratio``: β held
    at this value on every cable instead of fitted (docs/identification/estimator_variants.py
    ``beta-X``: held at the robot truth's own 0.05 it made k worse, the fit's β absorbs more than
    the creep); ``gear``: the gear's meshing losses (g_f, g_b) held, None (default): the parameter
    file's (:func:`gear_losses`); (0, 0) is the fit without them, in which the paper's eqs. 54-55 are
    μ = β = 0 (twin.identification.model_choice tests that fit). Raises ValueError when a cable has fewer than :data:`MIN_ROWS` rows (its motor never
    turned fast while its cable was taut), for a bad ``start`` or an unknown ``sigma``."""
    check_sigma(sigma)
    nc = params.n_cables
    _, rows = fit_rows(proc, params)
    counts = rows.sum(axis=0)
    if np.any(counts < MIN_ROWS):
        poor = [f"{j + 1} ({int(counts[j])} rows)" for j in range(nc) if counts[j] < MIN_ROWS]
        raise ValueError(f"{NAME}: cable(s) {', '.join(poor)} have fewer than {MIN_ROWS} instants with the motor "
                         f"faster than {MIN_SPEED_RAD_S:g} rad/s and a force above {MIN_FORCE_N:g} N; "
                         "run the identification trajectory")
    linear = linear_start(proc, params)
    k0, lam0 = (np.asarray(v, dtype=float) for v in (start or linear))
    if k0.shape != (nc,) or lam0.shape != (nc,) or not (np.all(np.isfinite(k0)) and np.all(np.isfinite(lam0))):
        raise ValueError(f"{NAME}: start must be {nc} finite k and λ, got {start}")
    gear = gear_losses(params) if gear is None else (float(gear[0]), float(gear[1]))
    if not all(0.0 <= g < 0.5 for g in gear):
        raise ValueError(f"{NAME}: gear losses must be in [0, 0.5), got {gear}")
    cables = _cables(proc, params, k0, lam0, damping, gear)
    free = np.arange(len(SYMBOLS)) != 2 if not damping else np.ones(len(SYMBOLS), dtype=bool)
    if creep_ratio is not None:
        if not BETA_BOUNDS[0] <= creep_ratio <= BETA_BOUNDS[1]:
            raise ValueError(f"{NAME}: creep_ratio must be within {BETA_BOUNDS}, got {creep_ratio}")
        free[5] = False
    values, taus = np.zeros((nc, len(SYMBOLS))), np.zeros(nc)
    for j, c in enumerate(cables):
        beta0 = 0.0 if creep_ratio is None else float(creep_ratio)
        starts = [np.array([max(kk, 0.1 * c.scale[0]), max(ll, 0.0), 0.0, 0.1, 10.0, beta0, params.friction.c_s])
                  for kk, ll in dict.fromkeys(((k0[j], lam0[j]), (linear[0][j], linear[1][j])))]
        values[j], taus[j] = _least_squares(c, starts, taus_s, free)
    frees = [_hold_flat_shape(values[j], free) for j in range(nc)]
    zs: list[FloatArray] | None = None
    sim: Simulated | None = None
    iterations, converged = 0, True
    if instruments:
        # τ again, from each τ's IV solution: the least-squares stage picked it on the noisy stretch,
        # with the noise's bias, and a wrong β, τ trades against k.
        costs = np.zeros((len(taus_s), nc))
        moments = np.zeros((len(taus_s), nc))
        grid_values, grid_sims, first = [], [], {}
        by_moment = TAU_CHOICE == "iv" and len(taus_s) > 1  # a held τ (one grid point) has nothing to choose
        for i, tau in enumerate(taus_s):
            vals, _, it, _, sim_i = _instrumental(proc, params, cables, values, np.full(nc, tau), frees, first)
            iterations = max(iterations, it)
            for j, c in enumerate(cables):
                r = _residual(vals[j], *c.args(tau))
                costs[i, j] = float(r @ r)
                if by_moment:
                    z = _tau_column(vals[j], tau, c, sim_i.x[:, j], sim_i.x_dot[:, j])
                    moments[i, j] = float(z @ r) / max(float(np.linalg.norm(z) * np.linalg.norm(r)), 1e-300)
            grid_values.append(vals)
            grid_sims.append(sim_i)
        best = np.argmin(costs, axis=0)
        chosen = np.array([grid_values[best[j]][j] for j in range(nc)])
        taus = refine_tau(np.asarray(taus_s, dtype=float), costs)
        if by_moment:
            taus, chosen = _iv_taus(np.asarray(taus_s, dtype=float), moments, costs, taus, chosen, grid_values)
        # Z at the chosen τ, the neck's re-simulation started from the grid's nearest one
        near = int(np.argmin(np.abs(np.log(np.asarray(taus_s, dtype=float)) - np.log(np.median(taus)))))
        values, zs, it, ok, sim = _instrumental(proc, params, cables, chosen, taus, frees, start=grid_sims[near])
        iterations, converged = max(iterations, it), ok
    est = _estimate(proc, cables, values, taus, free, frees, zs, sim, sigma, threshold)
    how = (f"instrumental variables (simulated model, {'' if converged else 'NOT converged in '}"
           f"at most {iterations} iterations per τ)" if instruments
           else "nonlinear least squares")
    g_f, g_b = gear
    est = dataclasses.replace(est, estimator=(
        f"{how}; friction (1 + a·μ)·t + a·F₀, a = (2/π)·arctan(c_f·θ̇), |θ̇| ≥ {MIN_SPEED_RAD_S:g} rad/s"
        + (f", gear meshing loss {g_f:g} winding / {g_b:g} back-driven (held, parameter file)" if g_f or g_b else "")
        + "; Kelvin creep τ = "
        + (f"{taus_s[0]:.3g} s (held, given)" if len(taus_s) == 1 else f"{', '.join(f'{t:.2g}' for t in taus)} s")
        + ("" if damping else "; no damping")))
    return LoadFrictionFit(est, taus, (k0, lam0), np.asarray(counts, dtype=np.int64))


def creep_taus(creep_time_s: float | None) -> tuple[float, ...]:
    """The τ grid (s) of :func:`fit_load_friction`: :data:`TAUS_S` (τ chosen from the record) or the
    line's creep time constant measured apart, held. Raises ValueError for a τ that is not a finite
    positive number of seconds.

    A creep time is a property of the line, measurable on a bench (a weight hung on a sample of the
    line, its elongation recorded for a minute), unlike k and λ, which depend on the routing. On the
    robot truth, held at the truth's own τ it adds little to the τ estimated at its moment's root
    (:func:`_iv_taus`; ±2σ coverage of Table 2 150 / 145 against 149 / 145 of 160 on the
    identification loop) and costs on law 1's campaigns (109 against 122 of 160, where the free τ
    absorbs part of the friction offset the model lacks): docs/identification-coverage.md, "The
    creep element and its time constant". Not a default."""
    tau = check_creep_time(creep_time_s)
    return TAUS_S if tau is None else (tau,)


def _iv_taus(grid_s, moments, costs, taus, chosen, grid_values):
    """τ (s) per cable as IDIM-IV estimates the other parameters: at the root of its instrument's
    moment, z_τᵀρ(τ) = 0 with z_τ = ∂ρ/∂τ on the stretch simulated from the encoders (free of camera
    noise), ρ the residual of that τ's IV solution; ``moments`` (len(grid), n_cables) normalised.
    The root is interpolated linearly in log τ between the grid points where the moment changes
    sign; where it changes sign more than once, the root next to the lower camera residual; where
    it does not (β = 0: τ changes nothing, or the root is off the grid), ``taus`` as given (the
    camera residual's choice, :func:`refine_tau`). Returns the τ and the IV solutions the final
    iteration starts from (the grid point next to the root).

    Why not the camera residual alone: it is least squares on the noisy stretch, and picked τ with
    the noise's bias (0.5-8 s per cable on the robot truth, whose τ is 2 s), which moved k(4) and
    λ(4) by 5-17 points; at the moment's root the ±2σ coverage of Table 2 on the robot truth went
    from 134 / 129 to 149 / 145 of 160 (seeds 21-40 / 41-60, docs/identification-coverage.md)."""
    u = np.log(grid_s)
    taus, chosen = taus.copy(), chosen.copy()
    for j in range(moments.shape[1]):
        m = moments[:, j]
        roots = [(i, u[i] + (u[i + 1] - u[i]) * m[i] / (m[i] - m[i + 1])) for i in range(len(u) - 1)
                 if m[i] != 0 and m[i + 1] != 0 and np.sign(m[i]) != np.sign(m[i + 1])]
        if roots:
            i, root = min(roots, key=lambda r: min(costs[r[0], j], costs[r[0] + 1, j]))
            taus[j] = float(np.exp(root))
            near = i if costs[i, j] <= costs[i + 1, j] else i + 1
            chosen[j] = grid_values[near][j]
    return taus, chosen


def refine_tau(grid_s: FloatArray, costs: FloatArray) -> FloatArray:
    """τ (s) per cable between the grid's points: the vertex of the parabola in log τ through the
    best grid point and its two neighbours (``costs``: (len(grid), n_cables) camera residuals of
    each τ's IV solution); the best grid point itself at the grid's ends or where the three points
    do not curve upwards."""
    u = np.log(grid_s)
    out = np.empty(costs.shape[1])
    for j in range(costs.shape[1]):
        i = int(np.argmin(costs[:, j]))
        out[j] = grid_s[i]
        if 0 < i < len(grid_s) - 1:
            a, b, _ = np.polyfit(u[i - 1:i + 2], costs[i - 1:i + 2, j], 2)
            if a > 0:
                out[j] = float(np.exp(np.clip(-b / (2 * a), u[i - 1], u[i + 1])))
    return out


def _tau_column(p: FloatArray, tau_s: float, c: _Cable, x: FloatArray | None = None,
                x_dot: FloatArray | None = None) -> FloatArray:
    """∂ρ/∂τ (rows,) by a central difference of 0.1 % of τ, on the camera's stretch or on ``x``."""
    d = 1e-3 * tau_s
    return (_residual(p, *c.args(tau_s + d, x, x_dot)) - _residual(p, *c.args(tau_s - d, x, x_dot))) / (2 * d)


def _hold_flat_shape(p: FloatArray, free: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The parameters estimated for this cable: ``free`` less c_f when the fit put it at its upper
    bound. The shape is then a sign on the fit's rows (|θ̇| ≥ 5 rad/s), c_f's column of the
    Jacobian vanishes, and it would only add noise to the instruments and the σ: held there."""
    fj = free.copy()
    if p[6] >= C_F_BOUNDS[1] * (1 - 1e-6):
        p[6] = C_F_BOUNDS[1]
        fj[6] = False
    return fj


def _estimate(proc: Processed, cables: list[_Cable], values: FloatArray, taus: FloatArray, free: NDArray[np.bool_],
              frees: list[NDArray[np.bool_]],
              zs: list[FloatArray] | None, sim: Simulated | None, sigma: str,
              threshold: float) -> Estimate:
    """The :class:`Estimate`: σ of the linearised estimator v − v_true ≈ −B·ρ at the solution,
    B = (ZᵀJ)⁻¹Zᵀ (Z = J for least squares), by the HAC sandwich with the rows' instants as the
    time index (at least the filter's memory as lag, as the pipeline's). τ counts as estimated:
    it was picked by the camera residual, i.e. by least squares, so J and Z both get its column
    ∂ρ/∂τ (where β > 0; with β = 0, τ changes nothing). ``sim``: the instruments' simulation, whose
    stretch x, ẋ gives Z's τ column."""
    nc, n_par = len(cables), len(SYMBOLS)
    min_lag = int(np.ceil(HAC_MIN_LAG_PERIODS * proc.rate_hz / proc.cutoff_hz))
    sd = np.zeros((nc, n_par))
    active: list[str] = []
    lags: list[int] = []
    conds: list[float] = []
    sse = 0.0
    for j, c in enumerate(cables):
        res = _residual(values[j], *c.args(taus[j]))
        fj = frees[j]
        J = _jacobian(values[j], c.scale, fj, *c.args(taus[j]))
        conds.append(float(np.linalg.cond(J)))
        Z = J if zs is None else zs[j]
        if values[j, 5] > BETA_BOUNDS[0] + 1e-9 * c.scale[5]:
            jt = _tau_column(values[j], taus[j], c)
            zt = jt if sim is None else _tau_column(values[j], taus[j], c, sim.x[:, j], sim.x_dot[:, j])
            J, Z = np.column_stack([J, jt]), np.column_stack([Z, zt])
        try:
            B = np.asarray(np.linalg.solve(Z.T @ J, Z.T), dtype=np.float64)[: int(fj.sum())]
        except np.linalg.LinAlgError:
            # τ's column vanishes where β is tiny but not 0 (τ then changes nothing): the pseudo-inverse
            # gives the other parameters' rows as without it, instead of failing the identification
            B = np.asarray(np.linalg.pinv(Z.T @ J) @ Z.T, dtype=np.float64)[: int(fj.sum())]
        idx = np.flatnonzero(c.rows).astype(np.int64)
        if sigma == "hac":
            cov, lag = uncertainty.hac_covariance(B, res, idx, proc.n, min_lag=min_lag, n_used=int(proc.fitted.sum()))
        else:
            cov, lag = uncertainty.white_covariance(B, res), 0
        sd[j, fj] = np.sqrt(np.abs(np.diag(cov)))
        lags.append(lag)
        sse += float(res @ res)
        at = free & ((values[j] <= c.lo + 1e-9 * c.scale) | (values[j] >= c.hi - 1e-9 * c.scale))
        active += [f"{SYMBOLS[i]}({j + 1})" for i in np.flatnonzero(at)]
    v, sd_v = values.T.reshape(-1), sd.T.reshape(-1)  # symbol-major: k(1..nc), lambda(1..nc), ...
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = sd_v / np.abs(v)
    lag = max(lags)
    return Estimate(
        method="variable", equations="eqs. 54-55 with load-dependent friction and creep",
        names=sum((param_names(sym, nc) for sym in SYMBOLS), ()), values=v, sigma=sd_v, relative_sigma=rel,
        condition_number=max(conds), residual_norm=float(np.sqrt(sse)), n_rows=int(sum(c.rows.sum() for c in cables)),
        n_samples=int(proc.fitted.sum()), threshold=threshold,
        sigma_method=f"HAC (Newey-West, Bartlett, {lag} lags)" if sigma == "hac" else "eq. 50 (white residuals)",
        hac_lag=lag, active_bounds=tuple(active),
    )
