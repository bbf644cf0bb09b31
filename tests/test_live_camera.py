"""The live view's α_IP is one camera's: two cameras publishing α_IP on one bus (`xneck up`'s twin
camera and a second `xneck camera --source twin`, or a ``usb:0``) made the live ``camera`` series,
and the dashboard's α_IP line, jump between them at each read.

Real Zenoh sessions on loopback; the series is read as the broadcaster reads it
(:meth:`server.live.LatestValues.live_series` of the fresh series, :data:`~server.live.LIVE_MAX_AGE_S`)."""

from __future__ import annotations

import time
from typing import Any

import zenoh
from busutil import wait_until

from bridge import bus
from bridge.session import camera_attachment
from server.live import LIVE_MAX_AGE_S, LiveBus

#: each camera's α_IP (rad), told apart by their first joint's
ALPHA = {"cam-a": 0.1, "cam-b": 0.5, "": 0.9}


def _alpha(seq: int, camera: str) -> bytes:
    return bus.encode(bus.CameraAlpha(seq=seq, stamp_s=seq / 30 + 0.05, capture_stamp_s=seq / 30,
                                      alpha_ip_rad=[ALPHA[camera], 0.2, 0.3], source="twin-render"))


def _put(pub: Any, seq: int, camera: str) -> None:
    """α_IP of the camera process ``camera`` ('' : a sample naming none, an older camera process)."""
    if camera:
        pub.put(_alpha(seq, camera), attachment=camera_attachment(camera))
    else:
        pub.put(_alpha(seq, camera))


def _shown(live: LiveBus) -> dict[str, Any] | None:
    """The ``camera`` entry of the live frame the broadcaster would send now."""
    _, series = live.values.live_series(LIVE_MAX_AGE_S)
    return series.get("camera")


def _camera_shown(live: LiveBus) -> str | None:
    """Which camera's α_IP the live frame shows (by its value), None for none."""
    shown = _shown(live)
    return None if shown is None else next(c for c, a in ALPHA.items() if shown["alpha_ip_rad"][0] == a)


def test_two_cameras_publishing_alpha_ip_the_live_series_shows_one_of_them(sessions) -> None:
    a, b = sessions
    live = LiveBus(b)
    pub = a.declare_publisher(bus.CAMERA_ALPHA, congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        assert wait_until(lambda: (_put(pub, 0, "cam-a"), _camera_shown(live) == "cam-a")[1], 10, 0.05)
        shown = []
        for k in range(1, 61):  # both at once, interleaved; either may be the newest at a read
            first, second = ("cam-a", "cam-b") if k % 2 else ("cam-b", "cam-a")
            _put(pub, k, first)
            _put(pub, 100 + k, second)
            time.sleep(0.01)
            shown.append(_camera_shown(live))
        assert set(shown) == {"cam-a"}, shown
        assert (_shown(live) or {}).get("instance") == "cam-a"  # the frame says which camera it shows
    finally:
        pub.undeclare()
        live.close()
