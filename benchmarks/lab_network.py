"""What network the PC↔BeagleBone link needs: the control loop across a link with delay, jitter and stalls.

    .venv/bin/python benchmarks/lab_network.py [--seconds 24] [--delays-ms 0,0.5,1,2,4,8,16,32]
            [--jitter-ms 0.5,1,2 --jitter-base-ms 1] [--stall-ms 200 --stall-rate 0.2] [--no-direct]

The distributed set-up (docs/bridge.md, deployment) in real processes on this machine: the bridge
(``xneck bridge --driver twin``, real time, 500 Hz) listens on loopback TCP as the board's listens
on the lab network; the controller (``xneck controller --law 2`` following a trajectory, as
``benchmarks/controller_latency.py`` runs it) connects to it as ``xneck up --no-bridge --bridge-at``'s
does (``--no-autoconnect``, listening on a Unix socket of its own), but through a user-space link
(``benchmarks/_delay_link.py``: this kernel has no netem) that holds every byte a one-way delay,
optionally jittered, optionally stalled. The bridge and the controller get what ``xneck up`` gives
them (SCHED_FIFO on the last CPU); the link runs in a process of its own at SCHED_FIFO 45 on the
other CPUs (it stands for wires and radios, not for a program competing with the loop).

Each case prints, over the trajectory:
  - the bridge's holds (its states' ``drive`` turning to "hold", read from the bytes at the
    bridge's end of the link, up to the controller's last command: the hold after its exit is not
    the link's), its ticks in hold, and the commands it refused as answering a state too old
    (its ``Health.rejected["command_stale_state"]``);
  - the state→command round trip as the bridge's side sees it: from a state's bytes leaving the
    bridge to the bytes of the command answering it reaching the bridge (matched by ``stamp_s``
    in the bus's JSON, by ``_delay_link.BusTap``), p50/p99/max from 1 s after the first answer (the
    controller's start is not the link's), and the share of states answered;
  - the controller's deadline misses (its own: arrival → put over 2 ms; the link is not in it);
  - the tracking error |e| = |α^d − α̂| (degrees, every joint, from the controller's statuses
    while the trajectory runs), mean and max, and their ratio to the 0 ms case of this run.
First, the link's own cost: a ping-pong of 200-byte messages to an echo server, direct and through
the link at 0 ms (interleaved): what the relay adds to each pass (the baseline of every figure).
``--no-direct`` skips the case without the link (the loop as on one machine, for reference: its
holds are the bridge's ``Health`` count less the one its controller's exit leaves); the 0 ms case
runs again last, to show how far two runs of one case differ on the machine as it is. The
campaign's outcome is the controller's (``xneck/campaign/events``): a link that makes its law
re-start too often aborts it (``controller/service.py``, ``RESTARTS_WINDOW_S``).

Not modelled: the board's slower CPU (the bridge's tick is the x86 one here), the bridge and the
controller sharing one CPU here (two machines on the robot), TCP's own reaction to loss (a stall
stands for a retransmission; no congestion window, no reordering below TCP) and bandwidth (the
path carries about 0.2 MB/s each way at 500 Hz; the link forwards whatever one ``recv`` returns).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

import _repo  # noqa: E402, F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)

from bridge import bus  # noqa: E402
from bridge.session import free_tcp_port, open_session  # noqa: E402
from controller.trajectory import Trajectory  # noqa: E402
from server.child_processes import ENV_PARENT, cpu_split, isolate  # noqa: E402

PY = [sys.executable, "-m", "server.cli"]
LINK_PRIORITY = 45  # SCHED_FIFO: above everything but the loop's processes (50/49), which it never shares a CPU with
BRIDGE = "labnet-bridge"
CONTROLLER = "labnet-controller"
STOP_S = 10.0  # SIGTERM, then SIGKILL after this long
#: s after the first answered state before round trips count: the controller's first answer waits for
#: its start (135 ms once at 0 ms, 2026-11-30), which is no figure of the link
SETTLE_S = 1.0


@dataclass(frozen=True)
class Case:
    name: str
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    stall_ms: float = 0.0
    stall_rate: float = 0.0
    link: bool = True

    def link_args(self) -> list[str]:
        return ["--delay-ms", str(self.delay_ms), "--jitter-ms", str(self.jitter_ms), "--stall-ms", str(self.stall_ms),
                "--stall-rate", str(self.stall_rate)]


def _env() -> dict[str, str]:
    # this tree first, whatever the venv's editable install points at; the endpoints on each command line only
    drop = ("XNECK_ZENOH_LISTEN", "XNECK_ZENOH_CONNECT", "XNECK_ZENOH_CREDENTIALS", "XNECK_ZENOH_TLS")
    # ENV_PARENT: each child gets SIGTERM when this process dies, however it dies (a SIGKILL too)
    return {k: v for k, v in os.environ.items() if k not in drop} | {
        "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1", ENV_PARENT: str(os.getpid())}


def _start(argv: list[str], log: Path) -> subprocess.Popen:
    with open(log, "wb") as f:
        return subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=REPO,
                                env=_env(), start_new_session=True)


def _stop(procs: list[subprocess.Popen]) -> None:
    """SIGTERM to each process group, newest first; SIGKILL to any left after :data:`STOP_S`."""
    for p in reversed(procs):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGTERM)
    deadline = time.monotonic() + STOP_S
    for p in reversed(procs):
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):  # slow to exit: the others still stopped
                p.wait(5)


def _link_argv(listen_port: int, to_port: int, case: Case, record: Path | None = None) -> list[str]:
    other = ",".join(str(c) for c in sorted(cpu_split()[1]))
    return [sys.executable, str(HERE / "_delay_link.py"), "--listen", f"127.0.0.1:{listen_port}",
            "--to", f"127.0.0.1:{to_port}", *case.link_args(), "--fifo", str(LINK_PRIORITY), "--cpus", other,
            *(["--record", str(record)] if record else [])]


def _wait_listening(port: int, proc: subprocess.Popen, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return
        time.sleep(0.05)
    raise RuntimeError(f"nothing listens on 127.0.0.1:{port} (process exit {proc.poll()})")


def link_baseline(tmp: Path, pings: int) -> dict[str, float]:
    """The link's own added latency at 0 ms (module docstring)."""
    server = socket.create_server(("127.0.0.1", 0))
    echo_port = server.getsockname()[1]

    def serve() -> None:
        with contextlib.suppress(OSError):
            while True:
                conn, _ = server.accept()
                threading.Thread(target=echo, args=(conn,), daemon=True).start()

    def echo(conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError):
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            while data := conn.recv(4096):
                conn.sendall(data)

    threading.Thread(target=serve, daemon=True).start()
    port = free_tcp_port()
    link = _start(_link_argv(port, echo_port, Case("0 ms")), tmp / "baseline-link.log")
    rtt: dict[str, list[float]] = {"direct": [], "link": []}
    try:
        _wait_listening(port, link)
        socks = {"direct": socket.create_connection(("127.0.0.1", echo_port)),
                 "link": socket.create_connection(("127.0.0.1", port))}
        msg = b"x" * 200
        for s in socks.values():
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for k in range(pings + 50):
            for name, s in socks.items():
                t0 = time.perf_counter_ns()
                s.sendall(msg)
                got = 0
                while got < len(msg):
                    got += len(s.recv(4096))
                if k >= 50:  # warm-up
                    rtt[name].append((time.perf_counter_ns() - t0) * 1e-6)
                time.sleep(0.001)  # at about the loop's rate, not back to back
        for s in socks.values():
            s.close()
    finally:
        _stop([link])
        server.close()
    d, lk = np.array(rtt["direct"]), np.array(rtt["link"])
    out = {"direct_p50_ms": float(np.median(d)), "direct_p99_ms": float(np.percentile(d, 99)),
           "link_p50_ms": float(np.median(lk)), "link_p99_ms": float(np.percentile(lk, 99)),
           "added_one_way_p50_ms": float(np.median(lk) - np.median(d)) / 2,
           "added_one_way_p99_ms": float(np.percentile(lk, 99) - np.percentile(d, 99)) / 2}
    print(f"the link's own cost ({pings} ping-pongs of 200 bytes each way, interleaved, one every ~1 ms): round trip "
          f"direct median {out['direct_p50_ms']:.3f} ms / p99 {out['direct_p99_ms']:.3f} ms, through the link at 0 ms "
          f"median {out['link_p50_ms']:.3f} / p99 {out['link_p99_ms']:.3f} ms: the link adds "
          f"{1e3 * out['added_one_way_p50_ms']:.0f} µs (median) / {1e3 * out['added_one_way_p99_ms']:.0f} µs (p99) "
          "per pass (one way)", flush=True)
    return out


def trajectory_file(seconds: float, tmp: Path) -> tuple[Path, float]:
    """controller_latency.py's bench trajectory, ``seconds // 12`` repetitions (at least one)."""
    waypoints = [[0, 0, 0], [40, 30, 20], [0, 0, 0], [-30, -20, -40], [0, 0, 0]]
    reps = max(1, int(seconds // 12))
    traj = Trajectory.from_degrees(waypoints * reps + [[0, 0, 0]], durations_s=2.0, dwell_s=1.0, name="labnet")
    path = tmp / "traj.json"
    path.write_text(traj.to_json())
    return path, traj.duration_s


def run_case(case: Case, traj: Path, duration_s: float, tmp: Path) -> dict:
    """One run (module docstring); every process it starts is stopped before it returns or raises."""
    tag = case.name.replace(" ", "_").replace("/", "-")
    bridge_port = free_tcp_port()
    bridge_at = f"tcp/127.0.0.1:{bridge_port}"
    controller_at = f"unixsock-stream/{tmp / f'{tag}-controller.sock'}"
    record = tmp / f"{tag}-link.json"
    health: list[bus.Health] = []
    e_deg: list[list[float]] = []
    misses = [0, 0]  # deadline misses, overruns (the most any status said: they start again at 0 after a campaign)
    statuses = [0]
    events: list[bus.CampaignEvent] = []
    lock = threading.Lock()

    def on_health(sample) -> None:
        with lock:
            health.append(bus.decode(bus.Health, sample.payload.to_bytes()))

    def on_status(sample) -> None:
        s = bus.decode(bus.ControllerStatus, sample.payload.to_bytes())
        with lock:
            statuses[0] += 1
            misses[0], misses[1] = max(misses[0], s.deadline_misses), max(misses[1], s.overruns)
            if s.campaign_id and not s.holding:
                e_deg.append(s.e_rad)

    def on_event(sample) -> None:
        with lock:
            events.append(bus.decode(bus.CampaignEvent, sample.payload.to_bytes()))

    procs: list[subprocess.Popen] = []
    try:
        bridge = _start([*PY, "bridge", "--driver", "twin", "--seed", "1", "--listen", bridge_at, "--no-autoconnect",
                         "--instance", BRIDGE], tmp / f"{tag}-bridge.log")
        procs.append(bridge)
        isolate(bridge.pid, "bridge")
        # The observer links to both ends directly (not through the link) and subscribes only to
        # the bridge's health and the controller's statuses: no state or command goes its way.
        with open_session(listen=[], connect=[bridge_at, controller_at], autoconnect=False) as s:
            subs = [s.declare_subscriber(bus.health_key("bridge", BRIDGE), on_health),
                    s.declare_subscriber(bus.CONTROLLER_STATUS, on_status),
                    s.declare_subscriber(bus.CAMPAIGN_EVENTS, on_event)]
            deadline = time.monotonic() + 120
            while not health:  # the bridge is up (its twin compiled or loaded)
                if bridge.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the bridge did not come up: see {tmp / f'{tag}-bridge.log'}")
                time.sleep(0.1)
            connect = bridge_at
            if case.link:
                link_port = free_tcp_port()
                link = _start(_link_argv(link_port, bridge_port, case, record), tmp / f"{tag}-link.log")
                procs.append(link)
                _wait_listening(link_port, link)
                connect = f"tcp/127.0.0.1:{link_port}"
            ctl = _start([*PY, "controller", "--law", "2", "--trajectory", str(traj), "--listen", controller_at,
                          "--connect", connect, "--no-autoconnect", "--instance", CONTROLLER], tmp / f"{tag}-controller.log")
            procs.append(ctl)
            isolate(ctl.pid, "controller")
            try:
                code = ctl.wait(duration_s + 30)  # a campaign slowed by holds aborts within 10 s
            except subprocess.TimeoutExpired:
                code = None
            time.sleep(1.2)  # the bridge's health after the controller's end
            for sub in subs:
                sub.undeclare()
    finally:
        _stop(procs)
    with lock:
        last = health[-1] if health else None
        e = np.degrees(np.abs(np.array(e_deg))) if e_deg else np.zeros((0, 3))
        ended = next((ev for ev in reversed(events) if ev.event in ("finished", "aborted", "interrupted")), None)
        progress = max((ev.progress for ev in events), default=0.0)
    said = [ln for ln in (tmp / f"{tag}-controller.log").read_text(errors="replace").splitlines()
            if "abort" in ln.lower() or "error" in ln.lower()]
    out: dict = {"case": case.name, "controller_exit": code, "controller_said": " | ".join(said[-3:]),
                 "outcome": ended.event if ended else "no end", "outcome_message": ended.message if ended else "",
                 "progress": progress, "statuses": statuses[0], "status_ticks": len(e),
                 "deadline_misses": misses[0], "overruns": misses[1],
                 "e_mean_deg": float(e.mean()) if e.size else float("nan"),
                 "e_max_deg": float(e.max()) if e.size else float("nan"),
                 "bridge_holds_total": last.received.get("holds", -1) if last else -1,
                 "stale_commands": last.rejected.get("command_stale_state", -1) if last else -1,
                 "bridge_overruns": last.received.get("overruns", -1) if last else -1}
    if case.link:
        r = json.loads(record.read_text())
        tap, until = r["tap"], r["tap"]["until_last_command"]
        rtt = np.array(tap["rtt_ms"])[np.array(tap["rtt_at_s"]) >= SETTLE_S]
        out |= {"holds": until["holds"], "hold_ticks": until["hold_states"], "states": until["states"],
                "answered": len(tap["rtt_ms"]) / max(until["states"], 1),  # every answer, the first second's too
                "rtt_p50_ms": float(np.median(rtt)) if rtt.size else float("nan"),
                "rtt_p99_ms": float(np.percentile(rtt, 99)) if rtt.size else float("nan"),
                "rtt_max_ms": float(rtt.max()) if rtt.size else float("nan"),
                "link": r["link"], "drives": tap["drives"]}
        if out["outcome"] == "no end" and not tap["drives"].get("active"):
            out["outcome"] = "drives never enabled (every command refused)"
    else:  # no tap: the bridge's own count, less the hold its controller's exit leaves
        out |= {"holds": max(out["bridge_holds_total"] - 1, 0), "hold_ticks": None}
    return out


def _outcome(r: dict) -> str:
    return f"{r['outcome']} at {100 * r['progress']:.0f} %" if r["outcome"] in ("aborted", "no end") else r["outcome"]


def _f(x: float | None, fmt: str = ".2f") -> str:
    return "–" if x is None or x != x else format(x, fmt)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--seconds", type=float, default=24.0, help="trajectory length per case, in repetitions of 12 s")
    ap.add_argument("--delays-ms", default="0,0.5,1,2,4,8,16,32", help="one-way delays of the constant cases (0 first: the baseline)")
    ap.add_argument("--jitter-ms", default="0.5,1,2", help="jittered cases: means of the exponential extra delay, "
                    "comma-separated (empty or 0: none)")
    ap.add_argument("--jitter-base-ms", type=float, default=1.0, help="jittered and stall cases: their constant delay")
    ap.add_argument("--stall-ms", type=float, default=200.0, help="stall case: each stall's length (0: no stall case)")
    ap.add_argument("--stall-rate", type=float, default=0.2, help="stall case: stalls per second and direction")
    ap.add_argument("--no-direct", action="store_true", help="skip the case without the link")
    ap.add_argument("--pings", type=int, default=3000, help="ping-pongs of the link's baseline")
    ap.add_argument("--json", type=Path, default=None, help="also write every figure here")
    ap.add_argument("--keep", type=Path, default=None, help="keep the processes' logs and the links' records in this folder")
    args = ap.parse_args()
    # SIGTERM (and a hangup) end the run as Ctrl-C does: through the finally clauses that stop every process
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda signum, _frame: sys.exit(128 + signum))
    try:
        delays = [float(d) for d in args.delays_ms.split(",") if d.strip()]
    except ValueError:
        ap.error(f"--delays-ms {args.delays_ms!r}: comma-separated numbers")
    if 0.0 not in delays:
        delays.insert(0, 0.0)  # the baseline of the ratios
    delays = [0.0] + [d for d in delays if d != 0.0]
    cases = [] if args.no_direct else [Case("no link", link=False)]
    cases += [Case(f"{d:g} ms", delay_ms=d) for d in delays]
    try:
        jitters = [float(j) for j in args.jitter_ms.split(",") if j.strip() and float(j) > 0]
    except ValueError:
        ap.error(f"--jitter-ms {args.jitter_ms!r}: comma-separated numbers")
    cases += [Case(f"{args.jitter_base_ms:g} ms + exp({j:g} ms) jitter", delay_ms=args.jitter_base_ms, jitter_ms=j)
              for j in jitters]
    if args.stall_ms > 0 and args.stall_rate > 0:
        cases.append(Case(f"{args.jitter_base_ms:g} ms + {args.stall_ms:g} ms stalls at {args.stall_rate:g}/s",
                          delay_ms=args.jitter_base_ms, stall_ms=args.stall_ms, stall_rate=args.stall_rate))
    cases.append(Case("0 ms, again"))  # how far two runs of the same case differ on this machine now
    print(f"lab network, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}, load {' '.join(f'{x:.2f}' for x in os.getloadavg())}, "
          f"{len(cases)} cases; the loop on CPU {sorted(cpu_split()[0])}, the link on {sorted(cpu_split()[1])}", flush=True)
    results: list[dict] = []
    with contextlib.ExitStack() as stack:
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
        tmp = args.keep or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="xneck-labnet-")))
        baseline = link_baseline(tmp, args.pings)
        traj, duration = trajectory_file(args.seconds, tmp)
        print(f"each case: `xneck controller --law 2` on a {duration:.0f} s trajectory through the link to "
              "`xneck bridge --driver twin`", flush=True)
        for case in cases:
            t0 = time.monotonic()
            r = run_case(case, traj, duration, tmp)
            r["load"] = os.getloadavg()[0]
            results.append(r)
            print(f"  {case.name}: {time.monotonic() - t0:.0f} s, load {r['load']:.2f}, holds {r['holds']}, "
                  f"round trip p50 {_f(r.get('rtt_p50_ms'), '.3f')} ms, e mean {_f(r['e_mean_deg'], '.3f')}°"
                  + ("" if r["outcome"] == "finished" else f"; campaign {_outcome(r)}: {r['outcome_message']}"), flush=True)
    base = next((r for r in results if r["case"] == "0 ms"), None)
    print("\n| one-way link | link held, up p50/p99 (ms) | round trip at the bridge p50 / p99 / max (ms) "
          "| answered | holds | ticks in hold | stale commands | deadline misses | e mean / max (°) "
          "| e mean / max vs 0 ms | campaign | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        link = r.get("link", {}).get("up")
        held = f"{_f(link['held_p50_ms'], '.3f')} / {_f(link['held_p99_ms'], '.3f')}" if link else "–"
        rtt = (f"{_f(r['rtt_p50_ms'], '.3f')} / {_f(r['rtt_p99_ms'], '.3f')} / {_f(r['rtt_max_ms'], '.1f')}"
               if "rtt_p50_ms" in r else "–")
        ratio = (f"{r['e_mean_deg'] / base['e_mean_deg']:.2f} / {r['e_max_deg'] / base['e_max_deg']:.2f}"
                 if base and base["e_mean_deg"] > 0 else "–")
        answered = f"{100 * r['answered']:.1f} %" if "answered" in r else "–"
        outcome = _outcome(r)
        print(f"| {r['case']} | {held} | {rtt} | {answered} | {r['holds']} | {_f(r['hold_ticks'], 'd')} "
              f"| {r['stale_commands']} | {r['deadline_misses']} | {r['e_mean_deg']:.3f} / {r['e_max_deg']:.3f} "
              f"| {ratio} | {outcome} | {r['load']:.2f} |")
    if base and "rtt_p50_ms" in base:
        print("\nround trip over the 0 ms case (p50): " + ", ".join(
            f"{r['case']} +{r['rtt_p50_ms'] - base['rtt_p50_ms']:.2f} ms" for r in results
            if "rtt_p50_ms" in r and r is not base))
    print(f"ended {time.strftime('%Y-%m-%d %H:%M:%S %Z')}, load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json:
        args.json.write_text(json.dumps({"baseline": baseline, "cases": results}, indent=1))


if __name__ == "__main__":
    main()
