"""Statics and stiffness of the 2-X chain (eqs. 15-22) and of the 3-X prototype."""

from __future__ import annotations

import numpy as np
import pytest

from twin.analysis.kinematics import jacobian, joint_points, side_lengths_at_half_alpha
from twin.analysis.statics import (
    Design,
    cartesian_stiffness,
    forces_two_cables,
    joint_stiffness,
    potential_gradient,
    potential_hessian,
    prototype_2x,
    redundancy_segment,
    side_length_derivatives,
    stiffness_extremes,
    wrench_feasible_two_cables,
)


def _potential(d: Design, half_alpha: np.ndarray) -> np.ndarray:
    """U_springs + U_gravity from the geometry directly (eq. 16), as an independent reference."""
    ll, lr = side_lengths_at_half_alpha(half_alpha, d.L, d.b)
    springs = 0.5 * (d.array("k_l") * (ll - d.array("l0_l")) ** 2 + d.array("k_r") * (lr - d.array("l0_r")) ** 2)
    # Masses from the bar ends: diagonals at their midpoints, top bars at their middles.
    P = joint_points(half_alpha, d.L, d.b)
    y_diag = 0.5 * (P[..., :-1, 1] + P[..., 1:, 1])  # the two diagonals' midpoints average here
    y_top = P[..., 1:, 1]
    grav = d.gravity * (2 * d.m_diagonal * y_diag + d.m_bar * y_top)
    return springs.sum(-1) + grav.sum(-1)


def _grad(f, half_alpha, h=1e-6):
    return np.stack([(f(half_alpha + h * e) - f(half_alpha - h * e)) / (2 * h) for e in np.eye(half_alpha.shape[-1])], -1)


@pytest.mark.parametrize("n", [2, 3])
def test_gradient_and_hessian_match_the_potential(n):
    d = Design(k_l=(150.0, 90.0, 60.0)[:n], k_r=(140.0, 80.0, 70.0)[:n], l0_l=(0.047, 0.037, 0.03)[:n],
               l0_r=(0.045, 0.035, 0.032)[:n])
    half_alpha = np.random.default_rng(0).uniform(-1.5, 1.5, (200, n))
    np.testing.assert_allclose(potential_gradient(d, half_alpha), _grad(lambda t: _potential(d, t), half_alpha), atol=1e-8)
    np.testing.assert_allclose(potential_hessian(d, half_alpha), _grad(lambda t: potential_gradient(d, t), half_alpha),
                               atol=1e-7)


def test_side_length_derivatives():
    t = np.linspace(-1.5, 1.5, 50)
    _, _, dll, dlr, _, ddlr = side_length_derivatives(t, 0.1, 0.05)
    np.testing.assert_allclose(dll, _grad(lambda x: side_lengths_at_half_alpha(x[..., 0], 0.1, 0.05)[0], t[:, None])[:, 0], atol=1e-8)
    np.testing.assert_allclose(ddlr, _grad(lambda x: side_length_derivatives(x[..., 0], 0.1, 0.05)[3], t[:, None])[:, 0],
                               atol=1e-7)
    assert np.all(dll < 0) and np.all(dlr > 0)  # antagonistic pair inside the flat singularities


def _total_gradient(d, half_alpha, f_l, f_r):
    """∂U_total/∂θ with the cable work of eq. (22) (or (20) when f is shared)."""
    def U(t):
        ll, lr = side_lengths_at_half_alpha(t, d.L, d.b)
        return _potential(d, t) + (f_l * ll + f_r * lr).sum(-1)
    return _grad(U, half_alpha)


def test_two_cable_forces_are_in_equilibrium():
    d = prototype_2x()
    half_alpha = np.random.default_rng(1).uniform(-1.4, 1.4, (300, 2))
    f = forces_two_cables(d, half_alpha)
    fl = np.repeat(f[:, :1], 2, axis=1)
    fr = np.repeat(f[:, 1:], 2, axis=1)
    np.testing.assert_allclose(_total_gradient(d, half_alpha, fl, fr), 0.0, atol=1e-7)


def test_two_cables_cannot_leave_the_diagonal_without_gravity():
    # Section 3.4: identical springs and no gravity leave only θ1 = θ2 reachable.
    d = prototype_2x(k_l=(90.0, 90.0), k_r=(90.0, 90.0), l0_l=(0.04, 0.04), l0_r=(0.04, 0.04), gravity=0.0,
                     f_min=0.0, f_max=1e3)
    t = np.linspace(-1.4, 1.4, 41)
    T = np.stack(np.meshgrid(t, t, indexing="ij"), -1)
    off = ~np.eye(41, dtype=bool)
    assert not wrench_feasible_two_cables(d, T)[off].any()


def test_four_cable_redundancy_segment_and_stiffness_extremes():
    d = prototype_2x()
    half_alpha = np.random.default_rng(2).uniform(-1.3, 1.3, (400, 2))
    se = stiffness_extremes(d, half_alpha)
    assert se.feasible.mean() > 0.9  # far larger than the two-cable WFW
    assert wrench_feasible_two_cables(d, half_alpha).mean() < se.feasible.mean()
    ok = se.feasible
    for F, K in ((se.forces_min, se.K_joint_min), (se.forces_max, se.K_joint_max)):
        assert np.all((F[ok] >= d.f_min - 1e-9) & (F[ok] <= d.f_max + 1e-9))
        np.testing.assert_allclose(_total_gradient(d, half_alpha[ok], F[ok, :, 0], F[ok, :, 1]), 0.0, atol=1e-7)
        np.testing.assert_allclose(K[ok], joint_stiffness(d, half_alpha[ok], F[ok, :, 0], F[ok, :, 1]))
    # Off-diagonal terms depend only on gravity; the diagonal spans a range (min <= max).
    np.testing.assert_allclose(se.K_joint_min[ok][:, 0, 1], se.K_joint_max[ok][:, 0, 1])
    assert np.all(se.K_joint_min[ok][:, [0, 1], [0, 1]] <= se.K_joint_max[ok][:, [0, 1], [0, 1]] + 1e-12)
    # No point inside the segment beats the ends (K is affine along it).
    seg = redundancy_segment(d, half_alpha[ok])
    for s in np.linspace(0, 1, 5):
        fr = seg.s_lo + s * (seg.s_hi - seg.s_lo)
        K = joint_stiffness(d, half_alpha[ok], seg.A + seg.B * fr, fr)
        assert np.all(K[:, [0, 1], [0, 1]] >= se.K_joint_min[ok][:, [0, 1], [0, 1]] - 1e-9)
        assert np.all(K[:, [0, 1], [0, 1]] <= se.K_joint_max[ok][:, [0, 1], [0, 1]] + 1e-9)
    # Eq. (19) and "K_x, K_y are extreme at the same forces".
    J = jacobian(half_alpha[ok], d.L, d.b)
    np.testing.assert_allclose(se.K_c_min[ok], cartesian_stiffness(se.K_joint_min[ok], J))
    good = np.isfinite(se.K_c_min[ok]).all(axis=(-1, -2))
    assert np.all(np.diagonal(se.K_c_min[ok][good], axis1=1, axis2=2)
                  <= np.diagonal(se.K_c_max[ok][good], axis1=1, axis2=2) + 1e-9)


def test_infeasible_force_bounds_give_empty_wfw():
    d = prototype_2x(f_min=0.0, f_max=1e-3)
    assert not stiffness_extremes(d, np.array([[0.6, -0.4]])).feasible.any()


def test_bad_design_is_rejected():
    with pytest.raises(ValueError, match="k_r"):
        Design(k_l=(1.0, 2.0), k_r=(1.0,))
    with pytest.raises(ValueError, match="f_min"):
        prototype_2x(f_min=5.0, f_max=1.0)
    with pytest.raises(ValueError, match="half_alpha"):
        potential_gradient(prototype_2x(), np.zeros(3))


# --- 3-X prototype ------------------------------------------------------------------------------

params_mod = pytest.importorskip("twin.model.params")


@pytest.fixture(scope="module")
def model3():
    from twin.model.numeric import build

    p = params_mod.load_params()
    return build(p), p.limits


def test_3x_equilibrium_and_null_vector(model3):
    from twin.analysis.statics import statics_3x
    from twin.model.cables import Z
    from twin.model.dynamics import g

    m, lim = model3
    alpha = np.radians([[0, 0, 0], [40, 30, 20], [50, 50, 50], [-30, -40, -50]])
    st = statics_3x(m, alpha, lim.f_min, lim.f_max)
    assert st.feasible.all()
    # ERRATA: at (40, 30, 20)°, −Z1⁻¹Z2 = (0.826, 0.859, 0.832).
    np.testing.assert_allclose(st.n[1, :3], [0.826, 0.859, 0.832], atol=2e-3)
    assert np.all(st.n > 0)
    for t in (st.t_lo, st.t_hi, 0.5 * (st.t_lo + st.t_hi)):
        f = st.f_p + st.n * t[:, None]
        np.testing.assert_allclose(np.einsum("kij,kj->ki", Z(m, alpha), f), g(m, alpha), atol=1e-9)
        assert np.all((f >= lim.f_min - 1e-9) & (f <= lim.f_max + 1e-9))


def test_3x_stiffness_rises_with_tension(model3):
    from twin.analysis.statics import statics_3x, stiffness_3x
    from twin.analysis.workspace import maps_3x

    m, lim = model3
    alpha = np.radians([[0, 0, 0], [20, -10, 15]])
    st = statics_3x(m, alpha, lim.f_min, lim.f_max)
    K_lo = stiffness_3x(m, alpha, st.f_p + st.n * st.t_lo[:, None])
    K_hi = stiffness_3x(m, alpha, st.f_p + st.n * st.t_hi[:, None])
    np.testing.assert_allclose(K_lo, np.swapaxes(K_lo, -1, -2))
    assert np.all(np.diagonal(K_hi, axis1=1, axis2=2) > np.diagonal(K_lo, axis1=1, axis2=2))
    mp = maps_3x(m, lim.f_min, lim.f_max, n=7)
    assert 0.0 < mp.feasible.mean() < 1.0  # bounded forces cut the ±90° cube
    assert mp.feasible[3, 3, 3]  # straight neck
