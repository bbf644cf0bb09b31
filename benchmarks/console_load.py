"""Does the console slow the control loop? Issue 6's benchmark.

Runs the real console (``xneck server --pace realtime``, a subprocess) and two real-time control
campaigns (§7 control test, 500 Hz twin and controller processes on the console's hub): one with
no live client, one with 20 WebSocket clients reading ``/api/live`` (plus the viser view's scene
thread, always on). During each, status reads ``GET /api/campaigns/<id>`` are issued at 50
requests per second. Prints, from the archives: the controller's tick period p99 and deadline
misses with 20 clients against none (and their ratio), and the REST p99 latency of the status reads.

Run: ``.venv/bin/python benchmarks/console_load.py`` (about 1 minute; ``--clients N`` to change 20).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

import httpx  # noqa: E402
import numpy as np  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from bridge import bus  # noqa: E402
from bridge.archive import read_campaign  # noqa: E402
from bridge.session import free_tcp_port  # noqa: E402

TOKEN = "bench-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def live_clients(base: str, n: int, stop: threading.Event) -> tuple[list[threading.Thread], list[int]]:
    counts = [0] * n

    def run(i: int) -> None:
        with connect(base.replace("http", "ws") + "/api/live", open_timeout=10) as ws:
            while not stop.is_set():
                try:
                    ws.recv(timeout=0.5)
                    counts[i] += 1
                except TimeoutError:
                    continue

    threads = [threading.Thread(target=run, args=(i,), daemon=True) for i in range(n)]
    for t in threads:
        t.start()
    return threads, counts


def campaign(client: httpx.Client, base: str, data: Path, n_clients: int) -> dict[str, float]:
    stop = threading.Event()
    threads, counts = live_clients(base, n_clients, stop) if n_clients else ([], [])
    time.sleep(1.0 if n_clients else 0.0)
    r = client.post("/api/campaigns", json={"kind": "control", "law": 2, "pace": "realtime"}, headers=AUTH)
    r.raise_for_status()
    cid = r.json()["id"]
    latencies = []
    period, next_t = 1 / 50, time.perf_counter()
    while True:  # 50 status reads per second until the campaign ends
        t0 = time.perf_counter()
        status = client.get(f"/api/campaigns/{cid}").json()["status"]
        latencies.append(time.perf_counter() - t0)
        if status != "running":
            break
        next_t += period
        time.sleep(max(0.0, next_t - time.perf_counter()))
    stop.set()
    for t in threads:
        t.join(2)
    if status != "finished":
        raise RuntimeError(f"campaign {cid}: {status}: {client.get(f'/api/campaigns/{cid}').json()['message']}")
    c = read_campaign(data / "campaigns" / f"{cid}.mcap")
    st = [m for _, m in c.messages(bus.CONTROLLER_STATUS) if not m.holding]
    ticks = np.array([m.tick_s for m in st[1:]])
    return {"tick_p99_ms": float(np.percentile(ticks, 99) * 1e3), "tick_median_ms": float(np.median(ticks) * 1e3),
            "deadline_misses": float(st[-1].deadline_misses), "rest_p99_ms": float(np.percentile(latencies, 99) * 1e3),
            "rest_reads": float(len(latencies)), "frames_per_client": float(np.mean(counts)) if counts else 0.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--clients", type=int, default=20)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="xneck-bench-") as tmp:
        data = Path(tmp) / "data"
        port = free_tcp_port()
        base = f"http://127.0.0.1:{port}"
        env = {**os.environ, "XNECK_TOKEN": TOKEN}
        proc = subprocess.Popen([sys.executable, "-m", "server.cli", "server", "--port", str(port), "--data-dir",
                                 str(data), "--pace", "realtime"], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, env=env, start_new_session=True)
        try:
            with httpx.Client(base_url=base, timeout=10) as client:
                deadline = time.monotonic() + 40
                while True:
                    try:
                        client.get("/api/system/health").raise_for_status()
                        break
                    except httpx.HTTPError:
                        if time.monotonic() > deadline:
                            raise
                        time.sleep(0.3)
                none = campaign(client, base, data, 0)
                many = campaign(client, base, data, args.clients)
        finally:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
    print(f"{'':34s}{'0 clients':>12s}{f'{args.clients} clients':>12s}{'ratio':>8s}")
    for key, label in (("tick_p99_ms", "controller tick p99 (ms)"), ("tick_median_ms", "controller tick median (ms)"),
                       ("deadline_misses", "controller deadline misses"), ("rest_p99_ms", "REST status read p99 (ms)")):
        a, b = none[key], many[key]
        ratio = f"{b / a:8.2f}" if a > 0 else ("    1.00" if b == 0 else "     inf")
        print(f"{label:34s}{a:12.3f}{b:12.3f}{ratio}")
    print(f"status reads per run: {none['rest_reads']:.0f} / {many['rest_reads']:.0f} at 50/s; "
          f"live frames per client: {many['frames_per_client']:.0f}")


if __name__ == "__main__":
    main()
