"""A camera moved after its calibration (audit of the camera): its α_IP were wrong with high
confidence (panned 3°: 0.47° mean error, confidence 0.93, no joint missing). The base plate's
reference markers, fixed on the plate, move in the image with the camera only: the detector
compares them with where the calibration puts them and reports every joint missing, with the
reason, when they moved more than ``MOVED_PX`` (docs/camera.md, "Camera moved").

Real rendered frames: the twin's camera drawn at a turned pose, measured with the calibration of
the unmoved one (as ``benchmarks/camera_moved.py`` measures the threshold's margins)."""

from __future__ import annotations

import math

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

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
