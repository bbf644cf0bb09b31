"""Where the camera's frames come from: a USB camera, a video file, or the twin's truth.

- :class:`UsbSource` (``usb:N`` or ``/dev/videoN``): OpenCV capture at 1280×720, 30 fps. The
  exposure's time stamp is the wall time at which the frame was grabbed minus the camera's
  latency (``latency_s``, half an exposure plus the transfer: measure it once with a visible sync
  event, see docs/camera.md); frames lost by the driver are counted from the gaps between grabs.
  A failed grab or retrieve (common on USB: a corrupt frame, a bus hiccup) is retried every
  :data:`RETRY_PAUSE_S` for up to :data:`RETRY_WINDOW_S`; a camera that gives no frame for that
  long is lost, and ``read`` raises :class:`SourceLost` naming it and how long it had run (it
  never returns None: a live camera has no normal end).
- :class:`FileSource` (``file:VIDEO``): a recorded video, as the paper processed its videos
  offline (§4.2); time stamps are the video's own, plus ``t0_s``: the container's time of each
  frame (``CAP_PROP_POS_MSEC``) while it is available and consistent, else the frame count / fps.
  A damaged video is read as far as it can be, never silently: a frame that cannot be decoded is
  skipped and the frames after it keep their time (counted in ``undecodable``); a frame the
  container's clock steps over (a zero-size AVI chunk: dropped when recorded) is counted in
  ``gaps``; at the end the frames read are compared with the count the container declares
  (``CAP_PROP_FRAME_COUNT``), and :meth:`FileSource.loss` says what is missing (a truncated file).
- :class:`TwinShutter` (``twin``): the exposure schedule of the twin's camera on the truth's
  clock (simulated time): an exposure every 1/``rate_hz`` s, the frame ready ``latency_s`` later.
  The bus process (``twin.camera.process``) feeds it the twin's truth and renders each exposure.
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from bridge import bus

log = logging.getLogger("xneck.camera")

RETRY_WINDOW_S = 1.0  # s: a live camera that gives no frame for this long, despite retries, is lost
RETRY_PAUSE_S = 0.05  # s between two attempts after a failed grab (about 20 in the window)


class SourceError(RuntimeError):
    """A frame source cannot be opened or used; the message says why."""


class SourceLost(SourceError):
    """A live source stopped giving frames and did not come back within its retry window."""


@dataclass
class Frame:
    capture_s: float  # middle of the exposure, on the source's clock
    image: np.ndarray  # H×W×3 BGR uint8


def parse_source(text: str) -> tuple[str, str]:
    """``("usb", "N" or "/dev/videoN")``, ``("file", path)`` or ``("twin", "")``; ``ValueError`` otherwise."""
    text = str(text).strip()
    if text == "twin":
        return "twin", ""
    if re.fullmatch(r"usb:\d{1,3}", text):
        return "usb", text[4:]
    if re.fullmatch(r"/dev/video\d{1,3}", text):
        return "usb", text
    if text.startswith("file:") and len(text) > 5:
        return "file", text[5:]
    raise ValueError(f"--source {text!r}: expected usb:N, /dev/videoN, file:VIDEO or twin")


@dataclass(frozen=True)
class VideoLoss:
    """What a video lacked (:meth:`FileSource.loss`): ``damaged`` when frames could not be decoded
    or are missing from the file; ``text`` one line for the operator."""

    damaged: bool
    text: str


class FileSource:
    """Frames of a video file with their time stamps (the module doc: the container's clock, else
    the frame count at the nominal frame rate)."""

    BAD_READS_S = 1.0  # s of video: this many failed reads in a row end the video (a real end fails forever)

    def __init__(self, path: str | Path, t0_s: float = 0.0) -> None:
        path = Path(path)
        if not path.is_file():  # a directory is not "no such file" (user audit)
            raise SourceError(f"{path}: {'is a directory, not a video file' if path.is_dir() else 'no such video file'}")
        self.cap = cv2.VideoCapture(str(path))
        if not self.cap.isOpened():
            raise SourceError(f"{path}: OpenCV cannot open this video")
        # The decoder allocates the size the container declares, frame after frame: a file of a few
        # kB may declare frames no camera makes (audit of 2026-11-26, follow-up of the JPEG bombs).
        width, height = self.cap.get(cv2.CAP_PROP_FRAME_WIDTH), self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT)
        if not (1 <= width <= bus.FRAME_MAX_SIDE_PX and 1 <= height <= bus.FRAME_MAX_SIDE_PX):
            self.cap.release()
            raise SourceError(f"{path}: frames of {width:.0f}×{height:.0f} px, more than a camera frame may be "
                              f"({bus.FRAME_MAX_SIDE_PX} px a side): refused before decoding")
        fps = float(self.cap.get(cv2.CAP_PROP_FPS))
        if not (math.isfinite(fps) and 1.0 <= fps <= 1000.0):
            raise SourceError(f"{path}: implausible frame rate {fps}")
        self.fps = fps
        self.t0_s = float(t0_s)
        count = float(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.declared = int(count) if math.isfinite(count) and 1 <= count < 1e9 else 0  # 0: the container says none
        self.frames = 0  # frames decoded
        self.undecodable = 0  # reads that failed before a later frame decoded: skipped, their time kept
        self.gaps = 0  # frames the container's clock steps over, beyond the failed reads (dropped when recorded)
        self.ended = False  # read to its end (not stopped before)
        self.container_clock = True  # stamps from the container's time; False once it was not consistent
        self._last_s: float | None = None  # video time of the last frame decoded (s, without t0_s)
        self.name = f"file:{path.name}"

    @property
    def missing(self) -> int:
        """Once ended: frames the container declares that were neither read nor accounted for as
        undecodable or skipped by its clock (cut from the end, or lost where nothing dates them)."""
        if not self.ended or not self.declared:
            return 0
        return max(0, self.declared - self.frames - self.undecodable - self.gaps)

    @property
    def dropped(self) -> int:
        """Frames lost so far (``CameraAlpha.dropped``): skipped, then, once ended, missing."""
        return self.undecodable + self.gaps + self.missing

    def _container_time(self) -> float | None:
        """The container's time of the frame just decoded (s), if it is available and consistent:
        later than the last frame's, and within the declared length (plus 1 s). OpenCV says 0 for
        a frame without a time stamp."""
        t = float(self.cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0
        if not math.isfinite(t) or t < 0.0 or (self._last_s is not None and t <= self._last_s + 1e-6):
            return None
        if self.declared and t > self.declared / self.fps + 1.0:
            return None
        return t

    def read(self) -> Frame | None:
        failed = 0
        while True:
            ok, image = self.cap.read()
            if ok and image is not None:
                break
            failed += 1
            accounted = self.frames + self.undecodable + self.gaps + failed
            if (self.declared and accounted >= self.declared) or failed >= max(1, round(self.BAD_READS_S * self.fps)):
                self.ended = True
                return None
        # By count: one period after the last frame for each frame decoded or failed since.
        t = failed / self.fps if self._last_s is None else self._last_s + (1 + failed) / self.fps
        if self.container_clock:
            container = self._container_time()
            if container is not None:
                t = container
            elif self._last_s is not None:  # mixed clocks would jump back and forth: the count from here on
                self.container_clock = False
                log.info("%s: frame %d has no consistent time in its container (%.3f ms after %.3f s): "
                         "frames are stamped by their count from there", self.name, self.frames + 1,
                         self.cap.get(cv2.CAP_PROP_POS_MSEC), self._last_s)
        # Frames between the last one and this one: the failed reads first, the rest skipped by the clock.
        lost = max(0, round(t * self.fps) if self._last_s is None else round((t - self._last_s) * self.fps) - 1)
        self.undecodable += min(failed, lost)
        self.gaps += lost - min(failed, lost)
        self._last_s = t
        self.frames += 1
        return Frame(self.t0_s + t, image)

    def loss(self) -> VideoLoss | None:
        """What the video lacked, as far as it was read (None: nothing, or not read to its end and
        nothing skipped so far)."""
        if not (self.undecodable or self.gaps or self.missing):
            return None
        parts = []
        if self.undecodable:
            parts.append(f"{self.undecodable} could not be decoded and {'was' if self.undecodable == 1 else 'were'} "
                         f"skipped, the frames after them keeping their time")
        if self.gaps:
            parts.append(f"{self.gaps} the container's clock skips (dropped when recorded)")
        if self.missing:
            last = -1.0 / self.fps if self._last_s is None else self._last_s
            parts.append(f"{self.missing} missing after {last:.3f} s ({self.missing / self.fps:.3f} s of video): "
                         f"cut from its end (a truncated file), or lost where the container keeps no time for "
                         f"them (then the frames after them are stamped early by as much)")
        read = (f"{self.frames} of the {self.declared} frames its container declares were read" if self.declared
                else f"{self.frames} frames were read (the container declares no count)")
        return VideoLoss(damaged=bool(self.undecodable or self.missing), text=f"{self.name}: {read}; " + "; ".join(parts))

    def close(self) -> None:
        self.cap.release()


class UsbSource:
    """A V4L2 camera through OpenCV; ``read`` blocks until the next frame."""

    def __init__(self, device: str, width: int = 1280, height: int = 720, fps: float = 30.0, latency_s: float = 0.05,
                 clock: Callable[[], float] = time.time) -> None:
        """``clock`` (s) stamps each grab: this PC's wall clock by default, ``time.monotonic`` when
        the camera maps its stamps onto the bridge's clock (:mod:`twin.camera.clock`)."""
        target: int | str = int(device) if device.isdigit() else device
        self.cap = cv2.VideoCapture(target, cv2.CAP_V4L2)
        if not self.cap.isOpened():
            raise SourceError(f"camera {device}: cannot open (is it plugged in, and is the user in group 'video'?)")
        self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        self.cap.set(cv2.CAP_PROP_FPS, fps)
        self.fps = float(self.cap.get(cv2.CAP_PROP_FPS)) or fps
        self.latency_s = float(latency_s)
        self.clock = clock
        self.retry_window_s = RETRY_WINDOW_S
        self.dropped = 0
        self.frames = 0  # frames read
        self.retries = 0  # failed grabs or retrieves that a later attempt got past
        self._opened_s = self._last_frame_s = time.monotonic()
        self._last_grab_s: float | None = None
        self.name = f"usb:{device}"

    def _grab(self) -> tuple[float, np.ndarray] | None:
        if not self.cap.grab():
            return None
        grabbed_s = self.clock()
        ok, image = self.cap.retrieve()
        return (grabbed_s, image) if ok and image is not None else None

    def _retry(self) -> tuple[float, np.ndarray]:
        """After a failed grab: attempts every RETRY_PAUSE_S until one gives a frame, or raise
        :class:`SourceLost` once ``retry_window_s`` has passed since the first failure."""
        first = time.monotonic()
        failures = 1
        while True:
            now = time.monotonic()
            if now - first >= self.retry_window_s:
                raise SourceLost(f"{self.name}: no frame for {now - self._last_frame_s:.1f} s ({failures} grabs failed), "
                                 f"after {self._last_frame_s - self._opened_s:.1f} s running and {self.frames} frames: "
                                 f"the camera was unplugged, or it stalled")
            time.sleep(RETRY_PAUSE_S)
            got = self._grab()
            if got is not None:
                self.retries += failures
                log.warning("%s: %d grab(s) failed, a frame again after %.2f s", self.name, failures, time.monotonic() - first)
                return got
            failures += 1

    def read(self) -> Frame:
        """The next frame; :class:`SourceLost` once none came for ``retry_window_s`` (module doc)."""
        got = self._grab()
        if got is None:
            got = self._retry()
        grabbed_s, image = got
        self.frames += 1
        self._last_frame_s = time.monotonic()
        if self._last_grab_s is not None:
            missed = round((grabbed_s - self._last_grab_s) * self.fps) - 1
            self.dropped += max(0, missed)
        self._last_grab_s = grabbed_s
        return Frame(grabbed_s - self.latency_s, image)

    def close(self) -> None:
        self.cap.release()


@dataclass
class Exposure:
    capture_s: float
    alpha_rad: np.ndarray
    ready_s: float = 0.0


@dataclass
class TwinShutter:
    """Exposures every 1/``rate_hz`` s of the truth's clock, each ready ``latency_s`` after it.

    :meth:`feed` takes every truth sample (time, α) in order and returns the exposures whose
    latency has elapsed, stamped with the time they became ready. A gap in the truth longer than
    a frame period (a stalled twin) skips the exposures it covers and counts them as dropped.
    ``on_exposure`` is called with each exposure when it is taken (a renderer can start on it
    while its latency elapses).

    A clock that jumps back past the last exposure (a restarted twin) or ahead by more than
    ``restart_gap_s`` (and 3 periods) is a new clock, not a stall: the schedule starts again at
    that sample (``restarts`` counts it, ``last_jump`` says from where to where). Without this a
    twin restarted at 0 after 600 s got no exposure for 600 s, and one truth stamped 1e12 s
    stopped the camera for good with 3e13 frames counted dropped (audit of 2026-11-26). The
    exposures still pending on the old clock are never released on the new one: they count as dropped.
    """

    rate_hz: float = 30.0
    latency_s: float = 0.05
    restart_gap_s: float = 1.0  # a longer gap is a new clock; a shorter one a stall whose exposures count as dropped
    dropped: int = 0  # exposures skipped because the truth stalled, or pending when its clock restarted
    discarded: int = 0  # of those, exposures taken (in ``exposures``) and pending when the clock restarted
    exposures: int = 0  # exposures taken
    restarts: int = 0  # times the truth's clock jumped back, or far ahead, and the schedule started again
    last_jump: tuple[float, float] | None = None  # (from, to) of the last restart, for a log line
    on_exposure: Callable[[Exposure], None] | None = None
    _next_s: float | None = None
    _pending: list[Exposure] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not (0.0 < self.rate_hz <= 1000.0 and 0.0 <= self.latency_s <= 1.0 and self.restart_gap_s > 0.0):
            raise ValueError("rate_hz must be in (0, 1000] Hz, latency_s in [0, 1] s and restart_gap_s > 0")

    def feed(self, t_s: float, alpha_rad: np.ndarray) -> list[Exposure]:
        period = 1.0 / self.rate_hz
        if self._next_s is not None and (t_s + 1e-9 < self._next_s - period
                                         or t_s - self._next_s > max(self.restart_gap_s, 3.0 * period)):
            # (as FrameDecimator: earlier than the last exposure is a new clock; so is far ahead)
            self.restarts += 1
            self.last_jump = (self._next_s - period, t_s)
            self.dropped += len(self._pending)
            self.discarded += len(self._pending)
            self._pending = []
            self._next_s = None
        if self._next_s is None:
            self._next_s = t_s
        if t_s + 1e-9 >= self._next_s:
            late = int((t_s - self._next_s + 1e-9) // period)
            self.dropped += late
            self._pending.append(Exposure(t_s, np.array(alpha_rad, dtype=float)))
            self.exposures += 1
            if self.on_exposure is not None:
                self.on_exposure(self._pending[-1])
            self._next_s += (late + 1) * period
        ready = [e for e in self._pending if e.capture_s + self.latency_s <= t_s + 1e-9]
        if ready:
            self._pending = self._pending[len(ready):]
            for e in ready:
                e.ready_s = t_s
        return ready

    @property
    def pending(self) -> int:
        """Exposures taken whose latency has not elapsed yet."""
        return len(self._pending)
