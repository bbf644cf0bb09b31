"""The user-space network link of ``benchmarks/lab_network.py`` (``benchmarks/_delay_link.py``).

Behaviour, not speed: bytes arrive complete and in order both ways, the configured delay is applied
(a lower bound, counted on the relay's own clock), stalls hold the stream, the bus tap matches a
command to its state, and the link closes within bounded time. No wall-clock upper bounds."""

from __future__ import annotations

import importlib.util
import itertools
import random
import socket
import sys
import threading
import time
from pathlib import Path

from busutil import wait_until

_spec = importlib.util.spec_from_file_location(
    "_delay_link", Path(__file__).resolve().parents[1] / "benchmarks" / "_delay_link.py")
assert _spec is not None and _spec.loader is not None
delay_link = importlib.util.module_from_spec(_spec)
sys.modules["_delay_link"] = delay_link  # its dataclasses look their module up there
_spec.loader.exec_module(delay_link)

TIMEOUT_S = 20.0


class Echo:
    """A TCP server that echoes every byte of each connection, then closes its side on EOF."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.threads: list[threading.Thread] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            t = threading.Thread(target=self._echo, args=(conn,), daemon=True)
            t.start()
            self.threads.append(t)

    @staticmethod
    def _echo(conn: socket.socket) -> None:
        with conn:
            while data := conn.recv(65536):
                conn.sendall(data)
            conn.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        self.server.close()


def _exchange(port: int, payload: bytes) -> bytes:
    """Send ``payload`` in uneven pieces while reading the echo; returns everything read to EOF."""
    got = bytearray()
    with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S) as s:
        def read() -> None:
            while data := s.recv(65536):
                got.extend(data)

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        rng, i = random.Random(1), 0
        while i < len(payload):
            n = rng.choice((1, 7, 200, 4096, 70000))
            s.sendall(payload[i:i + n])
            i += n
        s.shutdown(socket.SHUT_WR)
        reader.join(TIMEOUT_S)
        assert not reader.is_alive(), "the echo never ended"
    return bytes(got)


def test_bytes_arrive_complete_and_in_order_both_ways_with_jitter() -> None:
    echo = Echo()
    payload = random.Random(0).randbytes(600_000)
    link = delay_link.DelayLink(("127.0.0.1", 0), ("127.0.0.1", echo.port),
                                delay_link.LinkConfig(delay_ms=0.2, jitter_ms=0.5, seed=3))
    try:
        port = link.start()
        assert _exchange(port, payload) == payload  # up to the echo and back down: both directions
        assert wait_until(lambda: link.stats()["down"]["bytes"] == len(payload))  # counted after it went
        stats = link.stats()
        assert stats["up"]["bytes"] == stats["down"]["bytes"] == len(payload)
    finally:
        link.close()
        echo.close()


def test_the_configured_delay_is_applied_to_every_chunk_each_way() -> None:
    echo = Echo()
    link = delay_link.DelayLink(("127.0.0.1", 0), ("127.0.0.1", echo.port), delay_link.LinkConfig(delay_ms=20))
    try:
        port = link.start()
        with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S) as s:
            for k in range(5):
                t0 = time.monotonic()
                s.sendall(b"ping %d" % k)
                assert s.recv(64) == b"ping %d" % k
                assert time.monotonic() - t0 >= 0.040  # two passes of 20 ms
        for name in ("up", "down"):
            # A pass is counted after its bytes went: the echo's last may be read before (a race that
            # failed this test one run in three).
            def held(name: str = name) -> list[int]:
                return [h for d in link.directions if d.name == name for h in d.held_ns]
            assert wait_until(lambda: len(held()) == 5), (name, held())
            assert min(held()) >= 20_000_000, (name, held())
    finally:
        link.close()
        echo.close()


def test_release_times_keep_order_and_stalls_hold_the_stream() -> None:
    """Jitter never reorders (each release at or after the previous one); every stall begun holds
    what comes at or after its start until its end."""
    rng = random.Random(5)
    config = delay_link.LinkConfig(delay_ms=1, jitter_ms=3, stall_ms=50, stall_rate_hz=20, seed=5)
    schedule = delay_link.Schedule(config, rng, 0)
    releases, t = [], 0
    for _ in range(5000):
        t += 2_000_000  # a chunk every 2 ms, 10 s
        r = schedule.release_ns(t)
        assert r >= t + 1_000_000
        releases.append(r)
    assert releases == sorted(releases)
    assert schedule.stalls > 50  # about 100: one 50 ms after the end of each, on average, over 10 s
    gaps = [b - a for a, b in itertools.pairwise(releases)]
    assert sum(g >= 40_000_000 for g in gaps) > 0  # the stream stood still at least once


def test_the_bus_tap_matches_commands_to_states_across_chunk_boundaries() -> None:
    tap = delay_link.BusTap()
    state = (b'\x10\x00{"v":2,"seq":7,"stamp_s":12.346,"theta_rad":[0.1,0.2,0.3,0.4],'
             b'"force_applied_N":[10.0,20.0,30.0,40.0],"drive":"hold","hold_reason":"x"}')
    command = b'{"v":2,"seq":3,"stamp_s":12.346,"force_N":[1.0,2.0,3.0,4.0],"source":"law2"}'
    tap("down", "recv", 1_000, state[:40])
    tap("down", "recv", 2_000, state[40:])
    tap("up", "sent", 5_000, command[:30])
    tap("up", "sent", 9_000, command[30:] + b'{"v":2,"seq":4,"stamp_s":99.0,"force_N":[1]}')
    r = tap.record()
    assert r["states"] == 1 and r["drives"] == {"hold": 1}
    assert r["commands"] == 2 and r["unmatched_commands"] == 1
    assert r["rtt_ms"] == [(9_000 - 2_000) * 1e-6]
    assert r["holds"] == 1 and r["until_last_command"] == {"states": 1, "holds": 1, "hold_states": 1}


def test_closing_ends_every_thread_with_a_connection_still_open() -> None:
    echo = Echo()
    link = delay_link.DelayLink(("127.0.0.1", 0), ("127.0.0.1", echo.port), delay_link.LinkConfig(delay_ms=1))
    port = link.start()
    s = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S)
    try:
        s.sendall(b"hello")
        assert s.recv(16) == b"hello"
        link.close()
        threads = [t for d in link.directions for t in d.threads]
        assert threads and not any(t.is_alive() for t in threads)
        assert link._acceptor is not None and not link._acceptor.is_alive()
        assert s.recv(16) == b""  # the client sees the link end
        try:
            socket.create_connection(("127.0.0.1", port), timeout=2).close()
            refused = False
        except OSError:
            refused = True
        assert refused, "the link still listens after close()"
    finally:
        s.close()
        echo.close()
