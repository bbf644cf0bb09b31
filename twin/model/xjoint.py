"""Geometry of one X-joint (anti-parallelogram) as exact jets of its angle α.

Joint frame: origin at the middle of the base bar, x along the base bar to the right, y along
the neck when α = 0. Base bar A = (−b/2, 0), B = (b/2, 0); top bar C (left), D (right) with its
middle at P and orientation α (α > 0 turns the top bar anticlockwise and shortens the LEFT side).
Diagonal bars A–D and B–C have length L; springs run along the sides A–C (left) and B–D (right).

Equations (3-X paper, with ERRATA.md): side lengths l_l, l_r (eqs. 1-2), ψ (eq. 7, the angle of
the diagonal B→C from the base bar), variable cable lengths of cases (a)-(d) (eqs. 3-6).
P = m(α)·(−sin(α/2), cos(α/2)) with m = sqrt(L² − b² cos²(α/2)) is 2-X paper eq. 1-2.
"""

from __future__ import annotations

import numpy as np

from twin.model import jet
from twin.model.compiled import kernel_array, njit

# Rows of the (N_ROWS, 3) jet table that joint_jets fills: (value, d/dα, d²/dα²) per quantity.
L_LEFT, L_RIGHT, PSI = 0, 1, 2
CASE_A, CASE_B, CASE_C, CASE_D = 3, 4, 5, 6  # variable cable length of cases (a)-(d), m
P_X, P_Y = 7, 8  # middle of the top bar, m
BODY0 = 9  # bodies (AD diagonal, BC diagonal, top bar), 3 rows each: centre x, centre y, angle φ
N_BODIES = 3
C_X, C_Y, D_X, D_Y = 18, 19, 20, 21  # top-bar ends, m (for drawing)
N_ROWS = 22

CASE_ROW = {"a": CASE_A, "b": CASE_B, "c": CASE_C, "d": CASE_D}


@njit(cache=True)
def _store(out, row, j):
    out[row, 0] = j[0]
    out[row, 1] = j[1]
    out[row, 2] = j[2]


@njit(cache=True)
def _pulley_case(side, r, alpha, sign):
    """Eqs. 3 (sign = −1, left side) and 4 (sign = +1, right side): the cable leaves a pulley of
    radius r tangentially; q is the free straight length."""
    if r == 0.0:
        return side
    q = jet.sqrt(jet.shift(jet.mul(side, side), -r * r))
    return jet.add(q, jet.scale(jet.sub(jet.scale(alpha, 0.5 * sign), jet.atan(jet.scale(q, 1.0 / r))), r))


@njit(cache=True)
def joint_jets(L, b, r, alpha_value, out):
    """Fill ``out`` (N_ROWS, 3) with the jets of every quantity of one X-joint at α (rad)."""
    a = (alpha_value, 1.0, 0.0)
    h = jet.scale(a, 0.5)
    s, c = jet.sin(h), jet.cos(h)
    m = jet.sqrt(jet.shift(jet.scale(jet.mul(c, c), -b * b), L * L))
    ll = jet.sub(m, jet.scale(s, b))  # eq. 1
    lr = jet.add(m, jet.scale(s, b))  # eq. 2 (ERRATA 1)
    px = jet.scale(jet.mul(m, s), -1.0)
    py = jet.mul(m, c)
    ca, sa = jet.cos(a), jet.sin(a)
    cx, cy = jet.sub(px, jet.scale(ca, 0.5 * b)), jet.sub(py, jet.scale(sa, 0.5 * b))
    dx, dy = jet.add(px, jet.scale(ca, 0.5 * b)), jet.add(py, jet.scale(sa, 0.5 * b))
    psi = jet.atan2(cy, jet.shift(cx, -0.5 * b))  # eq. 7: diagonal B→C against the base bar
    _store(out, L_LEFT, ll)
    _store(out, L_RIGHT, lr)
    _store(out, PSI, psi)
    _store(out, CASE_A, _pulley_case(ll, r, a, -1.0))
    _store(out, CASE_B, _pulley_case(lr, r, a, 1.0))
    _store(out, CASE_C, jet.sub(ll, jet.scale(a, r)))  # eq. 5
    _store(out, CASE_D, jet.scale(jet.sub(jet.scale(psi, 2.0), a), r))  # eq. 6
    _store(out, P_X, px)
    _store(out, P_Y, py)
    # Diagonal A–D: centre (A + D)/2, angle of D − A.
    _store(out, BODY0 + 0, jet.scale(jet.shift(dx, -0.5 * b), 0.5))
    _store(out, BODY0 + 1, jet.scale(dy, 0.5))
    _store(out, BODY0 + 2, jet.atan2(dy, jet.shift(dx, 0.5 * b)))
    # Diagonal B–C: centre (B + C)/2, angle ψ.
    _store(out, BODY0 + 3, jet.scale(jet.shift(cx, 0.5 * b), 0.5))
    _store(out, BODY0 + 4, jet.scale(cy, 0.5))
    _store(out, BODY0 + 5, psi)
    # Top bar: centre P, angle α.
    _store(out, BODY0 + 6, px)
    _store(out, BODY0 + 7, py)
    _store(out, BODY0 + 8, a)
    _store(out, C_X, cx)
    _store(out, C_Y, cy)
    _store(out, D_X, dx)
    _store(out, D_Y, dy)


@njit(cache=True)
def _table(L, b, r, flat):
    out = np.empty((flat.size, N_ROWS, 3))
    for k in range(flat.size):
        joint_jets(L, b, r, flat[k], out[k])
    return out


def jets(L: float, b: float, r: float, alpha: np.ndarray | float) -> np.ndarray:
    """Jet table for every angle of ``alpha`` (any shape, rad): shape alpha.shape + (N_ROWS, 3)."""
    alpha = np.asarray(alpha, dtype=float)
    flat = kernel_array(alpha.reshape(-1))  # one compiled version, whatever alpha's shape
    return _table(float(L), float(b), float(r), flat).reshape(alpha.shape + (N_ROWS, 3))


def side_lengths(L: float, b: float, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Spring (side) lengths l_l(α), l_r(α) in m, eqs. 1-2, vectorised over ``alpha`` (rad)."""
    t = jets(L, b, 0.0, alpha)
    return t[..., L_LEFT, 0], t[..., L_RIGHT, 0]


def psi(L: float, b: float, alpha: np.ndarray | float) -> np.ndarray:
    """ψ(α), eq. 7: angle (rad) between the base bar and the diagonal bar B→C."""
    return jets(L, b, 0.0, alpha)[..., PSI, 0]
