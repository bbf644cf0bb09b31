"""Tension distribution over the redundant cables (3-X paper §6.2, eqs. 62-65).

With N short cables (one ending at each joint, Z1 triangular) and one long cable (Z2):
Γ^d = Z1·f_short + Z2·f_long, so f = p + n·f_long with p = (Z1⁻¹Γ^d, 0) and
n = (−Z1⁻¹Z2, 1) > 0 (eq. 63). Each cable needs f_i ≥ lb_i = max(t_min + f_friction,i +
(R/r_d)·I_a·θ̈_i, f_min) (eq. 65); every bound gives a lower bound on f_long and the greatest is
taken, which minimises ‖f‖ while meeting them all. Forces above f_max are clamped and reported.
Written for any N; the 3-X prototype has N = 3.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Distribution(NamedTuple):
    f: np.ndarray  # (N+1,) N, forces to command, in cable order
    saturated: np.ndarray  # (N+1,) bool, clamped at f_max
    f_long: float  # N, the long cable's force before clamping
    feasible: bool  # False when n has a non-positive entry (outside the region where eq. 63 works)


def distribute(
    Z: np.ndarray, gamma_d: np.ndarray, lower: np.ndarray, f_max: float, short: np.ndarray, long: int
) -> Distribution:
    """Forces f (N) with Z·f = Γ^d (N·m) and f ≥ ``lower`` (N), eqs. 63-65.

    ``short`` holds the cable index of each joint's short cable, ``long`` the long cable's index.
    """
    Z1, Z2 = Z[:, short], Z[:, long]
    p_short = np.linalg.solve(Z1, gamma_d)
    n_short = -np.linalg.solve(Z1, Z2)
    feasible = bool(np.all(n_short > 0))
    # f_short,i = p_i + n_i·f_long >= lower_i  <=>  f_long >= (lower_i − p_i)/n_i when n_i > 0.
    with np.errstate(divide="ignore", invalid="ignore"):
        candidates = np.where(n_short > 0, (lower[short] - p_short) / n_short, -np.inf)
    f_long = float(max(lower[long], np.max(candidates)))
    f = np.empty(Z.shape[1])
    f[short] = p_short + n_short * f_long
    f[long] = f_long
    saturated = f > f_max
    return Distribution(np.minimum(f, f_max), saturated, f_long, feasible)


def lower_bounds(t_min: float, f_min: float, f_friction: np.ndarray, inertia_force: np.ndarray) -> np.ndarray:
    """Eq. 65: max(t_min + f_friction + (R/r_d)·I_a·θ̈, f_min) per cable (N)."""
    return np.maximum(t_min + f_friction + inertia_force, f_min)
