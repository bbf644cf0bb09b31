"""The controller on a hostile bus (issue 13, findings 1, 2, 3, 6, 7, 8 on the controller side): a
real bridge (twin driver, real time) and a real controller service as processes on a loopback
hub, attacked from the test's own Zenoh session as a console or an intruder would."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest
from busutil import wait_until
from test_bridge_node import Collector

from bridge import bus
from bridge.session import free_tcp_port, open_session, publisher
from controller.laws import LawConfig
from controller.trajectory import Trajectory
from server.child_processes import isolate, loop_environ

# realtime: it asserts the commands keep flowing at 500 Hz while a worker validates a long
# trajectory; beside another module's stack on the loop CPU they once stopped 4.5 s (fresh-clone
# CI of 4c18a07), and its own stack had made test_console_strays' late (CI of c4babec).
pytestmark = pytest.mark.realtime

XNECK = [sys.executable, "-m", "server.cli"]
NOD = Trajectory.from_degrees([[0, 0, 0], [8, 4, 0], [0, 0, 0]], 1.0, 0.2, name="nod")


class Stack:
    def __init__(self, tmp: Path):
        self.tmp, self.hub = tmp, f"tcp/127.0.0.1:{free_tcp_port()}"
        self.session = open_session(listen=[self.hub], connect=[])
        self.procs: list[subprocess.Popen] = []
        self.seq = 0
        self.requests = publisher(self.session, bus.CAMPAIGN_REQUEST)
        self.raw_requests = self.session.declare_publisher(bus.CAMPAIGN_REQUEST)
        self.states = Collector(self.session, bus.MOTOR_STATE)
        self.commands = Collector(self.session, bus.MOTOR_COMMAND)
        self.status = Collector(self.session, bus.CONTROLLER_STATUS)
        self.events = Collector(self.session, bus.CAMPAIGN_EVENTS)
        self.health = Collector(self.session, f"{bus.PREFIX}/health/controller/*", bus.Health)
        self.bridge = self.start_bridge()
        self.controller = self.spawn("controller", "controller", "--law", "2")

    def spawn(self, name: str, *args: str) -> subprocess.Popen:
        # Placed as `xneck up` places its loop processes (loop CPU, real-time priority once set up):
        # fresh-clone CI of b6b400c saw a 3.0 N per-tick change at the e-stop's release on a stack
        # starved beside the other worker (a 64 ms gap in its commands), as d8ae598's saw campaigns
        # aborted on unplaced stacks (tests/test_stack.py `_procs(place=True)`).
        with open(self.tmp / f"{name}-{len(self.procs)}.log", "wb") as log:
            p = subprocess.Popen([*XNECK, *args, "--listen", "tcp/127.0.0.1:0", "--connect", self.hub], stdout=log,
                                 stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                                 env={**os.environ, "PYTHONUNBUFFERED": "1", **loop_environ(args[0])})
        isolate(p.pid, args[0], realtime=False)
        self.procs.append(p)
        return p

    def start_bridge(self) -> subprocess.Popen:
        return self.spawn("bridge", "bridge", "--driver", "twin")

    def request(self, cid: str, action: Literal["start", "stop"] = "start", **fields: Any) -> None:
        self.seq += 1
        self.requests.put(bus.CampaignRequest(seq=self.seq, stamp_s=time.time(), campaign_id=cid, action=action,
                                              **fields))

    def answers(self, cid: str) -> list[Any]:
        return [e for e in self.events.messages() if getattr(e, "campaign_id", None) == cid]

    def final(self, cid: str, timeout_s: float) -> bus.CampaignEvent:
        assert wait_until(lambda: any(e.event in ("finished", "aborted") for e in self.answers(cid)), timeout_s, 0.05), \
            (cid, self.answers(cid), self.log("controller"))
        return next(e for e in self.answers(cid) if e.event in ("finished", "aborted"))

    def log(self, name: str) -> str:
        return "\n".join(p.read_text(errors="replace")[-3000:] for p in sorted(self.tmp.glob(f"{name}-*.log")))

    def close(self) -> None:
        for p in reversed(self.procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(self.procs):
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        for c in (self.states, self.commands, self.status, self.events, self.health):
            c.close()
        self.requests.close()
        self.raw_requests.undeclare()
        self.session.close()


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    s = Stack(tmp_path_factory.mktemp("faults"))
    try:
        assert wait_until(lambda: len(s.status.messages()) > 200 and s.health.messages(), 120, 0.1), \
            s.log("controller") + s.log("bridge")
        yield s
    finally:
        s.close()


def _alive(stack: Stack) -> None:
    assert stack.controller.poll() is None, stack.log("controller")
    n = len(stack.status.messages())
    assert wait_until(lambda: len(stack.status.messages()) > n + 100, 10, 0.05), "the controller went quiet"


HOSTILE = {
    "empty-list": "[]", "null": "null", "one": "1", "deep": "[" * 50000 + "]" * 50000,
    "deep-waypoints": '{"waypoints_deg": ' + "[" * 50000 + "]" * 50000 + "}",
    "path": json.dumps("/etc/passwd"), "missing-file": json.dumps("/nonexistent/trajectory.json"),
    "long": json.dumps({"waypoints_deg": [[0, 0, 0], [1, 1, 1]], "durations_s": [1e6]}),
    "many": json.dumps({"waypoints_deg": [[0, 0, 0]] * 20000, "durations_s": 0.01}),
}


def test_malformed_campaign_requests_are_answered_counted_and_never_stop_the_controller(stack):
    """Finding 2: each request is refused with a reason (an aborted event of its id), counted in
    the controller's health; garbage that cannot be answered is counted; the service goes on."""
    for name, text in HOSTILE.items():  # one at a time: the service prepares one campaign at a time
        stack.request(f"bad-{name}", trajectory_json=text)
        ev = stack.final(f"bad-{name}", 30)
        assert ev.event == "aborted" and ev.message.startswith("refused") and "preparing" not in ev.message, (name, ev)
    for raw in (b"\x00garbage", b"{}", b'{"v": 1, "seq": 1, "stamp_s": 0, "campaign_id": "x", "action": "start"}',
                json.dumps({"v": 2, "seq": 1, "stamp_s": 0, "campaign_id": "../../etc", "action": "start"}).encode(),
                json.dumps({"v": 2, "seq": 1, "stamp_s": 0, "campaign_id": "x", "action": "start", "law": 7}).encode(),
                b'{"v": 2, "trajectory_json": "' + b"a" * 400_000 + b'"}'):
        stack.raw_requests.put(raw)
    assert "passwd" not in "".join(e.message for e in stack.answers("bad-path"))  # never opened, never echoed
    _alive(stack)
    assert wait_until(lambda: stack.health.messages()[-1].rejected[bus.CAMPAIGN_REQUEST] >= len(HOSTILE) + 6, 30, 0.1), \
        (stack.health.messages()[-1].rejected, stack.health.messages()[-1].last_reject_reason[:300])
    assert stack.health.messages()[-1].last_reject_reason
    # ... and the service still runs a good campaign, with its own counters (finding 7).
    idle_ticks = stack.status.messages()[-1].ticks
    stack.request("good", trajectory_json=NOD.to_json())
    assert stack.final("good", 60).event == "finished", stack.answers("good")
    mine = [s for s in stack.status.messages() if s.campaign_id == "good"]
    assert idle_ticks > 200 and mine[0].ticks < 50 and mine[-1].ticks >= mine[0].ticks  # counted from its start
    fin = stack.answers("good")[-1]
    assert fin.ticks >= mine[-1].ticks and f"overruns {fin.overruns}," in fin.message


def test_a_start_request_delivered_twice_runs_once_and_its_copy_is_counted(stack):
    """Review of session 53: the copy of a start request (the bus delivering it twice, a peer
    re-publishing it) was refused with an ``aborted`` event of the running campaign's id, which
    the console takes for that campaign's end. The copy is ignored and counted in Health."""
    rejected = stack.health.messages()[-1].rejected[bus.CAMPAIGN_REQUEST]
    stack.request("twice", trajectory_json=NOD.to_json())
    stack.request("twice", trajectory_json=NOD.to_json())
    assert stack.final("twice", 60).event == "finished", stack.answers("twice")
    assert [e.event for e in stack.answers("twice")].count("started") == 1, stack.answers("twice")
    assert not [e for e in stack.answers("twice") if e.event == "aborted"], stack.answers("twice")
    assert wait_until(lambda: stack.health.messages()[-1].rejected[bus.CAMPAIGN_REQUEST] > rejected, 10, 0.05)
    # the reason of the first Health that counted it: a later one may carry another topic's
    # reason (a state refused as ahead of the clock on a loaded machine, fresh-clone CI of session 54)
    first = next(h for h in stack.health.messages() if h.rejected[bus.CAMPAIGN_REQUEST] > rejected)
    assert "ignored" in first.last_reject_reason, first.last_reject_reason


def test_a_long_trajectory_is_refused_or_prepared_off_the_loop(stack):
    """Finding 8: a request beyond the maximum duration is refused with the reason at once; a long
    one within it is validated by a worker while the loop keeps commanding."""
    stack.request("too-long", trajectory_json=Trajectory.from_degrees([[0, 0, 0], [5, 5, 5]], 1000.0).to_json())
    ev = stack.final("too-long", 30)
    assert ev.event == "aborted" and "longer than" in ev.message
    rows = [[0, 0, 0], [3, 3, 3]] * 150
    long_ok = Trajectory.from_degrees(rows, 1.0, 0.95, name="long")  # 585 s, within the 600 s maximum
    t0 = time.perf_counter()
    stack.request("long", trajectory_json=long_ok.to_json())
    assert wait_until(lambda: stack.answers("long"), 30, 0.05), stack.log("controller")
    answered = time.perf_counter()
    ev = stack.answers("long")[0]
    assert ev.event == "started" or "time budget" in ev.message, ev
    sent = [t for t, _ in stack.commands.timed() if t0 <= t <= answered]
    # The loop went on commanding (it stopped for 11 s before); on 2 shared cores the worker and
    # the bridge compete for the CPU, so only a gap of seconds would be the loop waiting for it.
    assert len(sent) > 10 and np.diff([t0, *sent, answered]).max() < 3.0
    stack.request("long", action="stop")
    assert stack.final("long", 10).event == "aborted"


def test_forged_states_are_rejected_and_real_ones_keep_flowing(stack):
    """Finding 3: a state from the future (same bridge, same epoch) or from another bridge run is
    rejected and counted; the controller keeps answering the real bridge."""
    real = stack.states.messages()[-1]
    # block: all 80 must arrive to be counted, and a state's key drops under congestion (fresh-clone
    # CI of 2026-11-30 counted fewer than 80 in 30 s on a loaded machine)
    forged = publisher(stack.session, bus.MOTOR_STATE, block=True)
    try:
        for i in range(20):
            forged.put(bus.MotorState(**{**bus.as_plain(real), "seq": 10**6 + i, "stamp_s": 1e12}))
            forged.put(bus.MotorState(**{**bus.as_plain(real), "seq": 10**6 + i, "epoch": "forged", "stamp_s": 0.0}))
            # audit of 2026-11-26: the bound run's epoch, a fresh stamp, applied forces out of range
            now = stack.states.messages()[-1].stamp_s
            forged.put(bus.MotorState(**{**bus.as_plain(real), "stamp_s": now, "force_applied_N": [1e308] * 4}))
            forged.put(bus.MotorState(**{**bus.as_plain(real), "stamp_s": now, "force_applied_N": [1.0] * 7}))
            time.sleep(0.01)
    finally:
        forged.close()
    _alive(stack)
    last = stack.status.messages()[-1]
    assert last.stamp_s < 1e6 and abs(last.stamp_s - stack.states.messages()[-1].stamp_s) < 1.0
    assert wait_until(lambda: stack.health.messages()[-1].rejected[bus.MOTOR_STATE] >= 80, 30, 0.1)
    assert max(abs(f) for c in stack.commands.messages()[-50:] for f in c.force_N) <= 100.0


def test_every_command_is_on_the_state_clock_with_sender_and_epoch(stack):
    """Finding 6: holds included, every command carries the stamp and epoch of a state it answers."""
    time.sleep(0.5)
    commands = stack.commands.messages()
    time.sleep(0.1)  # the states they answer have arrived by then
    states = {(s.epoch, s.stamp_s) for s in stack.states.messages()}
    instance = stack.health.messages()[-1].instance
    assert len(commands) >= 200 and all(c.sender == instance for c in commands)
    # Over every command so far: on a loaded machine this test's own subscriber misses bursts of
    # states now and then (never the property under test), which a window of 200 could be.
    answered = [c for c in commands if (c.epoch, c.stamp_s) in states]
    assert len(answered) >= 0.97 * len(commands), [c for c in commands if c not in answered][:3]
    assert all(c.stamp_s < 1e5 for c in commands)  # never the wall clock (≈ 1.8e9 s)


def test_estop_release_brings_no_force_step_and_no_wind_up(stack):
    """Finding 1 (controller side): while the e-stop holds the drives disabled the controller
    sends the hold forces, not a growing law output; on release it takes over without a step."""
    estop = publisher(stack.session, bus.ESTOP)
    try:
        t_on = time.perf_counter()
        estop.put(bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="test e-stop"))
        assert wait_until(lambda: stack.states.messages()[-1].drive == "disabled", 30, 0.01)

        def seen_disabled() -> list[tuple[float, float]]:  # when the controller's statuses say it saw the e-stop
            return [(t, s.stamp_s) for t, s in stack.status.timed() if t >= t_on and "drives disabled" in s.hold_reason]

        # Not a fixed delay after the bridge: on a loaded machine the controller may see it later.
        assert wait_until(seen_disabled, 30, 0.01)
        t_dis, stamp_dis = seen_disabled()[0]
        time.sleep(3.0)
        t_off = time.perf_counter()
        estop.put(bus.EStop(seq=2, stamp_s=time.time(), engaged=False, reason="released"))
        assert wait_until(lambda: stack.states.messages()[-1].drive == "active", 30, 0.01)

        def answered_since_release() -> int:  # states the law answered since (not a fixed second:
            # on a loaded machine the stack had answered 9 in it, CI of session 45), by their stamps:
            # this test's subscriber, lagging on a loaded machine, received holds answering states of
            # the e-stop after t_off, and counted them (25 commands after it, CI of session 47)
            off = max(s.stamp_s for t, s in stack.states.timed() if t >= t_on and s.drive == "disabled")
            return len({c.stamp_s for t, c in stack.commands.timed() if c.stamp_s > off})

        assert wait_until(lambda: answered_since_release() > 150, 60, 0.05), answered_since_release()
        t_end = time.perf_counter()
    finally:
        estop.close()
    sent = [(t, c) for t, c in stack.commands.timed() if t >= t_on]
    cmds = [(t, np.array(c.force_N), c.stamp_s) for t, c in sent]
    # From the state on which the controller saw the e-stop (its stamp: on a loaded machine this
    # test's subscriber receives the last law commands after the status that says so).
    during = np.array([f for t, f, stamp in cmds if stamp >= stamp_dis and t <= t_off])
    # Nothing grows: the hold forces only follow α̂ as the neck settles on slack cables.
    assert len(during) > 100 and np.ptp(during, axis=0).max() < 8.0 and during.max() < 40.0, np.ptp(during, axis=0)
    window = [(f, c) for (t, c), (_t, f, _stamp) in zip(sent, cmds, strict=True) if t_off - 0.2 <= t <= t_end]
    # No step when the law takes over again, per controller tick, over the law's answers to new
    # states: on a loaded machine the bridge's states stall now and then, and the controller holds
    # after 10 ms without one, re-answering the last state with the static hold forces (a few N from
    # a moving law's: the fault campaign of CI at 2c0ceff saw 4.5 N); and this test's subscriber
    # misses a few commands now and then, the change across such a gap being several ticks'.
    law, newest = [], -np.inf
    for f, c in window:
        if c.stamp_s > newest:
            law.append((f, c.stamp_s))
            newest = c.stamp_s
    ticks = np.maximum(np.round(np.diff([stamp for _f, stamp in law]) / 0.002), 1.0)
    per_tick = np.abs(np.diff([f for f, _stamp in law], axis=0)) / ticks[:, None]
    assert len(law) > 100 and per_tick.max() < 3.0, (per_tick.max(), ticks.max())
    # Holds included, each command sent moves at most the law's force rate from the one before
    # (controller/laws.py, LawConfig.force_rate_max_N_s), once the drives obey again.
    step_N = LawConfig(law=2).force_rate_max_N_s / 500.0
    last_off = max(s.stamp_s for t, s in stack.states.timed() if t >= t_on and s.drive == "disabled")
    active = [(f, c.seq) for f, c in window if c.stamp_s > last_off]
    sent_between = np.diff([seq for _f, seq in active])
    moved = np.abs(np.diff([f for f, _seq in active], axis=0)).max(axis=1)
    assert len(active) > 100 and np.all(moved <= step_N * sent_between + 1e-6), (moved.max(), sent_between.max())
    disabled = [s for t, s in stack.status.timed() if t_dis <= t <= t_off]
    assert disabled and all(s.holding and "drives disabled" in s.hold_reason for s in disabled), \
        [(s.holding, s.hold_reason) for s in disabled if not (s.holding and "drives disabled" in s.hold_reason)]


def test_a_restarted_bridge_is_followed_at_once(stack):
    """Finding 3: a bridge killed and started again (new epoch, clock from 0) is taken at once;
    the controller re-initialises from its state and commands it (the new bridge enables)."""
    old_epoch = stack.states.messages()[-1].epoch
    os.killpg(stack.bridge.pid, signal.SIGKILL)
    stack.bridge.wait(10)
    stack.bridge = stack.start_bridge()
    assert wait_until(lambda: any(s.epoch != old_epoch for s in stack.states.messages()[-50:]), 60, 0.1), \
        stack.log("bridge")
    t_new = time.perf_counter()
    assert wait_until(lambda: any(c.epoch not in ("", old_epoch) for c in stack.commands.messages()[-50:]), 30, 0.01)
    assert time.perf_counter() - t_new < 2.0  # at once, not after the old stamps are caught up
    assert wait_until(lambda: stack.states.messages()[-1].drive == "active", 30, 0.05)
    first = next(c for c in stack.commands.messages() if c.epoch not in ("", old_epoch))
    assert first.stamp_s < 5.0  # the new run's clock
    _alive(stack)
