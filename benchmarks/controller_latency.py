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
Run: ``.venv/bin/python benchmarks/controller_latency.py [--seconds 60] [--baseline-tree DIR]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
import _timing  # noqa: E402  (benchmarks/ is sys.path[0] when run as a script)

from bridge import bus  # noqa: E402
from bridge.session import free_tcp_port, open_session  # noqa: E402
from controller.distribution import distribute, lower_bounds  # noqa: E402
from controller.laws import ComputedTorque, LawConfig  # noqa: E402
from controller.trajectory import Trajectory, control_test_trajectory  # noqa: E402
from twin.model import cables, dynamics  # noqa: E402
from twin.model.params import load_params  # noqa: E402
from twin.sim.simulator import Twin, TwinConfig  # noqa: E402

TARGET_P99_MS = 0.1  # issue 21
TARGET_LATENCY_P99_MS = 1.0


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


def on_the_bus(seconds: float, controller_tree: Path | None = None) -> dict[str, float]:
    """The bus run; ``controller_tree``: run `xneck controller` from that source tree (e.g. a
    ``git archive`` of an older commit) for a baseline measured beside this one. Returns the
    observer's figures."""
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    waypoints = [[0, 0, 0], [40, 30, 20], [0, 0, 0], [-30, -20, -40], [0, 0, 0]]
    reps = max(1, int(seconds // 12))
    traj = Trajectory.from_degrees(waypoints * reps + [[0, 0, 0]], durations_s=2.0, dwell_s=1.0, name="bench")
    tmp = Path(tempfile.mkdtemp(prefix="xneck-bench-"))
    (tmp / "traj.json").write_text(traj.to_json())
    state_rx: dict[float, int] = {}
    latencies: list[float] = []
    last_status: list[bus.ControllerStatus] = []
    timings: list[bus.ControllerTiming] = []
    states_seen = [0]
    lock = threading.Lock()

    def on_state(sample):
        msg = bus.decode(bus.MotorState, sample.payload.to_bytes())
        with lock:
            state_rx[msg.stamp_s] = time.perf_counter_ns()
            states_seen[0] += 1

    def on_cmd(sample):
        now = time.perf_counter_ns()
        msg = bus.decode(bus.ForceCommand, sample.payload.to_bytes())
        with lock:
            sent = state_rx.pop(msg.stamp_s, None)
            if sent is not None:
                latencies.append((now - sent) * 1e-6)

    def on_status(sample):
        # The counts start again at zero when the campaign ends: keep the status with the most.
        msg = bus.decode(bus.ControllerStatus, sample.payload.to_bytes())
        if not last_status or (msg.deadline_misses, msg.overruns) >= (last_status[0].deadline_misses,
                                                                     last_status[0].overruns):
            last_status[:] = [msg]

    def on_timing(sample):
        timings.append(bus.decode(bus.ControllerTiming, sample.payload.to_bytes()))

    common = ["--listen", "tcp/127.0.0.1:0", "--connect", hub]
    with open_session(listen=[hub], connect=[]) as s:
        subs = [s.declare_subscriber(bus.MOTOR_STATE, on_state), s.declare_subscriber(bus.MOTOR_COMMAND, on_cmd),
                s.declare_subscriber(bus.CONTROLLER_STATUS, on_status), s.declare_subscriber(bus.CONTROLLER_TIMING, on_timing)]
        py = [sys.executable, "-m", "server.cli"]
        twin = subprocess.Popen([*py, "twin", "--seed", "1", *common], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        ctl = subprocess.Popen([*py, "controller", "--law", "2", "--trajectory", str(tmp / "traj.json"), *common],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=controller_tree)
        try:
            ctl.wait(timeout=traj.duration_s + 60)
        finally:
            for p in (ctl, twin):
                p.terminate()
                p.wait(10)
            for sub in subs:
                sub.undeclare()
    lat = np.array(latencies)
    status = last_status[0] if last_status else None
    print(f"\ncontroller benchmark, on the bus: real-time twin at 500 Hz + `xneck controller --law 2`, "
          f"{traj.duration_s:.0f} s" + (f", controller from {controller_tree}" if controller_tree else ""))
    if len(lat) == 0 or status is None:
        print("no commands observed: the run failed")
        return {}
    slow = np.nonzero(lat > 2.0)[0]
    # Every state is owed a command within a period: the share that got one (a controller that
    # answers only some states must not look faster for it).
    on_time = int(np.sum(lat <= 2.0)) / max(states_seen[0], 1)
    print(f"states seen {states_seen[0]}, answered {len(lat)}, answered within 2 ms: {100 * on_time:.2f} %")
    print(f"state-to-command latency over {len(lat)} ticks: p50 {np.percentile(lat, 50):.3f} ms, "
          f"p99 {np.percentile(lat, 99):.3f} ms, max {lat.max():.3f} ms; above 2 ms: {len(slow)} ticks"
          + (f" (first at tick {slow[0]}, last at tick {slow[-1]})" if len(slow) else ""))
    stage_report(timings)
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
    ap.add_argument("--baseline-tree", type=Path, default=None,
                    help="also run the bus part with the controller of this source tree (e.g. `git archive "
                         "COMMIT | tar -x -C DIR`), first, and print this one's ratios to it (same machine load)")
    args = ap.parse_args()
    in_process()
    if not args.skip_bus:
        base = on_the_bus(args.seconds, args.baseline_tree) if args.baseline_tree else {}
        new = on_the_bus(args.seconds)
        if base and new:
            print("\nthis controller / baseline: " + ", ".join(
                f"{k} {new[k] / base[k]:.2f}" for k in ("latency_p50_ms", "latency_p99_ms", "answered_within_2ms")
                if base[k]))


if __name__ == "__main__":
    main()
