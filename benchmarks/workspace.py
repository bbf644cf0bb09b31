"""Time a 400 x 400 joint-space wrench-feasible and stiffness map of the 2-X prototype.

    .venv/bin/python benchmarks/workspace.py [--n 400] [--repeats 15]

Target: under 2 s. Prints median and p99 over repeats, and the speed-up against a baseline run in
the same process: the same functions called point by point in a Python loop on a smaller grid,
scaled up to n x n.
"""

from __future__ import annotations

import argparse
import time

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import numpy as np

from twin.analysis.statics import prototype_2x, stiffness_extremes, wrench_feasible_two_cables
from twin.analysis.workspace import joint_grid, joint_maps_2x


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=400, help="grid points per axis")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--baseline-n", type=int, default=40, help="grid of the per-point loop")
    args = parser.parse_args()
    d = prototype_2x()

    joint_maps_2x(d, 8)  # warm-up: imports, LAPACK initialisation
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        maps = joint_maps_2x(d, args.n)
        times.append(time.perf_counter() - t0)
    times = np.array(times)
    med, p99 = np.median(times), np.percentile(times, 99)

    _, grid = joint_grid(args.baseline_n)
    t0 = time.perf_counter()
    for th in grid.reshape(-1, 2):
        stiffness_extremes(d, th)
        wrench_feasible_two_cables(d, th)
    base = (time.perf_counter() - t0) * (args.n / args.baseline_n) ** 2

    print(f"2-X joint-space WFW + stiffness map, {args.n} x {args.n} = {args.n**2} configurations")
    print(f"  vectorised: median {med:.3f} s, p99 {p99:.3f} s over {args.repeats} runs (target < 2 s)")
    print(f"  per-point loop on {args.baseline_n} x {args.baseline_n}, scaled to {args.n} x {args.n}: {base:.1f} s")
    print(f"  speed-up: {base / med:.0f}x;  four-cable WFW covers {100 * maps.wfw4.mean():.1f}% of the grid,"
          f" two-cable {100 * maps.wfw2.mean():.1f}%")


if __name__ == "__main__":
    main()
