"""A campaign's final ``ControllerTiming`` (its figures at the end) reaches its record and quality.

The official CI of 2026-12-02 (stop 64) lost it on a loaded machine: the campaign's MCAP ended on
a periodic timing 84 ticks short of the campaign's count, and its quality took the latency of that
window. Two causes, one test each: the timing key drops under congestion (right for the periodic
windows, not for the one final message), and each Zenoh subscriber's callback runs in its own
thread (zenoh-python's default), so the console heard the end event, put after the final timing,
while the thread of the timing's subscriber was still behind (the recorder's own case is
tests/test_archive.py's).
"""

from __future__ import annotations

import threading
import time

import msgspec
import numpy as np
import pytest
import zenoh
from busutil import wait_until

from bridge import bus
from bridge.session import free_tcp_port, open_session
from controller.laws import LawConfig
from controller.process import ControllerNode, ControllerProcessConfig
from controller.timing import TickTimes, timing_message
from server.quality import CampaignMonitor
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


def _timing(campaign_id: str, ticks: int, p50_ms: float) -> bytes:
    empty = np.zeros((0, 4))
    msg = timing_message(1, 1.0, campaign_id, empty, np.zeros(0), TickTimes(), ticks, 0, 0)
    return bus.encode(msgspec.structs.replace(msg, campaign_latency_p50_ms=p50_ms, campaign_latency_p99_ms=p50_ms))


def test_the_quality_waits_for_the_final_timing_its_subscriber_has_not_taken_yet(
    sessions: tuple[zenoh.Session, zenoh.Session], monkeypatch: pytest.MonkeyPatch,
) -> None:
    a, b = sessions
    monitor = CampaignMonitor(b)
    decode = monitor._decode

    def slow(msg_type, sample):  # the timing subscriber's thread, behind on a loaded machine
        if msg_type is bus.ControllerTiming:
            time.sleep(0.3)
        return decode(msg_type, sample)

    monkeypatch.setattr(monitor, "_decode", slow)
    ends: list[bus.CampaignEvent] = []
    sub = b.declare_subscriber(bus.CAMPAIGN_EVENTS, lambda s: ends.append(bus.decode(bus.CampaignEvent, s.payload.to_bytes())))
    timings = a.declare_publisher(bus.CONTROLLER_TIMING, congestion_control=zenoh.CongestionControl.BLOCK)
    events = a.declare_publisher(bus.CAMPAIGN_EVENTS, congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        assert wait_until(lambda: (timings.put(_timing("c-1", 10, 0.1)), monitor.counters().get("latency_p50_ms"))[1],
                          10, 0.05)  # the route is up, a window of the campaign taken
        monitor.begin()
        timings.put(_timing("c-1", 500, 0.7))  # its final figures, then its end, as the controller puts them
        events.put(bus.encode(bus.CampaignEvent(seq=1, stamp_s=1.0, campaign_id="c-1", kind="control",
                                                event="finished", ticks=500)))
        assert wait_until(lambda: bool(ends), 10, 0.01)
        monitor.note_event(ends[0])
        assert monitor.counters()["latency_p50_ms"] == 0.1  # the race is there: the end came first
        assert monitor.wait_final_timing("c-1", 5.0)
        monitor.end()
        assert monitor.counters()["latency_p50_ms"] == 0.7
        # A campaign whose final timing never comes is not waited for past the time given.
        monitor.note_event(msgspec.structs.replace(ends[0], ticks=501))
        assert not monitor.wait_final_timing("c-1", 0.2)
    finally:
        sub.undeclare()
        timings.undeclare()
        events.undeclare()
        monitor.close()
