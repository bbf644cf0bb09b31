"""Replays hold the robot as campaigns do (audit of 2026-11-26): over real HTTP, two replays, or a
replay and a campaign, started at the same moment: exactly one is accepted, the other gets 409 with
the reason, and after stop and e-stop nothing keeps publishing recorded states on the bus."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
from server_harness import AUTH, running_server, wait_until

from bridge import bus
from bridge.archive import write_campaign
from bridge.session import open_session, publisher
from server.records import CampaignIndex, CampaignRecord

TICKS = 30_000  # 60 s at 500 Hz: reading the archive takes a good fraction of a second, the window of the race


def _seed(data: Path, cid: str = "run-a") -> str:
    """A finished control run in the console's data directory, as a campaign leaves it."""
    index = CampaignIndex(data / "campaigns")
    index.dir.mkdir(parents=True, exist_ok=True)
    msgs = []
    for k in range(TICKS):
        t = 10.0 + k / 500
        ns = int(t * 1e9)
        msgs.append((bus.MOTOR_STATE, ns, bus.MotorState(seq=k, stamp_s=t, theta_rad=[0.0] * 4,
                                                          force_applied_N=[5.0, 6.0, 7.0, 8.0], drive="active",
                                                          epoch="e", bridge="b")))
        msgs.append((bus.CONTROLLER_STATUS, ns + 1, bus.ControllerStatus(
            seq=k, stamp_s=t, law="law2", tick_s=0.002, compute_s=0.001, overruns=0, deadline_misses=0,
            saturated=[False] * 4, alpha_hat_rad=[0.0] * 3, alpha_d_rad=[0.0] * 3, e_rad=[0.0] * 3, holding=False,
            campaign_id=cid, ticks=k)))
    write_campaign(index.mcap(cid), msgs, {"campaign_id": cid, "kind": "control", "law": "law2"})
    index.save(CampaignRecord(id=cid, kind="control", law="law2", trajectory="control_test",
                              parameter_set="prototype_3x", target="twin", status="finished",
                              created_at="2026-11-26T10:00:00"))
    return cid


def _together(*calls: Callable[[], httpx.Response]) -> list[httpx.Response]:
    barrier = threading.Barrier(len(calls))
    out: list[httpx.Response | None] = [None] * len(calls)

    def run(i: int, call: Callable[[], httpx.Response]) -> None:
        barrier.wait()
        out[i] = call()

    threads = [threading.Thread(target=run, args=(i, c)) for i, c in enumerate(calls)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert all(r is not None for r in out)
    return out  # pyright: ignore[reportReturnType] - checked above


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    data = tmp_path_factory.mktemp("replay") / "data"
    cid = _seed(data)
    _seed(data, "damaged")
    with running_server(data, viser=False) as (base, app_), \
            httpx.Client(base_url=base, timeout=60) as a, httpx.Client(base_url=base, timeout=60) as b:
        app: Any = app_
        session = open_session(connect=[app.state.hub])
        states: list[float] = []
        sub = session.declare_subscriber(bus.MOTOR_STATE, lambda _s: states.append(time.monotonic()))
        try:
            yield a, b, cid, states, data
        finally:
            sub.undeclare()
            session.close()


def _idle(client: httpx.Client) -> bool:
    h = client.get("/api/system/health").json()
    return h["running_campaign_id"] is None and not (h["replay"] or {}).get("running")


def test_two_replays_at_once_one_is_refused_and_stop_and_estop_silence_the_bus(console) -> None:
    a, b, cid, states, _data = console
    first, second = _together(lambda: a.post(f"/api/campaigns/{cid}/replay", json={"speed": 1.0}, headers=AUTH),
                              lambda: b.post(f"/api/campaigns/{cid}/replay", json={"speed": 1.0}, headers=AUTH))
    codes = sorted((first.status_code, second.status_code))
    assert codes == [200, 409], (first.text, second.text)
    refused = first if first.status_code == 409 else second
    assert f"replay of {cid}" in refused.json()["detail"], refused.text
    assert refused.json()["replay"] == cid and refused.json()["running_campaign_id"] is None, refused.text
    assert wait_until(lambda: len(states) > 50, 10), "the accepted replay published nothing"
    assert a.post(f"/api/campaigns/{cid}/stop", headers=AUTH).status_code == 200
    assert a.post("/api/system/estop", json={"engaged": True, "reason": "test"}, headers=AUTH).status_code == 200
    try:
        assert wait_until(lambda: _idle(a), 10)
        # Messages in flight land first (a fixed 0.5 s was short on a loaded machine): 0.5 s with
        # none, within 10 s, and then none for 2 s more.
        assert wait_until(lambda: not [t for t in states if t > time.monotonic() - 0.5], 10), \
            "the replay went on publishing after stop and e-stop"
        quiet_from = time.monotonic()
        time.sleep(2.0)
        assert [t for t in states if t > quiet_from] == [], "recorded MotorStates published after stop and e-stop"
        assert _idle(a)
    finally:
        a.post("/api/system/estop", json={"engaged": False, "reason": ""}, headers=AUTH)


def test_a_409_for_a_replay_says_it_is_a_replay_not_a_running_campaign() -> None:
    """User audit: a campaign asked for during a replay got a 409 whose ``running_campaign_id``
    was the replayed archive's campaign, which ended long ago (the health said none ran). The 409
    names the replay in ``replay`` and says so in ``detail``; ``running_campaign_id`` is null, as
    in the health; a campaign's 409 and the e-stop's have ``replay`` null."""
    import json

    from server.campaigns import Busy, DrivesDisabled
    from server.routes_campaigns import _conflict

    def body(exc: Busy | DrivesDisabled) -> dict[str, Any]:
        r = _conflict(exc)
        assert r.status_code == 409
        return json.loads(bytes(r.body))

    replay = body(Busy("control-1", "replay of"))
    assert replay["replay"] == "control-1" and replay["running_campaign_id"] is None and replay["estop"] is False
    assert replay["detail"].startswith("a replay of control-1 is running") and "/api/campaigns/control-1/stop" in \
        replay["detail"], replay
    campaign = body(Busy("control-2"))
    assert campaign == {"detail": "campaign control-2 is running", "running_campaign_id": "control-2", "estop": False,
                        "replay": None}
    assert body(DrivesDisabled("x"))["replay"] is None


def test_a_replay_and_a_campaign_at_once_only_one_holds_the_robot(console) -> None:
    a, b, cid, _states, _data = console
    body = {"kind": "control", "waypoints": {"waypoints_deg": [[0, 0, 0], [5, 0, 0], [0, 0, 0]], "durations_s": 3}}
    replay, campaign = _together(lambda: a.post(f"/api/campaigns/{cid}/replay", json={"speed": 1.0}, headers=AUTH),
                                 lambda: b.post("/api/campaigns", json=body, headers=AUTH))
    try:
        assert sorted((replay.status_code, campaign.status_code)) in ([200, 409], [201, 409]), \
            (replay.status_code, replay.text, campaign.status_code, campaign.text)
        refused = replay if replay.status_code == 409 else campaign
        assert " is running" in refused.json()["detail"], refused.text
    finally:
        if campaign.status_code == 201:
            a.post(f"/api/campaigns/{campaign.json()['id']}/stop", headers=AUTH)
        a.post(f"/api/campaigns/{cid}/stop", headers=AUTH)
        assert wait_until(lambda: _idle(a), 60, 0.5)


def test_a_replay_whose_archive_does_not_read_leaves_the_robot_free(console) -> None:
    a, _b, cid, _states, data = console
    mcap = CampaignIndex(data / "campaigns").mcap("damaged")
    mcap.write_bytes(mcap.read_bytes()[:4096])  # cut short after start-up (which would have recovered it)
    r = a.post("/api/campaigns/damaged/replay", json={"speed": 1.0}, headers=AUTH)
    assert r.status_code == 422 and "cannot replay" in r.json()["detail"], r.text
    assert _idle(a)
    r = a.post(f"/api/campaigns/{cid}/replay", json={"speed": 4.0}, headers=AUTH)  # the claim was released
    assert r.status_code == 200, r.text
    a.post(f"/api/campaigns/{cid}/stop", headers=AUTH)
    assert wait_until(lambda: _idle(a), 10, 0.2)


def test_a_replay_never_republishes_a_campaign_request(tmp_path: Path) -> None:
    """Audit of 2026-11-27: the recorder archives every key, the campaign request the console sent
    a controller service (``xneck up``) included; a replay published it again and the service
    started the campaign anew, moving the robot. Requests, like commands and e-stops, stay in the
    archive."""
    from controller.trajectory import control_test_trajectory
    from server.replay import Replay

    request = bus.CampaignRequest(seq=1, stamp_s=10.0, campaign_id="run-r", action="start", kind="control", law=2,
                                  trajectory_json=control_test_trajectory().to_json())
    state = bus.MotorState(seq=0, stamp_s=10.0, theta_rad=[0.0] * 4, force_applied_N=[5.0] * 4, drive="active",
                           epoch="e", bridge="b")
    path = write_campaign(tmp_path / "run-r.mcap", [(bus.CAMPAIGN_REQUEST, 10**18, request),
                                                   (bus.MOTOR_STATE, 10**18 + 1, state)], {"campaign_id": "run-r"})
    with open_session(listen=["tcp/127.0.0.1:0"], connect=[]) as session:
        replay = Replay(session, "run-r", path)
        assert replay.total == 1
        assert [key for _, key, _ in replay._messages] == [bus.MOTOR_STATE]


def test_a_replay_never_stands_for_the_bridge_whose_estop_is_engaged(console) -> None:
    """Audit of 2026-11-28: with the bridge's e-stop engaged, a replay's recorded states (drive
    active, no e-stop) on the live key made the console, and so the dashboard, show the e-stop
    released and the drives active about a third of the time. Replayed messages carry the
    REPLAYED attachment, and the bridge's word is never taken from them."""
    a, _b, cid, _states, _data = console
    stop = threading.Event()
    session = open_session(connect=[a.get("/api/system/health").json()["hub"]])

    def bridge() -> None:  # a bridge with its e-stop engaged, at the control rate
        pub = publisher(session, bus.MOTOR_STATE)
        k = 0
        while not stop.is_set():
            k += 1
            pub.put(bus.MotorState(seq=k, stamp_s=time.time(), theta_rad=[0.0] * 4, force_applied_N=[0.0] * 4,
                                   drive="disabled", epoch="live", bridge="live-bridge", estop_engaged=True,
                                   estop_reason="the live bridge"))
            time.sleep(0.002)
        pub.close()

    thread = threading.Thread(target=bridge, daemon=True)
    thread.start()
    try:
        assert wait_until(lambda: a.get("/api/system/health").json()["estop"].get("engaged") is True, 10)
        r = a.post(f"/api/campaigns/{cid}/replay", json={"speed": 1.0}, headers=AUTH)
        assert r.status_code == 200, r.text
        seen = []
        for _ in range(30):
            seen.append(a.get("/api/system/health").json()["estop"])
            time.sleep(0.1)
        assert all(e.get("engaged") is True and e.get("source") == "bridge" for e in seen), \
            [e for e in seen if not e.get("engaged")][:3]
    finally:
        a.post(f"/api/campaigns/{cid}/stop", headers=AUTH)
        stop.set()
        thread.join(5)
        session.close()
        assert wait_until(lambda: _idle(a), 20)


def test_the_bridges_state_is_its_newest_live_one_even_behind_replayed_ones(sessions) -> None:
    """Fresh-clone CI of session 39: during a replay, /api/system/health once showed the console's
    own e-stop (the bridge's word lost): the live state's ring held one sample, and whenever a
    replayed state was the newest when it was read, no live state was taken; a run of such reads
    made the bridge's state look stale. The newest live state is taken from behind replayed ones."""
    from bridge.session import REPLAYED
    from server.live import LiveBus

    a, b = sessions
    live = LiveBus(b)
    try:
        def state(k: int, epoch: str) -> bytes:
            return bus.encode(bus.MotorState(seq=k, stamp_s=float(k), theta_rad=[0.0] * 4, force_applied_N=[0.0] * 4,
                                             drive="disabled", epoch=epoch, bridge=epoch, estop_engaged=epoch == "live"))

        for k in range(1, 20):  # every read finds replayed states newest, the live one just behind
            a.put(bus.MOTOR_STATE, state(k, "live"))
            for j in range(3):
                a.put(bus.MOTOR_STATE, state(100 * k + j, "replay"), attachment=REPLAYED)
            time.sleep(0.02)
        assert wait_until(lambda: (live.values.latest_valid("state") or (0, None))[1] is not None, 5, 0.05)
        got = live.values.latest_valid("state")
        assert got is not None and got[1].epoch == "live" and got[1].seq >= 10, got
    finally:
        live.close()
