"""The 3D view draws the camera's frustum where the calibration puts it, while a camera runs
(issue 18: "the camera's frustum when a camera runs"). A real viser server in this process, fed
through the console's own LatestValues."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import viser.transforms as vtf

from bridge import bus
from server.live import LatestValues
from server.scene import NeckScene, camera_frustum_pose
from twin.camera.calibration import twin_calibration
from twin.model.params import load_params


def test_the_frustum_sits_at_the_calibrated_camera_and_looks_at_the_neck() -> None:
    cal = twin_calibration()
    wxyz, position, fov, aspect = camera_frustum_pose(cal)
    R_cw = vtf.SO3(np.asarray(wxyz)).as_matrix()  # camera → base frame
    # The base frame's points project where the calibration projects them: x_cam = R_cw^T (p − position).
    p = np.array([[0.0, 0.115, 0.0], [0.05, 0.2, 0.0], [-0.04, 0.0, 0.0]])
    cam = (p - position) @ R_cw
    px = cal.fx * cam[:, 0] / cam[:, 2] + cal.cx
    py = cal.fy * cam[:, 1] / cam[:, 2] + cal.cy
    undistorted = np.column_stack([px, py])
    expected = replace(cal, dist=(0.0, 0.0, 0.0, 0.0, 0.0)).project(p[:, :2])  # the pinhole, no lens distortion
    assert np.allclose(undistorted, expected, atol=1e-6)
    assert position[2] > 0.3  # in front of the neck's plane, about half a metre away
    assert math.isclose(aspect, 1280 / 720) and 0.3 < fov < 1.2


@pytest.mark.parametrize(("source", "shown"), [("twin-render", True), ("usb:0", True), ("twin-noise", False)])
def test_the_frustum_is_shown_while_a_camera_publishes(source: str, shown: bool) -> None:
    values = LatestValues()
    scene = NeckScene(values, load_params())
    try:
        scene.update()
        assert scene.frustum.visible is False  # no camera yet
        msg = bus.CameraAlpha(seq=1, stamp_s=1.0, alpha_ip_rad=[0.1, None, -0.1], capture_stamp_s=0.95,
                              confidence=[0.9, 0.0, 0.8] if source != "twin-noise" else [], source=source)
        values.put_raw("camera", bus.encode(msg))
        scene.update()
        assert scene.frustum.visible is shown
    finally:
        scene.close()
