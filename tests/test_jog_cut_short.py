"""A jog cut short by a death of the controller (or the bridge) says so itself (review of session 46),
and so does one the controller aborted (CI of 8b61d5c).

Before, only the dashboard's header said the death (server.process_faults); the jog's own state,
``GET /api/jog`` and ``jog`` in the health (which the jog panel reads), said nothing, and the
panel went on showing the move as under way. Pure functions and the routes on an app without a bus.
"""

from __future__ import annotations

import asyncio
import time

import httpx

from bridge import bus
from server.routes_jog import JOG_END_MARGIN_S, JogDesk, cuts_jog, stop_jog, under_way

CONTROLLER = "controller process exited (signal SIGKILL), restarting controller in 1 s (1 of 2 within 10 min)"
CAMERA = "camera process exited (code 3), restarting camera in 1 s (1 of 2 within 10 min)"


def test_only_a_death_of_a_process_a_jog_needs_cuts_it() -> None:
    assert cuts_jog(CONTROLLER) and cuts_jog("bridge process exited (signal SIGKILL)")
    assert cuts_jog("controller process hung (its loop silent for 2.1 s), killed")
    assert cuts_jog(f"{CAMERA}; {CONTROLLER}")  # two deaths of one pass
    assert not cuts_jog(CAMERA) and not cuts_jog("xneck up was stopped (SIGINT)")
    assert not cuts_jog("a camera process said: controller process exited")  # the name starts a cause


def test_a_jog_was_under_way_from_its_sending_until_its_move_and_settle_were_over() -> None:
    # sent at 10 s, its move and settle over at 13 s; the console hears of a death at fault_s, the
    # death itself at most died_within_s before
    assert under_way(10.0, 13.0, 12.0, 1.0)
    assert under_way(10.0, 13.0, 14.0, 1.5)  # heard late (a hang takes 2 s to judge): died by 12.5 s
    assert not under_way(10.0, 13.0, 14.0, 0.5)  # died at 13.5 s at the earliest: the move was over
    assert not under_way(10.0, 13.0, 9.0, 1.0)  # heard of before the jog was sent
    assert under_way(10.0, 13.0, 13.0, -1.0)  # a negative window is none


class _Campaigns:
    def abort(self, reason: str, ended_within_s: float | None, stack_stopping: bool = False) -> None:
        return None  # no campaign ran


class _Journal:
    def record(self, event: str, **fields) -> None:
        pass


def _app(desk: JogDesk):
    from fastapi import FastAPI

    from server import routes_jog, routes_system
    from server.process_faults import ProcessFaults

    app = FastAPI()
    app.include_router(routes_system.router)
    app.include_router(routes_jog.router)
    app.state.campaigns, app.state.journal, app.state.process_faults, app.state.token, app.state.jog = (
        _Campaigns(), _Journal(), ProcessFaults(), "tok", desk)
    return app


def test_the_jogs_state_says_the_death_that_cut_it_short_and_not_one_after_it() -> None:
    desk = JogDesk(session=None)
    auth = {"Authorization": "Bearer tok"}

    async def main() -> list[dict]:
        seen = []
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=_app(desk)), base_url="http://t") as c:
            async def told(reason: str, within_s: float = 0.5) -> None:
                r = await c.post("/api/system/abort", json={"reason": reason, "ended_within_s": within_s}, headers=auth)
                assert r.status_code == 200, r.text
                seen.append((await c.get("/api/jog")).json()["jog"])

            seen.append((await c.get("/api/jog")).json()["jog"])  # none yet
            with desk.lock:
                desk.sent("jog-1", [4.0, 0.0, 0.0], 2.0, time.monotonic())
            await told(CAMERA)  # the camera's death does not end a jog
            await told(CONTROLLER)
            await told("bridge process exited (signal SIGKILL)")  # the first cause stays
            with desk.lock:  # a jog whose move and settle were over long before the death
                desk.sent("jog-2", [0.0, 0.0, 0.0], 1.0, time.monotonic() - 1.0 - JOG_END_MARGIN_S - 5.0)
            await told(CONTROLLER)
        return seen

    none, camera, cut, again, over = asyncio.run(main())
    assert none is None
    assert camera["jog_id"] == "jog-1" and camera["ended"] is None, camera
    assert cut["ended"] == CONTROLLER and cut["to_deg"] == [4.0, 0.0, 0.0] and cut["duration_s"] == 2.0, cut
    assert again["ended"] == CONTROLLER
    assert over["jog_id"] == "jog-2" and over["ended"] is None, over


def _aborted(jog_id: str, message: str, kind: str = "jog", event: str = "aborted") -> bus.CampaignEvent:
    return bus.CampaignEvent(seq=1, stamp_s=1.0, campaign_id=jog_id, kind=kind, event=event, message=message)  # pyright: ignore[reportArgumentType]


STALLED = ("the law re-started 7 times in 10 s (the bridge's holds or stale states: the commands come late or "
           "the states stall), each stopping the campaign's clock: it advanced 0.4 s of its trajectory meanwhile")


def test_a_jog_the_controller_aborts_says_why_unless_this_console_stopped_it() -> None:
    """CI of 8b61d5c: a starved controller's jog ended with the neck at 5° of 15° while the jog's
    state (and the panel) went on as if the neck were moving there; a controller's abort (no
    progress, drives off, a latch) is said now."""
    desk = JogDesk(session=None)
    with desk.lock:
        desk.sent("jog-1", [15.0, 0.0, 0.0], 1.3, time.monotonic())
    desk.heard(_aborted("jog-0", "superseded"))  # another jog's end
    desk.heard(_aborted("jog-1", "not a jog", kind="control"))
    desk.heard(_aborted("jog-1", "", event="progress"))
    assert desk.last is not None and desk.last["ended"] == ""
    desk.heard(_aborted("jog-1", STALLED + "\n\x1b[2Jforged line"))
    assert desk.last["ended"].startswith("aborted by the controller: the law re-started 7 times"), desk.last
    assert "\n" not in desk.last["ended"] and "\x1b" not in desk.last["ended"]  # plain text, one line
    first = desk.last["ended"]
    desk.heard(_aborted("jog-1", "drives disabled"))
    assert desk.last["ended"] == first  # the first reason stands
    # stopped from this console ("hold here"): its "stopped by the user" is no cut
    with desk.lock:
        desk.sent("jog-2", [5.0, 0.0, 0.0], 1.0, time.monotonic())

    class _Live:
        def live_statuses(self, _max_age_s: float) -> dict:
            return {}

    class _State:
        jog, live = desk, _Live()

    stop_jog(_State())  # no bus to send the stop on (logged): the desk's state is what is checked
    assert desk.last["stopped"] is True
    desk.heard(_aborted("jog-2", "stopped by the user"))
    assert desk.last["ended"] == ""
