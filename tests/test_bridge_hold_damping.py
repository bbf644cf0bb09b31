"""The bridge's hold on cables an e-stop left slack (bridge/safety.py, "Hold damping";
bridge/motor_speed.py). Session 37: the controller gone while it took up the slack of an e-stop
(controller/take_up.py), the bridge's watchdog held with its rule (eq. 33 from the encoders, which
slack cables make wrong), the slack cables' drums broke free and wound in unloaded, and the neck
snapped up at 494-599°/s on the robot truth (docs/safety/controller_gone.py). Each motor is now damped while the bridge holds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from bridge.motor_speed import MotorSpeed
from bridge.safety import Inputs
from controller.laws import encoder_hold_forces

DT = 0.002


def _held_by_the_bridge(params, seed: int, gone_at_s: float, damping_N_s_rad: float | None = None):
    """The e-stop of the take-up tests, released; the controller stops ``gone_at_s`` into the
    take-up and the bridge holds for 3 s as its node does: the hold rule of the encoders' angles,
    the speeds of :class:`MotorSpeed`. Returns (peak joint speed °/s, the loop, the hold rule)."""
    from test_take_up import _dropped_on_slack_cables

    loop = _dropped_on_slack_cables(params, seed)
    loop.run(gone_at_s, estop=((False, "audit"),))
    assert loop.svc.taking_up
    safety = loop.safety
    if damping_N_s_rad is not None:
        safety.config = dataclasses.replace(safety.config, hold_damping_N_s_rad=damping_N_s_rad)
    rule = encoder_hold_forces(params)
    speed = MotorSpeed(params.n_cables, DT)
    speed.update(loop.tick.theta_meas.tolist())
    peak = 0.0
    for _ in range(round(3.0 / DT)):
        d = safety.step(Inputs(command_age_s=0.02, states_unanswered=5, hold_N=rule(loop.tick.theta_meas).tolist(),
                               speed_rad_s=speed.rad_s))
        assert d.drive == "hold"
        loop.tick = loop.twin.tick(np.asarray(d.force_N))
        speed.update(loop.tick.theta_meas.tolist())
        peak = max(peak, math.degrees(float(np.abs(loop.tick.alpha_dot).max())))
    return peak, loop, rule


@pytest.mark.parametrize(("seed", "gone_at_s"), [(0, 0.05), (1, 0.6)])
def test_a_hold_on_slack_cables_does_not_snap_the_neck(params, seed, gone_at_s):
    """Before: 600°/s (gone at 0.05 s) and 498°/s (0.6 s). Now within the trajectories' 86°/s,
    and at rest the damping is let go: the forces are the hold's own."""
    peak, loop, rule = _held_by_the_bridge(params, seed, gone_at_s)
    assert peak <= 86.0, peak
    at_rest = list(loop.safety.force)
    d = loop.safety.step(Inputs(command_age_s=0.02, states_unanswered=5, hold_N=rule(loop.tick.theta_meas).tolist(),
                                speed_rad_s=[0.0] * params.n_cables))
    assert d.force_N.tolist() == at_rest  # no damping left to let go


def test_without_the_damping_the_same_hold_snaps_the_neck(params):
    """The finding itself, kept as the reference the damping is measured against."""
    peak, _loop, _rule = _held_by_the_bridge(params, 0, 0.05, damping_N_s_rad=0.0)
    assert peak > 200.0, peak


def test_motor_speeds_are_low_passed_differences_and_survive_a_bad_reading():
    speed = MotorSpeed(2, DT, cutoff_hz=20.0)
    speed.update([0.0, 0.0])
    for k in range(1, 200):
        v = speed.update([0.01 * k, -0.02 * k])  # 5 rad/s and -10 rad/s
    assert v == pytest.approx([5.0, -10.0], rel=1e-6)
    first = MotorSpeed(1, DT, cutoff_hz=20.0)
    first.update([0.0])
    one_count = first.update([2 * math.pi / 2048])[0]
    assert 0.0 < one_count < 0.25 * (2 * math.pi / 2048) / DT  # a count's flicker, filtered
    assert speed.update([math.nan, 0.0]) == [0.0, 0.0]  # restarts rather than carry NaN
    assert speed.update([1.0, 1.0]) == [0.0, 0.0]
    with pytest.raises(ValueError):
        MotorSpeed(2, 0.0)


def test_a_reading_no_motor_can_make_restarts_the_speeds_and_stamps_time_them():
    """Session 37's audit: a reading 1e4 rad off (an encoder glitch) read as a speed had the
    hold's damping push a cable 33 N for 168 ms; a tick 40 ms late divided by 2 ms read a motor at
    1.5 rad/s as 7.8 rad/s."""
    from bridge.motor_speed import MAX_GAP_S, MAX_SPEED_RAD_S

    speed = MotorSpeed(1, DT)
    speed.update([0.0], 0.0)
    speed.update([0.0], DT)
    assert speed.update([1e4], 2 * DT) == [0.0] and speed.bad_readings == 1  # a glitch
    assert speed.update([0.0], 3 * DT) == [0.0] and speed.bad_readings == 2  # and back
    assert speed.update([MAX_SPEED_RAD_S * DT * 0.9], 4 * DT)[0] > 0.0  # fast, but a motor can
    steady = MotorSpeed(1, DT)
    t = 0.0
    for k in range(300):  # 1.5 rad/s, one tick in ten 40 ms late
        t += 0.040 if k % 10 == 9 else DT
        v = steady.update([1.5 * t], t)[0]
        assert abs(v - 1.5) < 0.05 or k < 100, (k, v)
    assert steady.update([1.5 * t], t) == [0.0]  # no time passed: starts again
    steady.update([0.0], t + MAX_GAP_S + 0.1)
    assert steady.update([0.0], t + MAX_GAP_S + 0.1 + DT) == [0.0]


def test_a_bad_reading_during_a_hold_barely_moves_the_forces_and_not_the_neck(params):
    """Held at a 30° jog's pose, one reading 1e4 rad off, then one 3 rad off (the most a motor
    can turn in a tick, 1600 rad/s), against the same hold without them."""
    from bridge_loop import BridgeLoop
    from test_controller_service import _request

    from controller.trajectory import Trajectory

    def held(glitch: dict[int, float]) -> tuple[np.ndarray, np.ndarray]:
        loop = BridgeLoop(params, seed=0)
        loop.run(0.5)
        jog = Trajectory.from_degrees([[30.0, 0.0, 0.0]], [], 0.0, "jog").to_json()
        loop.svc.handle(_request("j1", kind="jog", trajectory_json=jog), loop.stamp_s)
        loop.run(4.0)
        forces, alphas = [], []
        for k in range(round(0.6 / DT)):
            d = loop.safety.step(Inputs(command_age_s=0.02, states_unanswered=5,
                                        hold_N=loop.hold_rule(loop.tick.theta_meas).tolist(),
                                        speed_rad_s=loop.speed.rad_s))
            loop.tick = loop.twin.tick(np.asarray(d.force_N))
            reading = loop.tick.theta_meas.tolist()
            reading[3] += glitch.get(k, 0.0)
            loop.speed.update(reading)
            forces.append(d.force_N)
            alphas.append(loop.tick.alpha.copy())
        return np.array(forces), np.array(alphas)

    f0, a0 = held({})
    f1, a1 = held({100: 1e4, 200: 3.0})
    df = np.abs(f1 - f0).max(axis=1)
    assert df.max() <= 10.0 and (df > 1.0).sum() * DT <= 0.04, (df.max(), (df > 1.0).sum())
    assert np.degrees(np.abs(a1 - a0)).max() <= 0.1
