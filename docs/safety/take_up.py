"""After an e-stop: the slack the fall leaves, with and without the controller's take-up
(docs/safety.md, "After an e-stop: taking up the slack"; controller/take_up.py).

    .venv/bin/python docs/safety/take_up.py             # about 7 s on the 2-CPU machine
    .venv/bin/python docs/safety/take_up.py --seeds 0   # one seed

What runs: the controller's campaign service (controller.service.CampaignService) closed on the
twin's robot truth (twin.sim.simulator.Twin, unmodelled stiction 1.3·f_s among its effects)
through the bridge's safety rules (bridge.safety.Safety: the e-stop, the enable ramp of 1 N a
tick), one state per 2 ms in one process, as the lockstep campaign does. The audit of 2026-11-28's
case: law 2 runs the §7 control test, an e-stop 4.5 s in drops the moving neck, released 2 s
later; then 6 s with the drives back. "without" is the same with the take-up turned off (its peak
set to 0: the law takes over at once, as before controller/take_up.py).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bridge import bus
from bridge.safety import Inputs, Safety, SafetyConfig
from controller import service as service_module
from controller.laws import LawConfig, hold_forces
from controller.service import CampaignService
from controller.trajectory import control_test_trajectory
from twin.model.params import load_params
from twin.sim.simulator import Twin, TwinConfig

DT = 0.002


class Loop:
    """The campaign service closed on the robot truth through the bridge's safety rules, one
    state per 2 ms (the module docstring); ``rows`` keeps (t, α, α̇, α̂, applied, command, slack,
    law ran, taking up) of every state. docs/safety/controller_gone.py drives it too."""

    def __init__(self, seed: int, safety_config: dict | None = None) -> None:
        self.params = params = load_params()
        self.twin = Twin(params, TwinConfig(camera=False, seed=seed, truth="robot"))
        self.svc = CampaignService(params, LawConfig(law=2), settle_s=0.5)
        self.safety = Safety(SafetyConfig(n_motors=params.n_cables, f_min_N=params.limits.f_min,
                                          f_max_N=params.limits.f_max, max_force_step_N=1.0, **(safety_config or {})))
        self.tick = self.twin.tick(np.zeros(params.n_cables))
        self.svc.initialise(self.tick.theta_meas)
        self.rows: list[tuple] = []

    def step(self, estop: tuple = ()) -> None:
        svc, safety, tick = self.svc, self.safety, self.tick
        drive = safety.drive
        svc.drive_reason = safety.estop_reason if drive == "disabled" else safety.hold_reason
        out = svc.control(tick.theta_meas, tick.t_s, drive, np.asarray(safety.force))
        if out.law_ran:
            svc.advance(tick.t_s)
        svc.drain_events()
        hold = hold_forces(self.params, np.clip(out.alpha_hat_rad, -1.0, 1.0)).tolist()
        d = safety.step(Inputs(command_N=out.force_N.tolist(), command_age_s=0.0, states_unanswered=0,
                               estop=estop, hold_N=hold, sender="c"))
        self._record(d.force_N, out)

    def _record(self, force_N, out) -> None:
        self.tick = tick = self.twin.tick(np.asarray(force_N, dtype=float))
        self.rows.append((tick.t_s, tick.alpha, tick.alpha_dot, out.alpha_hat_rad, np.asarray(force_N, dtype=float),
                          out.force_N, tick.slack.copy(), out.law_ran, self.svc.taking_up))

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / DT)):
            self.step()

    def dropped_and_released(self) -> tuple[float, np.ndarray, int]:
        """The audit's case up to the release: (stamp of the release, α then, cables slack then)."""
        self.run(1.0)
        req = bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="c-1", action="start",
                                  trajectory_json=control_test_trajectory().to_json())
        self.svc.handle(req, self.tick.t_s)
        self.run(4.5)
        self.step(((True, "e-stop"),))
        self.run(2.0)
        released = (self.tick.t_s, self.tick.alpha.copy(), int(self.tick.slack.sum()))
        self.step(((False, "release"),))
        return released


def summary(rows: list[tuple], since_s: float, alpha0: np.ndarray) -> dict:
    """The figures of the tables from the rows after ``since_s``."""
    start = next(k for k, r in enumerate(rows) if r[0] > since_s)
    after = rows[start:]
    t = np.array([r[0] for r in after]) - since_s
    taut = [k for k, r in enumerate(after) if not r[6].any()]
    law_from = next((k for k, r in enumerate(after) if r[7] and not r[8]), None)
    end = after[-1]
    applied = np.array([r[4] for r in rows[start - 1:]])
    command = np.array([r[5] for r in after])
    return {
        "taut after (s)": t[taut[0]] if taut else math.nan,
        "slack at the end": int(end[6].sum()),
        "law from (s)": t[law_from] if law_from is not None else math.nan,
        "moved (deg)": np.degrees(end[1] - alpha0),
        "peak joint speed (deg/s)": math.degrees(max(float(np.abs(r[2]).max()) for r in after)),
        "α̂ error at the end (deg)": np.degrees(np.abs(end[3] - end[1])).max(),
        "largest applied step (N/tick)": float(np.abs(np.diff(applied, axis=0)).max()),
        "largest command step after 20 ms (N/tick)": float(np.abs(np.diff(command[10:], axis=0)).max()),
        "largest applied force (N)": float(applied.max()),
    }


def print_result(label: str, res: dict) -> None:
    fields = []
    for k, v in res.items():
        if isinstance(v, np.ndarray):
            fields.append(f"{k} {np.round(v, 1).tolist()}")
        elif isinstance(v, float):
            fields.append(f"{k} {v:.2f}")
        else:
            fields.append(f"{k} {v}")
    print(f"{label}: " + "; ".join(fields))


def run(seed: int, take_up: bool) -> dict:
    loop = Loop(seed)
    peak = service_module.take_up_peak_N
    if not take_up:
        service_module.take_up_peak_N = lambda _params: 0.0
    try:
        released_at, alpha0, slack0 = loop.dropped_and_released()
        loop.run(6.0)
    finally:
        service_module.take_up_peak_N = peak
    return {"slack at release": slack0, **summary(loop.rows, released_at - 1e-9, alpha0)}


def main() -> None:
    ap = argparse.ArgumentParser(description="After an e-stop: the slack the fall leaves, with and without the take-up.")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    for take_up in (False, True):
        print(f"## {'with' if take_up else 'without'} the take-up")
        for seed in args.seeds:
            print_result(f"seed {seed}", run(seed, take_up))

if __name__ == "__main__":
    main()
