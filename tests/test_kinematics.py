"""Kinematics of the 2-X chain against the 2-X paper and ERRATA.md (published values only)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from twin.analysis.kinematics import (
    aspect,
    characteristic_quartic,
    det_jacobian_2x,
    fk,
    foldback_half_alpha1,
    ik_2x,
    ik_2x_batch,
    is_cuspidal,
    jacobian,
    side_lengths_at_half_alpha,
    singular_half_alpha1,
    wrap_angle,
)
from twin.analysis.workspace import cartesian_counts, cuspidality_threshold_numeric, max_solutions_on_axis

# ERRATA.md, "2-X paper": section 2.3 example, (θ1, θ2) in degrees, "about" = 2 decimals.
PAPER_IK = np.array([(-33.18, 91.46), (16.24, -48.34), (30.51, -87.50), (-16.46, 45.20)])


def test_fk_two_joints_is_eq3():
    rng = np.random.default_rng(0)
    L, b = 1.3, 0.7
    t = rng.uniform(-np.pi, np.pi, (100, 2))
    l1 = np.sqrt(L**2 - b**2 * np.cos(t[:, 0]) ** 2)
    l2 = np.sqrt(L**2 - b**2 * np.cos(t[:, 1]) ** 2)
    x = -l1 * np.sin(t[:, 0]) - l2 * np.sin(2 * t[:, 0] + t[:, 1])
    y = l1 * np.cos(t[:, 0]) + l2 * np.cos(2 * t[:, 0] + t[:, 1])
    np.testing.assert_allclose(fk(t, L, b), np.stack([x, y], -1), atol=1e-12)


def test_fk_n_joints_straight_and_bar_geometry():
    L, b = 0.1, 0.05
    np.testing.assert_allclose(fk(np.zeros(5), L, b), [0.0, 5 * np.sqrt(L**2 - b**2)])
    # Each side is l ∓ b sin θ; at θ = 0 both equal the median, and l_r(θ) = l_l(−θ).
    t = np.linspace(-1.5, 1.5, 7)
    ll, lr = side_lengths_at_half_alpha(t, L, b)
    np.testing.assert_allclose(ll, side_lengths_at_half_alpha(-t, L, b)[1])
    assert np.all(ll[t > 0] < lr[t > 0])  # θ > 0 shortens the left side


def test_paper_example_four_solutions():
    sol = np.degrees(ik_2x(0.03, 1.6, 1.0, 2.0 / 3.0))
    assert sol.shape == (4, 2)
    for ref in PAPER_IK:
        assert np.min(np.abs(sol - ref).max(axis=1)) < 0.02


def test_ik_scales_with_L():
    a = ik_2x(0.03, 1.6, 1.0, 2.0 / 3.0)
    b = ik_2x(0.003, 0.16, 0.1, 0.2 / 3.0)
    np.testing.assert_allclose(a, b, atol=1e-9)


def test_fk_of_ik_on_random_reachable_points():
    rng = np.random.default_rng(1)
    for L, b in ((1.0, 2 / 3), (0.1, 0.05), (2.0, 0.5), (1.0, 0.95)):
        half_alpha = rng.uniform(-np.pi, np.pi, (3000, 2))
        p = fk(half_alpha, L, b)
        sol = ik_2x_batch(p[:, 0], p[:, 1], L, b)
        n = (~np.isnan(sol[..., 0])).sum(-1)
        assert np.isin(n, (2, 4)).all()  # generic points: two or four solutions
        ok = ~np.isnan(sol[..., 0])
        err = np.linalg.norm(fk(np.where(ok[..., None], sol, 0.0), L, b) - p[:, None, :], axis=-1)
        assert np.all(err[ok] < 1e-9 * L)
        # The configuration we started from is among the solutions.
        dist = np.abs(wrap_angle(sol - half_alpha[:, None, :])).max(-1)
        assert np.all(np.nanmin(dist, axis=1) < 1e-7)


def test_quartic_vanishes_at_solutions():
    L, b = 1.0, 2 / 3
    a = characteristic_quartic(0.03, 1.6, L, b)
    for th in ik_2x(0.03, 1.6, L, b):
        # φ1: direction of the diagonal from the base-left node to the top-right node of joint 1.
        mid = np.array([-np.sin(th[0]), np.cos(th[0])]) * np.sqrt(L**2 - b**2 * np.cos(th[0]) ** 2)
        d = mid + 0.5 * b * np.array([np.cos(2 * th[0]) + 1, np.sin(2 * th[0])])
        t = np.tan(np.arctan2(d[1], d[0]) / 2)
        assert abs(np.polyval(a, t)) < 1e-9 * np.abs(a).max()


def test_outside_workspace_has_no_solution_and_bad_design_raises():
    assert ik_2x(3.0, 0.0, 1.0, 0.5).shape == (0, 2)
    with pytest.raises(ValueError, match="b"):
        ik_2x(0.0, 1.0, 1.0, 1.2)
    with pytest.raises(ValueError, match="L"):
        ik_2x(0.0, 1.0, -1.0, 0.5)
    with pytest.raises(ValueError, match="x and y"):
        ik_2x(np.nan, 1.0, 1.0, 0.5)


def test_jacobian_matches_finite_differences_and_eq12():
    rng = np.random.default_rng(2)
    L, b = 1.0, 2 / 3
    t = rng.uniform(-np.pi, np.pi, (500, 3))
    J = jacobian(t, L, b)
    h = 1e-6
    Jn = np.stack([(fk(t + h * e, L, b) - fk(t - h * e, L, b)) / (2 * h) for e in np.eye(3)], -1)
    np.testing.assert_allclose(J, Jn, atol=1e-8)
    J2 = jacobian(t[:, :2], L, b)
    np.testing.assert_allclose(det_jacobian_2x(t[:, 0], t[:, 1], L, b), np.linalg.det(J2), atol=1e-12)


def test_jacobian_matches_the_closed_form_of_eq11():
    """Eq. (11) term by term (prototype ratio b/L = 1/2). As extracted, the first numerator term of
    ∂x/∂θ2 reads −sin(2θ1+θ2)·b²cosθ2·sinθ2; differentiating eq. (3) gives +: it must mirror the
    −cos(2θ1+θ2)·b²cosθ2·sinθ2 of ∂y/∂θ2 (∂x/∂θ2 = −(l2' S + l2 C), ∂y/∂θ2 = l2' C − l2 S)."""
    L, b = 0.1, 0.05
    t = np.random.default_rng(7).uniform(-1.5, 1.5, (300, 2))
    c1, s1, c2, s2 = np.cos(t[:, 0]), np.sin(t[:, 0]), np.cos(t[:, 1]), np.sin(t[:, 1])
    S, C = np.sin(2 * t[:, 0] + t[:, 1]), np.cos(2 * t[:, 0] + t[:, 1])
    r1, r2 = np.sqrt(L**2 - b**2 * c1**2), np.sqrt(L**2 - b**2 * c2**2)
    eq11 = np.array([
        [-(-2 * b**2 * c1**3 + L**2 * c1 + b**2 * c1 + 2 * r2 * C * r1) / r1,
         -(+S * b**2 * c2 * s2 - C * c2**2 * b**2 + L**2 * C) / r2],  # sign of the first term corrected
        [-(-2 * b**2 * c1**2 * s1 + L**2 * s1 + 2 * r2 * S * r1) / r1,
         -(-C * b**2 * c2 * s2 - S * c2**2 * b**2 + L**2 * S) / r2],
    ]).transpose(2, 0, 1)
    np.testing.assert_allclose(jacobian(t, L, b), eq11, rtol=0, atol=1e-15)


def test_limited_solution_counts_match_the_legends_of_figs_9_and_11():
    """With |θ_i| < π/2: the prototype ratio b/L = 1/2 (Fig. 11, legend 1, 2 and 4 solutions) has a
    small 4-solution swallowtail on the axis and no 3-solution region; b = 2/3 (Fig. 9, centre,
    legend 1 to 4) has both."""
    half = np.bincount(cartesian_counts(1.0, 0.5, n=300).limited.ravel(), minlength=5)
    assert half[1] > half[2] > half[4] > 0 and half[3] == 0
    two_thirds = np.bincount(cartesian_counts(1.0, 2 / 3, n=300).limited.ravel(), minlength=5)
    assert np.all(two_thirds[1:] > 0)


@pytest.mark.parametrize("b", [0.3, 2 / 3, 0.9])
def test_det_vanishes_on_singularity_curves(b):
    L = 1.0
    t2 = np.linspace(-np.pi, np.pi, 1001)
    J = jacobian(np.stack([singular_half_alpha1(t2, L, b), t2], -1), L, b)
    assert np.abs(np.linalg.det(J)).max() < 1e-12
    J = jacobian(np.stack([foldback_half_alpha1(t2), t2], -1), L, b)
    assert np.abs(np.linalg.det(J)).max() < 1e-12
    np.testing.assert_allclose(fk(np.stack([foldback_half_alpha1(t2), t2], -1), L, b), 0.0, atol=1e-12)
    # ...and not on a generic point off them.
    assert abs(det_jacobian_2x(0.3, 0.9, L, b)) > 1e-3


def test_two_solutions_per_aspect_at_a_four_solution_point():
    # Section 2.4: the manipulator is cuspidal, its four solutions split two and two over aspects.
    sol = ik_2x(0.03, 1.6, 1.0, 2 / 3)
    assert sorted(aspect(sol[:, 0], sol[:, 1], 1.0, 2 / 3)) == [-1, -1, 1, 1]


def test_cuspidality_closed_form():
    assert is_cuspidal(0.1, 0.05)  # ERRATA: the prototype ratio 1/2 is cuspidal
    assert is_cuspidal(1.0, 0.41) and not is_cuspidal(1.0, 0.40)


def test_cuspidality_threshold_found_by_counting_solutions():
    b_star = cuspidality_threshold_numeric(1.0, tol=1e-4)
    assert abs(b_star - 1 / np.sqrt(6)) < 2e-4
    assert max_solutions_on_axis(2.0, 2.0 * 0.5) == 4
    assert max_solutions_on_axis(2.0, 2.0 * 0.38) == 2


def test_solution_counts_by_region():
    # Section 2.5/2.7: 2 and 4 solutions without limits; at most 4, mostly 1 with |θ| < π/2.
    cc = cartesian_counts(1.0, 2 / 3, n=120)
    assert set(np.unique(cc.total)) <= {0, 1, 2, 3, 4} and (cc.total == 4).any()
    assert np.all(cc.limited <= cc.total)
    assert np.bincount(cc.limited.ravel())[1] > np.bincount(cc.limited.ravel())[2:].sum()
    assert np.array_equal(cc.by_type.sum(axis=(-1, -2)), cc.total)
    assert max_solutions_on_axis(1.0, 0.3) == 2
    cc = cartesian_counts(1.0, 0.3, n=80)
    assert cc.total.max() == 2


def test_cli_ik_and_cuspidal():
    from server.cli import app

    r = CliRunner().invoke(app, ["kinematics", "ik", "--L", "1", "--b", "0.6667", "--x", "0.03", "--y", "1.6", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert out["count"] == 4
    r = CliRunner().invoke(app, ["kinematics", "ik", "--L", "1", "--b", "1.5", "--x", "0", "--y", "1"])
    assert r.exit_code != 0 and "smaller than L" in r.output
    r = CliRunner().invoke(app, ["kinematics", "cuspidal", "--L", "1", "--b", "0.5", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert out["cuspidal"] and out["max_ik_solutions_found"] == 4
    r = CliRunner().invoke(app, ["kinematics", "cuspidal", "--L", "1", "--b", "0.5"])
    assert "cuspidal" in r.output
