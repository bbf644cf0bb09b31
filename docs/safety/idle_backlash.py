"""A slack cable's motor crossing the gear's backlash while the neck is idle after the first
enable, then a jog (docs/safety.md, "The law's force rate"; session 46).

    .venv/bin/python docs/safety/idle_backlash.py                        # laws 1-3, seeds 0-2, about 20 s
    .venv/bin/python docs/safety/idle_backlash.py --accel-max 250 50     # α̂̇'s bound then and now
    .venv/bin/python docs/safety/idle_backlash.py --control-test         # what the bound costs tracking, about 1 min

The controller's campaign service closed on the robot truth through the bridge's safety rules in
one process: idle from the first enable for ``--idle`` s, then a jog to ``--jog`` (degrees). On
the robot truth a cable held at the law's floor sits under the motors' stiction; its motor
crosses the gear's backlash (0.44 rad) within a tick and the encoder jumps, which α̂ reads as
about 0.5° of the joints. Per run: the largest encoder change in a tick, the largest change of the
applied forces in a tick (after the first 10 ticks) and the ticks above 5 N, for each
``LawConfig.alpha_hat_accel_max_rad_s2`` given (the first the baseline of the ratio).
``--control-test``: the §7 control test instead (from rest, robot truth): the tracking error
α − α^d of the truth (rms per joint and largest, degrees), the largest force change per tick,
and the truth's joint accelerations (what the bound must not cut).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.laws import LawConfig
from controller.offline import ServiceLoop
from controller.trajectory import Trajectory, control_test_trajectory
from twin.model.params import load_params
from twin.sim.simulator import TwinConfig


def idle_then_jog(params, config: LawConfig, seed: int, idle_s: float, jog_deg: list[float],
                  after_s: float = 3.0) -> tuple[float, np.ndarray]:
    """(largest encoder change in a tick (rad), the applied forces' change per tick (N)) of one run."""
    loop = ServiceLoop(params, config, TwinConfig(camera=False, seed=seed, truth="robot"))
    jog_k = round(idle_s * config.rate_hz)
    applied, theta = [], []
    for k in range(jog_k + round(after_s * config.rate_hz)):
        if k == jog_k:
            loop.start(Trajectory.from_degrees([jog_deg], [], 0.0, "jog"), kind="jog", campaign_id="jog")
        theta.append(loop.tick.theta_meas.copy())
        applied.append(loop.step())
    jump = float(np.abs(np.diff(np.array(theta), axis=0)).max())
    return jump, np.abs(np.diff(np.array(applied[10:]), axis=0)).max(axis=1)


def control_test(params, config: LawConfig, seed: int) -> tuple[np.ndarray, float, float, float, float]:
    """(rms of α − α^d per joint (°), largest |α − α^d| (°), largest applied force change in a tick
    (N), the truth's |α̈| p99.9 and largest (rad/s², a joint a tick)) over the §7 control test from
    0.2 s after its start, started after 1 s idle."""
    dt = 1.0 / config.rate_hz
    loop = ServiceLoop(params, config, TwinConfig(camera=False, seed=seed, truth="robot"))
    trajectory, start_k = control_test_trajectory(), round(1.0 / dt)
    error, applied, alpha_dot = [], [], []
    for k in range(start_k + round(trajectory.duration_s / dt)):
        if k == start_k:
            loop.start(trajectory, campaign_id="ct")
        alpha, f = loop.tick.alpha.copy(), loop.step()
        if k > start_k + round(0.2 / dt):
            error.append(np.degrees(alpha - loop.last_alpha_d))
            applied.append(f)
            alpha_dot.append(loop.tick.alpha_dot.copy())
    e, accel = np.array(error), np.abs(np.diff(np.array(alpha_dot), axis=0)) / dt
    return (np.sqrt((e ** 2).mean(axis=0)), float(np.abs(e).max()),
            float(np.abs(np.diff(np.array(applied), axis=0)).max()), float(np.percentile(accel, 99.9)), float(accel.max()))


def main() -> None:
    ap = argparse.ArgumentParser(description="Force steps of a backlash crossing while idle after the first enable.")
    ap.add_argument("--law", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--seed", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--idle", type=float, default=1.0, help="s idle from the first enable before the jog")
    ap.add_argument("--jog", type=float, nargs=3, default=[20.0, -10.0, 10.0], help="the jog's target (degrees)")
    ap.add_argument("--accel-max", type=float, nargs="+", default=[250.0, LawConfig().alpha_hat_accel_max_rad_s2],
                    help="LawConfig.alpha_hat_accel_max_rad_s2 values (rad/s²); the first is the baseline")
    ap.add_argument("--control-test", action="store_true", help="the §7 control test's tracking instead")
    args = ap.parse_args()
    params = load_params()
    if args.control_test:
        print("robot truth, the §7 control test from rest; α − α^d of the truth:")
        for law in args.law:
            for seed in args.seed:
                for a in args.accel_max:
                    rms, worst, step, p999, peak = control_test(params, LawConfig(law=law, alpha_hat_accel_max_rad_s2=a), seed)
                    print(f"law {law}, seed {seed}, α̂̇ bound {a:g} rad/s²: rms {np.round(rms, 2).tolist()}°, "
                          f"largest {worst:.2f}°, largest force change {step:.2f} N/tick; the truth's |α̈| p99.9 "
                          f"{p999:.0f}, largest {peak:.0f} rad/s²", flush=True)
        return
    print(f"robot truth, idle {args.idle:g} s from the first enable, then a jog to {args.jog}°; applied forces:")
    for law in args.law:
        for seed in args.seed:
            peaks = []
            for a in args.accel_max:
                jump, steps = idle_then_jog(params, LawConfig(law=law, alpha_hat_accel_max_rad_s2=a),
                                            seed, args.idle, args.jog)
                peaks.append(float(steps.max()))
                print(f"law {law}, seed {seed}, α̂̇ bound {a:g} rad/s²: largest encoder change {jump:.2f} rad/tick, "
                      f"largest force change {steps.max():.2f} N/tick, ticks above 5 N {int((steps > 5).sum())}"
                      + (f", {peaks[-1] / peaks[0]:.2f} of the baseline's" if len(peaks) > 1 else ""), flush=True)


if __name__ == "__main__":
    main()
