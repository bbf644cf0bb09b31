"""A network link with delay, for benchmarks: a TCP relay that forwards bytes both ways late.

    link = DelayLink(("127.0.0.1", 0), ("127.0.0.1", bridge_port), LinkConfig(delay_ms=2, jitter_ms=0.5))
    port = link.start()          # connect here instead of to the bridge
    ...
    link.close()                 # every socket closed, every thread joined, within bounded time

Each accepted connection gets one connection to the target and two directions; in each, a reader
thread stamps every chunk it receives and a writer thread sends it at its release time:

    release = max(arrival + delay + jitter, previous release)   (bytes stay in order, as TCP keeps them)

then, if a stall of the stream has begun by then (a Poisson process of ``stall_rate_hz`` per second
and direction), not before that stall's end: a hold of ``stall_ms`` of everything in flight, as a
TCP retransmission on a lossy Wi-Fi link holds the segments behind the lost one. Jitter is drawn
per chunk: ``exp`` (mean ``jitter_ms``; a long tail, as on a shared link) or ``uniform`` (0 to 2 ×
``jitter_ms``). The kernel has no netem here (``tc qdisc netem`` is missing), hence user space.

What the relay itself adds (a thread hand-over and the writer's wake-up; ``sleep`` overshoots a few
tens of µs) is measured by ``benchmarks/lab_network.py`` at zero configured delay, the baseline.

``python benchmarks/_delay_link.py --listen 127.0.0.1:P --to 127.0.0.1:Q [--delay-ms ...]
[--record FILE]`` runs one until SIGTERM; ``--record`` taps the bus (:class:`BusTap`) and writes
what it saw to FILE (JSON) at the end.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import math
import os
import queue
import random
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

#: ``tap(direction, event, t_ns, data)``: direction "up" (client → target: controller → bridge) or
#: "down" (target → client); event "recv" (read from its source) or "sent" (written to its destination).
Tap = Callable[[str, str, int, bytes], None]
CHUNK = 65536
CLOSE_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class LinkConfig:
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    jitter: str = "exp"  # "exp" or "uniform"
    stall_ms: float = 0.0
    stall_rate_hz: float = 0.0  # stalls per second, per direction
    seed: int = 0

    def __post_init__(self) -> None:
        if min(self.delay_ms, self.jitter_ms, self.stall_ms, self.stall_rate_hz) < 0:
            raise ValueError(f"negative link parameter in {self}")
        if self.jitter not in ("exp", "uniform"):
            raise ValueError(f"jitter {self.jitter!r}: exp or uniform")


class Schedule:
    """Release times of one direction (module docstring), in ``time.monotonic_ns``."""

    def __init__(self, config: LinkConfig, rng: random.Random, now_ns: int) -> None:
        self.c, self.rng = config, rng
        self.last_ns = 0
        self.stalls = 0
        self.next_stall_ns = self._after(now_ns)

    def _after(self, t_ns: int) -> float:
        rate = self.c.stall_rate_hz
        return t_ns + self.rng.expovariate(rate) * 1e9 if rate > 0 and self.c.stall_ms > 0 else math.inf

    def release_ns(self, arrival_ns: int) -> int:
        c = self.c
        extra = 0.0
        if c.jitter_ms > 0:
            extra = self.rng.expovariate(1 / c.jitter_ms) if c.jitter == "exp" else self.rng.uniform(0, 2 * c.jitter_ms)
        t = max(arrival_ns + int((c.delay_ms + extra) * 1e6), self.last_ns)
        while t >= self.next_stall_ns:  # a stall has begun by then: held until its end
            end = self.next_stall_ns + c.stall_ms * 1e6
            self.stalls += 1
            t = max(t, int(end))
            self.next_stall_ns = self._after(int(end))
        self.last_ns = t
        return t


class _Direction:
    """One direction of one connection: reader and writer threads."""

    def __init__(self, name: str, src: socket.socket, dst: socket.socket, schedule: Schedule, tap: Tap | None,
                 on_end: Callable[[], None]) -> None:
        self.name, self.src, self.dst, self.schedule, self.tap, self.on_end = name, src, dst, schedule, tap, on_end
        self.q: queue.SimpleQueue[tuple[int, int, bytes] | None] = queue.SimpleQueue()
        self.bytes = 0
        self.held_ns: list[int] = []  # per chunk: sent − received
        self.threads = [threading.Thread(target=self._read, name=f"link-{name}-rx", daemon=True),
                        threading.Thread(target=self._write, name=f"link-{name}-tx", daemon=True)]

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def _read(self) -> None:
        try:
            while data := self.src.recv(CHUNK):
                now = time.monotonic_ns()
                if self.tap is not None:
                    self.tap(self.name, "recv", now, data)
                self.q.put((now, self.schedule.release_ns(now), data))
        except OSError:
            pass
        self.q.put(None)

    def _write(self) -> None:
        try:
            while (item := self.q.get()) is not None:
                arrival, release, data = item
                wait = release - time.monotonic_ns()
                if wait > 0:
                    time.sleep(wait * 1e-9)
                self.dst.sendall(data)
                now = time.monotonic_ns()
                self.bytes += len(data)
                self.held_ns.append(now - arrival)
                if self.tap is not None:
                    self.tap(self.name, "sent", now, data)
            with contextlib.suppress(OSError):
                self.dst.shutdown(socket.SHUT_WR)  # the source closed: pass the end on, after the bytes
        except OSError:
            pass
        finally:
            self.on_end()


class DelayLink:
    """The relay (module docstring): listens on ``listen``, forwards to ``target``."""

    def __init__(self, listen: tuple[str, int], target: tuple[str, int], config: LinkConfig | None = None,
                 tap: Tap | None = None) -> None:
        self.listen, self.target, self.config, self.tap = listen, target, config or LinkConfig(), tap
        self.rng = random.Random(self.config.seed)
        self.directions: list[_Direction] = []
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self._server: socket.socket | None = None
        self._acceptor: threading.Thread | None = None
        self._closed = False

    def start(self) -> int:
        """Listen; returns the port."""
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(self.listen)
        s.listen(16)
        self._server = s
        self._acceptor = threading.Thread(target=self._accept, name="link-accept", daemon=True)
        self._acceptor.start()
        return s.getsockname()[1]

    def _accept(self) -> None:
        assert self._server is not None
        while True:
            try:
                client, _ = self._server.accept()
            except OSError:
                return
            try:
                upstream = socket.create_connection(self.target, timeout=5)
                upstream.settimeout(None)
            except OSError:
                client.close()
                continue
            for sock in (client, upstream):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            ends = [2]
            lock = threading.Lock()

            def ended(client: socket.socket = client, upstream: socket.socket = upstream,
                      ends: list[int] = ends, lock: threading.Lock = lock) -> None:
                with lock:
                    ends[0] -= 1
                    last = ends[0] == 0
                if last:  # both directions done: the connection is over
                    for sock in (client, upstream):
                        sock.close()

            now = time.monotonic_ns()
            with self._lock:
                if self._closed:
                    client.close()
                    upstream.close()
                    return
                # a generator of its own per direction: two reader threads draw at once
                up, down = (Schedule(self.config, random.Random(self.rng.random()), now) for _ in range(2))
                pair = [_Direction("up", client, upstream, up, self.tap, ended),
                        _Direction("down", upstream, client, down, self.tap, ended)]
                self._sockets += [client, upstream]
                self.directions += pair
            for d in pair:
                d.start()

    def stats(self) -> dict[str, dict[str, float]]:
        """Per direction: bytes, chunks, stalls, held time (sent − received) median/p99/max in ms."""
        out = {}
        for name in ("up", "down"):
            ds = [d for d in self.directions if d.name == name]
            held = sorted(h for d in ds for h in d.held_ns)

            def pick(q: float, held: list[int] = held) -> float:
                return held[min(len(held) - 1, int(q * len(held)))] * 1e-6 if held else math.nan

            out[name] = {"bytes": sum(d.bytes for d in ds), "chunks": len(held),
                         "stalls": sum(d.schedule.stalls for d in ds),
                         "held_p50_ms": pick(0.5), "held_p99_ms": pick(0.99), "held_max_ms": pick(1.0)}
        return out

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Stop listening, cut every connection, join every thread (each at most ``timeout_s``)."""
        with self._lock:
            self._closed = True
            sockets, threads = list(self._sockets), [t for d in self.directions for t in d.threads]
        if self._server is not None:
            with contextlib.suppress(OSError):
                self._server.shutdown(socket.SHUT_RDWR)
            self._server.close()
        for sock in sockets:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        deadline = time.monotonic() + timeout_s
        for t in [*([self._acceptor] if self._acceptor else []), *threads]:
            t.join(max(0.0, deadline - time.monotonic()))
        for sock in sockets:
            sock.close()

    def __enter__(self) -> DelayLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class BusTap:
    """The control path as the bridge's side of the link sees it, from the bytes (the bus's JSON
    payloads, unencrypted): when each state left the bridge (read from it, direction "down") and
    when each command answering it reached the bridge (written to it, direction "up"), matched by
    ``stamp_s``; and each state's ``drive`` (a hold shows as "hold")."""

    STATE = re.compile(rb'"stamp_s":([-0-9.eE+]+),"theta_rad":\[[^\]]*\],"force_applied_N":\[[^\]]*\],"drive":"(\w+)"')
    COMMAND = re.compile(rb'"stamp_s":([-0-9.eE+]+),"force_N":\[')
    KEEP = 400  # bytes of a chunk's end kept for a message split across two chunks

    def __init__(self) -> None:
        self.states: dict[bytes, int] = {}
        self.drives: collections.Counter[str] = collections.Counter()
        self.rtt_ns: list[int] = []
        self.rtt_at_ns: list[int] = []  # when each answered state left the bridge
        self.commands = self.unmatched = 0
        self.holds = 0  # states whose drive turned to "hold"
        self._drive = ""
        # (states, holds, states in hold) when the newest command reached the bridge: a controller
        # that ends (its trajectory done) leaves a last hold that is not the link's doing
        self.at_last_command = (0, 0, 0)
        self._tail = {"down": b"", "up": b""}
        self._lock = threading.Lock()

    def _scan(self, direction: str, data: bytes, pattern: re.Pattern[bytes]) -> list[re.Match[bytes]]:
        tail = self._tail[direction]
        buf = tail + data
        self._tail[direction] = buf[-self.KEEP:]
        return [m for m in pattern.finditer(buf) if m.end() > len(tail)]

    def __call__(self, direction: str, event: str, t_ns: int, data: bytes) -> None:
        if direction == "down" and event == "recv":
            found = self._scan(direction, data, self.STATE)
            with self._lock:
                for m in found:
                    self.states[m.group(1)] = t_ns
                    drive = m.group(2).decode()
                    self.drives[drive] += 1
                    self.holds += drive == "hold" and self._drive != "hold"
                    self._drive = drive
        elif direction == "up" and event == "sent":
            found = self._scan(direction, data, self.COMMAND)
            with self._lock:
                for m in found:
                    self.commands += 1
                    sent = self.states.pop(m.group(1), None)
                    if sent is None:
                        self.unmatched += 1
                    else:
                        self.rtt_ns.append(t_ns - sent)
                        self.rtt_at_ns.append(sent)
                if found:
                    self.at_last_command = (sum(self.drives.values()), self.holds, self.drives["hold"])

    def record(self) -> dict:
        with self._lock:
            states, holds, hold_states = self.at_last_command
            return {"states": sum(self.drives.values()), "drives": dict(self.drives), "commands": self.commands,
                    "unmatched_commands": self.unmatched, "rtt_ms": [r * 1e-6 for r in self.rtt_ns],
                    "rtt_at_s": [(t - self.rtt_at_ns[0]) * 1e-9 for t in self.rtt_at_ns],
                    "holds": self.holds, "until_last_command": {"states": states, "holds": holds,
                                                                "hold_states": hold_states}}


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--listen", required=True, type=_address, help="HOST:PORT to listen on")
    ap.add_argument("--to", required=True, type=_address, help="HOST:PORT to forward to")
    ap.add_argument("--delay-ms", type=float, default=0.0)
    ap.add_argument("--jitter-ms", type=float, default=0.0)
    ap.add_argument("--jitter", choices=("exp", "uniform"), default="exp")
    ap.add_argument("--stall-ms", type=float, default=0.0)
    ap.add_argument("--stall-rate", type=float, default=0.0, help="stalls per second and direction")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--record", default="", help="tap the bus (BusTap) and write it and the link's stats here at the end")
    ap.add_argument("--fifo", type=int, default=0, help="SCHED_FIFO priority of every thread (0: leave it)")
    ap.add_argument("--cpus", default="", help="comma-separated CPUs for every thread (default: leave it)")
    args = ap.parse_args()
    parent = os.environ.get("XNECK_DIE_WITH_PARENT", "")
    if parent.isdigit() and sys.platform.startswith("linux"):  # as server.child_processes.die_with_parent
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
        if os.getppid() != int(parent):
            return
    if args.cpus:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, {int(c) for c in args.cpus.split(",")})
    if args.fifo:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    config = LinkConfig(args.delay_ms, args.jitter_ms, args.jitter, args.stall_ms, args.stall_rate, args.seed)
    tap = BusTap() if args.record else None
    link = DelayLink(args.listen, args.to, config, tap)
    port = link.start()
    print(f"link {args.listen[0]}:{port} -> {args.to[0]}:{args.to[1]} {asdict(config)}", flush=True)
    while not stop.wait(0.2):
        pass
    link.close()
    if args.record:
        assert tap is not None
        with open(args.record, "w", encoding="utf-8") as f:
            json.dump({"config": asdict(config), "link": link.stats(), "tap": tap.record()}, f)
    sys.exit(0)


if __name__ == "__main__":
    main()
