"""Drawable geometry of the neck at a configuration α: bars, springs, cables and pulleys as 3D
line segments, shared by the viser scene and the Foxglove scene channel of the archive.

Frame: the robot's base frame (``twin.model.chain``), x to the right along the base bar, y up along the
straight neck, z = 0 (the neck is planar), metres. Gravity is −y.

Cables are schematic: each cable is drawn through the bar ends its routing names — cases (a) and
(c) along the left side A→C, (b) along the right side B→D, (d) crossing from the side the cable is
on to the other one — starting at its motor below the base. Lengths drawn are not the model's
cable lengths (pulley wraps are not drawn); the model (``twin.model.cables``) owns those.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from twin.model.chain import bar_ends
from twin.model.numeric import Model, build
from twin.model.params import Params

A, B, C, D = 0, 1, 2, 3
MOTOR_DROP_M = 0.03  # how far below the base bar the motors are drawn (m)
PULLEY_SIDES = 12


def _to3(p: np.ndarray) -> np.ndarray:
    """(..., 2) planar points -> (..., 3) with z = 0."""
    return np.concatenate([p, np.zeros(p.shape[:-1] + (1,))], axis=-1)


@dataclass(frozen=True)
class NeckGeometry:
    """Segments of one pose; every array is (K, 2, 3) in metres, base frame."""

    bars: np.ndarray
    springs: np.ndarray
    cables: tuple[np.ndarray, ...]  # one (K_j, 2, 3) per cable, motor index order
    pulleys: np.ndarray


class NeckDrawing:
    """Computes :class:`NeckGeometry` for a parameter set (build once, call per frame)."""

    def __init__(self, params: Params) -> None:
        self.params = params
        self.model: Model = build(params)
        self.n_joints = params.n_joints
        self.n_cables = params.n_cables
        self.routes = params.routes
        self.pulley_radius_m = float(params.geometry.r)
        angle = np.linspace(0.0, 2.0 * np.pi, PULLEY_SIDES + 1)
        ring = np.stack([np.cos(angle), np.sin(angle)], axis=-1) * max(self.pulley_radius_m, 1e-3)
        self._ring = np.stack([ring[:-1], ring[1:]], axis=1)  # (S, 2, 2)

    def ends(self, alpha: np.ndarray) -> np.ndarray:
        """Bar ends A, B, C, D of every joint, (N, 4, 2) in m."""
        return bar_ends(self.model, np.asarray(alpha, dtype=float))

    def skeleton(self, alpha: np.ndarray) -> np.ndarray:
        """Bars only (for ghosts): base bar, then per joint the diagonals and the top bar, (K, 2, 3)."""
        e = self.ends(alpha)
        segs = [e[0, [A, B]]]
        for j in range(self.n_joints):
            segs += [e[j, [A, D]], e[j, [B, C]], e[j, [C, D]]]
        return _to3(np.stack(segs))

    def geometry(self, alpha: np.ndarray) -> NeckGeometry:
        e = self.ends(alpha)
        bars = self.skeleton(alpha)
        springs = _to3(np.stack([e[j, [A, C]] for j in range(self.n_joints)]
                                + [e[j, [B, D]] for j in range(self.n_joints)]))
        cables = tuple(_to3(self._cable(e, route)) for route in self.routes)
        centres = e.reshape(-1, 2)  # every bar end carries a pulley on the prototype
        pulleys = _to3((centres[:, None, None, :] + self._ring[None]).reshape(-1, 2, 2))
        return NeckGeometry(bars=bars, springs=springs, cables=cables, pulleys=pulleys)

    def motors(self) -> tuple[np.ndarray, ...]:
        """The motors' drums, one ring of radius r_d per cable under the base where its cable
        starts, (S, 2, 3) each in m (the base is fixed: drawn once)."""
        e = self.ends(np.zeros(self.n_joints))
        ring = self._ring / max(self.pulley_radius_m, 1e-3) * float(self.params.geometry.r_d)
        out = []
        for route in self.routes:
            start = e[0, A if route[0][1] in "ac" else B] - np.array([0.0, MOTOR_DROP_M + float(self.params.geometry.r_d)])
            out.append(_to3(start + ring))
        return tuple(out)

    def bounds(self, alpha_max_rad: float) -> tuple[np.ndarray, np.ndarray]:
        """(centre (3,), half extents (3,)) of the box holding the neck over its joint range and its
        motors: what a camera frames so that the whole neck shows at any pose, in m."""
        # A grid over the joint range: a bent X-joint can stand taller than a straight one.
        steps = np.linspace(-alpha_max_rad, alpha_max_rad, 5 if self.n_joints <= 3 else 3)
        poses = [np.array(p) for p in itertools.product(steps, repeat=self.n_joints)]
        points = [self.geometry(p).bars.reshape(-1, 3) for p in poses] + [m.reshape(-1, 3) for m in self.motors()]
        cloud = np.concatenate(points)
        lo, hi = cloud.min(axis=0), cloud.max(axis=0)
        return (lo + hi) / 2.0, (hi - lo) / 2.0

    def _cable(self, e: np.ndarray, route: tuple[tuple[int, str], ...]) -> np.ndarray:
        first_case = route[0][1]
        left = first_case in "ac"
        start = e[0, A if left else B]
        points = [start - np.array([0.0, MOTOR_DROP_M]), start]
        for joint, case in route:
            if case in "ac":
                left = True
                points.append(e[joint, C])
            elif case == "b":
                left = False
                points.append(e[joint, D])
            else:  # crossing: ends on the other side
                points.append(e[joint, D if left else C])
                left = not left
        p = np.asarray(points)
        return np.stack([p[:-1], p[1:]], axis=1)


def tension_colors(tension_N: np.ndarray, f_max_N: float) -> np.ndarray:
    """RGB (0-255) per cable: blue at 0 N through green to red at ``f_max_N``, (M, 3) uint8."""
    x = np.clip(np.asarray(tension_N, dtype=float) / max(f_max_N, 1e-9), 0.0, 1.0)
    r = np.clip(2.0 * x - 0.5, 0.0, 1.0)
    g = 1.0 - np.abs(2.0 * x - 1.0)
    b = np.clip(1.0 - 2.0 * x, 0.0, 1.0)
    return (255 * np.stack([r, g, b], axis=-1)).astype(np.uint8)
