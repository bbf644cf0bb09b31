"""Campaign archive: one MCAP file per campaign, recorded from the bus (this module), read back
(:mod:`bridge.archive_read`) and recovered after a crash (:mod:`bridge.archive_recovery`).

File layout (readable by Foxglove and by :func:`bridge.archive_read.read_campaign`)
    - one channel per key, topic ``"/" + key``, ``message_encoding="json"``, with the key's JSON
      Schema (``encoding="jsonschema"``, name ``xneck.<Type>``) from :mod:`bridge.bus`;
    - ``log_time``: receive time at the recorder (``time.time_ns()``);
      ``publish_time``: the message's ``stamp_s`` in ns in the sender's clock (simulated time for
      the twin), or the log time if the stamp is negative; ``sequence``: the message's ``seq`` mod 2^32;
    - metadata ``xneck.campaign.start`` written first (so a crash keeps it), then ``xneck.campaign``
      and ``xneck.recorder`` (counters) when the campaign ends; see :data:`CAMPAIGN_KEYS`;
    - chunked, indexed, lz4-compressed when ``lz4`` is installed (zstandard is not a dependency).

Camera frames
    ``xneck/camera/frame`` (:class:`bridge.bus.CameraFrame`) is not stored as the bus message: each
    frame that passes :func:`bridge.bus.check_camera_frame` becomes a ``foxglove.CompressedImage``
    (JSON, schema :data:`COMPRESSED_IMAGE_SCHEMA`; ``timestamp`` the exposure, ``data`` the JPEG in
    base64) on :data:`IMAGE_TOPIC`, so Foxglove's Image panel plays the video beside the plots.
    The markers found on it are not archived (``/xneck/camera/alpha_ip`` has what they measured).
    At most :data:`FRAME_QUEUE_MAX` frames wait for the writer; more are dropped and counted.

What is recorded
    Only payloads that decode as their key's type of the contract (and, for α_IP, whose capture
    is not after its publication: :func:`bridge.bus.check_camera_alpha_stamps`). Unknown keys and rejected
    payloads are not written (a schema-less channel would break plots and replays); they are
    counted per key in ``xneck.recorder`` with the last reason, so their existence is on record.

Crash safety
    The recorder closes the open chunk and fsyncs at least every ``flush_period_s`` (1 s), so a
    killed recorder loses that much, plus what still waits in its queue: on an overloaded machine
    the writer thread lags, seconds of backlog (a fresh-clone CI run lost about 4 s). :func:`bridge.archive_recovery.recover` rewrites such a file as a valid,
    indexed one with outcome ``interrupted``. A writer holds an exclusive ``flock`` on its file
    for as long as it writes, so :func:`writer_alive` tells a live recording (never to be
    "recovered") from a dead one; the kernel drops the lock when the writer dies.

Storage faults
    A write that fails (ENOSPC, EROFS, EIO) ends the recording: the writer thread stops, calls
    ``on_error`` (the campaign runner stops the campaign) and :meth:`CampaignRecorder.stop` raises
    :class:`ArchiveError` naming the fault (:func:`storage_reason`). The file is left unfinished,
    its flushed chunks intact: :func:`bridge.archive_recovery.finish_in_place` finishes it where it
    lies, with no room for a copy (the console does at once, outcome ``failed``), or
    :func:`bridge.archive_recovery.recover` by a copy. Small files next to the archives (indexes,
    records) are written with :func:`atomic_write`.
"""

from __future__ import annotations

import collections
import contextlib
import datetime as dt
import errno
import fcntl
import os
import queue
import stat
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any, BinaryIO

import msgspec
import zenoh
from mcap.writer import CompressionType, Writer

from bridge import bus
from bridge.session import camera_of, controller_of, run_of

try:  # lz4 comes with mcap; keep the archive writable without it.
    import lz4.frame  # noqa: F401

    COMPRESSION = CompressionType.LZ4
except ImportError:  # pragma: no cover
    COMPRESSION = CompressionType.NONE

MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])
PROFILE = "xneck"
CAMPAIGN_START = "xneck.campaign.start"
CAMPAIGN = "xneck.campaign"
RECORDER = "xneck.recorder"
RECOVERY = "xneck.recovery"
#: Keys of the ``xneck.campaign`` metadata record (all values are strings).
CAMPAIGN_KEYS = (
    "campaign_id", "kind", "law", "trajectory", "parameter_set", "software_version",
    "start_time", "end_time", "outcome",
)
#: Conventional outcomes; ``interrupted`` is set by :func:`bridge.archive_recovery.recover`.
OUTCOMES = ("finished", "aborted", "failed", "interrupted")
CHUNK_SIZE = 256 * 1024
IMAGE_TOPIC = "/xneck/camera/image"
IMAGE_SCHEMA_NAME = "foxglove.CompressedImage"
#: Foxglove's JSON Schema of ``foxglove.CompressedImage`` (the required fields of the published
#: schemas/jsonschema/CompressedImage.json; the installed packages do not ship Foxglove's schemas).
#: Foxglove picks its image decoder by the schema name; bytes travel as base64 in JSON.
COMPRESSED_IMAGE_SCHEMA: dict[str, Any] = {
    "title": IMAGE_SCHEMA_NAME, "description": "A compressed image", "type": "object",
    "properties": {
        "timestamp": {"type": "object", "title": "time", "description": "Timestamp of image", "properties": {
            "sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}},
        "frame_id": {"type": "string", "description": "Frame of reference for the image"},
        "data": {"type": "string", "contentEncoding": "base64", "description": "Compressed image data"},
        "format": {"type": "string", "description": "Image format"},
    },
    "required": ["timestamp", "frame_id", "data", "format"],
}
# Messages waiting for the writer thread. A lockstep campaign publishes about 1600 a second; on a
# loaded machine (a bus campaign beside two CPU-bound benchmarks, 2026-11-26) the writer stalled
# long enough to fill 20 000 and dropped 66 321 messages (40 %), and the analysis failed. 100 000
# hold a minute of stall at about 35 MB (entries of ~350 B); past that the recorder drops and counts.
QUEUE_MAX = 100_000
# The last second an MCAP time (uint64 ns, kept below 2^63) can hold: a valid bus message may be
# stamped 1e300 s, and int(1e300 * 1e9) killed the writer thread (audit of 2026-11-26).
MAX_STAMP_S = 9.2e9
FRAME_QUEUE_MAX = 8  # frames (≤ 1.4 MB each on the wire) waiting for the writer: bounds the recorder's memory
# How long a stop named after a campaign's end event waits for the recorder's own subscriber to have
# it (CampaignRecorder.stop's ``end_of``); its thread is at most the backlog of one loaded moment behind.
END_WAIT_S = 5.0
ENDS_KEPT = 16  # campaign ids whose end event the recorder heard, the latest (a flood of forged ends stays bounded)


def compressed_image(stamp_s: float, frame_id: str, data: bytes, image_format: str = "jpeg") -> bytes:
    """JSON of one ``foxglove.CompressedImage``; ``stamp_s`` (within [0, 2^63) ns, else 0) becomes
    its ``timestamp``."""
    ns = round(stamp_s * 1e9) if 0.0 <= stamp_s < MAX_STAMP_S else 0
    return msgspec.json.encode({"timestamp": {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000},
                                "frame_id": frame_id, "data": data, "format": image_format})


class ArchiveError(Exception):
    """A campaign file cannot be read or written; names the file and the reason."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        super().__init__(f"{os.fspath(path)}: {reason}")
        self.path = Path(path)
        self.reason = reason

    def __reduce__(self) -> tuple[Any, tuple[type[ArchiveError], tuple[Any, ...], dict[str, Any]]]:
        # rebuilt as it is, not through its constructor from its message (the default, a TypeError):
        # an analysis' process hands it over (server/analysis_process.py)
        return _rebuilt_error, (type(self), self.args, dict(self.__dict__))


def _rebuilt_error(cls: type[ArchiveError], args: tuple[Any, ...], state: dict[str, Any]) -> ArchiveError:
    error = cls.__new__(cls)
    error.args = args
    error.__dict__.update(state)
    return error


def software_version() -> str:
    """Version of the installed xneck package (``unknown`` when run from a bare checkout)."""
    try:
        return importlib_metadata.version("xneck")
    except importlib_metadata.PackageNotFoundError:
        return "unknown"


def iso_time(time_ns: int | None = None) -> str:
    """UTC ISO 8601 time of ``time_ns`` (now if None), with microseconds."""
    t = time.time_ns() if time_ns is None else time_ns
    return dt.datetime.fromtimestamp(t / 1e9, tz=dt.UTC).isoformat(timespec="microseconds")


def storage_reason(exc: BaseException) -> str:
    """One line for a storage fault: ``No space left on device (ENOSPC)``; other errors as repr."""
    if isinstance(exc, OSError) and exc.errno is not None and exc.errno in errno.errorcode:
        return f"{exc.strerror or os.strerror(exc.errno)} ({errno.errorcode[exc.errno]})"
    return f"{type(exc).__name__}: {exc}"


def atomic_write(path: str | os.PathLike[str], data: bytes) -> None:
    """Replace ``path`` by ``data`` so that a crash or a full disk leaves the old or the new
    content, never a mix: write a temporary file beside it, fsync, rename, fsync the directory.
    Raises the ``OSError`` (the old file is intact and no temporary file remains)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    fsync_dir(path.parent)


def writer_alive(path: str | os.PathLike[str]) -> bool:
    """Whether a live process (this one included) is writing ``path`` (it holds the writer's flock).
    Anything but a regular file is written by nobody: opening a FIFO had blocked the console's
    start for ever (review of session 53); opened non-blocking, in case one is swapped in."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return False
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        return False
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return False
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
    return False


def _check_metadata(path: Path, metadata: Mapping[str, str]) -> dict[str, str]:
    bad = {k: v for k, v in metadata.items() if not isinstance(k, str) or not isinstance(v, str)}
    if bad:
        raise ArchiveError(path, f"metadata keys and values must be strings, got {bad!r}")
    return dict(metadata)


class ArchiveWriter:
    """An MCAP writer that registers one schema and channel per key on first use."""

    def __init__(self, path: Path, chunk_size: int = CHUNK_SIZE) -> None:
        self.path = path
        try:
            self._file: BinaryIO = open(path, "xb")  # noqa: SIM115 - held until close(); "x": never overwrite a campaign
        except OSError as exc:
            raise ArchiveError(path, f"cannot create the file ({storage_reason(exc)})") from None
        # Held until the file is closed (or the process dies): tells recovery the writer is alive.
        fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        self.writer = Writer(self._file, chunk_size=chunk_size, compression=COMPRESSION)
        self.writer.start(profile=PROFILE, library=f"xneck/{software_version()}")
        self._channels: dict[str, int] = {}
        self.count = 0

    def channel(self, key: str, msg_type: type[bus.BusMessage]) -> int:
        channel_id = self._channels.get(key)
        if channel_id is None and msg_type is bus.CameraFrame:
            schema_id = self.writer.register_schema(name=IMAGE_SCHEMA_NAME, encoding="jsonschema",
                                                    data=msgspec.json.encode(COMPRESSED_IMAGE_SCHEMA))
            channel_id = self._channels[key] = self.writer.register_channel(
                topic=IMAGE_TOPIC, message_encoding="json", schema_id=schema_id,
                metadata={"key": key, "version": str(bus.schema_version(msg_type))})
        if channel_id is None:
            schema_id = self.writer.register_schema(
                name=bus.schema_name(msg_type), encoding="jsonschema", data=bus.json_schema_bytes(msg_type)
            )
            channel_id = self.writer.register_channel(
                topic=bus.mcap_topic(key), message_encoding="json", schema_id=schema_id,
                metadata={"key": key, "version": str(bus.schema_version(msg_type))},
            )
            self._channels[key] = channel_id
        return channel_id

    def add(self, key: str, msg: bus.BusMessage, data: bytes, log_time_ns: int) -> None:
        if isinstance(msg, bus.CameraFrame):  # Foxglove's image message, not the bus's
            data = compressed_image(msg.capture_stamp_s, msg.frame_id, msg.data, msg.format)
        stamp_s = msg.stamp_s
        publish_ns = int(stamp_s * 1e9) if 0.0 <= stamp_s < MAX_STAMP_S else log_time_ns
        self.writer.add_message(
            channel_id=self.channel(key, type(msg)), log_time=log_time_ns, data=data,
            publish_time=publish_ns, sequence=msg.seq % 2**32,
        )
        self.count += 1

    def flush(self, fsync: bool = True) -> None:
        self.writer.flush()
        self._file.flush()  # out of Python's buffer, so that fsync covers it and a full disk shows now
        if fsync:
            os.fsync(self._file.fileno())

    def finish(self) -> None:
        try:
            self.writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._file.close()

    def abandon(self) -> None:
        with contextlib.suppress(OSError):  # closing flushes the buffer, which fails again on a full disk
            self._file.close()


@dataclass(frozen=True)
class RecorderStats:
    """Counters of a recorder. ``dropped`` samples found the queue full (writer too slow)."""

    received: int
    recorded: int
    dropped: int
    rejected: dict[str, int]
    last_reject_reason: str
    skipped: int = 0  # valid messages ``keep`` turned away (another bridge's, controller's or twin's)


class CampaignRecorder:
    """Records every message of the bus matching ``keys`` into one MCAP file, from construction
    until :meth:`stop`.

    The Zenoh callback only time-stamps and enqueues (bounded queue; a full queue drops and counts).
    A daemon writer thread decodes, writes, and closes the chunk every ``flush_period_s``.
    ``metadata`` (strings) should carry the :data:`CAMPAIGN_KEYS` known at start; it is written at
    once as ``xneck.campaign.start``. ``keep(key, message, run, camera, controller)``, if given, says which
    decoded messages are written (the others are counted, ``skipped``): a campaign's own bridge and
    controller only, its twin's truth and one camera; ``run`` is the bridge run the sample names in
    its attachment (:func:`bridge.session.run_of`: the twin's ``Truth``), ``camera`` the camera
    process it names (:func:`bridge.session.camera_of`: its α_IP), ``controller`` the controller a
    ``ControllerStatus`` names (:func:`bridge.session.controller_of`), each '' if none.
    Use as a context manager or call :meth:`stop`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        path: str | os.PathLike[str],
        metadata: Mapping[str, str],
        keys: Iterable[str] = (bus.ALL,),
        *,
        queue_size: int = QUEUE_MAX,
        flush_period_s: float = 1.0,
        chunk_size: int = CHUNK_SIZE,
        on_error: Callable[[BaseException], None] | None = None,
        keep: Callable[[str, bus.BusMessage, str, str, str], bool] | None = None,
    ) -> None:
        self.path = Path(path)
        self._keep = keep  # the writer thread's filter of decoded messages (None: all); counted as skipped
        self._skipped = 0
        self._metadata = _check_metadata(self.path, metadata)
        self._metadata.setdefault("software_version", software_version())
        self._metadata.setdefault("start_time", iso_time())
        self._flush_period_s = flush_period_s
        self._queue: queue.Queue[tuple[str, bytes, int, str, str, str] | None] = queue.Queue(maxsize=queue_size)
        self._received = self._dropped = 0
        self._frames_queued = 0
        self._rejected: dict[str, int] = {}
        self._last_reason = ""
        self._lock = threading.Lock()
        self._stopped = False
        self._error: BaseException | None = None
        self._on_error = on_error
        self._ends: collections.deque[str] = collections.deque(maxlen=ENDS_KEPT)  # see stop's end_of
        self._end_heard = threading.Condition(self._lock)

        self._out = ArchiveWriter(self.path, chunk_size)
        try:
            self._out.writer.add_metadata(CAMPAIGN_START, self._metadata)
            self._out.flush()
        except OSError as exc:
            self._out.abandon()
            raise ArchiveError(self.path, f"recording failed: {storage_reason(exc)}") from exc
        self._thread = threading.Thread(target=self._run, name=f"recorder:{self.path.name}", daemon=True)
        self._thread.start()
        self._subs = [session.declare_subscriber(k, self._on_sample) for k in keys]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        now_ns = time.time_ns()
        key = str(sample.key_expr)
        frame = key == bus.CAMERA_FRAME
        with self._lock:
            if frame and self._frames_queued >= FRAME_QUEUE_MAX:  # a flood of large frames must not fill memory
                self._dropped += 1
                return
            self._frames_queued += frame
        msg_type = bus.message_type(key)
        try:
            if msg_type is not None:  # a huge payload is refused before it is copied (bus.PAYLOAD_MAX_BYTES)
                bus.check_payload_size(msg_type, len(sample.payload))
            run, camera = (run_of(sample), camera_of(sample)) if self._keep else ("", "")
            controller = controller_of(sample) if self._keep and key == bus.CONTROLLER_STATUS else ""
            payload = sample.payload.to_bytes()
            self._queue.put_nowait((key, payload, now_ns, run, camera, controller))
            if key == bus.CAMPAIGN_EVENTS:  # after it is queued: all before it is (stop's end_of)
                self._note_end(payload)
        except bus.BusDecodeError as exc:
            with self._lock:
                self._received += 1
                self._frames_queued -= frame
            self._reject(key, exc.reason)
            return
        except queue.Full:
            with self._lock:
                self._dropped += 1
                self._frames_queued -= frame
            if key == bus.CAMPAIGN_EVENTS:  # dropped, but what came before it was dealt with
                self._note_end(payload)
            return
        with self._lock:
            self._received += 1

    def _note_end(self, payload: bytes) -> None:
        """Note the campaign an end event (finished, aborted) names; a malformed one is the writer's
        to reject, as any other."""
        try:
            ev = bus.decode(bus.CampaignEvent, payload)
        except bus.BusDecodeError:
            return
        if ev.event in ("finished", "aborted"):
            with self._end_heard:
                self._ends.append(ev.campaign_id)
                self._end_heard.notify_all()

    def _reject(self, key: str, reason: str) -> None:
        with self._lock:
            self._rejected[key] = self._rejected.get(key, 0) + 1
            self._last_reason = f"{key}: {reason}"

    def _run(self) -> None:
        last_flush = time.monotonic()
        try:
            while True:
                try:
                    item = self._queue.get(timeout=min(0.1, self._flush_period_s))
                except queue.Empty:
                    item = ()
                if item is None:
                    return
                if item:
                    key, payload, log_time_ns, run, camera, controller = item
                    if key == bus.CAMERA_FRAME:
                        with self._lock:
                            self._frames_queued -= 1
                    msg_type = bus.message_type(key)
                    if msg_type is None:
                        self._reject(key, "no message type is registered for this key")
                    else:
                        try:
                            msg = bus.decode(msg_type, payload)
                            if isinstance(msg, bus.CameraFrame):
                                bus.check_camera_frame(msg)  # Foxglove would show garbage
                            elif isinstance(msg, bus.CameraAlpha):
                                bus.check_camera_alpha_stamps(msg)  # a stray's absurd capture: not a clock step
                        except bus.BusDecodeError as exc:
                            self._reject(key, exc.reason)
                        else:
                            if self._keep is None or self._keep(key, msg, run, camera, controller):
                                self._out.add(key, msg, payload, log_time_ns)
                            else:
                                self._skipped += 1
                if time.monotonic() - last_flush >= self._flush_period_s:
                    self._out.flush()
                    last_flush = time.monotonic()
        except BaseException as exc:  # noqa: BLE001 - reported by stop(), not lost in a thread
            self._error = exc
            if self._on_error is not None:
                with contextlib.suppress(Exception):
                    self._on_error(exc)

    @property
    def stats(self) -> RecorderStats:
        with self._lock:
            return RecorderStats(
                received=self._received, recorded=self._out.count, dropped=self._dropped,
                rejected=dict(self._rejected), last_reject_reason=self._last_reason, skipped=self._skipped,
            )

    def stop(self, outcome: str = "finished", extra_metadata: Mapping[str, str] | None = None,
             timeout_s: float = 10.0, *, final_metadata: Callable[[], Mapping[str, str]] | None = None,
             end_of: str = "") -> Path:
        """Stop recording, write the ``xneck.campaign`` and ``xneck.recorder`` records and finish
        the file. ``extra_metadata`` (strings) is merged into ``xneck.campaign``, then what
        ``final_metadata`` returns, asked once the writer has written its last message: what says
        what the file holds (the α_IP recorded, server.campaign_runner) is not asked while a
        backlog still waits. ``end_of``: the campaign whose end event the caller heard; the stop
        first waits (up to :data:`END_WAIT_S`) until the recorder's own subscriber has it too. Why:
        each subscriber's callback runs in its own thread (zenoh-python's default), so the caller
        may hear the end while the recorder's thread still has what came before it, such as the
        controller's final timing (the official CI of stop 64 lost it). Idempotent."""
        if self._stopped:
            return self.path
        if end_of:
            with self._end_heard:
                self._end_heard.wait_for(lambda: end_of in self._ends, END_WAIT_S)
        self._stopped = True
        for sub in self._subs:
            sub.undeclare()
        # The sentinel must get in even if the queue is full: make room by dropping the oldest.
        while True:
            try:
                self._queue.put(None, timeout=0.1)
                break
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self._queue.get_nowait()
                    with self._lock:
                        self._dropped += 1
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            self._out.abandon()
            raise ArchiveError(self.path, f"the writer thread did not stop within {timeout_s} s")
        if self._error is not None:
            self._out.abandon()
            raise ArchiveError(self.path, f"recording failed: {storage_reason(self._error)}") from self._error
        final = dict(self._metadata)
        final.update(_check_metadata(self.path, extra_metadata or {}))
        if final_metadata is not None:
            final.update(_check_metadata(self.path, final_metadata()))
        final["end_time"] = iso_time()
        final["outcome"] = outcome
        stats = self.stats
        try:
            # The open chunk first: a metadata record goes to the file at once, so written before
            # the last chunk it claimed messages a full disk then lost (audit of 2026-11-26).
            self._out.flush()
            self._out.writer.add_metadata(CAMPAIGN, final)
            self._out.writer.add_metadata(RECORDER, {
                "received": str(stats.received), "recorded": str(stats.recorded), "dropped": str(stats.dropped),
                "rejected": msgspec.json.encode(stats.rejected).decode(),
                "last_reject_reason": stats.last_reject_reason, "skipped": str(stats.skipped),
            })
            self._out.finish()
        except OSError as exc:  # the file stays as it is: recover() salvages its flushed chunks
            self._out.abandon()
            raise ArchiveError(self.path, f"finishing failed: {storage_reason(exc)}") from exc
        return self.path

    def __enter__(self) -> CampaignRecorder:
        return self

    def __exit__(self, exc_type: object, *_exc: object) -> None:
        self.stop("finished" if exc_type is None else "failed")


def write_campaign(
    path: str | os.PathLike[str],
    messages: Iterable[tuple[str, int, bus.BusMessage]],
    metadata: Mapping[str, str],
    *,
    chunk_size: int = CHUNK_SIZE,
) -> Path:
    """Write a campaign offline (tests, replays, conversions).

    ``messages``: ``(key, log_time_ns, message)`` in log-time order. ``metadata`` becomes the
    ``xneck.campaign`` record (``software_version`` and ``outcome`` default to the installed
    version and ``finished``).
    """
    path = Path(path)
    meta = _check_metadata(path, metadata)
    meta.setdefault("software_version", software_version())
    meta.setdefault("outcome", "finished")
    out = ArchiveWriter(path, chunk_size)
    try:
        out.writer.add_metadata(CAMPAIGN_START, meta)
        for key, log_time_ns, msg in messages:
            expected = bus.message_type(key)
            if expected is None or type(msg) is not expected:
                raise ArchiveError(path, f"{key!r} does not carry {type(msg).__name__}")
            out.add(key, msg, bus.encode(msg), int(log_time_ns))
        out.writer.add_metadata(CAMPAIGN, meta)
        out.finish()
    except BaseException:
        out.abandon()
        path.unlink(missing_ok=True)
        raise
    return path


def fsync_dir(directory: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

__all__ = [
    "CAMPAIGN", "CAMPAIGN_KEYS", "CAMPAIGN_START", "COMPRESSED_IMAGE_SCHEMA", "IMAGE_SCHEMA_NAME", "IMAGE_TOPIC",
    "OUTCOMES", "RECORDER", "RECOVERY",
    "ArchiveError", "ArchiveWriter", "CampaignRecorder", "RecorderStats", "atomic_write", "compressed_image",
    "fsync_dir", "iso_time", "software_version", "storage_reason", "write_campaign", "writer_alive",
]
