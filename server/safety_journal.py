"""The console's safety journal: an append-only JSON Lines file of every e-stop this console sent
and every transition of a bridge's state it saw (user audit of ``xneck up``, session 42: an
e-stop engaged and released between two campaigns was in no record the console keeps).

File: ``<data_dir>/safety/journal.jsonl``, one JSON object a line, newest last. Each line has:

- ``time``: wall-clock time the line was made, ISO 8601 in UTC with microseconds;
- ``stamp_s``: the same instant in seconds since the Unix epoch (``time.time()``);
- ``event``: what happened (``estop_sent``, from the console's REST route; ``bridge_run`` and
  ``bridge_state``, from :mod:`server.bridge_transitions`), then the event's own fields;
- ``repeated`` (only on a line that stands for repeats, below): how many identical events this
  line stands for, the first of them at ``repeated_since`` (ISO 8601, UTC), the last at ``time``.

Repeats are coalesced (:class:`Repeats`): a producer that names what makes its event the same
(``repeat_key``: the e-stop route gives engage or release, reason, the client's host (any port), its user
agent, the holder and the outcome) has an event identical to the line just written within
:data:`REPEAT_WINDOW_S` of it counted, not written; the count is written as one line (the last
repeat's fields, ``repeated``, ``repeated_since``) when the window ends, every window while they
go on, or at once when a different event comes, before it. The first event is written at once,
a different one is never dropped nor reordered, and events without a key (the bridge's
transitions, whose own limits are in :mod:`server.bridge_transitions`) are never coalesced. A
token holder flooding the e-stop route (hundreds a second, each engaging) had written a line of
~320 bytes each: ~15 600 of them rotated the journal and ~31 500 (a minute or two) pushed out the
previous file and whatever it kept; now such a flood writes about one line a second. The e-stop
itself acts on every request: only its line is coalesced.

Written by a thread of its own from a bounded queue (:data:`QUEUE_LINES`): neither the e-stop's
route nor the bus's state path waits for the disk, and neither ever sees a write fail. Each line
is one ``write`` (the rest written after a short one) to the file opened in append mode for it
(a few lines a second at most: the file moved or deleted meanwhile is made again, not written to
where it went), so a crash of the console loses no line written (not fsync'd: a power cut may lose the last seconds, as the page
cache does).

Bounded: at :data:`MAX_BYTES` the file is renamed ``journal.1.jsonl`` (the one before it goes)
and a new one starts, so a flapping or forged e-stop cannot fill the disk (10 MB at most, both).
The file is opened without following a symbolic link and refused unless it is a regular file
(review of session 43: a link at its path was followed, a FIFO written into). A write that
fails (disk full, read-only, the path taken by a directory, a link, a FIFO) is counted in
:attr:`SafetyJournal.write_errors`, its reason kept in :attr:`SafetyJournal.last_error`, and
logged at most once every :data:`FAILURE_LOG_PERIOD_S` (:class:`bridge.log_limit.LogLimit`); the
next line tries again (a disk freed meanwhile is written to again).

Reading (:func:`read_journal`) takes the newest lines of the two files, both opened under the lock
the writer holds while it rotates (a rotation between two opens had made a read return a file
twice: review of session 43); a last line without its newline (torn by a crash mid-write) and
lines that are not a JSON object naming an ``event`` are skipped and counted. What is at a
file's path is opened non-blocking without following a symbolic link, and refused unless it is a
regular file (a FIFO had blocked the read in ``open``: review of session 43). A line written after a torn one first ends it (a newline), so it is whole
itself.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import stat
import threading
import time
from collections import deque
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

from bridge.archive import iso_time, storage_reason
from bridge.log_limit import LogLimit

log = logging.getLogger("xneck.server")

JOURNAL_DIR = "safety"  # under the console's data directory
JOURNAL_FILE = "journal.jsonl"
PREVIOUS_FILE = "journal.1.jsonl"  # the file before the current one (one kept)
MAX_BYTES = 5_000_000  # a file is rotated before a line would take it past this (bytes)
QUEUE_LINES = 1000  # lines waiting for the writer; beyond, a line is dropped and counted
FAILURE_LOG_PERIOD_S = 60.0  # s: at most one log line a period about writes that fail
READ_MAX_LINES = 1000  # lines one read returns at most (GET /api/system/safety-journal?limit=)
#: bytes read back from the end of a file at most: a garbage line of a gigabyte (someone else's
#: writes) must not be read whole to find the lines after it
READ_MAX_BYTES = 2 * MAX_BYTES
READ_BLOCK_BYTES = 64 * 1024  # read back from the end in blocks of this many bytes
LINE_MAX_BYTES = 64 * 1024  # a longer line is no line of the journal's (about 1 kB): skipped unread
#: lines a read examines beyond the events it returns, at most: millions of short garbage lines
#: (someone else's writes) must not cost a read seconds of CPU
READ_MAX_SKIPPED = 10_000
#: s after a line during which identical events (the same ``repeat_key``) are counted, not written
REPEAT_WINDOW_S = 1.0


class Repeats:
    """Which lines to write of events that repeat (module docstring), on the caller's clock
    (seconds): pure, no thread or file. At most one group of repeats is open: the event last
    written and the identical ones counted since, so the lines stay in the order events came."""

    def __init__(self, window_s: float = REPEAT_WINDOW_S) -> None:
        self.window_s = window_s
        self._key: Hashable | None = None  # of the event last written (None: no group open)
        self._ends = 0.0  # when the open group's window ends (clock)
        self._count = 0  # identical events counted in this window, not yet written
        self._last: dict[str, Any] = {}  # the newest of them
        self._since = ""  # the ``time`` of the first of them

    def offer(self, key: Hashable | None, line: dict[str, Any], now: float) -> list[dict[str, Any]]:
        """The lines to write, in order, now that event ``line`` came at ``now``: none if it repeats
        the open group's (same ``key``, not None, within its window), else the group's count first
        (if any) and then ``line``."""
        out = self.expire(now)
        if key is not None and key == self._key:
            if self._count == 0:
                self._since = line.get("time", "")
            self._count += 1
            self._last = line
            return out
        out += self.close()
        out.append(line)
        if key is not None:
            self._key, self._ends = key, now + self.window_s
        return out

    def expire(self, now: float) -> list[dict[str, Any]]:
        """The open group's count, if its window ended by ``now`` (a new window starts: a flood
        goes on as one line a window); the group closes on a window without repeats."""
        if self._key is None or now < self._ends:
            return []
        if self._count == 0:
            self._key = None
            return []
        out = [self._summary()]
        self._ends = now + self.window_s
        return out

    def close(self) -> list[dict[str, Any]]:
        """The open group's count (if any), now; the group closes."""
        out = [self._summary()] if self._count else []
        self._key, self._count = None, 0
        return out

    def deadline(self) -> float | None:
        """When the open group's count is due (clock), None when nothing is counted."""
        return self._ends if self._key is not None and self._count else None

    def _summary(self) -> dict[str, Any]:
        line = {**self._last, "repeated": self._count, "repeated_since": self._since}
        self._count, self._last = 0, {}
        return line


class SafetyJournal:
    """The journal of one data directory (module docstring); :meth:`record` never raises."""

    def __init__(self, data_dir: Path, max_bytes: int = MAX_BYTES, repeat_window_s: float = REPEAT_WINDOW_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.dir = Path(data_dir) / JOURNAL_DIR
        self.path = self.dir / JOURNAL_FILE
        self.previous = self.dir / PREVIOUS_FILE
        self.max_bytes = max_bytes
        self.written = 0  # lines written since start
        self.write_errors = 0  # lines that could not be written (each tried once)
        self.dropped = 0  # lines dropped: the queue was full (the writer stuck on the disk) or closed
        self.last_error = ""  # why the last write failed ("" if none did)
        self._limit = LogLimit(FAILURE_LOG_PERIOD_S)
        self._queue: deque[bytes] = deque()
        self._repeats = Repeats(repeat_window_s)  # under _cond
        self._clock = clock  # s, the repeats' windows
        self._cond = threading.Condition()
        self._writing = False
        self._closed = False
        #: held while the writer rotates and while a read opens both files: a read has the two files
        #: of one moment, never the same file twice (or a gap) when a rotation comes between its opens
        self._files_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="safety-journal", daemon=True)
        self._thread.start()

    # -- producers (any thread) -------------------------------------------------------------------
    def record(self, event: str, *, repeat_key: Hashable | None = None, **fields: Any) -> None:
        """Queue one line: ``time``, ``stamp_s`` (now), ``event`` and ``fields`` (JSON values; a
        value that is not one is written as its ``str``). Never raises, never waits for the disk.
        With a ``repeat_key`` (hashable, not written), an event identical to the one just written
        (same ``event`` and key) within :data:`REPEAT_WINDOW_S` is counted, not written (:class:`Repeats`)."""
        try:
            now_ns = time.time_ns()
            line = {"time": iso_time(now_ns), "stamp_s": now_ns / 1e9, "event": event, **fields}
            _encode(line)  # a line that cannot be written is not a repeat either
        except (TypeError, ValueError) as exc:  # a NaN (no JSON has it): a caller's bug
            self._failed(f"line not encoded ({type(exc).__name__}: {exc})")
            return
        with self._cond:
            if self._closed:
                self.dropped += 1
                return
            for out in self._repeats.offer(None if repeat_key is None else (event, repeat_key), line, self._clock()):
                self._queue_line(out)
            self._cond.notify()

    def _queue_line(self, line: dict[str, Any]) -> None:
        """Queue ``line`` for the writer (holding ``_cond``), or count it dropped when the queue is full."""
        if len(self._queue) >= QUEUE_LINES:
            self.dropped += 1
            return
        self._queue.append(_encode(line))

    def flush(self, timeout_s: float = 1.0) -> bool:
        """Wait until every line queued so far was written (or failed); False after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._queue or self._writing:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def status(self) -> dict[str, Any]:
        """Counters for the health and the journal's route: ``written``, ``write_errors``,
        ``dropped`` (lines), ``last_error`` ("" if no write failed)."""
        return {"written": self.written, "write_errors": self.write_errors, "dropped": self.dropped,
                "last_error": self.last_error}

    def close(self, timeout_s: float = 2.0) -> None:
        """Write what is queued (within ``timeout_s``) and stop the writer; lines recorded after
        are dropped (counted)."""
        with self._cond:  # the repeats counted so far are written too
            for out in self._repeats.close():
                self._queue_line(out)
            self._cond.notify()
        self.flush(timeout_s)
        with self._cond:
            self._closed = True
            self.dropped += len(self._queue)
            self._queue.clear()
            self._cond.notify_all()
        self._thread.join(timeout_s)

    def open_for_reading(self) -> tuple[list[BinaryIO], list[str]]:
        """(the current file and the previous one, those that exist, opened together for reading:
        no rotation between the two opens; the caller closes them, one line per file refused:
        ``"journal.jsonl: a FIFO, not a regular file: not read"``). Never waits on what is at a
        path: opened non-blocking, a symbolic link not followed, anything but a regular file refused."""
        files: list[BinaryIO] = []
        refused: list[str] = []
        with self._files_lock:
            for path in (self.path, self.previous):
                try:
                    fd = _open_regular(path, os.O_RDONLY)
                except FileNotFoundError:
                    continue
                except OSError as exc:
                    refused.append(f"{path.name}: {_refusal(exc)}: not read")
                    continue
                files.append(os.fdopen(fd, "rb"))
        return files, refused

    # -- the writer thread ------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    due = self._repeats.deadline()
                    if due is None:
                        self._cond.wait()
                        continue
                    now = self._clock()
                    if now < due:
                        self._cond.wait(due - now)
                        continue
                    for out in self._repeats.expire(now):  # a window of repeats ended: their count
                        self._queue_line(out)
                if not self._queue:  # closed and nothing left
                    break
                data = self._queue.popleft()
                self._writing = True
            try:
                self._write(data)
            finally:
                with self._cond:
                    self._writing = False
                    self._cond.notify_all()

    def _write(self, data: bytes) -> None:
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            fd = _open_append(self.path)
            try:
                size = os.fstat(fd).st_size
                if size and size + len(data) > self.max_bytes:
                    os.close(fd)
                    fd = -1
                    with self._files_lock:
                        os.replace(self.path, self.previous)
                        fd = _open_append(self.path)
                elif size and os.pread(fd, 1, size - 1) != b"\n":
                    data = b"\n" + data  # end the line a crash tore: this one is whole
                _write_all(fd, data)  # one write of the whole line as a rule: O_APPEND, unbuffered
            finally:
                if fd >= 0:
                    os.close(fd)
            self.written += 1
        except OSError as exc:
            self._failed(_refusal(exc))

    def _failed(self, reason: str) -> None:
        self.write_errors += 1
        self.last_error = reason
        held = self._limit.allow()
        if held is not None:
            log.error("the safety journal %s could not be written: %s%s", self.path, reason, LogLimit.tail(held))


def _encode(line: dict[str, Any]) -> bytes:
    """One journal line: ``line`` as JSON (a value JSON has not written as its ``str``; a NaN
    raises ValueError) and its newline."""
    return (json.dumps(line, ensure_ascii=False, allow_nan=False, default=str) + "\n").encode("utf-8", "replace")


def _open_append(path: Path) -> int:
    """The journal's file opened to append (made if missing); a symbolic link, a FIFO, anything but
    a regular file is refused (:class:`NotRegularFile`: a failed write), never followed or waited on."""
    return _open_regular(path, os.O_RDWR | os.O_APPEND | os.O_CREAT)


def _write_all(fd: int, data: bytes) -> None:
    """All of ``data``: a write that takes part of it (a signal, the disk's last bytes) is
    followed by one for the rest; one that takes none, or fails, raises (a failed write)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        if n <= 0:
            raise OSError(errno.EIO, f"a write took {n} bytes of {len(view)}")
        view = view[n:]


class NotRegularFile(OSError):
    """What is at the journal's path is no regular file (a FIFO, a device, a directory, a symbolic
    link): refused, neither read nor written (a FIFO would block, a link write elsewhere)."""

    def __init__(self, what: str) -> None:
        super().__init__(errno.EINVAL, what)


_FILE_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
               (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _open_regular(path: Path, flags: int, mode: int = 0o644) -> int:
    """``os.open(path, flags)`` that never blocks (``O_NONBLOCK``: a FIFO's open waits for its other
    end without it), follows no symbolic link (``O_NOFOLLOW``) and refuses anything but a regular
    file (:class:`NotRegularFile`)."""
    try:
        fd = os.open(path, flags | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOFOLLOW", 0), mode)
    except OSError as exc:
        if exc.errno == errno.ELOOP:  # O_NOFOLLOW: the path is a symbolic link
            raise NotRegularFile("a symbolic link, not followed") from exc
        if exc.errno == errno.EISDIR:
            raise NotRegularFile("a directory, not a regular file") from exc
        raise
    try:
        kind = os.fstat(fd).st_mode
        if not stat.S_ISREG(kind):
            what = next((name for test, name in _FILE_KINDS if test(kind)), "something")
            raise NotRegularFile(f"{what}, not a regular file")
    except BaseException:
        os.close(fd)
        raise
    return fd


def _refusal(exc: OSError) -> str:
    """Why a file was not read or written, in one line."""
    return exc.strerror or str(exc) if isinstance(exc, NotRegularFile) else storage_reason(exc)


def read_journal(journal: SafetyJournal, limit: int) -> tuple[list[dict[str, Any]], int, list[str]]:
    """(the newest ``limit`` events of the journal, oldest first, each a line parsed; the number
    of lines skipped among those read: a torn last line, lines that are not a JSON object with a
    string ``event``; a line per file refused or unreadable, :meth:`SafetyJournal.open_for_reading`).
    Lines written meanwhile may or may not be in it. A read gives up after
    :data:`READ_MAX_SKIPPED` lines skipped (at most ``limit`` + that many examined): events
    beyond that much garbage are not found."""
    newest_first: list[dict[str, Any]] = []
    skipped = 0
    files, refused = journal.open_for_reading()
    try:
        for f in files:  # newest file first
            if len(newest_first) >= limit or skipped >= READ_MAX_SKIPPED:
                break
            for raw in _lines_backward(f):
                if len(newest_first) >= limit or skipped >= READ_MAX_SKIPPED:
                    break
                event = _parse(raw) if raw is not None else None
                if event is None:
                    skipped += 1
                else:
                    newest_first.append(event)
    finally:
        for f in files:
            f.close()
    return newest_first[::-1], skipped, refused


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")  # NaN, Infinity: the route's JSON answer could not carry them


def _parse(raw: bytes) -> dict[str, Any] | None:
    try:
        event = json.loads(raw, parse_constant=_no_constant)
    except (ValueError, RecursionError):  # not JSON, not UTF-8, NaN; nested beyond Python's stack
        return None
    return event if isinstance(event, dict) and isinstance(event.get("event"), str) else None


def _lines_backward(f: BinaryIO) -> Iterator[bytes | None]:
    """The lines of the file ``f``, last first, blank ones left out; None for a line skipped unread:
    the last one without its newline (torn), one longer than :data:`LINE_MAX_BYTES`. Reads back from
    the end in blocks, at most :data:`READ_MAX_BYTES` (a line begun before that is left out); an
    unreadable file has none."""
    try:
        pos = end = f.seek(0, os.SEEK_END)
        if end == 0:
            return
        f.seek(end - 1)
        torn = f.read(1) != b"\n"
        first = True  # the next segment is the one after the file's last newline
        tail = b""  # the end of a line whose start is not read yet
        dropping = False  # the line being read is too long: its start is dropped too
        while pos > 0 and end - pos < READ_MAX_BYTES:
            step = min(READ_BLOCK_BYTES, pos)
            pos -= step
            f.seek(pos)
            parts = (f.read(step) + tail).split(b"\n")
            tail, complete = parts[0], parts[1:]
            if dropping and complete:
                complete, dropping = complete[:-1], False  # the too long line's start
            elif dropping:
                tail = b""  # more of the too long line
            for line in reversed(complete):
                if first:  # b"" after the last newline, unless the line there is torn
                    first = False
                    if torn:
                        yield None
                elif len(line) > LINE_MAX_BYTES:  # its start was in ``tail``, its end in this block
                    yield None
                elif line.strip():
                    yield line
            if len(tail) > LINE_MAX_BYTES:
                first, tail, dropping = False, b"", True
                yield None
        if pos == 0 and not dropping:
            if first:  # no newline in the whole file
                yield None
            elif tail.strip():
                yield tail
    except OSError:
        return
