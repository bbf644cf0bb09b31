"""`xneck campaign control|identification` refuse bad input before anything runs, with a message,
not a traceback (the campaigns themselves: tests/test_campaign.py, realtime)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from server.cli import app


@pytest.mark.parametrize("kind", ["control", "identification"])
def test_an_existing_archive_is_refused_and_kept(tmp_path, kind):
    out = tmp_path / "earlier.mcap"
    out.write_bytes(b"an earlier campaign")
    r = CliRunner().invoke(app, ["campaign", kind, "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert "exists" in r.stderr and "never overwritten" in r.stderr
    assert r.exception is None or isinstance(r.exception, SystemExit)  # a message, not a traceback
    assert out.read_bytes() == b"an earlier campaign"


def test_an_unknown_estimator_is_refused_before_the_campaign_runs(tmp_path):
    out = tmp_path / "c.mcap"
    r = CliRunner().invoke(app, ["campaign", "identification", "--estimator", "magic", "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert "'magic'" in r.stderr and "loadfriction" in r.stderr
    assert r.exception is None or isinstance(r.exception, SystemExit)
    assert not out.exists()


@pytest.mark.parametrize("value, extra, said", [("0", [], "positive number of seconds"),
                                               ("-2", [], "positive number of seconds"),
                                               ("nan", [], "positive number of seconds"),
                                               ("2", ["--estimator", "iv"], "load-friction fit")])
def test_a_bad_creep_time_is_refused_before_the_campaign_runs(tmp_path, value, extra, said):
    out = tmp_path / "c.mcap"
    r = CliRunner().invoke(app, ["campaign", "identification", "--creep-time-s", value, *extra, "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert "--creep-time-s" in r.stderr and said in r.stderr
    assert r.exception is None or isinstance(r.exception, SystemExit)
    assert not out.exists()


def test_a_trajectory_beyond_the_limits_is_refused_before_anything_moves(tmp_path, xneck) -> None:
    bad = tmp_path / "reach.json"
    bad.write_text(json.dumps({"name": "reach", "waypoints_deg": [[0, 0, 0], [30, 70, 0], [0, 0, 0]],
                               "durations_s": [3.0, 3.0]}))
    out = tmp_path / "never.mcap"
    run = xneck("campaign", "control", "--trajectory", str(bad), "--out", str(out))
    assert run.returncode == 2 and "waypoint 1" in run.stderr and "70" in run.stderr
    assert not out.exists()
    fast = tmp_path / "fast.json"
    fast.write_text(json.dumps({"waypoints_deg": [[0, 0, 0], [50, 50, 50]], "durations_s": [0.2]}))
    run = xneck("campaign", "control", "--trajectory", str(fast), "--out", str(out))
    assert run.returncode == 2 and "segment 0" in run.stderr and not out.exists()



def test_an_estimator_alias_is_taken_as_xneck_identify_takes_it():
    """`xneck identify --estimator ls` was accepted while `xneck campaign identification` refused
    it: the campaign's option resolves the aliases the identification knows, to the estimator's name."""
    from server.cli.options import check_estimator

    assert check_estimator("ls") == "ols" and check_estimator("load-friction") == "loadfriction"
    assert check_estimator("auto") == "auto"


@pytest.mark.parametrize("argv, said", [
    (["--robot"], "say where the robot's bridge listens"),
    (["--connect", "tcp/127.0.0.1:7447"], "--connect applies to --robot"),
    (["--robot", "--connect", "bogus"], "not of the form"),
])
def test_a_robot_campaign_must_say_where_the_bridge_is(tmp_path, monkeypatch, argv, said):
    """`xneck campaign control --robot` opened a bus of its own that no bridge could find (its hub
    on a random port, no --connect): it waited 120 s in silence, then said 'timed out'."""
    monkeypatch.delenv("XNECK_ZENOH_CONNECT", raising=False)
    out = tmp_path / "c.mcap"
    r = CliRunner().invoke(app, ["campaign", "control", *argv, "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert said in r.stderr
    assert not out.exists()
