"""The camera in campaign archives and in the console (issue 15): JPEG frames on the bus
(``xneck/camera/frame``), recorded as ``foxglove.CompressedImage``, served to the camera panel,
detection health in ``/api/system/health``, and the panel in Chromium.

Real processes on a loopback Zenoh bus, a real uvicorn console, real MCAP files read back with
the mcap reader, a real browser; the frames are rendered by the twin's camera.
"""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import msgspec
import numpy as np
import pytest
from busutil import bus_pair, wait_until

cv2 = pytest.importorskip("cv2")

from bridge import bus  # noqa: E402
from bridge.archive import IMAGE_TOPIC, CampaignRecorder  # noqa: E402
from bridge.archive_read import read_campaign  # noqa: E402
from bridge.session import open_session, publisher  # noqa: E402
from twin.camera.detect import Detector  # noqa: E402
from twin.camera.frames import FrameDecimator, frame_message  # noqa: E402
from twin.camera.render import Renderer, RenderOptions  # noqa: E402

ARTIFACTS = Path(__file__).resolve().parent.parent / "artifacts"
CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run", "--disable-quic"]


def xneck(*args: str) -> list[str]:
    return [sys.executable, "-m", "server.cli", *args]


@pytest.fixture(scope="module")
def rendered(model, params):
    """One rendered frame at α = (10, -20, 30)° and what the detector finds on it."""
    image = Renderer(model, options=RenderOptions(noise_dn=2.0, blur_px=0.8), seed=3).render(np.radians([10.0, -20.0, 30.0]))
    found = Detector(params.n_joints, params.geometry.L, params.geometry.b).detect(image)
    return image, found


# --- the contract --------------------------------------------------------------------------------


def test_camera_frame_round_trips_and_hostile_frames_are_refused(rendered) -> None:
    image, found = rendered
    msg = frame_message(7, image, found, capture_s=2.0, stamp_s=2.05, source="twin-render")
    assert (msg.width, msg.height, msg.format) == (1280, 720, "jpeg")
    assert len(msg.marker_bar) == 2 * 4 + 4 and msg.marker_bar.count(-1) == 4  # 4 bars + the base plate's 4
    assert bus.decode(bus.CAMERA_FRAME, bus.encode(msg)) == msg
    bus.check_camera_frame(msg)
    assert cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR).shape == (720, 1280, 3)

    def payload(**changes) -> bytes:
        doc = json.loads(bus.encode(msg))
        doc.update(changes)
        return json.dumps(doc).encode()

    too_big = base64.b64encode(b"\xff\xd8\xff" + bytes(bus.FRAME_DATA_MAX_BYTES)).decode()
    for bad in (payload(data=too_big), payload(width=0), payload(format="png"), payload(marker_bar=[5] * 65),
                payload(frame_id="../etc")):
        with pytest.raises(bus.BusDecodeError):
            bus.decode(bus.CAMERA_FRAME, bad)
    for bad in (payload(data=base64.b64encode(b"GIF89a....").decode()), payload(markers_px=[1.0]),
                payload(marker_bar=[0], markers_px=[1281.0, 5.0])):
        with pytest.raises(bus.BusDecodeError):
            bus.check_camera_frame(bus.decode(bus.CAMERA_FRAME, bad))
    # audit of 2026-11-26: the size the JPEG declares is what the browser allocates. A 1 kB bomb
    # declaring 60000×60000 px in a frame that says 1280×720, or a real JPEG of another size.
    sof = msg.data.index(b"\xff\xc0")
    bomb = msg.data[:sof + 5] + (60000).to_bytes(2, "big") * 2 + msg.data[sof + 9:sof + 600]
    small = cv2.imencode(".jpg", image[:240, :320])[1].tobytes()
    for data, reason in ((bomb, "60000×60000 px"), (small, "320×240 px"), (b"\xff\xd8\xff\xd9", "no frame header")):
        with pytest.raises(bus.BusDecodeError, match=reason):
            bus.check_camera_frame(bus.decode(bus.CAMERA_FRAME, payload(data=base64.b64encode(data).decode())))


def test_frames_are_decimated_on_the_capture_clock() -> None:
    five = FrameDecimator(5.0)
    kept = [k for k in range(90) if five.due(k / 30.0)]
    assert kept == list(range(0, 90, 6))  # 30 fps → every 6th frame, exactly
    assert five.due(0.01)  # the clock jumped back (a new video): starts again
    assert not any(FrameDecimator(0.0).due(k / 30.0) for k in range(30))


# --- the archive ---------------------------------------------------------------------------------


def test_campaign_mcap_holds_the_camera_process_frames_as_foxglove_compressed_images(tmp_path, model) -> None:
    from mcap.reader import make_reader

    alphas = np.radians([[2.0 * k, -1.5 * k, 1.0 * k] for k in range(24)])  # 0.8 s of video at 30 fps
    renderer = Renderer(model, seed=4)
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (1280, 720))
    for a in alphas:
        writer.write(renderer.render(a))
    writer.release()
    path = tmp_path / "campaign.mcap"
    with bus_pair() as (hub, session, _connect):
        recorder = CampaignRecorder(session, path, {"campaign_id": "cam", "kind": "control"})
        try:
            done = subprocess.run(xneck("camera", "--source", f"file:{video}", "--fast", "--t0", "10",
                                        "--frame-rate-hz", "5", "--connect", hub),
                                  capture_output=True, text=True, timeout=120)
            assert done.returncode == 0, done.stderr
            assert wait_until(lambda: recorder.stats.recorded >= len(alphas) + 4, 10.0), recorder.stats
        finally:
            recorder.stop()
    stats = recorder.stats
    assert stats.rejected == {} and stats.dropped == 0, stats

    with open(path, "rb") as f:
        reader = make_reader(f)
        images = [(s, c, m) for s, c, m in reader.iter_messages(topics=[IMAGE_TOPIC])]
    assert len(images) == 4  # 0.8 s of video at 5 Hz: frames 0, 6, 12 and 18
    schema, channel = images[0][0], images[0][1]
    assert schema is not None and schema.name == "foxglove.CompressedImage" and schema.encoding == "jsonschema"
    assert json.loads(schema.data)["title"] == "foxglove.CompressedImage"
    assert channel.message_encoding == "json" and channel.metadata["key"] == bus.CAMERA_FRAME
    stamps = []
    for _s, _c, message in images:
        doc = json.loads(message.data)
        assert set(doc) == {"timestamp", "frame_id", "data", "format"} and doc["format"] == "jpeg"
        picture = cv2.imdecode(np.frombuffer(base64.b64decode(doc["data"]), np.uint8), cv2.IMREAD_COLOR)
        assert picture is not None and picture.shape == (720, 1280, 3)
        stamps.append(doc["timestamp"]["sec"] + doc["timestamp"]["nsec"] * 1e-9)
    assert stamps == pytest.approx(10.0 + np.array([0, 6, 12, 18]) / 30.0, abs=1e-6)  # the exposures' own time
    # The archive reader still reads the whole campaign: α_IP of every frame, the images as JSON.
    campaign = read_campaign(path)
    assert len(campaign.messages(bus.CAMERA_ALPHA)) == len(alphas)
    assert campaign.schemas[IMAGE_TOPIC] == "foxglove.CompressedImage"


def test_the_recorder_refuses_a_frame_that_is_not_a_jpeg(tmp_path, rendered) -> None:
    image, found = rendered
    good = frame_message(1, image, found, 1.0, 1.0, "test")
    not_jpeg = msgspec.structs.replace(good, seq=2, data=b"\x89PNG\r\n\x1a\n0000")
    path = tmp_path / "c.mcap"
    with bus_pair() as (_hub, session, connect):
        recorder = CampaignRecorder(session, path, {"campaign_id": "c"})
        try:
            pub = publisher(connect(), bus.CAMERA_FRAME)
            assert wait_until(lambda: (pub.put(not_jpeg), recorder.stats.rejected.get(bus.CAMERA_FRAME, 0) > 0)[1], 10.0, 0.2)
            assert "not a JPEG" in recorder.stats.last_reject_reason
            pub.put(good)
            assert wait_until(lambda: recorder.stats.recorded == 1, 10.0)
        finally:
            recorder.stop()
    campaign = read_campaign(path)
    [(_t, doc)] = campaign.messages(IMAGE_TOPIC)
    assert base64.b64decode(doc["data"]) == good.data and campaign.schemas[IMAGE_TOPIC] == "foxglove.CompressedImage"


# --- the console ---------------------------------------------------------------------------------


def test_camera_route_and_detection_health_on_a_real_console(tmp_path, rendered) -> None:
    from server_harness import running_server

    from server.camera_feed import MAX_FRAME_PAYLOAD

    image, found = rendered
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=30) as c:
        empty = c.get("/api/camera").json()
        assert empty == {"health": None, "alpha": None, "frame": None}
        assert c.get("/api/camera/frame.jpg").status_code == 404
        hub = c.get("/api/system/health").json()["hub"]
        with open_session(listen=["tcp/127.0.0.1:0"], connect=[hub]) as session:
            alpha_pub, frame_pub = publisher(session, bus.CAMERA_ALPHA), publisher(session, bus.CAMERA_FRAME)
            frame = frame_message(3, image, found, 5.0, 5.05, "twin-render")
            seq = [0]

            def publish_alpha() -> None:
                seq[0] += 1
                alpha_pub.put(bus.CameraAlpha(seq=seq[0], stamp_s=5.0 + seq[0] / 30, capture_stamp_s=5.0,
                                              alpha_ip_rad=[0.17, -0.35, None], confidence=[0.99, 0.98, 0.0],
                                              source="twin-render"))

            def frame_seen() -> bool:
                frame_pub.put(frame)
                publish_alpha()
                return c.get("/api/camera").json()["frame"] is not None

            assert wait_until(frame_seen, 20.0, 0.1)
            for _ in range(30):  # 30 Hz for a second
                publish_alpha()
                time.sleep(1 / 30)
            state = c.get("/api/camera").json()
            health = c.get("/api/system/health").json()["camera"]
            jpeg = c.get(state["frame"]["url"])
            # A hostile frame (not a JPEG) is refused and counted; the last good one stays.
            session.put(bus.CAMERA_FRAME, bus.encode(msgspec.structs.replace(frame, seq=4, data=b"<html>....")))
            assert wait_until(lambda: c.get("/api/system/health").json()["camera"]["frames_rejected"] == 1, 10.0, 0.1)
            assert c.get("/api/camera").json()["frame"]["seq"] == 3
            # An oversized payload is refused as it arrives, before anything decodes it.
            session.put(bus.CAMERA_FRAME, b"{" + b" " * MAX_FRAME_PAYLOAD + b"}")
            assert wait_until(lambda: c.get("/api/system/health").json()["camera"]["frames_rejected"] == 2, 10.0, 0.1)
            assert c.get("/api/camera").json()["frame"]["seq"] == 3
    assert jpeg.status_code == 200 and jpeg.headers["content-type"] == "image/jpeg" and jpeg.content == frame.data
    assert jpeg.headers["cache-control"] == "no-store" and jpeg.headers["x-frame-seq"] == "3"
    f = state["frame"]
    assert (f["width"], f["height"], f["seq"], f["capture_stamp_s"]) == (1280, 720, 3, 5.0)
    assert f["marker_bar"] == frame.marker_bar and f["markers_px"] == pytest.approx(frame.markers_px)
    assert state["alpha"]["alpha_ip_rad"] == [0.17, -0.35, None] and state["alpha"]["fresh"] is True
    assert health["missing_joints"] == [3] and health["fresh"] is True and health["source"] == "twin-render"
    assert 10.0 < health["rate_hz"] < 40.0, health  # about 30 α_IP messages per second were published
    assert health["missing_fraction"] == [0.0, 0.0, 1.0]
    assert 0.0 <= health["age_s"] < 1.0 and 0.0 <= health["frame_age_s"] < 30.0
    assert health["frames_received"] >= 1


@pytest.mark.skipif(not os.path.exists(CHROMIUM), reason="Debian chromium not installed (bash .ci/setup)")
def test_dashboard_camera_panel_shows_the_twin_camera_with_its_markers(tmp_path, params) -> None:
    playwright_sync = pytest.importorskip("playwright.sync_api")
    from server_harness import running_server

    ARTIFACTS.mkdir(exist_ok=True)
    stop = threading.Event()
    with running_server(tmp_path / "data", viser=False) as (base, _app), playwright_sync.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        camera = None
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1100}, bypass_csp=True)  # server.guard.CSP forbids eval (tests/browser_harness.py)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(base + "/", wait_until="load")
            page.wait_for_function("window.xneckCamera && window.xneckCamera.polls > 0", timeout=15000)
            assert "no camera" in page.inner_text("#camera-state")

            hub = httpx.get(base + "/api/system/health", timeout=10).json()["hub"]
            log = open(tmp_path / "camera.log", "wb")  # noqa: SIM115 - the child's output while it runs
            # The twin's rendered camera, joint 3's head-bar marker covered: the panel says "missing".
            camera = subprocess.Popen(xneck("camera", "--source", "twin", "--rate", "10", "--frame-rate-hz", "5",
                                            "--occlude", "3:1", "--connect", hub, "--instance", "panel-test"),
                                      stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            with open_session(listen=["tcp/127.0.0.1:0"], connect=[hub]) as session:
                truth = publisher(session, bus.TWIN_TRUTH)
                alpha = np.radians([15.0, -25.0, 20.0])

                def feed_truth() -> None:  # the twin's truth at 50 Hz of the bus clock, held still
                    k, t0 = 0, time.monotonic()
                    while not stop.wait(0.02):
                        k += 1
                        truth.put(bus.Truth(seq=k, stamp_s=time.monotonic() - t0, alpha_rad=list(alpha),
                                            alpha_dot_rad_s=[0.0] * 3, theta_rad=[0.0] * 4, theta_dot_rad_s=[0.0] * 4,
                                            tension_N=[0.0] * 4, elongation_m=[0.0] * 4, slack=[False] * 4,
                                            near_singular=False))

                feeder = threading.Thread(target=feed_truth, daemon=True)
                feeder.start()
                try:
                    deadline = time.monotonic() + 150  # cold caches: the camera compiles the model first
                    while not page.evaluate("window.xneckCamera.frames >= 2 && window.xneckCamera.markers > 0"):
                        tail = (tmp_path / "camera.log").read_text(errors="replace")[-2000:]
                        assert camera.poll() is None, f"the camera process exited: {tail}"
                        assert time.monotonic() < deadline, f"no frame in the panel within 150 s: {tail}"
                        page.wait_for_timeout(250)
                    page.wait_for_timeout(500)
                    text = page.inner_text("#camera-alpha")
                    state = page.evaluate("window.xneckCamera")
                    health = httpx.get(base + "/api/system/health", timeout=10).json()["camera"]
                    page.locator("#camera").screenshot(path=str(ARTIFACTS / "camera_panel.png"))
                finally:
                    stop.set()
                    feeder.join(5)
            assert state["state"] == "live" and state["markers"] >= 8, state
            # The canvas shows the picture: not blank, and the overlay's colour is on it.
            pixels = page.evaluate("""() => { const c = document.querySelector('#camera-canvas');
                const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let lit = 0;
                for (let i = 0; i < d.length; i += 4 * 97) if (d[i] + d[i + 1] + d[i + 2] > 60) lit++; return lit; }""")
            assert pixels > 100, pixels
            rows = text.splitlines()
            assert any("α1" in r and "15." in r for r in rows) and any("α2" in r and "-25." in r for r in rows), text
            assert any("α3" in r and "missing" in r for r in rows), text
            assert health["source"] == "twin-render" and health["missing_joints"] == [3] and health["rate_hz"] > 0
            assert health["frame_age_s"] is not None
            assert not errors, errors
        finally:
            stop.set()
            if camera is not None:
                camera.terminate()
                try:
                    camera.wait(10)
                except subprocess.TimeoutExpired:
                    camera.kill()
                    camera.wait(5)
            browser.close()
