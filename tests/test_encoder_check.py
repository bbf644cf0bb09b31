"""The stuck-encoder check (controller/encoder_check.py): the fourth cable's redundancy against a
frozen encoder reading, on the twin's robot truth, closed through the controller's campaign
service in one process as the lockstep campaign runs it (docs/safety.md, "Stuck encoder")."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import pytest

from controller.encoder_check import (
    PERSISTENCE_S,
    SLACK_SETTLE_S,
    THRESHOLD_M,
    EncoderConsistency,
    detector_model,
    encoder_residual,
    residuals,
)
from controller.laws import LawConfig
from controller.service import CampaignService
from controller.trajectory import Trajectory, control_test_trajectory
from twin.model import cables
from twin.sim.simulator import Twin, TwinConfig


def _campaign(params, traj: Trajectory, truth: str = "robot", law: int = 2, freeze: tuple[int, float] | None = None,
              seed: int = 0):
    """The campaign on a twin of ``truth`` with the check called as the service would call it
    (before the law, with its last α̂, the forces it sent and its filtered θ̇). ``freeze`` =
    (encoder, time s): that reading stays where it was then, for the law too. Stops at the first
    fault. Returns (first fault's stamp or nan, its reason, the check, |s| per tick)."""
    twin = Twin(params, TwinConfig(truth=truth, seed=seed, camera=False))
    svc = CampaignService(params, LawConfig(law=law), service=False, settle_s=1.0)
    check = EncoderConsistency(params)
    tick = twin.tick(np.zeros(params.n_cables))
    svc.initialise(tick.theta_meas)
    svc.begin(traj, tick.t_s)
    frozen, s = None, []
    for _ in range(round((traj.duration_s + 1.0) * 500) + 50):
        theta = tick.theta_meas.copy()
        if freeze is not None and tick.t_s >= freeze[1]:
            frozen = theta[freeze[0]] if frozen is None else frozen
            theta[freeze[0]] = frozen
        ctl = svc.ctl
        why = check.update(theta, ctl.estimator.alpha_hat, ctl.f_prev, ctl.theta_dot, tick.t_s, svc.drive == "active")
        s.append(abs(check.s))
        if why:
            return tick.t_s, why, check, np.array(s)
        out = svc.control(theta, tick.t_s)
        if out.law_ran:
            svc.advance(tick.t_s)
        if not svc.running:
            break
        tick = twin.tick(out.force_N)
    return math.nan, "", check, np.array(s)


def _consistent(params, alpha_deg, tension_N):
    """Encoder angles (rad) that agree exactly with α and tensions t (the detector's own eq. 54 at
    rest): θ = (l_c0 + x − l_c(α))/ρ."""
    m = detector_model(params)
    alpha = np.radians(np.asarray(alpha_deg, dtype=float))
    t = np.asarray(tension_N, dtype=float)
    x = t / (m.k + m.lam * t)
    return m, alpha, (m.l_c0 + x - cables.l_c(m, alpha)) / m.rho


def test_the_residual_vanishes_on_consistent_readings_and_names_a_cable_length_error_exactly(params):
    m, alpha, theta = _consistent(params, [[20, -10, 30], [-40, 25, 5]], [[30, 25, 20, 40], [12, 50, 33, 20]])
    force = np.array([[30, 25, 20, 40], [12, 50, 33, 20]], dtype=float)
    s, r = residuals(m, theta, alpha, force)  # θ̇ = 0: no friction, the tension is the force
    assert s.shape == (2,) and r.shape == (2, 4)
    assert np.abs(s).max() < 1e-12 and np.abs(r).max() < 1e-12
    # Encoder j short by 1 mm of cable: r_j is that 1 mm (measured − implied), whichever j.
    for j in range(4):
        wrong = theta.copy()
        wrong[:, j] -= 1e-3 / m.rho
        r = encoder_residual(m, wrong, alpha, force)
        np.testing.assert_allclose(r[:, j], -1e-3, rtol=1e-9)
    one = encoder_residual(m, theta[0], alpha[0], force[0])  # one tick: shape (n_cables,)
    assert one.shape == (4,) and np.abs(one).max() < 1e-12


def test_a_set_that_says_its_cables_are_rigid_is_checked_on_their_stretch_all_the_same(params):
    """A campaign's own parameter set with ``cables.model = "rigid"`` built a check that predicted
    no stretch: every campaign then aborted on a stuck-encoder fault (0.05-11.5 s in, laws 1-3;
    audit of session 43). The real cables stretch whatever a set says: the check takes the set's
    variable-stiffness section, and readings consistent with it leave no residual."""
    import tomllib

    from twin.model.params import params_from_dict

    raw = tomllib.loads(params.to_toml())
    raw["cables"]["model"] = "rigid"
    rigid = params_from_dict(raw, "rigid-set")
    _, alpha, theta = _consistent(params, [[20, -10, 30]], [[30, 25, 20, 40]])
    force = np.array([[30, 25, 20, 40]], dtype=float)
    s, r = residuals(detector_model(rigid), theta, alpha, force)
    assert np.abs(s).max() < 1e-12 and np.abs(r).max() < 1e-12, (s, r)


def test_the_residual_is_near_zero_on_the_model_truth(params):
    """On the twin of the parameter file the check's only error is its stretch at rest, where the
    model's 3000 N·s/m cable damper carries part of the tension while moving (3.5 mm measured,
    docs/safety.md); at rest after the move it is the encoders' resolution."""
    traj = Trajectory.from_degrees([[0, 0, 0], [20, -10, 15]], 2.0, [0.0, 3.0], name="pose")
    fault_at, why, check, s = _campaign(params, traj, truth="model")
    assert math.isnan(fault_at), why
    assert s.max() < 0.5 * THRESHOLD_M
    assert abs(check.s) < 5e-5  # m: at rest on the pose (4 µm measured; an encoder count is 2.5 µm of cable)


def test_a_normal_robot_truth_campaign_raises_no_fault(params):
    """§7 control test, law 2, on the robot truth (stiction, creep, backlash, pulley errors):
    quiet, with the margin the threshold was chosen with (normal |s| max 5.7 mm, 1.5 × → 9 mm)."""
    fault_at, why, _, s = _campaign(params, control_test_trajectory())
    assert math.isnan(fault_at), why
    assert len(s) > 6500  # the whole campaign ran
    assert s.max() < THRESHOLD_M / 1.5


@pytest.mark.parametrize("encoder", [0, 1, 2, 3])
def test_a_stuck_encoder_is_flagged_and_named_within_a_second(params, encoder):
    """Frozen at 3.9 s, just before the neck leaves (50, 50, 50)°: measured 0.7-0.9 s to the
    fault, the frozen one named first (docs/safety.md, "Stuck encoder")."""
    t_freeze = 3.9
    fault_at, why, check, _ = _campaign(params, control_test_trajectory(), freeze=(encoder, t_freeze))
    assert not math.isnan(fault_at), "the stuck encoder was not detected"
    assert t_freeze < fault_at <= t_freeze + 1.2
    assert check.suspects[0] == encoder, why
    assert why.startswith(f"encoder {encoder + 1} ") and "stuck" in why and why.endswith("encoder fault")


def test_one_tick_beyond_the_threshold_does_not_latch_a_sustained_one_does(params):
    m, alpha, theta = _consistent(params, [10, 20, -15], [20, 20, 20, 30])
    force, still = np.array([20, 20, 20, 30.0]), np.zeros(4)
    check = EncoderConsistency(params)
    jump = theta.copy()
    jump[1] += 2 * THRESHOLD_M / m.rho / 0.4  # ≥ 2 thresholds of parity (n_j ≥ 0.4)
    dt = 0.002
    assert check.update(theta, alpha, force, still, 0.0) == ""
    assert check.update(jump, alpha, force, still, dt) == ""  # one tick
    assert abs(check.s) > THRESHOLD_M
    assert check.update(theta, alpha, force, still, 2 * dt) == ""
    # Sustained, but with the drives not active: no fault, and the persistence starts again.
    for k in range(40):
        assert check.update(jump, alpha, force, still, (3 + k) * dt, active=False) == ""
    k0 = 43
    reasons = [check.update(jump, alpha, force, still, (k0 + k) * dt) for k in range(40)]
    first = next(k for k, why in enumerate(reasons) if why)
    assert first * dt == pytest.approx(PERSISTENCE_S, abs=dt / 2)


def test_a_clock_step_told_of_is_no_persistence(params):
    """Review of session 53: a step of the states' clock under the 5 s that abort a campaign (NTP)
    left the check's times on the old clock, so a residual above the threshold for one tick and a
    step forward made a fault at the next tick. A step the controller is told of is no time."""
    m, alpha, theta = _consistent(params, [10, 20, -15], [20, 20, 20, 30])
    force, still = np.array([20, 20, 20, 30.0]), np.zeros(4)
    jump = theta.copy()
    jump[1] += 2 * THRESHOLD_M / m.rho / 0.4
    dt, step = 0.002, 1.0
    check = EncoderConsistency(params)
    assert check.update(theta, alpha, force, still, 0.0) == ""
    assert check.update(jump, alpha, force, still, dt) == ""
    check.clock_stepped(step)
    assert check.update(jump, alpha, force, still, 2 * dt + step) == ""  # 2 ms above it, not 1 s
    reasons = [check.update(jump, alpha, force, still, (3 + k) * dt + step) for k in range(40)]
    first = next(k for k, why in enumerate(reasons) if why)
    assert (first + 2) * dt == pytest.approx(PERSISTENCE_S, abs=dt / 2)


@pytest.mark.parametrize("bad", ["theta", "alpha", "force", "theta_dot", "stamp"])
def test_non_finite_input_is_a_fault_at_once_not_an_exception(params, bad):
    _, alpha, theta = _consistent(params, [10, 20, -15], [20, 20, 20, 30])
    inputs = {"theta": theta, "alpha": alpha, "force": np.array([20, 20, 20, 30.0]), "theta_dot": np.zeros(4)}
    check = EncoderConsistency(params)
    assert check.update(inputs["theta"], inputs["alpha"], inputs["force"], inputs["theta_dot"], 0.0) == ""
    stamp = 0.002
    if bad == "stamp":
        stamp = math.nan
    else:
        inputs[bad] = inputs[bad].copy()
        inputs[bad][0] = math.nan if bad != "force" else math.inf
    why = check.update(inputs["theta"], inputs["alpha"], inputs["force"], inputs["theta_dot"], stamp)
    assert "non-finite" in why and why.endswith("encoder fault")
    m = detector_model(params)
    s, r = residuals(m, inputs["theta"], inputs["alpha"], inputs["force"], inputs["theta_dot"])
    if bad != "stamp":
        assert math.isnan(float(s)) and np.isnan(r).all()


def test_the_controller_service_aborts_a_campaign_on_a_stuck_encoder_and_holds(params):
    """Wired into the service (``CampaignService._encoder_fault``): encoder 2 freezes mid-move, the
    campaign ends ``aborted`` naming it, and the hold latches; with the check off it went on."""
    from test_controller_service import Loop, _request

    from controller.trajectory import Trajectory

    swing = Trajectory.from_degrees([[0, 0, 0], [30, -20, 10], [0, 0, 0]], 3.0, 0.2, name="swing")
    outcomes = {}
    for threshold in (None, THRESHOLD_M):
        loop = Loop(params)
        loop.svc.encoder_threshold_m = threshold
        loop.svc.encoder_check = loop.svc._make_encoder_check()
        loop.svc.handle(_request("c-1", trajectory_json=swing.to_json()), loop.stamp_s)
        loop.run(1.0)
        frozen = float(loop.tick.theta_meas[1])
        for _ in range(1000):  # 2 s with encoder 2 stuck
            theta = np.array(loop.tick.theta_meas, dtype=float)
            theta[1] = frozen
            out = loop.svc.control(theta, loop.stamp_s)
            if out.law_ran:
                loop.svc.advance(loop.stamp_s)
            loop.events += loop.svc.drain_events()
            loop.tick = loop.twin.tick(out.force_N)
        ended = [e for e in loop.events if e.campaign_id == "c-1" and e.event in ("finished", "aborted")]
        outcomes[threshold] = (ended[-1].event, ended[-1].message) if ended else ("running", "")
        if threshold is not None:
            assert loop.svc.latched and "encoder 2 stuck" in loop.svc.hold_reason
    assert outcomes[None][0] == "running", outcomes
    assert outcomes[THRESHOLD_M][0] == "aborted" and "encoder 2 stuck" in outcomes[THRESHOLD_M][1], outcomes


@pytest.mark.parametrize("seed", [0, 1])
def test_no_stuck_encoder_fault_when_the_drives_come_back_from_an_estop_with_slack_cables(params, seed):
    """Audit of 2026-11-26: at [35, −25, 20]° an e-stop lets the neck fall back on slack cables;
    on release, while the bridge's ramp takes the slack up, the parity reached −13 mm and latched
    "encoder 1 stuck" 60 ms after the enable (4 seeds of 4). The check waits for the cables to be
    taut again after the drives were off."""
    from bridge_loop import BridgeLoop
    from test_console_jog_service import _jog

    loop = BridgeLoop(params, seed=seed)
    loop.run(1.0)
    loop.svc.handle(_jog("j", [35.0, -25.0, 20.0]), loop.stamp_s)
    loop.run(4.0)
    loop.run(3.0, estop=((True, "test"),))
    assert loop.safety.drive == "disabled"
    loop.run(3.0, estop=((False, "test"),))
    assert loop.safety.drive == "active" and not loop.svc.latched, loop.svc.hold_reason


#: (params, seed) → the loop :func:`_dropped_on_slack_cables` returns, simulated once per process
_DROPPED: dict[tuple[int, int], tuple[Any, Any]] = {}


def _dropped_on_slack_cables(params, seed: int):
    """The audit of 2026-11-28 (its `s8_estop_release_encoder.sh` on `xneck up`, 3 runs of 3): an
    e-stop through the console 4.5 s into the §7 control test (law 2, robot truth), the neck
    moving down from (50, 50, 50)°, released 2 s later. The neck falls with the drives off; the
    three right cables go slack and the motors' stiction (19-24 N) holds their drums against the
    hold's forces (t_min = 8.5 N) after the release. Returns the loop at the release: a deep copy
    of one simulated once per parameter set and seed (7.5 s of ticks, 0.7 s of CPU, asked for by
    some 25 tests of test_take_up, test_encoder_check and test_bridge_hold_damping). The run is
    deterministic from its seed, and a copy holds no mutable state of the original (the params,
    frozen, are shared): each test continues a loop of its own, tick for tick the one it would
    have simulated."""
    from bridge_loop import BridgeLoop
    from test_controller_service import _request

    key = (id(params), seed)
    if key not in _DROPPED or _DROPPED[key][0] is not params:
        loop = BridgeLoop(params, seed=seed)
        loop.run(1.0)
        loop.svc.handle(_request("c-1", trajectory_json=control_test_trajectory().to_json()), loop.stamp_s)
        loop.run(4.5)
        loop.run(2.0, estop=((True, "audit"),))
        _DROPPED[key] = (params, loop)
    loop = copy.deepcopy(_DROPPED[key][1], {id(params): params})
    assert loop.safety.drive == "disabled"
    return loop


def _until_ended(loop, cid: str, seconds: int = 25) -> list:
    ended: list = []
    for _ in range(seconds):
        loop.run(1.0)
        ended = [e for e in loop.events if e.campaign_id == cid and e.event in ("finished", "aborted")]
        if ended:
            break
    return ended


@pytest.mark.parametrize("seed", [0, 1])
def test_no_stuck_encoder_fault_after_an_estop_drops_a_moving_neck_on_slack_cables(params, seed):
    """Audit of 2026-11-28: "encoder 1 or 4 stuck ... −64.6 mm" about 0.55 s after the release,
    with healthy encoders (here 0.56 s after it, "encoder 4 or 2 stuck"). The check allows the
    slack it measured when the drives came back (controller/encoder_check.py, "Slack") while the
    controller takes it up (controller/take_up.py), and a campaign sent meanwhile with its
    parameter set, as the console sends it, runs after the take-up without a fault."""
    from test_controller_service import _request

    loop = _dropped_on_slack_cables(params, seed)
    loop.run(0.45, estop=((False, "audit"),))
    assert loop.safety.drive == "active" and not loop.svc.latched, loop.svc.hold_reason
    # What the check saw: three cables still slack, the encoders beyond the threshold (what the
    # check blind to slack latched on), all of it allowed as the slack of the release.
    check = loop.svc.encoder_check
    assert check is not None
    assert loop.tick.slack[:3].all() and loop.svc.taking_up
    assert check.s < -THRESHOLD_M and check.slack_m > THRESHOLD_M
    # The next campaign with a set of its own: the service builds the check anew for its
    # geometry once the take-up is over, and the slack allowed goes with it.
    loop.svc.handle(_request("c-2", trajectory_json=control_test_trajectory().to_json(),
                             parameters_toml=params.to_toml()), loop.stamp_s)
    ended = _until_ended(loop, "c-2")
    assert [e.event for e in ended] == ["finished"], [e.message for e in ended]
    assert loop.svc.encoder_check is not check
    assert not loop.svc.latched and loop.svc.encoder_check.slack_m == 0.0  # taut: the check is as before


@pytest.mark.parametrize("encoder", [0, 1, 2, 3])
def test_a_stuck_encoder_on_the_slack_cables_of_an_estop_is_caught(params, encoder):
    """The allowance for slack does not hide a stuck encoder: frozen 0.6 s after the release (the
    check judging again, the slack allowed), while the take-up winds the cables in, it latches
    the hold during the take-up or within 2 s of the next campaign's start."""
    from test_controller_service import _request

    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.6, estop=((False, "audit"),))
    check = loop.svc.encoder_check
    assert check is not None
    assert not loop.svc.latched and check.slack_m > THRESHOLD_M and loop.svc.taking_up
    stuck = {encoder: float(loop.tick.theta_meas[encoder])}
    loop.run(3.5, stuck=stuck)
    if not loop.svc.latched:
        loop.svc.handle(_request("c-2", trajectory_json=control_test_trajectory().to_json(),
                                 parameters_toml=params.to_toml()), loop.stamp_s)
        t_start = loop.stamp_s
        while not loop.svc.latched and loop.stamp_s < t_start + 2.0:
            loop.run(0.002, stuck=stuck)
    assert loop.svc.latched, f"encoder {encoder + 1} stuck, not detected"
    why = loop.svc.hold_reason
    assert "stuck" in why and why.endswith("encoder fault"), why


def test_the_slack_measured_as_the_drives_come_back_is_allowed_and_only_it(params):
    """EncoderConsistency alone (its module docstring, "Slack"): cable 1 paid out 30 mm beyond its
    path while the drives were off. Measured while they come back (``settling``, zero force), that
    slack is allowed once they apply forces again, though the parity is beyond the threshold. A
    further shortfall of two thresholds (an encoder stuck while its motor winds in) latches after
    the usual persistence; a parity above the threshold (an encoder stuck while its motor pays
    out: slack only ever lowers it) ends the allowance and latches once the snap's
    ``SLACK_SETTLE_S`` has passed."""
    alpha_deg, force = [10, 20, -15], np.array([20, 20, 20, 30.0])
    m, alpha, taut = _consistent(params, alpha_deg, force)  # the encoders of taut, stretched cables
    still, dt = np.zeros(4), 0.002
    slack = taut.copy()
    slack[0] = _consistent(params, alpha_deg, np.zeros(4))[2][0] - 0.03 / m.rho  # no stretch, 30 mm slack

    def settled(check):
        for k in range(250):  # the service's settling window, forces ramping from zero (zero here)
            assert check.update(slack, alpha, np.zeros(4), still, k * dt, active=False, settling=True) == ""
        assert check.slack_m > THRESHOLD_M  # the parity of that slack alone is beyond the threshold
        return 250 * dt

    check = EncoderConsistency(params)
    t = settled(check)
    for k in range(100):
        assert check.update(slack, alpha, force, still, t + k * dt) == "", check.s
    assert check.s < -THRESHOLD_M and check.slack_m > THRESHOLD_M / 2  # allowed, not forgotten
    t += 100 * dt
    wound = slack.copy()
    wound[1] -= 2 * THRESHOLD_M / m.rho / 0.4  # encoder 2 misses ≥ 2 thresholds of parity of winding in
    reasons = [check.update(wound, alpha, force, still, t + k * dt) for k in range(40)]
    first = next(k for k, why in enumerate(reasons) if why)
    assert first * dt == pytest.approx(PERSISTENCE_S, abs=dt / 2)
    assert "slack the cables had when the drives came back" in reasons[first]

    check = EncoderConsistency(params)
    t = settled(check)
    assert check.update(slack, alpha, force, still, t) == ""
    paid = slack.copy()
    paid[1] += (-check.s + 2 * THRESHOLD_M) / m.rho / 0.4  # encoder 2 misses a paying out: s ≥ +thr
    reasons = [check.update(paid, alpha, force, still, t + (1 + k) * dt) for k in range(400)]
    assert check.slack_m == 0.0 and check.s > THRESHOLD_M
    first = next(k for k, why in enumerate(reasons) if why)
    assert first * dt == pytest.approx(SLACK_SETTLE_S + PERSISTENCE_S, abs=dt / 2)  # after the snap's settling
    assert "slack" not in reasons[first] and reasons[first].endswith("encoder fault")
