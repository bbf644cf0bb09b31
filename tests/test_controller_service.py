"""The controller's campaign service as a pure state machine (issue 12): its life cycle, holds and
request handling, against the twin's simulator in the same process, without any bus."""

from __future__ import annotations

import json
import math
from typing import Literal

import msgspec
import numpy as np
import pytest

from bridge import bus
from bridge.safety import Inputs, Ownership, Safety, SafetyConfig
from controller.laws import LawConfig, hold_forces
from controller.prepare import Refused, prepare
from controller.service import MOTOR_SPEED_MAX_RAD_S, CampaignService
from controller.state_gate import StateGate
from controller.trajectory import Trajectory
from twin.sim.simulator import Twin, TwinConfig

NOD = Trajectory.from_degrees([[0, 0, 0], [10, 5, 0]], 1.0, 0.2, name="nod")


def _request(cid="c-1", action: Literal["start", "stop"] = "start", trajectory_json=NOD.to_json(),
             **kw) -> bus.CampaignRequest:
    return bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id=cid, action=action, trajectory_json=trajectory_json, **kw)


def _robot_loop(params, law: int, seed: int):
    """The service (law ``law``) on the robot truth through the bridge's safety rules, the pieces
    a test steps by hand: (twin, service, safety, the bridge's hold rule, motor speeds, first tick)."""
    from bridge.motor_speed import MotorSpeed
    from controller.laws import encoder_hold_forces

    twin = Twin(params, TwinConfig(camera=False, seed=seed, truth="robot"))
    svc = CampaignService(params, LawConfig(law=law), settle_s=0.5, service=True)
    safety = Safety(SafetyConfig(n_motors=params.n_cables, f_min_N=params.limits.f_min, f_max_N=params.limits.f_max))
    hold_rule, speed = encoder_hold_forces(params), MotorSpeed(params.n_cables, 0.002)
    tick = twin.tick(np.zeros(params.n_cables))
    svc.initialise(tick.theta_meas)
    return twin, svc, safety, hold_rule, speed, tick


class Loop:
    """The service closed on the simulator, one state per 2 ms: what the bus shell does."""

    def __init__(self, params, service=True):
        self.twin = Twin(params, TwinConfig(camera=False, seed=1))
        self.svc = CampaignService(params, LawConfig(law=2), service=service, settle_s=0.2)
        self.tick = self.twin.tick(np.zeros(params.n_cables))
        self.svc.initialise(self.tick.theta_meas)
        self.events: list = []
        self.outputs: list = []

    @property
    def stamp_s(self) -> float:
        return self.tick.t_s

    def run(self, seconds: float, theta=None) -> None:
        for _ in range(round(seconds * 500)):
            out = self.svc.control(self.tick.theta_meas if theta is None else theta, self.stamp_s)
            self.outputs.append(out)
            if out.law_ran:
                self.svc.advance(self.stamp_s)
            self.events += self.svc.drain_events()
            self.tick = self.twin.tick(out.force_N)


@pytest.fixture
def loop(params):
    return Loop(params)


def test_idle_service_holds_the_neck_where_it_started(loop):
    loop.run(0.5)
    assert loop.svc.phase == "idle" and not loop.events
    assert np.degrees(np.abs(loop.tick.alpha)).max() < 1.0
    assert all(o.law_ran and np.all(np.isfinite(o.force_N)) for o in loop.outputs)


def test_a_requested_campaign_runs_to_finished_and_then_holds_its_last_waypoint(loop):
    loop.svc.handle(_request(), loop.stamp_s)
    assert loop.svc.phase == "running"
    loop.run(NOD.duration_s + 0.2 + 0.05)
    kinds = [e.event for e in loop.events]
    assert kinds[0] == "started" and kinds[-1] == "finished" and "progress" in kinds
    assert all(e.campaign_id == "c-1" for e in loop.events)
    assert loop.svc.phase == "finished" and not loop.svc.running
    np.testing.assert_allclose(loop.svc.hold_target, NOD.waypoints_rad[-1])
    assert np.degrees(np.abs(loop.tick.alpha - NOD.waypoints_rad[-1])).max() < 2.0  # law 2 with rigid cables in α̂


def test_stop_aborts_the_running_campaign_and_a_second_start_is_refused(loop):
    loop.svc.handle(_request("c-1"), loop.stamp_s)
    loop.run(0.1)
    loop.svc.handle(_request("c-2"), loop.stamp_s)
    loop.svc.handle(_request("c-other", action="stop"), loop.stamp_s)  # not the running one: ignored
    loop.svc.handle(_request("c-1", action="stop"), loop.stamp_s)
    events = loop.events + loop.svc.drain_events()
    refused = [e for e in events if e.campaign_id == "c-2"]
    assert [e.event for e in refused] == ["aborted"] and "running campaign c-1" in refused[0].message
    stopped = [e for e in events if e.campaign_id == "c-1"][-1]
    assert stopped.event == "aborted" and stopped.message == "stopped by the user" and 0 < stopped.progress < 1
    assert loop.svc.phase == "aborted" and not loop.svc.running


def test_a_request_stopped_while_prepared_never_starts_even_when_its_id_is_asked_again(loop, params):
    """The process prepares off its loop: start X, stop X, start Y with X's id (another bus client,
    a console restarted within its second), and X's preparation ends first. Only Y may run: X
    ran instead when the service matched preparations by id alone (audit of 2026-11-27)."""
    far = Trajectory.from_degrees([[0, 0, 0], [30, 0, 0]], 2.0, name="stopped one")
    x, y = _request("jog-1", trajectory_json=far.to_json()), _request("jog-1")
    svc = loop.svc
    assert svc.request_start(x)
    svc.stop("jog-1", loop.stamp_s)
    assert svc.request_start(y)
    svc.prepared(prepare(x, params, svc.law), x, loop.stamp_s)  # X's worker ends first: dropped
    assert not svc.running and svc.phase == "starting"
    svc.prepared(prepare(y, params, svc.law), y, loop.stamp_s)
    assert svc.running and svc.campaign_id == "jog-1"
    loop.run(NOD.duration_s + 0.2 + 0.1)
    events = loop.events
    assert [e.event for e in events][:2] == ["aborted", "started"], events
    assert "stopped by the user before it started" in events[0].message
    np.testing.assert_allclose(svc.hold_target, NOD.waypoints_rad[-1])  # Y's waypoint, not X's 30°


def test_a_trajectory_beyond_the_limits_is_refused_with_the_reason(loop):
    reach = Trajectory.from_degrees([[0, 0, 0], [30, 70, 0]], 3.0)
    loop.svc.handle(_request("c-far", trajectory_json=reach.to_json()), loop.stamp_s)
    (ev,) = loop.svc.drain_events()
    assert ev.event == "aborted" and ev.campaign_id == "c-far" and "waypoint 1" in ev.message
    assert loop.svc.phase == "idle"


def test_a_diverging_estimate_latches_a_hold_at_the_last_sane_estimate(loop, params):
    loop.svc.handle(_request(), loop.stamp_s)
    loop.run(0.3)
    # encoders gone mad, each step one a motor could make (a larger one is an encoder fault, below)
    theta = loop.tick.theta_meas.copy()
    for _ in range(40):
        theta = theta + np.array([3.0, -3.0, 0.0, 0.0])
        loop.run(0.002, theta=theta)
        if loop.svc.latched:
            break
    sane = loop.svc.hold_alpha().copy()
    aborted = [e for e in loop.events if e.event == "aborted"]
    assert len(aborted) == 1 and "diverging estimate" in aborted[0].message, aborted
    assert loop.svc.latched and loop.svc.hold_reason.startswith("diverging")
    loop.run(0.2, theta=theta)  # the hold's forces reached at the law's force rate
    last = loop.outputs[-1]
    assert not last.law_ran
    np.testing.assert_allclose(last.force_N, hold_forces(params, sane))
    # A new campaign lifts the latch.
    loop.svc.handle(_request("c-2", trajectory_json=Trajectory.from_degrees([[0, 0, 0]], [], 0.1).to_json()),
                    loop.stamp_s)
    assert not loop.svc.latched and loop.svc.phase == "running"


def test_a_law_that_computes_non_finite_forces_latches_a_hold_that_sends_finite_ones(loop, params):
    """Session 47: the law's non-finite command (never sent: the divergence check catches it) was
    left as the last command, and the latched hold ramped from it: NaN forces every tick after,
    which the bridge refuses, so the controller's own hold never held. The hold ramps from what
    was last sent."""
    loop.svc.handle(_request(), loop.stamp_s)
    loop.run(0.3)
    sent = loop.outputs[-1].force_N.copy()
    law_step = loop.svc.ctl.step

    def broken(*args, **kwargs):
        cmd = law_step(*args, **kwargs)
        cmd.f[:] = np.nan
        loop.svc.ctl.f_prev[:] = np.nan  # as the law's kernel leaves it
        return cmd

    loop.svc.ctl.step = broken  # type: ignore[method-assign]
    loop.run(0.002)
    loop.svc.ctl.step = law_step  # type: ignore[method-assign]
    assert loop.svc.latched and loop.svc.hold_reason.startswith("diverging"), loop.svc.hold_reason
    loop.run(0.1)
    forces = np.array([o.force_N for o in loop.outputs[-51:]])
    assert np.all(np.isfinite(forces)), forces[:3]
    assert float(np.abs(forces[0] - sent).max()) <= LawConfig(law=2).force_rate_max_N_s / 500.0 + 1e-9
    np.testing.assert_allclose(forces[-1], hold_forces(params, loop.svc.hold_alpha()), atol=1e-6)


def _fast_request(cid="fast"):
    """A validated move at the speed and acceleration limits: 0 → 40° on every joint and back."""
    d = math.radians(40.0)
    t = max(2 * d / 1.5, math.sqrt(2 * math.pi * d / 3.0)) * 1.001
    return _request(cid, trajectory_json=json.dumps({"name": "fast", "waypoints_deg": [[0, 0, 0], [40, 40, 40], [0, 0, 0]],
                                                      "durations_s": [t, t], "dwell_s": 0.0}))


def test_an_encoder_that_jumps_faster_than_a_motor_turns_latches_a_hold(loop):
    """Audit of 2026-11-26: one encoder stepping by 60 rad (and staying there) moved α̂ by a few
    degrees only, so the law drove the real joint 3 to 85°, past its 60° limit, and the campaign
    ended 'finished'. A step no motor can make in the time between two states latches a hold where
    the estimate was, and aborts the campaign."""
    loop.svc.handle(_request(), loop.stamp_s)
    loop.run(0.3)
    before = loop.svc.ctl.estimator.alpha_hat.copy()
    theta = loop.tick.theta_meas.copy()
    theta[2] += 60.0
    loop.run(0.2, theta=theta)
    assert loop.svc.latched and "encoder 3" in loop.svc.hold_reason, loop.svc.hold_reason
    aborted = [e for e in loop.events if e.event == "aborted"]
    assert len(aborted) == 1 and "encoder 3" in aborted[0].message
    np.testing.assert_allclose(loop.outputs[-1].alpha_hat_rad, before, atol=math.radians(0.5))
    assert np.degrees(np.abs(loop.tick.alpha)).max() < 30.0  # the neck stayed where it was


def test_a_latched_hold_never_aims_beyond_the_joint_limit(loop, params):
    """Audit of 2026-11-26: an encoder running away over two ticks left an α̂ of −72.6° (within
    the 80° divergence limit) as the 'last sane' one; the latched hold aimed there, 60 % beyond the
    joint limit, with the neck at 0°. The hold aims within ±alpha_max, as the bridge's own hold does."""
    loop.run(0.3)
    limit = math.radians(params.limits.alpha_max_deg)
    loop.svc.last_sane = np.array([-math.radians(72.6), 0.0, 0.0])  # as the runaway's first tick left it
    loop.svc.ctl.estimator.alpha_hat[:] = [math.radians(-200.0), 0.0, 0.0]
    loop.svc.latched = True
    assert np.abs(loop.svc.hold_alpha()).max() <= limit + 1e-12
    loop.svc.latched = False
    loop.svc.ctl.estimator.alpha_hat[:] = 0.0
    # and the law itself never records one beyond the limit as the place to hold
    loop.svc.handle(_request(), loop.stamp_s)
    loop.run(0.1)
    assert np.abs(loop.svc.last_sane).max() <= limit


def test_every_hold_while_the_bridge_obeys_keeps_the_laws_force_rate(params):
    """Audit of 2026-11-26: the controller's own holds (a stale gap, the divergence latch) sent raw
    hold forces while the bridge was active, which passes them through: 21.9 N in one tick during
    a validated fast move (the law's bound: 10 N), and the law then resumed from its own last
    forces, another 21.9 N. Holds go through the same bound, from what was last commanded."""
    bound = LawConfig(law=2).force_rate_max_N_s / 500.0
    worst = 0.0
    for gap_at in (1.2, 1.45, 1.7, 1.95):
        loop = Loop(params)
        loop.svc.handle(_fast_request(), loop.stamp_s)
        loop.run(gap_at)
        sent = [loop.outputs[-1].force_N]
        for k in range(3):  # three ticks without a state: the process holds
            sent.append(loop.svc.stale("stale state", 0.012 + 0.002 * k).force_N)
        loop.run(0.02)
        sent += [o.force_N for o in loop.outputs[-10:]]
        worst = max(worst, float(np.abs(np.diff(np.array(sent), axis=0)).max()))
    assert worst <= bound + 1e-9, worst


def test_a_new_campaign_after_a_divergence_latch_starts_from_the_encoders(params):
    """Audit of 2026-11-26: after one tick of mad encoders the latched estimator kept α̂ at
    thousands of degrees; a new campaign (or jog) copied it and aborted on its first tick, so only
    a bridge restart recovered. Lifting the latch starts the estimate again from the encoders
    (eq. 33's absolute α̂)."""
    loop = Loop(params)
    loop.run(0.5)
    loop.run(0.002, theta=loop.tick.theta_meas + np.array([1e3, -1e3, 0.0, 0.0]))
    assert loop.svc.latched
    loop.run(0.5)
    loop.svc.handle(_request("c-2", trajectory_json=Trajectory.from_degrees([[0, 0, 0]], [], 0.5).to_json()),
                    loop.stamp_s)
    loop.run(1.5)
    assert [e.event for e in loop.events if e.campaign_id == "c-2"][-1] == "finished", loop.events[-3:]
    assert not loop.svc.latched
    # within eq. 33's own error (it takes the cables as rigid), not thousands of degrees
    np.testing.assert_allclose(loop.svc.ctl.estimator.alpha_hat, loop.tick.alpha, atol=math.radians(2.0))


def test_a_headless_campaign_ends_aborted_on_divergence(params):
    loop = Loop(params, service=False)
    loop.svc.begin(NOD, loop.stamp_s)
    loop.run(0.1)
    loop.run(0.004, theta=np.array([1e3, -1e3, 0.0, 0.0]))
    assert loop.svc.outcome == "aborted" and loop.events[-1].event == "aborted"


# -- issue 13: a controller safe on a hostile bus (pure parts) --------------------------------


class DriveLoop(Loop):
    """The loop with the bridge's drive state: while not "active" the plant gets no force."""

    def run_drive(self, seconds: float, drive: str) -> list:
        outs = []
        for _ in range(round(seconds * 500)):
            on = drive in ("active", "hold")
            applied = self.outputs[-1].force_N if (self.outputs and on) else np.zeros(4)
            out = self.svc.control(self.tick.theta_meas, self.stamp_s, drive=drive, force_applied_N=applied)
            outs.append(out)
            self.outputs.append(out)
            if out.law_ran:
                self.svc.advance(self.stamp_s)
            self.events += self.svc.drain_events()
            # In a hold the bridge applies its own hold forces (at its estimate, here the truth).
            bridge = hold_forces(self.svc.params, self.tick.alpha) if drive == "hold" else out.force_N
            self.tick = self.twin.tick(bridge if on else np.zeros(4))
        return outs


def test_drives_off_send_only_hold_forces_and_re_enable_starts_from_the_estimate(params):
    """Finding 1: with the drives disabled the law neither winds up nor steps when they return."""
    loop = DriveLoop(params)
    loop.run_drive(0.3, "active")
    before = loop.outputs[-1].force_N
    off = loop.run_drive(2.0, "disabled")
    assert not any(o.law_ran for o in off)  # holds only: no PID, no integral
    for o in off[::50]:
        np.testing.assert_allclose(o.force_N, hold_forces(params, o.alpha_hat_rad), atol=1e-9)
    assert np.all(loop.svc.ctl.integral == 0)
    assert loop.svc.hold_reason.startswith("drives disabled")
    inactive = loop.run_drive(0.004, "inactive")  # released: the bridge waits for a command
    assert not inactive[-1].law_ran
    # After an e-stop the slack is taken up first (controller/take_up.py, tests/test_take_up.py):
    # holds on a rising floor, then the law from α̂.
    back = loop.run_drive(0.1, "active")
    assert not any(o.law_ran for o in back) and "slack" in loop.svc.hold_reason, loop.svc.hold_reason
    back += loop.run_drive(3.9, "active")
    first = next(k for k, o in enumerate(back) if o.law_ran)
    assert all(o.law_ran for o in back[first:])
    np.testing.assert_allclose(back[first].alpha_d_rad, back[first].alpha_hat_rad, atol=1e-3)  # α^d starts at α̂
    steps = np.abs(np.diff([o.force_N for o in [inactive[-1], *back]], axis=0)).max()
    assert steps < 2.0, steps  # no force step as the floor rises, nor when the law takes over again
    assert np.abs(back[-1].force_N - before).max() < 15.0


def test_a_campaign_during_which_the_drives_are_disabled_ends_aborted(params):
    loop = DriveLoop(params)
    loop.svc.handle(_request(), loop.stamp_s)
    loop.run_drive(0.2, "active")
    loop.svc.drive_reason = "e-stop: console"
    loop.run_drive(0.01, "disabled")
    ev = [e for e in loop.events if e.event == "aborted"]
    assert len(ev) == 1 and "drives disabled" in ev[0].message
    loop.svc.handle(_request("c-2"), loop.stamp_s)  # cannot start while disabled
    (refused,) = loop.svc.drain_events()
    assert refused.event == "aborted" and "drives disabled" in refused.message


def test_a_controller_the_bridge_does_not_obey_only_observes_and_takes_over_without_a_step(params):
    """Audit of 2026-11-26: a second controller (another stack) ran its law on the states of a
    bridge that refused its commands; its integral wound up to [100, 100, 100, 8.5] N and when the
    owner's session ended 2 s into a campaign the applied forces stepped by 91.5 N in one tick. Closed
    on the twin through the bridge's own rules (Safety, Ownership): the refused controller only
    observes (hold forces at its α̂), and after the handover the forces move at most 1 N per tick
    and the neck stays where the old owner left it. A campaign on a controller the bridge does not
    obey is aborted with the reason."""
    twin = Twin(params, TwinConfig(camera=False, seed=1))
    tick = twin.tick(np.zeros(params.n_cables))
    a, b = (CampaignService(params, LawConfig(law=2), service=True, settle_s=5.0) for _ in range(2))
    for svc in (a, b):
        svc.initialise(tick.theta_meas)
    safety = Safety(SafetyConfig(n_motors=params.n_cables, f_min_N=params.limits.f_min,
                                 f_max_N=params.limits.f_max, max_force_step_N=1.0))
    owner = Ownership("e1")
    owner.appeared("A")
    owner.appeared("B")
    a.handle(_request(), tick.t_s)
    switch, applied, alpha = 1000, [], []
    for k in range(switch + 300):
        if k == switch:
            owner.vanished("A")  # A's session ends 2 s into its campaign
        outs = {}
        for name, svc in (("A", a), ("B", b)):
            if name == "A" and k >= switch:
                continue
            obeyed = owner.owner in ("", name)
            outs[name] = svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force), obeyed)
            if outs[name].law_ran:
                svc.advance(tick.t_s)
            svc.drain_events()
            if name == "B" and k < switch:
                assert not outs[name].law_ran and np.all(svc.ctl.integral == 0)
        command = next(outs[n].force_N for n in ("A", "B") if n in outs and owner.admit(n, "e1") == "")
        decision = safety.step(Inputs(command_N=command.tolist(), command_age_s=0.0, states_unanswered=0,
                                      sender=owner.owner))
        applied.append(decision.force_N)
        tick = twin.tick(decision.force_N)
        alpha.append(tick.alpha)
    steps = np.abs(np.diff(np.array(applied), axis=0)).max(axis=1)
    print(f"\nlargest force step across the handover: {steps[switch - 5:].max():.2f} N per tick")
    assert owner.owner == "B" and b.drive == "active"
    assert steps[switch - 5:].max() <= 1.0 + 1e-9
    moved = np.degrees(np.abs(np.array(alpha[switch:]) - alpha[switch - 1]).max())
    assert moved < 1.0, moved
    # B's own campaign while A owns the bridge: aborted, with the reason.
    b.handle(_request("c-2"), tick.t_s)
    owner.owner = "A"
    b.drive_reason = "the bridge obeys controller A, not this one"
    b.control(tick.theta_meas, tick.t_s, "active", np.asarray(safety.force), obeyed=False)
    (*_, ended) = b.drain_events()
    assert ended.event == "aborted" and "obeys controller A" in ended.message


def test_leaving_a_hold_blends_the_reference_from_the_estimate_back_to_the_trajectory(params):
    loop = DriveLoop(params)
    loop.svc.handle(_request(), loop.stamp_s)
    loop.run_drive(0.5, "active")
    held = loop.run_drive(0.3, "hold")  # the bridge's watchdog held: the law goes on for a tick,
    assert held[0].law_ran  # then (HOLD_RESTART_S) it re-starts, holding at α̂
    assert not any(o.law_ran for o in held[2:]) and loop.svc.hold_reason.startswith("drives hold")
    back = loop.run_drive(2.5, "active")
    np.testing.assert_allclose(back[0].alpha_d_rad, back[0].alpha_hat_rad, atol=1e-3)
    assert np.abs(np.diff(np.array([o.alpha_d_rad for o in back]), axis=0)).max() < math.radians(0.5)
    assert loop.events[-1].event == "finished"


def _state(stamp_s, epoch="e1", bridge="b1", seq=1):
    return bus.MotorState(seq=seq, stamp_s=stamp_s, theta_rad=[0.0] * 4, force_applied_N=[0.0] * 4,
                          drive="active", epoch=epoch, bridge=bridge)


def test_the_gate_takes_states_of_one_bridge_run_on_a_consistent_clock():
    """Finding 3: a forged stamp from the future or another bridge run is refused; real states go on."""
    gate = StateGate()
    assert gate.admit(_state(5.000), now_s=100.000) == ""
    assert "ahead" in gate.admit(_state(1e12), now_s=100.001)
    assert gate.admit(_state(5.002), now_s=100.002) == ""  # real states keep flowing
    assert "back in time" in gate.admit(_state(4.0), now_s=100.003)
    assert gate.admit(_state(5.002), now_s=100.004) == ""  # a lockstep re-publication
    assert "bound to" in gate.admit(_state(0.0, epoch="forged"), now_s=100.005)
    # A restarted bridge (new epoch, new instance, stamps from 0) once the old run fell silent:
    # taken at its second state (a lone state after a silence may be forged, the next test).
    assert "confirms" in gate.admit(_state(0.0, epoch="e2", bridge="b2"), now_s=100.5)
    assert gate.admit(_state(0.002, epoch="e2", bridge="b2"), now_s=100.502) == "" and gate.epoch == "e2"
    assert gate.admit(_state(0.004, epoch="e2", bridge="b2"), now_s=100.504) == ""
    assert gate.admit(_state(5.004), now_s=100.503) != ""  # the old run is not taken back


def test_a_forged_state_after_a_stall_is_not_taken_and_a_stepped_clock_is():
    """Found under load (two test suites at once): the controller's CPU stalled longer than
    ``rebind_s``, the next state to arrive was a forged one of the same run stamped 1e12 s, the
    gate bound to it and the controller answered it, then refused the real states as going back
    in time until the next re-bind. After a stall, a stamp far ahead of the run's clock is only a
    candidate: taken when the next state confirms it (a bridge whose clock stepped), dropped when a
    real one comes first."""
    gate = StateGate()
    assert gate.admit(_state(5.000), now_s=100.000) == ""
    # 0.4 s of stall, then the forged state arrives first, then the real ones
    assert "ahead" in gate.admit(_state(1e12), now_s=100.400)
    assert gate.admit(_state(5.400), now_s=100.401) == ""
    assert gate.admit(_state(5.402), now_s=100.402) == ""
    assert "ahead" in gate.admit(_state(1e12), now_s=100.403)  # bound again: never taken
    # A bridge whose clock stepped 10 s forward: taken at its second state, and followed.
    assert "ahead" in gate.admit(_state(15.800), now_s=100.800)
    assert gate.admit(_state(15.802), now_s=100.802) == ""
    assert gate.admit(_state(15.804), now_s=100.804) == ""
    assert "back in time" in gate.admit(_state(5.806), now_s=100.806)


class _SteppingClock:
    """The service on the simulator behind a StateGate whose bridge's clock steps by ``off`` (s)
    when told: what ControllerNode._on_state does with the gate's word."""

    def __init__(self, params) -> None:
        self.loop, self.gate = Loop(params), StateGate()
        self.off, self.wall0 = 0.0, 1000.0

    def state(self, stamp_s: float) -> bus.MotorState:
        return bus.MotorState(seq=1, stamp_s=stamp_s, theta_rad=self.loop.tick.theta_meas.tolist(),
                              force_applied_N=[0.0] * 4, drive="active", epoch="e1", bridge="b1")

    def ticks(self, seconds: float) -> None:
        loop = self.loop
        for _ in range(round(seconds * 500)):
            stamp, now = loop.stamp_s + self.off, self.wall0 + loop.stamp_s
            if self.gate.admit(self.state(stamp), now) == "":
                if self.gate.stepped_s is not None:
                    loop.svc.clock_stepped(self.gate.stepped_s, stamp)
                out = loop.svc.control(loop.tick.theta_meas, stamp)
                if out.law_ran:
                    loop.svc.advance(stamp)
            else:  # the process's loop holds on stale states
                out = loop.svc.stale("stale state", 0.05)
            loop.outputs.append(out)
            loop.events += loop.svc.drain_events()
            loop.tick = loop.twin.tick(out.force_N)


STEPPING_TRAJECTORY = Trajectory.from_degrees([[0, 0, 0], [20, 10, 0], [0, 0, 0]], 2.0, 0.5, name="t")


@pytest.mark.parametrize("step_s", [100.0, -100.0])
def test_a_campaign_on_a_bridge_clock_that_steps_ends_aborted_and_the_law_restarts_bumplessly(params, step_s):
    """Audit of 2026-11-27: the gate re-binds to the bridge's own run once its wall clock stepped
    (NTP; the BeagleBone has no RTC battery), and the trajectory runs on the states' stamps: 100 s
    forward, a campaign 1.5 s into its 5.5 s ended 'finished' on the next tick, most of it never
    run; 100 s back, it went on for 100 s more. The step ends it 'aborted' with the reason, and
    the law re-starts from the measurement without a force step."""
    run = _SteppingClock(params)
    loop = run.loop
    loop.svc.handle(_request("c", trajectory_json=STEPPING_TRAJECTORY.to_json()), loop.stamp_s)
    run.ticks(1.5)
    assert loop.svc.running
    run.off = step_s
    run.ticks(1.0)
    final = [e for e in loop.events if e.event in ("finished", "aborted")]
    assert [e.event for e in final] == ["aborted"] and "clock stepped by" in final[0].message, final
    assert final[0].progress < 0.5, final[0].progress
    assert not loop.svc.running and run.gate.stepped_s is None
    forces = np.array([o.force_N for o in loop.outputs])
    assert np.abs(np.diff(forces, axis=0)).max() <= LawConfig(law=2).force_rate_max_N_s / 500.0 + 1e-9
    run.ticks(1.0)  # held where it is, and a new campaign runs on the new clock
    loop.svc.handle(_request("c-2", trajectory_json=Trajectory.from_degrees([[0, 0, 0]], [], 0.2).to_json()),
                    loop.stamp_s + run.off)
    run.ticks(2.5)
    assert [e.event for e in loop.events if e.campaign_id == "c-2"][-1] == "finished"


def test_a_re_bind_of_half_a_second_under_load_does_not_end_the_campaign(params):
    """A fresh-clone CI run (2026-11-27) under `xneck up`: the twin's clock and the controller's view
    of it drifted 0.53 s apart under load, the gate re-bound, and the step check aborted a healthy
    campaign. Steps under CLOCK_STEP_ABORT_S leave it running, as before the check."""
    from controller.service import CLOCK_STEP_ABORT_S

    run = _SteppingClock(params)
    loop = run.loop
    loop.svc.handle(_request("c", trajectory_json=STEPPING_TRAJECTORY.to_json()), loop.stamp_s)
    run.ticks(1.5)
    run.off = 0.5
    assert run.off < CLOCK_STEP_ABORT_S
    run.ticks(STEPPING_TRAJECTORY.duration_s)
    final = [e for e in loop.events if e.event in ("finished", "aborted")]
    assert [e.event for e in final] == ["finished"], final


def test_a_stray_run_seen_first_gives_way_to_the_bridge_that_states_at_the_control_rate():
    """Audit of 2026-11-26: the first state ever was bound whatever it was; a forged run seen first
    by a (re)starting controller and kept alive at 10 Hz deafened it to the real bridge (0 of 5000
    states taken over 10 s). A run that states at the law's rate while the bound one does not
    takes over; once bound to it, a slower run never does, nor a faster one beside it."""
    gate = StateGate(rate_hz=500.0)
    assert gate.admit(_state(0.0, epoch="forged", bridge="evil"), now_s=100.0) == ""
    taken = {"real": 0, "forged": 0}
    for k in range(1, 5001):  # 10 s: the bridge at 500 Hz, the forger at 10 Hz
        now = 100.0 + k * 0.002
        taken["real"] += gate.admit(_state(1000.0 + k * 0.002, epoch="real", bridge="b1"), now) == ""
        if k % 50 == 0:
            taken["forged"] += gate.admit(_state(k * 0.002, epoch="forged", bridge="evil"), now) == ""
    assert (gate.bridge, gate.epoch) == ("b1", "real")
    assert taken["real"] >= 4800 and taken["forged"] <= 2, taken
    # Bound to the bridge: a forger at twice the rate beside it is never taken.
    for k in range(5001, 6001):
        now = 100.0 + k * 0.002
        assert gate.admit(_state(1000.0 + k * 0.002, epoch="real", bridge="b1"), now) == ""
        for j in range(2):
            assert gate.admit(_state(k * 0.002 + j * 0.001, epoch="forged", bridge="evil"), now + j * 0.001) != ""
    assert gate.epoch == "real"


@pytest.mark.parametrize("text, reason", [
    ("[]", "object"), ("null", "object"), ("1", "object"), ('"trajectory.json"', "object"),
    ("[" * 5000 + "]" * 5000, "object"), ('{"waypoints_deg": ' + "[" * 5000 + "]" * 5000 + "}", "waypoints_deg"),
    ('{"waypoints_deg": [[0, 0, 0], [1, 1, 1]], "durations_s": [1e300]}', "longer than"),
    ('{"waypoints_deg": [[0, 0, 0], [1, 1, 1]], "durations_s": [-1]}', "duration"),
    ('{"waypoints_deg": [[0, 0, 0], [1, 1, 1]], "durations_s": [1], "dwell_s": 1000}', "longer than"),
    (json.dumps({"waypoints_deg": [[0, 0, 0]] * 5001, "durations_s": 1.0}), "waypoints"),
    ('{"waypoints_deg": [[0, 0, 0], [1, 1]], "durations_s": 1}', "joints"),
    ('{"waypoints_deg": [[0, 0, 0], [1, 1, 1e999]], "durations_s": 1}', "JSON"),
    ("", "no trajectory"), ("{", "JSON"),
])
def test_hostile_trajectories_are_refused_with_a_reason(params, text, reason):
    with pytest.raises(Refused, match=reason):
        prepare(_request(trajectory_json=text), params, LawConfig())


def test_a_trajectory_named_by_path_is_never_opened(params, tmp_path, monkeypatch):
    path = tmp_path / "nod.json"
    path.write_text(NOD.to_json())
    opened = []
    real_open = open
    monkeypatch.setattr("builtins.open", lambda f, *a, **k: (opened.append(str(f)), real_open(f, *a, **k))[1])
    with pytest.raises(Refused):
        prepare(_request(trajectory_json=json.dumps(str(path))), params, LawConfig())
    assert str(path) not in opened


def test_hostile_parameter_sets_are_refused(params):
    for toml in ("a = " + "[" * 3000 + "]" * 3000, "not toml [", "[geometry]\nn_joints = 7\n"):
        with pytest.raises(Refused):
            prepare(_request(parameters_toml=toml), params, LawConfig())


@pytest.mark.parametrize("widened", ["alpha_max_deg = 85.0", "f_max = 400.0", "t_min = 2.0", "f_min = 0.5"])
def test_a_campaigns_parameter_set_never_widens_the_robots_limits(params, widened):
    """Audit of 2026-11-29 (session 40): a request's parameter set with alpha_max_deg 85 and f_max
    400 N had its 80° trajectory validated against its own limits, then adopted: the neck reached
    72° against the robot's 60°, and the campaign ``finished``. The campaign's set is taken with
    each limit no wider than the robot's (the process's ``--params``)."""
    name, value = (x.strip() for x in widened.split("="))
    own = getattr(params.limits, name)
    toml = "\n".join(f"{name} = {value}" if line.split("=")[0].strip() == name and line.lstrip().startswith(name)
                     and "[" not in line else line for line in params.to_toml().splitlines())
    assert toml != params.to_toml(), "the set's limit was not replaced"
    assert getattr(prepare(_request(parameters_toml=toml), params, LawConfig()).params.limits, name) == own
    if name == "alpha_max_deg":  # the audit's case: validated against the robot's 60°
        far = Trajectory.from_degrees([[0, 0, 0], [80, 0, 0]], 4.0, 1.0, name="far")
        with pytest.raises(Refused, match="exceeds"):
            prepare(_request(parameters_toml=toml, trajectory_json=far.to_json()), params, LawConfig())


def test_a_robot_file_tighter_than_the_consoles_set_tightens_its_campaigns(params):
    """Review of session 40: `xneck up --params robot.toml` gives the file to the bridge and the
    controller, not to the console, which sends its own set with every campaign: with a robot
    file of alpha_max_deg 55 every campaign was refused ("beyond the robot's 55°"). It is prepared
    with the robot's limits."""
    robot = msgspec.structs.replace(params, limits=msgspec.structs.replace(params.limits, alpha_max_deg=55.0))
    ok = prepare(_request(parameters_toml=params.to_toml()), robot, LawConfig())
    assert ok.params.limits.alpha_max_deg == 55.0 and ok.params.limits.f_max == params.limits.f_max
    far = Trajectory.from_degrees([[0, 0, 0], [58, 0, 0]], 4.0, 1.0, name="past the robot's 55")
    with pytest.raises(Refused, match="exceeds"):
        prepare(_request(parameters_toml=params.to_toml(), trajectory_json=far.to_json()), robot, LawConfig())


def test_a_campaigns_parameter_set_may_tighten_the_robots_limits(params):
    toml = params.to_toml().replace(f"alpha_max_deg = {params.limits.alpha_max_deg!r}", "alpha_max_deg = 30.0")
    assert "alpha_max_deg = 30.0" in toml
    far = Trajectory.from_degrees([[0, 0, 0], [40, 0, 0]], 4.0, 1.0, name="far")
    with pytest.raises(Refused, match="exceeds"):
        prepare(_request(parameters_toml=toml, trajectory_json=far.to_json()), params, LawConfig())
    assert prepare(_request(parameters_toml=toml), params, LawConfig()).params.limits.alpha_max_deg == 30.0


def test_the_approach_from_the_present_pose_is_validated_too(params):
    """Audit of 2026-11-29 (session 40): the move the service prepends from α̂ to the first
    waypoint was never validated; between (20, 23, −40)° and (−57, −52, 56)°, each a valid pose,
    it asked a cable up to 118 N (f_max 100 N). A request from such a pose is refused, saying
    which move and how to go; from near the first waypoint, or without a pose, it is accepted."""
    there = Trajectory.from_degrees([[-57, -52, 56]], [], name="far jog")
    req = _request(trajectory_json=there.to_json(), kind="jog")
    assert prepare(req, params, LawConfig()).trajectory.n_waypoints == 1  # the pose alone is valid
    with pytest.raises(Refused, match=r"the move from the present pose \[20.0, 23.0, -40.0\]° to the first "
                                      r"waypoint: .*f_max.*; go there through a pose in between"):
        prepare(req, params, LawConfig(), alpha_from_rad=np.radians([20.0, 23.0, -40.0]))
    assert prepare(req, params, LawConfig(), alpha_from_rad=np.radians([-56.8, -52.0, 56.0])).trajectory is not None
    gentle = Trajectory.from_degrees([[10, 5, 0]], [], name="near jog")
    assert prepare(_request(trajectory_json=gentle.to_json(), kind="jog"), params, LawConfig(),
                   alpha_from_rad=np.radians([20.0, 23.0, -40.0])).trajectory is not None


def test_validation_past_its_time_budget_is_refused(params):
    from controller.trajectory import identification_trajectory

    req = _request(trajectory_json=identification_trajectory().to_json(), law=1)
    with pytest.raises(Refused, match="time budget"):
        prepare(req, params, LawConfig(), budget_s=0.05)


def test_counters_are_per_campaign(loop):
    loop.svc.count_timing(True, True)
    loop.svc.count_timing(True, False)
    loop.svc.handle(_request(), loop.stamp_s)
    assert (loop.svc.overruns, loop.svc.deadline_misses) == (0, 0)
    loop.run(0.1)
    loop.svc.count_timing(True, False)
    loop.run(NOD.duration_s + 0.3)
    fin = loop.events[-1]
    assert fin.event == "finished" and (fin.overruns, fin.deadline_misses) == (1, 0) and fin.ticks > 500
    assert "overruns 1, deadline misses 0" in fin.message


def test_a_stale_gap_re_starts_the_law_from_the_measurement(loop):
    """Any gap the process held for (from its stale_s, 10 ms) re-starts the law: α^d from α̂. A
    short one (below 0.1 s) used to let the law go on from the hold (session 46: its commands then
    stepped 10 N a tick back to the law's)."""
    loop.svc.handle(_request(), loop.stamp_s)
    loop.run(0.5)
    assert not loop.svc.stale("stale state", 0.012).law_ran
    loop.run(0.002)
    np.testing.assert_allclose(loop.outputs[-1].alpha_d_rad, loop.outputs[-1].alpha_hat_rad, atol=1e-3)


@pytest.mark.parametrize("law", [2, 1])
def test_a_campaign_started_from_an_idle_hold_on_the_robot_truth_steps_no_force(params, law):
    """Audit of 2026-11-28: under `xneck up` (robot truth) every campaign start stepped the cable
    forces 10 N a tick for several ticks: the new law began with a fresh integral, dropping what
    held the neck against the stiction and the model's errors, and at α̂ instead of where α^d
    rested. The law's integral share, filtered velocities and α^d now go on."""
    loop = Loop.__new__(Loop)
    loop.twin = Twin(params, TwinConfig(camera=False, seed=1, truth="robot"))
    loop.svc = CampaignService(params, LawConfig(law=2), service=True, settle_s=0.2)
    loop.tick = loop.twin.tick(np.zeros(params.n_cables))
    loop.svc.initialise(loop.tick.theta_meas)
    loop.events, loop.outputs = [], []
    loop.run(6.0)  # the idle hold's integral takes up what the model does not know
    idle = np.array([o.force_N for o in loop.outputs[-500:]])
    n0 = len(loop.outputs)
    loop.svc.handle(_request(trajectory_json=NOD.to_json(), law=law), loop.stamp_s)
    loop.run(0.5)
    assert "started" in [e.event for e in loop.events]
    forces = np.array([o.force_N for o in loop.outputs[n0 - 1:]])
    idle_step = float(np.abs(np.diff(idle, axis=0)).max())
    start_step = float(np.abs(np.diff(forces, axis=0)).max())
    assert start_step <= max(2.0, 2 * idle_step), (start_step, idle_step)


@pytest.mark.parametrize(("limit", "value"), [("t_min", 30.0), ("f_min", 15.0)])
def test_a_campaign_with_another_floor_or_law_starts_from_the_last_command(params, limit, value):
    """Audit of session 43: a campaign's own parameter set raising t_min to 30 N stepped the forces
    10 N a tick for 2 ticks at its start, f_min 15 N 9.35 N in one tick (law 2 → 3 at a held pose
    one tick of 7 N: the stretch estimate starts anew): another floor or law starts from the last
    command at 1 N a tick."""
    import tomllib

    from twin.model.params import params_from_dict

    loop = Loop(params)
    loop.run(2.0)
    n0 = len(loop.outputs)
    raw = tomllib.loads(params.to_toml())
    raw["limits"][limit] = value
    loop.svc.handle(_request(law=2, parameters_toml=params_from_dict(raw, f"{limit} {value}").to_toml()), loop.stamp_s)
    loop.run(0.3)
    assert "started" in [e.event for e in loop.events], loop.events
    forces = np.array([o.force_N for o in loop.outputs[n0 - 1:]])
    step = float(np.abs(np.diff(forces, axis=0)).max())
    assert step <= 1.0 + 1e-9, step
    assert forces[-1].min() > value - 5.0, forces[-1]  # the new floor (a tension: ± friction) reached at that rate


@pytest.mark.parametrize("law", [2, 3])
def test_a_controller_restarted_while_the_bridge_runs_starts_from_where_the_neck_is(params, law) -> None:
    """Audit of 2026-11-29: a controller process started while the bridge ran (a crash and its
    restart, a redeploy) took the neck for straight whatever the encoders read: α̂ 0 with the
    neck 45° up, so its hold's feed-forward and the next campaign's approach started from a pose
    the neck was not in. It starts from the encoders' absolute reading (eq. 33) with the stretch
    the state's forces hold (eq. 58 at rest) and holds the neck where it is."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from bridge_loop import BridgeLoop

    from controller.trajectory import control_test_trajectory

    loop = BridgeLoop(params, seed=0, law=law)
    loop.run(1.0)
    loop.svc.handle(_request("c-1", trajectory_json=control_test_trajectory().to_json(), law=law), loop.stamp_s)
    loop.run(3.0)
    bent = loop.tick.alpha.copy()
    assert np.degrees(bent).min() > 15.0  # the neck is well up
    svc = CampaignService(params, LawConfig(law=law), settle_s=0.5)  # the new process, on its first state
    svc.initialise(loop.tick.theta_meas, loop.applied[-1])
    assert np.degrees(np.abs(svc.ctl.estimator.alpha_hat - bent)).max() < 8.0, np.degrees(svc.ctl.estimator.alpha_hat)
    loop.svc = svc
    loop.run(1.0)
    assert np.degrees(np.abs(loop.tick.alpha - bent)).max() < 8.0, np.degrees(loop.tick.alpha)  # held there
    assert np.degrees(np.abs(loop.outputs[-1].alpha_hat_rad - loop.tick.alpha)).max() < 8.0


def test_a_first_state_far_off_any_pose_is_held_within_the_joint_limits(params) -> None:
    """Audit of 2026-11-29: eq. 33 answers any encoder reading, and a first state read 50 rad off
    gave a hold target of (−135, 84, −107)°; a non-finite force is not taken for a stretch."""
    svc = CampaignService(params, LawConfig(law=3), settle_s=0.5)
    svc.initialise(np.array([50.0, -50.0, 50.0, -50.0]), np.array([10.0, math.nan, 10.0, 10.0]))
    limit = math.radians(params.limits.alpha_max_deg)
    assert np.all(np.abs(svc.hold_target) <= limit + 1e-12), np.degrees(svc.hold_target)
    assert np.all(svc.ctl.estimator.x_c == 0.0)


def test_a_jog_prepared_behind_a_jog_that_ends_aborted_is_dropped(params):
    """Review of session 40: jog B, asked for while jog A runs, has its approach validated from
    A's target (``start_pose``). A then ended ``aborted`` while B was still being prepared, and B
    started from where A had stopped: an approach nobody validated. B is dropped with A's end, as
    a jog already waiting for A is."""
    from bridge_loop import BridgeLoop

    loop = BridgeLoop(params)
    svc = loop.svc
    loop.run(1.0)

    def jog(cid: str, deg: list[float]) -> bus.CampaignRequest:
        return _request(cid, trajectory_json=Trajectory.from_degrees([deg], [], 0.0, "jog").to_json(), kind="jog")

    svc.handle(jog("jog-a", [40.0, 0.0, 0.0]), loop.stamp_s)
    loop.run(0.4)
    assert svc.running and svc.campaign_id == "jog-a"
    b = jog("jog-b", [-20.0, 15.0, 0.0])
    assert svc.request_start(b)  # the shell's worker prepares it ...
    validated_from = svc.start_pose()  # ... its approach from A's target
    assert validated_from is not None
    assert np.allclose(np.degrees(validated_from), [40.0, 0.0, 0.0])
    svc.stop("jog-a", loop.stamp_s)  # A ends aborted meanwhile
    svc.prepared(prepare(b, params, LawConfig(law=2), alpha_from_rad=validated_from), b, loop.stamp_s)
    loop.run(2.0)
    assert not (svc.running and svc.campaign_id == "jog-b")
    ends = [e for e in loop.events if e.campaign_id == "jog-b" and e.event in ("started", "aborted")]
    assert [e.event for e in ends] == ["aborted"] and "jog jog-a ended aborted" in ends[0].message, ends


def test_a_campaign_asked_for_during_a_stops_brake_is_checked_from_where_the_brake_rests(params):
    """A stop brakes α^d to rest (``controller.trajectory.brake_at``) and a campaign asked for
    meanwhile starts from there; its approach had been checked from α̂ on the way (session 41)."""
    from bridge_loop import BridgeLoop

    loop = BridgeLoop(params)
    svc = loop.svc
    loop.run(1.0)
    svc.handle(_request("jog-a", trajectory_json=Trajectory.from_degrees([[40.0, 0.0, 0.0]], [], 0.0, "jog").to_json(),
                        kind="jog"), loop.stamp_s)
    loop.run(1.5)  # mid-move
    assert svc.running
    svc.stop("jog-a", loop.stamp_s)
    assert svc.braking
    validated_from = svc.start_pose()
    on_the_way = np.array(svc.ctl.estimator.alpha_hat)
    while svc.braking:
        loop.run(0.002)
    rest = np.asarray(svc.reference(loop.stamp_s)[0])
    assert validated_from is not None
    assert np.degrees(np.abs(validated_from - rest)).max() < 0.05, np.degrees([validated_from, rest])
    assert np.degrees(np.abs(on_the_way - rest)).max() > 0.5  # what the old check had started from


def test_a_starved_controller_whose_bridge_flaps_hold_active_re_starts_the_law_and_its_commands_stay_bounded(params):
    """Audit of session 43: a starved controller (stopped 40 ms, running 8 ms) made the bridge's
    watchdog flap hold/active every 48 ms. No single hold lasted 0.1 s (the threshold then), so the law ran on
    while the neck was held, α^d advancing and its integral winding up: its commands climbed to
    f_max and the bridge ramped to them at each hand-back (the neck at 217-378°/s, α 71.9°). The
    hold time now adds up: the law re-starts from the measurement (a hold at α̂ while held, then a
    fresh integral and α^d blended from α̂), and no command leaves the bridge's forces by more than
    the law's rate bound."""
    traj = Trajectory.from_degrees([[0, 0, 0], [30, 20, 10], [-10, 25, 20]], 1.5, 0.2, name="sweep")
    loop = Loop(params)
    safety = Safety(SafetyConfig(n_motors=params.n_cables, f_min_N=params.limits.f_min,
                                 f_max_N=params.limits.f_max))
    loop.svc.handle(_request(trajectory_json=traj.to_json()), loop.stamp_s)
    f_max, step_max = params.limits.f_max, loop.svc.law.force_rate_max_N_s * 0.002
    commands, restarted, age = [], False, 0
    for k in range(round(2.5 * 500)):
        starved = 250 <= k < 550 and (k - 250) % 24 < 20  # 0.6 s from 0.5 s into the campaign
        out = loop.svc.control(loop.tick.theta_meas, loop.stamp_s, safety.drive, np.asarray(safety.force))
        if out.law_ran:
            loop.svc.advance(loop.stamp_s)
        loop.events += loop.svc.drain_events()
        restarted |= loop.svc.drive == "hold" and loop.svc.hold_reason.startswith("drives hold")
        age = age + 1 if starved else 0
        commands.append(out.force_N)  # lost or not: one promise after the other
        d = safety.step(Inputs(command_N=None if starved else out.force_N.tolist(), command_age_s=0.002 * age,
                               states_unanswered=age, hold_N=hold_forces(params, loop.tick.alpha).tolist()))
        loop.tick = loop.twin.tick(np.asarray(d.force_N, dtype=float))
    sent = np.array(commands)
    print(f"\nlargest command {sent.max():.1f} N, largest step between commands {np.abs(np.diff(sent, axis=0)).max():.2f} N")
    assert sent.max() < 0.95 * f_max, sent.max(axis=0)  # it had climbed to f_max
    assert np.abs(np.diff(sent, axis=0)).max() <= step_max + 1e-6
    assert restarted


@pytest.mark.parametrize(("law", "lost_s", "stop"), [(2, 0.3, False), (3, 0.3, False), (2, 0.05, False),
                                                     (3, 0.08, False), (2, 0.05, True), (3, 0.02, True)])
def test_a_single_watchdog_hold_mid_trajectory_hands_back_within_the_trajectory_speed_limit(params, law, lost_s, stop):
    """Session 43's open point (docs/safety/watchdog_handback.py): 0.3 s of lost commands 3 s into
    the §7 control test on the robot truth, the bridge's watchdog holding the neck meanwhile. At
    the take-over α^d was blended from α̂ but α̇^d was the trajectory's at once: the law asked the
    held neck for the trajectory's speed in one tick (10 N a tick) and it reached 128-130°/s, past
    the trajectories' own bound (86°/s). The campaign's clock now stops while the law re-starts and
    comes back up to speed gently, so the neck stays within that bound and the campaign still ends
    ``finished`` (later, by the time it was held). A loss of 20-98 ms (a hold shorter than
    0.1 s, the threshold then) did not re-start the law at all: its commands climbed to f_max on the
    held neck and it reached 133-157°/s (laws 2-3, session 46); it re-starts after a period now.
    ``stop``: the user stops the campaign one tick before the loss; its brake went on through the
    re-start on the states' clock while the hold stopped the neck, and the law took over asking
    ~50°/s of a neck at rest: 104-183°/s (review of session 46). The law now holds at α̂ there."""
    from controller.trajectory import TrajectoryLimits, control_test_trajectory

    traj = control_test_trajectory()
    twin, svc, safety, hold_rule, speed, tick = _robot_loop(params, law, seed=0)
    lost = range(500 + 1500, 500 + 1500 + round(lost_s / 0.002))  # from 3 s into the campaign
    events, alpha_dot, applied, age = [], [], [], 0
    for k in range(lost.stop + 750):
        if k == 500:
            svc.handle(_request("ct", law=law, trajectory_json=traj.to_json()), tick.t_s)
        if stop and k == lost.start - 1:
            svc.stop("ct", tick.t_s)
        out = svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force))
        if out.law_ran:
            svc.advance(tick.t_s)
        events += svc.drain_events()
        age = age + 1 if k in lost else 0
        d = safety.step(Inputs(command_N=None if k in lost else out.force_N.tolist(), command_age_s=0.002 * age,
                               states_unanswered=age, hold_N=hold_rule(tick.theta_meas).tolist(),
                               speed_rad_s=speed.rad_s))
        tick = twin.tick(np.asarray(d.force_N, dtype=float))
        speed.update(tick.theta_meas.tolist())
        if k >= lost.stop - 1:  # from the hand-back (the hold's own ramp is the bridge's rule 3)
            applied.append(np.asarray(d.force_N, dtype=float))
        if k >= lost.stop:
            alpha_dot.append(tick.alpha_dot.copy())
    peak, step = float(np.abs(alpha_dot).max()), float(np.abs(np.diff(applied, axis=0)).max())
    print(f"\nlaw {law}: peak joint speed after the hand-back {math.degrees(peak):.1f}°/s, {step:.2f} N a tick")
    assert peak <= float(TrajectoryLimits().per_joint(3)[1].min()), math.degrees(peak)
    assert step <= 2.0  # the bridge's ramp back to the re-started law, and the law
    assert [e.event for e in events if e.event == "aborted"] == (["aborted"] if stop else [])
    assert svc.running != stop


def test_the_law_takes_over_after_stale_states_without_a_force_step(params):
    """Audit of session 44: after 0.3 s without states mid-campaign (the controller's own hold,
    the bridge active throughout) the law's first commands stepped 10 and 6.5 N a tick from the
    hold's (law 2, robot truth): the hold and the law differ by their friction and velocity
    terms. Taking over from its own hold, the law's command now moves at the take-up's 1 N a tick
    until it meets the law's, as after a take-up."""
    from controller.take_up import FORCE_STEP_N
    from controller.trajectory import control_test_trajectory

    twin, svc, safety, hold_rule, speed, tick = _robot_loop(params, 2, seed=0)
    stale = range(2000, 2150)  # 0.3 s from 3 s into the campaign
    sent, last_state_s = [], tick.t_s
    for k in range(stale.stop + 250):
        if k == 500:
            svc.handle(_request("ct", trajectory_json=control_test_trajectory().to_json()), tick.t_s)
        if k in stale:  # what the process shell does without states: the hold, sent on
            out = svc.stale("stale state", tick.t_s - last_state_s)
        else:
            out = svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force))
            last_state_s = tick.t_s
            if out.law_ran:
                svc.advance(tick.t_s)
        svc.drain_events()
        sent.append(out.force_N)
        d = safety.step(Inputs(command_N=out.force_N.tolist(), command_age_s=0.0, states_unanswered=0,
                               hold_N=hold_rule(tick.theta_meas).tolist(), speed_rad_s=speed.rad_s))
        tick = twin.tick(np.asarray(d.force_N, dtype=float))
        speed.update(tick.theta_meas.tolist())
    steps = np.abs(np.diff(np.array(sent[stale.stop - 1:]), axis=0)).max(axis=1)
    print(f"\nlargest command step after the hand-back {steps.max():.2f} N/tick")
    assert svc.running
    assert steps.max() <= 2 * FORCE_STEP_N, steps[:12]


def test_a_small_step_back_of_the_clock_after_a_stall_is_no_encoder_fault(params):
    """Audit of session 44: 0.3 s without states mid-move, then the bridge's clock stepped 2 s back
    (under CLOCK_STEP_ABORT_S: the campaign goes on). The encoders' speed check measured the
    stall's motion over no time, "encoder 4 moved 3.82 rad in 0 ms", and aborted the campaign; it
    now spans the time that passed, as the law's gap does."""
    from controller.trajectory import control_test_trajectory

    loop = Loop(params)
    loop.twin = Twin(params, TwinConfig(camera=False, seed=0, truth="robot"))
    loop.tick = loop.twin.tick(np.zeros(params.n_cables))
    loop.svc.initialise(loop.tick.theta_meas)
    loop.run(1.0)
    loop.svc.handle(_request("c", trajectory_json=control_test_trajectory().to_json()), loop.stamp_s)
    loop.run(3.0)
    start = loop.tick.theta_meas.copy()
    last_s = loop.stamp_s
    for _ in range(150):  # the stall: the process's loop holds on stale states
        out = loop.svc.stale("stale state", loop.stamp_s - last_s)
        loop.tick = loop.twin.tick(out.force_N)
    assert np.abs(loop.tick.theta_meas - start).max() > MOTOR_SPEED_MAX_RAD_S * 0.002  # moved more than one tick allows
    loop.svc.clock_stepped(-2.0, loop.stamp_s - 2.0)
    for _ in range(50):
        out = loop.svc.control(loop.tick.theta_meas, loop.stamp_s - 2.0)
        loop.events += loop.svc.drain_events()
        loop.tick = loop.twin.tick(out.force_N)
    assert loop.svc.running and not [e for e in loop.events if e.event == "aborted"], loop.events


@pytest.mark.parametrize("stop", [False, True])
def test_a_campaign_of_another_law_gives_the_hold_back_to_the_services_own_law(params, stop):
    """User audit of session 46: after an identification (law 1) the stack held, and jogged, with
    law 1 until a campaign of another law ran, though ``--law`` is the law it holds with between
    campaigns. The service's own law and set come back when a campaign ends, finished or stopped,
    without a force step (the take-up's 1 N a tick from the last command)."""
    loop = Loop(params)
    loop.run(0.3)
    loop.svc.handle(_request(law=1), loop.stamp_s)
    assert loop.svc.law.law == 1
    loop.run(0.6 if stop else NOD.duration_s + 0.5)
    if stop:
        loop.svc.handle(_request(action="stop"), loop.stamp_s)
    before = len(loop.outputs)
    loop.run(1.0)
    assert [e.event for e in loop.events if e.event in ("finished", "aborted")] == ["aborted" if stop else "finished"]
    assert loop.svc.law.law == 2 and loop.svc.ctl.config.law == 2
    forces = np.array([o.force_N for o in loop.outputs[before - 5:]])
    assert np.abs(np.diff(forces, axis=0)).max() <= 2.0


def test_the_law_returns_from_a_short_stale_gap_mid_trajectory_without_a_force_step(params):
    """Session 46: no state for 20 ms 3 s into the §7 control test (robot truth, law 2); the
    process holds by itself after 10 ms on the last state's stamp, which the bridge takes. Below
    the 0.1 s it then took to re-start, the law went on from that hold and its commands stepped
    10 N a tick back to the law's; re-started (``STALE_RESTART_S``), it winds back gently. And
    its hold reaches the hold forces over ``HOLD_RAMP_S``, as the bridge's does: within the law's
    10 N a tick only, it had stepped 10 and 4.9 N (session 47)."""
    from controller.trajectory import TrajectoryLimits, control_test_trajectory

    twin, svc, safety, hold_rule, speed, tick = _robot_loop(params, 2, seed=0)
    stale = range(500 + 1500, 500 + 1510)  # 20 ms from 3 s into the campaign
    peak, applied, held, age, command = 0.0, [], [], 0, None
    for k in range(stale.stop + 500):
        if k == 500:
            svc.handle(_request("ct", law=2, trajectory_json=control_test_trajectory().to_json()), tick.t_s)
        if k in stale:  # nothing answered for the process's stale_s, then its own hold
            age, command = (age + 1, None) if k - stale.start < 5 else \
                (0, svc.stale("stale state", 0.002 * (k - stale.start + 1)).force_N.tolist())
        else:
            out = svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force))
            if out.law_ran:
                svc.advance(tick.t_s)
            age, command = 0, out.force_N.tolist()
        svc.drain_events()
        d = safety.step(Inputs(command_N=command, command_age_s=0.002 * age, states_unanswered=age,
                               hold_N=hold_rule(tick.theta_meas).tolist(), speed_rad_s=speed.rad_s))
        if k >= stale.stop - 1:
            applied.append(np.asarray(d.force_N, dtype=float))
        if stale.start - 1 <= k < stale.stop:
            held.append(np.asarray(d.force_N, dtype=float))
        tick = twin.tick(np.asarray(d.force_N, dtype=float))
        speed.update(tick.theta_meas.tolist())
        if k >= stale.stop:
            peak = max(peak, float(np.abs(tick.alpha_dot).max()))
    step = float(np.abs(np.diff(applied, axis=0)).max())
    assert step <= 2.0, step
    entry = np.abs(np.diff(held, axis=0)).max(axis=1)  # from the last state's tick into the hold
    assert entry.max() <= 5.0 and np.count_nonzero(entry > 1.0) >= 3, entry
    assert peak <= float(TrajectoryLimits().per_joint(3)[1].min()) and svc.running


def test_a_campaign_whose_law_re_starts_all_the_time_is_aborted_naming_why(params):
    """Review of session 46: commands lost 12 ms every 60 ms (a one-tick hold of the bridge each
    time, a controller whose commands come late all the time): every re-start stopped the
    campaign's clock and brought it back up to speed, and the campaign stood at 15 % until the
    console's 600 s timeout, which does not say why. A window of ``RESTARTS_WINDOW_S`` with at
    least ``RESTARTS_MIN`` re-starts and less than ``PROGRESS_MIN_RATIO`` of it advanced ends it
    aborted, saying so."""
    from controller.trajectory import control_test_trajectory

    twin, svc, safety, hold_rule, speed, tick = _robot_loop(params, 2, seed=1)
    svc.handle(_request("ct", law=2, trajectory_json=control_test_trajectory().to_json()), tick.t_s)
    events, age = [], 0
    for k in range(round(14.0 / 0.002)):
        out = svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force))
        if out.law_ran:
            svc.advance(tick.t_s)
        events += svc.drain_events()
        if not svc.running:
            break
        lost = k > 500 and k % 30 < 6
        age = age + 1 if lost else 0
        d = safety.step(Inputs(command_N=None if lost else out.force_N.tolist(), command_age_s=0.002 * age,
                               states_unanswered=age, hold_N=hold_rule(tick.theta_meas).tolist(),
                               speed_rad_s=speed.rad_s))
        tick = twin.tick(np.asarray(d.force_N, dtype=float))
        speed.update(tick.theta_meas.tolist())
    end = [e for e in events if e.event in ("finished", "aborted")]
    assert [e.event for e in end] == ["aborted"], events[-3:]
    assert "re-started" in end[0].message and "advanced" in end[0].message and end[0].progress < 0.5, end[0]


def test_a_campaign_right_after_a_latch_takes_over_from_its_hold_without_a_step(params):
    """Session 47 (docs/safety/transition_fuzz.py): a campaign asked for 4 ms after an encoder
    glitch latched the hold (the control test 2.5 s in, law 2, robot truth, through the bridge's
    rules) had the law take over at its full 10 N a tick: the latch's hold had not reached the
    hold forces, and nothing bounded the law's first commands to it. They now wind down from the
    hold at the take-up's 1 N a tick, as after the controller's own stale hold."""
    from bridge_loop import BridgeLoop

    from controller.trajectory import control_test_trajectory

    loop = BridgeLoop(params, seed=0)
    loop.run(0.5)
    loop.svc.handle(_request("c-1", trajectory_json=control_test_trajectory().to_json()), loop.stamp_s)
    loop.run(2.5)
    glitched = loop.tick.theta_meas.copy()
    loop.run(0.002, stuck={1: float(glitched[1]) - 29.3})
    assert loop.svc.latched
    loop.run(0.002)
    start = len(loop.applied) - 1
    loop.svc.handle(_request("c-2", trajectory_json=control_test_trajectory().to_json()), loop.stamp_s)
    loop.run(0.5)
    assert loop.svc.running and not loop.svc.latched
    step = float(np.abs(np.diff(np.array(loop.applied[start:]), axis=0)).max())
    assert step <= 2.0, step


@pytest.mark.parametrize("when", ["running", "prepared", "waiting behind a jog"])
def test_a_start_request_delivered_twice_is_ignored_not_answered_aborted(loop, params, when):
    """Review of session 53: a start whose campaign id was already running (or being prepared, or
    a jog waiting) was refused with an ``aborted`` event under that very id; the console, which
    matches events by id, ended its record there (aborted, no stop owed) while the controller ran
    the campaign on, and the console's stop of a duplicated jog cancelled only the waiting copy.
    The duplicate is ignored and counted; the campaign runs, and one stop stops it."""
    svc, kind = loop.svc, ("jog" if when == "waiting behind a jog" else "control")
    far = Trajectory.from_degrees([[0, 0, 0], [10, 5, 0]], 3.0, 0.2, name="long")
    first = _request("c-1", trajectory_json=far.to_json(), kind=kind)
    if when == "prepared":
        assert svc.request_start(first)
    elif when == "running":
        svc.handle(first, loop.stamp_s)
        loop.run(0.1)
    else:
        svc.handle(_request("jog-0", trajectory_json=far.to_json(), kind="jog"), loop.stamp_s)
        loop.run(0.1)
        svc.handle(first, loop.stamp_s)  # waits for jog-0
        assert svc.stoppable() == {"jog-0", "c-1"}
    assert not svc.request_start(_request("c-1", trajectory_json=far.to_json(), kind=kind))
    assert svc.duplicate_starts == 1
    if when == "prepared":
        svc.prepared(prepare(first, params, svc.law), first, loop.stamp_s)
    loop.run(0.1)
    events = loop.events + svc.drain_events()
    assert not [e for e in events if e.campaign_id == "c-1" and e.event == "aborted"], events
    assert "c-1" in svc.stoppable()
    svc.stop("c-1", loop.stamp_s)
    assert "c-1" not in svc.stoppable()
    ended = [e for e in svc.drain_events() if e.campaign_id == "c-1"]
    assert [e.event for e in ended] == ["aborted"] and "stopped by the user" in ended[0].message


def test_a_jog_is_checked_on_the_law_and_set_it_runs_on(params):
    """Review of session 53: a jog was checked with the request's parameter set and law, but the
    service runs a jog on its own (it keeps them): a set with its masses zeroed passed a pose that
    the robot's set refuses, and the console's jogs were checked with the message's default law.
    A jog's request carries no set (refused if it does) and is checked on the service's law."""
    import dataclasses

    from controller.prepare import Refused

    far = Trajectory.from_degrees([[60.0, -60.0, 60.0]], [], 0.0, "jog")
    with pytest.raises(Refused, match="f_max"):
        prepare(_request("j-1", kind="jog", trajectory_json=far.to_json()), params, LawConfig(law=2))
    with pytest.raises(Refused, match="parameters_toml must be empty"):
        prepare(_request("j-2", kind="jog", trajectory_json=far.to_json(), parameters_toml=params.to_toml()),
                params, LawConfig(law=2))
    near = Trajectory.from_degrees([[5.0, 0.0, 0.0]], [], 0.0, "jog")
    held = dataclasses.replace(LawConfig(law=3), no_pulleys=True)
    got = prepare(_request("j-3", kind="jog", trajectory_json=near.to_json(), law=1), params, held)
    assert got.law == held  # the service's law, not the message's
    control = prepare(_request("c-3", trajectory_json=near.to_json(), law=1), params, held)
    assert control.law.law == 1  # a campaign's own law, as before


def test_a_new_bridge_run_met_under_way_starts_from_its_forces_too(loop, params):
    """Review of session 53: a bridge run met under way (the gate re-bound to a run already going:
    a stray run seen first, then the robot's bridge) started the estimate from the encoders alone,
    as if the cables held no load: α̂ off by their stretch, and the slack test that decides an owed
    take-up read f = 0. It starts as a first state does, from the forces its state says."""
    bent = Trajectory.from_degrees([[20.0, 10.0, -10.0]], [], 0.0, "jog")
    loop.svc.handle(_request("j", kind="jog", trajectory_json=bent.to_json()), loop.stamp_s)
    loop.run(3.0)
    theta, f = loop.tick.theta_meas.copy(), loop.outputs[-1].force_N.copy()
    assert f.max() > 10.0
    first = CampaignService(params, LawConfig(law=2), service=True)
    first.initialise(theta, f)
    rebound = CampaignService(params, LawConfig(law=2), service=True)
    rebound.initialise(np.zeros_like(theta))
    rebound.new_bridge_run(theta, 1.0, "bridge-2", f)
    np.testing.assert_allclose(rebound.ctl.estimator.alpha_hat, first.ctl.estimator.alpha_hat)
    np.testing.assert_allclose(rebound.ctl.estimator.x_c, first.ctl.estimator.x_c)
    assert rebound._joined == first._joined and rebound._reestimate_when_taut == first._reestimate_when_taut
    unloaded = CampaignService(params, LawConfig(law=2), service=True)
    unloaded.initialise(theta)  # what the re-bind did before
    off = np.degrees(np.abs(unloaded.ctl.estimator.alpha_hat - first.ctl.estimator.alpha_hat)).max()
    assert off > 0.5, off  # the forces matter here
    assert np.degrees(np.abs(first.ctl.estimator.alpha_hat - loop.tick.alpha)).max() < off
