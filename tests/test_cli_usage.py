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

