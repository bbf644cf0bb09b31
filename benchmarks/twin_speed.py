"""Speed of the twin: real-time factor of the full model stepped at 500 Hz (issue 21's target:
at least 150x real time with the model truth, 200x as the stretch; issue 3's 50x with every
robot effect on, issue 16), so a 100 s campaign is a sub-second CI job.

Input: the forces law 2 commands on the §7 control test (recorded once from an in-process run).
Prints the per-tick cost of Twin.tick (median, p99) and the real-time factor with the model truth
(every effect of twin/sim/truth.py off), each robot effect alone, and every effect on (issue 16:
still >= 50x), both in wall time and in this process's CPU time (the machine may be shared);
the cost of a calibration replay (``Twin.advance``, robot truth, what `xneck twin calibrate` runs);
then the ratio against scipy's solve_ivp (Radau, rtol 1e-8) integrating the same model over the
same held forces, in the same process. Run: ``.venv/bin/python benchmarks/twin_speed.py``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
import _repo  # noqa: E402, F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing  # noqa: E402  (benchmarks/ is sys.path[0] when run as a script)

summary = _timing.summary

from controller.laws import LawConfig  # noqa: E402
from controller.offline import run_closed_loop  # noqa: E402
from controller.trajectory import control_test_trajectory  # noqa: E402
from twin.model import dynamics  # noqa: E402
from twin.model.params import load_params  # noqa: E402
from twin.sim.simulator import Twin, TwinConfig  # noqa: E402
from twin.sim.truth import EFFECTS, load_truth  # noqa: E402

TARGET_RTF = 150.0  # the full model, model truth (issue 21)
STRETCH_RTF = 200.0
TARGET_RTF_ROBOT = 50.0  # with robot effects on (issues 3 and 16)
RADAU_SPAN_S = 2.0  # Radau is slow: compare both on the first 2 s of the same input


def main() -> None:
    params = load_params()
    forces = run_closed_loop(params, LawConfig(law=2), control_test_trajectory()).force_N
    robot = load_truth("robot")
    truths = [("model truth (every effect off)", "model")] + [(f"robot: {e} alone", robot.only(e)) for e in EFFECTS]
    truths.append(("robot truth (every effect on)", robot))
    print(f"xneck twin benchmark: {len(forces)} ticks ({len(forces) / 500:.1f} s simulated) of the full model, "
          f"variable-stiffness cables and friction, camera on; load average {os.getloadavg()[0]:.1f} "
          f"on {os.cpu_count()} CPUs")
    medians = []
    for label, truth in truths:
        twin = Twin(params, TwinConfig(truth=truth))  # variable stiffness + friction, camera on
        rtf, rtf_cpu, rtf_median = _time_ticks(twin, forces, label)
        medians.append(twin.dt / rtf_median)
        target = TARGET_RTF if truth == "model" else TARGET_RTF_ROBOT
        verdict = "meets" if rtf_median >= target else "MISSES"
        if truth == "model":
            verdict += f"; stretch {STRETCH_RTF:.0f}x {'met' if rtf_median >= STRETCH_RTF else 'not met'}"
        print(f"  real-time factor: {rtf:.0f}x wall, {rtf_cpu:.0f}x CPU, {rtf_median:.0f}x from the median tick "
              f"(a 100 s campaign takes {100 / rtf:.2f} s); target >= {target:.0f}x (median tick, robust to a "
              f"shared machine's preemption) -> {verdict}")
    print(f"every effect on: median tick {medians[-1] / medians[0]:.2f}x the model truth's (same run, same load)")
    print(f"  load average after the real-time factors: {os.getloadavg()[0]:.1f}")
    # What `xneck twin calibrate` runs per evaluation: Twin.advance (no sensors, no Tick) over a recording.
    twin = Twin(params, TwinConfig(truth=robot, camera=False))
    twin.advance(forces[0])
    twin.reset()
    per_tick = np.empty(len(forces))
    for k, f in enumerate(forces):
        t0 = time.perf_counter()
        twin.advance(f)
        per_tick[k] = time.perf_counter() - t0
    summary("Twin.advance (calibration replays), robot truth", per_tick)
    print(f"  one replay of this {len(forces) / 500:.0f} s recording: about {np.median(per_tick) * len(forces):.2f} s "
          f"({twin.dt / float(np.median(per_tick)):.0f}x real time from the median tick)")
    twin = Twin(params, TwinConfig())
    dt = twin.dt
    clock = time.perf_counter

    # Radau on the same held forces, tick by tick, for RADAU_SPAN_S.
    m = twin.model
    n, nc = m.n_joints, m.n_cables
    ticks = int(RADAU_SPAN_S / dt)
    state = np.zeros(2 * (n + nc))
    t0 = clock()
    for f in forces[:ticks]:
        def rhs(_t, s, f=f):
            acc = dynamics.accelerations(m, s[:n], s[n:n + nc], s[n + nc:2 * n + nc], s[2 * n + nc:], f)
            return np.concatenate([s[n + nc:], acc.alpha_ddot, acc.theta_ddot])

        state = solve_ivp(rhs, (0.0, dt), state, method="Radau", rtol=1e-8, atol=1e-10).y[:, -1]
    radau = clock() - t0
    twin.reset()
    t0 = clock()
    for f in forces[:ticks]:
        tick = twin.tick(f)
    ours = clock() - t0
    err = np.degrees(np.abs(tick.alpha - state[:n])).max()
    print(f"solve_ivp Radau over the first {RADAU_SPAN_S:.0f} s: {radau:.2f} s; Twin.tick: {ours:.3f} s; "
          f"ratio Radau / twin: {radau / ours:.0f}x; max |Δα| at the end {err:.4f}°")


def _time_ticks(twin: Twin, forces: np.ndarray, label: str) -> tuple[float, float, float]:
    """Real-time factors (wall, CPU, period / median tick) of ``twin`` over ``forces``; prints the
    per-tick summary."""
    twin.tick(forces[0])  # compile outside the timing
    twin.reset()
    per_tick = np.empty(len(forces))
    clock = time.perf_counter
    t_all, cpu = clock(), time.process_time()
    for k, f in enumerate(forces):
        t0 = clock()
        twin.tick(f)
        per_tick[k] = clock() - t0
    wall, cpu = clock() - t_all, time.process_time() - cpu
    summary(f"Twin.tick, {label}", per_tick)
    sim_s = len(forces) * twin.dt
    return sim_s / wall, sim_s / cpu, twin.dt / float(np.median(per_tick))


if __name__ == "__main__":
    main()
