"""A whole control campaign through the REST API of a real server (uvicorn on 127.0.0.1, lockstep
twin and controller processes), followed on the live WebSocket, its MCAP downloaded and every
channel read back; one campaign at a time; replay onto the bus shows on the live endpoint."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import pytest
from server_harness import AUTH, LiveSocket, running_server, start_campaign, wait_until
from websockets.sync.client import connect

from bridge import bus
from bridge.archive_read import read_campaign
from bridge.session import publisher
from server.foxglove_scene import SCENE_TOPIC, SCHEMA_NAME


class LiveFollower(LiveSocket):
    """Keeps what the test checks of the live frames."""

    def __init__(self, base: str) -> None:
        self.frames = 0
        self.status_stamps: list[float] = []
        self.forces: list[list[float]] = []
        self.campaign_events: list[dict] = []
        super().__init__(base)

    def on_frame(self, frame: dict) -> None:
        self.frames += 1
        s = frame["series"]
        if "status" in s:
            self.status_stamps.append(s["status"]["stamp_s"])
        if "state" in s:
            self.forces.append(s["state"]["force_applied_N"])
        if "campaign" in s:
            self.campaign_events.append(s["campaign"])


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    with (running_server(tmp_path_factory.mktemp("console")) as (base, app),
          httpx.Client(base_url=base, timeout=30) as client):
        yield base, client, app


def test_control_campaign_end_to_end(console, tmp_path: Path) -> None:
    base, client, app = console
    live = LiveFollower(base)
    try:
        r = client.post("/api/campaigns", json={"kind": "control", "law": 2, "trajectory": "control_test",
                                                "pace": "lockstep"}, headers=AUTH)
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        assert r.json()["status"] == "running"

        # One campaign at a time: a second start gets 409 naming the running one; it cannot be deleted.
        second = client.post("/api/campaigns", json={"kind": "control"}, headers=AUTH)
        assert second.status_code == 409 and second.json()["running_campaign_id"] == cid
        assert second.json()["estop"] is False
        assert client.delete(f"/api/campaigns/{cid}", headers=AUTH).status_code == 409
        assert client.get(f"/api/campaigns/{cid}/mcap").status_code == 409

        progress = []

        def done() -> bool:
            rec = client.get(f"/api/campaigns/{cid}").json()
            progress.append(rec["progress"])
            return rec["status"] != "running"

        assert wait_until(done, 120, 0.25), "campaign did not end within 120 s"
        rec = client.get(f"/api/campaigns/{cid}").json()
        assert rec["status"] == "finished", rec["message"]
        assert rec["progress"] == 1.0 and any(0 < p < 1 for p in progress)
        assert rec["metrics"]["ticks"] > 6000 and rec["scene_messages"] > 10
    finally:
        live.close()

    # The live endpoint carried the campaign: many frames, increasing simulated time, 4 forces.
    assert live.frames > 30, live.frames
    assert len(live.status_stamps) > 30 and live.status_stamps[-1] > 10.0
    assert all(len(f) == 4 for f in live.forces)
    assert any(e["campaign_id"] == cid for e in live.campaign_events)

    # Listing with filters, results tables shaped like Table 3, figures.
    listed = client.get("/api/campaigns", params={"status": "finished", "kind": "control"}).json()
    assert cid in [c["id"] for c in listed]
    assert client.get("/api/campaigns", params={"kind": "identification"}).json() == []
    res = client.get(f"/api/campaigns/{cid}/results").json()
    titles = [t["title"] for t in res["tables"]]
    assert titles[0].startswith("Table 3") and res["tables"][0]["rows"][0][0] == "law2"
    assert res["metrics"]["e_mean_all_deg"] < 1.0
    for url in res["figures"]:
        fig = client.get(url)
        assert fig.status_code == 200 and fig.content[:8] == b"\x89PNG\r\n\x1a\n"

    # The MCAP download: every bus channel plus the Foxglove scene, all readable.
    mcap = client.get(f"/api/campaigns/{cid}/mcap")
    assert mcap.status_code == 200
    path = tmp_path / "download.mcap"
    path.write_bytes(mcap.content)
    campaign = read_campaign(path)
    assert campaign.info["outcome"] == "finished" and campaign.info["campaign_id"] == cid
    # What the request resolved to is what REST and the archive both say (issue 14, finding 6).
    info = campaign.info
    assert (info["target"], info["pace"], info["twin_truth"], info["seed"], info["law"], info["parameter_set"]) == \
        (rec["target"], rec["pace"], rec["truth"], str(rec["seed"]), rec["law"], rec["parameter_set"]) == \
        ("twin", "lockstep", "model", "0", "law2", "prototype_3x")
    for key in (bus.MOTOR_STATE, bus.MOTOR_COMMAND, bus.CAMERA_ALPHA, bus.TWIN_TRUTH, bus.CONTROLLER_STATUS,
                bus.CAMPAIGN_EVENTS):
        assert campaign.messages(key), key
        msg_type = bus.message_type(key)
        assert msg_type is not None and campaign.schemas[bus.mcap_topic(key)] == bus.schema_name(msg_type)
    assert campaign.schemas[SCENE_TOPIC] == SCHEMA_NAME
    update = campaign.topics[SCENE_TOPIC][0][1]
    entity = update["entities"][0]
    assert entity["frame_id"] == "base" and len(entity["lines"]) >= 7  # bars, springs, pulleys, 4 cables
    for topic, msgs in campaign.topics.items():
        assert msgs, topic

    # Replay onto the bus: the live endpoint shows it as if it were live.
    live = LiveFollower(base)
    try:
        r = client.post(f"/api/campaigns/{cid}/replay", json={"speed": 4.0}, headers=AUTH)
        assert r.status_code == 200, r.text
        assert wait_until(lambda: len(live.status_stamps) > 10, 15)
        assert client.post(f"/api/campaigns/{cid}/replay", json={}, headers=AUTH).status_code == 409
        client.post(f"/api/campaigns/{cid}/stop", headers=AUTH)
        assert wait_until(lambda: not client.get("/api/system/health").json()["replay"]["running"], 5)
    finally:
        live.close()

    # Delete: gone from the list and from disk.
    assert client.delete(f"/api/campaigns/{cid}", headers=AUTH).status_code == 204
    assert client.get(f"/api/campaigns/{cid}").status_code == 404
    assert not list(Path(app.state.settings.data_dir).glob(f"campaigns/{cid}*"))


def test_a_stalled_live_client_does_not_hold_frames_back(console) -> None:
    """A WebSocket client that never reads keeps a bounded queue; another client still gets frames."""
    base, _client, app = console
    broadcaster = app.state.broadcaster
    # never read; so its close handshake never completes either: dropped after 1 s, not websockets'
    # default 10 s of waiting for the console's close frame behind the unread ones (after the checks)
    stalled = connect(base.replace("http", "ws") + "/api/live", open_timeout=5, close_timeout=1)
    try:
        values = app.state.live.values
        for i in range(200):  # simulate bus traffic directly: the broadcaster sends only on change
            values.put("estop", bus.EStop(seq=i, stamp_s=float(i), engaged=False, reason=f"t{i}"))
            time.sleep(0.005)
        live = LiveFollower(base)
        try:
            for i in range(200, 260):
                values.put("estop", bus.EStop(seq=i, stamp_s=float(i), engaged=False, reason=f"t{i}"))
                time.sleep(0.01)
            assert wait_until(lambda: live.frames > 5, 5)
        finally:
            live.close()
        assert all(c.queue.qsize() <= c.queue.maxsize for c in broadcaster.clients)
    finally:
        stalled.close()


def test_a_stop_stops_a_campaign_whose_events_come_faster_than_the_runner_polls(console) -> None:
    """A lockstep twin runs faster than real time: its progress events (one per 0.5 s of campaign
    time) came every 0.2 s on the 2-CPU test machine and faster on a quicker one. The runner
    looked at the stop (and its deadline) only when no event had come for 0.2 s, so a stop asked
    while events kept coming was never seen: the campaign ran to its end (audit of 2026-11-27).
    Here the events of a fast machine are added to the campaign's own: the stop still stops it."""
    _base, client, app = console
    cid = start_campaign(client, {"kind": "control", "law": 2, "waypoints": {
        "name": "long", "waypoints_deg": [[0, 0, 0], [5, 5, 5], [0, 0, 0], [5, 5, 5], [0, 0, 0]],
        "durations_s": 10.0, "dwell_s": 0.2}}, progress=0.01)
    flooding = threading.Event()
    events = publisher(app.state.session, bus.CAMPAIGN_EVENTS)

    def flood() -> None:
        seq = 0
        while not flooding.is_set():
            seq += 1
            events.put(bus.CampaignEvent(seq=seq, stamp_s=time.time(), campaign_id=cid, kind="control",
                                         event="progress", progress=0.01))
            time.sleep(0.05)

    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    try:
        time.sleep(0.5)
        assert client.post(f"/api/campaigns/{cid}/stop", headers=AUTH).status_code == 200
        stopped = wait_until(lambda: client.get(f"/api/campaigns/{cid}").json()["status"] != "running", 10, 0.2)
    finally:
        flooding.set()
        flooder.join(2)
        events.close()
        wait_until(lambda: client.get(f"/api/campaigns/{cid}").json()["status"] != "running", 120, 0.5)
    rec = client.get(f"/api/campaigns/{cid}").json()
    assert stopped and rec["status"] == "aborted" and rec["message"] == "stopped by the user", (stopped, rec["status"], rec["message"])
    # its archive is complete: it gets its Foxglove scene as a finished one does (its drawing, in a
    # child process, had been killed by the campaign's own stop: review of session 51)
    assert rec["scene_messages"] > 0, rec


def test_the_console_shows_and_trusts_no_state_or_camera_message_of_another_robots_size() -> None:
    """Any peer may publish: a MotorState with one force too many froze the dashboard's live view
    and a CameraAlpha grading 1 joint of 3 its camera panel (audit of 2026-11-27). The console's
    store rejects them as it does garbage (server.live.receiver_checks), keeping the last valid."""
    from server.live import LatestValues, receiver_checks

    values = LatestValues()
    values.checks = receiver_checks(4, 3)

    def state(forces: list[float], seq: int) -> bytes:
        return bus.encode(bus.MotorState(seq=seq, stamp_s=seq * 0.002, theta_rad=[0.0] * 4, force_applied_N=forces,
                                         drive="active", epoch="e1", bridge="b1"))

    values.put_raw("state", state([10.0] * 4, 1))
    assert values.latest_valid("state")[1].seq == 1
    for bad in ([10.0] * 5, [10.0, -1.0, 10.0, 10.0], [10.0] * 3):  # (NaN does not even encode)
        values.put_raw("state", state(bad, 2))
        assert values.get("state") is None
        assert values.latest_valid("state")[1].seq == 1  # the last valid one stands
    assert values.rejected == 3
    values.put_raw("state", state([0.0, 1e6, 5.0, 5.0], 3))  # another set's f_max is not this console's to judge
    assert values.get("state").seq == 3

    def camera(alpha: list[float | None], confidence: list[float]) -> bytes:
        return bus.encode(bus.CameraAlpha(seq=1, stamp_s=0.1, capture_stamp_s=0.1, alpha_ip_rad=alpha,
                                          confidence=confidence, source="peer"))

    values.put_raw("camera", camera([0.1, 0.2, 0.3], [0.5]))
    assert values.get("camera") is None
    values.put_raw("camera", camera([0.1, None, 0.3], [0.5, 0.0, 0.9]))
    assert values.get("camera").alpha_ip_rad == [0.1, None, 0.3]


def test_the_truth_shown_stays_the_runs_when_no_command_names_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """CI of session 42: with a second twin on the hub, once the campaign's commands stopped the
    truth followed the newest state's run, any bridge's, and flipped between the two twins; the run
    shown stays while its truth comes, and is left once it falls silent."""
    from types import SimpleNamespace

    import zenoh

    from bridge.session import run_attachment
    from server import live

    monkeypatch.setattr(live, "RUN_FOLLOW_MAX_AGE_S", 1.0)  # 0.2 s: a loaded machine stalls that long
    ring: list = []
    values = live.LatestValues()
    values.add_source("truth", lambda: ring.pop(0) if ring else None, by_run=True)

    def truth(run: str, stamp_s: float) -> SimpleNamespace:
        msg = bus.Truth(seq=1, stamp_s=stamp_s, alpha_rad=[0.0] * 3, alpha_dot_rad_s=[0.0] * 3, theta_rad=[0.0] * 4,
                        theta_dot_rad_s=[0.0] * 4, tension_N=[1.0] * 4, elongation_m=[0.0] * 4, slack=[False] * 4,
                        near_singular=False)
        return SimpleNamespace(payload=zenoh.ZBytes(bus.encode(msg)), attachment=zenoh.ZBytes(run_attachment(run)))

    def state(run: str) -> None:
        values.put("state", bus.MotorState(seq=1, stamp_s=1.0, theta_rad=[0.0] * 4,
                                                force_applied_N=[0.0] * 4, drive="active", epoch=run,
                                                bridge=f"b-{run}"))

    state("campaign")
    ring[:] = [truth("campaign", 4.0), truth("stray", 0.6)]
    assert values.get("truth").stamp_s == 4.0
    for k in range(5):  # the stray's state is the newest now and then; the campaign's truth keeps coming
        state("stray" if k % 2 == 0 else "campaign")
        ring[:] = [truth("stray", 0.7 + k), truth("campaign", 4.1 + k)]
        assert values.get("truth").stamp_s == 4.1 + k, k
    time.sleep(1.1)  # the campaign's twin gone silent: the stray's is the one left
    state("stray")
    ring[:] = [truth("stray", 9.0)]
    assert values.get("truth").stamp_s == 9.0


def test_the_twins_own_camera_shown_stays_the_runs_the_truth_shows(monkeypatch: pytest.MonkeyPatch) -> None:
    """Follow-up of session 42: the stack's own camera (a twin's, preferred) was picked by the
    newest state's run, so with a second twin on the hub it flipped between the two twins' α_IP
    once the campaign's commands stopped, while the truth beside it stayed; it follows the truth's run."""
    from types import SimpleNamespace

    import zenoh

    from bridge.session import run_attachment
    from server import live
    from server.quality import TWIN_CAMERA

    monkeypatch.setattr(live, "RUN_FOLLOW_MAX_AGE_S", 1.0)  # 0.2 s: a loaded machine stalls that long
    truths: list = []
    alphas: list = []
    values = live.LatestValues()
    values.add_source("truth", lambda: truths.pop(0) if truths else None, by_run=True)
    values.add_source("camera", lambda: alphas.pop(0) if alphas else None, by_camera=True)
    values.prefer_camera = lambda: (TWIN_CAMERA, live.CHOSEN_STACK)

    def sample(msg: bus.BusMessage, run: str) -> SimpleNamespace:
        return SimpleNamespace(payload=zenoh.ZBytes(bus.encode(msg)), attachment=zenoh.ZBytes(run_attachment(run)))

    def truth(run: str, stamp_s: float) -> SimpleNamespace:
        return sample(bus.Truth(seq=1, stamp_s=stamp_s, alpha_rad=[0.0] * 3, alpha_dot_rad_s=[0.0] * 3,
                                theta_rad=[0.0] * 4, theta_dot_rad_s=[0.0] * 4, tension_N=[1.0] * 4,
                                elongation_m=[0.0] * 4, slack=[False] * 4, near_singular=False), run)

    def alpha(run: str, stamp_s: float) -> SimpleNamespace:
        return sample(bus.CameraAlpha(seq=1, stamp_s=stamp_s, capture_stamp_s=stamp_s, alpha_ip_rad=[0.0] * 3,
                                      source="twin-noise"), run)

    def state(run: str) -> None:
        values.put("state", bus.MotorState(seq=1, stamp_s=1.0, theta_rad=[0.0] * 4, force_applied_N=[0.0] * 4,
                                           drive="active", epoch=run, bridge=f"b-{run}"))

    state("campaign")
    truths[:], alphas[:] = [truth("campaign", 4.0)], [alpha("campaign", 4.0), alpha("stray", 0.6)]
    assert values.get("camera").stamp_s == 4.0
    for k in range(5):  # the stray's state is the newest now and then; the campaign's twin keeps sending
        state("stray" if k % 2 == 0 else "campaign")
        truths[:] = [truth("stray", 0.7 + k), truth("campaign", 4.1 + k)]
        alphas[:] = [alpha("stray", 0.7 + k), alpha("campaign", 4.1 + k)]
        assert values.get("truth").stamp_s == 4.1 + k, k
        assert values.get("camera").stamp_s == 4.1 + k, k
