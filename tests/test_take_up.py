"""Taking up the slack an e-stop leaves (controller/take_up.py, docs/safety.md "After an e-stop"):
the drives come back onto cables the falling neck left slack, the motors' stiction (19-24 N on the
robot truth) holds their drums against the hold's forces (t_min = 8.5 N), and α̂ (eq. 35, counted
from the encoders' increments) stays 5-13° off until a move winds the slack in (audit of
2026-11-28). The controller now raises every cable's floor past the friction after such a release,
holds the neck at α̂ while the motors wind in, and only then lets the law hold the pose."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from controller import take_up as rules
from controller.take_up import TakeUp, take_up_peak_N
from controller.trajectory import control_test_trajectory

# pure computation, no bus or process: beside the realtime modules at nice 19 (tests/conftest.py)
pytestmark = pytest.mark.background

DT = 0.002


def _dropped_on_slack_cables(params, seed: int):
    from test_encoder_check import _dropped_on_slack_cables as dropped

    return dropped(params, seed)


def _request(cid: str):
    from test_controller_service import _request as request

    return request(cid, trajectory_json=control_test_trajectory().to_json())


def _jog_request(cid: str, trajectory):
    from test_controller_service import _request as request

    return request(cid, trajectory_json=trajectory.to_json(), kind="jog")


def _ended(loop, cid: str) -> list:
    return [e for e in loop.events if e.campaign_id == cid and e.event in ("finished", "aborted")]


@pytest.mark.parametrize("seed", [0, 1])
def test_the_slack_of_an_estop_is_taken_up_after_the_release_bumplessly(params, seed):
    """Before: 10 s after the release three cables were still slack and α̂ 12-15° off on joint 1
    (the law's hold forces 8.5-16 N, below the stiction). Now they are taut within 2.5 s, α̂ is back
    within the law's usual error on this truth (law 2 tracked the same test 1-5° off before the
    e-stop), the neck moved no faster than the trajectories may (86°/s), and no force the bridge
    applied changed by more than its enable ramp's 1 N a tick."""
    loop = _dropped_on_slack_cables(params, seed)
    assert loop.tick.slack.sum() >= 2  # the fall left cables slack
    start = len(loop.applied) - 1
    speeds: list[float] = []
    loop.run(DT, estop=((False, "audit"),))
    reason = ""
    for k in range(round(2.5 / DT)):
        loop.run(DT)
        speeds.append(float(np.abs(loop.tick.alpha_dot).max()))
        if k == round(0.3 / DT):
            reason = loop.svc.hold_reason  # what the controller's status says meanwhile
    assert "slack" in reason, reason
    assert not loop.tick.slack.any(), loop.tick.slack
    assert loop.outputs[-1].law_ran and loop.svc.hold_reason == ""  # the law holds the neck again
    err_deg = np.degrees(np.abs(loop.outputs[-1].alpha_hat_rad - loop.tick.alpha))
    assert err_deg.max() <= 5.0, err_deg
    assert not loop.svc.latched and loop.safety.drive == "active", loop.svc.hold_reason
    assert math.degrees(max(speeds)) <= 86.0
    applied = np.array(loop.applied[start:])
    assert np.abs(np.diff(applied, axis=0)).max() <= 1.0 + 1e-9
    loop.run(2.0)  # the floor is let go again once the cables are taut
    assert loop.svc.pretension_N == 0.0 and not loop.tick.slack.any()


def test_a_campaign_asked_for_during_the_take_up_starts_after_it(params):
    """Not refused, not started on slack cables: it waits, as behind a stop's brake, and runs
    once the law holds the neck again (module docstring of controller/service.py)."""
    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.2, estop=((False, "audit"),))
    assert loop.svc.taking_up
    loop.svc.handle(_request("c-2"), loop.stamp_s)
    assert not loop.svc.running and not _ended(loop, "c-2")
    while loop.svc.taking_up:
        loop.run(DT)
        assert not loop.svc.running
    assert not loop.tick.slack.any()
    for _ in range(25):
        loop.run(1.0)
        if _ended(loop, "c-2"):
            break
    assert [e.event for e in _ended(loop, "c-2")] == ["finished"], [e.message for e in _ended(loop, "c-2")]
    assert not loop.svc.latched


def test_no_take_up_at_the_first_enable(params):
    """The drives start ``inactive`` and the cables as calibrated: the first enable is not an
    e-stop's release, the law takes over at once with the floor at t_min."""
    from bridge_loop import BridgeLoop

    loop = BridgeLoop(params, seed=0)
    loop.run(0.1)
    assert loop.safety.drive == "active" and not loop.svc.taking_up
    assert all(o.law_ran for o in loop.outputs[5:]) and loop.svc.pretension_N == 0.0


def test_an_estop_during_the_take_up_ends_it_and_the_next_release_starts_one_from_its_floor(params):
    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.6, estop=((False, "audit"),))
    level = loop.svc.pretension_N
    assert loop.svc.taking_up and level > 5.0
    loop.run(0.3, estop=((True, "again"),))
    assert loop.safety.drive == "disabled" and loop.svc._take_up is None
    below = loop.svc.pretension_N
    assert below < level  # let go at the release rate while the drives are off, not dropped
    loop.run(DT, estop=((False, "again"),))
    loop.run(0.1)
    assert loop.svc.taking_up and loop.svc.pretension_N >= below - 1e-9
    loop.run(3.0)
    assert not loop.svc.taking_up and not loop.tick.slack.any() and loop.outputs[-1].law_ran


def test_the_take_up_ramps_its_floor_and_ends_once_the_motors_are_still():
    t = TakeUp(peak_N=10.0, rate_N_s=20.0, start_N=2.0)
    moving, still = np.array([0.0, 30.0, 0.0, 0.0]), np.zeros(4)
    stamps = iter(np.arange(0.0, 10.0, DT))
    levels = []
    for _ in range(300):  # 0.6 s: 2 N + 20 N/s reaches the peak after 0.4 s
        t.damp(moving, DT)
        assert t.step(next(stamps))
        levels.append(t.level_N)
    assert levels[0] == 2.0 and max(np.diff(levels)) <= 20.0 * DT + 1e-12 and levels[-1] == 10.0
    while abs(t.damping_N[1]) >= rules.DAMPING_N_S_RAD * rules.STILL_RAD_S:  # the filter lets go
        t.damp(still, DT)
        assert t.step(next(stamps))
    ticks = 0
    while t.step(next(stamps)):
        t.damp(still, DT)
        ticks += 1
    assert abs(ticks - rules.STILL_FOR_S / DT) <= 1 and t.done_reason == "taut"
    t.damp(moving, DT)
    assert not t.step(next(stamps))  # done stays done


def test_the_take_up_ends_at_the_peak_after_a_bounded_time_when_a_motor_keeps_turning():
    t = TakeUp(peak_N=1.0, rate_N_s=100.0)
    stamp, turning = 0.0, np.array([5.0, 0.0, 0.0, 0.0])
    t.damp(turning, DT)
    while t.step(stamp):
        t.damp(turning, DT)
        stamp += DT
        assert stamp < 0.01 + rules.PEAK_MAX_S + 2 * DT
    assert stamp >= rules.PEAK_MAX_S and "still turned" in t.done_reason


def test_the_damping_opposes_each_motors_speed_low_passed():
    t = TakeUp(peak_N=1.0, rate_N_s=1.0)
    assert np.all(t.damping_N == 0.0)
    t.damp(np.array([10.0, -10.0, 0.0, 0.0]), DT)
    first = t.damping_N
    assert np.allclose(first, [-rules.DAMPING_N_S_RAD * 10, rules.DAMPING_N_S_RAD * 10, 0, 0])
    t.damp(np.zeros(4), DT)  # a speed that drops at once is followed, not jumped to
    after = t.damping_N
    assert 0 < -after[0] < -first[0] and -after[0] > 0.5 * -first[0]


def test_the_peak_follows_the_friction_the_controller_knows(params):
    assert take_up_peak_N(params) == pytest.approx(rules.TAKE_UP_FRICTION_FACTOR * max(params.friction.f_s)
                                                   - params.limits.t_min)
    assert take_up_peak_N(params) > 1.5 * max(params.friction.f_s) - params.limits.t_min  # past breakaway


def test_the_peak_floor_stays_below_half_of_f_max_whatever_the_friction(params):
    """An identified set with a large f_s (80 N) must not have the take-up ask for f_max."""
    import msgspec

    heavy = msgspec.structs.replace(params, friction=msgspec.structs.replace(params.friction, f_s=(80.0,) * 4))
    assert take_up_peak_N(heavy) == pytest.approx(0.5 * params.limits.f_max - params.limits.t_min)


def test_a_new_bridge_run_during_the_take_up_ends_it(params):
    """A restarted bridge starts a new run: its encoders start again as calibrated, and its
    first enable is not an e-stop's release. (A new run met under way is judged as a controller's
    start is: test_a_controller_restarted_during_the_take_up_takes_the_slack_up.)"""
    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.3, estop=((False, "audit"),))
    assert loop.svc.taking_up
    loop.svc.new_bridge_run(np.zeros(params.n_cables), loop.stamp_s, "bridge-2")
    assert not loop.svc.taking_up
    loop.run(0.1)
    assert not loop.svc.taking_up and loop.outputs[-1].law_ran


@pytest.mark.parametrize("kw", [{"peak_N": -1.0, "rate_N_s": 1.0}, {"peak_N": math.nan, "rate_N_s": 1.0},
                                {"peak_N": 1.0, "rate_N_s": 0.0}, {"peak_N": 1.0, "rate_N_s": math.inf}])
def test_bad_take_up_settings_are_refused(kw):
    with pytest.raises(ValueError):
        TakeUp(**kw)


@pytest.mark.parametrize("kind", ["control", "jog"])
def test_a_campaign_that_waited_for_the_take_up_starts_without_a_step(params, kind):
    """Audit of 2026-11-29: the waiting campaign started at the hand-over and its trajectory's
    pretension (none) replaced the take-up's floor (29 N) at once: three 10 N steps of the applied
    forces. The floor left over is now let go at ``PRETENSION_RELEASE_N_S`` under the
    trajectory's own, as after an aborted campaign's."""
    from test_controller_service import _request as request

    from controller.service import PRETENSION_RELEASE_N_S
    from controller.trajectory import Trajectory

    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.2, estop=((False, "audit"),))
    req = (_request("c-2") if kind == "control" else
           request("c-2", kind="jog", trajectory_json=Trajectory.from_degrees([[10.0, 10.0, 10.0]], [], 0.0,
                                                                              "jog").to_json()))
    loop.svc.handle(req, loop.stamp_s)
    start = len(loop.applied) - 1
    for _ in range(round(4.0 / DT)):
        loop.run(DT)
        if loop.svc.running:
            break
    assert loop.svc.running and loop.svc.pretension_N > 20.0
    started = len(loop.applied)
    floors = []
    for _ in range(round(1.0 / DT)):
        loop.run(DT)
        floors.append(loop.svc.pretension_N)
    assert min(np.diff(floors)) >= -PRETENSION_RELEASE_N_S * DT - 1e-9 and floors[-1] == 0.0
    # the take-up and the campaign's first 0.3 s (later on, the control test's moves step the
    # law's forces by 2-3 N a tick with or without the take-up before)
    applied = np.array(loop.applied[start:started + round(0.3 / DT)])
    assert np.abs(np.diff(applied, axis=0)).max() <= 1.0 + 1e-9


@pytest.mark.parametrize("at_s", [0.8, 1.2])
def test_an_encoder_fault_during_the_take_up_lets_it_end_under_the_latch(params, at_s):
    """Audit of 2026-11-29: an encoder fault latching while the drums wound in dropped the take-up
    at once, its damping (up to 44 N) with it, under the law's bound: 10 N a tick for 5-6 ticks;
    it was then cut short at the take-up's rate. Session 47: a latch left the slack undamped (a
    latch still in force at a release: 500-845°/s), so the take-up now goes on under the latch,
    at the last sane α̂, the command moving 1 N a tick at most, and the latch's plain hold follows
    once the slack is in and its floor let go."""
    from controller.laws import hold_forces
    from controller.service import PRETENSION_RELEASE_N_S

    loop = _dropped_on_slack_cables(params, 0)
    loop.run(at_s, estop=((False, "audit"),))
    take_up = loop.svc._take_up
    assert take_up is not None and np.abs(take_up.damping_N).max() > 10.0
    start = len(loop.applied) - 1
    loop.run(DT, stuck={0: float(loop.tick.theta_meas[0]) + 100.0})  # one faulty reading
    assert loop.svc.latched and "encoder 1" in loop.svc.latch_reason
    loop.run(DT)
    assert loop.svc._take_up is take_up and "latched: encoder 1" in loop.svc.hold_reason, loop.svc.hold_reason
    for _ in range(round(5.0 / DT)):
        loop.run(DT)
        if loop.svc._take_up is None:
            break
    assert loop.svc._take_up is None and loop.svc.latched
    assert loop.svc.hold_reason.startswith("the cables' slack is taken up") and "latched: encoder 1" in loop.svc.hold_reason
    loop.run(loop.svc.pretension_N / PRETENSION_RELEASE_N_S + 0.5)
    applied = np.array(loop.applied[start:])
    assert np.abs(np.diff(applied, axis=0)).max() <= 1.0 + 1e-9
    assert loop.svc.hold_reason.startswith("encoder 1"), loop.svc.hold_reason  # the latch's hold, plain
    np.testing.assert_allclose(loop.outputs[-1].force_N, hold_forces(params, loop.svc.hold_alpha()))


class _Drifting:
    """Encoder 4's reading creeping at ``rate`` rad/s from now on (a drum, an encoder creeping):
    the motors never look still and the take-up ends on its ``PEAK_MAX_S``."""

    def __init__(self, loop, rate: float):
        self.loop, self.rate, self.off = loop, rate, 0.0

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / DT)):
            self.off += self.rate * DT
            self.loop.run(DT, stuck={3: float(self.loop.tick.theta_meas[3]) + self.off})


@pytest.mark.parametrize("rate", [1.0, 4.0])
def test_a_take_up_ending_on_its_time_limit_hands_over_without_a_step(params, rate):
    """Audit of 2026-11-29: ended by ``PEAK_MAX_S`` with a motor still turning, the take-up handed
    over with its damping in the last command (up to 10 N): the law's first command dropped it at
    once. The hand-over now moves 1 N a tick at most until the law's command is met."""
    loop = _dropped_on_slack_cables(params, 0)
    loop.run(DT, estop=((False, "audit"),))
    start = len(loop.applied) - 1
    drift = _Drifting(loop, rate)
    drift.run(0.1)
    while loop.svc.taking_up:
        drift.run(DT)
        assert len(loop.applied) - start < round(6.0 / DT)
    drift.run(0.3)
    applied = np.array(loop.applied[start:])
    assert np.abs(np.diff(applied, axis=0)).max() <= 1.0 + 1e-9
    assert loop.outputs[-1].law_ran and not loop.svc.latched


def test_a_clock_stepping_back_does_not_defeat_the_time_limit():
    """Audit of 2026-11-29: the time at the peak was the stamp less the stamp it was reached at,
    so a clock stepping back an hour kept a take-up with a turning motor going for an hour. It
    is now the sum of the positive steps between states (as controller/encoder_check.py)."""
    t = TakeUp(peak_N=1.0, rate_N_s=100.0)
    stamp, turning, ticks = 0.0, np.array([5.0, 0.0, 0.0, 0.0]), 0
    t.damp(turning, DT)
    while t.step(stamp):
        t.damp(turning, DT)
        stamp += DT
        ticks += 1
        if ticks == round(1.0 / DT):
            stamp -= 3600.0  # that tick counts as no time
        assert ticks * DT < 0.01 + rules.PEAK_MAX_S + 3 * DT
    assert "still turned" in t.done_reason


def test_a_told_clock_step_shifts_the_take_up_with_it():
    """A step the controller is told of (``clock_stepped``) is no time spent: forward, the floor had
    jumped to its peak and the time limit ended the take-up at once (audit of 2026-11-29)."""
    t = TakeUp(peak_N=10.0, rate_N_s=20.0)
    t.damp(np.array([5.0, 0.0, 0.0, 0.0]), DT)
    for k in range(50):
        assert t.step(k * DT)
    level = t.level_N
    t.clock_stepped(3600.0)
    assert t.step(3600.0 + 50 * DT)
    assert t.level_N == pytest.approx(level + 20.0 * DT)


@pytest.mark.parametrize("step_s", [3600.0, 3.0])
def test_a_clock_step_during_the_take_up_neither_ends_it_nor_steps_the_forces(params, step_s):
    """Audit of 2026-11-29: the bridge's clock set forward an hour 1.6 s into the take-up (at its
    peak) ended it on its time limit at once, handing over with up to 10 N steps. Review of session
    53: a step under the 5 s that aborts a campaign (an NTP step, 3 s here) was not passed on to
    the take-up, whose floor jumped to its peak, so its hold climbed at 1 N a tick, and whose
    stillness ended it on one still state."""
    from bridge_loop import BridgeLoop

    loop = _dropped_on_slack_cables(params, 0)
    loop.run(1.6, estop=((False, "audit"),))
    assert loop.svc.taking_up
    start = len(loop.applied) - 1

    class Shifted(BridgeLoop):
        @property
        def stamp_s(self) -> float:
            return self.tick.t_s + step_s

    level = loop.svc._take_up.level_N
    loop.__class__ = Shifted
    loop.svc.clock_stepped(step_s, loop.stamp_s)
    loop.run(DT)
    assert loop.svc._take_up.level_N <= level + rules.TAKE_UP_RATE_N_S * 2 * DT  # its rate, not the step's
    loop.run(0.1)
    assert loop.svc.taking_up  # the motors still wind in
    for _ in range(round(3.0 / DT)):
        loop.run(DT)
        if not loop.svc.taking_up:
            break
    loop.run(0.3)
    assert not loop.tick.slack.any() and loop.outputs[-1].law_ran
    applied = np.array(loop.applied[start:])
    assert np.abs(np.diff(applied, axis=0)).max() <= 1.0 + 1e-9


def test_the_floor_cap_keeps_the_hold_under_its_margin_of_f_max(params):
    """The take-up's floor at 2·max f_s had the distribution load other cables 1.7-2.7× as much:
    f_max at 357 of 729 poses of a ±60° grid (audit of 2026-11-29). :func:`floor_cap_N` is the
    floor at which the hold's largest force is ``PEAK_FORCE_FRACTION``·f_max."""
    import itertools

    from controller.laws import hold_forces

    top = rules.PEAK_FORCE_FRACTION * params.limits.f_max
    grid = np.radians(np.arange(-60.0, 61.0, 20.0))
    capped = 0
    for alpha in itertools.product(grid, grid, grid):
        a = np.array(alpha)
        cap = rules.floor_cap_N(params, a)
        if hold_forces(params, a).max() >= top:
            assert cap == 0.0
            continue
        assert hold_forces(params, a, cap).max() == pytest.approx(top, abs=1e-6)
        assert hold_forces(params, a, cap + 0.5).max() > top
        capped += cap < take_up_peak_N(params)
    assert capped > 0


def test_the_floor_follows_a_cap_below_its_peak_and_reaching_it_is_the_peak():
    t = TakeUp(peak_N=10.0, rate_N_s=20.0, start_N=8.0)
    t.damp(np.zeros(4), DT)
    assert t.step(0.0, cap_N=5.0) and t.level_N == 5.0  # dropped to it (the hold's command: 1 N a tick)
    stamp = 0.0
    while t.step(stamp, cap_N=5.0):
        t.damp(np.zeros(4), DT)
        stamp += DT
        assert t.level_N == 5.0
    assert stamp == pytest.approx(rules.STILL_FOR_S, abs=2 * DT)
    # Still at a capped floor is not "taut": the motors may have stopped on their friction.
    assert t.done_reason.startswith("the floor was capped at t_min + 5 N") and "may still be slack" in t.done_reason


def test_the_take_up_at_a_tilted_pose_keeps_every_cable_under_its_margin_of_f_max(params):
    """Audit of 2026-11-29: jogged to (−30, 0, 30)°, e-stopped 0.1 s and released, the take-up's
    peak drove cable 1 to f_max (100 N) for 26 ticks."""
    from bridge_loop import BridgeLoop
    from test_controller_service import _request as request

    from controller.trajectory import Trajectory

    loop = BridgeLoop(params, seed=0)
    loop.run(0.5)
    jog = Trajectory.from_degrees([[-30.0, 0.0, 30.0]], [], 0.0, "jog")
    loop.svc.handle(request("j", kind="jog", trajectory_json=jog.to_json()), loop.stamp_s)
    for _ in range(20):
        loop.run(0.5)
        if _ended(loop, "j"):
            break
    loop.run(0.1, estop=((True, "x"),))
    start = len(loop.applied)
    loop.run(4.0, estop=((False, "x"),))
    applied = np.array(loop.applied[start:])
    assert applied.max() <= rules.PEAK_FORCE_FRACTION * params.limits.f_max + 1.0
    assert loop.outputs[-1].law_ran and not loop.svc.latched


def test_a_campaign_after_a_latch_an_estop_and_its_release_starts(params):
    """Audit of 2026-11-29: the release found the hold latched (a stuck encoder), returned before
    the take-up the e-stop owed was started or given up, and every new campaign waited for it
    forever. The campaign (what lifts a latch) now lifts it, and starts after the take-up (which
    since session 47 runs under the latch, at the last sane α̂, the latch lifted at its end)."""
    from bridge_loop import BridgeLoop

    loop = BridgeLoop(params, seed=0)
    loop.run(1.0)
    loop.svc.handle(_request("c-1"), loop.stamp_s)
    loop.run(1.0)
    frozen = float(loop.tick.theta_meas[0])
    for _ in range(5):
        loop.run(1.0, stuck={0: frozen})
        if loop.svc.latched:
            break
    assert loop.svc.latched
    loop.run(1.0, estop=((True, "operator"),))
    loop.run(0.5, estop=((False, "operator"),))
    loop.svc.handle(_request("c-2"), loop.stamp_s)
    reasons = set()
    for _ in range(round(5.0 / DT)):
        loop.run(DT)
        reasons.add(loop.svc.hold_reason.split(":")[0])
        if loop.svc.running:
            break
    assert loop.svc.running and not loop.svc.latched, [e.message for e in loop.events if e.campaign_id == "c-2"]
    assert "taking up the cables' slack after the e-stop" in reasons


def test_the_status_says_the_floor_now_a_waiting_campaign_and_how_the_take_up_ended(params):
    """Audit of 2026-11-29: the status gave the peak, not the floor now; a waiting campaign was
    nowhere to be seen; and how the take-up ended (taut, or its time limit) was never said. The
    hold's reason (the status, and the process's log when it changes) now says all three."""
    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.3, estop=((False, "audit"),))
    loop.svc.handle(_request("c-2"), loop.stamp_s)
    loop.run(DT)
    reason = loop.svc.hold_reason
    take_up = loop.svc._take_up
    assert take_up is not None
    level = take_up.level_N
    assert f"floor t_min + {level:.0f} N" in reason and "c-2" in reason, reason
    reasons = []
    while not loop.svc.running:
        loop.run(DT)
        reasons.append(loop.svc.hold_reason)
        assert len(reasons) < round(4.0 / DT)
    assert any("slack is taken up (taut)" in r for r in reasons), reasons[-5:]


def _restarted_controller(loop, params, gone_s: float = 0.2) -> None:
    """The controller process dies (the bridge's watchdog holds the forces) and a new one joins the
    bridge's run, as controller/process.py starts: α̂ from the first state it sees (eq. 33)."""
    from controller.laws import LawConfig
    from controller.service import CampaignService

    loop.run(gone_s, drop_commands=True)
    loop.svc = CampaignService(params, LawConfig(law=2), settle_s=0.5)
    loop.svc.initialise(loop.tick.theta_meas, np.asarray(loop.safety.force))


def test_a_controller_restarted_during_the_take_up_takes_the_slack_up(params):
    """Session 36's leftover: a controller restarted while the slack of an e-stop was being taken
    up knew nothing of the e-stop; its law held α̂ at t_min, below the motors' stiction, and the
    cables stayed slack. A controller joining a bridge run under way cannot know what the cables
    went through: it takes the slack up first, as after a release, bumplessly."""
    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.3, estop=((False, "audit"),))
    assert loop.svc.taking_up and loop.tick.slack.any()
    _restarted_controller(loop, params)
    assert loop.tick.slack.any()
    start = len(loop.applied) - 1
    reasons, speeds = [], []
    for _ in range(round(3.0 / DT)):
        loop.run(DT)
        reasons.append(loop.svc.hold_reason)
        speeds.append(float(np.abs(loop.tick.alpha_dot).max()))
    assert any("slack" in r and "started" in r for r in reasons), reasons[:3]
    # from the new controller's own commands on (the bridge's hold while none came is its own
    # test: test_bridge_hold_damping)
    assert math.degrees(max(speeds[round(0.1 / DT):])) <= 86.0
    assert not loop.tick.slack.any(), loop.tick.slack
    assert loop.outputs[-1].law_ran and loop.svc.hold_reason == ""
    err_deg = np.degrees(np.abs(loop.outputs[-1].alpha_hat_rad - loop.tick.alpha))
    assert err_deg.max() <= 5.0, err_deg
    assert np.abs(np.diff(np.array(loop.applied[start:]), axis=0)).max() <= 1.0 + 1e-9


def test_a_controller_restarted_on_taut_cables_takes_up_without_moving_the_neck(params):
    """The take-up a restarted controller runs when nothing was slack: the floor rises, no motor
    turns, the law takes over within its time limit, and the neck stays where it was held."""
    from bridge_loop import BridgeLoop

    loop = BridgeLoop(params, seed=0)
    loop.run(1.0)
    loop.svc.handle(_request("c-1"), loop.stamp_s)
    loop.run(3.0)
    loop.svc.stop("c-1", loop.stamp_s)
    loop.run(2.0)
    assert not loop.svc.running and not loop.tick.slack.any()
    _restarted_controller(loop, params)
    held = loop.tick.alpha.copy()
    start = len(loop.applied) - 1
    taking_up = False
    for _ in range(round(4.0 / DT)):
        loop.run(DT)
        taking_up |= loop.svc.taking_up
        assert np.degrees(np.abs(loop.tick.alpha - held)).max() <= 2.0
    assert taking_up and loop.outputs[-1].law_ran and not loop.tick.slack.any()
    assert np.abs(np.diff(np.array(loop.applied[start:]), axis=0)).max() <= 1.0 + 1e-9


@pytest.mark.parametrize("seed", [0, 1])
def test_a_controller_restarted_late_in_the_take_up_still_reads_alpha_hat_again(params, seed):
    """Session 37's audit: restarted 1.2 s into the take-up, one cable still slack, the first
    state's parity read −5.3 to −8.1 mm, above the first threshold (−9 mm): no re-estimate was
    owed and α̂, 12-22° off at the join, was still 6-9° off 6 s later."""
    loop = _dropped_on_slack_cables(params, seed)
    loop.run(1.2, estop=((False, "audit"),))
    assert loop.tick.slack.any() and loop.svc.taking_up
    _restarted_controller(loop, params)
    assert loop.svc._reestimate_when_taut  # owed from the first state
    loop.run(6.0)
    assert not loop.tick.slack.any() and loop.outputs[-1].law_ran
    err_deg = np.degrees(np.abs(loop.outputs[-1].alpha_hat_rad - loop.tick.alpha))
    assert err_deg.max() <= 5.0, err_deg


@pytest.mark.parametrize("seed", [0, 1])
def test_a_campaign_process_joining_after_an_estop_runs_after_the_take_up(params, seed):
    """Session 37's audit: a campaign process (its own trajectory, controller/process.py) joined
    the run just after an e-stop's release, began at once on three slack cables with α̂ 33° off,
    drove the neck to 62° (the joint limit is 60°) and ended ``finished`` with α̂ 18° off. It now
    waits for the take-up (its status says so), then approaches its first waypoint from α̂."""
    from controller.laws import LawConfig
    from controller.service import CampaignService

    loop = _dropped_on_slack_cables(params, seed)
    loop.run(DT, estop=((False, "audit"),))
    loop.svc = svc = CampaignService(params, LawConfig(law=2), settle_s=0.5, service=False, campaign_id="c-own")
    svc.initialise(loop.tick.theta_meas, np.asarray(loop.safety.force))
    svc.begin_own(control_test_trajectory(), loop.stamp_s)
    assert not svc.running and svc.taking_up
    loop.run(0.5)
    assert not svc.running and "c-own waits for it" in svc.hold_reason, svc.hold_reason
    alpha_max = 0.0
    for _ in range(30):
        loop.run(1.0)
        alpha_max = max(alpha_max, float(np.degrees(np.abs(loop.tick.alpha)).max()))
        if svc.outcome:
            break
    ended = [e for e in loop.events if e.campaign_id == "c-own" and e.event in ("finished", "aborted")]
    assert [e.event for e in ended] == ["finished"], [e.message for e in ended]
    assert alpha_max <= params.limits.alpha_max_deg, alpha_max
    err_deg = np.degrees(np.abs(loop.outputs[-1].alpha_hat_rad - loop.tick.alpha))
    assert err_deg.max() <= 5.0, err_deg


def test_an_estop_while_a_campaign_process_waits_for_the_take_up_aborts_it_once(params):
    from controller.laws import LawConfig
    from controller.service import CampaignService

    loop = _dropped_on_slack_cables(params, 0)
    loop.run(DT, estop=((False, "audit"),))
    loop.svc = svc = CampaignService(params, LawConfig(law=2), settle_s=0.5, service=False, campaign_id="c-own")
    svc.initialise(loop.tick.theta_meas, np.asarray(loop.safety.force))
    svc.begin_own(control_test_trajectory(), loop.stamp_s)
    loop.run(0.3)
    loop.run(0.1, estop=((True, "again"),))
    ended = [e for e in loop.events if e.campaign_id == "c-own" and e.event in ("finished", "aborted")]
    assert [e.event for e in ended] == ["aborted"] and "before it started" in ended[0].message, ended
    assert svc.outcome == "aborted" and not svc.running


def test_a_campaign_asked_for_during_the_take_up_is_checked_from_where_the_take_up_leaves_the_neck(params):
    """Session 40's open point: the approach of a campaign asked for during the take-up was
    validated from α̂ then, off by the slack, and run from where the take-up left the neck, a
    move nobody checked. The pose is now known only once the slack is wound in; the preparation
    waits for it (the shell's worker, :func:`controller.prepare.start_pose_when_known`)."""
    from test_controller_service import _request as request

    from controller.laws import LawConfig
    from controller.prepare import prepare, start_pose_when_known
    from controller.trajectory import Trajectory

    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.2, estop=((False, "audit"),))
    assert loop.svc.taking_up and loop.svc.start_pose() is None
    slack_alpha = np.array(loop.svc.ctl.estimator.alpha_hat)
    req = request("jog-t", kind="jog", trajectory_json=Trajectory.from_degrees([[10.0, 10.0, 10.0]], [], 0.0,
                                                                                "jog").to_json())
    assert loop.svc.request_start(req)
    clock = {"s": 0.0}

    def one_tick(_s: float) -> None:  # the worker's wait, as the loop goes on meanwhile
        loop.run(DT)
        clock["s"] += DT

    pose = start_pose_when_known(loop.svc.start_pose, lambda: loop.svc.wants(req), clock=lambda: clock["s"],
                                 sleep=one_tick)
    assert not loop.svc.taking_up and not loop.tick.slack.any()
    assert math.degrees(np.abs(pose - slack_alpha).max()) > 2.0  # what the old check had started from
    loop.svc.prepared(prepare(req, params, LawConfig(law=2), alpha_from_rad=pose), req, loop.stamp_s)
    assert loop.svc.running and loop.svc.trajectory is not None
    started_at = np.asarray(loop.svc.trajectory.waypoints_rad[0])
    assert math.degrees(np.abs(started_at - pose).max()) < 0.5, np.degrees([started_at, pose])


def test_a_take_up_that_never_ends_refuses_the_waiting_preparation_and_a_stop_gives_it_up():
    from controller.prepare import GivenUp, Refused, start_pose_when_known

    clock = {"s": 0.0}

    def later(s: float) -> None:
        clock["s"] += s

    with pytest.raises(Refused, match="still being taken up after 30 s"):
        start_pose_when_known(lambda: None, lambda: True, clock=lambda: clock["s"], sleep=later)
    asked = iter([True, True, False])
    with pytest.raises(GivenUp):
        start_pose_when_known(lambda: None, lambda: next(asked), clock=lambda: clock["s"], sleep=later)
    assert start_pose_when_known(lambda: np.zeros(3), lambda: False).tolist() == [0.0, 0.0, 0.0]


def test_the_newest_campaign_asked_for_during_the_take_up_is_the_one_that_runs(params):
    """Review of session 41: with the preparation waiting for the take-up, a second request (a
    slider dragged on right after a release) was refused ("preparing campaign jog-A") and the
    first one ran; before, the newest one superseded it, as behind a stop's brake."""
    from test_controller_service import _request as request

    from controller.laws import LawConfig
    from controller.prepare import prepare
    from controller.trajectory import Trajectory

    def jog(cid: str, deg: list[float]):
        return request(cid, kind="jog", trajectory_json=Trajectory.from_degrees([deg], [], 0.0, "jog").to_json())

    loop = _dropped_on_slack_cables(params, 0)
    loop.run(0.2, estop=((False, "audit"),))
    svc = loop.svc
    a, b = jog("jog-A", [10.0, 0.0, 0.0]), jog("jog-B", [-10.0, 5.0, 0.0])
    assert svc.request_start(a)  # the worker waits for the take-up with it
    loop.run(0.3)
    assert svc.taking_up and svc.request_start(b)
    assert not svc.wants(a) and svc.wants(b)  # the worker gives A up
    loop.run(DT)  # the answers go out with the next state's
    superseded = [e for e in loop.events if e.campaign_id == "jog-A"]
    assert [e.event for e in superseded] == ["aborted"] and "superseded by jog-B" in superseded[0].message
    while svc.start_pose() is None:
        loop.run(DT)
    svc.prepared(prepare(b, params, LawConfig(law=2), alpha_from_rad=svc.start_pose()), b, loop.stamp_s)
    assert svc.running and svc.campaign_id == "jog-B"


def test_a_latch_in_force_at_the_release_still_takes_the_slack_up(params):
    """Session 47 (docs/safety/transition_fuzz.py): an encoder glitch latched the hold while the
    drives were off; at the release the latched hold, without the take-up (which waited for the
    latch to be lifted), let the slack cables' drums wind in undamped and the neck reached
    500-845°/s (laws 1-3). The take-up now runs under the latch, at the last sane α̂: the neck
    moves as after a release without the latch, and the latch's hold follows."""

    def peak_after_release(glitch: bool) -> tuple[float, Any]:
        loop = _dropped_on_slack_cables(params, 0)
        if glitch:  # one reading off by more than a motor turns in a tick
            loop.run(DT, stuck={3: float(loop.tick.theta_meas[3]) + 54.5})
            assert loop.svc.latched and "encoder 4" in loop.svc.hold_reason
        loop.run(DT, estop=((False, "audit"),))
        peak = 0.0
        for _ in range(round(2.0 / DT)):
            loop.run(DT)
            peak = max(peak, float(np.abs(loop.tick.alpha_dot).max()))
        return math.degrees(peak), loop

    plain, _ = peak_after_release(False)
    latched, loop = peak_after_release(True)
    assert latched <= 1.2 * plain, (latched, plain)
    assert loop.svc.latched and "latched: encoder 4" in loop.svc.hold_reason, loop.svc.hold_reason


def test_an_estop_engaged_and_released_within_a_stale_gap_is_taken_for_one(params):
    """Session 47 (docs/safety/transition_fuzz.py): an e-stop engaged and released while no state
    reached the controller (232 ms of stale states) left it seeing "inactive" only, which a
    bridge's first states also are: the campaign ran on from the neck that fell, with no take-up.
    Drives inactive after they were active under its commands are an e-stop's release (nothing
    else leaves a bridge so): the campaign is aborted saying so, and the slack taken up."""
    from bridge_loop import BridgeLoop

    loop = BridgeLoop(params, seed=0)
    loop.run(0.5)
    loop.svc.handle(_request("c-1"), loop.stamp_s)
    loop.run(3.5)
    assert loop.svc.running
    # 232 ms without states: the controller holds by itself from 10 ms (its commands, on a state
    # older than the bridge's answer window, refused: none reach the bridge here), and the bridge
    # sees the e-stop engaged 8 ms in and released 210 ms later
    for k in range(116):
        if k >= 5:
            loop.svc.stale("stale state", DT * (k + 1))
        events = ((True, "operator"),) if k == 4 else ((False, "operator"),) if k == 109 else ()
        loop._bridge_tick(None, DT * (k + 1), k + 1, events)
    assert loop.safety.drive == "inactive"
    reasons = set()
    for _ in range(round(0.5 / DT)):
        loop.run(DT)
        reasons.add(loop.svc.hold_reason.split(":")[0])
    ended = _ended(loop, "c-1")
    assert ended and ended[0].event == "aborted" and "e-stop was engaged and released" in ended[0].message, ended
    assert "taking up the cables' slack after the e-stop" in reasons, reasons


def test_an_estop_while_another_controller_owns_the_bridge_is_taken_up_at_the_hand_back(params):
    """Session 47 (docs/safety/transition_fuzz2.py): the service took the bridge's states for
    "inactive" while it obeyed another controller, so an e-stop engaged and released meanwhile was
    never recorded: handed back during the other's take-up, the law ran at once on slack cables
    and α̂ was 12.2° off 3 s later (4.6° after the same e-stop seen). It owes the take-up now."""
    from bridge_loop import BridgeLoop

    from controller.laws import LawConfig
    from controller.service import CampaignService
    from controller.trajectory import Trajectory

    loop = BridgeLoop(params, seed=0)
    loop.run(0.3)
    loop.svc.handle(_jog_request("j", Trajectory.from_degrees([[35.0, -25.0, 20.0]], [], 0.0, "jog")), loop.stamp_s)
    loop.run(2.7)
    other = CampaignService(params, LawConfig(law=2), settle_s=0.5, service=True)
    other.initialise(loop.tick.theta_meas, np.asarray(loop.safety.force))
    for k in range(350):  # 0.7 s of the other's commands, an e-stop 0.1-0.5 s in
        theta, drive, force = loop.tick.theta_meas, loop.safety.drive, np.asarray(loop.safety.force)
        loop.svc.drive_reason = "the bridge obeys controller o, not this one"
        loop.svc.control(theta, loop.stamp_s, drive, force, obeyed=False)
        other.drive_reason = loop.safety.estop_reason if drive == "disabled" else loop.safety.hold_reason
        command = other.control(theta, loop.stamp_s, drive, force).force_N.tolist()
        loop._bridge_tick(command, 0.0, 0, ((True, "operator"),) if k == 50 else ((False, "operator"),) if k == 250 else ())
    reasons = set()
    for _ in range(round(3.0 / DT)):
        loop.run(DT)
        reasons.add(loop.svc.hold_reason.split(":")[0])
    assert "taking up the cables' slack after the e-stop" in reasons, reasons
    error = np.degrees(np.abs(loop.svc.ctl.estimator.alpha_hat - loop.tick.alpha).max())
    assert error < 8.0, error


def test_a_campaign_lifting_a_latch_after_an_estop_takes_over_without_a_step(params):
    """Review of session 47: a latch's lift winds the law's take-over down from the latch's hold
    only when the drives had not been off; after an e-stop under the latch (its take-up done,
    the latch's hold applied for seconds) the law took over at 4.4 N a tick."""
    from bridge_loop import BridgeLoop

    loop = BridgeLoop(params, seed=0)
    loop.run(1.0)
    loop.run(DT, stuck={1: float(loop.tick.theta_meas[1]) - 29.3})  # one glitch: a latch
    assert loop.svc.latched
    loop.run(0.5, estop=((True, "operator"),))
    loop.run(4.0, estop=((False, "operator"),))
    assert loop.svc.latched and loop.svc._take_up is None
    start = len(loop.applied) - 1
    loop.svc.handle(_request("c-1"), loop.stamp_s)
    loop.run(0.3)
    assert loop.svc.running
    step = float(np.abs(np.diff(np.array(loop.applied[start:]), axis=0)).max())
    assert step <= 1.5, step
