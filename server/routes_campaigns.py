"""``/api/campaigns``: create, list, status, stop, delete, results, MCAP download, figures, replay,
and an identification's parameter set saved to the console's sets."""

from __future__ import annotations

import contextlib
import os
from collections.abc import AsyncIterator
from typing import Any, BinaryIO, Literal

import anyio
from fastapi import APIRouter, Depends, HTTPException, Query, Request, status
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from bridge.archive import MAGIC
from server.archive_reads import archive_reads, read_failure
from server.auth import require_operator, require_token
from server.campaign_request import CampaignCreate, RequestError, prepare
from server.campaigns import (
    REPLAY_OF,
    Busy,
    CampaignManager,
    DrivesDisabled,
    NotFound,
    NotStopped,
    RunningElsewhere,
)
from server.records import CampaignRecord, CampaignStatus, valid_id
from server.results import FIGURES, control_tables, identification_tables, quality_tables, render_figure

router = APIRouter(prefix="/api/campaigns", tags=["campaigns"])


class OpenFileResponse(FileResponse):
    """A :class:`FileResponse` (ranges and all) of a file the route has opened already: its size is
    the open file's and its bytes are read from it, so a delete or an atomic rewrite of the path
    while the response is under way changes nothing of it. A FileResponse by path stat'ed and
    opened the file after the route had returned: a campaign deleted meanwhile was a 500 or a
    transfer broken after its 200 (audit of 2026-11-27)."""

    def __init__(self, file: BinaryIO, **kwargs: Any) -> None:
        self._file = file
        super().__init__(file.name, stat_result=os.fstat(file.fileno()), **kwargs)

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        scope = {**scope, "extensions": {k: v for k, v in scope.get("extensions", {}).items()
                                         if k != "http.response.pathsend"}}  # by path: what this avoids
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._file.close()

    @contextlib.asynccontextmanager
    async def _open_file(self) -> AsyncIterator[anyio.AsyncFile[bytes]]:
        yield anyio.AsyncFile(self._file)  # closed by __call__


def _manager(request: Request) -> CampaignManager:
    return request.app.state.campaigns


def _record(manager: CampaignManager, campaign_id: str) -> CampaignRecord:
    if not valid_id(campaign_id):
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no campaign {campaign_id!r}")
    try:
        return manager.get(campaign_id)
    except NotFound:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no campaign {campaign_id!r}") from None


def _conflict(exc: Busy | DrivesDisabled) -> JSONResponse:
    """409: what holds the robot: ``running_campaign_id``, the campaign running (null when it is
    the e-stop or a replay, as in ``/api/system/health``); ``replay``, the campaign whose archive a
    replay publishes (null when it is no replay); ``estop``, whether the e-stop refused it. A
    replay's 409 had named the replayed campaign as running (user audit)."""
    if isinstance(exc, DrivesDisabled):
        return JSONResponse(status_code=status.HTTP_409_CONFLICT, content={
            "detail": f"{exc}: release the e-stop first", "running_campaign_id": None, "estop": True, "replay": None})
    replay = exc.what == REPLAY_OF
    if isinstance(exc, RunningElsewhere):
        detail = (f"campaign {exc.running_id} is still running on controller {exc.controller or '(unknown)'}, not "
                  f"recorded since this console's restart: stop it first (POST /api/campaigns/{exc.running_id}/stop)")
    elif replay:
        detail = (f"a {REPLAY_OF} {exc.running_id} is running (its archive published again, nothing recorded): "
                  f"stop it first (POST /api/campaigns/{exc.running_id}/stop)")
    else:
        detail = f"{exc.what} {exc.running_id} is running"
    return JSONResponse(status_code=status.HTTP_409_CONFLICT, content={
        "detail": detail, "running_campaign_id": None if replay else exc.running_id, "estop": False,
        "replay": exc.running_id if replay else None})


@router.post("", status_code=status.HTTP_201_CREATED, response_model=CampaignRecord,
             dependencies=[Depends(require_token), Depends(require_operator)],
             responses={409: {"description": "Another campaign is running (its id in running_campaign_id, "
                                             "estop false), a replay runs (the replayed campaign's id in replay, "
                                             "running_campaign_id null), or the e-stop disables the drives "
                                             "(running_campaign_id null, estop true)"},
                        422: {"description": "Invalid body, or a choice this console cannot honour; loc names "
                                             "the field"},
                        503: {"description": "An `xneck up` stack's console whose controller service is not on "
                                             "the bus (being restarted or stopped)"},
                        507: {"description": "The archive cannot be written (free space with the figures, "
                                             "read-only, I/O error)"}})
async def create_campaign(body: CampaignCreate, request: Request) -> Any:
    """Start a campaign, exactly as asked (omitted fields: the documented defaults) or not at all.
    The trajectory is validated as the controller does before anything moves."""
    manager = _manager(request)
    if manager.running_id is not None:  # cheap early answer; start() re-checks under its lock
        return _conflict(Busy(manager.running_id))
    service = manager.service_alive()
    if request.app.state.settings.stack and not service:
        # Run as a console of its own, it spawned a twin and a controller on the stack's bus, whose
        # bridge then obeyed that controller for a while (audit of session 44).
        return JSONResponse(status_code=503, content={"detail": (
            "the stack's controller service is not on the bus (being restarted by `xneck up --restarts`, or "
            "stopped): try again once it is back (GET /api/system/processes lists it as campaign-service)")})
    try:
        prepared = await run_in_threadpool(prepare, body, request.app.state.params, request.app.state.settings,
                                           service)
    except RequestError as exc:
        return JSONResponse(status_code=422, content={"detail": exc.detail()})
    try:
        # Off the event loop: after a crash recovery start() may wait seconds for the bus, and on
        # the loop that wait had held the e-stop's answer back 5 s (review of session 40).
        return await run_in_threadpool(manager.start, prepared)
    except (Busy, DrivesDisabled) as exc:
        return _conflict(exc)


@router.get("", response_model=list[CampaignRecord])
def list_campaigns(request: Request,
                   status_: CampaignStatus | None =
                   Query(None, alias="status"),
                   kind: Literal["identification", "control"] | None = None,
                   law: str | None = Query(None, pattern=r"^(law)?[123](-no-pulleys)?$",
                                           description="Control law: 1, 2 or 3 as the POST body's `law`, or the "
                                           "record's name (law1..law3, law2-no-pulleys...)"),
                   limit: int = Query(100, ge=1, le=1000)) -> list[CampaignRecord]:
    # A number is the body's law (audit of 2026-11-29: ?law=2 was a silent [], ?law=7 too).
    if law is not None and not law.startswith("law"):
        law = f"law{law}"
    return _manager(request).list(status_, kind, law, limit)


@router.get("/{campaign_id}", response_model=CampaignRecord)
def get_campaign(campaign_id: str, request: Request) -> CampaignRecord:
    """Status with progress (0-1) and, once ended, the metrics."""
    return _record(_manager(request), campaign_id)


@router.post("/{campaign_id}/stop", response_model=CampaignRecord,
             dependencies=[Depends(require_token), Depends(require_operator)],
             responses={409: {"description": "A controller runs the campaign unrecorded and did not answer the "
                                             "stop: the reason"}})
def stop_campaign(campaign_id: str, request: Request) -> Any:
    """Ask a running campaign (or replay) to stop; it ends as ``aborted`` within a few seconds. A
    campaign a controller runs on unrecorded (``running_on``: this console was restarted during it)
    is stopped on that controller before the answer, whose message says so."""
    _record(_manager(request), campaign_id)
    try:
        return _manager(request).stop(campaign_id)
    except NotStopped as exc:
        return JSONResponse(status_code=status.HTTP_409_CONFLICT, content={"detail": str(exc)})


@router.delete("/{campaign_id}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response, dependencies=[Depends(require_token)],
               responses={409: {"description": "The campaign is running"}})
def delete_campaign(campaign_id: str, request: Request) -> Response:
    _record(_manager(request), campaign_id)
    try:
        _manager(request).delete(campaign_id)
    except Busy as exc:
        return _conflict(exc)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/{campaign_id}/results")
def campaign_results(campaign_id: str, request: Request) -> dict[str, Any]:
    """Metrics and tables shaped like the 3-X paper's (Table 3 for control, Tables 1-2 for identification)."""
    rec = _record(_manager(request), campaign_id)
    tables = identification_tables(rec.identification) + control_tables(rec.law, rec.metrics) + \
        quality_tables(rec.quality)
    return {"id": rec.id, "kind": rec.kind, "status": rec.status, "message": rec.message, "quality": rec.quality,
            "law": rec.law, "metrics": rec.metrics,
            "identification": rec.identification, "identification_status": rec.identification_status,
            "tables": tables,
            "figures": [f"/api/campaigns/{rec.id}/figures/{n}.png" for n in FIGURES] if rec.status != "running" else [],
            "mcap": f"/api/campaigns/{rec.id}/mcap"}


def _unfinished_mcap(file: BinaryIO) -> bool:
    """Whether the open ``file`` is an MCAP file, or its beginning, without the closing magic (no
    footer: what a recording cut short leaves). A file that is no MCAP at all is not judged here."""
    size = os.fstat(file.fileno()).st_size
    if not MAGIC.startswith(os.pread(file.fileno(), len(MAGIC), 0)):
        return False
    return size < 2 * len(MAGIC) or os.pread(file.fileno(), len(MAGIC), size - len(MAGIC)) != MAGIC


@router.get("/{campaign_id}/mcap", response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}}},
                       503: {"description": "The archive is unfinished (its recording failed and it could not be "
                                            "finished yet): the reason, and when it is repaired"}})
def download_mcap(campaign_id: str, request: Request) -> FileResponse:
    """The campaign's MCAP archive (readable by Foxglove; 409 while it is being recorded, 503 while
    an ended campaign's archive is unfinished: a file without its footer is not served as a 200)."""
    manager = _manager(request)
    rec = _record(manager, campaign_id)
    if rec.status == "running":
        raise HTTPException(status.HTTP_409_CONFLICT, "the campaign is still being recorded")
    path = manager.index.mcap(campaign_id)
    try:
        file = open(path, "rb")  # noqa: SIM115 - the response closes it
    except FileNotFoundError:  # none, or deleted since the record was read
        raise HTTPException(status.HTTP_404_NOT_FOUND, "this campaign has no archive") from None
    if _unfinished_mcap(file):
        file.close()
        why = manager.archive_problem(campaign_id)
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE,
                            "the campaign's archive is unfinished (no MCAP footer): nothing could read it"
                            + (f"; it could not be finished: {why}" if why else "")
                            + "; the console repairs it at its next start")
    return OpenFileResponse(file, media_type="application/octet-stream", filename=path.name)


@router.get("/{campaign_id}/figures/{name}.png", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}})
async def figure(campaign_id: str, name: str, request: Request) -> FileResponse:
    """Report figure: ``tracking`` (α̂, α^d, α_IP per joint) or ``forces``."""
    rec = _record(_manager(request), campaign_id)
    if name not in FIGURES:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no figure {name!r}; figures: {', '.join(FIGURES)}")
    if rec.status == "running":
        raise HTTPException(status.HTTP_409_CONFLICT, "figures are drawn once the campaign has ended")
    manager = _manager(request)
    out = manager.index.figures(campaign_id) / f"{name}.png"
    if not out.exists():
        mcap = manager.index.mcap(campaign_id)

        def draw() -> None:
            if not out.exists():  # drawn by the request this one waited for
                render_figure(mcap, name, out)

        try:
            # its archive read outside PYPLOT_LOCK: one per archive, two at most, on threads of
            # their own, never the pool the e-stop's POST needs (review of session 53)
            await archive_reads(request.app.state).run(mcap, draw)
        except Exception as exc:  # noqa: BLE001 - a damaged archive is a 422, not a crash
            # not the exception's text alone: it named the data directory (review of session 53)
            raise HTTPException(422, f"cannot draw {name}: {read_failure(campaign_id, mcap, exc)}") from None
    try:
        file = open(out, "rb")  # noqa: SIM115 - the response closes it
    except FileNotFoundError:  # the campaign was deleted meanwhile
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no campaign {campaign_id!r}") from None
    return OpenFileResponse(file, media_type="image/png")


class ParameterSetRequest(BaseModel, extra="forbid"):
    name: str = Field(..., min_length=1, max_length=64, description="Name of the new parameter set (letters, "
                      "digits, '_', '.', '-'); an existing set is never replaced.")


@router.post("/{campaign_id}/parameter-set", status_code=status.HTTP_201_CREATED,
             dependencies=[Depends(require_token)],
             responses={409: {"description": "Not an identified identification campaign, or the name is taken"},
                        422: {"description": "A bad name, or an archive that no longer identifies"}})
async def save_parameter_set(campaign_id: str, body: ParameterSetRequest, request: Request) -> dict[str, Any]:
    """Store an identification campaign's identified parameter set under ``name`` (what `xneck
    identify --out` writes: k, λ, f_s, c_a where well identified, the rest the campaign's set, a
    header with the provenance), ready for ``PUT /api/params/active``: the set the campaign's
    analysis identified (server.identified_sets; identified again if it was not kept). Returns which
    values were used, which kept their base value and why, and the ``--set`` values of the output
    error's structure (reported, not written)."""
    from server.identified_sets import NotIdentified, cached_set, save_identified_set
    from twin.identification.pipeline import IdentificationError
    from twin.model.params import ParameterError

    manager = _manager(request)
    rec = _record(manager, campaign_id)
    try:
        return await run_in_threadpool(lambda: save_identified_set(
            manager.mcap_path(campaign_id), rec, request.app.state.params, body.name,
            cached_set(manager.index.figures(campaign_id))))
    except (NotIdentified, FileExistsError) as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    except (ParameterError, IdentificationError) as exc:
        raise HTTPException(422, str(exc)) from None


class ReplayRequest(BaseModel):
    speed: float = Field(1.0, gt=0, le=100, description="Playback speed (1 = as recorded).")


@router.post("/{campaign_id}/replay", dependencies=[Depends(require_token)],
             responses={409: {"description": "A campaign or replay is running"}})
async def replay_campaign(campaign_id: str, request: Request, body: ReplayRequest | None = None) -> Any:
    """Publish the archive back onto the bus (never force commands or e-stops); the live views
    show it as if it were live."""
    _record(_manager(request), campaign_id)
    speed = body.speed if body else 1.0
    try:
        return await run_in_threadpool(_manager(request).replay, campaign_id, speed)
    except Busy as exc:
        return _conflict(exc)
    except Exception as exc:  # noqa: BLE001 - e.g. an archive that cannot be read
        raise HTTPException(422, f"cannot replay: {exc}") from None
