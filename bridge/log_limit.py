"""At most one log line a period for one kind of event that any peer can cause.

A peer flooding refused e-stop releases wrote a full log line for each: 22.5 MB in 5 s on the
bridge's disk (the board's SD card), and its ticks stretched to 24 ms, 420 periods skipped; 2000
holder tokens let go wrote 2000 lines and stretched a tick to 63 ms (audit of session 42). The
first event of a burst is logged at once; those within ``period_s`` of a logged one are counted
and the count is said with the next line logged.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class LogLimit:
    """Whether to log one more event of a kind now (thread-safe: Zenoh callbacks call it)."""

    def __init__(self, period_s: float = 1.0, clock: Callable[[], float] = time.monotonic) -> None:
        if not period_s > 0:
            raise ValueError(f"period_s must be positive, not {period_s!r}")
        self.period_s = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self._last = -float("inf")
        self._held = 0
        self.suppressed = 0  # events not logged in all

    def allow(self) -> int | None:
        """None: do not log this event (counted); else log it, saying how many were not logged
        since the last line (0: none)."""
        now = self._clock()
        with self._lock:
            if now - self._last < self.period_s:
                self._held += 1
                self.suppressed += 1
                return None
            self._last, held, self._held = now, self._held, 0
            return held

    @staticmethod
    def tail(held: int) -> str:
        """What a logged line adds about the events not logged before it ('' for none)."""
        return f" ({held} more since the last such line, not logged)" if held else ""
