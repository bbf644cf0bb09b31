"""Heavy reads of campaign archives for open GETs (a comparison's traces, a report's figures).

Such a GET needs no token, and a read of a 600 s archive takes seconds and hundreds of MB. They
ran on anyio's default pool of 40 threads, the pool the e-stop's POST needed too, each request
reading the whole archive again while the first had not kept its result yet: 45 parallel compare
GETs delayed an e-stop 7.3 s and took the console to 621 MB (review of session 53). Now:

- one read at a time per archive (a lock per path): requests for the same archive wait for the
  first one's read, then find what it kept (the traces' JSON, the figure's PNG);
- at most :data:`ARCHIVE_READERS` reads at once, on threads of their own (an
  ``anyio.CapacityLimiter``), never the default pool's.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import anyio
import anyio.to_thread

from bridge.archive import ArchiveError, storage_reason

#: archive reads at once, whatever the number of GETs waiting (each may take ~1 MB per second recorded)
ARCHIVE_READERS = 2

T = TypeVar("T")


class ArchiveReads:
    """The locks and threads of archive reads (module docstring). Used on the app's event loop
    only: :func:`archive_reads` makes it there."""

    def __init__(self, readers: int = ARCHIVE_READERS) -> None:
        self.limiter = anyio.CapacityLimiter(readers)
        self._locks: dict[str, tuple[anyio.Lock, int]] = {}  # path -> (its lock, requests using it)

    async def run(self, archive: Path, read: Callable[..., T], *args: Any) -> T:
        """``read(*args)`` on one of the reading threads, after any read of ``archive`` under way
        (``read`` checks first what that one kept)."""
        key = os.fspath(archive)
        lock, users = self._locks.get(key) or (anyio.Lock(), 0)
        self._locks[key] = (lock, users + 1)
        try:
            async with lock:
                return await anyio.to_thread.run_sync(read, *args, limiter=self.limiter)
        finally:
            # forgotten with its last user: a lock per archive ever read would only grow
            lock, users = self._locks[key]
            if users <= 1:
                del self._locks[key]
            else:
                self._locks[key] = (lock, users - 1)


def archive_reads(state: Any) -> ArchiveReads:
    """The app's :class:`ArchiveReads`, made on first use in the app's event loop (the limiter
    needs it; no await between the test and the set)."""
    reads = getattr(state, "archive_reads", None)
    if reads is None:
        reads = state.archive_reads = ArchiveReads()
    return reads


def read_failure(campaign_id: str, archive: Path, exc: BaseException) -> str:
    """Why ``archive`` could not be read, for an open GET's answer: never its path, which names
    the console's data directory (review of session 53: a record without an archive answered it)."""
    what = f"cannot read campaign {campaign_id}'s archive"
    if isinstance(exc, FileNotFoundError):
        return f"campaign {campaign_id} has no archive"
    if isinstance(exc, OSError):
        return f"{what}: {storage_reason(exc)}"
    if isinstance(exc, ArchiveError):  # its message starts with the path; its reason does not
        return f"{what}: {exc.reason}"
    # the console's own words on the content (a figure of 2,000 joints), the folder cut out
    return f"{what}: {type(exc).__name__}: {str(exc).replace(os.fspath(archive.parent) + os.sep, '')}"
