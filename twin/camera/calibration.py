"""The camera's calibration: intrinsics (pinhole + Brown-Conrady distortion) and the pose of the
neck's plane, with the two conversions the renderer and the detector need.

- :class:`Calibration` maps plane points (m, the base frame of ``twin.model.chain``, z = 0) to
  pixels (:meth:`Calibration.project`, what a lens does) and distorted pixels back to the plane
  (:meth:`Calibration.to_plane`: undistortion, then the plane homography H = K·[r1 r2 t]).
- :func:`intrinsics_from_checkerboard` calibrates K and the distortion from frames of a
  checkerboard (OpenCV's ``calibrateCamera``), once per camera and lens setting.
- :func:`extrinsics_from_reference` solves the plane's pose from the base plate's four reference
  markers (``solvePnP``, IPPE for planar targets), once per camera placement.
- :func:`twin_calibration` is the twin's nominal camera: 1280×720, about 0.5 m in front of the
  neck, slightly tilted, mild barrel distortion, framing the whole workspace within the joint limits.

Files are JSON (:meth:`Calibration.save` / :func:`load_calibration`), validated on load.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np


class CalibrationError(ValueError):
    """A calibration file or a calibration input is unusable; the message says why."""


# Plausibility bounds of a calibration (Calibration._check_plausible).
FOCAL_MIN_SIZES = 0.05  # focal length, in multiples of the image's larger side: a 170° fisheye
FOCAL_MAX_SIZES = 100.0  # a 0.6° field of view
PIXEL_ASPECT_MAX = 2.0  # fy/fx: square pixels are 1, anamorphic optics up to 2
RADIAL_MAX = 100.0  # |k1|, |k2|, |k3|: wide lenses fit |k| < 1, a free k3 may reach tens
TANGENTIAL_MAX = 1.0  # |p1|, |p2|: real lenses fit under 0.01
ROTATION_MAX_RAD = 2 * math.pi  # |rvec|: every rotation has one at most π; OpenCV's refinement may pass π
DISTANCE_MIN_M = 0.01  # |tvec|: the plane's origin from the camera, for a camera on a lab bench
DISTANCE_MAX_M = 5.0


def _in_range(name: str, value: float, low: float, high: float, unit: str = "") -> None:
    """:class:`CalibrationError` naming ``name``, its value and [low, high] unless low ≤ value ≤ high."""
    if not (low <= value <= high):
        raise CalibrationError(f"{name} = {value:g}{unit} is not plausible: expected {low:g} to {high:g}{unit}")


@dataclass(frozen=True)
class Calibration:
    """Pinhole camera looking at the neck's plane. ``dist`` = (k1, k2, p1, p2, k3) in OpenCV's
    order; ``rvec``/``tvec`` map plane coordinates (m) to camera coordinates (m)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    rvec: tuple[float, float, float] = (math.pi, 0.0, 0.0)
    tvec: tuple[float, float, float] = (0.0, 0.0, 0.5)

    def __post_init__(self) -> None:
        values = [self.fx, self.fy, self.cx, self.cy, *self.dist, *self.rvec, *self.tvec]
        if len(self.dist) != 5 or len(self.rvec) != 3 or len(self.tvec) != 3:
            raise CalibrationError("dist needs 5 coefficients, rvec and tvec 3 each")
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise CalibrationError("every calibration value must be a finite number")
        if not (16 <= self.width <= 8192 and 16 <= self.height <= 8192):
            raise CalibrationError(f"image size {self.width}×{self.height} is not plausible")
        if not (self.fx > 0 and self.fy > 0):
            raise CalibrationError("focal lengths must be positive")
        if self.tvec[2] <= 0:
            raise CalibrationError("the plane must lie in front of the camera (tvec z > 0)")
        self._check_plausible()

    def _check_plausible(self) -> None:
        """Finite is not enough: cx = 1e300 px or a camera 1e9 m away passed as a calibration
        (user audit) and rendered or detected nonsense. The ranges are generous on purpose (any
        real lens, the twin's camera and what OpenCV fits on a sane checkerboard pass); the error
        names the field, its value and the range."""
        w, h, size = self.width, self.height, max(self.width, self.height)
        # A principal point is near the image's centre; decentred or cropped sensors move it, not
        # beyond half an image outside it.
        _in_range("cx", self.cx, -0.5 * w, 1.5 * w, " px")
        _in_range("cy", self.cy, -0.5 * h, 1.5 * h, " px")
        # f = size / (2 tan(FOV/2)): 0.05 × the larger side is a 170° fisheye's, 100 × a 0.6° telephoto's.
        for name, f in (("fx", self.fx), ("fy", self.fy)):
            _in_range(name, f, FOCAL_MIN_SIZES * size, FOCAL_MAX_SIZES * size, " px")
        _in_range("fy/fx", self.fy / self.fx, 1.0 / PIXEL_ASPECT_MAX, PIXEL_ASPECT_MAX)
        for name, k in zip(("k1", "k2", "p1", "p2", "k3"), self.dist):
            bound = TANGENTIAL_MAX if name.startswith("p") else RADIAL_MAX
            _in_range(f"dist {name}", k, -bound, bound)
        _in_range("|rvec|", math.hypot(*self.rvec), 0.0, ROTATION_MAX_RAD, " rad")
        _in_range("|tvec|", math.hypot(*self.tvec), DISTANCE_MIN_M, DISTANCE_MAX_M, " m")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=float)

    def homography(self) -> np.ndarray:
        """H (3×3): plane (x, y, 1) → undistorted normalised image coordinates (up to scale)."""
        R, _ = cv2.Rodrigues(np.asarray(self.rvec, dtype=float))
        return np.column_stack([R[:, 0], R[:, 1], np.asarray(self.tvec, dtype=float)])

    def project(self, plane_xy: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) of plane points (n, 2) in m, through the lens (distortion included)."""
        pts = np.asarray(plane_xy, dtype=float).reshape(-1, 2)
        obj = np.column_stack([pts, np.zeros(len(pts))])
        px, _ = cv2.projectPoints(obj, np.asarray(self.rvec, float), np.asarray(self.tvec, float), self.K, self.dist_array)
        return px.reshape(-1, 2)

    def to_plane(self, pixels: np.ndarray) -> np.ndarray:
        """Plane points (n, 2) in m of distorted pixel positions (n, 2): lens distortion corrected."""
        px = np.asarray(pixels, dtype=float).reshape(-1, 1, 2)
        if len(px) == 0:
            return np.zeros((0, 2))
        norm = cv2.undistortPoints(px, self.K, self.dist_array, None, None, None,
                                       (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)).reshape(-1, 2)
        h = np.column_stack([norm, np.ones(len(norm))]) @ np.linalg.inv(self.homography()).T
        return h[:, :2] / h[:, 2:3]

    def with_pose(self, rvec: Sequence[float] | np.ndarray, tvec: Sequence[float] | np.ndarray) -> Calibration:
        """The same camera at another pose (3 values each)."""
        r = [float(v) for v in np.ravel(rvec)]
        t = [float(v) for v in np.ravel(tvec)]
        if len(r) != 3 or len(t) != 3:
            raise CalibrationError("rvec and tvec need 3 values each")
        return replace(self, rvec=(r[0], r[1], r[2]), tvec=(t[0], t[1], t[2]))

    def to_json(self) -> str:
        return json.dumps({"format": "xneck-camera-calibration", "version": 1, **asdict(self)}, indent=2)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_json() + "\n")


def calibration_from_dict(data: object) -> Calibration:
    """A :class:`Calibration` from parsed JSON; :class:`CalibrationError` on anything unexpected."""
    if not isinstance(data, dict) or data.get("format") != "xneck-camera-calibration" or data.get("version") != 1:
        raise CalibrationError("not an xneck camera calibration (format/version 1)")
    fields = {k: v for k, v in data.items() if k not in ("format", "version")}
    expected = set(Calibration.__dataclass_fields__)
    if set(fields) != expected:
        raise CalibrationError(f"fields must be exactly {sorted(expected)}")
    try:
        for name in ("dist", "rvec", "tvec"):
            fields[name] = tuple(float(v) for v in fields[name])
        for name in ("width", "height"):
            if not isinstance(fields[name], int) or isinstance(fields[name], bool):
                raise CalibrationError(f"{name} must be an integer")
        for name in ("fx", "fy", "cx", "cy"):
            if isinstance(fields[name], bool) or not isinstance(fields[name], (int, float)):
                raise CalibrationError(f"{name} must be a number")
        return Calibration(**fields)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(str(exc)) from None


CALIBRATION_MAX_BYTES = 1 << 20  # a calibration file is about 600 bytes; a larger one is refused unread


def load_calibration(path: str | Path) -> Calibration:
    """The calibration in ``path``; :class:`CalibrationError` (one line, naming the file) for
    anything else: unreadable, over :data:`CALIBRATION_MAX_BYTES`, not UTF-8, not JSON (nested too
    deeply for the parser included: 200,000 nested arrays were a RecursionError traceback, audit of
    2026-11-29), or not a valid calibration."""
    try:
        with open(path, "rb") as f:
            data = f.read(CALIBRATION_MAX_BYTES + 1)
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read ({exc.strerror})") from None
    if len(data) > CALIBRATION_MAX_BYTES:
        raise CalibrationError(f"{path}: larger than 1 MiB, not a calibration file")
    try:
        parsed = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not UTF-8 text, not a calibration file") from None
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}: not JSON ({exc})") from None
    except RecursionError:
        raise CalibrationError(f"{path}: not a calibration (JSON nested too deeply)") from None
    try:
        return calibration_from_dict(parsed)
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from None


def look_at_pose(target_xy: tuple[float, float], distance_m: float, tilt_deg: float = 0.0,
                 pan_deg: float = 0.0, roll_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) of a camera ``distance_m`` in front of the plane (on +z), aimed at ``target_xy``,
    turned by ``tilt_deg`` about its x axis, ``pan_deg`` about its y axis, ``roll_deg`` about its axis."""
    base = np.diag([1.0, -1.0, -1.0])  # camera x right = plane x, camera y down = −plane y, looks along −z
    def rot(axis: int, deg: float) -> np.ndarray:
        r = np.zeros(3)
        r[axis] = math.radians(deg)
        return cv2.Rodrigues(r)[0]
    R = rot(2, roll_deg) @ rot(1, pan_deg) @ rot(0, tilt_deg) @ base
    target = np.array([target_xy[0], target_xy[1], 0.0])
    # The optical axis passes through the target at the given distance.
    axis_world = R.T @ np.array([0.0, 0.0, 1.0])
    centre = target - distance_m * axis_world
    tvec = -R @ centre
    return cv2.Rodrigues(R)[0].ravel(), tvec


def twin_calibration() -> Calibration:
    """The twin's nominal camera (1280×720, as on the prototype): frames x ∈ ±0.3 m, y ∈ −0.08…0.31 m."""
    rvec, tvec = look_at_pose((0.0, 0.115), 0.52, tilt_deg=4.0, pan_deg=-3.0, roll_deg=0.5)
    return Calibration(width=1280, height=720, fx=1000.0, fy=1000.0, cx=641.3, cy=358.2,
                       dist=(-0.08, 0.03, 0.0004, -0.0003, 0.0), rvec=tuple(rvec), tvec=tuple(tvec))


def intrinsics_from_checkerboard(frames: Sequence[np.ndarray], pattern: tuple[int, int], square_m: float,
                                 ) -> tuple[Calibration, float]:
    """Intrinsics from frames of a checkerboard with ``pattern`` = (columns, rows) inner corners.

    Returns the calibration (pose of the last view, to be replaced by :func:`extrinsics_from_reference`)
    and the RMS reprojection error in pixels. Raises :class:`CalibrationError` with fewer than 3 views.
    """
    cols, rows = pattern
    obj = np.zeros((cols * rows, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    obj_pts, img_pts, size = [], [], None
    for frame in frames:
        gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        size = gray.shape[::-1]
        found, corners = cv2.findChessboardCorners(gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            continue
        corners = cv2.cornerSubPix(gray, corners, (7, 7), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4))
        obj_pts.append(obj)
        img_pts.append(corners)
    if len(obj_pts) < 3 or size is None:
        raise CalibrationError(f"the checkerboard was found in {len(obj_pts)} frames; at least 3 are needed")
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj_pts, img_pts, size, None, None,
                                                     flags=cv2.CALIB_FIX_K3)
    d = [float(v) for v in np.ravel(dist)[:5]]
    cal = Calibration(width=int(size[0]), height=int(size[1]), fx=float(K[0, 0]), fy=float(K[1, 1]),
                      cx=float(K[0, 2]), cy=float(K[1, 2]), dist=(d[0], d[1], d[2], d[3], d[4]))
    cal = cal.with_pose(rvecs[-1], tvecs[-1])
    return cal, float(rms)


def extrinsics_from_reference(intrinsics: Calibration, reference_px: np.ndarray, reference_m: np.ndarray) -> Calibration:
    """The plane's pose from the reference markers' pixels (n ≥ 4, same order as ``reference_m``)."""
    px = np.asarray(reference_px, dtype=float).reshape(-1, 2)
    pl = np.asarray(reference_m, dtype=float).reshape(-1, 2)
    if len(px) < 4 or len(px) != len(pl):
        raise CalibrationError(f"{len(px)} reference markers found; 4 are needed")
    obj = np.column_stack([pl, np.zeros(len(pl))])
    ok, rvec, tvec = cv2.solvePnP(obj, px, intrinsics.K, intrinsics.dist_array, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError("solvePnP found no pose for the reference markers")
    rvec, tvec = cv2.solvePnPRefineLM(obj, px, intrinsics.K, intrinsics.dist_array, rvec, tvec)
    if tvec.ravel()[2] <= 0:
        raise CalibrationError("the reference markers put the plane behind the camera")
    return intrinsics.with_pose(rvec, tvec)
