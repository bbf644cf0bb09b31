"""A campaign's final ``ControllerTiming`` (its figures at the end) gets through a congested bus.

The official CI of 2026-12-02 (stop 64) lost it on a loaded machine: the campaign's MCAP ended on
a periodic timing 84 ticks short of the campaign's count, and its quality took the latency of that
window. The periodic ones may drop (a stale window is worth nothing); the final one is written once
per campaign and is what the archive and the quality keep, so it must wait instead.
"""

from __future__ import annotations

import threading
import time

from busutil import wait_until

from bridge import bus
from bridge.session import free_tcp_port, open_session
from controller.laws import LawConfig
from controller.process import ControllerNode, ControllerProcessConfig
from twin.model.params import load_params

FLOOD = 20_000  # periodic timings (~1.5 kB each): more than loopback's socket buffers hold


def test_a_campaigns_final_timing_waits_out_a_stalled_reader_where_the_periodic_ones_drop():
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(listen=[hub], connect=[]) as console_side, open_session(connect=[hub]) as ctl_side:
        got: list[bus.ControllerTiming] = []
        stalled, release = threading.Event(), threading.Event()

        def on_timing(sample) -> None:
            if stalled.is_set():  # a console that stopped reading: its link's buffers fill up
                release.wait(30)
            got.append(bus.decode(bus.ControllerTiming, sample.payload.to_bytes()))

        sub = console_side.declare_subscriber(bus.CONTROLLER_TIMING, on_timing)
        node = ControllerNode(ctl_side, load_params(), LawConfig(law=2), None,
                              ControllerProcessConfig(exit_when_done=False, instance="c-final-timing"))
        final: threading.Thread | None = None
        try:
            assert wait_until(lambda: (node.publish_timing(0.0), bool(got))[1], 30, 0.05)
            stalled.set()
            for k in range(FLOOD):
                node.publish_timing(k * 1e-3)
            final = threading.Thread(target=node.publish_timing, args=(time.time(), ("c-1", 1234, 5, 6)), daemon=True)
            final.start()
            time.sleep(0.5)  # the final one is put meanwhile, into the congested link
            release.set()
            final.join(20)
            assert not final.is_alive()

            def last_is_final() -> bool:
                return bool(got) and got[-1].campaign_id == "c-1"

            assert wait_until(last_is_final, 20, 0.05), got[-1:]
            # The congestion was real: periodic timings were dropped on the way.
            assert len(got) < FLOOD, len(got)
            end = got[-1]
            assert (end.campaign_ticks, end.campaign_deadline_misses, end.campaign_overruns) == (1234, 5, 6)
        finally:
            release.set()
            if final is not None:
                final.join(20)
            node.close()
            sub.undeclare()
