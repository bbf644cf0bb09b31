"""The paper's computed-torque control laws (3-X paper §6, eqs. 59-66).

One tick of :class:`ComputedTorque`: α̂ from the encoders (eq. 35, :mod:`twin.model.estimation`),
the PID outer loop w = α̈^d + k_v·ė + k_p·e + k_i∫e (eq. 59, k_p = 3ω², k_v = 3ω, k_i = ω³,
ω = 11 rad/s), the simplified model Γ^d = M(α̂)w + g(α̂) + Z(α̂)·f_friction(θ̇^d) (eq. 66), and
the tension distribution (eqs. 63-65, :mod:`controller.distribution`) with θ^d, θ̇^d, θ̈^d in the
friction and inertia terms "to avoid any force discontinuity" (§6.2).

The laws differ only in the controller's model (§6.3, Table 3):
- law 1: no friction, rigid cables in α̂;
- law 2: friction, rigid cables in α̂;
- law 3: friction, and elastic cables (variable stiffness, eq. 58) in α̂;
- ``no_pulleys``: law 2 computed with r = 0 (Z and α̂ without pulleys), the Table 3 variant.

Beyond the paper, every law bounds the rate of its commanded forces (``LawConfig.force_rate_max_N_s``):
an encoder that jumps (a slack cable crossing the gear backlash) must not step the cables.

Time step: a tick told the stamp of its state (the bridge's clock; a lockstep twin's simulated
time) differentiates θ and α̂, integrates e and predicts the stretch (eq. 58) over the time since
the last state the law took, not over 1/rate_hz. States the controller never answers (the process
skipping a burst's stale ones when it is behind, the state gate refusing one, Zenoh dropping one)
had it divide two periods' increment by one: θ̇ and α̂̇ doubled for a tick, the k_v term of eq. 59
spiked, and law 2's control test stepped its commands by the 10 N rate bound 74 times with 5 % of
the states missed singly, never with none (audit; tests/test_laws_missed_states.py). How the gap
is taken (:meth:`ComputedTorque.tick_time`):

- the velocity filters divide by the whole gap (the mean velocity over it, however long) and their
  low-pass weight is that of the gap, so across a long one they restart from that mean rather
  than spike;
- the integral and eq. 58 take the gap bounded by ``MAX_STEP_PERIODS`` periods: beyond them the
  process was holding on stale states (``stale_s``, 10 ms), not controlling, and its integral is
  not to wind up over a hold (after ``STALE_RESTART_S`` the service re-starts it anyway);
- no gap is known (the first state, after a reset: a new bridge run, a re-estimate; a tick without a
  stamp: the warm-up, tests), or the stamps do not advance: one period, as before; a clock step
  the controller is told of is taken out of the gap (:meth:`ComputedTorque.clock_stepped`);
- a gap within ``PERIOD_TOLERANCE_S`` of the period is the period itself, so a steady clock (a
  twin without timing jitter, stamps k·2 ms rounded) gives the very numbers of a fixed period.

The rate bound stays per command (``force_rate_max_N_s``/rate_hz): what the bridge is sent in one
message is what may step the cables.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from controller import kernel
from controller.distribution import distribute, lower_bounds
from twin.model import dynamics
from twin.model.estimation import PseudoInverseEstimator, alpha_hat_3, long_cable, short_cables
from twin.model.numeric import Model, build
from twin.model.params import Params

LAWS = (1, 2, 3)
#: periods of a gap between states over which the integral and eq. 58 still run (module docstring,
#: "Time step"): 10 ms at 500 Hz, the process's ``stale_s``, beyond which it holds.
MAX_STEP_PERIODS = 5
#: s within which a gap between stamps is the nominal period (float rounding of stamps, 0.24 µs on
#: a wall clock's epoch seconds; a bridge's real jitter is of order 0.1 ms).
PERIOD_TOLERANCE_S = 1e-6


@dataclass(frozen=True)
class LawConfig:
    """Which law, and its gains. ``omega`` in rad/s (eq. 59)."""

    law: int = 2
    no_pulleys: bool = False
    omega: float = 11.0
    rate_hz: float = 500.0
    velocity_filter_hz: float = 50.0  # first-order low-pass on finite differences of α̂ and θ
    # The most a commanded force may change per second (N/s; 10 N per 500 Hz tick). Not from the
    # paper: a slack cable crossing the gear backlash makes the encoder jump, α̂̇ spikes and the k_v
    # term of eq. 59 steps the forces by up to 84 N in a tick (law 1 on the robot truth). The bound
    # never binds on smooth tracking (steps stay below 5 N); math.inf turns it off.
    force_rate_max_N_s: float = 5000.0
    # The most α̂̇'s new sample may differ from its filtered value, per second of the gap (rad/s²;
    # 0.1 rad/s in a 2 ms tick). Not from the paper: a cable that goes slack under the motors'
    # stiction lets its motor cross the gear's backlash (0.44 rad) within a tick, α̂ jumps by
    # about 0.5° and the k_v term of eq. 59 answered with 10 N a tick, the force rate bound, for
    # 2-4 ticks, 26 N in all, even while idle at law 2 (robot truth; session 44), and with 250
    # rad/s² still one tick of 8-9.5 N (session 46). Through the velocity filter the filtered α̂̇
    # then follows at most β·50 ≈ 23 rad/s² (β = 0.47 at 500 Hz): 8 times the trajectories' 3
    # rad/s², within the neck's own p99.9 (14-34 rad/s², slack cables included), the control test's
    # tracking unchanged; the noise of smooth tracking (|sample − filtered| p99 0.1 rad/s) is
    # trimmed at it (docs/safety.md); math.inf: no bound.
    alpha_hat_accel_max_rad_s2: float = 50.0

    def __post_init__(self) -> None:
        if self.law not in LAWS:
            raise ValueError(f"law must be one of {LAWS}, got {self.law!r}")
        if not (self.omega > 0 and math.isfinite(self.omega)):
            raise ValueError(f"omega must be a positive number (rad/s), got {self.omega}")
        if not self.alpha_hat_accel_max_rad_s2 > 0:  # inf allowed: no bound
            raise ValueError(f"alpha_hat_accel_max_rad_s2 must be positive (rad/s²) or inf, got {self.alpha_hat_accel_max_rad_s2}")
        if not self.force_rate_max_N_s > 0:  # inf allowed: no bound
            raise ValueError(f"force_rate_max_N_s must be a positive rate (N/s) or inf, got {self.force_rate_max_N_s}")

    @property
    def name(self) -> str:
        return f"law{self.law}" + ("-no-pulleys" if self.no_pulleys else "")


def controller_model(params: Params, config: LawConfig) -> Model:
    """The controller's model of the robot for a law (module docstring)."""
    cable_model = "variable" if config.law == 3 else "rigid"
    return build(params, cable_model, friction=config.law != 1, pulleys=not config.no_pulleys)


class Command(NamedTuple):
    f: np.ndarray  # (n_cables,) N
    alpha_hat: np.ndarray  # (N,) rad
    e: np.ndarray  # (N,) rad, α^d − α̂
    saturated: np.ndarray  # (n_cables,) bool
    gamma_d: np.ndarray  # (N,) N·m


class ComputedTorque:
    """State of one law between ticks: the α̂ estimator, the PID integral, filtered velocities."""

    def __init__(self, params: Params, config: LawConfig = LawConfig()):
        self.params, self.config = params, config
        self.model = controller_model(params, config)
        self.dt = 1.0 / config.rate_hz
        self.short, self.long = short_cables(self.model), long_cable(self.model)
        self.kp, self.kv, self.ki = 3 * config.omega**2, 3 * config.omega, config.omega**3
        self._beta = 1.0 - math.exp(-2 * math.pi * config.velocity_filter_hz * self.dt)
        self.estimator = PseudoInverseEstimator(self.model, self.dt)
        self.reset()

    def reset(self, alpha: np.ndarray | None = None, theta: np.ndarray | None = None,
              stamp_s: float | None = None) -> None:
        """Start again at α̂ = ``alpha`` with the encoders at ``theta`` (default: zeros, the
        straight neck of eq. 20), read at ``stamp_s`` (s; None: unknown, the next tick then spans
        one period). The state lives in arrays allocated here, which every tick updates in place
        (:mod:`controller.kernel`)."""
        m = self.model
        self.estimator.reset(alpha, theta)
        self.integral = np.zeros(m.n_joints)
        self.alpha_hat_dot = np.zeros(m.n_joints)
        self.theta_dot = np.zeros(m.n_cables)
        self.f_prev = np.zeros(m.n_cables)
        self._has_prev = theta is not None
        self._theta_prev = np.zeros(m.n_cables) if theta is None else np.array(theta, dtype=float)
        self._work = kernel.scratch(m.n_joints, m.n_cables)
        self._gains = np.array([self.kp, self.kv, self.ki, self.dt, self._beta,
                                self.config.force_rate_max_N_s * self.dt, self.dt, self.config.alpha_hat_accel_max_rad_s2])
        self._stamp_prev = math.nan  # s, the stamp of the state θ_prev was read at (nan: unknown)
        self.gap_s = self.dt  # s, the time the last tick's estimate spanned (tick_time)
        self._theta = np.zeros(m.n_cables)
        self._ref = (np.zeros(m.n_joints), np.zeros(m.n_joints), np.zeros(m.n_joints))
        self._out = (np.zeros(m.n_cables), np.zeros(m.n_cables, dtype=np.bool_), np.zeros(m.n_joints),
                     np.zeros(m.n_joints))
        self._alpha_out = np.zeros(m.n_joints)
        if stamp_s is not None:
            self._stamp_prev = float(stamp_s)

    def tick_time(self, stamp_s: float | None) -> float:
        """Take the time since the last state for a tick on the state stamped ``stamp_s`` (s; None:
        unknown) and set the gains with it (module docstring, "Time step"): the gap (s), also kept
        in :attr:`gap_s`. A handful of float operations, one ``exp`` when the gap is not the period."""
        prev = self._stamp_prev
        self._stamp_prev = math.nan if stamp_s is None else stamp_s
        gap = self.dt if stamp_s is None else stamp_s - prev  # nan when prev is unknown
        if not gap > 0.0 or not math.isfinite(gap) or abs(gap - self.dt) <= PERIOD_TOLERANCE_S:
            gap = self.dt
        g = self._gains
        if gap != g[6]:
            g[3] = min(gap, MAX_STEP_PERIODS * self.dt)
            g[4] = self._beta if gap == self.dt else 1.0 - math.exp(-2 * math.pi * self.config.velocity_filter_hz * gap)
            g[6] = gap
        self.gap_s = gap
        return gap

    @property
    def stamp_s(self) -> float | None:
        """The stamp (s) of the last state the law took, None if unknown."""
        return None if math.isnan(self._stamp_prev) else self._stamp_prev

    def clock_stepped(self, step_s: float) -> None:
        """The states' clock stepped by ``step_s`` (s) since the last state (the state gate's
        ``stepped_s``): not time that passed, so it is taken out of the next gap."""
        self._stamp_prev += step_s

    def _state(self) -> tuple[np.ndarray, ...]:
        est = self.estimator
        return (self._theta_prev, self.theta_dot, est.alpha_hat, self.alpha_hat_dot, est.theta, est.x_c, self.f_prev,
                self.integral)

    def observe(self, theta: np.ndarray, f_applied: np.ndarray, stamp_s: float | None = None) -> np.ndarray:
        """Follow the measured state without commanding (drives off, or the bridge holding): α̂
        and the velocity filters take the encoders θ (rad) and the forces ``f_applied`` (N) the
        drives really apply, and the integral stays at zero, so nothing winds up and the next
        :meth:`step` starts from the measurement (bumpless re-start). ``stamp_s``: the state's
        stamp (s; module docstring, "Time step"). Returns α̂ (rad)."""
        self.f_prev[:] = f_applied
        self.tick_time(stamp_s)
        self._estimate(theta)
        self.integral[:] = 0.0
        return self.estimator.alpha_hat.copy()

    def restart_integral(self) -> None:
        """Forget the PID integral (eq. 59): a law taking over again starts without the error
        accumulated before."""
        self.integral[:] = 0.0

    def _estimate(self, theta: np.ndarray) -> None:
        """α̂ from the encoders (eq. 35) with ``f_prev`` the forces over the last period, and the
        filtered θ̇ and α̂̇ (:func:`controller.kernel.estimate`)."""
        self._theta[:] = theta
        w, est = self._work, self.estimator
        g = self._gains
        kernel.estimate(self.model, g[3], g[6], g[4], g[7], self._has_prev, self._theta, self._theta_prev, self.theta_dot,
                        est.alpha_hat, self.alpha_hat_dot, est.theta, est.x_c, self.f_prev, w[0], w[1], w[2], w[3],
                        w[9], w[10], w[12], w[13], w[14], w[18], w[19], w[20])
        self._has_prev = True

    def step(self, theta: np.ndarray, alpha_d: np.ndarray, alpha_d_dot: np.ndarray, alpha_d_ddot: np.ndarray,
             pretension_N: float = 0.0, stamp_s: float | None = None) -> Command:
        """One control tick from the encoder angles θ (rad) and the desired α^d, α̇^d, α̈^d: one
        call of the compiled :func:`controller.kernel.law_tick`. ``pretension_N`` raises every
        cable's floor t_min (eq. 65; a trajectory's pretension). ``stamp_s``: the state's stamp
        (s), whose gap from the last one the tick spans (module docstring, "Time step"; None: one
        period). The arrays of the returned :class:`Command` are the law's own and change at the
        next tick: copy what you keep."""
        self.tick_time(stamp_s)
        self._theta[:] = theta
        a, ad, add = self._ref
        a[:], ad[:], add[:] = alpha_d, alpha_d_dot, alpha_d_ddot
        kernel.law_tick(self.model, self._gains, self.short, self.long, self._has_prev, self._theta, a, ad, add,
                        float(pretension_N), self._state(), self._work, self._out)
        self._has_prev = True
        self._alpha_out[:] = self.estimator.alpha_hat
        f, saturated, e, gamma = self._out
        return Command(f, self._alpha_out, e, saturated, gamma)


@functools.lru_cache(maxsize=8)
def _hold_model(params: Params) -> tuple[Model, np.ndarray, int]:
    m = build(params, "rigid", friction=False)
    return m, short_cables(m), long_cable(m)


def hold_forces(params: Params, alpha: np.ndarray, pretension_N: float = 0.0) -> np.ndarray:
    """Forces (N) that hold the neck still at α (rad): Z f = g(α) with every cable at least at
    t_min + ``pretension_N`` (eqs. 63-65 with w = 0 and no motion). What the controller commands
    when it must stop. The model is built once per parameter set: this runs inside 2 ms ticks."""
    m, short, long = _hold_model(params)
    terms = dynamics.evaluate(m, alpha)
    lower = lower_bounds(m.t_min + pretension_N, m.f_min, np.zeros(m.n_cables), np.zeros(m.n_cables))
    return distribute(terms.Z, terms.g, lower, m.f_max, short, long).f


def encoder_hold_forces(params: Params):
    """The bridge's hold rule as a function θ (rad, encoders) → f (N): :func:`hold_forces` at the
    rigid-cable α̂ of eq. 33 (what laws 1-2 assume), with α̂ kept within the joint limits so a
    wild estimate cannot ask for wild forces. Given to :class:`bridge.node.BridgeNode`."""
    rigid = build(params, "rigid", friction=False)
    alpha_max = math.radians(params.limits.alpha_max_deg)

    def hold(theta: np.ndarray) -> np.ndarray:
        alpha = alpha_hat_3(rigid, theta)
        if not np.all(np.isfinite(alpha)):
            alpha = np.zeros_like(alpha)
        return hold_forces(params, np.clip(alpha, -alpha_max, alpha_max))

    return hold


def nominal_forces(params: Params, config: LawConfig):
    """The forces (N) the law would command on a nominal path (α̂ = α^d, e = 0, so w = α̈^d),
    after the tension distribution and before clamping at f_max, as a function
    (α, α̇, α̈[, pretension (T,) N]) on a time grid, each (T, N) -> (f (T, n_cables), feasible (T,):
    the distribution is possible, n > 0 in eq. 63). Used by :func:`nominal_force_check` and by the excitation design
    (:mod:`server.cli.excitation`), which needs the cable tensions along a candidate path."""
    m = controller_model(params, config)
    short, long = short_cables(m), long_cable(m)

    def forces(alpha: np.ndarray, alpha_dot: np.ndarray, alpha_ddot: np.ndarray,
               pretension: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        terms = dynamics.evaluate(m, alpha, alpha_dot)
        floor = np.full(len(alpha), m.t_min) if pretension is None else m.t_min + np.asarray(pretension, dtype=float)
        f = np.empty((len(alpha), m.n_cables))
        feasible = np.ones(len(alpha), dtype=bool)
        for k in range(len(alpha)):
            Z = terms.Z[k]
            theta_d_dot = Z.T @ alpha_dot[k] / m.rho
            theta_d_ddot = (Z.T @ alpha_ddot[k] + terms.Z_dot[k].T @ alpha_dot[k]) / m.rho
            f_fric = dynamics.f_friction(m, theta_d_dot)
            gamma = terms.M[k] @ alpha_ddot[k] + terms.g[k] + Z @ f_fric
            d = distribute(Z, gamma, lower_bounds(floor[k], m.f_min, f_fric, m.I_a * theta_d_ddot / m.rho),
                           np.inf, short, long)
            f[k], feasible[k] = d.f, d.feasible
        return f, feasible

    return forces


def nominal_force_check(params: Params, config: LawConfig):
    """A ``force_check`` for :func:`controller.trajectory.validate`: the forces the law would
    command on the nominal path (:func:`nominal_forces`) must lie within [f_min, f_max], and the
    distribution must be possible (n > 0, eq. 63)."""
    forces = nominal_forces(params, config)
    f_max = controller_model(params, config).f_max

    def check(alpha: np.ndarray, alpha_dot: np.ndarray, alpha_ddot: np.ndarray,
              pretension: np.ndarray) -> tuple[np.ndarray, str]:
        f, feasible = forces(alpha, alpha_dot, alpha_ddot, pretension)
        ok = feasible & (f.max(axis=1) <= f_max)
        worst = ""
        bad = np.flatnonzero(~ok)
        if bad.size:
            k = int(bad[0])
            worst = ("the cables cannot hold this configuration (eq. 63 needs −Z1⁻¹Z2 > 0)" if not feasible[k]
                     else f"needs {f[k].max():.1f} N on cable {int(np.argmax(f[k])) + 1} > f_max = {f_max:g} N")
        return ok, worst

    return check
