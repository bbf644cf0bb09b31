"""A study's runs as Dask tasks, their rows streamed into partitioned Parquet under the study directory.

Layout of ``DIR``::

    study.json                 the study (its definition and digest): DIR holds this study only
    runs/law=<n>/part-*.parquet one row per finished run (law 0: design studies); the law is the folder's
                               only (hive partitioning), never a column of the file too
    summary.json, figures/     written at the end (server.studies.report)

Resumable: the finished run ids are read back (the ``run_id`` column only) and skipped. A batch of
rows becomes visible at once (written to a hidden temp file, fsynced, renamed), so a crash at any
moment leaves whole batches and no partial or repeated row; what was computed but not yet written
is simply run again. One process at a time runs a study directory (an flock on ``DIR/.lock``).
A worker killed mid-study loses its running tasks only: the scheduler gives them to another worker
(``distributed.scheduler.allowed-failures`` times before it gives up on a task). The study's
configuration is a task too (:func:`_config`), which the scheduler computes again when every copy of
it died with its workers; runs the cluster cancels all the same end the study with a
:class:`StudyError` that says so, the finished rows kept.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from threading import Event
from typing import Any

from server.studies.spec import RunSpec, Study, StudyError, expand, for_kind

RUNS_DIR = "runs"
STUDY_FILE = "study.json"
Progress = Callable[[int, int, str], None]  # (finished runs, all runs, message)


def software_version() -> str:
    """xneck's version (as campaign archives record it) and the checkout's commit when there is one:
    a study's rows may come from several machines and days."""
    from bridge.archive import software_version as package_version

    v = package_version()
    head = Path(__file__).resolve().parents[2] / ".git" / "HEAD"
    with contextlib.suppress(OSError):
        ref = head.read_text().strip()
        sha = (head.parent / ref[5:]).read_text().strip() if ref.startswith("ref: ") else ref
        v += f"+g{sha[:10]}"
    return v


def part_files(out: Path) -> list[Path]:
    """Every committed batch (hidden temp files of an interrupted write are not batches)."""
    return sorted(p for p in (Path(out) / RUNS_DIR).glob("law=*/part-*.parquet") if not p.name.startswith("."))


def _read_part(f: Path, columns: list[str] | None = None) -> Any:
    """One batch as a pyarrow Table; :class:`StudyError` naming the file when it is not one (truncated,
    overwritten), instead of pyarrow's message that names no file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(f, columns=columns)
    except (OSError, ValueError, pa.ArrowException) as exc:
        raise StudyError(f"{f}: not a readable batch of rows ({exc})") from None
    if "run_id" not in table.column_names:
        raise StudyError(f"{f}: a batch of rows without run_id")
    return table


def law_of(f: Path | str) -> int:
    """The law of a batch: its folder's ``law=<n>``; :class:`StudyError` for a folder that names none."""
    folder = Path(f).parent.name
    try:
        return int(folder.split("=", 1)[1])
    except (IndexError, ValueError):
        raise StudyError(f"{f}: a batch outside a law=<n> folder") from None


def with_law(table: Any, law: int) -> Any:
    """``table`` with its folder's law as the column after ``run_id`` (int64, as rows always had it).
    Batches of xneck before 2026-12 also hold it in the file: that copy is replaced by the folder's."""
    import pyarrow as pa

    if "law" in table.column_names:
        table = table.drop_columns(["law"])
    at = table.column_names.index("run_id") + 1 if "run_id" in table.column_names else 0
    return table.add_column(at, pa.field("law", pa.int64()), pa.array([law] * table.num_rows, pa.int64()))


def finished_ids(out: Path) -> set[str]:
    done: set[str] = set()
    for f in part_files(out):
        done.update(_read_part(f, ["run_id"]).column("run_id").to_pylist())
    return done


def read_rows(out: Path) -> list[dict[str, Any]]:
    """All rows of a study directory, one per run id (the first written, should a copy ever exist)."""
    import pyarrow as pa

    files = part_files(out)
    if not files:
        return []
    try:
        table = pa.concat_tables([with_law(_read_part(f), law_of(f)) for f in files], promote_options="default")
    except (ValueError, pa.ArrowException) as exc:
        if isinstance(exc, StudyError):
            raise
        raise StudyError(f"{Path(out) / RUNS_DIR}: batches whose columns do not agree ({exc})") from None
    seen: set[str] = set()
    rows = []
    for row in table.to_pylist():
        if row["run_id"] not in seen:
            seen.add(row["run_id"])
            rows.append(row)
    return rows


def write_batch(out: Path, rows: list[dict[str, Any]]) -> list[Path]:
    """Rows as one Parquet file per law partition, each made visible atomically (temp + fsync + rename).

    The law is the folder's ``law=<n>`` only: stored in the file too (int64) it clashed with the int32
    pyarrow infers from the folder, and ``pyarrow.dataset.dataset(DIR/runs, partitioning="hive")``
    refused every study. xneck's readers take it from the folder (:func:`with_law`)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    written = []
    for law in sorted({r["law"] for r in rows}):
        part = [r for r in rows if r["law"] == law]
        keys = [k for k in dict.fromkeys(k for r in part for k in r) if k != "law"]
        table = pa.Table.from_pylist([{k: r.get(k) for k in keys} for r in part])
        folder = Path(out) / RUNS_DIR / f"law={law}"
        folder.mkdir(parents=True, exist_ok=True)
        name = f"part-{time.time_ns()}-{os.getpid()}.parquet"
        tmp = folder / f".{name}.tmp"
        with open(tmp, "wb") as fh:
            pq.write_table(table, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, folder / name)
        written.append(folder / name)
    return written


@contextlib.contextmanager
def study_dir(study: Study, out: Path, inputs: str = "") -> Iterator[Path]:
    """``out`` locked for this process and holding ``study`` (created, or checked to be the same study).
    ``inputs``: a digest of what the files it names held (parameter set, truth, trajectory): an edited
    file makes another study, whose rows must not mix with these."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / ".lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise StudyError(f"{out}: another process is running this study") from None
        meta = out / STUDY_FILE
        if meta.exists():
            try:
                old = json.loads(meta.read_text())
            except (OSError, ValueError) as exc:
                raise StudyError(f"{meta}: unreadable ({exc}); use a new --out") from None
            if old.get("digest") != study.digest():
                raise StudyError(f"{out} holds another study ({old.get('digest')}, {old.get('study', {}).get('kind')}): "
                                 "its rows would mix with this one's; use a new --out")
            if inputs and old.get("inputs", inputs) != inputs:
                raise StudyError(f"{out}: the parameter set, truth or trajectory file changed since this study started: "
                                 "its rows would mix two robots; use a new --out")
        else:
            tmp = out / f".{STUDY_FILE}.tmp"
            tmp.write_text(json.dumps({"digest": study.digest(), "inputs": inputs, "study": study.canonical(),
                                       "created": time.time()}, indent=2))
            os.replace(tmp, meta)
        for stale in (out / RUNS_DIR).glob("law=*/.part-*.tmp"):  # a crashed writer's; we hold the lock
            stale.unlink(missing_ok=True)
        yield out


def load_study(out: Path) -> Study:
    """The study a directory holds; :class:`StudyError` when its study.json is not one."""
    try:
        doc = json.loads((Path(out) / STUDY_FILE).read_text())
    except (OSError, ValueError) as exc:
        raise StudyError(f"{out}: not a study directory ({exc})") from None
    try:
        data = dict(doc["study"])
        for key in ("vary", "laws", "set"):
            if key in data:  # a design study records no laws
                data[key] = tuple(data[key])
        return for_kind(Study(**data))
    except (KeyError, TypeError, ValueError) as exc:  # edited by hand, or written by another version
        raise StudyError(f"{Path(out) / STUDY_FILE}: not a study definition ({type(exc).__name__}: {exc})") from None


IN_FLIGHT_PER_WORKER = 4  # runs submitted and not finished, per worker: enough to keep each busy, never the study
POLL_S = 0.25  # s: how often a stop is looked at while every run in flight is still running
RESIZE_S = 5.0  # s: how often the window follows the cluster's size


def local_worker_cap() -> int:
    """Local worker processes at most: the CPUs this process may run on (its affinity, which a
    container or ``taskset`` narrows; not os.cpu_count(), which counts the machine's). A run is
    CPU-bound: a worker more than the CPUs only adds its memory (16 workers on 2 CPUs: 5 GB, load 21)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def check_workers(workers: int | None, option: str = "--workers") -> int:
    """The local workers of a study: ``workers`` (default :func:`local_worker_cap`); above the cap,
    :class:`StudyError` names it. Refused, not clamped: the study then runs as asked or not at all."""
    cap = local_worker_cap()
    if workers is None:
        return cap
    if not 1 <= workers <= cap:
        raise StudyError(f"{option} {workers}: at most {cap} local workers, the CPUs this process may use "
                         f"(a worker more only adds its memory); use --scheduler for a larger cluster")
    return workers


def in_flight_limit(workers: int) -> int:
    """Runs submitted and not yet finished at most, for a cluster of ``workers`` single-threaded
    workers (threads, for workers of several)."""
    return IN_FLIGHT_PER_WORKER * max(1, workers)


def _threads(client: Any) -> int:
    """The cluster's worker threads now (the scheduler's totals, without the list of workers)."""
    info = client.scheduler_info(n_workers=0)
    return int(info.get("total_threads") or len(info.get("workers", {})))


def loopback_cluster(n_workers: int, threads_per_worker: int = 1, processes: bool = True, **kwargs: Any) -> Any:
    """A dask.distributed LocalCluster whose every listener is on 127.0.0.1: no scheduler dashboard,
    the scheduler's and the workers' HTTP routes (health; the workers' dashboard pages too, where
    bokeh is installed, which it is not here) on free loopback ports. With Dask's defaults
    the scheduler's routes take 8787 (a second cluster warned 'Port 8787 is in use'), and a
    cluster of in-process workers (``processes=False``) listens on 0.0.0.0 and ``::``: a Dask
    scheduler runs what it is sent, so nothing of it may face the lab network. ``kwargs``:
    LocalCluster's."""
    from distributed import LocalCluster

    return LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker, processes=processes,
                        dashboard_address=None,  # pyright: ignore[reportArgumentType] - None: no dashboard (documented)
                        worker_dashboard_address="127.0.0.1:0",
                        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}, **kwargs)


def _client(workers: int | None, scheduler: str | None) -> tuple[Any, Any]:
    from distributed import Client

    if scheduler:
        try:
            return Client(scheduler, timeout=20), None
        except (OSError, TimeoutError) as exc:
            raise StudyError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        except ValueError as exc:  # not an address ('missing port number'): was a traceback
            raise StudyError(f"--scheduler {scheduler!r}: not a scheduler address tcp://HOST:PORT ({exc})") from None
    n = check_workers(workers)
    _workers_ignore_ctrl_c()
    cluster = loopback_cluster(n, preload=["server.studies.worker"])
    try:
        return Client(cluster), cluster
    except BaseException:  # its workers would live on in the console (review of session 48)
        cluster.close()
        raise


def _workers_ignore_ctrl_c() -> None:
    """In a command's main thread: the LocalCluster's worker processes ignore SIGINT, so a terminal's
    Ctrl-C (sent to its whole process group, the workers included) reaches this process alone, which
    stops the study (runs in flight cancelled, rows kept, summary written) and closes the cluster.
    Before, each worker died of its KeyboardInterrupt mid-run, printing its traceback, and the
    scheduler its 'lost scattered data'.

    How: the workers are forked by multiprocessing's fork server (distributed's
    ``multiprocessing-method: forkserver``) started here with SIGINT ignored; its children keep the
    disposition it started with, also those a nanny starts again after a worker died. Only the fork
    server's start (a fork, milliseconds) runs with SIGINT ignored here. A spawned worker (the default)
    takes the disposition of this process at that moment instead, which must handle Ctrl-C. Checked
    on distributed 2026.8 (tests/test_studies.py: Ctrl-C to a real ``xneck study`` process group).
    Elsewhere (the console's study thread, which cannot set signal handlers) the default is kept."""
    import multiprocessing.forkserver
    import signal
    import threading

    import dask.config
    from distributed.utils import get_mp_context

    if threading.current_thread() is not threading.main_thread():
        return
    dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"})  # also for workers restarted later
    get_mp_context()  # distributed's preload of the fork server (its imports), before the fork server starts
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        multiprocessing.forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, previous)


def run_study(study: Study, out: Path, *, workers: int | None = None, scheduler: str | None = None, client: Any = None,
              progress: Progress | None = None, stop: Event | None = None, flush_rows: int = 32,
              flush_s: float = 2.0) -> dict[str, Any]:
    """Run every unfinished run of ``study`` into ``out`` and write its summary and figures.

    ``client``: an existing dask.distributed Client (else one on ``scheduler``, else a LocalCluster of
    ``workers`` processes, default and at most the CPUs this process may use: :func:`check_workers`).
    ``stop``: set to stop early: the runs in flight are cancelled, the rows finished so far are kept
    and a rerun goes on. Returns the summary (server.studies.report)."""
    from server.studies.report import check_outputs, write_outputs
    from server.studies.run import config_for

    out = Path(out)
    if client is None and not scheduler:
        check_workers(workers)  # before the study directory exists or a cluster starts
    cfg = config_for(study, software_version())
    runs = expand(study)  # a view: each run is built when its window takes it
    total = len(runs)
    inputs = hashlib.sha256(json.dumps([cfg.params, cfg.truth, cfg.trajectory_json], sort_keys=True).encode()).hexdigest()[:16]
    with study_dir(study, out, inputs):
        check_outputs(out)  # a file in the way of the summary: said now, not after the runs
        done = finished_ids(out)
        finished = runs.count_finished(done)  # by their ids: no run built
        if progress:
            progress(finished, total, "resuming" if done else "starting")
        if finished == total:
            summary = _finished_summary(out, total)
            if summary is not None:  # a rerun of a finished study: nothing to run or draw again
                return summary
        elif not (stop and stop.is_set()):
            _execute(cfg, runs.unfinished(done), out, total, finished, client, workers, scheduler, progress, stop,
                     flush_rows, flush_s)
        return write_outputs(out, study, total)


def _finished_summary(out: Path, total: int) -> dict[str, Any] | None:
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return summary if summary.get("runs_done") == total else None


def _config(cfg: Any) -> Any:
    """The study's configuration, as the result of a task rather than scattered data: the scheduler
    computes a task again when every worker holding its result died, where scattered data is lost for
    good and every run waiting on it cancelled ('already forgotten'). A broadcast's replicas do not
    prevent that: the Active Memory Manager (on by default) drops the copies no waiting task needs
    (its ReduceReplicas policy), so one killed worker could hold the last (the official CI of stop 65)."""
    return cfg


_REASONS = {"scheduler-connection-lost": "the connection to the scheduler was lost"}


def _interrupted(exc: BaseException, finished: int, in_flight: int) -> StudyError:
    """The StudyError of a study the cluster stopped: runs it cancelled (distributed's FutureCancelledError
    of one future, FuturesCancelledError of several; their reasons in words where distributed's are codes)
    or a connection to the scheduler lost (CommClosedError, an OSError naming no file)."""
    if isinstance(exc, OSError):
        reasons = f"the connection to the scheduler was lost ({type(exc).__name__}: {exc})"
    else:
        groups = [str(g.reason) for g in getattr(exc, "error_groups", ())] or [str(getattr(exc, "reason", None) or exc)]
        reasons = "; ".join(sorted({_REASONS.get(r, r) for r in groups}))
    return StudyError(f"the Dask cluster cancelled the study's runs in flight ({in_flight}: {reasons}); the "
                      f"{finished} run(s) finished in this call are kept: run the same command again to go on")


def _close(client: Any) -> None:
    """Close a client made here. One that lost its scheduler is trying to connect again, and closing it
    cancels that attempt, which distributed logged as an ERROR with two tracebacks after the study had
    already said the connection was lost (:func:`_interrupted`): that logger is quiet for the close."""
    import logging

    if client.status == "running":
        client.close()
        return
    log = logging.getLogger("distributed.client")
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        client.close()
    finally:
        log.setLevel(level)


def _execute(cfg: Any, todo: Iterable[RunSpec], out: Path, total: int, done: int, client: Any, workers: int | None,
             scheduler: str | None, progress: Progress | None, stop: Event | None, flush_rows: int,
             flush_s: float) -> None:
    from distributed import wait
    from distributed.client import FutureCancelledError, FuturesCancelledError

    from server.studies.run import run_one

    own_client, cluster = client is None, None
    if own_client:
        client, cluster = _client(workers, scheduler)
    in_flight: set[Any] = set()
    pending: list[dict[str, Any]] = []
    last_flush = time.monotonic()
    t0 = time.monotonic()
    finished = 0
    stopped = stop.is_set if stop is not None else (lambda: False)
    try:
        digest = cfg.study.digest()
        cfg_future = client.submit(_config, cfg, key=f"xneck-study-{digest}-config-{os.getpid()}-{time.time_ns()}",
                                   pure=False)
        # a window of runs at a time, not the whole study: 200,000 futures took GBs in the scheduler,
        # and a stop had to wait behind them (and cancel them one by one)
        limit, sized = 0, -math.inf
        queue = iter(todo)  # built one at a time as the window takes them
        while True:
            if time.monotonic() - sized >= RESIZE_S:  # a cluster's workers may come (and go) while it runs
                limit, sized = in_flight_limit(_threads(client)), time.monotonic()
            while len(in_flight) < limit and not stopped():
                r = next(queue, None)
                if r is None:
                    break
                in_flight.add(client.submit(run_one, cfg_future, r, key=f"xneck-study-{digest}-{r.run_id}", pure=False))
            if not in_flight or stopped():
                break
            try:  # wakes for a finished run or, every POLL_S, to look at the stop
                waited: Any = wait(list(in_flight), timeout=POLL_S, return_when="FIRST_COMPLETED")  # sync: not a coroutine
                done_now = waited.done
            except TimeoutError:
                continue
            except (FutureCancelledError, FuturesCancelledError, OSError) as exc:  # was distributed's traceback
                raise _interrupted(exc, finished, len(in_flight)) from None
            for fut in done_now:
                in_flight.discard(fut)
                try:
                    row = fut.result()
                except (FutureCancelledError, FuturesCancelledError, OSError) as exc:  # OSError: the scheduler's
                    raise _interrupted(exc, finished, len(in_flight) + 1) from None
                pending.append(row)
                fut.release()
                finished += 1
                if len(pending) >= flush_rows or time.monotonic() - last_flush >= flush_s:
                    write_batch(out, pending)
                    pending, last_flush = [], time.monotonic()
                if progress:
                    rate = finished / max(time.monotonic() - t0, 1e-9)
                    progress(done + finished, total, f"{rate:.2f} runs/s")
    finally:
        if pending:  # whatever finished is kept, also on Ctrl-C
            write_batch(out, pending)
        if in_flight and client.status == "running":  # a stop does not wait for the runs in progress: one call
            client.cancel(list(in_flight))  # cancels them all (a lost scheduler took them already)
        if own_client:  # a client made here (on --scheduler too: it held a connection open) and its cluster
            _close(client)
            if cluster is not None:
                cluster.close()
