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
from controller.offline import run_closed_loop
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
    free = np.abs(np.diff(_held_then_jump(params, LawConfig(law=1, force_rate_max_N_s=math.inf)), axis=0))
    assert free[199:].max() > 2 * per_tick  # without the bound, the jump is a force step
    bounded = np.abs(np.diff(_held_then_jump(params, config), axis=0))
    assert bounded.max() <= per_tick + 1e-9


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
