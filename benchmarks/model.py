"""Cost of one evaluation of the model terms (l_c, Z, M, c, g): issue 2's speed target.

The controller has 2 ms per tick for everything, so one configuration must cost at most 100 µs
at p99. Prints median and p99 for one configuration (the compiled kernel the 500 Hz loop calls,
and the public vectorised API), per configuration in a batch of 10,000, and the ratio against a
baseline in the same process: Z by central differences of l_c through the public API (what
exact jets replace). Run: ``.venv/bin/python benchmarks/model.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
import _repo  # noqa: E402, F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing  # noqa: E402  (benchmarks/ is sys.path[0] when run as a script)

summary, time_calls = _timing.summary, _timing.time_calls

from twin.model import cables, dynamics  # noqa: E402
from twin.model.numeric import build  # noqa: E402
from twin.model.params import load_params  # noqa: E402

TARGET_P99_US = 100.0


def main() -> None:
    model = build(load_params())
    rng = np.random.default_rng(0)
    alpha, alpha_dot = np.radians([40.0, 30.0, 20.0]), np.array([0.3, -0.2, 0.5])
    work = dynamics.scratch_buffers(model)
    tab, lc, Z, Zd, Mm, cm, g, M, c, _ = work

    def kernel():
        dynamics.evaluate_into(model, alpha, alpha_dot, tab, lc, Z, Zd, Mm, cm, g)
        dynamics.motor_terms(model, Z, Zd, alpha_dot, Mm, cm, M, c)

    def public():
        dynamics.evaluate(model, alpha, alpha_dot)

    batch = rng.uniform(-1.0, 1.0, size=(10_000, 3))
    batch_dot = rng.uniform(-1.0, 1.0, size=(10_000, 3))

    def fd_baseline():
        h = 1e-6
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            cables.l_c(model, alpha + e) - cables.l_c(model, alpha - e)
        dynamics.evaluate(model, alpha, alpha_dot)

    print("xneck model benchmark: one evaluation of (l_c, Z, Ż, M, c, g) for the 3-X prototype")
    k_med, k_p99 = summary("one configuration, compiled kernel (controller path)", time_calls(kernel, 20_000))
    p_med, p_p99 = summary("one configuration, public API dynamics.evaluate", time_calls(public, 20_000))
    summary("per configuration, batch of 10,000", time_calls(lambda: dynamics.evaluate(model, batch, batch_dot), 30, 2), per=10_000)
    b_med, _ = summary("baseline: public API + Z by central differences of l_c", time_calls(fd_baseline, 5_000))
    print(f"ratio baseline / kernel (median): {b_med / k_med:6.1f}x    baseline / public API: {b_med / p_med:6.1f}x")
    worst = max(k_p99, p_p99)
    verdict = "meets" if worst <= TARGET_P99_US else "MISSES"
    print(f"target: p99 <= {TARGET_P99_US:.0f} µs per configuration -> {verdict} (worst p99 {worst:.2f} µs)")


if __name__ == "__main__":
    main()
