"""``POST /api/jog`` over real HTTP (issue 18): what is refused, and why, before anything moves;
the viser panel's jog folder, which moves nothing for a websocket client without the API token.
The jog that moves the neck is in tests/test_console_browser.py (a real stack)."""

from __future__ import annotations

import json
import math
import threading
import time
from typing import Any

import httpx
import msgspec
import pytest
import viser
import zstandard
from busutil import bridge_state, controller_status, repeating, two_controllers
from server_harness import AUTH, TOKEN, running_server, wait_until
from websockets.sync.client import connect

from bridge import bus
from bridge.session import liveliness_token, open_session, publisher


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    with running_server(tmp_path_factory.mktemp("jog") / "data", viser=False) as (base, app), \
            httpx.Client(base_url=base, timeout=10) as client:
        yield client, app


def test_a_jog_out_of_the_joint_limits_is_refused_with_the_checkers_message(console):
    client, _ = console
    r = client.post("/api/jog", json={"alpha_deg": [0, 75, 0]}, headers=AUTH)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["loc"] == ["body", "alpha_deg"]
    assert "out of the joint limits" in detail["msg"] and "α2 = 75°" in detail["msg"], detail
    r = client.post("/api/jog", json={"alpha_deg": [0, 0]}, headers=AUTH)
    assert r.status_code == 422 and "wrong number of joints" in r.json()["detail"][0]["msg"], r.text
    for bad in (b'{"alpha_deg": []}', b'{"alpha_deg": ["x", 0, 0]}', b'{"alpha": [0, 0, 0]}',
                b'{"alpha_deg": [1e400, 0, 0]}', b'{"alpha_deg": [NaN, 0, 0]}'):
        r = client.post("/api/jog", content=bad, headers={**AUTH, "Content-Type": "application/json"})
        assert r.status_code == 422, (bad, r.text)


def test_a_jog_with_strings_or_bools_for_angles_is_refused_not_coerced(console):
    """Review: the body was not strict, so ``["10", true, 0]`` was taken as [10, 1, 0]° and moved
    the neck. Without a controller service an accepted body gets a 503: a 422 says the body was refused."""
    client, _ = console
    for body, bad_index in (({"alpha_deg": ["10", True, 0]}, 0), ({"alpha_deg": [True, 0, 0]}, 0),
                            ({"alpha_deg": [0, False, 0]}, 1), ({"alpha_deg": [0, "5", 0]}, 1)):
        r = client.post("/api/jog", json=body, headers=AUTH)
        assert r.status_code == 422, (body, r.text)
        detail = r.json()["detail"]
        assert detail[0]["loc"] == ["body", "alpha_deg", bad_index], (body, detail)
        assert detail[0]["msg"] == "Input should be a valid number", (body, detail)
    r = client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}, headers=AUTH)  # ints stay good degrees
    assert r.status_code == 503, r.text


def test_a_jog_needs_the_token_and_a_controller_service(console):
    client, _ = console
    assert client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}).status_code == 401
    r = client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}, headers=AUTH)
    assert r.status_code == 503 and "no controller service" in r.json()["detail"], r.text


def test_a_jog_is_refused_while_the_estop_is_engaged(console):
    client, _ = console
    assert client.post("/api/system/estop", json={"engaged": True, "reason": "test"}, headers=AUTH).status_code == 200
    try:
        r = client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}, headers=AUTH)
        assert r.status_code == 409 and "release the e-stop" in r.json()["detail"] and "test" in r.json()["detail"]
    finally:
        client.post("/api/system/estop", json={"engaged": False, "reason": "test"}, headers=AUTH)
    assert client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}, headers=AUTH).status_code == 503


class ViserPanel:
    """A bare viser websocket client, as any web page the operator visits could open one to
    127.0.0.1: it finds the "Jog (deg)" folder the console builds for it and sets its inputs."""

    def __init__(self, port: int) -> None:
        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],  # pyright: ignore[reportArgumentType]
                          origin="http://evil.example", max_size=None, open_timeout=5)  # pyright: ignore[reportArgumentType]
        self.folders: dict[str, str] = {}  # label -> uuid
        self.inputs: dict[tuple[str, str], str] = {}  # (container uuid, label) -> uuid
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        # A browser's viewer sends its camera first; viser counts the client as connected from then on.
        self._send({"type": "ViewerCameraMessage", "wxyz": [1, 0, 0, 0], "position": [0, 0, 1], "fov": 1.0,
                    "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640, "look_at": [0, 0, 0],
                    "up_direction": [0, 0, 1]})
        assert wait_until(lambda: all(self._uuid(label) for label in ("α1", "API token", "hold here")), 10), \
            (self.folders, self.inputs)

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                raw = self.ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            except Exception:  # noqa: BLE001 - closed
                return
            assert isinstance(raw, bytes)
            n_inner, n_comp = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
            inner = zstandard.ZstdDecompressor().decompress(raw[16:16 + n_comp], max_output_size=n_inner)
            for m in msgspec.msgpack.decode(inner)["messages"]:
                label = (m.get("props") or {}).get("label")
                if label is None:
                    continue
                if m.get("type") == "GuiFolderMessage":
                    self.folders[label] = m["uuid"]
                elif "container_uuid" in m:
                    self.inputs[(m["container_uuid"], label)] = m["uuid"]

    def _uuid(self, label: str) -> str | None:
        folder = self.folders.get("Jog (deg)")
        return self.inputs.get((folder, label)) if folder else None

    def _send(self, message: dict) -> None:
        self.ws.send(msgspec.msgpack.encode(message))

    def set(self, label: str, value: object) -> None:
        self._send({"type": "GuiUpdateMessage", "uuid": self._uuid(label), "updates": {"value": value}})

    def click(self, label: str) -> None:
        self.set(label, True)

    def close(self) -> None:
        self._stop.set()
        self._reader.join(2)
        self.ws.close()


@pytest.fixture(scope="module")
def viser_console(tmp_path_factory):
    """A console with its viser panel and a stand-in controller service (its liveliness token and
    a status at 50 Hz), and every CampaignRequest the console publishes on the bus."""
    with running_server(tmp_path_factory.mktemp("jog-viser") / "data", viser=True) as (_base, app_):
        app: Any = app_
        session = open_session(connect=[app.state.hub])
        requests: list[bus.CampaignRequest] = []
        # The console addresses its requests to the one service on the bus (server/service_choice.py).
        sub = session.declare_subscriber(bus.campaign_request_key("stand-in"), lambda s: requests.append(
            bus.decode(bus.CampaignRequest, s.payload.to_bytes())))
        token = liveliness_token(session, "campaign-service", "stand-in")
        pub = publisher(session, bus.CONTROLLER_STATUS)
        stop = threading.Event()

        def status() -> None:
            seq = 0
            while not stop.is_set():
                seq += 1
                pub.put(bus.ControllerStatus(seq=seq, stamp_s=time.time(), law="law2", tick_s=0.002, compute_s=1e-4,
                                             overruns=0, deadline_misses=0, saturated=[False] * 4,
                                             alpha_hat_rad=[0.0] * 3, alpha_d_rad=[0.0] * 3, e_rad=[0.0] * 3,
                                             holding=True))
                time.sleep(0.02)

        thread = threading.Thread(target=status, daemon=True)
        thread.start()
        try:
            assert wait_until(lambda: app.state.presence.any_alive("campaign-service")
                              and app.state.live.values.fresh("status", 0.5) is not None, 10)
            yield app, requests
        finally:
            stop.set()
            thread.join(2)
            sub.undeclare()
            token.undeclare()
            pub.close()
            session.close()


def test_the_viser_panel_jogs_only_for_a_client_whose_token_field_holds_the_api_token(viser_console):
    # audit of 2026-11-26: any web page could open the viser websocket and move the neck, no token asked.
    app, requests = viser_console
    scene = app.state.scene
    stranger, operator = ViserPanel(scene.port), ViserPanel(scene.port)
    try:
        stranger.set("API token", "guess")
        stranger.set("α1", 15.0)
        time.sleep(1.5)  # several of the scene thread's sends
        assert requests == [], requests
        # the refusal is shown once the scene thread has handled the update (late on a loaded machine)
        texts = lambda: [j.text.content for j in scene.jogs.values()]  # noqa: E731
        assert wait_until(lambda: any("not sent" in t and "token" in t for t in texts()), 10), texts()

        operator.set("API token", TOKEN)
        operator.set("α2", 8.0)
        assert wait_until(lambda: any(r.action == "start" for r in requests), 5), requests
        start = next(r for r in requests if r.action == "start")
        assert start.kind == "jog" and json.loads(start.trajectory_json)["waypoints_deg"] == [[0.0, 8.0, 0.0]]
        # Each client has its own folder: the stranger's α1 never reached the operator's sliders.
        assert sorted(tuple(s.value for s in j.sliders) for j in scene.jogs.values()) == \
            [(0.0, 8.0, 0.0), (15.0, 0.0, 0.0)]

        stranger.click("hold here")
        time.sleep(1.0)
        assert [r.action for r in requests] == ["start"], requests
        operator.click("hold here")
        assert wait_until(lambda: [r.action for r in requests] == ["start", "stop"], 5), requests
        assert requests[1].campaign_id == start.campaign_id
    finally:
        stranger.close()
        operator.close()


def test_a_jog_the_controller_aborts_is_said_cut_short_in_the_viser_panel_that_sent_it(viser_console):
    """Review of session 57: the dashboard's jog panel said a jog the controller had aborted was cut
    short, the viser panel went on showing "→ jog-…". Its status line now says it, with the
    controller's reason as plain text; another client's line is left alone."""
    app, requests = viser_console
    scene = app.state.scene
    operator, other = ViserPanel(scene.port), ViserPanel(scene.port)
    try:
        n = len(requests)
        operator.set("API token", TOKEN)
        operator.set("α3", -6.0)
        assert wait_until(lambda: any(r.action == "start" for r in requests[n:]), 10), requests[n:]
        jog_id = next(r for r in requests[n:] if r.action == "start").campaign_id
        mine = lambda: [j for j in scene.jogs.values() if jog_id in j.text.content]  # noqa: E731
        assert wait_until(lambda: len(mine()) == 1, 10), [j.text.content for j in scene.jogs.values()]
        others = [j.text.content for j in scene.jogs.values() if j is not mine()[0]]
        with open_session(connect=[app.state.hub]) as peer:
            peer.put(bus.CAMPAIGN_EVENTS, bus.encode(bus.CampaignEvent(
                seq=1, stamp_s=time.time(), campaign_id=jog_id, kind="jog", event="aborted",
                message="drives disabled: e-stop [x](javascript:1) <b>here</b>")))
            assert wait_until(lambda: "cut short" in mine()[0].text.content, 10), mine()[0].text.content
        line = mine()[0].text.content
        assert line == (f"→ {jog_id} **cut short**: aborted by the controller: drives disabled: e-stop "
                        r"\[x\]\(javascript:1\) &lt;b&gt;here&lt;/b&gt;"), line
        assert [j.text.content for j in scene.jogs.values() if j is not mine()[0]] == others
    finally:
        operator.close()
        other.close()


PAYLOAD = ("<iframe srcdoc=\"<script>p=parent;p.__pwned=1</script>\"></iframe> "
           "[token](javascript:alert(1)) ![x](http://evil.example/x.png) **bold** `code` &amp;")


def test_a_refusal_reason_from_the_bus_reaches_the_viser_panel_as_plain_text():
    """Audit of 2026-11-26: an e-stop reason published by any peer on the bus came back in the jog's
    409 and viser rendered it as HTML: an ``<iframe srcdoc>`` ran script beside the token field and
    read the API token. The status line escapes HTML and every markdown mark."""
    from server.scene import jog_status_markdown, plain_markdown

    line = jog_status_markdown(409, {"detail": f"drives disabled: e-stop ({PAYLOAD})"})
    assert line.startswith("**refused (409)**: ")
    body = line.removeprefix("**refused (409)**: ")
    assert "<" not in body and ">" not in body  # no tag at all
    for mark in "[]()!*`":
        assert all(body[i - 1] == "\\" for i, ch in enumerate(body) if ch == mark), (mark, body)
    assert "&amp;amp;" in body  # an entity in the text is shown as typed, not decoded
    assert plain_markdown("α1 = 15.0°") == "α1 = 15.0°"
    assert plain_markdown("a\n# heading\n- item") == "a # heading - item"  # one line: no block marks
    detail_list = jog_status_markdown(422, {"detail": [{"msg": "<b>x</b>"}, "y"]})
    assert "<b>" not in detail_list and "&lt;b&gt;x&lt;/b&gt;; y" in detail_list
    assert jog_status_markdown(202, {"jog_id": "jog-1"}) == "→ jog-1"


def test_a_jog_starts_from_the_alpha_hat_of_the_controller_the_bridge_obeys(console):
    """Session 40's review: the jog took α̂ from the newest status of any controller. A second
    controller on the bus (started by hand with another parameter set, or one whose encoders
    were zeroed elsewhere) answering after the bridge's owner set the start of the move, and of
    its check, to a pose the neck is not in. The jog now reads the status of the service it sends
    the jog to (the one the bridge obeys)."""
    client, app = console
    owner = controller_status(alpha_hat_rad=(math.radians(2.0), 0.0, 0.0))
    other = controller_status(alpha_hat_rad=(math.radians(25.0), 0.0, 0.0))
    with open_session(listen=["tcp/127.0.0.1:0"], connect=[app.state.hub]) as peer:
        tokens = [liveliness_token(peer, "campaign-service", name) for name in ("ctl-owner", "ctl-other")]
        try:
            with two_controllers(peer, bridge_state("ctl-owner"), owner, other):  # the owner answers first
                def jog() -> httpx.Response:
                    return client.post("/api/jog", json={"alpha_deg": [4, 0, 0]}, headers=AUTH)

                assert wait_until(lambda: jog().status_code not in (503, 429), 20, 0.6)
                time.sleep(0.2)  # the route allows one jog per JOG_MIN_INTERVAL_S (0.1 s)
                r = jog()
        finally:
            for token in tokens:
                token.undeclare()
        assert r.status_code == 202, r.text
        assert r.json()["from_deg"][0] == pytest.approx(2.0, abs=1e-6), r.json()


def _requests_seen(peer) -> list[tuple[str, str, str]]:
    """(key, campaign id, action) of every campaign request ``peer`` hears, bare or addressed."""
    seen: list[tuple[str, str, str]] = []

    def on_request(sample) -> None:
        req = bus.decode(bus.CampaignRequest, sample.payload.to_bytes())
        seen.append((str(sample.key_expr), req.campaign_id, req.action))

    peer.declare_subscriber(f"{bus.CAMPAIGN_REQUEST}/**", on_request)
    peer.declare_subscriber(bus.CAMPAIGN_REQUEST, on_request)
    return seen


def test_a_jog_stop_goes_to_each_controller_running_a_jog(console):
    """Review of session 41: the stop of a jog another controller runs (another console's) went
    to the key of this console's last jog's controller, which it does not read."""
    client, app = console
    with open_session(listen=["tcp/127.0.0.1:0"], connect=[app.state.hub]) as peer:
        seen = _requests_seen(peer)
        tokens = [liveliness_token(peer, "campaign-service", name) for name in ("ctl-owner", "ctl-other")]
        try:  # the owner idle, the other one running a jog of its own
            with two_controllers(peer, bridge_state("ctl-owner"), controller_status(),
                                 controller_status("jog-120000-9")):
                assert wait_until(lambda: client.post("/api/jog", json={"alpha_deg": [3, 0, 0]},
                                                      headers=AUTH).status_code == 202, 20, 0.3)
                r = client.post("/api/jog/stop", headers=AUTH)
                assert r.status_code == 200 and "jog-120000-9" in r.json()["stopped"], r.text
                assert wait_until(lambda: any(a == "stop" and c == "jog-120000-9" for _, c, a in seen), 5)
        finally:
            for token in tokens:
                token.undeclare()
        stops = {(key.rsplit("/", 1)[-1], cid) for key, cid, action in seen if action == "stop"}
        assert ("ctl-other", "jog-120000-9") in stops, seen
        mine = [cid for key, cid, action in seen if action == "start"]
        assert mine and (("ctl-owner", mine[-1]) in stops), seen  # this console's own jog: to its controller


def test_a_controller_status_naming_no_instance_does_not_stop_the_jog_stops(console):
    """Review of the fix: a peer's status whose controller name is no instance name ("forged
    name") made the stop raise before the next controller's stop, and every later stop sent
    nothing. Its stop goes to the bare key; the others to their controllers."""
    from bridge.session import controller_attachment

    client, app = console
    with open_session(listen=["tcp/127.0.0.1:0"], connect=[app.state.hub]) as peer:
        seen = _requests_seen(peer)
        forged = controller_status("jog-120000-6")

        def forger() -> None:
            peer.put(bus.CONTROLLER_STATUS, forged, attachment=controller_attachment("forged name"))

        with two_controllers(peer, bridge_state("ctl-owner"), controller_status(), controller_status("jog-120000-9")), \
                repeating(forger, 0.01):
            assert wait_until(lambda: {"jog-120000-6", "jog-120000-9"} <= set(
                client.post("/api/jog/stop", headers=AUTH).json()["stopped"]), 20, 0.3)
            assert wait_until(lambda: {("xneck/campaign/request", "jog-120000-6"),
                                       ("xneck/campaign/request/ctl-other", "jog-120000-9")}
                              <= {(k, c) for k, c, a in seen if a == "stop"}, 5), seen


def test_a_jog_the_controller_aborts_says_why_in_the_jogs_state(console):
    """CI of 8b61d5c: a starved controller's jog ended with the neck at 5° of 15°; ``GET /api/jog``
    and the health's ``jog`` (the panel's source) went on as if the neck were moving there. The
    jog's ``aborted`` event on the bus now ends it with the controller's reason; a malformed event
    is ignored."""
    client, app = console
    reason = "the law re-started 6 times in 10 s: it advanced 0.3 s of its trajectory meanwhile"
    with open_session(listen=["tcp/127.0.0.1:0"], connect=[app.state.hub]) as peer:
        token = liveliness_token(peer, "campaign-service", "ctl-owner")
        try:
            with two_controllers(peer, bridge_state("ctl-owner"), controller_status(), controller_status()):
                answers: list[httpx.Response] = []
                assert wait_until(lambda: answers.append(client.post("/api/jog", json={"alpha_deg": [6, 0, 0]},
                                                                     headers=AUTH)) or answers[-1].status_code == 202, 20, 0.3)
                jog_id = answers[-1].json()["jog_id"]
                assert client.get("/api/jog").json()["jog"]["ended"] is None
                peer.put(bus.CAMPAIGN_EVENTS, b'{"v": 2, "campaign_id": "' + jog_id.encode() + b'", "event": "aborted"')
                peer.put(bus.CAMPAIGN_EVENTS, bus.encode(bus.CampaignEvent(
                    seq=1, stamp_s=1.0, campaign_id=jog_id, kind="jog", event="aborted", message=reason)))
                assert wait_until(lambda: client.get("/api/jog").json()["jog"]["ended"] is not None, 10, 0.1)
                health = client.get("/api/system/health").json()["jog"]
        finally:
            token.undeclare()
    assert health["jog_id"] == jog_id and health["ended"] == f"aborted by the controller: {reason}", health
