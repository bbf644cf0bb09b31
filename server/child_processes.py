"""Child processes of the console: the `xneck` command lines it starts (campaign runner, `xneck up`),
how they are stopped, how they are scheduled, and the last lines of their logs for an error message.

One place for what both orchestrators do, so a stop always means SIGTERM, a grace period (the
bridge ramps its forces down and closes its archive in it), then SIGKILL.

Isolation (issue 21): the loop's processes (bridge, twin, controller) get real-time priority
(SCHED_FIFO, the bridge's safety above the controller) and the last CPU; everything else the
console starts (and the console itself: viewers, figures, the 3D scene) the other CPUs, so a
viewer never competes with the loop. What the kernel does not permit falls back (FIFO → nice −10
→ nothing) and is reported: :func:`isolate` answers what each process really got, read back from
the kernel, with the reason of each refusal; ``/api/system/processes`` shows it for every xneck
process of this machine (:func:`local_processes`). ``XNECK_REALTIME=0`` leaves scheduling alone;
``XNECK_LOOP_CPUS`` (a CPU list, ``"3"`` or ``"2-3"``) names the loop's CPUs instead of the last
one (a CPU the lab keeps free with ``isolcpus``, or one per stack when two run on one machine).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from bridge.runtime import ENV_LOOP_PRIORITY, fifo_or_nice

ENV_REALTIME = "XNECK_REALTIME"
ENV_LOOP_CPUS = "XNECK_LOOP_CPUS"
#: SCHED_FIFO priority of each loop process (1-99): the bridge (its watchdog and hold) first; the
#: robot's bridge unit has 50 too (docs/bridge.md).
LOOP_PRIORITY = {"bridge": 50, "twin": 50, "controller": 49}
KINDS = ("bridge", "twin", "controller", "server", "camera", "up", "campaign")
_POLICIES = {os.SCHED_OTHER: "other", os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr",
             getattr(os, "SCHED_BATCH", -1): "batch", getattr(os, "SCHED_IDLE", -2): "idle"}
_refusals: dict[int, list[str]] = {}  # pid -> why a request was refused (what isolate could not do)


def xneck_argv(*args: str) -> list[str]:
    """The argv of ``xneck <args>`` run by this very interpreter (the venv's, whatever PATH says)."""
    return [sys.executable, "-m", "server.cli", *args]


def start_xneck(args: list[str], log: Path, env: dict[str, str], *, append: bool = False,
                start_new_session: bool = False) -> subprocess.Popen:
    """``xneck <args>`` started as a child by this very interpreter: stdout and stderr to ``log``
    (appended to, or truncated), stdin ``/dev/null``, ``env`` its whole environment. The one place
    the orchestrators (campaign runner, `xneck up`) start a child; the test suite forks them from a
    server that has the imports and kernels loaded (tests/forkserver_client.py)."""
    with open(log, "ab" if append else "wb") as out:
        return subprocess.Popen(xneck_argv(*args), stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=env, start_new_session=start_new_session)


#: prctl(2) option: the signal the kernel sends a process when the thread that started it dies.
PR_SET_PDEATHSIG = 1
#: Set by a supervisor (``xneck up``) in a child's environment: its own pid, whose death stops the child.
ENV_PARENT = "XNECK_DIE_WITH_PARENT"


def die_with_parent(parent_pid: int) -> None:
    """This process gets SIGTERM (its clean stop: drives off, archive closed) when ``parent_pid``,
    the process that started it, dies, however it dies (audit of 2026-11-26: a ``kill -9`` or a
    hangup of ``xneck up`` left the console, bridge and controller running under init, and the
    next ``xneck up`` joined them). Set by the child itself at start-up, not in a ``preexec_fn``
    (unsafe in a parent with threads, as Zenoh's are). Linux only; elsewhere nothing."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the prctl: nothing will signal us
        os.kill(os.getpid(), signal.SIGTERM)


def die_with_parent_from_env() -> None:
    """:func:`die_with_parent` for the pid in ``XNECK_DIE_WITH_PARENT``, if any (taken out of the
    environment: this process's own children answer to it, not to its parent)."""
    value = os.environ.pop(ENV_PARENT, "")
    if value.isdigit():
        die_with_parent(int(value))


#: What :func:`stop_child` answers for a child that SIGKILL did not end within the grace period.
STILL_EXITING = "killed, still exiting"


def stop_child(proc: subprocess.Popen, grace_s: float) -> str:
    """SIGTERM, then SIGKILL after ``grace_s`` seconds. Returns ``""`` if it stopped on SIGTERM (or
    had ended), ``"killed"`` if it had to be killed, :data:`STILL_EXITING` if even SIGKILL had not
    ended it after another ``grace_s``. Never raises for that: a killed process whose threads
    cannot run their exit (a CPU starved by real-time work, a thread in the kernel) had raised
    ``TimeoutExpired`` out of ``xneck up``'s clean-up, which then stopped none of the other
    children (audit of 2026-11-30), and out of a campaign runner's, which then recorded nothing."""
    if proc.poll() is not None:
        return ""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(grace_s)
        return ""
    except subprocess.TimeoutExpired:
        return "killed" if kill_child(proc, grace_s) else STILL_EXITING


def kill_child(proc: subprocess.Popen, wait_s: float) -> bool:
    """SIGKILL, then wait up to ``wait_s`` seconds: whether it has ended (False: still exiting, to
    be judged again later; it never raises for that)."""
    with contextlib.suppress(ProcessLookupError):
        proc.kill()
    try:
        proc.wait(wait_s)
        return True
    except subprocess.TimeoutExpired:
        return False


def process_state(pid: int) -> str:
    """What the kernel says process ``pid`` is doing, for a message: ``"state T, in
    do_signal_stop"`` (/proc's state letter and the kernel function it waits in), or why it
    cannot say."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        state = stat[stat.rindex(")") + 2:].split()[0]
        wchan = Path(f"/proc/{pid}/wchan").read_text().strip()
    except (OSError, ValueError, IndexError) as exc:
        return f"its state unreadable: {getattr(exc, 'strerror', None) or exc}"
    return f"state {state}" + (f", in {wchan}" if wchan and wchan != "0" else "")


def exit_how(returncode: int) -> str:
    """How a child ended, from its ``Popen.returncode``: ``"signal SIGKILL"`` for a negative one
    (killed by that signal), ``"code 1"`` otherwise."""
    if returncode < 0:
        try:
            return f"signal {signal.Signals(-returncode).name}"
        except ValueError:
            return f"signal {-returncode}"
    return f"code {returncode}"


def log_tail(path: Path, lines: int) -> str:
    """The last ``lines`` lines of a child's log ('' if it cannot be read)."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


#: Above any CPU number a kernel gives (CONFIG_NR_CPUS is at most 8192): a range to it is a typo.
MAX_CPU = 8191


def _parse_cpu_list(text: str) -> set[int]:
    """``"0-2,5"`` (the kernel's CPU list format) -> {0, 1, 2, 5}; ValueError for anything else
    (a range backwards or past :data:`MAX_CPU`: "0-100000000000" was enumerated for minutes)."""
    cpus: set[int] = set()
    for part in text.strip().split(","):
        if part:
            lo, _, hi = part.partition("-")
            first, last = int(lo), int(hi or lo)
            if not 0 <= first <= last <= MAX_CPU:
                raise ValueError(f"CPU range {part!r}")
            cpus.update(range(first, last + 1))
    return cpus


def machine_cpus() -> set[int]:
    """The CPUs this machine (or this container's cpuset) offers, whatever this very process's
    affinity: the console that isolates a campaign's processes runs off the loop's CPU itself."""
    for path in ("/sys/fs/cgroup/cpuset.cpus.effective", "/sys/devices/system/cpu/online"):
        with contextlib.suppress(OSError, ValueError):
            cpus = _parse_cpu_list(Path(path).read_text())
            if cpus:
                return cpus
    return set(range(os.cpu_count() or 1))


def cpu_split(cpus: set[int] | None = None) -> tuple[set[int], set[int]]:
    """(the loop's CPUs, everyone else's) out of ``cpus`` (default: :func:`machine_cpus`): those
    ``$XNECK_LOOP_CPUS`` names, else the last CPU, for the loop and the rest for the others; one
    CPU is shared by all. A list naming no CPU of ``cpus``, or all of them, or that does not
    parse, is refused (:func:`loop_cpus_refusal`) and the last CPU is the loop's."""
    cpus = machine_cpus() if cpus is None else set(cpus)
    if len(cpus) < 2:
        return cpus, cpus
    loop = _named_loop_cpus(cpus)[0] or {max(cpus)}
    return loop, cpus - loop


def loop_cpus_refusal(cpus: set[int] | None = None) -> str:
    """Why ``$XNECK_LOOP_CPUS`` is not used for the loop's CPUs out of ``cpus`` ('' if it is, or
    is not set)."""
    return _named_loop_cpus(machine_cpus() if cpus is None else set(cpus))[1]


def _named_loop_cpus(cpus: set[int]) -> tuple[set[int], str]:
    """(the CPUs of ``cpus`` that ``$XNECK_LOOP_CPUS`` names, '') if they leave some to the others;
    (empty, why not) if the list does not parse or leaves none; (empty, '') if it is not set."""
    value = os.environ.get(ENV_LOOP_CPUS, "").strip()
    if not value:
        return set(), ""
    try:
        chosen = _parse_cpu_list(value) & cpus
    except ValueError:
        return set(), f"{ENV_LOOP_CPUS}={value[:40]!r} is no CPU list (e.g. 3 or 2-3): the last CPU is the loop's"
    if not chosen or chosen == cpus:
        return set(), (f"{ENV_LOOP_CPUS}={value[:40]!r} leaves no CPU to the loop or none to the others (this "
                       f"machine's: {sorted(cpus)}): the last CPU is the loop's")
    return chosen, ""


def _tids(pid: int) -> list[int]:
    """The threads of process ``pid`` (just ``pid`` where /proc cannot say)."""
    try:
        return sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return [pid]


def isolate(pid: int, kind: str, realtime: bool = True) -> dict[str, Any]:
    """Schedule process ``pid`` as its ``kind`` asks (module docstring) and return what it got
    (:func:`scheduling`). ``realtime=False``: its CPUs only; a loop process started with
    :func:`loop_environ` then takes its real-time priority itself once set up (raised at its exec,
    it computed its imports and caches for seconds at SCHED_FIFO on the loop's CPU, above another
    stack's controller there, which was killed as hung: fresh-user audit of 2026-12-01). Call it
    right after the process started: it sets every thread the
    process has by then (the interpreter may already have started some, e.g. when this caller
    was slow to run), and the threads it starts later inherit. A thread that made itself nicer
    than its process's main thread (the bridge's hold worker, which must not run at real-time
    priority) is left as it is; the main thread's nice is the reference, not 0, because a
    process started under ``nice`` passes its nice to every thread it starts."""
    refused: list[str] = []
    if os.environ.get(ENV_REALTIME, "1") == "0":
        refused.append(f"{ENV_REALTIME}=0: scheduling left alone")
    else:
        if why := loop_cpus_refusal():
            refused.append(why)
        loop_cpus, other_cpus = cpu_split()
        is_loop = kind in LOOP_PRIORITY
        base_nice = _nice(pid)
        for tid in _tids(pid):
            try:
                os.sched_setaffinity(tid, loop_cpus if is_loop else other_cpus)
            except ProcessLookupError:
                continue  # a thread that ended meanwhile
            except OSError as exc:
                refused.append(f"CPU affinity: {exc.strerror or exc}")
            if not is_loop or not realtime or (tid != pid and _nice(tid) > base_nice):
                continue
            try:
                refused.extend(fifo_or_nice(tid, LOOP_PRIORITY[kind]))
            except ProcessLookupError:
                continue
    _refusals[pid] = sorted(set(refused))
    return scheduling(pid, kind)


def loop_environ(kind: str) -> dict[str, str]:
    """What the environment of a ``kind`` process started with ``isolate(..., realtime=False)``
    needs to take its loop's real-time priority itself at its loop's start
    (:func:`bridge.runtime.take_loop_priority`): nothing for other kinds or ``XNECK_REALTIME=0``."""
    if kind not in LOOP_PRIORITY or os.environ.get(ENV_REALTIME, "1") == "0":
        return {}
    return {ENV_LOOP_PRIORITY: str(LOOP_PRIORITY[kind])}


def _nice(tid: int) -> int:
    try:
        return os.getpriority(os.PRIO_PROCESS, tid)
    except OSError:
        return 0


def isolate_self(kind: str = "server") -> dict[str, Any]:
    """:func:`isolate` of this very process (the console: off the loop's CPU)."""
    return isolate(os.getpid(), kind)


def scheduling(pid: int, kind: str = "") -> dict[str, Any]:
    """What process ``pid`` got, read back from the kernel: policy, real-time priority, nice,
    CPUs, and what was refused when it was isolated (empty if it was not isolated here)."""
    out: dict[str, Any] = {"pid": pid, "kind": kind}
    try:
        out["policy"] = _POLICIES.get(os.sched_getscheduler(pid), "unknown")
        out["rt_priority"] = os.sched_getparam(pid).sched_priority
        out["nice"] = os.getpriority(os.PRIO_PROCESS, pid)
        out["cpus"] = sorted(os.sched_getaffinity(pid))
    except OSError as exc:
        out["error"] = exc.strerror or str(exc)
    out["refused"] = _refusals.get(pid, [])
    return out


def _kind_of(argv: list[str]) -> str:
    """``bridge`` for ``python -m server.cli bridge ...`` or ``xneck bridge ...``, else ''."""
    for i, arg in enumerate(argv[:-1]):
        if arg == "server.cli" or arg.endswith("/xneck") or arg == "xneck":
            return argv[i + 1] if argv[i + 1] in KINDS else ""
    return ""


def local_processes() -> list[dict[str, Any]]:
    """:func:`scheduling` of every xneck process on this machine (found by its command line),
    this console included."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        with contextlib.suppress(OSError):
            argv = Path(f"/proc/{entry}/cmdline").read_bytes().decode(errors="replace").split("\0")
            kind = _kind_of(argv)
            if kind or int(entry) == os.getpid():
                found.append(scheduling(int(entry), kind or "server"))
    return sorted(found, key=lambda p: p["pid"])


def thread_scheduling(pid: int) -> dict[str, int]:
    """How many threads of process ``pid`` run under each policy, e.g. ``{"fifo 49": 11}``:
    :func:`isolate` sets the threads there are and the later ones inherit, so this is where
    a thread that demoted itself shows (and one isolation missed would)."""
    counts: dict[str, int] = {}
    if not Path(f"/proc/{pid}").exists():
        return counts
    for tid in _tids(pid):
        with contextlib.suppress(OSError):
            policy = _POLICIES.get(os.sched_getscheduler(tid), "unknown")
            prio = os.sched_getparam(tid).sched_priority
            key = f"{policy} {prio}" if prio else policy
            counts[key] = counts.get(key, 0) + 1
    return counts
