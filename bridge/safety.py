"""The bridge's safety rules as a pure state machine: no bus, no clock, no driver.

Each tick :class:`bridge.node.BridgeNode` gathers the facts of the tick in :class:`Inputs` (a valid
command received since the last tick, the age of the newest valid command, the e-stop events, the
encoder angles) and :meth:`Safety.step` answers with a :class:`Decision`: the drive state, the
forces to write, whether the drives must be enabled, the hold reason and what to log. The node
only moves data between the bus, this machine and the driver, so every rule below is tested
without a bus (tests/test_bridge_safety.py) and is the same for the robot, the twin and a replay.

Rules (the numbers live in :class:`SafetyConfig`):

Clamping
    Valid command forces are clamped to [f_min, f_max] (a cable must stay taut; counted).
Activation
    The drives start disabled (``inactive``: zero force). The first valid command enables them
    (``active``).
Watchdog
    When no valid command arrived for ``command_timeout_s`` (real time only), the forces ramp
    linearly over ``hold_ramp_ticks`` from those applied to the hold forces of the encoder angles
    at that moment (``drive = "hold"``, ``hold_reason`` says why). The next valid command resumes
    ``active``.
E-stop
    An engaged e-stop disables the drives (``disabled``, zero force) and every command is ignored
    until it is released; then the drives are ``inactive`` until the next valid command. The node
    turns an undecodable e-stop payload into an engaged event (fail safe).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

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


@dataclass(frozen=True)
class SafetyConfig:
    """The numbers of the rules. Forces in N, times in s."""

    n_motors: int
    f_min_N: float
    f_max_N: float
    command_timeout_s: float = 0.010  # no valid command for this long -> hold
    hold_ramp_ticks: int = 5  # ticks of the linear ramp to the hold forces
    max_force_step_N: float = 1.0  # after an enable: the most any force may change in one tick
    watchdog: bool = True  # off in lockstep, where time stands still without commands

    def __post_init__(self) -> None:
        f_min, f_max = self.f_min_N, self.f_max_N
        if not (math.isfinite(f_min) and math.isfinite(f_max) and 0.0 <= f_min < f_max):
            raise ValueError(f"the force range must be 0 <= f_min < f_max (N), got ({f_min}, {f_max})")
        if self.n_motors < 1 or self.hold_ramp_ticks < 1:
            raise ValueError(f"n_motors and hold_ramp_ticks must be >= 1, got {self.n_motors}, {self.hold_ramp_ticks}")
        if not (math.isfinite(self.max_force_step_N) and self.max_force_step_N > 0):
            raise ValueError(f"max_force_step_N must be a positive force (N), got {self.max_force_step_N}")
        if not (math.isfinite(self.command_timeout_s) and self.command_timeout_s > 0):
            raise ValueError(f"command_timeout_s must be a positive number of seconds, got {self.command_timeout_s}")


@dataclass(frozen=True)
class Inputs:
    """The facts of one tick.

    ``command_N``: the forces of a valid command received since the last step (None if none);
    ``source``: its sender's law, for the log. ``command_age_s``: age of the newest valid
    command (None if none ever arrived). ``estop``: e-stop events since the last step.
    ``theta_rad``: the encoder angles of the last read.
    """

    theta_rad: np.ndarray
    command_N: Sequence[float] | None = None
    source: str = ""
    command_age_s: float | None = None
    estop: Sequence[EStopEvent] = ()


@dataclass(frozen=True)
class Decision:
    """What the node must do this tick: enable or disable the drives (``enabled``), write
    ``force_N`` if enabled (zeros otherwise), publish ``drive`` and ``hold_reason``, and log
    ``events`` (``(logging level, message)`` pairs)."""

    drive: DriveState
    force_N: np.ndarray
    enabled: bool
    hold_reason: str = ""
    estop_engaged: bool = False
    estop_reason: str = ""
    events: tuple[tuple[int, str], ...] = field(default=())


class Safety:
    """The state machine of the module docstring. Not thread-safe: one caller (the bridge loop)."""

    def __init__(self, config: SafetyConfig, hold_forces: HoldForces) -> None:
        self.config = config
        self._hold_forces = hold_forces
        n = config.n_motors
        self.drive: DriveState = "inactive"
        self.hold_reason = ""
        self.estop_engaged = False  # latched from engage to release
        self.estop_reason = ""
        self.force = np.zeros(n)  # N, decided at the last step
        self._ramp_from = self._ramp_to = np.zeros(n)
        self._ramp_k = 0
        self._target = np.zeros(n)  # N, the clamped forces of the newest valid command
        self._bumpless = False  # after an enable, until the applied forces reach the command
        self.clamped = self.holds = 0
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
                self.drive, self.hold_reason, self.estop_reason = "disabled", "", reason
                self.estop_engaged = True
                self.force = np.zeros(self.config.n_motors)
                changed = True
                self._log(logging.WARNING, f"e-stop engaged ({reason}): drives disabled")
            elif not engaged and self.drive == "disabled":
                self.drive, self.estop_reason, self.estop_engaged = "inactive", "", False
                changed = True
                self._log(logging.WARNING, f"e-stop released ({reason}): drives inactive until the next valid command")
        return changed

    # -- one tick ------------------------------------------------------------------------------
    def step(self, inputs: Inputs) -> Decision:
        """Decide this tick's drive state and forces from its facts."""
        cfg = self.config
        was_disabled = self.drive == "disabled"
        self.apply_estop(inputs.estop)
        if self.drive == "disabled" or was_disabled:
            pass  # a command never outlives the e-stop, nor one that may predate its release
        elif inputs.command_N is not None:
            if self.drive == "inactive":
                self._log(logging.INFO, f"first valid command from {inputs.source!r}: drives enabled, "
                                        f"ramping at {cfg.max_force_step_N:g} N per tick")
            elif self.drive == "hold":
                self._log(logging.INFO, f"valid commands from {inputs.source!r} again: leaving hold, "
                                        f"ramping at {cfg.max_force_step_N:g} N per tick")
            if self.drive != "active":
                self._bumpless = True  # every enable starts from the forces applied now
            self.drive, self.hold_reason = "active", ""
            self._target = self.clamp(inputs.command_N)
        elif self.drive == "active" and cfg.watchdog and inputs.command_age_s is not None:
            age_s = inputs.command_age_s
            if age_s > cfg.command_timeout_s:
                self._start_hold(f"no valid command for {age_s * 1e3:.0f} ms "
                                 f"(timeout {cfg.command_timeout_s * 1e3:.0f} ms)", inputs.theta_rad)
        if self.drive == "active":
            self.force = self._towards_target()
        elif self.drive == "hold":
            self._ramp_k = min(self._ramp_k + 1, cfg.hold_ramp_ticks)
            w = self._ramp_k / cfg.hold_ramp_ticks
            self.force = (1.0 - w) * self._ramp_from + w * self._ramp_to
        if not self.enabled:
            self.force = np.zeros(cfg.n_motors)
        return Decision(drive=self.drive, force_N=self.force.copy(), enabled=self.enabled,
                        hold_reason=self.hold_reason if self.drive == "hold" else "",
                        estop_engaged=self.estop_engaged, estop_reason=self.estop_reason,
                        events=self.take_events())

    def take_events(self) -> tuple[tuple[int, str], ...]:
        """The log events since the last call (``(logging level, message)``), oldest first."""
        events, self._events = tuple(self._events), []
        return events

    def _towards_target(self) -> np.ndarray:
        """Bumpless enable: at most ``max_force_step_N`` per tick from the present forces until the
        command is reached; from then on commands pass through."""
        if not self._bumpless:
            return self._target.copy()
        step = self.config.max_force_step_N
        f = self.force + np.clip(self._target - self.force, -step, step)
        if np.array_equal(f, self._target):
            self._bumpless = False
            self._log(logging.INFO, "bumpless ramp done: commands pass through")
        return f

    def clamp(self, force_N: Sequence[float]) -> np.ndarray:
        """Forces within [f_min, f_max]; counts the commands that needed it. On plain floats: for
        four values numpy's clip costs about 20 µs, a large part of a Cortex-A8's tick budget
        (benchmarks/bridge_tick.py)."""
        lo, hi = self.config.f_min_N, self.config.f_max_N
        f = [float(x) for x in force_N]
        clamped = [min(max(x, lo), hi) for x in f]
        if clamped != f:
            self.clamped += 1
        return np.array(clamped)

    def hold_target(self, theta_rad: np.ndarray) -> np.ndarray:
        """Hold forces at the encoder angles, within [f_min, f_max]. A hold function that fails or
        answers nonsense never fails the hold itself: the present forces are kept."""
        try:
            f = np.asarray(self._hold_forces(np.asarray(theta_rad, dtype=float)), dtype=float)
        except Exception:  # any failure of the hold rule must not fail the hold itself
            log.exception("hold forces failed at θ = %s rad; holding the applied forces",
                          np.asarray(theta_rad).tolist())
            f = self.force
        if f.shape != self.force.shape or not np.all(np.isfinite(f)):
            f = self.force
        return np.clip(f, self.config.f_min_N, self.config.f_max_N)

    def _start_hold(self, reason: str, theta_rad: np.ndarray) -> None:
        self.drive, self.hold_reason = "hold", reason
        self.holds += 1
        self._ramp_from = self.force.copy()
        self._ramp_to = self.hold_target(theta_rad)
        self._ramp_k = 0
        self._log(logging.WARNING, f"hold: {reason}; ramping to {np.round(self._ramp_to, 2).tolist()} N "
                                   f"over {self.config.hold_ramp_ticks} ticks")

    def _log(self, level: int, message: str) -> None:
        self._events.append((level, message))


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
        if not INSTANCE_NAME.match(sender):
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


__all__ = ["Decision", "EStopEvent", "HoldForces", "Inputs", "Ownership", "Safety", "SafetyConfig"]
