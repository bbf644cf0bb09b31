"""Excitation design (issue 17): `xneck excitation design` optimises cycloids within the limits and
beats the §5.2.2 cycloids on its criterion; the file it writes is a campaign's trajectory."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from controller.laws import nominal_force_check
from controller.trajectory import Trajectory, TrajectoryLimits, identification_trajectory, load_trajectory, validate
from server.cli import app
from server.cli.excitation import _problem
from twin.identification.excitation import DesignError, design, score

# Computation only, in this process and its `xneck` runs: it runs beside the realtime modules at
# nice 19 (tests/conftest.py), in the CPU they leave.
pytestmark = pytest.mark.background


@pytest.fixture
def cli():
    """The `xneck` app in this process (typer's runner): the commands' own argument checks."""
    from typer.testing import CliRunner

    return CliRunner()


@pytest.fixture(scope="module")
def problem(params):
    # a ±50° box: room to beat the cycloids at 20 s in a few iterations (in the default box, the
    # §5.2.2 amplitudes, the cycloids already sit on the box's corners and the gain is small)
    return _problem(params, 20.0, 0.6, box_deg="50")


@pytest.fixture(scope="module")
def designed(problem):
    return design(problem, seed=1, starts=1, maxiter=6)


def test_design_respects_the_limits(designed, problem, params):
    from server.cli.options import law_config

    traj = Trajectory(designed.waypoints_rad, designed.durations_s, designed.dwell_s, "designed")
    assert traj.duration_s == pytest.approx(20.0, abs=1e-6)
    np.testing.assert_allclose(traj.waypoints_rad[[0, -1]], 0.0)  # starts and ends straight, at rest
    assert np.all(np.abs(np.degrees(traj.waypoints_rad)) <= 50.0 + 1e-9)  # within the asked box
    # the campaign's own checks, independently of the design's: joints, speed, acceleration, forces
    limits = TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg))
    validate(traj, limits, params.n_joints, nominal_force_check(params, law_config(1, False)))
    # the moves use at most the asked fraction (0.6) of the speed and acceleration limits
    assert np.all(traj.segment_peak_velocity() <= 0.6 * 1.5 * (1 + 1e-5))
    assert np.all(traj.segment_peak_acceleration() <= 0.6 * 3.0 * (1 + 1e-5))
    assert designed.score.penalty == 0.0


def test_design_beats_the_paper_cycloids_on_the_criterion(designed, problem):
    paper = identification_trajectory()
    base = score(problem, paper.waypoints_rad, paper.durations_s, paper.dwell_s)
    d = designed.score
    # D-optimality per second of record: at least e ≈ 2.7 times the information volume (the
    # variable rows of still motors count for nothing, as in the identification)
    assert d.log_det > base.log_det + 1.0, (d, base)
    assert d.log_det_variable > base.log_det_variable
    # predicted relative σ at the same duration: lower on the whole for k and λ. Not each one: a
    # k's information comes from turning motors at low tension, where the cycloids already spend
    # their moves (docs/identification.md, "How far a design goes as the limits are opened")
    ratio = {n: d.relative_sigma[n] / base.relative_sigma[n] for n in base.relative_sigma}
    assert np.prod([ratio[f"{s}({j})"] for s in ("k", "lambda") for j in range(1, 5)]) < 0.8, ratio


def test_a_design_started_from_a_trajectory_is_at_least_as_good_on_the_criterion(problem):
    """``start``: the CLI starts from the §5.2.2 cycloids, so its design never loses to them."""
    from twin.identification.excitation import _timing

    w0 = np.radians([[0, 0, 0], [40, 30, 20], [-40, -30, -20], [40, -30, 20], [-40, 30, -20], [0, 0, 0]])
    d = design(problem, seed=5, starts=0, maxiter=3, start=w0)
    durations, dwell, _ = _timing(problem, w0)
    assert d.score.log_det >= score(problem, w0, durations, dwell).log_det
    with pytest.raises(DesignError, match="starting design has shape"):
        design(problem, seed=5, starts=0, maxiter=1, start=w0[:4])


def test_holds_none_stretches_the_moves_and_fill_keeps_the_stops(params):
    w = np.radians([[0, 0, 0], [30, 20, 10], [-30, -20, -10], [0, 0, 0]])
    from twin.identification.excitation import _timing

    stretched = _problem(params, 20.0, 0.6)
    durations, dwell, overrun = _timing(stretched, w)
    assert overrun == 0.0 and np.all(dwell[1:-1] == 0.0) and durations.sum() + dwell.sum() == pytest.approx(20.0)
    stops = _problem(params, 20.0, 0.6, holds="fill")
    short, held, _ = _timing(stops, w)
    assert np.all(held[1:-1] > 0.0) and np.all(short < durations)
    assert short.sum() + held.sum() == pytest.approx(20.0)


def test_a_force_limit_is_a_penalty_the_design_avoids(params):
    """With f_max lowered, poses that need large forces are out: the design must stay feasible
    (penalty 0, validation passed) rather than return the unconstrained optimum."""
    from twin.model.params import load_params

    low = load_params(overrides={"limits.f_max": 60.0})
    p = _problem(low, 12.0, 0.6)
    d = design(p, seed=2, starts=1, maxiter=3)
    assert d.score.penalty == 0.0
    f, ok = p.forces(*p.path(np.zeros(3), d.waypoints_rad[1], float(d.durations_s[0]), np.linspace(0, d.durations_s[0], 20)))
    assert ok.all() and f.max() <= 60.0


def test_cli_writes_a_file_the_identification_campaign_accepts(xneck, tmp_path, params):
    from server.cli.options import law_config, load_checked_trajectory

    out = tmp_path / "exc.json"
    r = xneck("excitation", "design", "--duration", "12", "--out", str(out), "--starts", "1", "--maxiter", "2",
              "--seed", "3", "--json", timeout=300)
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert report["trajectory_file"] == str(out)
    # progress on stderr (the defaults take minutes; input audit of session 49: none was printed)
    assert "design: start 1 of 1: optimising (2 iterations at most)" in r.stderr, r.stderr
    assert re.search(r"design: start 1 of 1: iteration [12] of at most 2, criterion -?[\d.]", r.stderr), r.stderr
    # a 12 s design after 2 iterations: its criterion is reported beside the cycloids' (the gain
    # itself is test_design_beats_the_paper_cycloids_on_the_criterion's)
    assert math.isfinite(report["designed"]["log_det"]) and math.isfinite(report["paper_4x6_cycloids"]["log_det"])
    assert report["pretension_max_N"] == 0.0 and not any(report["pretension_N"])
    assert "pretension_N" not in json.loads(out.read_text())  # files without one stay as they were
    assert json.loads(out.with_name("exc.design.json").read_text())["seed"] == 3
    # the loader `xneck campaign identification --trajectory FILE` uses, with its validation
    traj = load_checked_trajectory(str(out), params, law_config(1, False))
    assert traj.duration_s == pytest.approx(12.0, abs=1e-6)
    assert load_trajectory(out).name == "excitation-seed3"


def test_a_pretension_design_writes_a_schedule_the_campaign_accepts(cli, tmp_path, params):
    """--pretension-max: each inner waypoint also gets a floor raise in [0, bound], 0 at both ends;
    the file carries it and passes the campaign's validation (pretension rate and law 1's forces
    with the raised floor)."""
    from server.cli.options import law_config, load_checked_trajectory

    out = tmp_path / "pre.json"
    r = cli.invoke(app, ["excitation", "design", "--duration", "14", "--out", str(out), "--starts", "1",
                         "--maxiter", "2", "--seed", "4", "--pretension-max", "30"])
    assert r.exit_code == 0, r.output
    P = np.asarray(json.loads(out.read_text())["pretension_N"])
    assert P[0] == 0.0 and P[-1] == 0.0 and P.max() > 0.0 and P.max() <= 30.0 + 1e-9
    traj = load_checked_trajectory(str(out), params, law_config(1, False))
    np.testing.assert_allclose(traj.pretension_N, P)
    assert "pretension: 0 …" in r.output
    r = cli.invoke(app, ["excitation", "design", "--out", str(tmp_path / "x.json"), "--pretension-max", "150"])
    assert r.exit_code == 2 and "pretension bound" in r.stderr


@pytest.mark.parametrize(("args", "message"), [
    (("--duration", "2"), "duration must be"),
    (("--duration", "nan"), "duration must be"),
    (("--speed", "1.5"), "speed is a fraction"),
    (("--waypoints", "2"), "at least 3"),
    (("--criterion", "e"), "criterion must be d"),
    # one value is every joint's (docs/identification.md runs --box-deg 55): the message says so (input audit)
    (("--box-deg", "40,70,20"), "--box-deg needs one amplitude for every joint or 3, one per joint"),
    (("--box-deg", "40,30"), "--box-deg needs one amplitude for every joint or 3, one per joint"),
    (("--box-deg", "forty"), "--box-deg must be numbers"),
    (("--holds", "some"), "holds must be none"),
    # beyond what one campaign runs: they optimised for hours (audit of 2026-11-27)
    (("--duration", "1e9"), "a campaign runs at most 600 s"),
    (("--waypoints", "1000000"), "--waypoints 1000000: at most 98 in 97 s"),
])
def test_bad_design_requests_are_refused_clearly(cli, tmp_path, args, message):
    r = cli.invoke(app, ["excitation", "design", "--out", str(tmp_path / "x.json"), *args])
    assert r.exit_code == 2, r.output
    assert message in r.stderr
    assert r.exception is None or isinstance(r.exception, SystemExit)  # a message, not a traceback
    assert not (tmp_path / "x.json").exists()


@pytest.mark.parametrize("existing", ["x.json", "x.design.json"])
def test_an_existing_design_or_its_scores_are_refused_unless_force(cli, tmp_path, existing):
    """Input audit: `excitation design --out FILE` replaced FILE and <stem>.design.json without a
    word, where identify, campaign --out and twin calibrate refuse an existing output."""
    (tmp_path / existing).write_text("earlier\n")
    args = ["excitation", "design", "--out", str(tmp_path / "x.json"), "--duration", "12", "--starts", "1",
            "--maxiter", "0"]
    r = cli.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert r.stderr.count("error:") == 1 and f"{tmp_path / existing} exists" in r.stderr and "--force" in r.stderr
    assert (tmp_path / existing).read_text() == "earlier\n"
    r = cli.invoke(app, [*args, "--force"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "x.json").read_text())["waypoints_deg"]
    assert json.loads((tmp_path / "x.design.json").read_text())["trajectory_file"] == str(tmp_path / "x.json")


def test_the_default_box_is_the_paper_amplitudes(params):
    p = _problem(params, 12.0, 0.6)
    np.testing.assert_allclose(np.degrees(p.alpha_max), [40.0, 30.0, 20.0])


def test_a_trajectory_file_out_of_limits_is_refused_before_anything_runs(cli, tmp_path):
    bad = tmp_path / "fast.json"
    bad.write_text(json.dumps({"waypoints_deg": [[0, 0, 0], [55, 0, 0], [0, 0, 0]], "durations_s": 0.5}))
    r = cli.invoke(app, ["campaign", "identification", "--trajectory", str(bad), "--out", str(tmp_path / "c.mcap")])
    assert r.exit_code == 2, r.output
    assert "trajectory rejected" in r.stderr and "too fast" in r.stderr
    assert not (tmp_path / "c.mcap").exists()


def test_design_problem_refuses_impossible_limits(params):
    with pytest.raises(DesignError, match="v_max"):
        from twin.identification.excitation import DesignProblem

        DesignProblem.create(params, duration_s=20.0, alpha_max_rad=1.0, v_max_rad_s=0.0, a_max_rad_s2=1.0,
                             path=lambda *a: a, forces=lambda *a: a)


@pytest.mark.parametrize("name", ["excitation.json", "holdfree.json", "pretension.json", "taut10.json"])
def test_the_documented_excitations_pass_the_campaign_validation(params, name):
    """The trajectory files docs/identification*.md measure (docs/identification/) still pass what
    `xneck campaign identification --trajectory FILE` checks: joint, speed, acceleration and law 1's
    forces. The hold-free one keeps the joints moving between its two 1 s rests (no holds)."""
    from pathlib import Path

    from server.cli.options import law_config

    path = Path(__file__).resolve().parents[1] / "docs" / "identification" / name
    traj = load_trajectory(path)
    limits = TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg))
    validate(traj, limits, params.n_joints, nominal_force_check(params, law_config(1, False)))
    assert traj.duration_s == pytest.approx(97.0, abs=0.5)  # the §5.2.2 duration: comparisons are per equal time
    if name == "holdfree.json":
        assert np.all(traj.dwell_s[1:-1] == 0.0) and np.all(traj.dwell_s[[0, -1]] == 1.0)
