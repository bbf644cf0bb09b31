"""The robot model (issue 2): cable transmission, inertia, potential, full dynamics."""

from __future__ import annotations

import numpy as np
import pytest

from twin.model import cables, chain, dynamics, xjoint
from twin.model.numeric import build
from twin.model.params import load_params

DEG = np.pi / 180


def test_side_lengths_are_mirrors_and_match_eqs_1_2(model):
    a = np.linspace(-1.5, 1.5, 41)
    ll, lr = xjoint.side_lengths(model.L, model.b, a)
    np.testing.assert_allclose(ll, xjoint.side_lengths(model.L, model.b, -a)[1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(ll, np.sqrt(model.L**2 - model.b**2 * np.cos(a / 2) ** 2) - model.b * np.sin(a / 2))
    assert np.all(np.diff(ll) < 0) and np.all(np.diff(lr) > 0)  # α > 0 shortens the left side


def test_psi_matches_eq_7(model):
    L, b = model.L, model.b
    a = np.linspace(-1.4, 1.4, 29)
    ca, sa = np.cos(a) + 1, np.sin(a)
    eq7 = 2 * np.arctan((-2 * L * sa - np.sqrt((2 * L * sa) ** 2 + (2 * L * ca) ** 2 - (2 * b * ca) ** 2)) / ((2 * b - 2 * L) * ca))
    np.testing.assert_allclose(xjoint.psi(L, b, a), eq7, rtol=1e-12)
    assert xjoint.psi(2.0, 1.0, 0.0) == pytest.approx(np.radians(120))  # ERRATA 2


def test_Z_matches_central_differences_of_l_c(model, rng):
    alpha = rng.uniform(-80, 80, size=(200, 3)) * DEG
    Z = cables.Z(model, alpha)
    h = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd = -(cables.l_c(model, alpha + e) - cables.l_c(model, alpha - e)) / (2 * h)
        np.testing.assert_allclose(Z[:, i, :], fd, rtol=1e-6, atol=1e-6 * np.abs(Z).max())


@pytest.mark.parametrize(
    "alpha_deg, table_mm",
    [
        ((0, 0, 0), [[-27.26, 0, 0, 29.60], [0, -27.26, 0, 29.60], [0, 0, -27.26, 27.26]]),
        ((40, 30, 20), [[-30.32, 0.89, 0.89, 23.54], [0, -29.99, 0.68, 25.18], [0, 0, -29.34, 24.43]]),
        ((50, 50, 50), [[-30.30, 1.09, 1.09, 21.89], [0, -30.30, 1.09, 21.89], [0, 0, -30.30, 19.55]]),
    ],
)
def test_Z_matches_errata_table(model, alpha_deg, table_mm):
    np.testing.assert_allclose(cables.Z(model, np.radians(alpha_deg)) * 1e3, table_mm, atol=0.006)


def test_Z1_triangular_negative_diagonal_and_null_direction_positive(model):
    grid = np.stack(np.meshgrid(*[np.linspace(-60, 60, 9) * DEG] * 3, indexing="ij"), -1).reshape(-1, 3)
    Z = cables.Z(model, grid)
    Z1, Z2 = Z[:, :, :3], Z[:, :, 3]
    assert np.all(np.tril(Z1, -1) == 0)
    assert np.all(np.diagonal(Z1, axis1=1, axis2=2) < 0)
    assert np.all(-np.linalg.solve(Z1, Z2[..., None])[..., 0] > 0)
    assert np.all(Z2 > 0)


def test_without_pulleys_Z1_is_diagonal(params, rng):
    no_pulleys = build(params, pulleys=False)
    Z1 = cables.Z(no_pulleys, rng.uniform(-1, 1, size=(50, 3)))[:, :, :3]
    off = Z1 - np.einsum("kii->ki", Z1)[:, :, None] * np.eye(3)
    assert np.all(off == 0)
    with_pulleys = cables.Z(build(params), np.radians([40, 30, 20]))[:, :3]
    assert np.abs(with_pulleys - np.diag(np.diag(with_pulleys))).max() > 5e-4


def test_Z_dot_is_the_time_derivative_of_Z(model, rng):
    alpha, alpha_dot = rng.uniform(-1, 1, 3), rng.uniform(-2, 2, 3)
    h = 1e-6
    fd = (cables.Z(model, alpha + h * alpha_dot) - cables.Z(model, alpha - h * alpha_dot)) / (2 * h)
    np.testing.assert_allclose(cables.Z_dot(model, alpha, alpha_dot), fd, rtol=1e-6, atol=1e-9)


def test_theta_of_rigid_cables_eq_20_21(model, rng):
    assert np.all(cables.theta_rigid(model, np.zeros(3)) == 0)
    alpha, alpha_dot = rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3)
    h = 1e-6
    theta_dot = (cables.theta_rigid(model, alpha + h * alpha_dot) - cables.theta_rigid(model, alpha - h * alpha_dot)) / (2 * h)
    np.testing.assert_allclose(theta_dot, cables.Z(model, alpha).T @ alpha_dot / model.rho, rtol=1e-6)


def test_inertia_is_symmetric_positive_definite(model, rng):
    alpha = rng.uniform(-80, 80, size=(500, 3)) * DEG
    terms = dynamics.evaluate(model, alpha)
    for mat in (terms.M_m, terms.M):
        np.testing.assert_allclose(mat, np.swapaxes(mat, 1, 2), rtol=1e-12, atol=0)
        assert np.all(np.linalg.eigvalsh(mat) > 0)
    # The geared motors dominate (3-X paper §3.2).
    assert np.all(np.trace(terms.M, axis1=1, axis2=2) > 5 * np.trace(terms.M_m, axis1=1, axis2=2))


def test_g_is_the_gradient_of_the_potential(model, rng):
    alpha = rng.uniform(-70, 70, size=(50, 3)) * DEG
    g = dynamics.g(model, alpha)
    h = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd = (dynamics.potential_energy(model, alpha + e) - dynamics.potential_energy(model, alpha - e)) / (2 * h)
        np.testing.assert_allclose(g[:, i], fd, rtol=1e-5, atol=1e-7)


def test_statics_are_the_full_evaluations_terms(model, rng):
    """dynamics.statics (the identification's re-simulated neck) gives evaluate's l_c, Z and g,
    bit for bit, at any speed the full evaluation is asked for (statics need none), one
    configuration or a batch."""
    alpha = rng.uniform(-70, 70, size=(4, 5, 3)) * DEG
    full = dynamics.evaluate(model, alpha.reshape(-1, 3), rng.normal(size=(20, 3)))
    l_c, Z, g = dynamics.statics(model, alpha)
    assert l_c.shape == (4, 5, model.n_cables) and Z.shape == (4, 5, 3, model.n_cables) and g.shape == (4, 5, 3)
    np.testing.assert_array_equal(l_c.reshape(full.l_c.shape), full.l_c)
    np.testing.assert_array_equal(Z.reshape(full.Z.shape), full.Z)
    np.testing.assert_array_equal(g.reshape(full.g.shape), full.g)
    one = dynamics.statics(model, alpha[1, 2])
    assert [v.shape for v in one] == [(model.n_cables,), (3, model.n_cables), (3,)]
    np.testing.assert_array_equal(one[2], full.g[7])
    with pytest.raises(ValueError, match=r"alpha must have shape \(\.\.\., 3\)"):
        dynamics.statics(model, np.zeros(2))


def test_straight_neck_is_an_equilibrium_of_springs_and_gravity(model):
    np.testing.assert_allclose(dynamics.g(model, np.zeros(3)), 0, atol=1e-12)


def test_coriolis_matches_christoffel_symbols_of_M(model, rng):
    """c = Ṁα̇ − ½∂(α̇ᵀMα̇)/∂α, with ∂M/∂α by central differences."""
    h = 1e-6
    for _ in range(5):
        alpha, ad = rng.uniform(-1, 1, 3), rng.uniform(-2, 2, 3)
        dM = []
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            dM.append((dynamics.M(model, alpha + e) - dynamics.M(model, alpha - e)) / (2 * h))
        dM = np.array(dM)  # dM[k] = ∂M/∂α_k
        Mdot = np.einsum("kij,k->ij", dM, ad)
        expected = Mdot @ ad - 0.5 * np.einsum("kij,i,j->k", dM, ad, ad)
        np.testing.assert_allclose(dynamics.c(model, alpha, ad), expected, rtol=1e-5, atol=1e-9)


def _rk4_energy_drift(model, h, t_end):
    """Unforced, frictionless, rigid cables: integrate with RK4 and return max |E − E0|."""
    n, nc = model.n_joints, model.n_cables

    def rhs(s):
        alpha, alpha_dot = s[:n], s[n:]
        theta_dot = cables.Z(model, alpha).T @ alpha_dot / model.rho
        acc = dynamics.accelerations(model, alpha, cables.theta_rigid(model, alpha), alpha_dot, theta_dot, np.zeros(nc))
        return np.concatenate([alpha_dot, acc.alpha_ddot])

    def energy(s):
        terms = dynamics.evaluate(model, s[:n])
        return 0.5 * s[n:] @ terms.M @ s[n:] + terms.U

    s = np.concatenate([np.radians([30.0, -20.0, 40.0]), [1.0, -0.5, 0.8]])
    e0, drift = energy(s), 0.0
    for _ in range(int(round(t_end / h))):
        k1 = rhs(s)
        k2 = rhs(s + 0.5 * h * k1)
        k3 = rhs(s + 0.5 * h * k2)
        k4 = rhs(s + h * k3)
        s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        drift = max(drift, abs(energy(s) - e0))
    return drift, e0


def test_frictionless_rigid_model_conserves_energy(params):
    model = build(params, "rigid", friction=False)
    coarse, e0 = _rk4_energy_drift(model, 4e-3, 2.0)
    fine, _ = _rk4_energy_drift(model, 2e-3, 2.0)
    assert fine < coarse / 8  # fourth order: halving the step divides the error by about 16
    assert fine < 1e-6 * abs(e0) + 1e-7


def test_elastic_tension_pulls_only(params, model):
    x = np.array([1e-3, 0.0, -1e-3, 2e-3])
    t = dynamics.tension(model, x, np.zeros(4))
    assert t[0] > 0 and t[1] == 0 and t[2] == 0 and t[3] > 0
    assert dynamics.tension(model, np.full(4, 1e-4), np.full(4, -1.0)).max() == 0  # the damper cannot push
    linear = dynamics.tension(build(params, "linear"), np.full(4, 1e-3), np.zeros(4))
    np.testing.assert_allclose(linear, np.array([10454, 9256, 8319, 5336]) * 1e-3)


def test_variable_stiffness_solves_eq_54(model):
    x, xd = np.array([1e-3, 2e-3, 3e-3, 4e-3]), np.array([1e-4, -1e-4, 0, 2e-4])
    t = dynamics.tension(model, x, xd)
    np.testing.assert_allclose(t, (model.k + model.lam * t) * x + model.c_a * xd, rtol=1e-12)


def test_friction_models(params):
    m = build(params)
    td = np.array([-100.0, -0.1, 0.0, 100.0])
    f = dynamics.f_friction(m, td)
    assert f[2] == 0 and f[0] < 0 < f[3]
    np.testing.assert_allclose(abs(f[[0, 3]]), m.f_s[[0, 3]], rtol=0.02)
    sign = build(load_params(overrides={"friction.model": "sign"}))
    np.testing.assert_allclose(dynamics.f_friction(sign, td), np.sign(td) * m.f_s)


def test_full_model_at_rest_and_under_pretension(model):
    """Winding every cable in by the same small angle stretches them; at α = 0 the tensions
    must then balance (Zt = 0 only if the pretension is consistent), and θ̈ opposes the wind-in."""
    theta = np.full(4, 0.5)  # rad at the motor shaft, stretch ρ·0.5 = 0.4 mm
    f = np.zeros(4)
    acc = dynamics.accelerations(model, np.zeros(3), theta, np.zeros(3), np.zeros(4), f)
    np.testing.assert_allclose(acc.tension, dynamics.tension(model, model.rho * theta, np.zeros(4)))
    assert acc.n_slack == 0 and np.all(acc.theta_ddot < 0)
    slack = dynamics.accelerations(model, np.zeros(3), -theta, np.zeros(3), np.zeros(4), f)
    assert slack.n_slack == 4 and np.all(slack.tension == 0)


def test_static_forces_hold_the_elastic_model_in_place(model):
    """Forces with Z f = g and the matching cable stretch give zero accelerations."""
    alpha = np.radians([20.0, -10.0, 30.0])
    terms = dynamics.evaluate(model, alpha)
    Z = terms.Z
    null = np.append(-np.linalg.solve(Z[:, :3], Z[:, 3]), 1.0)
    f = np.append(np.linalg.solve(Z[:, :3], terms.g), 0.0) + 20.0 * null
    x = np.array([_stretch_for(model, j, f[j]) for j in range(4)])
    theta = (x - (terms.l_c - model.l_c0)) / model.rho
    acc = dynamics.accelerations(model, alpha, theta, np.zeros(3), np.zeros(4), f)
    np.testing.assert_allclose(acc.tension, f, rtol=1e-9)
    np.testing.assert_allclose(acc.alpha_ddot, 0, atol=1e-6)
    np.testing.assert_allclose(acc.theta_ddot, 0, atol=1e-6)


def _stretch_for(model, j, t):
    return t / (model.k[j] + model.lam[j] * t)  # eq. 54 at rest


def test_bar_ends_form_x_joints(model, rng):
    alpha = rng.uniform(-1.2, 1.2, size=(20, 3))
    ends = chain.bar_ends(model, alpha)
    A, B, C, D = (ends[..., k, :] for k in range(4))
    np.testing.assert_allclose(np.linalg.norm(D - A, axis=-1), model.L, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(C - B, axis=-1), model.L, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(D - C, axis=-1), model.b, rtol=1e-12)
    np.testing.assert_allclose(A[:, 1:], C[:, :-1], atol=1e-15)  # top bar i is base bar i+1
    ll, lr = xjoint.side_lengths(model.L, model.b, alpha)
    np.testing.assert_allclose(np.linalg.norm(C - A, axis=-1), ll, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(D - B, axis=-1), lr, rtol=1e-12)
    top_angle = np.arctan2(*(D - C)[..., ::-1].transpose(2, 0, 1))
    np.testing.assert_allclose(top_angle, np.cumsum(alpha, axis=-1), atol=1e-12)


def test_long_neck_routing_from_data(params):
    """An N-X neck with one long left cable and N right cables, as the conclusion plans."""
    n = 10
    routing = [" ".join([f"{i}d" for i in range(1, k)] + [f"{k}b"]) for k in range(1, n + 1)]
    routing.append(" ".join([f"{i}c" for i in range(1, n)] + [f"{n}a"]))
    per_joint = lambda v: [v] * n  # noqa: E731
    per_cable = lambda v: [v] * (n + 1)  # noqa: E731
    p = load_params(overrides={
        "geometry.n_joints": n, "cables.routing": routing,
        "springs.k_left": per_joint(200.0), "springs.k_right": per_joint(200.0), "springs.l0": per_joint(0.046),
        "bars.m_diagonal": per_joint(0.009), "bars.I_diagonal": per_joint(7.5e-6),
        "bars.m_top": per_joint(0.015), "bars.I_top": per_joint(3e-6),
        "friction.f_s": per_cable(15.0), "cables.linear.k": per_cable(9000.0), "cables.linear.c_a": per_cable(3000.0),
        "cables.variable.k": per_cable(5000.0), "cables.variable.lambda": per_cable(100.0),
        "cables.variable.c_a": per_cable(3000.0),
    })
    m = build(p)
    Z = cables.Z(m, np.full(n, 0.3))
    assert Z.shape == (n, n + 1)
    assert np.all(np.tril(Z[:, :n], -1) == 0) and np.all(np.diag(Z[:, :n]) < 0) and np.all(Z[:, n] > 0)
    assert np.all(np.linalg.eigvalsh(dynamics.M(m, np.full(n, 0.3))) > 0)


def test_read_only_inputs_and_any_shape_reuse_one_compiled_version_per_kernel(model):
    """numba compiles a version per argument type, and a read-only array (an archive's columns, a
    np.broadcast_to view) is another type: each batch kernel's first analysis of an archive compiled
    it again (5-10 s each in a fresh checkout). The public functions hand their kernels one form."""
    from twin.model import estimation
    from twin.model.compiled import numba_enabled

    if not numba_enabled():
        pytest.skip("the kernels run as plain Python here")
    a = np.full((5, model.n_joints), 0.1)
    x = np.full((5, model.n_cables), 1e-3)
    ro_a, ro_x = a.copy(), x.copy()
    ro_a.flags.writeable = ro_x.flags.writeable = False

    def calls(alpha, stretch):
        dynamics.evaluate(model, alpha, alpha)
        dynamics.evaluate(model, alpha)
        dynamics.statics(model, alpha)
        cables.batch(model, alpha, alpha)
        dynamics.tension(model, stretch, stretch)
        dynamics.f_friction(model, stretch)
        estimation.alpha_hat_3(model, stretch[0])

    kernels = (dynamics._evaluate_batch, dynamics._statics_batch, cables._cables_batch, xjoint._table,
               dynamics.friction_shape, dynamics.cable_tension_law)
    calls(a, x)
    xjoint.jets(model.L, model.b, model.r, a)
    before = [len(k.signatures) for k in kernels]
    calls(ro_a, ro_x)
    calls(np.broadcast_to(a[0], a.shape), np.broadcast_to(x[0], x.shape))
    for shape in ((3,), (2, 3, 4, 5), ()):
        xjoint.jets(model.L, model.b, model.r, np.zeros(shape))
    dynamics.f_friction(model, np.asfortranarray(x))  # not C-contiguous
    dynamics.friction_shapes(model.c_s, model.friction_sign, x[:, ::2])
    assert [len(k.signatures) for k in kernels] == before
