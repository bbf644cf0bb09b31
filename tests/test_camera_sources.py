"""Where the camera's frames come from, when they stop coming (audit of 2026-11-29).

- A live camera (`UsbSource`) that misses a grab retries for about a second
  (`source.RETRY_WINDOW_S`) and carries on; one that does not come back ends `xneck camera`
  non-zero, saying which camera and after how long. No USB camera exists here: a fake
  `cv2.VideoCapture` stands for it, the lowest layer, and everything above it is the real code.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from twin.camera.render import Renderer  # noqa: E402
from twin.camera.source import SourceError, UsbSource  # noqa: E402

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

    assert RETRY_WINDOW_S <= waited < RETRY_WINDOW_S + 1.0  # retried over the window, then gave up
    message = str(lost.value)
    assert re.match(r"usb:2: no frame for 1\.\d s \(\d+ grabs failed\), after \d\.\d s running and 5 frames", message), message
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

    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), Renderer(model, seed=1).render(np.radians([10.0, -20.0, 30.0])))
    with bus_pair() as (hub, session, _connect):
        got = []
        sub = session.declare_subscriber(bus.CAMERA_ALPHA, lambda s: got.append(s))
        t0 = time.monotonic()
        done = subprocess.run([sys.executable, "-c", SHIM, str(frame), "60", "camera", "--source", "usb:0",
                               "--frame-rate-hz", "0", "--connect", hub], capture_output=True, text=True, timeout=120)
        took = time.monotonic() - t0
        wait_until(lambda: len(got) >= 20, 5.0)
        sub.undeclare()
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert done.returncode == 1, done.stderr[-3000:]
    assert len(errors) == 1 and re.match(r"error: usb:0: no frame for 1\.\d s \(\d+ grabs failed\), after \d+\.\d s running "
                                         r"and 60 frames", errors[0]), done.stderr[-3000:]
    assert "Traceback" not in done.stderr and took < 60
    assert len(got) >= 20  # what it measured before the camera went was published
