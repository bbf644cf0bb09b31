"""The camera as the console sees it: the latest JPEG frame, the α_IP message rate, detection health.

The cameras publishing α_IP are told apart by the camera process (or bridge run) their samples
name (:func:`bridge.session.camera_of`, :func:`~bridge.session.run_of`), not by their source,
which two cameras share: two on the bus are named in the health, with a warning (their α_IP
were counted as one camera's rate, 59.5 Hz, and nothing said: audit of 2026-11-29).

Zenoh callbacks only store (the newest frame's raw payload, arrival times of α_IP messages);
a frame is decoded and checked (:func:`bridge.bus.check_camera_frame`) when the console reads
it, at most once, so a flood costs the bus callbacks nothing but a copy; a refused frame leaves
the last good one in place. A payload larger than
the contract's bound is refused in the callback without being kept. Refused payloads are counted
and never shown.
"""

from __future__ import annotations

import collections
import contextlib
import math
import threading
import time
from typing import Any

import zenoh

from bridge import bus
from bridge.session import camera_of, run_of
from server.live import LatestValues, fresh_camera
from server.presence import Presence
from server.quality import camera_name
from twin.camera.process import MOVED_NOW

#: A frame payload on the wire: base64 of the largest JPEG plus the JSON around it.
MAX_FRAME_PAYLOAD = bus.FRAME_DATA_MAX_BYTES * 4 // 3 + 64 * 1024
RATE_WINDOW_S = 2.0  # s over which the α_IP message rate is measured


class CameraFeed:
    """Latest camera frame and α_IP rate; subscribes on ``session`` (None: fed by :meth:`put_frame`)."""

    def __init__(self, session: zenoh.Session | None = None) -> None:
        self._lock = threading.Lock()
        self._raw: bytes | None = None
        self._received_s = -math.inf
        self._good: tuple[bus.CameraFrame, float] | None = None  # the latest valid frame, its arrival
        # (arrival, which joints were missing, the camera's name) of the latest valid α_IP messages
        self._alpha: collections.deque[tuple[float, tuple[bool, ...], str]] = collections.deque(maxlen=512)
        self.frames_received = 0
        self.frames_rejected = 0
        self.last_reject_reason = ""
        self.n_joints: int | None = None  # when set, an α_IP message of another joint count is not counted
        self._subs = [] if session is None else [
            session.declare_subscriber(bus.CAMERA_FRAME, lambda s: self.put_frame(s.payload.to_bytes())),
            session.declare_subscriber(bus.CAMERA_ALPHA,
                                       lambda s: self.note_alpha(s.payload.to_bytes(), camera_of(s) or run_of(s))),
        ]

    def put_frame(self, payload: bytes) -> None:
        with self._lock:
            if len(payload) > MAX_FRAME_PAYLOAD:
                self.frames_rejected += 1
                self.last_reject_reason = f"CameraFrame: {len(payload)}-byte payload exceeds {MAX_FRAME_PAYLOAD} B"
                return
            self._raw, self._received_s = payload, time.monotonic()
            self.frames_received += 1

    def note_alpha(self, payload: bytes, camera: str = "") -> None:
        """Counts a valid α_IP message of the camera process or bridge run ``camera`` ('' if its
        sample names none; a refused one is the live store's to count)."""
        try:
            msg = bus.decode(bus.CameraAlpha, payload)
            if self.n_joints is not None:
                bus.check_camera_alpha(msg, self.n_joints)
        except bus.BusDecodeError:
            return
        with self._lock:
            self._alpha.append((time.monotonic(), tuple(a is None for a in msg.alpha_ip_rad), camera_name(msg.source, camera)))

    def frame(self) -> tuple[bus.CameraFrame, float] | None:
        """The latest valid frame and its age (s since it arrived), or None. A refused frame
        does not hide the last good one."""
        with self._lock:
            raw, received = self._raw, self._received_s
            if raw is not None:
                self._raw = None  # decoded once, whatever the outcome
                try:
                    msg = bus.decode(bus.CameraFrame, raw)
                    bus.check_camera_frame(msg)
                except bus.BusDecodeError as exc:
                    self.frames_rejected += 1
                    self.last_reject_reason = exc.reason
                else:
                    self._good = (msg, received)
            good = self._good
        return None if good is None else (good[0], time.monotonic() - good[1])

    def alpha_window(self, window_s: float = RATE_WINDOW_S) -> tuple[float, list[float]]:
        """Valid α_IP messages per second over the last ``window_s``, and per joint the fraction
        of them that had it missing (empty without a message)."""
        now = time.monotonic()
        with self._lock:
            recent = [missing for t, missing, _ in self._alpha if now - t <= window_s]
        n_joints = min((len(m) for m in recent), default=0)
        fractions = [sum(m[j] for m in recent) / len(recent) for j in range(n_joints)]
        return len(recent) / window_s, fractions

    def cameras(self, window_s: float = RATE_WINDOW_S) -> list[str]:
        """The cameras whose α_IP came over the last ``window_s`` (sorted names, ``<source>@<camera>``
        or the source of one that names none: :func:`server.quality.camera_name`)."""
        now = time.monotonic()
        with self._lock:
            return sorted({name for t, _, name in self._alpha if now - t <= window_s})

    def alpha_age_s(self) -> float | None:
        """s since the latest valid α_IP message, None before any."""
        with self._lock:
            return time.monotonic() - self._alpha[-1][0] if self._alpha else None

    def close(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()


def moved_reason(presence: Presence) -> str | None:
    """Why every joint is missing when the camera moved since its calibration: the reason a camera
    process alive on the bus gives in its latest health while it says it is moved
    (:data:`twin.camera.process.MOVED_NOW`), e.g. "camera moved 4.8 px since its calibration
    (…; limit 2 px): redo the extrinsic calibration …"; several moved cameras' joined by "; ",
    each after its instance. None when no camera process says so (its references are back, or
    it ended: its health goes with its liveliness token)."""
    said = [(instance, h.last_reject_reason or "camera moved since its calibration")
            for instance, h in presence.health("camera") if h.received.get(MOVED_NOW, 0) > 0]
    if len(said) > 1:
        return "; ".join(f"{instance}: {reason}" for instance, reason in said)
    return said[0][1] if said else None


def clock_status(presence: Presence) -> dict[str, Any] | None:
    """The bridge clock of a live camera (``xneck camera --clock bridge``, twin/camera/clock.py) as
    its latest health says it: ``offset_us`` (bridge − that PC's wall clock), ``uncertainty_us``
    (grown with the age of its last sync), ``age_s`` (since that sync), ``stale`` (no sync for
    over a minute: the stamps may be off by more than said), ``resyncing`` (the bridge's clock
    jumped and the camera publishes nothing until re-synchronised), ``uncertain`` (too long without
    a sync: the camera publishes nothing until the bridge answers again), ``bridge`` (the instance
    followed). None when no camera process alive says one (a twin's camera, ``--clock local``)."""
    for _instance, h in presence.health("camera"):
        r = h.received
        if "clock_offset_us" not in r:
            continue
        bridge = next((k.split("/")[1] for k in r if k.startswith("clock_run/") and k.count("/") == 2), "")
        return {"offset_us": r["clock_offset_us"], "uncertainty_us": r.get("clock_uncertainty_us"),
                "age_s": r.get("clock_age_s"), "stale": bool(r.get("clock_stale", 0)),
                "resyncing": bool(r.get("clock_resyncing", 0)), "uncertain": bool(r.get("clock_uncertain", 0)),
                "bridge": bridge}
    return None


def camera_health(values: LatestValues, feed: CameraFeed | None = None,
                  presence: Presence | None = None) -> dict[str, Any] | None:
    """Detection health for ``/api/system/health`` from the latest ``CameraAlpha``: its source,
    whether the camera is fresh (``fresh``: :func:`server.live.fresh_camera`, the rule of the live
    frames and the 3D view too), the joints it reports missing (1-based), the per-joint confidence
    and the frames the source dropped; with ``feed``, the α_IP rate (``rate_hz``) and per joint the
    fraction of those messages that had it missing (``missing_fraction``), both over the last
    :data:`RATE_WINDOW_S`, the age of the latest α_IP message and of the latest JPEG frame (s, null
    without one), the frames refused, the ``cameras`` that published α_IP over that window
    (:meth:`CameraFeed.cameras`) and a ``warning`` when there are two or more (null otherwise: a
    campaign records one of them, and the rate counts all); with ``presence``, ``moved_reason`` (:func:`moved_reason`:
    why every joint is missing when the camera moved since its calibration, else null) and
    ``clock`` (:func:`clock_status`: a live camera's bridge clock, else null). None before any
    camera message."""
    msg = values.get("camera")
    if msg is None:
        return None
    out: dict[str, Any] = {
        "source": msg.source, "stamp_s": msg.stamp_s, "fresh": fresh_camera(values) is not None,
        "missing_joints": [i + 1 for i, a in enumerate(msg.alpha_ip_rad) if a is None],
        "confidence": list(msg.confidence), "dropped": msg.dropped,
    }
    if feed is not None:
        latest = feed.frame()
        rate_hz, missing_fraction = feed.alpha_window()
        cameras = feed.cameras()
        warning = (f"{len(cameras)} cameras publish α_IP ({', '.join(cameras)}): a campaign records one, "
                   f"the rate counts all" if len(cameras) > 1 else None)
        out.update({"cameras": cameras, "warning": warning, "rate_hz": rate_hz, "missing_fraction": missing_fraction, "age_s": feed.alpha_age_s(),
                    "frame_age_s": None if latest is None else latest[1],
                    "frames_received": feed.frames_received, "frames_rejected": feed.frames_rejected})
    if presence is not None:
        out["moved_reason"] = moved_reason(presence)
        out["clock"] = clock_status(presence)
    return out
