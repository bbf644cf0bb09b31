"""The test `--estimator auto` chooses by, over campaign seeds (docs/identification-coverage.md,
"The default estimator: `auto`").

Per seed: the identification closed loop (controller/identification_loop.py, the §5.2.2
cycloids) on the truth, then the load-friction fit and the one-sided test of the cables' pooled μ
(twin/identification/model_choice.py). Prints one line per seed, then the range.

    .venv/bin/python docs/identification/model_choice_scan.py --truth pipeline --first 21 --seeds 20
    .venv/bin/python docs/identification/model_choice_scan.py --truth robot --only cables --first 0 --seeds 3 --errors
    .venv/bin/python docs/identification/model_choice_scan.py --archive CAMPAIGN.mcap --errors
    .venv/bin/python docs/identification/model_choice_scan.py --truth model --campaign law1 --first 0 --seeds 1 --tau-grid
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

from controller.identification_loop import DAMPING_ONLY_TRUTH, law1_campaign, simulate_campaign
from controller.trajectory import recorded_excitation
from twin.identification.loadfriction import fit_load_friction
from twin.identification.model_choice import TEST_TAU_S, paper_model_test
from twin.identification.pipeline import identify_friction, identify_variable, preprocess
from twin.identification.record import campaign_data_from_mcap
from twin.model.params import load_params
from twin.sim.truth import EFFECTS, load_truth


def _sigma(est, symbol: str) -> np.ndarray:
    return np.array([est.sigma[est.names.index(f"{symbol}({j + 1})")] for j in range(len(est.vector(symbol)))])


def _pooled_z(v: np.ndarray, sd: np.ndarray) -> float:
    """The cables' values pooled with their precision, over its σ (as model_choice pools μ)."""
    ok = sd > 0
    w = 1.0 / sd[ok] ** 2
    return float(np.sum(w * v[ok]) / np.sqrt(np.sum(w)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--truth", default="pipeline", help="pipeline (the damping-only truth), robot, or a truth file")
    ap.add_argument("--first", type=int, default=21, help="first campaign seed")
    ap.add_argument("--seeds", type=int, default=20, help="how many seeds")
    ap.add_argument("--only", nargs="+", metavar="EFFECT", help=f"the truth with only these effects on ({', '.join(EFFECTS)})")
    ap.add_argument("--archive", nargs="+", type=Path, metavar="MCAP", help="recorded campaigns instead of simulated "
                    "ones, processed as `xneck identify` does")
    ap.add_argument("--errors", action="store_true", help="also Table 2's k and λ errors (%%) by IDIM-IV and by the "
                    "load-friction fit, and the pooled z of the creep β")
    ap.add_argument("--tau-grid", action="store_true", help="also the test's z on a fit over the whole τ grid "
                    "(what the test used before it held τ at model_choice.TEST_TAU_S)")
    ap.add_argument("--campaign", choices=("loop", "law1"), default="loop", help="loop (default): the known-answer "
                    "loop; law1: law 1's campaign as `xneck campaign identification` runs it")
    a = ap.parse_args()
    if a.seeds < 1:
        ap.error("--seeds must be at least 1")
    params = load_params()
    truth = DAMPING_ONLY_TRUTH if a.truth == "pipeline" else load_truth(a.truth)
    if a.only:
        truth = truth.only(*a.only)
    k_lam = np.r_[params.cables.variable.k, params.cables.variable.lam]
    tests = []
    runs = ([(str(f), f) for f in a.archive] if a.archive
            else [(f"{a.truth} seed {seed}", seed) for seed in range(a.first, a.first + a.seeds)])
    for label, run in runs:
        if isinstance(run, Path):
            proc = preprocess(campaign_data_from_mcap(run, recorded_excitation), params)
        else:
            data = (law1_campaign(run, truth, params) if a.campaign == "law1"
                    else simulate_campaign(run, truth=truth, params=params)[0])
            proc = preprocess(data, params)
        # the test's fit (model_choice): without the gear's loss, τ held at TEST_TAU_S
        lf = fit_load_friction(proc, params, gear=(0.0, 0.0), taus_s=(TEST_TAU_S,)).estimate
        t = paper_model_test(lf)
        tests.append(t)
        grid = (f"; with the whole τ grid z {paper_model_test(fit_load_friction(proc, params, gear=(0.0, 0.0)).estimate).z:.2f}"
                if a.tau_grid else "")
        print(f"{label}: pooled mu {t.mu:.3f} +- {t.sigma:.3f}, z {t.z:.2f}, p {t.p:.3g}, "
              f"{'rejected' if t.rejects_paper_model else 'kept'}{grid}", flush=True)
        if a.errors:
            iv = identify_variable(proc, params, identify_friction(proc, params).values, estimator="iv")
            shipped = fit_load_friction(proc, params).estimate  # the estimate, the gear's loss held
            for name, e in (("iv", iv), ("loadfriction", shipped)):
                err = 100 * (np.r_[e.vector("k"), e.vector("lambda")] / k_lam - 1)
                print(f"    {name}: k {', '.join(f'{x:+.1f}' for x in err[:4])} %, λ {', '.join(f'{x:+.1f}' for x in err[4:])} %")
            print(f"    pooled z of the creep β: {_pooled_z(lf.vector('beta'), _sigma(lf, 'beta')):.1f}", flush=True)
    z, p = [t.z for t in tests], [t.p for t in tests]
    print(f"{'archives' if a.archive else f'{a.truth} seeds {a.first}-{a.first + a.seeds - 1}'}: z {min(z):.1f} to {max(z):.1f}, "
          f"p {min(p):.3g}-{max(p):.3g}, paper's model rejected on {sum(t.rejects_paper_model for t in tests)}/{len(tests)}")


if __name__ == "__main__":
    main()
