"""The controller answers each state in Zenoh's callback; after it was held up, the stale states of
the burst that queued meanwhile are skipped, not answered late one by one (issue 21)."""

from __future__ import annotations

import threading
import time

import pytest
from busutil import wait_until

from bridge import bus
from bridge.session import free_tcp_port, open_session, publisher
from controller.laws import LawConfig
from controller.process import ControllerNode, ControllerProcessConfig
from twin.model.params import load_params

pytestmark = pytest.mark.realtime  # its premise is a burst that arrives at once


def _state(k: int) -> bus.MotorState:
    return bus.MotorState(seq=k, stamp_s=k * 0.002, theta_rad=[0.0] * 4, force_applied_N=[10.0] * 4, drive="active",
                          epoch="e1", bridge="b1")


def test_a_burst_of_stale_states_is_skipped_and_the_next_fresh_one_answered():
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(listen=[hub], connect=[]) as bridge_side, open_session(connect=[hub]) as ctl_side:
        answered: set[float] = set()
        sub = bridge_side.declare_subscriber(bus.MOTOR_COMMAND, lambda s: answered.add(
            bus.decode(bus.ForceCommand, s.payload.to_bytes()).stamp_s))
        node = ControllerNode(ctl_side, load_params(), LawConfig(law=2), None,
                              ControllerProcessConfig(exit_when_done=False, instance="c-burst"))
        pub = publisher(bridge_side, bus.MOTOR_STATE)
        stop = threading.Event()
        loop = threading.Thread(target=node.run, args=(stop,), daemon=True)
        loop.start()
        try:
            assert wait_until(lambda: (pub.put(_state(0)), 0.0 in answered)[1], 30, 0.05)
            t0 = time.perf_counter()
            time.sleep(0.06)  # the bridge's states 1..60 are due meanwhile: they come all at once
            for k in range(1, 61):
                pub.put(_state(k))
            time.sleep(max(0.0, t0 + 0.122 - time.perf_counter()))
            pub.put(_state(61))  # on time again
            assert wait_until(lambda: 0.122 in {round(s, 6) for s in answered}, 10, 0.01), (sorted(answered)[-5:], node._error, node.times.skipped)
            burst = {round(k * 0.002, 6) for k in range(1, 61)}
            answered_burst = burst & {round(s, 6) for s in answered}
            # The first of the burst is answered (the bridge waits for a command), most of the rest not.
            assert round(0.002, 6) in answered_burst
            assert len(answered_burst) < 30 and node.times.skipped + node.times.window_skipped >= 30, answered_burst
        finally:
            stop.set()
            loop.join(10)
            node.close()
            sub.undeclare()
            pub.close()
