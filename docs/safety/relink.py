"""How long a process that connects to a peer not yet listening stays unlinked once the peer
listens: Zenoh's default connect back-off against xneck's (``bridge.session.CONNECT_RETRY_MS``).

    .venv/bin/python docs/safety/relink.py              # about 2 min
    .venv/bin/python docs/safety/relink.py --trials 3

The case of docs/safety.md rule 4: ``xneck estop engage --hold`` (or a controller) connects to the
bridge's endpoint before the bridge listens; the bridge latches, and obeys, only once the link is up.
Each trial opens a subscriber session connecting to a free loopback port, waits ``delay`` s, then
opens the listening session there and publishes every 10 ms: the figure is the time from the
listener's open to the first message received (s), over delays spread across the back-off's cycle.
"""

from __future__ import annotations

import argparse
import json
import statistics
import threading
import time

import zenoh

from bridge.session import CONNECT_RETRY_MS, free_tcp_port, zenoh_config

DELAYS_S = (0.3, 0.9, 1.6, 2.4, 3.3, 4.7, 6.1)
GIVE_UP_S = 10.0


def first_message_s(delay_s: float, xneck_retry: bool) -> float:
    """s from the listener's open to the connecting session's first message (GIVE_UP_S if none)."""
    port = free_tcp_port()
    conf = zenoh_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"], credentials=None, tls=None)
    if not xneck_retry:  # Zenoh's own default
        conf.insert_json5("connect/retry", json.dumps(
            {"period_init_ms": 1000, "period_max_ms": 4000, "period_increase_factor": 2}))
    got = threading.Event()
    arrived: list[float] = []

    def heard(_sample: zenoh.Sample) -> None:
        if not got.is_set():
            arrived.append(time.monotonic())
            got.set()

    with zenoh.open(conf) as connecting:
        connecting.declare_subscriber("xneck-relink/probe", heard)
        time.sleep(delay_s)
        listen = zenoh_config(listen=[f"tcp/127.0.0.1:{port}"], connect=[], credentials=None, tls=None)
        t0 = time.monotonic()
        with zenoh.open(listen) as listening:
            pub = listening.declare_publisher("xneck-relink/probe")
            while not got.is_set() and time.monotonic() - t0 < GIVE_UP_S:
                pub.put(b"x")
                got.wait(0.01)
    return arrived[0] - t0 if arrived else GIVE_UP_S


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--trials", type=int, default=2, help="trials per delay (default 2)")
    args = ap.parse_args()
    if args.trials < 1:
        ap.error("--trials must be at least 1")
    print(f"connect back-off: xneck {CONNECT_RETRY_MS[0]}-{CONNECT_RETRY_MS[1]} ms, Zenoh's default 1000-4000 ms")
    print("delays before the listener opens (s):", ", ".join(f"{d:g}" for d in DELAYS_S))
    for label, xneck in (("zenoh default", False), ("xneck", True)):
        times = [first_message_s(d, xneck) for d in DELAYS_S for _ in range(args.trials)]
        print(f"{label:>13}: unlinked after the listener opened: median {statistics.median(times):.2f} s, "
              f"max {max(times):.2f} s over {len(times)} trials", flush=True)


if __name__ == "__main__":
    main()
