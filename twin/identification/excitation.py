"""Excitation design for the identification (3-X paper §5.2.2; after FloBaRoID's D-optimal
excitation and BIRDy's trajectory criteria): waypoints joined by rest-to-rest cycloids, chosen to
maximise the information of the friction (eq. 38) and variable-stiffness (eqs. 54-57) regressors.

Pure: trajectory parameters -> nominal signals -> regressor -> criterion. What depends on the
controller (the cycloidal path and the forces the law commands on it, with their limits) is passed
in as callables by the caller (``xneck excitation design``, :mod:`server.cli.excitation`): the
twin must not import the controller.

The design problem
------------------
A trajectory is K waypoints α_0 = 0, α_1 … α_{K-2}, α_{K-1} = 0 (rad; it starts and ends straight
and at rest, as §5.2.2 and the α̂ estimators assume) joined by cycloidal moves, with a 1 s rest at
each end. A move's shortest duration is what its peak speed 2|Δ|/T and acceleration 2π|Δ|/T² allow
at a fraction ``speed`` of the limits. ``holds="none"`` (the default) stretches every move by the
same factor until they fill the duration: a still motor gives neither regressor a row (eq. 37's
arctan is 0 at rest, and the identification drops the tension rows of slow motors), so a hold is
time without information. ``holds="fill"`` keeps the shortest moves and shares the remaining time
equally between holds at the waypoints (the §5.2.2 trajectory's stops).

Along the nominal path (α = α^d) the law's forces f give the cable tensions t_c = f − (R/r_d)I_a·θ̈
(eq. 41 without friction: the law-1 feed-forward has none, its integrator adds it on top), the
stretch x_c = t_c/(k + λ·t_c) (eq. 54 at rest, the base parameters), ẋ_c, and θ̇ = (Zᵀα̇ + ẋ_c)/ρ
(eq. 27 differentiated). The regressors, with each column scaled by the base value of its
parameter (so that the information is about *relative* precision, the unit of the σ's reported):

* friction, eq. 38: Z·diag(a)·diag(f_s), a = (2/π)arctan(c_s·θ̇) (eq. 37), N rows per sample;
* variable stiffness, eqs. 54-57: per cable [x_c·k, x_c·t_c·λ, ẋ_c·c_a] / (1 + λt_c/k), rows of
  slack cables (t_c < 2 N) and of motors slower than 1/c_s dropped as in the identification
  (regressors.moving_mask); the weight is the growth of the residual's noise with the tension
  (the stretch's noise σ_x enters t − kx − λxt as (k + λt)·σ_x).

Pretension. The redundant cables' internal force is free: raising every cable's floor t_min by a
pretension P (controller.trajectory, eq. 65) raises all four tensions without moving the neck.
The joint motion alone keeps the tensions near the floor (law 1 minimises ‖f‖), where t_c ≈ k·x_c
and k and λ are nearly collinear; sweeping P over [0, ``pretension_max_N``] spreads the tensions
over the curve of eq. 54 and decorrelates them. Each inner waypoint then has a pretension level
as well (the first and last stay at 0), joined by the same cycloids, and a move lasts long enough
for its pretension change at ``pretension_rate_N_s``.

Criterion (D-optimality): log det of each normalised information matrix F = Σ_rows wwᵀ·h / D
(h the sample step, D the duration), summed over the two regressors (they share no parameter, so
this is log det of the block-diagonal whole). The condition numbers reported are those of the
normalised regressors, √cond(F). Rest-to-rest cycloids make the information additive over moves
and holds: each is computed once and cached, so a finite-difference gradient costs two moves per
variable. Force limits enter as a penalty (scipy's L-BFGS-B keeps the waypoints in the joint
box); the final trajectory goes through the controller's own validation (``check``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from twin.model import dynamics
from twin.model.numeric import Model, build
from twin.model.params import Params

__all__ = [
    "DesignError",
    "DesignProblem",
    "Excitation",
    "Information",
    "Score",
    "design",
    "move_durations",
    "score",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

PathFn = Callable[[FloatArray, FloatArray, float, FloatArray], tuple[FloatArray, FloatArray, FloatArray]]
"""(start α (N,), end α (N,), move duration T (s), times in [0, T] (s)) -> α, α̇, α̈ (T, N) of the
cycloidal move (rad, rad/s, rad/s²). Given by the caller: the controller's trajectory."""

ForceFn = Callable[..., tuple[FloatArray, BoolArray]]
"""(α, α̇, α̈) (T, N)[, pretension (T,) N] -> (forces the law commands on that nominal path
(T, n_cables) N before any clamping, distribution feasible (T,)). Given by the caller:
:func:`controller.laws.nominal_forces`."""

CheckFn = Callable[[FloatArray, FloatArray, FloatArray, FloatArray], None]
"""(waypoints (K, N) rad, move durations (K-1,) s, holds (K,) s, pretension (K,) N) -> None, or
raises ValueError with the reason: the controller's trajectory validation (joint, speed,
acceleration, pretension, forces)."""

MIN_TENSION_N = 2.0  # the identification drops tension rows below this (slack cable), so does the design
MIN_MOVE_S = 1.0  # shortest move: below it the law's tracking, not the path, sets the motion
REST_S = 1.0  # initial and final rest (s), as the §5.2.2 trajectory (the estimators start at rest)
STEP_S = 0.1  # sample step of the design (s): moves last ≥ 1 s, 10 samples at least
FORCE_MARGIN = 0.9  # the design keeps the nominal forces under this fraction of f_max: the law adds
# feedback on top of the feed-forward, and the validation samples finer than the design


class DesignError(ValueError):
    """The excitation cannot be designed as asked (the message says why)."""


@dataclass(frozen=True, eq=False)
class DesignProblem:
    """What the design needs, built by :meth:`create` from a parameter set and the limits.

    alpha_max (N,) rad: the waypoints stay within ±alpha_max; v_max (N,) rad/s and a_max (N,)
    rad/s²: the peak speed and acceleration the moves use (the limits times ``speed``);
    duration_s: the whole trajectory, rests included."""

    model: Model
    f_s: FloatArray  # (nc,) N, base friction: column scale of the friction regressor
    k: FloatArray  # (nc,) N/m, base variable-stiffness parameters: column scales and x_c(t_c)
    lam: FloatArray  # (nc,) 1/m
    c_a: FloatArray  # (nc,) N·s/m
    alpha_max: FloatArray
    v_max: FloatArray
    a_max: FloatArray
    duration_s: float
    path: PathFn
    forces: ForceFn
    check: CheckFn | None = None
    criterion: str = "d"  # "d": D-optimality on every parameter; "ds": on k and λ (c_a a nuisance) + f_s
    pretension_max_N: float = 0.0  # largest pretension a waypoint may ask for (0: none, the joints alone)
    pretension_rate_N_s: float = 100.0  # peak rate of a pretension change (the trajectory limit)
    holds: str = "none"  # "none": moves stretched to fill the duration; "fill": shortest moves, then holds
    _cache: dict[Any, Information] = field(default_factory=dict, repr=False)

    @classmethod
    def create(cls, params: Params, *, duration_s: float, alpha_max_rad: FloatArray | float,
               v_max_rad_s: FloatArray | float, a_max_rad_s2: FloatArray | float, path: PathFn,
               forces: ForceFn, check: CheckFn | None = None, speed: float = 0.6,
               criterion: str = "d", pretension_max_N: float = 0.0,
               pretension_rate_N_s: float = 100.0, holds: str = "none") -> DesignProblem:
        """A problem for ``params`` (its variable-stiffness cables and friction are the base values)."""
        if not (math.isfinite(duration_s) and duration_s > 2 * REST_S + MIN_MOVE_S):
            raise DesignError(f"duration must be a number of seconds above {2 * REST_S + MIN_MOVE_S:g}, got {duration_s}")
        if not (math.isfinite(speed) and 0.0 < speed <= 1.0):
            raise DesignError(f"speed is a fraction of the speed and acceleration limits in (0, 1], got {speed}")
        if criterion not in ("d", "ds"):
            raise DesignError(f"criterion must be d (every parameter) or ds (k and λ, c_a a nuisance), got {criterion!r}")
        if holds not in ("none", "fill"):
            raise DesignError(f"holds must be none (moves fill the duration) or fill (shortest moves, then holds), got {holds!r}")
        if not (math.isfinite(pretension_max_N) and 0.0 <= pretension_max_N < params.limits.f_max):
            raise DesignError(f"the pretension bound must be in [0, f_max = {params.limits.f_max:g}) N, got {pretension_max_N}")
        if not (math.isfinite(pretension_rate_N_s) and pretension_rate_N_s > 0.0):
            raise DesignError(f"the pretension rate must be positive (N/s), got {pretension_rate_N_s}")
        n = params.n_joints
        per_joint = [np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy()
                     for v in (alpha_max_rad, v_max_rad_s, a_max_rad_s2)]
        for name, v in zip(("alpha_max", "v_max", "a_max"), per_joint):
            if not np.all(np.isfinite(v) & (v > 0)):
                raise DesignError(f"{name} must be positive and finite, got {v}")
        var = params.cables.variable
        return cls(model=build(params, "variable"), f_s=np.asarray(params.friction.f_s, dtype=float),
                   k=np.asarray(var.k, dtype=float), lam=np.asarray(var.lam, dtype=float),
                   c_a=np.asarray(var.c_a, dtype=float), alpha_max=per_joint[0], v_max=speed * per_joint[1],
                   a_max=speed * per_joint[2], duration_s=float(duration_s), path=path, forces=forces, check=check,
                   criterion=criterion, pretension_max_N=float(pretension_max_N),
                   pretension_rate_N_s=speed * float(pretension_rate_N_s), holds=holds)

    @property
    def n_joints(self) -> int:
        return int(self.model.n_joints)


class Information(NamedTuple):
    """Unnormalised information (Σ rows·rowsᵀ·h) of a piece of trajectory, and its force penalty."""

    friction: FloatArray  # (nc, nc)
    variable: FloatArray  # (3nc, 3nc), order k(1..nc), λ(1..nc), c_a(1..nc)
    penalty: float  # Σ (excess force / f_max)²·h, plus h per sample where the distribution fails

    def __add__(self, other: object) -> Information:  # type: ignore[override]
        assert isinstance(other, Information)
        return Information(self.friction + other.friction, self.variable + other.variable,
                           self.penalty + other.penalty)

    def scaled(self, s: float) -> Information:
        return Information(s * self.friction, s * self.variable, s * self.penalty)


def _information(p: DesignProblem, alpha: FloatArray, alpha_dot: FloatArray, alpha_ddot: FloatArray,
                 h: float, pretension: FloatArray | None = None) -> Information:
    """Regressor rows (module docstring) of nominal samples taken every ``h`` seconds, as
    information; ``pretension`` (T,) N raises the law's floor (None: none)."""
    m = p.model
    f, feasible = (p.forces(alpha, alpha_dot, alpha_ddot) if pretension is None
                   else p.forces(alpha, alpha_dot, alpha_ddot, pretension))
    terms = dynamics.evaluate(m, alpha, alpha_dot)
    zt_dot = np.einsum("nij,ni->nj", terms.Z, alpha_dot)  # Zᵀα̇ = −l̇_c
    theta_ddot = (np.einsum("nij,ni->nj", terms.Z, alpha_ddot) + np.einsum("nij,ni->nj", terms.Z_dot, alpha_dot)) / m.rho
    t_c = np.maximum(f - m.I_a * theta_ddot / m.rho, 0.0)
    x_c = t_c / (p.k + p.lam * t_c)
    x_dot = np.gradient(x_c, h, axis=0) if len(x_c) > 1 else np.zeros_like(x_c)
    theta_dot = (zt_dot + x_dot) / m.rho
    a = dynamics.friction_shapes(m.c_s, m.friction_sign, theta_dot)
    # The identification keeps the tension rows of turning motors only (regressors.moving_mask),
    # and the stretch's noise σ_x enters their residual t − kx − λxt as (k + λt)·σ_x: rows
    # weighted by 1/(1 + λt/k), the base noise being that at zero tension.
    kept = (t_c >= MIN_TENSION_N) & (np.abs(theta_dot) * m.c_s >= 1.0)
    weight = 1.0 / (1.0 + p.lam * t_c / p.k)
    fr = (terms.Z * (a * p.f_s)[:, None, :]).reshape(-1, m.n_cables)
    nc = m.n_cables
    var = np.zeros((3 * nc, 3 * nc))
    for j in range(nc):  # one cable's rows touch only its own k, λ, c_a
        rows = np.column_stack([x_c[:, j] * p.k[j], x_c[:, j] * t_c[:, j] * p.lam[j], x_dot[:, j] * p.c_a[j]])
        rows = (rows * weight[:, j, None])[kept[:, j]]
        idx = [j, nc + j, 2 * nc + j]
        var[np.ix_(idx, idx)] = rows.T @ rows
    excess = np.maximum(f.max(axis=1) / (FORCE_MARGIN * m.f_max) - 1.0, 0.0)
    penalty = float(np.sum(excess**2) + np.sum(~feasible))
    return Information(h * (fr.T @ fr), h * var, h * penalty)


def _move(p: DesignProblem, a: FloatArray, b: FloatArray, T: float, pa: float = 0.0, pb: float = 0.0) -> Information:
    key = ("move", a.tobytes(), b.tobytes(), T, pa, pb)
    if key not in p._cache:
        n = max(int(math.ceil(T / STEP_S)), 2)
        t = np.linspace(0.0, T, n + 1)
        alpha, alpha_dot, alpha_ddot = p.path(a, b, T, t)
        # The pretension follows the joints' cycloid: the same path, on one coordinate.
        pre = None if pa == pb == 0.0 else p.path(np.array([pa]), np.array([pb]), T, t)[0][:, 0]
        p._cache[key] = _information(p, alpha, alpha_dot, alpha_ddot, T / n, pre)
    return p._cache[key]


def _hold(p: DesignProblem, a: FloatArray, pa: float = 0.0) -> Information:
    """Information of one second held at ``a`` with the pretension ``pa`` (N)."""
    key = ("hold", a.tobytes(), pa)
    if key not in p._cache:
        z = np.zeros((1, p.n_joints))
        p._cache[key] = _information(p, a[None, :], z, z, 1.0, None if pa == 0.0 else np.array([pa]))
    return p._cache[key]


def move_durations(p: DesignProblem, waypoints: FloatArray, pretension: FloatArray | None = None) -> FloatArray:
    """Shortest duration (s) of each cycloidal move within ``p``'s speed and acceleration: peaks
    2|Δ|/T and 2π|Δ|/T² (controller.trajectory's exact cycloid peaks), and 2|ΔP|/T within the
    pretension rate; at least 1 s."""
    delta = np.abs(np.diff(waypoints, axis=0))
    t_v = 2.0 * delta / p.v_max
    t_a = np.sqrt(2.0 * math.pi * delta / p.a_max)
    t_move = np.maximum(t_v, t_a).max(axis=1)
    if pretension is not None:
        t_move = np.maximum(t_move, 2.0 * np.abs(np.diff(pretension)) / p.pretension_rate_N_s)
    # A hair above the bound: the validation compares the peak with the limit in floating point.
    return np.maximum(t_move * (1.0 + 1e-6), MIN_MOVE_S)


def _timing(p: DesignProblem, waypoints: FloatArray, pretension: FloatArray | None = None
            ) -> tuple[FloatArray, FloatArray, float]:
    """Move durations, holds (rests at both ends; the remaining time stretches the moves, or is
    shared by the inner holds: ``p.holds``), and how many seconds the shortest moves overrun the
    duration (0 when they fit)."""
    durations = move_durations(p, waypoints, pretension)
    k = len(waypoints)
    inner = p.duration_s - 2 * REST_S - durations.sum()
    dwell = np.zeros(k)
    if p.holds == "none":
        if inner > 0.0:
            durations = durations * ((p.duration_s - 2 * REST_S) / durations.sum())
    else:
        dwell[:] = max(inner, 0.0) / max(k - 2, 1)
    dwell[[0, -1]] = REST_S
    return durations, dwell, max(-inner, 0.0)


def information(p: DesignProblem, waypoints: FloatArray, durations: FloatArray, dwell: FloatArray,
                pretension: FloatArray | None = None) -> Information:
    """Information of a whole trajectory (any timing: the designed one or the paper's), with the
    pretension (K,) N at each waypoint (None: none)."""
    P = np.zeros(len(waypoints)) if pretension is None else np.asarray(pretension, dtype=float)
    total = Information(np.zeros((p.model.n_cables,) * 2), np.zeros((3 * p.model.n_cables,) * 2), 0.0)
    for i in range(len(waypoints)):
        if dwell[i] > 0:
            total = total + _hold(p, waypoints[i], float(P[i])).scaled(float(dwell[i]))
        if i + 1 < len(waypoints):
            total = total + _move(p, waypoints[i], waypoints[i + 1], float(durations[i]), float(P[i]), float(P[i + 1]))
    return total


class Score(NamedTuple):
    """How informative a trajectory is (module docstring)."""

    log_det: float  # log det F_friction + log det F_variable (normalised by the duration)
    log_det_friction: float
    log_det_variable: float
    cond_friction: float  # condition numbers of the normalised regressors, √cond(F)
    cond_variable: float
    penalty: float  # force-limit penalty (0 when every nominal force is within the margin)
    duration_s: float
    # √diag(F⁻¹) per parameter, names as the identification's ("f_s(1)", "k(1)", "lambda(1)", "c_a(1)"):
    # the relative σ up to the (common) noise level, per √s of record. Ratios between two designs
    # of the same duration predict the ratio of their σ's.
    relative_sigma: dict[str, float]
    # Ds-optimality on k and λ (c_a a nuisance): log det F_friction − Σ_cables log det Cov(k, λ)
    log_det_ds: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {k: float(v) for k, v in self._asdict().items() if k != "relative_sigma"}
        out["relative_sigma"] = dict(self.relative_sigma)
        return out


def _logdet(F: FloatArray) -> float:
    sign, val = np.linalg.slogdet(F)
    return float(val) if sign > 0 else -1e3  # singular: nothing to learn about some parameter


def _rel_sigma(F: FloatArray) -> FloatArray:
    try:
        return np.sqrt(np.abs(np.diag(np.linalg.inv(F))))
    except np.linalg.LinAlgError:
        return np.full(len(F), math.inf)


def _cond(F: FloatArray) -> float:
    s = np.linalg.eigvalsh(F)
    return float(math.sqrt(s[-1] / s[0])) if s[0] > 0 else math.inf


def score(p: DesignProblem, waypoints: FloatArray, durations: FloatArray, dwell: FloatArray,
          pretension: FloatArray | None = None) -> Score:
    """The design criterion of a trajectory (waypoints (K, N) rad, durations (K-1,) s, holds (K,) s,
    pretension (K,) N or None)."""
    waypoints = np.asarray(waypoints, dtype=float)
    durations = np.broadcast_to(np.asarray(durations, dtype=float), (len(waypoints) - 1,))
    dwell = np.broadcast_to(np.asarray(dwell, dtype=float), (len(waypoints),))
    duration = float(durations.sum() + dwell.sum())
    info = information(p, waypoints, durations, dwell, pretension).scaled(1.0 / duration)
    lf, lv = _logdet(info.friction), _logdet(info.variable)
    nc = p.model.n_cables
    # Schur complement: det Cov(k_j, λ_j)⁻¹ = det F_j / F_j(c_a, c_a) for each cable's 3×3 block
    c_a = np.diag(info.variable)[2 * nc:]
    ds = lf + sum(_logdet(info.variable[np.ix_([j, nc + j, 2 * nc + j], [j, nc + j, 2 * nc + j])])
                  - (math.log(c_a[j]) if c_a[j] > 0 else -1e3) for j in range(nc))
    names = [f"{s}({j + 1})" for s in ("f_s",) for j in range(nc)]
    names += [f"{s}({j + 1})" for s in ("k", "lambda", "c_a") for j in range(nc)]
    return Score(lf + lv, lf, lv, _cond(info.friction), _cond(info.variable), info.penalty, duration,
                 dict(zip(names, np.concatenate([_rel_sigma(info.friction), _rel_sigma(info.variable)]))), ds)


class Excitation(NamedTuple):
    """A designed excitation: the trajectory (SI) and its score."""

    waypoints_rad: FloatArray
    durations_s: FloatArray
    dwell_s: FloatArray
    score: Score
    iterations: int
    seed: int
    pretension_N: FloatArray  # (K,) N, zeros when the design has no pretension


PENALTY_WEIGHT = 1e4  # on the force penalty (per second, normalised); the log-dets move by units
OVERRUN_WEIGHT = 10.0  # per s² of moves that do not fit the duration


def _objective(p: DesignProblem, k: int) -> Callable[[FloatArray], float]:
    n = p.n_joints

    def f(u: FloatArray) -> float:
        w, P = _waypoints(p, u, k, n)
        durations, dwell, overrun = _timing(p, w, P)
        s = score(p, w, durations, dwell, P)
        # Keep memory bounded (~1.3 kB an entry). With holds="none" every evaluation stretches all the
        # moves anew, so the cache mostly serves the holds and the line search's repeated points.
        if len(p._cache) > 20_000:
            p._cache.clear()
        return -(s.log_det_ds if p.criterion == "ds" else s.log_det) + PENALTY_WEIGHT * s.penalty + OVERRUN_WEIGHT * overrun**2

    return f


def _n_vars(p: DesignProblem, k: int) -> int:
    """Design variables: each inner waypoint's joints, and its pretension when the problem has one."""
    return (k - 2) * (p.n_joints + (1 if p.pretension_max_N > 0.0 else 0))


def _waypoints(p: DesignProblem, u: FloatArray, k: int, n: int) -> tuple[FloatArray, FloatArray | None]:
    """The waypoints (K, N) rad and pretensions (K,) N (None without) of the design variables
    ``u``: joints as fractions of alpha_max in [−1, 1], pretensions as fractions of the bound in
    [0, 1]; the first and last waypoint straight, at rest and at 0 N."""
    v = np.round(np.asarray(u, dtype=float), 12)  # so that the cache sees a move again when the optimiser comes back
    w = np.zeros((k, n))
    w[1:-1] = v[:(k - 2) * n].reshape(k - 2, n) * p.alpha_max
    if p.pretension_max_N <= 0.0:
        return w, None
    P = np.zeros(k)
    P[1:-1] = np.round(v[(k - 2) * n:] * p.pretension_max_N, 9)
    return w, P


def _iterations_told(progress: Callable[[str], None], what: str, maxiter: int) -> Callable[..., None]:
    """An L-BFGS-B callback telling ``progress`` each iteration and the criterion there."""
    done = [0]

    # scipy passes the iterate as an OptimizeResult to a callback whose one parameter has this name
    def tell(intermediate_result: optimize.OptimizeResult) -> None:
        done[0] += 1
        progress(f"{what}: iteration {done[0]} of at most {maxiter}, criterion {float(intermediate_result.fun):.4g}")

    return tell


def design(p: DesignProblem, *, n_waypoints: int | None = None, seed: int = 0, starts: int = 2,
           maxiter: int = 40, margin: float = 0.95, start: FloatArray | None = None,
           progress: Callable[[str], None] | None = None) -> Excitation:
    """The D-optimal excitation of ``p`` (module docstring).

    ``n_waypoints`` K (default: one every 4 s, as the §5.2.2 trajectory's 25 in 97 s); the inner
    waypoints move within ±``margin``·alpha_max. ``start`` (K, N) rad, e.g. the §5.2.2 cycloids'
    waypoints: a first starting design, so the result is at least as good on the criterion; then
    ``starts`` random starting designs (seeded by ``seed``); each is improved by L-BFGS-B for at
    most ``maxiter`` iterations (``progress``, if given, is told each start and iteration in one
    line: a design at the defaults takes minutes); the best one that the
    caller's ``check`` accepts, with every nominal force under FORCE_MARGIN·f_max, is returned (a
    rejected one is shrunk towards the straight pose by 5 % steps until it passes). Raises :class:`DesignError` when none passes."""
    k = n_waypoints if n_waypoints is not None else max(int(round(p.duration_s / 4.0)) + 1, 3)
    if k < 3:
        raise DesignError(f"a design needs at least 3 waypoints (straight, one pose, straight), got {k}")
    n = p.n_joints
    rng = np.random.default_rng(seed)
    n_pre = _n_vars(p, k) - (k - 2) * n
    bounds = [(-margin, margin)] * ((k - 2) * n) + [(0.0, 1.0)] * n_pre
    best: tuple[float, FloatArray, int] | None = None
    initial = []
    if start is not None:
        w0 = np.asarray(start, dtype=float)
        if w0.shape != (k, n):
            raise DesignError(f"the starting design has shape {w0.shape}, the design {k} waypoints of {n} joints")
        initial.append(np.concatenate([np.clip(w0[1:-1] / p.alpha_max, -margin, margin).ravel(), np.zeros(n_pre)]))
    for _ in range(max(starts, 1)):
        initial.append(np.concatenate([rng.uniform(-margin, margin, size=(k - 2) * n), rng.uniform(0.0, 1.0, size=n_pre)]))
    for i, u0 in enumerate(initial):
        what = f"start {i + 1} of {len(initial)}" + (" (the given design)" if start is not None and i == 0 else "")

        if progress is not None:
            progress(f"{what}: optimising ({maxiter} iterations at most)")
        res = optimize.minimize(_objective(p, k), u0, method="L-BFGS-B", bounds=bounds,
                                options={"maxiter": maxiter, "eps": 1e-4},
                                callback=None if progress is None else _iterations_told(progress, what, maxiter))
        if best is None or res.fun < best[0]:
            best = (float(res.fun), np.asarray(res.x), int(res.nit))
    assert best is not None
    _, u, nit = best
    reason = ""
    for _ in range(40):
        w, P = _waypoints(p, u, k, n)
        durations, dwell, overrun = _timing(p, w, P)
        s = score(p, w, durations, dwell, P)
        pretension = np.zeros(k) if P is None else P
        try:
            if overrun > 1e-9:
                raise ValueError(f"the moves need {overrun:.2f} s more than the duration")
            if s.penalty > 0.0:
                raise ValueError(f"nominal forces above {FORCE_MARGIN:g}·f_max or not distributable")
            if p.check is not None:
                p.check(w, durations, dwell, pretension)
        except ValueError as exc:
            reason = str(exc)
            u = 0.95 * u  # towards the straight pose and a lower pretension
            continue
        return Excitation(w, durations, dwell, s, nit, seed, pretension)
    raise DesignError(f"no design passed the trajectory validation; last reason: {reason}")
