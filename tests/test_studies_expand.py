"""A study's runs are computed from their position, not built up front.

``expand()`` used to return a list of every run: a study at the limit (200,000 runs) held 83 MB of
run descriptions, built in 3.7 s (28 s under tracemalloc) in the study's thread before its first
run was submitted. The runs are now a view: the k-th run is computed
from k (law, grid point and sample by the axes' sizes), so counting, submitting a window, resuming
and paging cost what they touch. These tests hold the view to the eager expansion it replaced, run
for run: same order, same run ids, same values, same seeds."""

from __future__ import annotations

import itertools
import random
import tracemalloc

import numpy as np
import pytest

from server.studies.spec import MAX_RUNS, RunSpec, Study, StudyRuns, expand, run_count, study_from

pytestmark = pytest.mark.background  # computation only


def _eager_slots(s: Study):
    """(law, grid point index, grid point, sample) in the order expand() gave them at 0c249fc, lazily."""
    grids = [v for v in s.varies() if v.kind == "grid"]
    laws = (0,) if s.kind == "design" else s.laws
    for law in laws:
        for g, point in enumerate(itertools.product(*(v.grid().tolist() for v in grids))):
            for k in range(s.samples):
                yield law, g, point, k


def _eager_run(s: Study, law: int, g: int, point: tuple, k: int) -> RunSpec:
    """One run exactly as expand() built it at 0c249fc."""
    varies = s.varies()
    grids = [v for v in varies if v.kind == "grid"]
    randoms = [v for v in varies if v.kind != "grid"]
    seq = np.random.SeedSequence([s.seed, g, k])
    rng = np.random.default_rng(seq)
    values = {v.label: float(x) for v, x in zip(grids, point)}
    values.update({v.label: v.draw(rng) for v in randoms})
    twin_seed = int(seq.generate_state(1)[0])
    prefix = f"L{law}-" if law else ""
    return RunSpec(f"{prefix}g{g:04d}-s{k:05d}", law, twin_seed, values)


def _eager(s: Study) -> list[RunSpec]:
    return [_eager_run(s, *slot) for slot in _eager_slots(s)]


def test_expanding_a_study_at_the_limit_holds_no_list_of_its_runs() -> None:
    # 20,000 runs: the eager list held about 8 MB of them (200,000 at the limit: 83 MB, 28 s under
    # tracemalloc) before the first run could be submitted
    s = study_from("control", laws=(1, 2), samples=100, vary=("cables.variable.k=1000:3000:100", "friction.f_s=10%"))
    assert run_count(s) == 20_000
    tracemalloc.start()
    try:
        runs = expand(s)
        n, first, last = len(runs), runs[0], runs[-1]
        window = list(itertools.islice(iter(runs), 64))  # a submission window: what it takes, nothing more
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert n == 20_000 and window[0] == first and last.run_id == "L2-g0099-s00099"
    assert peak < 256 * 1024, f"expanding 20,000 runs peaked at {peak / 1e6:.1f} MB"


def test_every_run_is_the_one_the_eager_expansion_gave() -> None:
    studies = [
        study_from("control", laws=(1, 2, 3), samples=3, seed=7,
                   vary=("friction.f_s=20%", "cables.variable.k[4]=U(1500,2500)", "geometry.b=0.04:0.06:3",
                         "springs.k_left=N(100,5)", "cables.variable.lambda=1:2:2")),
        study_from("design", samples=4, vary=("geometry.n_joints=2:5:4", "geometry.b=0.02:0.08:3", "springs.k_left=10%")),
        study_from("design", samples=5, vary=("springs.k_left=10%",)),  # no grid: one grid point
        study_from("identification", samples=2),  # nothing varied
    ]
    for s in studies:
        runs, eager = expand(s), _eager(s)
        assert len(runs) == run_count(s) == len(eager)
        assert list(runs) == eager and [runs[k] for k in range(len(runs))] == eager
        assert runs[-1] == eager[-1] and runs[2:7] == eager[2:7] and runs[::-3] == eager[::-3]
        assert [runs.run_id(k) for k in range(len(runs))] == [r.run_id for r in eager]
        with pytest.raises(IndexError):
            runs[len(runs)]
        with pytest.raises(IndexError):
            runs[-len(runs) - 1]
    assert expand(studies[0]) == expand(studies[0]) == _eager(studies[0])
    assert expand(studies[0]) != expand(study_from("control", laws=(1, 2, 3), samples=3, seed=8, vary=studies[0].vary))


def test_the_kth_run_of_a_grid_of_millions_is_computed_from_k_alone() -> None:
    # beyond the limit (which study_from enforces): the view does not depend on it; 1.5 million runs,
    # two grid axes, a random path, three laws
    s = Study(kind="control", laws=(1, 2, 3), samples=5, seed=11,
              vary=("cables.variable.k=1000:3000:100", "springs.k_left=50:150:1000", "friction.f_s=10%"))
    assert run_count(s) == 1_500_000 > MAX_RUNS
    runs = expand(s)
    assert len(runs) == 1_500_000
    rng = random.Random(5)
    edges = [0, 4, 5, 4999, 5000, 499_999, 500_000, 500_001, 1_000_000, 1_499_999]
    wanted = sorted({*edges, *(rng.randrange(len(runs)) for _ in range(40))})
    slots = itertools.islice(_eager_slots(s), 0, None)
    at = 0
    for k in wanted:  # one pass through the eager order, building only the runs compared
        slot = next(itertools.islice(slots, k - at, None))
        at = k + 1
        assert runs[k] == _eager_run(s, *slot), k
        assert runs[k - len(runs)] == runs[k]


def test_a_run_id_gives_its_position_back_and_other_ids_none() -> None:
    s = study_from("control", laws=(1, 3), samples=3, vary=("geometry.b=0.04:0.06:4", "friction.f_s=10%"))
    runs = expand(s)
    assert [runs.position(r.run_id) for r in runs] == list(range(len(runs))) == list(range(24))
    for foreign in ("L2-g0000-s00000", "g0000-s00000", "L1-g0004-s00000", "L1-g0000-s00003", "L1-g0-s0",
                    "L1-g00000-s00000", "L1-g0001-s00001x", "", "L01-g0000-s00000", "L1-g-001-s00000"):
        assert runs.position(foreign) is None, foreign
    other = expand(study_from("control", laws=(1, 3), samples=3, seed=1, vary=s.vary))
    assert runs[7] in runs and runs.index(runs[7]) == 7 and runs.count(runs[7]) == 1
    assert other[7] not in runs and other[7].run_id == runs[7].run_id and "L1-g0000-s00000" not in runs
    with pytest.raises(ValueError):
        runs.index(other[7])
    with pytest.raises(ValueError):
        runs.index(runs[7], 8)
    design = expand(study_from("design", samples=2, vary=("geometry.b=0.04:0.06:3",)))
    assert design.position("g0002-s00001") == 5 and design.position("L1-g0002-s00001") is None


def test_resuming_skips_the_finished_runs_in_order_without_building_them() -> None:
    s = study_from("control", laws=(1, 2), samples=4, vary=("geometry.b=0.04:0.06:5", "friction.f_s=10%"))
    runs, eager = expand(s), _eager(s)
    done = {r.run_id for r in random.Random(2).sample(eager, 17)} | {"L3-g0000-s00000", "not-a-run"}
    assert runs.count_finished(done) == 17
    assert list(runs.unfinished(done)) == [r for r in eager if r.run_id not in done]
    assert list(runs.unfinished(set())) == eager and list(runs.unfinished({r.run_id for r in eager})) == []


def _builds(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Positions of the runs built (values drawn) from now on."""
    built: list[int] = []
    run = StudyRuns._run

    def counted(self: StudyRuns, i: int) -> RunSpec:
        built.append(i)
        return run(self, i)

    monkeypatch.setattr(StudyRuns, "_run", counted)
    return built


def test_a_resumed_study_builds_only_the_runs_it_submits(tmp_path, monkeypatch) -> None:
    # run_study kept a list of the unfinished runs, built from the whole expansion, before the first
    # window was submitted; and a finished study's rerun built every run to find nothing to do
    from server.studies import execute

    s = study_from("design", samples=100, vary=("geometry.b=0.03:0.06:20",), design_configurations=10)  # 2,000 runs
    runs = expand(s)
    out = tmp_path / "study"
    built = _builds(monkeypatch)
    seen: dict[str, object] = {}

    def execute_window(cfg, todo, out_, total, done, *_a) -> None:  # the Dask part: takes a first window
        seen.update(total=total, done=done, window=list(itertools.islice(todo, 8)))

    monkeypatch.setattr(execute, "_execute", execute_window)
    monkeypatch.setattr("server.studies.report.write_outputs", lambda out_, study, total: {"runs_total": total})
    progress: list[tuple[int, int, str]] = []
    assert execute.run_study(s, out, client=object(), progress=lambda *p: progress.append(p)) == {"runs_total": 2000}
    assert progress == [(0, 2000, "starting")] and seen["window"] == _eager(s)[:8] and built == list(range(8))

    built.clear()
    with execute.study_dir(s, out):  # 1,500 rows on disk, another study's id among them
        execute.write_batch(out, [{"run_id": runs.run_id(i), "law": 0} for i in range(1500)] + [{"run_id": "g9999-s00000", "law": 0}])
    progress.clear()
    assert execute.run_study(s, out, client=object(), progress=lambda *p: progress.append(p)) == {"runs_total": 2000}
    assert progress == [(1500, 2000, "resuming")] and seen["total"] == 2000 and seen["done"] == 1500
    assert seen["window"] == _eager(s)[1500:1508] and built == list(range(1500, 1508))

    built.clear()
    with execute.study_dir(s, out):
        execute.write_batch(out, [{"run_id": runs.run_id(i), "law": 0} for i in range(1500, 2000)])
    (out / "summary.json").write_text('{"runs_done": 2000, "kept": true}')
    assert execute.run_study(s, out, client=object()) == {"runs_done": 2000, "kept": True}
    assert built == []  # a finished study's rerun: nothing to build, nothing to run
