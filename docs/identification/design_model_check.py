"""Does the excitation design's model predict the σ the identification then reports? (issue 17)

For the §5.2.2 4×6 cycloids and each trajectory file given, this prints as markdown:

* the σ ratio (trajectory / cycloids) of every k and λ that ``xneck excitation design``'s model
  predicts (twin/identification/excitation.py: ``score``, the same call the CLI reports);
* the ratio of the mean relative σ the identification reports over campaign seeds, on the
  known-answer closed loop (controller/identification_loop.py, as
  ``benchmarks/identification.py --coverage --trajectory FILE``), and the mean |error|.

    .venv/bin/python docs/identification/design_model_check.py --truth robot --estimator loadfriction \\
        docs/identification/excitation.json docs/identification/holdfree.json docs/identification/pretension.json

A design model whose predictions do not follow the measured ratios designs for the wrong thing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from controller.identification_loop import DAMPING_ONLY_TRUTH, identify_campaign  # noqa: E402
from controller.trajectory import identification_trajectory, load_trajectory  # noqa: E402
from server.cli.excitation import _problem  # noqa: E402
from twin.identification.excitation import score  # noqa: E402
from twin.model.params import load_params  # noqa: E402
from twin.sim.truth import load_truth  # noqa: E402

NAMES = [f"k({j})" for j in range(1, 5)] + [f"lambda({j})" for j in range(1, 5)]


def measured(traj, truth, estimator: str, seeds: range, params) -> tuple[np.ndarray, np.ndarray]:
    """Mean relative σ and mean |relative error| of k(1..4), λ(1..4) over ``seeds``."""
    truth_values = np.r_[params.cables.variable.k, params.cables.variable.lam]
    sig, err = [], []
    for seed in seeds:
        var = identify_campaign(seed, truth, estimator, traj, params)
        idx = [var.names.index(n) for n in NAMES]
        sig.append(var.relative_sigma[idx])
        err.append(np.abs(var.values[idx] / truth_values - 1.0))
        print(f"  seed {seed} done", file=sys.stderr, flush=True)
    return np.mean(sig, axis=0), np.mean(err, axis=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("files", nargs="+", type=Path, help="trajectory files to compare with the cycloids")
    ap.add_argument("--truth", default="robot", help="pipeline (damping only), robot, or a truth file")
    ap.add_argument("--estimator", default="loadfriction")
    ap.add_argument("--first", type=int, default=21, help="first campaign seed")
    ap.add_argument("--seeds", type=int, default=5)
    args = ap.parse_args()
    params = load_params()
    truth = DAMPING_ONLY_TRUTH if args.truth == "pipeline" else load_truth(args.truth)
    problem = _problem(params, 97.0, 0.6, "ds")
    seeds = range(args.first, args.first + args.seeds)
    paper = identification_trajectory()

    def predicted(t):
        s = score(problem, t.waypoints_rad, t.durations_s, t.dwell_s, t.pretension_N)
        return np.array([s.relative_sigma[n] for n in NAMES])

    print(f"cycloids: {len(seeds)} campaigns", file=sys.stderr, flush=True)
    base_pred = predicted(paper)
    base_sig, base_err = measured(None, truth, args.estimator, seeds, params)
    cmd = " ".join(["docs/identification/design_model_check.py", *sys.argv[1:]])
    print(f"`{cmd}` (truth `{args.truth}`, estimator `{args.estimator}`, campaign seeds {seeds[0]}-{seeds[-1]}):\n")
    print("| trajectory | " + " | ".join(n.replace("lambda", "λ") for n in NAMES) + " |")
    print("|---|" + "---|" * len(NAMES))
    print("| cycloids: measured rel. σ (%) | " + " | ".join(f"{100 * v:.2f}" for v in base_sig) + " |")
    print("| cycloids: mean \\|err\\| (%) | " + " | ".join(f"{100 * v:.1f}" for v in base_err) + " |")
    for f in args.files:
        traj = load_trajectory(f)
        print(f"{f.name}: {len(seeds)} campaigns", file=sys.stderr, flush=True)
        sig, err = measured(traj, truth, args.estimator, seeds, params)
        name = f.name + (" (pretension)" if traj.has_pretension else "")
        print(f"| {name}: predicted σ ratio | " + " | ".join(f"{v:.2f}" for v in predicted(traj) / base_pred) + " |")
        print(f"| {name}: measured σ ratio | " + " | ".join(f"{v:.2f}" for v in sig / base_sig) + " |")
        print(f"| {name}: mean \\|err\\| (%) | " + " | ".join(f"{100 * v:.1f}" for v in err) + " |")


if __name__ == "__main__":
    main()
