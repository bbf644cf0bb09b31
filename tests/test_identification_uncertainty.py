"""Identification a researcher can trust (issue 17): estimators, bounds and honest σ.

Synthetic regressions check the estimators' contracts cheaply; one twin campaign (dynamics seed
5, camera-noise seeds 501-510: none of them used while the HAC lag and the IDIM-IV were developed,
on seeds 0 and 1) checks that the ±2σ intervals of Table 2's k and λ cover the truth. The camera
noise is re-drawn on the same motion: with the test's closed loop on the true α (not α_IP), the
camera noise never reaches the forces, so each draw is what another seed of that camera gives.
The full coverage over more campaigns is ``benchmarks/identification.py --coverage``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from controller.identification_loop import simulate_campaign
from twin.identification.estimators import least_squares, physical_bounds
from twin.identification.instruments import simulated_stretch
from twin.identification.pipeline import identify_friction, identify_variable, preprocess
from twin.identification.processing import CampaignData
from twin.model.numeric import build
from twin.model.params import load_params

# Computation only, in this process and its `xneck` runs: it runs beside the realtime modules at
# nice 19 (tests/conftest.py), in the CPU they leave.
pytestmark = pytest.mark.background

DYNAMICS_SEED = 5
NOISE_SEEDS = tuple(range(501, 511))


def _ar1(rng: np.random.Generator, n: int, rho: float) -> np.ndarray:
    e = rng.standard_normal(n)
    out = np.empty(n)
    out[0] = e[0]
    for i in range(1, n):
        out[i] = rho * out[i - 1] + math.sqrt(1 - rho**2) * e[i]
    return out


def test_hac_sigma_covers_with_correlated_residuals_where_eq50_does_not():
    """Issue 17's finding: eq. 50 assumes white residuals; on filtered data (here AR(1), ρ = 0.8)
    its ±2σ covers the truth far less than 95 % of the time, the HAC σ in at least 85 % of cases."""
    rng = np.random.default_rng(17)
    n, truth = 1000, np.array([2.0, -1.0])
    covered = {"white": 0, "hac": 0}
    runs = 60
    for _ in range(runs):
        x = np.column_stack([np.sin(np.linspace(0, 12, n)) + 0.3 * _ar1(rng, n, 0.9), np.ones(n)])
        y = x @ truth + _ar1(rng, n, 0.8)
        for kind in covered:
            est = least_squares(x, y, ("a(1)", "b(1)"), method="t", equations="t", n_samples=n, sigma=kind)
            covered[kind] += int(np.sum(np.abs(est.values - truth) <= 2 * est.sigma))
    assert covered["white"] / (2 * runs) < 0.6, covered
    assert covered["hac"] / (2 * runs) >= 0.85, covered


def test_a_hac_lag_spanning_much_of_a_short_record_flags_every_sigma_as_unreliable():
    """The HAC lag's floor is the filter's memory (3 cutoff periods: 59 instants at 1.6 Hz, 938 at
    a --cutoff-hz of 0.1); on a record of a few times that many instants Newey-West's σ is about
    half the true one even with white residuals (coverage of ±2σ ~60 %), and a real campaign
    (paper-0 at --cutoff-hz 0.1: lag 938 of 1809 instants) reported k with 4 % σ that was 5σ from
    the 1.6 Hz fit, and used it. Such an estimate must say its σ cannot be trusted."""
    rng = np.random.default_rng(23)
    n, truth, runs = 100, np.array([2.0, -1.0]), 60
    covered = 0
    for _ in range(runs):
        x = np.column_stack([np.sin(np.linspace(0, 2 * np.pi, n)) + 0.3 * rng.standard_normal(n), np.ones(n)])
        y = x @ truth + rng.standard_normal(n)
        est = least_squares(x, y, ("k(1)", "b(1)"), method="t", equations="t", n_samples=n, min_lag=59)
        covered += int(np.sum(np.abs(est.values - truth) <= 2 * est.sigma))
        assert est.hac_lag == 59 and est.sigma_unreliable
        assert est.badly_identified.all() and all("σ unreliable" in est.reason(i) for i in range(2))
    assert covered / (2 * runs) < 0.8, covered  # why: the σ is too small
    long = least_squares(np.column_stack([np.sin(np.linspace(0, 20, 1000)), np.ones(1000)]),
                         rng.standard_normal(1000), ("k(1)", "b(1)"), method="t", equations="t", n_samples=1000,
                         min_lag=59)
    assert not long.sigma_unreliable and "σ unreliable" not in long.reason(0)


def test_bounded_solution_holds_a_damping_at_zero_and_says_so():
    rng = np.random.default_rng(3)
    n = 300
    x = rng.standard_normal(n)
    x_dot = rng.standard_normal(n)
    y = 5000.0 * x - 80.0 * x_dot + rng.standard_normal(n)  # the data want a negative damping
    names = ("k(1)", "c_a(1)")
    W = np.column_stack([x, x_dot])
    free = least_squares(W, y, names, method="t", equations="t", n_samples=n)
    bounded = least_squares(W, y, names, method="t", equations="t", n_samples=n, bounds=physical_bounds(names))
    assert free.values[1] < 0 and free.active_bounds == ()
    assert bounded.values[1] == pytest.approx(0.0, abs=1e-6) and bounded.values[0] == pytest.approx(5000.0, rel=0.01)
    assert bounded.active_bounds == ("c_a(1)",)
    assert bounded.badly_identified.tolist() == [False, True]
    assert "bound" in bounded.reason(1) and bounded.rows()[1]["at_bound"]
    lo, hi = physical_bounds(("k(1)", "lambda(1)", "f_s(1)", "c_a(1)", "other"))
    assert lo[0] > 0 and lo[2] > 0 and lo[1] == 0 and lo[3] == 0 and lo[4] == -np.inf and np.all(hi == np.inf)


def test_wls_weights_the_noisy_group_down():
    """Two groups of equations for one parameter, one 20x noisier: WLS is closer and surer."""
    rng = np.random.default_rng(4)
    n = 200
    x = rng.uniform(1, 2, 2 * n)
    noise = np.r_[0.05 * rng.standard_normal(n), 1.0 * rng.standard_normal(n)]
    y = 3.0 * x + noise
    groups = np.r_[np.zeros(n, dtype=np.int64), np.ones(n, dtype=np.int64)]
    args: dict[str, Any] = dict(method="t", equations="t", n_samples=2 * n, groups=groups)
    ols = least_squares(x[:, None], y, ("a(1)",), estimator="ols", **args)
    wls = least_squares(x[:, None], y, ("a(1)",), estimator="wls", **args)
    assert wls.sigma[0] < 0.3 * ols.sigma[0]
    assert abs(wls.values[0] - 3.0) < 3 * wls.sigma[0]
    assert wls.estimator == "weighted least squares" and ols.estimator == "ordinary least squares"
    with pytest.raises(ValueError, match="estimator"):
        least_squares(x[:, None], y, ("a(1)",), estimator="magic", **args)


# --- on the twin -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def campaign():
    data, truth = simulate_campaign(DYNAMICS_SEED)
    return data, truth


@pytest.fixture(scope="module")
def params():
    return load_params()


def _redraw_camera(data: CampaignData, alpha_true: np.ndarray, seed: int, params) -> CampaignData:
    """The same motion seen by another camera seed: α at each capture + white noise (twin.sim.sensors.Camera)."""
    rng = np.random.default_rng(seed)
    at_capture = np.column_stack([np.interp(data.t_ip_s, data.t_s, alpha_true[:, i]) for i in range(data.n_joints)])
    noisy = at_capture + rng.normal(0.0, math.radians(params.sensors.camera_noise_deg), at_capture.shape)
    return CampaignData(data.t_s, data.theta_rad, data.force_N, data.t_ip_s, noisy, campaign=f"noise{seed}",
                        excitation_alpha_rad=data.excitation_alpha_rad)


def test_simulated_instruments_see_neither_the_camera_nor_the_forces(campaign, params):
    """IDIM-IV's instruments come from the model on the encoders: another camera draw and force
    errors (here +5 % and an offset) leave them unchanged; they follow the true stretch."""
    data, truth = campaign
    proc = preprocess(data, params)
    other = preprocess(_redraw_camera(data, truth["alpha"], 999, params), params)
    skewed = preprocess(CampaignData(data.t_s, data.theta_rad, 1.05 * data.force_N + 2.0, data.t_ip_s,
                                     data.alpha_ip_rad, excitation_alpha_rad=data.excitation_alpha_rad), params)
    m = build(params, "variable")
    k, lam = np.array(params.cables.variable.k), np.array(params.cables.variable.lam)
    ref = simulated_stretch(m, proc, k, lam)
    for p in (other, skewed):
        np.testing.assert_allclose(simulated_stretch(m, p, k, lam).x, ref.x, atol=1e-8)
    assert not np.allclose(other.x_c, proc.x_c, atol=1e-5)  # the regressor itself does change



def test_equilibrium_from_carried_jacobians_is_the_fresh_solves_root(campaign, params):
    """The re-simulation's chord steps (Jacobians kept while steps shrink, carried to the next IV
    iteration) land on the root a fresh solve finds; a carried Jacobian of the wrong shape, with a
    NaN, or far off (here 100 times too large) costs steps, not the root."""
    data, _ = campaign
    proc = preprocess(data, params)
    m = build(params, "variable")
    k, lam = np.array(params.cables.variable.k), np.array(params.cables.variable.lam)
    near = simulated_stretch(m, proc, 1.02 * k, 0.97 * lam)  # the previous IV iteration's (k, λ)
    fresh = simulated_stretch(m, proc, k, lam)
    assert near.jacobian is not None and near.jacobian.shape == (proc.n, m.n_joints, m.n_joints)
    bad_nan = near.jacobian.copy()
    bad_nan[3, 0, 0] = np.nan
    for jac in (near.jacobian, 100.0 * near.jacobian, bad_nan, near.jacobian[:-1]):
        carried = simulated_stretch(m, proc, k, lam, near.alpha, jac)
        np.testing.assert_allclose(carried.alpha, fresh.alpha, atol=1e-6)
        np.testing.assert_allclose(carried.x, fresh.x, atol=1e-8)

def test_intervals_cover_the_truth_over_camera_seeds(campaign, params):
    """Issue 17's target on the twin: the ±2σ intervals of Table 2's k and λ cover the truth in at
    least 85 % of cases (8 parameters × 10 camera seeds), and every k and λ is within 10 %.
    (Before the tension rows dropped motors slower than 1/c_s: 66/80 covered, cable 3's σ too small.)"""
    data, truth = campaign
    k_true, lam_true = np.array(params.cables.variable.k), np.array(params.cables.variable.lam)
    covered, cases, worst = 0, 0, 0.0
    for seed in NOISE_SEEDS:
        proc = preprocess(_redraw_camera(data, truth["alpha"], seed, params), params)
        var = identify_variable(proc, params, identify_friction(proc, params).values)
        assert "simulated model" in var.estimator and var.sigma_method.startswith("HAC")
        for symbol, true in (("k", k_true), ("lambda", lam_true)):
            idx = [i for i, n in enumerate(var.names) if n.startswith(symbol + "(")]
            covered += int(np.sum((var.ci_low[idx] <= true) & (true <= var.ci_high[idx])))
            cases += len(idx)
            worst = max(worst, float(np.max(np.abs(var.values[idx] / true - 1))))
    assert covered / cases >= 0.85, f"{covered}/{cases} covered"
    assert worst < 0.10, worst
