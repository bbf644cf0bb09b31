"""Does the console slow the control loop? Issue 6's benchmark.

Runs the real console (``xneck server --pace realtime``, a subprocess) and two real-time control
campaigns (§7 control test, 500 Hz twin and controller processes on the console's hub): one with
no live client, one with 20 WebSocket clients reading ``/api/live`` (plus the viser view's scene
thread, always on). During each, status reads ``GET /api/campaigns/<id>`` are issued at 50
requests per second. Prints, from the archives: the controller's tick period p99 and deadline
misses with 20 clients against none (and their ratio), the controller's own state-to-command
latency of each campaign (its final ``ControllerTiming``), and the REST p99 latency of the status
reads. Issue 21's target: tick p99 with 20 clients within 5 % of none, 0 deadline misses in both.

``--idle S``: instead, the idle stack's CPU (``xneck up`` with its twin bridge and controller
service, no campaign, no client) over S seconds, per process in % of one core (target: below 40 %
in total), and the bridge's watchdog holds and the controller's late ticks meanwhile (target 0
holds; ``--idle 600`` is issue 21's 10-minute soak). Ticks and holds are the bridge's own health
counters (1 Hz), so the figure is the stack's alone; ``--observe-streams`` adds this script's
subscriptions to every state and command (the reasons of each hold, the longest silence of the
commands), which the bridge and the controller then serve too. ``--campaigns`` runs §7 control
campaigns back to back through REST during the window (the soak "running campaigns"; holds are
counted the same way).

Run: ``.venv/bin/python benchmarks/console_load.py`` (about 1 minute; ``--clients N`` to change 20),
``.venv/bin/python benchmarks/console_load.py --idle 60``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

import _repo  # noqa: E402, F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import httpx  # noqa: E402
import numpy as np  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from bridge import bus  # noqa: E402
from bridge.archive_read import read_campaign  # noqa: E402
from bridge.session import free_tcp_port, open_session  # noqa: E402

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
    if status not in ("finished", "degraded"):  # degraded: finished, with its quality's reasons (printed)
        raise RuntimeError(f"campaign {cid}: {status}: {client.get(f'/api/campaigns/{cid}').json()['message']}")
    c = read_campaign(data / "campaigns" / f"{cid}.mcap")
    st = [m for _, m in c.messages(bus.CONTROLLER_STATUS) if not m.holding]
    ticks = np.array([m.tick_s for m in st[1:]])
    timing = [m for _, m in c.messages(bus.CONTROLLER_TIMING) if m.campaign_id == cid]
    final = timing[-1] if timing else None  # the controller's own figures of the whole campaign
    return {"tick_p99_ms": float(np.percentile(ticks, 99) * 1e3), "tick_median_ms": float(np.median(ticks) * 1e3),
            "deadline_misses": float(final.campaign_deadline_misses if final else max(m.deadline_misses for m in st)),
            "latency_p99_ms": float(final.campaign_latency_p99_ms) if final else float("nan"),
            "rest_p99_ms": float(np.percentile(latencies, 99) * 1e3),
            "rest_reads": float(len(latencies)), "outcome": client.get(f"/api/campaigns/{cid}").json()["message"], "frames_per_client": float(np.mean(counts)) if counts else 0.0}


def _cpu_ticks(pid: int) -> int:
    """utime + stime of a process, in clock ticks (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])
    except (OSError, IndexError, ValueError):
        return 0


def campaigns_loop(base: str, token: str, stop: threading.Event, outcomes: list[str]) -> None:
    """§7 control campaigns (law 2, real time) back to back through REST until ``stop``; each
    outcome (status and message) appended to ``outcomes``."""
    auth = {"Authorization": f"Bearer {token}"}
    with httpx.Client(base_url=base, timeout=10) as client:
        while not stop.is_set():
            r = client.post("/api/campaigns", json={"kind": "control", "law": 2, "pace": "realtime"}, headers=auth)
            if r.status_code >= 400:
                outcomes.append(f"refused {r.status_code}: {r.text[:200]}")
                stop.wait(2.0)
                continue
            cid = r.json()["id"]
            while True:
                body = client.get(f"/api/campaigns/{cid}").json()
                if body["status"] != "running" or stop.wait(0.5):
                    break
            outcomes.append(f"{body['status']}: {body.get('message', '')}"[:300])


def idle_stack(seconds: float, observe_streams: bool = False, with_campaigns: bool = False) -> None:
    """CPU of the idle `xneck up` stack, per process (module docstring)."""
    from server.child_processes import _kind_of  # the kind of an xneck command line

    with tempfile.TemporaryDirectory(prefix="xneck-bench-") as tmp:
        port, hub = free_tcp_port(), f"tcp/127.0.0.1:{free_tcp_port()}"
        up = subprocess.Popen([sys.executable, "-m", "server.cli", "up", "--port", str(port), "--hub", hub,
                               "--data-dir", str(Path(tmp) / "d"), "--viser-port", str(free_tcp_port())],
                              stdout=open(Path(tmp) / "up.log", "wb"), stderr=subprocess.STDOUT,  # noqa: SIM115
                              start_new_session=True)
        try:
            deadline = time.monotonic() + 120
            while True:  # the controller service is the last to come up
                try:
                    kinds = {p["kind"] for p in httpx.get(f"http://127.0.0.1:{port}/api/system/processes",
                                                          timeout=2).json()["processes"]}
                    if {"bridge", "campaign-service"} <= kinds:
                        break
                except httpx.HTTPError:
                    pass
                if time.monotonic() > deadline or up.poll() is not None:
                    raise RuntimeError("xneck up did not come up:\n" + (Path(tmp) / "up.log").read_text()[-2000:])
                time.sleep(0.5)
            time.sleep(5.0)  # past start-up (compilation, first connections)
            pids = {up.pid: "up"}
            for entry in Path("/proc").iterdir():
                if entry.name.isdigit():
                    try:
                        stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                        argv = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
                    except OSError:
                        continue
                    if int(stat[1]) == up.pid:
                        pids[int(entry.name)] = _kind_of(argv) or argv[-1]
            hz = os.sysconf("SC_CLK_TCK")
            holds, timing, reasons, gaps = [0, "active"], [], {}, [0.0, 0.0]
            seqs: list[int] = []  # the states' seq over the window: the bridge's ticks, even if this observer drops some
            health: list[bus.Health] = []  # the bridge's own counters (ticks, holds) at 1 Hz

            def on_state(sample) -> None:  # entries into the bridge's watchdog hold (a force ramp each)
                msg = bus.decode(bus.MotorState, sample.payload.to_bytes())
                seqs.append(msg.seq)
                if msg.drive == "hold" and holds[1] != "hold":
                    holds[0] += 1
                    reasons[msg.hold_reason] = reasons.get(msg.hold_reason, 0) + 1
                holds[1] = msg.drive

            def on_command(_sample) -> None:  # the longest silence on the command key, as seen here
                now = time.perf_counter()
                if gaps[1]:
                    gaps[0] = max(gaps[0], now - gaps[1])
                gaps[1] = now

            def on_health(sample) -> None:
                msg = bus.decode(bus.Health, sample.payload.to_bytes())
                if msg.process == "bridge":
                    health.append(msg)

            with open_session(listen=["tcp/127.0.0.1:0"], connect=[hub]) as session:
                # A 500 Hz subscriber is a third party on the loop's keys (Zenoh copies every state and
                # command to it): it is in the bridge's and controller's CPU, so only on request.
                subs = [session.declare_subscriber(f"{bus.PREFIX}/health/bridge/*", on_health),
                        session.declare_subscriber(bus.CONTROLLER_TIMING, lambda s: timing.append(
                            bus.decode(bus.ControllerTiming, s.payload.to_bytes())))]
                if observe_streams:
                    subs += [session.declare_subscriber(bus.MOTOR_STATE, on_state),
                             session.declare_subscriber(bus.MOTOR_COMMAND, on_command)]
                time.sleep(1.5)
                before = {pid: _cpu_ticks(pid) for pid in pids}
                holds[0], gaps[0] = 0, 0.0
                seqs.clear()
                reasons.clear()
                health.clear()
                stop, outcomes = threading.Event(), []
                runner = threading.Thread(target=campaigns_loop, args=(
                    f"http://127.0.0.1:{port}", (Path(tmp) / "d" / "token").read_text().strip(), stop, outcomes))
                if with_campaigns:
                    runner.start()
                time.sleep(seconds)
                used = {pid: (_cpu_ticks(pid) - before[pid]) / hz / seconds * 100 for pid in pids}
                stop.set()
                if with_campaigns:
                    runner.join(60)
                time.sleep(1.2)  # the health beat after the window
                for sub in subs:
                    sub.undeclare()
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(up.pid, signal.SIGTERM)
            try:
                up.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(up.pid, signal.SIGKILL)
    if with_campaigns:
        print(f"control campaigns run back to back in the window: {len(outcomes)}")
        for text in sorted(set(outcomes)):
            print(f"  {outcomes.count(text)} x {text}")
    print(f"{'busy' if with_campaigns else 'idle'} `xneck up` stack over {seconds:.0f} s, CPU in % of one core ({os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f}):")
    for pid, kind in sorted(pids.items(), key=lambda x: -used[x[0]]):
        print(f"  {kind:<12s} pid {pid:<8d} {used[pid]:6.1f} %")
    total = sum(used.values())
    print(f"  {'total':<21s} {total:6.1f} %" + ("" if with_campaigns else
          f"   (target below 40 %: {'meets' if total < 40 else 'MISSES'})"))
    if len(health) < 2:
        raise RuntimeError(f"{len(health)} bridge health message(s) in the window: cannot count ticks and holds")
    # A loaded machine runs fewer ticks, and fewer ticks cost less: the figure at the rate due.
    first, last = health[0], health[-1]
    rate_hz = (last.received["ticks"] - first.received["ticks"]) / (last.uptime_s - first.uptime_s)
    print(f"bridge ticks over the window (its health counters): {rate_hz:.0f} per s (500 due); the total at 500 Hz "
          f"would be about {total * 500 / rate_hz:.1f} %")
    ticks = sum(t.window_ticks for t in timing)
    late = sum(int(np.sum(t.latency_counts[int(np.searchsorted(t.bin_edges_ms, 2.0)):])) for t in timing)
    n_holds = last.received["holds"] - first.received["holds"]
    print(f"bridge watchdog holds (its health counters): {n_holds} (target 0); controller ticks {ticks}, answered "
          f"later than 2 ms: {late}, stale states of bursts skipped: {sum(t.window_skipped for t in timing)}")
    if observe_streams:
        print(f"observed on the streams: {holds[0]} hold entries, bridge ticks {len(seqs) and seqs[-1] - seqs[0]}; "
              f"hold reasons: {reasons or '-'}; longest silence on the command key seen by this (unprioritised) "
              f"observer: {gaps[0] * 1e3:.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--clients", type=int, default=20)
    parser.add_argument("--idle", type=float, default=0.0, help="measure the idle stack's CPU over this many s")
    parser.add_argument("--observe-streams", action="store_true",
                        help="with --idle: also subscribe to every state and command (hold reasons, the longest "
                             "command silence); the stack then also serves this observer at 500 Hz")
    parser.add_argument("--campaigns", action="store_true",
                        help="with --idle: run §7 control campaigns (law 2, real time) back to back through REST "
                             "during the window (the soak's 'running campaigns' half; CPU then is not idle)")
    args = parser.parse_args()
    if args.idle > 0:
        idle_stack(args.idle, args.observe_streams, args.campaigns)
        return
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
                       ("deadline_misses", "controller deadline misses"),
                       ("latency_p99_ms", "state-to-command p99 (ms, its own)"),
                       ("rest_p99_ms", "REST status read p99 (ms)")):
        a, b = none[key], many[key]
        ratio = f"{b / a:8.2f}" if a > 0 else ("    1.00" if b == 0 else "     inf")
        print(f"{label:34s}{a:12.3f}{b:12.3f}{ratio}")
    print(f"outcomes: no client: {none['outcome']}; {args.clients} clients: {many['outcome']}")
    print(f"status reads per run: {none['rest_reads']:.0f} / {many['rest_reads']:.0f} at 50/s; "
          f"live frames per client: {many['frames_per_client']:.0f}")


if __name__ == "__main__":
    main()
