"""``/api/jog``: move the neck to a pose by hand, through the controller service (issue 18).

A jog is a campaign request of kind ``jog`` (:class:`bridge.bus.CampaignRequest` v3) holding one
waypoint, the target; the controller reaches it by its gentle approach from α^d (peak 0.5 rad/s,
1 rad/s², :func:`controller.trajectory.approach`) and holds it. A jog asked for while a jog runs
waits for it (the newest one only), so a slider dragged in the dashboard chains moves, each from
rest, with no force step. Nothing is archived: a jog is not an experiment.

Before anything is sent, the move from the controller's α̂ (its latest status) to the target is
checked as a campaign is (:func:`server.campaign_request.check_trajectory`: joint limits, speed,
acceleration, forces on the nominal path with the law that holds the neck): a 422 carries the
checker's message. Refused with 409 while a campaign or a replay runs and while the drives are
disabled (the bridge's e-stop, its one truth) or when several controller services are on the bus
and the bridge obeys none of them (``server/service_choice.py``: a jog goes to one service);
503 without a controller service or its status;
429 when jogs come faster than ``JOG_MIN_INTERVAL_S`` (the sliders send at most a few per second).

``GET /api/jog`` (and ``jog`` in ``/api/system/health``, which the dashboard's jog panel reads)
says the last jog this console sent and, in ``ended``, why it ended before its move and settle
were over when a death of the controller or the bridge cut it short, as ``xneck up`` told the
console (``POST /api/system/abort``: :func:`note_fault`). Before, only the dashboard's header
said it; the jog panel went on showing the move as under way (review of session 46). It says too
why the controller aborted it, from the jog's ``aborted`` event on the bus (:meth:`JogDesk.heard`;
CI of 8b61d5c, reproduced beside busy loops: a starved controller's status named no campaign any
more, the neck at 5° of the jog's 15°, and the panel went on showing "→ [15, 0, 0]° in 1.3 s"),
unless this console stopped it itself (``POST /api/jog/stop``: the panel says "holding").
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from typing import Any

from fastapi import APIRouter, Depends, Request, status
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field

from bridge import bus
from bridge.safety import INSTANCE_NAME
from bridge.session import payload_of, publisher
from controller.laws import LawConfig
from controller.trajectory import Trajectory, TrajectoryError, approach
from server.auth import require_operator, require_token
from server.campaign_request import check_trajectory
from server.service_choice import choose_service

log = logging.getLogger("xneck.server")
router = APIRouter(prefix="/api/jog", tags=["jog"])

JOG_MIN_INTERVAL_S = 0.1  # s between two accepted jogs
# s after its planned move a jog still counts as under way: the controller's settle
# (controller.service.JOG_SETTLE_S, 0.2 s) and the request's transit
JOG_END_MARGIN_S = 0.5
# The processes whose death ends a jog, as xneck up names them in a cause ("controller process
# exited (signal SIGKILL), restarting controller in 1 s (...)"; causes of one pass joined by "; ").
JOG_CARRIERS = ("controller", "bridge")
STATUS_MAX_AGE_S = 0.5  # s: an older controller status says nothing about α̂ now


class JogRequest(BaseModel):
    """A jog's target. Strict, as :class:`server.campaign_request.CampaignCreate`: ``["10", true, 0]``
    was taken as [10, 1, 0]° and moved the neck (review); a string or a bool is a 422, not coerced
    (pydantic's strict float refuses bools too)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    alpha_deg: list[float] = Field(min_length=1, max_length=16, description="Target joint angles α1..αN (deg).")


class JogDesk:
    """The console's jog state: the publisher of requests, the last jog and when it was sent."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.requests: dict[str, Any] = {}  # target service ('' : any) -> its publisher
        self.target = ""  # the service the last jog went to (its stop goes there too)
        self.lock = threading.Lock()
        self.last_s = -math.inf
        self.last_id = ""
        self.seq = itertools.count(1)  # of the request messages
        self.ids = itertools.count(1)
        #: the last jog sent: jog_id, to_deg, duration_s, sent_s and ends_s (time.monotonic(): when
        #: its move and settle are over), ended (why it was cut short, "" if it was not), stopped
        #: (this console asked it to stop); None before any
        self.last: dict[str, Any] | None = None
        # Its end events, heard from before the first jog is sent (the desk is made for it).
        self.events = None if session is None else session.declare_subscriber(bus.CAMPAIGN_EVENTS, self._on_event)

    def _on_event(self, sample: Any) -> None:
        try:
            self.heard(bus.decode(bus.CampaignEvent, payload_of(sample, bus.CampaignEvent)))
        except bus.BusDecodeError:
            return  # a malformed event is the bus's to count (server.live), not the jog's

    def heard(self, event: bus.CampaignEvent) -> None:
        """A campaign event from the bus: the last jog's ``aborted`` (a controller's reason: no
        progress, drives off, a latch, a campaign's start) ends it with that reason, unless this
        console stopped it (:func:`stop_jog`) or it ended already (a death said first stands)."""
        if event.kind != "jog" or event.event not in ("aborted", "interrupted"):
            return
        with self.lock:
            last = self.last
            if last is None or last["jog_id"] != event.campaign_id or last["ended"] or last["stopped"]:
                return
            last["ended"] = f"{event.event} by the controller: {bus.plain_text(event.message, 300) or 'no reason given'}"

    def sent(self, jog_id: str, to_deg: list[float], duration_s: float, now_s: float) -> None:
        """Keep jog ``jog_id`` (to ``to_deg``, deg; its move ``duration_s`` long, s) as the last one,
        sent at ``now_s`` (time.monotonic()). The caller holds :attr:`lock`."""
        self.last = {"jog_id": jog_id, "to_deg": list(to_deg), "duration_s": duration_s, "sent_s": now_s,
                     "ends_s": now_s + duration_s + JOG_END_MARGIN_S, "ended": "", "stopped": False}

    def send(self, campaign_id: str, action: str, trajectory_json: str = "", target: str | None = None) -> None:
        """A request to the service ``target`` (None: the last jog's), bare if none is known."""
        target = self.target if target is None else target
        self.target = target
        if target not in self.requests:
            self.requests[target] = publisher(self.session, bus.campaign_request_key(target) if target
                                              else bus.CAMPAIGN_REQUEST)
        self.requests[target].put(bus.CampaignRequest(seq=next(self.seq), stamp_s=time.time(), campaign_id=campaign_id,
                                              action=action, kind="jog",  # pyright: ignore[reportArgumentType]
                                              trajectory_json=trajectory_json))


def desk_of(state: Any) -> JogDesk:
    desk = getattr(state, "jog", None)
    if desk is None:
        desk = state.jog = JogDesk(state.session)
    return desk


def law_of(name: str) -> LawConfig:
    """The law a controller status names (``law2``, ``law3-no-pulleys``); law 2 if unreadable."""
    digits = name[3:4] if name.startswith("law") else ""
    law = int(digits) if digits in ("1", "2", "3") else 2
    return LawConfig(law=law, no_pulleys=name.endswith("-no-pulleys"))


def jog_target(alpha_deg: list[float], params: Any, law: LawConfig) -> Trajectory:
    """The target pose as a one-waypoint trajectory, checked as a campaign's (joint limits, forces
    to hold it); raises :class:`TrajectoryError` with the checker's message."""
    target = Trajectory.from_degrees([alpha_deg], [], 0.0, "jog")
    check_trajectory(target, params, law)
    return target


def jog_move(target: Trajectory, alpha_hat_rad: list[float], params: Any, law: LawConfig) -> Trajectory:
    """The move from α̂ to ``target`` the controller will make, checked as a campaign's."""
    move = approach(target, alpha_hat_rad)
    check_trajectory(move, params, law)
    return move


def _unacceptable(exc: Exception) -> tuple[int, Any]:
    return 422, {"detail": [{"loc": ["body", "alpha_deg"], "msg": str(exc), "type": "value_error"}]}


def busy_reason(state: Any) -> str:
    """Why no jog can start now ('' if one can): a campaign or replay, or disabled drives."""
    campaigns = state.campaigns
    if campaigns.running_id is not None:
        return f"campaign {campaigns.running_id} is running"
    replay = campaigns.replay_status()
    if replay and replay.get("running"):
        return f"replay of {replay.get('campaign_id')} is running"
    estop = campaigns.estop_status()  # the bridge's word when it is fresh
    if estop["engaged"] or estop.get("drive") == "disabled":
        return f"the drives are disabled ({estop['reason'] or 'e-stop engaged'}): release the e-stop first"
    return ""


def request_jog(state: Any, alpha_deg: list[float]) -> tuple[int, Any]:
    """Check and send a jog to ``alpha_deg`` for the console whose app state is ``state``:
    (HTTP status, answer body). Shared by the REST route and the viser panel's sliders."""
    busy = busy_reason(state)
    if busy:
        return status.HTTP_409_CONFLICT, {"detail": busy}
    target, ambiguous = choose_service(state.presence.instances("campaign-service"), bridge_owners(state))
    ctl = service_status(state, target)
    law = law_of(ctl.law if ctl is not None else "")
    params = state.default_params
    try:
        target_pose = jog_target(alpha_deg, params, law)
    except (TrajectoryError, ValueError) as exc:
        return _unacceptable(exc)
    if not state.presence.any_alive("campaign-service"):
        return status.HTTP_503_SERVICE_UNAVAILABLE, {"detail": "no controller service on the bus (start the "
                                                              "stack with `xneck up`)"}
    if ambiguous:
        return status.HTTP_409_CONFLICT, {"detail": ambiguous}
    if ctl is None:
        return status.HTTP_503_SERVICE_UNAVAILABLE, {"detail": "no recent controller status: α̂ is unknown"}
    try:
        move = jog_move(target_pose, ctl.alpha_hat_rad, params, law)
    except (TrajectoryError, ValueError) as exc:
        return _unacceptable(exc)
    desk = desk_of(state)
    with desk.lock:
        now = time.monotonic()
        if now - desk.last_s < JOG_MIN_INTERVAL_S:
            return status.HTTP_429_TOO_MANY_REQUESTS, {"detail": f"jogs come faster than one per "
                                                                 f"{JOG_MIN_INTERVAL_S:g} s"}
        desk.last_s = now
        desk.last_id = f"jog-{time.strftime('%H%M%S')}-{next(desk.ids)}"
        desk.send(desk.last_id, "start", target_pose.to_json(), target)
        desk.sent(desk.last_id, alpha_deg, move.duration_s, now)
    return status.HTTP_202_ACCEPTED, {"jog_id": desk.last_id,
                                      "from_deg": [round(math.degrees(a), 3) for a in ctl.alpha_hat_rad],
                                      "to_deg": list(alpha_deg), "duration_s": move.duration_s}


def cuts_jog(cause: str) -> bool:
    """Whether a process fault ``cause`` as ``xneck up`` words it names the death or hang of a
    process a jog needs (:data:`JOG_CARRIERS`; a camera's does not end one)."""
    return any(part.strip().startswith(f"{name} process ") for part in cause.split(";") for name in JOG_CARRIERS)


def under_way(sent_s: float, ends_s: float, fault_s: float, died_within_s: float) -> bool:
    """Whether a jog sent at ``sent_s`` whose move and settle end at ``ends_s`` was under way when
    a process died that the console heard of at ``fault_s``, its death at most ``died_within_s``
    before (the supervisor's ``ended_within_s``; s, one monotonic clock): sent before the console
    heard of it, and not over before the death could have happened."""
    return sent_s <= fault_s and ends_s >= fault_s - max(0.0, died_within_s)


def note_fault(state: Any, cause: str, died_within_s: float | None) -> str:
    """Mark the last jog cut short by ``cause`` when it names a process a jog needs and the jog
    was under way (:func:`under_way`; ``died_within_s`` None: the death now). Returns the jog's id
    ('' when none was cut short)."""
    desk: JogDesk | None = getattr(state, "jog", None)  # none: no jog was ever sent
    if desk is None:
        return ""
    with desk.lock:
        last = desk.last
        if last is None or last["ended"] or not cuts_jog(cause):
            return ""
        if not under_way(last["sent_s"], last["ends_s"], time.monotonic(), died_within_s or 0.0):
            return ""
        last["ended"] = cause
        return last["jog_id"]


def jog_status(state: Any) -> dict[str, Any] | None:
    """The last jog this console sent: ``jog_id``, ``to_deg``, ``duration_s`` (its planned move),
    ``age_s`` (since it was sent), ``ended`` (why it was cut short: the supervisor's cause, or the
    controller's reason for aborting it; null if it was not); None before any."""
    desk: JogDesk | None = getattr(state, "jog", None)
    if desk is None:
        return None
    with desk.lock:
        last = None if desk.last is None else dict(desk.last)
    if last is None:
        return None
    return {"jog_id": last["jog_id"], "to_deg": last["to_deg"], "duration_s": last["duration_s"],
            "age_s": round(time.monotonic() - last["sent_s"], 1), "ended": last["ended"] or None}


def service_status(state: Any, service: str) -> bus.ControllerStatus | None:
    """The fresh live status of the controller ``service`` (the campaign service a jog goes to:
    the one the bridge obeys), else one naming no controller; None if neither. The newest status
    of any controller had set the jog's start: a second controller on the bus answering after the
    bridge's owner put it at its own α̂ (review of session 40)."""
    statuses = state.live.live_statuses(STATUS_MAX_AGE_S)
    return statuses.get(service) or statuses.get("")


def bridge_owners(state: Any) -> set[str]:
    """The controller the bridge obeys, from its latest fresh state (none if unknown)."""
    msg = state.live.values.fresh("state", STATUS_MAX_AGE_S)
    return {msg.owner} if msg is not None and getattr(msg, "owner", "") else set()


def stop_jog(state: Any) -> list[str]:
    """Stop jogging where the neck is: the waiting jog is dropped and the running one stopped
    (the controller then holds α̂). Returns the ids stopped."""
    desk = desk_of(state)
    # every controller's running jog, each stop to the controller that runs it (a service takes
    # the bare key and its own only: review of session 41 had them all go to the last jog's)
    # A name that is no instance name (any peer names itself) goes to the bare key, which every
    # service reads: it had raised and left every later stop sending nothing (review of the fix).
    running = {st.campaign_id: name if INSTANCE_NAME.fullmatch(name) else ""
               for name, st in state.live.live_statuses(STATUS_MAX_AGE_S).items() if st.campaign_id.startswith("jog-")}
    with desk.lock:
        if desk.last is not None:  # over now: a death after this stop did not cut it short
            desk.last["ends_s"] = min(desk.last["ends_s"], time.monotonic())
            desk.last["stopped"] = True  # nor did its "aborted: stopped by the user"
        last_target = desk.target
        sends = [(desk.last_id, last_target)] if desk.last_id else []
        sends += [(cid, name) for cid, name in running.items() if (cid, name) != (desk.last_id, last_target)]
        stopped = []
        try:
            for cid, target in sends:
                try:
                    desk.send(cid, "stop", target=target)
                    stopped.append(cid)
                except Exception as exc:  # noqa: BLE001 - one stop that cannot go must not keep the others
                    log.error("jog %s: its stop could not be sent to %r (%s: %s)", cid, target, type(exc).__name__, exc)
        finally:
            desk.target = last_target  # send() keeps the target it was given: the last jog's stays
    return list(dict.fromkeys(stopped))


@router.post("", status_code=status.HTTP_202_ACCEPTED, dependencies=[Depends(require_token), Depends(require_operator)],
             responses={409: {"description": "A campaign or replay runs, the e-stop is engaged, or several "
                                             "controller services are on the bus and the bridge obeys none"},
                        422: {"description": "The move is out of the joint limits or the force range (the "
                                             "checker's message)"},
                        429: {"description": "Jogs come too fast"},
                        503: {"description": "No controller service (or no status from it) on the bus"}})
def jog(body: JogRequest, request: Request) -> Any:
    """Move the neck to ``alpha_deg`` and hold it there (module docstring). The answer says the
    move planned from α̂: ``jog_id``, ``from_deg``, ``to_deg``, ``duration_s``."""
    code, answer = request_jog(request.app.state, body.alpha_deg)
    return JSONResponse(status_code=code, content=answer)


@router.get("")
def jog_last(request: Request) -> dict[str, Any]:
    """The last jog this console sent (:func:`jog_status`; ``jog`` null before any), and in
    ``ended`` why a death of the controller or the bridge cut it short."""
    return {"jog": jog_status(request.app.state)}


@router.post("/stop", dependencies=[Depends(require_token), Depends(require_operator)])
def jog_stop(request: Request) -> dict[str, Any]:
    """Stop jogging where the neck is: the waiting jog is dropped and the running one stopped
    (the controller then holds α̂)."""
    return {"stopped": stop_jog(request.app.state)}
