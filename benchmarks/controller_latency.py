"""Controller speed (issues 4 and 21): per-tick compute time, and state-to-command latency on the bus.

1. In process: the time of one ComputedTorque.step (law 3, the most expensive: estimation with
   eq. 58, model at α̂ and α^d, distribution; one compiled kernel, controller/kernel.py), median
   and p99, on the encoder angles of a recorded run. Target (issue 21) p99 <= 0.1 ms. For
   comparison, the numpy reference functions of its parts (not on the hot path any more), and
   Z by central differences of l_c, which the exact jets replace.
2. Over Zenoh on loopback against the real-time twin (500 Hz, `xneck twin`) with `xneck
   controller --law 2` following a trajectory for ``--seconds`` (default 60): state-to-command
   latency seen by an observer session (p50, p99), the share of states answered within a period,
   the controller's own stage times (decode, law, encode, put; its ``ControllerTiming``) and its
   deadline misses. Targets (issue 21): p99 <= 1 ms, 0 deadline misses over 60 s.
   ``--baseline-tree DIR`` runs an older controller first (``git archive COMMIT | tar -x -C DIR``)
   and prints the ratios: the machine's load is the same for both.

   Scheduling: by default the twin and the controller get what `xneck up` gives them
   (``server.child_processes.isolate``: SCHED_FIFO and the last CPU), and this observer (it plays
   the bridge's part: it timestamps states and commands) real-time priority below theirs on the
   other CPUs, so the other jobs of a shared machine, at normal priority, hold up neither the loop
   nor its measurement. What each process and each of its threads got is printed, refusals
   included. ``--no-isolate`` leaves scheduling alone, to compare.
   Stalls: a probe process per CPU (``_stall_probe.py``, above the loop's priority) records when
   the machine itself stopped running that CPU (and the steal time): each late answer is printed
   as during such a stall or not — the VM's doing, or ours.
Run: ``.venv/bin/python benchmarks/controller_latency.py [--seconds 60] [--no-isolate] [--baseline-tree DIR]``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
import _repo  # noqa: E402, F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing  # noqa: E402  (benchmarks/ is sys.path[0] when run as a script)
from _stall_probe import pin  # noqa: E402

from bridge import bus  # noqa: E402
from bridge.session import free_tcp_port, open_session  # noqa: E402
from controller.distribution import distribute, lower_bounds  # noqa: E402
from controller.laws import ComputedTorque, LawConfig  # noqa: E402
from controller.trajectory import Trajectory, control_test_trajectory  # noqa: E402
from server.child_processes import cpu_split, isolate, machine_cpus, scheduling, thread_scheduling  # noqa: E402
from twin.model import cables, dynamics  # noqa: E402
from twin.model.params import load_params  # noqa: E402
from twin.sim.simulator import Twin, TwinConfig  # noqa: E402

TARGET_P99_MS = 0.1  # issue 21
TARGET_LATENCY_P99_MS = 1.0
OBSERVER_PRIORITY = 40  # SCHED_FIFO, below the loop's (it must not delay what it measures)
LATE_MS = 2.0  # an answer later than a period


def in_process() -> None:
    params = load_params()
    traj = control_test_trajectory()
    twin = Twin(params, TwinConfig(camera=False))
    ctl = ComputedTorque(params, LawConfig(law=3))
    n = int(traj.duration_s * 500)
    ref = traj.sample(np.arange(1, n + 1) / 500)
    tick = twin.tick(np.zeros(4))
    step_t = np.empty(n)
    clock = time.perf_counter
    for k in range(n):
        t0 = clock()
        cmd = ctl.step(tick.theta_meas, ref.alpha[k], ref.alpha_dot[k], ref.alpha_ddot[k])
        step_t[k] = clock() - t0
        tick = twin.tick(cmd.f)
    print("controller benchmark, in process: law 3 on the §7 control test (14 s, 7000 ticks)")
    _, p99 = _timing.summary("ComputedTorque.step (whole tick)", step_t[100:], unit=1e-3, unit_name="ms")
    m, alpha, theta = ctl.model, cmd.alpha_hat, tick.theta_meas
    est = ctl.estimator
    print("  reference numpy parts (not on the hot path):")
    _timing.summary("  estimation (eq. 35 + eq. 58)", _timing.time_calls(
        lambda: est.update(theta, cmd.f, np.zeros(4)), 3000), unit=1e-3, unit_name="ms")
    _timing.summary("  model terms at α̂ and α^d", _timing.time_calls(
        lambda: (dynamics.evaluate(m, alpha), dynamics.evaluate(m, alpha, alpha)), 3000), unit=1e-3, unit_name="ms")
    Z = cables.Z(m, alpha)
    lower = lower_bounds(8.5, 2.0, np.zeros(4), np.zeros(4))
    _timing.summary("  tension distribution (eqs. 63-65)", _timing.time_calls(
        lambda: distribute(Z, np.ones(3), lower, 100.0, ctl.short, ctl.long), 3000), unit=1e-3, unit_name="ms")

    def fd_model():
        for i in range(3):
            e = np.zeros(3)
            e[i] = 1e-6
            cables.l_c(m, alpha + e) - cables.l_c(m, alpha - e)
        dynamics.evaluate(m, alpha)

    base = _timing.time_calls(fd_model, 3000)
    exact = _timing.time_calls(lambda: dynamics.evaluate(m, alpha), 3000)
    print(f"  baseline: Z by central differences costs {np.median(base) / np.median(exact):.1f}x the exact model terms")
    print(f"target: p99 <= {TARGET_P99_MS} ms -> {'meets' if p99 <= TARGET_P99_MS else 'MISSES'} ({p99:.3f} ms)")


def isolate_observer(realtime: bool = True) -> str:
    """Every thread of this process (the observer, Zenoh's included) at real-time priority below
    the loop's on the CPUs the loop does not use, or (``realtime`` False) back to the ordinary
    policy on every CPU; returns what the main thread got. Back to ordinary before the session
    closes: Zenoh's teardown, with every thread real-time on one CPU, was once seen spinning on
    it for minutes (a thread it waited for never ran)."""
    cpus, prio = (cpu_split()[1], OBSERVER_PRIORITY) if realtime else (machine_cpus(), 0)
    got = {}
    for tid in sorted(int(t) for t in os.listdir("/proc/self/task")):
        with contextlib.suppress(ProcessLookupError):
            got[tid] = pin(cpus, prio, tid)
    return got.get(os.getpid(), "")


def describe(name: str, pid: int) -> str:
    """What process ``pid`` and its threads got from the kernel, on one line."""
    got = scheduling(pid, name)
    if "error" in got:
        return f"  {name:<10s} pid {pid}: {got['error']}"
    prio = f" {got['rt_priority']}" if got["rt_priority"] else f" nice {got['nice']}"
    threads = ", ".join(f"{n} {k}" for k, n in sorted(thread_scheduling(pid).items()))
    refused = f"; refused: {'; '.join(got['refused'])}" if got["refused"] else ""
    return f"  {name:<10s} pid {pid}: {got['policy']}{prio}, CPUs {got['cpus']}; threads: {threads}{refused}"


def start_probes(seconds: float) -> list[subprocess.Popen]:
    """One :mod:`_stall_probe` per CPU of this machine, for ``seconds``."""
    return [subprocess.Popen([sys.executable, str(HERE / "_stall_probe.py"), str(cpu), str(seconds)],
                             stdout=subprocess.PIPE, text=True) for cpu in sorted(machine_cpus())]


def stall_report(probes: list[subprocess.Popen], late: list[tuple[int, int]]) -> None:
    """The machine's own stalls (the probes') and which late answers overlap one."""
    gaps: list[tuple[int, int, int]] = []  # (cpu, start ns, end ns)
    print("machine stalls seen by the probes (a CPU not running even a real-time task, "
          f"priority above the loop's, for more than {LATE_MS:.0f} ms):")
    for p in probes:
        p.terminate()  # the run is over: each prints what it saw
        out, _ = p.communicate(timeout=30)
        try:
            r = json.loads(out)
        except ValueError:
            print(f"  a probe failed (exit {p.returncode})")
            continue
        g = np.array([(b - a) * 1e-6 for a, b, _ in r["gaps"]])
        print(f"  CPU {r['cpu']} ({r['got']}): {len(g)} gaps, longest {g.max() if len(g) else 0:.1f} ms, "
              f"{np.sum(g > 10):d} longer than 10 ms; steal time {r['steal_ms']:.0f} ms, "
              f"of it during the gaps {sum(s for *_, s in r['gaps']):.0f} ms")
        gaps += [(r["cpu"], a, b) for a, b, _ in r["gaps"]]
    if not late:
        return
    during = sum(any(a < c1 and s0 < b for _, a, b in gaps) for s0, c1 in late)
    print(f"  of the {len(late)} answers later than {LATE_MS:.0f} ms, {during} overlap a machine stall "
          f"(the VM's or the kernel's doing), {len(late) - during} do not (the processes' doing: ours, or other real-time ones on the same CPU)")


def rt_cpu_ticks() -> dict[int, tuple[int, str]]:
    """CPU time so far (clock ticks) of the real-time threads (FIFO/RR) of every process on this
    machine, summed per process, with its command line: who else competes on the loop's CPU."""
    out: dict[int, tuple[int, str]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        with contextlib.suppress(OSError, ValueError, IndexError):
            total = 0
            for tid in os.listdir(f"/proc/{entry}/task"):
                stat = Path(f"/proc/{entry}/task/{tid}/stat").read_text()
                fields = stat[stat.rindex(")") + 2:].split()
                if int(fields[38]) in (os.SCHED_FIFO, os.SCHED_RR):  # policy
                    total += int(fields[11]) + int(fields[12])  # utime + stime
            if total:
                cmd = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                out[int(entry)] = (total, cmd.strip()[:90])
    return out


def rt_report(before: dict[int, tuple[int, str]], after: dict[int, tuple[int, str]], seconds: float,
              ours: set[int]) -> None:
    """Real-time CPU between two :func:`rt_cpu_ticks`, per process (% of one CPU): ours, and
    everyone else's (other stacks on this machine get SCHED_FIFO on the same CPU too; above 95 %
    of a CPU the kernel throttles every real-time task on it for the rest of each second)."""
    hz = os.sysconf("SC_CLK_TCK")
    used = {pid: (ticks - before.get(pid, (0, ""))[0]) / hz / seconds * 100 for pid, (ticks, _) in after.items()}
    mine = sum(u for pid, u in used.items() if pid in ours)
    others = sorted(((u, pid) for pid, u in used.items() if pid not in ours and u >= 1), reverse=True)
    print(f"real-time CPU over {seconds:.0f} s of the run (% of one CPU): this benchmark's processes {mine:.0f} %, "
          f"other real-time processes {sum(u for u, _ in others):.0f} %"
          + "".join(f"\n  {u:4.0f} %  pid {pid}: {after[pid][1]}" for u, pid in others[:6]))


def on_the_bus(seconds: float, controller_tree: Path | None = None, isolated: bool = True) -> dict[str, float]:
    """The bus run; ``controller_tree``: run `xneck controller` from that source tree (e.g. a
    ``git archive`` of an older commit) for a baseline measured beside this one; ``isolated``:
    schedule the twin and the controller as `xneck up` does (module docstring). Returns the
    observer's figures."""
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    waypoints = [[0, 0, 0], [40, 30, 20], [0, 0, 0], [-30, -20, -40], [0, 0, 0]]
    reps = max(1, int(seconds // 12))
    traj = Trajectory.from_degrees(waypoints * reps + [[0, 0, 0]], durations_s=2.0, dwell_s=1.0, name="bench")
    longest = 600.0  # s, the most a campaign may last (the controller refuses longer trajectories)
    if traj.duration_s > longest:  # the 10-minute soak: as many repetitions as fit
        reps = max(1, int(reps * longest / traj.duration_s))
        while reps > 1 and Trajectory.from_degrees(waypoints * reps + [[0, 0, 0]], durations_s=2.0,
                                                   dwell_s=1.0).duration_s > longest:
            reps -= 1
        traj = Trajectory.from_degrees(waypoints * reps + [[0, 0, 0]], durations_s=2.0, dwell_s=1.0, name="bench")
        print(f"--seconds {seconds:g}: the trajectory is cut to {traj.duration_s:.0f} s, the longest a campaign may last")
    tmp = Path(tempfile.mkdtemp(prefix="xneck-bench-"))
    (tmp / "traj.json").write_text(traj.to_json())
    state_rx: dict[float, int] = {}
    answers: list[tuple[int, int]] = []  # (state seen, its command seen), time.time_ns
    last_status: list[bus.ControllerStatus] = []
    timings: list[bus.ControllerTiming] = []
    state_stamps: list[float] = []
    answered_stamps: list[float] = []
    lock = threading.Lock()

    def on_state(sample):
        msg = bus.decode(bus.MotorState, sample.payload.to_bytes())
        with lock:
            state_rx[msg.stamp_s] = time.time_ns()
            state_stamps.append(msg.stamp_s)

    def on_cmd(sample):
        now = time.time_ns()
        msg = bus.decode(bus.ForceCommand, sample.payload.to_bytes())
        with lock:
            sent = state_rx.pop(msg.stamp_s, None)
            if sent is not None:
                answers.append((sent, now))
                answered_stamps.append(msg.stamp_s)

    def on_status(sample):
        # The counts start again at zero when the campaign ends: keep the status with the most.
        msg = bus.decode(bus.ControllerStatus, sample.payload.to_bytes())
        if not last_status or (msg.deadline_misses, msg.overruns) >= (last_status[0].deadline_misses,
                                                                     last_status[0].overruns):
            last_status[:] = [msg]

    def on_timing(sample):
        timings.append(bus.decode(bus.ControllerTiming, sample.payload.to_bytes()))

    common = ["--listen", "tcp/127.0.0.1:0", "--connect", hub]
    probes = start_probes(traj.duration_s + 20)
    rt: list[tuple[float, dict[int, tuple[int, str]]]] = []  # (time, rt_cpu_ticks()) 10 s in, 2 s before the end
    sched: list[str] = []
    with open_session(listen=[hub], connect=[]) as s:
        subs = [s.declare_subscriber(bus.MOTOR_STATE, on_state), s.declare_subscriber(bus.MOTOR_COMMAND, on_cmd),
                s.declare_subscriber(bus.CONTROLLER_STATUS, on_status), s.declare_subscriber(bus.CONTROLLER_TIMING, on_timing)]
        py = [sys.executable, "-m", "server.cli"]
        twin = subprocess.Popen([*py, "twin", "--seed", "1", *common], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if isolated:
            isolate(twin.pid, "twin")
        ctl = subprocess.Popen([*py, "controller", "--law", "2", "--trajectory", str(tmp / "traj.json"), *common],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=controller_tree)
        if isolated:
            isolate(ctl.pid, "controller")
            isolate_observer()  # after the children: a real-time parent would starve a child on its CPU
        try:
            with contextlib.suppress(subprocess.TimeoutExpired):
                ctl.wait(timeout=10)  # their threads are up by then: what each got
            sched = [describe("twin", twin.pid), describe("controller", ctl.pid), describe("observer", os.getpid())]
            rt.append((time.monotonic(), rt_cpu_ticks()))
            with contextlib.suppress(subprocess.TimeoutExpired):
                ctl.wait(timeout=max(traj.duration_s - 12, 1))
            rt.append((time.monotonic(), rt_cpu_ticks()))
            ctl.wait(timeout=traj.duration_s + 60)
        finally:
            ours = {os.getpid(), twin.pid, ctl.pid, *(p.pid for p in probes)}
            if isolated:
                isolate_observer(realtime=False)
            for p in (ctl, twin):
                p.terminate()
                p.wait(10)
            for sub in subs:
                sub.undeclare()
    status = last_status[0] if last_status else None
    print(f"\ncontroller benchmark, on the bus: real-time twin at 500 Hz + `xneck controller --law 2`, "
          f"{traj.duration_s:.0f} s" + (f", controller from {controller_tree}" if controller_tree else "")
          + ("" if isolated else ", --no-isolate"))
    print("scheduling (read back from the kernel 10 s into the run):", *sched, sep="\n")
    if not answers or status is None:
        print("no commands observed: the run failed")
        for p in probes:
            p.kill()
        return {}
    lat = np.array([(c - a) * 1e-6 for a, c in answers])
    slow = np.nonzero(lat > LATE_MS)[0]
    # Every state is owed a command within a period: the share that got one (a controller that
    # answers only some states must not look faster for it); those from its first answer to its
    # last (before, it was starting; after, it had finished).
    owed = int(np.sum((np.array(state_stamps) >= min(answered_stamps)) & (np.array(state_stamps) <= max(answered_stamps))))
    on_time = int(np.sum(lat <= LATE_MS)) / max(owed, 1)
    print(f"states seen {len(state_stamps)}, {owed} of them while the controller ran, answered {len(lat)}, "
          f"answered within 2 ms: {100 * on_time:.2f} %")
    print(f"state-to-command latency over {len(lat)} ticks: p50 {np.percentile(lat, 50):.3f} ms, "
          f"p99 {np.percentile(lat, 99):.3f} ms, max {lat.max():.3f} ms; above 2 ms: {len(slow)} ticks"
          + (f" (first at tick {slow[0]}, last at tick {slow[-1]})" if len(slow) else ""))
    stage_report(timings)
    stall_report(probes, [answers[i] for i in slow])
    if len(rt) == 2:
        rt_report(rt[0][1], rt[1][1], rt[1][0] - rt[0][0], ours)
    p99 = float(np.percentile(lat, 99))
    print(f"controller: deadline misses {status.deadline_misses}, compute overruns {status.overruns}; "
          f"targets p99 <= {TARGET_LATENCY_P99_MS} ms and no deadline miss -> "
          f"{'meets' if status.deadline_misses == 0 and p99 <= TARGET_LATENCY_P99_MS else 'MISSES'}")
    figures = {"latency_p50_ms": float(np.percentile(lat, 50)), "latency_p99_ms": float(np.percentile(lat, 99)),
               "commands": len(lat), "deadline_misses": status.deadline_misses, "overruns": status.overruns,
               "answered_within_2ms": on_time}
    print(json.dumps(figures))
    return figures


def stage_report(timings: list[bus.ControllerTiming]) -> None:
    """The controller's own view (``xneck/controller/timing``, about 1 Hz): each stage's p50/p99
    (the worst window's p99) and its latency from the state's arrival at its subscriber."""
    windows = [t for t in timings if t.window_ticks > 0]
    if not windows:
        print("controller timing: no ControllerTiming received")
        return
    ticks = sum(t.window_ticks for t in windows)
    print(f"controller's own timing over {ticks} ticks ({len(windows)} windows of about 1 s), "
          f"{sum(t.window_skipped for t in windows)} stale states of bursts skipped:")
    for stage in ("decode", "law", "encode", "put"):
        p50 = float(np.median([t.stage_p50_ms[stage] for t in windows]))
        p99 = max(t.stage_p99_ms[stage] for t in windows)
        print(f"  {stage:<8s} median p50 {p50:.3f} ms   worst p99 {p99:.3f} ms")
    counts = np.sum([t.latency_counts for t in windows], axis=0)
    edges = windows[0].bin_edges_ms
    above = int(counts[np.searchsorted(edges, 2.0):].sum())
    print(f"  arrival to put: median p50 {np.median([t.latency_p50_ms for t in windows]):.3f} ms, "
          f"worst p99 {max(t.latency_p99_ms for t in windows):.3f} ms, max {max(t.latency_max_ms for t in windows):.3f} ms, "
          f"{above} ticks >= 2 ms; tick period p99 {max(t.period_p99_ms for t in windows):.3f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="length of the bus run (s)")
    ap.add_argument("--skip-bus", action="store_true")
    ap.add_argument("--no-isolate", action="store_true",
                    help="leave scheduling alone (no SCHED_FIFO, no CPU affinity), to compare with the default")
    ap.add_argument("--baseline-tree", type=Path, default=None,
                    help="also run the bus part with the controller of this source tree (e.g. `git archive "
                         "COMMIT | tar -x -C DIR`), first, and print this one's ratios to it (same machine load)")
    args = ap.parse_args()
    in_process()
    if not args.skip_bus:
        base = on_the_bus(args.seconds, args.baseline_tree, not args.no_isolate) if args.baseline_tree else {}
        new = on_the_bus(args.seconds, isolated=not args.no_isolate)
        if base and new:
            print("\nthis controller / baseline: " + ", ".join(
                f"{k} {new[k] / base[k]:.2f}" for k in ("latency_p50_ms", "latency_p99_ms", "answered_within_2ms")
                if base[k]))


if __name__ == "__main__":
    main()
