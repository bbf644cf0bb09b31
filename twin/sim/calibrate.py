"""Calibrating a truth on recorded campaigns (issue 16): ``xneck twin calibrate``.

A truth's unknown values (friction shape and stiction level, current-loop bandwidth, torque-
constant errors, cable damping and creep, the command delay) are fitted to one or more recorded
campaigns. Each recording is *replayed*: the twin, started where the recording starts, is held
tick by tick at the forces the bridge applied (``MotorState.force_applied_N``, over the recorded
periods), in process and open loop. The fit minimises, with bounded
``scipy.optimize.least_squares``, the weighted mismatch of

- the motor angles θ (encoders, every ``every``-th tick), which carry the cables' stretch and so
  the forces;
- α_IP (the camera), against the replayed α at each frame's capture time;
- the cable tensions, only when asked (``use_twin_truth``, ``--use-twin-truth``) and the recording
  has them (the twin's ``Truth`` topic: twin recordings only; the prototype has no tension sensor).

By default the calibration reads what the prototype records too: the motor states and the camera.
The twin's ``Truth`` topic (true tensions, the true α at the start) is ignored unless asked for, so
a calibration on a twin recording is the one a prototype recording would get, and never sees the
answer (audit of 2026-12-01). With ``use_twin_truth`` it also fits the true tensions and starts the
replay at the true α: a diagnosis of the twin, not a calibration a prototype can have.

Start: the replays' mismatch has local minima (stiction makes the motion depend on the forces in
steps), so the local fit starts from the best of the base truth's values and ``starts`` points of a
scrambled Sobol sequence over the fitted values' bounds (log scale where the value is fitted on
one), each one cost evaluation. From the base alone (``--starts 0``), the short law 2 recording
of values injected into the robot truth in tests/test_calibrate.py ended in a local minimum far
from them (session 46, once the law's α̂̇ bound had made its commands smoother).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import re
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from scipy.optimize import least_squares

from bridge import toml_text
from twin.model.estimation import alpha_hat_3
from twin.model.params import Params
from twin.sim.simulator import Twin, TwinConfig
from twin.sim.truth import EFFECTS, Calibration, RobotTruth, TruthError, load_truth, robot_base

MOTOR_TOPIC = "/xneck/motor/state"
CAMERA_TOPIC = "/xneck/camera/alpha_ip"
TRUTH_TOPIC = "/xneck/twin/truth"
MIN_TICKS = 50  # a recording shorter than this (0.1 s at 500 Hz) says nothing about dynamics
MAX_GAP_S = 0.5  # a longer gap between motor states: not one continuous run
# In a fitted value's source when the fit stopped at --max-evaluations: a reader of the truth file
# must not take such values for a converged measurement.
NOT_CONVERGED = "not converged: stopped at the evaluation limit"


class CalibrationError(ValueError):
    """A recording or a request the calibration cannot use; the message says which and why."""


@dataclass(frozen=True)
class Unknown:
    """One fitted value: ``section.key`` (``index`` for per-motor/per-cable values), its bounds,
    and whether it is fitted on a log scale (values spanning decades)."""

    section: str
    key: str
    index: int | None
    low: float
    high: float
    log: bool = False

    @property
    def name(self) -> str:
        return f"{self.section}.{self.key}" + (f"[{self.index}]" if self.index is not None else "")


# The values a calibration may fit: (low, high, log scale, per motor/cable). Bounds are physical
# ranges, wide enough to hold any plausible prototype (truth.py gives the meaning of each).
FITTABLE: dict[str, tuple[float, float, bool, bool]] = {
    "friction.static_ratio": (1.0, 3.0, False, False),
    "friction.stribeck_velocity_rad_s": (0.05, 50.0, True, False),
    "friction.viscous_N_s_rad": (0.0, 0.2, False, False),
    "friction.asymmetry": (-0.5, 0.5, False, True),
    "friction.gear_loss_forward": (0.0, 0.5, False, False),
    "friction.gear_loss_backward": (0.0, 0.5, False, False),
    "friction.pulley_friction_per_N": (0.0, 0.5, False, True),
    "actuation.current_bandwidth_hz": (1.0, 5000.0, True, False),
    "actuation.torque_constant_factor": (0.7, 1.3, False, True),
    "cables.damping_N_s_m": (1.0, 5000.0, True, False),
    "cables.creep_ratio": (0.0, 0.3, False, False),
    "cables.creep_time_s": (0.1, 30.0, True, False),
}
DEFAULT_FIT = ("friction.static_ratio", "friction.viscous_N_s_rad", "actuation.current_bandwidth_hz",
               "actuation.torque_constant_factor", "cables.damping_N_s_m")
_NAME = re.compile(r"^([a-z]+)\.([a-z_A-Z]+)(?:\[(\d+)\])?$")


def unknowns(names: Sequence[str], n_cables: int) -> list[Unknown]:
    """The fitted values for names like ``friction.static_ratio`` or
    ``actuation.torque_constant_factor[2]`` (a per-motor name without index: every motor)."""
    out: list[Unknown] = []
    for raw in names:
        m = _NAME.match(raw.strip())
        base = f"{m.group(1)}.{m.group(2)}" if m else raw
        if m is None or base not in FITTABLE:
            raise CalibrationError(f"cannot fit {raw!r}: choose from {', '.join(FITTABLE)} "
                                   "(per-motor values also as name[i])")
        low, high, log, per = FITTABLE[base]
        if m.group(3) is not None and not per:
            raise CalibrationError(f"{base} is one value, not one per motor: drop [{m.group(3)}]")
        if m.group(3) is not None and int(m.group(3)) >= n_cables:
            raise CalibrationError(f"{raw}: index {m.group(3)} out of range (motors 0-{n_cables - 1})")
        indices = [int(m.group(3))] if m.group(3) is not None else (range(n_cables) if per else [None])
        out += [Unknown(m.group(1), m.group(2), i, low, high, log) for i in indices]
    seen = [u.name for u in out]
    if len(set(seen)) != len(seen):
        raise CalibrationError(f"a value is named twice in {', '.join(names)}")
    return out


def current_value(truth: RobotTruth, u: Unknown, n_cables: int) -> float:
    """``u``'s value in ``truth`` (a per-motor value not given in the file: its neutral default)."""
    value = getattr(getattr(truth, u.section), u.key)
    if u.index is None:
        return float(value)
    if not value:
        return 1.0 if u.key == "torque_constant_factor" else 0.0
    if len(value) != n_cables:
        raise CalibrationError(f"{u.section}.{u.key}: the base truth has {len(value)} values for {n_cables} motors")
    return float(value[u.index])


def with_values(truth: RobotTruth, fitted: Sequence[Unknown], values: Sequence[float] | np.ndarray, n_cables: int) -> RobotTruth:
    """``truth`` with ``values`` for ``fitted``; the section of every fitted value is switched on."""
    changes: dict[str, dict[str, Any]] = {}
    for u, v in zip(fitted, values, strict=True):
        section = changes.setdefault(u.section, {"enabled": True})
        if u.index is None:
            section[u.key] = float(v)
        else:
            current = section.get(u.key) or [current_value(truth, dataclasses.replace(u, index=i), n_cables)
                                             for i in range(n_cables)]
            current = list(current)
            current[u.index] = float(v)
            section[u.key] = tuple(current)
    for section, values_ in changes.items():
        truth = truth.replace(section, **values_)
    return truth


# -- recordings --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recording:
    """A recorded campaign as the replay needs it. Times in s on the bridge's clock (simulated
    time for the twin), θ in rad at the motor shafts, forces and tensions in N, α in rad."""

    name: str
    t_s: np.ndarray  # (T,) motor-state stamps, strictly increasing
    theta: np.ndarray  # (T, n_cables) encoder angles
    force: np.ndarray  # (T, n_cables) force applied during the period that ends at t_s[k]
    t_ip: np.ndarray  # (K,) camera capture times
    alpha_ip: np.ndarray  # (K, N)
    tension: np.ndarray | None  # (T, n_cables), the twin's Truth if asked for (use_twin_truth); else None
    alpha0: np.ndarray  # (N,) where the replay starts: α̂ (eq. 33) of θ[0]; the Truth's α if asked for
    info: dict[str, str] = field(default_factory=dict)  # the campaign's metadata (law, kind, ...)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])


def load_recording(path: str | Path, params: Params, span_s: float | None = None,
                   use_twin_truth: bool = False) -> Recording:
    """A campaign MCAP as a :class:`Recording` (the first ``span_s`` seconds of it), or
    :class:`CalibrationError` naming what is wrong with the file.

    The twin's ``Truth`` topic (true tensions, the true starting α) is read only with
    ``use_twin_truth`` (a diagnosis on twin recordings; a prototype's recording has no such topic):
    by default a twin recording is read as a prototype's would be (module docstring)."""
    from bridge.archive import ArchiveError  # the lower layer; imported when used
    from bridge.archive_read import read_campaign

    path = Path(path)
    try:
        camp = read_campaign(path, keys=(MOTOR_TOPIC, CAMERA_TOPIC, TRUTH_TOPIC) if use_twin_truth
                             else (MOTOR_TOPIC, CAMERA_TOPIC))
    except ArchiveError as exc:
        raise CalibrationError(f"cannot read the recording: {exc}") from None
    motor = [m for _, m in camp.messages(MOTOR_TOPIC)]
    if not motor:
        have = ", ".join(sorted(camp.counts)) or "none"
        raise CalibrationError(f"{path}: no motor states ({MOTOR_TOPIC}) to replay (channels present: {have})")
    nc, n = params.n_cables, params.n_joints
    try:
        t = np.array([m.stamp_s for m in motor], dtype=float)
        theta = np.array([m.theta_rad for m in motor], dtype=float)
        force = np.array([m.force_applied_N for m in motor], dtype=float)
    except (AttributeError, ValueError) as exc:
        raise CalibrationError(f"{path}: malformed motor states ({exc})") from None
    if theta.shape != (len(t), nc) or force.shape != (len(t), nc):
        raise CalibrationError(f"{path}: motor states do not carry {nc} motors (the parameter set's cables)")
    # A lockstep twin re-publishes its state while it waits for a command: one sample per stamp.
    t, first = np.unique(t, return_index=True)
    theta, force = theta[first], force[first]
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(theta)) and np.all(np.isfinite(force))):
        raise CalibrationError(f"{path}: non-finite motor angles, forces or stamps")
    if span_s is not None:
        keep = t <= t[0] + span_s
        t, theta, force = t[keep], theta[keep], force[keep]
    if len(t) < MIN_TICKS:
        raise CalibrationError(f"{path}: {len(t)} motor states, too short to calibrate on (at least {MIN_TICKS})")
    gaps = np.diff(t)
    if gaps.max() > MAX_GAP_S:
        k = int(np.argmax(gaps))
        raise CalibrationError(f"{path}: the motor states stop for {gaps[k]:.2f} s at t = {t[k]:.3f} s: "
                               "not one continuous run (cut it with --span)")
    frames = [m for _, m in camp.messages(CAMERA_TOPIC)]
    t_ip = np.array([m.capture_stamp_s for m in frames], dtype=float)
    alpha_ip = np.array([[np.nan if a is None else a for a in m.alpha_ip_rad] for m in frames],
                        dtype=float).reshape(len(frames), -1)
    if len(frames) and alpha_ip.shape[1] != n:
        raise CalibrationError(f"{path}: camera frames carry {alpha_ip.shape[1]} joints, the parameter set {n}")
    inside = (t_ip >= t[0]) & (t_ip <= t[-1]) & np.isfinite(alpha_ip).all(axis=1) if len(frames) else np.zeros(0, bool)
    t_ip, alpha_ip = t_ip[inside], alpha_ip[inside].reshape(-1, n)
    truth = {m.stamp_s: m for _, m in camp.messages(TRUTH_TOPIC)} if use_twin_truth else {}
    tension = None
    if sum(s in truth for s in t) >= 0.9 * len(t):  # the twin's Truth (a lockstep twin's first state has none)
        tension = np.array([truth[s].tension_N if s in truth else [np.nan] * nc for s in t], dtype=float)
    if t[0] in truth:
        alpha0 = np.array(truth[t[0]].alpha_rad, dtype=float)
    else:
        from twin.model.numeric import build

        alpha0 = alpha_hat_3(build(params), theta[0])
    return Recording(path.name, t, theta, force, t_ip, alpha_ip, tension, alpha0, dict(camp.info))


# -- replay ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Replayed:
    theta: np.ndarray  # (T, n_cables), θ as the encoders would read it (backlash on slack cables; not quantised)
    alpha: np.ndarray  # (T, N)
    tension: np.ndarray  # (T, n_cables)
    settling: np.ndarray  # (T,) bool: within settle_s of a re-start from the encoders (not compared)
    ok: bool  # False if the replay left the model's domain (flat joint, non-finite state)


@dataclass(frozen=True)
class Weights:
    """How replay and recording are compared: the residuals' scales (one standard deviation
    each: motor angle, camera, tension), which ticks, and the prediction horizon."""

    theta_rad: float = 0.05  # about 0.04 mm of cable (r_d/R = 0.8 mm/rad)
    alpha_ip_rad: float = math.radians(1.0)  # the camera's noise (§4.2)
    tension_N: float = 1.0
    every: int = 10  # compare θ and the tension every this many ticks (50 Hz at 500 Hz)
    skip_s: float = 0.2  # leave out the replay's start-up transient
    horizon_s: float = 0.25  # re-start the motors from the encoders this often (see replay)
    settle_s: float = 0.02  # after a re-start, the bars settle onto the cables: not compared


def replay(rec: Recording, params: Params, truth: RobotTruth, w: Weights = Weights()) -> Replayed:
    """The twin of ``truth`` held at the recording's applied forces over its periods (open loop,
    no camera, no jitter: the recorded stamps are the periods).

    Why it re-starts: with stiction the forces do not determine the motion; a motor that sticks
    a little earlier in the replay than on the robot keeps a different angle, and over seconds
    replay and recording part for good (the mismatch then jumps with tiny changes of a value, and
    no fit converges). So every ``w.horizon_s`` the motors are put where the encoders say (θ, and θ̇
    by a central difference); the bars, the current loops, creep and delayed commands carry on
    from the replay, and the bars settle onto the re-started cables within ``w.settle_s`` (light
    bars, stiff cables). What is compared is then a prediction over one horizon, as a model-based
    controller uses the model (``horizon_s`` = inf: one open-loop replay)."""
    truth = truth.replace("timing", jitter_s=0.0)
    twin = Twin(robot_base(truth, params), TwinConfig(camera=False, truth=truth))
    n, nc = twin.model.n_joints, twin.model.n_cables
    half_count = math.pi / params.sensors.encoder_counts_per_rev  # encoders truncate: θ ≈ reading + q/2
    twin.reset(alpha=np.clip(rec.alpha0, -2.5, 2.5), theta=rec.theta[0] + half_count)
    T = len(rec.t_s)
    theta, alpha, tension = np.empty((T, nc)), np.empty((T, n)), np.empty((T, nc))
    settling = np.zeros(T, dtype=bool)
    state = twin.state
    theta[0], alpha[0], tension[0] = state[n : n + nc], state[:n], twin.tension_N
    dt_nominal = twin.dt
    ok = True
    restart = (math.isfinite(w.horizon_s) and w.horizon_s > 0)
    next_restart = rec.t_s[0] + w.horizon_s if restart else math.inf
    settle_until = rec.t_s[0] + w.settle_s
    # Gear backlash shows in the encoders on slack cables only (twin.sim.simulator.Twin.tick): the replay
    # reads its motors as the encoders would, and re-starts a motor on a slack cable through its backlash.
    backlash = truth.actuation.backlash_rad if truth.actuation.enabled else 0.0
    cable_bits = np.arange(nc)
    slack = np.zeros(nc)
    for k in range(1, T):
        t = rec.t_s[k - 1]
        if t >= next_restart and k + 1 < T:
            state[n : n + nc] = rec.theta[k - 1] + half_count + backlash * slack
            state[2 * n + nc :] = (rec.theta[k] - rec.theta[k - 2]) / (rec.t_s[k] - rec.t_s[k - 2])
            next_restart += w.horizon_s
            settle_until = t + w.settle_s
        gap = rec.t_s[k] - t
        steps = max(1, int(round(gap / dt_nominal)))  # missed ticks on the robot: hold the force over them
        bits = 0
        for _ in range(steps):
            bits = twin.advance(rec.force[k], gap / steps)
            if bits >> 62 & 1:
                ok = False
        if backlash:
            slack = (bits >> cable_bits) & 1 if not bits >> 62 & 1 else slack * 0
        theta[k], alpha[k], tension[k] = state[n : n + nc] - backlash * slack, state[:n], twin.tension_N
        settling[k] = rec.t_s[k] <= settle_until
    if not (ok and np.all(np.isfinite(theta)) and np.all(np.isfinite(alpha))):
        ok = False
    return Replayed(theta, alpha, tension, settling, ok)


def _parts(rec: Recording, out: Replayed, params: Params, w: Weights) -> dict[str, np.ndarray]:
    """Unweighted residuals (replay − recording), in physical units, by kind."""
    use = (rec.t_s >= rec.t_s[0] + w.skip_s) & ~out.settling
    rows = np.nonzero(use)[0][:: w.every]
    half_count = math.pi / params.sensors.encoder_counts_per_rev
    parts = {"theta_rad": (out.theta[rows] - half_count - rec.theta[rows]).ravel()}
    tick_of_frame = np.clip(np.searchsorted(rec.t_s, rec.t_ip), 0, len(rec.t_s) - 1)
    frames = use[tick_of_frame]
    if frames.any():
        sim = np.column_stack([np.interp(rec.t_ip[frames], rec.t_s, out.alpha[:, i]) for i in range(out.alpha.shape[1])])
        parts["alpha_ip_deg"] = np.degrees(sim - rec.alpha_ip[frames]).ravel()
    if rec.tension is not None:
        r = out.tension[rows] - rec.tension[rows]
        parts["tension_N"] = r[np.isfinite(r)]
    return parts


def _scale(kind: str, w: Weights) -> float:
    return {"theta_rad": w.theta_rad, "alpha_ip_deg": math.degrees(w.alpha_ip_rad), "tension_N": w.tension_N}[kind]


def prediction_errors(rec: Recording, params: Params, truth: RobotTruth, w: Weights = Weights()) -> dict[str, float]:
    """RMS of replay − recording by kind (θ in rad, α_IP in deg, tension in N): how well ``truth``
    predicts ``rec`` over one horizon (:func:`replay`)."""
    out = replay(rec, params, truth, w)
    if not out.ok:
        return {"replay_failed": 1.0}
    return {k: float(np.sqrt(np.mean(v**2))) for k, v in _parts(rec, out, params, w).items()}


# -- the fit -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Result:
    truth: RobotTruth  # the base truth with the fitted values (and provenance)
    fitted: list[Unknown]
    values: np.ndarray
    sigma: np.ndarray
    residual_rms: dict[str, float]  # over every recording, by kind
    per_recording: dict[str, dict[str, float]]
    evaluations: int  # replays of every recording, the Jacobian's included
    cost: float
    converged: bool = True  # False: the fit stopped at max_evaluations, not at its tolerances


def _to_z(u: Unknown, v: float) -> float:
    return math.log(v) if u.log else v


def _from_z(u: Unknown, z: float) -> float:
    return math.exp(z) if u.log else z


def fit(recordings: Sequence[Recording], params: Params, base: RobotTruth, fitted: Sequence[Unknown],
        w: Weights = Weights(), progress: Callable[[str], None] | None = None, max_evaluations: int = 200,
        command: str = "", base_name: str = "", starts: int = 16) -> Result:
    """Fit ``fitted`` (from the best of ``base``'s values and ``starts`` screened points, module
    docstring, "Start"; 0: from ``base``'s alone) to ``recordings`` (module docstring).

    ``max_evaluations`` bounds the cost evaluations (scipy's ``max_nfev``), not the replays: each
    Jacobian, estimated by finite differences, costs one replay more per fitted value. A fit cut
    off by it is returned with ``converged`` False and says so in the sources it writes."""
    if max_evaluations < 1:
        raise CalibrationError(f"the evaluation limit must be at least 1, got {max_evaluations}")
    if not recordings:
        raise CalibrationError("no recording to calibrate on")
    if not fitted:
        raise CalibrationError("nothing to fit")
    if starts < 0:
        raise CalibrationError(f"the number of screened starts must be at least 0, got {starts}")
    nc = params.n_cables
    lo = np.array([_to_z(u, u.low) if not (u.log and u.low <= 0) else -50.0 for u in fitted])
    hi = np.array([_to_z(u, u.high) for u in fitted])
    margin = 1e-6 * (hi - lo)
    z0 = np.clip([_to_z(u, min(max(current_value(base, u, nc), u.low), u.high)) for u in fitted], lo + margin, hi - margin)
    evaluations = 0
    worst = 1e3  # residual (in σ) of a replay that failed: large, finite, so least_squares backs off

    def residuals(z: np.ndarray) -> np.ndarray:
        nonlocal evaluations
        evaluations += 1
        truth = with_values(base, fitted, [_from_z(u, zi) for u, zi in zip(fitted, z, strict=True)], nc)
        chunks = []
        for rec in recordings:
            out = replay(rec, params, truth, w)
            parts = _parts(rec, out, params, w)
            for kind, r in parts.items():
                chunks.append(r / _scale(kind, w) if out.ok else np.full(r.shape, worst))
        r = np.concatenate(chunks)
        if progress:
            shown = ", ".join(f"{u.name}={_from_z(u, zi):.4g}" for u, zi in zip(fitted, z, strict=True))
            progress(f"evaluation {evaluations}: cost {0.5 * float(r @ r):.6g}  ({shown})")
        return r

    z0 = _screened_start(residuals, z0, lo + margin, hi - margin, starts, progress)
    sol = least_squares(residuals, z0, bounds=(lo, hi), x_scale="jac", diff_step=1e-3, max_nfev=max_evaluations,
                        xtol=1e-6, ftol=1e-8)
    converged = sol.status != 0  # 0: max_nfev reached before any tolerance was met
    values = np.array([_from_z(u, zi) for u, zi in zip(fitted, sol.x, strict=True)])
    m, n = len(sol.fun), len(fitted)
    s2 = 2.0 * float(sol.cost) / max(m - n, 1)
    cov_z = s2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    sigma_z = np.sqrt(np.clip(np.diag(cov_z), 0.0, None))
    sigma = np.array([v * s if u.log else s for u, v, s in zip(fitted, values, sigma_z, strict=True)])
    truth = with_values(base, fitted, values, nc)
    per = {rec.name: prediction_errors(rec, params, truth, w) for rec in recordings}
    total: dict[str, float] = {}
    for kind in ("theta_rad", "alpha_ip_deg", "tension_N"):
        sq = [(v[kind], len(rec.t_s)) for rec, v in zip(recordings, per.values(), strict=True) if kind in v]
        if sq:
            total[kind] = math.sqrt(sum(e * e * c for e, c in sq) / sum(c for _, c in sq))
    when = dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    names = [rec.name for rec in recordings]
    sources = dict(truth.sources)
    for u in fitted:
        key = f"{u.section}.{u.key}"
        fitted_here = [f"[{x.index}] = {vv:.4g} ± {ss:.2g}" if x.index is not None else f"{vv:.4g} ± {ss:.2g}"
                       for x, vv, ss in zip(fitted, values, sigma, strict=True) if f"{x.section}.{x.key}" == key]
        sources[key] = (f"measurement: fitted by xneck twin calibrate to {', '.join(names)} on {when[:10]} "
                        f"({'; '.join(fitted_here)}, 1 σ)"
                        + ("" if converged else f"; {NOT_CONVERGED} ({evaluations} replays)"))
    provenance = Calibration(
        command=command, date=when, campaigns=names, base=base_name or base.name,
        fitted={u.name: float(v) for u, v in zip(fitted, values, strict=True)},
        sigma={u.name: float(s) for u, s in zip(fitted, sigma, strict=True)},
        residual_rms=total, evaluations=evaluations)
    truth = msgspec.structs.replace(truth, sources=sources, calibration=provenance)
    return Result(truth, list(fitted), values, sigma, total, per, evaluations, float(sol.cost), converged)


def _screened_start(residuals: Callable[[np.ndarray], np.ndarray], z0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    starts: int, progress: Callable[[str], None] | None) -> np.ndarray:
    """The point of least cost among ``z0`` and ``starts`` points of a scrambled Sobol sequence
    (seed 0: the same points every run) in the box [lo, hi] of the fit's variables."""
    if starts == 0:
        return z0
    from scipy.stats import qmc

    with warnings.catch_warnings():  # a count not a power of 2 loses Sobol's balance, not its use here
        warnings.simplefilter("ignore", UserWarning)
        sobol = qmc.Sobol(len(z0), rng=np.random.default_rng(0)).random(starts)
    candidates = [np.asarray(z0, dtype=float), *qmc.scale(sobol, lo, hi)]
    costs = [float(np.sum(residuals(c) ** 2)) for c in candidates]
    best = int(np.argmin(costs))
    if progress:
        progress(f"start: {'the base values' if best == 0 else f'screened point {best} of {starts}'} "
                 f"(cost {0.5 * costs[best]:.6g}; the base values' {0.5 * costs[0]:.6g})")
    return candidates[best]


def with_validation(truth: RobotTruth, validation: dict[str, dict[str, float]]) -> RobotTruth:
    """``truth`` with the held-out recordings' prediction errors in its provenance."""
    if truth.calibration is None:
        raise CalibrationError("only a calibrated truth records validations")
    return msgspec.structs.replace(truth, calibration=msgspec.structs.replace(truth.calibration, validation=validation))


# -- the file ----------------------------------------------------------------------------------


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def truth_toml(truth: RobotTruth, header: str = "") -> str:
    """``truth`` as a truth file (the format of twin/sim/robot_truth.toml) that ``--truth FILE``
    loads back to the same values; every value that differs from its default is written with its
    source, and ``[calibration]`` holds the provenance."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    lines.append(f"name = {_toml_value(truth.name)}")
    if truth.robot_params:  # the robot the values were fitted on (twin/sim/truth.py)
        lines.append(f"robot_params = {_toml_value(truth.robot_params)}")
    for section in EFFECTS:
        effect = getattr(truth, section)
        default = type(effect)()
        lines += ["", f"[{section}]", f"enabled = {_toml_value(effect.enabled)}"]
        for key in effect.__struct_fields__:
            if key == "enabled":
                continue
            value = getattr(effect, key)
            source = truth.sources.get(f"{section}.{key}")
            if source is None and value == getattr(default, key):
                continue
            source = source or "none: carried over from the base truth, which gave no source"
            lines.append(f"{key} = {{ value = {_toml_value(value)}, source = {_toml_value(source)} }}")
    if truth.calibration is not None:
        lines += ["", "[calibration]"]
        for key, value in msgspec.structs.asdict(truth.calibration).items():
            lines.append(f"{key} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def check_loadable(text: str, path: Path) -> RobotTruth:
    """Write ``text`` to ``path`` only if it loads back as a truth (never leave a file that
    ``--truth`` would refuse); returns what it loads to. Atomic: a write that fails (raising the
    OSError) leaves the previous file (``--force``) or none, never a half-written truth."""
    import tomllib

    from bridge.archive import atomic_write
    from twin.sim.truth import parse_truth

    try:
        parse_truth(toml_text.loads(text), path.stem)
    except (tomllib.TOMLDecodeError, TruthError) as exc:
        raise CalibrationError(f"the calibrated truth does not load back ({exc}); not written") from None
    atomic_write(path, text.encode("utf-8"))
    return load_truth(str(path))
