"""Tension distribution over the redundant cables (3-X paper §6.2, eqs. 62-65).

With N short cables (one ending at each joint, Z1 triangular) and one long cable (Z2):
Γ^d = Z1·f_short + Z2·f_long, so f = p + n·f_long with p = (Z1⁻¹Γ^d, 0) and
n = (−Z1⁻¹Z2, 1) > 0 (eq. 63). Each cable needs f_i ≥ lb_i = max(t_min + f_friction,i +
(R/r_d)·I_a·θ̈_i, f_min) (eq. 65); every bound gives a lower bound on f_long and the greatest is
taken, which minimises ‖f‖ while meeting them all. Forces above f_max are clamped and reported.
Written for any N; the 3-X prototype has N = 3.

Eqs. 63-65 exist once, as the kernel :func:`distribute_into` (numba's ``njit`` or plain Python,
:mod:`twin.model.compiled`), which the controller's tick (controller/kernel.py) calls on its own
arrays; :func:`distribute` is the numpy-facing wrapper that allocates and calls it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from twin.model.compiled import njit
from twin.model.estimation import solve_into


class Distribution(NamedTuple):
    f: np.ndarray  # (N+1,) N, forces to command, in cable order
    saturated: np.ndarray  # (N+1,) bool, clamped at f_max
    f_long: float  # N, the long cable's force before clamping
    feasible: bool  # False when n has a non-positive entry (outside the region where eq. 63 works)


@njit(cache=True)
def distribute_into(Z, gamma, lower, f_max, short, long, Z1, LU, vN, p, nvec, f, saturated):
    """Eqs. 63-65 (:func:`distribute`) into ``f`` and ``saturated``; returns (feasible, f_long):
    whether n = −Z1⁻¹Z2 > 0 (the region where eq. 63 works) and the long cable's force before
    clamping. Z1, LU (N, N), vN, p, nvec (N,) are scratch. Z1 is solved by elimination
    (:func:`twin.model.estimation.solve_into`): a singular Z1 gives non-finite forces."""
    N = Z.shape[0]
    for i in range(N):
        for k in range(N):
            Z1[i, k] = Z[i, short[k]]
    solve_into(Z1, gamma, LU, p)
    for i in range(N):
        vN[i] = -Z[i, long]
    solve_into(Z1, vN, LU, nvec)
    # f_short,i = p_i + n_i·f_long >= lower_i  <=>  f_long >= (lower_i − p_i)/n_i when n_i > 0.
    feasible = True
    f_long = lower[long]
    for i in range(N):
        if nvec[i] > 0.0:
            cand = (lower[short[i]] - p[i]) / nvec[i]
            if cand > f_long:
                f_long = cand
        else:
            feasible = False
    for i in range(N):
        f[short[i]] = p[i] + nvec[i] * f_long
    f[long] = f_long
    for j in range(f.shape[0]):
        saturated[j] = f[j] > f_max
        if saturated[j]:
            f[j] = f_max
    return feasible, f_long


def distribute(
    Z: np.ndarray, gamma_d: np.ndarray, lower: np.ndarray, f_max: float, short: np.ndarray, long: int
) -> Distribution:
    """Forces f (N) with Z·f = Γ^d (N·m) and f ≥ ``lower`` (N), eqs. 63-65 (:func:`distribute_into`).

    ``short`` holds the cable index of each joint's short cable, ``long`` the long cable's index.
    """
    Z = np.ascontiguousarray(Z, dtype=float)
    N, nc = Z.shape
    gamma = np.ascontiguousarray(gamma_d, dtype=float).reshape(N)
    lo = np.ascontiguousarray(lower, dtype=float).reshape(nc)
    short = np.ascontiguousarray(short, dtype=np.int64).reshape(N)
    long = int(long)
    # The kernel does not check indices (compiled, it would read outside the arrays).
    if not (np.all((short >= 0) & (short < nc)) and 0 <= long < nc):
        raise IndexError(f"cable indices short={short.tolist()}, long={long} outside 0..{nc - 1}")
    f, saturated = np.empty(nc), np.empty(nc, dtype=np.bool_)
    feasible, f_long = distribute_into(Z, gamma, lo, float(f_max), short, long, np.empty((N, N)), np.empty((N, N)), np.empty(N), np.empty(N),
                                       np.empty(N), f, saturated)
    return Distribution(f, saturated, float(f_long), bool(feasible))


def lower_bounds(t_min: float, f_min: float, f_friction: np.ndarray, inertia_force: np.ndarray) -> np.ndarray:
    """Eq. 65: max(t_min + f_friction + (R/r_d)·I_a·θ̈, f_min) per cable (N)."""
    return np.maximum(t_min + f_friction + inertia_force, f_min)
