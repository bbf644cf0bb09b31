"""Statics and stiffness of cable-actuated X-joint chains (2-X paper section 3; 3-X prototype).

2-X part (Furet & Wenger 2019, eqs. (15)-(22)), generalised to N joints where the paper allows:
the potential energy U = U_cables + U_springs + U_gravity (eq. 15) of N X-joints, each with two
linear lateral springs and mass on its median, is differentiated analytically in θ. Equilibrium is
∂U/∂θ = 0 (eq. 17) and the joint stiffness is K_θ = ∂²U/∂θ² (eq. 18); the Cartesian stiffness is
K_c = J⁻ᵀ K_θ J⁻¹ (eq. 19).

Two actuation strategies:
  * two cables (eq. 20): one cable along all left sides, one along all right sides (f_l, f_r);
    eq. (21) gives the unique forces of a configuration (2-X only).
  * 2N cables (eq. 22): joint i has its own antagonistic pair (f_li, f_ri), the cables of the
    upper joints strut-routed through the lower ones so only joint i's sides change their length.
    Each joint has a one-dimensional force redundancy (a segment in the force box); K_θi is affine
    along it, so its minimum and maximum sit at the segment's ends.

3-X prototype part: equilibrium Z(α) f = g(α) with four cables and three joints, one-dimensional
redundancy f = f_p + n t, through the numeric model of ``twin.model.numeric`` / ``twin.model.cables`` /
``twin.model.dynamics`` (3-X paper notation: joint angle α = 2θ, Z = −∂l_c/∂α).

Names: θ in the formulas is the 2-X paper's joint angle (half the top-bar angle, θ_i = α_i/2),
``half_alpha`` in the code (θ is the motor angle everywhere else in xneck); K_θ is ``K_joint``.

Units: SI. Lengths m, angles rad, forces N, torques N·m, joint stiffness N·m/rad, Cartesian
stiffness N/m. Cable forces are tensions (>= 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from twin.analysis.kinematics import check_design, jacobian, median_directions, median_length_derivatives

__all__ = [
    "Design",
    "ForceSegment",
    "Statics3X",
    "StiffnessExtremes",
    "cartesian_stiffness",
    "forces_two_cables",
    "joint_stiffness",
    "potential_gradient",
    "potential_hessian",
    "prototype_2x",
    "redundancy_segment",
    "side_length_derivatives",
    "statics_3x",
    "stiffness_3x",
    "stiffness_extremes",
    "wrench_feasible_two_cables",
]

GRAVITY = 9.81  # m/s²


@dataclass(frozen=True)
class Design:
    """An N-joint planar X-joint chain with lateral springs and cable force bounds.

    Attributes:
        L, b: diagonal and base/top bar lengths (m), identical for all joints.
        k_l, k_r: left/right spring stiffness of each joint (N/m), length N.
        l0_l, l0_r: left/right spring free lengths (m), length N.
        m_diagonal: mass of one diagonal bar (kg); m_bar: mass of one top bar (kg). The base bar of
            joint 1 is fixed; the top bar of joint i is the base bar of joint i+1.
        f_min, f_max: cable tension bounds (N).
        gravity: gravitational acceleration along −y (m/s²); 0 for a horizontal plane.
    """

    L: float = 0.1
    b: float = 0.05
    k_l: tuple[float, ...] = (150.0, 90.0)
    k_r: tuple[float, ...] = (150.0, 90.0)
    l0_l: tuple[float, ...] = (0.047, 0.037)
    l0_r: tuple[float, ...] = (0.047, 0.037)
    m_diagonal: float = 0.009
    m_bar: float = 0.006
    f_min: float = 0.5
    f_max: float = 50.0
    gravity: float = GRAVITY

    def __post_init__(self) -> None:
        check_design(self.L, self.b)
        n = len(self.k_l)
        for name in ("k_r", "l0_l", "l0_r"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} must have one entry per joint ({n}), got {getattr(self, name)}")
        for name in ("k_l", "k_r", "l0_l", "l0_r"):
            a = np.asarray(getattr(self, name), dtype=float)
            if not np.all(np.isfinite(a)) or np.any(a < 0):
                raise ValueError(f"{name} must be finite and non-negative, got {getattr(self, name)}")
        if not (0.0 <= self.f_min < self.f_max):
            raise ValueError(f"need 0 <= f_min < f_max, got f_min = {self.f_min}, f_max = {self.f_max}")
        if self.m_diagonal < 0 or self.m_bar < 0:
            raise ValueError("m_diagonal and m_bar must be non-negative")

    @property
    def n_joints(self) -> int:
        return len(self.k_l)

    def array(self, name: str) -> NDArray[np.float64]:
        """A per-joint parameter as a float array of shape (N,)."""
        return np.asarray(getattr(self, name), dtype=float)

    @property
    def joint_mass(self) -> float:
        """Moving mass of one joint: two diagonals and its top bar (kg)."""
        return 2.0 * self.m_diagonal + self.m_bar

    @property
    def com_fraction(self) -> float:
        """Joint centre of mass as a fraction of the median from its base-bar middle.

        The two diagonal midpoints average to half the median and the top bar sits at its end, so
        the centre of mass lies on the median at (m_d + m_bar) / (2 m_d + m_bar).
        """
        return (self.m_diagonal + self.m_bar) / self.joint_mass if self.joint_mass > 0 else 0.5


def prototype_2x(**overrides: Any) -> Design:
    """The 2-X prototype of the paper, section 3.3: L = 0.1 m, b = 0.05 m, k = 150/90 N/m,
    free lengths 0.047/0.037 m, ABS bar masses 0.009/0.006 kg.

    The paper's text does not give the force bounds; f_min = 0.5 N (cables taut) and
    f_max = 50 N are this project's assumptions, f_max chosen so that, as the paper reports, the
    four-cable wrench-feasible workspace covers (almost) the whole range |θ_i| < π/2.
    Pass ``k_l=(90.0, 90.0), k_r=(90.0, 90.0)`` for the identical-spring case of Fig. 14.
    """
    return Design(**overrides)


# --- geometry of the sides -------------------------------------------------------------------


def side_length_derivatives(half_alpha: ArrayLike, L: float, b: float) -> tuple[NDArray[np.float64], ...]:
    """Side lengths l_l, l_r = l ∓ b sin θ and their first and second θ-derivatives.

    Returns (l_l, l_r, dl_l, dl_r, ddl_l, ddl_r) (m, m/rad, m/rad²), each shaped like ``half_alpha``.
    For |θ| < π/2, dl_l < 0 < dl_r: the left cable pulls θ up, the right one pulls it down.
    """
    half_alpha = np.asarray(half_alpha, dtype=float)
    l, dl, ddl = median_length_derivatives(half_alpha, L, b)
    bs, bc = b * np.sin(half_alpha), b * np.cos(half_alpha)
    return l - bs, l + bs, dl - bc, dl + bc, ddl + bs, ddl - bs


# --- potential of springs and gravity ---------------------------------------------------------


def _phase_weights(n: int) -> NDArray[np.float64]:
    """a[j, k] = ∂φ_j/∂θ_k for the median directions of eq. (2)."""
    return np.tril(np.full((n, n), 2.0), -1) + np.eye(n)


def _gravity_weights(d: Design) -> NDArray[np.float64]:
    """w_j such that U_gravity = g Σ_j w_j h_j, h_j the height gained along median j (kg).

    Joint i's centre of mass is the sum of the full medians below it plus c times its own, so
    w_j = c m_j + Σ_{i>j} m_i.
    """
    n = d.n_joints
    m = d.joint_mass
    return m * (d.com_fraction + np.arange(n - 1, -1, -1, dtype=float))


def _check_half_alpha(half_alpha: ArrayLike, d: Design) -> NDArray[np.float64]:
    half_alpha = np.asarray(half_alpha, dtype=float)
    if half_alpha.ndim == 0 or half_alpha.shape[-1] != d.n_joints:
        raise ValueError(f"half_alpha must have shape (..., {d.n_joints}), got {half_alpha.shape}")
    return half_alpha


class _ChainTerms(NamedTuple):
    """What both derivatives of U need at ``half_alpha``: the phase weights a and median
    directions φ (eq. 2), the median length and its derivatives (eq. 1), the sides' (eq. 2)."""

    a: NDArray[np.float64]
    phi: NDArray[np.float64]
    median: tuple[NDArray[np.float64], ...]
    sides: tuple[NDArray[np.float64], ...]


def _chain_terms(d: Design, half_alpha: NDArray[np.float64]) -> _ChainTerms:
    return _ChainTerms(_phase_weights(d.n_joints), median_directions(half_alpha),
                       median_length_derivatives(half_alpha, d.L, d.b), side_length_derivatives(half_alpha, d.L, d.b))


def potential_gradient(d: Design, half_alpha: ArrayLike) -> NDArray[np.float64]:
    """∂(U_springs + U_gravity)/∂θ (N·m), eq. (16a)-(16b), shape (..., N).

    At equilibrium the cables balance it: −Σ f ∂l/∂θ equals this (right-hand side of eq. (21)).
    """
    a, phi, (l, dl, _), (ll, lr, dll, dlr, _, _) = _chain_terms(d, _check_half_alpha(half_alpha, d))
    springs = d.array("k_l") * (ll - d.array("l0_l")) * dll + d.array("k_r") * (lr - d.array("l0_r")) * dlr
    w = _gravity_weights(d)
    # h_j = l_j cos φ_j; ∂h_j/∂θ_k = δ_jk l'_j cos φ_j − l_j sin φ_j a_jk
    grav = w * dl * np.cos(phi) - np.einsum("...j,jk->...k", w * l * np.sin(phi), a)
    return springs + d.gravity * grav


def potential_hessian(d: Design, half_alpha: ArrayLike) -> NDArray[np.float64]:
    """∂²(U_springs + U_gravity)/∂θ² (N·m/rad), shape (..., N, N): K_θ of eq. (18) without cables."""
    n = d.n_joints
    a, phi, (l, dl, ddl), (ll, lr, dll, dlr, ddll, ddlr) = _chain_terms(d, _check_half_alpha(half_alpha, d))
    kl, kr = d.array("k_l"), d.array("k_r")
    springs = kl * (dll**2 + (ll - d.array("l0_l")) * ddll) + kr * (dlr**2 + (lr - d.array("l0_r")) * ddlr)
    w = _gravity_weights(d)
    s, c = np.sin(phi), np.cos(phi)
    eye = np.eye(n)
    cross = (w * dl * s)[..., :, None] * a  # [k, m] = w_k l'_k sin φ_k a_km
    grav = (
        (w * ddl * c)[..., :, None] * eye
        - cross
        - np.swapaxes(cross, -1, -2)
        - np.einsum("...j,jk,jm->...km", w * l * c, a, a)
    )
    return springs[..., :, None] * eye + d.gravity * grav


# --- cables ------------------------------------------------------------------------------------


def joint_stiffness(d: Design, half_alpha: ArrayLike, f_l: ArrayLike, f_r: ArrayLike) -> NDArray[np.float64]:
    """K_θ = ∂²U/∂θ² of eq. (18) (N·m/rad), shape (..., N, N).

    Args:
        f_l, f_r: left/right cable tension acting on each joint's sides (N), shape (..., N). For the
            two-cable strategy pass the same f_l (f_r) for every joint. The cables add
            f ∂²l/∂θ² to the diagonal only (eq. (20)/(22) are sums of f times side lengths).
    """
    half_alpha = _check_half_alpha(half_alpha, d)
    _, _, _, _, ddll, ddlr = side_length_derivatives(half_alpha, d.L, d.b)
    cables = np.asarray(f_l, dtype=float) * ddll + np.asarray(f_r, dtype=float) * ddlr
    return potential_hessian(d, half_alpha) + cables[..., :, None] * np.eye(d.n_joints)


def cartesian_stiffness(K_joint: ArrayLike, J: ArrayLike) -> NDArray[np.float64]:
    """K_c = J⁻ᵀ K_θ J⁻¹, eq. (19) (N/m), shape (..., 2, 2); NaN where J is singular."""
    K_joint = np.asarray(K_joint, dtype=float)
    J = np.asarray(J, dtype=float)
    if J.shape[-2:] != (2, 2):
        raise ValueError(f"J must be square 2x2 (a 2-X chain), got shape {J.shape}")
    det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
    scale = np.abs(J).max(axis=(-1, -2)) ** 2
    ok = np.abs(det) > 1e-9 * scale
    Jinv = np.linalg.inv(np.where(ok[..., None, None], J, np.eye(2)))
    Kc = np.swapaxes(Jinv, -1, -2) @ K_joint @ Jinv
    return np.where(ok[..., None, None], Kc, np.nan)


def forces_two_cables(d: Design, half_alpha: ArrayLike) -> NDArray[np.float64]:
    """Unique equilibrium forces (f_l, f_r) (N) of the two-cable strategy, eqs. (20)-(21).

    Solves Σ_i-rows [∂l_li/∂θ_i, ∂l_ri/∂θ_i] (f_l, f_r) = −∂(U_s + U_g)/∂θ. Shape (..., 2);
    NaN where the 2x2 system is singular (θ_1 = θ_2 for identical joints: both rows coincide).
    """
    if d.n_joints != 2:
        raise ValueError(f"the two-cable strategy of eq. (20) is defined for 2 joints, design has {d.n_joints}")
    half_alpha = _check_half_alpha(half_alpha, d)
    _, _, dll, dlr, _, _ = side_length_derivatives(half_alpha, d.L, d.b)
    rhs = -potential_gradient(d, half_alpha)
    a, bb = dll[..., 0], dlr[..., 0]
    c, e = dll[..., 1], dlr[..., 1]
    det = a * e - bb * c
    ok = np.abs(det) > 1e-12 * (np.abs(a * e) + np.abs(bb * c))
    det = np.where(ok, det, np.nan)
    f_l = (e * rhs[..., 0] - bb * rhs[..., 1]) / det
    f_r = (a * rhs[..., 1] - c * rhs[..., 0]) / det
    return np.stack([f_l, f_r], axis=-1)


def wrench_feasible_two_cables(d: Design, half_alpha: ArrayLike) -> NDArray[np.bool_]:
    """Wrench-feasible configurations of the two-cable strategy: f_min <= f_l, f_r <= f_max."""
    f = forces_two_cables(d, half_alpha)
    return np.all((f >= d.f_min) & (f <= d.f_max), axis=-1)


class ForceSegment(NamedTuple):
    """Feasible forces of each joint under the 2N-cable strategy: f_r in [s_lo, s_hi] and
    f_l = A + B f_r (N), all shaped (..., N); ``feasible`` is s_lo <= s_hi."""

    s_lo: NDArray[np.float64]
    s_hi: NDArray[np.float64]
    A: NDArray[np.float64]
    B: NDArray[np.float64]
    feasible: NDArray[np.bool_]


def redundancy_segment(d: Design, half_alpha: ArrayLike) -> ForceSegment:
    """The force redundancy of the 2N-cable strategy (eq. (22)) at each configuration.

    Joint i balances f_li ∂l_li/∂θ_i + f_ri ∂l_ri/∂θ_i = −∂(U_s + U_g)/∂θ_i (eq. 17), a line in the
    (f_li, f_ri) plane, cut by the box [f_min, f_max]². Parametrised by f_ri.
    """
    half_alpha = _check_half_alpha(half_alpha, d)
    _, _, dll, dlr, _, _ = side_length_derivatives(half_alpha, d.L, d.b)
    G = potential_gradient(d, half_alpha)
    with np.errstate(divide="ignore", invalid="ignore"):
        A = -G / dll
        B = -dlr / dll
        lo1 = (d.f_min - A) / B
        hi1 = (d.f_max - A) / B
    s_lo = np.maximum(d.f_min, np.minimum(lo1, hi1))
    s_hi = np.minimum(d.f_max, np.maximum(lo1, hi1))
    feasible = np.isfinite(s_lo) & np.isfinite(s_hi) & (s_lo <= s_hi)
    return ForceSegment(s_lo, s_hi, A, B, feasible)


class StiffnessExtremes(NamedTuple):
    """Minimum and maximum stiffness over the force redundancy (2N-cable strategy).

    K_joint_min/max: (..., N, N) N·m/rad, the diagonal minimised/maximised joint by joint
    (off-diagonal terms do not depend on the forces). f_min/f_max: (..., N, 2) forces (f_l, f_r)
    that realise them. K_c_min/max: (..., 2, 2) N/m for a 2-X chain (the diagonal K_x, K_y is
    monotone in every K_θi, so it is extreme at the same forces), NaN near singular J, else None.
    All NaN where the configuration is not wrench-feasible.
    """

    feasible: NDArray[np.bool_]
    K_joint_min: NDArray[np.float64]
    K_joint_max: NDArray[np.float64]
    forces_min: NDArray[np.float64]
    forces_max: NDArray[np.float64]
    K_c_min: NDArray[np.float64] | None
    K_c_max: NDArray[np.float64] | None


def stiffness_extremes(d: Design, half_alpha: ArrayLike) -> StiffnessExtremes:
    """Wrench feasibility and extreme stiffness of the 2N-cable strategy (Figs. 16-19).

    K_θi is affine in f_ri along the redundancy segment, so its extremes are at the segment ends;
    which end depends on the slope's sign, found per point.
    """
    half_alpha = _check_half_alpha(half_alpha, d)
    seg = redundancy_segment(d, half_alpha)
    _, _, _, _, ddll, ddlr = side_length_derivatives(half_alpha, d.L, d.b)
    slope = seg.B * ddll + ddlr  # dK_θi / df_ri along the segment
    s_min = np.where(slope >= 0, seg.s_lo, seg.s_hi)
    s_max = np.where(slope >= 0, seg.s_hi, seg.s_lo)
    f_at = lambda s: np.stack([seg.A + seg.B * s, s], axis=-1)  # noqa: E731
    feasible = np.asarray(seg.feasible.all(-1))
    nan = np.where(feasible[..., None, None], 0.0, np.nan)
    F_min, F_max = f_at(s_min) + nan, f_at(s_max) + nan
    K_min = joint_stiffness(d, half_alpha, F_min[..., 0], F_min[..., 1]) + nan
    K_max = joint_stiffness(d, half_alpha, F_max[..., 0], F_max[..., 1]) + nan
    Kc_min = Kc_max = None
    if d.n_joints == 2:
        J = jacobian(half_alpha, d.L, d.b)
        Kc_min, Kc_max = cartesian_stiffness(K_min, J), cartesian_stiffness(K_max, J)
    return StiffnessExtremes(feasible, K_min, K_max, F_min, F_max, Kc_min, Kc_max)


# --- 3-X prototype -------------------------------------------------------------------------------


class Statics3X(NamedTuple):
    """Static equilibrium Z(α) f = g(α) of the 3-X prototype with four cables.

    f(t) = f_p + n t for t in [t_lo, t_hi] keeps f_min <= f <= f_max; ``feasible`` is t_lo <= t_hi.
    f_p: (..., 4) particular solution with no force on the long cable (N); n: (..., 4) null vector
    of Z with 1 on the long cable (positive entries, ERRATA); t is the long-cable force (N), the
    long cable being :func:`twin.model.estimation.long_cable` (c4 on the prototype).
    """

    f_p: NDArray[np.float64]
    n: NDArray[np.float64]
    t_lo: NDArray[np.float64]
    t_hi: NDArray[np.float64]
    feasible: NDArray[np.bool_]


def _model_functions() -> tuple[Any, Any]:
    # Imported here so the 2-X analysis never depends on the 3-X model being importable.
    from twin.model.cables import Z
    from twin.model.dynamics import g

    return Z, g


def _cable_split(m: Any) -> tuple[NDArray[np.int64], int]:
    """The short cables (one per joint, Z1 upper triangular) and the long one (Z2), eq. 23."""
    from twin.model.estimation import long_cable, short_cables

    return short_cables(m), long_cable(m)


def statics_3x(m: Any, alpha: ArrayLike, f_min: float, f_max: float) -> Statics3X:
    """Force redundancy of the 3-X prototype at configurations ``alpha`` (rad, shape (..., 3)).

    Z = [Z1 | Z2] (short cables | long cable) with Z1 (3x3) upper triangular and invertible:
    f_p = [Z1⁻¹ g; 0] and n = [−Z1⁻¹ Z2; 1] (3-X paper, section 6.2). Every component of f(t) gives an interval for t.
    """
    if not (0.0 <= f_min < f_max):
        raise ValueError(f"need 0 <= f_min < f_max, got f_min = {f_min}, f_max = {f_max}")
    Zf, gf = _model_functions()
    alpha = np.asarray(alpha, dtype=float)
    Z = np.asarray(Zf(m, alpha), dtype=float)
    G = np.asarray(gf(m, alpha), dtype=float)
    if Z.shape[-1] != Z.shape[-2] + 1:
        raise ValueError(f"Z must have one more cable than joints, got shape {Z.shape}")
    short, long = _cable_split(m)
    Z1, Z2 = Z[..., short], Z[..., [long]]
    sol = np.linalg.solve(Z1, np.concatenate([G[..., None], -Z2], axis=-1))
    f_p = np.zeros(Z.shape[:-2] + (Z.shape[-1],))
    n = np.zeros_like(f_p)
    f_p[..., short], n[..., short], n[..., long] = sol[..., 0], sol[..., 1], 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = (f_min - f_p) / n
        hi = (f_max - f_p) / n
    t_lo = np.max(np.where(n > 0, lo, np.where(n < 0, hi, np.where(f_p >= f_min, -np.inf, np.inf))), axis=-1)
    t_hi = np.min(np.where(n > 0, hi, np.where(n < 0, lo, np.where(f_p <= f_max, np.inf, -np.inf))), axis=-1)
    return Statics3X(f_p, n, t_lo, t_hi, t_lo <= t_hi)


def stiffness_3x(m: Any, alpha: ArrayLike, f: ArrayLike, h: float = 1e-6) -> NDArray[np.float64]:
    """Joint stiffness K(α, f) = ∂(g − Z f)/∂α at fixed cable forces f (N·m/rad), shape (..., 3, 3).

    Central differences of the model functions with step h (rad); symmetrised, since both g and
    Z f are gradients of potentials (springs + gravity, and f·l_c).
    """
    Zf, gf = _model_functions()
    alpha = np.asarray(alpha, dtype=float)
    f = np.asarray(f, dtype=float)
    n = alpha.shape[-1]
    cols = []
    for k in range(n):
        e = np.zeros(n)
        e[k] = h
        tau_p = np.asarray(gf(m, alpha + e)) - np.einsum("...ij,...j->...i", np.asarray(Zf(m, alpha + e)), f)
        tau_m = np.asarray(gf(m, alpha - e)) - np.einsum("...ij,...j->...i", np.asarray(Zf(m, alpha - e)), f)
        cols.append((tau_p - tau_m) / (2.0 * h))
    K = np.stack(cols, axis=-1)
    return 0.5 * (K + np.swapaxes(K, -1, -2))
