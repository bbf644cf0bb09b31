"""Peers that stop reading must not deafen the healthy ones (found 2026-11-27).

Zenoh's TCP links linger 10 s on close (SO_LINGER, hard-coded in zenoh-link-tcp): when a peer
stops reading (a console machine suspended or unplugged, a process stopped) and its receive
window fills, the link's lease expires after 10 s and closing it blocks the Zenoh worker thread
that closes it until the linger runs out (eclipse-zenoh/zenoh#1101). With Zenoh's two receive
workers, two such peers (the console and its campaign runner, or a second recorder) left every
other process deaf for 10 s: the controller got no state, the bridge no command and no e-stop.
bridge.session gives every xneck process more receive workers (docs/safety.md).

The scenario is benchmarks/_bus_peer.py's (benchmarks/stalled_peers.py measures it): whole
processes (each its own Zenoh runtime), real Zenoh on 127.0.0.1, stopped within bounded time.
"""

from __future__ import annotations

import importlib.util
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from bridge.session import free_tcp_port

pytestmark = [pytest.mark.e2e, pytest.mark.realtime]  # 500 Hz between peers, no gap of a second: a loaded machine makes gaps of its own

_spec = importlib.util.spec_from_file_location(
    "_bus_peer", Path(__file__).resolve().parents[1] / "benchmarks" / "_bus_peer.py")
assert _spec is not None and _spec.loader is not None
bus_peer = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bus_peer)

STOPPED_S = 24.0  # the lease (10 s), then the linger (10 s), and a margin


def test_states_keep_flowing_between_two_peers_while_listeners_stop_reading() -> None:
    """The hub stopped, and the hub with another listener: two scenarios on their own hubs and
    processes, run at once (each is mostly its 24 s stop: one after the other, the module held a
    worker of the suite 75 s)."""
    scenarios = {"the-hub": 1, "the-hub-and-another-listener": 2}
    with ThreadPoolExecutor(len(scenarios)) as pool:
        runs = {name: pool.submit(bus_peer.run_stalled, f"tcp/127.0.0.1:{free_tcp_port()}", stopped, STOPPED_S)
                for name, stopped in scenarios.items()}
        results = {name: run.result(timeout=STOPPED_S + 120) for name, run in runs.items()}
    for name, result in results.items():
        # 500 Hz: a gap of a second is a deaf receiver (it was 10.04 s with two stopped listeners).
        assert result["received"] > 0.8 * 500 * STOPPED_S and result["max_gap_s"] < 1.0, (name, result)
