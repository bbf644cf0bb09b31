"""Where the camera's frames come from, when they stop coming (audit of 2026-11-29).

- A live camera (`UsbSource`) that misses a grab retries for about a second
  (`source.RETRY_WINDOW_S`) and carries on; one that does not come back ends `xneck camera`
  non-zero, saying which camera and after how long. No USB camera exists here: a fake
  `cv2.VideoCapture` stands for it, the lowest layer, and everything above it is the real code.
- A damaged video (`FileSource`): real files written by OpenCV, then damaged as a copy interrupted
  or a bad sector would: an undecodable frame is skipped and the later frames keep their own time,
  a frame the container's clock skips is counted, and a video that ends short of what its container
  declares says by how much.
"""

from __future__ import annotations

import re
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from test_camera import excitation  # noqa: E402

from twin.camera.render import Renderer  # noqa: E402
from twin.camera.source import FileSource, SourceError, UsbSource  # noqa: E402

FPS = 30.0


# --- a USB camera that misses grabs ---------------------------------------------------------------


class FakeCamera:
    """A V4L2 camera as OpenCV shows it: ``grab`` succeeds while ``plan(k)`` (k = 1, 2, … the grab's
    number) says so, ``retrieve`` then returns a copy of ``image``."""

    plan = staticmethod(lambda k: True)
    image = np.zeros((720, 1280, 3), np.uint8)

    def __init__(self, *_args: object) -> None:
        self.grabs = 0

    def isOpened(self) -> bool:
        return True

    def set(self, *_args: object) -> bool:
        return True

    def get(self, prop: int) -> float:
        return FPS if prop == cv2.CAP_PROP_FPS else 0.0

    def grab(self) -> bool:
        self.grabs += 1
        time.sleep(0.002)
        return bool(type(self).plan(self.grabs))

    def retrieve(self) -> tuple[bool, np.ndarray]:
        return True, type(self).image.copy()

    def release(self) -> None:
        pass


@pytest.fixture
def camera(monkeypatch):
    """``FakeCamera`` in place of ``cv2.VideoCapture``; set its ``plan``."""
    monkeypatch.setattr(cv2, "VideoCapture", FakeCamera)
    monkeypatch.setattr(FakeCamera, "plan", staticmethod(lambda k: True))
    return FakeCamera


def test_a_usb_camera_that_misses_a_few_grabs_carries_on_and_counts_the_gap(camera) -> None:
    camera.plan = staticmethod(lambda k: not 3 <= k <= 6)  # grabs 3-6 fail: a USB hiccup
    source = UsbSource("0")
    frames = [source.read() for _ in range(4)]
    assert all(f is not None for f in frames) and isinstance(source.cap, FakeCamera)
    assert source.cap.grabs == 8 and source.retries == 4
    assert source.dropped >= 1  # the time the retries took is a gap of frames the camera lost


def test_a_usb_camera_that_stops_raises_naming_it_after_about_a_second(camera) -> None:
    camera.plan = staticmethod(lambda k: k <= 5)  # unplugged after 5 frames
    source = UsbSource("2")
    for _ in range(5):
        assert source.read() is not None
    t0 = time.monotonic()
    with pytest.raises(SourceError) as lost:
        source.read()
    waited = time.monotonic() - t0
    from twin.camera.source import RETRY_WINDOW_S

    # retried over the window, then gave up (the upper bound only says it did give up: a loaded
    # machine stretches the wait, so it is 5 times the window's own length)
    assert RETRY_WINDOW_S <= waited < RETRY_WINDOW_S + 5.0
    message = str(lost.value)
    found = re.match(r"usb:2: no frame for (\d+\.\d) s \(\d+ grabs failed\), after \d+\.\d s running and 5 frames", message)
    assert found and float(found[1]) >= RETRY_WINDOW_S, message  # a stall makes it 2.0 s, never less than the window
    assert isinstance(source.cap, FakeCamera) and source.cap.grabs > 6  # it did retry


def test_a_failed_retrieve_is_retried_like_a_failed_grab(camera, monkeypatch) -> None:
    fails = iter([True, True])
    monkeypatch.setattr(camera, "retrieve", lambda self: (False, None) if next(fails, False) else (True, camera.image.copy()))
    source = UsbSource("0")
    assert source.read() is not None and source.retries == 2


SHIM = """
import sys, time, cv2
image, good = cv2.imread(sys.argv.pop(1)), int(sys.argv.pop(1))
class Unplugged:  # a camera unplugged after `good` frames: every later grab fails, as V4L2's does
    grabs = 0
    def __init__(self, *a): pass
    def isOpened(self): return True
    def set(self, *a): return True
    def get(self, prop): return 30.0 if prop == cv2.CAP_PROP_FPS else 0.0
    def grab(self):
        Unplugged.grabs += 1
        time.sleep(1 / 30)
        return Unplugged.grabs <= good
    def retrieve(self): return True, image.copy()
    def release(self): pass
cv2.VideoCapture = Unplugged
from server.cli import main
main()
"""


def test_xneck_camera_on_a_usb_camera_unplugged_exits_1_naming_it(tmp_path, model) -> None:
    """Audit of 2026-11-29: one failed grab ended `xneck camera --source usb:0` with exit 0 and the
    INFO line of a normal end, 2.3 s after it started."""
    from busutil import bus_pair, wait_until

    from bridge import bus
    from twin.camera.source import RETRY_WINDOW_S

    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), Renderer(model, seed=1).render(np.radians([10.0, -20.0, 30.0])))
    with bus_pair() as (hub, session, _connect):
        got = []
        sub = session.declare_subscriber(bus.CAMERA_ALPHA, lambda s: got.append(s))
        done = subprocess.run([sys.executable, "-c", SHIM, str(frame), "60", "camera", "--source", "usb:0",
                               "--frame-rate-hz", "0", "--clock", "local", "--connect", hub], capture_output=True, text=True,
                              timeout=120)  # it ends by itself: an exit, not a hang
        wait_until(lambda: len(got) >= 20, 5.0)
        sub.undeclare()
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert done.returncode == 1, done.stderr[-3000:]
    found = re.match(r"error: usb:0: no frame for (\d+\.\d) s \(\d+ grabs failed\), after \d+\.\d s running and 60 frames",
                     errors[0]) if len(errors) == 1 else None
    assert found and float(found[1]) >= RETRY_WINDOW_S, done.stderr[-3000:]  # 2.0 s after a stall: at least the window
    assert "Traceback" not in done.stderr
    assert len(got) >= 20  # what it measured before the camera went was published


# --- damaged video files --------------------------------------------------------------------------


def write_video(path: Path, images) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, images[0].shape[1::-1])
    for image in images:
        writer.write(image)
    writer.release()
    return path


def numbered(n: int) -> list[np.ndarray]:
    """Small grey frames whose level says their number (k·8)."""
    return [np.full((48, 64, 3), 8 * k, np.uint8) for k in range(n)]


def number_of(image: np.ndarray) -> int:
    return round(float(image.mean()) / 8)


def avi_chunks(data: bytes) -> list[tuple[int, int]]:
    """(offset, size) of each frame's chunk in an AVI's movi list (RIFF: tag, little-endian size, data, pad)."""
    i, out = data.index(b"movi") + 4, []
    while i + 8 <= len(data) and data[i:i + 4] != b"idx1":
        size = struct.unpack("<I", data[i + 4:i + 8])[0]
        if data[i + 2:i + 4] == b"dc":
            out.append((i, size))
        i += 8 + size + (size & 1)
    return out


def damaged(video: Path, name: str, how: str, k: int = 0) -> Path:
    """A copy of ``video`` with frame ``k`` made ``undecodable`` (its JPEG zeroed, the container
    intact), ``dropped`` (a zero-size chunk: a frame the recorder dropped, on the container's clock),
    its chunk ``unframed`` (header zeroed: the container loses the frame and its time), or the file
    ``truncated`` in the middle of frame k (a copy interrupted, a full card)."""
    data = bytearray(video.read_bytes())
    at, size = avi_chunks(bytes(data))[k]
    if how == "truncated":
        data = data[:at + 8 + size // 2]
    else:
        if how == "undecodable":
            data[at + 8:at + 8 + size] = bytes(size)
        elif how == "dropped":  # 00dc of size 0, then a JUNK chunk over the old data: nothing else moves
            data[at + 4:at + 16] = struct.pack("<I", 0) + b"JUNK" + struct.pack("<I", size - 8)
        else:
            data[at:at + 8] = bytes(8)
    out = video.with_name(name)
    out.write_bytes(bytes(data))
    return out


def read_all(source: FileSource) -> list:
    frames = []
    while (f := source.read()) is not None:
        frames.append(f)
    source.close()
    return frames


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    return write_video(tmp_path_factory.mktemp("clip") / "clip.avi", numbered(30))


def test_a_whole_video_is_read_on_its_own_clock_and_reports_nothing(clip) -> None:
    source = FileSource(clip, t0_s=5.0)
    frames = read_all(source)
    assert [number_of(f.image) for f in frames] == list(range(30))
    assert [f.capture_s for f in frames] == pytest.approx(5.0 + np.arange(30) / FPS)
    assert source.declared == 30 and source.dropped == 0 and source.loss() is None


def test_an_undecodable_frame_is_skipped_and_the_later_frames_keep_their_time(clip) -> None:
    """Audit of 2026-11-29: the read that failed on it ended the video there (14 of 30 frames, no
    word); where the reader did go on, every later frame was stamped a frame period early."""
    source = FileSource(damaged(clip, "undecodable.avi", "undecodable", k=14))
    frames = read_all(source)
    numbers = [number_of(f.image) for f in frames]
    assert numbers == [k for k in range(30) if k != 14]
    assert [f.capture_s for f in frames] == pytest.approx(np.array(numbers) / FPS, abs=1e-6)
    assert source.undecodable == 1 and source.dropped == 1
    loss = source.loss()
    assert loss is not None and loss.damaged
    assert "29 of the 30 frames" in loss.text and "1 could not be decoded" in loss.text, loss.text


def test_a_frame_the_container_skips_is_counted_and_the_later_frames_keep_their_time(clip) -> None:
    """A zero-size chunk is a frame the recorder dropped: the container's clock (CAP_PROP_POS_MSEC)
    steps over it, the frame index does not."""
    source = FileSource(damaged(clip, "dropped.avi", "dropped", k=15))
    frames = read_all(source)
    numbers = [number_of(f.image) for f in frames]
    assert numbers == [k for k in range(30) if k != 15]
    assert [f.capture_s for f in frames] == pytest.approx(np.array(numbers) / FPS, abs=1e-6)
    assert source.gaps == 1 and source.dropped == 1 and source.undecodable == 0
    loss = source.loss()
    assert loss is not None
    assert not loss.damaged and "1 the container's clock skips" in loss.text, loss.text


def test_a_truncated_video_says_how_many_frames_it_lacks(clip) -> None:
    source = FileSource(damaged(clip, "trunc.avi", "truncated", k=12))
    frames = read_all(source)
    n = len(frames)
    assert n in (12, 13) and [number_of(f.image) for f in frames] == list(range(n))
    loss = source.loss()
    assert loss is not None and loss.damaged and source.dropped == 30 - n
    assert f"{n} of the 30 frames" in loss.text and f"{30 - n} missing" in loss.text, loss.text
    assert f"after {(n - 1) / FPS:.3f} s" in loss.text


def test_a_frame_whose_chunk_is_lost_is_counted_though_its_time_cannot_be(clip) -> None:
    """The audit's hole.avi: the chunk's header is gone, the demuxer resynchronises on the next one
    and numbers it as if nothing were missing. Nothing in the file says where: the count does."""
    source = FileSource(damaged(clip, "unframed.avi", "unframed", k=15))
    frames = read_all(source)
    assert len(frames) == 29
    loss = source.loss()
    assert loss is not None
    assert loss.damaged and "1 missing" in loss.text, loss.text


def test_a_video_stopped_before_its_end_reports_no_loss(clip) -> None:
    source = FileSource(damaged(clip, "trunc2.avi", "truncated", k=12))
    assert source.read() is not None
    source.close()
    assert source.loss() is None  # not read to its end: nothing to compare with the container's count


# --- `xneck camera --source file:` on damaged videos ----------------------------------------------


@pytest.fixture(scope="module")
def rendered_clip(tmp_path_factory, model) -> tuple[Path, np.ndarray]:
    alphas = np.radians([[1.5 * k, -1.0 * k, 0.8 * k] for k in range(30)])
    renderer = Renderer(model, seed=2)
    path = tmp_path_factory.mktemp("rendered") / "run.avi"
    return write_video(path, [renderer.render(a) for a in alphas]), alphas


def run_camera_on(video: Path) -> tuple[subprocess.CompletedProcess, list]:
    from busutil import bus_pair, wait_until

    from bridge import bus

    with bus_pair() as (hub, session, _connect):
        got, lock = [], threading.Lock()

        def collect(sample) -> None:
            with lock:
                got.append(bus.decode(bus.CAMERA_ALPHA, sample.payload.to_bytes()))

        sub = session.declare_subscriber(bus.CAMERA_ALPHA, collect)
        done = subprocess.run([sys.executable, "-m", "server.cli", "camera", "--source", f"file:{video}", "--fast",
                               "--frame-rate-hz", "0", "--connect", hub], capture_output=True, text=True, timeout=120)
        count = sum(1 for line in done.stderr.splitlines() if " INFO camera " in line and " frames, " in line)
        wait_until(lambda: len(got) >= 10, 5.0)
        time.sleep(0.3)
        sub.undeclare()
    assert count == 1, done.stderr
    return done, sorted(got, key=lambda m: m.seq)


def test_xneck_camera_on_a_truncated_video_warns_of_the_shortfall_and_exits_1(rendered_clip) -> None:
    """Audit of 2026-11-29: 48 of 120 frames published, exit 0, no word."""
    video, _alphas = rendered_clip
    done, got = run_camera_on(damaged(video, "trunc.avi", "truncated", k=12))
    warnings = [line for line in done.stderr.splitlines() if " WARNING " in line]
    assert done.returncode == 1, done.stderr[-3000:]
    assert len(warnings) == 1 and "file:trunc.avi: " in warnings[0] and "of the 30 frames" in warnings[0], done.stderr
    assert "missing after" in warnings[0] and "Traceback" not in done.stderr
    n = len(got)
    assert n in (12, 13) and f"{n} of the 30 frames" in warnings[0]
    assert got[-1].dropped == 0  # the loss is known only at the end: the health counters carry it


def test_xneck_camera_on_a_video_with_an_undecodable_frame_keeps_the_time_of_the_rest(rendered_clip) -> None:
    video, alphas = rendered_clip
    done, got = run_camera_on(damaged(video, "hole.avi", "undecodable", k=12))
    assert done.returncode == 1 and "1 could not be decoded" in done.stderr, done.stderr[-3000:]
    kept = [k for k in range(30) if k != 12]
    assert len(got) == 29
    assert [m.capture_stamp_s for m in got] == pytest.approx(np.array(kept) / FPS, abs=1e-6)
    assert [m.dropped for m in got] == [0] * 12 + [1] * 17
    for m, k in zip(got, kept):  # each frame's α is the α of the instant it is stamped with
        assert np.degrees(np.abs(np.array(m.alpha_ip_rad) - alphas[k])).max() < 1.0


def test_xneck_camera_on_a_whole_video_exits_0(rendered_clip) -> None:
    video, _alphas = rendered_clip
    done, got = run_camera_on(video)
    assert done.returncode == 0 and " WARNING " not in done.stderr, done.stderr[-3000:]
    assert len(got) == 30 and [m.capture_stamp_s for m in got] == pytest.approx(np.arange(30) / FPS, abs=1e-6)


# --- `xneck camera align` on a damaged video ------------------------------------------------------


def _excitation(t: np.ndarray) -> np.ndarray:
    """Non-periodic multi-sines within ±45° (rad), one per joint."""
    return excitation(t, first_deg=27.0)


def test_xneck_camera_align_says_how_many_frames_the_video_lost_and_keeps_the_time_of_the_rest(tmp_path, params, model) -> None:
    import json

    from typer.testing import CliRunner

    from bridge import bus
    from bridge.archive import write_campaign
    from bridge.archive_read import read_campaign
    from server.cli import app

    t = np.arange(0.0, 12.0, 0.01)
    zeros = [0.0] * params.n_cables
    truths = [(bus.TWIN_TRUTH, int((1.7e9 + tk) * 1e9), bus.Truth(
        seq=k + 1, stamp_s=float(tk), alpha_rad=a.tolist(), alpha_dot_rad_s=[0.0] * 3, theta_rad=zeros, theta_dot_rad_s=zeros,
        tension_N=zeros, elongation_m=zeros, slack=[False] * params.n_cables, near_singular=False))
        for k, (tk, a) in enumerate(zip(t, _excitation(t)))]
    camp = write_campaign(tmp_path / "c.mcap", truths, {"campaign_id": "c1", "kind": "identification"})
    offset, renderer = 3.25, Renderer(model, seed=8)
    video = write_video(tmp_path / "run.avi", [renderer.render(_excitation(np.array([offset + k / FPS]))[0]) for k in range(90)])
    hole = damaged(video, "hole.avi", "undecodable", k=30)
    r = CliRunner().invoke(app, ["camera", "align", str(hole), str(camp), "--out", str(tmp_path / "a.mcap"), "--json", "--images", "0"])
    assert r.exit_code == 0, r.output
    prov = json.loads(r.stdout)
    assert prov["frames"] == 89 and prov["frames_declared"] == 90 and prov["frames_lost"] == 1, prov
    assert "warning: hole.avi: 89 of the 90 frames" in r.stderr and "1 could not be decoded" in r.stderr, r.stderr
    assert abs(prov["offset_s"] - offset) < 0.005
    frames = [m for _, m in read_campaign(tmp_path / "a.mcap").messages(bus.CAMERA_ALPHA)]
    kept = np.array([k for k in range(90) if k != 30])
    assert np.abs(np.array([f.capture_stamp_s for f in frames]) - (offset + kept / FPS)).max() < 0.005
    r = CliRunner().invoke(app, ["camera", "align", str(hole), str(camp), "--out", str(tmp_path / "b.mcap")])
    assert r.exit_code == 0 and "89 of the 90 frames" in r.output, r.output


def test_xneck_camera_on_a_video_without_a_frame_says_nothing_was_published(tmp_path) -> None:
    """User audit of session 45: a video of zero frames replayed '0 frames', exit 0."""
    from busutil import bus_pair

    empty = tmp_path / "zero.avi"
    writer = cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (64, 48))
    writer.release()
    with bus_pair() as (hub, _session, _connect):
        done = subprocess.run([sys.executable, "-m", "server.cli", "camera", "--source", f"file:{empty}", "--fast",
                               "--frame-rate-hz", "0", "--connect", hub], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "no frame decoded: nothing was published" in done.stderr, done.stderr[-3000:]
    assert "Traceback" not in done.stderr


def test_xneck_camera_replay_stopped_by_ctrl_c_says_it_was_interrupted(rendered_clip, tmp_path) -> None:
    """User audit of session 45: Ctrl-C 2.5 s into a 10 s replay printed '49 frames', exit 0."""
    import signal

    from busutil import bus_pair, wait_until

    from bridge import bus

    cap, clip = cv2.VideoCapture(str(rendered_clip[0])), []
    while (read := cap.read())[0]:
        clip.append(read[1])
    cap.release()
    video = write_video(tmp_path / "long.avi", clip * 10)  # 10 s at 30 fps, replayed in real time
    with bus_pair() as (hub, session, _connect):
        got: list = []
        sub = session.declare_subscriber(bus.CAMERA_ALPHA, lambda s: got.append(s))
        proc = subprocess.Popen([sys.executable, "-m", "server.cli", "camera", "--source", f"file:{video}",
                                 "--frame-rate-hz", "0", "--connect", hub], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            assert wait_until(lambda: len(got) > 0, 60.0)
            proc.send_signal(signal.SIGINT)
            _out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
            sub.undeclare()
    assert proc.returncode == 130, err[-3000:]
    assert "interrupted: " in err and "of the 300 it declares" in err and "Traceback" not in err, err[-3000:]


def test_xneck_camera_commands_print_no_opencv_or_ffmpeg_lines_only_their_own(tmp_path, params, xneck) -> None:
    """User audit: OpenCV's FFmpeg printed ``[mov,mp4,… @ 0x…] moov atom not found`` above xneck's
    error on a file that is not a video, and ``[mjpeg @ 0x…] No JPEG data found in image`` for an
    undecodable frame: the CLI silences OpenCV's log (server.cli.quiet_opencv); xneck says it itself."""
    from bridge import bus
    from bridge.archive import write_campaign

    zeros = [0.0] * params.n_cables
    truths = [(bus.TWIN_TRUTH, int((1.7e9 + k * 0.01) * 1e9), bus.Truth(
        seq=k + 1, stamp_s=k * 0.01, alpha_rad=[0.0] * 3, alpha_dot_rad_s=[0.0] * 3, theta_rad=zeros, theta_dot_rad_s=zeros,
        tension_N=zeros, elongation_m=zeros, slack=[False] * params.n_cables, near_singular=False)) for k in range(100)]
    camp = write_campaign(tmp_path / "c.mcap", truths, {"campaign_id": "c1"})
    not_video = tmp_path / "bad.mp4"
    not_video.write_bytes(b"not a video at all")
    # 1280×720 like the calibration, so the frames are decoded; frame 3 cannot be.
    big = write_video(tmp_path / "big.avi", [np.full((720, 1280, 3), 8 * k, np.uint8) for k in range(8)])
    hole = damaged(big, "hole.avi", "undecodable", k=3)
    runs = [
        (("camera", "align", str(not_video), str(camp), "--out", str(tmp_path / "a.mcap")),
         f"error: {not_video}: OpenCV cannot open this video"),
        (("camera", "--source", f"file:{not_video}"), f"error: {not_video}: OpenCV cannot open this video"),
        (("camera", "align", str(hole), str(camp), "--out", str(tmp_path / "b.mcap")),
         f"error: {hole}: 7 frames; at least 10 are needed"),
    ]
    for args, says in runs:
        r = xneck(*args)
        assert r.returncode == 2 and r.stderr.strip() == says, r.stderr
