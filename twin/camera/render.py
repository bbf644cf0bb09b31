"""The twin's camera: frames of the neck drawn from the truth, as the prototype's camera films it
(3-X paper §4.2: 1280×720, coloured markers on the base and top bars).

The scene lies in the neck's plane: a grey board, the base plate with its reference markers, and
per X-joint the crossed bars, the springs along the sides, the cables, the base/top bars and their
coloured markers (``twin.camera.layout``). Every outline is sampled densely in the plane and pushed
through the pinhole camera with its lens distortion (``Calibration.project``), so straight bars
curve as a real lens bends them. Then, in the order light meets a sensor: anti-aliased edges
(OpenCV's 1/16-pixel ``shift`` and ``LINE_AA``, optionally supersampled), lighting (a gradient and
vignetting), defocus blur, and Gaussian sensor noise. Occlusion covers chosen markers with a
grey disk (a finger, a cable bundle). Deterministic for a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from twin.camera.calibration import Calibration, twin_calibration
from twin.camera.layout import BAR_HUES_DEG, HUE_BGR, REFERENCE_HUE_DEG, MarkerLayout, marker_points
from twin.model import chain
from twin.model.numeric import Model

BOARD_BGR = (168, 168, 168)
PLATE_BGR = (120, 120, 120)
BAR_BGR = (35, 35, 35)
DIAGONAL_BGR = (70, 70, 70)
SPRING_BGR = (205, 205, 205)
CABLE_BGR = (45, 45, 45)
OCCLUDER_BGR = (110, 110, 110)
_SHIFT = 4
_SUB = 1 << _SHIFT
_MARGIN = 64  # px of extra sensor-noise bank: each frame reads it at a random offset
_NOISY_BACKGROUNDS = 4
_LIGHT_ONE = 128  # the lighting gain in fixed point (1/128): 8-bit arithmetic, under half a grey level off


@dataclass(frozen=True)
class RenderOptions:
    """Image degradations. ``noise_dn``: σ of the sensor noise in grey levels; ``blur_px``: σ of the
    defocus blur in pixels (0: none); ``gradient``: relative gain change from left to right edge;
    ``vignetting``: relative gain loss in the corners; ``gain``: overall exposure; ``occlude``:
    markers covered, as (bar, side) with bar 0 the base bar and side 0 left, 1 right;
    ``supersample``: draw at s× and average down (anti-aliasing beyond LINE_AA)."""

    noise_dn: float = 2.0
    blur_px: float = 0.8
    gradient: float = 0.15
    vignetting: float = 0.2
    gain: float = 1.0
    occlude: tuple[tuple[int, int], ...] = ()
    supersample: int = 2

    def __post_init__(self) -> None:
        for name in ("noise_dn", "blur_px", "gradient", "vignetting"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 50):
                raise ValueError(f"{name} must be in [0, 50], got {value}")
        if not (0.2 <= self.gain <= 3.0):
            raise ValueError(f"gain must be in [0.2, 3], got {self.gain}")
        if self.supersample not in (1, 2, 3, 4):
            raise ValueError("supersample must be 1, 2, 3 or 4")


_CIRCLE = np.column_stack([np.cos(np.linspace(0.0, 2.0 * math.pi, 40, endpoint=False)),
                           np.sin(np.linspace(0.0, 2.0 * math.pi, 40, endpoint=False))])  # a disk's outline, 40 points


def _disk(centre: np.ndarray, radius: float) -> np.ndarray:
    return centre + radius * _CIRCLE


def _band(p: np.ndarray, q: np.ndarray, width: float, extend: float = 0.0, step: float = 0.004) -> np.ndarray:
    """Outline of a rectangle of ``width`` around segment p–q (extended by ``extend`` at each end),
    sampled every ``step`` m so that lens distortion bends its sides."""
    d = q - p
    length = float(np.hypot(*d))
    u = d / length
    n = np.array([-u[1], u[0]]) * 0.5 * width
    a, b = p - extend * u, q + extend * u
    k = max(2, math.ceil((length + 2 * extend) / step) + 1)
    s = np.linspace(0.0, 1.0, k)[:, None]
    side = a + s * (b - a)
    return np.vstack([side + n, (side - n)[::-1]])


_ZIGZAG_TURNS = 9
_ZIGZAG_S = np.linspace(0.0, 1.0, 2 * _ZIGZAG_TURNS + 1)[:, None]  # along the spring
_ZIGZAG_SIDE = np.concatenate([[0.0], np.where(np.arange(1, 2 * _ZIGZAG_TURNS) % 2 == 0, -1.0, 1.0), [0.0]])[:, None]


def _zigzag(p: np.ndarray, q: np.ndarray, amplitude: float) -> np.ndarray:
    d = q - p
    u = d / max(float(np.hypot(*d)), 1e-9)
    return p + _ZIGZAG_S * d + (amplitude * _ZIGZAG_SIDE) * np.array([-u[1], u[0]])


def _to_pixels(cal: Calibration, plane_polys: list[np.ndarray]) -> list[np.ndarray]:
    """Plane polylines → fixed-point pixel polylines (1/16 px), one projection call for all."""
    if not plane_polys:
        return []
    fixed = np.round(cal.project(np.vstack(plane_polys)) * _SUB).astype(np.int32)
    return np.split(fixed, np.cumsum([len(p) for p in plane_polys])[:-1])


class Renderer:
    """Frames of the neck at joint angles α (rad) for one camera, layout and option set."""

    def __init__(self, model: Model, calibration: Calibration | None = None, layout: MarkerLayout | None = None,
                 options: RenderOptions | None = None, seed: int = 0) -> None:
        self.model = model
        self.calibration = calibration or twin_calibration()
        self.layout = layout or MarkerLayout()
        self.layout.check(model.n_joints, model.b)
        self.options = options or RenderOptions()
        self.rng = np.random.default_rng(seed)
        c, s = self.calibration, self.options.supersample
        self._draw_cal = c if s == 1 else replace(
            c, width=c.width * s, height=c.height * s, fx=c.fx * s, fy=c.fy * s,
            cx=s * c.cx + 0.5 * (s - 1), cy=s * c.cy + 0.5 * (s - 1))
        self._light = self._lighting()
        self._noise = None
        if self.options.noise_dn > 0:
            bank = np.round(self.rng.normal(0.0, self.options.noise_dn, size=(c.height + _MARGIN, c.width + _MARGIN, 3)))
            # Two 8-bit banks, what is added and what is taken away: saturating 8-bit adds, no widening.
            self._noise = (np.clip(bank, 0, 255).astype(np.uint8), np.clip(-bank, 0, 255).astype(np.uint8))
        self._static = self._static_layer()
        self._background = self._optics(self._static, 0, 0)
        # The static background with sensor noise, a few draws of it: a frame starts as one of
        # them and only the neck's region gets fresh noise (adding noise to the whole frame was
        # half the cost of a frame; the background's noise is then one of a few fixed patterns).
        self._backgrounds = [self._background if self._noise is None else self._noisy(self._background, 0, 0)
                             for _ in range(_NOISY_BACKGROUNDS if self._noise is not None else 1)]

    def _noisy(self, img: np.ndarray, x0: int, y0: int) -> np.ndarray:
        """``img`` (the sensor region starting at pixel (x0, y0)) plus sensor noise, at a random
        offset into the bank."""
        assert self._noise is not None
        dy, dx = (int(v) for v in self.rng.integers(0, _MARGIN, size=2))
        h, w = img.shape[:2]
        up, down = (bank[dy + y0:dy + y0 + h, dx + x0:dx + x0 + w] for bank in self._noise)
        return cv2.subtract(cv2.add(img, up), down)

    def _lighting(self) -> np.ndarray:
        """Gain per pixel (uint8 in 1/:data:`_LIGHT_ONE`, H×W×3): exposure, a left-to-right
        gradient, vignetting."""
        c, o = self.calibration, self.options
        x = (np.arange(c.width) - 0.5 * c.width) / (0.5 * c.width)
        y = (np.arange(c.height) - 0.5 * c.height) / (0.5 * c.width)
        xx, yy = np.meshgrid(x, y)
        gain = o.gain * (1.0 + 0.5 * o.gradient * xx) * (1.0 - o.vignetting * (xx**2 + yy**2) / (1.0 + (c.height / c.width) ** 2))
        fixed = np.clip(np.round(gain * _LIGHT_ONE), 0, 255).astype(np.uint8)
        return np.repeat(fixed[..., None], 3, axis=2)

    def _static_layer(self) -> np.ndarray:
        """Board, base plate and reference markers: the part of the frame that never moves."""
        c = self._draw_cal
        img = np.empty((c.height, c.width, 3), np.uint8)
        img[:] = BOARD_BGR
        plate = np.array([[-0.6, -0.012], [0.6, -0.012], [0.6, -0.3], [-0.6, -0.3]])
        edge = np.vstack([np.linspace(plate[0], plate[1], 60), np.linspace(plate[1], plate[2], 20),
                          np.linspace(plate[2], plate[3], 60), np.linspace(plate[3], plate[0], 20)])
        refs = [_disk(p, self.layout.reference_radius_m) for p in self.layout.reference()]
        polys = [edge, *refs]
        colours = [PLATE_BGR] + [HUE_BGR[REFERENCE_HUE_DEG]] * len(refs)
        for pts, colour in zip(_to_pixels(c, polys), colours):
            cv2.fillPoly(img, [pts], colour, lineType=cv2.LINE_AA, shift=_SHIFT)
        return img

    def _optics(self, img: np.ndarray, x0: int, y0: int) -> np.ndarray:
        """Drawing resolution → sensor: area average (anti-aliasing), defocus blur, lighting.
        ``img`` is the sensor region starting at pixel (x0, y0), at the drawing resolution."""
        s, o = self.options.supersample, self.options
        h, w = img.shape[0] // s, img.shape[1] // s
        if s > 1:
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        # The gain map is smooth, so blurring before lighting is the same image and keeps the
        # whole chain in saturating 8-bit arithmetic.
        if o.blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), o.blur_px)
        return cv2.multiply(img, self._light[y0:y0 + h, x0:x0 + w], scale=1.0 / _LIGHT_ONE, dtype=cv2.CV_8U)

    def _scene(self, alpha: np.ndarray) -> list[tuple[np.ndarray, tuple[int, int, int], int]]:
        """What moves, back to front, in the plane: (outline, colour, line thickness; 0 = filled)."""
        m, lay = self.model, self.layout
        ends = chain.bar_ends(m, alpha)  # (N, 4, 2): A, B, C, D per joint
        ops: list[tuple[np.ndarray, tuple[int, int, int], int]] = []
        for A, B, C, D in ends:
            ops += [(_zigzag(A, C, 0.004), SPRING_BGR, 2), (_zigzag(B, D, 0.004), SPRING_BGR, 2)]
        # Cables: along each side of the chain, just outside the springs (the pulleys' radius).
        phi = np.concatenate([[0.0], np.cumsum(alpha)])
        left = np.vstack([ends[0, 0], *(e[2] for e in ends)])
        right = np.vstack([ends[0, 1], *(e[3] for e in ends)])
        for side, sign in ((left, -1.0), (right, 1.0)):
            out = sign * m.r * np.column_stack([np.cos(phi), np.sin(phi)])
            ops.append((np.vstack([side[0] + out[0] + [0.0, -0.06], side + out]), CABLE_BGR, 1))
        for A, B, C, D in ends:
            ops += [(_band(A, D, 0.006), DIAGONAL_BGR, 0), (_band(B, C, 0.006), DIAGONAL_BGR, 0)]
        for p, q in [(ends[0, 0], ends[0, 1])] + [(e[2], e[3]) for e in ends]:
            ops.append((_band(p, q, 0.009, extend=0.004), BAR_BGR, 0))
        markers = marker_points(m, alpha, lay)
        for k, pair in enumerate(markers):
            ops += [(_disk(p, lay.radius_m), HUE_BGR[BAR_HUES_DEG[k]], 0) for p in pair]
        for bar, side in self.options.occlude:
            if 0 <= bar < len(markers) and side in (0, 1):
                ops.append((_disk(markers[bar, side], 2.0 * lay.radius_m), OCCLUDER_BGR, 0))
        return ops

    def render(self, alpha) -> np.ndarray:
        """A camera frame (H×W×3 BGR uint8) at joint angles ``alpha`` (rad).

        Only the region around the neck is drawn and filtered each frame (the rest is the static
        background, filtered once); the region is padded by the blur's reach so the result is the
        same as filtering the whole frame. Noise covers the whole frame: fresh over the region, one
        of a few pre-drawn patterns elsewhere."""
        alpha = np.asarray(alpha, dtype=float)
        c, s = self.calibration, self.options.supersample
        ops = self._scene(alpha)
        pixels = _to_pixels(self._draw_cal, [o[0] for o in ops])
        pts = np.vstack(pixels) / (_SUB * s)
        reach = math.ceil(4.0 * self.options.blur_px) + 2
        inner = (max(int(pts[:, 0].min()) - 4, 0), max(int(pts[:, 1].min()) - 4, 0),
                 min(int(pts[:, 0].max()) + 6, c.width), min(int(pts[:, 1].max()) + 6, c.height))
        pick = int(self.rng.integers(len(self._backgrounds))) if self._noise is not None else 0
        frame = self._backgrounds[pick].copy()
        if inner[2] > inner[0] and inner[3] > inner[1]:
            x0, y0 = max(inner[0] - reach, 0), max(inner[1] - reach, 0)
            x1, y1 = min(inner[2] + reach, c.width), min(inner[3] + reach, c.height)
            img = self._static[y0 * s:y1 * s, x0 * s:x1 * s].copy()
            shift = np.array([x0 * s, y0 * s], dtype=np.int32) * _SUB
            for pts_i, (_, colour, thickness) in zip(pixels, ops):
                local = pts_i - shift
                if thickness:
                    cv2.polylines(img, [local], False, colour, thickness * s, lineType=cv2.LINE_AA, shift=_SHIFT)
                else:
                    cv2.fillPoly(img, [local], colour, lineType=cv2.LINE_AA, shift=_SHIFT)
            region = self._optics(img, x0, y0)
            ix0, iy0 = inner[0] - x0, inner[1] - y0
            region = region[iy0:iy0 + inner[3] - inner[1], ix0:ix0 + inner[2] - inner[0]]
            if self._noise is not None:
                region = self._noisy(region, inner[0], inner[1])
            frame[inner[1]:inner[3], inner[0]:inner[2]] = region
        return frame


def marker_sheet(n_joints: int, layout: MarkerLayout | None = None, dpi: int = 300) -> np.ndarray:
    """A printable A4 sheet (BGR, ``dpi``) of every marker at its true size, labelled: two per bar
    (bar 0 is the base bar) and the base plate's reference markers. Print at 100 % scale."""
    lay = layout or MarkerLayout()
    px_per_m = dpi / 0.0254
    w, h = int(0.210 * px_per_m), int(0.297 * px_per_m)
    sheet = np.full((h, w, 3), 255, np.uint8)
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, dpi / 300.0
    cv2.putText(sheet, "xneck camera markers - print at 100% (check: the bar below is 100 mm)", (int(0.015 * px_per_m), int(0.015 * px_per_m)),
                font, 0.8 * scale, (0, 0, 0), max(1, int(2 * scale)), cv2.LINE_AA)
    y_bar = int(0.025 * px_per_m)
    cv2.rectangle(sheet, (int(0.015 * px_per_m), y_bar), (int(0.115 * px_per_m), y_bar + int(0.002 * px_per_m)), (0, 0, 0), -1)
    entries = [(f"bar {k} {'base' if k == 0 else f'top of joint {k}'}", BAR_HUES_DEG[k], lay.radius_m, 2) for k in range(n_joints + 1)]
    entries.append(("base plate reference", REFERENCE_HUE_DEG, lay.reference_radius_m, 4))
    y = 0.05
    for label, hue, radius, count in entries:
        cv2.putText(sheet, f"{label} (diameter {2000 * radius:.0f} mm) x{count}", (int(0.015 * px_per_m), int(y * px_per_m)),
                    font, 0.7 * scale, (0, 0, 0), max(1, int(2 * scale)), cv2.LINE_AA)
        y += 0.004 + radius
        for i in range(count * 2):  # spares
            centre = (int((0.02 + i * (2 * radius + 0.006)) * px_per_m), int(y * px_per_m))
            cv2.circle(sheet, centre, round(radius * px_per_m), HUE_BGR[hue], -1, cv2.LINE_AA)
        y += radius + 0.012
    return sheet


def checkerboard(pattern: tuple[int, int] = (9, 6), square_m: float = 0.02, dpi: int = 300) -> np.ndarray:
    """A printable checkerboard with ``pattern`` inner corners (columns, rows) for the intrinsic
    calibration (``twin.camera.calibration.intrinsics_from_checkerboard``)."""
    px = round(square_m * dpi / 0.0254)
    cols, rows = pattern[0] + 1, pattern[1] + 1
    margin = px
    board = np.full((rows * px + 2 * margin, cols * px + 2 * margin, 3), 255, np.uint8)
    for r in range(rows):
        for c in range(cols):
            if (r + c) % 2 == 0:
                board[margin + r * px: margin + (r + 1) * px, margin + c * px: margin + (c + 1) * px] = 0
    return board


def render_checkerboard(calibration: Calibration, rvec, tvec, pattern: tuple[int, int] = (9, 6), square_m: float = 0.02,
                        noise_dn: float = 2.0, blur_px: float = 0.8, seed: int = 0) -> np.ndarray:
    """A frame of the printed checkerboard (:func:`checkerboard`) held at pose (rvec, tvec): the
    twin's input to the intrinsic calibration. Board frame: the first inner corner at the origin,
    x along the columns, y along the rows, as ``calibrateCamera`` numbers them."""
    s = 2
    cal = replace(calibration, rvec=tuple(float(v) for v in np.ravel(rvec)), tvec=tuple(float(v) for v in np.ravel(tvec)))
    big = replace(cal, width=cal.width * s, height=cal.height * s, fx=cal.fx * s, fy=cal.fy * s,
                  cx=s * cal.cx + 0.5 * (s - 1), cy=s * cal.cy + 0.5 * (s - 1))
    img = np.full((big.height, big.width, 3), 90, np.uint8)
    cols, rows = pattern[0] + 1, pattern[1] + 1
    q = square_m
    paper = np.array([[-2 * q, -2 * q], [(cols) * q, -2 * q], [(cols) * q, (rows) * q], [-2 * q, (rows) * q]])
    polys, colours = [_band(0.5 * (paper[0] + paper[3]), 0.5 * (paper[1] + paper[2]), (rows + 2) * q, step=q / 4)], [(235, 235, 235)]
    for r in range(rows):
        for c in range(cols):
            if (r + c) % 2 == 0:
                x0, y0 = (c - 1) * q, (r - 1) * q
                k = np.linspace(0.0, q, 6)[:-1]
                square = np.vstack([np.column_stack([x0 + k, np.full(5, y0)]), np.column_stack([np.full(5, x0 + q), y0 + k]),
                                    np.column_stack([x0 + q - k, np.full(5, y0 + q)]), np.column_stack([np.full(5, x0), y0 + q - k])])
                polys.append(square)
                colours.append((20, 20, 20))
    for pts, colour in zip(_to_pixels(big, polys), colours):
        cv2.fillPoly(img, [pts], colour, lineType=cv2.LINE_AA, shift=_SHIFT)
    img = cv2.resize(img, (cal.width, cal.height), interpolation=cv2.INTER_AREA)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    if noise_dn > 0:
        noise = np.round(np.random.default_rng(seed).normal(0.0, noise_dn, img.shape)).astype(np.int16)
        img = cv2.add(img, noise, dtype=cv2.CV_8U)
    return img
