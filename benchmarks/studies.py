"""Study throughput on Dask: runs per second with 1 and 2 local workers, and the per-task overhead
against a plain loop of the same runs (issue 19).

    .venv/bin/python benchmarks/studies.py [--runs 20] [--trajectory control_test]

Each run is a §7 control campaign (law 2, the 14 s control_test trajectory, lockstep twin in
process) with friction and cable stiffness drawn 10 % off. The plain loop calls the per-run
function (server.studies.run.run_one) in this process; the Dask figures are whole studies
(server.studies.execute.run_study: tasks, Parquet batches, summary and figures) on a warm
LocalCluster of 1 then 2 worker processes. Overhead per task = (study wall time without the
summary and figures, which a study draws once whatever its size, x workers − the runs' own time
measured inside the workers) / runs. Targets (issue 19): 2 workers >= 1.7x the runs per second
of 1 on a 2-core machine; overhead <= 5 % of a run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing
import numpy as np

from server.studies.execute import loopback_cluster, read_rows, run_study, software_version
from server.studies.report import write_outputs
from server.studies.run import config_for, run_one
from server.studies.spec import expand, study_from

VARY = ("friction.f_s=10%", "cables.variable.k=10%")


def _study(runs: int, trajectory: str, seed: int):
    return study_from("control", samples=runs, vary=VARY, laws=(2,), trajectory=trajectory, seed=seed)


def _on_cluster(client, runs: int, trajectory: str, seed: int) -> tuple[float, float, np.ndarray]:
    """(wall s of a whole study, of its summary and figures alone, each run's own seconds inside its worker)."""
    study = _study(runs, trajectory, seed)
    with tempfile.TemporaryDirectory(prefix="xneck-bench-study-") as tmp:
        t0 = time.perf_counter()
        run_study(study, Path(tmp), client=client)
        wall = time.perf_counter() - t0
        t0 = time.perf_counter()
        write_outputs(Path(tmp), study, runs)  # once per study, whatever its size: not a per-task cost
        report = time.perf_counter() - t0
        return wall, report, np.array([r["run_s"] for r in read_rows(Path(tmp))])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20, help="runs per measurement")
    parser.add_argument("--trajectory", default="control_test")
    args = parser.parse_args()
    from distributed import Client

    study = _study(args.runs, args.trajectory, 1)
    cfg = config_for(study, software_version())
    runs = expand(study)
    run_one(cfg, runs[0])  # warm-up: imports, numba kernels from the cache
    loop = np.empty(len(runs))
    for k, r in enumerate(runs):
        t0 = time.perf_counter()
        run_one(cfg, r)
        loop[k] = time.perf_counter() - t0
    _timing.summary("plain loop: one run", loop, unit=1e-3, unit_name="ms")
    loop_rate = len(runs) / loop.sum()

    cluster = loopback_cluster(1)
    try:
        client = Client(cluster)
    except BaseException:
        cluster.close()
        raise
    try:
        rates, overheads, medians = {}, {}, {}
        for n in (1, 2):
            cluster.scale(n)
            client.wait_for_workers(n)
            _on_cluster(client, 2 * n, args.trajectory, 100 + n)  # warm every worker
            wall, report, inside = _on_cluster(client, args.runs, args.trajectory, 10 + n)
            _timing.summary(f"{n} worker(s): one run inside its worker", inside, unit=1e-3, unit_name="ms")
            print(f"{n} worker(s): study {wall:.1f} s, of which summary + figures {report:.1f} s")
            rates[n] = args.runs / (wall - report)
            overheads[n] = ((wall - report) * n - inside.sum()) / args.runs  # worker-seconds not spent in runs, per run
            medians[n] = float(np.median(inside))
        print(f"{'runs per second (without the report)':<40s} plain loop {loop_rate:6.2f}   1 worker {rates[1]:6.2f}   2 workers {rates[2]:6.2f}")
        print(f"2 workers / 1 worker: {rates[2] / rates[1]:.2f}x (target >= 1.7x on 2 cores)")
        for n in (1, 2):
            # against the runs measured in the same minutes: on a shared machine the plain loop's may be another load's
            print(f"overhead per task, {n} worker(s): {1e3 * overheads[n]:.1f} ms = {100 * overheads[n] / medians[n]:.1f} % "
                  f"of a run's median in the workers, {100 * overheads[n] / np.median(loop):.1f} % of the plain loop's (target <= 5 %)")
    finally:
        client.close()
        cluster.close()


if __name__ == "__main__":
    main()
