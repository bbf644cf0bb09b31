"""Cross-validation (issue 17): `xneck identify A.mcap --validate B.mcap` fits on A and reports
Figs. 4-8 and the tension/α̂ errors on B beside A's in-sample ones, as text and JSON."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from test_identification import _messages_of

from bridge import archive, bus
from controller.identification_loop import simulate_campaign
from controller.trajectory import identification_trajectory

DURATION_S = 13.0  # the shortest record the pipeline identifies: a move out, back and through


def _write(path, data, trajectory_json: str) -> None:
    archive.write_campaign(path, _messages_of(data), {"campaign_id": path.stem, "kind": "identification",
                                        "trajectory": trajectory_json})


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory):
    """Two short twin campaigns (the identification closed loop, controller/identification_loop.py; real MCAP
    files): A with seed 0, B with seed 1 (other sensor noise, so other data)."""
    d = tmp_path_factory.mktemp("cv")
    traj = identification_trajectory().to_json()
    a, _ = simulate_campaign(0, duration_s=DURATION_S)
    b, _ = simulate_campaign(1, duration_s=DURATION_S)
    _write(d / "A.mcap", a, traj)
    _write(d / "B.mcap", b, traj)
    return d / "A.mcap", d / "B.mcap"


def test_validate_prints_in_sample_and_out_of_sample_columns(campaigns, tmp_path):
    from typer.testing import CliRunner

    from server.cli import app

    a, b = campaigns
    # The command in this process (typer's runner: the same code, without re-importing numpy and
    # numba); without α̂ (Fig. 8, a 500 Hz estimator loop per cable model), the costly part.
    r = CliRunner().invoke(app, ["identify", str(a), "--validate", str(b), "--no-alpha-hat", "--out",
                                 str(tmp_path / "id")])
    assert r.exit_code == 0, r.output
    text = r.stdout
    assert "Cross-validation: fitted on A, validated on B" in text
    assert re.search(r"in-sample \(A\)\s+on B", text)
    rows = {}
    for line in text.splitlines():
        m = re.match(r"(.+?)\s+(-?\d+\.\d{3})\s+(-?\d+\.\d{3})$", line)
        if m:
            rows[m.group(1).strip()] = (float(m.group(2)), float(m.group(3)))
    for name in ("torque |Γ_m − Γ_rf| (N·m), eqs. 51-53", "tension (linear cables, eq. 42) (N)",
                 "tension (variable cables, eq. 42) (N)"):
        assert name in rows, (name, text)
        a_err, b_err = rows[name]
        assert np.isfinite(a_err) and np.isfinite(b_err) and a_err > 0 and b_err > 0
        # out of sample on a campaign of the same kind: the same order, not a broken prediction
        assert b_err < 5 * a_err + 1.0, (name, a_err, b_err)
    # A different noise realisation: B's errors are its own, not A's printed twice
    assert any(abs(x - y) > 1e-3 for x, y in rows.values())
    figs = sorted(p.name for p in (tmp_path / "id" / "validation").glob("*.png"))
    assert "fig4_torques.png" in figs and "fig7_tension_variable.png" in figs
    assert "is the identified campaign" not in r.stderr


def test_validating_on_the_identified_campaign_itself_is_said(campaigns, tmp_path):
    """Audit of session 49: --validate A (or a copy of A) printed its in-sample errors as "on B"
    without a word. Said, naming the campaign; the run goes on (it still shows the figures)."""
    import shutil

    from typer.testing import CliRunner

    from server.cli import app

    a, _ = campaigns
    copy = shutil.copy(a, tmp_path / "copy.mcap")
    for n, other in enumerate((a, copy)):
        r = CliRunner().invoke(app, ["identify", str(a), "--validate", str(other), "--no-alpha-hat", "--out",
                                     str(tmp_path / f"id{n}")])
        assert r.exit_code == 0, r.output
        assert f"warning: validation campaign {other} is the identified campaign (A)" in r.stderr, r.stderr


@pytest.fixture(scope="module")
def fit_a(campaigns, params):
    from controller.trajectory import recorded_excitation
    from twin.identification.record import identify_record

    return identify_record(campaigns[0], params, excitation=recorded_excitation, alpha_hat=False)


def test_out_of_sample_uses_the_models_fitted_on_a(campaigns, fit_a):
    """A's models on A itself reproduce A's in-sample figures exactly (same fits, same data); on B
    they give B's own errors; the JSON summary carries both columns."""
    from controller.trajectory import recorded_excitation
    from twin.identification.validation import cross_validate, load_validation_campaign, out_of_sample, summary

    assert fit_a.validation is not None
    same = out_of_sample(fit_a, fit_a.data, fit_a.processed, alpha_hat=False)
    for model in ("linear", "variable"):
        assert same.tension_error[model] == pytest.approx(fit_a.validation.tension_error[model], rel=1e-9)
    assert same.gamma_rf_error == pytest.approx(fit_a.validation.gamma_rf_error, rel=1e-9)
    cv = cross_validate(fit_a, load_validation_campaign(campaigns[1], recorded_excitation), alpha_hat=False)
    doc = json.loads(json.dumps(summary(cv)))  # JSON-ready
    assert doc["fitted_on"] == "A" and doc["validated_on"] == "B"
    tension = doc["errors"]["tension (variable cables, eq. 42) (N)"]
    assert tension["in_sample"] == pytest.approx(fit_a.validation.tension_error["variable"])
    assert tension["out_of_sample"] == pytest.approx(cv.validation.tension_error["variable"])
    assert tension["out_of_sample"] != pytest.approx(tension["in_sample"], rel=1e-6)
    assert doc["validation_processing"]["cutoff_hz"] > 0


def test_a_bad_validation_campaign_is_a_clear_error(campaigns, fit_a, tmp_path):
    from typer.testing import CliRunner

    from server.cli import app
    from twin.identification.pipeline import IdentificationError
    from twin.identification.validation import cross_validate, load_validation_campaign

    a, _ = campaigns
    # checked before A is fitted: the command fails at once, with B's name and the reason
    r = CliRunner().invoke(app, ["identify", str(a), "--validate", str(tmp_path / "missing.mcap"), "--out",
                                 str(tmp_path / "m")])
    assert r.exit_code == 2, r.output
    assert "validation campaign" in r.stderr and "missing.mcap" in r.stderr
    assert r.exception is None or isinstance(r.exception, SystemExit)  # a message, not a traceback
    assert not (tmp_path / "m").exists()
    motor_only = tmp_path / "motor_only.mcap"
    archive.write_campaign(motor_only, [(bus.MOTOR_STATE, 1, bus.MotorState(
        seq=0, stamp_s=0.0, theta_rad=[0.0] * 4, force_applied_N=[10.0] * 4, drive="active", epoch="e", bridge="b"))],
        {"campaign_id": "m"})
    with pytest.raises(IdentificationError, match=r"validation campaign .*motor_only.*missing channel.*camera"):
        load_validation_campaign(motor_only)
    # a campaign of another robot (two joints) is refused by name, not a broadcast error
    other = fit_a.data
    from twin.identification.pipeline import CampaignData

    two = CampaignData(other.t_s, other.theta_rad[:, :3], other.force_N[:, :3], other.t_ip_s, other.alpha_ip_rad[:, :2],
                       campaign="two-joints")
    with pytest.raises(IdentificationError, match="validation campaign two-joints: campaign has 3 motors"):
        cross_validate(fit_a, two, alpha_hat=False)
    # and by the command before A is fitted (audit of 2026-11-27): three motors were refused only
    # after A's fit and files, two joints as "excitation_alpha_rad must have shape (T, 2)"
    three = CampaignData(other.t_s, other.theta_rad[:, :3], other.force_N[:, :3], other.t_ip_s, other.alpha_ip_rad,
                         campaign="three-motors")
    for name, data, said in (("three.mcap", three, "its record has 3 motors, the parameter set 'prototype-3x' 4: "
                              "it is another robot's campaign"),
                             ("two.mcap", two, "the recorded trajectory moves 3 joints and the camera measures 2")):
        _write(tmp_path / name, data, identification_trajectory().to_json())
        r = CliRunner().invoke(app, ["identify", str(a), "--validate", str(tmp_path / name), "--out", str(tmp_path / "t")])
        assert r.exit_code == 2, r.output
        assert said in r.stderr, r.stderr
        assert not (tmp_path / "t").exists()


def test_a_bad_creep_time_is_a_clear_error_and_writes_nothing(campaigns, tmp_path):
    from typer.testing import CliRunner

    from server.cli import app

    a, _ = campaigns
    r = CliRunner().invoke(app, ["identify", str(a), "--creep-time-s", "-1", "--no-alpha-hat", "--out",
                                 str(tmp_path / "c")])
    assert r.exit_code == 2, r.output
    assert "creep time constant must be a positive number of seconds" in r.stderr
    assert r.exception is None or isinstance(r.exception, SystemExit)
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("override, said", [("motors.gear_loss_forward=0.6", "gear_loss_forward must be in [0, 0.5)"),
                                            ("motors.gear_loss_backward", "must look like key.path=value")])
def test_a_bad_parameter_override_is_a_clear_error_and_writes_nothing(campaigns, tmp_path, override, said):
    """``xneck identify --set`` changes the base parameter set as campaigns' ``--set`` does (the gear's
    loss the load-friction fit holds, for one); a value the parameter checks refuse is said."""
    from typer.testing import CliRunner

    from server.cli import app

    a, _ = campaigns
    r = CliRunner().invoke(app, ["identify", str(a), "--set", override, "--no-alpha-hat", "--out", str(tmp_path / "c")])
    assert r.exit_code == 2, r.output
    assert said in r.stderr, r.stderr
    assert not (tmp_path / "c").exists()


def test_torques_are_reported_in_newton_metres_not_a_stiffnesss_unit() -> None:
    """Audit of 2026-11-29: the torque errors |Γ_m − Γ_rf|, |Γ_m − Γ_r| (generalised forces
    conjugate to α in rad, N·m as twin.model.dynamics states) were labelled N·m/rad, a stiffness's unit."""
    import inspect

    from twin.identification import report, validation

    names = [name for name, _ in validation._ROWS]
    assert all("(N·m)" in n and "N·m/rad" not in n for n in names), names
    assert "N·m/rad" not in inspect.getsource(report), "report.py labels a torque N·m/rad"
