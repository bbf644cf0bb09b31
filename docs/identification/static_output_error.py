"""Table 2's k and λ without the motor forces: the neck's static output error (issues 16, 17; tried, not shipped).

Every estimator of the pipeline fits eq. 54 to a tension taken from the motor force less a
friction model (eq. 55, or the load-friction fit's (1 + a·μ)·t + a·F₀): whatever that model lacks
(on the robot truth the friction's direction asymmetry, a value without a source) biases k and λ,
λ(3) most (docs/identification-coverage.md, "What biases λ(3)"). Friction acts upstream of the
encoders, though. The neck's pose follows from the motor angles θ and the cables alone: at every
identification instant α solves the neck's equilibrium (eq. 32, quasi-static)

    Z(α)·t(x) = g(α),   x = l_c(α) − l_c0 + ρ·θ − c,   t = k·x/(1 − λx)   (eq. 54)

with c the Kelvin creep of the load-friction fit (τ·ċ = β·x/(1 − λx) − c). This script fits
(k, λ, β, τ) by bounded least squares so that this α, simulated from the encoders
(twin.identification.instruments.neck_equilibrium), matches the camera's α_IP: an output-error
estimator (BIRDy's DIDIM, with the encoders as the input) that never uses a force. What it
depends on instead is the structure: the lateral springs' rates and free lengths, the bar masses
(g), the pulley radii (Z, l_c), all from the parameter file, which the robot truth perturbs
(twin/sim/robot_truth.toml [structure]). Its biases are therefore of another kind than the force
fit's; the table it prints puts the two side by side on law 1's campaigns. The estimator built
from it, with the springs' rates free and the forces for the tension's scale, is
twin/identification/outputerror.py (`--estimator outputerror`).

    nice -n 5 .venv/bin/python docs/identification/static_output_error.py --first 61 --seeds 6 [--truth robot|model|FILE]
        [--without structure ...]

About 30 s a seed (the campaign, both fits). σ is not computed: this is a diagnosis.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.identification_loop import law1_campaign
from controller.trajectory import identification_trajectory
from twin.identification.loadfriction import fit_load_friction
from twin.identification.outputerror import _Neck
from twin.identification.processing import Processed, preprocess
from twin.model.numeric import build
from twin.model.params import Params, load_params
from twin.sim.truth import EFFECTS, load_truth

FloatArray = NDArray[np.float64]
EDGE_S = 5.0  # s dropped at each end: the zero-phase filter's edges


class StaticOutputError:
    """α simulated from the encoders for (k, λ, β, τ) with the parameter file's springs: the
    estimator's re-simulated neck (twin.identification.outputerror._Neck, warm-started from its
    last solve) with every spring-rate factor at 1."""

    def __init__(self, params: Params, proc: Processed) -> None:
        self.proc = proc
        m = build(params, "variable")
        self.neck = _Neck(params, m, proc, np.array(proc.alpha, dtype=float))
        self.springs = np.ones(2 * m.n_joints)
        self.keep = slice(int(EDGE_S * proc.rate_hz), proc.n - int(EDGE_S * proc.rate_hz))

    def alpha_of(self, k: FloatArray, lam: FloatArray, beta: float, tau_s: float) -> FloatArray:
        return self.neck.simulate(k, lam, beta, tau_s, self.springs)[0]

    def fit(self, k0: FloatArray, lam0: FloatArray) -> tuple[FloatArray, FloatArray, float, float, float]:
        """(k (N/m), λ (1/m), β, τ (s), rms α residual (rad)), from (k0, λ0); q = (log k/k0, log λ/λ0, β, log τ)."""
        nc = len(k0)

        def residual(q: FloatArray) -> FloatArray:
            a = self.alpha_of(np.exp(q[:nc]) * k0, np.exp(q[nc:2 * nc]) * lam0, float(q[2 * nc]), float(np.exp(q[-1])))
            return (a - self.proc.alpha)[self.keep].ravel()

        q0 = np.r_[np.zeros(2 * nc), 0.02, np.log(1.0)]
        lo = np.r_[np.full(2 * nc, -3.0), 0.0, np.log(0.2)]
        hi = np.r_[np.full(2 * nc, 3.0), 0.5, np.log(20.0)]
        sol = optimize.least_squares(residual, q0, bounds=(lo, hi), diff_step=1e-4, xtol=1e-8)
        return (np.exp(sol.x[:nc]) * k0, np.exp(sol.x[nc:2 * nc]) * lam0, float(sol.x[2 * nc]), float(np.exp(sol.x[-1])),
                float(np.sqrt(np.mean(sol.fun ** 2))))


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--first", type=int, default=61, help="first campaign seed (default 61)")
    ap.add_argument("--seeds", type=int, default=6, help="how many seeds (default 6)")
    ap.add_argument("--truth", default="robot", help="robot (default), model, or a truth file")
    ap.add_argument("--without", nargs="+", default=[], metavar="EFFECT",
                    help=f"switch these effects of the truth off ({', '.join(EFFECTS)}), e.g. structure")
    args = ap.parse_args()
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    try:
        truth = load_truth(args.truth)
        if args.without:
            truth = truth.only(*[e for e in EFFECTS if getattr(truth, e).enabled and e not in args.without],
                               *[e for e in args.without if e not in EFFECTS])  # an unknown name is refused there
    except (OSError, ValueError) as exc:
        ap.error(f"--truth {args.truth}: {exc}")
    params, traj = load_params(), identification_trajectory()
    true_k, true_lam = np.asarray(params.cables.variable.k, float), np.asarray(params.cables.variable.lam, float)
    # the start is no prior: every k at 4000 N/m, every λ at 80 /m (Table 2: 1900-6200, 53-121)
    k0, lam0 = np.full(params.n_cables, 4000.0), np.full(params.n_cables, 80.0)
    print(f"truth `{args.truth}`{' without ' + ', '.join(args.without) if args.without else ''}, law 1's campaigns (the rendered camera), seeds {args.first}-{args.first + args.seeds - 1}; "
          "error against Table 2 (%)\n")
    print("| seed | fit | k error (%) | λ error (%) | β, τ (s) | rms α residual (°) | fit time (s) |")
    print("|---|---|---|---|---|---|---|")
    within = {"static output error": 0, "loadfriction (shipped)": 0}
    for seed in range(args.first, args.first + args.seeds):
        proc = preprocess(law1_campaign(seed, truth, params, traj), params)
        t0 = time.perf_counter()
        k, lam, beta, tau, rms = StaticOutputError(params, proc).fit(k0, lam0)
        rows = [("static output error", k, lam, f"{beta:.3f}, {tau:.2g}", f"{np.degrees(rms):.3f}",
                 time.perf_counter() - t0)]
        t0 = time.perf_counter()
        est = fit_load_friction(proc, params).estimate
        rows.append(("loadfriction (shipped)", est.vector("k"), est.vector("lambda"),
                     f"{float(np.mean(est.vector('beta'))):.3f} (mean)", "–", time.perf_counter() - t0))
        for name, kk, ll, creep, res, dt in rows:
            ek, el = 100 * (kk / true_k - 1), 100 * (ll / true_lam - 1)
            within[name] += int(np.sum(np.abs(ek) <= 10) + np.sum(np.abs(el) <= 10))
            print(f"| {seed} | {name} | {', '.join(f'{e:+.1f}' for e in ek)} | {', '.join(f'{e:+.1f}' for e in el)} "
                  f"| {creep} | {res} | {dt:.0f} |", flush=True)
    print()
    for name, n in within.items():
        print(f"{name}: within 10 % {n}/{8 * args.seeds}")


if __name__ == "__main__":
    main()
