"""Where a command's CPU goes, by kind of process: what to cut when the suite's time grows.

The suite runs on two xdist workers and is CPU-bound on two CPUs (docs/testing.md), so its time is
its CPU seconds over two. ``XNECK_TEST_TIMELINE`` says which module took them, counting only the
worker and the children it waited for; this says which processes did: the workers' own tests, the
stacks' bridges, controllers and consoles, pyright, Chromium, pip, numba's warm-up...

It runs COMMAND, becomes its child subreaper (PR_SET_CHILD_SUBREAPER: an orphaned grandchild stays
below it, not below init; reaped as soon as it exits, as init would) and samples every descendant's
CPU (utime + stime, /proc/PID/stat) every ``--period-s``. A process is counted at its last sample
(an orphan of its own at its exit): what it ran after that (up to one period) and a process shorter
than a period are missed, and come out as "not sampled" against the command's whole CPU (getrusage
of its waited-for children). Prints, per kind, CPU seconds, share of the total and processes;
``--json FILE`` writes the same. Then the machine's busy CPU over the same span (/proc/stat) and
the processes outside the command that took most of it (kernel threads, a VM's agent). Standard library only, so a fresh clone's set-up can be measured
too. Run: ``python3 benchmarks/suite_cpu.py [--period-s 0.25] [--json FILE] -- bash .ci/run``.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import itertools
import json
import os
import re
import resource
import signal
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

TICKS_PER_S = os.sysconf("SC_CLK_TCK")
PR_SET_CHILD_SUBREAPER = 36

#: Kinds that say nothing of what runs: named with their parent's kind.
ANONYMOUS = frozenset({"python -c", "python multiprocessing child", "python", "sh", "bash"})

_XNECK = re.compile(r"(?:-m server\.cli|/xneck)\s+([a-z][a-z-]*)")


def kind(cmdline: str) -> str:
    """The kind of process a command line (NUL-separated words joined by spaces) is: ``xneck
    <command>`` for the project's processes (``python -m server.cli`` or the ``xneck`` script,
    forked ones included: they carry the command line they stand for), else the tool's name."""
    words = cmdline.split()
    if not words:
        return "(no command line)"
    if match := _XNECK.search(cmdline):
        return f"xneck {match.group(1)}"
    if "xneck_forkserver" in cmdline:
        return "fork server (tests)"
    if "exec(eval(sys.stdin.readline()" in cmdline:
        return "pytest worker (tests run in it)"
    if "-m pytest" in cmdline or Path(words[0]).name in ("pytest", "py.test"):
        return "pytest"
    if "pyright" in cmdline or Path(words[0]).name == "node":
        return "pyright"
    if "chrom" in Path(words[0]).name or (words[0] == "/proc/self/exe" and "--type=" in cmdline):  # its helpers
        return "chromium"
    if "controller.warmup" in cmdline:
        return "numba warm-up (set-up)"
    if re.search(r"-m pip\b|/pip3?\b", cmdline):
        return "pip"
    if Path(words[0]).name == "uv":  # .ci/setup's install
        return "uv"
    if "from multiprocessing" in cmdline:  # spawn_main, the resource tracker, a forkserver
        return "python multiprocessing child"
    if "distributed" in cmdline or "dask" in cmdline:
        return "dask"
    if "ruff" in cmdline:
        return "ruff"
    if "lint-imports" in cmdline or "importlinter" in cmdline:
        return "import-linter"
    name = Path(words[0]).name
    if name.startswith("python"):
        for flag, value in itertools.pairwise(words[1:]):
            if flag in ("-c", "-m"):
                return f"python -m {value}" if flag == "-m" else "python -c"
        script = next((w for w in words[1:] if not w.startswith("-")), "")
        return f"python {Path(script).name}" if script else "python"
    return name


@dataclass
class Tally:
    """CPU ticks per kind: finished processes' last samples, and the live ones'."""

    done: Counter = field(default_factory=Counter)
    processes: Counter = field(default_factory=Counter)
    live: dict[tuple[int, int], tuple[str, int]] = field(default_factory=dict)  # (pid, start) → (kind, ticks)
    #: processes outside the command (the machine's: kernel threads, a VM's agent): (pid, start) →
    #: [name, ticks at the first sample, ticks at the latest]
    outside: dict[tuple[int, int], list] = field(default_factory=dict)

    def sample(self, root: int) -> None:
        stats: dict[int, tuple[int, int, int]] = {}  # pid → (ppid, start, ticks)
        comms: dict[int, str] = {}
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                raw = Path(f"/proc/{entry}/stat").read_bytes()
            except OSError:
                continue
            fields = raw[raw.rindex(b")") + 2:].split()
            comms[int(entry)] = raw[raw.index(b"(") + 1:raw.rindex(b")")].decode(errors="replace")
            stats[int(entry)] = (int(fields[1]), int(fields[19]), int(fields[11]) + int(fields[12]))
        alive: set[tuple[int, int]] = set()
        for pid, (_, start, ticks) in stats.items():
            if pid == root or not _descends(pid, root, stats):  # not the sampler itself
                seen = self.outside.setdefault((pid, start), [f"[{comms[pid]}]", ticks, ticks])
                seen[2] = ticks
                continue
            key = (pid, start)
            alive.add(key)
            if key in self.live:
                self.live[key] = (self.live[key][0], ticks)
                continue
            try:
                cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            name = kind(cmdline) if cmdline else f"[{comms[pid]}]"  # a zombie has none
            ppid = stats[pid][0]
            parent = self.live.get((ppid, stats[ppid][1])) if ppid in stats else None
            if parent is not None and name in ANONYMOUS:  # say whose it is
                name = f"{name} (from {parent[0]})"
            self.live[key] = (name, ticks)
            self.processes[name] += 1
        for key in [k for k in self.live if k not in alive]:
            name, ticks = self.live.pop(key)
            self.done[name] += ticks

    def exited(self, pid: int) -> bool:
        """Whether ``pid`` is a zombie; if so its last CPU is counted (it may be reaped then)."""
        try:
            raw = Path(f"/proc/{pid}/stat").read_bytes()
        except OSError:
            return False
        fields = raw[raw.rindex(b")") + 2:].split()
        if fields[0] != b"Z":
            return False
        key, ticks = (pid, int(fields[19])), int(fields[11]) + int(fields[12])
        if key in self.live:
            name = self.live.pop(key)[0]
        else:  # shorter than a period: never sampled alive
            name = "[" + raw[raw.index(b"(") + 1:raw.rindex(b")")].decode(errors="replace") + "]"
            self.processes[name] += 1
        self.done[name] += ticks
        return True

    def outside_s(self) -> Counter:
        """CPU s per name of the processes outside the command, while it ran (from each one's first sample)."""
        out: Counter = Counter()
        for name, first, last in self.outside.values():
            out[name] += (last - first) / TICKS_PER_S
        return out

    def totals_s(self) -> Counter:
        total = Counter(self.done)
        for name, ticks in self.live.values():
            total[name] += ticks
        return Counter({name: ticks / TICKS_PER_S for name, ticks in total.items()})


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _descends(pid: int, root: int, stats: dict[int, tuple[int, int, int]]) -> bool:
    seen = 0
    while pid != root:
        if pid not in stats or pid <= 1 or seen > 64:
            return False
        pid, seen = stats[pid][0], seen + 1
    return True


def _machine_busy_s() -> float:
    """CPU s every CPU of the machine spent not idle since boot (/proc/stat's cpu line, proc(5))."""
    ticks = [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)  # idle, iowait
    return (sum(ticks[:8]) - idle) / TICKS_PER_S  # guest time is counted in user already


def run(command: list[str], period_s: float) -> tuple[int, Counter, Counter, float, float, float, Counter]:
    """Runs ``command`` to its end, sampling; returns (exit code, CPU s per kind, processes per
    kind, the command's whole CPU s, wall s, the machine's busy CPU s meanwhile, CPU s of the
    processes outside the command per name)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER)")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started, busy = time.monotonic(), _machine_busy_s()
    tally = Tally()
    proc = subprocess.Popen(command)
    me = os.getpid()
    def reap(_signum: int, _frame: object) -> None:
        # An orphan's zombie would stay "alive" to os.kill(pid, 0) and to a test waiting for it to
        # go: init reaps at once, and so must a subreaper. Counted first; never the command, whose
        # status Popen collects.
        for pid in _children(me):
            if pid != proc.pid and tally.exited(pid):
                with contextlib.suppress(ChildProcessError):
                    os.waitpid(pid, os.WNOHANG)

    signal.signal(signal.SIGCHLD, reap)
    try:
        while proc.poll() is None:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGCHLD})  # the handler counts too
            tally.sample(me)
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGCHLD})
            time.sleep(period_s)
    except KeyboardInterrupt:
        proc.send_signal(signal.SIGINT)
        proc.wait()
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    tally.sample(me)
    while True:  # orphans that outlived the command were re-parented here: reap them
        try:
            if os.waitpid(-1, os.WNOHANG) == (0, 0):
                break
        except ChildProcessError:
            break
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    whole = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return (proc.returncode, tally.totals_s(), tally.processes, whole, time.monotonic() - started,
            _machine_busy_s() - busy, tally.outside_s())


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--period-s", type=float, default=0.25, help="sampling period (s)")
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="the command to run, after --")
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command: suite_cpu.py [options] -- COMMAND ...")
    if not 0.01 <= args.period_s <= 10:
        parser.error("--period-s: between 0.01 and 10 s")
    try:
        code, seconds, processes, whole, wall, busy, outside = run(command, args.period_s)
    except OSError as exc:  # not found, not executable: as a shell says it
        print(f"suite_cpu.py: {command[0]}: {exc.strerror}", file=sys.stderr)
        return 127
    sampled = sum(seconds.values())
    print(f"\n{' '.join(command)}: exit {code}, {wall:.0f} s wall, {whole:.0f} CPU-s in all "
          f"({whole / max(wall, 1e-9):.2f} CPUs on average, {os.cpu_count()} here)")
    print(f"{'CPU s':>8} {'share':>6} {'procs':>6}  kind")
    for name, s in seconds.most_common():
        print(f"{s:8.1f} {100 * s / max(whole, 1e-9):5.1f}% {processes[name]:6d}  {name}")
    print(f"{whole - sampled:8.1f} {100 * (whole - sampled) / max(whole, 1e-9):5.1f}% {'':>6}  not sampled "
          f"(after a process's last sample, or shorter than {args.period_s} s)")
    # What the machine spent beside it: a VM's memory monitor (kdamond) and agent took about 8 % of
    # a suite run's CPU on 2026-12-02, which no change to the suite takes back.
    print(f"\nthe machine meanwhile: {busy:.0f} CPU-s busy, {busy - whole:.0f} outside the command; "
          "the largest outside it:")
    for name, s in outside.most_common(5):
        print(f"{s:8.1f} {100 * s / max(busy, 1e-9):5.1f}% of the machine's  {name}")
    if args.json:
        args.json.write_text(json.dumps({"command": command, "exit": code, "wall_s": wall, "cpu_s": whole,
                                         "machine_busy_s": busy, "outside": dict(outside.most_common(20)),
                                         "kinds": {n: {"cpu_s": s, "processes": processes[n]}
                                                   for n, s in seconds.most_common()}}, indent=1))
    return code


if __name__ == "__main__":
    sys.exit(main())
