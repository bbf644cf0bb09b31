"""A camera moved after its calibration (audit of the camera): its α_IP were wrong with high
confidence (panned 3°: 0.47° mean error, confidence 0.93, no joint missing). The base plate's
reference markers, fixed on the plate, move in the image with the camera only: the detector
compares them with where the calibration puts them and reports every joint missing, with the
reason, when they moved more than ``MOVED_PX`` (docs/camera.md, "Camera moved").

Real rendered frames: the twin's camera drawn at a turned pose, measured with the calibration of
the unmoved one (as ``benchmarks/camera_moved.py`` measures the threshold's margins)."""

from __future__ import annotations

import logging
import math
import threading
from typing import Any, cast

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from browser_harness import needs_chromium  # noqa: E402

from twin.camera.calibration import look_at_pose, twin_calibration  # noqa: E402
from twin.camera.detect import MOVED_PX, Detector  # noqa: E402
from twin.camera.layout import MarkerLayout  # noqa: E402
from twin.camera.render import Renderer, RenderOptions  # noqa: E402

NOMINAL = dict(tilt_deg=4.0, pan_deg=-3.0, roll_deg=0.5)  # twin_calibration()'s pose


def moved(**change: float):
    """The twin's camera turned from its calibrated pose (``look_at_pose`` angles, degrees)."""
    rvec, tvec = look_at_pose((0.0, 0.115), 0.52, **{**NOMINAL, **change})
    return twin_calibration().with_pose(rvec, tvec)


def detector_for(params) -> Detector:
    return Detector(params.n_joints, params.geometry.L, params.geometry.b, twin_calibration())


def poses(params, n: int, seed: int) -> np.ndarray:
    lim = math.radians(params.limits.alpha_max_deg)
    return np.random.default_rng(seed).uniform(-lim, lim, size=(n, params.n_joints))


def cover_reference(image: np.ndarray, index: int) -> np.ndarray:
    """The frame with one base-plate reference marker covered (a hand, a cable on the plate)."""
    out = image.copy()
    x, y = twin_calibration().project(MarkerLayout().reference()[index:index + 1])[0]
    cv2.circle(out, (round(x), round(y)), 20, (120, 120, 120), -1)
    return out


def test_a_camera_panned_3_degrees_reports_every_joint_missing_with_the_reason(params, model) -> None:
    renderer = Renderer(model, moved(pan_deg=-6.0), seed=1)
    detector = detector_for(params)
    for alpha in poses(params, 6, seed=0):
        detector.reset()
        found = detector.detect(renderer.render(alpha))
        assert found.alpha_rad == [None] * params.n_joints and found.confidence == [0.0] * params.n_joints
        assert found.reference_shift_px is not None and found.reference_shift_px > 2 * MOVED_PX
        assert found.reason.startswith(f"camera moved {found.reference_shift_px:.1f} px since its calibration")
        assert "--calibration" in found.reason
        assert len(found.markers_px) == 2 * (params.n_joints + 1) and len(found.reference_px) == 4  # kept for the picture


def test_a_camera_bumped_while_tracking_is_caught_on_the_next_frame(params, model) -> None:
    """Tracked (windowed) frames searched only the bars' windows: the references are searched too,
    in windows around their calibrated positions, so a bump is caught on the frame it happens."""
    path = np.radians(np.linspace([0.0, 0.0, 0.0], [20.0, -25.0, 30.0], 24))
    still, bumped = Renderer(model, seed=2), Renderer(model, moved(pan_deg=-6.0), seed=2)
    detector = detector_for(params)
    for alpha in path[:12]:
        found = detector.detect(still.render(alpha))
        assert None not in found.alpha_rad and not found.reason
    assert detector.windowed_frames >= 10
    for alpha in path[12:]:
        found = detector.detect(bumped.render(alpha))
        assert found.alpha_rad == [None] * params.n_joints and found.reason.startswith("camera moved")


def test_the_unmoved_camera_is_never_taken_as_moved(params, model) -> None:
    # Random poses, full search, at the benchmark's worst noise and blur...
    renderer = Renderer(model, options=RenderOptions(noise_dn=6.0, blur_px=1.6), seed=3)
    detector = detector_for(params)
    shifts = []
    for alpha in poses(params, 40, seed=1):
        detector.reset()
        found = detector.detect(renderer.render(alpha))
        assert None not in found.alpha_rad and not found.reason, found.reason
        shifts.append(found.reference_shift_px)
    # ... and a tracked 30 fps path: the check runs on windowed frames too, without a false alarm.
    tracked, tracker = Renderer(model, seed=4), detector_for(params)
    for alpha in np.radians(np.linspace([-50.0, 40.0, -55.0], [50.0, -45.0, 55.0], 150)):
        found = tracker.detect(tracked.render(alpha))
        assert None not in found.alpha_rad and not found.reason, found.reason
        shifts.append(found.reference_shift_px)
    assert tracker.windowed_frames >= 140
    assert None not in shifts and max(shifts) < 0.25 * MOVED_PX


def test_a_hidden_reference_skips_the_check_and_keeps_the_last_verdict(params, model) -> None:
    alpha = np.radians([15.0, -20.0, 25.0])
    # Unmoved, a reference covered: nothing to compare, α measured (and tracking still works).
    detector = detector_for(params)
    frame = cover_reference(Renderer(model, seed=5).render(alpha), 2)
    for _ in range(3):
        found = detector.detect(frame)
        assert found.reference_shift_px is None and None not in found.alpha_rad and not found.reason
    # Moved, then a reference covered: the camera did not move back, its joints stay missing.
    detector = detector_for(params)
    frame = Renderer(model, moved(pan_deg=-6.0), seed=5).render(alpha)
    assert detector.detect(frame).reason
    found = detector.detect(cover_reference(frame, 0))
    assert found.reference_shift_px is None and found.alpha_rad == [None] * params.n_joints and found.reason


def test_the_camera_process_says_it_once_per_episode_and_counts_it_in_its_health(params, model, caplog) -> None:
    from busutil import bus_pair, wait_until

    from bridge import bus
    from twin.camera.process import MOVED_NOW, CameraNode
    from twin.camera.source import Frame

    still, bumped = Renderer(model, seed=6), Renderer(model, moved(pan_deg=-6.0), seed=6)
    alpha = np.radians([10.0, -10.0, 20.0])
    frames = [still.render(alpha)] * 3 + [bumped.render(alpha)] * 4 + [still.render(alpha)] * 2 + [bumped.render(alpha)] * 3

    class Source:
        name, dropped, k = "file:bumped.avi", 0, 0

        def read(self):
            if self.k >= len(frames):
                return None
            self.k += 1
            return Frame(self.k / 30.0, frames[self.k - 1])

        def close(self) -> None:
            pass

    health: list[bus.Health] = []
    with bus_pair() as (_hub, hub, connect):
        sub = hub.declare_subscriber(bus.health_key("camera", "cam-test"),
                                     lambda s: health.append(bus.decode(bus.Health, s.payload.to_bytes())))
        camera = CameraNode(connect(), detector_for(params), instance="cam-test")
        try:
            with caplog.at_level(logging.INFO, logger="xneck.camera"):
                assert wait_until(lambda: (camera._maybe_health(force=True), bool(health))[1], 10.0)
                camera.run_source(Source(), threading.Event())
                assert wait_until(lambda: any(h.rejected.get("camera_moved") == 7 for h in health), 10.0)
        finally:
            camera.close()
            sub.undeclare()
    said = [r.getMessage() for r in caplog.records if "since its calibration" in r.getMessage()]
    assert len(said) == 2, said  # two episodes, each said once
    assert "every joint is reported missing" in said[0]
    assert sum("back where the calibration puts them" in r.getMessage() for r in caplog.records) == 1
    assert camera.moved_frames == 7 and camera.missing_joints == 7 * params.n_joints
    last = next(h for h in health if h.rejected.get("camera_moved") == 7)
    assert last.last_reject_reason.startswith("camera moved") and last.received[MOVED_NOW] == 1
    # Said as it happens, both ways (the console shows the reason from it, and takes it away).
    said_at = {(h.rejected.get("camera_moved"), h.received[MOVED_NOW]) for h in health}
    assert {(1, 1), (4, 0), (5, 1)} <= said_at, said_at  # (frames withheld, moved now) when found moved, back, moved


def test_xneck_camera_detect_says_why_every_joint_is_missing(xneck, tmp_path, model) -> None:
    frame = tmp_path / "bumped.png"
    cv2.imwrite(str(frame), Renderer(model, moved(pan_deg=-6.0), seed=1).render(np.radians([10.0, -20.0, 30.0])))
    result = xneck("camera", "detect", str(frame), "--json")
    assert result.returncode == 0, result.stderr
    assert "camera moved" in result.stderr and "since its calibration" in result.stderr


# --- the console and the alignment say why ---------------------------------------------------------


class BumpableCamera:
    """The camera process (:class:`twin.camera.process.CameraNode`, its own Zenoh session) on
    ``hub``, filming the still neck at 30 fps of wall time (5 JPEG frames a second for the card): through the moved camera while
    ``bumped`` is set, else through the calibrated one. Started by :meth:`start`, ended by :meth:`close`."""

    def __init__(self, hub: str, params, model) -> None:
        from bridge.session import open_session
        from twin.camera.process import CameraNode

        alpha = np.radians([10.0, -10.0, 20.0])
        self.frames = {False: Renderer(model, seed=7).render(alpha),
                       True: Renderer(model, moved(pan_deg=-6.0), seed=7).render(alpha)}
        self.bumped = threading.Event()
        self._stop = threading.Event()
        self._session = open_session(listen=["tcp/127.0.0.1:0"], connect=[hub])
        self.node = CameraNode(self._session, detector_for(params), instance="bumped-cam", frame_rate_hz=5.0)
        self._thread = threading.Thread(target=self.node.run_source, args=(self, self._stop), kwargs={"pace_fps": 30.0},
                                        daemon=True)
        self.name, self.dropped, self._k = "usb:0", 0, 0

    def read(self):  # the FrameSource the node reads
        from twin.camera.source import Frame

        self._k += 1
        return Frame(self._k / 30.0, self.frames[self.bumped.is_set()])

    def start(self) -> BumpableCamera:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self.node.close()
        self._session.close()


def test_the_console_says_why_every_joint_is_missing_while_the_camera_is_moved(tmp_path, params, model) -> None:
    """The camera process's health (``xneck/health/camera/<instance>``) carries the reason to the
    console's camera data (``/api/camera``, ``/api/system/health``); it is cleared when the
    references are back where the calibration puts them."""
    import httpx
    from server_harness import running_server, wait_until

    with (running_server(tmp_path / "data", viser=False) as (base, app), httpx.Client(base_url=base, timeout=10) as c):
        camera = BumpableCamera(cast(Any, app).state.hub, params, model)
        camera.bumped.set()
        camera.start()
        try:
            def reason() -> str | None:
                health = c.get("/api/camera").json()["health"]
                return None if health is None else health.get("moved_reason")

            assert wait_until(lambda: bool(reason()), 20.0, 0.1), c.get("/api/camera").json()["health"]
            moved_state = c.get("/api/camera").json()
            system = c.get("/api/system/health").json()["camera"]
            camera.bumped.clear()
            assert wait_until(lambda: reason() is None and None not in c.get("/api/camera").json()["alpha"]["alpha_ip_rad"],
                              10.0, 0.1), c.get("/api/camera").json()
        finally:
            camera.close()
    said = moved_state["health"]["moved_reason"]
    assert said.startswith("camera moved ") and " px since its calibration" in said and "--calibration" in said, said
    assert float(said.split()[2]) > 2 * MOVED_PX  # the shift in px, as the detector measured it
    assert moved_state["alpha"]["alpha_ip_rad"] == [None] * params.n_joints
    assert moved_state["health"]["missing_joints"] == list(range(1, params.n_joints + 1))
    assert system["moved_reason"].startswith("camera moved "), system  # /api/system/health's camera: the same


@needs_chromium
def test_the_camera_card_says_why_every_joint_is_missing_while_the_camera_is_moved(tmp_path, params, model) -> None:
    """The dashboard's camera card shows the reason under the picture, beside the joints
    ``missing``, and takes it away when the references are back."""
    from browser_harness import ARTIFACTS, dashboard_page
    from server_harness import running_server

    with running_server(tmp_path / "data", viser=False) as (base, app), dashboard_page(base) as (page, errors):
        camera = BumpableCamera(cast(Any, app).state.hub, params, model)
        camera.bumped.set()
        camera.start()
        try:
            page.wait_for_function("document.querySelector('#camera-reason')?.textContent.includes('camera moved')",
                                   timeout=20000)
            said = page.inner_text("#camera-reason")
            alpha_text = page.inner_text("#camera-alpha")
            page.locator("#camera").screenshot(path=str(ARTIFACTS / "camera_moved.png"))
            camera.bumped.clear()
            page.wait_for_function("!document.querySelector('#camera-reason').textContent"
                                   " && !document.querySelector('#camera-alpha').textContent.includes('missing')",
                                   timeout=10000)
            shown = page.is_visible("#camera-reason")
        finally:
            camera.close()
        assert not errors, errors
    assert "camera moved " in said and " px since its calibration" in said and "redo the extrinsic calibration" in said, said
    assert alpha_text.count("missing") == params.n_joints, alpha_text
    assert not shown


def test_xneck_camera_align_says_the_camera_moved_since_its_calibration(xneck, tmp_path, params, model) -> None:
    """A video filmed by a camera moved since its calibration: every joint is missing on every
    frame, and the alignment had failed with "never overlap"; it says the cause in one line, at
    the first moved frame (a camera bumped part-way included)."""
    from bridge import bus
    from bridge.archive import write_campaign

    t = np.arange(0.0, 3.0, 0.01)
    zeros = [0.0] * params.n_cables
    alpha = np.radians([10.0, -10.0, 20.0])
    truths = [(bus.TWIN_TRUTH, int((1.7e9 + tk) * 1e9), bus.Truth(
        seq=k + 1, stamp_s=float(tk), alpha_rad=(alpha * (1 + 0.1 * tk)).tolist(), alpha_dot_rad_s=[0.0] * 3,
        theta_rad=zeros, theta_dot_rad_s=zeros, tension_N=zeros, elongation_m=zeros, slack=[False] * params.n_cables,
        near_singular=False)) for k, tk in enumerate(t)]
    campaign = write_campaign(tmp_path / "c.mcap", truths, {"campaign_id": "c1", "kind": "identification"})
    still, bumped = Renderer(model, seed=9), Renderer(model, moved(pan_deg=-6.0), seed=9)
    out = tmp_path / "aligned.mcap"
    for name, bumped_from in (("bumped.avi", 0), ("bumped-later.avi", 30)):  # from the start; bumped after 1 s
        video = tmp_path / name
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (1280, 720))
        for k in range(45):
            writer.write((bumped if k >= bumped_from else still).render(alpha * (1 + 0.1 * (0.5 + k / 30.0))))
        writer.release()
        result = xneck("camera", "align", str(video), str(campaign), "--out", str(out))
        assert result.returncode != 0 and not out.exists(), result
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in result.stderr, result.stderr
        said = lines[0]
        assert "camera moved " in said and " px since its calibration" in said, said
        shift = float(said.split("camera moved ")[1].split()[0])
        assert shift > 2 * MOVED_PX, said
        assert f"found at {bumped_from / 30.0:.3f} s of the video (frame {bumped_from + 1})" in said, said
        assert "redo the extrinsic calibration" in said and "--calibration" in said, said
        assert "never overlap" not in said, said
