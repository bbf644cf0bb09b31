"""The console's live fan-out is decimated where samples enter it (issue 21): a 500 Hz key costs
it one store per read, not one Python callback per sample."""

from __future__ import annotations

import time

from busutil import wait_until

from bridge import bus
from bridge.session import free_tcp_port, open_session, publisher
from server.live import LiveBus


def _state(seq: int) -> bus.MotorState:
    return bus.MotorState(seq=seq, stamp_s=seq * 0.002, theta_rad=[0.0] * 4, force_applied_N=[1.0] * 4,
                          drive="active", epoch="e", bridge="b")


def test_a_burst_of_states_is_one_store_when_read_and_the_newest_wins():
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(listen=[hub], connect=[]) as a, open_session(connect=[hub]) as b:
        live = LiveBus(b)
        pub = publisher(a, bus.MOTOR_STATE)
        try:
            def first() -> bool:  # until the subscription is known to the publisher
                pub.put(_state(1))
                return live.values.get("state") is not None

            assert wait_until(first, 10, 0.05)
            before = live.values.version()
            for k in range(2, 1002):
                pub.put(_state(k))  # a burst: the real-time key may drop some under congestion
            time.sleep(0.2)
            pub.put(_state(1002))
            assert wait_until(lambda: live.values.get("state").seq == 1002, 10, 0.01)
            # Every read took at most the newest sample of the ring: far fewer stores than samples.
            assert live.values.version() - before < 1000 / 4
        finally:
            pub.close()
            live.close()
