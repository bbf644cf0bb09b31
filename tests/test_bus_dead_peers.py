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
import json
import warnings
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


LEASE_END_S = 15.0  # the links' leases expire 10-11 s after the first state; their closes linger 10 s more


def _deaf(result: dict) -> bool:
    # 500 Hz: a gap of a second is a deaf receiver (it was 10.04 s with two stopped listeners).
    return not (result["received"] > 0.8 * 500 * STOPPED_S and result["max_gap_s"] < 1.0)


def _deaf_at_the_leases_end(result: dict) -> bool:
    """Deaf from when the stopped peers' leases expired: the lingering closes hold the receive
    workers (the regression this module is for)."""
    return any(stall["at_s"] < LEASE_END_S and stall["gap_s"] >= 1.0 for stall in result["stalls"]) or \
        (result["max_gap_s"] >= 1.0 and result["at_s"] < LEASE_END_S)


def _run(stopped: int) -> dict:
    return bus_peer.run_stalled(f"tcp/127.0.0.1:{free_tcp_port()}", stopped, STOPPED_S)


def test_states_keep_flowing_between_two_peers_while_listeners_stop_reading() -> None:
    """The hub stopped, the hub with another listener, and with two others: three scenarios on
    their own hubs and processes, run at once (each is mostly its 24 s stop: one after the other,
    two of them held a worker of the suite 75 s).

    Deaf at the leases' end (about 10 s after the first state) fails at once: too few Zenoh
    receive workers, the regression this module is for, went deaf there for 10 s in 2 of 4 runs
    with 2 listeners stopped and 3 of 4 with 3 (`benchmarks/stalled_peers.py --stopped 2 --stop-s
    24 --layout hub --runtime default --runs 4`, 2026-11-30 12:03, and `--stopped 3`, 12:09).
    Deaf later is run once more, alone, and must not be again; the first
    result, with what every thread of the scenario was doing during the gap, is reported as a
    warning. Why: three times in some fifty runs of the suite since 2026-11-27 (none in
    `--runtime xneck --runs 10` of that benchmark, 2026-11-30 11:54) the control peer got no
    state for 5-6 s from 20 s after its first until about when the stopped listeners resumed: the
    publisher's Zenoh `net-0` thread in a lingering close (the third one's snapshot; docs/safety.md,
    "Peers that stop reading"), open."""
    scenarios = {"the-hub": 1, "the-hub-and-another-listener": 2, "the-hub-and-two-listeners": 3}
    with ThreadPoolExecutor(len(scenarios)) as pool:
        runs = {name: pool.submit(_run, stopped) for name, stopped in scenarios.items()}
        results = {name: run.result(timeout=STOPPED_S + 120) for name, run in runs.items()}
    for name, result in results.items():
        if not _deaf(result):
            continue
        # a string: pytest would shorten a dict, and the threads' snapshot is what tells the cause
        assert not _deaf_at_the_leases_end(result), f"{name}: {json.dumps(result)}"
        warnings.warn(f"stalled peers, {name}: deaf once after the leases' end, run again; {json.dumps(result)}",
                      stacklevel=1)
        again = _run(scenarios[name])
        assert not _deaf(again), f"{name}, deaf twice: {json.dumps(result)} then {json.dumps(again)}"
