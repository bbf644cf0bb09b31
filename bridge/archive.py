"""Campaign archive: one MCAP file per campaign, recorded from the bus, read back, and recovered.

File layout (readable by Foxglove and by :func:`read_campaign`)
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
    Only payloads that decode as their key's type of the contract. Unknown keys and rejected
    payloads are not written (a schema-less channel would break plots and replays); they are
    counted per key in ``xneck.recorder`` with the last reason, so their existence is on record.

Crash safety
    The recorder closes the open chunk and fsyncs at least every ``flush_period_s`` (1 s), so a
    killed recorder loses that much, plus what still waits in its queue: on an overloaded machine
    the writer thread lags, seconds of backlog (a fresh-clone CI run lost about 4 s). :func:`recover` rewrites such a file as a valid,
    indexed one with outcome ``interrupted``. A writer holds an exclusive ``flock`` on its file
    for as long as it writes, so :func:`writer_alive` tells a live recording (never to be
    "recovered") from a dead one; the kernel drops the lock when the writer dies.

Storage faults
    A write that fails (ENOSPC, EROFS, EIO) ends the recording: the writer thread stops, calls
    ``on_error`` (the campaign runner stops the campaign) and :meth:`CampaignRecorder.stop` raises
    :class:`ArchiveError` naming the fault (:func:`storage_reason`). Small files next to the
    archives (indexes, records) are written with :func:`atomic_write`.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import fcntl
import os
import queue
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any, BinaryIO

import msgspec
import numpy as np
import zenoh
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from bridge import bus

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
#: Conventional outcomes; ``interrupted`` is set by :func:`recover`.
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
    _fsync_dir(path.parent)


def writer_alive(path: str | os.PathLike[str]) -> bool:
    """Whether a live process (this one included) is writing ``path`` (it holds the writer's flock)."""
    try:
        with open(path, "rb") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    except FileNotFoundError:
        return False
    return False


def _check_metadata(path: Path, metadata: Mapping[str, str]) -> dict[str, str]:
    bad = {k: v for k, v in metadata.items() if not isinstance(k, str) or not isinstance(v, str)}
    if bad:
        raise ArchiveError(path, f"metadata keys and values must be strings, got {bad!r}")
    return dict(metadata)


class _ArchiveWriter:
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


class CampaignRecorder:
    """Records every message of the bus matching ``keys`` into one MCAP file, from construction
    until :meth:`stop`.

    The Zenoh callback only time-stamps and enqueues (bounded queue; a full queue drops and counts).
    A daemon writer thread decodes, writes, and closes the chunk every ``flush_period_s``.
    ``metadata`` (strings) should carry the :data:`CAMPAIGN_KEYS` known at start; it is written at
    once as ``xneck.campaign.start``. Use as a context manager or call :meth:`stop`.
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
    ) -> None:
        self.path = Path(path)
        self._metadata = _check_metadata(self.path, metadata)
        self._metadata.setdefault("software_version", software_version())
        self._metadata.setdefault("start_time", iso_time())
        self._flush_period_s = flush_period_s
        self._queue: queue.Queue[tuple[str, bytes, int] | None] = queue.Queue(maxsize=queue_size)
        self._received = self._dropped = 0
        self._frames_queued = 0
        self._rejected: dict[str, int] = {}
        self._last_reason = ""
        self._lock = threading.Lock()
        self._stopped = False
        self._error: BaseException | None = None
        self._on_error = on_error

        self._out = _ArchiveWriter(self.path, chunk_size)
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
            self._queue.put_nowait((key, sample.payload.to_bytes(), now_ns))
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
            return
        with self._lock:
            self._received += 1

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
                    key, payload, log_time_ns = item
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
                        except bus.BusDecodeError as exc:
                            self._reject(key, exc.reason)
                        else:
                            self._out.add(key, msg, payload, log_time_ns)
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
                rejected=dict(self._rejected), last_reject_reason=self._last_reason,
            )

    def stop(self, outcome: str = "finished", extra_metadata: Mapping[str, str] | None = None,
             timeout_s: float = 10.0) -> Path:
        """Stop recording, write the ``xneck.campaign`` and ``xneck.recorder`` records and finish
        the file. ``extra_metadata`` (strings) is merged into ``xneck.campaign``. Idempotent."""
        if self._stopped:
            return self.path
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
                "last_reject_reason": stats.last_reject_reason,
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
    out = _ArchiveWriter(path, chunk_size)
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


# --- reading ----------------------------------------------------------------------------------


@dataclass
class Campaign:
    """A campaign read back. ``topics`` maps each MCAP topic to ``[(log_time_ns, message), ...]``
    in log-time order; messages of the contract are decoded to their types, others (written by
    other tools) to plain JSON values."""

    path: Path
    metadata: dict[str, dict[str, str]]
    topics: dict[str, list[tuple[int, Any]]]
    schemas: dict[str, str] = field(default_factory=dict)

    @property
    def info(self) -> dict[str, str]:
        """The ``xneck.campaign`` record (falls back to ``xneck.campaign.start``)."""
        return self.metadata.get(CAMPAIGN) or self.metadata.get(CAMPAIGN_START, {})

    def messages(self, key: str) -> list[tuple[int, Any]]:
        """Messages of a key (``xneck/motor/state``) or topic (``/xneck/motor/state``)."""
        return self.topics.get(bus.mcap_topic(key), [])

    def series(self, key: str, field_name: str) -> tuple[np.ndarray, np.ndarray]:
        """``(log_time_ns int64 (N,), values (N, ...))`` of one field over a key's messages."""
        msgs = self.messages(key)
        t = np.array([t for t, _ in msgs], dtype=np.int64)
        values = np.array([getattr(m, field_name) for _, m in msgs])
        return t, values


def _check_file(path: Path) -> int:
    if not path.exists():
        raise ArchiveError(path, "no such file")
    if not path.is_file():
        raise ArchiveError(path, "not a regular file")
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
    if head != MAGIC:
        raise ArchiveError(path, "not an MCAP file (bad magic at the start)")
    return size


def is_complete(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is an MCAP file that was finished (magic at both ends). Raises
    :class:`ArchiveError` if it is missing or not MCAP at all."""
    path = Path(path)
    size = _check_file(path)
    if size < 2 * len(MAGIC):
        return False
    with open(path, "rb") as f:
        f.seek(size - len(MAGIC))
        return f.read() == MAGIC


def read_campaign(path: str | os.PathLike[str]) -> Campaign:
    """Read a finished campaign file. Raises :class:`ArchiveError` for a missing, non-MCAP,
    truncated or unfinished file (run :func:`recover` on the latter two), or a message that does
    not match its schema."""
    path = Path(path)
    if not is_complete(path):
        raise ArchiveError(path, "truncated or unfinished MCAP file (no footer): if its recording was "
                                 "interrupted, copy it into <data dir>/campaigns/ and start `xneck server` (or "
                                 "`xneck up`): the console repairs such files at start-up, as interrupted campaigns")
    topics: dict[str, list[tuple[int, Any]]] = {}
    schemas: dict[str, str] = {}
    metadata: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            reader = SeekingReader(f, validate_crcs=True)
            for record in reader.iter_metadata():
                metadata[record.name] = dict(record.metadata)  # the last record of a name wins
            # In file order, then each topic sorted by log time: the order mcap's log_time_order=True
            # gives (ties in file order; the sort is stable), without its Python heap, which took half
            # of the read (1.4 of 2.7 s for a 14 s control campaign).
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                topic = channel.topic
                if topic not in topics:
                    topics[topic] = []
                    schemas[topic] = schema.name if schema is not None else ""
                topics[topic].append((message.log_time, _decode_archived(path, channel, message)))
        for msgs in topics.values():
            msgs.sort(key=_log_time)
    except ArchiveError:
        raise
    except Exception as exc:  # noqa: BLE001 - mcap raises many types on a damaged file
        raise ArchiveError(path, f"damaged MCAP file ({type(exc).__name__}: {exc})") from None
    return Campaign(path=path, metadata=metadata, topics=topics, schemas=schemas)


def _log_time(item: tuple[int, Any]) -> int:
    return item[0]


def _decode_archived(path: Path, channel: Channel, message: Message) -> Any:
    msg_type = bus.message_type(bus.key_of_topic(channel.topic))
    if msg_type is None or channel.message_encoding != "json":
        if channel.message_encoding == "json":
            try:
                return msgspec.json.decode(message.data)
            except msgspec.DecodeError as exc:
                raise ArchiveError(path, f"{channel.topic}: invalid JSON ({exc})") from None
        return bytes(message.data)
    try:
        return bus.decode(msg_type, message.data)
    except bus.BusDecodeError as exc:
        raise ArchiveError(path, f"{channel.topic} at log time {message.log_time} ns: {exc.reason}") from None


# --- recovery ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecoveryReport:
    """What :func:`recover` did. ``status``: ``valid`` (finished file, untouched) or ``recovered``.

    ``bytes_discarded``: bytes after the last complete record (the chunk in progress at the
    crash). A chunk whose content is damaged (CRC or decompression failure) but whose framing is
    intact is skipped and reading goes on; damaged framing ends the salvage. ``corrupt_copy``: the
    original, kept only when something was damaged (not merely cut short), since a specialised
    tool might salvage more; a plain truncation keeps nothing, the discarded tail being an
    incomplete chunk. ``reason`` tells where reading stopped and which chunks were skipped.
    """

    path: Path
    status: str
    messages: int
    bytes_discarded: int = 0
    reason: str = ""
    corrupt_copy: Path | None = None


def recover(path: str | os.PathLike[str]) -> RecoveryReport:
    """Make ``path`` a valid, indexed campaign file, in place; idempotent.

    A finished file is left untouched (status ``valid``). An unfinished one (recorder killed) is
    read sequentially; every message of a complete chunk and every metadata record is rewritten
    to a temporary file that atomically replaces the original. Unless the file already holds a
    final ``xneck.campaign`` record, one is added from ``xneck.campaign.start`` with outcome
    ``interrupted`` and ``end_time`` the last message's log time. An ``xneck.recovery`` record
    tells what was salvaged. Raises :class:`ArchiveError` if the file is missing or not MCAP.
    """
    path = Path(path)
    if is_complete(path):
        try:
            # MCAP-level check only: a message of another schema version is no reason to rewrite.
            with open(path, "rb") as f:
                reader = SeekingReader(f, validate_crcs=True)
                for _ in reader.iter_metadata():
                    pass
                count = sum(1 for _ in reader.iter_messages(log_time_order=False))
        except Exception:  # noqa: BLE001 - a footer but a damaged body: salvage below
            pass
        else:
            return RecoveryReport(path=path, status="valid", messages=count)
    size = path.stat().st_size
    tmp = path.with_name(path.name + ".recovering")
    tmp.unlink(missing_ok=True)
    out = _ArchiveWriter(tmp)
    try:
        salvage = _Salvage(out)
        stop_reason, damaged = salvage.copy_from(path, size)
        if not salvage.header_seen:
            raise ArchiveError(path, f"no readable MCAP header, nothing to recover ({stop_reason})")
        recovery = {"recovered_at": iso_time(), "original_bytes": str(size),
                    "bytes_discarded": str(size - salvage.good_end), "messages": str(salvage.kept),
                    "reason": stop_reason}
        final = salvage.held.get(CAMPAIGN)
        if final is None:
            final = dict(salvage.start_metadata)
            last = salvage.last_log_ns
            final["end_time"] = iso_time(last) if last is not None else final.get("start_time", "")
            final["outcome"] = "interrupted"
        elif salvage.lost_messages() and final.get("outcome") != "interrupted":
            # A final record written before messages that never reached the disk is not the truth.
            recovery["outcome_before"] = final.get("outcome", "")
            final = {**final, "outcome": "interrupted"}
        out.writer.add_metadata(CAMPAIGN, final)
        for name, record in salvage.held.items():
            if name != CAMPAIGN:
                out.writer.add_metadata(name, record)
        out.writer.add_metadata(RECOVERY, recovery)
        out.finish()
    except BaseException:
        out.abandon()
        tmp.unlink(missing_ok=True)
        raise
    corrupt_copy = _keep_corrupt(path) if damaged else None
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    return RecoveryReport(
        path=path, status="recovered", messages=salvage.kept, bytes_discarded=size - salvage.good_end,
        reason=stop_reason, corrupt_copy=corrupt_copy,
    )


def _keep_corrupt(path: Path) -> Path:
    """A hard link to the damaged ``path`` under the first free name of ``NAME.corrupt``,
    ``NAME.corrupt.1``, …: a file damaged again after its recovery keeps both originals (the
    second replaced the first before; audit of 2026-11-27). A link, not a rename, so the campaign
    has a file under its name at every instant until the salvaged one replaces it."""
    for i in range(10_000):
        candidate = path.with_name(path.name + ".corrupt" + (f".{i}" if i else ""))
        try:
            os.link(path, candidate)
        except FileExistsError:
            continue
        except OSError:  # no hard links there (FAT, some network mounts): a rename to a free name
            if candidate.exists():
                continue
            os.rename(path, candidate)
        return candidate
    raise ArchiveError(path, "10000 damaged copies of it are kept already: nothing more is kept; remove some")


class _Salvage:
    """Copies every complete record of a damaged or unfinished MCAP file to a writer, streaming
    (a campaign may not fit in memory): schemas and channels get new ids, each chunk is parsed
    whole before any of its messages is written, so a chunk is kept entirely or not at all."""

    def __init__(self, out: _ArchiveWriter) -> None:
        self.out = out
        self.header_seen = False
        self.good_end = len(MAGIC)  # the reader checks the magic first
        self.kept = 0
        self.last_log_ns: int | None = None
        self.metadata_names: set[str] = set()
        self.skipped: list[str] = []
        self.start_metadata: dict[str, str] = {}
        self._schema_ids: dict[int, int] = {}
        self._channel_ids: dict[int, int] = {}
        self._topic_channels: dict[str, int] = {}  # topic -> channel id in the output
        self._inferred: dict[int, int | None] = {}  # lost channel id -> the one its messages' key gave
        self.held: dict[str, dict[str, str]] = {}  # the final records, written after every message
        self.damaged_chunks = False

    def copy_from(self, path: Path, size: int) -> tuple[str, bool]:
        """Returns why reading stopped, and whether it was damage rather than the end of the file."""
        with open(path, "rb") as f:
            try:
                for record in StreamReader(f, emit_chunks=True, validate_crcs=True).records:
                    if isinstance(record, Chunk):
                        try:
                            inner = breakup_chunk(record, validate_crc=True)
                        except Exception as exc:  # CRC or decompression failure
                            if f.tell() > size:
                                raise
                            # The chunk's framing is intact (its length led to the next record):
                            # skip its content, carry on with the next chunk.
                            self.skipped.append(f"chunk at byte {self.good_end} ({type(exc).__name__})")
                            self.damaged_chunks = True
                            inner = []
                        for r in inner:
                            self._copy(r)
                    else:
                        self._copy(record)
                    self.good_end = f.tell()
            except Exception as exc:  # noqa: BLE001 - mcap raises many types on a damaged file
                # mcap reads short records without complaint and fails later, so tell a
                # truncation (the record at good_end runs past the end of the file) from damage.
                if self.good_end == size:
                    return self._reason("end of file at a record boundary"), bool(self.skipped)
                if _runs_past_end(f, self.good_end, size):
                    return self._reason(f"truncated inside the record at byte {self.good_end}"), bool(self.skipped)
                return self._reason(f"damaged record at byte {self.good_end} ({type(exc).__name__}: {exc})"), True
            self.good_end = f.tell()  # past the closing magic
        return self._reason("end of file"), bool(self.skipped)

    def _reason(self, stop: str) -> str:
        found = sum(1 for c in self._inferred.values() if c is not None)
        stop = stop if not found else f"{stop}; {found} channel(s) lost with a damaged chunk told by their messages"
        return stop if not self.skipped else f"{stop}; skipped damaged {', '.join(self.skipped)}"

    def lost_messages(self) -> bool:
        """Whether messages the recorder counted as recorded are not among those kept."""
        if self.damaged_chunks:
            return True
        recorded = self.held.get(RECORDER, {}).get("recorded", "")
        return recorded.isdigit() and int(recorded) > self.kept

    def _infer_channel(self, lost_id: int, data: bytes) -> int | None:
        """The output channel of messages whose channel record was lost with a damaged chunk: the
        bus contract's key of their payload (each decodes as exactly one type), or None."""
        if lost_id not in self._inferred:
            key_type = _key_of_payload(data)
            out_id = None
            if key_type is not None:
                key, msg_type = key_type
                topic = IMAGE_TOPIC if msg_type is bus.CameraFrame else bus.mcap_topic(key)
                out_id = self._topic_channels.get(topic) or self.out.channel(key, msg_type)
                self._topic_channels[topic] = out_id
            self._inferred[lost_id] = out_id
        return self._inferred[lost_id]

    def _copy(self, record: object) -> None:
        writer = self.out.writer
        if isinstance(record, Header):
            self.header_seen = True
        elif isinstance(record, Schema):
            if record.id not in self._schema_ids:  # the summary repeats them
                self._schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel):
            if record.id not in self._channel_ids and (record.schema_id == 0 or record.schema_id in self._schema_ids):
                self._channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, self._schema_ids.get(record.schema_id, 0),
                    dict(record.metadata),
                )
                self._topic_channels.setdefault(record.topic, self._channel_ids[record.id])
        elif isinstance(record, Message):
            channel_id = self._channel_ids.get(record.channel_id)
            if channel_id is None:  # its channel was lost with a damaged chunk: its payload may tell
                channel_id = self._infer_channel(record.channel_id, record.data)
            if channel_id is not None:  # else uninterpretable
                writer.add_message(channel_id, record.log_time, record.data, record.publish_time, record.sequence)
                self.kept += 1
                self.out.count += 1
                self.last_log_ns = max(record.log_time, self.last_log_ns or 0)
        elif isinstance(record, Metadata) and record.name in (CAMPAIGN, RECORDER):
            self.held[record.name] = dict(record.metadata)  # checked against what was kept, then written
            self.metadata_names.add(record.name)
        elif isinstance(record, Metadata) and record.name != RECOVERY:
            writer.add_metadata(record.name, dict(record.metadata))
            self.metadata_names.add(record.name)
            if record.name == CAMPAIGN_START:
                self.start_metadata = dict(record.metadata)


def _key_of_payload(data: bytes) -> tuple[str, type[bus.BusMessage]] | None:
    """(key, type) of an archived payload by the one bus type it decodes as; None if none does."""
    if data[:1] == b"{" and b'"frame_id"' in data and b'"timestamp"' in data and b'"v"' not in data:
        return bus.CAMERA_FRAME, bus.CameraFrame  # archived as foxglove.CompressedImage
    keys = {t: k for k, t in bus.REGISTRY.items()}
    for msg_type in bus.MESSAGE_TYPES:
        if msg_type is bus.CameraFrame:
            continue
        try:
            msg = bus.decode(msg_type, data)
        except bus.BusDecodeError:
            continue
        if isinstance(msg, bus.Health):
            try:
                return bus.health_key(msg.process, msg.instance), msg_type
            except ValueError:
                return None
        return keys[msg_type], msg_type
    return None


def _runs_past_end(f: BinaryIO, offset: int, size: int) -> bool:
    if size - offset < 9:  # not even a complete opcode and length
        return True
    f.seek(offset)
    length = int.from_bytes(f.read(9)[1:], "little")
    return offset + 9 + length > size


def _fsync_dir(directory: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


__all__ = [
    "CAMPAIGN", "CAMPAIGN_KEYS", "CAMPAIGN_START", "COMPRESSED_IMAGE_SCHEMA", "IMAGE_SCHEMA_NAME", "IMAGE_TOPIC",
    "OUTCOMES", "RECORDER", "RECOVERY",
    "ArchiveError", "Campaign", "CampaignRecorder", "RecorderStats", "RecoveryReport", "atomic_write", "compressed_image",
    "is_complete", "iso_time", "read_campaign", "recover", "software_version", "storage_reason", "write_campaign",
    "writer_alive",
]
