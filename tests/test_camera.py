"""α_IP from a camera (issue 15): frames rendered by the twin are measured back by the detector.

Real OpenCV on real rendered frames (and real Zenoh/MCAP further down); fixed seeds.
"""

from __future__ import annotations

import base64
import json
import math
import re
import time
from dataclasses import replace

import msgspec
import numpy as np
import pytest
from typer.testing import CliRunner

cv2 = pytest.importorskip("cv2")

from twin.camera.calibration import (  # noqa: E402
    CalibrationError,
    calibration_from_dict,
    extrinsics_from_reference,
    intrinsics_from_checkerboard,
    load_calibration,
    look_at_pose,
    twin_calibration,
)
from twin.camera.detect import Detector  # noqa: E402
from twin.camera.layout import MarkerLayout  # noqa: E402
from twin.camera.render import Renderer, RenderOptions, render_checkerboard  # noqa: E402


def sweep(params, n: int, seed: int) -> np.ndarray:
    """Configurations within the joint limits: the corners of the box, then random ones."""
    lim = math.radians(params.limits.alpha_max_deg)
    corners = np.array(np.meshgrid(*[[-lim, lim]] * params.n_joints)).reshape(params.n_joints, -1).T
    rand = np.random.default_rng(seed).uniform(-lim, lim, size=(n, params.n_joints))
    return np.vstack([np.zeros(params.n_joints), corners, rand])


def detector_for(params, calibration=None) -> Detector:
    return Detector(params.n_joints, params.geometry.L, params.geometry.b, calibration)


def errors_deg(renderer: Renderer, detector: Detector, configs: np.ndarray, missing_ok: bool = False) -> np.ndarray:
    """|α_IP − α| in degrees per configuration and joint (inf for a missing joint if ``missing_ok``)."""
    out = []
    for alpha in configs:
        detector.reset()
        found = detector.detect(renderer.render(alpha))
        assert missing_ok or None not in found.alpha_rad, f"a joint is missing at α = {np.degrees(alpha)}°"
        measured = np.array([np.inf if a is None else a for a in found.alpha_rad])
        out.append(np.degrees(np.abs(measured - alpha)))
    return np.array(out)


def test_rendered_frames_are_measured_back_within_the_targets(params, model) -> None:
    renderer = Renderer(model, options=RenderOptions(noise_dn=3.0, blur_px=1.0), seed=11)
    err = errors_deg(renderer, detector_for(params), sweep(params, 25, seed=5))
    assert err.mean() <= 0.3 and err.max() <= 1.0, f"mean {err.mean():.3f}°, max {err.max():.3f}°"


def test_tracking_windows_give_the_full_search_result(params, model) -> None:
    renderer = Renderer(model, seed=2)
    detector = detector_for(params)
    path = np.radians(np.linspace([0.0, 0.0, 0.0], [30.0, -40.0, 50.0], 12))
    for alpha in path:
        tracked = detector.detect(frame := renderer.render(alpha))
        fresh = detector_for(params).detect(frame)
        assert tracked.alpha_rad == pytest.approx(fresh.alpha_rad, abs=1e-9)
        assert np.degrees(np.abs(np.array(tracked.alpha_rad) - alpha)).max() < 1.0
    assert detector.windowed_frames >= 10 and detector.full_frames <= 2


def test_an_occluded_marker_makes_its_joint_missing_and_the_others_valid(params, model) -> None:
    alpha = np.radians([25.0, -30.0, 40.0])
    head = Renderer(model, options=RenderOptions(occlude=((3, 0),)), seed=4)
    found = detector_for(params).detect(head.render(alpha))
    assert found.alpha_rad[2] is None and found.confidence[2] == 0.0
    assert np.degrees(np.abs(np.array(found.alpha_rad[:2]) - alpha[:2])).max() < 1.0
    assert min(found.confidence[:2]) > 0.5
    # A middle bar is shared by two joints: both lose it, the third is still measured.
    middle = Renderer(model, options=RenderOptions(occlude=((1, 1),)), seed=4)
    found = detector_for(params).detect(middle.render(alpha))
    assert found.alpha_rad[:2] == [None, None]
    assert found.alpha_rad[2] == pytest.approx(alpha[2], abs=math.radians(1.0))


def test_lens_distortion_is_corrected(params, model) -> None:
    wide = replace(twin_calibration(), dist=(-0.28, 0.09, 0.001, -0.001, 0.0))
    configs = sweep(params, 6, seed=9)
    renderer = Renderer(model, wide, seed=3)
    err = errors_deg(renderer, detector_for(params, wide), configs)
    assert err.mean() <= 0.3 and err.max() <= 1.0
    # The same frames read as if the lens were perfect: large errors, or joints rejected by the
    # geometric check (the distortion bends the bars' spacing).
    naive = errors_deg(renderer, detector_for(params, replace(wide, dist=(0.0,) * 5)), configs, missing_ok=True)
    assert naive.max() > 3 * err.max() and naive.max() > 0.5


def test_extrinsics_from_the_base_plate_reference_markers(params, model) -> None:
    truth = twin_calibration()
    frame = Renderer(model, truth, seed=1).render(np.zeros(params.n_joints))
    guess = truth.with_pose(*look_at_pose((0.0, 0.0), 0.8))  # the camera moved: pose unknown
    refs = detector_for(params, guess).detect(frame).reference_px
    assert len(refs) == 4
    solved = extrinsics_from_reference(guess, np.array(refs), MarkerLayout().reference())
    assert solved.tvec == pytest.approx(truth.tvec, abs=1e-3)
    rot = [cv2.Rodrigues(np.array(c.rvec))[0] for c in (solved, truth)]
    assert np.abs(rot[0] - rot[1]).max() < 2e-3
    err = errors_deg(Renderer(model, truth, seed=6), detector_for(params, solved), sweep(params, 4, seed=1))
    assert err.max() <= 1.0


def test_intrinsics_from_checkerboard_frames() -> None:
    truth = twin_calibration()
    rng = np.random.default_rng(0)
    frames = []
    for k in range(12):  # the board shown all over the field, as the docs tell a user to do
        aim = (0.08 + rng.uniform(-0.17, 0.17), 0.05 + rng.uniform(-0.09, 0.09))
        pose = look_at_pose(aim, 0.40 + 0.1 * rng.uniform(), tilt_deg=rng.uniform(-25, 25),
                            pan_deg=rng.uniform(-25, 25), roll_deg=rng.uniform(-20, 20))
        frames.append(render_checkerboard(truth, *pose, seed=k))
    cal, rms = intrinsics_from_checkerboard(frames, (9, 6), 0.02)
    assert rms < 0.5
    assert cal.fx == pytest.approx(truth.fx, rel=0.01) and cal.fy == pytest.approx(truth.fy, rel=0.01)
    assert cal.cx == pytest.approx(truth.cx, abs=8) and cal.cy == pytest.approx(truth.cy, abs=8)
    # The calibrated lens undistorts like the true one over the whole frame (within 1.5 px at the corners).
    grid = np.stack(np.meshgrid(np.linspace(100, 1180, 7), np.linspace(80, 640, 5)), -1).reshape(-1, 1, 2)
    a = cv2.undistortPoints(grid, truth.K, truth.dist_array, P=truth.K).reshape(-1, 2)
    b = cv2.undistortPoints(grid, cal.K, cal.dist_array, P=truth.K).reshape(-1, 2)
    assert np.abs(a - b).max() < 1.5
    with pytest.raises(CalibrationError, match="at least 3"):
        intrinsics_from_checkerboard(frames[:1] + [np.zeros_like(frames[0])] * 3, (9, 6), 0.02)


def test_calibration_files_are_validated(tmp_path) -> None:
    path = tmp_path / "cal.json"
    twin_calibration().save(path)
    assert load_calibration(path) == twin_calibration()
    good = json.loads(path.read_text())
    bad_cases = [
        ({**good, "fx": -1.0}, "positive"),
        ({**good, "dist": [0.0, 0.0]}, "5 coefficients"),
        ({**good, "tvec": [0.0, 0.0, -0.5]}, "in front"),
        ({**good, "width": "1280"}, "integer"),
        ({**good, "extra": 1}, "fields"),
        ({**good, "version": 2}, "version"),
        ([1, 2], "not an xneck"),
    ]
    for data, reason in bad_cases:
        with pytest.raises(CalibrationError, match=reason):
            calibration_from_dict(data)
    path.write_text("{not json")
    with pytest.raises(CalibrationError, match="not JSON"):
        load_calibration(path)


def test_a_calibration_with_absurd_but_finite_values_is_refused_naming_the_field(xneck, tmp_path) -> None:
    """User audit: cx = 1e300 px, fx = 1e300 px, a distortion coefficient of 1e6 or a camera 1e9 m
    away were accepted (only finiteness was checked) and rendered or measured nonsense."""
    good = json.loads(twin_calibration().to_json())
    cases = [
        ({"cx": 1e300}, r"cx = 1e\+300 px is not plausible: expected -640 to 1920 px"),
        ({"cy": -400.0}, r"cy = -400 px is not plausible"),
        ({"fx": 1e300}, r"fx = 1e\+300 px is not plausible"),
        ({"fy": 0.5}, r"fy = 0.5 px is not plausible"),
        ({"fx": 1000.0, "fy": 3000.0}, r"fy/fx = 3 is not plausible"),
        ({"dist": [1e6, 0.0, 0.0, 0.0, 0.0]}, r"dist k1 = 1e\+06 is not plausible"),
        ({"dist": [0.0, 0.0, 0.0, 5.0, 0.0]}, r"dist p2 = 5 is not plausible"),
        ({"rvec": [1e9, 0.0, 0.0]}, r"\|rvec\| = 1e\+09 rad is not plausible"),
        ({"tvec": [0.0, 0.0, 1e9]}, r"\|tvec\| = 1e\+09 m is not plausible: expected 0.01 to 5 m"),
        ({"tvec": [0.0, 0.0, 1e-9]}, r"\|tvec\| = 1e-09 m is not plausible"),
    ]
    for change, says in cases:
        with pytest.raises(CalibrationError, match=says):
            calibration_from_dict({**good, **change})
    # The command line says so in one line naming the file, before anything is rendered.
    path = tmp_path / "absurd.json"
    path.write_text(json.dumps({**good, "cx": 1e300}))
    out = tmp_path / "r.png"
    r = xneck("camera", "render", "--alpha", "1", "2", "3", "--out", str(out), "--calibration", str(path))
    assert r.returncode == 2 and r.stderr.strip() == f"error: {path}: cx = 1e+300 px is not plausible: expected -640 to 1920 px", r.stderr
    assert not out.exists()
    # Generous enough for real cameras: a wide lens, a phone's portrait frame, a far bench camera.
    calibration_from_dict({**good, "fx": 300.0, "fy": 300.0, "dist": [-0.4, 0.2, 0.001, -0.001, -0.1]})
    calibration_from_dict({**good, "width": 720, "height": 1280, "cx": 360.0, "cy": 640.0})
    calibration_from_dict({**good, "fx": 4000.0, "fy": 4000.0, "tvec": [0.1, -0.2, 3.0]})


def test_a_calibration_file_that_is_not_one_is_refused_in_one_line(xneck, tmp_path) -> None:
    """Audit of 2026-11-29: a JSON of 200,000 nested arrays (400 kB) made `xneck camera detect
    --calibration` print a 54-line RecursionError traceback; undecodable bytes a UnicodeDecodeError.
    Every command loads its calibration through `load_calibration`."""
    deep, binary, huge = tmp_path / "deep.json", tmp_path / "binary.json", tmp_path / "huge.json"
    deep.write_text("[" * 200_000 + "]" * 200_000)
    binary.write_bytes(cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))[1].tobytes())
    huge.write_text(" " * (2 << 20) + "{}")
    for path, says in ((deep, "nested too deeply"), (binary, "not UTF-8 text"), (huge, "larger than 1 MiB")):
        with pytest.raises(CalibrationError, match=says):
            load_calibration(path)
    frame = tmp_path / "f.png"
    cv2.imwrite(str(frame), np.zeros((720, 1280, 3), np.uint8))
    for args in (("camera", "detect", str(frame), "--calibration", str(deep)),
                 ("camera", "render", "--alpha", "1", "2", "3", "--out", str(tmp_path / "r.png"), "--calibration", str(deep)),
                 ("camera", "detect", str(frame), "--calibration", str(binary))):
        r = xneck(*args)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr[-2000:]
        assert str(tmp_path) in lines[0] and ("nested too deeply" in lines[0] or "not UTF-8" in lines[0]), lines


def test_detector_rejects_frames_of_the_wrong_shape(params) -> None:
    detector = detector_for(params)
    for frame in (np.zeros((720, 1280), np.uint8), np.zeros((480, 640, 3), np.uint8), np.zeros((720, 1280, 3), np.float32)):
        with pytest.raises(ValueError):
            detector.detect(frame)
    blank = detector.detect(np.full((720, 1280, 3), 128, np.uint8))
    assert blank.alpha_rad == [None] * params.n_joints and blank.confidence == [0.0] * params.n_joints


def test_cli_render_then_detect_json(tmp_path) -> None:
    from server.cli import app

    runner = CliRunner()
    frame = tmp_path / "f.png"
    r = runner.invoke(app, ["camera", "render", "--alpha", "12", "-25", "33", "--seed", "4", "--out", str(frame)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["camera", "detect", str(frame), "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["alpha_deg"] == pytest.approx([12.0, -25.0, 33.0], abs=1.0) and min(out["confidence"]) > 0.5
    covered = tmp_path / "c.png"
    r = runner.invoke(app, ["camera", "render", "--alpha", "12,-25,33", "--occlude", "3:1", "--out", str(covered)])
    assert r.exit_code == 0, r.output
    out = json.loads(runner.invoke(app, ["camera", "detect", str(covered), "--json"]).stdout)
    assert out["alpha_deg"][2] is None and out["confidence"][2] == 0.0
    # A JPEG whose EXIF says "rotate 90°" (a phone's): its pixels as stored, the calibration's size
    # (user audit of session 45: OpenCV turned it, refused as 720×1280)
    from PIL import Image

    turned = tmp_path / "exif6.jpg"
    image = Image.open(frame)
    exif = Image.Exif()
    exif[0x0112] = 6
    image.save(turned, quality=95, exif=exif)
    r = runner.invoke(app, ["camera", "detect", str(turned), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["alpha_deg"] == pytest.approx([12.0, -25.0, 33.0], abs=1.0)
    cal = tmp_path / "cal.json"
    cal.write_text("[]")
    r = runner.invoke(app, ["camera", "detect", str(frame), "--calibration", str(cal)])
    assert r.exit_code == 2 and "not an xneck camera calibration" in r.output
    r = runner.invoke(app, ["camera", "render", "--alpha", "1", "2", "--out", str(frame)])
    assert r.exit_code == 2 and "3 angles" in r.output
    (tmp_path / "junk.png").write_bytes(b"not an image")
    r = runner.invoke(app, ["camera", "detect", str(tmp_path / "junk.png")])
    assert r.exit_code == 2 and "not a readable image" in r.output
    sheet = tmp_path / "sheet.png"
    assert runner.invoke(app, ["camera", "markers", "--out", str(sheet), "--dpi", "150"]).exit_code == 0
    assert cv2.imread(str(sheet)).shape[:2] == (int(0.297 * 150 / 0.0254), int(0.210 * 150 / 0.0254))  # A4 at 150 dpi


def _bomb_jpeg(width: int, height: int) -> bytes:
    """A 16×16 JPEG whose frame header (SOF0) declares width×height: under 1 kB on disk, and a
    decoder that believes the header allocates width×height×3 bytes before reading any data."""
    buf = cv2.imencode(".jpg", np.full((16, 16, 3), 128, np.uint8))[1]
    data = bytearray(buf.tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 7] = height.to_bytes(2, "big")
    data[sof + 7:sof + 9] = width.to_bytes(2, "big")
    return bytes(data)


def _bomb_png(width: int, height: int) -> bytes:
    import zlib

    buf = cv2.imencode(".png", np.full((16, 16, 3), 128, np.uint8))[1]
    data = bytearray(buf.tobytes())
    data[16:24] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    data[29:33] = zlib.crc32(bytes(data[12:29])).to_bytes(4, "big")  # IHDR's CRC, so the chunk is a valid one
    return bytes(data)


def test_an_image_header_is_read_without_decoding_the_image() -> None:
    from twin.camera.imagefile import ImageFileError, image_size

    assert image_size(_bomb_jpeg(32000, 31000)) == ("jpeg", 32000, 31000)
    assert image_size(_bomb_png(60000, 60000)) == ("png", 60000, 60000)
    real = cv2.imencode(".jpg", np.zeros((720, 1280, 3), np.uint8))[1]
    assert image_size(real.tobytes()) == ("jpeg", 1280, 720)
    progressive = cv2.imencode(".jpg", np.zeros((9, 7, 3), np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1]
    assert image_size(progressive.tobytes()) == ("jpeg", 7, 9)  # SOF2
    for junk, says in ((b"not an image", "neither a PNG nor a JPEG"), (b"\xff\xd8\xff\xe0\x00", "no frame header"),
                       (_bomb_jpeg(0, 16), "0×16"), (b"\xff\xd8\xff\xe0\x00\x01", "segment length 1")):
        with pytest.raises(ImageFileError, match=re.escape(says)):
            image_size(junk)


def test_xneck_camera_detect_refuses_a_decompression_bomb_in_one_line(xneck, tmp_path) -> None:
    # audit of 2026-11-26: a 629-byte JPEG declaring 32000×32000 drove the command to 3 GB, then an
    # OpenCV traceback. The header is read first and a size other than the calibration's refused.
    for name, data, says in (("b32k.jpg", _bomb_jpeg(32000, 32000), "32000×32000"),
                             ("b60k.jpg", _bomb_jpeg(60000, 60000), "60000×60000"),
                             ("b60k.png", _bomb_png(60000, 60000), "60000×60000"),
                             ("small.jpg", _bomb_jpeg(640, 480), "640×480")):
        image = tmp_path / name
        image.write_bytes(data)
        assert len(data) < 1000
        r = xneck("camera", "detect", str(image), "--json")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:"), r.stderr[-2000:]
        assert says in lines[0] and "1280×720" in lines[0] and r.stdout == "", lines


# --- the bus contract: CameraAlpha v2 ------------------------------------------------------------


def test_camera_alpha_v2_carries_missing_joints_and_confidence() -> None:
    from bridge import bus

    msg = bus.CameraAlpha(seq=1, stamp_s=2.05, capture_stamp_s=2.0, alpha_ip_rad=[0.1, None, -0.2],
                          confidence=[0.9, 0.0, 1.0], source="twin-render", dropped=3)
    wire = bus.encode(msg)
    assert b"null" in wire and bus.decode(bus.CAMERA_ALPHA, wire) == msg
    bus.check_camera_alpha(msg, 3)
    # The twin's white-noise camera does not grade: no confidence at all is valid.
    bus.check_camera_alpha(bus.CameraAlpha(seq=1, stamp_s=0.0, capture_stamp_s=0.0, alpha_ip_rad=[0.0] * 3), 3)
    with pytest.raises(bus.BusDecodeError, match="version 1 is not supported"):
        bus.decode(bus.CAMERA_ALPHA, wire.replace(b'"v":2', b'"v":1'))
    bad = [
        (dict(alpha_ip_rad=[0.1, 0.2]), "2 angles for 3 joints"),
        (dict(alpha_ip_rad=[0.1, 4.0, 0.0]), "outside"),
        (dict(confidence=[0.9, 0.5, 1.0]), "0 when missing"),
        (dict(confidence=[1.5, 0.0, 1.0]), "confidence[0]"),
        (dict(confidence=[1.0]), "1 confidences"),
        (dict(dropped=-1), "dropped"),
    ]
    for change, reason in bad:
        with pytest.raises(bus.BusDecodeError, match=re.escape(reason)):
            bus.check_camera_alpha(msgspec_replace(msg, **change), 3)
    schema = bus.json_schema(bus.CameraAlpha)
    assert schema["properties"]["v"]["const"] == 2


def test_a_camera_alpha_captured_after_its_publication_is_refused() -> None:
    """A stray α_IP stamped capture 1e9 s (or 1e300 s) passed every check, was archived, and made
    the identification refuse the whole record for a clock step (audit of 2026-11-29). An exposure
    cannot end after the message that reports it: beyond a rounding tolerance it is refused."""
    from bridge import bus

    msg = bus.CameraAlpha(seq=1, stamp_s=10.05, capture_stamp_s=10.0, alpha_ip_rad=[0.1, 0.2, 0.3], source="twin-render")
    bus.check_camera_alpha_stamps(msg)
    bus.check_camera_alpha(msg, 3)
    same = msgspec_replace(msg, capture_stamp_s=10.05 + 0.5 * bus.CAPTURE_AFTER_PUBLICATION_MAX_S)  # rounding
    bus.check_camera_alpha(same, 3)
    for capture in (1e9, 1e300, 10.05 + 2 * bus.CAPTURE_AFTER_PUBLICATION_MAX_S):
        late = msgspec_replace(msg, capture_stamp_s=capture)
        bus.decode(bus.CAMERA_ALPHA, bus.encode(late))  # structure: valid (archives recorded so far still read)
        for check in (bus.check_camera_alpha_stamps, lambda m: bus.check_camera_alpha(m, 3)):
            with pytest.raises(bus.BusDecodeError, match=r"capture_stamp_s = .* after its publication stamp_s = 10\.05"):
                check(late)
    with pytest.raises(bus.BusDecodeError, match="not finite"):  # built in a process, never decoded
        bus.check_camera_alpha_stamps(msgspec_replace(msg, capture_stamp_s=-math.inf))


def msgspec_replace(msg, **changes):
    import msgspec

    return msgspec.structs.replace(msg, **changes)


# --- the bus process ------------------------------------------------------------------------------


def test_twin_shutter_exposes_at_the_rate_and_releases_after_the_latency() -> None:
    from twin.camera.source import TwinShutter

    shutter = TwinShutter(rate_hz=30.0, latency_s=0.05)
    out = []
    for k in range(500):  # 1 s of truth at 500 Hz
        t = k * 0.002
        out += [(e.capture_s, e.ready_s, float(e.alpha_rad[0])) for e in shutter.feed(t, np.array([t, 0.0, 0.0]))]
    captures = np.array([o[0] for o in out])
    assert len(out) == 29  # exposures at 0, 1/30, ... released by t = 0.998 s
    assert np.diff(captures) == pytest.approx(1 / 30, abs=0.002)
    assert all(0.05 - 1e-9 <= ready - cap < 0.05 + 0.002 for cap, ready, _ in out)
    assert all(a == pytest.approx(cap) for cap, _, a in out)  # α of the exposure time
    # A stalled truth (0.998 s → 1.2 s) loses the exposures due at 1.0, 1.033, ... 1.167 s, and says so.
    shutter.feed(1.2, np.zeros(3))
    assert shutter.dropped == 6


def test_the_twin_shutter_restarts_after_its_clock_jumps_back_or_far_ahead() -> None:
    # audit of 2026-11-26: after 600 s of truth, a twin restarted at t = 0 got no exposure for the next
    # 600 s; one truth stamped 1e12 s stopped the camera for good and counted 3e13 dropped frames.
    from twin.camera.source import TwinShutter

    def run(shutter: TwinShutter, t0: float, seconds: float) -> list:
        out = []
        for k in range(int(round(seconds * 500))):
            out += shutter.feed(t0 + k * 0.002, np.zeros(3))
        return out

    shutter = TwinShutter(rate_hz=30.0, latency_s=0.05)
    run(shutter, 0.0, 10.0)
    lost = shutter.pending  # taken on the old clock, never released on the new one
    assert shutter.restarts == 0 and shutter.dropped == 0 and lost >= 1
    again = run(shutter, 0.0, 2.0)  # the clock restarts at 0
    assert shutter.restarts == 1 and shutter.last_jump is not None and shutter.last_jump[1] == 0.0
    assert len(again) == 59 and shutter.dropped == lost  # as many as the first 2 s of a new shutter
    assert np.diff([e.capture_s for e in again]) == pytest.approx(1 / 30, abs=0.002)
    assert all(0.0 <= e.capture_s < 2.0 for e in again)  # nothing of the old clock

    lost += shutter.pending
    shutter.feed(1e12, np.zeros(3))  # one truth far ahead: a new clock, not 3e13 lost frames
    assert shutter.restarts == 2 and shutter.dropped == lost
    lost += shutter.pending
    after = run(shutter, 2.0, 2.0)  # and back to the twin's clock
    assert shutter.restarts == 3 and len(after) == 59 and shutter.dropped == lost
    assert shutter.discarded == lost  # every one of them taken, then discarded pending

    # a short stall is still a stall: its exposures are dropped and counted, the schedule kept
    run(shutter, 4.0, 0.2)
    shutter.feed(4.4, np.zeros(3))
    assert shutter.restarts == 3 and shutter.dropped == lost + 6  # due at 4.2, 4.233, ... 4.367 s


def test_camera_process_publishes_rendered_alpha_ip_from_the_twin_on_a_real_bus(params) -> None:
    import threading

    from busutil import bus_pair, run_in_thread, wait_until

    from bridge import bus
    from bridge.node import BridgeConfig, run_realtime
    from server.cli.processes import bridge_node
    from twin.camera.process import CameraNode
    from twin.camera.source import TwinShutter
    from twin.model.numeric import build
    from twin.sim.driver import TwinDriver, TwinDriverConfig

    n_ticks = 1500  # 3 s of the real-time twin at 500 Hz, drives disabled: the neck rests on its springs
    with bus_pair() as (_hub, hub, connect):
        got: dict[str, list] = {bus.TWIN_TRUTH: [], bus.CAMERA_ALPHA: []}
        lock = threading.Lock()

        def collect(sample) -> None:
            key = str(sample.key_expr)
            with lock:
                got[key].append(bus.decode(key, sample.payload.to_bytes()))

        subs = [hub.declare_subscriber(k, collect) for k in got]
        driver = TwinDriver(TwinDriverConfig(n_motors=params.n_cables, camera=False), params)
        driver.configure()
        twin = bridge_node(connect(), driver, params, BridgeConfig(lockstep=False, max_ticks=n_ticks))
        camera = CameraNode(connect(), detector_for(params), instance="test")
        stop = threading.Event()
        latency = params.sensors.camera_latency
        cam_thread, cam_out = run_in_thread(camera.run_twin, Renderer(build(params), seed=1), TwinShutter(30.0, latency), stop,
                                            None, 3.0)
        twin_thread, twin_out = run_in_thread(run_realtime, twin, stop)
        try:
            assert wait_until(lambda: len(got[bus.CAMERA_ALPHA]) >= 40, 30.0), f"{len(got[bus.CAMERA_ALPHA])} frames"
        finally:
            twin_thread.join(30)
            stop.set()
            cam_thread.join(10)
            # the last frame may still be on its way (CI of 2026-11-27: 89 published, 88 received at once)
            wait_until(lambda: len(got[bus.CAMERA_ALPHA]) >= camera.frames, 5.0)
            twin.shutdown()
            camera.close()
            for s in subs:
                s.undeclare()
        assert "error" not in cam_out and "error" not in twin_out, (cam_out, twin_out)
        frames, truths = list(got[bus.CAMERA_ALPHA]), list(got[bus.TWIN_TRUTH])
    assert {f.source for f in frames} == {"twin-render"}  # the twin's own noise camera is off
    truth_t = np.array([m.stamp_s for m in truths])
    truth_a = np.array([m.alpha_rad for m in truths])
    captures = np.array([f.capture_stamp_s for f in frames])
    assert np.median(np.diff(captures)) == pytest.approx(1 / 30, abs=0.0021)  # 30 fps of the bus clock
    for f in frames:
        bus.check_camera_alpha(f, params.n_joints)
        assert latency - 1e-9 <= f.stamp_s - f.capture_stamp_s <= latency + 0.1  # published after the exposure latency
        k = int(np.argmin(np.abs(truth_t - f.capture_stamp_s)))
        assert abs(truth_t[k] - f.capture_stamp_s) < 1e-6
        assert None not in f.alpha_ip_rad and min(f.confidence) > 0.5
        assert np.degrees(np.abs(np.array(f.alpha_ip_rad) - truth_a[k])).max() < 1.0
    assert camera.truth_rejected == 0 and camera.frames == len(frames)


# --- offline alignment ----------------------------------------------------------------------------


def excitation(t: np.ndarray, first_deg: float = 28.0) -> np.ndarray:
    """A non-periodic multi-sine per joint within ±(``first_deg`` + 18)° (rad), as an
    identification excitation (also tests/test_camera_sources.py)."""
    f = np.array([[0.23, 0.61], [0.31, 0.47], [0.17, 0.53]])
    return np.radians(np.column_stack([first_deg * np.sin(2 * np.pi * f[j, 0] * t + j) + 18 * np.sin(2 * np.pi * f[j, 1] * t + 2 * j)
                                       for j in range(3)]))


def test_a_video_of_a_campaign_is_aligned_within_one_frame(tmp_path, params, model) -> None:
    from bridge import bus
    from bridge.archive import write_campaign
    from bridge.archive_read import read_campaign
    from server.cli import app

    # The campaign: 20 s of truth at 100 Hz on its (simulated) clock.
    t = np.arange(0.0, 20.0, 0.01)
    alpha = excitation(t)
    zeros = [0.0] * params.n_cables
    truths = [(bus.TWIN_TRUTH, int((1.7e9 + tk) * 1e9), bus.Truth(
        seq=k + 1, stamp_s=float(tk), alpha_rad=a.tolist(), alpha_dot_rad_s=[0.0] * 3, theta_rad=zeros, theta_dot_rad_s=zeros,
        tension_N=zeros, elongation_m=zeros, slack=[False] * params.n_cables, near_singular=False)) for k, (tk, a) in enumerate(zip(t, alpha))]
    camp = write_campaign(tmp_path / "c.mcap", truths, {"campaign_id": "c1", "kind": "identification"})
    # The video: started 4.321 s into the campaign (not a whole number of frames), 10 s at 30 fps.
    offset = 4.321
    renderer = Renderer(model, seed=8)
    video = tmp_path / "run.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (1280, 720))
    for k in range(300):
        writer.write(renderer.render(excitation(np.array([offset + k / 30.0]))[0]))
    writer.release()
    out = tmp_path / "aligned.mcap"
    r = CliRunner().invoke(app, ["camera", "align", str(video), str(camp), "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    prov = json.loads(r.stdout)
    assert abs(prov["offset_s"] - offset) < 1 / 30  # the requirement: within one frame period
    assert abs(prov["offset_s"] - offset) < 0.005 and abs(prov["drift"]) < 1e-3
    assert prov["reference"] == "truth" and prov["rms_deg"] < 0.5
    # JSON numbers, not strings (user audit: "offset_s": "4.321000"); the archive's record keeps strings.
    floats = ("video_fps", "offset_s", "drift", "rms_deg", "runner_up_offset_s", "runner_up_rms_deg")
    assert all(type(prov[k]) is float for k in floats), prov
    ints = ("frames", "frames_used", "frames_declared", "frames_lost", "frames_written", "missing_joints",
            "replaced_camera_messages", "images", "replaced_images")
    assert all(type(prov[k]) is int for k in ints), prov
    assert prov["frames"] == 300 and prov["images"] == 50 and prov["video_fps"] == 30.0
    back = read_campaign(out)
    assert back.metadata["xneck.camera.alignment"]["offset_s"] == f"{prov['offset_s']:.6f}"
    frames = [m for _, m in back.messages(bus.CAMERA_ALPHA)]
    assert len(frames) == 300 and {f.source for f in frames} == {"file:run.mp4"}
    assert len(back.messages(bus.TWIN_TRUTH)) == len(truths)  # everything recorded is kept
    assert back.metadata["xneck.camera.alignment"]["video_sha256"] == prov["video_sha256"]
    assert back.info["campaign_id"] == "c1"
    images = back.messages("/xneck/camera/image")  # 5 JPEGs per second of video, for Foxglove's Image panel
    assert back.schemas["/xneck/camera/image"] == "foxglove.CompressedImage" and len(images) == 50
    first = images[0][1]
    assert first["format"] == "jpeg" and first["timestamp"]["sec"] == 4
    jpeg = cv2.imdecode(np.frombuffer(base64.b64decode(first["data"]), np.uint8), cv2.IMREAD_COLOR)
    assert jpeg.shape == (720, 1280, 3)
    t_ip = np.array([f.capture_stamp_s for f in frames])
    a_ip = np.array([f.alpha_ip_rad for f in frames], dtype=float)
    assert np.abs(t_ip - (offset + np.arange(300) / 30.0)).max() < 0.005
    assert np.degrees(np.abs(a_ip - excitation(t_ip))).max() < 1.0
    # Never overwrite; a campaign that the video does not overlap is refused with the reason.
    r = CliRunner().invoke(app, ["camera", "align", str(video), str(camp), "--out", str(out)])
    assert r.exit_code == 2 and "exists already" in r.output
    short = write_campaign(tmp_path / "short.mcap", truths[:50], {"campaign_id": "c2"})
    r = CliRunner().invoke(app, ["camera", "align", str(video), str(short), "--out", str(tmp_path / "x.mcap")])
    assert r.exit_code == 2 and "never overlap" in r.output
    # Another motion (user audit of session 45: written with exit 0, rms 7°, drift -108 %): refused.
    other = write_campaign(tmp_path / "other.mcap", [(k, ns, msgspec.structs.replace(m, alpha_rad=(-np.array(m.alpha_rad)).tolist()))
                                                     for k, ns, m in truths], {"campaign_id": "c3"})
    r = CliRunner().invoke(app, ["camera", "align", str(video), str(other), "--out", str(tmp_path / "y.mcap")])
    assert r.exit_code == 2 and "does not match this campaign's motion" in r.output, r.output
    assert not (tmp_path / "y.mcap").exists()


def test_detection_health_in_the_console(tmp_path) -> None:
    import httpx
    from busutil import wait_until
    from server_harness import running_server

    from bridge import bus
    from bridge.session import open_session, publisher

    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=30) as c:
        assert c.get("/api/system/health").json()["camera"] is None  # no camera yet
        hub = c.get("/api/system/health").json()["hub"]
        with open_session(listen=["tcp/127.0.0.1:0"], connect=[hub]) as session:
            pub = publisher(session, bus.CAMERA_ALPHA)
            msg = bus.CameraAlpha(seq=1, stamp_s=3.0, capture_stamp_s=2.95, alpha_ip_rad=[0.1, None, 0.2],
                                  confidence=[0.99, 0.0, 0.97], source="twin-render", dropped=2)

            def seen() -> bool:
                pub.put(msg)
                return c.get("/api/system/health").json()["camera"] is not None

            assert wait_until(seen, 20.0)
        camera = c.get("/api/system/health").json()["camera"]
    assert camera["source"] == "twin-render" and camera["missing_joints"] == [2] and camera["dropped"] == 2
    assert camera["confidence"] == [0.99, 0.0, 0.97] and camera["fresh"] is True


def test_xneck_camera_file_source_publishes_on_the_bus(tmp_path, model) -> None:
    import subprocess
    import sys
    import threading

    from busutil import bus_pair, wait_until

    from bridge import bus

    alphas = np.radians([[5.0 * k, -3.0 * k, 2.0 * k] for k in range(15)])
    renderer = Renderer(model, options=RenderOptions(occlude=((3, 1),)), seed=2)  # joint 3 hidden throughout
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (1280, 720))
    for a in alphas:
        writer.write(renderer.render(a))
    writer.release()
    with bus_pair() as (hub, session, _connect):
        got, lock = [], threading.Lock()

        def collect(sample) -> None:
            with lock:
                got.append(bus.decode(bus.CAMERA_ALPHA, sample.payload.to_bytes()))

        sub = session.declare_subscriber(bus.CAMERA_ALPHA, collect)
        done = subprocess.run([sys.executable, "-m", "server.cli", "camera", "--source", f"file:{video}", "--fast", "--t0", "100",
                               "--connect", hub], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        assert wait_until(lambda: len(got) >= len(alphas), 10.0)
        sub.undeclare()
    frames = sorted(got, key=lambda m: m.seq)
    assert len(frames) == len(alphas) and {m.source for m in frames} == {"file:clip.avi"}
    assert [m.capture_stamp_s for m in frames] == pytest.approx(100.0 + np.arange(len(alphas)) / 30.0)
    for m, a in zip(frames, alphas):
        assert m.alpha_ip_rad[2] is None and m.confidence[2] == 0.0
        assert np.degrees(np.abs(np.array(m.alpha_ip_rad[:2]) - a[:2])).max() < 1.0
    bad = subprocess.run([sys.executable, "-m", "server.cli", "camera", "--source", "webcam"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "expected usb:N" in bad.stderr


def test_identification_reader_drops_frames_with_a_missing_joint(tmp_path, params) -> None:
    from bridge import bus
    from bridge.archive import write_campaign
    from twin.identification.pipeline import IdentificationError
    from twin.identification.record import campaign_data_from_mcap

    n_m = params.n_cables
    states = [(bus.MOTOR_STATE, int(k * 2e6) + 1, bus.MotorState(seq=k + 1, stamp_s=k * 0.002, theta_rad=[0.01 * k] * n_m,
                                                                  force_applied_N=[10.0] * n_m, drive="active", epoch="e", bridge="b"))
              for k in range(1200)]  # 2.4 s: the pipeline's minimum record
    frames = [(bus.CAMERA_ALPHA, int(k / 30 * 1e9) + 2, bus.CameraAlpha(
        seq=k + 1, stamp_s=k / 30 + 0.05, capture_stamp_s=k / 30, source="twin-render",
        alpha_ip_rad=[0.1, None, 0.3] if k in (4, 5) else [0.1, 0.2, 0.3],
        confidence=[1.0, 0.0, 1.0] if k in (4, 5) else [1.0, 1.0, 1.0])) for k in range(72)]
    path = write_campaign(tmp_path / "c.mcap", sorted(states + frames, key=lambda m: m[1]), {"campaign_id": "c"})
    data = campaign_data_from_mcap(path)
    assert len(data.t_ip_s) == 70 and np.isfinite(data.alpha_ip_rad).all()
    assert 4 / 30 not in data.t_ip_s.tolist() and data.alpha_ip_rad[0].tolist() == [0.1, 0.2, 0.3]
    blind = [(key, t, msgspec_replace(m, alpha_ip_rad=[None, None, None], confidence=[0.0] * 3)) for key, t, m in frames]
    path = write_campaign(tmp_path / "blind.mcap", sorted(states + blind, key=lambda m: m[1]), {"campaign_id": "b"})
    with pytest.raises(IdentificationError, match="no camera frame measures every joint"):
        campaign_data_from_mcap(path)


def test_a_camera_behind_a_fast_twin_drops_frames_and_counts_every_one(params, model) -> None:
    """Truth arriving far faster than real time (a lockstep twin): the camera cannot render every
    exposure; each one is either published or counted as dropped, never silently lost."""
    import threading

    from busutil import bus_pair, run_in_thread, wait_until

    from bridge import bus
    from bridge.session import publisher
    from twin.camera.process import CameraNode
    from twin.camera.source import TwinShutter

    with bus_pair() as (_hub, hub, connect):
        camera = CameraNode(connect(), detector_for(params), instance="fast", queue_frames=2)
        shutter = TwinShutter(30.0, 0.05)
        stop = threading.Event()
        thread, out = run_in_thread(camera.run_twin, Renderer(model, seed=3), shutter, stop, None, 1.5)
        pub = publisher(hub, bus.TWIN_TRUTH)
        zeros = [0.0] * params.n_cables
        assert wait_until(lambda: (pub.put(bus.Truth(
            seq=0, stamp_s=0.0, alpha_rad=[0.0] * 3, alpha_dot_rad_s=[0.0] * 3, theta_rad=zeros, theta_dot_rad_s=zeros,
            tension_N=zeros, elongation_m=zeros, slack=[False] * params.n_cables, near_singular=False)), camera.truth_received > 0)[1], 10)
        for k in range(1, 1501):  # 3 s of simulated time in a burst
            t = k * 0.002
            pub.put(bus.Truth(seq=k, stamp_s=t, alpha_rad=[0.3 * math.sin(t), 0.0, -0.2], alpha_dot_rad_s=[0.0] * 3,
                              theta_rad=zeros, theta_dot_rad_s=zeros, tension_N=zeros, elongation_m=zeros,
                              slack=[False] * params.n_cables, near_singular=False))
        thread.join(60)
        camera.close()
    assert "error" not in out, out
    assert camera.queue_dropped > 0, "the burst should outrun the renderer"
    # Every exposure taken is published, dropped behind the renderer, still pending, or discarded
    # pending when the truth's clock jumped: a burst this fast may lose Truth messages on the bus
    # (their congestion control drops), and a gap of over 1 s is a new clock (CI of 2026-11-27:
    # 1.233 → 2.768 s, 2 exposures pending then, which this sum had left out).
    assert camera.frames + camera.queue_dropped + shutter.pending + shutter.discarded == shutter.exposures, (
        camera.frames, camera.queue_dropped, shutter)
    assert camera.dropped == camera.queue_dropped + shutter.dropped


def test_a_camera_on_the_twin_renders_one_twins_truth_and_takes_the_next_only_once_it_is_silent(params, model) -> None:
    """Two twins on the hub: their truths (two clocks, two poses) went into one shutter (audit of
    2026-11-29). The camera renders the run it heard first (the attachment, bridge.session.run_of),
    counts the other's as foreign, and follows another run only after FOLLOW_SILENT_S of silence."""
    import threading

    from busutil import bus_pair, run_in_thread, wait_until

    from bridge import bus
    from bridge.session import publisher, run_attachment
    from twin.camera.process import FOLLOW_SILENT_S, CameraNode
    from twin.camera.source import TwinShutter

    zeros = [0.0] * params.n_cables

    def truth(k: int, t: float, alpha: list[float]) -> bus.Truth:
        return bus.Truth(seq=k, stamp_s=t, alpha_rad=alpha, alpha_dot_rad_s=[0.0] * 3, theta_rad=zeros,
                         theta_dot_rad_s=zeros, tension_N=zeros, elongation_m=zeros, slack=[False] * params.n_cables,
                         near_singular=False)

    with bus_pair() as (_hub, hub, connect):
        camera = CameraNode(connect(), detector_for(params), instance="one-twin")
        shutter = TwinShutter(30.0, 0.05)
        stop = threading.Event()
        thread, out = run_in_thread(camera.run_twin, Renderer(model, seed=3), shutter, stop, None, 30.0)
        pub = publisher(hub, bus.TWIN_TRUTH)
        ours, stray = run_attachment("ours"), run_attachment("stray")
        try:
            assert wait_until(lambda: (pub.put(truth(0, 100.0, [0.2, 0.1, -0.1]), attachment=ours),
                                       camera.truth_received > 0)[1], 10)
            for k in range(1, 151):  # 0.3 s of both twins, about in real time
                pub.put(truth(k, 100.0 + 0.002 * k, [0.2, 0.1, -0.1]), attachment=ours)
                pub.put(truth(k, 0.002 * k, [-0.3, 0.0, 0.3]), attachment=stray)
                time.sleep(0.002)
            assert wait_until(lambda: camera.frames >= 3, 20), (camera.frames, shutter)
            assert camera.run == "ours" and camera.truth_foreign > 0 and shutter.restarts == 0, (camera.run, shutter)
            time.sleep(FOLLOW_SILENT_S + 0.2)  # our twin stops: the stray's is taken, on its own clock
            assert wait_until(lambda: (pub.put(truth(200, 0.5, [-0.3, 0.0, 0.3]), attachment=stray),
                                       camera.run == "stray")[1], 10)
            # (the run is switched just before the truth is fed to the shutter, in the callback)
            assert wait_until(lambda: shutter.restarts >= 1, 5) and shutter.restarts == 1
        finally:
            stop.set()
            thread.join(30)
            camera.close()
    assert "error" not in out, out


def test_a_video_declaring_frames_larger_than_any_camera_is_refused_before_decoding(tmp_path) -> None:
    """Audit of 2026-11-26 (follow-up of the JPEG bombs): a video's decoder allocates the frame
    size its container declares; `FileSource` refuses a side beyond bus.FRAME_MAX_SIDE_PX before
    reading a frame, and opens a small video as before."""
    import cv2

    from bridge import bus
    from twin.camera.source import FileSource, SourceError

    def video(name: str, width: int, height: int) -> str:
        path = str(tmp_path / name)
        writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (width, height))
        for _ in range(3):
            writer.write(np.zeros((height, width, 3), np.uint8))
        writer.release()
        return path

    small = FileSource(video("small.avi", 64, 48))
    try:
        frame = small.read()
        assert frame is not None and frame.image.shape == (48, 64, 3)
    finally:
        small.close()
    wide = bus.FRAME_MAX_SIDE_PX + 8
    with pytest.raises(SourceError, match=f"frames of {wide}×8 px, more than"):
        FileSource(video("wide.avi", wide, 8))


def test_the_alignment_takes_the_controllers_estimate_first_as_a_prototypes_campaign_has_it(tmp_path, params) -> None:
    """Truth audit of 2026-12-01: `auto` aligned a twin's campaign on the twin's truth, which a
    prototype's campaign never has, so the alignment was checked on an easier reference than the
    robot's. α̂ first, the truth only where no α̂ was recorded, or when asked for."""
    from bridge import bus
    from bridge.archive import write_campaign
    from twin.camera.align import campaign_reference

    t = np.arange(0.0, 2.0, 0.01)
    zeros = [0.0] * params.n_cables
    truth = [(bus.TWIN_TRUTH, int((1.7e9 + tk) * 1e9), bus.Truth(
        seq=k + 1, stamp_s=float(tk), alpha_rad=[0.1, 0.0, 0.0], alpha_dot_rad_s=[0.0] * 3, theta_rad=zeros,
        theta_dot_rad_s=zeros, tension_N=zeros, elongation_m=zeros, slack=[False] * params.n_cables,
        near_singular=False)) for k, tk in enumerate(t)]
    hat = [(bus.CONTROLLER_STATUS, int((1.7e9 + tk) * 1e9), bus.ControllerStatus(
        seq=k + 1, stamp_s=float(tk), law="law2", tick_s=0.002, compute_s=1e-4, overruns=0, deadline_misses=0,
        saturated=[False] * params.n_cables, alpha_hat_rad=[0.2, 0.0, 0.0], alpha_d_rad=[0.0] * 3, e_rad=[0.0] * 3,
        holding=False)) for k, tk in enumerate(t)]
    both = write_campaign(tmp_path / "both.mcap", truth + hat, {"campaign_id": "c1", "kind": "identification"})
    only_truth = write_campaign(tmp_path / "truth.mcap", truth, {"campaign_id": "c2", "kind": "identification"})
    ref = campaign_reference(both)
    assert ref.name == "alpha_hat" and np.allclose(ref.alpha_rad[:, 0], 0.2)
    assert campaign_reference(both, "truth").name == "truth"
    assert campaign_reference(only_truth).name == "truth"
