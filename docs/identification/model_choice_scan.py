"""The test `--estimator auto` chooses by, over campaign seeds (docs/identification-coverage.md,
"The default estimator: `auto`").

Per seed: the identification closed loop (controller/identification_loop.py, the §5.2.2
cycloids) on the truth, then the load-friction fit and the one-sided test of the cables' pooled μ
(twin/identification/model_choice.py). Prints one line per seed, then the range.

    .venv/bin/python docs/identification/model_choice_scan.py --truth pipeline --first 21 --seeds 20
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.identification_loop import DAMPING_ONLY_TRUTH, simulate_campaign
from twin.identification.loadfriction import fit_load_friction
from twin.identification.model_choice import paper_model_test
from twin.identification.pipeline import preprocess
from twin.model.params import load_params
from twin.sim.truth import load_truth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--truth", default="pipeline", help="pipeline (the damping-only truth), robot, or a truth file")
    ap.add_argument("--first", type=int, default=21, help="first campaign seed")
    ap.add_argument("--seeds", type=int, default=20, help="how many seeds")
    a = ap.parse_args()
    if a.seeds < 1:
        ap.error("--seeds must be at least 1")
    params = load_params()
    truth = DAMPING_ONLY_TRUTH if a.truth == "pipeline" else load_truth(a.truth)
    tests = []
    for seed in range(a.first, a.first + a.seeds):
        proc = preprocess(simulate_campaign(seed, truth=truth, params=params)[0], params)
        t = paper_model_test(fit_load_friction(proc, params).estimate)
        tests.append(t)
        print(f"{a.truth} seed {seed}: pooled mu {t.mu:.3f} +- {t.sigma:.3f}, z {t.z:.1f}, p {t.p:.3g}, "
              f"{'rejected' if t.rejects_paper_model else 'kept'}", flush=True)
    z, p = [t.z for t in tests], [t.p for t in tests]
    print(f"{a.truth} seeds {a.first}-{a.first + a.seeds - 1}: z {min(z):.1f} to {max(z):.1f}, "
          f"p {min(p):.3g}-{max(p):.3g}, paper's model rejected on {sum(t.rejects_paper_model for t in tests)}/{len(tests)}")


if __name__ == "__main__":
    main()
