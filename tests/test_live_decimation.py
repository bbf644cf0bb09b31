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


def _truth(seq: int, stamp_s: float) -> bus.Truth:
    zeros = [0.0] * 4
    return bus.Truth(seq=seq, stamp_s=stamp_s, alpha_rad=[0.0] * 3, alpha_dot_rad_s=[0.0] * 3, theta_rad=zeros,
                     theta_dot_rad_s=zeros, tension_N=zeros, elongation_m=zeros, slack=[False] * 4, near_singular=False)


def test_the_truth_shown_is_the_twins_whose_run_the_commands_answer_never_a_strays():
    """Two twins on the hub: the live truth flipped between their clocks (audit of 2026-11-29).
    It is the run's the newest command answers; a replay's (no run) only while that run has none."""
    from bridge.session import REPLAYED, run_attachment

    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(listen=[hub], connect=[]) as a, open_session(connect=[hub]) as b:
        live = LiveBus(b)
        live.values.watch("test", True)  # the truth is subscribed to while someone watches
        truths, commands = publisher(a, bus.TWIN_TRUTH), publisher(a, bus.MOTOR_COMMAND)
        try:
            def command() -> None:
                commands.put(bus.ForceCommand(seq=1, stamp_s=0.0, force_N=[5.0] * 4, source="law2", sender="ctl",
                                              epoch="ours"))

            def replayed_only() -> bool:  # the run followed has no truth yet: a replay's is shown
                command()
                truths.put(_truth(1, 99.0), attachment=REPLAYED)
                shown = live.values.get("truth")
                return shown is not None and shown.stamp_s == 99.0

            assert wait_until(replayed_only, 10, 0.05)
            shown = []
            for k in range(1, 200):
                command()
                truths.put(_truth(k, 100.0 + k), attachment=run_attachment("ours"))
                truths.put(_truth(k, 0.001 * k), attachment=run_attachment("stray"))
                truths.put(_truth(k, 50.0), attachment=REPLAYED)
                if k % 10 == 0:
                    time.sleep(0.01)
                    shown.append(live.values.get("truth").stamp_s)
            assert wait_until(lambda: live.values.get("truth").stamp_s == 299.0, 10, 0.01)
            assert all(s > 100.0 for s in shown[1:]) and shown == sorted(shown), shown
        finally:
            truths.close()
            commands.close()
            live.close()
