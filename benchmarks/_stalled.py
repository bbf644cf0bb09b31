"""A stopped peer seen from outside: the connections queued on its listener and the bridge's holds.

Stdlib only: shared by benchmarks/stalled_console.py and tests/test_up_stalled_console.py.
"""

from __future__ import annotations

import contextlib
import re
import threading
import time
from datetime import datetime
from pathlib import Path

LEASE_S = 10.0  # Zenoh's transport lease: the stopped console's links close after it
LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) ")


def accept_queue(port: int) -> int:
    """Connections the kernel accepted on the TCP socket listening on ``port`` (any address) that no
    process has taken yet: the listener's ``rx_queue`` in ``/proc/net/tcp{,6}`` (state 0A, LISTEN).
    A stopped process's listener keeps every connection made to it there."""
    queued = 0
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError):
            for row in Path(table).read_text().splitlines()[1:]:
                fields = row.split()
                if fields[3] == "0A" and int(fields[1].rsplit(":", 1)[1], 16) == port:
                    queued += int(fields[4].split(":")[1], 16)
    return queued


class AcceptWatch:
    """Samples :func:`accept_queue` every 0.1 s in a thread; ``rises`` holds (time.time(), queue)
    at each increase (a new connection attempt to the stopped listener, one per process retrying
    at that moment: Zenoh's open timeout closes them 10 s later, and they stay queued), and
    ``connections`` what the queue gained in all."""

    def __init__(self, port: int) -> None:
        self.port, self.rises, self.connections = port, [], 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        last = accept_queue(self.port)
        while not self._stop.wait(0.1):
            now = accept_queue(self.port)
            if now > last:
                self.rises.append((time.time(), now))
                self.connections += now - last
            last = now

    def __enter__(self) -> AcceptWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)


def holds_between(log: Path, since: float, until: float = float("inf")) -> list[str]:
    """The bridge's hold lines logged in the wall-clock interval [``since``, ``until``)."""
    lines = []
    for line in log.read_text(errors="replace").splitlines():
        m = LOG_TIME.match(line)
        if m and " hold: " in line and since <= datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp() < until:
            lines.append(line)
    return lines
