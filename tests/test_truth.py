"""The robot truth (issue 16): the effects the twin adds to the controller's model, each one
switchable, each changing what it should, and the §7 control test on the default truth keeping
the paper's findings (twin/sim/truth.py, twin/sim/robot_truth.toml, docs/twin-fidelity.md)."""

from __future__ import annotations

import math
import re
import tomllib

import numpy as np
import pytest

from controller.laws import LawConfig
from controller.offline import run_closed_loop
from controller.trajectory import control_test_trajectory
from twin.model.params import load_params
from twin.sim.integrator import RF_COLUMNS, _coulomb_level
from twin.sim.simulator import Twin, TwinConfig
from twin.sim.truth import (
    EFFECTS,
    ROBOT_TRUTH_FILE,
    SOURCE_KINDS,
    TruthError,
    check_truth,
    load_truth,
    parse_truth,
    truth_params,
)

ROBOT = load_truth("robot")
PAPER = {1: (0.52, 2.19), 2: (0.37, 1.51), 3: (0.66, 1.09)}  # §7: mean e, mean e_α (deg), prototype


def twin_with(*effects: str, **changes) -> Twin:
    """A twin of the default robot truth with only ``effects`` on; ``changes``: {section: {key: value}}."""
    truth = ROBOT.only(*effects)
    for section, values in changes.items():
        truth = truth.replace(section, **values)
    return Twin(config=TwinConfig(camera=False, truth=truth))


# -- the file -------------------------------------------------------------------------------------


def test_every_value_of_the_robot_truth_has_a_source():
    data = tomllib.loads(ROBOT_TRUTH_FILE.read_text())
    assert set(data) - {"name", "robot_params"} == set(EFFECTS) and data["robot_params"] == "prototype"
    for section in EFFECTS:
        assert data[section]["enabled"] is True, section
        for key, item in data[section].items():
            if key != "enabled":
                kind, _, why = item["source"].partition(":")
                assert kind in SOURCE_KINDS and len(why.strip()) > 10, (section, key)
    assert ROBOT.enabled() == EFFECTS and set(ROBOT.sources) == {
        f"{s}.{k}" for s in EFFECTS for k in data[s] if k != "enabled"}


def test_a_value_without_a_source_or_out_of_range_is_refused(tmp_path):
    with pytest.raises(TruthError, match=r"friction\.static_ratio: write it as"):
        parse_truth({"friction": {"enabled": True, "static_ratio": 1.3}})
    with pytest.raises(TruthError, match="source must start with one of"):
        parse_truth({"friction": {"static_ratio": {"value": 1.3, "source": "trust me"}}})
    with pytest.raises(TruthError, match="static_ratio must be >= 1"):
        parse_truth({"friction": {"static_ratio": {"value": 0.7, "source": "none: test"}}})
    with pytest.raises(TruthError, match="not an effect section"):
        parse_truth({"camera": {}})
    with pytest.raises(TruthError, match="does not exist"):
        check_truth(str(tmp_path / "missing.toml"))
    (tmp_path / "folder.toml").mkdir()  # user audit: a directory was "does not exist"
    with pytest.raises(TruthError, match=r"folder\.toml' is a directory"):
        check_truth(str(tmp_path / "folder.toml"))
    with pytest.raises(TruthError, match="truth must be one of"):
        check_truth("robots")
    bad = tmp_path / "bad.toml"
    bad.write_text("[timing\n")
    with pytest.raises(TruthError, match=r"bad\.toml"):
        load_truth(str(bad))


def _truth_file(tmp_path, section, key, value):
    path = tmp_path / f"{key}.toml"
    path.write_text(f'name = "t"\n[{section}]\nenabled = true\n{key} = {{ value = {value}, source = "none: test" }}\n')
    return str(path)


@pytest.mark.parametrize("section, key, value, reason", [
    ("friction", "pulley_reference_tension_N", "nan", "friction.pulley_reference_tension_N"),
    ("friction", "pulley_reference_tension_N", "-5.0", "friction.pulley_reference_tension_N"),
    ("friction", "viscous_N_s_rad", "inf", "friction.viscous_N_s_rad"),
    ("friction", "asymmetry", "[nan, 0.0, 0.0, 0.0]", "friction.asymmetry"),
    ("structure", "mass_factor", "[nan, 1.0, 1.0]", "structure.mass_factor"),
    ("structure", "mass_factor", "[0.0, 1.0, 1.0]", "structure.mass_factor"),
    ("structure", "spring_factor_left", "[1.0, -1.0, 1.0]", "structure.spring_factor_left"),
    ("structure", "l0_offset_m", "[inf, 0.0, 0.0]", "structure.l0_offset_m"),
    ("structure", "pulley_radius_offset_m", "nan", "structure.pulley_radius_offset_m"),
    ("structure", "mass_factor", "[1.0, 1.0]", "structure.mass_factor: 2 values for 3"),
    ("cables", "creep_time_s", "inf", "cables.creep_time_s"),
    ("actuation", "ripple_per_rev", "0", "actuation.ripple_per_rev"),
    ("actuation", "current_max_A", "nan", "actuation.current_max_A"),
])
def test_a_truth_file_with_a_value_the_twin_cannot_run_is_refused_when_checked(tmp_path, section, key, value, reason):
    """Audit of 2026-11-26: ``pulley_reference_tension_N = nan`` or ``mass_factor = [nan, 1, 1]``
    passed the ``--truth`` check; the campaign then started, wrote an aborted archive and failed 8 s
    later with "Array must not contain infs or NaNs", naming no key. Every value is checked (NaN
    never, ±inf only where it means "ideal"), and against the prototype's joints and cables."""
    with pytest.raises(TruthError, match=re.escape(reason)):
        check_truth(_truth_file(tmp_path, section, key, value))


def test_a_truth_file_that_does_not_decode_is_a_truth_error(tmp_path):
    """Audit of 2026-11-26: a nested-too-deeply truth file answered 500 on GET /api/truths."""
    deep = tmp_path / "deep.toml"
    deep.write_text("x = " + "[" * 50_000 + "]" * 50_000 + "\n")
    latin = tmp_path / "latin.toml"
    latin.write_bytes('name = "caf\xe9"\n'.encode("latin-1"))
    for path in (deep, latin):
        with pytest.raises(TruthError, match=path.name):
            check_truth(str(path))


def test_a_truth_file_loads_by_path_like_the_named_ones(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('name = "mine"\n[timing]\nenabled = true\ndelay_ticks = { value = 2, source = "measurement: test" }\n')
    assert check_truth(str(path)) == str(path)
    truth = load_truth(str(path))
    assert truth.name == "mine" and truth.enabled() == ("timing",) and truth.timing.delay_ticks == 2
    assert Twin(config=TwinConfig(camera=False, truth=str(path))).truth == truth
    assert load_truth("model").enabled() == () and truth_params(load_params(), "model") is not None


def test_table_1_and_table_2_stay_the_truths():
    """Identification keeps a known answer: the truth changes neither k, λ nor the friction levels."""
    p = load_params()
    q = truth_params(p, ROBOT)
    assert q.cables.variable.k == p.cables.variable.k and q.cables.variable.lam == p.cables.variable.lam
    assert q.friction == p.friction
    assert q.cables.variable.c_a == (ROBOT.cables.damping_N_s_m,) * 4
    assert q.springs.k_left == tuple(k * f for k, f in zip(p.springs.k_left, ROBOT.structure.spring_factor_left))
    assert q.bars.m_top[0] == pytest.approx(p.bars.m_top[0] * ROBOT.structure.mass_factor[0])
    assert q.geometry.r == pytest.approx(p.geometry.r + ROBOT.structure.pulley_radius_offset_m)


# -- each effect changes what it should -------------------------------------------------------------


def _settle(twin: Twin, f: np.ndarray, ticks: int):
    return [twin.tick(f) for _ in range(ticks)]


def test_stiction_makes_a_resting_motor_stick_and_it_breaks_away_above_the_static_level():
    """With the model's arctan friction a loaded motor never stops creeping (no friction at θ̇ = 0);
    with the robot's stiction it ends at rest (to round-off), and moves again once the load exceeds
    the static level."""
    f = np.array([20.0, 20.0, 20.0, 26.0])
    arctan = Twin(config=TwinConfig(camera=False))
    sticky = twin_with("friction")
    creeping = _settle(arctan, f, 1000)[-100:]
    stuck = _settle(sticky, f, 1000)[-100:]
    assert min(np.abs(t.theta_dot).max() for t in creeping) > 1e-4
    assert max(np.abs(t.theta_dot).max() for t in stuck) < 1e-12  # at rest up to round-off
    theta0 = stuck[-1].theta
    # 3 N more on motor 1 stays below its static level (about 1.3 × 11 N at these ~10 N tensions,
    # below the 40 N reference load): it does not move; 40 N more breaks it away and it winds.
    held = _settle(sticky, f + np.array([3.0, 0, 0, 0]), 100)
    assert abs(held[-1].theta[0] - theta0[0]) < 1e-9
    moved = _settle(sticky, f + np.array([40.0, 0, 0, 0]), 100)
    assert moved[-1].theta[0] - theta0[0] > 0.05


def test_friction_levels_follow_direction_force_and_tension():
    """Asymmetry by direction; around the reference load (where Table 1 holds), pulley friction
    grows with the tension, the gear loss with the motor force when driving and with the tension
    when driven (the kernel's level function)."""
    rf = np.zeros((1, RF_COLUMNS))
    rf[0, :] = [15.0, 14.0, 1.3, 2.0, 0.0, 0.08, 0.09, 0.1, 40.0]
    assert _coulomb_level(rf, 0, 1.0, 40.0, 40.0) == 15.0 and _coulomb_level(rf, 0, -1.0, 40.0, 40.0) == 14.0
    assert _coulomb_level(rf, 0, 1.0, 40.0, 60.0) == pytest.approx(17.0)  # pulleys: 0.1 × 20 N
    assert _coulomb_level(rf, 0, 1.0, 90.0, 40.0) == pytest.approx(19.0)  # gear, driving: 0.08 × 50 N
    assert _coulomb_level(rf, 0, -1.0, 90.0, 40.0) == pytest.approx(14.0)  # driven: the motor force does not count
    assert _coulomb_level(rf, 0, -1.0, 40.0, 0.0) == pytest.approx(14.0 - 4.0 - 3.6)
    assert _coulomb_level(rf, 0, 1.0, 0.0, -400.0) == 0.0  # never negative


def test_current_loop_lags_and_saturates_and_torque_constants_scale():
    ideal = dict(ripple_fraction=0.0, cogging_N=0.0, current_bandwidth_hz=math.inf)
    twin = twin_with("actuation", actuation=ideal)
    f = np.full(4, 20.0)
    assert twin._applied_force(f, twin.dt) == pytest.approx(f * np.array(ROBOT.actuation.torque_constant_factor))
    slow = twin_with("actuation", actuation={**ideal, "current_bandwidth_hz": 20.0, "torque_constant_factor": (1.0,) * 4})
    first = slow._applied_force(f, slow.dt).copy()
    # τ = 8 ms: the mean over the first 2 ms period is about 12 % of the step.
    assert 0.08 * 20 < first[0] < 0.16 * 20
    capped = twin_with("actuation", actuation={**ideal, "current_max_A": 1.0, "torque_constant_factor": (1.0,) * 4})
    k_t, rho = capped.params.motors.torque_constant, capped.model.rho
    assert capped._applied_force(np.full(4, 90.0), capped.dt) == pytest.approx(np.full(4, k_t / rho))


def test_ripple_and_cogging_depend_on_the_motor_angle():
    twin = twin_with("actuation", actuation=dict(current_bandwidth_hz=math.inf, torque_constant_factor=(1.0,) * 4))
    f = np.full(4, 20.0)
    forces = []
    for angle in np.linspace(0, 2 * math.pi / 6, 7):
        twin.state[twin._n:twin._n + twin._nc] = angle
        forces.append(twin._applied_force(f, twin.dt)[0])
    a = ROBOT.actuation
    assert max(forces) - min(forces) > 2 * 20 * a.ripple_fraction * 0.8
    assert forces[0] == pytest.approx(forces[-1])  # one period of 6 per turn


def test_one_tick_delay_and_jitter():
    f = np.full(4, 30.0)
    delayed = twin_with("timing", timing=dict(jitter_s=0.0))
    model = Twin(config=TwinConfig(camera=False))
    a = delayed.tick(f)
    b = model.tick(np.zeros(4))
    assert np.array_equal(a.alpha, b.alpha)  # the first command is not applied yet
    assert np.array_equal(delayed.tick(f).alpha, model.tick(f).alpha)
    jittery = twin_with("timing")
    stamps = np.array([jittery.tick(f).t_s for _ in range(500)])
    periods = np.diff(stamps)
    assert periods.std() == pytest.approx(ROBOT.timing.jitter_s, rel=0.3)
    assert periods.mean() == pytest.approx(jittery.dt, rel=0.01)


def test_creep_keeps_stretching_a_loaded_cable_after_the_elastic_response():
    f = np.full(4, 25.0)
    crept = twin_with("cables")
    plain = twin_with("cables", cables=dict(creep_ratio=0.0))
    x_crept = np.array([t.elongation for t in _settle(crept, f, 3000)])
    x_plain = np.array([t.elongation for t in _settle(plain, f, 3000)])
    assert x_crept[-1, 0] / x_plain[-1, 0] == pytest.approx(1 + ROBOT.cables.creep_ratio, rel=0.02)
    assert x_crept[250, 0] / x_plain[250, 0] < 1 + 0.5 * ROBOT.cables.creep_ratio  # creep takes seconds


def test_backlash_shows_only_on_a_slack_cable():
    twin = twin_with("actuation")
    taut = _settle(twin, np.full(4, 20.0), 200)[-1]  # the neck moves a little: the gear stays loaded
    assert not taut.slack.any()
    assert np.all(np.abs(taut.theta_meas - taut.theta) < 2 * math.pi / twin.counts_per_rev)
    theta = twin.theta
    theta[3] -= 2.0  # 1.6 mm of cable 4 paid out: slack until the others pull it taut
    twin.reset(theta=theta)
    ticks = _settle(twin, np.array([20.0, 20.0, 20.0, 0.0]), 400)
    slack = np.array([t.slack[3] for t in ticks])
    offset = np.array([t.theta[3] - t.theta_meas[3] for t in ticks])
    assert slack.sum() > 10
    assert offset[slack] == pytest.approx(ROBOT.actuation.backlash_rad, abs=0.01)
    assert np.all(offset[~slack] < 2 * math.pi / twin.counts_per_rev)


def test_robot_friction_needs_elastic_cables():
    with pytest.raises(ValueError, match="needs elastic cables"):
        Twin(config=TwinConfig(camera=False, cable_model="rigid", truth="robot"))


def _short_test():
    return control_test_trajectory(motion_s=1.5, dwell_s=0.5, rest_s=0.5)


def test_a_slower_current_loop_raises_the_tracking_error():
    """The outer loop (ω = 11 rad/s) hardly sees a current loop above ~10 Hz (docs/twin-fidelity.md);
    at 2 Hz its lag dominates the tracking error."""
    p, traj = load_params(), _short_test()
    e = {}
    for bw in (1000.0, 2.0):
        truth = ROBOT.only("actuation").replace("actuation", current_bandwidth_hz=bw)
        e[bw] = run_closed_loop(p, LawConfig(law=2), traj, TwinConfig(seed=3, truth=truth)).metrics()["e_mean_all_deg"]
    assert e[2.0] > 1.5 * e[1000.0], e


# -- the §7 control test on the default robot truth -------------------------------------------------


@pytest.fixture(scope="module")
def section7():
    p, traj = load_params(), control_test_trajectory()
    cfgs = {"law1": LawConfig(law=1), "law2": LawConfig(law=2), "law3": LawConfig(law=3),
            "no_pulleys": LawConfig(law=2, no_pulleys=True)}
    return {k: run_closed_loop(p, c, traj, TwinConfig(seed=11, truth="robot")).metrics() for k, c in cfgs.items()}


def test_the_default_robot_truth_keeps_the_papers_ordering(section7):
    e = {k: v["e_mean_all_deg"] for k, v in section7.items()}
    ea = {k: v["e_alpha_mean_all_deg"] for k, v in section7.items()}
    # law 2 tracks better than law 3, not law 1: on the robot truth law 1 ties it or leads (0.47°
    # against 0.48°, seed 11; law 2's forces are lower, tests/test_controller.py). It led law 1
    # only while the offline loop ran the law on a fixed period, blind to the twin's jitter.
    assert e["law2"] < e["law3"], e
    assert ea["law3"] < min(ea["law1"], ea["law2"]), ea  # law 3 estimates best
    assert e["no_pulleys"] > e["law2"] and ea["no_pulleys"] > ea["law2"]  # pulleys matter


def test_each_law_is_within_a_factor_2_of_the_prototype(section7):
    for law, (e_paper, ea_paper) in PAPER.items():
        m = section7[f"law{law}"]
        assert 0.5 < m["e_mean_all_deg"] / e_paper < 2.0, (law, m["e_mean_all_deg"])
        assert 0.5 < m["e_alpha_mean_all_deg"] / ea_paper < 2.0, (law, m["e_alpha_mean_all_deg"])


def test_truth_file_is_accepted_wherever_a_truth_name_is(tmp_path):
    """`--truth FILE` (the CLI's shared callback) and the twin driver's config take a truth file;
    a bad one is refused with the reason."""
    import msgspec
    import typer

    from server.cli.options import check_truth as cli_check
    from twin.sim.driver import TwinDriverConfig

    path = tmp_path / "mine.toml"
    path.write_text('[cables]\nenabled = true\ncreep_ratio = { value = 0.02, source = "none: test" }\n')
    assert cli_check(str(path)) == str(path.resolve()) and cli_check("robot") == "robot"
    with pytest.raises(typer.BadParameter, match="does not exist"):
        cli_check(str(tmp_path / "nope.toml"))
    assert TwinDriverConfig(truth=str(path)).truth == str(path)
    with pytest.raises(msgspec.ValidationError, match="truth must be one of"):
        msgspec.convert({"truth": "bogus"}, TwinDriverConfig)


# -- a truth file everywhere: REST, the console's settings under `xneck up` (issue 16) ---------------------------


CALIBRATED = ('name = "bench"\n[cables]\nenabled = true\n'
              'damping_N_s_m = { value = 55.0, source = "measurement: fitted by xneck twin calibrate to a.mcap" }\n'
              '[calibration]\ncommand = "xneck twin calibrate a.mcap --out bench.toml"\ndate = "2026-11-23T00:00:00Z"\n'
              'campaigns = ["a.mcap"]\nbase = "robot"\nfitted = { "cables.damping_N_s_m" = 55.0 }\n'
              'sigma = { "cables.damping_N_s_m" = 2.0 }\nresidual_rms = { theta_rad = 0.02 }\nevaluations = 12\n')


def test_truth_files_are_uploaded_validated_listed_and_run_over_rest(tmp_path):
    import httpx
    from server_harness import AUTH, running_server, wait_until

    from bridge.archive_read import read_campaign

    with running_server(tmp_path / "data") as (base, _app), httpx.Client(base_url=base, timeout=60) as client:
        put = lambda name, body: client.put(f"/api/truths/{name}", content=body, headers=AUTH)  # noqa: E731
        assert client.put("/api/truths/bench", content=CALIBRATED).status_code == 401  # the token is needed
        hostile = [
            ("robot", CALIBRATED, ["path", "name"], "built in"),
            ("bad$name", CALIBRATED, ["path", "name"], "must be 1-64"),
            ("bench", "", ["body"], "empty body"),
            ("bench", "\xff\xfe", ["body"], "invalid UTF-8"),
            ("bench", "x = " + "[" * 3000 + "]" * 3000, ["body"], "nested too deeply"),
            ("bench", "[camera]\nbias = 1\n", ["body"], "not an effect section"),
            ("bench", "[cables]\ndamping_N_s_m = 40.0\n", ["body"], "write it as"),
            ("bench", '[timing]\ndelay_ticks = { value = 9, source = "none: x" }\n', ["body"], "0-3"),
            ("bench", "[calibration]\ndate = 1\n", ["body"], "calibration"),
            ("bench", "a" * 70_000, ["body"], "more than"),
            ("bench", 'robot_params = "../../../etc/x.toml"\n', ["body"], "not a path"),
        ]
        for name, body, loc, reason in hostile:
            r = put(name, body.encode("latin-1") if body.startswith("\xff") else body)
            assert r.status_code == 422, (name, body[:40], r.text)
            detail = r.json()["detail"][0]
            assert detail["loc"] == loc and reason in detail["msg"], (name, body[:40], detail)
        assert not (tmp_path / "data" / "truths" / "bench.toml").exists()
        r = put("bench", CALIBRATED)
        assert r.status_code == 201 and r.json() == {"name": "bench", "effects": ["cables"], "calibrated": True}
        listed = {t["name"]: t for t in client.get("/api/truths").json()["truths"]}
        assert set(listed) == {"model", "robot", "bench"}
        assert listed["bench"]["calibration"]["campaigns"] == ["a.mcap"] and listed["robot"]["builtin"]
        assert client.get("/api/truths/bench").text == CALIBRATED
        assert client.get("/api/truths/nope").status_code == 404
        # A campaign request names a truth, never a path; an unknown name is a 422 that lists the known ones.
        for truth, reason in (("../../etc/passwd", "pattern"), ("/tmp/x.toml", "pattern"), ("other", "known: model, robot, bench")):
            r = client.post("/api/campaigns", json={"kind": "control", "truth": truth}, headers=AUTH)
            assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "truth"], r.text
            assert reason in r.json()["detail"][0]["msg"], r.text
        # The console starts the campaign's twin with the named file: the record names it, the MCAP says
        # which file the twin loaded.
        short = {"waypoints_deg": [[0, 0, 0], [10, 10, 10]], "durations_s": 1.0}
        r = client.post("/api/campaigns", json={"kind": "control", "law": 2, "truth": "bench", "waypoints": short},
                        headers=AUTH)
        assert r.status_code == 201 and r.json()["truth"] == "bench", r.text
        cid = r.json()["id"]
        assert wait_until(lambda: client.get(f"/api/campaigns/{cid}").json()["status"] != "running", 150, 0.3)
        rec = client.get(f"/api/campaigns/{cid}").json()
        assert rec["status"] in ("finished", "degraded") and rec["truth"] == "bench", rec
    stored = tmp_path / "data" / "truths" / "bench.toml"
    assert read_campaign(tmp_path / "data" / "campaigns" / f"{cid}.mcap").info["twin_truth"] == str(stored.resolve())


def test_xneck_up_with_a_truth_file_runs_campaigns_that_record_it(tmp_path):
    """`xneck up --truth FILE`: the stack's twin bridge runs the file, the console (--twin-truth FILE)
    takes it, a campaign records it (REST record and MCAP), and another truth is refused."""
    import os
    import subprocess
    import sys

    import httpx
    from server_harness import AUTH, TOKEN, stop_xneck_up, wait_until
    from test_stack import _alive_kinds

    from bridge.archive_read import read_campaign
    from bridge.session import free_tcp_port

    path = tmp_path / "bench.toml"
    path.write_text(CALIBRATED)
    port, hub, data = free_tcp_port(), f"tcp/127.0.0.1:{free_tcp_port()}", tmp_path / "d"
    base = f"http://127.0.0.1:{port}"
    env = {**os.environ, "XNECK_TOKEN": TOKEN, "PYTHONUNBUFFERED": "1"}
    with open(tmp_path / "up.log", "wb") as log:
        up = subprocess.Popen([sys.executable, "-m", "server.cli", "up", "--port", str(port), "--hub", hub,
                               "--data-dir", str(data), "--truth", str(path)], stdout=log, stderr=subprocess.STDOUT,
                              stdin=subprocess.DEVNULL, env=env, start_new_session=True)

    try:
        assert wait_until(lambda: {"bridge", "campaign-service"} <= _alive_kinds(base), 180, 0.3), (tmp_path / "up.log").read_text()
        short = {"waypoints_deg": [[0, 0, 0], [10, 10, 10]], "durations_s": 1.0}
        r = httpx.post(base + "/api/campaigns", json={"kind": "control", "truth": "robot", "waypoints": short},
                       headers=AUTH, timeout=60)
        assert r.status_code == 422 and "simulates the bench truth" in r.text, r.text
        r = httpx.post(base + "/api/campaigns", json={"kind": "control", "waypoints": short}, headers=AUTH, timeout=60)
        assert r.status_code == 201 and r.json()["truth"] == "bench", r.text
        cid = r.json()["id"]
        done = lambda: httpx.get(f"{base}/api/campaigns/{cid}", timeout=5).json()["status"] != "running"  # noqa: E731
        assert wait_until(done, 90, 0.3), (tmp_path / "up.log").read_text()[-3000:]
        rec = httpx.get(f"{base}/api/campaigns/{cid}", timeout=5).json()
        assert rec["status"] in ("finished", "degraded") and rec["truth"] == "bench", rec
    finally:
        stop_xneck_up(up)
    assert read_campaign(data / "campaigns" / f"{cid}.mcap").info["twin_truth"] == str(path.resolve())
    assert "twin (bench truth)" in (tmp_path / "up.log").read_text() or str(path.resolve()) in (tmp_path / "up.log").read_text()


def test_a_stored_truth_file_that_is_not_text_is_a_422_not_a_500(tmp_path):
    """Audit of 2026-11-27: GET /api/truths/{name} of a file put in <data dir>/truths by hand in
    Latin-1 answered 500 (the list already said why it does not load)."""
    import httpx
    from server_harness import running_server

    truths = tmp_path / "data" / "truths"
    truths.mkdir(parents=True)
    (truths / "latin.toml").write_bytes('name = "caf\xe9"\n'.encode("latin-1"))
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=60) as c:
        r = c.get("/api/truths/latin")
        assert r.status_code == 422 and "not UTF-8" in r.json()["detail"], r.text
        listed = {t["name"]: t for t in c.get("/api/truths").json()["truths"]}
        assert "error" in listed["latin"], listed
