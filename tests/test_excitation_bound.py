"""The least σ any excitation could give k and λ (issue 17's target): Elfving's c-optimal bound on
the design model, and `xneck excitation bound`, which says whether a σ ratio target is reachable."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import optimize

from controller.trajectory import identification_trajectory, load_trajectory
from server.cli import app
from server.cli.excitation import _problem
from twin.identification.excitation import MIN_TENSION_N, REST_S, design, score
from twin.identification.excitation_bound import c_optimal, rows, sigma_bound

# Computation only, in this process and its `xneck` runs: it runs beside the realtime modules at
# nice 19 (tests/conftest.py), in the CPU they leave.
pytestmark = pytest.mark.background

DOCS = Path(__file__).resolve().parents[1] / "docs" / "identification"


@pytest.fixture
def cli():
    from typer.testing import CliRunner

    return CliRunner()


def _mixture_min(r: np.ndarray, c: np.ndarray) -> float:
    """min cᵀF⁻¹c over mixtures of the columns of r, by a general optimiser (softmax weights):
    what Elfving's closed form must equal."""
    def f(u: np.ndarray) -> float:
        w = np.exp(u - u.max())
        w /= w.sum()
        F = (r * w) @ r.T
        try:
            return float(c @ np.linalg.solve(F, c))
        except np.linalg.LinAlgError:
            return 1e30
    starts = [np.zeros(r.shape[1])] + [np.random.default_rng(s).normal(size=r.shape[1]) for s in range(6)]
    return min(optimize.minimize(f, u0, method="Nelder-Mead",
                                 options={"xatol": 1e-10, "fatol": 1e-14, "maxiter": 20000}).fun for u0 in starts)


@pytest.mark.parametrize("c", [(1.0, 0.0), (0.0, 1.0), (1.0, -2.0)])
def test_elfvings_two_point_design_is_the_least_variance_over_all_mixtures(c):
    t = np.array([3.0, 12.0, 30.0, 55.0, 90.0])
    r = rows(5364.0, 88.7, t)
    b = c_optimal(r, c, t)
    assert b.variance == pytest.approx(_mixture_min(r, np.asarray(c)), rel=1e-4)
    # its own support and weights give that variance
    i, j = (list(t).index(x) for x in b.tensions_N)
    F = b.weights[0] * np.outer(r[:, i], r[:, i]) + b.weights[1] * np.outer(r[:, j], r[:, j])
    assert float(np.asarray(c) @ np.linalg.solve(F, c)) == pytest.approx(b.variance, rel=1e-9)


def test_the_k_row_peaks_where_the_cable_is_pulled_to_k_over_lambda():
    k, lam = 1908.0, 120.9
    t = np.linspace(1.0, 100.0, 9901)
    assert t[np.argmax(rows(k, lam, t)[0])] == pytest.approx(k / lam, abs=0.02)
    assert np.all(np.diff(rows(k, lam, t)[1]) > 0)  # λ's entry only grows with the tension


def test_no_trajectory_beats_the_bound(params):
    """The bound is below the design model's σ of the cycloids, of the documented designs and of a
    fresh design with a pretension, which tries hardest to spread the tensions."""
    p = _problem(params, 20.0, 0.6, box_deg="50", pretension_max_N=40.0)
    fresh = design(p, seed=4, starts=1, maxiter=4)
    p97 = _problem(params, 97.0, 0.6)
    paper = identification_trajectory()
    scored = [score(p97, paper.waypoints_rad, paper.durations_s, paper.dwell_s), fresh.score]
    for name in ("excitation", "pretension", "holdfree"):
        traj = load_trajectory(DOCS / f"{name}.json")
        scored.append(score(p97, traj.waypoints_rad, traj.durations_s, traj.dwell_s,
                            traj.pretension_N if traj.has_pretension else None))
    for s in scored:
        b = sigma_bound(p97.k, p97.lam, t_min_N=MIN_TENSION_N, t_max_N=params.limits.f_max,
                        moving_fraction=(s.duration_s - 2 * REST_S) / s.duration_s).relative_sigma()
        for name, least in b.items():
            assert s.relative_sigma[name] >= least, (name, s.duration_s)


def test_a_wider_tension_range_or_more_moving_time_lowers_the_bound():
    k, lam = [5378.0, 1908.0], [103.3, 120.9]
    base = sigma_bound(k, lam, t_min_N=2.0, t_max_N=100.0, moving_fraction=0.5)
    wider = sigma_bound(k, lam, t_min_N=2.0, t_max_N=150.0, moving_fraction=0.5)
    longer = sigma_bound(k, lam, t_min_N=2.0, t_max_N=100.0, moving_fraction=1.0)
    assert np.all(wider.k < base.k) and np.all(wider.lam < base.lam)
    np.testing.assert_allclose(longer.k, base.k / math.sqrt(2.0))


@pytest.mark.parametrize("kwargs, message", [
    (dict(k=[1.0, -2.0], lam=[1.0, 1.0], t_min_N=2, t_max_N=100, moving_fraction=1), "k must be positive"),
    (dict(k=[1.0], lam=[1.0], t_min_N=50, t_max_N=20, moving_fraction=1), "t_min < t_max"),
    (dict(k=[1.0], lam=[1.0], t_min_N=2, t_max_N=100, moving_fraction=0), "moving fraction"),
])
def test_bad_bound_requests_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        sigma_bound(**kwargs)


def test_cli_says_halving_every_sigma_at_the_paper_duration_is_out_of_reach(xneck):
    """Issue 17's target (σ of every k and λ halved against the 4×6 cycloids, 97 s): the design
    model allows no excitation to halve σ of k(2), even with every cable at any tension at every
    instant; a longer record, or a lower target, is reachable."""
    r = xneck("excitation", "bound", "--trajectory", str(DOCS / "excitation.json"), "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["duration_s"] == 97.0 and rep["target_ratio"] == 0.5
    k2 = rep["parameters"]["k(2)"]
    assert not k2["reachable"] and k2["bound_ratio"] > 0.5 and k2["shortest_duration_s"] > 97.0
    assert rep["reachable_all"] is False
    assert all(0 < p["bound_ratio"] < 1 for p in rep["parameters"].values())
    # the documented design is scored beside the bound, never below it
    designed = rep["trajectories_predicted_ratio"][str(DOCS / "excitation.json")]
    assert all(designed[n] >= p["bound_ratio"] for n, p in rep["parameters"].items())
    # the record the bound names for k(2) is enough, on the bound
    longer = xneck("excitation", "bound", "--duration", f"{k2['shortest_duration_s'] + 1:.1f}", "--json")
    assert json.loads(longer.stdout)["parameters"]["k(2)"]["reachable"]
    text = xneck("excitation", "bound", "--target", "0.6")
    assert text.returncode == 0 and "reachable on the design model" in text.stdout


@pytest.mark.parametrize("args, message", [
    (["--duration", "1.5"], "--duration must be"),
    (["--target", "-1"], "--target must be"),
    (["--t-max", "1"], "--t-max must be"),
    (["--t-max", "1e308"], "--t-max must be"),
    (["--trajectory", "nope.json"], "cannot read the trajectory file"),
])
def test_bad_cli_requests_are_refused_clearly(cli, args, message):
    r = cli.invoke(app, ["excitation", "bound", *args])
    assert r.exit_code == 2
    assert message in r.output
