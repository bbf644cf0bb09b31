"""Compile every numba kernel once so its machine code lands in the on-disk cache.

Run by ``.ci/setup``: without it the first processes of a fresh checkout each spend seconds
compiling (several at once on a small machine), which a lockstep campaign would mistake for a
dead peer. ``python -m controller.warmup``.
"""

from __future__ import annotations

import time

import numpy as np


def main() -> None:
    t0 = time.perf_counter()
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
    print(f"numba kernels compiled and cached in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
