"""Studies within their means (audit of /tmp/audit-studies): the number of joints varied only by
whole numbers that are what the row stores, a large study submitted a window at a time and stopped
at once, and local workers capped at the CPUs the process may use."""

from __future__ import annotations

import contextlib
import os
import re
import threading

import httpx
import pytest
from proc_net import LISTEN, tcp_sockets
from server_harness import AUTH, running_server

from server.studies import execute
from server.studies.execute import loopback_cluster, read_rows, run_study
from server.studies.run import apply_values, config_for, run_one
from server.studies.spec import StudyError, expand, study_from

# --- the number of joints -------------------------------------------------------------------------

NJOINTS_REFUSED = [
    # audit: the factor 0.9-1.1 was rounded to 1 joint and every row was a 1-joint neck
    ("geometry.n_joints=10%", "a relative spread"),
    ("geometry.n_joints=U(2,4)", "a uniform draw"),
    ("geometry.n_joints=N(3,0.5)", "a normal draw"),
    # audit: 2.5 was simulated as 2 joints (round half to even) and stored as x = 2.5
    ("geometry.n_joints=2:4:5", "2.5, 3.5 are not whole numbers"),
    ("geometry.n_joints=0:2:3", "1 to 12 joints"),
    ("geometry.n_joints=2:13:12", "1 to 12 joints"),
]


@pytest.mark.parametrize(("vary", "says"), NJOINTS_REFUSED)
def test_the_number_of_joints_is_varied_by_a_grid_of_whole_numbers_only(vary, says) -> None:
    study = study_from("design", samples=2, vary=(vary,), design_configurations=10)
    with pytest.raises(StudyError, match=re.escape(says)) as err:
        config_for(study, "v")
    assert "geometry.n_joints" in str(err.value) and "2:5:4" in str(err.value)  # what to write instead


def test_a_row_stores_the_number_of_joints_it_simulated() -> None:
    study = study_from("design", vary=("geometry.n_joints=2:3:2",), design_configurations=10)
    cfg = config_for(study, "v")
    rows = [run_one(cfg, r) for r in expand(study)]
    assert [(r["x:geometry.n_joints"], r["n_joints"], r["outcome"]) for r in rows] == [(2.0, 2.0, "finished"),
                                                                                      (3.0, 3.0, "finished")]
    with pytest.raises(StudyError, match=r"2\.5 is not a whole number"):  # never rounded behind the row's back
        apply_values(cfg, {"geometry.n_joints": 2.5})


# --- a large study, stopped -----------------------------------------------------------------------


def test_a_large_study_is_submitted_a_window_at_a_time_and_a_stop_keeps_its_rows(dask_client, tmp_path, monkeypatch) -> None:
    """Audit: 200,000 runs were all submitted before the first one was read (GBs in the scheduler),
    and the stop cancelled them one by one (522 s). Here at most a few runs per worker are ever
    submitted and not finished, and a stop cancels what is in flight in one call."""
    study = study_from("design", samples=5000, vary=("geometry.b=0.03:0.06:2",), design_configurations=10)
    total = len(expand(study))
    limit = execute.in_flight_limit(2)
    assert 2 <= limit <= 16
    submitted: list[str] = []
    cancels: list[int] = []
    real_submit, real_cancel = dask_client.submit, dask_client.cancel

    def submit(fn, *args, **kwargs):
        submitted.append(kwargs["key"])
        return real_submit(fn, *args, **kwargs)

    def cancel(futures, *args, **kwargs):
        cancels.append(len(futures))
        return real_cancel(futures, *args, **kwargs)

    monkeypatch.setattr(dask_client, "submit", submit)
    monkeypatch.setattr(dask_client, "cancel", cancel)
    stop = threading.Event()
    in_flight: list[int] = []
    seen: list[int] = []

    def progress(done: int, _total: int, _message: str) -> None:
        seen.append(done)
        in_flight.append(len(submitted) - done)
        if done >= 40:
            stop.set()

    summary = run_study(study, tmp_path, client=dask_client, progress=progress, stop=stop)
    rows = read_rows(tmp_path)
    assert 40 <= len(rows) == summary["runs_done"] == max(seen) < total and not summary["complete"]
    assert max(in_flight) <= limit, max(in_flight)  # never the whole study in the scheduler
    assert len(submitted) <= len(rows) + limit
    assert len(cancels) <= 1  # what was in flight, cancelled in one call
    assert len(set(submitted)) == len(submitted)


_release = threading.Event()
_started = threading.Event()


def _blocked_run(cfg, run):  # a run that takes until the test says (run on in-process workers)
    _started.set()
    _release.wait(120)
    return run_one(cfg, run)


def test_a_stop_does_not_wait_for_the_runs_in_progress(tmp_path, monkeypatch) -> None:
    """Audit: the stop was read only when a run finished. A stop while every worker is inside a
    long run ends the study without waiting for them."""
    from distributed import Client

    from server.studies import run as run_module

    monkeypatch.setattr(run_module, "run_one", _blocked_run)
    study = study_from("design", samples=50, vary=("geometry.b=0.03:0.06:2",), design_configurations=10)
    stop = threading.Event()
    _release.clear()
    _started.clear()
    cluster = loopback_cluster(1, threads_per_worker=2, processes=False)
    c = Client(cluster)
    try:
        threading.Thread(target=lambda: (_started.wait(60), stop.set()), daemon=True).start()
        summary = run_study(study, tmp_path, client=c, stop=stop)
        released_before = _release.is_set()
        assert _started.is_set() and not released_before, "the study waited for runs in progress"
        assert summary["runs_done"] == 0 and not summary["complete"]
    finally:
        _release.set()
        c.close()
        cluster.close()


# --- local workers --------------------------------------------------------------------------------


def _listening(pids: list[int]) -> list[str]:
    """The local addresses (hex ip:port, /proc/net/tcp's) of the TCP sockets in LISTEN that the
    processes ``pids`` hold."""
    return [f"{s.local[0]}:{s.local[1]:04X}" for s in tcp_sockets(pids) if s.state == LISTEN]


def _children(pid: int) -> list[int]:
    kids = []
    with contextlib.suppress(FileNotFoundError, ProcessLookupError):  # ended meanwhile: no children
        for task in os.listdir(f"/proc/{pid}/task"):
            # a thread that ended meanwhile has none
            with contextlib.suppress(FileNotFoundError, ProcessLookupError), \
                    open(f"/proc/{pid}/task/{task}/children") as f:
                kids += [int(k) for k in f.read().split()]
    return kids + [g for k in kids for g in _children(k)]


@pytest.mark.parametrize("processes", [False, True])
def test_a_studys_local_cluster_listens_on_loopback_only(processes) -> None:
    """Audit: a cluster of in-process workers (``processes=False``) listened on 0.0.0.0 and ``::``
    with Dask's defaults, and the scheduler's HTTP routes took 8787 (the suite warned 'Port 8787 is
    already in use'); a Dask scheduler runs what it is sent. Every listener of a study's cluster,
    its worker processes' too, is on 127.0.0.1 (worker processes already were: that case guards
    loopback_cluster's own settings)."""
    from distributed import Client

    me = os.getpid()
    before = set(_listening([me]))
    cluster = loopback_cluster(1, processes=processes)
    try:
        with Client(cluster) as client:
            assert client.submit(sum, [1, 2]).result(timeout=60) == 3
            opened = [a for a in _listening([me, *_children(me)]) if a not in before]
    finally:
        cluster.close()
    assert opened, "the cluster opened no listener: nothing was checked"
    loopback = ("0100007F:", "00000000000000000000000001000000:")  # 127.0.0.1 and ::1, as /proc/net writes them
    assert all(a.startswith(loopback) for a in opened), opened


def test_local_workers_are_capped_at_the_cpus_this_process_may_use(tmp_path) -> None:
    cap = len(os.sched_getaffinity(0))
    assert execute.local_worker_cap() == cap
    study = study_from("design", vary=("geometry.b=0.03:0.06:2",), design_configurations=10)
    with pytest.raises(StudyError, match=rf"--workers {cap + 1}: at most {cap}"):
        run_study(study, tmp_path / "out", workers=cap + 1)
    assert not (tmp_path / "out").exists()  # refused before the study directory or a cluster


def test_the_api_refuses_too_many_workers_and_a_spread_number_of_joints_with_422(tmp_path) -> None:
    cap = len(os.sched_getaffinity(0))
    body = {"kind": "design", "vary": ["geometry.b=0.03:0.06:2"], "design_configurations": 10}
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=60) as http:
        for workers in (cap + 1, 64):
            r = http.post("/api/studies", json={**body, "workers": workers}, headers=AUTH)
            assert r.status_code == 422 and f"at most {cap}" in r.text, r.text
        r = http.post("/api/studies", json={**body, "vary": ["geometry.n_joints=10%"]}, headers=AUTH)
        assert r.status_code == 422 and "whole numbers" in r.text, r.text
        assert http.get("/api/studies").json()["studies"] == []  # nothing started


def test_the_command_line_refuses_too_many_workers_in_one_line(tmp_path) -> None:
    from typer.testing import CliRunner

    from server.cli import app

    cap = len(os.sched_getaffinity(0))
    result = CliRunner().invoke(app, ["study", "design", "--out", str(tmp_path / "x"), "--workers", str(cap + 1),
                                      "--vary", "geometry.b=0.03:0.06:2"])
    assert result.exit_code == 2 and f"at most {cap}" in result.output, result.output
