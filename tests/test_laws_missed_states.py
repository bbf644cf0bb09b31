"""The law on the real time between the states it answers (controller/laws.py, "Time step").

States the controller never answers — the process skipping a burst's stale ones when it is behind
(controller/process.py ``_stale_in_burst``), the state gate refusing one, Zenoh dropping one — left
the law dividing two periods' encoder increment by one period: θ̇ and α̂̇ doubled for a tick, the
k_v term of eq. 59 spiked and the commanded forces stepped by the 10 N rate bound (audit: law 2's
control test in process, 5 % of the states missed singly, 74 ticks at the bound; none without
misses). The law now differentiates, integrates and predicts the stretch (eq. 58) over the gap
between the stamps of the states it answers."""

from __future__ import annotations

import numpy as np
import pytest
from bridge_loop import BridgeLoop

from controller.laws import ComputedTorque, LawConfig
from controller.trajectory import control_test_trajectory
from twin.sim.simulator import Twin, TwinConfig
from twin.sim.truth import load_truth

# pure computation, no bus or process: beside the realtime modules at nice 19 (tests/conftest.py)
pytestmark = pytest.mark.background

BOUND_N = 10.0  # the law's rate bound per command (LawConfig.force_rate_max_N_s at 500 Hz)


def _request(cid: str):
    from test_controller_service import _request as request

    return request(cid, trajectory_json=control_test_trajectory().to_json())


def _missed(k: int) -> bool:
    """Every 20th state, and a run of 3 every 200 ms, never answered."""
    return k % 20 == 19 or k % 100 in (50, 51, 52)


def _commanded_steps(params, unanswered, seconds: float = 8.0) -> tuple[np.ndarray, list]:
    """Per command, the largest change (N) of any cable's commanded force over law 2's control test
    in process (the bridge's safety rules, the robot truth), from its start for ``seconds``."""
    loop = BridgeLoop(params, seed=0, law=2)
    loop.run(1.0)
    loop.svc.handle(_request("ct"), loop.stamp_s)
    k0 = len(loop.outputs)
    loop.run(seconds, unanswered=unanswered)
    f = np.array([o.force_N for o in loop.outputs[k0 - 1:]])
    events = [(e.campaign_id, e.event, e.message) for e in loop.events if e.event != "progress"]
    return np.abs(np.diff(f, axis=0)).max(axis=1), events


def test_missed_states_do_not_step_the_commanded_forces(params):
    """Before: every 20th state and a run of 3 every 200 ms missed, the commands stepped by the
    10 N bound (module docstring); now as smooth as when every state is answered."""
    steps, events = _commanded_steps(params, _missed)
    assert ("ct", "aborted") not in [e[:2] for e in events], events
    assert steps.max() < 6.0, f"largest commanded step {steps.max():.2f} N"
    assert int((steps >= BOUND_N - 1e-6).sum()) == 0, f"{int((steps >= BOUND_N - 1e-6).sum())} ticks at the bound"


def _closed_loop(params, truth, stamped: bool, seconds: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Law 2 on a twin of ``truth`` in lockstep, the law told the states' stamps or not (then it
    takes every period as 1/rate_hz, as before): the commanded forces (T, n_cables) N and the
    tracking error α^d − α̂ (T, N) rad."""
    twin = Twin(params, TwinConfig(camera=False, seed=0, truth=truth))
    ctl = ComputedTorque(params, LawConfig(law=2))
    traj = control_test_trajectory()
    tick = twin.tick(np.zeros(params.n_cables))
    f, e = [], []
    for _ in range(round(seconds * 500)):
        a, ad, add = traj.sample_at(tick.t_s)
        cmd = ctl.step(tick.theta_meas, a, ad, add, traj.pretension_at(tick.t_s), stamp_s=tick.t_s if stamped else None)
        f.append(cmd.f.copy())
        e.append(cmd.e.copy())
        tick = twin.tick(cmd.f)
    return np.array(f), np.array(e)


def test_without_missed_states_on_a_steady_clock_the_commands_are_those_of_a_fixed_period(params):
    """A lockstep twin without the truth's timing jitter: its stamps are k·2 ms (with float
    rounding), and the law commands exactly what it did on its fixed period."""
    steady = load_truth("robot").replace("timing", jitter_s=0.0)
    stamped, fixed = _closed_loop(params, steady, True)[0], _closed_loop(params, steady, False)[0]
    np.testing.assert_array_equal(stamped, fixed)


def test_with_the_robots_timing_jitter_the_tracking_is_the_same(params):
    """The robot truth's 0.1 ms period jitter: the law now takes each period as it was; the
    closed loop's forces differ tick by tick (0.3 N on average over 6 s), its tracking does not
    (RMS of α^d − α̂ within 0.05° per joint)."""
    e1, e0 = _closed_loop(params, "robot", True)[1], _closed_loop(params, "robot", False)[1]
    rms1, rms0 = np.sqrt((e1**2).mean(axis=0)), np.sqrt((e0**2).mean(axis=0))
    np.testing.assert_allclose(np.degrees(rms1), np.degrees(rms0), atol=0.05)


def _at_bound(params, law: int, unanswered) -> int:
    loop = BridgeLoop(params, seed=0, law=law)
    loop.run(1.0)
    loop.svc.handle(_request("ct"), loop.stamp_s)
    k0 = len(loop.outputs)
    loop.run(8.0, unanswered=unanswered)
    f = np.array([o.force_N for o in loop.outputs[k0 - 1:]])
    return int((np.abs(np.diff(f, axis=0)).max(axis=1) >= BOUND_N - 1e-6).sum())


@pytest.mark.parametrize("law", [1, 3])
def test_other_laws_take_the_real_period_too(params, law):
    """Laws 1 and 3 (eq. 58's stretch predicted over the gap): missed states add no run of ticks
    at the bound (with the misses and a fixed period law 1 met it 100 times). The encoders'
    backlash jumps still meet it about once in 8 s (law 1 5 times before α̂̇'s bound, session 44):
    the same jump, shifted a few ticks by the misses, peaks at 9.7 N without them and at the bound
    with them, so one tick is the margin."""
    assert _at_bound(params, law, _missed) <= _at_bound(params, law, None) + 1
