"""The law's commanded forces change by at most ``force_rate_max_N_s`` (controller/laws.py).

Reproduces a finding of session 10: on the robot truth, law 1's floor t_min (8.5 N) lies below the
motors' friction, a back-driven cable goes slack, the gear's backlash is crossed in a tick, the
encoder jumps, and α̂̇ drives the k_v term of eq. 59 into force steps of up to 84 N per tick.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.laws import ComputedTorque, LawConfig
from controller.offline import ServiceLoop, run_closed_loop
from controller.trajectory import identification_trajectory
from twin.model.params import load_params
from twin.sim.simulator import TwinConfig

BACKLASH_RAD = 0.44  # robot_truth.toml [actuation] backlash_rad


@pytest.fixture(scope="module")
def params():
    return load_params()


def _held_then_jump(params, config: LawConfig) -> np.ndarray:
    """Forces of a law holding the straight neck, then one encoder jumping by the backlash."""
    ctl = ComputedTorque(params, config)
    zero = np.zeros(params.n_joints)
    theta = np.zeros(params.n_cables)
    forces = [ctl.step(theta, zero, zero, zero).f.copy() for _ in range(200)]
    theta[0] -= BACKLASH_RAD
    forces += [ctl.step(theta, zero, zero, zero).f.copy() for _ in range(20)]
    return np.array(forces)


def test_an_encoder_jump_moves_the_forces_at_the_bounded_rate(params):
    config = LawConfig(law=1)
    per_tick = config.force_rate_max_N_s / config.rate_hz
    free = np.abs(np.diff(_held_then_jump(params, LawConfig(law=1, force_rate_max_N_s=math.inf,
                                                            alpha_hat_accel_max_rad_s2=math.inf)), axis=0))
    assert free[199:].max() > 2 * per_tick  # without the bound, the jump is a force step
    bounded = np.abs(np.diff(_held_then_jump(params, config), axis=0))
    assert bounded.max() <= per_tick + 1e-9


def test_an_encoder_jump_is_not_taken_for_a_speed(params):
    """Session 44: at rest (law 2 idle on the robot truth, 0.64 s after the first enable) a cable
    under the motors' stiction lets its motor cross the backlash within a tick; the α̂̇ filter took
    the jump of α̂ for a speed and the k_v term stepped the forces 10 N a tick for 2-4 ticks. α̂̇'s
    new sample now differs from the filtered value by at most ``alpha_hat_accel_max_rad_s2``·dt,
    so the filtered α̂̇ changes by no more in a tick."""
    for law in (1, 2, 3):
        unbounded = LawConfig(law=law, alpha_hat_accel_max_rad_s2=math.inf)
        config = LawConfig(law=law)
        speed_bound = config.alpha_hat_accel_max_rad_s2 / config.rate_hz
        speeds = {}
        for c in (unbounded, config):
            ctl = ComputedTorque(params, c)
            zero, theta = np.zeros(params.n_joints), np.zeros(params.n_cables)
            for _ in range(200):
                ctl.step(theta, zero, zero, zero)
            theta[1] += BACKLASH_RAD
            peak, before = 0.0, ctl.alpha_hat_dot.copy()
            for _ in range(20):  # the largest change of the filtered α̂̇ in a tick
                ctl.step(theta, zero, zero, zero)
                peak = max(peak, float(np.abs(ctl.alpha_hat_dot - before).max()))
                before = ctl.alpha_hat_dot.copy()
            speeds[c] = peak
        assert speeds[unbounded] > 3 * speed_bound  # the jump read as a speed
        assert speeds[config] <= speed_bound + 1e-9
        free, bounded = (np.abs(_held_then_jump(params, c)[200:] - _held_then_jump(params, c)[199]).max()
                         for c in (unbounded, config))
        print(f"law {law}: peak force change after the jump {free:.1f} N unbounded, {bounded:.1f} N bounded")
        assert bounded < 0.75 * free


def _idle_after_enable(params, config: LawConfig, seconds: float = 1.2) -> tuple[float, float]:
    """The campaign service idle at the straight neck from the first enable, closed on the robot
    truth through the bridge's safety rules: (largest encoder change in a tick, rad; largest
    change of the applied forces in a tick after the first 10, N)."""
    loop = ServiceLoop(params, config, TwinConfig(camera=False, seed=0, truth="robot"))
    applied, theta = [], []
    for _ in range(round(seconds * config.rate_hz)):
        theta.append(loop.tick.theta_meas.copy())
        applied.append(loop.step())
    jump = float(np.abs(np.diff(np.array(theta), axis=0)).max())
    return jump, float(np.abs(np.diff(np.array(applied[10:]), axis=0)).max())


def test_a_backlash_crossing_while_idle_after_the_first_enable_moves_the_forces_gently(params):
    """Session 46: idle at laws 1-2 after the first enable (robot truth), a cable under the motors'
    stiction lets its motor cross the gear's backlash 0.64 s in; with α̂̇'s sample bounded at 250
    rad/s² the k_v term still stepped the applied forces 8-9.5 N in one tick. At the default bound
    (50 rad/s²) it is a ramp."""
    for law in (1, 2):
        jump, step = _idle_after_enable(params, LawConfig(law=law))
        assert jump > 0.8 * BACKLASH_RAD  # the backlash is crossed: the case is what is tested
        assert step < 4.0, f"law {law}: {step:.2f} N in a tick"


def test_the_first_command_starts_from_the_applied_forces(params):
    config = LawConfig(law=2)
    ctl = ComputedTorque(params, config)
    zero = np.zeros(params.n_joints)
    applied = np.full(params.n_cables, 30.0)
    ctl.observe(np.zeros(params.n_cables), applied)
    f = ctl.step(np.zeros(params.n_cables), zero, zero, zero).f
    assert np.abs(f - applied).max() <= config.force_rate_max_N_s / config.rate_hz + 1e-9


def test_law_1_on_the_robot_truth_commands_no_force_step(params):
    """The §5.2.2 identification campaign as law 1 runs it, on the robot truth (seed 0 slackens
    cable 1 at 5.76 s): no tick's command steps by more than the bound."""
    config = LawConfig(law=1)
    run = run_closed_loop(params, config, identification_trajectory(), TwinConfig(truth="robot", seed=0, camera=False))
    steps = np.abs(np.diff(run.force_N, axis=0))
    assert (run.tension_N < 0.5).any()  # cables do go slack: the bound is what is tested
    assert steps.max() <= config.force_rate_max_N_s / config.rate_hz + 1e-9


def test_a_bad_rate_bound_is_refused():
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="force_rate_max_N_s"):
            LawConfig(force_rate_max_N_s=bad)
        with pytest.raises(ValueError, match="alpha_hat_accel_max_rad_s2"):
            LawConfig(alpha_hat_accel_max_rad_s2=bad)
