"""Peer churn benchmark: does a peer linking to the bridge, or leaving, open a gap in the control path?

    .venv/bin/python benchmarks/peer_churn.py [--peers 8] [--period-s 3] [--runs 2] [--transport tcp,unix]
    sudo .venv/bin/python benchmarks/peer_churn.py --transport remote-unix,remote-tcp

Processes of their own on 127.0.0.1 (benchmarks/_bus_peer.py): a publisher of motor states at
500 Hz and camera frames (as the bridge) listens, a peer that answers at 500 Hz with a command and
a status connects to it and times the states it gets (as the controller). Then ``--peers``
listeners (a console, a CLI tool, a camera: each subscribing to every key) connect to the
publisher one after another, each living ``--period-s`` − 1 s; the baseline runs as long with
none. No real-time scheduling here (``xneck up`` gives the bridge and the controller SCHED_FIFO
on a CPU of their own): the new processes' start-up competes for the same two CPUs, so the gaps
mix Zenoh's linking and unlinking with CPU contention. ``--transport``: every process listens on
loopback TCP (``tcp``, as ``xneck up``'s control path did before 2026-11-27 11:00) or on a Unix
socket (``unix``, as it does now). ``remote-tcp`` and ``remote-unix`` (root): the publisher runs in
a network namespace of its own (benchmarks/_netns.py: another TCP stack, as the BeagleBone's, joined
by a veth pair) and listens on TCP there, as a bridge on its board; the other processes stay here
on loopback TCP or Unix sockets (``xneck up --bridge-at``'s PC side uses Unix sockets).

Printed per run: the states' inter-arrival median and p99, the longest gap and when (s after
the first state) with the peers' arrival times, and how many gaps exceeded 10 ms (the bridge's
command timeout: each one a hold); then the p99 ratio churn / baseline.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import tempfile
import time
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
from _bus_peer import run_churn
from _netns import board_namespace, quickack_state

REMOTE = ("remote-tcp", "remote-unix")


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--peers", type=int, default=8, help="peers that come and go (default 8)")
    ap.add_argument("--period-s", type=float, default=3.0, help="one peer started every PERIOD s (default 3)")
    ap.add_argument("--runs", type=int, default=2, help="runs of each case (default 2)")
    ap.add_argument("--transport", default="tcp,unix", help="what the processes listen on, of tcp and unix; "
                    "remote-tcp and remote-unix: the publisher in a network namespace of its own (the board, "
                    "over TCP; root), the other processes on loopback TCP or Unix sockets")
    args = ap.parse_args()
    if args.peers < 1 or args.period_s < 2.0 or args.runs < 1:
        ap.error("--peers and --runs must be ≥ 1, --period-s ≥ 2")
    transports = [t for t in args.transport.split(",") if t]
    if not transports or not set(transports) <= {"tcp", "unix", *REMOTE}:
        ap.error(f"--transport takes tcp, unix and {', '.join(REMOTE)}, got {args.transport!r}")
    if any(t in REMOTE for t in transports) and os.geteuid() != 0:
        ap.error("remote-* runs the publisher in a network namespace: run as root")
    loopback = "on" if quickack_state("127.0.0.1") else "off"
    print(f"peer churn, {time.strftime('%Y-%m-%d %H:%M')}, load {os.getloadavg()[0]:.1f}, {args.peers} peers, "
          f"one every {args.period_s:g} s; loopback route quickack {loopback}")
    print("| transport | case | run | states | gap median (ms) | gap p99 (ms) | longest gap (ms, at s) | gaps > 10 ms "
          "| peers at (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for transport in transports:
        p99: dict[str, list[float]] = {"baseline": [], "churn": []}
        for run in range(1, args.runs + 1):
            for case, peers in (("baseline", 0), ("churn", args.peers)):
                with contextlib.ExitStack() as stack:
                    d = stack.enter_context(tempfile.TemporaryDirectory(prefix="xneck-churn-"))
                    board = stack.enter_context(board_namespace()) if transport in REMOTE else None
                    r = run_churn(peers, args.period_s, slots=args.peers,
                                  unix_dir=Path(d) if transport.endswith("unix") else None, board=board)
                p99[case].append(r["p99_gap_s"])
                print(f"| {transport} | {case} | {run} | {r['received']} | {1e3 * r['median_gap_s']:.2f} | "
                      f"{1e3 * r['p99_gap_s']:.2f} | {1e3 * r['max_gap_s']:.0f} (at {r['at_s']:.2f}) | "
                      f"{r['gaps_over_10ms']} | {', '.join(f'{a:g}' for a in r['arrivals_s']) or '-'} |", flush=True)
        ratio = (sum(p99["churn"]) / len(p99["churn"])) / (sum(p99["baseline"]) / len(p99["baseline"]))
        print(f"| {transport} | gap p99, churn / baseline (mean of runs) | {ratio:.3f} | | | | | | |", flush=True)


if __name__ == "__main__":
    main()
