"""The twin's simulator (issue 3): accuracy, statics, slack, singularity, sensors, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from twin.model import dynamics
from twin.sim.simulator import Twin, TwinConfig

# pure computation, no bus or process: beside the realtime modules at nice 19 (tests/conftest.py)
pytestmark = pytest.mark.background


def static_forces(model, alpha, pretension=10.0):
    """Inverse statics: Z f = g(α) with the redundancy spent on pretension (f = f_p + τ·n)."""
    terms = dynamics.evaluate(model, alpha)
    Z = terms.Z
    null = np.append(-np.linalg.solve(Z[:, :-1], Z[:, -1]), 1.0)
    f = np.append(np.linalg.solve(Z[:, :-1], terms.g), 0.0)
    return f + (pretension - f.min()) / null.min() * null if f.min() < pretension else f


def test_matches_radau_on_the_same_inputs():
    twin = Twin(config=TwinConfig(camera=False))
    m = twin.model
    f = static_forces(m, np.radians([20.0, -10.0, 30.0]))
    n, nc = m.n_joints, m.n_cables

    def rhs(_t, s):
        acc = dynamics.accelerations(m, s[:n], s[n : n + nc], s[n + nc : 2 * n + nc], s[2 * n + nc :], f)
        return np.concatenate([s[n + nc :], acc.alpha_ddot, acc.theta_ddot])

    ticks = 400
    ref = solve_ivp(rhs, (0, ticks * twin.dt), np.zeros(2 * (n + nc)), method="Radau", rtol=1e-9, atol=1e-11,
                    t_eval=np.arange(1, ticks + 1) * twin.dt)
    assert ref.success
    ours = np.array([twin.tick(f).alpha for _ in range(ticks)])
    assert np.degrees(np.abs(ours - ref.y[:n].T)).max() < 0.01
    assert np.degrees(np.abs(ours[-1])).max() > 1.0  # it did move


def test_first_order_convergence_with_substeps():
    errors = []
    f = None
    for sub in (1, 2, 4, 16):
        twin = Twin(config=TwinConfig(camera=False, substeps=sub))
        f = static_forces(twin.model, np.radians([20.0, -10.0, 30.0])) if f is None else f
        errors.append(np.array([twin.tick(f).alpha for _ in range(200)]))
    e = [np.abs(x - errors[-1]).max() for x in errors[:-1]]
    assert e[1] < 0.7 * e[0] and e[2] < 0.7 * e[1]


def test_settles_at_the_configuration_of_its_static_forces():
    twin = Twin(config=TwinConfig(camera=False))
    target = np.radians([20.0, -10.0, 30.0])
    f = static_forces(twin.model, target)
    for _ in range(int(200 * 500)):
        tick = twin.tick(f)
    assert np.degrees(np.abs(tick.alpha - target)).max() < 0.1
    np.testing.assert_allclose(tick.tension, f, rtol=0.02)  # at rest friction vanishes (eq. 37)
    assert not tick.slack.any()


def test_cables_go_slack_when_forces_are_cut():
    """Without friction the springs snap the neck back when the forces are cut; the right cables'
    paths shorten faster than their idle motors wind, so they go slack and carry no tension.
    (With eq. 37's friction, which vanishes at rest, a cut cable instead relaxes slowly.)"""
    twin = Twin(config=TwinConfig(camera=False, friction=False))
    target = np.radians([20.0, 20.0, 20.0])
    twin.reset(target)
    f = static_forces(twin.model, target)
    for _ in range(100):
        tick = twin.tick(f)
    assert not tick.slack.any()
    ticks = [twin.tick(np.zeros(4)) for _ in range(250)]
    assert all(t.slack[:3].all() for t in ticks[90:200])
    assert all(np.all(t.tension[t.slack] == 0) and np.all(t.tension[~t.slack] > 0) for t in ticks)
    assert min(t.elongation[:3].max() for t in ticks[90:200]) < 0  # really slack, not just unloaded


def test_flat_singularity_is_flagged_and_never_crossed():
    twin = Twin(config=TwinConfig(camera=False, friction=False))
    twin.reset(np.radians([150.0, 0.0, 0.0]))
    pull_left = np.array([0.0, 0.0, 0.0, 100.0])
    flagged = flat = False
    for _ in range(5000):
        tick = twin.tick(pull_left)
        flagged |= tick.near_singular
        if tick.flat:
            flat = True
            break
    assert flagged and flat
    assert abs(tick.alpha[0]) < math.pi
    before = twin.alpha
    assert twin.tick(pull_left).flat and np.array_equal(twin.alpha, before)  # refused, not crossed


@pytest.mark.parametrize("overrides", [
    {"springs.k_left": [1e6] * 3, "springs.k_right": [1e6] * 3},
    {"cables.variable.k": [1e7] * 4, "cables.variable.lambda": [0.0] * 4},  # at 1e7 N/m no λ stiffens it further
    {"bars.m_diagonal": [0.0] * 3, "bars.I_diagonal": [0.0] * 3, "bars.m_top": [0.0, 0.0, 1e-3],
     "bars.I_top": [0.0] * 3},
])
def test_at_the_parameter_bounds_the_twin_still_integrates(overrides):
    """The bounds of twin.model.params (SPRING_K_MAX_N_M, CABLE_K_MAX_N_M, some mass) are where
    the 2 ms step was checked: 2 s of a constant 10 N command, no step refused at the flat
    singularity, the tension within a few N of the command (beyond them, audit of 2026-11-26:
    springs of 1e7 N/m refused 997 of 1000 steps, cables of 1e15 N/m reported 8e7 N)."""
    from twin.model.params import load_params

    twin = Twin(load_params(overrides=overrides), TwinConfig(camera=False))
    ticks = [twin.tick(np.full(4, 10.0)) for _ in range(1000)]
    assert not any(t.flat for t in ticks)
    assert max(float(np.abs(t.tension).max()) for t in ticks) < 15.0
    assert np.all(np.isfinite(ticks[-1].alpha))


def test_at_the_lambda_bound_the_twin_still_pulls_what_is_commanded():
    """Eq. 54's λ at its bound (twin.model.params.lambda_max_per_m: the cable's stiffness at f_max
    within CABLE_K_MAX_N_M): 10 N then 90 N commanded give tensions near the command (within the
    pulleys' friction); at λ = 1e6 1/m, 90 N gave 29 N, and at 1e12, 0.05 N (audit of session 46)."""
    from twin.model.params import lambda_max_per_m, load_params

    base = load_params()
    top = [lambda_max_per_m(k, base.limits.f_max) * (1 - 1e-9) for k in base.cables.variable.k]
    twin = Twin(load_params(overrides={"cables.variable.lambda": top}), TwinConfig(camera=False))
    for command in (10.0, 90.0):
        ticks = [twin.tick(np.full(4, command)) for _ in range(750)]
        assert not any(t.flat for t in ticks)
        assert np.all((0.8 * command < ticks[-1].tension) & (ticks[-1].tension < 1.1 * command)), (command, ticks[-1].tension)


def test_encoders_are_quantised_and_camera_is_noisy_late_and_30_hz():
    twin = Twin(config=TwinConfig(seed=3))
    f = static_forces(twin.model, np.radians([30.0, 20.0, 10.0]))
    q = 2 * math.pi / twin.params.sensors.encoder_counts_per_rev
    frames, truth = [], {}
    for _ in range(2500):  # 5 s
        tick = twin.tick(f)
        assert np.all((tick.theta - tick.theta_meas >= 0) & (tick.theta - tick.theta_meas < q))
        np.testing.assert_allclose(np.round(tick.theta_meas / q), tick.theta_meas / q, atol=1e-6)
        truth[round(tick.t_s, 6)] = tick.alpha
        for capture, alpha_ip in tick.frames:
            frames.append((tick.t_s, capture, alpha_ip))
    assert 145 <= len(frames) <= 151
    latency = twin.params.sensors.camera_latency
    assert all(abs(t - c - latency) < twin.dt + 1e-9 for t, c, _ in frames)
    noise = np.array([a - truth[round(c, 6)] for _, c, a in frames])
    assert 0.7 < np.degrees(noise.std()) < 1.3 and abs(np.degrees(noise.mean())) < 0.3


def test_same_seed_same_run_other_seed_other_camera_noise():
    def run(seed):
        twin = Twin(config=TwinConfig(seed=seed))
        f = static_forces(twin.model, np.radians([30.0, 20.0, 10.0]))
        out = [twin.tick(f) for _ in range(300)]
        return np.array([t.theta_meas for t in out]), [a for t in out for _, a in t.frames]

    a, b, c = run(7), run(7), run(8)
    assert np.array_equal(a[0], b[0]) and all(np.array_equal(x, y) for x, y in zip(a[1], b[1]))
    assert np.array_equal(a[0], c[0]) and not np.array_equal(a[1][0], c[1][0])


@pytest.mark.parametrize("cable_model", ["rigid", "linear"])
def test_other_cable_models_move_to_their_statics(cable_model):
    twin = Twin(config=TwinConfig(cable_model=cable_model, camera=False))
    target = np.radians([20.0, -10.0, 30.0])
    f = static_forces(twin.model, target)
    for _ in range(200 * 500):
        tick = twin.tick(f)
    assert np.degrees(np.abs(tick.alpha - target)).max() < 0.1


def test_reset_rejects_bad_states():
    twin = Twin()
    with pytest.raises(ValueError, match="alpha must be 3 finite angles"):
        twin.reset(np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError):
        twin.reset(np.radians([170.0, 0.0, 0.0]))


def test_robot_cable_damping_changes_only_the_cable_damping():
    """The robot truth's cable effect alone without creep (twin/sim/truth.py): the twin integrates
    the model with a real line's damping; after a force step the cable stretches within a
    fraction of a second instead of creeping. (Issue 16: `truth="robot"` now switches on every
    unmodelled effect, so this test takes the damping alone; tests/test_truth.py covers the rest.)"""
    from twin.sim.truth import C_A_ROBOT, load_truth, truth_params

    damping_only = load_truth("robot").only("cables").replace("cables", creep_ratio=0.0)
    model_twin = Twin(config=TwinConfig(camera=False))
    robot_twin = Twin(config=TwinConfig(camera=False, truth=damping_only))
    p, q = model_twin.params, robot_twin.params
    assert q.cables.variable.c_a == (C_A_ROBOT,) * 4 and q.cables.linear.c_a == (C_A_ROBOT,) * 4
    assert p.cables.variable.c_a == (3000.0,) * 4
    strip = lambda x: {k: v for k, v in x.to_dict().items() if k not in ("cables", "name")}  # noqa: E731
    assert strip(p) == strip(q) and p.cables.variable.k == q.cables.variable.k
    assert truth_params(p, "model") is p
    with pytest.raises(ValueError, match="truth must be one of"):
        TwinConfig(truth="bogus")

    f = np.full(4, 20.0)
    stretch = {}
    for name, twin in (("model", model_twin), ("robot", robot_twin)):
        ticks = [twin.tick(f) for _ in range(100)]  # 0.2 s
        stretch[name] = np.array([t.elongation[0] for t in ticks])
    # Low damping: most of the static stretch within 0.2 s; c_a = 3000 N·s/m (τ = c_a/k ≈ 0.4 s):
    # less than a third of it.
    assert stretch["robot"].max() > 1.5 * stretch["model"].max(), stretch
