"""How far the neck leaves its path while a hung bridge's ESCONs keep the last forces
(docs/bridge.md, "Why 0.5 s").

    .venv/bin/python docs/bridge-figures/frozen_forces.py              # about 5 s on the 2-CPU machine
    .venv/bin/python docs/bridge-figures/frozen_forces.py --points 48  # a denser sample, about 15 s

What runs: the controller's campaign service (controller.service.CampaignService, the state
machine the controller process runs on the bus) closed on the twin (twin.sim.simulator.Twin) in
one process, one state per 2 ms, as docs/safety/encoder_residual.py does, with law 2, the §7
control test trajectory and the twin on the robot truth (twin/sim/robot_truth.toml). A reference
run goes unfrozen to the last freeze plus 1 s. Then, for each of ``--points`` times evenly spaced over the moving
part of the trajectory (the middles of equal shares of first departure → last arrival), the same
run (same seed, so the same noise) again up to that time, from where the twin keeps getting the
last forces sent (a bridge hung with its drives enabled) and the service no longer runs. Printed:
the largest deviation from the reference, max over the joints of |α_frozen − α_reference| (deg,
the twin's true joint angles), within 0.1, 0.25, 0.5 and 1 s of the freeze (the max over that
window), per freeze point, then the max and median over the points.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.laws import LawConfig
from controller.service import CampaignService
from controller.trajectory import Trajectory, trajectory_by_name
from twin.model.params import Params, load_params
from twin.sim.simulator import Twin, TwinConfig

SETTLE_S = 1.0  # s held at the last waypoint, as a campaign does (CampaignService.settle_s)
HORIZONS_S = (0.1, 0.25, 0.5, 1.0)
LAW = 2


def run(params: Params, traj: Trajectory, seed: int, end_s: float,
        freeze_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One campaign of ``traj`` on a twin of the robot truth up to ``end_s`` (campaign time, s);
    from ``freeze_s`` on the twin keeps the last forces sent. Returns the campaign times (T,) and
    the twin's true α (T, joints), rad."""
    twin = Twin(params, TwinConfig(truth="robot", seed=seed, camera=False))
    svc = CampaignService(params, LawConfig(law=LAW), service=False, settle_s=SETTLE_S)
    force = np.zeros(params.n_cables)
    tick = twin.tick(force)
    svc.initialise(tick.theta_meas)
    svc.begin(traj, tick.t_s)
    t0 = tick.t_s
    times: list[float] = []
    alphas: list[np.ndarray] = []
    while tick.t_s - t0 <= end_s:
        if freeze_s is None or tick.t_s - t0 < freeze_s:
            out = svc.control(tick.theta_meas, tick.t_s)
            if out.law_ran:
                svc.advance(tick.t_s)
            svc.drain_events()
            force = out.force_N
        times.append(tick.t_s - t0)
        alphas.append(tick.alpha)
        tick = twin.tick(force)
    return np.array(times), np.array(alphas)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--points", type=int, default=12, help="freeze points over the moving part")
    args = ap.parse_args()
    if args.points < 1:
        ap.error(f"--points must be at least 1, got {args.points}")
    print(f"Command: .venv/bin/python docs/bridge-figures/frozen_forces.py {' '.join(sys.argv[1:])}".rstrip())
    print()
    started = time.perf_counter()
    params = load_params()
    traj = trajectory_by_name("control_test")
    segments = traj.segment_times()
    first, last = float(segments[0, 0]), float(segments[-1, 1])
    freezes = [first + (k + 0.5) * (last - first) / args.points for k in range(args.points)]
    end_s = max(freezes) + max(HORIZONS_S) + 0.01
    t_ref, a_ref = run(params, traj, args.seed, end_s)
    print(f"Law {LAW}, control test, robot truth, seed {args.seed}: forces frozen at {args.points} points over "
          f"{first:g}-{last:g} s (campaign time). Deviation from the unfrozen run, max over joints of "
          f"|α_frozen − α_reference| (deg), the largest within each horizon of the freeze.")
    print()
    print("| frozen at (s) | where | |α̇^d| max (°/s) | " + " | ".join(f"≤ {h:g} s" for h in HORIZONS_S) + " |")
    print("|---|---|---|" + "---|" * len(HORIZONS_S))
    rows = []
    for t_f in freezes:
        t, a = run(params, traj, args.seed, end_s, freeze_s=t_f)
        n = min(len(t), len(t_ref))
        if not np.array_equal(t[:n], t_ref[:n]):
            raise SystemExit("the frozen run's ticks differ from the reference's")
        before = t[:n] < t_f
        if not np.array_equal(a[:n][before], a_ref[:n][before]):
            raise SystemExit(f"the run frozen at {t_f:.3f} s differs from the reference before the freeze")
        at = t[:n][~before][0]  # the first state the service did not answer
        dev = np.degrees(np.max(np.abs(a[:n] - a_ref[:n]), axis=1))
        row = [float(dev[(t[:n] >= at) & (t[:n] <= at + h + 1e-9)].max()) for h in HORIZONS_S]
        rows.append(row)
        speed = math.degrees(float(np.max(np.abs(traj.sample(t_f).alpha_dot))))
        print(f"| {t_f:.3f} | {traj.describe_time(t_f)} | {speed:.0f} | " + " | ".join(f"{v:.1f}" for v in row) + " |",
              flush=True)
    table = np.array(rows)
    print()
    print("Over the points: " + "; ".join(
        f"within {h:g} s max {table[:, i].max():.1f}°, median {np.median(table[:, i]):.1f}°"
        for i, h in enumerate(HORIZONS_S)) + ".")
    print(f"({time.perf_counter() - started:.0f} s)")


if __name__ == "__main__":
    main()
