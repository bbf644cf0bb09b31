"""``xneck up --restarts N``: a child that dies is restarted after a back-off, not at once.

Review of session 46: a controller or camera that crashed at start-up was restarted on the
supervisor's next pass, its N restarts used up in a burst of a few seconds. The delay now grows as
systemd's RestartSec with RestartSteps: 1 s, 2 s, 4 s, ... at most 30 s, counted over the restart
window. Pure functions and a fake clock: no process is started here (the restart of a real
controller is in tests/test_up_child_death.py).
"""

from __future__ import annotations

import itertools

import pytest

from server.cli.up import RESTART_DELAY_MAX_S, RESTART_WINDOW_S, RestartPlan, restart_delay_s

PASS_S = 0.2  # the supervisor's pass


def test_the_delay_doubles_per_earlier_restart_and_is_capped() -> None:
    assert [restart_delay_s(n) for n in range(7)] == [1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0]
    assert restart_delay_s(100) == RESTART_DELAY_MAX_S == 30.0  # no overflow past the cap
    assert restart_delay_s(-1) == 1.0


def _starts_of_a_child_that_crashes_at_start(restarts: int, until_s: float) -> tuple[list[float], float | None]:
    """Drive a plan as the supervisor's loop does, a pass every PASS_S, for a controller that dies
    on the pass after each start. Returns the (re)start times (s) and when the stack stopped (None:
    it did not within ``until_s``)."""
    plan = RestartPlan(restarts)
    starts, alive, now = [0.0], True, 0.0
    while now < until_s:
        now = round(now + PASS_S, 6)
        if plan.due(now) == ["controller"]:
            starts.append(now)
            alive = True
            continue
        if alive:  # it dies on the first pass after it started
            alive = False
            plan.forget_old(now)
            if not plan.may_restart("controller"):
                return starts, now
            plan.plan("controller", now)
        assert alive or plan.waiting("controller")  # a dead child waits: not judged again each pass
    return starts, None


def test_a_child_that_crashes_at_start_is_restarted_ever_later_not_in_a_burst() -> None:
    starts, stopped = _starts_of_a_child_that_crashes_at_start(restarts=5, until_s=120.0)
    gaps = [round(b - a, 6) for a, b in itertools.pairwise(starts)]
    # each restart its delay after the death a pass after the start before it
    assert gaps == [PASS_S + d for d in (1.0, 2.0, 4.0, 8.0, 16.0)], gaps
    assert stopped is not None and stopped == pytest.approx(starts[-1] + PASS_S)  # the 6th death stops the stack
    # before the back-off, all 5 restarts were used up within 5 passes (2 s)
    assert starts[-1] > 30.0


def test_restarts_and_their_delay_are_counted_within_the_window_and_per_child() -> None:
    plan = RestartPlan(3)
    assert plan.plan("controller", 0.0) == 1.0 and plan.waiting("controller")
    assert plan.due(0.99) == [] and plan.due(1.0) == ["controller"] and not plan.waiting("controller")
    assert plan.plan("controller", 5.0) == 2.0
    assert plan.plan("camera", 5.0) == 1.0  # its own count: a flaky camera does not lengthen the controller's
    assert plan.due(6.0) == ["camera"] and plan.due(7.0) == ["controller"]
    assert plan.used("controller") == 2 and plan.may_restart("controller")
    assert not plan.may_restart("bridge") and not plan.may_restart("server")
    # past the window the old restarts no longer count, nor lengthen the delay
    plan.forget_old(5.0 + RESTART_WINDOW_S)
    assert plan.used("controller") == 0 and plan.plan("controller", 5.0 + RESTART_WINDOW_S) == 1.0
    plan.plan("controller", 700.0)
    plan.plan("controller", 701.0)
    assert not plan.may_restart("controller")  # 3 of 3 within the window
