"""The least σ any excitation could give each k and λ (issue 17's target, on the design model of
:mod:`twin.identification.excitation`): an upper bound on their information, whatever the trajectory.

Why a bound exists
------------------
In the design model a cable's variable-stiffness rows touch only its own (k, λ, c_a), and a row's
k and λ entries depend on the cable's tension t alone (eqs. 54-57 at rest, columns scaled by the
base values, each row weighted by 1/(1 + λt/k) for the stretch's noise):

    r(t) = [x·k, x·t·λ] / (1 + λt/k),   x = t/(k + λt)   (so r_k = t·k²/(k + λt)², r_λ = t²·λ·k/(k + λt)²)

r_k peaks at t = k/λ: a stiffer-than-linear cable tells less about k the harder it is pulled.
Whatever a trajectory does, the information it gives (k, λ) per second of record is therefore
a mixture Σ w_i·r(t_i)r(t_i)ᵀ over tensions in [t_min, t_max], times the fraction of the time
the motor turns (a still motor gives no row). Dropping the damping column c_a only adds
information, so the c-optimal design over that set of mixtures bounds the σ of k (c = e_k) or
λ (c = e_λ) from below, for every trajectory of that duration at once, even one that could put
every cable at any tension at every instant with all four motors turning all the time (no
trajectory can: the tensions follow the joints and one internal force).

Elfving's theorem gives that design: for two parameters it has at most two support points
t_1, t_2, and writing c = a_1·r(t_1) + a_2·r(t_2) its variance is (|a_1| + |a_2|)², with
weights ∝ |a_i|. :func:`c_optimal` searches every pair of a fine tension grid in closed form.

The bound is as good as the design model: the σ's it predicts followed the campaigns' within about
±0.2 in ratio on the damping-only truth (docs/identification.md); a noise on the tension instead of
the stretch would make k's information grow with the tension, and on the robot truth each motor's
force scale adds a type-B part no excitation reduces.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["Bound", "SigmaBound", "c_optimal", "rows", "sigma_bound"]

FloatArray = NDArray[np.float64]

GRID = 1500  # tensions in the grid: pairs (1.1 M) in closed form, under a second


def rows(k: float, lam: float, t: ArrayLike) -> FloatArray:
    """The (k, λ) entries of the weighted, scaled variable-stiffness row at tensions ``t`` (N), (2, n)
    (module docstring; k in N/m, λ in 1/m as eq. 54's base values)."""
    t = np.asarray(t, dtype=float)
    d = (k + lam * t) ** 2
    return np.stack([t * k * k / d, t * t * lam * k / d])


class Bound(NamedTuple):
    """A c-optimal design of a 2-parameter mixture: its variance (per unit of information weight)
    and its support (the two tensions, N, and their weights)."""

    variance: float
    tensions_N: tuple[float, float]
    weights: tuple[float, float]


def c_optimal(r: FloatArray, c: ArrayLike, t: FloatArray) -> Bound:
    """The least cᵀF⁻¹c over mixtures F = Σ w_i·r_i·r_iᵀ (Σ w_i = 1) of the columns of ``r`` (2, n)
    taken at the tensions ``t`` (n,): Elfving's two-point design, every pair in closed form."""
    c = np.asarray(c, dtype=float)
    n = r.shape[1]
    if r.shape[0] != 2 or c.shape != (2,) or n < 2:
        raise ValueError(f"c_optimal needs rows (2, n ≥ 2) and c (2,), got {r.shape} and {c.shape}")
    i, j = np.triu_indices(n, 1)
    det = r[0, i] * r[1, j] - r[1, i] * r[0, j]
    ok = np.abs(det) > 1e-12 * np.max(np.abs(r)) ** 2
    safe = np.where(ok, det, 1.0)
    a1 = (c[0] * r[1, j] - c[1] * r[0, j]) / safe  # c = a1·r_i + a2·r_j
    a2 = (c[1] * r[0, i] - c[0] * r[1, i]) / safe
    var = np.where(ok, (np.abs(a1) + np.abs(a2)) ** 2, np.inf)
    m = int(np.argmin(var))
    if not math.isfinite(var[m]):
        raise ValueError("no two rows span the parameters: they are collinear over the whole range")
    w1 = float(abs(a1[m]) / (abs(a1[m]) + abs(a2[m])))
    return Bound(float(var[m]), (float(t[i[m]]), float(t[j[m]])), (w1, 1.0 - w1))


class SigmaBound(NamedTuple):
    """Per cable: the least relative σ of k and λ per √s of record (the unit of
    :attr:`twin.identification.excitation.Score.relative_sigma`) and the designs that reach them."""

    k: FloatArray  # (nc,)
    lam: FloatArray  # (nc,)
    k_designs: tuple[Bound, ...]
    lam_designs: tuple[Bound, ...]
    t_min_N: float
    t_max_N: float
    moving_fraction: float

    def relative_sigma(self) -> dict[str, float]:
        """Named as the identification's parameters: "k(1)", …, "lambda(1)", …"""
        nc = len(self.k)
        return {**{f"k({j + 1})": float(self.k[j]) for j in range(nc)},
                **{f"lambda({j + 1})": float(self.lam[j]) for j in range(nc)}}


def sigma_bound(k: ArrayLike, lam: ArrayLike, *, t_min_N: float, t_max_N: float,
                moving_fraction: float, grid: int = GRID) -> SigmaBound:
    """The bound of the module docstring for each cable (k (nc,) N/m, λ (nc,) 1/m): tensions
    anywhere in [``t_min_N``, ``t_max_N``], the motor turning for ``moving_fraction`` of the
    record (e.g. all of it but the design's rests)."""
    k, lam = np.atleast_1d(np.asarray(k, dtype=float)), np.atleast_1d(np.asarray(lam, dtype=float))
    if k.shape != lam.shape or not (np.all(k > 0) and np.all(lam >= 0) and np.all(np.isfinite(k + lam))):
        raise ValueError(f"k must be positive and λ non-negative, of one shape each, got {k} and {lam}")
    if not (0.0 < t_min_N < t_max_N and math.isfinite(t_max_N)):
        raise ValueError(f"the tension range must satisfy 0 < t_min < t_max (N), got [{t_min_N}, {t_max_N}]")
    if not 0.0 < moving_fraction <= 1.0:
        raise ValueError(f"the moving fraction must be in (0, 1], got {moving_fraction}")
    t = np.linspace(t_min_N, t_max_N, grid)
    kd, ld = [], []
    for kj, lj in zip(k, lam):
        r = rows(kj, lj, t)
        kd.append(c_optimal(r, (1.0, 0.0), t))
        ld.append(c_optimal(r, (0.0, 1.0), t))
    per_s = lambda b: math.sqrt(b.variance / moving_fraction)  # noqa: E731
    return SigmaBound(np.array([per_s(b) for b in kd]), np.array([per_s(b) for b in ld]), tuple(kd), tuple(ld),
                      float(t_min_N), float(t_max_N), float(moving_fraction))
