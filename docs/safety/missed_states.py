"""The law's commanded force steps when the controller answers every state, and when it misses
some (docs/safety.md, "The law's force rate"; controller/laws.py, "Time step").

    .venv/bin/python docs/safety/missed_states.py                  # laws 1-3, about 5 s
    .venv/bin/python docs/safety/missed_states.py --law 2 --fixed-period   # as before: 1/rate_hz

The §7 control test (controller.trajectory.control_test_trajectory) on the robot truth, the
controller's campaign service closed on the twin through the bridge's safety rules in one process,
for ``--seconds`` from its start. "missed": every 20th state and a run of 3 every 200 ms reach no
controller (the process skipping a burst's stale states, the state gate, Zenoh dropping one); the
bridge re-applies the last command meanwhile. Per command, the largest change of any cable's
commanded force: its maximum, and the ticks above 5 N and at the law's 10 N bound.
``--fixed-period``: the law takes every gap as 1/rate_hz, as it did before it read the stamps.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bridge import bus
from bridge.motor_speed import MotorSpeed
from bridge.safety import Inputs, Safety, SafetyConfig
from controller.laws import ComputedTorque, LawConfig, encoder_hold_forces
from controller.service import CampaignService
from controller.trajectory import control_test_trajectory
from twin.model.params import load_params
from twin.sim.simulator import Twin, TwinConfig


def missed(k: int) -> bool:
    return k % 20 == 19 or k % 100 in (50, 51, 52)


def commanded_steps(params, law: int, seconds: float, unanswered) -> np.ndarray:
    """Per command, the largest change (N) of any cable's commanded force (module docstring)."""
    twin = Twin(params, TwinConfig(camera=False, seed=0, truth="robot"))
    svc = CampaignService(params, LawConfig(law=law), settle_s=0.5)
    safety = Safety(SafetyConfig(n_motors=params.n_cables, f_min_N=params.limits.f_min,
                                 f_max_N=params.limits.f_max, max_force_step_N=1.0))
    hold_rule, speed = encoder_hold_forces(params), MotorSpeed(params.n_cables, 0.002)
    tick = twin.tick(np.zeros(params.n_cables))
    svc.initialise(tick.theta_meas)
    speed.update(tick.theta_meas.tolist())
    sent: list[np.ndarray] = []
    start_k = 500  # 1 s of hold, then the campaign
    since = 0
    for k in range(start_k + round(seconds * 500)):
        if k == start_k:
            svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="ct", action="start", law=law,  # type: ignore[arg-type]
                                           trajectory_json=control_test_trajectory().to_json()), tick.t_s)
        if k > start_k and unanswered is not None and unanswered(k - start_k):
            since += 1
            command = sent[-1].tolist()
        else:
            since = 0
            svc.drive_reason = safety.estop_reason if safety.drive == "disabled" else safety.hold_reason
            out = svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force))
            if out.law_ran:
                svc.advance(tick.t_s)
            svc.drain_events()
            if k >= start_k:
                sent.append(out.force_N)
            command = out.force_N.tolist()
        d = safety.step(Inputs(command_N=command, command_age_s=0.002 * since, states_unanswered=since, estop=(),
                               hold_N=hold_rule(tick.theta_meas).tolist(), sender="c", speed_rad_s=speed.rad_s))
        tick = twin.tick(np.asarray(d.force_N))
        speed.update(tick.theta_meas.tolist())
    return np.abs(np.diff(np.array(sent), axis=0)).max(axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description="The law's commanded force steps with and without missed states.")
    ap.add_argument("--law", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--seconds", type=float, default=8.0, help="of the control test, from its start (s)")
    ap.add_argument("--fixed-period", action="store_true", help="the law takes every gap as 1/rate_hz (before)")
    args = ap.parse_args()
    if args.fixed_period:
        tick_time = ComputedTorque.tick_time
        ComputedTorque.tick_time = lambda self, stamp_s: tick_time(self, None)  # type: ignore[method-assign]
    params = load_params()
    print(f"law 1-3 on the robot truth, control test, {args.seconds:g} s; the law's period "
          + ("fixed (1/rate_hz)" if args.fixed_period else "from the stamps"))
    for law in args.law:
        for name, unanswered in (("every state answered", None), ("states missed", missed)):
            steps = commanded_steps(params, law, args.seconds, unanswered)
            print(f"law {law}, {name:21s}: largest commanded step {steps.max():5.2f} N, "
                  f"{int((steps > 5.0).sum()):3d} ticks > 5 N, {int((steps >= 10.0 - 1e-6).sum()):3d} at the 10 N bound",
                  flush=True)


if __name__ == "__main__":
    main()
