"""Studies of the console: one at a time in a background thread, on the data directory's ``studies/``.

The same code as ``xneck study`` (server.studies.execute.run_study); progress is kept in memory
while a study runs and read back from its directory otherwise (a study the console did not finish,
e.g. across a restart, shows as ``stopped`` and resumes when created again with the same definition).
The Dask cluster: ``XNECK_DASK_SCHEDULER`` (tcp://HOST:PORT, a cluster the lab runs) when set, else a
LocalCluster of the request's ``workers`` (default: this machine's cores).
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


class DamagedStudy(ValueError):
    """A study directory whose files do not read (edited by hand, truncated, another version's); the
    message names the study, the file and why."""


LIST_KEYS = ("id", "kind", "state", "runs_done", "runs_total", "fraction", "error")


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

        try:
            summary = run_study(run.study, self.root / study_id, workers=workers,
                                scheduler=os.environ.get(SCHEDULER_ENV) or None, progress=progress, stop=run.stop)
            run.done = summary["runs_done"]
            run.state = "complete" if summary["complete"] else "stopped"
        except Exception as exc:  # noqa: BLE001 - a study's failure (cluster lost, disk full) is its state, never the console's crash
            run.state, run.error = "failed", f"{type(exc).__name__}: {exc}"

    def stop(self, study_id: str) -> None:
        self._dir(study_id)
        run = self._runs.get(study_id)
        if run is not None:
            run.stop.set()

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
        import json

        from server.studies.execute import finished_ids, load_study

        summary_file = folder / "summary.json"
        summary = None
        if summary_file.is_file():
            try:
                summary = json.loads(summary_file.read_text())
            except ValueError as exc:
                raise StudyError(f"{summary_file}: not JSON ({exc})") from None
            if not isinstance(summary, dict):
                raise StudyError(f"{summary_file}: not a JSON object")
        figures = [f"/api/studies/{study_id}/figures/{n}" for n in (summary or {}).get("figures", [])]
        if run is None:  # not run by this console (or before its restart): the directory says
            study = load_study(folder)
            total = run_count(study)  # a study.json edited to 10^12 runs must not fill the memory here
            done = len(finished_ids(folder))
            state, message, error = ("complete" if done >= total else "stopped"), "", ""
        else:
            study, total, done, state, message, error = run.study, run.total, run.done, run.state, run.message, run.error
        return {"id": study_id, "kind": study.kind, "state": state, "runs_done": done, "runs_total": total,
                "fraction": done / total if total else 1.0, "message": message, "error": error,
                "study": study.canonical(), "summary": summary if state != "running" else None,
                "figures": figures if state != "running" else []}

    def results(self, study_id: str, offset: int, limit: int) -> dict[str, Any]:
        import math

        from server.studies.execute import read_rows

        folder = self._dir(study_id)
        try:
            rows = read_rows(folder)
        except (StudyError, OSError) as exc:
            raise DamagedStudy(f"study {study_id} is damaged: {exc}") from None
        page = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
                for r in rows[offset:offset + limit]]
        return {"total": len(rows), "offset": offset, "rows": page}

    def figure(self, study_id: str, name: str) -> Path:
        from server.studies.report import FIGURES

        path = self._dir(study_id) / "figures" / name
        if name not in FIGURES or not path.is_file():
            raise UnknownStudy(f"{study_id}/{name}")
        return path


def study_or_error(**fields: Any) -> Study:
    """A :class:`Study` from a request's fields; StudyError names what is wrong."""
    from server.studies.spec import study_from

    kind = fields.pop("kind")
    return study_from(kind, **fields)


__all__ = ["DamagedStudy", "StudyBusy", "StudyError", "StudyManager", "UnknownStudy", "study_or_error"]
