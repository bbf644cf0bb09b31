"""``/api/camera``: the camera panel's data — the latest JPEG frame, the markers found on it, α_IP.

Reading routes, open like the other GETs (no token). The JPEG is the one the camera published on
``xneck/camera/frame``, bounded by the bus contract (``bus.FRAME_DATA_MAX_BYTES``) and checked
(:func:`bridge.bus.check_camera_frame`) before it is served; the browser decodes it.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Request, status
from fastapi.responses import Response

from server.camera_feed import camera_health
from server.live import fresh_camera

router = APIRouter(prefix="/api/camera", tags=["camera"])


@router.get("")
def camera(request: Request) -> dict[str, Any]:
    """Latest camera state: ``health`` (as in ``/api/system/health``, null without a camera; its
    ``moved_reason`` says why every joint is missing when the camera moved since its calibration),
    ``alpha`` (the latest α_IP message: ``alpha_ip_rad`` with null for a missing joint,
    ``confidence``, ``fresh``) and ``frame`` (the latest JPEG's metadata: time stamps, size, its
    age in s, the markers found on it as ``marker_bar`` and ``markers_px`` = x0, y0, x1, y1, … in
    pixels, bar −1 = base-plate reference; ``url`` of the image), each null when absent."""
    s = request.app.state
    msg = s.live.values.get("camera")
    alpha = None if msg is None else {
        "alpha_ip_rad": msg.alpha_ip_rad, "confidence": msg.confidence, "source": msg.source, "stamp_s": msg.stamp_s,
        "fresh": fresh_camera(s.live.values) is not None}
    latest = s.camera.frame()
    frame = None
    if latest is not None:
        f, age_s = latest
        frame = {"seq": f.seq, "stamp_s": f.stamp_s, "capture_stamp_s": f.capture_stamp_s, "frame_id": f.frame_id,
                 "format": f.format, "width": f.width, "height": f.height, "bytes": len(f.data), "source": f.source,
                 "age_s": age_s, "marker_bar": f.marker_bar, "markers_px": f.markers_px,
                 "url": f"/api/camera/frame.jpg?seq={f.seq}"}
    return {"health": camera_health(s.live.values, s.camera, s.presence), "alpha": alpha, "frame": frame}


@router.get("/frame.jpg", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}}, "description": "The latest camera frame"},
                       404: {"description": "No camera frame yet"}})
def frame_jpeg(request: Request) -> Response:
    """The latest camera frame as JPEG (``X-Frame-Seq``: its ``seq``; never cached)."""
    latest = request.app.state.camera.frame()
    if latest is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no camera frame yet")
    f, _age = latest
    return Response(f.data, media_type="image/jpeg", headers={"Cache-Control": "no-store", "X-Frame-Seq": str(f.seq)})
