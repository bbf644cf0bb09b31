"""The controller answers each state in Zenoh's callback; after it was held up, the stale states of
the burst that queued meanwhile are skipped, not answered late one by one (issue 21)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import pytest
from busutil import wait_until

from bridge import bus
from bridge.session import BusPublisher, free_tcp_port, open_session, publisher
from controller.laws import LawConfig
from controller.process import ControllerNode, ControllerProcessConfig
from twin.model.params import load_params

pytestmark = pytest.mark.realtime  # its premise is a burst that arrives at once


def _state(k: int) -> bus.MotorState:
    return bus.MotorState(seq=k, stamp_s=k * 0.002, theta_rad=[0.0] * 4, force_applied_N=[10.0] * 4, drive="active",
                          epoch="e1", bridge="b1")


def _on_time_until_answered(pub, answered: set[float], t0: float, k: int, timeout_s: float = 10.0) -> int | None:
    """The bridge's states from ``k`` on, each at its due time (``t0`` + its stamp), until the
    controller answers one: the number of the first answered, None if none was within ``timeout_s``.
    A bridge states every period, so the first on time after a burst may still arrive on the
    burst's heels, where it is one of it (skipped; on a loaded machine, CI of 2026-12-02): the next
    is answered."""
    first, deadline = k, time.perf_counter() + timeout_s
    while time.perf_counter() < deadline:
        seen = {round(s, 6) for s in answered}
        if done := [j for j in range(first, k) if round(j * 0.002, 6) in seen]:
            return done[0]
        time.sleep(max(0.0, t0 + k * 0.002 - time.perf_counter()))
        pub.put(_state(k))
        k += 1
    return None


@contextlib.contextmanager
def _on_bus(instance: str) -> Iterator[tuple[BusPublisher[bus.BusMessage], set[float], set[float], ControllerNode]]:
    """A controller node (law 2) running on a real bus, answered once, and the bridge's end of it:
    the state publisher, the stamps of the commands that came back (s, rounded to 1 µs) and of the
    states the bus brought the controller's session."""
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(listen=[hub], connect=[]) as bridge_side, open_session(connect=[hub]) as ctl_side:
        answered: set[float] = set()
        sub = bridge_side.declare_subscriber(bus.MOTOR_COMMAND, lambda s: answered.add(
            round(bus.decode(bus.ForceCommand, s.payload.to_bytes()).stamp_s, 6)))
        delivered: set[float] = set()
        probe = ctl_side.declare_subscriber(bus.MOTOR_STATE, lambda s: delivered.add(
            round(bus.decode(bus.MotorState, s.payload.to_bytes()).stamp_s, 6)))
        node = ControllerNode(ctl_side, load_params(), LawConfig(law=2), None,
                              ControllerProcessConfig(exit_when_done=False, instance=instance))
        # Blocking, unlike the bridge's: on a loaded machine the bus dropped up to 44 of the burst's
        # 60 states at this end, and the burst is what these tests are about.
        pub = publisher(bridge_side, bus.MOTOR_STATE, block=True)
        stop = threading.Event()
        loop = threading.Thread(target=node.run, args=(stop,), daemon=True)
        loop.start()
        try:
            assert wait_until(lambda: (pub.put(_state(0)), 0.0 in answered)[1], 30, 0.05)
            yield pub, answered, delivered, node
        finally:
            stop.set()
            loop.join(10)
            node.close()
            sub.undeclare()
            probe.undeclare()
            pub.close()


def test_a_state_on_the_heels_of_a_burst_is_one_of_it_and_the_bridges_next_is_answered():
    """The controller held up (its tick lock taken) while the bridge's states 1-61 arrive, the last
    of them on time: they wait in Zenoh's thread and come back to back. The first is answered (the
    bridge waits for a command), most of the rest skipped, state 61 among them as a rule: it came
    on the burst's heels like the stale ones, as it did on CI's loaded machine, where the test
    below waited for its answer in vain. The bridge's next states, on time and apart, are answered."""
    with _on_bus("c-heels") as (pub, answered, _, node):
        with node._tick_lock:  # held up: a loaded machine, a long tick
            for k in range(1, 62):
                pub.put(_state(k))
            time.sleep(0.1)  # every one of them is in Zenoh's thread, waiting for the lock
        fresh = _on_time_until_answered(pub, answered, time.perf_counter() - 0.122, 62)  # 62 due in 2 ms
        burst = {round(k * 0.002, 6) for k in range(1, 62)} & answered
        # The first answered, most of the rest not: 10-19 of the 61 were answered in runs on an
        # idle 2-CPU VM, those that the GIL's hand-over to Zenoh's thread kept more than a
        # quarter period after the tick before (answering each would be 61).
        assert 0.002 in burst and len(burst) < 61 / 2, sorted(burst)
        assert fresh is not None, sorted(answered)[-5:]


def test_a_burst_of_stale_states_is_skipped_and_the_next_fresh_one_answered():
    with _on_bus("c-burst") as (pub, answered, delivered, node):
        t0 = time.perf_counter()
        time.sleep(0.06)  # the bridge's states 1..60 are due meanwhile: they come all at once
        for k in range(1, 61):
            pub.put(_state(k))
        fresh = _on_time_until_answered(pub, answered, t0, 61)
        assert fresh is not None, (sorted(answered)[-5:], node._error, sorted(delivered)[-5:], node.states.stats)
        burst = {round(k * 0.002, 6) for k in range(1, 61)}
        answered_burst = burst & answered
        # The first of the burst is answered (the bridge waits for a command), most of the rest not:
        # skipped as stale, or, when a loaded machine delivers them closer together than they
        # were sent, refused by the gate as running ahead of the controller's clock (StateGate's
        # skew_s). Those the bus brought, lest it drop some still.
        assert round(0.002, 6) in answered_burst
        arrived = len(burst & delivered)
        refused = node.states.stats.rejected
        assert refused == 0 or "ahead of the controller's clock" in node.states.stats.last_reject_reason
        not_answered = node.times.skipped + node.times.window_skipped + refused
        assert arrived >= 20 and len(answered_burst) < arrived / 2, (arrived, answered_burst)
        assert not_answered >= arrived - len(answered_burst), (arrived, answered_burst, node.times.skipped, refused)
