"""The loop watchdog: the drives go off when the bridge's real-time loop stops ticking.

The bridge's safety rules (the command watchdog, the e-stop) run inside its real-time loop, so a
loop that hangs (blocked in a call, a deadlock, an endless Python loop) takes them with it, and
on the robot the ESCONs go on driving the last currents with their enable lines high. A daemon
thread of the same process watches the loop: the loop stores the time of each tick in
:attr:`LoopWatchdog.last_tick_s` (one float attribute store, no lock: 7 ns here); every
``poll_s`` (50 ms) the thread looks whether it changed. After ``stall_s`` without a tick it calls
its action once (latched): for the bridge :func:`drives_off_and_exit`, which trips the driver
(:meth:`bridge.driver.Driver.trip`: every drive off from this thread, and latched, so a loop that
wakes up cannot enable or drive again), logs one line saying so and where the loop hung, and
ends the process with :data:`LOOP_STALL_EXIT`, so that a supervisor (systemd's ``ExecStopPost``
and ``Restart=``, ``xneck up --robot``) sees a failure.

What counts as a stall: time during which this thread ran and the loop did not tick. A stop of
the whole process or machine (SIGSTOP, a VM or CPU stall) stops this thread as well, so one look
counts for at most half the limit, however late it came: after such a stop the loop has the
other half to tick again, and does so within a period. The bridge rides such stops out by
design (on waking, the loop ramps the forces to the command computed meanwhile:
``Inputs.resumed_after_s``); a process frozen for good is what systemd's ``WatchdogSec=`` is for
(docs/bridge.md), the loop's own ping stops with it.

What it cannot do: run while the loop holds the GIL in a C call that never returns (no Python
thread runs then: systemd's watchdog again), or when the process or the kernel is dead. Under
a real-time policy (the robot's SCHED_FIFO) the thread raises itself one priority above the
loop: on the BeagleBone's single core, a loop spinning at the same FIFO priority would never
let it run.

Only the standard library: the bridge stays lean (tests/test_bridge_lean.py).
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger("xneck.bridge")

#: Exit code of a bridge whose loop watchdog fired (EX_SOFTWARE of sysexits.h): not 0, so
#: systemd's ``Restart=on-failure`` and ``xneck up --robot``'s drives-off apply, and not 1 (an
#: exception), 2 (a usage error) or 3 (``xneck up`` refused to start).
LOOP_STALL_EXIT = 70
#: ``xneck bridge --loop-stall`` by default (s): 250 ticks of 2 ms. Nearly 4 times the longest
#: stall of the loop alone seen in a running bridge (134 ms, a 20 MB command parsed on the GIL
#: before payloads were bounded), below the 1 s after which ``xneck up --robot`` kills a silent
#: bridge (its drives-off is a new process that first imports the bridge: seconds on the board).
#: docs/bridge.md, "The loop watchdog".
DEFAULT_STALL_S = 0.5
#: The shortest stall limit accepted (s): below it the thread's own wake-up jitter on a loaded
#: machine is of the same size.
MIN_STALL_S = 0.05
#: How often the thread looks (s), at most: a stall is seen ``stall_s`` to ``stall_s + poll_s``
#: after the last tick.
POLL_S = 0.05
#: After tripping the driver the action lets the loop's thread run this long (s), then trips it
#: again: a hardware write of the loop already past its latch check when the latch was set
#: lands meanwhile and is undone by the second pass.
SECOND_PASS_S = 0.005
#: The action's log line may take this long (s) before the process exits anyway: the hung loop
#: may hold the logging handler's lock (a blocked write to the journal's pipe).
LOG_TIMEOUT_S = 0.25

#: ``os._exit``, replaced by in-process tests (the action must not end the test run).
_exit: Callable[[int], object] = os._exit


class Trippable(Protocol):
    """What the action needs of a driver (:class:`bridge.driver.Driver`)."""

    name: str

    def trip(self) -> str: ...


class LoopWatchdog:
    """Calls ``on_stall(self, since_tick_s)`` once, from its own thread, when the loop has not
    stored a tick in :attr:`last_tick_s` for ``stall_s`` of the thread's regular watching
    (module docstring). ``stall_s = 0``: off (:meth:`start` does nothing, the loop's store stays
    as cheap). ``clock`` must be the loop's (``time.perf_counter``)."""

    __slots__ = ("_loop_ident", "_loop_native_id", "_seen", "_stop", "_thread", "clock", "fired", "last_tick_s",
                 "max_credit_s", "on_stall", "poll_s", "priority_note", "stall_s", "stalled_s")

    def __init__(self, stall_s: float, on_stall: Callable[[LoopWatchdog, float], object],
                 poll_s: float | None = None, clock: Callable[[], float] = time.perf_counter) -> None:
        if not (stall_s == 0 or stall_s >= MIN_STALL_S):  # also refuses NaN
            raise ValueError(f"loop_stall_s must be 0 (off) or at least {MIN_STALL_S} s, got {stall_s}")
        self.stall_s = float(stall_s)
        self.poll_s = float(poll_s) if poll_s is not None else min(POLL_S, self.stall_s / 4 or POLL_S)
        # The most one look counts, however late it came: half the limit, so that a stop of the
        # whole process (however long) is no stall unless the loop then stays silent for the other
        # half; and a look that was late for want of the GIL (a loop spinning in Python, threads
        # queueing for it on a loaded machine) still counts nearly in full.
        self.max_credit_s = max(2 * self.poll_s, self.stall_s / 2)
        self.on_stall, self.clock = on_stall, clock
        self.last_tick_s = self._seen = clock()  # the loop's store, every tick; the last one seen
        self.stalled_s = 0.0  # watched time without a tick
        self.fired = False  # latched
        self.priority_note = ""  # why the thread could not be raised above the loop ('' if it was or need not be)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop_ident: int | None = None
        self._loop_native_id: int | None = None

    # -- the thread's logic, driven by hand in tests ------------------------------------------------
    def check(self, seen_tick_s: float, gap_s: float) -> bool:
        """One look: ``seen_tick_s`` the loop's last store now, ``gap_s`` the time since the last
        look. True when this look fires (once: latched)."""
        if self.fired:
            return False
        if seen_tick_s != self._seen:
            self._seen, self.stalled_s = seen_tick_s, 0.0
            return False
        self.stalled_s += min(gap_s, self.max_credit_s)  # a stop of the whole process counts for at most this
        if self.stalled_s < self.stall_s - 1e-9:  # (ten looks of 0.05 s sum to 0.49999...)
            return False
        self.fired = True
        return True

    # -- the thread -----------------------------------------------------------------------------
    def start(self) -> None:
        """Watch the calling thread's loop (call it from the loop's thread, before its first tick)."""
        if self.stall_s == 0 or self._thread is not None:
            return
        self._loop_ident, self._loop_native_id = threading.get_ident(), threading.get_native_id()
        self.last_tick_s = self._seen = self.clock()  # a loop hung in its first tick is seen too
        self._thread = threading.Thread(target=self._run, name="xneck-loop-watchdog", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 1.0) -> None:
        """Stop watching. After it fired, wait for its action to end (in the bridge: the process
        ends there, so this never returns)."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(None if self.fired else timeout_s)

    def loop_stack(self) -> str:
        """Where the loop's thread is now (innermost last), for the log."""
        frame = sys._current_frames().get(self._loop_ident) if self._loop_ident is not None else None
        if frame is None:
            return "(the loop's thread is gone)"
        # Without the source lines: reading them (linecache) hands the GIL back and forth, which a
        # loop spinning in Python makes slow; file, line and function say where.
        where = []
        while frame is not None and len(where) < 8:
            where.append(f"  {frame.f_code.co_filename}:{frame.f_lineno} in {frame.f_code.co_name}")
            frame = frame.f_back
        return "\n".join(reversed(where))

    def _run(self) -> None:
        self.priority_note = self._raise_above_loop()
        if self.priority_note:
            log.warning("loop watchdog: %s", self.priority_note)
        last = self.clock()
        while not self._stop.wait(self.poll_s):
            now = self.clock()
            if self.check(self.last_tick_s, now - last):
                try:
                    self.on_stall(self, now - self.last_tick_s)
                except Exception:  # the action's own failure must still be seen
                    log.exception("loop watchdog: its action failed")
                return
            last = now

    def _raise_above_loop(self) -> str:
        """Under SCHED_FIFO/RR, one priority above the loop's thread (Linux: per thread); '' if
        done or not needed, else why not."""
        tid = self._loop_native_id
        try:
            policy = os.sched_getscheduler(tid or 0)
            if policy not in (os.SCHED_FIFO, os.SCHED_RR):
                return ""  # time-shared: the kernel shares the CPU, this thread inherits the loop's niceness
            prio = os.sched_getparam(tid or 0).sched_priority
            top = os.sched_get_priority_max(policy)
            if prio >= top:
                return f"the loop runs at the highest real-time priority ({prio}): a loop spinning on one core would starve this thread"
            os.sched_setscheduler(0, policy, os.sched_param(prio + 1))  # 0: this thread
        except AttributeError:
            return ""  # not Linux: no per-thread real-time scheduling to reason about
        except OSError as exc:
            return (f"could not run above the loop's real-time priority ({exc.strerror}; raise LimitRTPRIO by one): "
                    "a loop spinning on one core would starve this thread")
        return ""


def drives_off_and_exit(driver: Trippable, code: int = LOOP_STALL_EXIT) -> Callable[[LoopWatchdog, float], None]:
    """The bridge's action: trip ``driver`` (drives off, latched), trip it again after
    :data:`SECOND_PASS_S`, log one line (with where the loop hung) and end the process with
    ``code`` without running any handler (the loop's thread may hold any lock)."""

    def action(watchdog: LoopWatchdog, since_tick_s: float) -> None:
        try:
            t0 = time.perf_counter()
            error = driver.trip()
            off_s = time.perf_counter() - t0
            time.sleep(SECOND_PASS_S)
            error = driver.trip() or error
            outcome = f"COULD NOT disable every drive ({error})" if error else \
                f"drives disabled in {off_s * 1e3:.2f} ms and latched off"
            line = (f"loop watchdog: the real-time loop made no tick for {since_tick_s:.3f} s (limit "
                    f"{watchdog.stall_s:.3f} s): {outcome} (driver {driver.name}); exiting with code {code}. "
                    f"The loop's thread was at:\n{watchdog.loop_stack()}")
            writer = threading.Thread(target=log.critical, args=("%s", line), name="xneck-loop-watchdog-log",
                                      daemon=True)
            writer.start()
            writer.join(LOG_TIMEOUT_S)
        finally:
            _exit(code)  # whatever happened above: a hung loop must not be left running

    return action


__all__ = ["DEFAULT_STALL_S", "LOOP_STALL_EXIT", "MIN_STALL_S", "LoopWatchdog", "drives_off_and_exit"]
