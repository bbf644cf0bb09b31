"""How heavy a line's damping the output error tolerates, and what `auto`'s damping check sees (issue 16).

The output error (twin/identification/outputerror.py) holds the line's damping at 0: its pose is
quasi-static. `auto` takes it only where the load-friction fit of its test finds the damping force
(c_a + 2σ)·rms ẋ_c at most model_choice.QUASI_STATIC_DAMPING_N on every cable. This runs law 1's
campaign (as `xneck campaign identification`, in process, α_IP from rendered frames) on the robot
truth with its cable damping replaced, and prints per damping: the test fit's damping force (point
and upper bound) and the output error's k and λ errors against Table 2.

    nice -n 5 .venv/bin/python docs/identification/damping_sweep.py --damping 40,150,300,600,1200 --seed 0
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.identification_loop import law1_campaign
from controller.trajectory import identification_trajectory
from twin.identification.loadfriction import fit_load_friction
from twin.identification.model_choice import TEST_TAU_S, damping_check
from twin.identification.outputerror import fit_output_error
from twin.identification.processing import preprocess
from twin.model.params import load_params
from twin.sim.truth import load_truth


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--damping", default="40,150,300,600,1200", help="the line's damping c_a, N·s/m, comma-separated")
    ap.add_argument("--seed", type=int, default=0, help="campaign seed")
    args = ap.parse_args()
    params, traj, robot = load_params(), identification_trajectory(), load_truth("robot")
    true_k, true_lam = np.asarray(params.cables.variable.k), np.asarray(params.cables.variable.lam)
    pct = lambda a: ", ".join(f"{100 * x:+.1f}" for x in a)  # noqa: E731
    print(f"law 1's campaign, seed {args.seed}, robot truth with the line's damping replaced\n")
    print("| c_a (N·s/m) | test fit: c_a·rms ẋ_c (N) | (c_a + 2σ)·rms ẋ_c (N) | `auto` | output error: k error (%) | λ error (%) |")
    print("|---|---|---|---|---|---|")
    for c_a in (float(v) for v in args.damping.split(",")):
        proc = preprocess(law1_campaign(args.seed, robot.replace("cables", damping_N_s_m=c_a), params, traj), params)
        plain = fit_load_friction(proc, params, gear=(0.0, 0.0), taus_s=(TEST_TAU_S,)).estimate
        check = damping_check(plain, proc.x_c_dot)
        point = plain.vector("c_a") * np.sqrt(np.mean(proc.x_c_dot ** 2, axis=0))
        est = fit_output_error(proc, params)
        print(f"| {c_a:g} | {', '.join(f'{f:.2f}' for f in point)} | {', '.join(f'{f:.2f}' for f in check.force_N)} | "
              f"{'outputerror' if check.quasi_static else 'loadfriction'} | {pct(est.vector('k') / true_k - 1)} | "
              f"{pct(est.vector('lambda') / true_lam - 1)} |", flush=True)


if __name__ == "__main__":
    main()
