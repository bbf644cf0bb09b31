"""Bus flood benchmark: what a stranger on the lab network costs the bridge's control path.

    .venv/bin/python benchmarks/bus_flood.py [--count 200] [--seconds 30] [--flood none,tcp,sessions] [--viewers] [--tls]

The bridge listens on the lab network (docs/bridge.md, deployment), so anyone there can connect
to it. Processes of their own on 127.0.0.1 (benchmarks/_bus_peer.py): a publisher of motor states
at 500 Hz and camera frames (as the bridge) listens, a peer that answers at 500 Hz with a command
and a status connects to it and times the states it gets (as the controller). Once states flow,
a rogue process opens ``--count`` connections to the publisher and holds them for the rest of the
run: ``tcp``, plain TCP connections that send nothing; ``sessions``, Zenoh sessions that each
subscribe to every xneck key (each costs the publisher a send per state). Every flood runs twice:
without credentials (the baseline) and with ``XNECK_ZENOH_CREDENTIALS`` set for the publisher and
the control peer (a file made by ``xneck bus credentials``) but not for the rogue. ``--viewers``
adds a third run whose file also lists a viewer (``xneck bus add-user FILE viewer``), so that
every process runs Zenoh's access control (bridge.bus_credentials.viewer_access_control): what
the control path pays for it. ``--tls`` adds a run over a ``tls/`` link with a folder made by
``xneck bus tls`` (bridge.bus_tls) on top of the credentials: what encryption costs it.

Printed per run: the rogue's connections and how many linked, the states' inter-arrival median
and p99, the longest gap, and how many gaps exceeded 10 ms (the bridge's command timeout: each
one a hold) and 100 ms; then the p99 ratio with credentials / without (and with the access
control / credentials alone). The rogue shares this
machine's CPUs with the stack, which a stranger on another machine would not: a rogue here costs
more than one on the network would, so read the ratio, not the absolute figures.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
from _bus_peer import FLOODS, run_flood

from bridge.bus_credentials import ENV_CREDENTIALS, ENV_USER, add_entry, write_new
from bridge.bus_tls import ENV_TLS
from bridge.bus_tls import write_new as write_tls
from bridge.session import MAX_SESSIONS


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--count", type=int, default=200, help="the rogue's connections (default 200)")
    ap.add_argument("--seconds", type=float, default=30.0, help="the control peer's run (s; default 30)")
    ap.add_argument("--flood", default="none,tcp,sessions", help=f"floods to run, of {', '.join(FLOODS)}")
    ap.add_argument("--viewers", action="store_true", help="also run with a file that lists a viewer (access control on)")
    ap.add_argument("--tls", action="store_true", help="also run over a tls/ link (with the credentials)")
    args = ap.parse_args()
    floods = [x for x in args.flood.split(",") if x]
    if not floods or not set(floods) <= set(FLOODS):
        ap.error(f"--flood takes {', '.join(FLOODS)}, got {args.flood!r}")
    if args.count < 1 or args.seconds <= 5:
        ap.error("--count must be ≥ 1 and --seconds > 5")
    print(f"bus flood, {time.strftime('%Y-%m-%d %H:%M')}, load {os.getloadavg()[0]:.1f}, {args.seconds:g} s runs, "
          f"rogue connections {args.count}, sessions accepted per process {MAX_SESSIONS}")
    print("| flood | credentials | rogue linked / opened | states | gap median (ms) | gap p99 (ms) | longest gap (ms) "
          "| gaps > 10 ms | gaps > 100 ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    plain = {k: v for k, v in os.environ.items() if k not in (ENV_CREDENTIALS, ENV_USER, ENV_TLS)}
    with tempfile.TemporaryDirectory() as tmp:
        creds = write_new(Path(tmp) / "bus-credentials")
        runs = [("none", plain, "tcp"), ("yes", {**plain, ENV_CREDENTIALS: str(creds.path)}, "tcp")]
        if args.viewers:
            lab = write_new(Path(tmp) / "lab-credentials").path
            add_entry(lab, "viewer")
            runs.append(("yes, lists a viewer", {**plain, ENV_CREDENTIALS: str(lab)}, "tcp"))
        if args.tls:
            folder = write_tls(Path(tmp) / "tls", ["127.0.0.1"])
            runs.append(("yes, over tls/", {**plain, ENV_CREDENTIALS: str(creds.path), ENV_TLS: str(folder.path)}, "tls"))
        for flood in floods:
            p99 = {}
            for name, env, scheme in runs:
                r = run_flood(flood, args.count, args.seconds, env, plain, scheme)
                p99[name] = r["p99_gap_s"]
                rogue = "-" if r["rogue"] is None else f"{r['rogue']['linked']} / {r['rogue']['opened']}"
                print(f"| {flood} | {name} | {rogue} | {r['received']} | {1e3 * r['median_gap_s']:.2f} | "
                      f"{1e3 * r['p99_gap_s']:.2f} | {1e3 * r['max_gap_s']:.0f} | {r['gaps_over_10ms']} | "
                      f"{r['gaps_over_100ms']} |", flush=True)
            print(f"|   | gap p99, with / without credentials | {p99['yes'] / p99['none']:.3f} | | | | | | |", flush=True)
            if args.viewers:
                print(f"|   | gap p99, access control / credentials alone | {p99['yes, lists a viewer'] / p99['yes']:.3f} "
                      "| | | | | | |", flush=True)
            if args.tls:
                print(f"|   | gap p99, tls/ / tcp/ (both with credentials) | {p99['yes, over tls/'] / p99['yes']:.3f} "
                      "| | | | | | |", flush=True)


if __name__ == "__main__":
    main()
