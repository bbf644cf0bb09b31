"""The bridge as a bus process: a motor driver behind the safety rules, on the twin's topics.

Every tick (500 Hz) the node is a thin shell: bus in (the latest valid command, e-stop events) →
:meth:`bridge.safety.Safety.step` (the rules below, a pure state machine) → driver (enable or
disable, write the forces, step, read the encoders) → bus out (``MotorState`` with ``drive`` and
``hold_reason``; ``Health`` about once per second). The rules do not depend on any controller:

Commands
    A ``ForceCommand`` is valid when it decodes and every force lies in [0, f_max] with one force
    per motor (:func:`bridge.bus.check_force_command`), and it answers one of the newest states
    this run published: its ``stamp_s`` is that state's (the contract of ``ForceCommand``), one of
    the states of the last :data:`ANSWER_WINDOW_S` (50 ms, 25 at 500 Hz; at least twice the states
    a controller may leave unanswered before the watchdog holds: 10 had refused a loaded
    machine's late answers in bursts); anything else is counted as rejected (a
    command of a state gone, ``Health.rejected["command_stale_state"]``) and never moves a motor,
    so a command path that lags ends in the watchdog's hold (audit of 2026-11-29: a command
    answering a state 5 s old, or one 1e9 s ahead, had been obeyed). A command answering an older
    state than its sender's last accepted one (delayed, re-ordered, replayed) is refused too: it
    would move the cables back to older forces; the same state answered again is valid (the
    controller's own hold when no state reaches it). Valid forces are clamped to [f_min, f_max] (a cable must stay taut).
Activation
    The drives start disabled (``inactive``: angles published, zero force). The first valid
    command enables them (``active``).
Watchdog
    Real time: when no valid command arrived for ``command_timeout_s`` (10 ms) and the states
    published meanwhile went unanswered (5 at 500 Hz: a stall of the CPU that the bridge shares
    with the controller is not a silent controller), the forces ramp linearly, over
    ``hold_ramp_s`` (10 ms, counted in ticks), from those applied to the hold forces Z f = g(α̂)
    with every cable at t_min (:func:`controller.laws.hold_forces`) at the rigid-cable estimate α̂
    from the encoders (eq. 33, :func:`twin.model.estimation.alpha_hat_3`);
    ``drive = "hold"`` and ``hold_reason`` says why. The next valid command resumes ``active``.
    The hold forces are never computed in a tick (:class:`HoldWorker` keeps them fresh on a
    thread of its own, from readings :class:`bridge.motor_speed.MotorSpeed` trusts: none within 5
    ticks of an encoder glitch); without fresh ones of these angles (read at most 0.1 s before,
    within 0.2 rad of the angles read now plus what the motors turn meanwhile at their speed) the
    hold keeps the applied forces until they come, then moves to them at ``max_force_step_N`` per
    tick.
    Lockstep (twin only): one tick per new command, so simulated time stands still without
    commands and nothing can drift; the watchdog is off there.
E-stop
    ``EStop(engaged=true)`` on ``xneck/estop`` (the console's button publishes the same) disables
    the drives on the next tick (``drive = "disabled"``, zero force) and commands are ignored until
    ``EStop(engaged=false)``; then the drives are ``inactive`` until the next valid command. A
    payload on ``xneck/estop`` that cannot be decoded counts as engaged (fail safe). Whoever
    engages also holds a liveliness token (``xneck/estop/engaged/<holder>``) until it releases: the
    node asks for those alive before its first tick and follows them after, so a bridge started or
    relinked under an engaged e-stop is latched too, and a release acts only when no holder but its
    sender is left (:class:`bridge.safety.EStopHolders`, docs/safety.md).
    An engage is never lost to the messages after it (a queue of 64 had dropped it under a
    flood): the tick after it shows it, and releases that came after it apply from the next tick on.
Encoder reads
    A read of the encoders that fails (``OSError``: the board library's, a transient eQEP or bus
    error) does not end the loop: the tick keeps the last angles, publishes no state (none was
    measured; nothing new can answer it, so the forces stay those the newest command set) and
    feeds neither the speeds nor the hold worker. Counted (``Health.rejected["encoder_read"]``),
    logged at most once a second. More than ``max_read_errors`` (3) in a row: the tick raises as
    before, the loop ends and :meth:`BridgeNode.shutdown` disables the drives, the reason in the
    log and in the last ``Health``'s ``last_reject_reason``. One failed read had dropped every
    cable from 30 N to 0 (audit of 2026-11-29).
Driver messages
    What the driver publishes beside the states (the twin's ``Truth`` and α_IP) carries this run's
    ``epoch`` as its Zenoh attachment (:data:`bridge.session.RUN_PREFIX`): a ``Truth`` has no
    identity field, and a stray twin's was archived beside the campaign twin's.
Exit
    :meth:`BridgeNode.shutdown` (called from ``finally`` on Ctrl-C, SIGTERM or an exception, and
    from ``atexit`` as a backstop) disables the drives and publishes a last ``MotorState`` with
    ``drive = "disabled"``. A SIGKILL cannot be caught: on hardware only the ESCONs' own enable
    logic remains.
Clock
    The bridge serves its stamp clock (the driver's ``stamp_s()``, that of every ``MotorState``) as
    the queryable ``xneck/bridge/clock`` (:class:`bridge.clock_service.ClockService`), so a camera
    on another machine's clock can put its stamps on the bridge's (docs/camera.md, "One clock").
Loop watchdog
    Real time, ``loop_stall_s`` > 0 (``xneck bridge``: 0.5 s): when the loop makes no tick for
    that long while the process runs (hung in a call, a deadlock, an endless loop: the rules
    above run in the loop and hang with it), a thread of its own trips the driver (every drive
    off, latched) and ends the process with code 70 (:mod:`bridge.loop_watchdog`). Under systemd
    the loop also pings the unit's watchdog (:class:`bridge.runtime.SystemdNotify`).
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import faulthandler
import logging
import math
import os
import sys
import threading
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from bridge import bus
from bridge.clock_service import ClockService
from bridge.driver import Driver, Lifecycle
from bridge.estop_latch import LatchFile, read_latch
from bridge.log_limit import LogLimit
from bridge.loop_watchdog import MIN_STALL_S, LoopWatchdog, drives_off_and_exit
from bridge.motor_speed import MotorSpeed
from bridge.runtime import SystemdNotify, arrange_thread, no_core_dump, raise_loop_thread, take_loop_priority
from bridge.safety import RELEASE_TOKEN_WAIT_S, EStopHolders, HoldForces, Inputs, Ownership, Safety, SafetyConfig
from bridge.session import (
    BusPublisher,
    estop_holder_of,
    liveliness_token,
    payload_of,
    publisher,
    run_attachment,
    subscribe_latest,
)

log = logging.getLogger("xneck.bridge")
#: s of states a command may answer at least (:class:`BridgeNode`, "Commands"): a command path
#: that lags more than this (a buffering link) ends in the watchdog's hold.
ANSWER_WINDOW_S = 0.05
#: s during which a state names the last command refused as answering no recent state.
STALE_NOTE_S = 1.0

#: The real-time loop's GIL switch interval (s), instead of Python's 5 ms: a thread computing in
#: Python (the hold worker, a Zenoh callback) hands the GIL to a waking tick within this.
SWITCH_INTERVAL_S = 2e-4

#: s the start waits for the answer to "which e-stop tokens are alive": Zenoh answers a liveliness
#: query from the tokens it knows (0.1 ms on loopback), so this bounds only a sick session.
ESTOP_QUERY_S = 2.0
#: Holders seen letting go while that query runs, at most (a flood stops recording them); past
#: it, the query's answer still latches for every holder it names but those recorded going.
TOKENS_GONE_MAX = 1024


@dataclass(frozen=True)
class BridgeConfig:
    """Safety and timing of the bridge. Times in s (wall clock unless said otherwise)."""

    command_timeout_s: float = 0.010  # no valid command for this long -> hold (real time only)
    hold_ramp_s: float = 0.010  # duration of the ramp to the hold forces, counted in ticks
    max_force_step_N: float = 1.0  # after any enable: the most a force may change per tick (N)
    # While active: the most a force may change per second (N/s; inf: no bound), counted in ticks:
    # the computed-torque law's own bound (controller.laws.LawConfig.force_rate_max_N_s).
    max_force_rate_N_s: float = 5000.0
    lockstep: bool = False  # one tick per new command (twin driver only)
    republish_s: float = 0.05  # lockstep: re-publish the waiting state this often
    idle_timeout_s: float | None = None  # lockstep: stop after this long without a command
    startup_timeout_s: float | None = None  # lockstep: the limit before the first command (default: idle's)
    health_period_s: float = 1.0
    max_ticks: int | None = None  # stop after this many ticks (None: until stopped)
    instance: str = ""
    hold_tolerance_rad: float = 0.2  # angles closer than this to the last computed share its hold forces
    hold_refresh_s: float = 0.02  # the hold worker computes at most this often
    hold_max_age_s: float = 0.1  # hold forces of angles older than this are stale (a hold keeps the forces)
    # Real time: no tick for this long while the process runs -> drives tripped off, exit 70 (0: off,
    # for in-process callers such as tests, whose process it would end; `xneck bridge`: 0.5 s).
    loop_stall_s: float = 0.0
    # N·s/rad on each motor's speed while holding (bridge.safety, "Hold damping"; 0: off)
    hold_damping_N_s_rad: float = 1.0
    # encoder reads that may fail (OSError) in a row, each tick then keeping the last angles; one
    # more ends the loop, drives off (module docstring, "Encoder reads"). 3: 6 ms at 500 Hz.
    max_read_errors: int = 3
    # The e-stop latch file (bridge.estop_latch; None: none): a bridge restarted under an engaged
    # e-stop whose holder is gone starts latched. `xneck bridge --driver beaglebone`: on by default.
    estop_latch_path: Path | None = None

    def __post_init__(self) -> None:
        for name in ("command_timeout_s", "republish_s", "health_period_s", "max_force_step_N",
                     "hold_tolerance_rad", "hold_refresh_s", "hold_max_age_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                unit = {"N": "N", "rad": "rad"}.get(name.rsplit("_", 1)[-1], "s")
                raise ValueError(f"{name} must be a positive number ({unit}), got {value}")
        if not self.max_force_rate_N_s > 0:  # inf allowed: no bound; NaN fails the comparison
            raise ValueError(f"max_force_rate_N_s must be a positive rate (N/s) or inf, got {self.max_force_rate_N_s}")
        if self.max_read_errors < 0:
            raise ValueError(f"max_read_errors must be >= 0, got {self.max_read_errors}")
        if not (math.isfinite(self.hold_ramp_s) and self.hold_ramp_s >= 0):
            raise ValueError(f"hold_ramp_s must be >= 0 s, got {self.hold_ramp_s}")
        if not (self.loop_stall_s == 0 or (math.isfinite(self.loop_stall_s) and self.loop_stall_s >= MIN_STALL_S)):
            raise ValueError(f"loop_stall_s must be 0 (off) or at least {MIN_STALL_S} s, got {self.loop_stall_s}")


def _holders_text(holders: list[str], n: int = 5) -> str:
    """The holders named in a log line: the first ``n`` and how many more (any peer may hold)."""
    return ", ".join(holders[:n]) + (f" and {len(holders) - n} more" if len(holders) > n else "")


def _bounded(text: str, n: int = 200) -> str:
    """A string from the bus, cut to ``n`` characters and without control characters
    (:func:`bridge.bus.plain_text`): it goes into every state and the log."""
    return bus.plain_text(text, n)


def _demote_this_thread() -> None:
    """Take the calling thread out of real-time scheduling (Linux: per thread). Under the robot's
    SCHED_FIFO (docs/bridge.md) a thread computing for 20-50 ms would otherwise keep a single core
    from the loop until it blocks; as SCHED_OTHER the loop preempts it whenever it is runnable.
    Not niceness 19 as well: this thread holds the GIL while it computes, and on a loaded machine a
    nice-19 thread can wait long for a CPU with the GIL in hand, the loop waiting for it (priority
    inversion; suspected first for the 0.5 s stalls of 2026-11-26, which were Zenoh's threads at
    the loop's FIFO priority instead: :func:`bridge.runtime.raise_loop_thread`)."""
    tid = threading.get_native_id()
    arrange_thread(None)  # and out of a real-time priority the process takes later
    with contextlib.suppress(AttributeError, OSError):  # not Linux, or not allowed: carry on as is
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))


class HoldWorker:
    """The hold forces of the latest encoder angles, kept ready off the tick (issue 20).

    The hold rule (eq. 33 + eqs. 63-65) costs 1-3 ms in plain Python here and 20-50 ms on the
    BeagleBone's Cortex-A8, 10-25 periods: the tick that starts a hold must find it done. The
    tick hands over its angles when the encoders' reading is trusted (:meth:`offer`, one attribute
    store) and asks :meth:`ready` with the angles it read: the forces computed from angles read at
    most ``max_age_s`` ago and near these, else None (stale forces, or those of other angles, are
    never used; a hold then keeps the applied forces until fresh ones come). A thread of low priority
    wakes every ``poll_s``: when the angles moved more than ``tolerance_rad`` (any motor) from
    those of its last computation it computes again, at most once per ``refresh_s``; otherwise
    the forces it has still describe the angles and it only renews their time, so a still neck
    costs nothing. Fresh thus means at most ``poll_s + refresh_s`` plus one computation old while
    the neck moves: about 25 ms here, 40-80 ms on the Cortex-A8, well within ``max_age_s``.

    The tolerance, 0.2 rad at the motor shaft, is 0.16 mm of cable (r_d/R = 0.8 mm/rad): less
    than 0.4° of α̂ and 0.4 N of hold force on the prototype, below the 1 N a force may change in
    one tick. A hold rule that fails or answers nonsense leaves no forces (logged at most every
    10 s) and is tried again once the angles move.
    """

    LOG_PERIOD_S = 10.0

    def __init__(self, hold_forces: HoldForces, n_motors: int, tolerance_rad: float = 0.2,
                 refresh_s: float = 0.02, max_age_s: float = 0.1, poll_s: float = 0.01) -> None:
        self._hold_forces = hold_forces
        self.n_motors = n_motors
        self.tolerance_rad, self.refresh_s, self.max_age_s, self.poll_s = tolerance_rad, refresh_s, max_age_s, poll_s
        self._theta: list[float] | None = None  # the latest angles offered (a new list each time)
        self._tried: list[float] | None = None  # the angles of the last computation
        # (monotonic time of the angles, forces, the angles computed at)
        self._ready: tuple[float, list[float], list[float]] | None = None
        self.computed = self.failed = 0
        self._failures_logged = LogLimit(self.LOG_PERIOD_S)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def offer(self, theta_rad: list[float]) -> None:
        """The latest encoder angles (rad); the list must not be changed afterwards."""
        self._theta = theta_rad

    def ready(self, now_s: float, theta_rad: Sequence[float] | None = None,
              speed_rad_s: Sequence[float] | None = None) -> list[float] | None:
        """Hold forces (N) of angles read at most ``max_age_s`` before ``now_s`` (time.monotonic),
        else None. With ``theta_rad`` (the angles read now, rad): None as well unless the forces'
        angles are within ``tolerance_rad`` of them, plus what each motor turns at ``speed_rad_s``
        (rad/s, the low-passed speeds; none: 0) in the forces' age. Fresh forces of other angles
        (an encoder glitch the worker was shown, audit of 2026-11-29: 70.6 N on a cable for a whole
        hold) are not these angles' forces; those of a neck that moves on are."""
        ready = self._ready  # one read: the worker replaces the triple whole
        if ready is None:
            return None
        age = now_s - ready[0]
        if age > self.max_age_s:
            return None
        if theta_rad is not None:
            tol = self.tolerance_rad
            speed = speed_rad_s if speed_rad_s is not None and len(speed_rad_s) == len(theta_rad) else None
            for k, (x, y) in enumerate(zip(theta_rad, ready[2], strict=True)):
                v = speed[k] if speed is not None else 0.0
                if not abs(x - y) <= tol + abs(v) * max(age, 0.0):  # NaN: not within
                    return None
        return ready[1]

    def compute(self, theta_rad: list[float]) -> bool:
        """Compute the hold forces at ``theta_rad`` on the calling thread; True if they are ready."""
        self._tried, read_s = theta_rad, time.monotonic()
        try:
            f = np.asarray(self._hold_forces(np.array(theta_rad, dtype=float)), dtype=float)
            if f.shape != (self.n_motors,) or not np.all(np.isfinite(f)):
                raise ValueError(f"the hold rule answered {f.tolist()} N")
        except Exception as exc:  # noqa: BLE001 - a failing hold rule must not fail a hold (nor this thread)
            self._ready = None
            self.failed += 1
            if self._failures_logged.allow() is not None:  # the count says the rest
                log.error("hold forces failed at θ = %s rad (%s: %s; %d failures): a hold there keeps the "
                          "applied forces", [round(x, 3) for x in theta_rad], type(exc).__name__, exc, self.failed)
            return False
        self._ready = (read_s, f.tolist(), list(theta_rad))
        self.computed += 1
        return True

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="xneck-hold-forces", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def _run(self) -> None:
        _demote_this_thread()
        last = -math.inf
        while not self._stop.wait(self.poll_s):
            theta, tried, ready = self._theta, self._tried, self._ready
            if theta is None:
                continue
            now = time.monotonic()
            if tried is not None and _within(theta, tried, self.tolerance_rad):
                if ready is not None:
                    self._ready = (now, ready[1], ready[2])  # still these angles' forces
            elif now - last >= self.refresh_s:
                last = now
                self.compute(theta)


def _log_events(events: Sequence[tuple[int, str]]) -> None:
    for level, message in events:
        log.log(level, "%s", message)


def _within(a: Sequence[float], b: Sequence[float], tol: float) -> bool:
    """Every |a_i - b_i| <= tol (False for a NaN)."""
    return all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


class BridgeNode:
    """A :class:`bridge.driver.Driver` on the bus with the safety rules of the module docstring.

    Drive it with :func:`run_realtime` or :func:`run_lockstep`, or call :meth:`tick` yourself
    (tests do, to check what happens within one tick). Always end with :meth:`shutdown`.
    """

    def __init__(self, session: zenoh.Session, driver: Driver, hold_forces: HoldForces,
                 f_range_N: tuple[float, float], config: BridgeConfig = BridgeConfig()):
        f_min, f_max = (float(x) for x in f_range_N)
        if driver.state is Lifecycle.UNCONFIGURED:
            driver.configure()
        self.driver, self.config = driver, config
        self.session = session
        self.instance = config.instance or f"bridge-{uuid.uuid4().hex[:6]}"
        self.epoch = uuid.uuid4().hex[:12]  # this run: commands for another run are refused
        self._run = run_attachment(self.epoch)  # on its driver's messages (the twin's truth): their run
        n = driver.n_motors
        self.dt = driver.dt
        self.safety = Safety(SafetyConfig(
            n_motors=n, f_min_N=f_min, f_max_N=f_max, command_timeout_s=config.command_timeout_s,
            # the states a controller answering on time would have answered within the timeout
            command_timeout_states=max(1, int(config.command_timeout_s / self.dt + 1e-9)),
            hold_ramp_ticks=max(1, round(config.hold_ramp_s / self.dt)), max_force_step_N=config.max_force_step_N,
            max_active_step_N=config.max_force_rate_N_s * self.dt, watchdog=not config.lockstep,
            hold_damping_N_s_rad=config.hold_damping_N_s_rad))
        self.f_min, self.f_max = f_min, f_max
        self.force = np.zeros(n)  # N, what the drives apply now
        # Holds need the watchdog: lockstep never holds. The first hold forces (and whatever the
        # model compiles or loads) are computed here, so a hold is ready from the first tick on.
        self.hold = HoldWorker(hold_forces, n, config.hold_tolerance_rad, config.hold_refresh_s, config.hold_max_age_s)
        if not config.lockstep:
            self.hold.compute(driver.read().tolist())
            self.hold.start()

        # Ownership is decided where commands arrive (Zenoh's callback thread), so a refused
        # command never replaces the owner's latest one.
        self._owner_lock = threading.Lock()
        self.ownership = Ownership(self.epoch)
        self._controllers = session.liveliness().declare_subscriber(
            f"{bus.PREFIX}/alive/controller/*", self._on_controller, history=True)

        def check(cmd: bus.ForceCommand) -> None:
            bus.check_force_command(cmd, n, 0.0, self.f_max)
            answered = self._answered(cmd.stamp_s) if cmd.epoch == self.epoch else None
            if cmd.epoch == self.epoch and answered is None:
                # (another run's command: refused by its epoch below, the clearer reason)
                self.commands_stale += 1
                self._stale_seen = time.monotonic()
                raise bus.BusDecodeError(
                    f"ForceCommand from {cmd.sender!r}: answers no state of the last {len(self._state_stamps)} this "
                    f"bridge published (stamp_s {cmd.stamp_s!r}; newest {self.last_state_stamp_s!r})")
            with self._owner_lock:
                before = self.ownership.owner
                if answered is not None and cmd.sender == self._last_sender and answered < self._last_answered:
                    # A command delayed, re-ordered or replayed: it would move the cables back to
                    # older forces, and its arrival reset the watchdog (review of session 53). The
                    # same state answered again stays valid: the controller's own stale-state hold.
                    reason = (f"answers an older state than its last accepted command (state {answered}, "
                              f"after {self._last_answered}): delayed or replayed")
                else:
                    reason = self.ownership.admit(cmd.sender, cmd.epoch)
                if not reason and answered is not None:
                    self._last_sender, self._last_answered = cmd.sender, answered
            if reason:
                raise bus.BusDecodeError(f"ForceCommand from {cmd.sender!r}: {reason}")
            if before != cmd.sender:
                log.info("controller %r owns the bridge now", cmd.sender)

        # The stamps of the newest states published (module docstring, "Commands"): a fixed list
        # whose items the loop replaces and the callback reads (no lock; no item ever missing).
        # At least ANSWER_WINDOW_S of states: under a loaded machine's bursts a controller answered
        # 10-20 states late, and 10 states (2 × the watchdog's) had refused 11 % of its commands (a
        # browser test's stack, CI of session 40): holds where the watchdog saw none.
        n_stamps = max(2 * self.safety.config.command_timeout_states, round(ANSWER_WINDOW_S / self.dt))
        self._state_stamps: list[float | None] = [None] * n_stamps
        # Each one's number (``seq`` of the state), at the same place: a command's order is that of
        # the states it answers, not of the stamps (a wall clock may step back).
        self._state_numbers: list[int] = [0] * n_stamps
        self._stamp_k = 0
        self._last_sender, self._last_answered = "", 0  # the newest accepted command's sender and state
        # After a stall of the loop: the first state published after it (its number); a command
        # answering an older one was computed before the resume (:meth:`tick`).
        self._resume_number = 0
        self._stall_s = config.command_timeout_s  # a hold-up past it is a stall (Safety's own rule)
        self.commands_stale = 0  # commands refused for answering no recent state
        self._stale_seen = -math.inf  # monotonic s of the last command refused so
        self.last_state_stamp_s = math.nan  # s, the stamp of the newest state published
        self.commands = subscribe_latest(session, bus.MOTOR_COMMAND, validate=check)
        self._estop_lock = threading.Lock()
        self._estop_events: collections.deque[tuple[bool, str]] = collections.deque(maxlen=64)
        # Lines any peer can cause, one a second at most (bridge.log_limit).
        self._refusals_logged, self._waits_logged, self._tokens_logged = LogLimit(), LogLimit(), LogLimit()
        # The reason of the newest engage since the last tick: the bounded queue drops its oldest
        # events, and an engage followed by 64 more messages had been lost (audit of 2026-11-29).
        self._estop_engage: str | None = None
        self.estop_received = self.estop_rejected = 0
        # An engaged e-stop's holders (bridge.safety, "E-stop holders"): followed from now on, and
        # asked for before the first tick, so this run starts latched if one is alive. Made before
        # either subscriber, whose callbacks use them: an e-stop arriving in between was lost to
        # an AttributeError (review of session 53).
        self.estop_holders = EStopHolders()
        # The holders whose token the subscriber saw go while the start's query ran: its answer
        # about them may be older (None once the query is done; a flood stops recording).
        self._tokens_gone: set[str] | None = set()
        self._estop_sub = session.declare_subscriber(bus.ESTOP, self._on_estop)
        self._estop_tokens = session.liveliness().declare_subscriber(bus.ESTOP_ENGAGED_ALL, self._on_estop_token,
                                                                    history=True)
        self._latch_for_holders(session)
        self.latch_file: LatchFile | None = None
        self._latched_on_disk = False
        if config.estop_latch_path is not None:
            self._latch_from_disk(Path(config.estop_latch_path))
        self._state_pub = publisher(session, bus.MOTOR_STATE, block=config.lockstep)
        self._extra_pubs: dict[str, BusPublisher] = {}
        self._health = session.declare_publisher(bus.health_key("bridge", self.instance))
        self._token = liveliness_token(session, "bridge", self.instance)
        # The stamp clock of every state, served to whoever asks (a camera on another machine's
        # clock): read on a Zenoh thread, nothing of the loop's state touched but the stamp.
        self.clock = ClockService(session, driver.stamp_s, self.epoch, self.instance)

        self.mode: bus.DriveState = self.safety.drive  # "disabled" if started under an engaged e-stop
        self.hold_reason = ""
        self.theta = driver.read()
        self._theta_list = self.theta.tolist()  # the same angles as plain floats (the hold, the state)
        self.speed = MotorSpeed(n, self.dt)  # the motors' speeds, for a hold's damping (bridge.safety)
        self.speed.update(self._theta_list)
        self._consumed_ns = 0  # receive time of the newest command already shown to the safety rules
        # States published since the newest valid command arrived: the watchdog holds only once the
        # controller has had states to answer, not after a stall of the CPU it shares with the bridge.
        self._unanswered = 0
        self._source_key: tuple[str, str] = ("", "")
        self._source = ""
        self.ticks = self.overruns = 0
        self.periods_skipped = 0  # real-time periods in which no tick started (:func:`pace`)
        self.read_errors = 0  # encoder reads that failed (module docstring, "Encoder reads")
        self._read_errors_in_row = 0
        self._read_errors_logged = LogLimit(1.0)
        self.fault = ""  # why the loop ended, for the last Health (a read failure too many)
        self.tick_max_s = 0.0
        self._seq = {"state": 0, "health": 0}
        self._started = time.monotonic()
        self._closed = False
        atexit.register(self._atexit)

    @property
    def owner(self) -> str:
        with self._owner_lock:
            return self.ownership.owner

    @property
    def clamped(self) -> int:
        return self.safety.clamped

    @property
    def holds(self) -> int:
        return self.safety.holds

    @property
    def rate_limited(self) -> int:
        """Ticks whose active command moved the forces faster than ``max_force_rate_N_s``."""
        return self.safety.rate_limited

    @property
    def estop_reason(self) -> str:
        return self.safety.estop_reason

    # -- inputs ---------------------------------------------------------------------------------
    def _on_controller(self, sample: zenoh.Sample) -> None:
        # Zenoh callback thread: a controller's liveliness token appeared or vanished.
        try:
            _kind, name = bus.parse_liveliness_key(str(sample.key_expr))
        except ValueError:
            return
        with self._owner_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.ownership.appeared(name)
                released = False
            else:
                released = self.ownership.vanished(name)
        if released:
            log.warning("owner %r is gone: ownership released (the watchdog holds until a new owner)", name)

    def _on_estop(self, sample: zenoh.Sample) -> None:
        # Zenoh callback thread: decode and queue only; the loop acts on it within one tick.
        try:
            msg = bus.decode(bus.EStop, payload_of(sample, bus.EStop))
            event = (msg.engaged, _bounded(msg.reason) or "e-stop")
            valid = True
        except bus.BusDecodeError as exc:
            event = (True, _bounded(f"malformed e-stop message: {exc.reason}"))
            valid = False
        sender = _bounded(estop_holder_of(sample), 64)  # outside the lock: the tick takes it
        with self._estop_lock:
            # Queue before counting: whoever sees the count (tests, health) may rely on the next tick
            # applying the event, and the tick looks at the queue without the lock. A release is
            # refused while another e-stop holder's token is alive (bridge.safety.EStopHolders).
            applied = self.estop_holders.message(event, sender)
            if applied is not None:
                self._queue_estop(applied)
            waits = applied is None and self.estop_holders.waits_for(sender)
            self.estop_received += 1
            self.estop_rejected += 0 if valid else 1
        if applied is not None:
            return
        # Refused or waiting: the holders are named only in a line logged (a sort of 2000 strangers'
        # tokens under the lock, per message of a flood, held the tick up to 6.6 ms: review of
        # session 42), and a holder's own waiting release is not hidden by strangers' refusals.
        limit = self._waits_logged if waits else self._refusals_logged
        if (n := limit.allow()) is None:
            return
        with self._estop_lock:
            held = list(self.estop_holders.holders)
        who = _holders_text(sorted(held))
        if waits:
            log.info("e-stop release (%s) of %s: acts once its token is gone (still held: %s)%s", event[1], sender,
                     who, LogLimit.tail(n))
        else:
            log.warning("e-stop release (%s) refused: %s still hold the e-stop engaged%s", event[1], who,
                        LogLimit.tail(n))

    def _queue_estop(self, event: tuple[bool, str]) -> None:
        """Queue an e-stop event for the next tick (under ``_estop_lock``); an engage is also kept
        apart, so that no overflow of the queue removes it (:meth:`_take_estop_events`)."""
        self._estop_events.append(event)
        if event[0]:
            self._estop_engage = event[1]

    def _on_estop_token(self, sample: zenoh.Sample) -> None:
        # Zenoh callback thread: an e-stop holder's token appeared (engaged) or vanished.
        try:
            holder = _bounded(bus.parse_estop_token_key(str(sample.key_expr)), 64)
        except ValueError:
            return
        with self._estop_lock:
            expired = ""
            if self._tokens_gone is not None and len(self._tokens_gone) < TOKENS_GONE_MAX:
                if sample.kind == zenoh.SampleKind.PUT:
                    self._tokens_gone.discard(holder)
                else:
                    self._tokens_gone.add(holder)
            if sample.kind == zenoh.SampleKind.PUT:
                self._queue_estop(self.estop_holders.appeared(holder))
            elif (released := self.estop_holders.vanished(holder)) is not None:
                self._queue_estop(released)  # its own release came before its token went
            else:
                expired, self.estop_holders.expired = self.estop_holders.expired, ""
        if expired:
            log.warning("e-stop release (%s) of %r not applied: its token went more than %g s after it; release "
                        "again", expired, holder, RELEASE_TOKEN_WAIT_S)
        elif sample.kind != zenoh.SampleKind.PUT and (n := self._tokens_logged.allow()) is not None:
            log.info("e-stop holder %r let go (a latched e-stop stays until it is released)%s", holder, LogLimit.tail(n))

    def _latch_from_disk(self, path: Path) -> None:
        """Start latched if the e-stop latch file says so (:mod:`bridge.estop_latch`), and keep
        it up to date from now on (:meth:`_follow`)."""
        reason = read_latch(path)
        self.latch_file = LatchFile(path)
        self._latched_on_disk = reason is not None
        if reason is not None:
            log.warning("e-stop latched before this bridge started (%s: %s): the drives stay disabled until "
                        "a release", path, reason)
            self.safety.apply_estop([(True, _bounded(f"e-stop latched before this bridge started: {reason}"))])
            _log_events(self.safety.take_events())

    def _latch_for_holders(self, session: zenoh.Session) -> None:
        """Start latched if an e-stop token is alive (asked, not waited for from the subscriber:
        its history may come after the first commands)."""
        holders = []
        try:
            for reply in session.liveliness().get(bus.ESTOP_ENGAGED_ALL, timeout=ESTOP_QUERY_S):
                token = reply.ok  # None: an error reply
                if token is not None:
                    with contextlib.suppress(ValueError):  # not a token's key
                        holders.append(_bounded(bus.parse_estop_token_key(str(token.key_expr)), 64))
        except Exception as exc:  # noqa: BLE001 - the subscriber still follows the tokens
            log.error("could not ask for the e-stop's holders (%s: %s): following them as they come", type(exc).__name__, exc)
        with self._estop_lock:
            # A holder the subscriber saw go meanwhile stays gone: one that let go between the
            # query's answer and now had been put back for good, and every release refused until a
            # restart (review of session 53). Past the cap (a flood of tokens letting go), the answer
            # still latches for every holder it names but those recorded going: dropped whole, a
            # holder alive had been left to the subscriber's history, which may come after the first
            # commands (review of session 53's diff). A wrong latch is the safe side.
            gone, self._tokens_gone = self._tokens_gone or set(), None
            if len(gone) >= TOKENS_GONE_MAX:
                log.warning("e-stop: %d or more holders let go while this bridge asked for them; latched for "
                            "every holder the answer named (a release of one gone needs a restart)", TOKENS_GONE_MAX)
            events = [self.estop_holders.appeared(h) for h in sorted(set(holders)) if h not in gone]
        if events:
            self.safety.apply_estop(events)
            _log_events(self.safety.take_events())

    def _take_estop_events(self) -> list[tuple[bool, str]]:
        """The e-stop events to apply now, in order. After an engage, only the events up to the
        newest engage (the engage itself if the queue dropped it): the releases after it stay
        queued for the next tick, so at least one state shows every engage (drives disabled) and
        no flood of messages after it can remove it."""
        with self._estop_lock:
            events = list(self._estop_events)
            self._estop_events.clear()
            engage, self._estop_engage = self._estop_engage, None
            if engage is None:
                return events
            last = max((k for k, (engaged, _) in enumerate(events) if engaged), default=-1)
            self._estop_events.extend(events[last + 1:])  # released on the next tick at the earliest
        return events[:last + 1] if last >= 0 else [(True, engage)]

    def process_estop(self) -> bool:
        """Apply queued e-stop events now (between ticks); True if the drive state changed."""
        changed = self.safety.apply_estop(self._take_estop_events())
        self._follow()
        _log_events(self.safety.take_events())
        return changed

    def _follow(self) -> None:
        """Make the driver and the published state follow the safety rules' decision. The
        decision's log lines come after (formatting and writing them takes longer than a tick's
        work: the drives and the bus go first)."""
        if self.latch_file is not None and self.safety.estop_engaged != self._latched_on_disk:
            # Handed over before the drives move: a disable that raises or hangs (the loop watchdog
            # then ends the process) had left no latch on disk (review of session 53).
            self._latched_on_disk = self.safety.estop_engaged  # written off the tick (bridge.estop_latch)
            self.latch_file.set(self._latched_on_disk, self.safety.estop_reason)
        if self.safety.enabled:
            if self.driver.state is not Lifecycle.ACTIVE:
                self.driver.activate()
        elif self.driver.state is Lifecycle.ACTIVE:
            self.driver.deactivate()
        if self.safety.drive == "inactive" and self.mode == "disabled":
            # Released: only commands received after the release may enable the drives again.
            self._consumed_ns = max(self._consumed_ns, self.commands.latest_with_time()[1])
        self.mode = self.safety.drive
        self.hold_reason = self.safety.hold_reason if self.mode == "hold" else ""
        if self.mode in ("inactive", "hold") and (stale := self._stale_note()):
            self.hold_reason = f"{self.hold_reason}; {stale}" if self.hold_reason else stale
        if not self.safety.enabled:
            self.force = np.zeros(self.driver.n_motors)

    def _source_text(self, cmd: bus.ForceCommand) -> str:
        """``sender (law)`` of a command, for the log: formatted once per sender and law, not per
        tick (the tick's budget is a few µs of Python, benchmarks/bridge_tick.py)."""
        key = (cmd.sender, cmd.source)
        if key != self._source_key:
            self._source_key, self._source = key, f"{cmd.sender} ({_bounded(cmd.source, 64)})"
        return self._source

    # -- one period -----------------------------------------------------------------------------
    def tick(self, held_up_s: float = 0.0) -> None:
        """Bus in, safety rules, driver, bus out: one control period. Nothing here may cost more
        than a few µs on this machine (benchmarks/bridge_tick.py): the model is not called.
        ``held_up_s``: how long commands went unread before this tick (:func:`run_realtime` knows
        it; a stalled process or CPU): past the command timeout the safety rules ramp the command
        computed meanwhile, until one that answers a state published after the stall."""
        t0 = time.perf_counter()
        # An empty queue is read without its lock: an event appended meanwhile waits one tick,
        # as one arriving just after the read would.
        estop = self._take_estop_events() if self._estop_events else ()
        cmd, recv_ns = self.commands.latest_with_time()
        fresh = cmd if cmd is not None and recv_ns > self._consumed_ns else None
        if recv_ns > self._consumed_ns:
            self._consumed_ns, self._unanswered = recv_ns, 0
        if held_up_s > self._stall_s:
            self._resume_number = self._seq["state"] + 1  # the state this tick publishes
        # A command after a stall counts as the controller's answer to it only if it answers a
        # state published since: a late answer to one before had ended the ramp (review of session
        # 53). Looked up only while a stall's ramp may wait for one (a list scan).
        after_resume = fresh is None or not self._resume_number or \
            (self._answered(fresh.stamp_s) or 0) >= self._resume_number
        decision = self.safety.step(Inputs(
            command_N=fresh.force_N if fresh is not None else None,
            source=self._source_text(fresh) if fresh is not None else "",
            command_age_s=(time.monotonic_ns() - recv_ns) * 1e-9 if cmd is not None else None, estop=estop,
            sender=fresh.sender if fresh is not None else "", resumed_after_s=held_up_s,
            command_after_resume=after_resume,
            # a tick with a valid command neither starts nor continues a hold
            hold_N=self.hold.ready(time.monotonic(), self._theta_list, self.speed.rad_s) if fresh is None else None,
            states_unanswered=self._unanswered,
            speed_rad_s=self.speed.rad_s))
        if self._resume_number and not self.safety.ramp_awaits_answer:
            self._resume_number = 0  # no ramp waits: no command's state need be looked up
        if not (decision.drive == self.mode == "active" and self.driver.state is Lifecycle.ACTIVE):
            self._follow()  # something to follow (else nothing changed: the steady state, cheaper)
        self.force = self.driver.write(decision.force_N) if self.driver.state is Lifecycle.ACTIVE \
            else np.zeros(self.driver.n_motors)
        self.driver.step()
        self.ticks += 1
        if self._read():
            self.publish_state()
            self._unanswered += 1
        for key, msg in self.driver.extra_messages():
            pub = self._extra_pubs.get(key)
            if pub is None:
                pub = self._extra_pubs[key] = publisher(self.session, key, block=self.config.lockstep)
            pub.put(msg, attachment=self._run)  # whose truth this is (bridge.session.RUN_PREFIX)
        if decision.events:
            _log_events(decision.events)
        dt = time.perf_counter() - t0
        if dt > self.tick_max_s:
            self.tick_max_s = dt

    def _read(self) -> bool:
        """Read the encoders into ``theta``; False when the read failed and the last angles stand
        (module docstring, "Encoder reads"); raises when it failed more than ``max_read_errors``
        times in a row."""
        try:
            self.theta = self.driver.read()
        except OSError as exc:
            self.read_errors += 1
            self._read_errors_in_row += 1
            if self._read_errors_in_row > self.config.max_read_errors:
                self.fault = _bounded(f"encoder read failed {self._read_errors_in_row} times in a row "
                                      f"({type(exc).__name__}: {exc}): the loop ends, drives off")
                log.error("bridge %s: %s", self.instance, self.fault)
                raise
            if self._read_errors_logged.allow() is not None:  # the count says the rest
                log.warning("encoder read failed (%s: %s; %d in all): keeping the last angles and the forces",
                            type(exc).__name__, exc, self.read_errors)
            return False
        self._read_errors_in_row = 0
        self._theta_list = self.theta.tolist()
        # A late tick: divided by the time it took, on a clock no NTP step moves (a step had
        # restarted the filter and skipped the glitch check: review of session 53).
        self.speed.update(self._theta_list, self.driver.steady_s())
        if self.speed.trusted:  # never hold forces of a glitch's angles (bridge.motor_speed.TRUST_AFTER_READINGS)
            self.hold.offer(self._theta_list)
        return True

    # -- outputs --------------------------------------------------------------------------------
    def publish_state(self) -> None:
        self._seq["state"] += 1
        stamp = self.driver.stamp_s()
        if stamp != self.last_state_stamp_s:  # a lockstep bridge re-publishes its waiting state
            # recorded before the state goes out: an answer may arrive before put() returns
            self._stamp_k = (self._stamp_k + 1) % len(self._state_stamps)
            # the number first: a callback that finds the stamp finds its number (two stores)
            self._state_numbers[self._stamp_k] = self._seq["state"]
            self._state_stamps[self._stamp_k] = stamp
            self.last_state_stamp_s = stamp
        self._state_pub.put(bus.MotorState(
            seq=self._seq["state"], stamp_s=stamp, theta_rad=self._theta_list,
            force_applied_N=self.force.tolist(), drive=self.mode,
            hold_reason=self.hold_reason if self.mode in ("hold", "inactive") or self._closed else "",
            epoch=self.epoch,
            bridge=self.instance,
            # one attribute read (a str): the lock only guards the callback's read-modify-write
            owner=self.ownership.owner, estop_engaged=self.safety.estop_engaged, estop_reason=self.safety.estop_reason))

    def _answered(self, stamp_s: float) -> int | None:
        """The number of the state of ``stamp_s`` among the newest published, None if none (read
        on a Zenoh thread without a lock: the loop writes a place's number before its stamp)."""
        try:
            k = self._state_stamps.index(stamp_s)
        except ValueError:
            return None
        return self._state_numbers[k]

    def _stale_note(self) -> str:
        """Why the commands of the last :data:`STALE_NOTE_S` did not count ('' if none was stale): a
        controller whose every command answered a state gone (a link's round trip over 50 ms) had
        said only "drives inactive", forever (lab-network benchmark of 2026-11-30). The text does
        not change while it holds (no figure in it): the safety journal writes a line per change
        of a state's reason, and the gaps' explanations list each distinct one (review)."""
        if time.monotonic() - self._stale_seen > STALE_NOTE_S:
            return ""
        window_ms = len(self._state_stamps) * self.dt * 1e3
        return (f"commands refused: they answer no state of the last {window_ms:.0f} ms (a round trip too long? "
                "docs/bridge.md, what network the link needs)")

    def publish_health(self) -> None:
        stats = self.commands.stats
        self._seq["health"] += 1
        with self._estop_lock:
            estop_received, estop_rejected = self.estop_received, self.estop_rejected
        reason = stats.last_reject_reason
        self._health.put(bus.encode(bus.Health(
            seq=self._seq["health"], stamp_s=self.driver.stamp_s(), process="bridge", instance=self.instance,
            uptime_s=time.monotonic() - self._started,
            received={bus.MOTOR_COMMAND: stats.received, bus.ESTOP: estop_received, "ticks": self.ticks,
                      "overruns": self.overruns, "periods_skipped": self.periods_skipped, "clamped": self.clamped,
                      "holds": self.holds, "rate_limited": self.rate_limited,
                      "tick_max_us": int(self.tick_max_s * 1e6), bus.BRIDGE_CLOCK: self.clock.answered},
            rejected={bus.MOTOR_COMMAND: stats.rejected, bus.ESTOP: estop_rejected,
                      bus.BRIDGE_CLOCK: self.clock.refused + self.clock.failed, "encoder_read": self.read_errors,
                      "command_stale_state": self.commands_stale},
            last_reject_reason=self.fault or reason)))

    # -- exit -----------------------------------------------------------------------------------
    def shutdown(self, cause: str = "") -> None:
        """Disable the drives, publish the final state and health, close the driver and the bus
        objects. Safe to call more than once and from a half-dead state. ``cause``: why the bridge
        stops (e.g. "stopped by SIGTERM: its parent process (pid 812) died"), said in the final
        state's ``hold_reason`` beside ``drive = "disabled"`` (what a console records of a campaign
        the stop ended)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.driver.close()  # disables the drives first of all
        finally:
            self.hold.stop()
            with contextlib.suppress(Exception):
                # An e-stop that came after the last tick: the drives are off already, but the
                # next start must find it latched (review of session 53).
                if self._estop_events or self._estop_engage is not None:
                    self.safety.apply_estop(self._take_estop_events())
                    _log_events(self.safety.take_events())
            if self.latch_file is not None:
                if self.safety.estop_engaged != self._latched_on_disk:
                    self._latched_on_disk = self.safety.estop_engaged
                    self.latch_file.set(self._latched_on_disk, self.safety.estop_reason)
                self.latch_file.close()  # what the e-stop last did is on disk before the process ends
            failed = getattr(self.driver, "close_error", "")
            if failed:
                # Not "disabled": an enable line that does not read off may still drive. The bus and
                # the log say so even when the loop ended on that very fault (an e-stop whose
                # disable failed: the last state said disabled and no line said DRIVES MAY BE ON;
                # audit of 2026-11-28). "hold": drives that may be enabled, zero set values written.
                self.mode, self.hold_reason = "hold", f"DRIVES MAY BE ON: they could not be disabled ({failed})"
                log.error("bridge %s: %s", self.instance, self.hold_reason)
            else:
                self.mode, self.hold_reason = "disabled", f"bridge {cause}" if cause else ""
            self.force = np.zeros(self.driver.n_motors)
            for last in (self.publish_state, self.publish_health):
                with contextlib.suppress(Exception):  # the session may already be gone
                    last()
            closers = [self.commands.close, self._controllers.undeclare, self._estop_sub.undeclare,
                       self._estop_tokens.undeclare, self._state_pub.close,
                       self._health.undeclare, self._token.undeclare, self.clock.close]
            closers += [p.close for p in self._extra_pubs.values()]
            for closer in closers:
                with contextlib.suppress(Exception):  # close everything we can, whatever failed before
                    closer()
            atexit.unregister(self._atexit)

    def _atexit(self) -> None:
        # Backstop for an exit that skipped the finally blocks (e.g. sys.exit in another thread).
        self.driver.close()


def pace(now: float, due: float, dt: float) -> int | None:
    """The real-time loop's arithmetic after a tick that ended at ``now``, the next one being due
    at ``due`` (period ``dt``): None when it ended in time (the loop sleeps until ``due``), else the
    tick overran and this many whole periods are skipped (``floor((now - due) / dt)``, 0 or more):
    the loop moves ``due`` on by as many periods and ticks at once, never catching up.

    The skipped periods are those in which no tick started: a tick that starts on time and stalls
    600 ms at ``dt`` = 2 ms spans 300 periods, its own (the overrun) and 299 skipped; the next
    tick starts on time at 600 ms. So ticks + periods skipped = periods elapsed."""
    if now <= due:
        return None
    return math.floor((now - due) / dt)


def run_realtime(node: BridgeNode, stop: threading.Event, systemd: SystemdNotify | None = None) -> int:
    """Ticks paced by the clock at the driver's rate. A tick that ends after the next one was due
    is an overrun (counted, reported in ``Health``); whole periods lost are skipped, never caught
    up, and counted too (``periods_skipped`` in ``Health``: the one overrun of a 600 ms stall
    lost 299 ticks; :func:`pace`). With ``config.loop_stall_s`` > 0 a
    :class:`bridge.loop_watchdog.LoopWatchdog` watches the ticks (each stores its time and count:
    about 10 ns) and, should they stop, trips the driver and ends the process (code 70).
    ``systemd``: told ``READY=1`` as the loop starts and pinged (``WATCHDOG=1``) from this thread
    every ``ping_period_s``. Returns the number of ticks run."""
    cfg, dt = node.config, node.dt
    driver = node.driver
    watchdog = LoopWatchdog(cfg.loop_stall_s, drives_off_and_exit(driver), period_s=dt)
    start = time.perf_counter()
    k = 0
    next_health = start + cfg.health_period_s
    # The first ping at the first tick: a supervisor judges only a loop that has pinged once, and a
    # bridge hung between its start and a first ping a period later (its drives enabled 20 ms
    # in) was never judged hung (CI of session 52).
    next_ping = start if systemd is not None else math.inf
    node.publish_health()
    switch = sys.getswitchinterval()
    sys.setswitchinterval(min(switch, SWITCH_INTERVAL_S))
    # the priority a supervisor asked for, now that imports, model and hold are set up
    if why := take_loop_priority():
        log.warning("real-time loop: %s", why)
    above = raise_loop_thread()  # before the watchdog, which goes one above the loop
    if above:
        log.warning("real-time loop: %s", above)
    watchdog.start()
    if systemd is not None:
        if systemd.watchdog_s is not None:
            # systemd's watchdog kills with SIGABRT: the journal then shows where every thread was
            # (faulthandler needs no GIL, so a loop hung in a C call holding it is shown too).
            faulthandler.enable(all_threads=True)
        # A supervisor disables the drives once this process has ended: with no core to write
        # first (SIGABRT, SIGSEGV) it ends at once.
        if why := no_core_dump():
            log.warning("%s: a crash writes a core before the supervisor's drives-off", why)
        systemd.ready()
    began = math.nan  # when the last tick began
    try:
        while not stop.is_set() and (cfg.max_ticks is None or k < cfg.max_ticks) and not driver.exhausted:
            # How long commands went unread: late to start, or the last tick stalled (a tick that
            # overran puts the next one back on its slot, which then starts "on time": a 600 ms
            # stall inside a tick had shown as none, and its next command was not ramped; review
            # of session 53). NaN at the first tick: 0.
            t = time.perf_counter()
            held_up = max(t - (start + k * dt), t - began - dt)
            began = t
            node.tick(held_up if held_up == held_up else 0.0)
            k += 1
            now = time.perf_counter()
            watchdog.last_tick_s = now  # the loop watchdog's per-tick cost: two stores
            watchdog.ticks = k
            due = start + k * dt
            skipped = pace(now, due, dt)
            if skipped is None:
                time.sleep(due - now)
            else:
                node.overruns += 1
                if skipped:
                    node.periods_skipped += skipped
                    start += skipped * dt
            if now >= next_health:
                node.publish_health()
                next_health = now + cfg.health_period_s
            if now >= next_ping:  # finite only with systemd
                assert systemd is not None
                systemd.ping()
                next_ping = now + systemd.ping_period_s
    finally:
        sys.setswitchinterval(switch)
        # Fired: its action is ending the process (the drives are off); this thread must not go
        # on to a clean exit's code 0 meanwhile, nor re-raise what the tripped driver raised.
        watchdog.stop()
        if systemd is not None:
            systemd.stopping()
    return k


def run_lockstep(node: BridgeNode, stop: threading.Event) -> int:
    """One tick per new valid command (a new ``seq``), as fast as the controller goes; e-stops are
    acted upon within 5 ms even without commands. Returns the number of ticks run."""
    cfg = node.config
    last_seq = None
    k = 0
    idle_since = last_publish = time.monotonic()
    next_health = idle_since + cfg.health_period_s
    node.publish_state()
    node.publish_health()
    while not stop.is_set() and (cfg.max_ticks is None or k < cfg.max_ticks) and not node.driver.exhausted:
        cmd = node.commands.wait(0.005, lambda c: c.seq != last_seq)
        now = time.monotonic()
        if cmd is None or cmd.seq == last_seq:
            if node.process_estop() or now - last_publish >= cfg.republish_s:
                node.publish_state()
                last_publish = now
            limit = cfg.idle_timeout_s
            if last_seq is None and cfg.startup_timeout_s is not None:
                limit = cfg.startup_timeout_s  # peers may still be starting
            if limit is not None and now - idle_since > limit:
                log.info("no command for %.1f s: stopping", limit)
                break
        else:
            last_seq, idle_since, last_publish = cmd.seq, now, now
            node.tick()
            k += 1
        if now >= next_health:
            node.publish_health()
            next_health = now + cfg.health_period_s
    return k


__all__ = ["BridgeConfig", "BridgeNode", "HoldWorker", "run_lockstep", "run_realtime"]
