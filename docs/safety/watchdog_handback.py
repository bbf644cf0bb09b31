"""The bridge's watchdog hold while the controller still receives states but its commands are lost
(refused, a one-way link, a congested publisher, a starved process) for D s mid-campaign, then the
hand-back (docs/safety.md, "The law's force rate"; audit of session 43).

    .venv/bin/python docs/safety/watchdog_handback.py                     # laws 1-3, D 0 to 1.0 s, about 15 s
    .venv/bin/python docs/safety/watchdog_handback.py --flap        # a starved controller
    .venv/bin/python docs/safety/watchdog_handback.py --stalls 0.0005 0.002   # random stalls, the whole test

The §7 control test (controller.trajectory.control_test_trajectory) on the robot truth, the
controller's campaign service closed on the twin through the bridge's safety rules in one process.
``--at`` s into the campaign the commands stop reaching the bridge for D s (the states go on, so
the service sees the bridge's hold); the bridge's watchdog holds, and ramps to the controller's
commands again when they return. After the hand-back (1.5 s): the neck's peak joint speed and
largest |α| (truth), the largest applied force step per tick (and, in brackets, while lost: the
holds' entry), and the command at the hand-back.
D = 0: the same run without the loss (law 1 reaches 127°/s there without any fault). ``--flap``: the
controller starved (stopped 40 ms, running 8 ms, as SIGSTOP/SIGCONT did): its commands come through
8 ms in every 48 over D, and the bridge flaps hold/active. ``--stop``: the campaign is stopped one
tick before the loss, so its brake meets the hold (peak speed from the hand-back on). ``--stale``: the states are lost for D
instead (the commands would go through): the controller answers nothing for 10 ms, then holds by
itself (:meth:`CampaignService.stale`) on the last state's stamp, which the bridge takes until that
state is 50 ms old, then refuses, and its watchdog holds. ``--stalls P``: the whole control test
with, at each tick, a probability P that the commands stop for 12-20 ms (seeded; the bridge holds
from 10 ms), run with the law re-starting after any hold of more than a period (``HOLD_RESTART_S``,
session 46) and after 0.1 s of holds as before: how much later the campaign ends, the holds, and
the neck's peak joint speed over it.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import controller.service as service
from bridge import bus
from bridge.safety import Inputs
from controller.laws import LawConfig
from controller.offline import ServiceLoop
from controller.trajectory import control_test_trajectory
from twin.model.params import load_params
from twin.sim.simulator import TwinConfig

DT = 0.002


def _loop(params, law: int, seed: int):
    """The service (law ``law``) on the robot truth through the bridge's rules, as its node holds:
    (twin, service, safety, hold rule, motor speeds, first tick)."""
    loop = ServiceLoop(params, LawConfig(law=law), TwinConfig(camera=False, seed=seed, truth="robot"), settle_s=0.5)
    return loop.twin, loop.svc, loop.safety, loop.hold_rule, loop.speed, loop.tick


def handback(params, law: int, at_s: float, lost_s: float, after_s: float = 1.5, flap: bool = False,
             stale: bool = False, stop: bool = False) -> dict:
    """One run (module docstring): figures after the hand-back, or over the same window with no loss.
    ``stale``: the states, not the commands, are lost; the controller's own hold goes through.
    ``stop``: the user stops the campaign one tick before the loss (its brake meets the hold)."""
    twin, svc, safety, hold_rule, speed, tick = _loop(params, law, seed=0)
    start_k = 500  # 1 s of hold, then the campaign
    lost = range(start_k + round(at_s / DT), start_k + round((at_s + lost_s) / DT))
    end_k = lost.stop + round(after_s / DT)
    applied, alpha, alpha_dot, sent = [], [], [], np.zeros(params.n_cables)
    age = 0
    for k in range(end_k):
        if k == start_k:
            svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="ct", action="start", law=law,  # type: ignore[arg-type]
                                           trajectory_json=control_test_trajectory().to_json()), tick.t_s)
        if stop and k == lost.start - 1:
            svc.stop("ct", tick.t_s)
        svc.drive_reason = safety.estop_reason if safety.drive == "disabled" else safety.hold_reason
        gap_k = k - lost.start
        if stale and k in lost:
            # No state reaches the controller: it answers none for its stale_s (10 ms), then holds
            # by itself on the last state's stamp, which the bridge takes while that state is one of
            # its last 50 ms (bridge.node.ANSWER_WINDOW_S), then refuses; its watchdog then holds.
            if gap_k >= 5:
                out = svc.stale("stale state", DT * (gap_k + 1))
            taken = 5 <= gap_k < 25
            age, command = (0, out.force_N.tolist()) if taken else (age + 1, None)
        else:
            out = svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force))
            if out.law_ran:
                svc.advance(tick.t_s)
        svc.drain_events()
        if stale:
            if k not in lost:
                age, command = 0, out.force_N.tolist()
        elif k in lost and not (flap and (k - lost.start) % 24 >= 20):  # flap: 40 ms lost, 8 ms through
            age += 1
            command, sent = None, out.force_N
        else:
            age, command = 0, out.force_N.tolist()
        d = safety.step(Inputs(command_N=command, command_age_s=DT * age, states_unanswered=age, estop=(),
                               hold_N=hold_rule(tick.theta_meas).tolist(), sender="c", speed_rad_s=speed.rad_s))
        if k >= lost.start - 1:
            applied.append(np.asarray(d.force_N, dtype=float))
        tick = twin.tick(np.asarray(d.force_N, dtype=float))
        speed.update(tick.theta_meas.tolist())
        if k >= lost.stop:
            alpha.append(tick.alpha.copy())
            alpha_dot.append(tick.alpha_dot.copy())
    steps = np.abs(np.diff(np.array(applied), axis=0)).max(axis=1)  # from the tick before the loss
    n_lost = len(lost)
    return dict(speed=math.degrees(float(np.abs(alpha_dot).max())), alpha=math.degrees(float(np.abs(alpha).max())),
                step=float(steps[n_lost:].max()), held_step=float(steps[:n_lost].max()) if n_lost else 0.0, command=sent)


def stalls(params, law: int, p_stall: float, hold_restart_s: float, seed: int = 1) -> tuple[float, int, float, str]:
    """(campaign length from its start to its end event, s; the bridge's holds; peak joint speed,
    °/s; the end event) of the control test with random stalls of the commands (module docstring)."""
    default, service.HOLD_RESTART_S = service.HOLD_RESTART_S, hold_restart_s
    try:
        rng = np.random.default_rng(seed)
        twin, svc, safety, hold_rule, speed, tick = _loop(params, law, seed)
        start_k, lost_until, age, peak, holds, end = 250, -1, 0, 0.0, 0, "none"
        k = start_k
        for k in range(round(120 / DT)):
            if k == start_k:
                svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="ct", action="start", law=law,  # type: ignore[arg-type]
                                               trajectory_json=control_test_trajectory().to_json()), tick.t_s)
            out = svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force))
            if out.law_ran:
                svc.advance(tick.t_s)
            ended = [e.event for e in svc.drain_events() if e.event in ("finished", "aborted")]
            if ended:
                end = ended[0]
                break
            if k > start_k and k > lost_until and rng.random() < p_stall:
                lost_until = k + int(rng.integers(6, 10))  # 12-20 ms
            lost = k <= lost_until
            age = age + 1 if lost else 0
            was = safety.drive
            d = safety.step(Inputs(command_N=None if lost else out.force_N.tolist(), command_age_s=DT * age,
                                   states_unanswered=age, estop=(), hold_N=hold_rule(tick.theta_meas).tolist(),
                                   sender="c", speed_rad_s=speed.rad_s))
            holds += was != "hold" and safety.drive == "hold"
            tick = twin.tick(np.asarray(d.force_N, dtype=float))
            speed.update(tick.theta_meas.tolist())
            if k > start_k:
                peak = max(peak, float(np.abs(tick.alpha_dot).max()))
        return (k - start_k) * DT, holds, math.degrees(peak), end
    finally:
        service.HOLD_RESTART_S = default


def main() -> None:
    ap = argparse.ArgumentParser(description="The hand-back after the bridge's watchdog held for lost commands.")
    ap.add_argument("--law", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--lost", type=float, nargs="+", default=[0.0, 0.02, 0.05, 0.08, 0.3, 0.6, 1.0],
                    help="s of lost commands (0: none; the bridge holds from 10 ms)")
    ap.add_argument("--at", type=float, default=3.0, help="s into the control test the loss starts")
    ap.add_argument("--flap", action="store_true", help="a starved controller: 40 ms lost, 8 ms through, over D")
    ap.add_argument("--stale", action="store_true", help="the states are lost for D, not the commands: the "
                    "controller holds by itself from 10 ms (controller.process's stale_s)")
    ap.add_argument("--stop", action="store_true", help="the user stops the campaign one tick before the loss")
    ap.add_argument("--stalls", type=float, nargs="+", help="per-tick probabilities of a 12-20 ms stall (module docstring)")
    args = ap.parse_args()
    params = load_params()
    if args.stalls:
        print("control test on the robot truth with random 12-20 ms stalls of the commands:")
        for p_stall in args.stalls:
            for law in args.law:
                for hold_restart_s, name in ((0.1, "re-start after 0.1 s of holds (before)"),
                                             (service.HOLD_RESTART_S, "after a period (now)")):
                    length, holds, peak, end = stalls(params, law, p_stall, hold_restart_s)
                    print(f"P {p_stall:g}, law {law}, {name}: {end} after {length:.1f} s, {holds} holds, "
                          f"peak joint {peak:.0f}°/s", flush=True)
        return
    print(f"control test on the robot truth, {'states' if args.stale else 'commands'} lost from +{args.at:g} s; "
          "after the hand-back (1.5 s):")
    for law in args.law:
        for lost_s in args.lost:
            r = handback(params, law, args.at, lost_s, flap=args.flap, stale=args.stale, stop=args.stop)
            held = f"command at the hand-back {np.round(r['command'], 0).tolist()} N" if lost_s else "no loss"
            print(f"law {law}, lost {lost_s:.2f} s: peak joint {r['speed']:5.1f}°/s, max |α| {r['alpha']:4.1f}°, "
                  f"max applied step {r['step']:5.2f} N/tick ({r['held_step']:5.2f} while lost); {held}", flush=True)


if __name__ == "__main__":
    main()
