"""Bad input to the `xneck` commands (CLI audit of 2026-11-26): one `error:` line and exit status 2,
never a traceback, refused before any long work, and nothing lost or half-written; `--json` is
strict JSON; a fit cut off by its evaluation limit says so.

Every test runs the real command (the `xneck` fixture: a subprocess)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bridge import archive, bus
from bridge.session import free_tcp_port
from controller.identification_loop import simulate_campaign
from controller.trajectory import trajectory_by_name
from twin.analysis.workspace import CAPTIONS

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


def test_up_takes_the_consoles_data_directory_from_the_environment(xneck, a_file, tmp_path):
    """`xneck up` handed the console `--data-dir data` whatever XNECK_DATA_DIR said, while `xneck
    campaign` records into XNECK_DATA_DIR as the console's directory: it now reads the variable too
    (a file there is refused before anything starts; before, a stack started in ./data)."""
    run = xneck("up", "--port", str(free_tcp_port()), "--hub", f"tcp/127.0.0.1:{free_tcp_port()}", "--exit-after",
                "1", cwd=tmp_path, env={"XNECK_DATA_DIR": str(a_file)}, timeout=60)
    assert run.returncode == 2, (run.stdout, run.stderr)
    assert f"cannot use the data directory {a_file}" in run.stderr and "xneck is up" not in run.stdout
    assert not (tmp_path / "data").exists()


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


@pytest.mark.parametrize("name", ["{tmp}/escaped/evil", "../../evil"])
def test_a_parameter_set_name_that_is_no_file_name_is_refused_before_the_fit(xneck, campaign, tmp_path, name):
    """Audit of 2026-11-28: the identified set's files are named after the set, so --set
    name=/x/y (or a --params file's name) wrote them outside --out."""
    name = name.format(tmp=tmp_path)
    out = tmp_path / "a" / "b" / "id"
    _refused(xneck("identify", str(campaign), "--no-alpha-hat", "--out", str(out), "--set", f"name={name}"),
             "cannot name a file in --out")
    assert not list(tmp_path.rglob("*evil*"))


def test_workspace_maps_are_written_whole(xneck, tmp_path):
    out = tmp_path / "ws"
    (out / "3x_stiffness.png").mkdir(parents=True)
    _refused(xneck("workspace", "--design", "3x", "--n", "3", "--out", str(out)), f"cannot write {out}")
    assert sorted(p.name for p in out.iterdir()) == ["3x_stiffness.png", "3x_wfw.png"]  # no .tmp left


def _capped(*args: str, gib: float = 1.0) -> subprocess.CompletedProcess:
    """``xneck <args>`` with its address space capped at ``gib`` GiB: a command that started to
    build an array it cannot hold ends in a MemoryError there, instead of growing into the swap or
    the OOM killer of the machine running the tests."""
    import resource

    cap = int(gib * 2**30)

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    return subprocess.run([sys.executable, "-m", "server.cli", *args], capture_output=True, text=True,
                          timeout=120, preexec_fn=limit)


@pytest.mark.parametrize("design, n, said", [
    ("3x", "400", ["--n 400", "a 3x map of 400³ points needs ~", "GB", "at most 89 for this design"]),
    ("2x", "1000000", ["--n 1000000", "a 2x map of 1000000² points needs ~", "at most 1123 for this design"]),
    ("3x", "90", ["--n 90", "at most 89"]),
])
def test_a_workspace_grid_beyond_its_memory_bound_is_refused_before_any_array(tmp_path, design, n, said):
    """Audit of 2026-12: `workspace --design 3x --n 400` grew to 22 GB and was OOM-killed, `--design
    2x --n 1000000` ended in "Unable to allocate 7.28 TiB". Refused now from an estimate of the
    arrays' bytes, before any is built and before --out is made (the cap of 1 GiB would turn an
    allocation into a MemoryError traceback)."""
    out = tmp_path / "ws"
    _refused(_capped("workspace", "--design", design, "--n", n, "--out", str(out)), *said)
    assert not out.exists()


def test_the_workspace_help_states_the_grid_bounds(xneck):
    run = xneck("workspace", "--help", env={"COLUMNS": "200"})
    assert run.returncode == 0, run.stderr
    text = " ".join(run.stdout.split())
    assert "at most 1123 for 2x and 89 for 3x" in text, text


@pytest.mark.parametrize("n", ["-1", "1"])
def test_a_workspace_grid_below_two_is_one_error_line(xneck, tmp_path, n):
    _refused(xneck("workspace", "--n", n, "--out", str(tmp_path / "ws")), f"--n {n}", ">= 2")
    assert not (tmp_path / "ws").exists()


@pytest.mark.parametrize("design, n", [("2x", "2"), ("2x", "3"), ("3x", "2")])
def test_a_coarse_workspace_grid_writes_every_figure(xneck, tmp_path, design, n):
    """Audit of 2026-12: `workspace --n 2` (and 3) ended in an IndexError of the Cartesian stiffness
    figure (no grid point inside the four-cable WFW), with 8 of the 9 PNGs written. A coarse grid is
    a quick preview: every figure is written, a panel without data says so."""
    out = tmp_path / "ws"
    run = xneck("workspace", "--design", design, "--n", n, "--out", str(out), timeout=300)
    assert run.returncode == 0, (run.stdout, run.stderr)
    assert "Traceback" not in run.stderr and "Warning" not in run.stderr, run.stderr
    written = sorted(p.name for p in out.iterdir())
    assert written == sorted(f for f in CAPTIONS if f.startswith(design)), written
    assert sorted(Path(line).name for line in run.stdout.split()) == written


# -- 9. excitation design writes JSON, so its file is .json ---------------------------------------------


def test_an_excitation_out_that_is_not_json_is_refused_before_the_design(xneck, tmp_path):
    out = tmp_path / "e.toml"
    _refused(xneck("excitation", "design", "--duration", "20", "--out", str(out)), "--out", ".json")
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("command", ["control", "identification"])
@pytest.mark.parametrize("name", ["x.json", "x", "x.mcap.tmp"])
def test_a_campaign_out_that_is_not_mcap_is_refused_before_the_campaign(xneck, tmp_path, command, name):
    """Input audit: `campaign identification --out x.json` recorded an MCAP named .json."""
    out = tmp_path / name
    _refused(xneck("campaign", command, "--out", str(out)), "--out", ".mcap")
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


# -- 2b. a trajectory or parameter file that is no regular file, or huge ----------------------------------


@pytest.fixture
def special_inputs(tmp_path) -> dict[str, dict[str, Path]]:
    """For .json and .toml: a FIFO (reading it blocked for ever), a link to /dev/zero (read whole,
    a MemoryError traceback) and a sparse regular file of 4 MiB, past the loaders' bound
    (bridge.small_file.INPUT_FILE_MAX_BYTES, 1 MiB)."""
    out: dict[str, dict[str, Path]] = {}
    for kind in ("fifo", "zero", "big"):
        for suffix in (".json", ".toml"):
            path = tmp_path / f"{kind}{suffix}"
            if kind == "fifo":
                os.mkfifo(path)
            elif kind == "zero":
                path.symlink_to("/dev/zero")
            else:
                with path.open("wb") as f:
                    f.truncate(4 * 1024 * 1024)
            out.setdefault(kind, {})[suffix] = path
    return out


@pytest.mark.parametrize("kind, said", [("fifo", "a FIFO"), ("zero", "a character device"), ("big", "more than")])
@pytest.mark.parametrize("command, suffix", [
    (["campaign", "identification", "--trajectory", "{path}", "--out", "{out}"], ".json"),
    (["campaign", "control", "--trajectory", "{path}", "--out", "{out}"], ".toml"),
    (["excitation", "bound", "--trajectory", "{path}"], ".json"),
    (["campaign", "control", "--params", "{path}", "--out", "{out}"], ".toml"),
    (["identify", "{campaign}", "--params", "{path}", "--out", "{out}"], ".toml"),
])
def test_a_special_or_huge_input_file_is_one_error_line(xneck, tmp_path, campaign, special_inputs, command, suffix,
                                                        kind, said):
    """Input audit: a FIFO as --trajectory or --params hung the command for ever, /dev/zero (behind
    a link) ended in a MemoryError traceback; the loaders read a regular file of at most 1 MiB."""
    path = special_inputs[kind][suffix]
    out = tmp_path / "out.mcap"
    argv = [a.format(path=path, out=out, campaign=campaign) for a in command]
    line = _refused(xneck(*argv, timeout=60), str(path))
    assert said in line or (kind != "big" and "not a regular file" in line), line
    assert not out.exists()


# -- 10. a truncated archive: what the user can do -------------------------------------------------------


@pytest.mark.parametrize("command", ["identify", "camera align"])
def test_a_truncated_archive_says_how_to_recover_it(xneck, campaign, tmp_path, command):
    """``camera align`` read the archive its own way: a truncated one was "RecordLengthLimitExceeded
    ... (opcode 49)" (audit of session 42)."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(campaign.read_bytes()[:-200])
    argv = (["identify", str(cut), "--out", str(tmp_path / "id")] if command == "identify" else
            ["camera", "align", str(tmp_path / "video.mp4"), str(cut), "--out", str(tmp_path / "a.mcap")])
    (tmp_path / "video.mp4").write_bytes(b"not a video")
    line = _refused(xneck(*argv), "no footer")
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
    (["twin", "--listen", "tcp/127.0.0.1:99999", "--lockstep", "--startup-timeout", "1"], "the port must be at most 65535, got 99999"),
    (["bridge", "--driver", "twin", "--connect", "bogus", "--lockstep", "--startup-timeout", "1"],
     "connect endpoint 'bogus'"),
    (["controller", "--connect", "bogus", "--idle-timeout", "1"], "connect endpoint 'bogus'"),
    (["camera", "--source", "twin", "--listen", "bogus", "--max-frames", "1"], "listen endpoint 'bogus'"),
])
def test_a_bad_endpoint_is_one_line(xneck, argv, said):
    _refused(xneck(*argv, timeout=60), said)


@pytest.mark.parametrize("argv, said", [
    (["camera", "--source", "twin", "--clock", "bridge", "--max-frames", "1"], "--clock is for a live camera (usb:N)"),
    (["camera", "--source", "file:{tmp}/v.avi", "--clock", "local"], "--clock is for a live camera (usb:N)"),
    (["camera", "--source", "usb:0", "--clock", "sometimes"], "--clock 'sometimes': expected bridge, bridge:NAME"),
    (["camera", "--source", "usb:0", "--clock", "bridge:a b"], "--clock 'bridge:a b': expected bridge, bridge:NAME"),
])
def test_the_camera_clock_option_is_checked_before_anything_opens(xneck, tmp_path, argv, said):
    """``--clock``: a USB camera's stamps on the bridge's clock (docs/camera.md, "One clock"); a
    video's and the twin's camera's stamps are their own clocks, so they refuse it."""
    _refused(xneck(*[a.format(tmp=tmp_path) for a in argv], timeout=60), said)


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
    # As the help says: one evaluation, plus a Jacobian of one replay per fitted value (8 by default),
    # plus the screen of the fit's start (the base values and 16 points, --starts).
    assert summary["evaluations"] == 9 + 17
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


@pytest.fixture(scope="module")
def identified(xneck, campaign, tmp_path_factory):
    """`xneck identify CAMPAIGN --json --no-alpha-hat --out DIR` on the module's campaign, run once
    for the tests that read it as it is (the finished process, DIR): nothing writes into DIR."""
    out = tmp_path_factory.mktemp("identified") / "id"
    return xneck("identify", str(campaign), "--json", "--no-alpha-hat", "--out", str(out)), out


def test_identify_json_and_provenance_are_strict_json(identified):
    run, out = identified
    assert run.returncode == 0, run.stderr
    doc = _strict(run.stdout)
    sigmas = [p["relative_sigma"] for p in doc["table_2"]["parameters"]]
    assert None in sigmas  # a damping held at 0: its relative σ is infinite, written as null
    provenance = _strict(next(out.glob("*.provenance.json")).read_text())
    assert any(p["relative_sigma"] is None for p in provenance["parameters"])


def test_identify_refuses_to_replace_an_earlier_identifications_parameter_set(xneck, identified, campaign, tmp_path):
    """User audit of session 45: `xneck identify` into a folder holding an earlier identification's
    set (`xneck campaign identification`'s analysis, another estimator) replaced it without a word.
    Refused before the fit, the set untouched; --force replaces it."""
    import shutil

    run, out = identified
    assert run.returncode == 0, run.stderr
    again = tmp_path / "id"
    shutil.copytree(out, again)
    sets = sorted(again.glob("*-identified.toml"))
    assert len(sets) == 1
    before = sets[0].read_bytes()
    _refused(xneck("identify", str(campaign), "--no-alpha-hat", "--estimator", "ols", "--out", str(again)),
             str(sets[0]), "exists", "--force")
    assert sets[0].read_bytes() == before
    # under another set name, the folder's figures would have been replaced beside the first set,
    # then of another fit (audit of session 49): refused too, naming them
    figures = {p: p.read_bytes() for p in again.glob("fig*.png")}
    assert figures
    _refused(xneck("identify", str(campaign), "--no-alpha-hat", "--set", "name=other", "--out", str(again)),
             "holds an earlier identification's files", "fig4_torques.png", "--force")
    assert all(p.read_bytes() == b for p, b in figures.items()) and not list(again.glob("other*"))
    os.utime(sets[0], (1.0, 1.0))  # written again below: its time says so (the fit may give the same values)
    (again / "validation").mkdir(exist_ok=True)  # an earlier --validate's: not this run's, so removed
    (again / "fig8_alpha_hat.png").write_bytes(b"earlier")  # --no-alpha-hat writes no Fig. 8: removed too
    (again / "notes.txt").write_text("mine")  # not an identification's: kept
    forced = xneck("identify", str(campaign), "--no-alpha-hat", "--estimator", "ols", "--out", str(again), "--force")
    assert forced.returncode == 0, forced.stderr
    assert sets[0].stat().st_mtime > 1.0
    assert not (again / "validation").exists() and not (again / "fig8_alpha_hat.png").exists()
    assert (again / "notes.txt").read_text() == "mine" and (again / "fig4_torques.png").is_file()
    # the module's campaign is a control test: identified as asked, and said (user audit of session 45)
    assert f"warning: {campaign} is a control campaign, not an identification one" in forced.stderr, forced.stderr


def _ended(campaign: Path, path: Path, outcome: str, message: str) -> Path:
    """``campaign``'s messages rewritten into ``path`` with the ``xneck.campaign`` outcome and message given."""
    from bridge.archive_read import read_campaign

    original = read_campaign(campaign)
    msgs = [(bus.key_of_topic(topic), t, m) for topic, items in original.topics.items() for t, m in items]
    archive.write_campaign(path, sorted(msgs, key=lambda x: x[1]),
                           {**original.info, "outcome": outcome, "message": message})
    return path


@pytest.mark.parametrize("outcome", ["aborted", "interrupted"])
def test_identify_refuses_a_campaign_that_did_not_finish(xneck, campaign, tmp_path, outcome):
    """User audit of 2026-11-30: a campaign stopped by the user at 28 % was identified with exit 0 and
    no word (its set 20-25 % off the truth, ±2σ missing it), while the console saves no set from it
    (409). Refused before the fit, naming the outcome and its message; nothing written."""
    stopped = _ended(campaign, tmp_path / "stopped.mcap", outcome, "stopped by the user")
    out = tmp_path / "id"
    run = xneck("identify", str(stopped), "--no-alpha-hat", "--out", str(out), "--validate", str(stopped))
    _refused(run, f"outcome {outcome}: stopped by the user", "did not finish", "--partial")
    assert not out.exists()
    # a --validate campaign that did not finish is only said (the errors are of the part it recorded)
    assert f"warning: validation campaign {stopped} did not finish (outcome {outcome}" in run.stderr, run.stderr


def test_identify_partial_fits_an_aborted_campaign_and_says_so_everywhere(xneck, campaign, identified, tmp_path):
    """--partial fits it anyway: stderr, the tables' first line and the set's header say it was a
    partial campaign, with the outcome and how much was recorded; a finished one says nothing."""
    stopped = _ended(campaign, tmp_path / "stopped.mcap", "aborted", "stopped by the user")
    out = tmp_path / "id"
    run = xneck("identify", str(stopped), "--no-alpha-hat", "--partial", "--out", str(out))
    assert run.returncode == 0, run.stderr
    said = "fitted on a PARTIAL campaign that did not finish (outcome aborted: stopped by the user; 13.0 s recorded"
    assert f"warning: {said}" in run.stderr, run.stderr
    assert run.stdout.startswith(f"WARNING: {said}"), run.stdout[:400]
    header = next(out.glob("*-identified.toml")).read_text().splitlines()[:2]
    assert header[1].startswith(f"# WARNING: {said}"), header
    assert _strict(next(out.glob("*.provenance.json")).read_text())["warning"].startswith(said)
    clean, clean_out = identified  # the finished campaign: no warning anywhere
    assert _strict(clean.stdout)["campaign_outcome"] == {"outcome": "finished", "message": "", "partial": False}
    assert "PARTIAL" not in clean.stderr and "WARNING" not in next(clean_out.glob("*-identified.toml")).read_text()


def _without_files(doc: dict) -> dict:
    return {k: v for k, v in doc.items() if k not in ("files", "provenance", "record_notes")}


def test_identify_refuses_two_cameras_and_reads_the_one_chosen_past_a_stray_frame(xneck, campaign, identified,
                                                                                   tmp_path):
    """Audit of 2026-11-29: an archive holding the α_IP of two cameras was identified as one camera,
    exit 0 (k(4) 4464 → 7530 N/m); one stray frame stamped 1e9 s got the whole record refused for a
    clock step. The camera is chosen by name, the stray dropped and said, the tables those of the
    clean record."""
    import msgspec

    from bridge.archive_read import read_campaign

    original = read_campaign(campaign)
    msgs = [(bus.key_of_topic(topic), t, m) for topic, items in original.topics.items() for t, m in items]
    replace = msgspec.structs.replace
    msgs = [(k, t, replace(m, source="twin-noise") if k == bus.CAMERA_ALPHA else m) for k, t, m in msgs]
    frames = [(k, t, m) for k, t, m in msgs if k == bus.CAMERA_ALPHA]
    second = [(k, t + 16_000_000, replace(m, source="usb:1", capture_stamp_s=m.capture_stamp_s + 1 / 60,
                                          stamp_s=m.stamp_s + 1 / 60, alpha_ip_rad=[a + 0.05 for a in m.alpha_ip_rad]))
              for k, t, m in frames]
    k, t, m = frames[len(frames) // 2]
    stray = (k, t + 1, replace(m, seq=1, capture_stamp_s=1e9, stamp_s=1e9 + 0.05))
    mixed = tmp_path / "two.mcap"
    archive.write_campaign(mixed, sorted([*msgs, *second, stray], key=lambda x: x[1]), original.info)
    _refused(xneck("identify", str(mixed), "--out", str(tmp_path / "refused")), "2 cameras", "'usb:1'",
             "--alpha-ip-source")
    chosen = xneck("identify", str(mixed), "--alpha-ip-source", "twin-noise", "--json", "--no-alpha-hat",
                   "--out", str(tmp_path / "chosen"))
    assert chosen.returncode == 0, chosen.stderr
    assert "note: 1 camera frame(s)" in chosen.stderr and "1e+09" in chosen.stderr, chosen.stderr
    clean, _ = identified  # the same command on the clean record
    assert clean.returncode == 0, clean.stderr
    doc = _strict(chosen.stdout)
    assert len(doc["record_notes"]) == 1 and "1 camera frame(s)" in doc["record_notes"][0]
    assert _without_files(doc) == _without_files(_strict(clean.stdout))


def test_identify_says_when_alpha_ip_is_stamped_off_the_encoders_time(xneck, campaign, tmp_path):
    """A camera whose --latency (or clock) is off by 40 ms shifts every α_IP against θ and f, and the
    fit went on with it in silence. `xneck identify` measures the delay from the record, warns on
    stderr (also under --json) and puts it in the JSON; the unshifted record gets no warning."""
    import msgspec

    from bridge.archive_read import read_campaign

    original = read_campaign(campaign)
    replace = msgspec.structs.replace
    msgs = [(bus.key_of_topic(topic), t, m) for topic, items in original.topics.items() for t, m in items]
    late = [(k, t, replace(m, capture_stamp_s=m.capture_stamp_s + 0.04, stamp_s=m.stamp_s + 0.04))
            if k == bus.CAMERA_ALPHA else (k, t, m) for k, t, m in msgs]
    shifted = tmp_path / "late.mcap"
    archive.write_campaign(shifted, late, original.info)
    run = xneck("identify", str(shifted), "--json", "--no-alpha-hat", "--out", str(tmp_path / "late"))
    assert run.returncode == 0, run.stderr
    assert "warning: α_IP timing" in run.stderr and "ms late" in run.stderr and "--latency longer" in run.stderr, run.stderr
    timing = _strict(run.stdout)["alpha_ip_timing"]
    assert timing["resolved"] and 0.032 < timing["delay_s"] < 0.048, timing
    clean = xneck("identify", str(campaign), "--no-alpha-hat", "--out", str(tmp_path / "clean"))
    assert clean.returncode == 0, clean.stderr
    assert "α_IP timing: best matched" in clean.stdout and "warning: α_IP timing" not in clean.stderr, clean.stderr


# -- 8. numbers that make no sense ---------------------------------------------------------------------------


def test_the_twin_refuses_no_camera_with_an_alpha_ip_it_would_not_publish(xneck):
    """User audit of session 45: `xneck twin --no-camera --alpha-ip camera` was accepted and the
    twin published no α_IP at all."""
    _refused(xneck("twin", "--no-camera", "--alpha-ip", "camera", "--listen", "tcp/127.0.0.1:0", timeout=60),
             "--no-camera", "--alpha-ip camera")


@pytest.mark.parametrize("cutoff", ["1e-9", "0.001", "1e6"])
def test_a_cutoff_out_of_the_records_range_states_the_range(xneck, campaign, tmp_path, cutoff):
    """Input audit: `identify --cutoff-hz 1e-9` ended in "error: Singular matrix" (the Butterworth's
    coefficients), while 0.001 Hz said only that too few instants remained. Both, and a cutoff
    past the Nyquist frequency, state the range this record accepts, before any filter runs."""
    line = _refused(xneck("identify", str(campaign), "--cutoff-hz", cutoff, "--out", str(tmp_path / "o"),
                          "--no-alpha-hat", timeout=120), f"cutoff {float(cutoff):g} Hz is out of range",
                    "must be in [")
    assert "Singular" not in line
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


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
    (["camera", "--source", "twin", "--rate", "1e9"], "≤ 1000 frames per second"),  # user audit of session 45
    (["camera", "--source", "file:{junk}", "--t0", "1e17"], "≤ 1e+10 s"),
])
def test_a_non_finite_or_negative_number_is_refused(xneck, tmp_path, argv, said):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an archive")
    _refused(xneck(*[a.format(junk=junk, tmp=tmp_path) for a in argv], timeout=60), said, "must be a")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.mcap"]


@pytest.mark.parametrize("kind", ["control", "identification"])
def test_a_robot_campaign_that_cannot_end_within_its_timeout_is_refused(xneck, tmp_path, kind):
    """Audit of 2026-11-30: a trajectory as long as the timeout was aborted before its end every time
    (start-up and holds take wall time too); on the robot it is refused before anything moves."""
    run = xneck("campaign", kind, "--robot", "--connect", "tcp/127.0.0.1:9", "--timeout", "20",
                "--out", str(tmp_path / "c.mcap"), timeout=60)
    _refused(run, "aborted before its end", "a timeout of at least")
    assert not (tmp_path / "c.mcap").exists()


@pytest.mark.parametrize("argv", [
    ["campaign", "control", "--seed", "-1"], ["twin", "--seed", "-1"], ["excitation", "design", "--seed", "-1"],
    ["camera", "render", "--alpha", "0", "0", "0", "--out", "f.png", "--seed", "-1"], ["twin", "--max-ticks", "0"],
])
def test_a_negative_seed_or_count_is_a_usage_error(xneck, tmp_path, argv):
    run = xneck(*argv, cwd=tmp_path, timeout=60)
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    assert ("--seed" if "--seed" in argv else "--max-ticks") in run.stderr
    assert not list(tmp_path.iterdir())  # no archive, no image


# -- CLI audit of 2026-11-27 (audit-c) ----------------------------------------------------------------------


def _commands():
    """Every command of ``xneck`` (click's tree of the typer app), with its path."""
    import typer.main

    from server.cli import app

    def walk(command, path):
        yield path, command
        for name, sub in getattr(command, "commands", {}).items():
            yield from walk(sub, [*path, name])

    return list(walk(typer.main.get_command(app), ["xneck"]))


def test_help_texts_are_shown_as_written():
    """Typer renders help as Rich markup: `a:b:n` came out as `a🅱n` (the :b: emoji) in `xneck study
    --help`, and a `[word]` would vanish as a style tag."""
    from rich.text import Text

    for path, command in _commands():
        for name, text in [("help", command.help or ""), *((p.name, getattr(p, "help", None) or "") for p in command.params)]:
            assert Text.from_markup(text).plain == text, (" ".join(path), name, text)


def test_the_camera_help_names_its_commands():
    from server.cli.camera import camera_app

    names = {c.name for c in camera_app.registered_commands}
    listed = camera_app.info.help.split("and ")[-1].rstrip(".").split("/")
    assert set(listed) == names, (listed, names)


def _shell_blocks(text: str) -> list[str]:
    lines, blocks, i = text.split("\n"), [], 0
    while i < len(lines):
        if lines[i].strip() in ("```sh", "```bash"):
            j = next(k for k in range(i + 1, len(lines)) if lines[k].strip() == "```")
            blocks.append("\n".join(lines[i + 1:j]))
            i = j
        i += 1
    return blocks


def test_the_docs_shell_commands_parse_and_name_existing_options():
    """docs/studies.md's `--vary truth.friction.static_ratio=U(1.1,1.5)`, unquoted, was a shell
    syntax error when pasted."""
    import shlex
    import subprocess

    root = Path(__file__).resolve().parents[1]
    commands = dict((" ".join(path[1:]), c) for path, c in _commands())
    checked = 0
    for doc in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        for block in _shell_blocks(doc.read_text()):
            if "xneck" not in block:
                continue
            run = subprocess.run(["bash", "-n"], input=block, text=True, capture_output=True)
            assert run.returncode == 0, (doc.name, run.stderr)
            for line in block.replace("\\\n", " ").split("\n"):
                words = shlex.split(line, comments=True)
                if not words or words[0] != "xneck":
                    continue
                depth = max(n for n in range(1, len(words) + 1) if " ".join(words[1:n]) in commands)
                command = commands[" ".join(words[1:depth])]
                known = {o for p in command.params for o in (*p.opts, *p.secondary_opts)}
                for word in words[depth:]:
                    if word.startswith("--"):
                        assert word.split("=")[0] in known, (doc.name, line, word)
                checked += 1
    assert checked >= 5


@pytest.mark.parametrize("argv, said", [
    (["identify", "."], "cannot read campaign: .: is a directory, not a campaign file"),
    (["identify", "/"], "cannot read campaign: /: is a directory, not a campaign file"),
    (["camera", "align", "video.mp4", "."], ".: is a directory, not a campaign file"),
])
def test_a_campaign_that_is_a_folder_is_one_line(xneck, tmp_path, argv, said):
    """The default --out is named after the campaign's file: '.' and '/' have no name (a ValueError
    traceback from Path.with_name)."""
    _refused(xneck(*argv, cwd=tmp_path), said)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("argv, said", [
    (["camera", "detect", "d"], "d: is a directory, not an image file"),
    (["camera", "detect", "missing.png"], "missing.png: no such image file"),
    (["camera", "detect", "f.png", "--calibration", "d"], "--calibration: d: is a directory, not a calibration file"),
    (["camera", "render", "--alpha", "1", "2", "3", "--out", "r.png", "--calibration", "d"],
     "--calibration: d: is a directory, not a calibration file"),
    (["camera", "render", "--alpha", "1", "2", "3", "--out", "r.png", "--params", "d"],
     "--params: d: is a directory, not a parameter file"),
    (["camera", "align", "d", "c.mcap"], "d: is a directory, not a video file"),
    (["camera", "--source", "file:d"], "d: is a directory, not a video file"),
    (["model", "--params", "d", "--alpha", "0", "0", "0"], "--params: d: is a directory, not a parameter file"),
    (["study", "design", "--out", "s", "--study", "d"], "--study: d: is a directory, not a study file"),
    (["study", "design", "--out", "s", "--params", "d"], "--params: d: is a directory, not a parameter file"),
])
def test_a_directory_given_for_a_file_says_it_is_a_directory(xneck, tmp_path, argv, said):
    """User audit: a directory where a file is expected was reported as "no such file"
    (server.cli.options.check_input for every file option)."""
    for folder in ("d", "d.toml"):
        (tmp_path / folder).mkdir()
    (tmp_path / "f.png").write_bytes(b"")
    (tmp_path / "c.mcap").write_bytes(b"")
    _refused(xneck(*argv, cwd=tmp_path), said)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.mcap", "d", "d.toml", "f.png"]


@pytest.mark.parametrize("L", ["1e-200", "1e100", "1e200"])
def test_kinematics_in_any_unit_of_length(xneck, L):
    """Lengths are in any unit (kinematics.py): at L = 1e100 the IK's aspect was a NaN (a traceback),
    at 1e200 the cuspidality sweep overflowed, at 1e-200 it found two solutions instead of four."""
    ik = xneck("kinematics", "ik", "--L", L, "--b", str(0.5 * float(L)), "--x", "0",
               "--y", L, "--json")
    assert ik.returncode == 0, ik.stderr
    reference = xneck("kinematics", "ik", "--L", "1", "--b", "0.5", "--x", "0", "--y", "1", "--json")
    angles = lambda run: [s["theta_deg"] + [s["aspect"]] for s in _strict(run.stdout)["solutions"]]  # noqa: E731
    assert angles(ik) == angles(reference)
    cusp = xneck("kinematics", "cuspidal", "--L", L, "--b", str(0.5 * float(L)), "--json")
    assert cusp.returncode == 0, cusp.stderr
    doc = _strict(cusp.stdout)
    assert doc["cuspidal"] is True and doc["max_ik_solutions_found"] == 4
    assert doc["b_threshold_numeric"] == pytest.approx(float(L) / 6 ** 0.5, rel=1e-4)


def test_a_checkerboard_too_large_to_draw_is_refused(xneck, tmp_path):
    """At the options' upper ends the board asked numpy for 272 GiB: a MemoryError traceback."""
    out = tmp_path / "board.png"
    _refused(xneck("camera", "board", "--out", str(out), "--square", "0.2", "--dpi", "1200", "--columns", "30",
                   "--rows", "30"), "311817×311817 px", "--dpi")
    assert not out.exists()


def test_a_study_with_an_unknown_alpha_ip_is_refused_before_it_runs(xneck, tmp_path):
    """It ran every run (each failed) and wrote the study directory."""
    _refused(xneck("study", "control", "--out", str(tmp_path / "st"), "--alpha-ip", "bogus"), "--alpha-ip",
             "noise or camera")
    assert not (tmp_path / "st").exists()


def test_a_scheduler_that_is_no_address_is_one_line(xneck, tmp_path):
    run = xneck("study", "control", "--out", str(tmp_path / "st"), "--scheduler", "bogus")
    _refused(run, "--scheduler 'bogus'", "tcp://HOST:PORT")  # on a line of its own, after the progress line


@pytest.mark.parametrize("argv, said", [
    (["--params", "{tmp}/missing.toml"], "--params: {tmp}/missing.toml: no such parameter file"),
    (["--robot", "--driver-config", "{tmp}/missing.toml"], "cannot read the driver config"),
    # the bridge's own check, once the stack was up, had been the first word of a bad --loop-stall
    (["--robot", "--loop-stall", "0.01"], "--loop-stall must be 0 (off) or at least 0.05 s, not 0.01"),
    (["--loop-stall", "nan"], "--loop-stall: must be a finite number"),
    (["--no-bridge", "--loop-stall", "1"], "--loop-stall sets the watchdog of the bridge `xneck up` starts"),
])
def test_up_refuses_what_would_end_its_bridge_before_anything_starts(xneck, tmp_path, argv, said):
    """The stack started ("xneck is up"), then the bridge exited with the reason in its log; with
    --robot the launcher then reported "DRIVES MAY BE ON"."""
    run = xneck("up", *[a.format(tmp=tmp_path) for a in argv], "--data-dir", str(tmp_path / "data"),
                "--port", "1", "--exit-after", "3", timeout=60)
    _refused(run, said.format(tmp=tmp_path))
    assert "xneck is up" not in run.stdout and not (tmp_path / "data").exists()


@pytest.mark.parametrize("argv, said", [
    (["--hub", "bogus"], "listen endpoint 'bogus'"),
    (["--connect", "bogus"], "connect endpoint 'bogus'"),
    (["--hub", "tcp/127.0.0.1:99999"], "at most 65535"),
    (["--host", "no-such-host.invalid"], "--host no-such-host.invalid: cannot listen there"),
    # named without its source, the camera process was silently not the campaigns' (audit of 2026-11-29)
    (["--twin-camera", "cam-x"], "--twin-camera: Value error, names the stack's camera process"),
    (["--twin-camera", "cam-x", "--twin-alpha-ip", "noise"], "only with --twin-alpha-ip camera"),
])
def test_server_refuses_an_unusable_endpoint_or_host_in_one_line(xneck, tmp_path, argv, said):
    """Each was a traceback from the app's startup, after the URL was printed."""
    run = xneck("server", *argv, "--port", "0", "--data-dir", str(tmp_path / "data"), timeout=60)
    _refused(run, said)
    assert "xneck console" not in run.stdout and not (tmp_path / "data").exists()


def test_server_refuses_a_viser_port_that_is_busy_or_its_own_port(xneck, tmp_path):
    """viser took the next port without a word when its own was busy, so the 3D view was not where
    it was asked, and took the console's port when that was next (uvicorn then failed)."""
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        p = busy.getsockname()[1]
        run = xneck("server", "--viser-port", str(p), "--port", "0", "--data-dir", str(tmp_path / "data"), timeout=60)
        _refused(run, f"--viser-port {p}: 127.0.0.1:{p} is in use")
    run = xneck("server", "--viser-port", str(p), "--port", str(p), "--data-dir", str(tmp_path / "data"), timeout=60)
    _refused(run, f"--viser-port {p} is the console's --port")
    assert not (tmp_path / "data").exists()


def test_a_controller_campaign_kind_is_one_of_the_bus_kinds(xneck):
    """It had no help and took any word, which went into every campaign event."""
    _refused(xneck("controller", "--campaign-kind", "bogus", "--idle-timeout", "1"), "--campaign-kind 'bogus'",
             "control, identification, jog")


@pytest.mark.parametrize("argv", [
    ["campaign", "identification", "--estimator", "magic"],
    ["campaign", "identification", "--creep-time-s", "-2"],
    ["campaign", "identification", "--trajectory", "{tmp}/bad.json"],
    ["identify", "{campaign}", "--estimator", "magic"],
    ["identify", "{campaign}", "--sigma", "gaussian"],
    ["identify", "{campaign}", "--estimator", "iv", "--creep-time-s", "2"],
    ["identify", "{tmp}/bad.json"],
    ["identify", "{campaign}", "--validate", "{tmp}/bad.json"],
])
def test_an_identification_refusal_loads_nothing_of_the_identification(tmp_path, campaign, argv):
    """A bad option, trajectory or file is refused before the identification's pipeline is loaded
    (scipy.signal: seconds of import) or the archive read: the options' names and checks are
    twin.identification.options, an archive's soundness bridge.archive_read.check_finished."""
    (tmp_path / "bad.json").write_text('{"waypoints_deg": "not a list"}')
    argv = [a.replace("{tmp}", str(tmp_path)).replace("{campaign}", str(campaign)) for a in argv]
    out = tmp_path / ("never.mcap" if argv[0] == "campaign" else "never")
    run = subprocess.run([sys.executable, "-X", "importtime", "-m", "server.cli", *argv, "--out", str(out)],
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert run.returncode == 2, run.stderr[-2000:]
    imported = {line.rsplit("|", 1)[-1].strip() for line in run.stderr.splitlines() if line.startswith("import time:")}
    assert not {"twin.identification.pipeline", "scipy.signal"} & imported
    assert "twin.identification.options" in imported
    said = [line for line in run.stderr.splitlines() if line.startswith("error:") or "Invalid value" in line]
    assert said, run.stderr[-2000:]
    assert not out.exists()
