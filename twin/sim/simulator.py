"""The twin's simulator: the full model stepped at the control rate, with the prototype's sensors.

``Twin.tick(f)`` holds the motor forces f (N) for one control period (2 ms at 500 Hz), integrates
the full model (``twin.sim.integrator``) and returns what the bridge would report (quantised encoder
angles) plus the camera frames due now and the twin-only truth. Pure Python shell around the
compiled step; deterministic for a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np

from twin.model import cables
from twin.model.compiled import bind
from twin.model.numeric import RIGID, Model, build
from twin.model.params import Params, load_params
from twin.sim import integrator
from twin.sim.integrator import ACT_DECAY, ACT_MEAN_GAIN, NEAR_FLAT, RF_COLUMNS, actuate
from twin.sim.sensors import ALPHA_IP_KINDS, make_camera
from twin.sim.truth import RobotTruth, TruthError, load_truth, truth_params


@dataclass(frozen=True)
class TwinConfig:
    """What the twin simulates. Defaults: the paper's identified robot (Table 1 friction, Table 2
    variable-stiffness cables), 500 Hz, two integration substeps per tick. ``truth``: "model"
    integrates the parameter file as it is, "robot" the shipped robot truth (every unmodelled
    effect on), a path a truth file, or a :class:`twin.sim.truth.RobotTruth` (``twin.sim.truth``).
    ``alpha_ip``: the camera's α_IP, the true α plus white noise ("noise") or measured on frames
    rendered from the truth ("camera", ``twin.sim.sensors.make_camera``); ``camera=False``: none."""

    cable_model: Literal["rigid", "linear", "variable"] | None = None  # None: the parameter file's
    friction: bool = True
    rate_hz: float = 500.0
    substeps: int = 2
    seed: int = 0
    camera: bool = True
    truth: str | RobotTruth = "model"
    alpha_ip: Literal["noise", "camera"] = "noise"

    def __post_init__(self) -> None:
        if self.alpha_ip not in ALPHA_IP_KINDS:
            raise ValueError(f"alpha_ip must be one of {', '.join(ALPHA_IP_KINDS)}, got {self.alpha_ip!r}")
        try:
            load_truth(self.truth)
        except TruthError as exc:
            raise ValueError(str(exc)) from None
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"rate_hz must be a positive number, got {self.rate_hz}")
        if self.substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {self.substeps}")


class Tick(NamedTuple):
    """One control period's output. Times in s (simulated), angles in rad, forces in N. (A
    NamedTuple, not a frozen dataclass: as immutable, and built in a fraction of the time.)"""

    seq: int
    t_s: float
    theta_meas: np.ndarray  # encoder angles (quantised), as the bridge reports them
    frames: list[tuple[float, np.ndarray]]  # camera frames delivered now: (capture time, α_IP)
    alpha: np.ndarray  # truth from here on (twin-only)
    alpha_dot: np.ndarray
    theta: np.ndarray
    theta_dot: np.ndarray
    tension: np.ndarray
    elongation: np.ndarray
    slack: np.ndarray  # bool per cable
    near_singular: bool
    flat: bool  # a joint reached its flat configuration: the step was refused
    frame_confidence: tuple[np.ndarray, ...] = ()  # per frame, per joint in [0, 1]; empty: not graded


class Twin:
    """The simulated robot. State (α, θ, α̇, θ̇) starts straight and at rest with slack-free,
    unstretched cables (θ = 0 at α = 0, eq. 20). ``params`` is the model; ``self.params`` is what
    is integrated (the model plus the truth's structural errors and cable damping), and
    ``self.truth`` the effects applied around the integrator (``twin.sim.truth``)."""

    def __init__(self, params: Params | None = None, config: TwinConfig = TwinConfig()):
        self.truth: RobotTruth = load_truth(config.truth)
        model_params = params or load_params()
        self.params = truth_params(model_params, self.truth)
        self.config = config
        fr = self.truth.friction
        self.model: Model = build(self.params, config.cable_model, friction=config.friction and not fr.enabled)
        n, nc = self.model.n_joints, self.model.n_cables
        if fr.enabled and config.friction and self.model.cable_model == RIGID:
            raise ValueError("the robot truth's friction needs elastic cables (linear or variable), not rigid ones")
        self._rf = np.zeros((0, RF_COLUMNS))
        if fr.enabled and config.friction:
            self._rf = _friction_table(self.params, self.truth)
        self.dt = 1.0 / config.rate_hz
        self._n, self._nc = n, nc
        self._state = np.zeros(2 * (n + nc))
        self._tension = np.zeros(nc)
        self._stretch = np.zeros(nc)
        self._creep = np.zeros(nc)  # m, stretch of the creep element (cables effect)
        self._current = np.zeros(nc)  # A, the current loops' state (actuation effect)
        self._pending: list[np.ndarray] = []  # commands not yet applied (timing effect)
        a = self.truth.actuation
        self._kt_factor = np.asarray(a.torque_constant_factor or (1.0,) * nc, dtype=float)
        if self._kt_factor.shape != (nc,):
            raise ValueError(f"actuation.torque_constant_factor: {len(a.torque_constant_factor)} values for {nc} motors")
        self._k_t = self.params.motors.torque_constant
        self._force = np.zeros(nc)
        bw = a.current_bandwidth_hz
        self._tau_current = 1.0 / (2.0 * math.pi * bw) if math.isfinite(bw) else 0.0
        self._act = np.array([self._k_t, self.model.rho, a.current_max_A, 0.0, 0.0, a.ripple_fraction,
                              float(a.ripple_per_rev), a.cogging_N, float(a.cogging_per_rev)])  # integrator.ACT_*
        self._backlash = a.backlash_rad if a.enabled else 0.0
        t, c = self.truth.timing, self.truth.cables
        self._delay = t.delay_ticks if t.enabled else 0
        self._jitter = t.jitter_s if t.enabled else 0.0
        self._creep_on = c.enabled and c.creep_ratio > 0 and self.model.cable_model != RIGID
        self._rng_timing = np.random.default_rng([config.seed, 16])  # apart from the camera's noise stream
        self.seq = 0
        self.t_s = 0.0
        sensors = self.params.sensors
        self.camera = make_camera(config.alpha_ip, sensors, config.seed, self.model, model_params.geometry) \
            if config.camera else None
        self.counts_per_rev = sensors.encoder_counts_per_rev
        # Per-tick constants, so that tick() spends its time integrating (benchmarks/twin_speed.py).
        self._rad_per_count = 2.0 * math.pi / self.counts_per_rev
        self._all_cables = (1 << nc) - 1
        self._slack_of = (np.arange(1 << nc)[:, None] >> np.arange(nc)) & 1 == 1  # row: the integrator's slack bits
        self._actuation_on = a.enabled
        # One compiled call per period (integrator.advance), on arrays allocated here and updated in
        # place; what varies per period goes in through _io.
        self._cmd = np.zeros(nc)  # N, the command applied this period (after the timing effect's delay)
        self._io = np.zeros(integrator.IO_SIZE)
        self._io[integrator.IO_SUBSTEPS] = config.substeps
        self._io[integrator.IO_ACTUATION] = float(a.enabled)
        self._io[integrator.IO_CREEP] = float(self._creep_on)
        self._io[integrator.IO_CREEP_RATIO] = c.creep_ratio
        self._io[integrator.IO_BACKLASH] = self._backlash
        self._io[integrator.IO_RAD_PER_COUNT] = self._rad_per_count
        self._obs = np.zeros(integrator.observation_size(n, nc))
        self._advance = bind(integrator.advance, self.model, self._state, self._cmd, self._io,
                             integrator.scratch(n, nc), self._tension, self._stretch, self._rf, self._creep,
                             self._current, self._kt_factor, self._act, self._force, self._obs)
        self._h = -1.0  # the period the _io entries below were computed for

    @property
    def state(self) -> np.ndarray:
        """(α, θ, α̇, θ̇): the integrator's own array (write into it, e.g. ``state[:n] = ...``; it
        cannot be replaced by another)."""
        return self._state

    # -- state views (copies, so callers cannot corrupt the integrator's state) -----------------
    @property
    def alpha(self) -> np.ndarray:
        return self.state[: self._n].copy()

    @property
    def theta(self) -> np.ndarray:
        return self.state[self._n : self._n + self._nc].copy()

    @property
    def tension_N(self) -> np.ndarray:
        """Cable tensions (N) of the last substep."""
        return self._tension.copy()

    def reset(self, alpha: np.ndarray | None = None, theta: np.ndarray | None = None) -> None:
        """Put the robot at rest at ``alpha`` (rad) with motor angles ``theta`` (default: rigid
        cables, no stretch)."""
        n, nc = self._n, self._nc
        a = np.zeros(n) if alpha is None else np.asarray(alpha, dtype=float)
        if a.shape != (n,) or not np.all(np.isfinite(a)) or np.any(np.abs(a) >= NEAR_FLAT):
            raise ValueError(f"alpha must be {n} finite angles within ±{math.degrees(NEAR_FLAT):.0f}°, got {a}")
        th = cables.theta_rigid(self.model, a) if theta is None else np.asarray(theta, dtype=float)
        self.state[:] = 0.0
        self.state[:n], self.state[n : n + nc] = a, th
        self._creep[:] = 0.0
        self._current[:] = 0.0
        self._pending.clear()
        self.seq, self.t_s = 0, 0.0

    def _prepare(self, f: np.ndarray, period_s: float) -> None:
        """Everything the compiled period needs from Python: the command applied now (``f`` delayed
        by the timing effect) in ``_cmd``, and the constants of this period's length in ``_io`` and
        ``_act`` (computed again only when the period changes, i.e. with jitter)."""
        if self._delay:
            self._pending.append(np.array(f, dtype=float))
            self._cmd[:] = self._pending.pop(0) if len(self._pending) > self._delay else 0.0
        else:
            self._cmd[:] = f
        if period_s != self._h:
            self._h = period_s
            self._io[integrator.IO_H] = period_s / self.config.substeps
            if self._actuation_on and self._tau_current:
                decay = math.exp(-period_s / self._tau_current)
                self._act[ACT_DECAY], self._act[ACT_MEAN_GAIN] = decay, self._tau_current / period_s * (1.0 - decay)
            if self._creep_on:
                self._io[integrator.IO_CREEP_GAIN] = 1.0 - math.exp(-period_s / self.truth.cables.creep_time_s)

    def _applied_force(self, f: np.ndarray, period_s: float) -> np.ndarray:
        """The force (N) the motors put on the cables this period for the command ``f``: delayed
        (timing), through the current loop and the motor's torque errors (actuation). What
        :meth:`advance` applies first, in its compiled call; here on its own (it advances the
        delay line and the current loops as a period would)."""
        self._prepare(f, period_s)
        if not self._actuation_on:
            return self._cmd.copy()
        actuate(self._cmd, self._state[self._n : self._n + self._nc], self._current, self._kt_factor, self._act,
                self._force)
        return self._force

    def advance(self, f: np.ndarray, period_s: float | None = None) -> int:
        """Hold forces ``f`` for one period and step, without building a :class:`Tick` (no
        sensors, no camera): what replaying a recording needs (twin.sim.calibrate). ``period_s``:
        the period (default: the control period, with the truth's jitter). Returns the
        integrator's bit field (twin.sim.integrator.step)."""
        if period_s is None:
            period_s = self.dt
            if self._jitter:
                period_s = min(max(self.dt + self._jitter * self._rng_timing.standard_normal(), 0.5 * self.dt),
                               1.5 * self.dt)
        self._prepare(f, period_s)
        bits = int(self._advance())  # np.int64 when run as plain Python
        self.seq += 1
        self.t_s += period_s
        return bits

    def tick(self, f: np.ndarray, period_s: float | None = None) -> Tick:
        """Hold forces ``f`` (N, one per cable, assumed validated) for one period and step.
        ``period_s``: as in :meth:`advance`."""
        bits = self.advance(f, period_s)
        flat = bool(bits >> 62 & 1)
        n, nc = self._n, self._nc
        # The kernel wrote the state, tensions, stretch and encoders into _obs (integrator.advance);
        # one copy per tick, and the Tick's arrays are views of it. Backlash: a pulling cable keeps
        # the gear on one flank (the offset is zeroed at homing); a slack cable lets the motor shaft
        # turn through the backlash.
        o = self._obs.copy()
        alpha, m = o[:n], n + nc
        frames = self.camera.update(self.t_s, alpha) if self.camera else []
        return Tick(  # by position (keywords cost a NamedTuple twice the time): the fields in order
            self.seq,  # seq
            self.t_s,  # t_s
            o[2 * m + 2 * nc : 2 * m + 3 * nc],  # theta_meas: = sensors.quantise_encoder of θ through the backlash
            frames,  # frames
            alpha,  # alpha
            o[m : m + n],  # alpha_dot
            o[n:m],  # theta
            o[m + n : 2 * m],  # theta_dot
            o[2 * m : 2 * m + nc],  # tension
            o[2 * m + nc : 2 * m + 2 * nc],  # elongation
            self._slack_of[bits & self._all_cables].copy(),  # slack (flat: the step is refused, bits & all = 0)
            bool(o[-1]),  # near_singular
            flat,  # flat
            tuple(self.camera.confidence) if frames and self.camera else (),  # frame_confidence
        )


def _friction_table(params: Params, truth: RobotTruth) -> np.ndarray:
    """The integrator's robot-friction table (twin.sim.integrator.RF_*) from Table 1's f_s and the
    truth's friction section."""
    fr, nc = truth.friction, params.n_cables
    f_s = np.asarray(params.friction.f_s, dtype=float)
    asym = np.asarray(fr.asymmetry or (0.0,) * nc, dtype=float)
    pulley = np.asarray(fr.pulley_friction_per_N or (0.0,) * nc, dtype=float)
    if asym.shape != (nc,) or pulley.shape != (nc,):
        raise ValueError(f"friction.asymmetry and pulley_friction_per_N need {nc} values (one per cable)")
    table = np.empty((nc, RF_COLUMNS))
    table[:, 0], table[:, 1] = f_s * (1 + asym), f_s * (1 - asym)
    table[:, 2], table[:, 3], table[:, 4] = fr.static_ratio, fr.stribeck_velocity_rad_s, fr.viscous_N_s_rad
    table[:, 5], table[:, 6] = fr.gear_loss_forward, fr.gear_loss_backward
    table[:, 7], table[:, 8] = pulley, fr.pulley_reference_tension_N
    return table
