"""Does a message that must not be dropped, sent to a stopped peer, hold back the control path?

    .venv/bin/python benchmarks/stalled_block.py [--runs 2] [--transport unix,tcp] [--stop-s 12]

This process publishes a controller's two kinds of ``data``-priority messages on a session that
listens (as ``xneck up``'s controller does, on a Unix socket or loopback TCP): statuses at 500 Hz
(congestion control DROP, from the thread that stands for the tick) and campaign events every
0.5 s (BLOCK, ``bridge.session.RELIABLE_KEYS``, from another thread, as the controller's
housekeeping thread publishes them). A listener of every key (a console) in a process of its own
is stopped (SIGSTOP) for ``--stop-s`` after 2 s. Zenoh closes a transport on which a BLOCK message
waited ``transport/link/tx/queue/congestion_control/block/wait_before_close`` (5 s by default),
and all messages of one priority share its queue (eclipse-zenoh/zenoh#2584): does a status put()
wait behind an event's?

Printed per run: the status put()'s median, p99 and longest time and how many took over 5 ms (a
tick's budget is 2 ms), and the longest event put() with when it started (s after the stop) if it
waited over 100 ms.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import numpy as np

from bridge import bus
from bridge.session import free_tcp_port, open_session, publisher

LISTENER = """
import sys, time
sys.path.insert(0, {root!r})
from bridge.session import open_session
session = open_session(listen=[], connect=[{endpoint!r}])
session.declare_subscriber("xneck/**", lambda sample: None)
print("ready", flush=True)
time.sleep({life})
"""
STATUS = bus.ControllerStatus(seq=1, stamp_s=0.0, law="law2", tick_s=0.002, compute_s=1e-4, overruns=0,
                              deadline_misses=0, saturated=[False] * 4, alpha_hat_rad=[0.0] * 3,
                              alpha_d_rad=[0.0] * 3, e_rad=[0.0] * 3, holding=False, campaign_id="c", ticks=1)
EVENT = bus.CampaignEvent(seq=1, stamp_s=0.0, campaign_id="c", kind="control", event="progress", progress=0.5,
                          message="", ticks=1, overruns=0, deadline_misses=0)
STOP_AT_S = 2.0


def run_once(transport: str, stop_s: float, folder: Path) -> dict[str, float]:
    """One run; the listener process is stopped on return, within bounded time."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}" if transport == "tcp" else \
        f"unixsock-stream/{folder / f'control-{time.monotonic_ns()}.sock'}"
    root = str(Path(__file__).resolve().parents[1])
    with open_session(listen=[endpoint], connect=[]) as session:
        status, events = publisher(session, bus.CONTROLLER_STATUS), publisher(session, bus.CAMPAIGN_EVENTS)
        listener = subprocess.Popen([sys.executable, "-c", LISTENER.format(root=root, endpoint=endpoint,
                                                                           life=stop_s + 30)],
                                    stdout=subprocess.PIPE, text=True)
        try:
            assert listener.stdout is not None and listener.stdout.readline().strip() == "ready"
            time.sleep(1.0)  # the listener's subscription reaches this session
            stop = threading.Event()
            event_puts: list[tuple[float, float]] = []
            t_start = time.perf_counter()

            def publish_events() -> None:
                while not stop.is_set():
                    t0 = time.perf_counter()
                    events.put(EVENT)
                    event_puts.append((t0 - t_start, time.perf_counter() - t0))
                    stop.wait(0.5)

            thread = threading.Thread(target=publish_events, daemon=True)
            thread.start()
            puts, t_next, stopped = [], t_start, False
            while t_next < t_start + STOP_AT_S + stop_s:
                if not stopped and t_next >= t_start + STOP_AT_S:
                    listener.send_signal(signal.SIGSTOP)
                    stopped = True
                t0 = time.perf_counter()
                status.put(STATUS)
                puts.append(time.perf_counter() - t0)
                t_next += 0.002
                time.sleep(max(0.0, t_next - time.perf_counter()))
            stop.set()
            thread.join(10)
        finally:
            listener.send_signal(signal.SIGCONT)
            listener.kill()
            listener.wait(10)
    ms = np.asarray(puts) * 1e3
    at, longest = max(event_puts, key=lambda e: e[1])
    return {"median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max()),
            "over_5ms": int((ms > 5).sum()), "event_max_ms": longest * 1e3, "event_at_s": at - STOP_AT_S}


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=2, help="runs per transport (default 2)")
    ap.add_argument("--transport", default="unix,tcp", help="of unix and tcp (default unix,tcp)")
    ap.add_argument("--stop-s", type=float, default=12.0,
                    help="how long the listener stays stopped (s; default 12: past Zenoh's 10 s lease)")
    args = ap.parse_args()
    transports = [t for t in args.transport.split(",") if t]
    if not transports or any(t not in ("unix", "tcp") for t in transports):
        ap.error(f"--transport {args.transport!r}: give unix, tcp or both")
    print(f"{time.strftime('%Y-%m-%d %H:%M')}; load {Path('/proc/loadavg').read_text().split()[0]}; "
          f"listener stopped {args.stop_s:.0f} s from {STOP_AT_S:.0f} s")
    print("| transport | run | status put median (ms) | p99 | longest | over 5 ms | longest event put (ms) | at (s after the stop) |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="xneck-bench-block-") as tmp:
        for transport in transports:
            for k in range(args.runs):
                r = run_once(transport, args.stop_s, Path(tmp))
                at = f"{r['event_at_s']:.1f}" if r["event_max_ms"] > 100 else "(none waited)"
                print(f"| {transport} | {k + 1} | {r['median_ms']:.3f} | {r['p99_ms']:.3f} | {r['max_ms']:.1f} | "
                      f"{r['over_5ms']} | {r['event_max_ms']:.0f} | {at} |", flush=True)


if __name__ == "__main__":
    main()
