"""`xneck campaign control|identification` refuse bad input before anything runs, with a message,
not a traceback (the campaigns themselves: tests/test_campaign.py, realtime); Ctrl-C ends a campaign
as an abort; the runner's working folders (the CLI's kept when unfinished, the console's never)."""

from __future__ import annotations

import json
import os
import shutil
import threading
from pathlib import Path
from types import SimpleNamespace

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


@pytest.mark.parametrize("as_json", [False, True])
@pytest.mark.parametrize("kind", ["control", "identification"])
def test_ctrl_c_ends_the_campaign_and_says_where_its_archive_and_logs_are(tmp_path, monkeypatch, kind, as_json):
    """User audit: Ctrl-C on a CLI campaign exited 130 with nothing said (no end line, no archive,
    no ``process logs:``; nothing at all with --json) and its archive named no cause. Now SIGINT
    stops the campaign (the runner's stop, named ``interrupted by SIGINT``), which ends as any
    other: the table or the JSON summary, an ``error:`` line, exit 130. The runner is a fake
    that signals this process and waits for the stop, as the real one's loop does."""
    import signal

    import server.campaign_runner as runner

    def fake_run(spec, params, out: Path, progress=None, stop=None, **_):
        os.kill(os.getpid(), signal.SIGINT)
        assert stop is not None and stop.wait(5), "SIGINT did not stop the campaign"
        return runner.CampaignResult("c-1", out, "aborted", runner.stop_message(stop), law="law1",
                                     logs_dir=str(tmp_path / "logs"))

    monkeypatch.setattr(runner, "run_campaign", fake_run)
    out = tmp_path / "c.mcap"
    # What this process had: Python's KeyboardInterrupt, or SIG_IGN where the suite was started as
    # a background job of a non-interactive shell (a fresh-clone run of f93b801, 2026-12-02)
    before = signal.getsignal(signal.SIGINT)
    r = CliRunner().invoke(app, ["campaign", kind, "--out", str(out), *(["--json"] if as_json else [])])
    assert r.exit_code == 130, (r.exit_code, r.output, r.exception)
    assert "error: campaign c-1 aborted: interrupted by SIGINT" in r.stderr
    if as_json:
        summary = json.loads(r.stdout)
        assert summary["outcome"] == "aborted" and summary["message"] == "interrupted by SIGINT"
        assert summary["path"] == str(out) and summary["logs_dir"] == str(tmp_path / "logs")
    else:
        assert f"archive: {out}" in r.stdout and f"process logs: {tmp_path / 'logs'}" in r.stdout
    assert signal.getsignal(signal.SIGINT) is before  # given back once it ended


def test_a_stop_names_its_cause_else_the_users_stop() -> None:
    from server.campaign_runner import STOPPED_BY_USER, CausedStop, stop_message

    plain, caused = threading.Event(), CausedStop()
    plain.set()
    caused.stop("interrupted by SIGINT")
    caused.stop("interrupted by SIGTERM")  # the first cause stays
    assert stop_message(plain) == STOPPED_BY_USER and stop_message(caused) == "interrupted by SIGINT"
    assert caused.is_set()


# -- the campaigns' working folders (user audit: hundreds of /tmp/xneck-<id>-* left by the console) --------


@pytest.mark.parametrize("console, outcome, kept", [(True, "aborted", False), (True, "finished", False),
                                                    (True, "raises", False), (False, "aborted", True)])
def test_a_console_campaigns_folder_goes_whatever_its_outcome_a_cli_ones_stays_when_unfinished(
        tmp_path, monkeypatch, console, outcome, kept):
    """The runner's ``_run`` is a fake ending as the real one does: the folder named in
    ``logs_dir`` unless finished (removed by the real one then), or raising (a storage fault)."""
    import server.campaign_runner as runner

    made: list[Path] = []

    def fake_run(spec, params, path, progress, campaign_id, session, hub, stop, workdir, on_monitor=None):
        made.append(workdir)
        (workdir / "trajectory.json").write_text("{}")
        if outcome == "raises":
            raise OSError("no space left on device")
        if outcome == "finished":
            shutil.rmtree(workdir)
            return runner.CampaignResult(campaign_id, path, outcome, "")
        return runner.CampaignResult(campaign_id, path, outcome, "", logs_dir=str(workdir))

    monkeypatch.setattr(runner, "_run", fake_run)
    monkeypatch.setattr(runner.tempfile, "tempdir", str(tmp_path))
    spec = SimpleNamespace(kind="control")
    try:
        result = runner.run_campaign(spec, None, tmp_path / "c.mcap", session=object(), hub="tcp/x",  # pyright: ignore[reportArgumentType]
                                     console=console)
    except OSError:
        result = None
    assert made[0].name.startswith("xneck-console-" if console else "xneck-") and made[0].parent == tmp_path
    assert made[0].exists() is kept, list(tmp_path.iterdir())
    if result is not None:
        assert result.logs_dir == (str(made[0]) if kept else "")


def test_the_consoles_start_sweeps_only_its_own_ended_or_day_old_folders(tmp_path) -> None:
    from server.campaign_runner import STALE_WORKDIR_S, sweep_console_workdirs

    now = 1_800_000_000.0

    def folder(name: str, age_s: float = 0.0) -> Path:
        p = tmp_path / name
        p.mkdir()
        (p / "trajectory.json").write_text("{}")
        os.utime(p, (now - age_s, now - age_s))
        return p

    ended_console = folder("xneck-console-control-20261130-010203-ab12-k3j4h5g6")
    old_console = folder("xneck-console-control-20261128-010203-cd34-aaaaaaaa", STALE_WORKDIR_S + 60)
    running_elsewhere = folder("xneck-console-identification-20261130-010203-ef56-bbbbbbbb", 60)
    ended_before = folder("xneck-control-20261130-010203-0a0b-cccccccc")  # the naming before: this console's
    cli_kept = folder("xneck-identification-20261101-010203-9999-dddddddd", 30 * STALE_WORKDIR_S)  # a CLI's logs
    up = folder("xneck-up-22286-f61pq3_h")
    (tmp_path / "xneck-console-control-20261130-010203-ab12-file").write_text("not a folder")
    (tmp_path / "xneck-console-control-20261130-010203-ab12-link").symlink_to(up)
    ended = {"control-20261130-010203-ab12", "control-20261130-010203-0a0b"}
    removed = sweep_console_workdirs(ended.__contains__, tmp_path, now)
    assert sorted(removed) == sorted([ended_console, old_console, ended_before])
    assert all(p.exists() for p in (running_elsewhere, cli_kept, up)) and (up / "trajectory.json").exists()
    assert (tmp_path / "xneck-console-control-20261130-010203-ab12-file").exists()


@pytest.mark.parametrize("kind", ["control", "identification"])
def test_a_campaign_ended_midway_ends_its_progress_line_before_its_summary(tmp_path, monkeypatch, kind):
    """User audit: ``xneck campaign control --robot`` aborted printed its summary on the progress
    bar's line ("…the bridge obeys controlcampaign control-…"): the bar, redrawn in place, had its
    newline only at 100 %."""
    import server.campaign_runner as runner

    def fake_run(spec, params, out: Path, progress=None, stop=None, **_):
        assert progress is not None
        progress(0.4, "aborted: no controller the bridge obeys control")
        return runner.CampaignResult("c-1", out, "aborted", "no controller", law="law1")

    monkeypatch.setattr(runner, "run_campaign", fake_run)
    r = CliRunner().invoke(app, ["campaign", kind, "--out", str(tmp_path / "c.mcap")])
    assert r.exit_code == 1, (r.output, r.exception)
    assert r.output.count("\n") >= 2
    line = next(x for x in r.output.split("\n") if "obeys control" in x)
    assert "campaign c-1" not in line and "error:" not in line, r.output
