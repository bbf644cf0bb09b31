"""Machine-stall probe (issue 21): did the machine itself stop running this CPU, or was it us?

Run as a process of its own, pinned to one CPU at a real-time priority above the loop's
(``SCHED_FIFO`` 60, when permitted): it sleeps 1 ms at a time and records every wake-up later
than ``threshold_ms`` after the previous one, with its wall-clock times (``time.time_ns``, the
clock the observers use) and the CPU's steal time (``/proc/stat``, time the hypervisor ran
someone else) meanwhile. Nothing of this project can hold it up: a gap it sees is the VM or the
kernel. It costs a few µs per ms. Prints one JSON object when done.

``python benchmarks/_stall_probe.py CPU SECONDS [THRESHOLD_MS]``; SIGTERM ends it early (it still prints).
"""

from __future__ import annotations

import gc
import json
import os
import signal
import sys
import time

PROBE_PRIORITY = 60  # above the loop's processes (server/child_processes.py LOOP_PRIORITY)


def steal_ms(cpu: int) -> float:
    """The CPU's steal time so far (ms; /proc/stat counts in USER_HZ ticks)."""
    with open("/proc/stat") as f:
        for line in f:
            if line.startswith(f"cpu{cpu} "):
                return int(line.split()[8]) * 1e3 / os.sysconf("SC_CLK_TCK")
    return 0.0


def pin(cpus: set[int], priority: int, tid: int = 0) -> str:
    """Thread ``tid`` (0: this one; the threads it starts later inherit) on ``cpus`` at
    SCHED_FIFO ``priority`` (0: back to the ordinary policy); what it got, refusals named (the
    benchmark's observer uses it too)."""
    got = []
    try:
        os.sched_setaffinity(tid, cpus)
        got.append(f"CPUs {sorted(cpus)}")
    except OSError as exc:
        got.append(f"affinity refused: {exc.strerror}")
    policy = os.SCHED_FIFO if priority else os.SCHED_OTHER
    try:
        os.sched_setscheduler(tid, policy, os.sched_param(priority))
        got.append(f"fifo {priority}" if priority else "other")
    except OSError as exc:
        got.append(f"SCHED_FIFO refused: {exc.strerror}")
    return ", ".join(got)


def main() -> None:
    cpu, seconds = int(sys.argv[1]), float(sys.argv[2])
    threshold_ns = int(float(sys.argv[3] if len(sys.argv) > 3 else 2.0) * 1e6)
    got = pin({cpu}, PROBE_PRIORITY)
    stopped: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, _frame: stopped.append(signum))
    gc.disable()  # nothing here may stall the probe itself
    clock, sleep = time.time_ns, time.sleep
    steal0 = steal_last = steal_ms(cpu)
    gaps: list[tuple[int, int, float]] = []  # (before, after, steal ms since the last reading)
    wakeups = 0
    now = clock()
    end = now + int(seconds * 1e9)
    next_steal = now + 1_000_000_000
    while now < end and not stopped:
        prev = now
        sleep(0.001)
        now = clock()
        wakeups += 1
        if now - prev > threshold_ns or now >= next_steal:
            steal = steal_ms(cpu)
            if now - prev > threshold_ns:
                gaps.append((prev, now, steal - steal_last))
            steal_last, next_steal = steal, now + 1_000_000_000
    print(json.dumps({"cpu": cpu, "got": got, "wakeups": wakeups, "threshold_ms": threshold_ns / 1e6,
                      "steal_ms": steal_ms(cpu) - steal0, "gaps": gaps}))


if __name__ == "__main__":
    main()
