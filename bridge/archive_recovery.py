"""Recovering a campaign archive whose recording was cut short (a killed recorder, a crash, a
damaged chunk): :func:`recover` rewrites it, in place and atomically, as a valid indexed file with
every complete record it held and outcome ``interrupted`` (the file layout: :mod:`bridge.archive`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

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
)
from bridge.archive_read import is_complete


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
    out = ArchiveWriter(tmp)
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
    fsync_dir(path.parent)
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


__all__ = ["RecoveryReport", "recover"]
