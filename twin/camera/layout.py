"""Where the coloured markers sit on the neck, shared by the renderer and the detector.

As on the prototype (3-X paper §4.2, Fig. 1): two markers on each of the N+1 horizontal bars (the
base bar and the top bar of every X-joint), at ±``offset_m`` from the bar's middle along the bar;
one colour per bar, so a marker's colour names its bar and the geometry (which side of the bar the
previous bar lies on) names its side. Four reference markers of a colour no bar uses sit on the
fixed base plate: the extrinsic calibration (``twin.camera.calibration``) solves the camera pose
from them. Coordinates are in the neck's plane, the base frame of ``twin.model.chain`` (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.model import chain
from twin.model.numeric import Model

# Hues in degrees (0-360) and the BGR colour printed for each: saturated primaries, 60° apart or
# more, so blur and noise (which mix a marker with the grey board, not with another hue) never
# move a marker into a neighbour's class.
BAR_HUES_DEG = (0.0, 120.0, 240.0, 60.0, 180.0)  # red, green, blue, yellow, cyan: bar 0 (base) upwards
REFERENCE_HUE_DEG = 300.0  # magenta: the base plate's reference markers
HUE_BGR = {0.0: (40, 40, 230), 120.0: (40, 190, 40), 240.0: (230, 60, 40), 60.0: (30, 215, 215),
           180.0: (215, 200, 30), 300.0: (215, 40, 215)}


@dataclass(frozen=True)
class MarkerLayout:
    """Marker geometry: ``offset_m`` from the bar middle, disk ``radius_m``, and the base plate's
    reference markers (plane coordinates, m) in a fixed order (left to right, top row first)."""

    offset_m: float = 0.02
    radius_m: float = 0.004
    reference_m: tuple[tuple[float, float], ...] = ((-0.10, -0.025), (0.10, -0.025), (-0.10, -0.065), (0.10, -0.065))
    reference_radius_m: float = 0.006

    def check(self, n_joints: int, bar_length_m: float) -> None:
        if n_joints + 1 > len(BAR_HUES_DEG):
            raise ValueError(f"{n_joints} joints need {n_joints + 1} bar colours; the palette has {len(BAR_HUES_DEG)}")
        if not 0 < self.radius_m < self.offset_m <= 0.5 * bar_length_m:
            raise ValueError("markers must fit on the bar: 0 < radius < offset <= b/2")

    def reference(self) -> np.ndarray:
        return np.asarray(self.reference_m, dtype=float)


def bar_poses(model: Model, alpha) -> tuple[np.ndarray, np.ndarray]:
    """Middle (N+1, 2) in m and orientation (N+1,) in rad of the base bar and every top bar."""
    alpha = np.asarray(alpha, dtype=float)
    ends = chain.bar_ends(model, alpha)  # (N, 4, 2): A, B, C, D
    middles = np.vstack([0.5 * (ends[0, 0] + ends[0, 1]), 0.5 * (ends[:, 2] + ends[:, 3])])
    phi = np.concatenate([[0.0], np.cumsum(alpha)])
    return middles, phi


def marker_points(model: Model, alpha, layout: MarkerLayout) -> np.ndarray:
    """Plane positions (N+1, 2, 2) of every bar's left and right marker, m."""
    middles, phi = bar_poses(model, alpha)
    along = np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    return np.stack([middles - layout.offset_m * along, middles + layout.offset_m * along], axis=1)
