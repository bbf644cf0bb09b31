"""A study's runs: the lazy view (server.studies.spec.expand → StudyRuns) against the eager list it
replaced (a copy of expand() at 0c249fc), in the same process, on one study at the limit.

    .venv/bin/python benchmarks/studies_expand.py [--runs 200000] [--repeats 5]

(from any checkout: benchmarks/_repo.py puts its packages first)

Measured, each as median and p99 of the repeats, with the ratio eager / lazy: the time until the
first run can be submitted (eager: the whole list), all runs one after the other (what a study
that runs to its end builds in all), a resume with half the runs on disk until the first
unfinished run, and the peak memory (tracemalloc, once each) of expanding and taking the first run.
Target: the first run and a resume cost what they touch (not growing with the study); every run in
turn no slower than the eager list (ratio >= 0.9).
"""

from __future__ import annotations

import argparse
import itertools
import time
import tracemalloc
from collections.abc import Callable

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing
import numpy as np

from server.studies.spec import RunSpec, Study, expand


def eager_expand(s: Study) -> list[RunSpec]:
    """expand() as it was at 0c249fc: every run built into a list."""
    varies = s.varies()
    grids = [v for v in varies if v.kind == "grid"]
    randoms = [v for v in varies if v.kind != "grid"]
    points = list(itertools.product(*(v.grid().tolist() for v in grids))) or [()]
    laws = (0,) if s.kind == "design" else s.laws
    runs: list[RunSpec] = []
    for law in laws:
        for g, point in enumerate(points):
            for k in range(s.samples):
                seq = np.random.SeedSequence([s.seed, g, k])
                rng = np.random.default_rng(seq)
                values = {v.label: float(x) for v, x in zip(grids, point)}
                values.update({v.label: v.draw(rng) for v in randoms})
                twin_seed = int(seq.generate_state(1)[0])
                prefix = f"L{law}-" if law else ""
                runs.append(RunSpec(f"{prefix}g{g:04d}-s{k:05d}", law, twin_seed, values))
    return runs


def _times(fn: Callable[[], object], repeats: int) -> np.ndarray:
    out = np.empty(repeats)
    for k in range(repeats):
        t0 = time.perf_counter()
        fn()
        out[k] = time.perf_counter() - t0
    return out


def _peak(fn: Callable[[], object]) -> float:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _compare(label: str, eager: np.ndarray, lazy: np.ndarray, unit: float, unit_name: str) -> None:
    e, _ = _timing.summary(f"{label}: eager list", eager, unit=unit, unit_name=unit_name)
    la, _ = _timing.summary(f"{label}: lazy view", lazy, unit=unit, unit_name=unit_name)
    print(f"{label}: eager / lazy {e / la:.3g}x (medians)")


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--runs", type=int, default=200_000, help="runs of the study (a multiple of 2000)")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of each eager measurement")
    args = parser.parse_args()
    # a design sweep as docs/studies.md writes them: two grids and a relative spread, samples per point
    s = Study(kind="design", samples=args.runs // 2000, seed=1,
              vary=("geometry.b=0.02:0.08:40", "springs.k_left=50:150:50", "springs.k_right=10%"))
    assert len(expand(s)) == args.runs and expand(s)[-1] == eager_expand(s)[-1]
    print(f"study of {args.runs} runs ({s.vary}), {args.repeats} repeats of the eager path")

    lazy_first = _timing.time_calls(lambda: expand(s)[0], 200, warmup=5)
    eager_all = _times(lambda: eager_expand(s)[0], args.repeats)  # the first run waits for the whole list
    _compare("first run", eager_all, lazy_first, 1e-3, "ms")

    lazy_all = _times(lambda: sum(1 for _ in expand(s)), args.repeats)
    _compare("every run", eager_all, lazy_all, 1e-3, "ms")
    print(f"every run: per run eager {1e6 * np.median(eager_all) / args.runs:.1f} µs, "
          f"lazy {1e6 * np.median(lazy_all) / args.runs:.1f} µs (target: eager / lazy >= 0.9)")

    runs = expand(s)
    done = {runs.run_id(i) for i in range(0, args.runs, 2)} | {runs.run_id(i) for i in range(args.runs // 2)}  # 3/4
    eager_resume = _times(lambda: next(iter([r for r in eager_expand(s) if r.run_id not in done])), args.repeats)

    def lazy_resume() -> object:
        runs = expand(s)
        runs.count_finished(done)
        return next(runs.unfinished(done))

    _compare("resume (3/4 done): first unfinished", eager_resume, _times(lazy_resume, args.repeats), 1e-3, "ms")

    peaks = _peak(lambda: eager_expand(s)[0]), _peak(lambda: expand(s)[0])
    print(f"peak memory expanding and taking the first run: eager {peaks[0] / 1e6:.1f} MB, lazy {peaks[1] / 1e3:.1f} kB, "
          f"eager / lazy {peaks[0] / peaks[1]:.0f}x")


if __name__ == "__main__":
    main()
