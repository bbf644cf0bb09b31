"""Studies of the console: one at a time in a background thread, on the data directory's ``studies/``.

The same code as ``xneck study`` (server.studies.execute.run_study); progress is kept in memory
while a study runs and read back from its directory otherwise (a study the console did not finish,
e.g. across a restart, shows as ``stopped`` and resumes when created again with the same definition;
one that failed keeps its state and error in ``DIR/state.json``). Reading costs what a page needs, not
what the study holds (server.studies.rows: row counts from the Parquet footers); a summary older than
the rows on disk (a study resumed, then the console killed) is marked ``summary_stale`` and recomputed
in the background, one study at a time.
The Dask cluster: ``XNECK_DASK_SCHEDULER`` (tcp://HOST:PORT, a cluster the lab runs) when set, else a
LocalCluster of the request's ``workers`` (default and cap: the CPUs this process may use, ``os.sched_getaffinity``).
"""

from __future__ import annotations

import contextlib
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.studies.spec import Study, StudyError, run_count

STUDY_ID = re.compile(r"^(control|identification|design)-[0-9a-f]{16}$")  # kind-digest: the same study, the same directory
SCHEDULER_ENV = "XNECK_DASK_SCHEDULER"


class UnknownStudy(KeyError):
    pass


class StudyBusy(RuntimeError):
    pass


class NotRunning(RuntimeError):
    """A stop of a study that is not running (complete, stopped, failed): the message says its state."""


class UnknownFigure(LookupError):
    """A known study without the figure asked for; the message names both."""


class DamagedStudy(ValueError):
    """A study directory whose files do not read (edited by hand, truncated, another version's); the
    message names the study, the file and why."""


LIST_KEYS = ("id", "kind", "state", "runs_done", "runs_total", "fraction", "error")
STATE_FILE = "state.json"  # a failed study's state and error, for the console after a restart


@dataclass
class _Running:
    study: Study
    total: int
    stop: threading.Event = field(default_factory=threading.Event)
    done: int = 0
    message: str = "starting"
    state: str = "running"  # running, complete, stopped, failed
    error: str = ""
    thread: threading.Thread | None = None
    created: float = field(default_factory=time.time)


class StudyManager:
    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._lock = threading.Lock()
        self._runs: dict[str, _Running] = {}
        self._recompute: dict[str, threading.Thread] = {}  # stale summaries being recomputed, by study id
        self._recomputed: dict[str, int] = {}  # the row count each study's last recompute was tried at
        self._report_lock = threading.Lock()  # one recompute at a time (each reads all of its study's rows)

    def _dir(self, study_id: str) -> Path:
        """The directory of a known study (one this console started, maybe not on disk yet, or one on disk)."""
        if not STUDY_ID.fullmatch(study_id) or not (study_id in self._runs or (self.root / study_id / "study.json").is_file()):
            raise UnknownStudy(study_id)
        return self.root / study_id

    def create(self, study: Study, workers: int | None) -> tuple[str, int]:
        """Check the study (StudyError says why it cannot run), then start it; (id, runs)."""
        from server.studies.execute import software_version
        from server.studies.run import config_for

        config_for(study, software_version())  # every spec checked before anything starts
        total = run_count(study)  # counted, not built: the runs are built in the study's own thread
        with self._lock:
            if any(r.state == "running" for r in self._runs.values()):
                raise StudyBusy("a study is running; stop it or wait (one at a time on this machine)")
            study_id = f"{study.kind}-{study.digest()}"  # created again, a study resumes where it stopped
            run = _Running(study, total)
            self._runs[study_id] = run
        run.thread = threading.Thread(target=self._work, args=(study_id, run, workers), name=f"study-{study_id}",
                                      daemon=True)
        run.thread.start()
        return study_id, total

    def _work(self, study_id: str, run: _Running, workers: int | None) -> None:
        from server.studies.execute import run_study

        def progress(done: int, total: int, message: str) -> None:
            run.done, run.message = done, message

        folder = self.root / study_id
        with self._lock:
            recompute = self._recompute.get(study_id)
        if recompute is not None:  # its stale summary being redrawn holds the directory's lock: let it end
            recompute.join()
        try:
            summary = run_study(run.study, folder, workers=workers,
                                scheduler=os.environ.get(SCHEDULER_ENV) or None, progress=progress, stop=run.stop)
            run.done = summary["runs_done"]
            run.state = "complete" if summary["complete"] else "stopped"
            with contextlib.suppress(OSError):
                (folder / STATE_FILE).unlink(missing_ok=True)
        except Exception as exc:  # noqa: BLE001 - a study's failure (cluster lost, disk full) is its state, never the console's crash
            run.state, run.error = "failed", f"{type(exc).__name__}: {exc}"
            self._persist_failure(folder, run.error)

    @staticmethod
    def _persist_failure(folder: Path, error: str) -> None:
        """state.json: the failure and the rows it left, so a restarted console still says failed (and why)
        while the directory holds those rows; written atomically, only in a directory holding a study."""
        import json

        from server.studies.execute import STUDY_FILE
        from server.studies.rows import count_rows

        with contextlib.suppress(OSError, StudyError):
            if not (folder / STUDY_FILE).is_file():
                return
            tmp = folder / f".{STATE_FILE}.tmp"
            tmp.write_text(json.dumps({"state": "failed", "error": error, "runs_done": count_rows(folder),
                                       "time": time.time()}))
            os.replace(tmp, folder / STATE_FILE)

    def stop(self, study_id: str) -> None:
        """Stop a running study; :class:`NotRunning` says the state of one that is not (a stop of a complete
        study was accepted and did nothing), :class:`UnknownStudy` when there is none."""
        self._dir(study_id)
        run = self._runs.get(study_id)
        if run is not None and run.state == "running":
            run.stop.set()
            return
        try:
            state = self.progress(study_id)["state"]
        except DamagedStudy:
            state = "damaged"
        if state == "running":  # started meanwhile
            self.stop(study_id)
            return
        again = " (creating it again goes on where it stopped)" if state in ("stopped", "failed") else ""
        raise NotRunning(f"study {study_id!r} is {state}, not running: nothing to stop{again}")

    def ids(self) -> list[str]:
        """Every study, newest first: those this console started from the moment they are created (their
        thread writes study.json a moment later, or never when it fails first: the dashboard polls this
        list and must see them), and those on disk."""
        when: dict[str, float] = {}
        for p in self.root.iterdir() if self.root.is_dir() else ():
            if STUDY_ID.fullmatch(p.name):
                with contextlib.suppress(OSError):  # no study.json (yet), or removed meanwhile
                    when[p.name] = (p / "study.json").stat().st_mtime
        when.update({study_id: run.created for study_id, run in list(self._runs.items())})
        return sorted(when, key=lambda study_id: when[study_id], reverse=True)

    def listing(self) -> list[dict[str, Any]]:
        """:meth:`ids` with their progress (:data:`LIST_KEYS`). A directory that does not read is
        listed as ``damaged`` with the reason in ``error``: one broken study must not hide the others."""
        out = []
        for study_id in self.ids():
            try:
                p = self.progress(study_id)
            except UnknownStudy:  # removed since ids() saw it
                continue
            except DamagedStudy as exc:
                p = {"id": study_id, "kind": study_id.split("-", 1)[0], "state": "damaged", "runs_done": 0,
                     "runs_total": 0, "fraction": 0.0, "error": str(exc)}
            out.append({k: p[k] for k in LIST_KEYS})
        return out

    def progress(self, study_id: str) -> dict[str, Any]:
        """Progress and, once it ran, the summary. Raises :class:`UnknownStudy`, or
        :class:`DamagedStudy` when the directory's files do not read."""
        folder = self._dir(study_id)
        run = self._runs.get(study_id)
        try:
            return self._progress(study_id, folder, run)
        except (StudyError, OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
            if run is None and not (folder / "study.json").is_file():
                raise UnknownStudy(study_id) from None  # removed while it was read
            raise DamagedStudy(f"study {study_id} is damaged: {exc}") from None

    def _progress(self, study_id: str, folder: Path, run: _Running | None) -> dict[str, Any]:
        from server.studies.execute import load_study
        from server.studies.rows import count_rows

        summary = _json_object(folder / "summary.json")
        figures = [f"/api/studies/{study_id}/figures/{n}" for n in (summary or {}).get("figures", [])]
        on_disk = None
        if run is None:  # not run by this console (or before its restart): the directory says
            study = load_study(folder)
            total = run_count(study)  # a study.json edited to 10^12 runs must not fill the memory here
            done = on_disk = count_rows(folder)  # the batches' footers, not their rows
            state, message, error = ("complete" if done >= total else "stopped"), "", ""
            failed = _json_object(folder / STATE_FILE)
            if failed and failed.get("state") == "failed" and failed.get("runs_done") == done:  # no row since
                state, error = "failed", str(failed.get("error", ""))
        else:
            study, total, done, state, message, error = run.study, run.total, run.done, run.state, run.message, run.error
        stale = False
        if state != "running":
            on_disk = count_rows(folder) if on_disk is None else on_disk
            stale = on_disk > 0 and (summary is None or summary.get("runs_done") != on_disk)
            if stale:
                self._recompute_later(study_id, folder, study, total, on_disk)
        return {"id": study_id, "kind": study.kind, "state": state, "runs_done": done, "runs_total": total,
                "fraction": done / total if total else 1.0, "message": message, "error": error,
                "study": study.canonical(), "summary": summary if state != "running" else None,
                "summary_stale": stale, "figures": figures if state != "running" else []}

    def _recompute_later(self, study_id: str, folder: Path, study: Study, total: int, rows: int) -> None:
        """The summary and figures of the rows on disk, in a thread: once per row count (a directory whose
        rows do not read is not read again at every poll), never while this console runs that study, and
        under the directory's lock (a study resumed meanwhile, here or by ``xneck study``, waits or wins)."""
        with self._lock:
            run = self._runs.get(study_id)
            if (study_id in self._recompute or self._recomputed.get(study_id) == rows
                    or (run is not None and run.state == "running")):
                return
            self._recomputed[study_id] = rows
            thread = threading.Thread(target=self._redraw, args=(study_id, folder, study, total),
                                      name=f"study-summary-{study_id}", daemon=True)
            self._recompute[study_id] = thread
            thread.start()

    def _redraw(self, study_id: str, folder: Path, study: Study, total: int) -> None:
        from server.studies.execute import study_dir
        from server.studies.report import write_outputs

        try:
            with self._report_lock, contextlib.suppress(StudyError, OSError, ValueError), study_dir(study, folder):
                write_outputs(folder, study, total)
        finally:
            with self._lock:
                self._recompute.pop(study_id, None)

    def results(self, study_id: str, offset: int, limit: int) -> dict[str, Any]:
        from server.studies.rows import read_page

        folder = self._dir(study_id)
        try:
            total, page = read_page(folder, offset, limit)  # the batches the page spans only
        except (StudyError, OSError) as exc:
            raise DamagedStudy(f"study {study_id} is damaged: {exc}") from None
        return {"total": total, "offset": offset, "rows": page}

    def figure(self, study_id: str, name: str) -> Path:
        from server.studies.report import FIGURES

        folder = self._dir(study_id) / "figures"
        path = folder / name
        if name not in FIGURES or not path.is_file():
            present = [f for f in FIGURES if (folder / f).is_file()]
            raise UnknownFigure(f"study {study_id!r} has no figure {name!r} "
                                f"({'its figures: ' + ', '.join(present) if present else 'it has no figures yet'})")
        return path


def _json_object(path: Path) -> dict[str, Any] | None:
    """A JSON object file of the study directory, None when absent; StudyError when it is not one."""
    import json

    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except ValueError as exc:
        raise StudyError(f"{path}: not JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise StudyError(f"{path}: not a JSON object")
    return doc


def study_or_error(**fields: Any) -> Study:
    """A :class:`Study` from a request's fields; StudyError names what is wrong."""
    from server.studies.spec import study_from

    kind = fields.pop("kind")
    return study_from(kind, **fields)


__all__ = ["DamagedStudy", "NotRunning", "StudyBusy", "StudyError", "StudyManager", "UnknownFigure", "UnknownStudy",
           "study_or_error"]
