"""The viser 3D view of the neck, driven by the latest values of the bus.

Drawn in the base frame (y up, metres; ``server.neck_geometry``): the neck at α̂ (controller
status; the twin's truth when no controller runs) with bars, springs, pulleys and the four cables
coloured by tension (blue 0 N → red f_max; the twin's tension, else the applied forces); ghosts
of the bars at α^d (green) and α_IP (orange, camera); the base frame axes and a gravity arrow.
The α_IP ghost is shown only while the camera is fresh (:func:`server.live.fresh_camera`, the rule
of ``/api/camera``'s ``fresh``) and measures every joint: it had stayed at the last full pose after
a joint went missing and after the camera fell silent (audit of 2026-11-29).

The camera frames the neck's bounding volume over its joint range (:meth:`NeckDrawing.bounds`)
when a browser connects, when its view changes shape (a resized card) and on "reset view"; the
motors' drums (radius r_d), pulleys (r) and bars are drawn with the parameter set's dimensions.
A trajectory's motion can be previewed as a violet ghost (:meth:`NeckScene.preview`, the
editor's "preview in 3D"). The GUI panel has, for each client, a folder "Jog (deg)": a slider per
joint sending jog targets (``jog``, :func:`server.routes_jog.request_jog`; at most one per
``JOG_PERIOD_S`` while dragging, the last one where the slider stops), a "hold here" button
(``hold``) and an "API token" field. Any web page the operator visits can open viser's websocket
on 127.0.0.1 (it checks neither Origin nor token), so the folder is built per client (one client's
values never reach another) and its sliders and button act only while that client's token field
holds the console's API token (``token``), as ``POST /api/jog`` asks. A jog the client sent that
ends cut short (the controller aborted it, or a death of the controller or the bridge ended it:
``jog_state``, :func:`server.routes_jog.jog_status`) says so in its status line, as the dashboard's
jog panel does: it had gone on showing "→ jog-…" (review of session 57).

Nodes are created once; a daemon thread updates their properties at ``rate_hz`` inside
``server.atomic()`` so a browser never sees half a pose. It only reads :class:`LatestValues`,
never the bus, so a slow viser client cannot slow the control loop. While no viser client is
connected (and no preview or jog is under way) it redraws at ``IDLE_RATE_HZ`` only: the idle
console must cost next to nothing (issue 21); a client that connects wakes it at once.
"""

from __future__ import annotations

import contextlib
import hmac
import html
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import viser
import viser.transforms as vtf

from server.live import LatestValues, fresh_camera
from server.neck_geometry import NeckDrawing, tension_colors
from twin.camera.calibration import Calibration, twin_calibration
from twin.model.params import Params

log = logging.getLogger("xneck.scene")

BAR_RGB = (40, 40, 48)
SPRING_RGB = (150, 150, 160)
PULLEY_RGB = (90, 90, 110)
GHOST_D_RGB = (40, 170, 80)
GHOST_IP_RGB = (240, 140, 20)
PREVIEW_RGB = (150, 60, 200)
PREVIEW_HOLD_S = 1.0  # s the preview ghost stays at the last pose before it disappears
GRAVITY_RGB = (200, 30, 200)
MOTOR_RGB = (60, 60, 60)
CAMERA_RGB = (0, 120, 200)
CAMERA_FRUSTUM_SCALE_M = 0.06
JOG_PERIOD_S = 0.3  # s between two jog targets sent while a slider moves
FIT_MARGIN = 1.15  # the bounding box fills this much less than the view
TYPICAL_ASPECT = 1.4  # width/height of the dashboard's 3D card, for the camera before a client's is known
EARLY_UPDATES = 3  # camera updates after connecting that are fitted again (the client's initial camera races the fit)
# Redraws per second while nobody watches: geometry for 30 poses a second was most of the idle
# console's CPU (issue 21); the handles stay current within a second for a client that connects
# (it is woken at once anyway) and for anything reading them.
IDLE_RATE_HZ = 1.0
JOG_HELP = ("Moves the neck. Type the console's API token (printed by `xneck server`, or in "
            "`<data-dir>/token`) into **API token** first: any web page you visit can reach this panel, "
            "so without the token the sliders and *hold here* do nothing.")
NOT_SENT = "**not sent**: the API token field does not hold the console's token"


# Marks that make links, images, emphasis, code or tables anywhere in a line; those that act only at
# a line's start (#, -, +, 1.) cannot, since the text is made one line.
_MARKDOWN_SPECIAL = re.compile(r"([\\`*_\[\]()!|~>])")


def plain_markdown(text: object) -> str:
    """``text`` shown as itself in a viser markdown element: viser renders raw HTML in markdown, and
    a reason that reaches the panel may come from anyone on the bus (an e-stop reason carrying an
    ``<iframe srcdoc=...>`` ran script beside the token field: audit of 2026-11-26), so HTML is
    escaped and so is every markdown mark (no link, no image)."""
    one_line = " ".join(str(text).split())
    return _MARKDOWN_SPECIAL.sub(r"\\\1", html.escape(one_line, quote=False))


def jog_ended_markdown(jog_id: str, ended: object) -> str:
    """The jog folder's status line for a jog ``jog_id`` cut short, ``ended`` saying why."""
    return f"→ {plain_markdown(jog_id)} **cut short**: {plain_markdown(ended)}"


def jog_status_markdown(code: int, answer: object) -> str:
    """The jog folder's status line for the console's answer ``(code, answer)`` to a jog."""
    if code == 202 and isinstance(answer, dict):
        return f"→ {plain_markdown(answer.get('jog_id', ''))}"
    detail = answer.get("detail") if isinstance(answer, dict) else answer
    if isinstance(detail, list):
        detail = "; ".join(str(d.get("msg", d)) if isinstance(d, dict) else str(d) for d in detail)
    return f"**refused ({int(code)})**: {plain_markdown(detail)}"


@dataclass
class ClientJog:
    """The jog folder of one viser client: its sliders (deg), token field and status line, and the
    newest target (deg) not sent yet."""

    sliders: list[viser.GuiSliderHandle[float]]
    token: viser.GuiTextHandle
    text: viser.GuiMarkdownHandle
    target: list[float] | None = None
    sent_s: float = field(default=-math.inf)  # monotonic s of the last target sent
    jog_id: str = ""  # the last jog this client's sliders started, until its end is shown ('' : none)


def camera_frustum_pose(cal: Calibration) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(wxyz, position in m, vertical field of view in rad, aspect) of ``cal``'s camera in the
    robot's base frame, for viser's frustum (OpenCV convention, as the calibration's camera frame).
    ``rvec``/``tvec`` map plane (= base frame) points to the camera: the camera sits at −Rᵀt
    and turns by Rᵀ."""
    R = np.asarray(cv2.Rodrigues(np.asarray(cal.rvec, dtype=float))[0], dtype=float)
    position = -R.T @ np.asarray(cal.tvec, dtype=float)
    fov = 2.0 * math.atan2(cal.height / 2.0, cal.fy)
    return vtf.SO3.from_matrix(R.T).wxyz, position, fov, cal.width / cal.height


def _solid(segments: np.ndarray, rgb: tuple[int, int, int]) -> np.ndarray:
    return np.broadcast_to(np.asarray(rgb, dtype=np.uint8), segments.shape).copy()


class NeckScene:
    """A viser server showing the live neck. ``port`` 0 picks a free port; read :attr:`port`."""

    def __init__(self, values: LatestValues, params: Params, host: str = "127.0.0.1", port: int = 0,
                 rate_hz: float = 30.0, jog: Callable[[list[float]], tuple[int, Any]] | None = None,
                 hold: Callable[[], object] | None = None, calibration: Calibration | None = None,
                 token: Callable[[], str] | None = None,
                 jog_state: Callable[[], dict[str, Any] | None] | None = None) -> None:
        from bridge.session import free_tcp_port

        self.values = values
        self.jog, self.hold = jog, hold
        self.jog_state = jog_state  # the console's last jog (server.routes_jog.jog_status), for its end
        self.token = token  # the console's API token now; without it the panel never jogs
        self.jogs: dict[int, ClientJog] = {}  # client id -> its jog folder
        self._aspects: dict[int, float] = {}  # client id -> aspect ratio of its last fit
        self._preview: tuple[float, Any] | None = None  # (start, trajectory) of the motion previewed
        self._updates: dict[int, int] = {}  # client id -> camera updates seen
        self.rate_hz = rate_hz
        self.drawing = NeckDrawing(params)
        self.alpha_max_deg = float(params.limits.alpha_max_deg)
        self.centre, self.half_extents = self.drawing.bounds(math.radians(self.alpha_max_deg))
        self.f_max_N = float(params.limits.f_max)
        self.calibration = calibration or twin_calibration()
        self.server = viser.ViserServer(host=host, port=port or free_tcp_port(host), verbose=False)
        self.port = self.server.get_port()  # viser silently takes port+1 if the port is busy
        self.updates = 0
        self._stop = threading.Event()
        self._wake = threading.Event()  # a client connected, or close(): redraw now
        self._build()
        self._thread = threading.Thread(target=self._run, name="viser-scene", daemon=True)
        self._thread.start()

    def _build(self) -> None:
        scene = self.server.scene
        scene.set_up_direction("+y")
        self.server.gui.configure_theme(show_logo=False)
        self.server.gui.main_panel.minimize()  # the dashboard is the control surface; keep the neck visible
        # The neck is about 0.3 m tall: frame it from the front (+z) instead of viser's metres-scale default;
        # each client is fitted once its view's shape is known (fit()).
        cam = self.server.initial_camera
        cam.up = (0.0, 1.0, 0.0)
        cam.look_at = tuple(self.centre)
        cam.position = tuple(self.centre + np.array([0.0, 0.0, self.camera_distance(cam.fov, TYPICAL_ASPECT)]))
        cam.near = 0.01
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self._build_gui()
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
        self.ghost_preview = scene.add_line_segments("/ghost_preview", skel, _solid(skel, PREVIEW_RGB),
                                                     thickness=0.003, visible=False)
        self.bars = scene.add_line_segments("/neck/bars", g.bars, _solid(g.bars, BAR_RGB), thickness=0.004)
        self.springs = scene.add_line_segments("/neck/springs", g.springs, _solid(g.springs, SPRING_RGB),
                                               thickness=0.0015)
        self.pulleys = scene.add_line_segments("/neck/pulleys", g.pulleys, _solid(g.pulleys, PULLEY_RGB),
                                               thickness=0.001)
        for j, ring in enumerate(self.drawing.motors()):
            scene.add_line_segments(f"/motors/motor_{j + 1}", ring, _solid(ring, MOTOR_RGB), thickness=0.003,
                                    position=(0.0, 0.0, 0.002 * (j + 1)))
        # The camera's frustum at its calibrated pose (the twin's nominal camera), shown while a camera
        # (not the twin's white-noise α_IP) publishes.
        wxyz, position, fov, aspect = camera_frustum_pose(self.calibration)
        self.frustum = scene.add_camera_frustum("/camera", fov, aspect, scale=CAMERA_FRUSTUM_SCALE_M, thickness=0.002,
                                                color=CAMERA_RGB, wxyz=wxyz, position=position, visible=False)
        self.cables = []
        for j, segs in enumerate(g.cables):
            # z offset per cable so that cables sharing a side stay distinguishable
            self.cables.append(scene.add_line_segments(
                f"/neck/cable_{j + 1}", segs, _solid(segs, (0, 0, 255)), thickness=0.002,
                position=(0.0, 0.0, 0.002 * (j + 1))))

    # -- camera -------------------------------------------------------------------------------
    def camera_distance(self, fov_rad: float, aspect: float) -> float:
        """How far in front of the centre (+z) a camera of vertical field ``fov_rad`` and
        ``aspect`` (width/height) sees the whole bounding box, in m: the box's front face fills
        the tighter of the two fields."""
        hx, hy, hz = (float(v) for v in self.half_extents)
        tan_y = math.tan(max(fov_rad, 1e-3) / 2.0)
        tan_x = tan_y * max(aspect, 1e-3)
        return FIT_MARGIN * max(hx / tan_x, hy / tan_y) + hz

    def fit(self, client: viser.ClientHandle) -> None:
        """Frame the neck's bounding volume in ``client``'s view, from the front (+z)."""
        cam = client.camera
        self._aspects[client.client_id] = cam.aspect
        distance = self.camera_distance(cam.fov, cam.aspect)
        with client.atomic():  # position first: its setter moves look_at along
            cam.position = tuple(self.centre + np.array([0.0, 0.0, distance]))
            cam.look_at = tuple(self.centre)
            cam.up_direction = (0.0, 1.0, 0.0)

    def _on_connect(self, client: viser.ClientHandle) -> None:
        self.values.watch("3d view", True)  # the truth's tensions are drawn (server.live.VIEW_ONLY)
        self.fit(client)
        self._build_jog(client)
        self._wake.set()  # the idle thread draws the current pose for it now, then runs at rate_hz

        @client.camera.on_update
        def _(cam: viser.CameraHandle) -> None:  # a resized card changes the aspect: fit again
            seen = self._updates[client.client_id] = self._updates.get(client.client_id, 0) + 1
            if seen <= EARLY_UPDATES or abs(cam.aspect - self._aspects.get(client.client_id, cam.aspect)) > 0.02:
                self.fit(client)

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        self.jogs.pop(client.client_id, None)
        self._aspects.pop(client.client_id, None)
        self._updates.pop(client.client_id, None)
        if not self.server.get_clients():
            self.values.watch("3d view", False)

    # -- GUI panel: reset view, jog ---------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        reset = gui.add_button("reset view", hint="Frame the whole neck again")

        @reset.on_click
        def _(event: viser.GuiEvent) -> None:
            if event.client is not None:
                self.fit(event.client)

    def _build_jog(self, client: viser.ClientHandle) -> None:
        """``client``'s own jog folder (module docstring); nothing without a ``jog`` callable."""
        if self.jog is None:
            return
        gui = client.gui
        with gui.add_folder("Jog (deg)"):
            gui.add_markdown(JOG_HELP)
            token = gui.add_text("API token", "", hint="The console's API token (Authorization: Bearer <token>)")
            sliders = [gui.add_slider(f"α{j + 1}", -self.alpha_max_deg, self.alpha_max_deg, 0.5, 0.0)
                       for j in range(self.drawing.n_joints)]
            hold = gui.add_button("hold here", hint="Stop the move where the neck is")
            text = gui.add_markdown("")
        jog = ClientJog(sliders, token, text)
        for slider in sliders:
            slider.on_update(lambda _event: self._slider_moved(jog))
        hold.on_click(lambda _event: self._hold(jog))
        self.jogs[client.client_id] = jog

    def authorised(self, jog: ClientJog) -> bool:
        """Whether ``jog``'s token field holds the console's API token (in constant time)."""
        expected = self.token() if self.token is not None else ""
        return bool(expected) and hmac.compare_digest(jog.token.value.strip().encode(), expected.encode())

    def _slider_moved(self, jog: ClientJog) -> None:
        if not self.authorised(jog):
            jog.target, jog.text.content = None, NOT_SENT
            return
        jog.target = [float(s.value) for s in jog.sliders]
        self._wake.set()

    def _hold(self, jog: ClientJog) -> None:
        jog.target = None
        if not self.authorised(jog):
            jog.text.content = NOT_SENT
            return
        if self.hold is not None:
            self.hold()
            jog.jog_id, jog.text.content = "", "holding"

    def send_jog(self, now_s: float) -> None:
        """Send each client's newest slider pose if one waits and its last went ``JOG_PERIOD_S``
        ago; the token is checked again here (the field may have been cleared since the move)."""
        for jog in list(self.jogs.values()):
            target = jog.target
            if target is None or self.jog is None or now_s - jog.sent_s < JOG_PERIOD_S:
                continue
            jog.target, jog.sent_s = None, now_s
            if not self.authorised(jog):
                jog.text.content = NOT_SENT
                continue
            code, answer = self.jog(target)
            if code == 429:
                jog.target = target  # the newest goes next time
                continue
            jog.jog_id = str(answer.get("jog_id", "")) if code == 202 and isinstance(answer, dict) else ""
            jog.text.content = jog_status_markdown(code, answer)

    def show_jog_ends(self) -> None:
        """Say "cut short" in the status line of each client whose last jog ended so: the
        console's last jog (``jog_state``) is that client's, with an ``ended`` reason, as the
        dashboard's jog panel says it. A jog followed by another (any client's) is followed no more."""
        waiting = [j for j in list(self.jogs.values()) if j.jog_id]
        if not waiting or self.jog_state is None:
            return
        last = self.jog_state() or {}
        for jog in waiting:
            if jog.jog_id != last.get("jog_id"):
                jog.jog_id = ""
            elif last.get("ended"):
                jog.text.content = jog_ended_markdown(jog.jog_id, last["ended"])
                jog.jog_id = ""

    # -- preview of a trajectory's motion -------------------------------------------------------
    def preview(self, trajectory: Any) -> float:
        """Play ``trajectory`` (a :class:`controller.trajectory.Trajectory`) once as a violet ghost,
        in real time from now, before anything moves; returns its duration (s)."""
        self._preview = (time.monotonic(), trajectory)
        self._wake.set()  # played at rate_hz from now, even while no client is connected
        return float(trajectory.duration_s)

    def draw_preview(self, now_s: float) -> None:
        if self._preview is None:
            return
        start_s, traj = self._preview
        t = now_s - start_s
        if t > traj.duration_s + PREVIEW_HOLD_S:
            self._preview = None
            self.ghost_preview.visible = False
            return
        alpha = traj.sample(np.array([min(t, traj.duration_s)])).alpha[0]
        if alpha.shape == (self.drawing.n_joints,):
            self.ghost_preview.points = self.drawing.skeleton(alpha)
            self.ghost_preview.visible = True

    def pose(self) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """(α̂, α^d, α_IP, tension) from the latest values (rad, rad, rad, N); None when unknown, α_IP
        also while the camera is stale (:func:`server.live.fresh_camera`)."""
        status, truth = self.values.get("status"), self.values.get("truth")
        camera, state = fresh_camera(self.values), self.values.get("state")
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
            camera = fresh_camera(self.values)
            self.frustum.visible = bool(camera is not None and camera.source not in ("", "twin-noise"))
            if alpha_d is not None and alpha_d.shape == (n,) and np.all(np.isfinite(alpha_d)):
                self.ghost_d.points = self.drawing.skeleton(alpha_d)
                self.ghost_d.visible = True
            # α_IP only as the camera measures it now: hidden while a joint is missing (NaN) or the
            # camera is stale (None), shown again at the next fresh frame measuring every joint.
            if alpha_ip is not None and alpha_ip.shape == (n,) and np.all(np.isfinite(alpha_ip)):
                self.ghost_ip.points = self.drawing.skeleton(alpha_ip)
                self.ghost_ip.visible = True
            else:
                self.ghost_ip.visible = False
        self.updates += 1

    def watched(self) -> bool:
        """Whether the view is worth its full rate: a viser client is connected, or a preview or a
        jog from the panel is under way."""
        return bool(self._preview is not None or any(j.target is not None for j in list(self.jogs.values()))
                    or self.server.get_clients())

    def _run(self) -> None:
        last_version: tuple[int, bool] | None = None
        while True:
            self._wake.wait(1.0 / (self.rate_hz if self.watched() else min(IDLE_RATE_HZ, self.rate_hz)))
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                self.send_jog(time.monotonic())
                self.show_jog_ends()
                self.draw_preview(time.monotonic())
            except Exception:  # a jog that cannot be sent must not kill the view thread
                log.exception("jog or preview in the 3D view failed")
            # Redrawn on news, and when the camera turns stale: that is no news on the bus.
            version = (self.values.version(), fresh_camera(self.values) is not None)
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
        self._wake.set()
        self._thread.join(2.0)
        with contextlib.suppress(Exception):
            self.server.stop()
