"""Compile every numba kernel once so its machine code lands in the on-disk cache.

Run by ``.ci/setup``: without it the first processes of a fresh checkout each spend seconds
compiling (several at once on a small machine), which a lockstep campaign would mistake for a
dead peer, and a first identification or analysis spends a minute of CPU before its first result.
``python -m controller.warmup`` compiles the two parts below in two processes at once (one CPU
each), then runs both again in this process, which loads them from the cache and recompiles any
version the other process's cache index overwrote (numba updates an index by read-modify-write).

- ``control``: the 500 Hz loop, the twin's simulator and the encoder check, as the stack runs them.
- ``analysis``: the batch functions of the model (evaluate, statics, cables, jets, α̂ by eq. 33,
  tensions), the encoder check over a record and the identification's creep kernels, with the
  argument types the identification, the studies and the console's analysis give them.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np

PARTS = ("control", "analysis")


def control() -> None:
    """The stack's kernels: the twin in each cable model, each control law, the encoder check."""
    from controller.encoder_check import EncoderConsistency
    from controller.laws import ComputedTorque, LawConfig
    from twin.model.params import load_params
    from twin.sim.simulator import Twin, TwinConfig

    params = load_params()
    for cable_model in ("rigid", "linear", "variable"):
        twin = Twin(params, TwinConfig(cable_model=cable_model, camera=False))
        twin.tick(np.full(twin.model.n_cables, 10.0))
    for law in (1, 2, 3):
        ctl = ComputedTorque(params, LawConfig(law=law))
        ctl.step(np.zeros(params.n_cables), np.zeros(params.n_joints), np.zeros(params.n_joints), np.zeros(params.n_joints))
    EncoderConsistency(params).update(np.zeros(params.n_cables), np.zeros(params.n_joints), np.zeros(params.n_cables),
                                      np.zeros(params.n_cables), 0.0)


def analysis() -> None:
    """The batch kernels, called through the public functions that hand them their arrays (one
    compiled version each: twin.model.compiled.kernel_array), and eq. 54's tension law with the
    argument kinds its callers in twin/identification give it."""
    from controller.encoder_check import detector_model, residuals
    from twin.identification.loadfriction import MIN_STRETCH_FACTOR, _creep_tension, _creep_tension_jacobian
    from twin.identification.neck_sensitivity import creep_stretch_jacobian
    from twin.identification.outputerror import creep_stretch
    from twin.model import cables, dynamics, estimation, xjoint
    from twin.model.numeric import build
    from twin.model.params import load_params

    params = load_params()
    model = build(params, cable_model="variable")
    N, nc, n = params.n_joints, params.n_cables, 8
    alpha, theta = np.full((n, N), 0.1), np.zeros((n, nc))
    dynamics.evaluate(model, alpha)
    dynamics.evaluate(model, alpha, alpha)
    dynamics.statics(model, alpha)
    cables.batch(model, alpha, alpha)
    xjoint.jets(model.L, model.b, model.r, alpha)
    estimation.alpha_hat_3(model, theta[0])
    dynamics.accelerations(model, alpha[0], theta[0], alpha[0], theta[0], np.full(nc, 10.0))
    dynamics.f_friction(model, theta)
    x = np.full((n, nc), 1e-3)
    dynamics.tension(model, x, x)
    dynamics.tension(model, x[0], x[0])
    k, lam, c_a = model.k.copy(), model.lam.copy(), model.c_a.copy()
    dynamics.cable_tension_law(k, lam, 0.0, x, 0.0)  # instruments.py
    dynamics.cable_tension_law(k, 0.0, c_a, x, x)  # pipeline.py, the linear model
    dynamics.cable_tension_law(k, lam, c_a, x, x)  # pipeline.py and validation.py
    residuals(detector_model(params), theta, alpha, np.full((n, nc), 10.0), theta)
    _creep_tension(5e3, 100.0, 40.0, 0.1, x[:, 0].copy(), x[:, 0].copy(), 0.01, MIN_STRETCH_FACTOR)
    _creep_tension_jacobian(5e3, 100.0, 40.0, 0.1, x[:, 0].copy(), x[:, 0].copy(), 0.01, MIN_STRETCH_FACTOR)
    creep_stretch(x, lam, 0.1, 10.0, 0.032)
    creep_stretch_jacobian(x, np.zeros((n, nc, 2 * nc + 2)), lam, 0.1, 0.01, 0.01, MIN_STRETCH_FACTOR, 0, nc, nc + 1)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m controller.warmup", description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--part", choices=PARTS, help="compile one part in this process (default: both, in parallel)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.part:
        {"control": control, "analysis": analysis}[args.part]()
        print(f"numba kernels ({args.part}) compiled and cached in {time.perf_counter() - t0:.1f} s")
        return
    if (os.cpu_count() or 1) > 1:
        procs = [subprocess.Popen([sys.executable, "-m", "controller.warmup", "--part", part]) for part in PARTS]
        failed = [part for part, p in zip(PARTS, procs) if p.wait() != 0]
        if failed:
            sys.exit(f"warmup: the {', '.join(failed)} part failed (its error is above)")
    t1 = time.perf_counter()
    control()
    analysis()
    print(f"numba kernels compiled and cached in {time.perf_counter() - t0:.1f} s "
          f"(checked from the cache in {time.perf_counter() - t1:.1f} s)")


if __name__ == "__main__":
    main()
