"""Recovering a campaign archive whose recording was cut short (a killed recorder, a crash, a
damaged chunk): :func:`recover` rewrites it, in place and atomically, as a valid indexed file with
every complete record it held and outcome ``interrupted`` (the file layout: :mod:`bridge.archive`).

:func:`finish_in_place` finishes an unfinished file where it lies, for a disk with no room for a
copy (a recording that failed on a full disk): it cuts the torn last record and writes the final
records, the summary and the footer over it. It needs room only for those (about 20 kB for a
campaign, most of it the schemas the summary repeats), where :func:`recover` needs the whole
archive's size again; it refuses a file damaged inside (that is :func:`recover`'s work, which keeps
the original). Both take the outcome from the caller when the caller knows how the campaign ended
(``failed`` and the reason, from the console's record), else ``interrupted``.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from bridge import bus
from bridge.archive import (
    CAMPAIGN,
    CAMPAIGN_START,
    IMAGE_TOPIC,
    MAGIC,
    RECORDER,
    RECOVERY,
    ArchiveError,
    ArchiveWriter,
    fsync_dir,
    iso_time,
    storage_reason,
)
from bridge.archive_chunks import (
    BoundedReader,
    ChunkRefused,
    ReadBudget,
    ReadRefused,
    breakup_chunk,
    stream_records,
)
from bridge.archive_read import is_complete


@dataclass(frozen=True)
class RecoveryReport:
    """What :func:`recover` did. ``status``: ``valid`` (finished file, untouched) or ``recovered``.

    ``bytes_discarded``: bytes after the last complete record (the chunk in progress at the
    crash). A chunk whose content is damaged (CRC or decompression failure, or other than the size
    it declares: :mod:`bridge.archive_chunks` never decompresses past that bound, so a
    decompression bomb is such a chunk) but whose framing is intact is skipped and reading goes on;
    so are the chunks past a read's limit (:func:`bridge.archive_chunks.read_limit` of the file's
    size: a bomb of many chunks);
    damaged framing, or a record longer than ``MAX_RECORD_BYTES``, ends the salvage. ``corrupt_copy``: the
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


def recover(path: str | os.PathLike[str], outcome: str | None = None,
            fields: Mapping[str, str] | None = None) -> RecoveryReport:
    """Make ``path`` a valid, indexed campaign file, in place; idempotent.

    A finished file is left untouched (status ``valid``). An unfinished one (recorder killed) is
    read sequentially; every message of a complete chunk and every metadata record is rewritten
    to a temporary file that atomically replaces the original. Unless the file already holds a
    final ``xneck.campaign`` record, one is added from ``xneck.campaign.start`` with outcome
    ``interrupted`` and ``end_time`` the last message's log time. ``outcome`` and ``fields``
    (strings, e.g. ``message``): how the campaign ended when the caller knows it (a campaign that
    failed on a full disk), written into ``xneck.campaign`` instead (an outcome the file claimed
    is kept as ``outcome_before`` in ``xneck.recovery``). An ``xneck.recovery`` record tells what
    was salvaged. Raises :class:`ArchiveError` if the file is missing or not MCAP, or if writing
    the copy fails (a full disk: the file is left as it was, for :func:`finish_in_place`).
    """
    path = Path(path)
    valid = _valid(path)
    if valid is not None:
        return valid
    size = path.stat().st_size
    tmp = path.with_name(path.name + ".recovering")
    tmp.unlink(missing_ok=True)
    out = ArchiveWriter(tmp)
    try:
        salvage = _Salvage(out)
        try:
            stop_reason, damaged = salvage.copy_from(path, size)
        except _WriteFault as fault:
            raise ArchiveError(path, f"cannot write its recovered copy ({storage_reason(fault.error)}): the file "
                                     f"is left as it was") from fault.error
        if not salvage.header_seen:
            raise ArchiveError(path, f"no readable MCAP header, nothing to recover ({stop_reason})")
        recovery = {"recovered_at": iso_time(), "original_bytes": str(size),
                    "bytes_discarded": str(size - salvage.good_end), "messages": str(salvage.kept),
                    "reason": stop_reason}
        final = _final_record(salvage.held, salvage.start_metadata, salvage.last_log_ns, salvage.lost_messages(),
                              outcome, fields, recovery)
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
    fsync_dir(path.parent)
    return RecoveryReport(
        path=path, status="recovered", messages=salvage.kept, bytes_discarded=size - salvage.good_end,
        reason=stop_reason, corrupt_copy=corrupt_copy,
    )


def _valid(path: Path) -> RecoveryReport | None:
    """A ``valid`` report if ``path`` is a finished file whose records all read back, else None."""
    if not is_complete(path):
        return None
    try:
        # MCAP-level check only: a message of another schema version is no reason to rewrite.
        with open(path, "rb") as f:
            # Within a read's limit (a bomb of many chunks is salvaged: its chunks past it skipped).
            reader = BoundedReader(f, validate_crcs=True)
            for _ in reader.iter_metadata():
                pass
            count = sum(1 for _ in reader.iter_messages(log_time_order=False))
    except Exception:  # noqa: BLE001 - a footer but a damaged body: salvage
        return None
    return RecoveryReport(path=path, status="valid", messages=count)


def _final_record(held: Mapping[str, Mapping[str, str]], start_metadata: Mapping[str, str], last_log_ns: int | None,
                  lost_messages: bool, outcome: str | None, fields: Mapping[str, str] | None,
                  recovery: dict[str, str]) -> dict[str, str]:
    """The ``xneck.campaign`` record of a salvaged file (see :func:`recover`); notes in ``recovery``
    an outcome the file claimed and the salvage replaces."""
    claimed = held.get(CAMPAIGN)
    if claimed is None:
        final = dict(start_metadata)
        final["end_time"] = iso_time(last_log_ns) if last_log_ns is not None else final.get("start_time", "")
        final["outcome"] = "interrupted"
    elif lost_messages and claimed.get("outcome") != "interrupted":
        # A final record written before messages that never reached the disk is not the truth.
        recovery["outcome_before"] = claimed.get("outcome", "")
        final = {**claimed, "outcome": "interrupted"}
    else:
        final = dict(claimed)
    if outcome is not None:
        if claimed is not None and claimed.get("outcome", "") != outcome:
            recovery.setdefault("outcome_before", claimed.get("outcome", ""))
        final = {**final, **(fields or {}), "outcome": outcome}
    return final


def finish_in_place(path: str | os.PathLike[str], outcome: str | None = None,
                    fields: Mapping[str, str] | None = None) -> RecoveryReport:
    """Finish an unfinished campaign file where it lies, for a disk with no room for a copy.

    Reads the file sequentially up to its last complete record (the one after it was torn by the
    fault: a partial chunk, bytes an interrupted ``finish`` left), then writes over the torn part
    the final ``xneck.campaign`` record (as :func:`recover` makes it, ``outcome`` and ``fields``
    included), an ``xneck.recovery`` record (``method: in place``), the data end, a summary
    (schemas, channels, statistics, chunk and metadata indexes) and the footer, fsynced: an indexed
    file as :class:`bridge.archive.ArchiveWriter` finishes one. Space: only what it appends beyond
    the torn part (about 20 kB), never a copy. A finished file is left untouched (``valid``).

    Raises :class:`ArchiveError` for a file damaged inside (a record whose content fails its CRC
    or does not parse, not merely cut short: :func:`recover` salvages around it and keeps the
    original), one whose writer is alive, or a write that fails (the file is then cut back to its
    last complete record: it stays unfinished, what it held intact, for a later :func:`recover`).
    """
    path = Path(path)
    valid = _valid(path)
    if valid is not None:
        return valid
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError as exc:
        raise ArchiveError(path, f"cannot open it to finish it ({storage_reason(exc)})") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ArchiveError(path, "its writer is alive: not finished in place") from None
        size = os.fstat(fd).st_size
        index = _Index()
        stop_reason = index.scan(path, size)
        if not index.header_seen:
            raise ArchiveError(path, f"no readable MCAP header, nothing to finish ({stop_reason})")
        recovery = {"recovered_at": iso_time(), "method": "in place", "original_bytes": str(size),
                    "bytes_discarded": str(size - index.good_end), "messages": str(index.messages),
                    "reason": stop_reason}
        final = _final_record(index.held, index.start_metadata, index.last_ns, index.lost_messages(), outcome,
                              fields, recovery)
        tail = index.tail([(CAMPAIGN, final), (RECOVERY, recovery)])
        try:
            written = 0
            while written < len(tail):  # over the torn part first: those pages are the file's already
                written += os.pwrite(fd, tail[written:], index.good_end + written)
            os.ftruncate(fd, index.good_end + len(tail))
            os.fsync(fd)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, index.good_end)
                os.fsync(fd)
            raise ArchiveError(path, f"cannot finish it in place ({storage_reason(exc)}): it is kept up to its "
                                     f"last complete record, byte {index.good_end}") from exc
    finally:
        os.close(fd)  # drops the lock
    return RecoveryReport(path=path, status="recovered", messages=index.messages,
                          bytes_discarded=size - index.good_end, reason=stop_reason)


_SUMMARY_RECORDS = (DataEnd, Footer, ChunkIndex, MetadataIndex, AttachmentIndex, Statistics, SummaryOffset)


class _Index:
    """What :func:`finish_in_place` needs of an unfinished file, read sequentially without copying:
    its schemas and channels, an index of each complete chunk, metadata record and attachment, the
    message statistics, and where its last complete record ends (``good_end``)."""

    def __init__(self) -> None:
        self.header_seen = False
        self.good_end = len(MAGIC)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.chunk_indexes: list[ChunkIndex] = []
        self.metadata_indexes: list[MetadataIndex] = []
        self.attachment_indexes: list[AttachmentIndex] = []
        self.channel_counts: dict[int, int] = {}
        self.messages = 0
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.held: dict[str, dict[str, str]] = {}
        self.start_metadata: dict[str, str] = {}
        self._index_start = 0  # where the message indexes of the last chunk begin

    def scan(self, path: Path, size: int) -> str:
        """Index the complete records of ``path``; why reading stopped. Raises :class:`ArchiveError`
        for damage inside the file (not the torn end of an interrupted write)."""
        with open(path, "rb") as f:
            start = len(MAGIC)
            try:
                for record in stream_records(f, validate_crcs=True).records:
                    end = start + 9 + _declared_length(f, start)
                    if end > size:  # mcap reads a short last record silently
                        return f"truncated inside the record at byte {start}"
                    if end != f.tell():  # the reader skipped a record it does not know: the offsets would be wrong
                        raise ArchiveError(path, f"unknown or damaged record at byte {start}: not finished in place, "
                                                 f"a copying recovery salvages around it")
                    if isinstance(record, _SUMMARY_RECORDS):  # an interrupted finish: its summary is written anew
                        return f"the data section ends at byte {start}"
                    self._add(record, start, end)
                    self.good_end = start = end
            except ArchiveError:
                raise
            except Exception as exc:  # noqa: BLE001 - mcap raises many types on a damaged file
                if start == size:
                    return "end of file at a record boundary"
                if _runs_past_end(f, start, size):
                    return f"truncated inside the record at byte {start}"
                raise ArchiveError(path, f"damaged record at byte {start} ({type(exc).__name__}: {exc}): not "
                                         f"finished in place, a copying recovery salvages around it") from None
        return "end of file"

    def _add(self, record: McapRecord, start: int, end: int) -> None:
        if isinstance(record, Header):
            self.header_seen = True
        elif isinstance(record, Chunk):
            for inner in breakup_chunk(record, validate_crc=True):  # a damaged chunk raises: see scan()
                self._add(inner, 0, 0)
            self.chunk_indexes.append(ChunkIndex(
                message_start_time=record.message_start_time, message_end_time=record.message_end_time,
                chunk_start_offset=start, chunk_length=end - start, message_index_offsets={}, message_index_length=0,
                compression=record.compression, compressed_size=len(record.data),
                uncompressed_size=record.uncompressed_size))
            self._index_start = end
        elif isinstance(record, MessageIndex):
            if self.chunk_indexes:  # the last chunk's: they follow it
                last = self.chunk_indexes[-1]
                last.message_index_offsets[record.channel_id] = start
                last.message_index_length = end - self._index_start
        elif isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self.channels.setdefault(record.id, record)
        elif isinstance(record, Message):
            self.messages += 1
            self.channel_counts[record.channel_id] = self.channel_counts.get(record.channel_id, 0) + 1
            self.first_ns = record.log_time if self.first_ns is None else min(self.first_ns, record.log_time)
            self.last_ns = record.log_time if self.last_ns is None else max(self.last_ns, record.log_time)
        elif isinstance(record, Metadata):
            self.metadata_indexes.append(MetadataIndex(offset=start, length=end - start, name=record.name))
            if record.name in (CAMPAIGN, RECORDER):
                self.held[record.name] = dict(record.metadata)
            elif record.name == CAMPAIGN_START:
                self.start_metadata = dict(record.metadata)
        elif isinstance(record, Attachment):
            self.attachment_indexes.append(AttachmentIndex(
                offset=start, length=end - start, log_time=record.log_time, create_time=record.create_time,
                data_size=len(record.data), name=record.name, media_type=record.media_type))

    def lost_messages(self) -> bool:
        recorded = self.held.get(RECORDER, {}).get("recorded", "")
        return recorded.isdigit() and int(recorded) > self.messages

    def tail(self, metadata: list[tuple[str, dict[str, str]]]) -> bytes:
        """The bytes that finish the file after ``good_end``: ``metadata`` records, the data end,
        the summary (what :meth:`mcap.writer.Writer.finish` writes) and the footer."""
        data = RecordBuilder()
        for name, record in metadata:
            offset = self.good_end + data.count
            Metadata(name=name, metadata=record).write(data)
            self.metadata_indexes.append(MetadataIndex(offset=offset, length=self.good_end + data.count - offset,
                                                       name=name))
        DataEnd(data_section_crc=0).write(data)
        summary_start = self.good_end + data.count
        summary = RecordBuilder()
        offsets: list[SummaryOffset] = []
        statistics = Statistics(
            attachment_count=len(self.attachment_indexes), channel_count=len(self.channels),
            channel_message_counts=dict(self.channel_counts), chunk_count=len(self.chunk_indexes),
            message_count=self.messages, message_end_time=self.last_ns or 0, message_start_time=self.first_ns or 0,
            metadata_count=len(self.metadata_indexes), schema_count=len(self.schemas))
        groups: list[tuple[Opcode, list[McapRecord]]] = [
            (Opcode.SCHEMA, list(self.schemas.values())), (Opcode.CHANNEL, list(self.channels.values())),
            (Opcode.STATISTICS, [statistics]), (Opcode.CHUNK_INDEX, list(self.chunk_indexes)),
            (Opcode.ATTACHMENT_INDEX, list(self.attachment_indexes)),
            (Opcode.METADATA_INDEX, list(self.metadata_indexes))]
        for opcode, records in groups:
            group_start = summary.count
            for record in records:
                record.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + group_start,
                                         group_length=summary.count - group_start))
        summary_offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        summary_bytes = summary.end()
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start, summary_offset_start),
                         zlib.crc32(summary_bytes))
        footer = RecordBuilder()
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(footer)
        return data.end() + summary_bytes + footer.end() + MAGIC


def _declared_length(f: BinaryIO, offset: int) -> int:
    """The length field of the record at ``offset`` (its content's bytes, after opcode and length)."""
    head = os.pread(f.fileno(), 9, offset)
    return int.from_bytes(head[1:], "little") if len(head) == 9 else 1 << 62


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

    def __init__(self, out: ArchiveWriter) -> None:
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
        self._over_limit = False

    def copy_from(self, path: Path, size: int) -> tuple[str, bool]:
        """Returns why reading stopped, and whether it was damage rather than the end of the file.
        Raises :class:`_WriteFault` if writing the copy fails."""
        # What the copy holds is read back under this limit: chunks past it are not copied.
        budget = ReadBudget(size)
        with open(path, "rb") as f:
            try:
                for record in stream_records(f, validate_crcs=True).records:
                    if isinstance(record, Chunk):
                        try:
                            budget.spend(record)
                            inner = breakup_chunk(record, validate_crc=True)
                        except Exception as exc:  # CRC or decompression failure, a bomb (ChunkRefused, ReadRefused)
                            if f.tell() > size:
                                raise
                            # The chunk's framing is intact (its length led to the next record):
                            # skip its content, carry on with the next chunk.
                            self._skip(exc)
                            inner = []
                        self._write(inner)
                    else:
                        self._write([record])
                    self.good_end = f.tell()
            except _WriteFault:
                raise
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

    def _skip(self, exc: Exception) -> None:
        """Notes the chunk at ``good_end`` as skipped: damaged, or past the read's limit."""
        self.damaged_chunks = True
        if isinstance(exc, ReadRefused):  # every later chunk is past it too: said once
            if not self._over_limit:
                self.skipped.append(f"chunks from byte {self.good_end} on ({exc})")
            self._over_limit = True
            return
        why = f"{type(exc).__name__}: {exc}" if isinstance(exc, ChunkRefused) else type(exc).__name__
        self.skipped.append(f"chunk at byte {self.good_end} ({why})")

    def _write(self, records: list[McapRecord]) -> None:
        """Copies ``records``. An error here is the copy's (a full disk, EIO), not damage of the
        original: it must not end the salvage as if the original ended there (review of session
        53: an ENOSPC was read as "damaged record" and a copy missing a third of its messages
        replaced an intact file)."""
        try:
            for record in records:
                self._copy(record)
        except Exception as exc:
            raise _WriteFault(exc) from exc

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


class _WriteFault(Exception):
    """Writing the recovered copy failed (``error``): :func:`recover` fails, the original kept."""

    def __init__(self, error: Exception) -> None:
        super().__init__(str(error))
        self.error = error


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


__all__ = ["RecoveryReport", "finish_in_place", "recover"]
