"""The take-up's floor over the workspace: what the hold at its peak asks of the cables, with and
without the cap that keeps them under ``PEAK_FORCE_FRACTION``·f_max (docs/safety.md, "After an
e-stop: taking up the slack"; controller/take_up.py, ``floor_cap_N``).

    .venv/bin/python docs/safety/take_up_peak_grid.py            # about 10 s
    .venv/bin/python docs/safety/take_up_peak_grid.py --step 5   # finer, 25³ poses

For each pose α of a grid (joint limits ±``--limit`` degrees), the hold at α (eqs. 63-65, what
the take-up commands at α̂, without its damping) with the floor at the take-up's peak (t_min +
``take_up_peak_N``: 2·max f_s of Table 1) and at the capped one (min(peak, ``floor_cap_N``)).
The floor the cap leaves is compared with the motors' breakaway on the robot truth (up to
1.5·max f_s): below it, a slack cable's drum may not turn.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.laws import hold_forces
from controller.take_up import PEAK_FORCE_FRACTION, floor_cap_N, take_up_peak_N
from twin.model.params import load_params


def main() -> None:
    ap = argparse.ArgumentParser(description="The take-up's peak floor over the workspace.")
    ap.add_argument("--step", type=float, default=15.0, help="grid step (deg)")
    ap.add_argument("--limits", type=float, nargs="+", default=[30.0, 45.0, 60.0], help="grid half-widths (deg)")
    args = ap.parse_args()
    params = load_params()
    f_max, t_min = params.limits.f_max, params.limits.t_min
    peak = take_up_peak_N(params)
    breakaway = 1.5 * max(params.friction.f_s)
    print(f"floor at the peak: t_min + {peak:.1f} = {t_min + peak:.1f} N; cap at {PEAK_FORCE_FRACTION:g}·f_max = "
          f"{PEAK_FORCE_FRACTION * f_max:.0f} N; breakaway up to 1.5·max f_s = {breakaway:.1f} N")
    for limit in args.limits:
        grid = np.radians(np.arange(-limit, limit + 1e-9, args.step))
        at_fmax = 0
        worst_before = worst_after = 0.0
        floors: list[float] = []
        tmin_over = 0
        for alpha in itertools.product(grid, grid, grid):
            a = np.array(alpha)
            before = hold_forces(params, a, peak).max()
            floor = min(peak, floor_cap_N(params, a))
            after = hold_forces(params, a, floor).max()
            at_fmax += before >= f_max - 1e-9
            worst_before, worst_after = max(worst_before, before), max(worst_after, after)
            tmin_over += hold_forces(params, a).max() > PEAK_FORCE_FRACTION * f_max
            floors.append(t_min + floor)
        fl = np.array(floors)
        n = len(fl)
        print(f"±{limit:g}° step {args.step:g}° ({n} poses): peak floor -> f_max at {at_fmax} poses "
              f"(largest {worst_before:.1f} N); capped: largest {worst_after:.1f} N, the t_min hold alone above the cap at "
              f"{tmin_over}; floor (N) min/p10/median {fl.min():.1f}/{np.percentile(fl, 10):.1f}/{np.median(fl):.1f}, "
              f"below the peak at {(fl < t_min + peak - 1e-9).sum()}, below {breakaway:.1f} N at {(fl < breakaway).sum()}")
    a = np.radians([10.0, -20.0, 30.0])
    floor_cap_N(params, a)
    t0 = time.perf_counter()
    for _ in range(2000):
        floor_cap_N(params, a)
    t1 = time.perf_counter()
    for _ in range(2000):
        hold_forces(params, a, 5.0)
    t2 = time.perf_counter()
    print(f"floor_cap_N: {(t1 - t0) / 2000 * 1e6:.0f} µs a call (hold_forces: {(t2 - t1) / 2000 * 1e6:.0f} µs), once a tick during a take-up")


if __name__ == "__main__":
    main()
