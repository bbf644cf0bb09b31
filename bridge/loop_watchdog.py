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
ends the process with :data:`LOOP_STALL_EXIT`, so that a supervisor (systemd's ``ExecStopPost``,
``xneck up --robot``) sees a failure and sets the drives off again from outside.

What counts as a stall: time during which this thread ran and the loop did not tick. A stop of
the whole process or machine (SIGSTOP, a VM or CPU stall) stops this thread as well, so one look
counts for at most half the limit, however late it came, and a late look never fires by itself:
after such a stop the loop has at least one regular look's time to tick again, and does so within
a period (audit of 2026-11-26: a tolerated 0.3 s stall followed by a stop had tripped a healthy
bridge). A loop that still ticks, but rarely (a tick every 0.48 s kept every enable line high
for good, the e-stop taking 0.48 s), counts as hung too: fewer than :data:`MIN_TICK_FRACTION` of
its ticks over ``stall_s`` of watching. The action itself is bounded: should the trip block, the
process still ends within :data:`ACTION_TIMEOUT_S` (``faulthandler``'s own thread, which needs
no GIL). The bridge rides such stops out by
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

import faulthandler
import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger("xneck.bridge")

#: Exit code of a bridge whose loop watchdog fired (EX_SOFTWARE of sysexits.h): not 0, so
#: systemd's ``ExecStopPost`` sees a failure and ``xneck up --robot``'s drives-off applies, and
#: not 1 (an exception), 2 (a usage error) or 3 (``xneck up`` refused to start).
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

#: A loop that ticks fewer than this fraction of its ticks over ``stall_s`` of watching is hung
#: (at 500 Hz and 0.5 s: under 12 of 250 ticks, a tick every 40 ms or rarer, when the command
#: watchdog's 10 ms and the e-stop's tick no longer hold). Loaded development machines ran the
#: twin's bridge at 486-500 ticks/s (benchmarks/README.md): far above.
MIN_TICK_FRACTION = 0.05
#: The action may take this long (s) before ``faulthandler`` ends the process (status 1) with
#: every thread's stack: a trip that blocks must not leave a hung loop running with its drives on.
ACTION_TIMEOUT_S = 1.0

#: Python's switch interval while the action runs (s; CPython's default is 5 ms). The action's
#: hardware writes and its log hand the GIL back at every system call; a loop hung in a convoy
#: (short calls that release the GIL between less Python than the switch interval) takes it again
#: each time before this thread wakes, and a waiting thread only asks for it when no switch at all
#: came within one interval. At 5 ms each hand-back cost the action 5-10 ms: a median 103 ms (max
#: 178) for the fake board's trip at rest, over :data:`ACTION_TIMEOUT_S` once under CI's load
#: (faulthandler ended the bridge with status 1, its log line lost). At 1 µs this thread asks
#: within a microsecond, shorter than any Python a loop can run between two calls: a median 1.7 ms
#: (max 12.7) for the same trip (benchmarks/loop_watchdog.py, docs/bridge.md). Only for the
#: action: the process ends right after.
ACTION_SWITCH_INTERVAL_S = 1e-6
#: Python's switch interval while this thread's looks come late and the loop has not ticked (s),
#: until a look sees a tick. A loop hung in a convoy makes the thread's own looks wait for the GIL
#: as it makes the action's hand-backs wait (above), and late looks never fire (a stop of the
#: whole process looks the same): a convoyed bridge on a loaded 2-CPU machine ran 30 s without a
#: look in time and was never tripped (CI of 2026-11-29, ``test_the_action_gets_the_gil_from_a_loop_hung_in_a_convoy``).
#: Asking for the GIL within microseconds makes the next look regular. A healthy loop after a
#: stop of the process ticks before the next look, which puts the interval back: ≤ ``poll_s`` of it.
HURRY_SWITCH_INTERVAL_S = 1e-6

#: ``os._exit``, replaced by in-process tests (the action must not end the test run).
_exit: Callable[[int], object] = os._exit


class Trippable(Protocol):
    """What the action needs of a driver (:class:`bridge.driver.Driver`)."""

    name: str

    def trip(self) -> str: ...


class LoopWatchdog:
    """Calls ``on_stall(self, since_tick_s)`` once, from its own thread, when the loop has not
    stored a tick in :attr:`last_tick_s` for ``stall_s`` of the thread's regular watching, or
    has counted in :attr:`ticks` fewer than ``MIN_TICK_FRACTION`` of the ticks of ``period_s``
    over ``stall_s`` of watching (module docstring). ``stall_s = 0``: off (:meth:`start` does
    nothing, the loop's stores stay as cheap). ``clock`` must be the loop's (``time.perf_counter``)."""

    __slots__ = ("_loop_ident", "_loop_native_id", "_low_windows", "_seen", "_stop", "_switch_s", "_thread", "_window_s",
                 "_window_ticks", "clock", "fired", "last_tick_s", "late_looks", "looks", "max_credit_s", "min_ticks", "on_stall",
                 "poll_s", "priority_note", "rare_ticks", "stall_s", "stalled_s", "ticks")

    def __init__(self, stall_s: float, on_stall: Callable[[LoopWatchdog, float], object],
                 poll_s: float | None = None, clock: Callable[[], float] = time.perf_counter,
                 period_s: float | None = None) -> None:
        if not (stall_s == 0 or MIN_STALL_S <= stall_s < float("inf")):  # also refuses NaN
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
        self.ticks = 0  # the loop's count of ticks, stored every tick (with ``period_s``)
        self.rare_ticks = 0  # ticks of the window that fired check_rate (0: check fired)
        self._low_windows = 0  # windows in a row with too few ticks
        # Fewest ticks per ``stall_s`` of watching (0: no rate check, without a period).
        self.min_ticks = MIN_TICK_FRACTION * self.stall_s / period_s if period_s else 0.0
        self._window_s, self._window_ticks = 0.0, 0  # watched time and the tick count when the window began
        self.looks = 0  # looks taken (the thread's)
        self.late_looks = 0  # of them, later than ``max_credit_s`` without a tick (:meth:`pace`)
        self._switch_s: float | None = None  # the switch interval to restore while hurried
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
        if gap_s > self.max_credit_s:
            # A late look (the whole process stopped): it counts for at most half the limit and
            # never fires by itself, so a loop that woke with it has a regular look's time to tick.
            self.stalled_s = min(self.stalled_s + self.max_credit_s, self.stall_s - self.poll_s)
            return False
        self.stalled_s += gap_s
        if self.stalled_s < self.stall_s - 1e-9:  # (ten looks of 0.05 s sum to 0.49999...)
            return False
        self.fired = True
        return True

    def check_rate(self, ticks: int, gap_s: float) -> bool:
        """One look at the loop's tick count (``ticks``, ``gap_s`` since the last look): True when,
        over two windows of ``stall_s`` of watching in a row, some ticks but fewer than
        :attr:`min_ticks` came in each (a late look counts as :meth:`check` says, and ends no
        window with a verdict). Once: latched with :meth:`check`."""
        if self.fired or not self.min_ticks:
            return False
        self._window_s += min(gap_s, self.max_credit_s)
        if self._window_s < self.stall_s - 1e-9:
            return False
        came, self._window_s, self._window_ticks = ticks - self._window_ticks, 0.0, ticks
        # Two windows in a row with some ticks but too few: a window where the loop hung part-way
        # is followed by one without any, which is a stall (:meth:`check`, its own timing).
        low = 0 < came < self.min_ticks and gap_s <= self.max_credit_s
        self._low_windows = self._low_windows + 1 if low else 0
        if self._low_windows < 2:
            return False
        self.fired, self.rare_ticks = True, came
        return True

    def pace(self, seen_tick_s: float, gap_s: float) -> None:
        """Before a look (:meth:`check`'s arguments): a look later than ``max_credit_s`` with no tick
        since the last sets Python's switch interval to :data:`HURRY_SWITCH_INTERVAL_S` (a loop
        convoying the GIL made it late); the first look that sees a tick puts it back."""
        self.looks += 1
        if seen_tick_s != self._seen:
            if self._switch_s is not None:
                sys.setswitchinterval(self._switch_s)
                self._switch_s = None
            return
        if gap_s > self.max_credit_s and not self.fired:
            self.late_looks += 1
            if self._switch_s is None:
                self._switch_s = sys.getswitchinterval()
                sys.setswitchinterval(HURRY_SWITCH_INTERVAL_S)

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
        ends there, so this never returns); if it has not after ``2 · ACTION_TIMEOUT_S``, end the
        process here (a woken loop must not go on to a clean exit while the trip hangs)."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(2 * ACTION_TIMEOUT_S if self.fired else timeout_s)
            if self.fired and thread.is_alive():  # its action did not end the process in time: this thread does
                _exit(LOOP_STALL_EXIT)

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

    def other_threads(self) -> str:
        """Where every other thread of the process is (its name, innermost frame), for the log:
        what the loop may have waited for (a lock, the GIL held by a starved thread)."""
        names = {t.ident: t.name for t in threading.enumerate()}
        mine = (self._loop_ident, threading.get_ident())
        lines = []
        for ident, frame in sys._current_frames().items():
            if ident not in mine:
                lines.append(f"  {names.get(ident, ident)}: {frame.f_code.co_filename}:{frame.f_lineno} in "
                             f"{frame.f_code.co_name}")
        return "\n".join(lines) or "  (none)"

    def _run(self) -> None:
        self.priority_note = self._raise_above_loop()
        if self.priority_note:
            log.warning("loop watchdog: %s", self.priority_note)
        last = self.clock()
        self._window_ticks = self.ticks
        try:
            while not self._stop.wait(self.poll_s):
                now = self.clock()
                self.pace(self.last_tick_s, now - last)
                if self.check(self.last_tick_s, now - last) or self.check_rate(self.ticks, now - last):
                    try:
                        self.on_stall(self, now - self.last_tick_s)
                    except Exception:  # the action's own failure must still be seen
                        log.exception("loop watchdog: its action failed")
                    return
                last = now
        finally:  # stopped (or an action that returned: tests): the process's own interval again
            if self._switch_s is not None:
                sys.setswitchinterval(self._switch_s)
                self._switch_s = None

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
        # Should anything below block (a trip stuck in the hardware library), the process still
        # ends, with every thread's stack (a C thread: no GIL needed); audit of 2026-11-26.
        faulthandler.dump_traceback_later(ACTION_TIMEOUT_S, exit=True)
        switch_s = sys.getswitchinterval()
        sys.setswitchinterval(ACTION_SWITCH_INTERVAL_S)
        try:
            t0 = time.perf_counter()
            error = driver.trip()
            off_s = time.perf_counter() - t0
            time.sleep(SECOND_PASS_S)
            error = driver.trip() or error
            outcome = f"COULD NOT disable every drive ({error})" if error else \
                f"drives disabled in {off_s * 1e3:.2f} ms and latched off"
            what = (f"made only {watchdog.rare_ticks} ticks in {watchdog.stall_s:.3f} s (fewer than "
                    f"{watchdog.min_ticks:.0f}; the last {since_tick_s:.3f} s ago)") if watchdog.rare_ticks else \
                f"made no tick for {since_tick_s:.3f} s (limit {watchdog.stall_s:.3f} s)"
            line = (f"loop watchdog: the real-time loop {what}: {outcome} (driver {driver.name}); exiting with code {code}. "
                    f"The loop's thread was at:\n{watchdog.loop_stack()}\nOther threads:\n{watchdog.other_threads()}")
            writer = threading.Thread(target=log.critical, args=("%s", line), name="xneck-loop-watchdog-log",
                                      daemon=True)
            writer.start()
            writer.join(LOG_TIMEOUT_S)
        finally:
            _exit(code)  # whatever happened above: a hung loop must not be left running
            faulthandler.cancel_dump_traceback_later()  # reached only where _exit is replaced (tests)
            sys.setswitchinterval(switch_s)

    return action


__all__ = ["ACTION_TIMEOUT_S", "DEFAULT_STALL_S", "LOOP_STALL_EXIT", "MIN_STALL_S", "MIN_TICK_FRACTION", "LoopWatchdog",
           "drives_off_and_exit"]
