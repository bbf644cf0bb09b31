"""``/api/studies``: Monte Carlo and design studies of many headless twins on Dask (issue 19).

Create (token), list, progress, results (Parquet rows as JSON pages), figures, stop (token); the
same code as ``xneck study`` (server.studies). A request names built-in trajectories and truths
only: a path on the console's disk is nothing a browser may choose.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request, status
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from server.auth import require_token
from server.datadir import storage_problem
from server.guard import document_responses
from server.studies.execute import check_workers
from server.studies.service import (
    SCHEDULER_ENV,
    DamagedStudy,
    NotRunning,
    StudyBusy,
    StudyError,
    StudyManager,
    UnknownFigure,
    UnknownStudy,
    study_or_error,
)

router = APIRouter(prefix="/api/studies", tags=["studies"])
_lock = threading.Lock()


class StudyRequest(BaseModel):
    """A study as ``xneck study`` takes it (docs/studies.md)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    kind: Literal["control", "identification", "design"]
    samples: int = Field(1, ge=1, le=100_000)
    vary: list[str] = Field(default_factory=list, max_length=20, description="PATH=SPEC, e.g. friction.f_s=10%")
    seed: int = Field(0, ge=0, le=2**32 - 1)
    laws: list[Literal[1, 2, 3]] = Field(default_factory=lambda: [2], min_length=1, max_length=3)
    no_pulleys: bool = False
    trajectory: Literal["control_test", "identification"] | None = None
    truth: Literal["model", "robot"] | None = Field(
        None, description="What the twin simulates; default robot for an identification study, model otherwise")
    alpha_ip: Literal["noise", "camera"] = "noise"
    settle_s: float = Field(1.0, ge=0.0, le=60.0)
    model_follows: bool = False
    design_configurations: int = Field(2000, ge=10, le=100_000)
    estimator: Literal["auto", "iv", "ols", "wls", "loadfriction", "outputerror"] = Field(
        "auto", description="Identification: Table 2's estimator, as `xneck identify --estimator`.")
    workers: int | None = Field(None, ge=1, le=64, description="Local Dask workers: default and at most the CPUs the "
                                "console may use (its CPU affinity); more is refused with 422")


def _manager(request: Request) -> StudyManager:
    with _lock:
        manager = getattr(request.app.state, "studies", None)
        if manager is None:
            manager = request.app.state.studies = StudyManager(Path(request.app.state.settings.data_dir) / "studies")
        return manager


def _unknown(study_id: str) -> HTTPException:
    return HTTPException(status.HTTP_404_NOT_FOUND, f"no study {study_id!r}")


@router.post("", status_code=status.HTTP_202_ACCEPTED, dependencies=[Depends(require_token)],
             responses={409: {"description": "A study is running"}, 422: {"description": "The study is invalid; detail says why"},
                        507: {"description": "Not enough free space in the data directory"}})
async def create_study(body: StudyRequest, request: Request) -> dict[str, Any]:
    """Check and start a study; every spec is checked before anything runs."""
    if any(len(v) > 200 for v in body.vary):
        raise HTTPException(422, "vary: each PATH=SPEC at most 200 characters")
    if body.workers is not None and not os.environ.get(SCHEDULER_ENV):  # a local cluster: no more workers than CPUs
        try:
            check_workers(body.workers, "workers")
        except StudyError as exc:
            raise HTTPException(422, str(exc)) from None
    settings = request.app.state.settings
    folder = Path(settings.data_dir) / "studies"
    folder.mkdir(exist_ok=True)
    problem = storage_problem(folder, int(settings.min_free_mb * 1e6))  # rows and figures need room, as campaigns do
    if problem:
        raise HTTPException(status.HTTP_507_INSUFFICIENT_STORAGE, problem)
    fields = body.model_dump(exclude={"workers"})
    fields["laws"], fields["vary"] = tuple(fields["laws"]), tuple(fields["vary"])
    manager = _manager(request)

    def check_and_start() -> tuple[str, int]:
        # in the threadpool: checking the specs imports the model and loads parameter files, and
        # nothing of it may hold the event loop (health, live views) while it runs
        return manager.create(study_or_error(**fields), body.workers)

    try:
        study_id, total = await run_in_threadpool(check_and_start)
    except StudyError as exc:
        raise HTTPException(422, str(exc)) from None
    except StudyBusy as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    return {"id": study_id, "runs_total": total, "url": f"/api/studies/{study_id}"}


@router.get("")
async def list_studies(request: Request) -> dict[str, Any]:
    """Every study of the console, newest first, with its progress; a directory that does not read
    is listed with state ``damaged`` and the reason in ``error``."""
    return {"studies": await run_in_threadpool(_manager(request).listing)}


@router.get("/{study_id}", responses={404: {"description": "No such study"},
                                      422: {"description": "The study's directory does not read; detail says why"}})
async def study_progress(study_id: str, request: Request) -> dict[str, Any]:
    """Progress while it runs; its summary (metrics per law, Spearman sensitivities) and figure URLs after."""
    try:
        return await run_in_threadpool(_manager(request).progress, study_id)
    except UnknownStudy:
        raise _unknown(study_id) from None
    except DamagedStudy as exc:
        raise HTTPException(422, str(exc)) from None


@router.get("/{study_id}/results", responses={404: {"description": "No such study"},
                                              422: {"description": "The study's rows do not read; detail says why"}})
async def study_results(study_id: str, request: Request, offset: int = Query(0, ge=0, le=10_000_000),
                        limit: int = Query(200, ge=1, le=5000)) -> dict[str, Any]:
    """The rows so far (one per run: inputs ``x:<path>``, metrics, outcome, timing, version), a page at a time."""
    try:
        return await run_in_threadpool(_manager(request).results, study_id, offset, limit)
    except UnknownStudy:
        raise _unknown(study_id) from None
    except DamagedStudy as exc:
        raise HTTPException(422, str(exc)) from None


@router.get("/{study_id}/figures/{name}", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, 404: {"description": "No such study or figure"}})
async def study_figure(study_id: str, name: str, request: Request) -> FileResponse:
    try:
        return FileResponse(_manager(request).figure(study_id, name), media_type="image/png",
                            headers={"Cache-Control": "no-cache"})
    except UnknownStudy:
        raise _unknown(study_id) from None
    except UnknownFigure as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc.args[0])) from None


@router.post("/{study_id}/stop", status_code=status.HTTP_202_ACCEPTED, dependencies=[Depends(require_token)],
             responses={404: {"description": "No such study"},
                        409: {"description": "The study is not running (complete, stopped, failed); detail says which"}})
async def stop_study(study_id: str, request: Request) -> dict[str, str]:
    """Stop after the runs in progress; the rows so far stay and creating the same study again goes on."""
    try:
        await run_in_threadpool(_manager(request).stop, study_id)  # a study not running: its rows are counted
    except UnknownStudy:
        raise _unknown(study_id) from None
    except NotRunning as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    return {"id": study_id, "state": "stopping"}


document_responses(router.routes)  # the guard's and storage handler's answers, as every router's
