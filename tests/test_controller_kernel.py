"""The compiled law tick (controller/kernel.py), the kernels of eqs. 35, 58 and 63-65 it shares with
their numpy-facing wrappers (one implementation, compiled or plain Python; issue 20), checked
against LAPACK oracles, and the tick timing (controller/timing.py). Issue 21."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from test_bridge_lean import NO_NUMBA, ROOT  # the robot's situation: numba refused in a child

from bridge import bus
from controller import distribution, timing
from controller.distribution import distribute, lower_bounds
from controller.laws import ComputedTorque, LawConfig, controller_model
from twin.model import cables, compiled, dynamics, estimation
from twin.model.estimation import PseudoInverseEstimator, long_cable, short_cables
from twin.model.numeric import RIGID
from twin.model.params import load_params


@pytest.fixture(scope="module")
def params():
    return load_params()


def test_solve_into_equals_lapack():
    rng = np.random.default_rng(1)
    for _ in range(50):
        A, b = rng.normal(size=(3, 3)), rng.normal(size=3)
        x = np.empty(3)
        estimation.solve_into(A, b, np.empty((3, 3)), x)
        np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-10, atol=1e-12)


def lapack_distribution(Z, gamma, lower, f_max, short, long):
    """Eqs. 63-65 written with LAPACK, as the numpy code was before the kernel became the one
    implementation: the test's independent oracle (f, saturated, f_long, feasible)."""
    Z1, Z2 = Z[:, short], Z[:, long]
    p, n = np.linalg.solve(Z1, gamma), -np.linalg.solve(Z1, Z2)
    with np.errstate(divide="ignore", invalid="ignore"):
        f_long = max(lower[long], np.max(np.where(n > 0, (lower[short] - p) / n, -np.inf)))
    f = np.empty(Z.shape[1])
    f[short], f[long] = p + n * f_long, f_long
    return np.minimum(f, f_max), f > f_max, f_long, bool(np.all(n > 0))


def test_distribution_kernel_and_its_wrapper_equal_eqs_63_65(params):
    m = controller_model(params, LawConfig(law=2))
    short, long = short_cables(m), long_cable(m)
    rng = np.random.default_rng(2)
    for _ in range(30):
        alpha = rng.uniform(-0.5, 0.5, 3)
        Z = cables.Z(m, alpha)
        gamma = rng.normal(scale=2.0, size=3)
        lower = lower_bounds(m.t_min, m.f_min, rng.uniform(0, 3, 4), rng.normal(size=4))
        f_ref, sat_ref, f_long_ref, feasible_ref = lapack_distribution(Z, gamma, lower, m.f_max, short, long)
        f, sat = np.empty(4), np.empty(4, dtype=np.bool_)
        feasible, f_long = distribution.distribute_into(Z, gamma, lower, m.f_max, short, long, np.empty((3, 3)),
                                                        np.empty((3, 3)), np.empty(3), np.empty(3), np.empty(3), f, sat)
        np.testing.assert_allclose(f, f_ref, rtol=1e-9, atol=1e-9)
        assert sat.tolist() == sat_ref.tolist() and feasible == feasible_ref and abs(f_long - f_long_ref) < 1e-9
        d = distribute(Z, gamma, lower, m.f_max, short, long)
        np.testing.assert_array_equal(d.f, f)
        assert d.saturated.tolist() == sat.tolist() and d.feasible == feasible and d.f_long == f_long
    with pytest.raises(IndexError):  # the kernel does not check indices: the wrapper does
        distribute(Z, gamma, lower, m.f_max, np.array([0, 1, 7]), long)


def lstsq_estimator(m, dt):
    """Eq. 35 with eq. 58 written with LAPACK's least squares and Z from the cable kernel's
    numpy face, as the numpy estimator was before the kernel became the one implementation:
    the test's independent oracle. Returns update(θ, f_prev, θ̇) -> α̂."""
    state = {"alpha": np.zeros(m.n_joints), "theta": np.zeros(m.n_cables), "x_c": np.zeros(m.n_cables)}

    def update(theta, f_prev, theta_dot):
        if m.cable_model == RIGID:
            x_next = np.zeros(m.n_cables)
        else:
            t = f_prev - dynamics.f_friction(m, theta_dot)
            x_next = np.maximum(state["x_c"] + dt / m.c_a * (t - (m.k + m.lam * t) * state["x_c"]), 0.0)
        rhs = m.rho * (theta - state["theta"]) - (x_next - state["x_c"])
        step = np.linalg.lstsq(cables.Z(m, state["alpha"]).T, rhs, rcond=None)[0]
        step = np.linalg.lstsq(cables.Z(m, state["alpha"] + 0.5 * step).T, rhs, rcond=None)[0]
        state.update(alpha=state["alpha"] + step, theta=np.array(theta, dtype=float), x_c=x_next)
        return state["alpha"]

    return update


@pytest.mark.parametrize("law", [1, 3])
def test_the_law_estimate_equals_eq_35_with_eq_58(params, law):
    """α̂ of the compiled tick is the estimator's (twin.model.estimation), and both the LAPACK
    least-squares oracle's, along a motion."""
    ctl = ComputedTorque(params, LawConfig(law=law))
    ref = PseudoInverseEstimator(ctl.model, ctl.dt)
    oracle = lstsq_estimator(ctl.model, ctl.dt)
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
        expected = ref.update(theta, f, theta_dot)
        np.testing.assert_array_equal(cmd.alpha_hat, expected)  # the same kernel on the same inputs
        np.testing.assert_allclose(expected, oracle(theta, f, theta_dot), atol=1e-10)
        f = cmd.f.copy()


# Runs the wrappers and the kernels on seeded random inputs, prints JSON; run here (compiled)
# and in a child with numba refused (the robot's plain-Python path).
WRAPPERS_AND_KERNELS = """
import json, sys
import numpy as np
from controller import distribution, laws
from twin.model import cables, compiled, estimation
from twin.model.params import load_params

def run():
    params = load_params()
    rng = np.random.default_rng(58)
    out = {"numba": compiled.numba_enabled(), "elongation": [], "distribution": [], "alpha_hat": []}
    m = laws.controller_model(params, laws.LawConfig(law=3))
    short, long = estimation.short_cables(m), estimation.long_cable(m)
    for _ in range(20):
        x, f, td = rng.uniform(0, 2e-3, 4), rng.uniform(0, 60, 4), rng.normal(scale=5, size=4)
        wrapped = estimation.predict_elongation(m, x, f, td, 0.002)
        kernel = np.empty(4)
        estimation.elongation_into(m, x, f, td, 0.002, kernel)
        assert np.array_equal(wrapped, kernel)
        out["elongation"].append(wrapped.tolist())
        Z = cables.Z(m, rng.uniform(-0.6, 0.6, 3))
        gamma, lower = rng.normal(scale=2, size=3), rng.uniform(2, 12, 4)
        d = distribution.distribute(Z, gamma, lower, m.f_max, short, long)
        fk, sat = np.empty(4), np.empty(4, dtype=np.bool_)
        feasible, f_long = distribution.distribute_into(Z, gamma, lower, m.f_max, short, long, np.empty((3, 3)),
                                                        np.empty((3, 3)), np.empty(3), np.empty(3), np.empty(3), fk, sat)
        assert np.array_equal(d.f, fk) and d.f_long == f_long and d.feasible == feasible
        out["distribution"].append(d.f.tolist() + [d.f_long])
    est = estimation.PseudoInverseEstimator(m, 0.002)
    alpha, theta, x_c = np.zeros(3), np.zeros(4), np.zeros(4)
    work = estimation.pseudo_inverse_scratch(3, 4)
    for k in range(1, 60):
        th, f, td = 0.2 * np.sin(k / 20 * np.array([1.0, 1.3, 0.7, 1.1])), rng.uniform(5, 40, 4), rng.normal(size=4)
        wrapped = est.update(th, f, td)
        estimation.pseudo_inverse_update(m, 0.002, th, theta, x_c, alpha, f, td, *work)
        assert np.array_equal(wrapped, alpha) and np.array_equal(est.x_c, x_c)
        out["alpha_hat"].append(wrapped.tolist() + x_c.tolist())
    return out

print(json.dumps(run()))
"""


def test_wrappers_are_their_kernels_compiled_and_as_plain_python():
    """Eqs. 35, 58 and 63-65 exist once: the numpy-facing wrappers (predict_elongation,
    PseudoInverseEstimator, distribute) give exactly their kernels' numbers, and the kernels run
    compiled (this process) and as plain Python (a child with numba refused) agree to rounding."""
    assert compiled.numba_enabled(), "the PC's venv has numba: this compares the two ways to run the kernels"
    namespace: dict = {}
    exec(WRAPPERS_AND_KERNELS.replace("print(json.dumps(run()))", ""), namespace)
    here = namespace["run"]()
    env = {k: v for k, v in os.environ.items() if k != "XNECK_NO_NUMBA"}
    child = subprocess.run([sys.executable, "-c", NO_NUMBA + WRAPPERS_AND_KERNELS], capture_output=True, text=True,
                           timeout=300, cwd=ROOT, env=env)
    assert child.returncode == 0, child.stderr[-3000:]
    plain = json.loads(child.stdout)
    assert here["numba"] is True and plain["numba"] is False
    for key in ("elongation", "distribution", "alpha_hat"):
        np.testing.assert_allclose(np.array(plain[key]), np.array(here[key]), rtol=1e-12, atol=1e-12, err_msg=key)


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
