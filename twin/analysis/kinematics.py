"""Kinematics of planar chains of X-joints (Furet & Wenger 2019, "the 2-X paper", section 2).

Frames and units
----------------
Base frame: origin at the middle of the base bar of joint 1, x along that bar, y up. The reference
point p = (x, y) is the middle of the top bar of the last joint. Lengths in metres (or in any unit
shared by ``L``, ``b``, ``x`` and ``y``), angles in radians.

Each X-joint is an antiparallelogram with diagonal bars of length ``L`` and base/top bars of
length ``b`` (0 < b < L). Its configuration is θ_i, the angle of the median segment (base-bar
middle to top-bar middle) from the base-bar normal (the 2-X paper's symbol; ``half_alpha`` in the
code, because θ is the motor angle everywhere else in xneck); the top bar turns by α_i = 2 θ_i, and
θ_i in (−π, π] covers a full turn of the mechanism. θ_i > 0 tilts the joint to the left (−x) and
shortens its left side. |θ_i| = π/2 is the flat singularity of one X-joint; |θ_i| < π/2 is
"configuration up", which cable actuation requires.

Everything here is pure and vectorised over leading axes. The inverse kinematics of the 2-X chain
goes through the quartic characteristic polynomial of eqs. (7)-(9), derived with L = 1: ``x``,
``y`` and ``b`` are divided by ``L`` before it is used.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "FLAT",
    "aspect",
    "bar_nodes",
    "characteristic_quartic",
    "check_design",
    "cuspidal_threshold",
    "det_jacobian_2x",
    "fk",
    "foldback_half_alpha1",
    "ik_2x",
    "ik_2x_batch",
    "is_cuspidal",
    "jacobian",
    "joint_points",
    "median_directions",
    "median_length",
    "median_length_derivatives",
    "side_lengths_at_half_alpha",
    "singular_half_alpha1",
    "wrap_angle",
]

FLAT = np.pi / 2
"""|θ_i| of the flat singularity of one X-joint (rad)."""

_IK_TOL = 1e-9  # FK residual (in units of L) below which an IK candidate is a solution


def check_design(L: float, b: float) -> tuple[float, float]:
    """Validate the X-joint dimensions; raise ValueError naming the bad argument.

    The assembly needs b <= L, and b = L (each joint degenerates to a bar) or b = 0 (a plain 2R
    linkage) are degenerate designs the formulas below do not cover.
    """
    L = float(L)
    b = float(b)
    if not np.isfinite(L) or L <= 0.0:
        raise ValueError(f"L (diagonal bar length) must be a positive finite number, got {L}")
    if not np.isfinite(b) or b <= 0.0:
        raise ValueError(f"b (base/top bar length) must be a positive finite number, got {b}")
    if b >= L:
        raise ValueError(
            f"b (base/top bar length) must be smaller than L = {L} for an X-joint "
            f"(b = L is degenerate, b > L does not assemble), got b = {b}"
        )
    return L, b


def wrap_angle(a: ArrayLike) -> NDArray[np.float64]:
    """Wrap angles (rad) to (−π, π]."""
    a = np.asarray(a, dtype=float)
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def median_length(half_alpha: ArrayLike, L: float, b: float) -> NDArray[np.float64]:
    """Median-segment length l(θ) = sqrt(L² − b² cos²θ), eq. (1). Same unit as L."""
    c = np.cos(np.asarray(half_alpha, dtype=float))
    return np.sqrt(L * L - b * b * c * c)


def median_length_derivatives(
    half_alpha: ArrayLike, L: float, b: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """l(θ), dl/dθ and d²l/dθ² of eq. (1) (length, length/rad, length/rad²)."""
    half_alpha = np.asarray(half_alpha, dtype=float)
    l = median_length(half_alpha, L, b)
    s2 = np.sin(2.0 * half_alpha)
    dl = 0.5 * b * b * s2 / l
    ddl = (b * b * np.cos(2.0 * half_alpha) - dl * dl) / l
    return l, dl, ddl


def side_lengths_at_half_alpha(half_alpha: ArrayLike, L: float, b: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Left and right side lengths (l_l, l_r) = (l − b sin θ, l + b sin θ) of one X-joint.

    Both sides are parallel to the median; this is ERRATA eq. (2) of the 3-X paper written with
    θ = α/2 (l_r(θ) = l_l(−θ)). Positive for every θ since b < L.
    """
    half_alpha = np.asarray(half_alpha, dtype=float)
    l = median_length(half_alpha, L, b)
    bs = b * np.sin(half_alpha)
    return l - bs, l + bs


def median_directions(half_alpha: NDArray[np.float64]) -> NDArray[np.float64]:
    """Median-segment direction φ_i = −θ_i + Σ_{j<=i} 2θ_j of eq. (2), from the y axis (rad)."""
    return 2.0 * np.cumsum(half_alpha, axis=-1) - half_alpha


def _as_chain(half_alpha: ArrayLike) -> NDArray[np.float64]:
    half_alpha = np.asarray(half_alpha, dtype=float)
    if half_alpha.ndim == 0 or half_alpha.shape[-1] < 1:
        raise ValueError(f"half_alpha must have shape (..., N) with N >= 1 joints, got shape {half_alpha.shape}")
    return half_alpha


def joint_points(half_alpha: ArrayLike, L: float, b: float) -> NDArray[np.float64]:
    """Middles of the base bar and of every top bar, shape (..., N+1, 2), eq. (2) partial sums."""
    half_alpha = _as_chain(half_alpha)
    phi = median_directions(half_alpha)
    l = median_length(half_alpha, L, b)
    steps = np.stack([-l * np.sin(phi), l * np.cos(phi)], axis=-1)
    zero = np.zeros(steps.shape[:-2] + (1, 2))
    return np.concatenate([zero, np.cumsum(steps, axis=-2)], axis=-2)


def bar_nodes(half_alpha: ArrayLike, L: float, b: float) -> NDArray[np.float64]:
    """End nodes (left, right) of the base bar and of every top bar, shape (..., N+1, 2, 2).

    Bar i turns by Σ_{j<=i} 2θ_j; its nodes are its middle ± b/2 along it. The diagonal bars of
    joint i join left node of bar i−1 to right node of bar i and vice versa (for drawing).
    """
    half_alpha = _as_chain(half_alpha)
    mid = joint_points(half_alpha, L, b)
    turn = 2.0 * np.cumsum(half_alpha, axis=-1)
    turn = np.concatenate([np.zeros(turn.shape[:-1] + (1,)), turn], axis=-1)
    half = 0.5 * b * np.stack([np.cos(turn), np.sin(turn)], axis=-1)
    return np.stack([mid - half, mid + half], axis=-2)


def fk(half_alpha: ArrayLike, L: float, b: float) -> NDArray[np.float64]:
    """Forward kinematics of N X-joints in series, eq. (2) (eq. (3) for N = 2).

    Args:
        half_alpha: joint angles θ_i (rad), shape (..., N), joint 1 at the base.
        L, b: diagonal and base/top bar lengths.
    Returns:
        (x, y) of the middle of the last top bar in the base frame, shape (..., 2), unit of L.
    """
    half_alpha = _as_chain(half_alpha)
    phi = median_directions(half_alpha)
    l = median_length(half_alpha, L, b)
    return np.stack([-(l * np.sin(phi)).sum(-1), (l * np.cos(phi)).sum(-1)], axis=-1)


def jacobian(half_alpha: ArrayLike, L: float, b: float) -> NDArray[np.float64]:
    """Jacobian J = ∂(x, y)/∂θ of eq. (2), shape (..., 2, N) (length/rad); eqs. (10)-(11) for N = 2.

    Differentiated analytically: φ_i depends on θ_k with weight 1 (k = i) or 2 (k < i).
    """
    half_alpha = _as_chain(half_alpha)
    n = half_alpha.shape[-1]
    phi = median_directions(half_alpha)
    l, dl, _ = median_length_derivatives(half_alpha, L, b)
    # weights[i, k] = ∂φ_i/∂θ_k
    weights = np.tril(np.full((n, n), 2.0), -1) + np.eye(n)
    s, c = np.sin(phi), np.cos(phi)
    jx = -dl * s - np.einsum("...i,ik->...k", l * c, weights)
    jy = dl * c - np.einsum("...i,ik->...k", l * s, weights)
    return np.stack([jx, jy], axis=-2)


def det_jacobian_2x(half_alpha1: ArrayLike, half_alpha2: ArrayLike, L: float, b: float) -> NDArray[np.float64]:
    """det J of the 2-X chain (length²/rad²) from the closed form of eq. (12).

    Eq. (12) is det J with the never-vanishing factor l_1(θ_1) l_2(θ_2) cleared; it is divided back
    here so the result equals ``np.linalg.det(jacobian(...))``.
    """
    t1 = np.asarray(half_alpha1, dtype=float)
    t2 = np.asarray(half_alpha2, dtype=float)
    L2, b2 = L * L, b * b
    c1, s1, c2, s2 = np.cos(t1), np.sin(t1), np.cos(t2), np.sin(t2)
    l1 = median_length(t1, L, b)
    l2 = median_length(t2, L, b)
    eq12 = (
        (L2 - b2) * c1 * s2 * (L2 - 2.0 * b2 * c2 * c2)
        + s1 * c2 * (L2 * (L2 + b2) - 2.0 * L2 * b2 * c2 * c2)
        - 2.0 * s2 * c2 * l1 * l2 * b2
    )
    return eq12 / (l1 * l2)


def aspect(half_alpha1: ArrayLike, half_alpha2: ArrayLike, L: float, b: float) -> NDArray[np.int8]:
    """Aspect label (+1 or −1) of 2-X configurations: the sign of det J (section 2.4).

    The singularity curves split the (toroidal) joint space into two aspects, one per sign.
    0 on a singularity.
    """
    return np.sign(det_jacobian_2x(half_alpha1, half_alpha2, L, b)).astype(np.int8)


def singular_half_alpha1(half_alpha2: ArrayLike, L: float, b: float) -> NDArray[np.float64]:
    """The "outstretched" singularity curve of eq. (13): θ_1 as a function of θ_2 (rad).

    Eq. (13) gives tan θ_1; of its two branches θ_1 and θ_1 + π, det J vanishes on the one with
    cos θ_1 of the sign of the denominator of eq. (13) (its second factor is positive), which is
    what ``arctan2(numerator, denominator)`` returns. At cos θ_2 = 0 this gives θ_1 = ±π/2
    (both joints flat).
    """
    t2 = np.asarray(half_alpha2, dtype=float)
    L2, b2 = L * L, b * b
    c2, s2 = np.cos(t2), np.sin(t2)
    q = (2.0 * b2 * c2 * c2 - L2) ** 2
    num = -s2 * (q - L2 * b2)
    den = c2 * (q + 3.0 * L2 * b2 - 4.0 * c2 * c2 * b2 * b2)
    return np.arctan2(num, den)


def foldback_half_alpha1(half_alpha2: ArrayLike) -> NDArray[np.float64]:
    """The folded-back singularity θ_1 = −θ_2 ± π (section 2.4), wrapped to (−π, π] (rad).

    The two signs are one curve on the joint torus; drawn in the square (−π, π]² it shows as two
    lines. On it the two joints coincide and p = (0, 0).
    """
    return wrap_angle(-np.asarray(half_alpha2, dtype=float) + np.pi)


def cuspidal_threshold(L: float) -> float:
    """Base/top bar length b = L/√6 above which a 2-X chain with diagonals L is cuspidal (2.6)."""
    return float(L) / np.sqrt(6.0)


def is_cuspidal(L: float, b: float) -> bool:
    """True iff b < L < b√6: two identical X-joints in series are cuspidal with four IK solutions
    (section 2.6; ERRATA: the prototype ratio b/L = 1/2 is cuspidal)."""
    L, b = check_design(L, b)
    return bool(b < L < b * np.sqrt(6.0))


def characteristic_quartic(x: ArrayLike, y: ArrayLike, L: float, b: float) -> NDArray[np.float64]:
    """Coefficients (a_4, a_3, a_2, a_1, a_0) of eq. (7)-(8), shape (..., 5).

    The polynomial is in t = tan(φ_1/2), φ_1 the angle of the diagonal bar from the base-left
    node of joint 1. Eq. (8) is written for L = 1, so x, y and b are scaled by 1/L here.
    """
    L, b = check_design(L, b)
    x = np.asarray(x, dtype=float) / L
    y = np.asarray(y, dtype=float) / L
    b = b / L
    x2, y2, b2 = x * x, y * y, b * b
    r2 = x2 + y2
    r4 = r2 * r2  # x⁴ + 2x²y² + y⁴
    a4 = (b + 1) ** 2 * (b2 * y2 + r4 + 4 * x * r2 + 5 * x2 + y2 + 2 * x)
    a3 = 4 * y * (b + 1) * (2 * b2 * x + b2 - 2 * r2 - 4 * x - 1)
    a2 = 2 * (b2 * b2 * y2 + b2 * r4 + b2 * x2 - 10 * b2 * y2 + r4 - 3 * x2 + 9 * y2)
    a1 = 4 * y * (b - 1) * (2 * b2 * x - b2 + 2 * r2 - 4 * x + 1)
    a0 = (b - 1) ** 2 * (b2 * y2 + r4 - 4 * x * r2 + 5 * x2 + y2 - 2 * x)
    return np.stack(np.broadcast_arrays(a4, a3, a2, a1, a0), axis=-1)


def _quartic_phi1(coeffs: NDArray[np.float64]) -> NDArray[np.float64]:
    """Real roots of eq. (7) as angles φ_1 (rad), shape (..., 4), NaN where a root is complex.

    Solved as eigenvalues of companion matrices so that a whole grid goes through one LAPACK call.
    Where |a_0| > |a_4| the reversed polynomial in s = 1/t is solved instead, which keeps the root
    t = ∞ (φ_1 = π) of a vanishing a_4 finite.
    """
    rev = np.abs(coeffs[..., 4]) > np.abs(coeffs[..., 0])
    c = np.where(rev[..., None], coeffs[..., ::-1], coeffs)
    lead = c[..., :1]
    lead = np.where(lead == 0.0, 1.0, lead)  # all-zero polynomial: returns garbage, dropped by FK
    monic = c[..., 1:] / lead
    comp = np.zeros(coeffs.shape[:-1] + (4, 4))
    comp[..., 0, :] = -monic
    comp[..., 1, 0] = comp[..., 2, 1] = comp[..., 3, 2] = 1.0
    roots = np.linalg.eigvals(comp)
    real = np.abs(roots.imag) <= 1e-6 * (1.0 + np.abs(roots.real))
    r = roots.real
    half = np.where(rev[..., None], np.arctan2(1.0, r), np.arctan(r))
    return np.where(real, 2.0 * half, np.nan)


def ik_2x_batch(
    x: ArrayLike, y: ArrayLike, L: float, b: float, *, newton_steps: int = 2
) -> NDArray[np.float64]:
    """All real inverse-kinematic solutions of the 2-X chain, eqs. (7)-(9), on arrays of points.

    Args:
        x, y: reference point(s) in the base frame, broadcastable, unit of L.
        L, b: bar lengths, 0 < b < L.
        newton_steps: Gauss-Newton polish of each candidate on eq. (3) before the FK check.
    Returns:
        (θ_1, θ_2) in (−π, π], shape (..., 4, 2); solutions first (sorted by θ_1), NaN rows after.
        Every returned solution satisfies |FK(θ) − p| < 1e-9 L; quartic roots that do not
        (spurious or lost to round-off) are dropped.
    """
    L, b = check_design(L, b)
    x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
    bs = b / L
    p = np.stack([x, y], axis=-1)[..., None, :] / L  # (..., 1, 2), unit L
    phi1 = _quartic_phi1(characteristic_quartic(x, y, L, b))  # (..., 4)

    # Eq. (9): α_1 (mod 2π) from φ_1; the parallelogram root α_1 = π is not a solution.
    alpha1 = 2.0 * np.arctan2(bs - np.cos(phi1), np.sin(phi1))
    # Top-right node of joint 1 is L(cos φ_1, sin φ_1) from the base-left node (−b/2, 0); the
    # middle of its top bar is b/2 back along the bar. Its direction fixes θ_1 on the full turn,
    # which α_1 = 2θ_1 alone cannot.
    m1x = -0.5 * bs + np.cos(phi1) - 0.5 * bs * np.cos(alpha1)
    m1y = np.sin(phi1) - 0.5 * bs * np.sin(alpha1)
    half_alpha1 = np.arctan2(-m1x, m1y)
    # Joint 2 in the frame of the top bar of joint 1: its median points at p, which fixes θ_2
    # (the other candidate of eq. (4) points away and never closes the loop).
    dx, dy = p[..., 0] - m1x, p[..., 1] - m1y
    ca, sa = np.cos(2.0 * half_alpha1), np.sin(2.0 * half_alpha1)
    half_alpha2 = np.arctan2(-(ca * dx + sa * dy), -sa * dx + ca * dy)
    half_alpha = np.stack([half_alpha1, half_alpha2], axis=-1)  # (..., 4, 2)

    for _ in range(newton_steps):
        r = p - fk(half_alpha, 1.0, bs)
        J = jacobian(half_alpha, 1.0, bs)
        # Damped normal equations: a singular J (boundary points) must not blow the step up.
        JtJ = np.swapaxes(J, -1, -2) @ J + 1e-12 * np.eye(2)
        step = np.linalg.solve(JtJ, (np.swapaxes(J, -1, -2) @ r[..., None]))[..., 0]
        half_alpha = np.where(np.isfinite(step), half_alpha + step, half_alpha)
    half_alpha = wrap_angle(half_alpha)

    ok = np.linalg.norm(fk(half_alpha, 1.0, bs) - p, axis=-1) < _IK_TOL
    ok &= np.isfinite(half_alpha).all(-1)
    half_alpha = np.where(ok[..., None], half_alpha, np.nan)

    # A double root of the quartic gives the same configuration twice: keep one.
    for i in range(1, 4):
        for j in range(i):
            d = np.abs(wrap_angle(half_alpha[..., i, :] - half_alpha[..., j, :])).max(-1)
            dup = d < 1e-7
            half_alpha[..., i, :] = np.where(dup[..., None], np.nan, half_alpha[..., i, :])

    key = np.where(np.isnan(half_alpha[..., 0]), np.inf, half_alpha[..., 0])
    order = np.argsort(key, axis=-1)
    return np.take_along_axis(half_alpha, order[..., None], axis=-2)


def ik_2x(x: float, y: float, L: float, b: float) -> NDArray[np.float64]:
    """Every real IK solution of the 2-X chain at one point (x, y): array (n, 2) of (θ_1, θ_2) in
    (−π, π] rad, n in {0, 2, 4} generically (1 or 3 on boundaries). See :func:`ik_2x_batch`."""
    if not (np.isfinite(x) and np.isfinite(y)):
        raise ValueError(f"x and y must be finite numbers, got x = {x}, y = {y}")
    sol = ik_2x_batch(float(x), float(y), L, b)
    return sol[~np.isnan(sol[:, 0])]
