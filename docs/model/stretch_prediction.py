"""Eq. 58's predicted cable stretch against the twin's true stretch, with t = f − f_friction(θ̇) in
the variable stiffness (as implemented) and with λ·f as the paper prints it (docs/model.md,
"Elongation prediction (eq. 58)").

    .venv/bin/python docs/model/stretch_prediction.py                 # law 3, model truth, seed 0
    .venv/bin/python docs/model/stretch_prediction.py --truth robot   # the robot's unmodelled physics

What runs: the §7 control test with law 3 (the law whose α̂ uses eq. 58) closed on the twin in one
process, one state per 2 ms, as ``xneck campaign control --twin --law 3`` runs it over the bus
(controller.offline.run_closed_loop's loop, here keeping each tick's true stretch, true motor
velocities and the forces sent). Along the run, eq. 58 is stepped from x_c = 0 as the estimator
steps it, twice per input set:

- implemented: x_c⁺ = x_c + Δt/c_a·(t − (k + λ·t)·x_c), t = f − f_friction(θ̇)
  (twin.model.estimation.predict_elongation);
- as printed: x_c⁺ = x_c + Δt/c_a·(t − (k + λ·f)·x_c).

Inputs: "law" = what law 3 has, the forces it sent over the last period and its filtered encoder
velocities (the implemented prediction is then the law's own x_c, checked here); "truth" = the same
forces with the twin's true θ̇ at the start of each period (the formula alone). One row more, on the
truth inputs: t with the motor inertia that eq. 41 keeps and eq. 58 leaves out, t = f − f_friction(θ̇)
− I_a·θ̈/ρ (θ̈ from the twin's θ̇ over the period; a law has no clean θ̈), which says what the rest
of the implemented prediction's error is. Printed: |predicted − true stretch| in mm, max and p99 over
every cable and tick, and the max per cable. About 2 s on the 2-CPU machine (2026-11-26, numba's cache warm).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.laws import ComputedTorque, LawConfig
from controller.trajectory import control_test_trajectory
from twin.model.dynamics import f_friction
from twin.model.estimation import predict_elongation
from twin.model.params import load_params
from twin.sim.simulator import Twin, TwinConfig
from twin.sim.truth import load_truth

SETTLE_S = 1.0  # s held at the last waypoint, as a campaign does (run_closed_loop's settle_s)


def printed_eq58(model, x_c: np.ndarray, f: np.ndarray, theta_dot: np.ndarray, dt: float) -> np.ndarray:
    """Eq. 58 as the paper prints it: λ·f, not λ·t, in the variable stiffness."""
    t = f - f_friction(model, theta_dot)
    return np.maximum(x_c + dt / model.c_a * (t - (model.k + model.lam * f) * x_c), 0.0)


def with_inertia(model, x_c: np.ndarray, f: np.ndarray, theta_dot: np.ndarray, theta_ddot: np.ndarray,
                 dt: float) -> np.ndarray:
    """Eq. 58 (implemented) with the motor inertia in t: eq. 41's I_a·θ̈ at the drum, I_a·θ̈/ρ."""
    t = f - f_friction(model, theta_dot) - model.I_a * theta_ddot / model.rho
    return np.maximum(x_c + dt / model.c_a * (t - (model.k + model.lam * t) * x_c), 0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--truth", default="model", help="What the twin simulates: model, robot or a truth FILE.")
    parser.add_argument("--seed", type=int, default=0, help="Seed of the twin's sensor noise.")
    args = parser.parse_args()
    try:
        load_truth(args.truth)
    except ValueError as exc:  # an unknown truth or a bad truth file: one line, before anything runs
        parser.error(str(exc))
    start = time.perf_counter()
    params = load_params()
    traj = control_test_trajectory()
    twin = Twin(params, TwinConfig(seed=args.seed, truth=args.truth, camera=False))
    ctl = ComputedTorque(params, LawConfig(law=3))
    model, dt = ctl.model, ctl.dt
    nc = model.n_cables
    n = int(round((traj.duration_s + SETTLE_S) / twin.dt))
    true_x = np.empty((n, nc))
    x = {(inputs, form): np.zeros(nc) for inputs in ("law", "truth") for form in ("implemented", "printed")}
    x["truth", "+ inertia"] = np.zeros(nc)
    err = {key: np.empty((n, nc)) for key in x}
    law_gap = 0.0  # |the law's own x_c − the implemented prediction on the law's inputs|: 0 if this replays it
    tick = twin.tick(np.zeros(nc))  # the first state the law sees, after one period from rest
    theta_dot_start = np.zeros(nc)  # the twin's θ̇ at the start of the period that just ended
    for k in range(n):
        a_d, a_d_dot, a_d_ddot = traj.sample_at(tick.t_s)
        f_over = ctl.f_prev.copy()  # the forces over the period that ended at this state (eq. 58's f)
        cmd = ctl.step(tick.theta_meas, a_d, a_d_dot, a_d_ddot, traj.pretension_at(tick.t_s))
        true_x[k] = tick.elongation
        for form, step in (("implemented", predict_elongation), ("printed", printed_eq58)):
            x["truth", form] = step(model, x["truth", form], f_over, theta_dot_start, dt)
            x["law", form] = step(model, x["law", form], f_over, ctl.theta_dot, dt)
        x["truth", "+ inertia"] = with_inertia(model, x["truth", "+ inertia"], f_over, theta_dot_start,
                                               (tick.theta_dot - theta_dot_start) / dt, dt)
        law_gap = max(law_gap, float(np.max(np.abs(x["law", "implemented"] - ctl.estimator.x_c))))
        for key in x:
            err[key][k] = x[key] - true_x[k]
        theta_dot_start = tick.theta_dot.copy()
        tick = twin.tick(cmd.f)
    wall = time.perf_counter() - start
    print(f"§7 control test, law 3, twin truth {args.truth}, seed {args.seed}: {n} ticks ({n * twin.dt:.1f} s); "
          f"true stretch up to {1e3 * true_x.max():.3f} mm")
    print(f"the law's own x_c against the implemented prediction on its inputs: max {1e3 * law_gap:.2g} mm")
    print("|predicted − true stretch| (mm)")
    print(f"  {'inputs':7s} {'eq. 58':12s} {'max':>8s} {'p99':>8s}   max per cable")
    for (inputs, form), e in err.items():
        a = 1e3 * np.abs(e)
        per = " ".join(f"{v:.3f}" for v in a.max(axis=0))
        print(f"  {inputs:7s} {form:12s} {a.max():8.3f} {np.percentile(a, 99):8.3f}   {per}")
    print(f"wall {wall:.1f} s")


if __name__ == "__main__":
    main()
