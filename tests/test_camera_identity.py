"""Two cameras of one kind on one bus (audit of 2026-11-29): `xneck up --alpha-ip camera` and a
second `xneck camera --source twin` both published α_IP as ``source`` "twin-render"; the campaign
recorded both, interleaved (916 messages in 15 s, stamps going back, neighbours 10° apart), said
``foreign_alpha_ip: {}`` and ended ``finished``, and the console's health showed 59.5 Hz with no
warning. ``CameraAlpha.source`` names the kind of camera (twin-render, usb:0), not the camera:
a camera process names itself in the attachment of what it publishes
(:func:`bridge.session.camera_of`), and a campaign records one camera by that name.

Real Zenoh sessions on loopback; the last test runs the audit's processes."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh
from busutil import bus_pair
from server_harness import wait_until

from bridge import bus
from bridge.archive import CampaignRecorder
from bridge.archive_read import read_campaign
from bridge.session import camera_attachment, camera_of, run_attachment
from server.camera_feed import CameraFeed, camera_health
from server.live import LatestValues
from server.quality import CampaignMonitor, camera_note


def _alpha(seq: int, source: str = "twin-render") -> bytes:
    return bus.encode(bus.CameraAlpha(seq=seq, stamp_s=seq / 30 + 0.05, capture_stamp_s=seq / 30,
                                      alpha_ip_rad=[0.1, 0.2, 0.3], source=source))


def _record(sessions, path: Path, expect: tuple[str, str] | None) -> tuple[CampaignMonitor, CampaignRecorder]:
    """A monitor and its recorder (expecting ``expect`` = (source, camera) if given) while two
    'twin-render' cameras publish, named 'cam-a' (first, alone) and 'cam-b', then 'cam-a' again
    interleaved with 'cam-b' (10 each), and 5 α_IP naming no camera (an older camera process)."""
    a, b = sessions
    monitor = CampaignMonitor(b)
    if expect is not None:
        monitor.expect_alpha_ip_source(*expect)
    kept: list[int] = []  # the seqs the recorder's writer asked ``monitor.keep`` about, in order

    def keep(key: str, msg: bus.BusMessage, *args: str) -> bool:
        kept.append(msg.seq)
        return monitor.keep(key, msg, *args)

    recorder = CampaignRecorder(b, path, {"campaign_id": "c-id"}, flush_period_s=0.2, keep=keep)
    alphas = a.declare_publisher(bus.CAMERA_ALPHA, congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        assert wait_until(lambda: (alphas.put(_alpha(0), attachment=camera_attachment("cam-a")),
                                   recorder.stats.received > 0)[1], 10, 0.05)
        for k in range(1, 11):
            alphas.put(_alpha(k), attachment=camera_attachment("cam-a"))
            alphas.put(_alpha(100 + k), attachment=camera_attachment("cam-b"))
        for k in range(1, 6):
            alphas.put(_alpha(200 + k))
        # the last one put reached the writer, then the writer dealt with all: not a count, which the
        # seed's late copies (put until the recorder heard one) reach with the tail still on its way
        assert wait_until(lambda: 205 in kept, 10, 0.02), kept
        assert wait_until(lambda: recorder.stats.recorded + recorder.stats.skipped == recorder.stats.received,
                          10, 0.02), recorder.stats
    finally:
        recorder.stop("finished")
        monitor.close()
        alphas.undeclare()
    return monitor, recorder


def test_two_cameras_of_one_source_are_told_apart_by_their_instance(sessions, tmp_path: Path) -> None:
    path = tmp_path / "cameras.mcap"
    monitor, recorder = _record(sessions, path, None)
    counters = monitor.counters()
    assert counters["alpha_ip_source"] == "twin-render" and counters["alpha_ip_camera"] == "cam-a", counters
    assert counters["foreign_alpha_ip"] == {"twin-render@cam-b": 10} and counters["foreign_messages"] == 10, counters
    seqs = [m.seq for _, m in read_campaign(path).messages(bus.CAMERA_ALPHA)]
    assert seqs[-15:] == [*range(1, 11), *range(201, 206)], seqs  # cam-a's, and the unnamed ones as before
    assert recorder.stats.skipped == 10
    note = camera_note(counters)
    assert "'twin-render@cam-b' (10)" in note and "'twin-render@cam-a'" in note, note


def test_the_camera_the_campaign_started_is_recorded_whichever_instance_came_first(sessions, tmp_path: Path) -> None:
    path = tmp_path / "cameras.mcap"
    monitor, _ = _record(sessions, path, ("twin-render", "cam-b"))
    counters = monitor.counters()
    assert counters["alpha_ip_camera"] == "cam-b", counters
    foreign = counters["foreign_alpha_ip"]  # cam-a's first α_IP, put until the recorder heard one, and 10 more
    assert foreign.keys() == {"twin-render@cam-a"} and foreign["twin-render@cam-a"] >= 11, counters
    seqs = [m.seq for _, m in read_campaign(path).messages(bus.CAMERA_ALPHA)]
    assert seqs == [*range(101, 111), *range(201, 206)], seqs


def test_a_twin_rendering_its_own_camera_is_recorded_not_a_stray_camera_of_its_source(sessions) -> None:
    """Audit of 2026-11-29 (of this change): a lockstep twin renders its α_IP in its driver (the
    samples carry its run, not a camera's name); a stray ``xneck camera --source twin`` on the hub
    was adopted as the first *named* camera, and both were recorded, interleaved. The runner now
    expects the twin's own camera (``TWIN_CAMERA``)."""
    from server.quality import TWIN_CAMERA

    _, b = sessions
    monitor = CampaignMonitor(b)
    try:
        monitor.expect_alpha_ip_source("twin-render", TWIN_CAMERA)
        alpha = bus.decode(bus.CameraAlpha, _alpha(1))
        assert not monitor.keep(bus.CAMERA_ALPHA, alpha, camera="stray")  # first, and still not the campaign's
        assert monitor.keep(bus.CAMERA_ALPHA, alpha, run="run-1")
        assert not monitor.keep(bus.CAMERA_ALPHA, alpha, camera="stray")
        counters = monitor.counters()
        assert counters["alpha_ip_camera"] == TWIN_CAMERA and counters["foreign_alpha_ip"] == {"twin-render@stray": 2}
    finally:
        monitor.close()


def test_an_adopted_camera_restarted_under_a_new_name_goes_on_being_recorded(sessions) -> None:
    """Audit of 2026-11-29 (of this change): a camera process's default name is random, so one
    restarted mid-campaign came back as another camera and all its later α_IP were set aside. The
    camera adopted (none named by the runner) hands over to a live one once its own token is gone;
    while it lives, a second camera is still set aside."""
    from bridge.session import liveliness_token

    a, b = sessions
    monitor = CampaignMonitor(b)
    alpha = bus.decode(bus.CameraAlpha, _alpha(1, "usb:0"))
    old = liveliness_token(a, "camera", "cam-old")
    new = None
    try:
        assert wait_until(lambda: "cam-old" in monitor._cameras_alive, 10, 0.02)
        assert monitor.keep(bus.CAMERA_ALPHA, alpha, camera="cam-old")
        new = liveliness_token(a, "camera", "cam-new")
        assert wait_until(lambda: "cam-new" in monitor._cameras_alive, 10, 0.02)
        assert not monitor.keep(bus.CAMERA_ALPHA, alpha, camera="cam-new")  # two alive: the first stays
        old.undeclare()
        assert wait_until(lambda: "cam-old" not in monitor._cameras_alive, 10, 0.02)
        assert monitor.keep(bus.CAMERA_ALPHA, alpha, camera="cam-new")  # the restarted camera
        assert not monitor.keep(bus.CAMERA_ALPHA, alpha, camera="cam-old")  # a late sample of the old one
        assert monitor.counters()["alpha_ip_camera"] == "cam-new"
        # a camera whose token was never seen is not taken for gone: no handover to another then
        unseen = CampaignMonitor(b)
        try:
            assert unseen.keep(bus.CAMERA_ALPHA, alpha, camera="cam-unseen")
            assert wait_until(lambda: "cam-new" in unseen._cameras_alive, 10, 0.02)
            assert not unseen.keep(bus.CAMERA_ALPHA, alpha, camera="cam-new")
        finally:
            unseen.close()
    finally:
        monitor.close()
        if new is not None:
            new.undeclare()


def test_a_camera_process_names_itself_on_its_alpha_ip_and_frames(params) -> None:
    """What `xneck camera` publishes carries ``xneck-camera:<instance>``; a bridge's driver's α_IP
    keeps its run (bridge.session.run_of), not a camera name."""
    from twin.camera.calibration import twin_calibration
    from twin.camera.detect import Detection, Detector
    from twin.camera.process import CameraNode

    seen: list[tuple[str, str]] = []
    with bus_pair() as (_hub, hub, connect):
        subs = [hub.declare_subscriber(k, lambda s: seen.append((str(s.key_expr), camera_of(s))))
                for k in (bus.CAMERA_ALPHA, bus.CAMERA_FRAME)]
        detector = Detector(params.n_joints, params.geometry.L, params.geometry.b, twin_calibration())
        node = CameraNode(connect(), detector, instance="cam-x", frame_rate_hz=30.0)
        cal = twin_calibration()
        image = np.zeros((cal.height, cal.width, 3), dtype=np.uint8)
        found = Detection(alpha_rad=[0.1] * params.n_joints, confidence=[1.0] * params.n_joints)
        try:
            k = [0]

            def publish() -> bool:
                k[0] += 1
                node.publish(found, k[0] / 10, k[0] / 10 + 0.05, "twin-render", image)
                return {key for key, _ in seen} == {bus.CAMERA_ALPHA, bus.CAMERA_FRAME}

            assert wait_until(publish, 10, 0.1), seen
        finally:
            node.close()
            for sub in subs:
                sub.undeclare()
    assert {camera for _, camera in seen} == {"cam-x"}, seen


def test_the_consoles_camera_health_says_when_two_cameras_publish(sessions) -> None:
    """The health's α_IP rate counted both cameras as one (59.5 Hz) and said nothing."""
    a, b = sessions
    feed = CameraFeed(b)
    alphas = a.declare_publisher(bus.CAMERA_ALPHA, congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        def one() -> bool:
            alphas.put(_alpha(1), attachment=camera_attachment("cam-a"))
            return feed.alpha_window()[0] > 0
        assert wait_until(one, 10, 0.05)
        assert feed.cameras() == ["twin-render@cam-a"]
        for k in range(10):
            alphas.put(_alpha(k), attachment=camera_attachment("cam-b"))
            alphas.put(_alpha(k), attachment=run_attachment("run-1"))  # a twin bridge's white noise
        assert wait_until(lambda: len(feed.cameras()) == 3, 10, 0.02), feed.cameras()
        assert feed.cameras() == ["twin-render@cam-a", "twin-render@cam-b", "twin-render@run-1"]
    finally:
        feed.close()
        alphas.undeclare()


def test_camera_health_names_the_cameras_and_warns_of_a_second() -> None:
    feed = CameraFeed()
    values = LatestValues()
    values.put_raw("camera", _alpha(1))
    feed.note_alpha(_alpha(1), "cam-a")
    health = camera_health(values, feed)
    assert health is not None and health["cameras"] == ["twin-render@cam-a"] and health["warning"] is None, health
    feed.note_alpha(_alpha(2), "cam-b")
    health = camera_health(values, feed)
    assert health is not None and health["cameras"] == ["twin-render@cam-a", "twin-render@cam-b"], health
    assert "2 cameras" in health["warning"] and "twin-render@cam-b" in health["warning"], health


@pytest.mark.e2e
def test_xneck_ups_camera_campaign_records_its_camera_beside_a_second_camera_of_the_same_source(tmp_path: Path) -> None:
    """The audit's set-up: `xneck up --alpha-ip camera` and a second `xneck camera --source twin`
    (the same source string) on its hub. The campaign records `xneck up`'s camera, names the other,
    and the console's camera health warns of two cameras; the dashboard's live α_IP is `xneck up`'s
    camera's only, before and during the campaign (it flipped between both)."""
    from test_console_strays import _assert_one_camera_shown, _campaign, _live_cameras
    from test_stack import _alive_kinds, _procs
    from test_stack_faults import GENTLE, _wait_end

    from bridge.session import free_tcp_port

    port, hub = free_tcp_port(), f"tcp/127.0.0.1:{free_tcp_port()}"
    base, data = f"http://127.0.0.1:{port}", tmp_path / "d"
    with _procs() as spawn:
        spawn(["up", "--port", str(port), "--hub", hub, "--data-dir", str(data), "--alpha-ip", "camera"],
              tmp_path / "up.log")
        assert wait_until(lambda: {"bridge", "campaign-service", "camera"} <= _alive_kinds(base), 180, 0.3), \
            (tmp_path / "up.log").read_text()[-2000:]
        spawn(["camera", "--source", "twin", "--seed", "7", "--noise", "6", "--frame-rate-hz", "0",
               "--instance", "second-cam", "--listen", "tcp/127.0.0.1:0", "--connect", hub], tmp_path / "camera.log")

        def two() -> bool:
            health = httpx.get(base + "/api/camera", timeout=5).json()["health"] or {}
            return len(health.get("cameras") or []) == 2
        assert wait_until(two, 120, 0.5), (tmp_path / "camera.log").read_text()[-2000:]
        health = httpx.get(base + "/api/camera", timeout=5).json()["health"]
        assert "2 cameras" in health["warning"], health
        with _live_cameras(base) as live:
            time.sleep(1.0)
            rec = _wait_end(base, _campaign(base, GENTLE), 180)
    assert rec["status"] in ("finished", "degraded"), rec
    quality = rec["quality"]
    _assert_one_camera_shown(live, quality["alpha_ip_camera"])
    assert quality["alpha_ip_source"] == "twin-render" and quality["alpha_ip_camera"] != "second-cam", quality
    # counted, whatever rate a shared machine leaves the second camera (a count asked >6.5 Hz for 4.6 s)
    assert quality["foreign_alpha_ip"].get("twin-render@second-cam", 0) > 0, quality
    assert "twin-render@second-cam" in rec["message"], rec["message"]
    campaign = read_campaign(data / "campaigns" / f"{rec['id']}.mcap")
    stamps = [m.stamp_s for _, m in campaign.messages(bus.CAMERA_ALPHA)]
    assert stamps and all(b > a for a, b in itertools.pairwise(stamps)), "two cameras' α_IP interleaved"
