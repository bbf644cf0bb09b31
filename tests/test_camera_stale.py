"""A camera that falls silent while the controller goes on (an unplugged USB camera): the console
shows its α_IP only while it is fresh (audit of 2026-11-29: ``/api/camera`` said ``fresh: false``
while every live frame still carried the α_IP of seconds before, which the dashboard plotted at
each new status time as a live line, and the 3D view kept the α_IP ghost at the old pose, after a
joint went missing too).

A real console (uvicorn on 127.0.0.1) fed on its Zenoh hub by this test posing as the controller
and the camera; its live WebSocket, the dashboard in Chromium, its viser scene.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

import httpx
from browser_harness import dashboard_page, needs_chromium
from server_harness import LiveSocket, running_server, wait_until

from bridge import bus
from bridge.session import camera_attachment, open_session, publisher
from server.live import CAMERA_MAX_AGE_S

N_JOINTS = 3
CAMERA = "cam-lab1"  # the camera process the peer poses as
SETTLE_S = 0.5  # s beyond CAMERA_MAX_AGE_S a loaded machine may take to see the camera stale


class Peers:
    """The controller's status at 100 Hz and the camera's α_IP at 30 Hz, on the console's hub,
    stamped on this process's monotonic clock (the console's own, here) from ``t0``. ``camera``:
    set while the camera publishes; ``missing``: the joints (0-based) it reports missing."""

    def __init__(self, hub: str) -> None:
        self.t0 = time.monotonic()
        self.camera = threading.Event()
        self.status = threading.Event()
        self.status.set()
        self.missing: set[int] = set()
        self._stop = threading.Event()
        self._session = open_session(listen=["tcp/127.0.0.1:0"], connect=[hub])
        self._status = publisher(self._session, bus.CONTROLLER_STATUS)
        self._camera = publisher(self._session, bus.CAMERA_ALPHA)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def now(self) -> float:
        return time.monotonic() - self.t0

    @staticmethod
    def alpha(t: float) -> list[float]:
        return [0.2 + 0.05 * t] * N_JOINTS  # the neck keeps moving after the camera stops

    def _run(self) -> None:
        k = cam_seq = 0
        while not self._stop.wait(0.01):
            k += 1
            t = self.now()
            a = self.alpha(t)
            if self.status.is_set():
                self._status.put(bus.ControllerStatus(
                    seq=k, stamp_s=t, law="law2", tick_s=0.002, compute_s=1e-4, overruns=0, deadline_misses=0,
                    saturated=[False] * 4, alpha_hat_rad=a, alpha_d_rad=a, e_rad=[0.0] * N_JOINTS, holding=False))
            if self.camera.is_set() and k % 3 == 0:
                cam_seq += 1
                ip: list[float | None] = [None if j in self.missing else a[j] for j in range(N_JOINTS)]
                self._camera.put(bus.CameraAlpha(seq=cam_seq, stamp_s=t, capture_stamp_s=t - 0.05, alpha_ip_rad=ip,
                                                 confidence=[0.0 if x is None else 1.0 for x in ip], source="usb:0"),
                                 attachment=camera_attachment(CAMERA))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self._status.close()
        self._camera.close()
        self._session.close()


def hub_of(app: object) -> str:
    """The Zenoh endpoint a running console (:func:`server_harness.running_server`'s app) listens on."""
    return cast(Any, app).state.hub


@contextmanager
def peers(hub: str) -> Iterator[Peers]:
    p = Peers(hub)
    try:
        yield p
    finally:
        p.close()


class LiveFrames(LiveSocket):
    """Every frame's series as it came."""

    def __init__(self, base: str) -> None:
        self.frames: list[dict[str, Any]] = []
        super().__init__(base)

    def on_frame(self, frame: dict[str, Any]) -> None:
        self.frames.append(frame["series"])

    def with_status(self, after_s: float, before_s: float = float("inf")) -> list[dict[str, Any]]:
        return [s for s in list(self.frames) if "status" in s and after_s < s["status"]["stamp_s"] < before_s]


def test_live_frames_carry_alpha_ip_only_while_the_camera_is_fresh(tmp_path: Path) -> None:
    """The camera stops while the status goes on: once it is stale by ``/api/camera``'s rule (no
    α_IP for CAMERA_MAX_AGE_S), no live frame carries one; it comes back with the camera."""
    with (running_server(tmp_path / "data", viser=False) as (base, app_), httpx.Client(base_url=base, timeout=10) as c,
          peers(hub_of(app_)) as p):
        live = LiveFrames(base)
        try:
            p.camera.set()
            assert wait_until(lambda: any("camera" in s for s in live.with_status(0.0)), 15, 0.05)
            time.sleep(1.0)
            p.camera.clear()
            off_s = p.now()
            # ten frames past the camera's staleness, however long a loaded machine takes to send them
            # (not a fixed window: the status may come slower than 100 Hz), clear of the camera's return
            assert wait_until(lambda: len(live.with_status(off_s + CAMERA_MAX_AGE_S + SETTLE_S, p.now() - 0.3)) >= 10,
                              30, 0.05), len(live.frames)
            cam = c.get("/api/camera").json()
            on_s = p.now()
            p.camera.set()
            assert wait_until(lambda: any("camera" in s for s in live.with_status(on_s)), 10, 0.05)
        finally:
            live.close()
    assert cam["alpha"]["fresh"] is False and cam["health"]["fresh"] is False, cam
    assert cam["health"]["age_s"] > CAMERA_MAX_AGE_S, cam
    stale = live.with_status(off_s + CAMERA_MAX_AGE_S + SETTLE_S, on_s - 0.3)
    assert len(stale) >= 10, len(stale)  # the status went on: frames kept coming
    carrying = [s["camera"] for s in stale if "camera" in s]
    assert not carrying, f"{len(carrying)} of {len(stale)} frames of a stale camera carry its α_IP: {carrying[0]}"
    # from its first frame to its stop, the fresh camera's α_IP is in nearly every frame: a loaded
    # machine may starve this test's publishing thread past the staleness once, as in the dashboard's
    # test below (the final CI of session 41); not a fixed 0.8 s window, which may hold no frame
    first_s = min(s["status"]["stamp_s"] for s in live.with_status(0.0, off_s) if "camera" in s)
    fresh = [s for s in live.with_status(0.0, off_s) if s["status"]["stamp_s"] >= first_s]
    assert fresh and sum("camera" in s for s in fresh) >= 0.8 * len(fresh), \
        f"{sum('camera' not in s for s in fresh)} of {len(fresh)} frames of a fresh camera lack its α_IP"


@needs_chromium
def test_the_dashboard_draws_a_gap_and_says_camera_stale_when_the_camera_falls_silent(tmp_path: Path) -> None:
    """The joint plots' α_IP: a line while the camera publishes, a gap (null), not the last value
    drawn flat at each new status time, once it is stale; the camera panel says "camera stale", and
    the live panel which camera the α_IP drawn is of, "no camera" once none is fresh."""
    with (running_server(tmp_path / "data", viser=False) as (base, app_), peers(hub_of(app_)) as p,
          dashboard_page(base) as (page, errors)):
        page.wait_for_function("document.querySelectorAll('#plot-joints .uplot').length === 3", timeout=15000)
        p.camera.set()
        page.wait_for_function("jointPlots[0].data[3].some((v) => v !== null)", timeout=15000)
        page.wait_for_function("document.querySelector('#camera-state').textContent.includes('usb:0')", timeout=10000)
        page.wait_for_function("(t) => document.querySelector('#live-camera').textContent === t",
                               arg=f"α_IP: camera {CAMERA} (first seen)", timeout=10000)
        time.sleep(1.0)
        p.camera.clear()
        off_s = p.now()
        # ten status points past the camera's staleness: 2 s idle, longer on a loaded machine (the
        # fresh-clone CI of session 37 saw 6 in 2 s)
        page.wait_for_function("(th) => jointPlots[0].data[0].filter((t) => t > th).length >= 10",
                               arg=off_s + CAMERA_MAX_AGE_S + SETTLE_S, timeout=20000)
        page.wait_for_function("window.xneckCamera.state === 'stale'", timeout=5000)
        state_text = page.inner_text("#camera-state")
        page.wait_for_function("document.querySelector('#live-camera').textContent === 'α_IP: no camera'", timeout=5000)
        t_s, ip_deg = page.evaluate("[jointPlots[0].data[0].slice(), jointPlots[0].data[3].slice()]")
        assert not errors, errors
    stale = [v for t, v in zip(t_s, ip_deg, strict=True) if t > off_s + CAMERA_MAX_AGE_S + SETTLE_S]
    assert len(stale) >= 10, len(stale)
    drawn = [v for v in stale if v is not None]
    assert not drawn, f"{len(drawn)} of {len(stale)} points of a stale camera drawn as α_IP (first {drawn[0]:.2f}°)"
    # from its first drawn point to its stop, the fresh camera is drawn at the status points (not a
    # fixed 0.8 s window: the fresh-clone CI of session 39, loaded, had no point in it), at nearly
    # all of them: the final CI of session 41, loaded, had this test's own publishing thread
    # starved past the 1 s staleness once (points 0.2-0.65 s apart, then one gap)
    first_s = next(t for t, v in zip(t_s, ip_deg, strict=True) if v is not None)
    before = [v for t, v in zip(t_s, ip_deg, strict=True) if first_s <= t < off_s]
    assert before and sum(v is not None for v in before) >= 0.8 * len(before), before
    assert "camera stale" in state_text, state_text


def test_the_3d_view_hides_the_alpha_ip_ghost_while_a_joint_is_missing_or_the_camera_is_stale(tmp_path: Path) -> None:
    """docs/camera.md: the 3D view hides the α_IP ghost while a joint is missing (it stayed at the
    last full pose), and while the camera is stale (it stayed after the camera fell silent, with
    the controller's status going on, and with the whole bus silent); fresh frames show it again."""
    with running_server(tmp_path / "data") as (_base, app_), peers(hub_of(app_)) as p:
        scene = cast(Any, app_).state.scene

        def shown() -> bool:
            return bool(scene.ghost_ip.visible)

        p.camera.set()
        assert wait_until(shown, 15, 0.05), "the ghost of a fresh camera measuring every joint"
        p.missing = {1}
        assert wait_until(lambda: not shown(), 5, 0.05), "joint 2 missing: the ghost stayed at the last full pose"
        p.missing = set()
        assert wait_until(shown, 5, 0.05)
        p.camera.clear()
        assert wait_until(lambda: not shown(), CAMERA_MAX_AGE_S + 4, 0.05), "a stale camera's ghost stayed"
        p.camera.set()
        assert wait_until(shown, 5, 0.05), "fresh frames show the ghost again"
        p.status.clear()
        p.camera.clear()  # nothing comes any more: the view still hides what is not now
        # the view redraws once a second while nobody watches (server/scene.py IDLE_RATE_HZ); a loaded
        # machine delays that (the fresh-clone CI of session 37 missed 5 s once)
        assert wait_until(lambda: not shown(), CAMERA_MAX_AGE_S + 12, 0.05), "a stale camera's ghost stayed, bus silent"
