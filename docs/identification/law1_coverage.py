"""Law 1's identification campaigns run in process, then ``loadfriction``: the k and λ errors and
the ±2σ coverage over seeds (docs/identification-coverage.md, "The friction's shape").

The campaign is what `xneck campaign identification` runs on the bus: law 1 on the §5.2.2
cycloids against the robot truth with the rendered camera, here through the offline closed loop
(controller.offline.run_closed_loop), about 10 s a seed plus the fit.

    nice -n 19 .venv/bin/python docs/identification/law1_coverage.py --first 21 --seeds 20 [--creep-time-s 2]
        [--estimator outputerror|auto]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.identification_loop import law1_campaign
from controller.trajectory import identification_trajectory
from twin.identification.loadfriction import creep_taus, fit_load_friction
from twin.identification.model_choice import auto_choice
from twin.identification.outputerror import fit_output_error
from twin.identification.pipeline import identify_friction, identify_variable
from twin.identification.processing import preprocess
from twin.model.params import load_params


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--first", type=int, default=21, help="first campaign seed")
    ap.add_argument("--seeds", type=int, default=20, help="how many seeds")
    ap.add_argument("--truth", default="robot", help="robot, model, or a truth file")
    ap.add_argument("--creep-time-s", type=float, help="the line's creep time held in the fit (as `xneck identify "
                    "--creep-time-s`); default: chosen from each campaign")
    ap.add_argument("--estimator", choices=("loadfriction", "outputerror", "auto"), default="loadfriction",
                    help="Table 2's estimator: loadfriction (default), outputerror (twin/identification/outputerror.py) "
                    "or auto (the users' default, through the pipeline: its choice is printed per seed)")
    args = ap.parse_args()
    if args.creep_time_s is not None and args.estimator == "outputerror":
        ap.error("--creep-time-s applies to the load-friction fit (and auto)")
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    params, traj = load_params(), identification_trajectory()
    truth = {"k": np.asarray(params.cables.variable.k), "lambda": np.asarray(params.cables.variable.lam)}
    within = covered = cases = 0
    rel_sigma: dict[str, list[np.ndarray]] = {"k": [], "lambda": []}
    chose: dict[str, int] = {}
    print("| seed | k error (%) | λ error (%) | covered by ±2σ (k, λ) | "
          + ("auto chose: " if args.estimator == "auto" else "") + "c_f (s/rad) |")
    print("|---|---|---|---|---|")
    for seed in range(args.first, args.first + args.seeds):
        data = law1_campaign(seed, args.truth, params, traj)
        proc = preprocess(data, params)
        if args.estimator == "auto":
            f_s = identify_friction(proc, params).values
            est = identify_variable(proc, params, f_s, estimator="auto", creep_time_s=args.creep_time_s)
            chose[auto_choice(est.estimator)[0]] = chose.get(auto_choice(est.estimator)[0], 0) + 1
        elif args.estimator == "outputerror":
            est = fit_output_error(proc, params)
        else:
            est = fit_load_friction(proc, params, taus_s=creep_taus(args.creep_time_s)).estimate
        cells = []
        for sym in ("k", "lambda"):
            v, sd = est.vector(sym), est.sigma[[i for i, n in enumerate(est.names) if n.split("(")[0] == sym]]
            err, cov = v / truth[sym] - 1, np.abs(v - truth[sym]) <= 2 * sd
            rel_sigma[sym].append(sd / np.abs(v))
            within, covered, cases = within + int(np.sum(np.abs(err) <= 0.10)), covered + int(cov.sum()), cases + 4
            cells.append((", ".join(f"{100 * e:+.1f}" for e in err), int(cov.sum())))
        c_f = ", ".join(f"{c:.3g}" for c in est.vector("c_f")) if "c_f(1)" in est.names else "– (a sign)"
        if args.estimator == "auto":
            c_f = f"{auto_choice(est.estimator)[0]}: {c_f}"
        print(f"| {seed} | {cells[0][0]} | {cells[1][0]} | {cells[0][1]}/4, {cells[1][1]}/4 | {c_f} |", flush=True)
    print(f"\nwithin 10 %: {within}/{cases}; covered by ±2σ: {covered}/{cases}")
    mean = {sym: ", ".join(f"{100 * x:.1f}" for x in np.mean(v, axis=0)) for sym, v in rel_sigma.items()}
    print(f"mean relative σ (%): k {mean['k']}; λ {mean['lambda']}")
    if chose:
        print("auto chose: " + ", ".join(f"{name} on {n}" for name, n in sorted(chose.items())))


if __name__ == "__main__":
    main()
