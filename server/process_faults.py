"""The stack's process faults this console was told of, for the dashboard's header.

``xneck up`` tells the console of every death, hang and restart of its processes (``POST
/api/system/abort``, :func:`server.cli.up.abort_campaign`). The safety journal keeps each one
(``process_fault``), but nobody reads a journal while watching the neck: a controller that was
restarted between two campaigns left no trace on the dashboard (follow-up of session 44). Here
the count and the newest one since the console started, for ``/api/system/health``.
"""

from __future__ import annotations

import threading
import time
from typing import Any

#: characters of the newest fault's reason the health carries (the journal has it whole)
REASON_MAX_CHARS = 300


class ProcessFaults:
    """How many process faults were reported since the console started, and the newest one.
    Thread-safe: the abort route runs on the server's worker threads."""

    def __init__(self, clock=time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._count = 0
        self._last: tuple[str, float, str | None] | None = None  # reason, when (clock), campaign id

    def record(self, reason: str, campaign_id: str | None) -> None:
        """One fault: ``reason`` as the supervisor said it, the campaign it ended (None if none)."""
        with self._lock:
            self._count += 1
            self._last = (reason[:REASON_MAX_CHARS], self._clock(), campaign_id)

    def status(self) -> dict[str, Any]:
        """``count`` since the console started; ``last_reason``, ``last_age_s`` (seconds ago) and
        ``last_campaign_id`` of the newest (null without one)."""
        with self._lock:
            count, last = self._count, self._last
        if last is None:
            return {"count": 0, "last_reason": None, "last_age_s": None, "last_campaign_id": None}
        reason, at, campaign_id = last
        return {"count": count, "last_reason": reason, "last_age_s": round(self._clock() - at, 1),
                "last_campaign_id": campaign_id}
