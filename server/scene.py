"""The viser 3D view of the neck, driven by the latest values of the bus.

Drawn in the base frame (y up, metres; ``server.neck_geometry``): the neck at α̂ (controller
status; the twin's truth when no controller runs) with bars, springs, pulleys and the four cables
coloured by tension (blue 0 N → red f_max; the twin's tension, else the applied forces); ghosts
of the bars at α^d (green) and α_IP (orange, camera); the base frame axes and a gravity arrow.

Nodes are created once; a daemon thread updates their properties at ``rate_hz`` inside
``server.atomic()`` so a browser never sees half a pose. It only reads :class:`LatestValues`,
never the bus, so a slow viser client cannot slow the control loop.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time

import numpy as np
import viser

from server.live import LatestValues
from server.neck_geometry import NeckDrawing, tension_colors
from twin.model.params import Params

log = logging.getLogger("xneck.scene")

BAR_RGB = (40, 40, 48)
SPRING_RGB = (150, 150, 160)
PULLEY_RGB = (90, 90, 110)
GHOST_D_RGB = (40, 170, 80)
GHOST_IP_RGB = (240, 140, 20)
GRAVITY_RGB = (200, 30, 200)


def _solid(segments: np.ndarray, rgb: tuple[int, int, int]) -> np.ndarray:
    return np.broadcast_to(np.asarray(rgb, dtype=np.uint8), segments.shape).copy()


class NeckScene:
    """A viser server showing the live neck. ``port`` 0 picks a free port; read :attr:`port`."""

    def __init__(self, values: LatestValues, params: Params, host: str = "127.0.0.1", port: int = 0,
                 rate_hz: float = 30.0) -> None:
        from bridge.session import free_tcp_port

        self.values = values
        self.rate_hz = rate_hz
        self.drawing = NeckDrawing(params)
        self.f_max_N = float(params.limits.f_max)
        self.server = viser.ViserServer(host=host, port=port or free_tcp_port(host), verbose=False)
        self.port = self.server.get_port()  # viser silently takes port+1 if the port is busy
        self.updates = 0
        self._stop = threading.Event()
        self._build()
        self._thread = threading.Thread(target=self._run, name="viser-scene", daemon=True)
        self._thread.start()

    def _build(self) -> None:
        scene = self.server.scene
        scene.set_up_direction("+y")
        self.server.gui.configure_theme(show_logo=False)
        self.server.gui.main_panel.minimize()  # the dashboard is the control surface; keep the neck visible
        # The neck is about 0.3 m tall: frame it from the front (+z) instead of viser's metres-scale default.
        cam = self.server.initial_camera
        cam.up = (0.0, 1.0, 0.0)
        cam.look_at = (0.03, 0.14, 0.0)
        cam.position = (0.06, 0.2, 0.5)
        cam.near = 0.01
        zero = np.zeros(self.drawing.n_joints)
        g = self.drawing.geometry(zero)
        scene.add_frame("/base", axes_length=0.04, axes_radius=0.0015)
        arrow = np.array([[[0.12, 0.05, 0.0], [0.12, -0.01, 0.0]],
                          [[0.12, -0.01, 0.0], [0.11, 0.005, 0.0]],
                          [[0.12, -0.01, 0.0], [0.13, 0.005, 0.0]]])
        scene.add_line_segments("/gravity", arrow, _solid(arrow, GRAVITY_RGB), thickness=0.002)
        scene.add_label("/gravity/label", "g", position=(0.125, 0.02, 0.0))
        skel = self.drawing.skeleton(zero)
        self.ghost_d = scene.add_line_segments("/ghost_alpha_d", skel, _solid(skel, GHOST_D_RGB), thickness=0.002,
                                               visible=False)
        self.ghost_ip = scene.add_line_segments("/ghost_alpha_ip", skel, _solid(skel, GHOST_IP_RGB), thickness=0.002,
                                                visible=False)
        self.bars = scene.add_line_segments("/neck/bars", g.bars, _solid(g.bars, BAR_RGB), thickness=0.004)
        self.springs = scene.add_line_segments("/neck/springs", g.springs, _solid(g.springs, SPRING_RGB),
                                               thickness=0.0015)
        self.pulleys = scene.add_line_segments("/neck/pulleys", g.pulleys, _solid(g.pulleys, PULLEY_RGB),
                                               thickness=0.001)
        self.cables = []
        for j, segs in enumerate(g.cables):
            # z offset per cable so that cables sharing a side stay distinguishable
            self.cables.append(scene.add_line_segments(
                f"/neck/cable_{j + 1}", segs, _solid(segs, (0, 0, 255)), thickness=0.002,
                position=(0.0, 0.0, 0.002 * (j + 1))))

    def pose(self) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """(α̂, α^d, α_IP, tension) from the latest values (rad, rad, rad, N); None when unknown."""
        status, truth = self.values.get("status"), self.values.get("truth")
        camera, state = self.values.get("camera"), self.values.get("state")
        alpha_hat = np.asarray(status.alpha_hat_rad) if status else (np.asarray(truth.alpha_rad) if truth else None)
        alpha_d = np.asarray(status.alpha_d_rad) if status else None
        alpha_ip = np.asarray(camera.alpha_ip_rad, dtype=float) if camera else None  # a missing joint (null) → NaN
        tension = np.asarray(truth.tension_N) if truth else (np.asarray(state.force_applied_N) if state else None)
        return alpha_hat, alpha_d, alpha_ip, tension

    def update(self) -> None:
        alpha_hat, alpha_d, alpha_ip, tension = self.pose()
        n = self.drawing.n_joints
        with self.server.atomic():
            if alpha_hat is not None and alpha_hat.shape == (n,):
                g = self.drawing.geometry(alpha_hat)
                self.bars.points = g.bars
                self.springs.points = g.springs
                self.pulleys.points = g.pulleys
                colors = (tension_colors(tension, self.f_max_N) if tension is not None
                          and len(tension) == len(self.cables) else None)
                for j, handle in enumerate(self.cables):
                    handle.points = g.cables[j]
                    if colors is not None:
                        handle.colors = np.broadcast_to(colors[j], g.cables[j].shape).copy()
            for handle, alpha in ((self.ghost_d, alpha_d), (self.ghost_ip, alpha_ip)):
                if alpha is not None and alpha.shape == (n,) and np.all(np.isfinite(alpha)):
                    handle.points = self.drawing.skeleton(alpha)
                    handle.visible = True
        self.updates += 1

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        last_version = -1
        while not self._stop.wait(period):
            version = self.values.version()
            if version == last_version:
                continue
            last_version = version
            try:
                self.update()
            except Exception:  # a drawing bug must not kill the view thread
                log.exception("scene update failed")
                time.sleep(1.0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        with contextlib.suppress(Exception):
            self.server.stop()
