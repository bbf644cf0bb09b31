"""A trajectory's pretension (controller.trajectory): the floor t_min raised per waypoint, joined by
cycloids, checked before anything moves, followed by the law, and let go gently when a campaign
stops at high tension."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bridge import bus
from controller.laws import ComputedTorque, LawConfig, controller_model, hold_forces, nominal_force_check
from controller.service import HOLD_RAMP_S, PRETENSION_RELEASE_N_S, CampaignService
from controller.trajectory import (
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    approach,
    load_trajectory,
    trajectory_from_json,
    validate,
)
from twin.sim.simulator import Twin, TwinConfig

LIMITS = TrajectoryLimits()
# still joints, the floor raised to 40 N over 2 s, held 2 s, let go over 2 s
SQUEEZE = Trajectory.from_degrees([[0, 0, 0], [0, 0, 0], [0, 0, 0]], 2.0, [0.5, 2.0, 0.5], "squeeze", [0.0, 40.0, 0.0])


def test_the_pretension_follows_the_joints_cycloids():
    t = np.linspace(-1.0, SQUEEZE.duration_s + 1.0, 1201)
    P = SQUEEZE.pretension(t)
    assert P[0] == 0.0 and P[-1] == 0.0 and P.max() == pytest.approx(40.0)
    np.testing.assert_allclose(SQUEEZE.pretension(SQUEEZE.waypoint_times()), [0.0, 40.0, 0.0])
    # rest-to-rest: half way through the first move it is half way, and its peak rate is 2|ΔP|/T
    assert SQUEEZE.pretension(0.5 + 1.0) == pytest.approx(20.0)
    assert np.max(np.gradient(P, t)) == pytest.approx(SQUEEZE.segment_peak_pretension_rate()[0], rel=2e-3)
    # the controller's scalar sampling gives the same numbers
    np.testing.assert_allclose([SQUEEZE.pretension_at(float(x)) for x in t], P, atol=1e-12)


def test_pretension_survives_the_file_round_trip_and_is_absent_when_zero(tmp_path):
    path = tmp_path / "squeeze.json"
    path.write_text(json.dumps(SQUEEZE.to_dict()))
    back = load_trajectory(path)
    np.testing.assert_allclose(back.pretension_N, [0.0, 40.0, 0.0])
    assert trajectory_from_json(SQUEEZE.to_json()).has_pretension
    plain = Trajectory.from_degrees([[0, 0, 0], [10, 0, 0]], 1.0)
    assert "pretension_N" not in plain.to_dict() and not plain.has_pretension
    # the gentle approach a controller puts in front keeps the schedule, 0 at the new start
    moved = approach(SQUEEZE, np.radians([5.0, 0.0, 0.0]))
    np.testing.assert_allclose(moved.pretension_N, [0.0, 0.0, 40.0, 0.0])


@pytest.mark.parametrize(("pretension", "message"), [
    ([0.0, -5.0, 0.0], "negative or non-finite pretension"),
    ([0.0, math.nan, 0.0], "negative or non-finite pretension"),
    ([0.0, 10.0], "expected 3 pretension"),
])
def test_malformed_pretensions_are_refused(pretension, message):
    with pytest.raises(TrajectoryError, match=message):
        Trajectory.from_degrees([[0, 0, 0]] * 3, 2.0, 0.5, "bad", pretension)


def test_validation_wants_zero_at_both_ends_and_a_gentle_rate(params):
    with pytest.raises(TrajectoryError, match="must start and end at 0 N"):
        validate(Trajectory.from_degrees([[0, 0, 0]] * 2, 2.0, 0.5, "end", [0.0, 10.0]), LIMITS, 3)
    fast = Trajectory.from_degrees([[0, 0, 0]] * 3, 0.5, 0.5, "fast", [0.0, 40.0, 0.0])
    with pytest.raises(TrajectoryError, match=r"segment 0 .* changes the pretension too fast: .* needs at least 0.8 s"):
        validate(fast, LIMITS, 3)
    validate(SQUEEZE, LIMITS, 3)  # 40 N over 2 s peaks at 40 N/s


def test_the_force_check_sees_the_raised_floor(params):
    law = LawConfig(law=1)
    check = nominal_force_check(params, law)
    validate(SQUEEZE, LIMITS, 3, check)
    f_max = controller_model(params, law).f_max
    too_much = Trajectory.from_degrees([[0, 0, 0]] * 3, 2.0, 0.5, "too much", [0.0, f_max, 0.0])
    with pytest.raises(TrajectoryError, match=r"forces out of bounds .* > f_max"):
        validate(too_much, LIMITS, 3, check)


def test_the_law_raises_every_cable_by_the_pretension(params):
    m = controller_model(params, LawConfig(law=2))
    forces = {}
    for P in (0.0, 25.0):  # one tick from zero forces: without the rate bound, which would hide the floor
        ctl = ComputedTorque(params, LawConfig(law=2, force_rate_max_N_s=math.inf))
        ctl.reset(theta=np.zeros(params.n_cables))
        z = np.zeros(params.n_joints)
        forces[P] = ctl.step(np.zeros(params.n_cables), z, z, z, P).f.copy()
    # straight and still: Γ^d = 0, so every cable sits on the floor t_min (+ P), short ones above
    assert forces[0.0].min() == pytest.approx(m.t_min, abs=1e-6)
    assert forces[25.0].min() == pytest.approx(m.t_min + 25.0, abs=1e-6)
    assert np.all(forces[25.0] > forces[0.0] + 20.0)


class _Loop:
    """The campaign service closed on the simulator, one state per 2 ms (as tests/test_controller_service.py)."""

    def __init__(self, params):
        self.twin = Twin(params, TwinConfig(camera=False, seed=3))
        self.svc = CampaignService(params, LawConfig(law=2), settle_s=0.2)
        self.tick = self.twin.tick(np.zeros(params.n_cables))
        self.svc.initialise(self.tick.theta_meas)
        self.forces: list[np.ndarray] = []
        self.events: list = []

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds * 500)):
            out = self.svc.control(self.tick.theta_meas, self.tick.t_s)
            if out.law_ran:
                self.svc.advance(self.tick.t_s)
            self.events += self.svc.drain_events()
            self.forces.append(out.force_N.copy())
            self.tick = self.twin.tick(out.force_N)


def test_a_campaign_at_high_tension_stopped_by_the_user_lets_go_without_a_step(params):
    loop = _Loop(params)
    loop.run(0.2)
    loop.svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="squeeze", action="start",
                                        trajectory_json=SQUEEZE.to_json()), loop.tick.t_s)
    loop.run(3.0)  # on the 40 N plateau
    assert loop.svc.pretension_N == pytest.approx(40.0)
    squeezed = loop.forces[-1].copy()
    loop.svc.handle(bus.CampaignRequest(seq=2, stamp_s=0.0, campaign_id="squeeze", action="stop"), loop.tick.t_s)
    n_before = len(loop.forces)
    loop.run(0.02)
    # the law goes on holding with the floor coming down at PRETENSION_RELEASE_N_S, not dropping
    # 40 N: the ticks change by what law 2 changes them on the plateau (≈ 0.7 N with quantised
    # encoders) plus the re-targeting of α^d to α̂ at the stop
    step = np.abs(np.diff(np.array(loop.forces[n_before - 1:]), axis=0)).max()
    assert step < 2.0, step
    assert loop.forces[-1].min() > squeezed.min() - 2.0
    loop.run(40.0 / PRETENSION_RELEASE_N_S + 0.2)
    assert loop.svc.pretension_N == 0.0 and loop.svc.phase == "aborted"
    steps = np.abs(np.diff(np.array(loop.forces[n_before - 1:]), axis=0)).max()
    assert steps < 2.0, steps
    # a hold from here (e.g. a diverging estimate) commands the plain floor again, reached over
    # the hold's ramp from the law's last command (HOLD_RAMP_S, as the bridge's hold)
    held = [loop.svc.hold("test").force_N for _ in range(round(HOLD_RAMP_S * 500))]
    np.testing.assert_allclose(held[-1], hold_forces(params, loop.svc.hold_alpha()))


def test_a_finished_pretension_campaign_ends_on_the_plain_floor(params):
    loop = _Loop(params)
    loop.svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="squeeze", action="start",
                                        trajectory_json=SQUEEZE.to_json()), loop.tick.t_s)
    loop.run(SQUEEZE.duration_s + 0.5)
    assert [e.event for e in loop.events][-1] == "finished"
    assert loop.svc.pretension_N == 0.0
    forces = np.array(loop.forces)
    assert forces.max() > 40.0  # the plateau was commanded
    assert np.abs(np.diff(forces, axis=0)).max() < 2.0  # and reached and left without a step


def test_a_short_hold_within_the_campaign_keeps_the_floor(params):
    """States stall for a few ticks mid-campaign (the service holds): the floor stays where the
    campaign has it, so the law resumes without a step; it is let go only once the campaign ends."""
    loop = _Loop(params)
    loop.svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="squeeze", action="start",
                                        trajectory_json=SQUEEZE.to_json()), loop.tick.t_s)
    loop.run(3.0)
    for _ in range(10):
        held = loop.svc.stale("no state", 0.02)
    assert loop.svc.pretension_N == pytest.approx(40.0)
    np.testing.assert_allclose(held.force_N, hold_forces(params, loop.svc.hold_alpha(), 40.0))


def test_a_campaign_started_right_after_an_abort_at_high_tension_lets_the_floor_go_gently(params):
    """Audit of 2026-11-29: the next campaign's pretension (none) replaced the floor the aborted
    one left (40 N) at its first tick. It is now let go at ``PRETENSION_RELEASE_N_S`` under it."""
    loop = _Loop(params)
    loop.svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="squeeze", action="start",
                                        trajectory_json=SQUEEZE.to_json()), loop.tick.t_s)
    loop.run(3.0)
    loop.svc.handle(bus.CampaignRequest(seq=2, stamp_s=0.0, campaign_id="squeeze", action="stop"), loop.tick.t_s)
    loop.run(0.01)
    n_before = len(loop.forces)
    plain = Trajectory.from_degrees([[0, 0, 0], [5, 0, 0]], 2.0, 0.5, "plain")
    loop.svc.handle(bus.CampaignRequest(seq=3, stamp_s=0.0, campaign_id="next", action="start",
                                        trajectory_json=plain.to_json()), loop.tick.t_s)
    while not loop.svc.running:  # it waits for the stop's brake
        loop.run(0.002)
        assert len(loop.forces) < n_before + 500
    floors = []
    for _ in range(round(1.0 / 0.002)):
        loop.run(0.002)
        floors.append(loop.svc.pretension_N)
    assert floors[0] > 35.0 and floors[-1] == 0.0
    assert min(np.diff(floors)) >= -PRETENSION_RELEASE_N_S * 0.002 - 1e-9
    steps = np.abs(np.diff(np.array(loop.forces[n_before - 1:]), axis=0)).max()
    assert steps < 2.0, steps
