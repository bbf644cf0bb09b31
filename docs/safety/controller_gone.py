"""The controller gone during the take-up of an e-stop's slack: the bridge's hold meanwhile, and
a controller restarted on the slack (docs/safety.md, "After an e-stop: taking up the slack").

    .venv/bin/python docs/safety/controller_gone.py             # about 40 s on the 2-CPU machine
    .venv/bin/python docs/safety/controller_gone.py --seeds 0   # one seed

The case of docs/safety/take_up.py (law 2, §7 control test, e-stop 4.5 s in, released 2 s later,
robot truth). The controller stops ``--gone`` s into the take-up; the bridge's watchdog holds as
its node does (bridge.node: the hold rule of the encoders' angles,
controller.laws.encoder_hold_forces, and each motor damped on bridge.motor_speed's speeds).

1. Gone for good: the bridge holds 3 s, with its damping and without it (``hold_damping_N_s_rad``
   0, as before session 37).
2. Restarted: a new controller joins after 0.2 s of the bridge's hold (as controller/process.py,
   from the first state it sees) and runs 6 s; "unrecognised" is the same with the join not
   recognised as a run under way (controller.service.UNDER_WAY_M and UNDER_WAY_N infinite: no
   take-up, no re-estimate, as before session 37).
3. Restarted on taut cables: no e-stop; the control test stopped 3 s in, the neck held 2 s, then
   the controller gone 0.2 s and a new one joining: the take-up it owes anyway, what it costs.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from take_up import DT, Loop, print_result, summary

from bridge import bus
from bridge.motor_speed import MotorSpeed
from bridge.safety import Inputs
from controller import service as service_module
from controller.laws import LawConfig, encoder_hold_forces
from controller.service import CampaignService
from controller.trajectory import control_test_trajectory


class GoneLoop(Loop):
    """:class:`take_up.Loop` with the bridge holding on its own while no controller commands."""

    def __init__(self, seed: int, damping_N_s_rad: float) -> None:
        super().__init__(seed, {"hold_damping_N_s_rad": damping_N_s_rad})
        self.rule = encoder_hold_forces(self.params)
        self.speed = MotorSpeed(self.params.n_cables, DT)

    def step(self, estop: tuple = ()) -> None:
        super().step(estop)
        self.speed.update(self.tick.theta_meas.tolist())  # as the node: every tick

    def held(self, seconds: float) -> None:
        """The bridge's watchdog hold: no command, the states unanswered."""
        out = self.svc.hold("the controller is gone")  # what the rows show as its output
        for _ in range(round(seconds / DT)):
            d = self.safety.step(Inputs(command_age_s=0.02, states_unanswered=5,
                                        hold_N=self.rule(self.tick.theta_meas).tolist(), speed_rad_s=self.speed.rad_s))
            self._record(d.force_N, out)
            self.speed.update(self.tick.theta_meas.tolist())


def gone_for_good(seed: int, gone_s: float, damping_N_s_rad: float) -> dict:
    loop = GoneLoop(seed, damping_N_s_rad)
    loop.dropped_and_released()
    loop.run(gone_s)
    since, alpha0 = loop.tick.t_s, loop.tick.alpha.copy()
    loop.held(3.0)
    res = summary(loop.rows, since, alpha0)
    return {k: res[k] for k in ("slack at the end", "moved (deg)", "peak joint speed (deg/s)",
                                "largest applied force (N)")}


def restarted(seed: int, gone_s: float, recognised: bool) -> dict:
    loop = GoneLoop(seed, 1.0)
    loop.dropped_and_released()
    loop.run(gone_s)
    loop.held(0.2)
    saved = service_module.UNDER_WAY_M, service_module.UNDER_WAY_N
    if not recognised:
        service_module.UNDER_WAY_M = service_module.UNDER_WAY_N = math.inf
    try:
        loop.svc = CampaignService(loop.params, LawConfig(law=2), settle_s=0.5)
        loop.svc.initialise(loop.tick.theta_meas, np.asarray(loop.safety.force))
        since, alpha0, slack0 = loop.tick.t_s, loop.tick.alpha.copy(), int(loop.tick.slack.sum())
        loop.run(6.0)
    finally:
        service_module.UNDER_WAY_M, service_module.UNDER_WAY_N = saved
    end = summary(loop.rows, since, alpha0)
    # from the new controller's own commands on: the first 0.1 s is the bridge's hold's momentum
    after = summary(loop.rows, since + 0.1, alpha0)
    return {"slack at the join": slack0, "taut after (s)": end["taut after (s)"],
            "slack at the end": end["slack at the end"], "law from (s)": end["law from (s)"],
            "α̂ error at the end (deg)": end["α̂ error at the end (deg)"],
            "peak joint speed from 0.1 s (deg/s)": after["peak joint speed (deg/s)"],
            "largest applied step (N/tick)": end["largest applied step (N/tick)"]}


def restarted_taut(seed: int) -> dict:
    loop = GoneLoop(seed, 1.0)
    loop.run(1.0)
    loop.svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="c-1", action="start",
                                        trajectory_json=control_test_trajectory().to_json()), loop.tick.t_s)
    loop.run(3.0)
    loop.svc.stop("c-1", loop.tick.t_s)
    loop.run(2.0)
    loop.held(0.2)
    loop.svc = CampaignService(loop.params, LawConfig(law=2), settle_s=0.5)
    loop.svc.initialise(loop.tick.theta_meas, np.asarray(loop.safety.force))
    since, alpha0, slack0 = loop.tick.t_s, loop.tick.alpha.copy(), int(loop.tick.slack.sum())
    loop.run(4.0)
    end = summary(loop.rows, since, alpha0)
    return {"slack at the join": slack0, "law from (s)": end["law from (s)"], "moved (deg)": end["moved (deg)"],
            "peak joint speed (deg/s)": end["peak joint speed (deg/s)"],
            "α̂ error at the end (deg)": end["α̂ error at the end (deg)"],
            "largest applied step (N/tick)": end["largest applied step (N/tick)"]}


def main() -> None:
    ap = argparse.ArgumentParser(description="The controller gone during the take-up of an e-stop's slack.")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--gone", type=float, nargs="+", default=[0.05, 0.3, 0.6], help="s into the take-up")
    args = ap.parse_args()
    print("## 1. gone for good: the bridge holds 3 s")
    for damping in (0.0, 1.0):
        for seed in args.seeds:
            for gone in args.gone:
                print_result(f"hold damping {damping:g} N·s/rad, seed {seed}, gone {gone:g} s in",
                             gone_for_good(seed, gone, damping))
    print("## 2. restarted after 0.2 s of the bridge's hold")
    for recognised in (False, True):
        for seed in args.seeds:
            print_result(f"{'recognised' if recognised else 'unrecognised'}, seed {seed}, gone 0.3 s in",
                         restarted(seed, 0.3, recognised))
    print("## 3. restarted on taut cables (no e-stop)")
    for seed in args.seeds:
        print_result(f"seed {seed}", restarted_taut(seed))


if __name__ == "__main__":
    main()
