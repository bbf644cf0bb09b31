"""A bus peer in a process of its own (its own Zenoh runtime), for benchmarks/stalled_peers.py,
benchmarks/bus_flood.py, benchmarks/peer_churn.py and tests/test_bus_dead_peers.py: ``python benchmarks/_bus_peer.py ROLE
SECONDS LISTEN CONNECT [COUNT [no-autoconnect]]`` (the endpoints comma-separated, "" for none;
``no-autoconnect``: the session opens no link by gossip, ``bridge.session.NO_AUTOCONNECT``); every
role exits by itself after SECONDS. Credentials as every xneck process reads them (``XNECK_ZENOH_CREDENTIALS``).

Roles:
    ``listener`` subscribes to every xneck key (the console, the hub; another console, a recorder),
                 prints ``ready`` once declared and ``seen`` at its first message,
    ``publish``  publishes motor states at 500 Hz and 40 kB camera frames at 30 Hz (as the bridge),
    ``control``  subscribes to the motor states and, as the controller does, publishes a command
                 and a status at 500 Hz; prints ``ready`` at the first state and, at the end, one
                 JSON line: the number of states received, the longest gap between two (s) and
                 its time (s since the first state), the gaps' median and p99 (s), and how many
                 exceeded 10 ms (the bridge's command timeout) and 100 ms; ``stalls``: for each time
                 no state came for 0.5 s (at most 3), when (``at_s``, as ``at_s`` above), how long
                 the gap lasted (``gap_s``) and what the threads of every process of the scenario
                 were doing then (:func:`_threads_now`), so that a gap seen once on a CI machine
                 says where it came from.
    ``rogue-sessions`` a stranger on the network: opens COUNT Zenoh sessions to CONNECT at once (16
                 threads), each subscribing to every xneck key, and holds them; prints one JSON line
                 once they are open: how many, how many linked to a peer, the seconds it took.
    ``rogue-tcp``  opens COUNT plain TCP connections to CONNECT's address, sends nothing, holds them;
                 prints the same line (``linked``: connections the listener accepted).

Layouts (:data:`LAYOUTS`): ``hub``, every peer connects to the hub; ``up``, ``xneck up``'s from
2026-11-27 (server/cli/up.py): the publisher listens, the control peer connects to it, the hub
connects to both and the other listeners to the hub, on loopback TCP; ``stack``, ``xneck up``'s
since 2026-11-30: as ``up``, but the publisher and the control peer listen on Unix sockets and
open no link by gossip (``--no-autoconnect``), so the listeners link to them, over those sockets.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

try:
    import _repo  # noqa: F401  (run as a script, as the peers are: this checkout's packages, benchmarks/_repo.py)
except ModuleNotFoundError:  # loaded by its path (tests/test_bus_dead_peers.py): the suite's own checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bridge import bus
from bridge.session import open_session, publisher

PEER = [sys.executable, str(Path(__file__).resolve())]


LAYOUTS = ("hub", "up", "stack")
ANY = "tcp/127.0.0.1:0"
NO_AUTOCONNECT_ARG = "no-autoconnect"


def _publish(listen: list[str], connect: list[str], seconds: float, autoconnect: bool = True) -> None:
    with open_session(listen=listen, connect=connect, autoconnect=autoconnect) as session:
        states = publisher(session, bus.MOTOR_STATE)
        frames = publisher(session, bus.CAMERA_FRAME)
        frame = bus.CameraFrame(seq=0, stamp_s=0.0, capture_stamp_s=0.0, width=640, height=480,
                                data=b"\xff\xd8" + bytes(40_000))
        t0 = time.monotonic()
        k = 0
        while (now := time.monotonic()) - t0 < seconds:
            k += 1
            states.put(bus.MotorState(seq=k, stamp_s=now - t0, theta_rad=[0.0] * 4, force_applied_N=[1.0] * 4,
                                      drive="active", epoch="e", bridge="bridge-test"))
            if k % 17 == 0:
                frames.put(frame)
            time.sleep(max(0.0, t0 + 0.002 * k - time.monotonic()))


STALL_S = 0.5  # no state for this long: the control role notes what every thread was doing
MAX_STALLS = 3
IDLE_FRAMES = ("futex", "epoll_wait", "nanosleep", "poll_schedule")


def _read(path: str) -> str:
    try:
        with open(path) as f:
            return f.read().strip()
    except OSError:
        return ""


def _scenario(siblings_of: int, endpoints: set[str]) -> list[tuple[Path, str]]:
    """The processes of one scenario: among the bus peers whose parent is ``siblings_of``, those
    linked to ``endpoints`` (the caller's own) through endpoints they listen on or connect to,
    directly or through each other (a test runs several scenarios at once). (folder in /proc, role)."""
    peers = []
    for proc in Path("/proc").glob("[0-9]*"):
        if f"\nPPid:\t{siblings_of}\n" not in _read(f"{proc}/status"):
            continue
        argv = _read(f"{proc}/cmdline").split("\0")
        if len(argv) >= 6 and argv[1] == PEER[1]:
            peers.append((proc, argv[2], {e for arg in argv[4:6] for e in arg.split(",") if e and e != ANY}))
    linked, mine = [], set(endpoints) - {ANY}
    while True:
        more = [p for p in peers if p[2] & mine and p not in linked]
        if not more:
            return sorted(((proc, role) for proc, role, _ in linked), key=lambda p: int(p[0].name))
        linked += more
        mine |= {e for p in more for e in p[2]}


def _threads_now(processes: list[tuple[Path, str]]) -> list[str]:
    """One line per thread of ``processes`` ((folder in /proc, role), :func:`_scenario`): pid, role,
    the thread's name and state, its system call (``/proc/.../syscall``: number first, if this
    user may read it) and its kernel stack's innermost frames (as root; else its wait channel);
    a stopped process (SIGSTOP) in one line. Threads idle in a futex, a poll or a sleep (innermost
    frame) are counted, not listed: what is left is what a process waits in (a socket's close, say)."""
    lines: list[str] = []
    for proc, role in processes:
        status = _read(f"{proc}/status")
        if not status:
            continue  # gone
        if "\nState:\tT" in status:
            lines.append(f"{proc.name} {role}: stopped")
            continue
        idle = 0
        for task in sorted(proc.glob("task/*"), key=lambda p: int(p.name)):
            state = next((ln.split(":", 1)[1].strip() for ln in _read(f"{task}/status").splitlines()
                          if ln.startswith("State:")), "?")
            stack = [ln.split("] ", 1)[-1] for ln in _read(f"{task}/stack").splitlines()][:5] or \
                [f"wchan {_read(f'{task}/wchan')}"]
            if state.startswith("S") and any(w in stack[0] for w in IDLE_FRAMES):
                idle += 1
                continue
            lines.append(f"{proc.name} {role} {_read(f'{task}/comm')} {state} "
                         f"syscall={_read(f'{task}/syscall').split(' ')[0] or '?'} {' < '.join(stack)}")
        lines.append(f"{proc.name} {role}: {idle} threads idle (futex, poll, sleep)")
    return lines


def _control(listen: list[str], connect: list[str], seconds: float, autoconnect: bool = True) -> None:
    times: list[float] = []
    stalls: list[dict] = []
    lock = threading.Lock()
    done = threading.Event()

    def on_state(_sample: object) -> None:
        with lock:
            times.append(time.monotonic())
            if len(times) == 1:
                print("ready", flush=True)

    def watch() -> None:  # a gap that happens once in a CI run must say where it came from
        noted = -1.0
        while not done.wait(0.1):
            with lock:
                last = times[-1] if times else None
            if last is not None and last != noted and time.monotonic() - last > STALL_S \
                    and len(stalls) < MAX_STALLS:
                noted = last
                scenario = _scenario(os.getppid(), {*listen, *connect})
                stalls.append({"at_s": round(last - times[0], 3), "index": times.index(last),
                               "threads": _threads_now(scenario)})

    threading.Thread(target=watch, daemon=True).start()
    with open_session(listen=listen, connect=connect, autoconnect=autoconnect) as session:
        sub = session.declare_subscriber(bus.MOTOR_STATE, on_state)
        commands = publisher(session, bus.MOTOR_COMMAND)
        status = publisher(session, bus.CONTROLLER_STATUS)
        t0 = time.monotonic()
        k = 0
        while (now := time.monotonic()) - t0 < seconds:
            k += 1
            commands.put(bus.ForceCommand(seq=k, stamp_s=now - t0, force_N=[5.0] * 4, source="test", sender="ctl",
                                          epoch="e"))
            status.put(bus.ControllerStatus(
                seq=k, stamp_s=now - t0, law="test", tick_s=0.002, compute_s=1e-4, overruns=0, deadline_misses=0,
                saturated=[False] * 4, alpha_hat_rad=[0.1] * 3, alpha_d_rad=[0.1] * 3, e_rad=[0.0] * 3,
                holding=False))
            time.sleep(max(0.0, t0 + 0.002 * k - time.monotonic()))
        sub.undeclare()
    done.set()
    with lock:
        t = np.asarray(times)
    gaps = np.diff(t)
    worst = int(np.argmax(gaps)) if gaps.size else 0
    for stall in stalls:  # how long that gap lasted in the end (s)
        i = stall.pop("index")
        stall["gap_s"] = round(float(gaps[i]), 3) if i < gaps.size else round(time.monotonic() - float(t[i]), 3)
    print(json.dumps({
        "received": int(t.size),
        "max_gap_s": float(gaps[worst]) if gaps.size else float("inf"),
        "at_s": float(t[worst] - t[0]) if gaps.size else 0.0,
        "median_gap_s": float(np.median(gaps)) if gaps.size else float("inf"),
        "p99_gap_s": float(np.quantile(gaps, 0.99)) if gaps.size else float("inf"),
        "gaps_over_10ms": int(np.sum(gaps > 0.010)),
        "gaps_over_100ms": int(np.sum(gaps > 0.100)),
        "stalls": stalls,
    }), flush=True)


def _listen_all(listen: list[str], connect: list[str], seconds: float) -> None:
    seen = threading.Event()

    def on_sample(_sample: object) -> None:
        if not seen.is_set():
            seen.set()
            print("seen", flush=True)

    with open_session(listen=listen, connect=connect) as session:
        sub = session.declare_subscriber(f"{bus.PREFIX}/**", on_sample)
        print("ready", flush=True)
        time.sleep(seconds)
        sub.undeclare()


def _rogue_sessions(connect: list[str], seconds: float, count: int) -> None:
    from concurrent.futures import ThreadPoolExecutor

    t0 = time.monotonic()

    def one(_: int):
        session = open_session(listen=[], connect=connect)
        session.declare_subscriber(f"{bus.PREFIX}/**", lambda _s: None)
        return session

    with ThreadPoolExecutor(16) as pool:
        sessions = list(pool.map(one, range(count)))
    time.sleep(1.0)  # links still being established
    linked = sum(1 for s in sessions if list(s.info.peers_zid()))
    print(json.dumps({"opened": len(sessions), "linked": linked, "open_s": time.monotonic() - t0}), flush=True)
    time.sleep(max(0.0, seconds - (time.monotonic() - t0)))
    for s in sessions:
        s.close()


def _rogue_tcp(connect: list[str], seconds: float, count: int) -> None:
    import socket

    t0 = time.monotonic()
    host, _, port = connect[0].partition("/")[2].rpartition(":")
    held = []
    for _ in range(count):
        with contextlib.suppress(OSError):
            held.append(socket.create_connection((host, int(port)), timeout=2.0))
    time.sleep(1.0)
    alive = 0
    for s in held:  # a connection the listener dropped reads as closed (b"") or errs
        s.setblocking(False)
        try:
            alive += s.recv(1) != b""
        except BlockingIOError:
            alive += 1
        except OSError:
            pass
    print(json.dumps({"opened": len(held), "linked": alive, "open_s": time.monotonic() - t0}), flush=True)
    time.sleep(max(0.0, seconds - (time.monotonic() - t0)))
    for s in held:
        s.close()


def _start(role: str, seconds: float, listen: list[str], connect: list[str],
           env: Mapping[str, str] | None, count: int = 0, prefix: list[str] | None = None,
           autoconnect: bool = True) -> subprocess.Popen[str]:
    return subprocess.Popen([*(prefix or []), *PEER, role, str(seconds), ",".join(listen), ",".join(connect), str(count),
                             *([] if autoconnect else [NO_AUTOCONNECT_ARG])],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True,
                            env=None if env is None else dict(env))


def _expect(proc: subprocess.Popen[str], word: str) -> None:
    assert proc.stdout is not None
    line = proc.stdout.readline()  # bounded: every role exits by itself
    if line.strip() != word:
        raise RuntimeError(f"a bus peer did not say {word!r}: {line}{proc.stdout.read()}")


def run_stalled(hub: str, stopped: int, stop_s: float, env: Mapping[str, str] | None = None,
                layout: str = "hub") -> dict:
    """The stalled-listeners scenario on ``hub`` (e.g. ``tcp/127.0.0.1:PORT``, free): a hub, a
    publisher, a control peer and ``stopped - 1`` more listeners, each a process with ``env``
    (None: this one's), linked as ``layout`` says (module doc); once every listener has seen a
    message, the hub and the listeners are stopped (SIGSTOP) for ``stop_s``. Returns the control
    peer's JSON line (module doc). Every process is stopped on return, within bounded time."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout {layout!r} is not one of {LAYOUTS}")
    life = stop_s + 40.0
    procs: list[subprocess.Popen[str]] = []
    sockets = tempfile.TemporaryDirectory(prefix="xneck-stalled-")  # the stack layout's Unix sockets
    autoconnect = layout != "stack"
    try:
        if layout == "hub":
            hub_peer = _start("listener", life, [hub], [], env)
            publish_at, control_at = [ANY], [ANY]
            publish_to = control_to = [hub]
        else:
            from bridge.session import free_tcp_port

            publish_ep, control_ep = (f"tcp/127.0.0.1:{free_tcp_port()}", f"tcp/127.0.0.1:{free_tcp_port()}") \
                if layout == "up" else tuple(f"unixsock-stream/{sockets.name}/{n}.sock" for n in ("publish", "control"))
            hub_peer = _start("listener", life, [hub], [publish_ep, control_ep], env)
            publish_at, control_at = [publish_ep], [control_ep]
            publish_to, control_to = [], [publish_ep]
        procs.append(hub_peer)
        _expect(hub_peer, "ready")
        listeners = [hub_peer]
        for _ in range(stopped - 1):
            listeners.append(_start("listener", life, [ANY], [hub], env))
            procs.append(listeners[-1])
            _expect(listeners[-1], "ready")
        procs.append(_start("publish", life, publish_at, publish_to, env, autoconnect=autoconnect))
        control = _start("control", stop_s + 12.0, control_at, control_to, env, autoconnect=autoconnect)
        procs.append(control)
        _expect(control, "ready")
        for p in listeners:  # linked: stopping one that never was proves nothing
            _expect(p, "seen")
        time.sleep(1.0)
        for p in listeners:
            p.send_signal(signal.SIGSTOP)
        time.sleep(stop_s)
        for p in listeners:
            p.send_signal(signal.SIGCONT)
        out, _ = control.communicate(timeout=30)
        return json.loads(out.strip().splitlines()[-1])
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                p.send_signal(signal.SIGCONT)
                p.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.communicate(timeout=10)
        sockets.cleanup()


FLOODS = ("none", "tcp", "sessions")


def _kill_all(procs: list[subprocess.Popen[str]]) -> None:
    for p in procs:
        with contextlib.suppress(ProcessLookupError):
            p.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.communicate(timeout=10)


def run_flood(flood: str, count: int, seconds: float, env: Mapping[str, str], rogue_env: Mapping[str, str],
              scheme: str = "tcp") -> dict:
    """A stranger floods the bridge's listener: a publisher (the bridge) listens on a free loopback
    port, a control peer connects to it, both with ``env``; once states flow, a rogue process with
    ``rogue_env`` opens ``count`` connections of kind ``flood`` (:data:`FLOODS`; "none" for none) to
    the publisher and holds them. Returns the control peer's JSON line (module doc) with the rogue's
    as ``rogue`` (None without flood). ``scheme``: the listener's endpoint, ``tcp`` or ``tls`` (then
    ``env`` needs XNECK_ZENOH_TLS). Every process is stopped on return, within bounded time."""
    if flood not in FLOODS:
        raise ValueError(f"flood {flood!r} is not one of {FLOODS}")
    from bridge.session import free_tcp_port

    endpoint = f"{scheme}/127.0.0.1:{free_tcp_port()}"
    procs: list[subprocess.Popen[str]] = []
    try:
        procs.append(_start("publish", seconds + 30.0, [endpoint], [], env))
        control = _start("control", seconds, [ANY], [endpoint], env)
        procs.append(control)
        _expect(control, "ready")
        rogue_line = None
        if flood != "none":
            rogue = _start(f"rogue-{flood}", seconds + 10.0, [], [endpoint], rogue_env, count)
            procs.append(rogue)
            assert rogue.stdout is not None
            rogue_line = rogue.stdout.readline()  # bounded: the rogue exits by itself
        out, _ = control.communicate(timeout=seconds + 60.0)
        result = json.loads(out.strip().splitlines()[-1])
        try:
            result["rogue"] = None if rogue_line is None else json.loads(rogue_line)
        except json.JSONDecodeError:
            raise RuntimeError(f"the rogue peer failed: {rogue_line}{procs[-1].communicate(timeout=30)[0]}") from None
        return result
    finally:
        _kill_all(procs)


def run_churn(peers: int, period_s: float, slots: int | None = None, env: Mapping[str, str] | None = None,
              unix_dir: Path | None = None, board: Any = None) -> dict:
    """Peers that come and go: a publisher (the bridge) listens on a free loopback port and a
    control peer connects to it; once states flow, ``peers`` listener processes (each a console or
    a tool subscribing to every key) connect to the publisher one after another, each living
    ``period_s`` - 1 s, one started every ``period_s``; the run lasts ``slots`` (default ``peers``)
    periods and 4 s (0 peers and the churn's slots: the baseline).
    Returns the control peer's JSON line (module doc) with ``arrivals_s``, when each peer was
    started (s since the control peer's first state). With ``unix_dir``, every process listens on a
    Unix socket there instead of loopback TCP. With ``board`` (benchmarks/_netns.py: another
    network stack, as the BeagleBone's), the publisher runs in it and listens on TCP at its
    address (the remote bridge's layout); the other processes stay on this machine, listening as
    ``unix_dir`` says. Every process is stopped on return."""
    from bridge.session import free_tcp_port

    def listen_at(name: str) -> list[str]:
        return [ANY] if unix_dir is None else [f"unixsock-stream/{unix_dir / name}.sock"]

    if board is not None:  # the bridge on its board: other machines reach it over TCP
        endpoint = f"tcp/{board.board_ip}:{free_tcp_port()}"
    else:
        endpoint = f"tcp/127.0.0.1:{free_tcp_port()}" if unix_dir is None else listen_at("publish")[0]
    seconds = 4.0 + period_s * (peers if slots is None else slots)
    procs: list[subprocess.Popen[str]] = []
    try:
        procs.append(_start("publish", seconds + 30.0, [endpoint], [], env,
                            prefix=None if board is None else board.exec_prefix))
        control = _start("control", seconds, listen_at("control"), [endpoint], env)
        procs.append(control)
        _expect(control, "ready")
        t0 = time.monotonic()
        arrivals = []
        time.sleep(2.0)
        for i in range(peers):
            arrivals.append(round(time.monotonic() - t0, 2))
            peer = _start("listener", period_s - 1.0, listen_at(f"peer-{i}"), [endpoint], env)
            procs.append(peer)
            time.sleep(period_s)
        out, _ = control.communicate(timeout=seconds + 60.0)
        result = json.loads(out.strip().splitlines()[-1])
        result["arrivals_s"] = arrivals
        return result
    finally:
        _kill_all(procs)


def main(argv: list[str]) -> None:
    role, seconds = argv[0], float(argv[1])
    listen, connect = ([e for e in arg.split(",") if e] for arg in argv[2:4])
    autoconnect = NO_AUTOCONNECT_ARG not in argv[5:]
    if role == "publish":
        _publish(listen, connect, seconds, autoconnect)
    elif role == "control":
        _control(listen, connect, seconds, autoconnect)
    elif role == "listener":
        _listen_all(listen, connect, seconds)
    elif role == "rogue-sessions":
        _rogue_sessions(connect, seconds, int(argv[4]))
    elif role == "rogue-tcp":
        _rogue_tcp(connect, seconds, int(argv[4]))
    else:
        raise SystemExit(f"unknown role {role!r}")


if __name__ == "__main__":
    main(sys.argv[1:])
