"""Studies on Dask (issue 19): specs checked before anything runs, a small study on a real
LocalCluster of 2 worker processes, resume after a crash of the study's process (no row lost or
repeated), a worker killed mid-study (its tasks retried), and /api/studies over real HTTP.

Runs are the §7 loop on a short nod (0.6 s of simulated time) so that each costs about 0.1 s."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from server_harness import AUTH, running_server, wait_until

from server.studies.execute import finished_ids, part_files, read_rows, run_study
from server.studies.run import config_for, identification_metrics, run_one
from server.studies.spec import StudyError, expand, parse_vary, study_from

NOD = {"name": "nod", "waypoints_deg": [[0, 0, 0], [4, 4, 4], [0, 0, 0]], "durations_s": 0.25, "dwell_s": 0.05}
VARY = ("friction.f_s=20%", "cables.variable.k[4]=U(1500,2500)")


@pytest.fixture(scope="module")
def nod(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("traj") / "nod.json"
    path.write_text(json.dumps(NOD))
    return str(path)


def _study(nod: str, samples: int, **kw):
    return study_from("control", samples=samples, vary=VARY, laws=(1, 2), trajectory=nod, settle_s=0.1, **{"seed": 3, **kw})


BAD_SPECS = [
    ("friction.f_s", "write PATH=SPEC"),
    ("friction.f_s=abc", "none of: 10%"),
    ("friction.f_s=150%", "relative spread must be in (0, 100)"),
    ("friction.f_s=N(10,0)", "sigma must be > 0"),
    ("friction.f_s=U(3,1)", "needs a < b"),
    ("geometry.b=0.04:0.06:0", "n >= 1"),
    ("geometry.b=0.03:0.06:1", "one point cannot include both ends 0.03 and 0.06"),  # ran 0.03 only
    ("friction.nope=10%", "unknown key 'nope'"),
    ("friction.model=10%", "not numeric"),
    ("friction.f_s[9]=10%", "has 4 elements, no [9]"),
    ("geometry.b=U(0.02,0.2)", "must be smaller than L"),
    ("truth.friction.static_ratio=10%", "need --truth robot"),
    ("geometry.n_joints=3:5:3", "only a design study"),
]


def test_a_grid_of_one_point_is_its_one_value_and_both_ends_need_two() -> None:
    assert parse_vary("geometry.b=0.05:0.05:1").grid().tolist() == [0.05]
    assert parse_vary("geometry.b=0.03:0.06:2").grid().tolist() == [0.03, 0.06]
    for spec in ("geometry.b=0.03:0.06:1", "geometry.b=0.05:0.05:3"):
        with pytest.raises(StudyError, match="a:b:n"):
            parse_vary(spec)


def test_bad_specs_are_rejected_with_a_clear_message_before_anything_runs(tmp_path) -> None:
    from typer.testing import CliRunner

    from server.cli import app

    for vary, says in BAD_SPECS:
        with pytest.raises(StudyError, match=re.escape(says)):
            config_for(study_from("control", vary=(vary,), samples=2), "v")
    out = tmp_path / "study"
    for vary, says in (BAD_SPECS[1], BAD_SPECS[9]):  # the command line says it and starts nothing
        result = CliRunner().invoke(app, ["study", "control", "--out", str(out), "--vary", vary, "--samples", "2"])
        assert result.exit_code == 2 and says in result.output, result.output
        assert not out.exists()
    result = CliRunner().invoke(app, ["study", "design", "--out", str(out), "--vary", "geometry.b=0.03:0.06:2",
                                      "--vary", "geometry.b=10%"])
    assert result.exit_code == 2 and "varied twice" in result.output and not out.exists()


def test_a_bad_set_value_of_a_study_is_said_to_be_the_set_value(tmp_path) -> None:
    from typer.testing import CliRunner

    from server.cli import app

    out = tmp_path / "study"
    result = CliRunner().invoke(app, ["study", "control", "--out", str(out), "--set", "friction.f_s=nan"])
    assert result.exit_code == 2, result.output
    assert "error: --set friction.f_s=nan: " in result.output and "prototype_3x.toml:" not in result.output, result.output
    assert not out.exists()


def test_runs_are_fixed_by_the_seed_and_every_law_meets_the_same_robots(nod) -> None:
    s = _study(nod, 3)
    a, b = expand(s), expand(s)
    assert a == b and len(a) == 6 and len({r.run_id for r in a}) == 6
    by_law = {law: [r for r in a if r.law == law] for law in (1, 2)}
    assert [r.values for r in by_law[1]] == [r.values for r in by_law[2]]  # common random numbers
    assert [r.seed for r in by_law[1]] == [r.seed for r in by_law[2]]
    assert all(0.8 <= r.values["friction.f_s"] <= 1.2 and 1500 <= r.values["cables.variable.k[4]"] <= 2500 for r in a)
    assert expand(_study(nod, 3, seed=4)) != a
    grid = study_from("design", vary=("geometry.b=0.04:0.06:3", "springs.k_left=10%"), samples=2)
    assert len(expand(grid)) == 6 and {r.values["geometry.b"] for r in expand(grid)} == {0.04, 0.05, 0.06}
    assert parse_vary("friction.f_s[2]=N(15,1)").label == "friction.f_s[2]"
    ident = study_from("identification", samples=2)
    assert ident.trajectory == "identification" and {r.law for r in expand(ident)} == {1}  # §5.2.2 runs law 1


def test_a_study_with_too_many_runs_is_refused_by_counting_without_building_them(monkeypatch) -> None:
    # audit of 2026-11-26: the count was len(expand(study)): 10^9 samples built runs for minutes,
    # a grid of 10^11 points asked numpy for 745 GiB. The count is arithmetic now; expand must not run.
    from server.studies import spec

    def no_expand(_study):
        raise AssertionError("the limit check built the runs")

    monkeypatch.setattr(spec, "expand", no_expand)
    with pytest.raises(StudyError, match=r"1000000000000 runs .*more than the limit of 200000"):
        study_from("control", samples=10**12)
    with pytest.raises(StudyError, match=r"300000000000 runs \(3 laws × 100000 grid points × 1000000 samples\)"):
        study_from("control", laws=(1, 2, 3), samples=10**6, vary=("friction.f_s=10%", "cables.variable.k=1000:3000:100000"))
    with pytest.raises(StudyError, match=r"100000000000 points, more than the limit of 200000"):  # each grid capped alone
        study_from("design", vary=("geometry.b=0.02:0.08:100000000000",))
    with pytest.raises(StudyError, match=r"more than the limit of 200000"):  # digits past int()'s own limit too
        study_from("design", vary=("geometry.b=0.02:0.08:" + "9" * 5000,))
    s = study_from("design", samples=3, vary=("geometry.b=0.04:0.06:3", "springs.k_left=1:2:4"))
    monkeypatch.undo()
    assert spec.run_count(s) == len(expand(s)) == 36
    s = _study("nod.json", 5)
    assert spec.run_count(s) == len(expand(s)) == 10


def test_the_command_line_refuses_a_study_with_too_many_runs_in_one_line(xneck, tmp_path) -> None:
    out = tmp_path / "x"
    for args, says in ((("control", "--samples", "1000000000"), "1000000000 runs"),
                       (("design", "--vary", "geometry.b=0.02:0.08:100000000000"), "100000000000 points")):
        r = xneck("study", *args, "--out", str(out))
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:"), r.stderr[-2000:]
        assert says in lines[0] and "200000" in lines[0], lines
        assert not out.exists()


def test_the_api_refuses_a_huge_study_with_422_and_checks_it_off_the_event_loop(tmp_path, monkeypatch) -> None:
    # audit of 2026-11-26: the check ran in the async handler: the console answered nothing (health
    # included) for 46 s, then failed with MemoryError. Here the check is held until the health has
    # answered: if the check ran on the event loop, the health could not answer and the gate never opens.
    from server.studies import spec

    gate, checking = threading.Event(), threading.Event()
    original = spec.study_from

    def held(*args, **kwargs):
        checking.set()
        gate.wait(60)
        return original(*args, **kwargs)

    monkeypatch.setattr(spec, "study_from", held)
    body = {"kind": "design", "samples": 100000, "vary": ["geometry.b=0.02:0.08:100000"]}
    answer: dict = {}
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=90) as http:
        post = threading.Thread(target=lambda: answer.update(r=http.post("/api/studies", json=body, headers=AUTH)))
        post.start()
        try:
            assert checking.wait(60), "the study was never checked"
            health = http.get("/api/system/health", timeout=30)  # a loop held by the check never answers
            assert health.status_code == 200
        finally:
            gate.set()
            post.join(90)
    r = answer["r"]
    assert r.status_code == 422, r.text
    assert "10000000000 runs" in r.json()["detail"] and "200000" in r.json()["detail"], r.text
    assert not (tmp_path / "data" / "studies").exists() or not any((tmp_path / "data" / "studies").iterdir())


def test_a_study_directory_refuses_a_study_whose_files_changed(nod, tmp_path) -> None:
    """The same flags over an edited trajectory (or parameter, truth) file are another robot's runs."""
    from server.studies.execute import study_dir

    traj = tmp_path / "nod.json"
    traj.write_text(json.dumps(NOD))
    s = study_from("control", trajectory=str(traj), vary=VARY)
    with study_dir(s, tmp_path / "out", "inputs-a"):
        pass
    with study_dir(s, tmp_path / "out", "inputs-a"):  # the same study goes on
        pass
    with pytest.raises(StudyError, match="changed since this study started"), study_dir(s, tmp_path / "out", "inputs-b"):
        pass


def test_a_small_study_end_to_end_on_two_workers(nod, dask_client, tmp_path) -> None:
    s = _study(nod, 3)
    summary = run_study(s, tmp_path, client=dask_client)
    rows = read_rows(tmp_path)
    assert sorted(r["run_id"] for r in rows) == sorted(r.run_id for r in expand(s))
    assert all(r["outcome"] == "finished" for r in rows), [r["message"] for r in rows]
    assert {f.parent.name for f in part_files(tmp_path)} == {"law=1", "law=2"}  # partitioned by law
    assert summary["complete"] and summary["outcomes"] == {"finished": 6}
    assert set(summary["metrics"]) == {"1", "2"} and summary["metrics"]["2"]["e_mean_all_deg"]["n"] == 3
    assert set(summary["sensitivity_spearman"]["1"]["e_mean_all_deg"]) == {"friction.f_s", "cables.variable.k[4]"}
    assert json.loads((tmp_path / "summary.json").read_text())["digest"] == s.digest()
    assert {"distributions.png", "sensitivity.png"} <= {p.name for p in (tmp_path / "figures").iterdir()}
    # a run again is the same row: deterministic from its seed, the twin on the sampled robot
    run = expand(s)[4]
    again = dask_client.submit(run_one, config_for(s, rows[0]["version"]), run, pure=False).result()
    row = next(r for r in rows if r["run_id"] == run.run_id)
    assert again["e_mean_all_deg"] == row["e_mean_all_deg"] and again["force_max_N[4]"] == row["force_max_N[4]"]
    assert row["x:friction.f_s"] == run.values["friction.f_s"] and row["version"]
    # the robot differs from the controller's model: another draw gives another run
    assert len({r["e_mean_all_deg"] for r in rows if r["law"] == 2}) == 3
    # another study in the same directory is refused (its rows would mix)
    with pytest.raises(StudyError, match="holds another study"):
        run_study(_study(nod, 4), tmp_path, client=dask_client)


def test_resume_after_the_study_process_is_killed_loses_and_repeats_no_row(nod, dask_client, tmp_path) -> None:
    """`xneck study` on the cluster (--scheduler), SIGKILLed once its first batch is on disk; the
    rerun finishes the rest, never repeating a row; a third run has nothing to do."""
    s = _study(nod, 20)
    args = [sys.executable, "-m", "server.cli", "study", "control", "--out", str(tmp_path), "--samples", "20",
            "--law", "1", "--law", "2", "--trajectory", nod, "--seed", "3", "--scheduler", dask_client.scheduler.address]
    args += [x for v in VARY for x in ("--vary", v)]
    (tmp_path / "settle.toml").write_text("settle_s = 0.1\n")
    args += ["--study", str(tmp_path / "settle.toml")]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        assert wait_until(lambda: bool(part_files(tmp_path)) or proc.poll() is not None, 90), "no batch written"
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    partial = finished_ids(tmp_path)
    total = len(expand(s))
    assert 0 < len(partial) < total, (len(partial), proc.stderr.read().decode()[-2000:] if proc.stderr else "")
    (tmp_path / "runs" / "law=1" / ".part-crashed.parquet.tmp").write_bytes(b"half a file")  # a write cut short
    summary = run_study(s, tmp_path, client=dask_client)
    ids = [r["run_id"] for r in read_rows(tmp_path)]
    import pyarrow.parquet as pq

    stored = sum(pq.read_metadata(f).num_rows for f in part_files(tmp_path))
    assert stored == len(ids) == len(set(ids)) == total and summary["complete"]
    assert not list(tmp_path.glob("runs/*/.part-*"))
    files = part_files(tmp_path)
    assert run_study(s, tmp_path, client=dask_client)["runs_done"] == total
    assert part_files(tmp_path) == files  # nothing left to run, nothing written


def test_the_rows_read_as_the_docs_say_with_pyarrow_and_the_law_is_the_folder_only(nod, dask_client, tmp_path) -> None:
    """Audit: docs/studies.md's read, ``pyarrow.dataset.dataset("DIR/runs", partitioning="hive")``,
    raised 'Field law has incompatible types: int64 vs int32' on every study: the writer stored
    ``law`` in each file as well as in its ``law=<n>`` folder. The docs' own line is run here."""
    import pyarrow
    import pyarrow.dataset  # the documented line uses pyarrow.dataset
    import pyarrow.parquet as pq

    doc = (Path(__file__).resolve().parents[1] / "docs" / "studies.md").read_text()
    documented = re.search(r"`(pyarrow\.dataset\.dataset\(\"DIR/runs\"[^`]*)`", doc)
    assert documented, "docs/studies.md no longer says how to read the rows"
    s = _study(nod, 2)
    run_study(s, tmp_path, client=dask_client)
    table = eval(documented.group(1).replace("DIR", str(tmp_path)), {"pyarrow": pyarrow})
    laws = dict(zip(table.column("run_id").to_pylist(), table.column("law").to_pylist(), strict=True))
    assert laws == {r.run_id: r.law for r in expand(s)}
    assert all("law" not in pq.read_schema(f).names for f in part_files(tmp_path))  # the folder says it, once
    assert {r["run_id"]: r["law"] for r in read_rows(tmp_path)} == laws  # xneck's own reader too


def test_a_directory_written_with_law_in_its_files_still_reads_and_resumes(tmp_path) -> None:
    """Batches of an older xneck (``law`` an int64 column in the file too) and new ones (the folder
    only) in one directory: the summary's reader and the console's pages give every row its law."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from server.studies.execute import study_dir, write_batch
    from server.studies.rows import read_page

    s = study_from("control", samples=2, laws=(1, 2))
    runs = list(expand(s))
    rows = [{"run_id": r.run_id, "law": r.law, "seed": r.seed, "outcome": "finished", "message": ""} for r in runs]
    with study_dir(s, tmp_path):
        old = tmp_path / "runs" / "law=1" / "part-1-1.parquet"
        old.parent.mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist([r for r in rows if r["law"] == 1]), old)  # as the old writer did
        write_batch(tmp_path, [r for r in rows if r["law"] == 2])
    assert pq.read_schema(old).field("law").type == pa.int64()
    assert {r["run_id"]: r["law"] for r in read_rows(tmp_path)} == {r.run_id: r.law for r in runs}
    assert finished_ids(tmp_path) == {r.run_id for r in runs}
    total, page = read_page(tmp_path, 0, 10)
    assert total == 4 and {r["run_id"]: r["law"] for r in page} == {r.run_id: r.law for r in runs}
    assert list(page[0])[:3] == ["run_id", "law", "seed"]  # the column where it always was


def test_ctrl_c_stops_the_command_cleanly_with_the_summary_of_its_rows_and_says_how_to_go_on(dask_client, tmp_path) -> None:
    """Audit: Ctrl-C (SIGINT to the terminal's process group) during ``xneck study`` killed the
    LocalCluster's worker processes too (their KeyboardInterrupt tracebacks and the scheduler's 'lost
    scattered data' on stderr) and left no summary. The first Ctrl-C now stops the study: the runs in
    flight are cancelled, the rows kept, their summary written, exit 130; a rerun goes on."""
    traj = tmp_path / "slow_nod.json"  # ~0.5 s a run: the study is still running when Ctrl-C comes
    traj.write_text(json.dumps({**NOD, "durations_s": 1.5}))
    (tmp_path / "settle.toml").write_text("settle_s = 0.1\n")
    out = tmp_path / "study"
    args = [sys.executable, "-m", "server.cli", "study", "control", "--out", str(out), "--samples", "8", "--law", "1",
            "--law", "2", "--trajectory", str(traj), "--study", str(tmp_path / "settle.toml"), "--workers", "1",
            "--vary", VARY[0]]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    err: list[bytes] = []
    reader = threading.Thread(target=lambda: err.extend(iter(lambda: proc.stderr.read1(4096), b"")), daemon=True)  # type: ignore[union-attr]
    reader.start()
    try:
        assert wait_until(lambda: re.search(rb"\b[1-9]\d*/16 runs", b"".join(err)) is not None or proc.poll() is not None,
                          120), b"".join(err).decode()[-2000:]
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole process group
        proc.wait(120)  # stderr is the reader's alone; stdout (the summary's table) fits in its pipe
        stdout = proc.stdout.read().decode()  # type: ignore[union-attr]
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    reader.join(10)
    stderr = b"".join(err).decode()
    assert proc.returncode == 130, (proc.returncode, stderr[-3000:])
    for noise in ("Traceback", "KeyboardInterrupt", "distributed.", "lost scattered data"):
        assert noise not in stderr, stderr[-3000:]
    rows = read_rows(out)
    assert 0 < len(rows) < 16, len(rows)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs_done"] == len(rows) and not summary["complete"]
    assert (out / "figures" / "distributions.png").is_file()
    assert f"{len(rows)}/16 runs" in stdout  # the summary's table of the rows it has
    assert "interrupted" in stderr and "run the same command again" in stderr and str(out) in stderr, stderr[-2000:]
    # the same study goes on where it stopped
    s = study_from("control", file=tmp_path / "settle.toml", samples=8, laws=(1, 2), trajectory=str(traj), vary=VARY[:1])
    assert run_study(s, out, client=dask_client)["complete"]
    ids = [r["run_id"] for r in read_rows(out)]
    assert sorted(ids) == sorted(r.run_id for r in expand(s))


def test_a_worker_killed_mid_study_loses_only_its_running_tasks(nod, dask_client, tmp_path) -> None:
    s = _study(nod, 8)
    pids = dask_client.run(os.getpid)
    victim = next(iter(pids.values()))
    killed: list[int] = []

    def progress(done: int, total: int, message: str) -> None:
        if done >= 4 and not killed:  # mid-study: both workers busy with a run
            os.kill(victim, signal.SIGKILL)  # the nanny restarts it; the scheduler reschedules its task
            killed.append(done)

    summary = run_study(s, tmp_path, client=dask_client, progress=progress)
    assert killed and killed[0] < len(expand(s))
    ids = [r["run_id"] for r in read_rows(tmp_path)]
    assert sorted(ids) == sorted(r.run_id for r in expand(s)) and summary["outcomes"] == {"finished": 16}
    assert victim not in dask_client.run(os.getpid).values()


def test_every_worker_killed_at_once_mid_study_loses_nothing(nod, dask_client, tmp_path) -> None:
    """The study's configuration reaches the workers as a task the scheduler can compute again, not
    as scattered data: the Active Memory Manager drops a broadcast's extra replicas (ReduceReplicas),
    so one worker's death lost the only copy and cancelled every run in flight ('already forgotten',
    the official CI of stop 65). Killing every worker at once loses every replica on any scheduler."""
    s = _study(nod, 8)
    victims = set(dask_client.run(os.getpid).values())
    killed: list[int] = []

    def progress(done: int, total: int, message: str) -> None:
        if done >= 4 and not killed:
            for pid in victims:
                os.kill(pid, signal.SIGKILL)
            killed.append(done)

    summary = run_study(s, tmp_path, client=dask_client, progress=progress)
    assert killed and killed[0] < len(expand(s))
    ids = [r["run_id"] for r in read_rows(tmp_path)]
    assert sorted(ids) == sorted(r.run_id for r in expand(s)) and summary["outcomes"] == {"finished": 16}
    assert not victims & set(dask_client.run(os.getpid).values())


def test_runs_the_cluster_cancels_end_the_study_with_a_clear_error_and_a_rerun_goes_on(nod, dask_client,
                                                                                       tmp_path) -> None:
    """Runs cancelled by the cluster (here by key, as another client or an operator may) stop the study
    with a StudyError that says what happened and what to do, the finished rows kept; it was
    distributed's FuturesCancelledError traceback."""
    from distributed import Future

    s = _study(nod, 4)
    keys = [f"xneck-study-{s.digest()}-{r.run_id}" for r in expand(s)]
    cancelled: list[int] = []

    def progress(done: int, total: int, message: str) -> None:
        if done >= 2 and not cancelled:
            dask_client.cancel([Future(k, dask_client) for k in keys], force=True)
            cancelled.append(done)

    with pytest.raises(StudyError, match=r"cancelled the study's runs in flight .*run the same command again"):
        run_study(s, tmp_path, client=dask_client, progress=progress)
    kept = [r["run_id"] for r in read_rows(tmp_path)]
    assert len(kept) >= cancelled[0] and len(kept) < len(expand(s))
    assert run_study(s, tmp_path, client=dask_client)["complete"]
    assert sorted(r["run_id"] for r in read_rows(tmp_path)) == sorted(r.run_id for r in expand(s))


def test_a_scheduler_lost_mid_study_ends_the_command_with_what_to_do_and_keeps_the_rows(nod, dask_client,
                                                                                         tmp_path) -> None:
    """`xneck study --scheduler` whose scheduler dies mid-study (the docs' `dask scheduler` and `dask
    worker` commands, on loopback): exit 2, 'the connection to the scheduler was lost' and 'run the same
    command again', in bounded time; the rows written so far kept, and the study goes on elsewhere."""
    dask = str(Path(sys.executable).with_name("dask"))
    out, sched_file = tmp_path / "study", tmp_path / "scheduler.json"
    procs: list[subprocess.Popen] = []

    def start(args: list[str]) -> subprocess.Popen:
        procs.append(subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      start_new_session=True))
        return procs[-1]

    try:
        scheduler = start([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                           "--scheduler-file", str(sched_file)])
        assert wait_until(lambda: sched_file.is_file() and "address" in sched_file.read_text(), 60)
        address = json.loads(sched_file.read_text())["address"]
        start([dask, "worker", address, "--nworkers", "1", "--nthreads", "1", "--host", "127.0.0.1",
               "--no-dashboard", "--death-timeout", "20"])
        (tmp_path / "settle.toml").write_text("settle_s = 0.1\n")
        args = [sys.executable, "-m", "server.cli", "study", "control", "--out", str(out), "--samples", "6",
                "--law", "1", "--law", "2", "--trajectory", nod, "--seed", "3", "--scheduler", address,
                "--study", str(tmp_path / "settle.toml")] + [x for v in VARY for x in ("--vary", v)]
        study = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                 start_new_session=True)
        procs.append(study)
        assert wait_until(lambda: bool(part_files(out)) or study.poll() is not None, 120), "no batch written"
        assert study.poll() is None, study.communicate()[1][-2000:]
        os.killpg(scheduler.pid, signal.SIGKILL)
        _, stderr = study.communicate(timeout=90)
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(10)
    assert study.returncode == 2, stderr[-3000:]
    assert "connection to the scheduler was lost" in stderr and "run the same command again" in stderr, stderr[-3000:]
    assert "Traceback" not in stderr, stderr
    kept = finished_ids(out)
    s = study_from("control", file=tmp_path / "settle.toml", samples=6, laws=(1, 2), trajectory=nod, vary=VARY,
                   seed=3)
    assert 0 < len(kept) < len(expand(s))
    assert run_study(s, out, client=dask_client)["complete"]
    ids = [r["run_id"] for r in read_rows(out)]
    assert sorted(ids) == sorted(r.run_id for r in expand(s))


def test_an_identification_study_takes_an_estimator_and_counts_the_covered_intervals() -> None:
    """An identification study is the coverage test run as users run studies: Table 2 by the
    estimator asked for, and per run which k and λ the ±2σ interval covers."""
    assert "estimator" not in study_from("identification").canonical()  # the default keeps older studies' digests
    assert study_from("identification", estimator="iv").digest() != study_from("identification").digest()
    with pytest.raises(StudyError, match="choose"):
        study_from("identification", estimator="magic")
    with pytest.raises(StudyError, match="identification studies"):
        study_from("control", estimator="iv")
    rows = {}
    for estimator in ("iv", "loadfriction"):
        s = study_from("identification", samples=1, seed=2, truth="robot", estimator=estimator, settle_s=0.5)
        run = expand(s)[0]
        rows[estimator] = row = run_one(config_for(s, "v"), run)
        assert row["outcome"] == "finished", row["message"]
        for name in ("k", "lambda"):
            covered = [row[f"{name}_covered[{i}]"] for i in range(1, 5)]
            assert set(covered) <= {0.0, 1.0} and row[f"{name}_covered_fraction"] == pytest.approx(sum(covered) / 4)
            within = [row[f"{name}_rel_error[{i}]"] <= 0.10 for i in range(1, 5)]
            assert row[f"{name}_within_10pct_fraction"] == pytest.approx(sum(within) / 4)
    # the estimator is the one asked for: the paper's eq. 55 (iv) and the load-friction fit differ on the robot truth
    assert rows["iv"]["k_rel_error[1]"] != pytest.approx(rows["loadfriction"]["k_rel_error[1]"], rel=1e-3)



def test_a_study_on_a_scheduler_leaves_no_client_of_its_own_connected(nod, dask_client, tmp_path) -> None:
    """The console runs studies in a thread on a configured scheduler: each used to leave its Client
    connected to the scheduler for as long as the console ran."""

    def clients() -> int:
        return dask_client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.clients))

    before = clients()
    done: dict[str, object] = {}
    worker = threading.Thread(target=lambda: done.update(
        summary=run_study(_study(nod, 2), tmp_path / "s", scheduler=dask_client.scheduler.address)))
    worker.start()
    worker.join(120)
    assert not worker.is_alive() and done, "the study did not finish"
    assert wait_until(lambda: clients() == before, 10), (before, clients())

def test_a_damaged_study_directory_is_listed_as_damaged_and_the_others_still_are(tmp_path) -> None:
    # audit of 2026-11-26: one damaged directory made GET /api/studies (all of them) a 500.
    from server.studies.execute import STUDY_FILE
    from server.studies.service import study_or_error

    studies = tmp_path / "data" / "studies"

    def on_disk(seed: int):
        st = study_or_error(kind="control", samples=1, vary=(), seed=seed, laws=(2,), no_pulleys=False, trajectory=None,
                            truth="model", alpha_ip="noise", settle_s=1.0, model_follows=False,
                            design_configurations=2000, estimator="auto")
        folder = studies / f"control-{st.digest()}"
        folder.mkdir(parents=True)
        (folder / STUDY_FILE).write_text(json.dumps({"study": st.canonical()}))
        return folder

    good = on_disk(0)
    on_disk(1).joinpath("summary.json").write_text("{truncated")
    parquet = on_disk(2) / "runs" / "law=2"
    parquet.mkdir(parents=True)
    (parquet / "part-0.parquet").write_bytes(b"PAR1garbage")
    for sid, text in (("control-0123456789abcdef", "{not json"), ("control-fedcba9876543210", '{"x": 1}'),
                      ("control-00000000000000ff", '{"study": {"kind": "control", "bogus": 1}}')):
        (studies / sid).mkdir()
        (studies / sid / STUDY_FILE).write_text(text)
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=30) as http:
        r = http.get("/api/studies")
        assert r.status_code == 200, r.text
        listed = {s["id"]: s for s in r.json()["studies"]}
        assert len(listed) == 6
        assert listed[good.name]["state"] == "stopped" and listed[good.name]["runs_total"] == 1
        damaged = {sid: s for sid, s in listed.items() if sid != good.name}
        for sid, s in damaged.items():
            assert s["state"] == "damaged" and s["error"], s
            one = http.get(f"/api/studies/{sid}")
            assert one.status_code == 422 and one.json()["detail"] == s["error"], (sid, one.status_code, one.text)
        assert any("summary.json" in s["error"] for s in damaged.values())
        assert any("part-0.parquet" in s["error"] for s in damaged.values())
        assert "study.json" in listed["control-fedcba9876543210"]["error"]
        assert http.get(f"/api/studies/{parquet.parent.parent.name}/results").status_code == 422
        assert http.get(f"/api/studies/{good.name}").status_code == 200
        assert http.get(f"/api/studies/{good.name}/results").json()["total"] == 0


def test_the_studies_api_creates_lists_reports_and_serves_figures(nod, dask_client, tmp_path, monkeypatch) -> None:
    """Last in this file: the console's own Client in its thread leaves dask's shared event loop
    unusable to a Client of another thread (distributed 2026.8), so no test uses ``dask_client`` after it."""
    from server.studies.service import SCHEDULER_ENV

    monkeypatch.setenv(SCHEDULER_ENV, dask_client.scheduler.address)
    body = {"kind": "design", "samples": 2, "vary": ["geometry.b=0.04:0.06:2", "springs.k_left=10%"],
            "design_configurations": 50}
    with running_server(tmp_path / "data") as (base, _app), httpx.Client(base_url=base, timeout=30) as http:
        assert http.post("/api/studies", json=body).status_code == 401
        bad = http.post("/api/studies", json={**body, "vary": ["geometry.b=U(1,2)"]}, headers=AUTH)
        assert bad.status_code == 422 and "must be smaller than L" in bad.text
        assert http.post("/api/studies", json={**body, "trajectory": "/etc/passwd"}, headers=AUTH).status_code == 422
        bad = http.post("/api/studies", json={**body, "estimator": "iv"}, headers=AUTH)  # Table 2's: identification only
        assert bad.status_code == 422 and "identification studies" in bad.text, bad.text
        created = http.post("/api/studies", json=body, headers=AUTH)
        assert created.status_code == 202, created.text
        sid = created.json()["id"]
        assert created.json()["runs_total"] == 4
        assert wait_until(lambda: http.get(f"/api/studies/{sid}").json()["state"] != "running", 120)
        p = http.get(f"/api/studies/{sid}").json()
        assert p["state"] == "complete" and p["runs_done"] == 4 and p["summary"]["outcomes"] == {"finished": 4}
        assert [s["id"] for s in http.get("/api/studies").json()["studies"]] == [sid]
        rows = http.get(f"/api/studies/{sid}/results", params={"limit": 3}).json()
        assert rows["total"] == 4 and len(rows["rows"]) == 3 and "feasible_fraction" in rows["rows"][0]
        assert "design_maps.png" in " ".join(p["figures"])
        png = http.get(f"/api/studies/{sid}/figures/design_maps.png")
        assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
        assert http.get(f"/api/studies/{sid}/figures/..%2Fstudy.json").status_code == 404
        assert http.get("/api/studies/control-0123456789abcdef").status_code == 404
        assert http.post(f"/api/studies/{sid}/stop").status_code == 401


def test_a_run_whose_twin_stood_at_the_flat_singularity_is_diverged_not_finished(monkeypatch) -> None:
    """Audit of 2026-11-26: a twin that refused 999 of 1000 steps at a joint's flat singularity
    (it stood still, its tensions in kN) gave a study row 'finished' with its metrics. A refused
    step is counted by the closed loop (Run.flat_steps) and such a run is 'diverged', with why."""
    from twin.sim.simulator import Twin

    real_tick = Twin.tick

    def refusing(self, force):
        tick = real_tick(self, force)
        return tick._replace(flat=True) if tick.seq % 100 == 0 else tick

    s = study_from("control", samples=1, seed=2, settle_s=0.2)
    run = expand(s)[0]
    assert run_one(config_for(s, "v"), run)["outcome"] == "finished"
    monkeypatch.setattr(Twin, "tick", refusing)
    row = run_one(config_for(s, "v"), run)
    assert row["outcome"] == "diverged" and "flat singularity" in row["message"], row["message"]
    assert row["flat_steps"] > 0


def test_a_study_of_a_physically_absurd_robot_is_refused_before_anything_runs() -> None:
    """User audit: ``--set friction.f_s=6e299`` ran, and its run ended 'finished' (the twin stood
    at rest, every force saturated). A friction beyond the motors' peak force is refused by the
    parameter set's validation (twin.model.params), so the study is, as a --set or at a --vary's extreme."""
    s = study_from("control", set=("friction.f_s=[6e299,6e299,6e299,6e299]",))
    with pytest.raises(StudyError, match=r"friction.f_s = \[6e\+299.*must be below the motors' peak force at the cable, 229.4 N"):
        config_for(s, "v")
    s = study_from("control", vary=("friction.f_s=U(10,300)",))
    with pytest.raises(StudyError, match=r"--vary friction.f_s=U\(10,300\): at 300: .*peak force"):
        config_for(s, "v")


def test_a_run_that_divides_by_zero_or_gives_non_finite_numbers_is_not_finished(monkeypatch) -> None:
    """A gear ratio of 6e299 divided by zero in the dynamics: the ZeroDivisionError was a traceback
    that ended the whole study; it is the run's 'failed' with its reason. A non-finite metric of
    numpy's own type (float32 is no Python float) was not seen and the run 'finished'."""
    from server.studies import run as run_module

    s = study_from("design", set=("geometry.R=6e299",), design_configurations=10)
    row = run_one(config_for(s, "v"), expand(s)[0])
    assert row["outcome"] == "failed" and row["message"].startswith("ZeroDivisionError"), row
    monkeypatch.setattr(run_module, "_design", lambda cfg, run, params: {"n_joints": 3.0, "feasible_fraction": np.float32("nan")})
    s = study_from("design", design_configurations=10)
    row = run_one(config_for(s, "v"), expand(s)[0])
    assert row["outcome"] == "diverged" and row["message"] == "non-finite metrics: feasible_fraction", row


def test_a_study_records_and_hashes_only_the_fields_its_kind_uses(tmp_path) -> None:
    """User audit: a design study's study.json showed laws, a trajectory and a truth it never ran,
    and its digest (hence its directory, its resume and its console id) changed with them."""
    from dataclasses import asdict

    from server.studies.execute import STUDY_FILE, load_study, study_dir

    design = study_from("design", design_configurations=10)
    unused: dict[str, Any] = dict(laws=(1, 3), no_pulleys=True, trajectory="identification", truth="robot",
                                  alpha_ip="camera", settle_s=5.0, model_follows=True)
    assert study_from("design", design_configurations=10, **unused) == design  # the console sends its truth select
    assert study_from("design", design_configurations=10, **unused).digest() == design.digest()
    design_fields = {"kind", "samples", "seed", "vary", "params_file", "set", "design_configurations"}
    with study_dir(design, tmp_path / "d"):
        pass
    recorded = json.loads((tmp_path / "d" / STUDY_FILE).read_text())
    assert set(recorded["study"]) == design_fields and recorded["digest"] == design.digest()
    assert load_study(tmp_path / "d") == design
    # a control study records its campaign's fields, not the design's configurations
    assert set(study_from("control").canonical()) == design_fields - {"design_configurations"} | {
        "laws", "no_pulleys", "trajectory", "truth", "alpha_ip", "settle_s", "model_follows"}
    # Resume: the digests of studies recorded before are kept (these are the previous version's),
    # and a directory whose study.json recorded every field still holds the same study.
    # (an identification study's default truth became the robot's on 2026-12-01: the one on the
    # model truth, asked for, keeps its digest)
    assert [study_from(k, truth="model" if k == "identification" else None).digest()
            for k in ("control", "identification", "design")] == [
        "825a25500aefa78c", "8cb27dc463fbc46c", "92705072dafb4453"]
    old = tmp_path / "old"
    old.mkdir()
    (old / STUDY_FILE).write_text(json.dumps({"digest": "92705072dafb4453", "study": asdict(study_from("design"))}))
    assert load_study(old) == study_from("design")
    with study_dir(study_from("design"), old):
        pass
    # a design study runs no twin: a truth path is refused, not left to fail every run
    with pytest.raises(StudyError, match=r"design study .* runs no twin"):
        study_from("design", vary=("truth.friction.static_ratio=U(1.1,1.5)",), truth="robot")


def test_identification_metrics_of_a_twin_value_of_zero_are_undefined_not_a_divergence() -> None:
    """A twin with linear cables (λ = 0, which the parameter file allows and a study may vary to,
    e.g. cables.variable.lambda[1]=0:150:4) has no relative error for λ: it used to be inf, and the
    run, whose identification had worked, was counted ``diverged`` (non-finite metrics) and left
    out of the summary. The undefined values are None; the ±2σ coverage is value ± 2σ."""
    from twin.identification.estimators import Estimate
    from twin.identification.regressors import param_names
    from twin.model.params import load_params

    params = load_params(None, {"cables.variable.lambda": [0.0, 100.0, 100.0, 100.0]})
    k, f_s = np.array(params.cables.variable.k), np.array(params.friction.f_s)

    def est(names, values, sigma):
        values, sigma = np.asarray(values, dtype=float), np.asarray(sigma, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return Estimate(method="m", equations="e", names=names, values=values, sigma=sigma,
                            relative_sigma=sigma / np.abs(values), condition_number=1.0, residual_norm=1.0,
                            n_rows=100, n_samples=100)

    lam = [0.0, 103.0, 89.5, 100.0]  # λ(1) held at its bound 0, λ(3) 10.5 % low with a 1 % σ
    variable = est(param_names("k", 4) + param_names("lambda", 4), [*(1.05 * k), *lam],
                   [*(0.03 * k), 2.0, 2.0, 0.9, 2.0])
    friction = est(param_names("f_s", 4), f_s, 0.01 * f_s)
    m = identification_metrics({"friction": friction, "variable": variable}, params)
    assert all(isinstance(x, float) and math.isfinite(x) for x in m.values() if x is not None), m
    assert m["lambda_rel_error[1]"] is None and m["lambda_rel_sigma_max"] is None
    assert m["lambda_rel_error_max"] == pytest.approx(0.105)
    assert m["lambda_within_10pct_fraction"] == pytest.approx(2 / 3)  # over the three defined: 3 %, 10.5 %, 0 %
    assert [m[f"lambda_covered[{i}]"] for i in range(1, 5)] == [1.0, 1.0, 0.0, 1.0]  # 0 ± 4 covers 0, 89.5 ± 1.8 not 100
    assert m["k_rel_error_max"] == pytest.approx(0.05) and m["k_covered_fraction"] == 1.0  # 5 % off, σ 3 %


def test_an_identification_study_defaults_to_the_robot_truth_by_every_entry() -> None:
    """Truth audit of 2026-12-01: ``xneck study identification`` and the console's studies ran on
    the model truth by default, the controller's own model, where an identification finds the
    parameter file it started from; identification campaigns default to the robot truth."""
    from server.routes_studies import StudyRequest
    from server.studies.service import study_or_error

    assert study_from("identification").truth == "robot"
    assert study_from("identification", truth="model").truth == "model"  # asked for: kept
    assert study_from("control").truth == "model"
    rest = StudyRequest.model_validate({"kind": "identification"}).model_dump(exclude={"workers"})
    assert study_or_error(**rest).truth == "robot"
    rest = StudyRequest.model_validate({"kind": "control"}).model_dump(exclude={"workers"})
    assert study_or_error(**rest).truth == "model"
