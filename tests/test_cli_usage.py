"""Bad input to the `xneck` commands (CLI audit of 2026-11-26): one `error:` line and exit status 2,
never a traceback, refused before any long work, and nothing lost or half-written; `--json` is
strict JSON; a fit cut off by its evaluation limit says so.

Every test runs the real command (the `xneck` fixture: a subprocess)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bridge import archive, bus
from controller.identification_loop import simulate_campaign
from controller.trajectory import trajectory_by_name

NOT_A_FOLDER = b"a regular file, kept as it is\n"


def _strict(text: str):
    """json.loads refusing NaN and ±Infinity, as jq or JSON.parse do."""

    def refuse(constant: str):
        raise ValueError(f"not strict JSON: {constant}")

    return json.loads(text, parse_constant=refuse)


def _refused(run, *said: str) -> str:
    """The run was refused as a usage error: status 2, an `error:` line saying ``said``, no traceback."""
    assert run.returncode == 2, (run.stdout, run.stderr)
    assert "Traceback" not in run.stderr, run.stderr
    errors = [line for line in run.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, run.stderr
    for s in said:
        assert s in errors[0], errors[0]
    return errors[0]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    """A short control-test campaign of the twin as an archive (controller/identification_loop.py):
    its identification holds a damping at its bound, whose relative σ is infinite."""
    path = tmp_path_factory.mktemp("campaign") / "control.mcap"
    traj = trajectory_by_name("control_test")
    data, _ = simulate_campaign(0, duration_s=13.0, trajectory=traj)
    msgs = [(bus.MOTOR_STATE, int(t * 1e9), bus.MotorState(seq=k, stamp_s=float(t), theta_rad=list(th),
                                                          force_applied_N=list(f), drive="active", epoch="e", bridge="b"))
            for k, (t, th, f) in enumerate(zip(data.t_s, data.theta_rad, data.force_N, strict=True))]
    msgs += [(bus.CAMERA_ALPHA, int(t * 1e9) + 1, bus.CameraAlpha(seq=k, stamp_s=float(t), alpha_ip_rad=list(a),
                                                                 capture_stamp_s=float(t)))
             for k, (t, a) in enumerate(zip(data.t_ip_s, data.alpha_ip_rad, strict=True))]
    msgs.sort(key=lambda m: m[1])
    archive.write_campaign(path, msgs, {"campaign_id": path.stem, "kind": "control", "trajectory": traj.to_json()})
    return path


@pytest.fixture
def a_file(tmp_path) -> Path:
    path = tmp_path / "text.mcap"
    path.write_bytes(NOT_A_FOLDER)
    return path


# -- 1. an unusable --out, refused before the work ----------------------------------------------------


@pytest.mark.parametrize("command, out_name", [
    # The campaign given is not an archive: had the work started first, the error would be about it.
    (["identify", "{junk}", "--out", "{out}"], "sub"),
    (["twin", "calibrate", "{junk}", "--out", "{out}", "--span", "2", "--max-evaluations", "1"], "c.toml"),
    (["campaign", "control", "--out", "{out}"], "x.mcap"),
    (["campaign", "identification", "--out", "{out}"], "x.mcap"),
    (["excitation", "design", "--duration", "20", "--starts", "1", "--maxiter", "1", "--out", "{out}"], "e.json"),
    (["study", "control", "--out", "{out}"], "st"),
    (["workspace", "--design", "3x", "--n", "3", "--out", "{out}"], "ws"),
    (["camera", "render", "--alpha", "0", "0", "0", "--out", "{out}"], "f.png"),
])
def test_an_out_below_a_regular_file_is_refused_before_any_work(xneck, tmp_path, a_file, command, out_name):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an archive")
    argv = [a.format(junk=junk, out=a_file / out_name) for a in command]
    _refused(xneck(*argv, timeout=120), "--out", f"{a_file} is not a directory")
    assert a_file.read_bytes() == NOT_A_FOLDER


def test_an_out_where_no_folder_can_be_made_is_refused_before_the_fit(xneck, tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an archive")
    _refused(xneck("identify", str(junk), "--out", "/proc/xneck-audit"), "--out", "cannot write in /proc")


def test_a_data_directory_that_is_a_file_is_refused_before_a_campaign(xneck, a_file):
    _refused(xneck("campaign", "control", env={"XNECK_DATA_DIR": str(a_file)}), "data directory",
             f"{a_file} is not a directory")


def test_the_out_check_leaves_no_folder_behind(xneck, tmp_path):
    """The check tries a file in the folders it would create, then removes them: a command refused
    afterwards (here the study itself refuses --samples 0) leaves nothing."""
    _refused(xneck("study", "control", "--out", str(tmp_path / "new" / "deeper" / "st"), "--samples", "0"),
             "--samples")
    assert not (tmp_path / "new").exists()


def test_a_write_that_fails_after_the_fit_is_one_line_and_leaves_no_temporary_file(xneck, campaign, tmp_path):
    out = tmp_path / "id"
    (out / "fig4_torques.png").mkdir(parents=True)  # the folder takes files, but not this one
    _refused(xneck("identify", str(campaign), "--no-alpha-hat", "--out", str(out)), f"cannot write {out}")
    assert sorted(p.name for p in out.iterdir()) == ["fig4_torques.png"]


def test_workspace_maps_are_written_whole(xneck, tmp_path):
    out = tmp_path / "ws"
    (out / "3x_stiffness.png").mkdir(parents=True)
    _refused(xneck("workspace", "--design", "3x", "--n", "3", "--out", str(out)), f"cannot write {out}")
    assert sorted(p.name for p in out.iterdir()) == ["3x_stiffness.png", "3x_wfw.png"]  # no .tmp left


# -- 9. excitation design writes JSON, so its file is .json ---------------------------------------------


def test_an_excitation_out_that_is_not_json_is_refused_before_the_design(xneck, tmp_path):
    out = tmp_path / "e.toml"
    _refused(xneck("excitation", "design", "--duration", "20", "--out", str(out)), "--out", ".json")
    assert not out.exists() and not list(tmp_path.iterdir())


# -- 2. an unreadable --trajectory -----------------------------------------------------------------------


@pytest.mark.parametrize("command", [["campaign", "control"], ["campaign", "identification"], ["controller"]])
@pytest.mark.parametrize("name, content, said", [
    ("missing.json", None, "cannot read the trajectory file (No such file or directory)"),
    ("dir.json", "folder", "cannot read the trajectory file (Is a directory)"),
    ("bytes.toml", b"\xff\xfe garbage", "not a UTF-8 text file"),
])
def test_an_unreadable_trajectory_file_is_refused(xneck, tmp_path, command, name, content, said):
    path = tmp_path / name
    if content == "folder":
        path.mkdir()
    elif content is not None:
        path.write_bytes(content)
    out = tmp_path / "c.mcap"
    extra = [] if command == ["controller"] else ["--out", str(out)]
    _refused(xneck(*command, "--trajectory", str(path), *extra), f"{path}: {said}")
    assert not out.exists()


def test_a_trajectory_of_another_type_names_what_to_give_not_a_function(xneck, tmp_path):
    line = _refused(xneck("campaign", "control", "--trajectory", str(tmp_path / "t.yaml"), "--out",
                          str(tmp_path / "c.mcap")), ".json or .toml", "identification or control_test")
    assert "trajectory_by_name" not in line


# -- 10. a truncated archive: what the user can do -------------------------------------------------------


def test_a_truncated_archive_says_how_to_recover_it(xneck, campaign, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(campaign.read_bytes()[:-200])
    line = _refused(xneck("identify", str(cut), "--out", str(tmp_path / "id")), "no footer")
    assert "campaigns/" in line and "xneck server" in line and "recover()" not in line


# -- 3, 4. ports and endpoints ---------------------------------------------------------------------------


@pytest.mark.parametrize("argv", [
    ["up", "--port", "99999", "--exit-after", "3"], ["up", "--port", "0", "--exit-after", "3"],
    ["up", "--viser-port", "70000", "--exit-after", "3"], ["server", "--port", "70000"],
    ["server", "--viser-port", "-1"],
])
def test_a_port_out_of_range_is_a_usage_error(xneck, tmp_path, argv):
    run = xneck(*argv, "--data-dir", str(tmp_path / "data"), timeout=60)
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    assert argv[1] in run.stderr
    assert not (tmp_path / "data").exists()  # nothing started


def test_a_hub_port_out_of_range_is_refused_before_anything_starts(xneck, tmp_path):
    _refused(xneck("up", "--hub", "tcp/127.0.0.1:99999", "--data-dir", str(tmp_path / "data"), "--exit-after", "3"),
             "--hub", "65535")
    assert not (tmp_path / "data").exists()


@pytest.mark.parametrize("argv, said", [
    (["twin", "--listen", "bogus", "--lockstep", "--startup-timeout", "1"], "listen endpoint 'bogus'"),
    (["twin", "--listen", "tcp/127.0.0.1:99999", "--lockstep", "--startup-timeout", "1"], "invalid port"),
    (["bridge", "--driver", "twin", "--connect", "bogus", "--lockstep", "--startup-timeout", "1"],
     "connect endpoint 'bogus'"),
    (["controller", "--connect", "bogus", "--idle-timeout", "1"], "connect endpoint 'bogus'"),
    (["camera", "--source", "twin", "--listen", "bogus", "--max-frames", "1"], "listen endpoint 'bogus'"),
])
def test_a_bad_endpoint_is_one_line(xneck, argv, said):
    _refused(xneck(*argv, timeout=60), said)


# -- 5, 6. the calibration's evaluation limit ------------------------------------------------------------


def test_an_evaluation_limit_below_one_is_refused(xneck, campaign, tmp_path):
    run = xneck("twin", "calibrate", str(campaign), "--out", str(tmp_path / "c.toml"), "--max-evaluations", "0")
    assert run.returncode == 2 and "Traceback" not in run.stderr and "--max-evaluations" in run.stderr
    assert not (tmp_path / "c.toml").exists()


def test_a_fit_stopped_by_the_evaluation_limit_says_so(xneck, campaign, tmp_path):
    out = tmp_path / "c.toml"
    run = xneck("twin", "calibrate", str(campaign), "--out", str(out), "--span", "2", "--max-evaluations", "1",
                "--json")
    assert run.returncode == 0, run.stderr
    summary = _strict(run.stdout)
    assert summary["converged"] is False and summary["status"] == "not converged: stopped at the evaluation limit"
    # As the help says: one evaluation, plus a Jacobian of one replay per fitted value (8 by default).
    assert summary["evaluations"] == 9
    assert "warning: the fit is not converged" in run.stderr
    text = out.read_text()
    fitted = [line for line in text.splitlines() if "measurement: fitted by xneck twin calibrate" in line]
    assert len(fitted) == 5 and all("not converged: stopped at the evaluation limit" in line for line in fitted)
    help_text = xneck("twin", "calibrate", "--help", env={"COLUMNS": "400"}).stdout
    assert "Jacobians are not counted" in help_text and "1 runs 9 replays" in help_text


def test_a_converged_fit_is_not_marked(xneck, campaign, tmp_path):
    out = tmp_path / "c.toml"
    run = xneck("twin", "calibrate", str(campaign), "--out", str(out), "--span", "1", "--fit",
                "friction.viscous_N_s_rad", "--max-evaluations", "60", "--json")
    assert run.returncode == 0, run.stderr
    assert _strict(run.stdout)["converged"] is True and "warning" not in run.stderr
    assert "not converged" not in out.read_text()


# -- 7. strict JSON ----------------------------------------------------------------------------------------


def test_identify_json_and_provenance_are_strict_json(xneck, campaign, tmp_path):
    out = tmp_path / "id"
    run = xneck("identify", str(campaign), "--json", "--no-alpha-hat", "--out", str(out))
    assert run.returncode == 0, run.stderr
    doc = _strict(run.stdout)
    sigmas = [p["relative_sigma"] for p in doc["table_2"]["parameters"]]
    assert None in sigmas  # a damping held at 0: its relative σ is infinite, written as null
    provenance = _strict(next(out.glob("*.provenance.json")).read_text())
    assert any(p["relative_sigma"] is None for p in provenance["parameters"])


# -- 8. numbers that make no sense ---------------------------------------------------------------------------


@pytest.mark.parametrize("argv, said", [
    (["identify", "{junk}", "--threshold", "nan"], "--threshold"),
    (["identify", "{junk}", "--threshold", "0"], "--threshold"),
    (["identify", "{junk}", "--cutoff-hz", "inf"], "--cutoff-hz"),
    (["twin", "--lockstep", "--idle-timeout", "nan"], "--idle-timeout"),
    (["twin", "--lockstep", "--startup-timeout", "-1"], "--startup-timeout"),
    (["bridge", "--driver", "twin", "--hold-ramp", "nan"], "--hold-ramp"),
    (["controller", "--idle-timeout", "inf"], "--idle-timeout"),
    (["campaign", "control", "--timeout", "nan"], "--timeout"),
    (["twin", "calibrate", "{junk}", "--out", "{tmp}/c.toml", "--span", "nan"], "--span"),
    (["twin", "calibrate", "{junk}", "--out", "{tmp}/c.toml", "--horizon", "nan"], "--horizon"),
    (["camera", "render", "--alpha", "0", "0", "0", "--out", "{tmp}/f.png", "--noise", "nan"], "--noise"),
    (["up", "--exit-after", "nan", "--data-dir", "{tmp}/data"], "--exit-after"),
])
def test_a_non_finite_or_negative_number_is_refused(xneck, tmp_path, argv, said):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an archive")
    _refused(xneck(*[a.format(junk=junk, tmp=tmp_path) for a in argv], timeout=60), said, "must be a")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.mcap"]


@pytest.mark.parametrize("argv", [
    ["campaign", "control", "--seed", "-1"], ["twin", "--seed", "-1"], ["excitation", "design", "--seed", "-1"],
    ["camera", "render", "--alpha", "0", "0", "0", "--out", "f.png", "--seed", "-1"], ["twin", "--max-ticks", "0"],
])
def test_a_negative_seed_or_count_is_a_usage_error(xneck, tmp_path, argv):
    run = xneck(*argv, cwd=tmp_path, timeout=60)
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    assert ("--seed" if "--seed" in argv else "--max-ticks") in run.stderr
    assert not list(tmp_path.iterdir())  # no archive, no image
