"""A stopped console under the real `xneck up`: does it add bridge holds to the ones the stack has anyway?

    .venv/bin/python benchmarks/stalled_console.py [--rounds 3] [--baseline-s 12] [--stop-s 24]

Starts `xneck up` (the twin, free ports, its data in a temporary folder), waits for the bridge's
bumpless ramp and 5 s more, then ``--rounds`` times: ``--baseline-s`` with every process running
(the baseline), ``--stop-s`` with the console stopped (SIGSTOP: a hung process), its resume and 8 s
to settle. Counted per window: the bridge's holds (its log's ``hold:`` lines; each a bumpless ramp
after 10 ms without a command) and the connections queued on the stopped console's hub listener
(``_stalled.accept_queue``: a process retrying the console; none since 634f4cd). Printed: a row per
round, then each window's holds per minute over all rounds. A stopped console's own effect is the
stopped windows' rate above the baseline's; the stop's first 10 s (Zenoh's lease, while the links
to the console are still open) and the rest are counted apart (docs/safety.md, "Peers that stop
reading"; tests/test_up_stalled_console.py).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
from _stalled import LEASE_S, AcceptWatch, holds_between

from bridge.session import free_tcp_port


def _server_of(up_pid: int) -> int | None:
    """The pid of the `xneck server` child of ``up_pid`` (its kind read as the console reads it)."""
    from server.child_processes import _kind_of

    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                argv = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
                if ppid == up_pid and _kind_of(argv) == "server":
                    return int(entry.name)
    return None


def _wait_for(what: str, ok: Callable[[], bool], up: subprocess.Popen, log: Path, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not ok():
        if up.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"xneck up: {what} not seen in {timeout_s:.0f} s:\n{log.read_text(errors='replace')[-2000:]}")
        time.sleep(0.3)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--baseline-s", type=float, default=12.0, help="running window before each stop (s)")
    ap.add_argument("--stop-s", type=float, default=24.0, help="how long the console stays stopped (s)")
    args = ap.parse_args()
    if args.rounds < 1 or args.baseline_s <= 0 or args.stop_s <= LEASE_S:
        ap.error(f"--rounds ≥ 1, --baseline-s > 0 and --stop-s > {LEASE_S:g} (the lease) are needed")
    with tempfile.TemporaryDirectory(prefix="xneck-stalled-") as tmp:
        hub_port = free_tcp_port()
        up_log, bridge_log = Path(tmp) / "up.log", Path(tmp) / "d" / "logs" / "bridge.log"
        with open(up_log, "wb") as out:
            up = subprocess.Popen([sys.executable, "-m", "server.cli", "up", "--port", str(free_tcp_port()),
                                   "--hub", f"tcp/127.0.0.1:{hub_port}", "--data-dir", str(Path(tmp) / "d"),
                                   "--viser-port", str(free_tcp_port())],
                                  stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        try:
            _wait_for("the bridge's bumpless ramp", lambda: bridge_log.exists()
                      and "bumpless ramp done" in bridge_log.read_text(errors="replace"), up, up_log, 180)
            time.sleep(5.0)  # past the start-up
            server = _server_of(up.pid)
            if server is None:
                raise SystemExit("xneck up has no server child")
            print(f"xneck up {up.pid}, console {server}, hub port {hub_port}; {args.rounds} rounds of "
                  f"{args.baseline_s:g} s running, {args.stop_s:g} s stopped", flush=True)
            print("round | holds running | holds stopped, first 10 s | holds stopped, after | connections to the stopped console")
            totals = [0, 0, 0, 0]
            for k in range(args.rounds):
                t0 = time.time()
                time.sleep(args.baseline_s)
                with AcceptWatch(hub_port) as watch:
                    t1 = time.time()
                    os.kill(server, signal.SIGSTOP)
                    try:
                        time.sleep(args.stop_s)
                    finally:
                        os.kill(server, signal.SIGCONT)
                        t2 = time.time()
                row = [len(holds_between(bridge_log, t0, t1)), len(holds_between(bridge_log, t1, t1 + LEASE_S)),
                       len(holds_between(bridge_log, t1 + LEASE_S, t2)), watch.connections]
                totals = [a + b for a, b in zip(totals, row, strict=True)]
                print(f"{k + 1} | {row[0]} in {t1 - t0:.1f} s | {row[1]} | {row[2]} in {t2 - t1 - LEASE_S:.1f} s | {row[3]}",
                      flush=True)
                time.sleep(8.0)  # the console's links come back
            minutes = [args.rounds * s / 60 for s in (args.baseline_s, LEASE_S, args.stop_s - LEASE_S)]
            print(f"holds per minute: running {totals[0] / minutes[0]:.1f}, stopped first 10 s {totals[1] / minutes[1]:.1f}, "
                  f"stopped after {totals[2] / minutes[2]:.1f}; connections to the stopped console: {totals[3]}")
        finally:
            if up.poll() is None:
                up.send_signal(signal.SIGTERM)  # the supervisor stops its children in the safe order
            try:
                up.wait(40)
            except subprocess.TimeoutExpired:
                os.killpg(up.pid, signal.SIGKILL)
                up.wait(10)


if __name__ == "__main__":
    main()
