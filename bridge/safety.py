"""The bridge's safety rules as a pure state machine: no bus, no clock, no driver.

Each tick :class:`bridge.node.BridgeNode` gathers the facts of the tick in :class:`Inputs` (a valid
command received since the last tick, the age of the newest valid command, the e-stop events, the
fresh hold forces of the encoder angles) and :meth:`Safety.step` answers with a :class:`Decision`: the drive state, the
forces to write, whether the drives must be enabled, the hold reason and what to log. The node
only moves data between the bus, this machine and the driver, so every rule below is tested
without a bus (tests/test_bridge_safety.py) and is the same for the robot, the twin and a replay.

Rules (the numbers live in :class:`SafetyConfig`):

Clamping
    Valid command forces are clamped to [f_min, f_max] (a cable must stay taut; counted).
Activation
    The drives start disabled (``inactive``: zero force). The first valid command enables them
    (``active``).
Bumpless
    Every enable (the first command, leaving a hold, after an e-stop release), every change of
    the commanding controller (a new owner's first command) and every tick after the bridge's own
    loop was held up longer than the command timeout (``Inputs.resumed_after_s``: a stalled CPU
    or process woke up to a command computed meanwhile) starts from the forces applied now and
    moves at most ``max_force_step_N`` per tick until the command is reached (after a stall: a
    command answering a state published after it, ``Inputs.command_after_resume``); then
    commands pass through, within the active rate bound.
Active rate bound
    While ``active`` the forces move at most ``max_active_step_N`` per tick towards the newest
    command (default 10 N: the computed-torque law's own 5000 N/s at 500 Hz,
    ``controller.laws.LawConfig.force_rate_max_N_s``, so its commands pass through untouched).
    It keeps a controller that jumps (one slowed by a flood, a lab's own, a bug) from stepping
    the cables; the bounded ticks are counted (``rate_limited``) and each run of them logged once.
Watchdog
    When no valid command arrived for ``command_timeout_s`` (real time only) while at least
    ``command_timeout_states`` states went out unanswered (the node counts them), the forces ramp
    linearly over ``hold_ramp_ticks`` from those applied to the hold forces of the encoder
    angles, the ramp no faster than ``max_active_step_N`` per tick (a longer ramp from far: from f_max
    the 5 ticks had taken 18 N a tick; the damping below adds at most ``max_force_step_N``;
    ``drive = "hold"``, ``hold_reason`` says why). The hold forces are computed off the
    tick (the node's :class:`bridge.node.HoldWorker`) and handed in with the tick's facts when
    fresh; without them the hold keeps the applied forces (within [f_min, f_max]) and moves to
    the hold forces once they come, at most ``max_force_step_N`` per tick. The next valid command
    resumes ``active``.
Hold damping
    While holding, each motor is damped on its low-passed speed (``Inputs.speed_rad_s``,
    :mod:`bridge.motor_speed`): ``hold_damping_N_s_rad`` per rad/s beyond a dead band of
    ``hold_damping_deadband_rad_s`` (the encoders' counts), the damping moving at most
    ``max_force_step_N`` per tick, at most ``hold_damping_max_N`` either way and never past the
    room [f_min, f_max] leaves each hold force (no wind-up while a force is clamped). A hold on cables an
    e-stop left slack (the controller gone while it took the slack up) otherwise let the drums wind
    in unloaded and the neck snapped up at 494-599°/s; damped, 53-59°/s (robot truth,
    docs/safety/controller_gone.py; tests/test_bridge_hold_damping.py). A neck at rest is not
    damped: its forces are the hold's.
Speed
    One step runs in every 2 ms tick of a Cortex-A8: the forces are plain floats, not numpy arrays
    (numpy's per-call overhead on four values is most of a tick, benchmarks/bridge_tick.py), and
    only :class:`Decision` hands an array to the driver.
E-stop
    An engaged e-stop disables the drives (``disabled``, zero force) and every command is ignored
    until it is released; then the drives are ``inactive`` until the next valid command. A command
    in a tick whose events engage (or release) the e-stop is ignored: it may predate them. The node
    turns an undecodable e-stop payload into an engaged event (fail safe).
E-stop holders
    Whoever engages the e-stop keeps a liveliness token on the bus until it releases
    (:data:`bridge.bus.ESTOP_ENGAGED_ALL`), so a bridge that starts, or links back, after the
    ``EStop`` went out still sees it: each token that appears is an engaged event naming its
    holder, and the node asks for the tokens alive before its first tick (it starts latched). A
    release takes effect only when no holder is left, its sender's token gone too (a release
    naming a holder whose token lives waits for that token to vanish: :class:`EStopHolders`):
    another's release does not end an e-stop a console still holds. A holder that vanishes (it
    released, crashed or lost its link) releases nothing: the latch stays until an explicit
    release, since only the bridges that did not see the engage need the token (audit of the
    e-stop, S3).
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from bridge.bus import DriveState

log = logging.getLogger("xneck.bridge")

HoldForces = Callable[[np.ndarray], np.ndarray]
"""θ (rad, one per motor) → the cable forces (N) that hold the neck still there."""

#: A controller instance name as the bridge accepts it: a key chunk, short enough to publish in
#: every state and to log.
INSTANCE_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")

EStopEvent = tuple[bool, str]
"""(engaged, reason) of one e-stop message, in arrival order."""


class HolderWords(str):
    """The reason of an engage that names its sender, a would-be e-stop holder
    (:meth:`EStopHolders.message`): only its ``sender``'s own words may replace the generic
    reason of that holder's token (:meth:`Safety.apply_estop`), whichever of the token and the
    message arrives first. Any peer's engage had replaced it, so that ``xneck estop status`` and
    every state showed a stranger's "cleared, safe to release" (audit of session 42)."""

    sender: str

    def __new__(cls, text: str, sender: str) -> HolderWords:
        words = super().__new__(cls, text)
        words.sender = sender
        return words


@dataclass(frozen=True)
class SafetyConfig:
    """The numbers of the rules. Forces in N, times in s."""

    n_motors: int
    f_min_N: float
    f_max_N: float
    command_timeout_s: float = 0.010  # no valid command for this long -> hold
    # ... and this many states published unanswered meanwhile (when the caller counts them): the
    # node sets command_timeout_s / period (5 at 500 Hz), so a silent controller holds on the same
    # tick as by age alone, and a stall of the CPU the bridge and controller share does not.
    command_timeout_states: int = 1
    hold_ramp_ticks: int = 5  # ticks of the linear ramp to the hold forces
    max_force_step_N: float = 1.0  # after an enable: the most any force may change in one tick
    max_active_step_N: float = 10.0  # while active: the most any force may change in one tick (inf: off)
    watchdog: bool = True  # off in lockstep, where time stands still without commands
    # N·s/rad on each motor's speed while holding (module docstring, "Hold damping"): 1 held the
    # snap of a hold on slack cables to 57-66°/s in session 37's tuning runs (robot truth); 2
    # chattered (450-620 ticks of changing force in the 2 s after, at rest) and let 83-90°/s
    # through. 0: off.
    hold_damping_N_s_rad: float = 1.0
    # rad/s of motor speed not damped: a count's flicker low-passed (1.5 rad/s raw at 500 Hz)
    hold_damping_deadband_rad_s: float = 2.0
    # N, the most the damping adds to or takes from a force (session 37's audit: unbounded, a bad
    # reading could push a cable 48 N for 0.6 s). The snap of the slack drums needs about 30: capped
    # at 15 N the neck reached 224°/s, at 30 N 59°/s (docs/safety/controller_gone.py's case, seed 0).
    hold_damping_max_N: float = 30.0

    def __post_init__(self) -> None:
        f_min, f_max = self.f_min_N, self.f_max_N
        if not (math.isfinite(f_min) and math.isfinite(f_max) and 0.0 <= f_min < f_max):
            raise ValueError(f"the force range must be 0 <= f_min < f_max (N), got ({f_min}, {f_max})")
        if self.n_motors < 1 or self.hold_ramp_ticks < 1 or self.command_timeout_states < 1:
            raise ValueError(f"n_motors, hold_ramp_ticks and command_timeout_states must be >= 1, got "
                             f"{self.n_motors}, {self.hold_ramp_ticks}, {self.command_timeout_states}")
        if not (math.isfinite(self.max_force_step_N) and self.max_force_step_N > 0):
            raise ValueError(f"max_force_step_N must be a positive force (N), got {self.max_force_step_N}")
        if not self.max_active_step_N > 0:  # inf allowed: no bound; NaN fails the comparison
            raise ValueError(f"max_active_step_N must be a positive force (N) or inf, got {self.max_active_step_N}")
        for name in ("hold_damping_N_s_rad", "hold_damping_deadband_rad_s", "hold_damping_max_N"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
        if not (math.isfinite(self.command_timeout_s) and self.command_timeout_s > 0):
            raise ValueError(f"command_timeout_s must be a positive number of seconds, got {self.command_timeout_s}")


class Inputs(NamedTuple):
    """The facts of one tick (a tuple: built every tick, it must be cheap).

    ``command_N``: the forces of a valid command received since the last step (None if none);
    ``source``: its sender's law, for the log; ``sender``: the controller instance that sent it
    (a change of sender is ramped, module docstring). ``command_age_s``: age of the newest valid
    command (None if none ever arrived). ``states_unanswered``: states published since the newest
    valid command arrived (None: not counted, the age alone decides). ``estop``: e-stop events since
    the last step. ``hold_N``: fresh hold forces of the encoder angles (computed off the tick), None
    when there are none. ``speed_rad_s``: the motors' low-passed speeds (rad/s at the shaft,
    :class:`bridge.motor_speed.MotorSpeed`) for a hold's damping, None: not damped.
    """

    command_N: Sequence[float] | None = None
    source: str = ""
    command_age_s: float | None = None
    sender: str = ""
    resumed_after_s: float = 0.0  # how long the bridge's own loop was held up before this tick (s)
    command_after_resume: bool = True  # False: ``command_N`` answers a state published before that hold-up
    estop: Sequence[EStopEvent] = ()
    hold_N: Sequence[float] | None = None
    states_unanswered: int | None = None
    speed_rad_s: Sequence[float] | None = None


class Decision(NamedTuple):
    """What the node must do this tick: enable or disable the drives (``enabled``), write
    ``force_N`` if enabled (zeros otherwise), publish ``drive`` and ``hold_reason``, and log
    ``events`` (``(logging level, message)`` pairs)."""

    drive: DriveState
    force_N: np.ndarray
    enabled: bool
    hold_reason: str = ""
    estop_engaged: bool = False
    estop_reason: str = ""
    events: tuple[tuple[int, str], ...] = ()


class Safety:
    """The state machine of the module docstring. Not thread-safe: one caller (the bridge loop)."""

    def __init__(self, config: SafetyConfig) -> None:
        self.config = config
        n = config.n_motors
        self.drive: DriveState = "inactive"
        self.hold_reason = ""
        self.estop_engaged = False  # latched from engage to release
        self.estop_reason = ""
        self._zero = [0.0] * n
        self.force: list[float] = self._zero  # N, decided at the last step (never mutated in place)
        self._ramp_from = self._ramp_to = self._zero
        self._ramp_k = 0  # ticks into the linear hold ramp; -1: bounded steps to hold forces found late
        self._hold_ready = True  # False while a hold keeps the applied forces, waiting for hold forces
        self._hold_force = self._zero  # N, the hold's undamped forces at the last step
        self._damping = self._zero  # N, the damping added to them (module docstring, "Hold damping")
        self._target = self._zero  # N, the clamped forces of the newest valid command
        self._bumpless = False  # after an enable, until the applied forces reach the command
        self._stale_target = False  # after a stall of the loop, until a command answering a state after it
        self._sender = ""  # the controller whose commands the applied forces follow
        self.clamped = self.holds = self.rate_limited = 0
        self._bounding = False  # in a run of ticks bounded by max_active_step_N (logged once per run)
        self._events: list[tuple[int, str]] = []

    @property
    def enabled(self) -> bool:
        """True while the drives must be enabled."""
        return self.drive in ("active", "hold")

    # -- e-stop --------------------------------------------------------------------------------
    def apply_estop(self, events: Sequence[EStopEvent]) -> bool:
        """Apply e-stop events in order; True if the drive state changed. :meth:`step` calls it
        first; the lockstep loop also calls it between commands."""
        changed = False
        for engaged, reason in events:
            if engaged and self.drive != "disabled":
                self.drive, self.hold_reason, self.estop_reason = "disabled", "", str(reason)  # not HolderWords: encoded
                self.estop_engaged = True
                self.force = self._zero
                changed = True
                self._log(logging.WARNING, f"e-stop engaged ({reason}): drives disabled")
            elif engaged and self.estop_engaged and isinstance(reason, HolderWords) \
                    and self.estop_reason == EStopHolders.reason(reason.sender):
                # The holder's own words, come after its token (they travel apart): the operator's
                # reason ("Escape key") had been lost to the token's (browser test, CI of session 40).
                self.estop_reason = str(reason)
            elif not engaged and self.drive == "disabled":
                self.drive, self.estop_reason, self.estop_engaged = "inactive", "", False
                changed = True
                self._log(logging.WARNING, f"e-stop released ({reason}): drives inactive until the next valid command")
        return changed

    # -- one tick ------------------------------------------------------------------------------
    def step(self, inputs: Inputs) -> Decision:
        """Decide this tick's drive state and forces from its facts."""
        if (self.drive == "active" and inputs.command_N is not None and not inputs.estop
                and not self._bumpless and inputs.sender == self._sender
                and inputs.resumed_after_s <= self.config.command_timeout_s):
            # The steady state, nearly every tick: the rules below reduce to clamp and pass through
            # (within the active rate bound).
            self._target = self.clamp(inputs.command_N)
            self.force = self._within_rate(self._target)
            return Decision("active", np.array(self.force), True, "", self.estop_engaged, self.estop_reason,
                            self.take_events() if self._events else ())
        cfg = self.config
        stalled = inputs.resumed_after_s > cfg.command_timeout_s and self.drive == "active"
        if stalled:
            # A stall of the bridge itself is no silence of the controller (the watchdog never saw
            # it), but what it commands now was computed meanwhile: a step (audit of 2026-11-26).
            # The commands in hand predate the resume (the applied forces, often): the ramp goes on
            # until one that answers the new states is reached (audit of 2026-11-28).
            self._bumpless = self._stale_target = True
            self._log(logging.WARNING, f"the bridge's loop was held up {inputs.resumed_after_s * 1e3:.0f} ms: "
                                       f"ramping at {cfg.max_force_step_N:g} N per tick")
        was_disabled = self.drive == "disabled"
        self.apply_estop(inputs.estop)
        if self.drive == "disabled" or was_disabled or any(engaged for engaged, _ in inputs.estop):
            pass  # a command never outlives the e-stop, nor one that may predate its engage or release
        elif inputs.command_N is not None:
            if self.drive == "inactive":
                self._log(logging.INFO, f"first valid command from {inputs.source!r}: drives enabled, "
                                        f"ramping at {cfg.max_force_step_N:g} N per tick")
            elif self.drive == "hold":
                self._log(logging.INFO, f"valid commands from {inputs.source!r} again: leaving hold, "
                                        f"ramping at {cfg.max_force_step_N:g} N per tick")
            elif inputs.sender != self._sender:
                self._log(logging.WARNING, f"controller {inputs.sender!r} commands now (was {self._sender!r}): "
                                           f"ramping at {cfg.max_force_step_N:g} N per tick")
            if self.drive != "active" or inputs.sender != self._sender:
                self._bumpless = True  # every enable and every new sender starts from the forces applied now
            self._sender = inputs.sender
            self.drive, self.hold_reason = "active", ""
            self._target = self.clamp(inputs.command_N)
            self._stale_target = self._stale_target and (stalled or not inputs.command_after_resume)
        elif self.drive == "active" and cfg.watchdog and inputs.command_age_s is not None:
            age_s, unanswered = inputs.command_age_s, inputs.states_unanswered
            if age_s > cfg.command_timeout_s and (unanswered is None or unanswered >= cfg.command_timeout_states):
                self._start_hold(f"no valid command for {age_s * 1e3:.0f} ms (timeout {cfg.command_timeout_s * 1e3:.0f} ms)"
                                 + ("" if unanswered is None else f", {unanswered} states unanswered"), inputs.hold_N)
        if self.drive == "active":
            self.force = self._towards_target()
        elif self.drive == "hold":
            self.force = self._damped(self._hold_step(inputs.hold_N), inputs.speed_rad_s)
        else:
            self.force = self._zero
        return Decision(self.drive, np.array(self.force), self.enabled,
                        self.hold_reason if self.drive == "hold" else "", self.estop_engaged, self.estop_reason,
                        self.take_events() if self._events else ())

    @property
    def ramp_awaits_answer(self) -> bool:
        """Whether the ramp after a stall of the loop waits for a command answering a state
        published after it (``Inputs.command_after_resume``)."""
        return self._stale_target

    def take_events(self) -> tuple[tuple[int, str], ...]:
        """The log events since the last call (``(logging level, message)``), oldest first."""
        events, self._events = tuple(self._events), []
        return events

    def _towards_target(self) -> list[float]:
        """Bumpless enable: at most ``max_force_step_N`` per tick from the present forces until the
        command is reached; from then on commands pass through (within the active rate bound)."""
        if not self._bumpless:
            return self._within_rate(self._target)
        f = _step_towards(self.force, self._target, self.config.max_force_step_N)
        if f == self._target and not self._stale_target:
            self._bumpless = False
            self._log(logging.INFO, "bumpless ramp done: commands pass through")
        return f

    def _within_rate(self, target: list[float]) -> list[float]:
        """``target`` if no force moves more than ``max_active_step_N`` from the applied ones, else
        the applied forces moved towards it by that much (counted, each run logged once)."""
        lim = self.config.max_active_step_N
        for a, t in zip(self.force, target):  # a loop, not a comprehension: half the cost per tick
            if t - a > lim or a - t > lim:
                break
        else:
            self._bounding = False
            return target
        f = _step_towards(self.force, target, lim)
        self.rate_limited += 1
        if not self._bounding:
            self._bounding = True
            self._log(logging.WARNING, f"active commands step more than {lim:g} N per tick: moving at {lim:g} N "
                                       f"per tick (commanded {[round(x, 2) for x in target]} N)")
        return f

    def clamp(self, force_N: Sequence[float]) -> list[float]:
        """Forces within [f_min, f_max]; counts the commands that needed it."""
        f = [float(x) for x in force_N]
        clamped = self._in_range(f)
        if clamped != f:
            self.clamped += 1
        return clamped

    def hold_target(self, hold_N: Sequence[float] | None) -> list[float] | None:
        """Hold forces handed in with a tick, within [f_min, f_max]; None if there are none or
        they are not one finite force per motor (nonsense never fails a hold)."""
        if hold_N is None or len(hold_N) != self.config.n_motors:
            return None
        f = [float(x) for x in hold_N]
        return self._in_range(f) if all(map(math.isfinite, f)) else None

    def _in_range(self, f: list[float]) -> list[float]:
        lo, hi = self.config.f_min_N, self.config.f_max_N
        return [lo if x < lo else hi if x > hi else x for x in f]  # not min/max: 4x faster here

    def _start_hold(self, reason: str, hold_N: Sequence[float] | None) -> None:
        self.drive, self.hold_reason = "hold", reason
        self.holds += 1
        self._ramp_from, self._ramp_k = self.force, 0
        self._hold_force, self._damping = self.force, self._zero
        target = self.hold_target(hold_N)
        self._hold_ready = target is not None
        if target is None:  # the applied forces (within [f_min, f_max]) until hold forces are ready
            target = self._in_range(self.force)
            self._log(logging.WARNING, f"hold: {reason}; no hold forces ready for these angles: keeping the "
                                       f"applied forces {[round(x, 2) for x in target]} N until they are")
        else:
            self._log(logging.WARNING, f"hold: {reason}; ramping to {[round(x, 2) for x in target]} N "
                                       f"over {self.config.hold_ramp_ticks} ticks")
        self._ramp_to = target

    def _hold_step(self, hold_N: Sequence[float] | None) -> list[float]:
        """One tick of a hold: the linear ramp to its target. A hold that kept the applied forces
        takes hold forces that became ready as its new target, approached at most
        ``max_force_step_N`` per tick (bumpless, as every enable)."""
        if not self._hold_ready:
            target = self.hold_target(hold_N)
            if target is not None:
                self._hold_ready, self._ramp_to, self._ramp_k = True, target, -1
                self._log(logging.INFO, f"hold forces ready: moving to {[round(x, 2) for x in target]} N "
                                        f"at {self.config.max_force_step_N:g} N per tick")
        if self._ramp_k < 0:
            return _step_towards(self._hold_force, self._ramp_to, self.config.max_force_step_N)
        n_ramp = self.config.hold_ramp_ticks
        self._ramp_k = min(self._ramp_k + 1, n_ramp)
        w = self._ramp_k / n_ramp
        linear = [(1.0 - w) * a + w * b for a, b in zip(self._ramp_from, self._ramp_to, strict=True)]
        # no faster than any command may move them: from f_max the 5 ticks had taken 18 N a tick
        return _step_towards(self._hold_force, linear, self.config.max_active_step_N)

    def _damped(self, hold: list[float], speed_rad_s: Sequence[float] | None) -> list[float]:
        """The hold's forces ``hold`` with each motor damped on its speed (module docstring,
        "Hold damping"), the damping moving at most ``max_force_step_N`` per tick."""
        self._hold_force = hold
        cfg = self.config
        c, band, cap, step = cfg.hold_damping_N_s_rad, cfg.hold_damping_deadband_rad_s, cfg.hold_damping_max_N, \
            cfg.max_force_step_N
        if speed_rad_s is None or len(speed_rad_s) != cfg.n_motors or c == 0.0:
            if self._damping is self._zero:
                return hold
            speed_rad_s = self._zero  # no speeds (a caller that gives none): the damping is let go
        lo, hi = cfg.f_min_N, cfg.f_max_N
        damping, force, active = [], [], False
        # One loop, plain floats (a hold tick on a Cortex-A8): the damping wanted against the speed
        # beyond the dead band, reached at ``step`` a tick, within ±cap and within the room the force
        # range leaves the hold force, so a clamped force does not wind it up (it had held loaded
        # cables at f_min 140-200 ms after a glitch, session 37's audit).
        for h, d, v in zip(hold, self._damping, speed_rad_s):
            w = -c * (v - band) if v > band else -c * (v + band) if v < -band else 0.0  # NaN: 0
            d = w if d - step <= w <= d + step else d + step if w > d else d - step
            room_lo, room_hi = lo - h, hi - h
            d = max(room_lo if room_lo > -cap else -cap, min(room_hi if room_hi < cap else cap, d))
            active = active or d != 0.0
            damping.append(d)
            f = h + d
            force.append(lo if f < lo else hi if f > hi else f)
        self._damping = damping if active else self._zero
        return force

    def _log(self, level: int, message: str) -> None:
        self._events.append((level, message))


def _step_towards(force: list[float], target: list[float], step: float) -> list[float]:
    """``force`` moved towards ``target`` by at most ``step`` per component (the bounded rate of
    every enable)."""
    return [f + min(max(t - f, -step), step) for f, t in zip(force, target, strict=True)]


#: How a holder's token's e-stop reason ends (:meth:`EStopHolders.reason`): a message's reason
#: replaces it once it comes (:meth:`Safety.apply_estop`).
TOKEN_REASON_TAIL = " (it holds the e-stop token)"


#: s a release naming a holder whose token is still alive waits for that token to go
#: (:class:`EStopHolders`): the holder drops its token, then releases, and the two may arrive
#: in either order; a release naming a holder that keeps its token is a forgery, or stale.
RELEASE_TOKEN_WAIT_S = 2.0


class EStopHolders:
    """Who holds the e-stop engaged (their liveliness tokens), and whether a release may act
    (module docstring, "E-stop holders"). The node feeds it the tokens as they appear and vanish
    and every decoded e-stop message, and queues the events it answers. Not thread-safe: the node
    calls it under its e-stop lock.

    A holder releases by dropping its token and publishing the release, which names it
    (:func:`bridge.session.estop_holder_of`). The two may arrive in either order (a liveliness
    subscriber and a sample subscriber have callback threads of their own): a release naming a
    holder whose token is still alive acts when that token vanishes, within
    :data:`RELEASE_TOKEN_WAIT_S`, if no other holder is left then. It had acted at once, so that
    anyone on the bus could release a live console's e-stop by naming it (holder names are
    public; review of session 41). A release that names no holder, or one whose token is gone,
    acts when none is left. A holder's token that vanishes releases nothing by itself, and an
    engage drops every release still waiting (it came before, and must not undo the engage).
    What is left: a forged release naming a live holder acts if that holder's link drops within
    :data:`RELEASE_TOKEN_WAIT_S` after it (holder names are public; credentials keep forgers off
    the bus: docs/safety.md).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.holders: set[str] = set()
        self._clock = clock
        self._pending: dict[str, tuple[float, EStopEvent]] = {}  # holder -> (when, its release)
        self.expired = ""  # the reason of the last release that waited too long for its token ('' none)

    @staticmethod
    def reason(holder: str) -> str:
        """The e-stop reason of a holder's token (a token carries no text of its own)."""
        return f"e-stop engaged by {holder}{TOKEN_REASON_TAIL}"

    def appeared(self, holder: str) -> EStopEvent:
        """A holder's token appeared: an engaged event. A release still waiting for a token is
        dropped: it came before this engage and must not undo it."""
        self.holders.add(holder)
        self._pending.clear()
        return True, self.reason(holder)

    def vanished(self, holder: str) -> EStopEvent | None:
        """A holder's token vanished: it holds no longer. Its own release, if it came first
        (within :data:`RELEASE_TOKEN_WAIT_S`, no engage since), is returned to act now when no
        other holder is left; else None: a vanishing token releases nothing. A release that
        waited longer is :attr:`expired` (the node warns: release again)."""
        self.holders.discard(holder)
        pending = self._pending.pop(holder, None)
        if pending is None:
            return None
        if self._clock() - pending[0] > RELEASE_TOKEN_WAIT_S:
            self.expired = pending[1][1]
            return None
        return None if self.holders else pending[1]

    def waits_for(self, holder: str) -> bool:
        """Whether a release naming ``holder`` waits for its token to go."""
        return holder in self._pending

    def message(self, event: EStopEvent, holder: str = "") -> EStopEvent | None:
        """An e-stop message's event as it is to be applied, from ``holder`` ('' if it names
        none): an engage as it is, its reason :class:`HolderWords` when it names ``holder``; a
        release if no holder is left (``holder``'s token being
        gone already), else None: refused (:attr:`holders` says who holds it), or kept until
        ``holder``'s token vanishes (:meth:`vanished`)."""
        engaged, reason = event
        if engaged:
            # A release still waiting for a token came before this engage: it must not undo it
            # when that token goes (review of session 41: a re-engage, or another's, undone).
            self._pending.clear()
            return (True, HolderWords(reason, holder)) if holder else event
        if holder and holder in self.holders:
            self._pending[holder] = (self._clock(), event)
            return None
        return None if self.holders else event


class Ownership:
    """One controller owns the bridge at a time (issue 13, finding 5), decided from facts only.

    The node reports controllers' liveliness tokens as they appear and vanish
    (``xneck/alive/controller/<instance>``) and asks :meth:`admit` for every decoded command. The
    sender of the first command whose token is alive becomes the owner; commands from any other
    sender are refused ("bridge owned by <owner>"), and so is every command whose ``epoch`` is not
    this bridge run's (computed for a previous run). When the owner's token vanishes the bridge
    has no owner (its watchdog holds meanwhile) and the next live sender takes over. Not
    thread-safe: the node calls it under one lock.
    """

    def __init__(self, epoch: str) -> None:
        self.epoch = epoch
        self.owner = ""
        self._alive: set[str] = set()

    def appeared(self, sender: str) -> None:
        self._alive.add(sender)

    def alive(self, sender: str) -> bool:
        """Whether ``sender``'s token is known alive (its command may take an ownerless bridge)."""
        return sender in self._alive

    def vanished(self, sender: str) -> bool:
        """Forget a token; True if it was the owner's (ownership released)."""
        self._alive.discard(sender)
        if sender and sender == self.owner:
            self.owner = ""
            return True
        return False

    def admit(self, sender: str, epoch: str) -> str:
        """"" if a command of ``sender`` answering bridge run ``epoch`` is to be obeyed (taking
        ownership if there is no owner), else the reason it is refused."""
        if not INSTANCE_NAME.fullmatch(sender):
            return f"sender {sender[:40]!r}{'...' if len(sender) > 40 else ''} is not a valid controller instance name"
        if self.owner and sender != self.owner:
            return f"bridge owned by {self.owner}"
        if epoch != self.epoch:
            return f"command for bridge epoch {epoch[:40]!r}, this bridge run is {self.epoch!r}"
        if not self.owner:
            if sender not in self._alive:
                return f"sender {sender!r} has no liveliness token (xneck/alive/controller/<sender>)"
            self.owner = sender
        return ""


__all__ = ["Decision", "EStopEvent", "EStopHolders", "HoldForces", "HolderWords", "Inputs", "Ownership", "Safety", "SafetyConfig"]
