"""Decimated JPEG frames for the console and the archive (``xneck/camera/frame``, CameraFrame v1).

The camera measures α on every frame (30 fps) but a person watching the console, or Foxglove
playing a campaign back, needs a few frames per second: :class:`FrameDecimator` keeps one
exposure per 1/``rate_hz`` s of the source's clock (the bus clock: simulated time for the twin,
so a lockstep campaign is filmed at the same rate of *its* time), and :func:`frame_message`
encodes it as JPEG with the centroids the detector used, so the console can draw them over it.
"""

from __future__ import annotations

import cv2
import numpy as np

from bridge import bus
from twin.camera.detect import Detection

REFERENCE_BAR = -1  # marker_bar of a base-plate reference marker


class FrameDecimator:
    """``due(capture_s)`` is true for the first exposure and then once per 1/``rate_hz`` s of
    capture time (never for ``rate_hz`` ≤ 0). A clock that jumps back (a new video, a restarted
    twin) starts again."""

    def __init__(self, rate_hz: float) -> None:
        self.period_s = 1.0 / rate_hz if rate_hz > 0 else None
        self._last_s: float | None = None

    def due(self, capture_s: float) -> bool:
        if self.period_s is None:
            return False
        # 1 % of slack so that 30 fps at 5 Hz keeps exactly every 6th frame despite rounding.
        if self._last_s is not None and self._last_s <= capture_s < self._last_s + 0.99 * self.period_s:
            return False
        self._last_s = capture_s
        return True


def frame_message(seq: int, image: np.ndarray, found: Detection, capture_s: float, stamp_s: float,
                  source: str, quality: int = 75, frame_id: str = "camera") -> bus.CameraFrame:
    """The CameraFrame of ``image`` (H×W×3 BGR uint8) and what ``found`` located on it.
    Raises ``ValueError`` if the JPEG exceeds the contract's size bound (lower ``quality``)."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("OpenCV could not encode the frame as JPEG")
    data = buf.tobytes()
    if len(data) > bus.FRAME_DATA_MAX_BYTES:
        raise ValueError(f"a {len(data)}-byte JPEG exceeds the bus bound ({bus.FRAME_DATA_MAX_BYTES} B): lower the quality")
    h, w = image.shape[:2]
    bars, xy = [], []
    centroids = [(bar, p) for (bar, _side), p in sorted(found.markers_px.items())]
    centroids += [(REFERENCE_BAR, p) for p in found.reference_px]
    for bar, (x, y) in centroids:
        if 0.0 <= x <= w and 0.0 <= y <= h:  # a centroid is inside the image; keep the message valid anyway
            bars.append(int(bar))
            xy += [float(x), float(y)]
    return bus.CameraFrame(seq=seq, stamp_s=float(stamp_s), capture_stamp_s=float(capture_s), frame_id=frame_id,
                           format="jpeg", width=int(w), height=int(h), data=data, marker_bar=bars, markers_px=xy,
                           source=source[:256])
