"""The compiled law tick (controller/kernel.py) against the reference implementations it replaces
on the hot path, and the tick timing (controller/timing.py). Issue 21."""

from __future__ import annotations

import numpy as np
import pytest

from bridge import bus
from controller import kernel, timing
from controller.distribution import distribute, lower_bounds
from controller.laws import ComputedTorque, LawConfig, controller_model
from twin.model import cables
from twin.model.estimation import PseudoInverseEstimator, long_cable, short_cables
from twin.model.params import load_params


@pytest.fixture(scope="module")
def params():
    return load_params()


def test_solve_into_equals_lapack():
    rng = np.random.default_rng(1)
    for _ in range(50):
        A, b = rng.normal(size=(3, 3)), rng.normal(size=3)
        x = np.empty(3)
        kernel.solve_into(A, b, np.empty((3, 3)), x)
        np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-10, atol=1e-12)


def test_distribution_kernel_equals_eqs_63_65(params):
    m = controller_model(params, LawConfig(law=2))
    short, long = short_cables(m), long_cable(m)
    rng = np.random.default_rng(2)
    for _ in range(30):
        alpha = rng.uniform(-0.5, 0.5, 3)
        Z = cables.Z(m, alpha)
        gamma = rng.normal(scale=2.0, size=3)
        lower = lower_bounds(m.t_min, m.f_min, rng.uniform(0, 3, 4), rng.normal(size=4))
        ref = distribute(Z, gamma, lower, m.f_max, short, long)
        f, sat = np.empty(4), np.empty(4, dtype=np.bool_)
        feasible = kernel.distribute_into(Z, gamma, lower, m.f_max, short, long, np.empty((3, 3)), np.empty((3, 3)),
                                          np.empty(3), np.empty(3), np.empty(3), f, sat)
        np.testing.assert_allclose(f, ref.f, rtol=1e-9, atol=1e-9)
        assert sat.tolist() == ref.saturated.tolist() and feasible == ref.feasible


@pytest.mark.parametrize("law", [1, 3])
def test_the_law_estimate_equals_eq_35_with_eq_58(params, law):
    """α̂ of the compiled tick is the reference estimator's (twin.model.estimation) along a motion."""
    ctl = ComputedTorque(params, LawConfig(law=law))
    ref = PseudoInverseEstimator(ctl.model, ctl.dt)
    theta_dot = np.zeros(4)
    z = np.zeros(3)
    f = np.zeros(4)  # the law's forces over the last period (none before the first tick)
    t = np.arange(1, 400) / 500
    thetas = 0.3 * np.sin(np.outer(t, [1.0, 1.3, 0.7, 1.1]))
    prev = np.zeros(4)
    beta = 1.0 - np.exp(-2 * np.pi * ctl.config.velocity_filter_hz * ctl.dt)
    ctl.reset(theta=np.zeros(4))
    ref.reset(theta=np.zeros(4))
    for theta in thetas:
        cmd = ctl.step(theta, z, z, z)
        theta_dot += beta * ((theta - prev) / ctl.dt - theta_dot)
        prev = theta
        expected = ref.update(theta, f, theta_dot).copy()
        np.testing.assert_allclose(cmd.alpha_hat, expected, atol=1e-10)
        f = cmd.f.copy()


def test_tick_times_give_stage_durations_latency_histograms_and_campaign_quantiles():
    times = timing.TickTimes(capacity=16)
    t = 1_000_000_000
    for k in range(10):  # arrival every 2 ms; stages 0.05, 0.1, 0.02, 0.03 ms (latency 0.2 ms)
        a = t + k * 2_000_000
        lat = times.record(a, a + 50_000, a + 150_000, a + 170_000, a + 200_000)
        assert lat == 200_000
    stages, period = times.window()
    np.testing.assert_array_equal(stages[0], [50_000, 100_000, 20_000, 30_000])
    assert len(period) == 9 and np.all(period == 2_000_000)
    msg = timing.timing_message(1, 0.0, "c-1", stages, period, times, ticks=10, deadline_misses=0, overruns=0)
    assert bus.decode(bus.ControllerTiming, bus.encode(msg)) == msg
    assert msg.window_ticks == 10 and abs(msg.latency_p99_ms - 0.2) < 1e-9 and abs(msg.period_p50_ms - 2.0) < 1e-9
    assert sum(msg.campaign_latency_counts) == 10 and sum(msg.campaign_period_counts) == 9
    assert msg.campaign_latency_p99_ms == 0.3  # the upper edge of the bin holding 0.2 ms
    assert times.window()[0].shape == (0, 4)  # read once


def test_sampling_one_time_equals_the_vectorised_trajectory():
    """The controller's per-tick sample (Trajectory.sample_at, cycloid_at) is the vectorised one."""
    from controller.trajectory import Trajectory, control_test_trajectory, cycloid, cycloid_at

    for traj in (control_test_trajectory(), Trajectory.from_degrees([[10, -5, 3]], durations_s=[], name="one")):
        t = np.concatenate([np.linspace(-1.0, traj.duration_s + 1.0, 2001), traj._depart, traj._arrive])
        ref = traj.sample(t)
        for k, tk in enumerate(t):
            a, ad, add = traj.sample_at(float(tk))
            np.testing.assert_allclose(a, ref.alpha[k], rtol=0, atol=1e-15)
            np.testing.assert_allclose(ad, ref.alpha_dot[k], rtol=0, atol=1e-15)
            np.testing.assert_allclose(add, ref.alpha_ddot[k], rtol=0, atol=1e-15)
    for tau in (-0.5, 0.0, 1e-9, 0.25, 0.5, 0.999, 1.0, 1.5):
        np.testing.assert_allclose(cycloid_at(tau), [float(x) for x in cycloid(tau)], rtol=0, atol=1e-15)
