"""What every bus process shares: logging, a stop event set by SIGINT/SIGTERM, endpoint lists, priority,
systemd's notification socket.

The command-line options of these processes live with the one ``xneck`` command line
(:mod:`server.cli.options`); this module only holds what runs inside the processes."""

from __future__ import annotations

import logging
import math
import os
import resource
import signal
import socket
import threading


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )


class Stop(threading.Event):
    """The stop event of a bus process, with ``cause``: why it was set ("" until then)."""

    cause: str = ""


def stop_cause(signum: int, parent_pid: int, ppid: int) -> str:
    """Why a process stops on signal ``signum``, as its last state says it: a supervisor's death
    (the kernel's parent-death SIGTERM, ``xneck up`` killed) is named as such, since its children
    were stopped by it, not by anyone's stop (the console had recorded "the drives were disabled
    during the campaign: the bridge's drives are disabled", user audit of session 46). ``ppid``:
    the parent now, ``parent_pid`` the one at start-up."""
    name = signal.Signals(signum).name
    if ppid != parent_pid:
        return f"stopped by {name}: its parent process (pid {parent_pid}) died"
    return f"stopped by {name}"


def stop_on_signals() -> Stop:
    """An event set by Ctrl-C or SIGTERM, so loops end cleanly and sessions get closed; its
    ``cause`` says which signal, and whether the process's parent had died (:func:`stop_cause`)."""
    stop = Stop()
    parent_pid = os.getppid()

    def handler(signum: int, _frame: object) -> None:
        stop.cause = stop_cause(signum, parent_pid, os.getppid())
        logging.getLogger("xneck").info("signal %s: stopping (%s)", signal.Signals(signum).name, stop.cause)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def endpoints(values: list[str] | None) -> list[str] | None:
    """CLI endpoint list: None (not given) defers to the environment."""
    return list(values) if values else None


def raise_priority(niceness: int = -10) -> bool:
    """Ask the OS to schedule this real-time process before ordinary work (the console, a
    browser rendering WebGL in software): on a small machine they would otherwise delay ticks.
    Needs the right to lower niceness (root or CAP_SYS_NICE); without it, carries on as is."""
    try:
        os.nice(niceness)
        return True
    except (PermissionError, OSError):
        logging.getLogger("xneck").info("could not raise the scheduling priority (needs CAP_SYS_NICE)")
        return False


#: Set by a supervisor for a loop process (``xneck up``, the console's campaign runner:
#: :func:`server.child_processes.loop_environ`): the SCHED_FIFO priority it takes once it is set
#: up, at its loop's start (:func:`take_loop_priority`). Taken at its exec instead, its imports,
#: model and numba caches computed for seconds at that priority on the loop's CPU, above another
#: stack's controller there, which was killed as hung (fresh-user audit of 2026-12-01).
ENV_LOOP_PRIORITY = "XNECK_LOOP_PRIORITY"
LOOP_NICE = -10  # where real-time priority is not permitted
_arranged: dict[int, int | None] = {}  # native thread id -> its place against the loop's priority


def fifo_or_nice(tid: int, prio: int) -> list[str]:
    """Put thread ``tid`` at SCHED_FIFO ``prio``, or where that is not permitted at nice
    :data:`LOOP_NICE`; what was refused (empty if FIFO was taken). ``ProcessLookupError``
    (the thread ended meanwhile) is the caller's to skip."""
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(prio))
        return []
    except ProcessLookupError:
        raise
    except (AttributeError, OSError) as exc:
        refused = [f"SCHED_FIFO {prio}: {getattr(exc, 'strerror', None) or exc}"]
    try:
        os.setpriority(os.PRIO_PROCESS, tid, LOOP_NICE)
    except OSError as exc2:
        refused.append(f"nice {LOOP_NICE}: {exc2.strerror or exc2}")
    return refused


def arrange_thread(offset: int | None) -> None:
    """Say where the calling thread stands against its process's loop priority, for a priority
    taken later (:func:`take_loop_priority`): ``None`` out of real-time scheduling (the bridge's
    hold worker), ``-1`` one below (the controller's own threads). The caller applies it now too
    if the process already runs at real-time priority."""
    _arranged[threading.get_native_id()] = offset


def take_loop_priority() -> str:
    """The real-time priority ``$XNECK_LOOP_PRIORITY`` asks for, taken now by every thread of this
    process but those placed by :func:`arrange_thread` (at their place); where SCHED_FIFO is not
    permitted, nice :data:`LOOP_NICE`. Without the variable nothing is done (a systemd unit gives
    the policy at exec, or nobody asked). '' if done, else why not (logged by the caller)."""
    value = os.environ.get(ENV_LOOP_PRIORITY, "")
    if not value:
        return ""
    try:
        prio = int(value)
        if not 1 <= prio <= 98:
            raise ValueError
    except ValueError:
        return f"{ENV_LOOP_PRIORITY}={value[:20]!r} is no real-time priority (1-98): scheduling left as is"
    refused: set[str] = set()
    done: set[int] = set()
    for _pass in range(3):  # again for a thread started meanwhile by one not yet raised (it inherited nothing)
        try:
            tids = {int(t) for t in os.listdir("/proc/self/task")}
        except OSError:
            tids = {threading.get_native_id()}
        for tid in list(_arranged):  # a place of a thread that ended: its id may come back for another
            if tid not in tids:
                _arranged.pop(tid, None)
        if tids <= done:
            break
        for tid in sorted(tids - done):
            done.add(tid)
            offset = _arranged.get(tid, 0)
            if offset is None:
                continue
            try:
                refused.update(fifo_or_nice(tid, max(1, prio + offset)))
            except ProcessLookupError:
                continue  # a thread that ended meanwhile
    return "; ".join(sorted(refused))


def raise_loop_thread() -> str:
    """Under a real-time policy (SCHED_FIFO/RR, as the robot's unit and ``xneck up`` give the whole
    process), put the calling thread, the real-time loop, one priority above the process's other
    threads: Zenoh's threads inherit the process's priority, and at the same FIFO priority on one
    CPU a Zenoh thread busy with a burst (a peer that stops reading, new subscribers, start-up)
    kept the loop from waking for 0.5 s while the loop watchdog, one above, still ran (three
    full-suite runs of 2026-11-26). '' if done or not needed, else why not (logged by the caller)."""
    try:
        policy = os.sched_getscheduler(0)
        if policy not in (os.SCHED_FIFO, os.SCHED_RR):
            return ""
        prio = os.sched_getparam(0).sched_priority
        if prio >= os.sched_get_priority_max(policy) - 1:
            return f"the process runs at real-time priority {prio}: no room above it for the loop and its watchdog"
        os.sched_setscheduler(0, policy, os.sched_param(prio + 1))  # 0: this thread (Linux)
    except AttributeError:
        return ""
    except OSError as exc:
        return (f"could not raise the loop above the process's real-time priority ({exc.strerror}; "
                "LimitRTPRIO must allow two above the process's)")
    return ""


def no_core_dump() -> str:
    """Set this process's core-file size limit (soft) to 0: a process killed by a signal whose
    default action dumps core (systemd's watchdog SIGABRT, a SIGSEGV in a hardware library) then
    ends at once. A core is written before the process has ended, so before its supervisor's
    drives-off (the unit's ``ExecStopPost``, ``xneck up``) can run: systemd-coredump compressing
    a whole Python process image takes seconds on a small board. The stacks are in the log
    (faulthandler) all the same. '' if done, else why not."""
    try:
        _soft, hard = resource.getrlimit(resource.RLIMIT_CORE)
        resource.setrlimit(resource.RLIMIT_CORE, (0, hard))
    except (OSError, ValueError) as exc:
        return f"core dumps stay on ({exc})"
    return ""


class SystemdNotify:
    """sd_notify(3) in a few lines, without libsystemd: datagrams to ``$NOTIFY_SOCKET``.

    Under a unit with ``Type=notify`` and ``WatchdogSec=`` (docs/bridge.md), systemd sets
    ``NOTIFY_SOCKET`` and ``WATCHDOG_USEC``. The bridge says ``READY=1`` when its real-time loop
    starts, ``WATCHDOG=1`` from the loop's own thread every :attr:`ping_period_s` (half of
    ``WATCHDOG_USEC``, as sd_watchdog_enabled(3) advises) and ``STOPPING=1`` when it ends. A loop
    that stops ticking stops the pings, whatever stopped it (a SIGSTOP, a C call holding the GIL:
    what the in-process loop watchdog cannot see), and systemd kills the service (``WatchdogSignal``,
    SIGABRT by default), then runs ``ExecStopPost``. Every send is non-blocking and never raises:
    a failure is logged once and the loop goes on.
    """

    def __init__(self, address: str, watchdog_s: float | None = None) -> None:
        self.address = address
        self.watchdog_s = watchdog_s
        #: How often the loop pings (s); inf without a watchdog.
        self.ping_period_s = watchdog_s / 2 if watchdog_s else math.inf
        self.sent = self.failed = 0
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self._target = "\0" + address[1:] if address.startswith("@") else address  # "@": Linux abstract namespace

    @classmethod
    def from_environ(cls, environ: dict[str, str] | None = None) -> SystemdNotify | None:
        """The notifier systemd asked for, or None (not under systemd, or not a unix socket).
        ``WATCHDOG_PID`` naming another process (the variables were inherited) turns the
        watchdog off."""
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        if not address.startswith(("/", "@")):
            if address:
                logging.getLogger("xneck").warning("NOTIFY_SOCKET=%r is not a unix socket: systemd is not told", address)
            return None
        watchdog_s = None
        try:
            usec = int(env.get("WATCHDOG_USEC", "0"))
            pid = int(env.get("WATCHDOG_PID", str(os.getpid())))
        except ValueError:
            usec, pid = 0, -1
        if usec > 0 and pid == os.getpid():
            watchdog_s = usec * 1e-6
        return cls(address, watchdog_s)

    def send(self, state: str) -> bool:
        try:
            self._sock.sendto(state.encode(), socket.MSG_DONTWAIT, self._target)
        except OSError as exc:
            self.failed += 1
            if self.failed == 1:
                logging.getLogger("xneck").warning("could not notify systemd at %s (%s): %s", self.address,
                                                   exc.strerror or exc, state.split("=")[0])
            return False
        self.sent += 1
        return True

    def ready(self) -> bool:
        return self.send("READY=1")

    def ping(self) -> bool:
        return self.send("WATCHDOG=1")

    def stopping(self) -> bool:
        return self.send("STOPPING=1")

    def close(self) -> None:
        self._sock.close()
