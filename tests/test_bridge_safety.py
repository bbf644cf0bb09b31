"""The bridge's safety rules as a pure state machine (issue 12), tick by tick without a bus:
activation, clamping, the watchdog's ramp to the hold forces, leaving the hold, the e-stop."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from bridge.safety import EStopHolders, Inputs, Ownership, Safety, SafetyConfig

N = 4
HOLD = np.array([10.0, 12.0, 14.0, 16.0])  # the hold forces the node's worker has ready


def machine(**config) -> Safety:
    cfg = {"n_motors": N, "f_min_N": 2.0, "f_max_N": 100.0, "command_timeout_s": 0.010, "hold_ramp_ticks": 5,
           **config}
    return Safety(SafetyConfig(**cfg))


def cmd(force, age_s=0.0, source="law2", **extra) -> Inputs:
    return Inputs(command_N=[float(f) for f in force], source=source, command_age_s=age_s, **extra)


def idle(age_s=None, hold: np.ndarray | None = HOLD, **extra) -> Inputs:
    """A tick without a command; ``hold``: the hold forces ready for its angles (None: none)."""
    return Inputs(command_age_s=age_s, hold_N=None if hold is None else hold.tolist(), **extra)


def test_drives_start_inactive_and_the_first_valid_command_enables_them():
    s = machine()
    d = s.step(idle())
    assert (d.drive, d.enabled, d.force_N.tolist()) == ("inactive", False, [0.0] * N)
    d = s.step(cmd([20.0] * N))
    assert d.drive == "active" and d.enabled
    assert any("drives enabled" in m for _lvl, m in d.events)


def test_command_forces_are_clamped_to_the_force_range_and_counted():
    s = machine(max_active_step_N=math.inf)  # the clamp alone (the active rate bound: below)
    for _ in range(25):  # past the bumpless ramp from zero
        s.step(cmd([20.0] * N))
    d = s.step(cmd([0.5, 50.0, 100.0, 0.0]))
    assert d.force_N.tolist() == [2.0, 50.0, 100.0, 2.0]
    assert s.clamped == 1


def test_watchdog_ramps_linearly_to_the_hold_forces_then_a_command_leaves_the_hold():
    s = machine()
    start = np.full(N, 30.0)
    for _ in range(100):  # long enough for any start-up ramp to be over
        s.step(cmd(start))
    d = s.step(idle(age_s=0.009))
    assert d.drive == "active"  # within the timeout: keep the last command
    ramp = [s.step(idle(age_s=0.011 + 0.002 * k)) for k in range(7)]
    assert all(r.drive == "hold" and "no valid command for 11 ms" in ramp[0].hold_reason for r in ramp)
    assert s.holds == 1
    for k, r in enumerate(ramp[:5]):
        w = (k + 1) / 5
        assert r.force_N == pytest.approx((1 - w) * start + w * HOLD)
    assert ramp[-1].force_N.tolist() == HOLD.tolist()
    assert any(lvl == logging.WARNING and m.startswith("hold:") for lvl, m in ramp[0].events)
    d = s.step(cmd([25.0] * N))
    assert d.drive == "active" and d.hold_reason == ""
    assert any("leaving hold" in m for _lvl, m in d.events)


def test_the_ramp_into_a_hold_moves_no_force_faster_than_the_active_rate_bound():
    """Audit of 2026-11-29 (session 39): two controllers of one name drove the forces to f_max, and
    the hold's 5-tick linear ramp from there took 18-19 N a tick, beyond the 10 N per tick any
    command may move them. The ramp keeps its 5 ticks when it can, and takes longer when not."""
    s = machine(max_active_step_N=10.0)
    start = np.array([100.0, 100.0, 20.0, 100.0])
    for _ in range(200):  # past the start-up ramp
        s.step(cmd(start))
    applied = [s.step(cmd(start)).force_N]
    applied += [s.step(idle(age_s=0.011 + 0.002 * k)).force_N for k in range(15)]
    assert _max_step(applied) <= 10.0 + 1e-9, np.diff(np.array(applied), axis=0)
    assert applied[-1].tolist() == HOLD.tolist()  # reached: 90 N at 10 N a tick is 9 ticks
    assert applied[5][2] == pytest.approx(HOLD[2])  # a 6 N gap still ramps linearly over 5 ticks


def test_a_stall_of_the_loops_cpu_is_not_a_silent_controller():
    # The 10-minute idle soak (benchmarks/console_load.py --idle 600) held once or twice: the
    # VM took the loop's CPU, which the bridge and the controller share, for tens of ms. The
    # bridge (the higher priority) ran first after it and found its last command 50 ms old,
    # while the controller had not yet had the CPU to answer the one state published before.
    # A hold needs the controller to have had states to answer: five, and 10 ms.
    s = machine(command_timeout_states=5)
    for _ in range(100):
        s.step(cmd([30.0] * N, states_unanswered=0))
    d = s.step(idle(age_s=0.052, states_unanswered=1))  # the first tick after a 50 ms stall
    assert d.drive == "active" and s.holds == 0
    for k in range(2, 5):  # the controller still silent: its states are not yet 5
        assert s.step(idle(age_s=0.052 + 0.002 * k, states_unanswered=k)).drive == "active"
    d = s.step(idle(age_s=0.062, states_unanswered=5))
    assert d.drive == "hold" and s.holds == 1
    assert "no valid command for 62 ms (timeout 10 ms), 5 states unanswered" in d.hold_reason


def test_a_silent_controller_holds_on_the_same_tick_as_by_its_commands_age_alone():
    s = machine(command_timeout_states=5)
    for _ in range(100):
        s.step(cmd([30.0] * N, states_unanswered=0))
    # the normal pace: a state every 2 ms, the last command 0.5 ms after the state it answered
    for k in range(1, 5):
        assert s.step(idle(age_s=0.0015 + 0.002 * k, states_unanswered=k)).drive == "active"
    assert s.step(idle(age_s=0.0115, states_unanswered=5)).drive == "hold"


def test_without_the_watchdog_lockstep_never_holds():
    s = machine(watchdog=False)
    s.step(cmd([20.0] * N))
    assert s.step(idle(age_s=10.0)).drive == "active"


@pytest.mark.parametrize("hold", [None, np.array([10.0, np.nan, 14.0, 16.0]), np.array([10.0, 12.0, 14.0])],
                         ids=["none ready", "NaN", "too few"])
def test_without_hold_forces_ready_a_hold_keeps_the_present_forces(hold):
    s = machine()
    for _ in range(100):
        s.step(cmd([30.0] * N))
    for k in range(6):
        d = s.step(idle(age_s=0.02 + k, hold=hold))
    assert d.drive == "hold" and d.force_N.tolist() == [30.0] * N


def test_hold_forces_ready_later_are_reached_at_the_bounded_rate():
    s = machine(max_force_step_N=1.0)
    for _ in range(100):
        s.step(cmd([30.0] * N))
    first = s.step(idle(age_s=0.02, hold=None))
    assert first.drive == "hold" and any("no hold forces ready" in m for _lvl, m in first.events)
    ready = [s.step(idle(age_s=0.03 + k)) for k in range(30)]
    assert any("hold forces ready" in m for _lvl, m in ready[0].events)
    forces = [first.force_N] + [r.force_N for r in ready]
    assert forces[0].tolist() == [30.0] * N and _max_step(forces) <= 1.0 + 1e-12
    assert all(r.drive == "hold" for r in ready) and ready[-1].force_N.tolist() == HOLD.tolist()


def test_a_hold_without_hold_forces_during_the_start_up_ramp_raises_the_forces_to_f_min():
    s = machine(max_force_step_N=1.0)
    assert s.step(cmd([30.0] * N)).force_N.tolist() == [1.0] * N  # bumpless from zero: below f_min
    hold = [s.step(idle(age_s=0.02 + k, hold=None)).force_N for k in range(6)]
    assert hold[-1].tolist() == [2.0] * N


def test_hold_forces_are_kept_within_the_force_range():
    s = machine()
    for _ in range(100):
        s.step(cmd([30.0] * N))
    for k in range(8):  # 30 -> 100 N at most 10 N a tick: 7 ticks
        d = s.step(idle(age_s=0.02 + k, hold=np.array([0.5, 12.0, 150.0, 16.0])))
    assert d.force_N.tolist() == [2.0, 12.0, 100.0, 16.0]


def test_estop_disables_at_once_ignores_commands_and_release_waits_for_a_new_command():
    s = machine()
    s.step(cmd([20.0] * N))
    d = s.step(cmd([20.0] * N, estop=[(True, "console button")]))
    assert (d.drive, d.enabled, d.force_N.tolist()) == ("disabled", False, [0.0] * N)
    assert d.estop_reason == "console button"
    assert s.step(cmd([30.0] * N)).drive == "disabled"  # ignored while engaged
    d = s.step(idle(estop=[(False, "cleared")]))
    assert (d.drive, d.enabled, d.estop_reason) == ("inactive", False, "")
    assert s.step(cmd([25.0] * N)).drive == "active"


def test_release_and_command_in_the_same_tick_does_not_enable():
    # The command may have been sent before the release: only a later one may enable the drives.
    s = machine()
    s.step(cmd([20.0] * N, estop=[(True, "button")]))
    assert s.step(cmd([20.0] * N, estop=[(False, "cleared")])).drive == "inactive"
    assert s.step(cmd([20.0] * N)).drive == "active"


def test_an_undecodable_estop_counts_as_engaged_and_a_release_while_running_changes_nothing():
    s = machine()
    s.step(cmd([20.0] * N))
    assert s.apply_estop([(False, "route check")]) is False
    assert s.step(cmd([20.0] * N)).drive == "active"
    d = s.step(idle(age_s=0.0, estop=[(True, "malformed e-stop message: bad JSON")]))
    assert d.drive == "disabled" and d.estop_reason.startswith("malformed e-stop message")



def test_an_estop_engaged_and_released_within_one_tick_does_not_let_an_older_command_enable():
    """Audit of 2026-11-26: with [engage, release] in one tick's events, a command received before
    the engage came out ``active``: the drives were never switched off. A command in a tick that
    saw an engage may predate it, as one in a tick that saw a release may predate that."""
    s = machine()
    for _ in range(40):
        s.step(cmd([30.0] * N))
    d = s.step(cmd([30.0] * N, estop=[(True, "button"), (False, "cleared")]))
    assert (d.drive, d.enabled, d.force_N.tolist()) == ("inactive", False, [0.0] * N)
    assert s.step(cmd([30.0] * N)).drive == "active"  # the next command, after the release, enables

# -- bumpless enable (issue 13, finding 1) ---------------------------------------------------------

FINDING_1 = [81.0, 22.0, 8.0, 28.0]  # the first command seen after an e-stop release


def _max_step(forces) -> float:
    return float(np.abs(np.diff(np.array(forces), axis=0)).max())


def test_estop_release_ramps_to_the_first_commands_at_the_bounded_rate():
    s = machine(max_force_step_N=1.0)
    for _ in range(200):
        s.step(cmd([9.0] * N))
    applied = [s.step(cmd([9.0] * N)).force_N]
    applied.append(s.step(idle(age_s=0.0, estop=[(True, "console button")])).force_N)
    applied.append(s.step(idle(age_s=0.0, estop=[(False, "cleared")])).force_N)
    commands = [FINDING_1, [100.0, 48.0, 8.0, 54.0]] + [[100.0, 48.0, 8.0, 54.0]] * 150
    applied += [s.step(cmd(c)).force_N for c in commands]
    steps = np.abs(np.diff(np.array(applied[2:]), axis=0))
    assert steps.max() <= 1.0 + 1e-12, steps.max()
    assert applied[-1].tolist() == [100.0, 48.0, 8.0, 54.0]  # reached, then passed through


def test_an_estop_holders_token_engages_and_a_release_needs_no_other_holder_left():
    """Audit S3: the e-stop's holders (their liveliness tokens) keep it engaged for a bridge that
    never saw the EStop. A release acts when no holder but its sender is left, whichever of the
    sender's token drop and release comes first; a token that vanishes releases nothing."""
    h = EStopHolders()
    assert h.appeared("console-a") == (True, "e-stop engaged by console-a (it holds the e-stop token)")
    h.appeared("console-b")
    assert h.message((True, "button"), "console-a") == (True, "button")  # an engage acts as it is
    assert h.message((False, "cleared"), "console-a") is None  # console-b holds it still
    assert h.vanished("console-a") is None  # console-a let go: console-b holds it still
    assert h.message((False, "someone"), "") is None
    h.vanished("console-b")  # crashed: releases nothing by itself...
    assert h.holders == set()
    assert h.message((False, "cleared"), "") == (False, "cleared")  # ...an explicit release does
    # The holder's release before its token's drop (two callback threads): it acts once the
    # token is gone (review of session 41: anyone could name a live holder in a release).
    h.appeared("console-a")
    assert h.message((False, "cleared"), "console-a") is None
    assert h.vanished("console-a") == (False, "cleared")
    assert h.holders == set()
    # Applied in Safety: a holder's engage latches like any other; its release ends it.
    s = machine()
    s.step(cmd([20.0] * N))
    assert s.step(idle(age_s=0.0, estop=[h.appeared("console-a")])).drive == "disabled"
    assert s.estop_reason == "e-stop engaged by console-a (it holds the e-stop token)"
    assert s.step(cmd([20.0] * N)).drive == "disabled"
    assert h.message((False, "cleared"), "console-a") is None
    release = h.vanished("console-a")
    assert release is not None and s.step(idle(age_s=0.0, estop=[release])).drive == "inactive"


def test_a_release_naming_a_live_holder_waits_for_its_token_and_a_forged_one_never_acts():
    """Review of session 41: a release whose attachment named the console, its token alive, was
    obeyed at once: anyone on the bus could release the console's e-stop (holder names are
    public: a liveliness query finds them). It now acts only once that token is gone, within
    ``RELEASE_TOKEN_WAIT_S`` of the release (the holder drops its token, then releases: the two
    may arrive in either order); a forged release then expires."""
    from bridge.safety import RELEASE_TOKEN_WAIT_S

    now = {"s": 0.0}
    h = EStopHolders(clock=lambda: now["s"])
    h.appeared("console-a")
    assert h.message((False, "forged"), "console-a") is None  # its token lives: not yet
    now["s"] += RELEASE_TOKEN_WAIT_S + 0.1
    assert h.vanished("console-a") is None  # the console crashed much later: the forgery expired
    h.appeared("console-a")
    h.appeared("console-b")
    assert h.message((False, "cleared"), "console-a") is None
    assert h.vanished("console-a") is None  # console-b still holds it
    assert h.message((False, "cleared by b"), "console-b") is None
    assert h.vanished("console-b") == (False, "cleared by b")
    # the token gone first: the release acts at once
    h.appeared("console-c")
    assert h.vanished("console-c") is None
    assert h.message((False, "cleared by c"), "console-c") == (False, "cleared by c")


def test_every_enable_is_bumpless_then_commands_pass_through():
    s = machine(max_force_step_N=1.0)
    start_up = [s.step(cmd(FINDING_1)).force_N for _ in range(100)]
    assert start_up[0].tolist() == [1.0, 1.0, 1.0, 1.0]  # from zero, one step
    assert _max_step([np.zeros(N), *start_up]) <= 1.0 + 1e-12
    assert start_up[-1].tolist() == FINDING_1
    # Reached: commands within the active rate bound (10 N per tick) pass through at once
    # (clamped), in both directions.
    assert s.step(cmd([75.0, 30.0, 1.0, 36.0])).force_N.tolist() == [75.0, 30.0, 2.0, 36.0]
    # Leaving a hold: from the hold forces, at the bounded rate.
    hold = [s.step(idle(age_s=0.02 + k)).force_N for k in range(8)]  # 75 -> 10 N: 7 ticks of 10 N at most
    assert hold[-1].tolist() == HOLD.tolist()
    leave = [s.step(cmd(FINDING_1)).force_N for _ in range(100)]
    assert _max_step([hold[-1], *leave]) <= 1.0 + 1e-12
    assert leave[-1].tolist() == FINDING_1


# -- the rate of active commands (docs/safety.md, fault table) -----------------------------------


def test_active_commands_that_jump_move_the_forces_at_the_bounded_rate_and_are_counted():
    """Fault table of docs/safety.md: while active, commands passed through unbounded, so a
    controller slowed to 247 Hz by a flood stepped the cables 12.9 N in one tick, and nothing but
    the law's own bound kept a controller (a lab's own, a bug) from stepping them from f_min to
    f_max. Active commands now move the forces at most ``max_active_step_N`` per tick (default
    10 N: the law's own 5000 N/s at 500 Hz, so its commands pass through untouched)."""
    s = machine()
    assert s.config.max_active_step_N == 10.0
    for _ in range(60):
        s.step(cmd([30.0] * N))
    applied = [s.step(cmd([30.0] * N)).force_N]
    jump = [90.0, 2.0, 30.0, 45.0]
    d = s.step(cmd(jump))
    assert d.force_N.tolist() == [40.0, 20.0, 30.0, 40.0]
    assert [m for _lvl, m in d.events if "10 N per tick" in m], d.events
    applied.append(d.force_N)
    # A tick without a new command (the controller late, within the timeout) goes on towards it.
    d = s.step(idle(age_s=0.002))
    assert (d.drive, d.force_N.tolist()) == ("active", [50.0, 10.0, 30.0, 45.0])
    applied.append(d.force_N)
    later = [s.step(cmd(jump)) for _ in range(6)]
    applied += [x.force_N for x in later]
    assert _max_step(applied) <= 10.0 + 1e-12
    assert applied[-1].tolist() == jump
    assert s.rate_limited == 5  # 40, 50, 60, 70, 80 N: bounded; 90 N was within the bound
    assert not any(later_d.events for later_d in later)  # one log line per run of bounded ticks
    # A step of exactly the bound passes through.
    assert s.step(cmd([80.0, 12.0, 20.0, 55.0])).force_N.tolist() == [80.0, 12.0, 20.0, 55.0]
    assert s.rate_limited == 5


def test_the_active_rate_bound_is_a_positive_force():
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="max_active_step_N"):
            machine(max_active_step_N=bad)
    assert machine(max_active_step_N=math.inf).config.max_active_step_N == math.inf  # explicitly off


# -- ownership (issue 13, finding 5) ---------------------------------------------------------------


def test_the_first_live_sender_owns_the_bridge_others_are_refused_until_its_token_vanishes():
    own = Ownership(epoch="e1")
    assert "no liveliness token" in own.admit("ctl-a", "e1")  # not alive: never an owner
    own.appeared("ctl-a")
    own.appeared("ctl-b")
    assert own.admit("ctl-a", "e1") == "" and own.owner == "ctl-a"
    assert own.admit("ctl-b", "e1") == "bridge owned by ctl-a"
    assert own.admit("ctl-a", "e1") == ""
    assert own.vanished("ctl-c") is False and own.owner == "ctl-a"
    assert own.vanished("ctl-a") is True and own.owner == ""
    assert own.admit("ctl-a", "e1") != ""  # gone is gone until its token is back
    assert own.admit("ctl-b", "e1") == "" and own.owner == "ctl-b"


def test_a_command_for_another_bridge_run_is_refused():
    own = Ownership(epoch="e2")
    own.appeared("ctl-a")
    reason = own.admit("ctl-a", "e1")
    assert "epoch" in reason and "e1" in reason and own.owner == ""
    assert own.admit("ctl-a", "e2") == ""


def test_an_oversized_or_odd_sender_never_becomes_the_owner():
    # Published in every state at 500 Hz and logged: a name from the bus is bounded like an instance name.
    own = Ownership(epoch="e1")
    for name in ("x" * 65, "a b", "", "ctl/other"):
        own.appeared(name)
        assert "not a valid controller instance name" in own.admit(name, "e1"), name
    assert own.owner == ""
    huge = own.admit("y" * 100_000, "e1")
    assert len(huge) < 200


def test_a_new_owners_first_command_is_ramped_to_not_stepped():
    """Audit of 2026-11-26: the owner's session ended and a second controller's command came within
    the watchdog's timeout: the applied forces stepped from 30 N to [90, 2, 90, 2] N in one tick
    (91.5 N in a closed loop). A change of sender is an enable like any other: bumpless."""
    s = machine(max_force_step_N=1.0)
    for _ in range(60):
        s.step(cmd([30.0] * N, sender="ctl-a"))
    applied = [s.step(cmd([30.0] * N, sender="ctl-a")).force_N]
    d = s.step(cmd([90.0, 2.0, 90.0, 2.0], sender="ctl-b"))
    assert any("ctl-b" in m and "ramping" in m for _lvl, m in d.events)
    applied.append(d.force_N)
    applied += [s.step(cmd([90.0, 2.0, 90.0, 2.0], sender="ctl-b")).force_N for _ in range(80)]
    assert _max_step(applied) <= 1.0 + 1e-12
    assert applied[-1].tolist() == [90.0, 2.0, 90.0, 2.0]  # reached, then passed through
    # The same sender's commands pass through at once, as before (within the active rate bound).
    assert s.step(cmd([85.0, 7.0, 82.0, 10.0], sender="ctl-b")).force_N.tolist() == [85.0, 7.0, 82.0, 10.0]


def test_a_bridge_loop_held_up_beyond_the_timeout_ramps_the_next_command():
    """Audit of 2026-11-26: a bridge stopped for 0.3-25 s mid-campaign (SIGSTOP; a VM or kernel
    stall) stayed 'active' throughout, so on waking it applied the controller's newest command at
    once and the law's return after it: 13-24 N in one tick. A tick that comes after a hold-up of
    the bridge's own loop longer than the command timeout ramps like an enable."""
    s = machine(max_force_step_N=1.0)
    for _ in range(60):
        s.step(cmd([30.0] * N))
    applied = [s.step(cmd([30.0] * N)).force_N]
    d = s.step(cmd([54.0, 30.0, 30.0, 6.0], resumed_after_s=0.3))
    assert any("held up" in m and "ramping" in m for _lvl, m in d.events)
    applied.append(d.force_N)
    applied += [s.step(cmd([54.0, 30.0, 30.0, 6.0])).force_N for _ in range(40)]
    assert _max_step(applied) <= 1.0 + 1e-12
    assert applied[-1].tolist() == [54.0, 30.0, 30.0, 6.0]


@pytest.mark.parametrize("at_resume", ["no command", "the command from before the stall"])
def test_a_stall_ramps_until_a_command_computed_after_it_is_reached(at_resume):
    """Audit of 2026-11-28 (a 1 s SIGSTOP of `xneck up`'s bridge mid-campaign, 3 resumes of 3): the
    first tick after the stall had no new command, or the one sent before the stall, which equals
    the applied forces, so the ramp ended at once ("bumpless ramp done") and the controller's
    answers to the new states stepped the cables 10 N per tick. The ramp ends only on a command
    that arrived after the resume."""
    s = machine(max_force_step_N=1.0, command_timeout_states=5)
    for _ in range(60):
        s.step(cmd([30.0] * N, states_unanswered=0))
    applied = [np.array(s.force)]
    first = (idle(age_s=1.0, states_unanswered=1, resumed_after_s=1.0) if at_resume == "no command"
             else cmd([30.0] * N, age_s=0.0, resumed_after_s=1.0))
    d = s.step(first)
    assert d.drive == "active" and any("held up" in m for _lvl, m in d.events)
    assert not any("ramp done" in m for _lvl, m in d.events)
    applied.append(d.force_N)
    answers = [[54.0, 30.0, 30.0, 6.0], [64.0, 28.0, 30.0, 2.0], [74.0, 26.0, 30.0, 2.0]]
    applied += [s.step(cmd(answers[min(k, 2)], states_unanswered=0)).force_N for k in range(60)]
    assert _max_step(applied) <= 1.0 + 1e-12
    assert applied[-1].tolist() == answers[2]


def _holding(s: Safety, force: float = 30.0) -> None:
    for _ in range(100):
        s.step(cmd(np.full(N, force)))
    for k in range(10):  # into the hold, past its 5-tick ramp
        s.step(idle(age_s=0.011 + 0.002 * k))
    assert s.drive == "hold" and s.force == HOLD.tolist()


def test_a_hold_damps_each_motor_beyond_its_dead_band_at_a_bounded_rate():
    """bridge/safety.py, "Hold damping": −c·(|v| − band) against each motor's speed, reached at
    max_force_step_N a tick, let go the same way; none within the dead band or without speeds."""
    s = machine(hold_damping_N_s_rad=1.0, hold_damping_deadband_rad_s=2.0)
    _holding(s)
    speeds = [12.0, -7.0, 1.5, math.nan]  # winding in fast, paying out, a count's flicker, no reading
    steps = [s.step(idle(age_s=0.05, speed_rad_s=speeds)).force_N for _ in range(15)]
    assert np.abs(np.diff(np.vstack([HOLD, *steps]), axis=0)).max() <= 1.0 + 1e-12
    # 10 N off the first (held at f_min = 2 N), 5 N onto the second, none on the others
    assert steps[-1].tolist() == pytest.approx([2.0, 17.0, 14.0, 16.0])
    for _ in range(15):  # at rest again: the damping is let go at the same rate
        d = s.step(idle(age_s=0.05, speed_rad_s=[0.0] * N))
    assert d.force_N.tolist() == HOLD.tolist()


def test_a_command_after_a_damped_hold_starts_from_the_applied_forces():
    s = machine()
    _holding(s)
    for _ in range(5):
        applied = s.step(idle(age_s=0.05, speed_rad_s=[20.0, 0.0, 0.0, 0.0])).force_N
    d = s.step(cmd(np.full(N, 30.0)))
    assert d.drive == "active" and np.abs(d.force_N - applied).max() <= 1.0 + 1e-12


@pytest.mark.parametrize("bad", [{"hold_damping_N_s_rad": -1.0}, {"hold_damping_N_s_rad": math.nan},
                                 {"hold_damping_deadband_rad_s": math.inf}])
def test_bad_hold_damping_settings_are_refused(bad):
    with pytest.raises(ValueError, match="hold_damping"):
        machine(**bad)


def test_the_hold_damping_is_capped_and_does_not_wind_up_against_the_force_range():
    """Session 37's audit: unbounded, the damping pushed a cable 48 N; clamped at f_min it kept
    growing, and the cable sat at f_min 140-200 ms after the speed had gone."""
    s = machine(hold_damping_max_N=30.0)
    _holding(s)
    for _ in range(60):  # a motor paying out at 100 rad/s, another winding in as fast
        d = s.step(idle(age_s=0.05, speed_rad_s=[-100.0, 100.0, 0.0, 0.0]))
    assert d.force_N.tolist() == pytest.approx([10.0 + 30.0, 2.0, 14.0, 16.0])  # capped; floored at f_min
    d = s.step(idle(age_s=0.05, speed_rad_s=[0.0] * N))
    assert d.force_N.tolist() == pytest.approx([39.0, 3.0, 14.0, 16.0])  # at once back up from f_min: no wind-up


def test_the_holders_own_reason_replaces_its_tokens_whichever_comes_first():
    """CI of session 40: the console's e-stop message and its token travel apart; when the token
    came first the bridge kept its generic reason and the operator's ("Escape key") was lost.
    The message's reason replaces the token's; a token coming after a message changes nothing."""
    h = EStopHolders()
    for first, second, shown in (("token", "message", "Escape key"), ("message", "token", "Escape key")):
        s = machine()
        s.step(cmd([20.0] * N))
        events = {"token": h.appeared("console-a"), "message": h.message((True, "Escape key"), "console-a")}
        assert s.step(idle(age_s=0.0, estop=[events[first]])).drive == "disabled"
        assert s.step(idle(age_s=0.0, estop=[events[second]])).drive == "disabled"
        assert s.estop_reason == shown, (first, s.estop_reason)
        h.vanished("console-a")


def test_only_a_holders_own_engage_replaces_its_tokens_reason():
    """Audit of session 42: any peer's engage replaced the reason of an e-stop held through a
    token ("test stop by console-abc123, cleared - safe to release" in every state, the holder
    still holding). A stranger's engage, named or not, leaves it; the holder's own replaces it."""
    h = EStopHolders()
    s = machine()
    s.step(cmd([20.0] * N))
    assert s.step(idle(age_s=0.0, estop=[h.appeared("console-a")])).drive == "disabled"
    token_reason = s.estop_reason
    for stranger in ("", "cli-x", "console-b"):
        s.step(idle(age_s=0.0, estop=[h.message((True, "cleared, safe to release"), stranger)]))
        assert s.estop_reason == token_reason, stranger
    s.step(idle(age_s=0.0, estop=[h.message((True, "Escape key"), "console-a")]))
    assert s.estop_reason == "Escape key" and type(s.estop_reason) is str
    # The holder's words taken before its token was known, applied after it (a bridge that starts
    # under `xneck estop engage --hold`: the token from its start-up query, the message queued;
    # CI of session 42): still the holder's own.
    h, s = EStopHolders(), machine()
    s.step(cmd([20.0] * N))
    words = h.message((True, "before the bridge"), "cli-a")
    s.apply_estop([h.appeared("cli-a")])
    s.step(idle(age_s=0.0, estop=[words]))
    assert s.estop_reason == "before the bridge"
    # A named engage that disables: its reason goes into every state as a plain str (msgspec
    # encodes no str subclass: the bridge had published no state after one).
    s = machine()
    s.step(cmd([20.0] * N))
    s.step(idle(age_s=0.0, estop=[EStopHolders().message((True, "first words"), "cli-b")]))
    assert s.drive == "disabled" and type(s.estop_reason) is str


def test_an_engage_after_a_release_waiting_for_its_token_is_never_undone_by_it():
    """Review of session 41 (the fix's review): a release waiting for its holder's token was
    applied when the token went even after a newer engage: the holder's own quick re-engage (the
    drives free for the ticks until its new token came), or another operator's engage, undone."""
    from bridge.safety import RELEASE_TOKEN_WAIT_S

    now = {"s": 0.0}
    # (b) the holder releases and re-engages at once: release, engage message, old token gone
    h = EStopHolders(clock=lambda: now["s"])
    h.appeared("console-a")
    assert h.message((False, "cleared"), "console-a") is None
    assert h.message((True, "pressed again"), "console-a") == (True, "pressed again")
    assert h.vanished("console-a") is None
    # (c) another engages meanwhile (its token comes and goes: a terminal without --hold)
    h = EStopHolders(clock=lambda: now["s"])
    h.appeared("console-a")
    assert h.message((False, "cleared"), "console-a") is None
    assert h.message((True, "terminal"), "cli-b") == (True, "terminal")
    h.appeared("cli-b")
    h.vanished("cli-b")
    now["s"] += 0.5
    assert h.vanished("console-a") is None
    # a release whose token goes too late is said expired (the node warns: release again)
    h = EStopHolders(clock=lambda: now["s"])
    h.appeared("console-a")
    assert h.message((False, "cleared"), "console-a") is None
    now["s"] += RELEASE_TOKEN_WAIT_S + 1.0
    assert h.vanished("console-a") is None and h.expired == "cleared"
    assert h.message((False, "again"), "console-a") == (False, "again")  # the next one acts
