"""The camera's bus process: frames → detector → ``xneck/camera/alpha_ip`` (CameraAlpha v2).

One :class:`CameraNode` per process, whatever the source: :meth:`CameraNode.run_source` reads a
USB camera or a video file; :meth:`CameraNode.run_twin` renders the twin's truth
(``xneck/twin/truth``) through :class:`twin.camera.render.Renderer` on the exposure schedule of
:class:`twin.camera.source.TwinShutter`, so the twin's α_IP comes from real image processing with a
realistic latency, stamped on the bus clock (the truth's simulated time). Health counters go to
``xneck/health/camera/<instance>`` every second; the liveliness token says the camera is up.
A camera moved since its calibration (:attr:`twin.camera.detect.Detection.reason`) is said there
as it happens, and again when the references are back: ``received[MOVED_NOW]`` is 1 while it is
moved (a state, not a count) and ``last_reject_reason`` its reason then, which the console shows
on its camera card (:func:`server.camera_feed.camera_health`).
With ``frame_rate_hz`` > 0, a few frames per second also go out as JPEG on ``xneck/camera/frame``
(:mod:`twin.camera.frames`) for the console's camera panel and the campaign archive. A live
camera's exposures are stamped on the bridge's clock when the node has a
:class:`twin.camera.clock.BridgeClock` (``xneck camera --clock bridge``, the default for USB).

One twin at a time: a ``Truth`` has no identity field, and with a second twin on the hub the
camera fed both twins' truths into one shutter, two clocks and two poses (audit of 2026-11-29).
The bridge running a twin names its run in each truth's attachment (:func:`bridge.session.run_of`;
'' for a publisher that names none); the camera renders the run whose truth it received first
and sets the others aside (counted, ``foreign_truth`` in its health) until that run has been
silent for :data:`FOLLOW_SILENT_S` (a twin that stopped or restarted: a restart is a new run),
then follows the next run that speaks, its clock jump handled as any restart of the truth's clock.
The Zenoh callback only decodes and schedules; rendering and detection run on the caller's thread.

One camera, its name: ``CameraAlpha.source`` says the kind of camera (``twin-render``, ``usb:0``),
which two cameras share; each α_IP and frame carries the node's ``instance`` as its Zenoh
attachment (:func:`bridge.session.camera_attachment`), so a campaign records one camera's
(``server.quality``, "One camera") and the console says when two publish.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import threading
import time
import uuid
from typing import Protocol

import numpy as np
import zenoh

from bridge import bus
from bridge.session import camera_attachment, liveliness_token, payload_of, publisher, run_of
from twin.camera.clock import BridgeClock
from twin.camera.detect import Detection, Detector
from twin.camera.frames import FrameDecimator, frame_message
from twin.camera.render import Renderer
from twin.camera.source import Exposure, Frame, TwinShutter

log = logging.getLogger("xneck.camera")

FOLLOW_SILENT_S = 1.0  # s (wall clock) without the followed twin's truth before another's is taken
#: Health ``received`` key: 1 while the detector finds the camera moved since its calibration, else 0.
MOVED_NOW = "camera_moved_now"


class FrameSource(Protocol):
    name: str

    @property
    def dropped(self) -> int: ...  # frames the source lost so far

    def read(self) -> Frame | None: ...

    def close(self) -> None: ...


class CameraNode:
    """Publishes what ``detector`` measures; ``instance`` names it on the bus."""

    HEALTH_PERIOD_S = 1.0

    def __init__(self, session: zenoh.Session, detector: Detector, instance: str = "", queue_frames: int = 4,
                 frame_rate_hz: float = 0.0, jpeg_quality: int = 75, clock: BridgeClock | None = None) -> None:
        self.session = session
        self.clock = clock  # a live source's stamps go onto the bridge's clock (run_source)
        self.detector = detector
        self.instance = instance or uuid.uuid4().hex[:8]
        self._pub = publisher(session, bus.CAMERA_ALPHA)
        self._attachment = camera_attachment(self.instance)  # on its α_IP and frames: this camera (module docstring)
        self._health = publisher(session, bus.health_key("camera", self.instance))
        self._frames = publisher(session, bus.CAMERA_FRAME) if frame_rate_hz > 0 else None
        self._decimator = FrameDecimator(frame_rate_hz)
        self._jpeg_quality = jpeg_quality
        self.images = 0  # JPEG frames published
        self._token = liveliness_token(session, "camera", self.instance)
        self._seq = 0
        self._started = time.monotonic()
        self._last_health = -math.inf
        self.frames = 0
        self.missing_joints = 0
        self.dropped = 0  # frames the source lost, as published in CameraAlpha.dropped
        self.queue_dropped = 0  # twin: exposures dropped because rendering fell behind
        self.clock_restarts = 0  # twin: the truth's clock jumped (a restarted twin) and the shutter started again
        self.clock_dropped = 0  # live: frames not published while the bridge clock was re-synchronised after a jump
        self.truth_received = 0
        self.truth_rejected = 0
        self.truth_foreign = 0  # twin: truths of another run than the one rendered (module docstring)
        self.run = ""  # twin: the bridge run whose truth is rendered ('' until one came, or it names none)
        self._last_reject = ""
        self.moved = False  # the detector finds the camera moved since its calibration (Detection.reason)
        self.moved_frames = 0  # frames whose joints were withheld for it
        self._moved_reason = ""  # the latest frame's reason while moved
        self._queue: collections.deque[Exposure] = collections.deque()
        self._queue_frames = queue_frames
        self._cond = threading.Condition()

    # --- publishing ---------------------------------------------------------------------------

    def publish(self, found: Detection, capture_s: float, stamp_s: float, source: str,
                image: np.ndarray | None = None) -> bus.CameraAlpha:
        self._seq += 1
        self.frames += 1
        self.missing_joints += sum(a is None for a in found.alpha_rad)
        if found.reason:  # the camera moved since its calibration: said once per episode, counted in the health
            self.moved_frames += 1
            self._last_reject = self._moved_reason = found.reason
            if not self.moved:
                self.moved = True
                log.warning("camera %s: %s; every joint is reported missing until then", self.instance, found.reason)
                self._maybe_health(force=True)
        elif self.moved:
            self.moved = False
            log.warning("camera %s: the base-plate reference markers are back where the calibration puts them "
                        "(%.1f px): α_IP measured again", self.instance, found.reference_shift_px or 0.0)
            self._maybe_health(force=True)  # the console takes the reason away now, not at the next period
        msg = bus.CameraAlpha(seq=self._seq, stamp_s=float(stamp_s), capture_stamp_s=float(capture_s),
                              alpha_ip_rad=[None if a is None else float(a) for a in found.alpha_rad],
                              confidence=[float(c) for c in found.confidence], source=source, dropped=self.dropped)
        self._pub.put(msg, attachment=self._attachment)
        if image is not None and self._frames is not None and self._decimator.due(capture_s):
            try:
                self._frames.put(frame_message(self.images + 1, image, found, capture_s, stamp_s, source, self._jpeg_quality),
                                 attachment=self._attachment)
                self.images += 1
            except ValueError as exc:  # too large a JPEG: α_IP goes on, the console shows no picture
                log.warning("camera %s: frame not published: %s", self.instance, exc)
        self._maybe_health()
        return msg

    def _maybe_health(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_health < self.HEALTH_PERIOD_S:
            return
        self._last_health = now
        received = {bus.TWIN_TRUTH: self.truth_received, "foreign_truth": self.truth_foreign,
                    "frames": self.frames, "dropped": self.dropped,
                    "missing_joints": self.missing_joints, "images": self.images,
                    "clock_restarts": self.clock_restarts, MOVED_NOW: int(self.moved)}
        rejected = {bus.TWIN_TRUTH: self.truth_rejected, "camera_moved": self.moved_frames}
        if self.clock is not None:  # the bridge clock's offset, uncertainty, run, steps (twin.camera.clock)
            clock_received, clock_rejected = self.clock.health()
            received.update(clock_received)
            rejected.update(clock_rejected)
            rejected["clock_frames"] = self.clock_dropped
        self._health.put(bus.Health(
            seq=self._seq, stamp_s=time.time(), process="camera", instance=self.instance, uptime_s=now - self._started,
            received=received, rejected=rejected,
            # while moved, its reason: a truth refused between two frames does not hide it
            last_reject_reason=self._moved_reason if self.moved else self._last_reject))

    # --- sources -------------------------------------------------------------------------------

    def run_source(self, source: FrameSource, stop: threading.Event, max_frames: int | None = None,
                   pace_fps: float | None = None) -> int:
        """Read, detect, publish until the source ends, ``stop`` is set or ``max_frames`` were
        published. ``pace_fps`` replays a file at its frame rate (None: as fast as detection runs).
        A video file's time stamps are its own: ``stamp_s`` = ``capture_stamp_s``. A live source's
        are this PC's wall clock, or, with ``clock`` (the node's), the bridge's: the source's
        ``clock`` is then set to ``clock.local`` (a live source without one is refused) and both
        stamps get ``clock.offset_s`` added (one
        value per exposure, so a re-sync never puts a capture after its publication); while the
        bridge's clock jumped and is being re-synchronised, frames are dropped and counted
        (``clock_dropped``, :meth:`twin.camera.clock.BridgeClock.offset_for`). A live source
        that is lost raises (:class:`twin.camera.source.SourceLost`): the last health counters are
        published first."""
        started = time.monotonic()
        if self.clock is not None and not source.name.startswith("file:"):
            # The offset maps the clock's local time: the grabs must be timed on it (UsbSource's
            # default is the wall clock: captures went out 1.8e9 s after their publication).
            if not hasattr(source, "clock"):
                raise ValueError(f"{source.name}: a live source on the bridge's clock must time its grabs on a "
                                 f"settable 'clock' (the BridgeClock's local time)")
            if source.clock is not self.clock.local:  # type: ignore[attr-defined]
                log.info("camera %s: %s times its grabs on the bridge clock's local time (monotonic)",
                         self.instance, source.name)
                source.clock = self.clock.local  # type: ignore[attr-defined]
        try:
            while not stop.is_set() and (max_frames is None or self.frames < max_frames):
                frame = source.read()
                if frame is None:
                    break
                if pace_fps:
                    delay = started + self.frames / pace_fps - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                self.dropped = source.dropped
                try:
                    found = self.detector.detect(frame.image)
                except ValueError as exc:  # a frame of another size: the calibration does not fit
                    raise RuntimeError(f"{source.name}: {exc}") from None
                capture = frame.capture_s
                if source.name.startswith("file:"):
                    stamp = capture
                elif self.clock is not None:
                    if not math.isfinite(self.clock.offset_s):
                        raise RuntimeError(f"{source.name}: the camera clock is not synchronised with a bridge yet")
                    offset = self.clock.offset_for(capture)  # one value for both stamps
                    if offset is None:  # the bridge's clock jumped and the re-sync is not done: not stamped wrong
                        self.clock_dropped += 1
                        self._maybe_health()
                        continue
                    capture, stamp = capture + offset, self.clock.local() + offset
                else:
                    stamp = time.time()
                self.publish(found, capture, stamp, source.name, frame.image)
        finally:
            self.dropped = source.dropped  # a file's missing end is known only now
            self._maybe_health(force=True)
        return self.frames

    def run_twin(self, renderer: Renderer, shutter: TwinShutter, stop: threading.Event,
                 max_frames: int | None = None, idle_timeout_s: float | None = None) -> int:
        """Render the twin's truth on ``shutter``'s schedule and publish what the detector sees.

        Frames wait in a short queue between the truth callback and this thread; when rendering
        falls behind (a twin running faster than real time), the oldest frames are dropped and
        counted. Returns when ``stop`` is set, after ``max_frames``, or after ``idle_timeout_s``
        without truth."""
        n = self.detector.n_joints
        last_truth = [time.monotonic()]
        followed: list[str | None] = [None]  # the run rendered (None: none yet)

        def foreign(run: str, now: float) -> bool:
            """(Under the lock.) Another twin's truth while the one rendered speaks: counted."""
            if followed[0] is None or run == followed[0] or now - last_truth[0] >= FOLLOW_SILENT_S:
                return False
            self.truth_foreign += 1
            return True

        def on_truth(sample: zenoh.Sample) -> None:
            run, now = run_of(sample), time.monotonic()
            with self._cond:
                if foreign(run, now):  # before decoding: a stray's 500 Hz costs no decode
                    return
            try:
                truth = bus.decode(bus.Truth, payload_of(sample, bus.Truth))
                if len(truth.alpha_rad) != n:
                    raise bus.BusDecodeError(f"Truth: {len(truth.alpha_rad)} angles for {n} joints")
            except bus.BusDecodeError as exc:
                with self._cond:
                    self.truth_rejected += 1
                    self._last_reject = f"{sample.key_expr}: {exc.reason}"
                return
            with self._cond:
                if foreign(run, now):  # another run was taken meanwhile (callbacks may run at once)
                    return
                if followed[0] != run:
                    if followed[0] is not None:
                        log.warning("camera %s: the twin of run %r was silent for %.1f s: rendering run %r's truth now",
                                    self.instance, followed[0], now - last_truth[0], run)
                    followed[0] = self.run = run
                self.truth_received += 1
                last_truth[0] = now
                for exposure in shutter.feed(truth.stamp_s, np.asarray(truth.alpha_rad)):
                    if len(self._queue) >= self._queue_frames:
                        self._queue.popleft()
                        self.queue_dropped += 1
                    self._queue.append(exposure)
                if shutter.restarts != self.clock_restarts and shutter.last_jump is not None:
                    # said once per jump: the camera goes on on the new clock, but the operator should know why
                    self.clock_restarts = shutter.restarts
                    log.warning("camera %s: the truth's clock jumped from %.3f s to %.3f s: exposures start again there",
                                self.instance, *shutter.last_jump)
                self._cond.notify_all()

        sub = self.session.declare_subscriber(bus.TWIN_TRUTH, on_truth)
        try:
            while not stop.is_set() and (max_frames is None or self.frames < max_frames):
                with self._cond:
                    if not self._queue:
                        self._cond.wait(0.1)
                    exposure = self._queue.popleft() if self._queue else None
                    dropped = self.queue_dropped + shutter.dropped
                if exposure is None:
                    if idle_timeout_s is not None and time.monotonic() - last_truth[0] > idle_timeout_s:
                        log.info("camera %s: no truth for %.1f s, stopping", self.instance, idle_timeout_s)
                        break
                    self._maybe_health()
                    continue
                image = renderer.render(exposure.alpha_rad)
                found = self.detector.detect(image)
                self.dropped = dropped
                self.publish(found, exposure.capture_s, exposure.ready_s, "twin-render", image)
        finally:
            sub.undeclare()
        with self._cond:
            self.dropped = self.queue_dropped + shutter.dropped
        self._maybe_health(force=True)
        return self.frames

    def close(self) -> None:
        closers = [self._pub.close, self._health.close, self._token.undeclare]
        if self._frames is not None:
            closers.append(self._frames.close)
        for closer in closers:
            with contextlib.suppress(Exception):  # the session may be closed already
                closer()
