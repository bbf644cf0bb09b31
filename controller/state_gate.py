"""Which motor states the controller takes: those of one bridge run, on a clock consistent with
the controller's own (:class:`StateGate`; finding 3 of issue 13, docs/safety.md)."""

from __future__ import annotations

import math

from bridge import bus


class StateGate:
    """Which motor states the controller takes (finding 3 of issue 13): those of one bridge run
    (``bridge`` instance and ``epoch``), with stamps that never go back and never run ahead of the
    controller's own clock by more than ``skew_s`` since the last state taken (a lockstep twin's
    2 ms step per state is within it). Only after ``rebind_s`` without any state taken does the
    gate start again: at once from a state that continues the bound run's clock, else from a
    state of a new run (a restarted bridge) or of a stepped clock once the next state confirms it
    (same run, not earlier, not ahead of it). Another run, or a stamp off the bound run's clock,
    beside a live bridge is never taken, nor is a lone one that arrives first after a stall of the
    controller's CPU. A state that copies the live run's bridge and epoch (both in every state on
    the bus) with a stamp a little ahead is taken: the gate tells runs and clocks apart, not a
    forger from the bridge (20 Hz of such states kept the real bridge's refused, audit of
    2026-11-29); the bus's credentials keep strangers off it (docs/safety.md, "Who may link to the
    bridge"). ``now_s``: a monotonic clock (s).

    The first state ever is taken as it comes (there is nothing to compare it with), so a stray
    run seen first could keep the gate, fed at a few Hz, away from the bridge (audit of
    2026-11-26). With ``rate_hz`` (the law's), a rival run that for ``confirm_s`` states at half
    that rate or more, consistently on its own clock, while the bound run gave fewer than a tenth
    of it, is taken: a bridge states at the control rate. A run bound at that rate never gives way
    to another, however fast."""

    def __init__(self, skew_s: float = 0.05, rebind_s: float = 0.25, rate_hz: float | None = None,
                 confirm_s: float = 0.1) -> None:
        self.skew_s, self.rebind_s = skew_s, rebind_s
        self.rate_hz, self.confirm_s = rate_hz, confirm_s
        self.bridge = self.epoch = ""
        self._stamp = self._wall = -math.inf  # the newest stamp taken, and when
        self._taken = -math.inf  # when the last state was taken (a re-publication too)
        self._candidate: tuple[str, str, float, float] | None = None  # (bridge, epoch, stamp, when)
        self._n_taken = 0  # states taken so far
        # s the bound run's clock stepped by, when the last state taken re-bound the gate to its own
        # run on a stepped clock (None otherwise): the campaign on the old clock cannot go on
        self.stepped_s: float | None = None
        # a run other than the bound one: [bridge, epoch, stamp, when, states, since, _n_taken then]
        self._rival: list | None = None

    def _bind(self, state: bus.MotorState, now_s: float) -> str:
        self.stepped_s = None
        self.bridge, self.epoch = state.bridge, state.epoch
        self._stamp, self._wall = state.stamp_s, now_s
        self._taken, self._candidate, self._rival = now_s, None, None
        self._n_taken += 1
        return ""

    def _rival_takes_over(self, state: bus.MotorState, now_s: float) -> bool:
        """Count ``state`` (of another run than the bound one) for its run; True when that run
        states at the control rate and the bound one does not (class docstring)."""
        if self.rate_hz is None:
            return False
        r = self._rival
        if r is None or self._check(state, r[0], r[1], r[2], r[3], now_s):
            self._rival = [state.bridge, state.epoch, state.stamp_s, now_s, 1, now_s, self._n_taken]
            return False
        r[2], r[3], r[4] = max(r[2], state.stamp_s), now_s, r[4] + 1
        elapsed = now_s - r[5]
        expected = elapsed * self.rate_hz
        return elapsed >= self.confirm_s and r[4] >= 0.5 * expected and self._n_taken - r[6] < 0.1 * expected

    def _check(self, state: bus.MotorState, bridge: str, epoch: str, stamp: float, wall: float,
               now_s: float) -> str:
        """"" if ``state`` continues the run ``bridge``/``epoch`` last seen at ``stamp`` (its
        clock) and ``wall`` (ours), else why not."""
        if (state.bridge, state.epoch) != (bridge, epoch):
            return (f"MotorState of bridge {state.bridge!r} run {state.epoch!r}: the controller is bound to "
                    f"{bridge!r} run {epoch!r}, which is alive")
        if state.stamp_s < stamp:
            return f"MotorState stamp {state.stamp_s:.6g} s goes back in time (last {stamp:.6g} s)"
        ahead = (state.stamp_s - stamp) - (now_s - wall)
        if ahead > self.skew_s:
            return (f"MotorState stamp {state.stamp_s:.6g} s runs {ahead:.3g} s ahead of the controller's clock "
                    f"(at most {self.skew_s:g} s)")
        return ""

    def admit(self, state: bus.MotorState, now_s: float) -> str:
        """"" if ``state`` is taken, else why not."""
        if not self.epoch:
            return self._bind(state, now_s)  # the first state ever: nothing to compare it with
        why = self._check(state, self.bridge, self.epoch, self._stamp, self._wall, now_s)
        if why and (state.bridge, state.epoch) != (self.bridge, self.epoch) and self._rival_takes_over(state, now_s):
            return self._bind(state, now_s)
        if now_s - self._taken >= self.rebind_s and why:
            cand = self._candidate
            if cand is not None and not self._check(state, *cand, now_s):
                same_run = (state.bridge, state.epoch) == (self.bridge, self.epoch)
                step_s = (cand[2] - self._stamp) - (cand[3] - self._wall)
                self._bind(state, now_s)
                self.stepped_s = step_s if same_run else None
                return ""
            self._candidate = (state.bridge, state.epoch, state.stamp_s, now_s)
            return f"{why}; after {now_s - self._taken:.3g} s without a state, taken if the next one confirms it"
        if why:
            return why
        if state.stamp_s > self._stamp:
            self._stamp, self._wall = state.stamp_s, now_s
        self._taken, self._candidate, self.stepped_s = now_s, None, None
        self._n_taken += 1
        return ""


__all__ = ["StateGate"]
