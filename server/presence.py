"""Which xneck processes are alive, from their Zenoh liveliness tokens (``xneck/alive/<kind>/<id>``).

A token vanishes when its process ends or its session drops, so this is the console's ground
truth for "is the twin / controller / bridge up"; no polling, no heartbeats to tune.
"""

from __future__ import annotations

import contextlib
import threading
import time

import zenoh

from bridge import bus


class Presence:
    """Live set of processes on the bus; the callback only updates a dict under a lock."""

    def __init__(self, session: zenoh.Session) -> None:
        self._lock = threading.Lock()
        self._alive: dict[str, tuple[str, str, float]] = {}  # key -> (kind, instance, monotonic s when seen)
        self._sub = session.liveliness().declare_subscriber(bus.ALIVE_ALL, self._on_sample, history=True)

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

    def processes(self) -> list[dict[str, object]]:
        """``[{"kind", "instance", "since_s"}]`` sorted by kind then instance; ``since_s`` is how
        long (s) the console has seen the process alive (a duration, not a time of day)."""
        now = time.monotonic()
        with self._lock:
            items = sorted(self._alive.values())
        return [{"kind": k, "instance": i, "since_s": round(now - s, 3)} for k, i, s in items]

    def any_alive(self, kind: str) -> bool:
        with self._lock:
            return any(k == kind for k, _, _ in self._alive.values())

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._sub.undeclare()
