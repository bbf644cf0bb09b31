"""Calibrating a truth on recorded campaigns (issue 16, twin/sim/calibrate.py, `xneck twin calibrate`):
the calibrator recovers values injected into a twin's truth from its recordings, writes a truth
file that `--truth FILE` loads back with its provenance, and refuses bad recordings by name.

The recordings are real MCAP files written as the lockstep bridge writes them (state k: the
stamp and encoder angles after tick k, the force applied during it), from the law running
in process against the twin: the same loop as `xneck campaign control --twin`, seconds instead
of minutes.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from bridge import bus
from bridge.archive import write_campaign
from controller.laws import ComputedTorque, LawConfig
from controller.trajectory import control_test_trajectory
from twin.model.params import load_params
from twin.sim import calibrate
from twin.sim.simulator import Twin, TwinConfig
from twin.sim.truth import RobotTruth, load_truth

# pure computation, no bus or process: beside the realtime modules at nice 19 (tests/conftest.py)
pytestmark = pytest.mark.background

PARAMS = load_params()
ROBOT = load_truth("robot")


def record(path: Path, truth: RobotTruth, law: int = 2, seconds: float = 4.0, seed: int = 0) -> Path:
    """A campaign MCAP of ``law`` on the §7 test's first ``seconds`` against a twin of ``truth``."""
    twin = Twin(PARAMS, TwinConfig(truth=truth, seed=seed))
    ctl = ComputedTorque(PARAMS, LawConfig(law=law))
    n = int(seconds * 500)
    ref = control_test_trajectory().sample(np.arange(1, n + 1) / 500)
    nc = PARAMS.n_cables

    def state(seq: int, stamp_s: float, theta: list[float], force: list[float]) -> bus.MotorState:
        return bus.MotorState(seq=seq, stamp_s=stamp_s, theta_rad=theta, force_applied_N=force, drive="active",
                              epoch="e1", bridge="twin-test", owner="ctl")

    msgs: list[tuple[str, int, bus.BusMessage]] = [(bus.MOTOR_STATE, 0, state(0, 0.0, [0.0] * nc, [0.0] * nc))]
    theta = np.zeros(nc)
    for k in range(n):
        f = ctl.step(theta, ref.alpha[k], ref.alpha_dot[k], ref.alpha_ddot[k]).f.copy()
        tick = twin.tick(f)
        theta = tick.theta_meas
        t_ns = (k + 1) * 2_000_000
        msgs.append((bus.MOTOR_STATE, t_ns, state(k + 1, tick.t_s, theta.tolist(), f.tolist())))
        msgs.append((bus.TWIN_TRUTH, t_ns, bus.Truth(
            seq=k + 1, stamp_s=tick.t_s, alpha_rad=tick.alpha.tolist(), alpha_dot_rad_s=tick.alpha_dot.tolist(),
            theta_rad=tick.theta.tolist(), theta_dot_rad_s=tick.theta_dot.tolist(), tension_N=tick.tension.tolist(),
            elongation_m=tick.elongation.tolist(), slack=tick.slack.tolist(), near_singular=tick.near_singular)))
        for capture, alpha_ip in tick.frames:
            msgs.append((bus.CAMERA_ALPHA, t_ns, bus.CameraAlpha(seq=k + 1, stamp_s=tick.t_s, capture_stamp_s=capture,
                                                                alpha_ip_rad=alpha_ip.tolist(), source="twin-noise")))
    return write_campaign(path, msgs, {"campaign_id": path.stem, "kind": "control", "law": f"law{law}",
                                       "target": "twin", "twin_truth": truth.name})


# The robot truth with three values changed: what the calibration should find from the base (robot) values.
INJECTED = {"friction.static_ratio": 1.6, "cables.damping_N_s_m": 80.0, "actuation.current_bandwidth_hz": 30.0}
TRUE = (ROBOT.replace("friction", static_ratio=1.6).replace("cables", damping_N_s_m=80.0)
        .replace("actuation", current_bandwidth_hz=30.0))


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[int, Path]:
    where = tmp_path_factory.mktemp("recordings")
    return {law: record(where / f"law{law}.mcap", TRUE, law=law) for law in (1, 2, 3)}


@pytest.fixture(scope="module")
def calibrated(recordings, tmp_path_factory) -> tuple[Path, str]:
    """`xneck twin calibrate` on the law 2 recording, validated on laws 1 and 3 (in process)."""
    from typer.testing import CliRunner

    from server.cli import app

    out = tmp_path_factory.mktemp("truth") / "calibrated.toml"
    args = ["twin", "calibrate", str(recordings[2]), "--out", str(out), *[a for n in INJECTED for a in ("--fit", n)],
            "--validate", str(recordings[1]), "--validate", str(recordings[3])]
    run = CliRunner().invoke(app, args)
    assert run.exit_code == 0, run.output
    return out, run.output


# How close each injected value comes back. From θ and α_IP alone (the default: the twin's tensions
# are not read) the current-loop bandwidth is the least constrained: 26.9 Hz for 30 Hz on 2026-12-01
# (within 10 % while the fit also read the twin's true tensions).
TOLERANCE = {"friction.static_ratio": 0.10, "cables.damping_N_s_m": 0.10, "actuation.current_bandwidth_hz": 0.15}


def test_the_calibration_recovers_injected_truth_values(calibrated):
    """The injected values differ from the base in the fitted values only (and the recording is
    short): a check of the fit's mechanics, not of a calibration against unmodelled effects
    (docs/twin-fidelity.md, "Demonstration", shows that case)."""
    out, output = calibrated
    truth = load_truth(str(out))
    found = {"friction.static_ratio": truth.friction.static_ratio, "cables.damping_N_s_m": truth.cables.damping_N_s_m,
             "actuation.current_bandwidth_hz": truth.actuation.current_bandwidth_hz}
    for name, value in INJECTED.items():
        assert found[name] == pytest.approx(value, rel=TOLERANCE[name]), (name, found[name], output)
    # The robot truth's own values (1.3, 40 N·s/m, 1 kHz) were far from these: it moved there.
    assert abs(ROBOT.cables.damping_N_s_m - 80.0) / 80.0 > 0.4


def test_the_truth_file_keeps_its_provenance_and_the_held_out_prediction_errors(calibrated, recordings):
    out, output = calibrated
    truth = load_truth(str(out))
    cal = truth.calibration
    assert cal is not None and cal.campaigns == ["law2.mcap"] and cal.base == "robot"
    assert set(cal.fitted) == set(INJECTED) == set(cal.sigma) and all(s >= 0 for s in cal.sigma.values())
    assert cal.command.startswith("xneck twin calibrate") or cal.command == ""
    # By default only what a prototype records is fitted: no tensions from the twin's Truth topic.
    assert set(cal.residual_rms) == {"theta_rad", "alpha_ip_deg"}
    assert truth.sources["cables.damping_N_s_m"].startswith("measurement: fitted by xneck twin calibrate to law2.mcap")
    # Values it did not fit stay the robot truth's, with their sources.
    assert truth.friction.pulley_friction_per_N == ROBOT.friction.pulley_friction_per_N
    assert truth.sources["friction.pulley_friction_per_N"] == ROBOT.sources["friction.pulley_friction_per_N"]
    # Held out: laws 1 and 3 are predicted better by the calibrated truth than by the base one,
    # and the camera mismatch falls to its noise (σ = 1°).
    for name in ("law1.mcap", "law3.mcap"):
        errors = cal.validation[name]
        assert errors["theta_rad"] < 0.2 * errors["base_theta_rad"], (name, errors)
        assert errors["alpha_ip_deg"] < 1.2 < errors["base_alpha_ip_deg"], (name, errors)
    assert "held-out predictions" in output and "law3.mcap" in output
    # The file is a truth file like the shipped one: it parses on its own.
    assert tomllib.loads(out.read_text())["calibration"]["campaigns"] == ["law2.mcap"]


def test_a_recording_without_tensions_calibrates_on_encoders_and_camera(recordings, tmp_path):
    """The prototype has no tension sensor: θ and α_IP alone still find the cable damping."""
    from bridge.archive_read import read_campaign

    camp = read_campaign(recordings[2])
    robot_like = tmp_path / "robot_like.mcap"
    write_campaign(robot_like, [(bus.key_of_topic(topic), t, m) for topic, msgs in camp.topics.items()
                                if topic != bus.mcap_topic(bus.TWIN_TRUTH) for t, m in msgs], {"campaign_id": "robot_like"})
    rec = calibrate.load_recording(robot_like, PARAMS)
    assert rec.tension is None and len(rec.t_ip) > 50
    base = TRUE.replace("cables", damping_N_s_m=30.0)
    result = calibrate.fit([rec], PARAMS, base, calibrate.unknowns(["cables.damping_N_s_m"], 4))
    assert result.values[0] == pytest.approx(80.0, rel=0.10)
    assert set(result.residual_rms) == {"theta_rad", "alpha_ip_deg"}


def _tampered(path: Path, out: Path) -> Path:
    """``path`` with its twin Truth topic falsified (tensions doubled plus 5 N, α off by 0.3 rad):
    what a calibration that reads the Truth topic would fit differently."""
    import msgspec

    from bridge.archive_read import read_campaign

    camp = read_campaign(path)
    truth_topic = bus.mcap_topic(bus.TWIN_TRUTH)
    msgs: list[tuple[str, int, bus.BusMessage]] = []
    for topic, items in camp.topics.items():
        for t, m in items:
            if topic == truth_topic:
                assert isinstance(m, bus.Truth)
                m = msgspec.structs.replace(m, tension_N=[2.0 * x + 5.0 for x in m.tension_N],
                                            alpha_rad=[a + 0.3 for a in m.alpha_rad])
            msgs.append((bus.key_of_topic(topic), t, m))
    return write_campaign(out, msgs, dict(camp.info))


def test_the_calibration_ignores_the_twins_truth_topic_unless_asked(recordings, tmp_path):
    """A prototype's recording has no Truth topic (true tensions, true α): by default the
    calibration must not read it, so a twin recording whose Truth topic was falsified gives the very
    same fit; ``use_twin_truth`` (``--use-twin-truth``) reads it, and then the fit changes."""
    tampered = _tampered(recordings[2], tmp_path / "tampered.mcap")
    fitted = calibrate.unknowns(["cables.damping_N_s_m"], 4)
    base = TRUE.replace("cables", damping_N_s_m=30.0)

    def run(path: Path, use: bool) -> calibrate.Result:
        rec = calibrate.load_recording(path, PARAMS, span_s=2.0, use_twin_truth=use)
        return calibrate.fit([rec], PARAMS, base, fitted, max_evaluations=8, starts=0)

    honest = calibrate.load_recording(recordings[2], PARAMS)
    falsified = calibrate.load_recording(tampered, PARAMS)
    assert honest.tension is None and falsified.tension is None
    np.testing.assert_array_equal(honest.alpha0, falsified.alpha0)
    by_default = run(recordings[2], False), run(tampered, False)
    np.testing.assert_array_equal(by_default[0].values, by_default[1].values)
    assert by_default[0].cost == by_default[1].cost
    assert set(by_default[1].residual_rms) == {"theta_rad", "alpha_ip_deg"}
    # Asked for, the Truth topic is read: the falsified one changes the fit (so the check above has teeth).
    asked = run(recordings[2], True), run(tampered, True)
    assert "tension_N" in asked[1].residual_rms
    assert asked[1].cost > 10 * asked[0].cost
    assert not np.array_equal(asked[0].values, asked[1].values)


def _truncated(path: Path, tmp_path: Path) -> Path:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return cut


def test_bad_recordings_and_requests_get_clear_errors(recordings, tmp_path):
    from typer.testing import CliRunner

    from server.cli import app

    text = tmp_path / "notes.mcap"
    text.write_text("not a recording")
    empty = write_campaign(tmp_path / "empty.mcap", [], {"campaign_id": "empty"})
    short = write_campaign(tmp_path / "short.mcap", [(bus.MOTOR_STATE, 0, bus.MotorState(
        seq=0, stamp_s=0.0, theta_rad=[0.0] * 4, force_applied_N=[0.0] * 4, drive="active", epoch="e", bridge="b"))],
        {"campaign_id": "short"})
    cases = [
        (tmp_path / "missing.mcap", "no such file"),
        (text, "not an MCAP file"),
        (_truncated(recordings[2], tmp_path), "truncated or unfinished"),
        (empty, "no motor states"),
        (short, "too short to calibrate on"),
    ]
    runner = CliRunner()
    for path, reason in cases:
        with pytest.raises(calibrate.CalibrationError, match=reason):
            calibrate.load_recording(path, PARAMS)
        run = runner.invoke(app, ["twin", "calibrate", str(path), "--out", str(tmp_path / "t.toml")])
        assert run.exit_code == 2 and reason in run.output and "Traceback" not in run.output, (path, run.output)
    run = runner.invoke(app, ["twin", "calibrate", str(recordings[2]), "--out", str(tmp_path / "t.toml"),
                              "--fit", "friction.f_s"])
    assert run.exit_code == 2 and "cannot fit 'friction.f_s'" in run.output
    with pytest.raises(calibrate.CalibrationError, match=r"index 7 out of range"):
        calibrate.unknowns(["actuation.torque_constant_factor[7]"], 4)
    existing = tmp_path / "there.toml"
    existing.write_text("")
    run = runner.invoke(app, ["twin", "calibrate", str(recordings[2]), "--out", str(existing)])
    assert run.exit_code == 2 and "exists" in run.output
    assert not (tmp_path / "t.toml").exists()  # nothing written on any refusal


def test_the_written_truth_round_trips(tmp_path):
    """truth_toml writes every value that is not a default, with its source: the shipped robot
    truth written out loads back equal."""
    path = tmp_path / "again.toml"
    calibrate.check_loadable(calibrate.truth_toml(ROBOT), path)
    again = load_truth(str(path))
    for section in ("friction", "actuation", "structure", "cables", "timing"):
        assert getattr(again, section) == getattr(ROBOT, section), section
    assert again.sources == ROBOT.sources and again.robot_params == ROBOT.robot_params == "prototype"
    assert math.isinf(calibrate.current_value(load_truth("model"), calibrate.unknowns(
        ["actuation.current_bandwidth_hz"], 4)[0], 4))


def test_a_parameter_set_the_base_truths_robot_does_not_use_is_warned_about(recordings, tmp_path):
    """The replays run the base truth's robot (robot_params: the shipped robot truth's is the
    prototype's), so a --set for the robot's structure would be ignored without a word."""
    from typer.testing import CliRunner

    from server.cli import app

    out = tmp_path / "t.toml"
    run = CliRunner().invoke(app, ["twin", "calibrate", str(recordings[2]), "--out", str(out), "--fit",
                                   "actuation.current_bandwidth_hz", "--max-evaluations", "1",
                                   "--set", "springs.k_left=[610.0,200.0,200.0]"])
    assert run.exit_code == 0, run.output
    assert "differs in springs.k_left, which the replays do not use" in run.output, run.output
    assert load_truth(str(out)).robot_params == "prototype"  # the robot the values were fitted on
