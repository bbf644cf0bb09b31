"""Stalled peers benchmark: does the control path keep flowing while listeners stop reading?

    .venv/bin/python benchmarks/stalled_peers.py [--stopped 1,2] [--stop-s 34] [--layout hub,up,stack]
        [--runtime default,xneck] [--runs 1]

Processes of their own on 127.0.0.1 (benchmarks/_bus_peer.py): a hub that subscribes to every
key (as the console does), a publisher of motor states at 500 Hz and camera frames (as the
bridge), a peer that answers at 500 Hz with a command and a status and times the states it gets
(as the controller), and ``N - 1`` more listeners of every key. The hub and the listeners are
stopped (SIGSTOP) for ``--stop-s``: their links' leases expire after 10 s and Zenoh's TCP links
linger up to 10 s on close (eclipse-zenoh/zenoh#1101; docs/safety.md, "Peers that stop reading").
Layouts: ``hub``, every peer connects to the hub (as ``xneck up`` linked them before
2026-11-27); ``up``, the publisher listens, the control peer connects to it and the hub to both,
as ``xneck up`` linked the bridge, the controller and the console from 2026-11-27, on loopback TCP;
``stack``, as ``up`` with the publisher and the control peer on Unix sockets and opening no link by
gossip, as ``xneck up`` links them since 2026-11-30 (server/cli/up.py).

Each case runs ``--runs`` times with each runtime of ``--runtime``: Zenoh's default (2 receive
workers, ``ZENOH_RUNTIME`` set so in the children: the baseline) and xneck's (bridge.session:
``ZENOH_RX_WORKERS``). Printed per run: the states' inter-arrival median and p99, the longest gap
and when (s after the first state; the stop starts about 1 s in), and how many gaps exceeded
10 ms (the bridge's command timeout: each one a hold) and 100 ms; with both runtimes, the longest
gap's ratio xneck / baseline; after a run in which no state came for 0.5 s, what every thread of
the scenario's processes was doing then (benchmarks/_bus_peer.py, ``stalls``).
"""

from __future__ import annotations

import argparse
import os
import time

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
from _bus_peer import LAYOUTS, run_stalled

from bridge.session import ENV_ZENOH_RUNTIME, ZENOH_RX_WORKERS, free_tcp_port

ZENOH_DEFAULT = "(rx: (worker_threads: 2))"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--stopped", default="1,2", help="numbers of stopped listeners, the hub included (default 1,2)")
    ap.add_argument("--stop-s", type=float, default=34.0, help="how long they stay stopped (s; default 34: the "
                    "lease, the linger, and two of the peers' 11-14 s retries to a stopped hub)")
    ap.add_argument("--layout", default="hub,up,stack", help="layouts to run, of hub, up and stack (default all)")
    ap.add_argument("--runtime", default="default,xneck", help="Zenoh runtimes, of default and xneck "
                    "(default both)")
    ap.add_argument("--runs", type=int, default=1, help="runs of each case and runtime (default 1)")
    args = ap.parse_args()
    layouts = [x for x in args.layout.split(",") if x]
    if not layouts or not set(layouts) <= set(LAYOUTS):
        ap.error(f"--layout takes {', '.join(LAYOUTS)}, got {args.layout!r}")
    runtimes = [x for x in args.runtime.split(",") if x]
    if not runtimes or not set(runtimes) <= {"default", "xneck"}:
        ap.error(f"--runtime takes default and/or xneck, got {args.runtime!r}")
    if args.runs < 1:
        ap.error(f"--runs {args.runs}: at least 1")
    print(f"stalled peers, {time.strftime('%Y-%m-%d %H:%M')}, load {os.getloadavg()[0]:.1f}, stopped {args.stop_s:g} s; "
          f"xneck: {ZENOH_RX_WORKERS} receive workers, baseline: Zenoh's default {ZENOH_DEFAULT}")
    print("| layout | stopped listeners | runtime | states | gap median (ms) | gap p99 (ms) | longest gap (ms, at s) "
          "| gaps > 10 ms | gaps > 100 ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    xneck_env = {k: v for k, v in os.environ.items() if k != ENV_ZENOH_RUNTIME}
    envs = {"Zenoh default": {**xneck_env, ENV_ZENOH_RUNTIME: ZENOH_DEFAULT}, "xneck": xneck_env}
    names = [name for name in envs if name.split()[-1] in runtimes]
    stalls = []
    for layout in layouts:
        for n in (int(x) for x in args.stopped.split(",")):
            for _ in range(args.runs):
                worst = {}
                for name in names:
                    r = run_stalled(f"tcp/127.0.0.1:{free_tcp_port()}", n, args.stop_s, envs[name], layout=layout)
                    worst[name] = r["max_gap_s"]
                    print(f"| {layout} | {n} | {name} | {r['received']} | {1e3 * r['median_gap_s']:.2f} | "
                          f"{1e3 * r['p99_gap_s']:.2f} | {1e3 * r['max_gap_s']:.0f} (at {r['at_s']:.1f}) | "
                          f"{r['gaps_over_10ms']} | {r['gaps_over_100ms']} |", flush=True)
                    stalls += [(layout, n, name, stall) for stall in r["stalls"]]
                if len(worst) == 2:
                    print(f"|   |   | longest gap, xneck / baseline | {worst['xneck'] / worst['Zenoh default']:.3f} "
                          "| | | | | |", flush=True)
    for layout, n, name, stall in stalls:
        print(f"\nno state for 0.5 s from {stall['at_s']:.1f} s ({layout}, {n} stopped, {name}); the threads then:")
        print("\n".join(f"    {line}" for line in stall["threads"]))


if __name__ == "__main__":
    main()
