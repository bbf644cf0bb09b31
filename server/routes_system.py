"""``/api/system``: health, processes alive on the bus, mode, e-stop, the safety journal, abort with a
cause; ``/api/config`` for the dashboard."""

from __future__ import annotations

import json
import logging
import time
from typing import Any

import anyio
import anyio.to_thread
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from bridge import bus, small_file
from bridge.archive import software_version
from controller.laws import LAWS
from controller.trajectory import NAMED_TRAJECTORIES, trajectory_json_schema
from server.auth import require_operator, require_token
from server.camera_feed import camera_health
from server.child_processes import local_processes
from server.guard import ESTOP_MAX_BODY_BYTES, MAX_JSON_DEPTH, TOO_LARGE, json_depth_exceeds
from server.live import bridge_status
from server.routes_jog import jog_status, note_fault
from server.safety_journal import READ_MAX_LINES, SafetyJournal, read_journal

log = logging.getLogger("xneck.server")

router = APIRouter(tags=["system"])

USER_AGENT_MAX_CHARS = 120  # of a client's User-Agent as journalled and logged
#: threads reading the safety journal at once, their own: never those of anyio's default pool (the
#: sync routes'), whatever the disk does and however many GETs (no token) wait
JOURNAL_READERS = 2
#: threads publishing e-stops, their own too: anyio's default pool is any open GET's (a flood of
#: 45 compare GETs had held it and the e-stop waited 7.3 s for a thread: review of session 53)
ESTOP_SENDERS = 2


@router.get("/api/system/health")
def health(request: Request) -> dict[str, Any]:
    """The console's state at a glance (docs/console.md, "System health"). ``bridge``: how old the
    bridge's latest valid motor state is (``state_age_s``, seconds on the monotonic clock, null
    before any; it grows while the bridge is silent) and its ``drive``, ``owner`` and ``instance``
    as of that state. ``bus``: who may link to the console's session (bridge.session.access_summary;
    ``open`` when anyone on the network may; ``changed_since_start``, its credentials and TLS files
    replaced since it started, which its session does not apply until a restart).
    ``unrecorded_campaign``: ``{"id", "controller"}`` of a campaign of this console's that a
    controller service still runs though the console no longer records it (it was restarted during
    it; ``running_campaign_id`` names it too), else null. ``process_faults``: how many deaths,
    hangs and restarts of the stack's processes ``xneck up`` reported since the console started,
    and the newest (server.process_faults). ``uptime_s`` in seconds."""
    s = request.app.state
    elsewhere = s.campaigns.unrecorded()
    return {
        "status": "ok", "version": software_version(), "uptime_s": time.monotonic() - s.started,
        "mode": s.settings.mode, "pace": s.settings.pace, "hub": s.hub,
        "bus": {**s.bus_access, "changed_since_start": small_file.changed(s.bus_files)},
        "viser_port": s.scene.port if s.scene else None,
        # a campaign of this console's that a controller runs on unrecorded (it was restarted during
        # it) is the running one too: the dashboard follows it and its Stop stops it
        "running_campaign_id": s.campaigns.running_id or (elsewhere[0] if elsewhere else None),
        "unrecorded_campaign": {"id": elsewhere[0], "controller": elsewhere[1]} if elsewhere else None,
        "replay": s.campaigns.replay_status(),
        "recovery_errors": s.campaigns.recovery_errors,  # file -> why start-up could not repair it
        "parameter_set": s.params.active_status(),  # the active set; the one named instead and why it did not load
        "estop": s.campaigns.estop_status(),  # the bridge's latched e-stop when it reports one
        "bridge": bridge_status(s.live.values),  # how old its latest motor state is: live or silent
        "camera": camera_health(s.live.values, s.camera, s.presence),  # detection health (issue 15); None without a camera
        "safety_journal": _journal_status(s),  # lines written, failed, dropped; transitions suppressed
        "process_faults": s.process_faults.status(),  # deaths, hangs, restarts xneck up reported
        "jog": jog_status(s),  # the last jog, and why a death cut it short (the dashboard's jog panel)
        "live": {"clients": len(s.broadcaster.clients), "frames_sent": s.broadcaster.frames_sent,
                 "rejected_payloads": s.live.values.rejected},
    }


@router.get("/api/system/processes")
def processes(request: Request) -> dict[str, Any]:
    """Processes whose Zenoh liveliness token is on the bus (twin, controller, bridge, ...), and
    ``scheduling``: what each xneck process of this machine got from the kernel (policy,
    real-time priority, nice, CPUs) and what it was refused (issue 21: the loop's processes at
    real-time priority on their own CPU where permitted, the console off it). Each process carries
    its latest health counters (``health``, server.presence); ``health_rejected`` counts the
    health messages refused (malformed, or their key and body disagreeing)."""
    presence = request.app.state.presence
    return {"processes": presence.processes(), "scheduling": local_processes(),
            "health_rejected": presence.health_rejected}


@router.get("/api/system/mode")
def mode(request: Request) -> dict[str, str]:
    """``twin`` (campaigns start their own twin) or ``robot`` (they drive the bridge on the bus)."""
    return {"mode": request.app.state.settings.mode, "pace": request.app.state.settings.pace}


#: The reason sent when the request names none: a release's says it released, never "console"
#: alone, which read as the engage's cause in the answer and the bridge's log (user audit).
DEFAULT_REASONS = {True: "console", False: "released from the console"}


class EStopRequest(BaseModel):
    """The e-stop's body, as strict as the campaigns' (user audit): an unknown field
    (``{"release": true}``) or a value that is not a JSON boolean (``"off"``, ``0``,
    ``"false"``) is a 422, never coerced into a release or ignored into an engage."""

    model_config = ConfigDict(extra="forbid", strict=True)

    engaged: bool = Field(True, description="true engages, false releases (a JSON boolean: nothing else).")
    reason: str | None = Field(None, max_length=200, description="Why; none: \"console\" for an engage, "
                                                                  "\"released from the console\" for a release.")

    def why(self) -> str:
        """The reason sent: the one given, else the default of an engage or a release."""
        return self.reason if self.reason is not None else DEFAULT_REASONS[self.engaged]


MALFORMED_ANSWER = ("The body is no e-stop request (an unknown field, a value that is not a JSON boolean, a "
                    "reason too long): the e-stop was ENGAGED all the same, never released (``engaged``: true "
                    "in the answer), and ``detail`` says what was wrong.")


@router.post("/api/system/estop", dependencies=[Depends(require_token), Depends(require_operator)],
             openapi_extra={"requestBody": {"required": False, "content": {"application/json": {
                 "schema": EStopRequest.model_json_schema()}}}},
             responses={422: {"description": MALFORMED_ANSWER},
                        413: {"description": "The body is larger than the console takes: the e-stop was ENGAGED "
                                             "all the same (``engaged``: true), the body left unread."}})
async def estop(request: Request) -> Any:
    """Engage or release the e-stop: published on the bus (the bridge disables its drives and
    latches it); engaging also aborts the running campaign and any replay. The answer is what was
    sent; ``/api/system/health`` shows what the bridge reports (``estop.source``). Published
    first, then logged and journalled (a failed publication too): a log handler that blocks does
    not delay the e-stop (review of session 43).

    A body that is no :class:`EStopRequest` engages it all the same and answers 422
    (:data:`MALFORMED_ANSWER`): the body is strict, so nothing is coerced into a release, and a
    caller's typo in an emergency (``{"engage": true}``, JSON cut short, not JSON at all) still
    stops the robot (user audit and review of session 46; before, unknown fields were ignored and
    ``"off"``, ``0``, ``"false"`` released). The body is read here, not by FastAPI, whose own
    refusals (422, 400) had sent nothing; a key given twice is malformed too. A body larger than
    the console takes engages it too, answering 413 (the guard's 413 had sent nothing): for this
    route that is :data:`~server.guard.ESTOP_MAX_BODY_BYTES`, whatever the rest take (a 248 KB body
    of 28,000 keys had held the e-stop 5.75 s: review of session 53). Published on threads of its
    own (:data:`ESTOP_SENDERS`), its token checked on the event loop: no GET delays it."""
    too_large = request.scope.get(TOO_LARGE)
    if too_large is not None:  # the guard read no further: engaged, never a release
        body, errors, status = None, [{"type": "too_large", "loc": ["body"], "msg": f"larger than the console takes ({too_large})"}], 413
    else:
        body, errors = _estop_body(await request.body())
        status = 413 if errors and errors[0]["type"] == "too_large" else 422
    if body is None:
        first = errors[0]
        where = ".".join(str(x) for x in first["loc"][1:]) or "body"
        why = bus.plain_text(f"console (malformed e-stop request: {where}: {first['msg']})")
        await anyio.to_thread.run_sync(_send_estop, request, True, why, limiter=_estop_senders(request))
        return JSONResponse(status_code=status, content={"detail": errors, "engaged": True, "reason": why})
    why = body.why()
    await anyio.to_thread.run_sync(_send_estop, request, body.engaged, why, limiter=_estop_senders(request))
    return {"engaged": body.engaged, "reason": why}


def _own_threads(request: Request, name: str, threads: int) -> anyio.CapacityLimiter:
    """The app's limiter ``name`` of ``threads`` threads, never anyio's default pool: made in the
    app's event loop on first use (no await between the test and the set)."""
    s = request.app.state
    limiter = getattr(s, name, None)
    if limiter is None:
        limiter = anyio.CapacityLimiter(threads)
        setattr(s, name, limiter)
    return limiter


def _estop_senders(request: Request) -> anyio.CapacityLimiter:
    """The e-stop's own threads (:data:`ESTOP_SENDERS`)."""
    return _own_threads(request, "estop_senders", ESTOP_SENDERS)


ESTOP_ERRORS_MAX = 5  # errors an e-stop's 422 lists (a body of 100 unknown keys answered 2.9 MB)


def _estop_body(raw: bytes) -> tuple[EStopRequest | None, list[dict[str, Any]]]:
    """The e-stop request in ``raw`` (no body: an engage), or None and the errors (at most
    :data:`ESTOP_ERRORS_MAX`, each ``type``, ``loc`` (its parts cut to 64 characters), ``msg``)."""

    def no_twice(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        # a set, one pass: keys.count(k) per key was O(n²) on the event loop, 28,000 keys held the
        # e-stop 5.75 s before it was published (review of session 53)
        seen: set[str] = set()
        twice: set[str] = set()
        for k, _ in pairs:
            (twice if k in seen else seen).add(k)
        if twice:
            raise ValueError(f"key given twice: {', '.join(sorted(twice)[:ESTOP_ERRORS_MAX])}")
        return dict(pairs)

    if len(raw) > ESTOP_MAX_BODY_BYTES:  # the guard's cap too; this holds if it is ever left out
        return None, [{"type": "too_large", "loc": ["body"],
                       "msg": f"larger than the e-stop takes (request body of {len(raw)} bytes: at most "
                              f"{ESTOP_MAX_BODY_BYTES} bytes)"}]
    if json_depth_exceeds(raw):  # the guard leaves this path's body to the route
        return None, [{"type": "json_invalid", "loc": ["body"], "msg": f"JSON nested deeper than {MAX_JSON_DEPTH} levels"}]
    try:
        value = json.loads(raw.decode("utf-8-sig"), object_pairs_hook=no_twice) if raw.strip() else {}
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        return None, [{"type": "json_invalid", "loc": ["body"], "msg": bus.plain_text(f"not JSON: {exc}")}]
    try:
        return EStopRequest.model_validate({} if value is None else value), []
    except ValidationError as exc:
        return None, [{"type": e["type"], "loc": ["body", *(bus.plain_text(str(x), 64) for x in e["loc"])],
                       "msg": bus.plain_text(e["msg"])} for e in exc.errors()[:ESTOP_ERRORS_MAX]]


def _send_estop(request: Request, engaged: bool, why: str) -> None:
    """Publish an e-stop request, then log and journal it (module docstring of :func:`estop`)."""
    s = request.app.state
    error = "unexpected error"
    try:
        s.campaigns.estop(engaged, why)
        error = ""
    except Exception as exc:
        error = bus.plain_text(f"{type(exc).__name__}: {exc}")
        raise
    finally:
        sent = {"engaged": engaged, "reason": bus.plain_text(why), **_requester(request),
                "holder": s.campaigns.estop_holder}
        log.warning("e-stop %s by %s (%s, %s): %r%s", "engaged" if engaged else "released", sent["client"],
                    sent["auth"], sent["user_agent"] or "no user agent", sent["reason"],
                    f"; NOT PUBLISHED: {error}" if error else "")
        # queued, never written here: a journal that cannot write does not fail the e-stop. The same
        # request again from the same host (any port: a new connection each) within a second is
        # counted in one line, not written each: a flood had rotated the journal's older lines out.
        peer = request.client
        same = (engaged, sent["reason"], peer.host if peer is not None else "", sent["user_agent"],
                sent["holder"], error)
        s.journal.record("estop_sent", repeat_key=same, **sent, published=not error, error=error)


def _requester(request: Request) -> dict[str, Any]:
    """Who sent a request, as the console knows it: ``client``, the peer's address ``host:port``
    (a proxy's if one is in between: no forwarded header is trusted); ``user_agent`` (cut);
    ``auth``, what allowed it (the console's one bearer token: not a person); ``bus_user`` and
    ``bus_role``, the console's own bus identity (bridge.session.access_summary; null user
    without credentials), under which the e-stop reaches the bridge."""
    peer = request.client
    access = getattr(request.app.state, "bus_access", None) or {}
    return {"client": f"{peer.host}:{peer.port}" if peer is not None else "unknown",
            "user_agent": bus.plain_text(request.headers.get("user-agent", ""), USER_AGENT_MAX_CHARS),
            "auth": "bearer token", "bus_user": access.get("user"), "bus_role": access.get("role")}


def _journal_status(s: Any) -> dict[str, Any]:
    return {**s.journal.status(), **s.transitions.status()}


@router.get("/api/system/safety-journal")
async def safety_journal(request: Request,
                   limit: int = Query(100, ge=1, le=READ_MAX_LINES,
                                      description="How many of the newest events to return.")) -> dict[str, Any]:
    """The console's safety journal (docs/console.md, "Safety journal"; server.safety_journal):
    ``events``, the newest ``limit`` lines, oldest first, each as written (``time`` ISO 8601
    UTC, ``stamp_s`` s since the epoch, ``event``: ``estop_sent``, ``process_fault``, ``bridge_run``,
    ``bridge_state``, and its fields); ``skipped``, lines read that are not events (a line torn
    by a crash, garbage); ``journal``, the counters since the console started (``written``,
    ``write_errors``, ``last_error``, ``dropped`` lines; ``suppressed`` transitions no line
    shows, ``runs_forgotten``, ``owed`` lines and ``oldest_owed_s``); ``unreadable``, a line per
    file not read (``"journal.jsonl: a FIFO, not a regular file: not read"``: what is at its path
    is refused, never waited on). Open like the other reads (no token): read on
    :data:`JOURNAL_READERS` threads of its own, so no number of GETs delays the e-stop's POST."""
    s = request.app.state
    readers = _own_threads(request, "journal_readers", JOURNAL_READERS)
    events, skipped, unreadable = await anyio.to_thread.run_sync(_read_journal, s.journal, limit, limiter=readers)
    return {"events": events, "skipped": skipped, "unreadable": unreadable, "journal": _journal_status(s)}


def _read_journal(journal: SafetyJournal, limit: int) -> tuple[list[dict[str, Any]], int, list[str]]:
    journal.flush(0.5)  # what was queued before this request, written (a moment at most)
    return read_journal(journal, limit)


class AbortRequest(BaseModel):
    reason: str = Field(..., min_length=1, max_length=300,
                        description="The cause, first in the campaign's message, e.g. \"bridge process exited "
                                    "(signal SIGKILL)\".")
    ended_within_s: float | None = Field(None, ge=0, le=60, description="Also name a campaign that already ended "
                                         "aborted within this many seconds before the request (it saw the cause's "
                                         "side effect first); null: only a running one.")
    stack_stopping: bool = Field(False, description="The console is stopped next (`xneck up` stopping its stack): "
                                 "the campaign's 3D scene is not added, so its record is final at once.")


@router.post("/api/system/abort", dependencies=[Depends(require_token), Depends(require_operator)])
def abort(body: AbortRequest, request: Request) -> dict[str, Any]:
    """Stop the running campaign because of a cause the console cannot see itself (``xneck up``
    tells it which of its processes died, and how): the campaign ends ``aborted`` with ``reason``
    first in its record and in its archive, what it saw itself after that. Answers once its record
    is final (at most 10 s): ``campaign_id`` (null if none was running or ended within
    ``ended_within_s``), its ``status`` and ``message``. Nothing else changes: the bridge, the
    controller and the e-stop are left as they are (the controller holds as after any stop). The
    cause is journalled (``process_fault``, :mod:`server.safety_journal`): a stack's deaths, hangs
    and restarts stay on record between campaigns too."""
    s = request.app.state
    rec = None
    try:
        rec = s.campaigns.abort(body.reason, body.ended_within_s, stack_stopping=body.stack_stopping)
    finally:
        # the same cause again from the same host within a second is counted in one line (a flood of
        # a token holder's would rotate older lines out, as the e-stop's did)
        who = _requester(request)
        same = (bus.plain_text(body.reason), (request.client.host if request.client else ""), who["user_agent"],
                rec.id if rec else None, rec.status if rec else None)
        s.journal.record("process_fault", repeat_key=same, reason=bus.plain_text(body.reason),
                         campaign_id=rec.id if rec else None, campaign_status=rec.status if rec else None, **who)
        s.process_faults.record(bus.plain_text(body.reason), rec.id if rec else None)
        note_fault(s, bus.plain_text(body.reason), body.ended_within_s)  # a jog it cut short says so
    if rec is None:
        return {"campaign_id": None, "status": None, "message": None}
    return {"campaign_id": rec.id, "status": rec.status, "message": rec.message}


@router.get("/api/config")
def config(request: Request) -> dict[str, Any]:
    """What the dashboard needs to build its forms and embed the 3D view."""
    s = request.app.state
    return {
        "viser_port": s.scene.port if s.scene else None, "mode": s.settings.mode, "pace": s.settings.pace,
        "live_rate_hz": s.settings.live_rate_hz, "laws": list(LAWS), "kinds": ["control", "identification"],
        "trajectories": list(NAMED_TRAJECTORIES), "waypoints_schema": trajectory_json_schema(),
        "parameter_sets": s.params.names(), "active_parameter_set": s.params.active(),
        "n_joints": s.default_params.n_joints, "n_motors": s.default_params.n_cables,
        "f_max_N": s.default_params.limits.f_max, "alpha_max_deg": s.default_params.limits.alpha_max_deg,
    }
