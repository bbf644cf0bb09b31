"""The bridge's safety rules on a real Zenoh bus (issue 7): clamping, the 10 ms watchdog to the
hold forces, the e-stop, the drives disabled on exit, a killed controller, a flood of malformed
commands. The twin driver stands in for the motors; the rules are the same for the robot."""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zenoh
from busutil import bus_pair, run_in_thread, wait_until

from bridge import bus
from bridge.driver import Lifecycle
from bridge.node import BridgeConfig, BridgeNode, HoldWorker, pace, run_realtime
from bridge.safety import SafetyConfig
from bridge.session import liveliness_token, publisher, subscribe_latest
from controller.laws import encoder_hold_forces, hold_forces
from server.cli.processes import bridge_node
from twin.sim.driver import TwinDriver, TwinDriverConfig

pytestmark = pytest.mark.realtime  # the watchdog's hold timing and the node's ticks, on a real bus
DT = 0.002
XNECK = [sys.executable, "-m", "server.cli"]


class Collector:
    """Every message of one key with its receive time (perf_counter)."""

    def __init__(self, session, key, msg_type=None):
        self.items: list[tuple[float, object]] = []
        self._lock = threading.Lock()
        msg_type = msg_type or bus.message_type(key)
        assert msg_type is not None, key

        def cb(sample):
            try:
                msg = bus.decode(msg_type, sample.payload.to_bytes())
            except bus.BusDecodeError:
                return
            with self._lock:
                self.items.append((time.perf_counter(), msg))

        self._sub = session.declare_subscriber(key, cb)

    def messages(self):
        with self._lock:
            return [m for _, m in self.items]

    def latest(self):
        with self._lock:
            return self.items[-1][1]

    def timed(self):
        with self._lock:
            return list(self.items)

    def close(self):
        self._sub.undeclare()


def _node(session, params, **config) -> BridgeNode:
    driver = TwinDriver(TwinDriverConfig(seed=0, camera=False), params)
    return bridge_node(session, driver, params, BridgeConfig(**config))


def _command(seq, force, answers, source="law2", sender="test"):
    """A command of controller ``sender`` answering ``answers``: a node's newest state (one is
    published first if it has none yet), a ``MotorState``, or a bridge epoch (a run's stamp made
    up: for commands refused by their epoch). The bridge obeys only its owner, a controller with
    a live token (:func:`_as_controller`), and only answers to its newest states."""
    if isinstance(answers, BridgeNode):
        if math.isnan(answers.last_state_stamp_s):
            answers.publish_state()
        epoch, stamp = answers.epoch, answers.last_state_stamp_s
    elif isinstance(answers, bus.MotorState):
        epoch, stamp = answers.epoch, answers.stamp_s
    else:
        epoch, stamp = answers, time.time()
    return bus.ForceCommand(seq=seq, stamp_s=stamp, force_N=[float(f) for f in force], source=source,
                            sender=sender, epoch=epoch)


def _as_controller(session, name="test"):
    """Make ``session`` a controller on the bus: its liveliness token, as ``xneck controller`` has."""
    return liveliness_token(session, "controller", name)


def _epoch(states) -> str:
    """The bridge epoch of the latest state a Collector saw."""
    assert wait_until(lambda: len(states.messages()) > 0, 30.0)
    return states.messages()[-1].epoch


def _stop_process(proc: subprocess.Popen, sig=signal.SIGTERM, timeout=10.0) -> int:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
            raise
    return proc.returncode


def _spawn(args, log_path):
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([*XNECK, *args], stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    return proc


def _settled(collector: Collector, quiet_s: float = 0.3, timeout_s: float = 5.0) -> None:
    """Wait until ``collector`` has received nothing for ``quiet_s`` (at most ``timeout_s``): what a
    process sent before it exited lands first (a fixed 0.2 s was short on a loaded machine)."""
    seen = [len(collector.messages()), time.monotonic()]

    def quiet() -> bool:
        n = len(collector.messages())
        if n != seen[0]:
            seen[:] = [n, time.monotonic()]
        return time.monotonic() - seen[1] >= quiet_s

    wait_until(quiet, timeout_s, 0.02)


def _latest_seq(node: BridgeNode) -> int | None:
    """The seq of the newest command ``node`` accepted (None before any)."""
    latest = node.commands.latest()
    return None if latest is None else latest.seq


def _put_until(pub, msg, predicate, timeout_s=5.0) -> bool:
    """Publish ``msg`` every 20 ms until ``predicate()``: the first messages on a fresh route may be lost."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pub.put(msg)
        if wait_until(predicate, 0.02, 0.002):
            return True
    return False


# -- within one tick (the node driven by hand) ------------------------------------------------------


def test_valid_commands_are_clamped_and_bad_ones_never_move_a_motor(params):
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params, command_timeout_s=5.0)  # no watchdog between manual ticks
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        try:
            node.tick()
            assert node.mode == "inactive" and node.driver.state is Lifecycle.INACTIVE
            assert node.force.tolist() == [0.0] * 4
            assert _put_until(pub, _command(1, [0.5, 50.0, 100.0, 0.0], node), lambda: node.commands.stats.accepted >= 1)
            node.tick()
            assert node.mode == "active" and node.driver.state is Lifecycle.ACTIVE
            assert node.force.tolist() == [1.0, 1.0, 1.0, 1.0]  # bumpless: 1 N per tick from zero
            for _ in range(99):
                node.tick()
            assert node.force.tolist() == [2.0, 50.0, 100.0, 2.0]  # raised to f_min = 2 N
            assert node.clamped == 1
            for bad in (_command(2, [10.0, 10.0, 100.5, 10.0], node), _command(3, [10.0, -0.1, 10.0, 10.0], node),
                        _command(4, [10.0, 10.0, 10.0], node)):
                pub.put(bad)
            pub._pub.put(b'{"v":2,"seq":5,"stamp_s":0,"force_N":[NaN,1,1,1],"source":"x","sender":"test","epoch":"%s"}'
                         % node.epoch.encode())
            pub._pub.put(b"\x00garbage")
            assert wait_until(lambda: node.commands.stats.rejected == 5, 5.0)
            node.tick()
            assert node.force.tolist() == [2.0, 50.0, 100.0, 2.0]  # still the last valid command
        finally:
            node.shutdown()
        assert node.driver.state is Lifecycle.CLOSED


def test_estop_disables_the_drives_within_one_tick_until_released(params):
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params, command_timeout_s=5.0)
        cmd_pub = publisher(hub_session, bus.MOTOR_COMMAND)
        estop_pub = publisher(hub_session, bus.ESTOP)
        states = Collector(hub_session, bus.MOTOR_STATE)
        try:
            assert _put_until(cmd_pub, _command(1, [20.0] * 4, node), lambda: node.commands.stats.accepted >= 1)
            node.tick()
            assert node.mode == "active"
            assert _put_until(estop_pub, bus.EStop(seq=0, stamp_s=time.time(), engaged=False, reason="route check"),
                              lambda: node.estop_received >= 1)
            node.tick()  # a release while not engaged changes nothing
            assert node.mode == "active"
            estop_pub.put(bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="console button"))
            assert wait_until(lambda: len(node._estop_events) == 1, 5.0)
            node.tick()  # one tick
            assert node.driver.state is Lifecycle.INACTIVE
            assert node.mode == "disabled" and node.force.tolist() == [0.0] * 4
            assert wait_until(lambda: any(s.drive == "disabled" for s in states.messages()), 5.0)
            engaged = next(s for s in states.messages() if s.drive == "disabled")
            assert engaged.estop_engaged and engaged.estop_reason == "console button"
            # Commands are ignored while engaged.
            n = node.commands.stats.accepted
            cmd_pub.put(_command(2, [30.0] * 4, node))
            assert wait_until(lambda: node.commands.stats.accepted == n + 1, 5.0)
            node.tick()
            assert node.mode == "disabled" and node.driver.state is Lifecycle.INACTIVE
            # Released: inactive, and a command sent before the release does not re-enable.
            estop_pub.put(bus.EStop(seq=2, stamp_s=time.time(), engaged=False, reason="cleared"))
            assert wait_until(lambda: len(node._estop_events) == 1, 5.0)
            node.tick()
            assert node.mode == "inactive" and node.driver.state is Lifecycle.INACTIVE
            cmd_pub.put(_command(3, [25.0] * 4, node))
            assert wait_until(lambda: node.commands.stats.accepted == n + 2, 5.0)
            node.tick()
            assert node.mode == "active" and node.force.tolist() == [1.0] * 4  # bumpless from zero
            # An e-stop payload that cannot be decoded counts as engaged (fail safe).
            estop_pub._pub.put(b'{"v":7,"engaged":false}')
            assert wait_until(lambda: len(node._estop_events) == 1, 5.0)
            node.tick()
            assert node.mode == "disabled" and node.estop_rejected == 1
            # ... and says so in every state: one e-stop truth for the console and the controller.
            assert wait_until(lambda: states.messages()[-1].estop_engaged, 5.0)
            assert states.messages()[-1].estop_reason.startswith("malformed e-stop message: EStop: schema version 7")
            released = [s for s in states.messages() if s.drive == "active"]
            assert released and not any(s.estop_engaged or s.estop_reason for s in released)
        finally:
            node.shutdown()
            states.close()


def test_estop_release_ramps_the_forces_instead_of_stepping_to_the_first_command(params):
    """Issue 13, finding 1: after a release the first commands were [81, 22, 8, 28] N and
    [100, 48, 8, 54] N from about 9 N; the applied forces must move at most 1 N per tick."""
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params, command_timeout_s=5.0, max_force_step_N=1.0)
        cmd_pub = publisher(hub_session, bus.MOTOR_COMMAND)
        estop_pub = publisher(hub_session, bus.ESTOP)
        states = Collector(hub_session, bus.MOTOR_STATE)
        applied = []

        def tick():
            node.tick()
            applied.append(node.force.copy())
            # at the loop's 500 Hz: back-to-back ticks put a burst of states the bus may drop (states
            # are sent best effort), and every state is counted below (a fresh-clone CI run was short
            # of them once; not reproduced alone or beside two busy loops)
            time.sleep(DT)

        try:
            assert _put_until(cmd_pub, _command(1, [9.0] * 4, node), lambda: node.commands.stats.accepted >= 1)
            for _ in range(20):
                tick()
            assert node.force.tolist() == [9.0] * 4
            assert _put_until(estop_pub, bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="button"),
                              lambda: node.estop_received >= 1)
            tick()
            assert node.mode == "disabled"  # the e-stop itself cuts the forces at once
            engaged = len(applied) - 1
            estop_pub.put(bus.EStop(seq=2, stamp_s=time.time(), engaged=False, reason="cleared"))
            assert wait_until(lambda: node.estop_received >= 2, 5.0)
            tick()
            assert node.mode == "inactive"
            for k, force in enumerate([[81.0, 22.0, 8.0, 28.0]] + [[100.0, 48.0, 8.0, 54.0]] * 3):
                n = node.commands.stats.accepted
                cmd_pub.put(_command(2 + k, force, node))
                assert wait_until(lambda: node.commands.stats.accepted > n, 5.0)
                tick()
            for _ in range(120):
                tick()
            # States go best effort: on a loaded machine a few are dropped (the suite beside a busy
            # loop, session 52; a fresh-clone CI run before). Every one is waited for a while, and
            # the published steps are compared between consecutive seq numbers only.
            wait_until(lambda: len(states.messages()) >= len(applied), 5.0)
            seen = states.messages()  # before the shutdown's final state
        finally:
            node.shutdown()
            states.close()
        steps = np.abs(np.diff(np.array(applied[engaged:]), axis=0)).max(axis=1)
        print(f"\nlargest force step per tick: {steps.max():.2f} N")
        assert steps.max() <= 1.0 + 1e-9, steps.round(1).tolist()
        assert applied[-1].tolist() == [100.0, 48.0, 8.0, 54.0]
        after = seen[next(i for i, s in enumerate(seen) if s.drive == "disabled"):]
        published = [np.abs(np.subtract(b.force_applied_N, a.force_applied_N)).max()
                     for a, b in itertools.pairwise(after) if b.seq == a.seq + 1]
        assert len(published) > 100 and max(published) <= 1.0 + 1e-9, (len(after), len(published))


def test_one_controller_owns_the_bridge_and_a_second_is_refused_until_the_owner_is_gone(params):
    """Issue 13, finding 5: two stacks could command one bridge. Now the first live sender owns it,
    another is refused and reported, and a new one takes over once the owner's session is gone."""
    with bus_pair() as (_hub, hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        ctl_a, ctl_b = connect(), connect()
        tokens = [_as_controller(ctl_a, "ctl-a"), _as_controller(ctl_b, "ctl-b")]  # kept: a dropped token vanishes
        pub_a, pub_b = publisher(ctl_a, bus.MOTOR_COMMAND), publisher(ctl_b, bus.MOTOR_COMMAND)
        states = Collector(hub_session, bus.MOTOR_STATE)
        health = Collector(hub_session, bus.health_key("bridge", node.instance), bus.Health)
        try:
            assert _put_until(pub_a, _command(1, [20.0] * 4, node, sender="ctl-a"), lambda: node.owner == "ctl-a")
            node.tick()
            assert node.mode == "active"
            n = node.commands.stats.rejected
            assert _put_until(pub_b, _command(1, [60.0] * 4, node, sender="ctl-b"),
                              lambda: node.commands.stats.rejected > n
                              and node.commands.stats.last_reject_reason.endswith("bridge owned by ctl-a"))
            assert node.commands.stats.last_reject_reason.endswith("bridge owned by ctl-a")
            assert node.commands.latest().sender == "ctl-a"  # a refused command never replaces the owner's
            # A command computed for another bridge run is refused too, even from the owner.
            n = node.commands.stats.rejected
            assert _put_until(pub_a, _command(2, [20.0] * 4, "an-old-epoch", sender="ctl-a"),
                              lambda: node.commands.stats.rejected > n
                              and "epoch 'an-old-epoch'" in node.commands.stats.last_reject_reason)
            assert "epoch 'an-old-epoch'" in node.commands.stats.last_reject_reason
            node.tick()
            node.publish_health()
            assert wait_until(lambda: health.messages() and states.messages(), 5.0)
            assert health.messages()[-1].rejected[bus.MOTOR_COMMAND] >= 2
            state = states.messages()[-1]
            assert (state.owner, state.epoch, state.bridge) == ("ctl-a", node.epoch, node.instance)
            ctl_a.close()  # the owner's session ends: its liveliness token vanishes
            assert wait_until(lambda: node.owner == "", 5.0)
            assert _put_until(pub_b, _command(2, [30.0] * 4, node, sender="ctl-b"), lambda: node.owner == "ctl-b")
            node.tick()
            assert wait_until(lambda: states.messages()[-1].owner == "ctl-b", 5.0)
        finally:
            node.shutdown()
            states.close()
            health.close()
            del tokens



def _send_and_tick(node, pub, seq, force, sender):
    """Publish one command of ``sender`` until the node has taken it, then tick once."""
    n = node.commands.stats.accepted
    assert _put_until(pub, _command(seq, force, node, sender=sender), lambda: node.commands.stats.accepted > n,
                      timeout_s=5.0), node.commands.stats.last_reject_reason
    node.tick()


def test_a_new_owner_within_the_watchdogs_timeout_is_ramped_to_not_stepped(params):
    """Audit of 2026-11-26: the owner's session ended and a second controller's command arrived
    within the 10 ms watchdog: the bridge applied it on the next tick, a 60 N step. A new owner's
    first command is an enable like any other: at most ``max_force_step_N`` per tick."""
    with bus_pair() as (_hub, _hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)  # the handover, not the watchdog, is tested
        ctl_a, ctl_b = connect(), connect()
        tokens = [_as_controller(ctl_a, "ctl-a"), _as_controller(ctl_b, "ctl-b")]
        pub_a, pub_b = publisher(ctl_a, bus.MOTOR_COMMAND), publisher(ctl_b, bus.MOTOR_COMMAND)
        applied = []
        try:
            for k in range(80):
                _send_and_tick(node, pub_a, k + 1, [30.0] * 4, "ctl-a")
            applied.append(node.force.copy())
            assert applied[-1].tolist() == [30.0] * 4
            ctl_a.close()
            assert wait_until(lambda: node.owner == "", 5.0)
            for k in range(80):
                _send_and_tick(node, pub_b, k + 1, [90.0, 2.0, 90.0, 2.0], "ctl-b")
                applied.append(node.force.copy())
        finally:
            node.shutdown()
            del tokens
        steps = np.abs(np.diff(np.array(applied), axis=0)).max(axis=1)
        print(f"\nlargest force step per tick across the handover: {steps.max():.2f} N")
        assert steps.max() <= 1.0 + 1e-9
        assert applied[-1].tolist() == [90.0, 2.0, 90.0, 2.0]


@contextlib.contextmanager
def _node_at_30_N(params):
    """A node commanded by one controller ("test") at 30 N on every cable, past its start-up ramp
    (command timeout 5 s: the tests tick by hand); yields (node, its command publisher)."""
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params, command_timeout_s=5.0)
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        try:
            for k in range(40):
                _send_and_tick(node, pub, k + 1, [30.0] * 4, "test")
            assert node.force.tolist() == [30.0] * 4
            yield node, pub
        finally:
            node.shutdown()


def test_active_commands_that_jump_move_the_forces_at_the_bounded_rate(params):
    """Fault table of docs/safety.md: while active, the bridge passed any command through, so a
    controller slowed by a flood stepped the cables 12.9 N in one tick. On the bus: a jump from 30 N
    to f_max moves the applied forces at most ``max_force_rate_N_s`` × dt per tick (10 N at 500 Hz,
    the law's own bound), and the health message counts the bounded ticks."""
    assert BridgeConfig().max_force_rate_N_s * 0.002 == 10.0
    with _node_at_30_N(params) as (node, pub):
        assert node.safety.config.max_active_step_N == BridgeConfig().max_force_rate_N_s * node.dt
        health = Collector(node.session, bus.health_key("bridge", node.instance))
        applied = [node.force.copy()]
        jump = [params.limits.f_max, 2.0, 30.0, 45.0]
        try:
            for k in range(12):
                _send_and_tick(node, pub, 100 + k, jump, "test")
                applied.append(node.force.copy())
            node.publish_health()
            assert wait_until(lambda: len(health.messages()) > 0, 5.0)
            counted = health.messages()[-1].received["rate_limited"]
        finally:
            health.close()
        steps = np.abs(np.diff(np.array(applied), axis=0)).max(axis=1)
        print(f"\nlargest force step per tick after a jump to f_max: {steps.max():.2f} N")
        assert steps.max() <= 10.0 + 1e-9 and steps[0] == 10.0
        assert applied[-1].tolist() == jump
        assert counted == node.rate_limited == int(np.ceil((params.limits.f_max - 30.0) / 10.0)) - 1


def test_a_wall_clock_step_back_does_not_deafen_the_bridge(params, monkeypatch):
    """Audit of 2026-11-26: receive times were wall-clock times, so after the clock stepped back
    (an NTP step; the BeagleBone has no RTC battery) every new command looked older than the last
    one taken and was ignored, with no hold: 60 s back ignored every command. Receive times and
    the watchdog's age are on the monotonic clock."""
    real_ns = time.time_ns
    offset = [0]
    monkeypatch.setattr(time, "time_ns", lambda: real_ns() - offset[0])
    with _node_at_30_N(params) as (node, pub):
        offset[0] = 60 * 10**9  # the wall clock steps back by 60 s
        for k in range(40):
            _send_and_tick(node, pub, 100 + k, [60.0] * 4, "test")
        assert node.mode == "active"
        assert node.force.tolist() == [60.0] * 4  # obeyed (30 ticks of the 1 N ramp, then reached)


def test_an_oversized_command_is_refused_unread_and_an_oversized_estop_engages(params):
    """Audit of 2026-11-26: a 20 MB ForceCommand was copied and parsed in the bridge's callback
    (the loop stalled 134 ms, an e-stop took 175 ms). Payloads beyond the contract's bound for
    their type are refused by their size; an e-stop that cannot be read counts as engaged."""
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params, command_timeout_s=5.0)
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        try:
            _send_and_tick(node, pub, 1, [20.0] * 4, "test")
            huge = bus.encode(_command(2, [60.0] * 4, node)).replace(b'"source":"law2"',
                                                                           b'"source":"' + b"x" * 2_000_000 + b'"')
            n = node.commands.stats.rejected
            # BLOCK: a put's default (DROP) may drop a 2 MB message's fragments on a loaded machine,
            # and nothing came to refuse (a fresh-clone CI of f93b801, 2026-12-02)
            hub_session.put(bus.MOTOR_COMMAND, huge, congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_until(lambda: node.commands.stats.rejected > n, 5.0)
            assert "ForceCommand: payload of 2000" in node.commands.stats.last_reject_reason
            assert node.commands.latest().force_N == [20.0] * 4
            release = bus.encode(bus.EStop(seq=1, stamp_s=time.time(), engaged=False, reason="x" * 100_000))
            hub_session.put(bus.ESTOP, release, congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_until(lambda: node.estop_received >= 1, 5.0)
            node.tick()
            assert node.mode == "disabled" and node.estop_rejected == 1
            assert "payload of" in node.estop_reason
        finally:
            node.shutdown()


def test_a_bridge_woken_from_a_stall_ramps_to_the_command_computed_meanwhile(params, monkeypatch):
    """Audit of 2026-11-26: the bridge SIGSTOPped 0.3-25 s mid-campaign stayed 'active', so on
    waking it applied the controller's newest command (a hold computed meanwhile) and the law's
    return after it: 13-24 N in one tick. The realtime loop tells each tick how late it starts;
    past the command timeout the command is ramped."""
    with _node_at_30_N(params) as (node, pub):
        applied = [node.force.copy()]
        n = node.commands.stats.accepted
        assert _put_until(pub, _command(100, [54.0, 30.0, 30.0, 6.0], node), lambda: node.commands.stats.accepted > n)
        node.tick(held_up_s=6.0)  # past this node's command timeout (5 s here, 10 ms by default)
        applied.append(node.force.copy())
        for _ in range(30):
            node.tick()
            applied.append(node.force.copy())
        assert np.abs(np.diff(np.array(applied), axis=0)).max() <= 1.0 + 1e-9
        assert applied[-1].tolist() == [54.0, 30.0, 30.0, 6.0]

    # run_realtime measures the lateness: a sleep that overslept 50 ms shows in the next tick
    seen: list[float] = []

    class Recorder:
        config, dt = BridgeConfig(max_ticks=20), 0.002
        driver = type("D", (), {"exhausted": False})()
        overruns = periods_skipped = 0

        def tick(self, held_up_s=0.0):
            seen.append(held_up_s)

        def publish_health(self):
            pass

    real_sleep = time.sleep
    overslept = []

    def sleep(s):
        real_sleep(s + (0.05 if not overslept else 0.0))
        overslept.append(True)

    monkeypatch.setattr("bridge.node.time.sleep", sleep)
    run_realtime(Recorder(), threading.Event())  # type: ignore[arg-type]
    assert max(seen) >= 0.045 and sorted(seen)[-2] < 0.01, seen


def test_a_late_answer_to_a_state_from_before_a_stall_does_not_end_its_ramp(params):
    """Review of session 53: the ramp after a stall of the bridge's loop ended on the first command
    that arrived after it, so the controller's late answer to a state from before the stall (equal
    to the applied forces, as a controller stalled too sends) ended it, and the answer to the new
    states then moved 10 N per tick. It ends only on a command answering a state published after
    the stall."""
    with _node_at_30_N(params) as (node, pub):
        before = node.last_state_stamp_s  # answered by the last command, published before the stall
        applied = [node.force.copy()]
        node.tick(held_up_s=6.0)  # past this node's command timeout (5 s here)
        applied.append(node.force.copy())
        n = node.commands.stats.accepted
        late = bus.ForceCommand(seq=100, stamp_s=before, force_N=[30.0] * 4, source="law2", sender="test",
                                epoch=node.epoch)
        assert _put_until(pub, late, lambda: node.commands.stats.accepted > n), node.commands.stats.last_reject_reason
        node.tick()
        applied.append(node.force.copy())
        _send_and_tick(node, pub, 101, [54.0, 30.0, 30.0, 6.0], "test")  # answers a state after the stall
        applied.append(node.force.copy())
        for _ in range(30):
            node.tick()
            applied.append(node.force.copy())
    assert np.abs(np.diff(np.array(applied), axis=0)).max() <= 1.0 + 1e-9, np.diff(np.array(applied), axis=0)
    assert applied[-1].tolist() == [54.0, 30.0, 30.0, 6.0]


def test_a_command_answering_an_older_state_than_the_last_accepted_one_is_refused(params):
    """Review of session 53: any command answering one of the last states was taken, the last to
    arrive winning, so a command delayed, re-ordered or replayed moved the cables back to older
    forces (and reset the watchdog). A command of the same controller answering an older state
    than its last accepted one is refused; the same state answered again is still taken (the
    controller's own hold when no state reaches it)."""
    with _node_at_30_N(params) as (node, pub):
        old = node.last_state_stamp_s
        for k in range(3):
            _send_and_tick(node, pub, 50 + k, [40.0] * 4, "test")
        newest = node.last_state_stamp_s
        _send_and_tick(node, pub, 60, [41.0] * 4, "test")  # answers ``newest``
        rejected = node.commands.stats.rejected
        replay = bus.ForceCommand(seq=61, stamp_s=old, force_N=[25.0] * 4, source="law2", sender="test",
                                  epoch=node.epoch)
        assert _put_until(pub, replay, lambda: node.commands.stats.rejected > rejected)
        assert "older state than its last accepted command" in node.commands.stats.last_reject_reason
        node.tick()
        assert node.force.tolist() == [41.0] * 4 and node.mode == "active"
        again = bus.ForceCommand(seq=62, stamp_s=newest, force_N=[42.0] * 4, source="law2", sender="test",
                                 epoch=node.epoch)
        n = node.commands.stats.accepted
        assert _put_until(pub, again, lambda: node.commands.stats.accepted > n)  # the same state again: taken
        node.tick()
        assert node.force.tolist() == [42.0] * 4


class _WallClockStepDriver(TwinDriver):
    """The twin, stamped as hardware is (a wall clock) that ``step_s`` moves at once, with a reading
    ``glitch_rad`` off at the same tick; its steady clock is the simulated time."""

    step_s = glitch_rad = 0.0

    def stamp_s(self) -> float:
        return super().stamp_s() + self.step_s

    def steady_s(self) -> float:
        return super().stamp_s()

    def _on_read(self) -> np.ndarray:
        return super()._on_read() + self.glitch_rad


def test_an_encoder_glitch_at_a_wall_clock_step_is_still_caught(params):
    """Review of session 53: the motors' speeds were differentiated on the driver's stamps, a wall
    clock on the board (NTP steps it; no RTC battery), so a backward step restarted the speed filter
    without the glitch check, and an encoder glitch in that tick was taken for angles (bad_readings
    0, trusted). The speeds use the driver's steady clock."""
    with bus_pair() as (_hub, _hub_session, connect):
        driver = _WallClockStepDriver(TwinDriverConfig(seed=0, camera=False), params)
        node = bridge_node(connect(), driver, params, BridgeConfig(command_timeout_s=5.0))
        try:
            for _ in range(20):
                node.tick()
            assert node.speed.bad_readings == 0 and node.speed.trusted
            driver.step_s, driver.glitch_rad = -1.0, 1e4
            node.tick()
            assert node.speed.bad_readings == 1 and not node.speed.trusted
        finally:
            node.shutdown()


def test_the_pace_of_the_real_time_loop_counts_the_periods_a_stall_skipped():
    """A tick that ends after the next one was due is one overrun; the whole periods it lost are
    skipped and counted (they had shown as that one overrun: a 600 ms stall at 500 Hz was 1 of
    ~300 periods without a tick). A tick that starts on time (t = 0) and stalls 600 ms: 299
    periods skipped, and the next tick starts on the slot at 600 ms."""
    dt = 0.002
    assert pace(0.0019, dt, dt) is None and pace(dt, dt, dt) is None  # in time: the loop sleeps
    assert pace(0.0035, dt, dt) == 0  # late, within a period: an overrun, nothing skipped
    assert pace(0.0041, dt, dt) == 1
    assert pace(0.6, dt, dt) == 299 and pace(0.6003, dt, dt) == 299 and pace(0.6021, dt, dt) == 300


def test_a_stalled_tick_shows_in_health_as_one_overrun_and_the_periods_it_skipped(params, monkeypatch):
    """The loop on an injected clock (no wall time): ten ticks of 0.3 ms each, the fourth stalls
    600 ms. Health carries 1 overrun and 299 periods skipped; the tick after the stall starts on
    its slot (not late by the stall) and the loop does not catch up, but it is told how long
    commands went unread."""

    class Clock:  # the loop's perf_counter and sleep; everything else is the real time module
        now = 0.0

        def perf_counter(self):
            return self.now

        def sleep(self, s):
            self.now += max(s, 0.0)

        def __getattr__(self, name):
            return getattr(time, name)

    clock = Clock()
    monkeypatch.setattr("bridge.node.time", clock)
    with bus_pair() as (_hub, _hub_session, connect):
        node = _node(connect(), params, max_ticks=10)
        health = Collector(node.session, bus.health_key("bridge", node.instance))
        real_tick, late = node.tick, []

        def tick(held_up_s=0.0):
            late.append(held_up_s)
            real_tick(held_up_s)
            clock.now += 0.0003 + (0.6 if len(late) == 4 else 0.0)

        monkeypatch.setattr(node, "tick", tick)
        try:
            assert run_realtime(node, threading.Event()) == 10
            node.publish_health()
            assert wait_until(lambda: any(m.received.get("periods_skipped") for m in health.messages()), 5.0)
            received = health.messages()[-1].received
        finally:
            health.close()
            node.shutdown()
    assert (node.overruns, node.periods_skipped) == (1, 299)
    assert (received["overruns"], received["periods_skipped"]) == (1, 299)
    # The tick after the stall starts on its slot, but commands went unread for the stall: it says
    # so, for the safety rules' ramp (review of session 53: it had said 0.3 ms, and no ramp came).
    assert late[4] == pytest.approx(0.6 + 0.0003 - DT, abs=1e-9), late
    assert max(late[:4] + late[5:]) < 0.001, late
    assert node.dt == DT and clock.now == pytest.approx((10 + 299) * DT)  # ticks + skipped = periods elapsed

# -- the hold forces off the tick (issue 20) ------------------------------------------------------


def _recording_hold(params, fail=False):
    """The bridge's hold rule, recording the calls made from inside a tick of the loop thread."""
    real = encoder_hold_forces(params)
    loop_thread = threading.get_ident()
    record = {"ticking": False, "in_tick": 0, "elsewhere": []}

    def hold(theta):
        if record["ticking"] and threading.get_ident() == loop_thread:
            record["in_tick"] += 1
        else:
            record["elsewhere"].append(threading.get_ident())
        if fail:
            raise RuntimeError("no model here")
        return real(theta)

    def tick(node):
        record["ticking"] = True
        try:
            node.tick()
        finally:
            record["ticking"] = False

    return hold, record, tick


def _held_node(session, params, hold):
    driver = TwinDriver(TwinDriverConfig(seed=0, camera=False), params)
    # A fine tolerance: the worker recomputes whenever the twin's neck moves at all. The ramp
    # alone: the twin's neck moves, which the hold's damping would add to (tests/test_bridge_hold_damping.py).
    return BridgeNode(session, driver, hold, (params.limits.f_min, params.limits.f_max),
                      BridgeConfig(command_timeout_s=0.010, hold_tolerance_rad=0.01, hold_damping_N_s_rad=0.0))


def test_the_hold_worker_serves_only_fresh_forces_and_computes_only_when_the_angles_move():
    calls = []

    def hold(theta):
        calls.append(theta.tolist())
        return np.full(4, 10.0) + theta

    worker = HoldWorker(hold, 4, tolerance_rad=0.2, refresh_s=0.0, max_age_s=0.1, poll_s=0.002)
    assert worker.ready(time.monotonic()) is None  # nothing before the first computation
    assert worker.compute([0.0] * 4)
    now = time.monotonic()
    assert worker.ready(now) == [10.0] * 4
    assert worker.ready(now + 0.2) is None  # stale: older than max_age_s
    worker.offer([0.1] * 4)  # within the tolerance: the same forces, their time renewed
    worker.start()
    try:
        tid = worker._thread.native_id if worker._thread is not None else None
        assert tid is not None and wait_until(lambda: os.sched_getscheduler(tid) == os.SCHED_OTHER, 2.0)
        # Not niceness 19: a starved thread holding the GIL had stalled the loop (priority inversion).
        assert os.getpriority(os.PRIO_PROCESS, tid) == os.getpriority(os.PRIO_PROCESS, 0)
        time.sleep(0.2)  # time to compute again, were it to (it must not: same angles)
        # renewed (not stale) once the worker has run; a starved worker may be late doing so
        assert wait_until(lambda: worker.ready(time.monotonic()) == [10.0] * 4, 5.0) and len(calls) == 1
        worker.offer([1.0] * 4)  # moved: computed again, on the worker's thread
        assert wait_until(lambda: worker.ready(time.monotonic()) == [11.0] * 4, 5.0)
        assert len(calls) == 2
    finally:
        worker.stop()


def test_a_failing_hold_rule_leaves_no_hold_forces():
    def broken(_theta):
        raise RuntimeError("no model here")

    worker = HoldWorker(broken, 4)
    assert not worker.compute([0.0] * 4)
    assert worker.ready(time.monotonic()) is None and worker.failed == 1
    nonsense = HoldWorker(lambda theta: np.array([1.0, np.nan, 1.0, 1.0]), 4)
    assert not nonsense.compute([0.0] * 4) and nonsense.ready(time.monotonic()) is None


def test_the_tick_that_starts_a_hold_uses_hold_forces_computed_off_the_tick(params):
    hold, record, tick = _recording_hold(params)
    real = encoder_hold_forces(params)
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _held_node(connect(), params, hold)
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        f_cmd = hold_forces(params, np.zeros(3)) + 5.0
        try:
            assert _put_until(pub, _command(1, f_cmd, node), lambda: node.commands.stats.accepted >= 1)
            for seq in range(2, 62):  # past the bumpless ramp from zero; the twin's neck moves meanwhile
                tick(node)
                # Each command delivered before the next tick: on a loaded machine, commands put in
                # a burst had arrived 25 states late, rightly refused, and the watchdog held early.
                # Put once and waited for by its seq: a late copy would answer the hold's states.
                pub.put(_command(seq, f_cmd, node))
                assert wait_until(lambda seq=seq: _latest_seq(node) == seq, 5.0)
            assert node.mode == "active" and node.force.tolist() == pytest.approx(f_cmd.tolist())
            tick(node)  # takes the last command
            for _ in range(4):  # states unanswered: a hold needs five (the controller's silence)
                tick(node)
            assert node.mode == "active"
            # the worker catches up with these angles (a fixed sleep: a starved worker's were stale)
            assert wait_until(lambda: node.hold.ready(time.monotonic(), node.theta.tolist()) is not None, 5.0)
            before, theta = node.force.copy(), node.theta.copy()
            tick(node)
            assert node.mode == "hold"
            assert record["in_tick"] == 0, "the tick that started the hold computed the hold forces"
            assert any(t != threading.get_ident() for t in record["elsewhere"]), "no worker thread computed them"
            first = node.force.copy()
            for _ in range(4):
                tick(node)
            target = node.force.copy()
            # The ramp starts at once (a fifth of the way in the first tick) towards hold forces of
            # angles within the worker's tolerance of these.
            np.testing.assert_allclose(first, before + (target - before) / 5, atol=1e-9)
            exact = np.clip(real(theta), params.limits.f_min, params.limits.f_max)
            np.testing.assert_allclose(target, exact, atol=0.05)
            assert record["in_tick"] == 0
        finally:
            node.shutdown()


def test_a_stall_of_the_loops_cpu_starts_no_hold_a_silent_controller_does(params):
    """The watchdog guards against a controller that stops answering, not against a CPU that the
    bridge and the controller share being taken from both: after a 50 ms stall right after a
    state went out (the controller had no time to answer it), the bridge keeps the drives active
    and the late answer is obeyed; a controller that stays silent trips the hold once five states
    are unanswered (the idle soak: 1-2 holds in 10 min, each a force ramp for nothing)."""
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params)  # the default watchdog: 10 ms
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        f_cmd = hold_forces(params, np.zeros(3)) + 5.0
        k = 0

        def answer() -> None:  # the controller's reply to the state just published
            nonlocal k
            k += 1
            seen = node.commands.stats.accepted
            pub.put(_command(k, f_cmd, node))
            assert wait_until(lambda: node.commands.stats.accepted > seen, 2.0)

        try:
            assert _put_until(pub, _command(k, f_cmd, node), lambda: node.commands.stats.accepted >= 1)
            for _ in range(40):  # past the bumpless ramp from zero, every state answered
                node.tick()
                answer()
            node.tick()  # a state goes out; then the CPU is gone before the controller answers it
            assert node.mode == "active"
            time.sleep(0.050)
            node.tick()  # the bridge runs first after the stall
            assert node.mode == "active" and node.holds == 0, node.hold_reason
            answer()  # the controller's late answer
            node.tick()
            assert node.mode == "active" and node.holds == 0
            ticks = 0
            while node.mode == "active" and ticks < 10:  # now the controller is silent
                time.sleep(DT)
                node.tick()
                ticks += 1
            assert node.mode == "hold" and node.holds == 1 and ticks == 5, (ticks, node.hold_reason)
            assert "5 states unanswered" in node.hold_reason
        finally:
            node.shutdown()


def test_without_hold_forces_ready_the_hold_keeps_the_present_forces(params):
    hold, record, tick = _recording_hold(params, fail=True)
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _held_node(connect(), params, hold)
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        f_cmd = [20.0, 15.0, 10.0, 12.0]
        try:
            assert _put_until(pub, _command(1, f_cmd, node), lambda: node.commands.stats.accepted >= 1)
            for seq in range(2, 42):
                tick(node)
                pub.put(_command(seq, f_cmd, node))  # delivered before the next tick, as above
                assert wait_until(lambda seq=seq: _latest_seq(node) == seq, 5.0)
            time.sleep(0.05)
            for _ in range(10):
                tick(node)
            assert node.mode == "hold" and node.force.tolist() == f_cmd
            assert record["in_tick"] == 0
        finally:
            node.shutdown()


def test_every_bridge_run_has_its_own_epoch(params):
    with bus_pair() as (_hub, _hub_session, connect):
        first, second = _node(connect(), params), _node(connect(), params)
        first.shutdown()
        second.shutdown()
    assert first.epoch and second.epoch and first.epoch != second.epoch


def test_the_twins_truth_names_in_its_attachment_the_bridge_run_its_states_carry(params):
    """A Truth has no identity field: the bridge names its run (``MotorState.epoch``) in the Zenoh
    attachment of what its driver publishes, so a console tells two twins' truths apart."""
    from bridge.session import run_of

    with bus_pair() as (_hub, hub_session, connect):
        node = _node(connect(), params)
        runs: list[str] = []
        sub = hub_session.declare_subscriber(bus.TWIN_TRUTH, lambda s: runs.append(run_of(s)))
        try:
            assert wait_until(lambda: (node.tick(), len(runs) >= 3)[1], 10.0, 0.002)
        finally:
            sub.undeclare()
            node.shutdown()
    assert set(runs) == {node.epoch}, runs


def test_an_estop_reason_from_the_bus_is_bounded_before_it_goes_into_every_state(params):
    # 5 kB: within the e-stop's payload bound (a larger payload is refused unread and engages,
    # test_an_oversized_command_is_refused_unread_and_an_oversized_estop_engages)
    with bus_pair() as (_hub, hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        estop_pub = publisher(hub_session, bus.ESTOP)
        states = Collector(hub_session, bus.MOTOR_STATE)
        try:
            assert _put_until(estop_pub, bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="x" * 5_000),
                              lambda: node.estop_received >= 1)
            node.tick()
            assert wait_until(lambda: states.messages() and states.messages()[-1].estop_engaged, 5.0)
        finally:
            node.shutdown()
            states.close()
        reason = states.messages()[-1].estop_reason if states.messages()[-1].estop_engaged else node.estop_reason
        assert reason.startswith("xxx") and len(reason) <= 200, len(reason)


# -- real time -----------------------------------------------------------------------------------


def _hold_check(timed_states, timed_commands):
    """The hold after the last command: (wall time from the last command to the first hold state,
    both as received here; the age of the bridge's last valid command when it tripped, from its
    hold_reason; how late the tripping tick came (the wall gap between the last active state
    and the first hold state as received here, beyond one period: a loaded machine delays a tick,
    and the watchdog can only trip at a tick); simulated time of the ramp to the hold forces; the
    hold forces at the end)."""
    t_cmd = timed_commands[-1][0]
    after = [(t, s) for t, s in timed_states if t > t_cmd and s.drive != "disabled"]
    # The final hold follows the last active state (a sender that stalls for over 10 ms can trip
    # an earlier hold whose states are still in flight when the last command is sent).
    first_hold = max(i for i, (_t, s) in enumerate(after) if s.drive == "active") + 1
    t_hold, hold = after[first_hold][0], [s for _t, s in after[first_hold:]]
    assert all(s.drive == "hold" and "no valid command" in s.hold_reason for s in hold)
    target = np.array(hold[-1].force_applied_N)
    # The ramp ends where the forces start moving by at most the 1 N a tick of the hold's damping
    # (bridge/safety.py, "Hold damping": a neck still moving is damped after the ramp, until it rests).
    forces = np.array([s.force_applied_N for s in hold])
    fast = np.flatnonzero(np.abs(np.diff(forces, axis=0)).max(axis=1) > 1.0 + 1e-9)
    reached = hold[int(fast[-1]) + 1 if len(fast) else 0]
    before = np.array(after[first_hold - 1][1].force_applied_N) if first_hold else None
    if before is not None:  # a linear ramp: the first hold tick moved one step towards the target,
        # give or take the hold's damping on a neck still moving (up to max_force_step_N a tick, from
        # the first: fresh-clone CI of 2026-11-30 saw 0.4-0.7 N away with the controller killed mid-move)
        step = SafetyConfig(n_motors=4, f_min_N=0.0, f_max_N=1.0).max_force_step_N  # the default
        assert np.all(np.abs(np.array(hold[0].force_applied_N) - target) <= np.abs(before - target) + step + 1e-9)
    age_ms = int(re.search(r"no valid command for (\d+) ms", hold[0].hold_reason).group(1))
    late = max(0.0, t_hold - after[first_hold - 1][0] - DT) if first_hold else 0.0
    # The rule also waits for 5 states unanswered (10 ms of ticks): a hold that came with the 5th
    # came at the first tick it could, and the age beyond the timeout is the loop's own lateness
    # before it (fresh-clone CI of 2026-11-26: the loop held up 208 ms right after the kill, then
    # "no valid command for 216 ms (timeout 10 ms), 5 states unanswered"; tests/test_stack.py too).
    unanswered = re.search(r"(\d+) states unanswered", hold[0].hold_reason)
    if unanswered and int(unanswered.group(1)) == 5:
        late = max(late, age_ms * 1e-3 - 0.010 - DT)
    if late:
        print(f"the tick that tripped the hold came {late * 1e3:.1f} ms late (as received here)")
    return t_hold - t_cmd, age_ms * 1e-3, late, reached.stamp_s - hold[0].stamp_s + DT, target


def test_watchdog_ramps_to_the_hold_forces_when_commands_stop(params):
    switch = sys.getswitchinterval()
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params)
        states = Collector(hub_session, bus.MOTOR_STATE)
        commands = Collector(hub_session, bus.MOTOR_COMMAND)
        stop = threading.Event()
        th, out = run_in_thread(run_realtime, node, stop)
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        f_cmd = hold_forces(params, np.zeros(3)) + 5.0
        try:
            assert wait_until(lambda: len(states.messages()) > 5, 10.0)
            t_end = time.perf_counter() + 0.4
            k = 0
            while time.perf_counter() < t_end:
                k += 1
                pub.put(_command(k, f_cmd, node))
                time.sleep(DT)
            assert wait_until(lambda: sum(s.drive == "hold" for s in states.messages()) > 30, 5.0)
        finally:
            stop.set()
            th.join(5)
            node.shutdown()
            wait_until(lambda: states.messages()[-1].drive == "disabled", 2.0)
            states.close()
            commands.close()
        assert "error" not in out, out.get("error")
        assert sys.getswitchinterval() == switch  # the loop's 0.2 ms is restored when it ends
        msgs = states.messages()
        assert msgs[-1].drive == "disabled"  # shutdown published the final state
        to_hold, age, late, ramp, target = _hold_check(states.timed(), commands.timed())
        print(f"\nwatchdog: hold {to_hold * 1e3:.1f} ms (wall, seen here) and {age * 1e3:.0f} ms (bridge's receive "
              f"clock) after the last command, ramp {ramp * 1e3:.0f} ms (sim)")
        # The hold starts after the 10 ms timeout (plus at most a tick and the loop's jitter) and
        # the forces reach the hold forces within 10 ms of simulated time. Seen from here, a
        # dropped last command or a loaded machine may add a few ms.
        assert 0.010 <= age <= 0.010 + 2 * DT + late, (age, late)
        assert 0.010 <= to_hold <= 0.030 + late, (to_hold, late)  # (a held-up loop's lateness: _hold_check)
        assert ramp <= 0.010 + 1e-9, ramp
        theta = np.array(msgs[-1].theta_rad)
        assert np.all(target >= params.limits.f_min) and np.all(target <= params.limits.f_max)
        assert np.abs(theta).max() < 10  # sanity: nothing ran away


def test_estop_in_real_time_takes_effect_on_the_next_tick(params):
    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params, command_timeout_s=1.0)
        states = Collector(hub_session, bus.MOTOR_STATE)
        arrived_after: list[int] = []  # the seq of the newest state published when the e-stop arrived
        queue = node._queue_estop

        def _queue_estop(event):
            arrived_after.append(node._seq["state"])
            queue(event)

        node._queue_estop = _queue_estop
        stop = threading.Event()
        th, out = run_in_thread(run_realtime, node, stop)
        cmd_pub = publisher(hub_session, bus.MOTOR_COMMAND)
        estop_pub = publisher(hub_session, bus.ESTOP)
        try:
            first = _command(1, [20.0] * 4, node)
            # the first messages on a fresh route may be lost: repeat the command until the drive is active
            assert wait_until(lambda: (cmd_pub.put(first), any(s.drive == "active" for s in states.messages()))[1],
                              10.0, 0.02)
            time.sleep(0.1)
            sent = time.perf_counter()
            estop_pub.put(bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="test"))
            assert wait_until(lambda: any(s.drive == "disabled" for s in states.messages()), 5.0)
        finally:
            stop.set()
            th.join(5)
            node.shutdown()
            states.close()
        assert "error" not in out, out.get("error")
        timed = states.timed()
        first_disabled = next(t for t, s in timed if s.drive == "disabled")
        later_active = [s for t, s in timed if t > first_disabled and s.drive != "disabled"]
        assert not later_active
        # Counted in ticks, not in wall time (a loaded machine delays a tick, not its order): the
        # tick that follows the e-stop's arrival disables the drives; a tick already past its read
        # of the e-stop queue when it arrived publishes one more active state.
        disabled_seq = next(s.seq for s in states.messages() if s.drive == "disabled")
        assert arrived_after and disabled_seq <= arrived_after[0] + 2, (disabled_seq, arrived_after)
        print(f"\ne-stop: drives disabled {(first_disabled - sent) * 1e3:.1f} ms after it was sent (wall, seen here)")


# -- real processes ------------------------------------------------------------------------------


def test_sigterm_leaves_the_drives_disabled(tmp_path):
    with bus_pair() as (hub, hub_session, _connect):
        _token = _as_controller(hub_session)
        states = Collector(hub_session, bus.MOTOR_STATE)
        proc = _spawn(["bridge", "--driver", "twin", "--listen", "tcp/127.0.0.1:0", "--connect", hub,
                       "--instance", "sigterm-test"], tmp_path / "bridge.log")
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        try:
            assert wait_until(lambda: len(states.messages()) > 0, 30.0), (tmp_path / "bridge.log").read_text()
            _epoch(states)  # a state of the bridge, to answer
            k = 0
            while not any(s.drive == "active" for s in states.messages()[-5:]):
                k += 1
                pub.put(_command(k, [20.0] * 4, states.latest()))
                time.sleep(DT)
                assert k < 5000
            for _ in range(50):
                k += 1
                pub.put(_command(k, [20.0] * 4, states.latest()))
                time.sleep(DT)
            rc = _stop_process(proc)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        _settled(states)
        states.close()
        log = (tmp_path / "bridge.log").read_text()
        assert rc == 0, log
        last = states.messages()[-1]
        assert last.drive == "disabled" and last.force_applied_N == [0.0] * 4, log
        assert "drives disabled" in log


def test_killed_controller_leaves_the_twin_holding_within_its_joint_limits(params, tmp_path, caplog):
    alpha_max = math.radians(params.limits.alpha_max_deg)
    with bus_pair() as (hub, hub_session, connect):
        node = _node(connect(), params)
        states = Collector(hub_session, bus.MOTOR_STATE)
        commands = Collector(hub_session, bus.MOTOR_COMMAND)
        truths = Collector(hub_session, bus.TWIN_TRUTH)
        stop = threading.Event()
        th, out = run_in_thread(run_realtime, node, stop)
        ctl = _spawn(["controller", "--trajectory", "control_test", "--listen", "tcp/127.0.0.1:0",
                      "--connect", hub, "--idle-timeout", "20"], tmp_path / "controller.log")
        try:
            # Let the controller drive the neck away from straight (control_test rises to 50° per joint
            # after a 1 s dwell, which starts once the drives are on: a count of active states had
            # killed it on the cycloid's steep part, 5-11° up by 0.1 s of start-up; session 44).
            def raised() -> bool:
                return any(np.degrees(np.abs(t.alpha_rad)).max() > 10.0 for t in truths.messages()[-50:])

            assert wait_until(raised, 40.0), (tmp_path / "controller.log").read_text()
            ctl.kill()  # SIGKILL: no goodbye message, the commands just stop
            ctl.wait(5)
            n_before = len(states.messages())
            assert wait_until(lambda: len(states.messages()) > n_before + 250, 5.0)
        finally:
            if ctl.poll() is None:
                ctl.kill()
                ctl.wait(5)
            stop.set()
            th.join(5)
            node.shutdown()
            states.close()
            commands.close()
            truths.close()
        assert "error" not in out, out.get("error")
        to_hold, age, late, ramp, target = _hold_check(states.timed(), commands.timed())
        print(f"\ncontroller killed: hold {to_hold * 1e3:.1f} ms (wall, seen here) and {age * 1e3:.0f} ms (bridge's "
              f"clock) after its last command, ramp {ramp * 1e3:.0f} ms (sim); holds before the kill: {node.holds - 1}")
        assert 0.010 <= age <= 0.010 + 2 * DT + late, (age, late)
        assert to_hold <= 0.030 + late, (to_hold, late)
        ramp_max = 0.010
        if any("loop was held up" in r.getMessage() for r in caplog.records):
            # After a stall of its own loop the bridge ramps whatever it applies next at 1 N a tick
            # (bridge/safety.py, "Bumpless"): the hold too (fresh-clone CI of 2026-12-02: held up
            # 486 ms as the controller was killed, a 46 ms ramp).
            t_cmd = commands.timed()[-1][0]
            first = next(s for t, s in states.timed() if t > t_cmd and s.drive == "hold")
            step = SafetyConfig(n_motors=4, f_min_N=0.0, f_max_N=1.0).max_force_step_N
            ramp_max = max(ramp_max, (np.abs(np.array(first.force_applied_N) - target).max() / step + 2) * DT)
        assert ramp <= ramp_max + 1e-9, (ramp, ramp_max)
        alpha = np.array([t.alpha_rad for t in truths.messages()])
        moved = np.degrees(np.abs(alpha).max())
        print(f"max |α| {moved:.1f}° (limit {params.limits.alpha_max_deg:.0f}°)")
        assert moved > 5.0, f"the controller barely moved the neck ({moved:.1f}°)"
        assert np.abs(alpha).max() <= alpha_max, np.degrees(np.abs(alpha).max(axis=0))
        # Holding: the neck stays put in the 0.5 s after the ramp.
        held = alpha[-100:]
        assert np.ptp(held, axis=0).max() < math.radians(5.0), np.degrees(np.ptp(held, axis=0))


FLOOD = r"""
import sys, time
from bridge.session import open_session
from bridge import bus
hub, seconds = sys.argv[1], float(sys.argv[2])
who = b'"source":"f","sender":"f","epoch":"e"'
bad = [b"\x00garbage", b'{"v":2,"seq":1,"stamp_s":0,"force_N":[NaN,1,1,1],' + who + b'}',
       b'{"v":3,"seq":1,"stamp_s":0,"force_N":[1,1,1,1],' + who + b'}',
       b'{"v":2,"seq":1,"stamp_s":0,"force_N":[1,1,1],' + who + b'}',
       b'{"v":2,"seq":1,"stamp_s":0,"force_N":[500,1,1,1],' + who + b'}',
       b'{"v":2,"seq":1,"stamp_s":0,"force_N":[-1,1,1,1],' + who + b'}']
with open_session(listen=["tcp/127.0.0.1:0"], connect=[hub]) as s:
    pub = s.declare_publisher(bus.MOTOR_COMMAND)
    time.sleep(1.0)  # let the routes settle
    sent, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        due = int((time.perf_counter() - start) * 5000)  # 5 kHz: ten times the control rate
        while sent < due:
            pub.put(bad[sent % len(bad)])
            sent += 1
        time.sleep(0.0005)
    print(sent, flush=True)
"""


def test_flood_of_malformed_commands_is_counted_and_the_valid_controller_obeyed(tmp_path):
    with bus_pair() as (hub, hub_session, _connect):
        _token = _as_controller(hub_session, "valid-controller")
        states = Collector(hub_session, bus.MOTOR_STATE)
        health = Collector(hub_session, bus.health_key("bridge", "flood-test"), bus.Health)
        bridge = _spawn(["bridge", "--driver", "twin", "--listen", "tcp/127.0.0.1:0", "--connect", hub,
                         "--instance", "flood-test"], tmp_path / "bridge.log")
        flood = None
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        valid = [20.0, 25.0, 30.0, 1.0]  # the last one is clamped to f_min
        try:
            assert wait_until(lambda: len(states.messages()) > 0, 30.0), (tmp_path / "bridge.log").read_text()
            _epoch(states)  # a state of the bridge, to answer
            flood = subprocess.Popen([sys.executable, "-c", FLOOD, hub, "3.0"], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
            k = 0
            start = time.perf_counter()
            while flood.poll() is None and time.perf_counter() - start < 15:
                k += 1
                pub.put(_command(k, valid, states.latest(), sender="valid-controller"))
                time.sleep(DT)
            flood_out, flood_err = flood.communicate(timeout=10)
            assert flood.returncode == 0, flood_err
            assert _stop_process(bridge) == 0
        finally:
            for p in (bridge, flood):
                if p is not None and p.poll() is None:
                    p.kill()
                    p.wait(5)
        _settled(health)
        states.close()
        health.close()
        sent = int(flood_out.split()[-1])
        final = health.messages()[-1]
        log = (tmp_path / "bridge.log").read_text()
        ticks, overruns = final.received["ticks"], final.received["overruns"]
        rejected = final.rejected[bus.MOTOR_COMMAND]
        print(f"\nflood: sent {sent}, rejected {rejected}; valid sent {k}, accepted "
              f"{final.received[bus.MOTOR_COMMAND] - rejected}; ticks {ticks}, overruns {overruns}, "
              f"max tick {final.received['tick_max_us']} µs")
        assert sent >= 0.9 * 5000 * 3.0
        assert rejected >= 0.9 * sent, log  # counted (the bus may drop a few under DROP congestion)
        # Overruns are reported, not bounded here: on a loaded machine they follow the load, not the
        # flood (about 0.3 % when idle; benchmarks/faults.py measures the budget). What must hold on
        # any machine: the flood is counted, never obeyed, and a hold says why.
        assert 0 <= overruns <= ticks and final.received["tick_max_us"] > 0, log
        seen = states.messages()
        active = [s for s in seen if s.drive == "active"]
        assert len(active) > 500
        assert all(s.hold_reason for s in seen if s.drive == "hold")  # late valid commands: the watchdog, named
        target = np.array([20.0, 25.0, 30.0, 2.0])

        def obeys(prev, s) -> bool:  # the command, or the bumpless ramp to it after an enable (≤ 1 N per tick)
            f = np.array(s.force_applied_N)
            if np.array_equal(f, target):
                return True
            if s.drive != "active" or prev is None or s.seq != prev.seq + 1:
                return False
            p = np.array(prev.force_applied_N)
            return bool(np.abs(f - p).max() <= 1.0 + 1e-9 and np.all(np.abs(target - f) <= np.abs(target - p) + 1e-9))

        obeyed = [s for prev, s in zip([None, *seen], seen) if s.drive == "active" and obeys(prev, s)]
        assert len(obeyed) >= 0.95 * len(active), {s.drive for s in active}
        assert "drives disabled" in log


def test_lockstep_ticks_once_per_command_and_never_holds(params):
    from bridge.node import run_lockstep

    with bus_pair() as (_hub, hub_session, connect):
        _token = _as_controller(hub_session)
        node = _node(connect(), params, lockstep=True, idle_timeout_s=5.0)
        states = subscribe_latest(hub_session, bus.MOTOR_STATE)
        stop = threading.Event()
        th, out = run_in_thread(run_lockstep, node, stop)
        pub = publisher(hub_session, bus.MOTOR_COMMAND)
        try:
            assert states.wait(10.0) is not None
            last = 0.0
            for k in range(1, 21):
                for _attempt in range(20):  # resend on loss, as the controller does
                    pub.put(_command(k, [15.0] * 4, node))
                    got = states.wait(0.25, lambda s: s.stamp_s > last + 1e-9)
                    if got is not None and got.stamp_s > last + 1e-9:
                        break
                assert got.stamp_s == pytest.approx(k * DT) and got.drive == "active"
                last = got.stamp_s
                if k == 10:
                    time.sleep(0.1)  # ten timeouts of wall time: simulated time stands still, no hold
        finally:
            stop.set()
            th.join(5)
            node.shutdown()
        assert "error" not in out, out.get("error")
        assert node.holds == 0 and node.ticks == 20


def test_replay_driver_publishes_the_archived_angles(params, tmp_path):
    from bridge.archive import write_campaign
    from bridge.drivers.replay import ReplayConfig, ReplayDriver

    archived = [bus.MotorState(seq=k, stamp_s=DT * k, theta_rad=[0.01 * k, 0.02 * k, -0.01 * k, 0.0],
                               force_applied_N=[10.0] * 4, drive="active", epoch="e0", bridge="b0") for k in range(50)]
    path = write_campaign(tmp_path / "c.mcap", [(bus.MOTOR_STATE, k * 2_000_000, s) for k, s in enumerate(archived)],
                          {"campaign_id": "replay", "kind": "control"})
    with bus_pair() as (_hub, hub_session, connect):
        states = Collector(hub_session, bus.MOTOR_STATE)
        node = bridge_node(connect(), ReplayDriver(ReplayConfig(path=str(path))), params, BridgeConfig())
        try:
            time.sleep(0.3)  # let the subscriber's route settle before the first tick
            ticks = run_realtime(node, threading.Event())  # stops by itself at the end of the archive
        finally:
            node.shutdown()
        assert wait_until(lambda: states.messages() and states.messages()[-1].drive == "disabled", 5.0)
        states.close()
    assert ticks == 50
    replayed = [s.theta_rad for s in states.messages() if s.drive != "disabled"]
    assert replayed == [s.theta_rad for s in archived][-len(replayed):]  # each state once, in order
    assert len(replayed) >= 45  # all but those published before the route settled
