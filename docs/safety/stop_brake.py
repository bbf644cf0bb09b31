"""A user's stop of a running campaign: the force step it causes and where the neck comes to rest
(docs/safety.md, "A stop while the law tracks"; session 45).

    .venv/bin/python docs/safety/stop_brake.py            # about 5 s
    .venv/bin/python docs/safety/stop_brake.py --resume   # stops while the campaign comes back up to speed

A swing (0 → [30, -20, 10]° → 0, cycloids of 1.05 s, 0.2 s dwell: its first move peaks at
2.9 rad/s², near the trajectories' 3 rad/s² bound) run by the controller's campaign service (law 2)
closed on the twin, one state per 2 ms as the bus shell does, and stopped at several times of its
first move. Per stop: α̈^d when stopped, the largest change per tick of the commanded forces over
the 0.1 s after the stop, the same over the same window of a run that is not stopped (what the
swing itself does), how far α^d travels from the stop to where it rests (fastest joint), and
the brake's length. ``--resume``: 0.45 s in (the first move at speed) the states stall for 0.2 s
(the law re-starts, the campaign's clock stops), and the stop comes at several times after the
take-over, while the clock's resume ramp brings the trajectory back up to speed (session 44 had
measured a 2.95 N step for such a stop).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bridge import bus
from controller.laws import LawConfig
from controller.service import CampaignService
from controller.trajectory import Trajectory
from twin.model.params import load_params
from twin.sim.simulator import Twin, TwinConfig

DT = 0.002
SWING = Trajectory.from_degrees([[0, 0, 0], [30, -20, 10], [0, 0, 0]], 1.05, 0.2, name="swing")


def run(params, stop_at_s: float | None, until_s: float, stale: tuple[float, float] | None = None) -> dict:
    """The swing from its start; stopped ``stop_at_s`` s in (None: not stopped); ``stale`` = (from
    s, for s): no state reaches the service meanwhile (it holds, :meth:`CampaignService.stale`)."""
    twin = Twin(params, TwinConfig(camera=False, seed=1))
    svc = CampaignService(params, LawConfig(law=2), service=True, settle_s=0.2)
    tick = twin.tick(np.zeros(params.n_cables))
    svc.initialise(tick.theta_meas)
    svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="swing", action="start",
                                   trajectory_json=SWING.to_json()), tick.t_s)
    forces, alpha_d, at = [], [], None
    stalled = range(0) if stale is None else range(round(stale[0] / DT), round((stale[0] + stale[1]) / DT))
    for k in range(round(until_s / DT)):
        if stop_at_s is not None and k == round(stop_at_s / DT):
            ref = svc.reference(tick.t_s)
            at = {"k": k, "alpha_d": np.array(ref[0]), "alpha_ddot": np.array(ref[2])}
            svc.handle(bus.CampaignRequest(seq=2, stamp_s=0.0, campaign_id="swing", action="stop"), tick.t_s)
        if k in stalled:
            out = svc.stale("stale state", (k - stalled.start + 1) * DT)
        else:
            out = svc.control(tick.theta_meas, tick.t_s)
            if out.law_ran:
                svc.advance(tick.t_s)
        svc.drain_events()
        forces.append(np.array(out.force_N))
        alpha_d.append(np.array(out.alpha_d_rad))
        tick = twin.tick(out.force_N)
    return {"forces": np.array(forces), "alpha_d": np.array(alpha_d), "at": at, "rest": svc.hold_target.copy()}


def main() -> None:
    ap = argparse.ArgumentParser(description="A user's stop of a running campaign: its force step and travel.")
    ap.add_argument("--resume", action="store_true", help="stop while the campaign resumes after stalled states")
    args = ap.parse_args()
    params = load_params()
    if args.resume:
        stale = (0.45, 0.2)
        plain = run(params, None, 2.5, stale)
        print("| stop after the take-over (s) | step per tick after the stop (N) | without the stop (N) |")
        print("|---|---|---|")
        for after in (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4):
            stop_at = sum(stale) + after
            stopped = run(params, stop_at, stop_at + 1.5, stale)
            window = slice(stopped["at"]["k"] - 1, stopped["at"]["k"] + 50)
            step = np.abs(np.diff(stopped["forces"][window], axis=0)).max()
            base = np.abs(np.diff(plain["forces"][window], axis=0)).max()
            print(f"| {after:.2f} | {step:.2f} | {base:.2f} |")
        return
    plain = run(params, None, 2.5)
    print("| stop at (s) | α̈^d then (rad/s², largest) | step per tick after the stop (N) | without the stop (N) "
          "| α^d travel to rest (°, fastest joint) | α^d at rest matches (°) |")
    print("|---|---|---|---|---|---|")
    for stop_at in (0.26, 0.4, 0.5, 0.6, 0.79, 1.0):
        stopped = run(params, stop_at, stop_at + 1.5)
        k = stopped["at"]["k"]
        window = slice(k - 1, k + 50)
        step = np.abs(np.diff(stopped["forces"][window], axis=0)).max()
        base = np.abs(np.diff(plain["forces"][window], axis=0)).max()
        travel = np.degrees(np.abs(stopped["rest"] - stopped["at"]["alpha_d"])).max()
        settled = np.degrees(np.abs(stopped["alpha_d"][-1] - stopped["rest"])).max()
        print(f"| {stop_at:.2f} | {np.abs(stopped['at']['alpha_ddot']).max():.2f} | {step:.2f} | {base:.2f} "
              f"| {travel:.2f} | {settled:.1e} |")


if __name__ == "__main__":
    main()
