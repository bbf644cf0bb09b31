"""Which xneck processes are alive, from their Zenoh liveliness tokens (``xneck/alive/<kind>/<id>``),
and each one's latest health counters (``xneck/health/<kind>/<id>``, :class:`bridge.bus.Health`).

A token vanishes when its process ends or its session drops, so this is the console's ground
truth for "is the twin / controller / bridge up"; no polling, no heartbeats to tune. Health
messages are kept only for processes alive, one each (what the bus sends cannot grow the
console's memory), and only when they decode and their body names the process of their key.
"""

from __future__ import annotations

import contextlib
import threading
import time

import zenoh

from bridge import bus
from bridge.session import payload_of


class Presence:
    """Live set of processes on the bus; the callback only updates a dict under a lock."""

    def __init__(self, session: zenoh.Session) -> None:
        self._lock = threading.Lock()
        self._alive: dict[str, tuple[str, str, float]] = {}  # key -> (kind, instance, monotonic s when seen)
        self._health: dict[tuple[str, str], tuple[float, bus.Health]] = {}  # (kind, instance) -> (monotonic s, msg)
        self.health_rejected = 0  # Health payloads refused (malformed, oversized, key and body disagreeing)
        self._sub = session.liveliness().declare_subscriber(bus.ALIVE_ALL, self._on_sample, history=True)
        self._health_sub = session.declare_subscriber(bus.HEALTH_ALL, self._on_health)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            kind, instance = bus.parse_liveliness_key(key)
        except ValueError:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.setdefault(key, (kind, instance, time.monotonic()))
            else:
                self._alive.pop(key, None)
                self._health.pop((kind, instance), None)

    def _on_health(self, sample: zenoh.Sample) -> None:
        # Zenoh callback thread: never raises; a refused payload is counted.
        parts = str(sample.key_expr).split("/")
        try:
            msg = bus.decode(bus.Health, payload_of(sample, bus.Health))
        except bus.BusDecodeError:
            msg = None
        if msg is None or len(parts) != 4 or (msg.process, msg.instance) != (parts[2], parts[3]):
            with self._lock:
                self.health_rejected += 1
            return
        try:
            token = bus.liveliness_key(msg.process, msg.instance)
        except ValueError:  # names no process can have (a key chunk may hold what a name may not)
            token = ""
        with self._lock:
            if token in self._alive:
                self._health[(msg.process, msg.instance)] = (time.monotonic(), msg)
            else:
                self.health_rejected += not token

    def processes(self) -> list[dict[str, object]]:
        """``[{"kind", "instance", "since_s", "health"}]`` sorted by kind then instance; ``since_s``
        is how long (s) the console has seen the process alive (a duration, not a time of day).
        ``health``: its latest Health (``received`` and ``rejected`` counters, ``last_reject_reason``,
        ``uptime_s``) and ``age_s``, how long ago it came (s; about 1 s when the process is well),
        or None before any."""
        now = time.monotonic()
        with self._lock:
            items = sorted(self._alive.values())
            health = {k: self._health.get(k[:2]) for k in items}
        return [{"kind": k, "instance": i, "since_s": round(now - s, 3), "health": _health_view(health[(k, i, s)], now)}
                for k, i, s in items]

    def health(self, kind: str) -> list[tuple[str, bus.Health]]:
        """(instance, latest Health) of every process of ``kind`` alive that sent one, by instance."""
        with self._lock:
            return sorted(((i, h) for (k, i), (_t, h) in self._health.items() if k == kind), key=lambda ih: ih[0])

    def instances(self, kind: str) -> list[str]:
        """The instances of ``kind`` alive on the bus."""
        with self._lock:
            return sorted(i for k, i, _ in self._alive.values() if k == kind)

    def any_alive(self, kind: str) -> bool:
        with self._lock:
            return any(k == kind for k, _, _ in self._alive.values())

    def close(self) -> None:
        for sub in (self._sub, self._health_sub):
            with contextlib.suppress(Exception):
                sub.undeclare()


def _health_view(latest: tuple[float, bus.Health] | None, now: float) -> dict[str, object] | None:
    if latest is None:
        return None
    t, h = latest
    return {"age_s": round(now - t, 3), "uptime_s": h.uptime_s, "received": dict(h.received),
            "rejected": dict(h.rejected), "last_reject_reason": h.last_reject_reason}
