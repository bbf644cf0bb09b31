"""α_IP from a camera frame: coloured markers → sub-pixel centroids → the neck's plane → α.

1. Segmentation. Chroma (max − min of B, G, R) separates the saturated markers from everything
   else in the scene (grey board, black bars, silver springs) whatever the lighting; connected
   components of chroma > ``chroma_min`` are the candidate blobs, classified by the hue of their
   mean colour to the nearest palette hue (``twin.camera.layout``).
2. Sub-pixel centroid: chroma-weighted first moments over the blob's neighbourhood, weights
   ``chroma − chroma_floor``. A marker's edge pixel mixes marker and board linearly and its
   chroma is linear in that mix, so the weighted centroid is the centroid of the drawn disk, blur
   and anti-aliasing included.
3. Plane: centroids are undistorted and mapped to the neck's plane with the calibration's
   homography (``Calibration.to_plane``): lens distortion and perspective corrected.
4. Bars: a bar's two markers give its middle and orientation φ_k; its left/right order comes from
   the neighbouring bar, which always lies on the neck side of the bar (its normal · the vector
   between middles > 0 for |α| < 180°). α_i = φ_i − φ_{i−1} (2-X paper eq. 2: the top bar of
   joint i turns by α_i relative to its base bar).
5. Check with the X-joint geometry: the middle of the top bar must sit at
   P(α_i) = m(α_i)·(−sin(α_i/2), cos(α_i/2)) in the base bar's frame (2-X paper eqs. 1-2, with
   m = √(L² − b² cos²(α/2))), and the markers must be 2·offset apart. The residual grades the
   joint's ``confidence`` = exp(−½ (residual/σ)²); beyond ``outlier_m`` the joint is an outlier.
   A joint whose bar lacks a marker, or an outlier, is reported missing (None), never guessed.
6. Camera moved: the base plate's four reference markers are compared with where the calibration
   projects them (``Calibration.project`` of ``MarkerLayout.reference_m``). A camera bumped after
   its extrinsic calibration measures α wrong with high confidence (panned 3°: 0.5° mean error,
   confidence 0.93), which no check on the bars sees; the references, fixed on the plate, move
   with the camera only. When the largest shift exceeds ``moved_px`` every joint is reported
   missing, with the reason (``Detection.reason``). A frame where not all four are found cannot
   be checked: the last verdict holds (a camera does not move back by itself).

Speed: after a frame where every marker was found, the next frame is searched only in windows
around the last centroids (a few percent of the pixels); any miss falls back to the full frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from twin.camera.calibration import Calibration, twin_calibration
from twin.camera.layout import BAR_HUES_DEG, REFERENCE_HUE_DEG, MarkerLayout

# Largest shift (px) of a reference marker from where the calibration projects it before the frame
# is refused. Measured (``benchmarks/camera_moved.py``, docs/camera.md "Camera moved"): the unmoved
# twin camera 0.07 px median, 0.13 px at most (noise 6, blur 1.6), 15× below; panned 1° 1.5 px
# (α error 0.15° mean, 0.34° max, let through), 2° 3.2 px, 3° 4.8 px (0.45° mean, 0.98° max), 2.4× above.
MOVED_PX = 2.0
# What to do about it, in the reason: the extrinsics are solved from the same four markers.
RECALIBRATE = ("redo the extrinsic calibration on a frame of the neck at rest (docs/camera.md, Calibration) "
               "and restart the camera with it (--calibration)")


def moved_reason(shift_px: float, limit_px: float = MOVED_PX, todo: str = RECALIBRATE, where: str = "") -> str:
    """The one sentence of a camera moved since its calibration: the references' largest shift
    ``shift_px`` (px) beyond ``limit_px`` (px), ``where`` it was found (e.g. ", found at 2.000 s of
    the video"), and ``todo``, what to do about it (:data:`RECALIBRATE` for a live camera)."""
    return (f"camera moved {shift_px:.1f} px since its calibration (a base-plate reference marker "
            f"from where the calibration puts it; limit {limit_px:g} px){where}: {todo}")


@dataclass(frozen=True)
class DetectorConfig:
    """Thresholds. ``chroma_min`` (grey levels) seeds a blob, ``chroma_floor`` is subtracted from
    the weights (noise on grey has chroma of a few levels); ``hue_tolerance_deg`` classifies;
    ``window_px`` is the half size of a tracking window; ``sigma_m`` grades the geometric residual,
    ``outlier_m`` rejects a joint; ``moved_px``: the largest shift (px) of a base-plate reference
    marker from its calibrated position before the camera is taken as moved (``math.inf``: never;
    docs/camera.md, "Camera moved", for the measured shifts)."""

    chroma_min: float = 60.0
    chroma_floor: float = 18.0
    hue_tolerance_deg: float = 25.0
    min_area_px: int = 12
    window_px: int = 40
    sigma_m: float = 0.002
    outlier_m: float = 0.006
    spacing_tolerance_m: float = 0.004
    moved_px: float = MOVED_PX


@dataclass
class Blob:
    hue_deg: float
    centre_px: np.ndarray  # (2,) sub-pixel, distorted image
    area_px: int


@dataclass
class Detection:
    """One frame's result. ``alpha_rad[i]`` is None for a missing joint (confidence 0 then).
    ``markers_px`` maps (bar, side) to the centroid used; ``reference_px`` the base plate's."""

    alpha_rad: list[float | None]
    confidence: list[float]
    markers_px: dict[tuple[int, int], tuple[float, float]] = field(default_factory=dict)
    reference_px: list[tuple[float, float]] = field(default_factory=list)
    residual_m: list[float | None] = field(default_factory=list)
    reference_shift_px: float | None = None  # largest |found − calibrated| of the four references (None: not all four found)
    reason: str = ""  # why every joint is missing when it is not the markers' fault (the camera moved), else ''

    @property
    def alpha_deg(self) -> list[float | None]:
        return [None if a is None else math.degrees(a) for a in self.alpha_rad]

    def as_json(self) -> dict:
        return {"alpha_deg": self.alpha_deg, "confidence": self.confidence}


def _hue_deg(bgr: np.ndarray) -> float:
    b, g, r = (float(v) for v in bgr)
    mx, mn = max(r, g, b), min(r, g, b)
    c = mx - mn
    if c <= 0:
        return float("nan")
    if mx == r:
        h = ((g - b) / c) % 6.0
    elif mx == g:
        h = (b - r) / c + 2.0
    else:
        h = (r - g) / c + 4.0
    return 60.0 * h


def _hue_distance(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


class Detector:
    """Measures α (rad) of an N-joint neck from frames of one calibrated camera.

    ``L_m`` and ``b_m`` are the X-joint's diagonal and bar lengths (``Params.geometry``).
    :meth:`detect` keeps the last centroids to search windows in the next frame; :meth:`reset`
    forgets them (e.g. after a jump in a video).
    """

    def __init__(self, n_joints: int, L_m: float, b_m: float, calibration: Calibration | None = None,
                 layout: MarkerLayout | None = None, config: DetectorConfig | None = None) -> None:
        self.n_joints = n_joints
        self.L_m, self.b_m = float(L_m), float(b_m)
        self.calibration = calibration or twin_calibration()
        self.layout = layout or MarkerLayout()
        self.layout.check(n_joints, b_m)
        self.config = config or DetectorConfig()
        self.hues = list(BAR_HUES_DEG[: n_joints + 1]) + [REFERENCE_HUE_DEG]
        # Where the calibration puts the base plate's references, in the order of Detection.reference_px.
        self._reference_expected = self.calibration.project(self.layout.reference())
        self._moved_px: float | None = None  # the last verdict: the shift of a moved camera, None if not moved
        self._last: list[np.ndarray] | None = None  # centroids of the last complete detection, per bar marker
        self._previous: list[np.ndarray] | None = None  # and of the one before (for the velocity)
        self.full_frames = 0
        self.windowed_frames = 0

    @property
    def moved_px(self) -> float | None:
        """The verdict in force: the references' largest shift (px) of a camera moved since its
        calibration, None while it is not (:attr:`Detection.reason` says it on every frame)."""
        return self._moved_px

    def reset(self) -> None:
        """Forget the tracking windows (a jump in a video). The camera-moved verdict stays: the
        camera's placement does not change with the video's time."""
        self._last = self._previous = None

    # --- segmentation ---------------------------------------------------------------------------

    def _blobs(self, image: np.ndarray, x0: int = 0, y0: int = 0) -> list[Blob]:
        """Blobs of one image region; centres in full-frame pixels."""
        cfg = self.config
        b, g, r = cv2.split(image)
        chroma = cv2.subtract(cv2.max(cv2.max(b, g), r), cv2.min(cv2.min(b, g), r))
        _, mask = cv2.threshold(chroma, cfg.chroma_min, 255, cv2.THRESH_BINARY)
        # Outer contours find the seeds (much faster than labelling the whole frame); each blob is
        # then labelled within its own small patch.
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        out = []
        h, w = chroma.shape
        pad = 3
        for contour in contours:
            x, y, bw, bh = cv2.boundingRect(contour)
            if bw * bh < cfg.min_area_px:
                continue
            xa, ya, xb, yb = max(x - pad, 0), max(y - pad, 0), min(x + bw + pad, w), min(y + bh + pad, h)
            n, labels, stats, _ = cv2.connectedComponentsWithStats(mask[ya:yb, xa:xb], connectivity=8)
            if n < 2:
                continue
            k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
            area = int(stats[k, cv2.CC_STAT_AREA])
            if area < cfg.min_area_px:
                continue
            weights = chroma[ya:yb, xa:xb].astype(np.float32) - cfg.chroma_floor
            # Only this blob's neighbourhood: pixels of another seeded blob get no weight.
            weights[(weights < 0) | ((labels != 0) & (labels != k))] = 0.0
            mom = cv2.moments(weights)
            if mom["m00"] <= 0:
                continue
            colour = cv2.mean(image[ya:yb, xa:xb], mask=(labels == k).astype(np.uint8))[:3]
            centre = np.array([mom["m10"] / mom["m00"] + xa + x0, mom["m01"] / mom["m00"] + ya + y0])
            out.append(Blob(_hue_deg(np.asarray(colour)), centre, area))
        return out

    def _classify(self, blobs: list[Blob]) -> dict[int, list[Blob]]:
        """Blobs per palette index (bars 0..N, then N+1 for the reference markers)."""
        classes: dict[int, list[Blob]] = {i: [] for i in range(len(self.hues))}
        for blob in blobs:
            if not math.isfinite(blob.hue_deg):
                continue
            d = [_hue_distance(blob.hue_deg, h) for h in self.hues]
            i = int(np.argmin(d))
            if d[i] <= self.config.hue_tolerance_deg:
                classes[i].append(blob)
        return classes

    def _windowed(self, image: np.ndarray) -> list[Blob] | None:
        """Blobs found in windows around each marker's predicted position (constant velocity from
        the last two frames), and around each base-plate reference's calibrated position (so the
        camera-moved check runs on tracked frames too), or None if one was not found whole: no blob
        of its colour in its window, or a blob cut by the window's edge (its centroid would be biased)."""
        assert self._last is not None
        h, w = image.shape[:2]
        half = self.config.window_px
        found: list[Blob] = []
        previous = self._previous if self._previous is not None else self._last
        bars = [(self.hues[index // 2], 2.0 * last - before)  # two markers per bar, in bar order
                for index, (last, before) in enumerate(zip(self._last, previous))]
        references = [(REFERENCE_HUE_DEG, centre) for centre in self._reference_expected]
        for hue, centre in bars + references:
            x, y = round(centre[0]), round(centre[1])
            xa, ya, xb, yb = max(x - half, 0), max(y - half, 0), min(x + half, w), min(y + half, h)
            if xb - xa < 4 or yb - ya < 4:
                return None
            blobs = [bl for bl in self._blobs(image[ya:yb, xa:xb], xa, ya)
                     if math.isfinite(bl.hue_deg) and _hue_distance(bl.hue_deg, hue) <= self.config.hue_tolerance_deg]
            if not blobs:
                return None
            best = min(blobs, key=lambda bl: float(np.hypot(*(bl.centre_px - centre))))
            reach = math.sqrt(best.area_px / math.pi) + 4.0
            cx, cy = best.centre_px
            inner = (cx - reach >= xa or xa == 0) and (cx + reach <= xb or xb == w) and \
                (cy - reach >= ya or ya == 0) and (cy + reach <= yb or yb == h)
            if not inner:
                return None
            found.append(best)
        return found

    # --- geometry -------------------------------------------------------------------------------

    def _top_middle(self, alpha: float) -> np.ndarray:
        """P(α), 2-X paper eqs. 1-2: middle of the top bar in the base bar's frame (m)."""
        m = math.sqrt(self.L_m**2 - (self.b_m * math.cos(0.5 * alpha)) ** 2)
        return m * np.array([-math.sin(0.5 * alpha), math.cos(0.5 * alpha)])

    def _bars(self, classes: dict[int, list[Blob]]) -> list[tuple[np.ndarray, np.ndarray, tuple[Blob, Blob]] | None]:
        """Per bar: (the two plane points, unordered), (middle), blobs; None without exactly one pair."""
        spacing = 2.0 * self.layout.offset_m
        out: list = []
        for k in range(self.n_joints + 1):
            blobs = classes.get(k, [])
            best = None
            if len(blobs) >= 2:
                plane = self.calibration.to_plane(np.array([bl.centre_px for bl in blobs]))
                pairs = [(abs(float(np.hypot(*(plane[i] - plane[j]))) - spacing), i, j)
                         for i in range(len(blobs)) for j in range(i + 1, len(blobs))]
                err, i, j = min(pairs)
                # Two candidates for a bar is a clean view; more means a reflection or a stray colour:
                # accept the pair with the right spacing only if it is unambiguous.
                ok = err <= self.config.spacing_tolerance_m and (len(blobs) == 2 or sum(
                    1 for e, _, _ in pairs if e <= self.config.spacing_tolerance_m) == 1)
                if ok:
                    best = (plane[[i, j]], 0.5 * (plane[i] + plane[j]), (blobs[i], blobs[j]))
            out.append(best)
        return out

    def _orient(self, pts: np.ndarray, middle: np.ndarray, toward: np.ndarray, sign: float) -> tuple[np.ndarray, float]:
        """Order (left, right) of a bar's points so that its normal points ``sign``·toward ``toward``."""
        d = pts[1] - pts[0]
        normal = np.array([-d[1], d[0]])
        if sign * float(normal @ (toward - middle)) < 0:
            pts = pts[::-1]
            d = -d
        return pts, math.atan2(d[1], d[0])

    def detect(self, image: np.ndarray) -> Detection:
        """α of every joint in one BGR frame of the calibrated size."""
        cal = self.calibration
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError("a frame must be an H×W×3 uint8 BGR image")
        if image.shape[:2] != (cal.height, cal.width):
            raise ValueError(f"frame is {image.shape[1]}×{image.shape[0]}, the calibration {cal.width}×{cal.height}")
        blobs = self._windowed(image) if self._last is not None else None
        if blobs is not None:
            found = self._measure(blobs)
            if None not in found.alpha_rad:
                self.windowed_frames += 1
                return found
            # A window caught the wrong blob (two markers crossing): search the whole frame.
        self.full_frames += 1
        return self._measure(self._blobs(image))

    def _measure(self, blobs: list[Blob]) -> Detection:
        """α from the blobs of one frame (the body of :meth:`detect`)."""
        classes = self._classify(blobs)
        bars = self._bars(classes)
        n = self.n_joints
        phi: list[float | None] = [None] * (n + 1)
        markers: dict[tuple[int, int], tuple[float, float]] = {}
        middles = [None if bar is None else bar[1] for bar in bars]
        for k, bar in enumerate(bars):
            if bar is None:
                continue
            pts, middle, pair = bar
            below, above = (middles[k - 1] if k > 0 else None), (middles[k + 1] if k < n else None)
            if k == 0:
                toward, sign = middle + np.array([0.0, 1.0]), 1.0  # the base bar is upright
            elif below is not None:
                toward, sign = below, -1.0  # the previous bar lies below this one
            elif above is not None:
                toward, sign = above, 1.0
            else:
                continue
            ordered_pts, phi[k] = self._orient(pts, middle, toward, sign)
            swapped = not np.allclose(ordered_pts[0], pts[0])
            left, right = (pair[1], pair[0]) if swapped else pair
            markers[(k, 0)] = (float(left.centre_px[0]), float(left.centre_px[1]))
            markers[(k, 1)] = (float(right.centre_px[0]), float(right.centre_px[1]))
        alpha: list[float | None] = [None] * n
        conf = [0.0] * n
        residual: list[float | None] = [None] * n
        for i in range(n):
            base, top = phi[i], phi[i + 1]
            if base is None or top is None:
                continue
            a = math.remainder(top - base, 2.0 * math.pi)
            m_base, m_top = middles[i], middles[i + 1]
            assert m_base is not None and m_top is not None  # both bars have an orientation
            rel = m_top - m_base
            c, s = math.cos(base), math.sin(base)
            local = np.array([c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1]])
            res = float(np.hypot(*(local - self._top_middle(a))))
            residual[i] = res
            if res > self.config.outlier_m:
                continue
            alpha[i] = a
            conf[i] = math.exp(-0.5 * (res / self.config.sigma_m) ** 2)
        # Reference markers in the layout's order: rows top to bottom, each row left to right.
        by_row = sorted(classes.get(n + 1, []), key=lambda bl: bl.centre_px[1])
        refs = [bl for i in range(0, len(by_row), 2) for bl in sorted(by_row[i:i + 2], key=lambda bl: bl.centre_px[0])]
        # Keep the tracking windows only when every bar marker was found (else a full search next time).
        if len(markers) == 2 * (n + 1):
            self._previous = self._last
            self._last = [np.array(markers[(k, s)]) for k in range(n + 1) for s in (0, 1)]
        else:
            self._last = self._previous = None
        reference_px = [(float(b.centre_px[0]), float(b.centre_px[1])) for b in refs]
        shift = self._check_moved(reference_px)
        reason = ""
        if self._moved_px is not None:
            # Every α would be measured through the wrong pose: none is reported (markers kept, for the picture).
            reason = moved_reason(self._moved_px, self.config.moved_px)
            alpha = [None for _ in range(n)]
            conf = [0.0] * n
        return Detection(alpha_rad=alpha, confidence=conf, markers_px=markers, reference_px=reference_px,
                         residual_m=residual, reference_shift_px=shift, reason=reason)

    def _check_moved(self, reference_px: list[tuple[float, float]]) -> float | None:
        """The largest shift (px) of the references from their calibrated positions, None unless
        all four were found (the verdict then stays as it was); updates the verdict."""
        expected = self._reference_expected
        if len(reference_px) != len(expected):
            return None
        shift = float(np.max(np.hypot(*(np.asarray(reference_px) - expected).T)))
        self._moved_px = shift if shift > self.config.moved_px else None
        return shift
