"""A jog cut short by a death of the controller (or the bridge) says so itself (review of session 46).

Before, only the dashboard's header said the death (server.process_faults); the jog's own state,
``GET /api/jog`` and ``jog`` in the health (which the jog panel reads), said nothing, and the
panel went on showing the move as under way. Pure functions and the routes on an app without a bus.
"""

from __future__ import annotations

import asyncio
import time

import httpx

from server.routes_jog import JOG_END_MARGIN_S, JogDesk, cuts_jog, under_way

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
