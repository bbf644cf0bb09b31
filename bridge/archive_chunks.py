"""Reading MCAP chunks within bounds: an archive is hostile input from disk.

mcap 1.x decompresses a chunk whole (``mcap.stream_reader.get_chunk_data_stream``:
``lz4.frame.decompress(chunk.data)``, ``zstandard.decompress``) and never compares what comes out
with the chunk's declared ``uncompressed_size``. A 17.7 MB file whose one LZ4 chunk declared
100 bytes and held 4 GiB of zeros took 2.4 GB of memory in ``xneck identify``, 4.5 GB in
:func:`bridge.archive_recovery.recover` and 5.2 GB in ``xneck server``'s start-up recovery (audit
of 2026-11-28). Here each chunk is decompressed by a bounded stream that stops at its declared size
(itself at most :data:`MAX_CHUNK_BYTES`): a chunk that holds more, or less, is refused with
:class:`ChunkRefused` before more than that was ever allocated; a read of many chunks decompresses
at most :func:`read_limit` of its file's size, summed (else :class:`ReadRefused`).
:func:`breakup_chunk` replaces mcap's, and :class:`BoundedReader` the queries of mcap's
``SeekingReader`` that the project uses; every reader of archives (:mod:`bridge.archive_read`,
:mod:`bridge.archive_recovery`, ``twin.camera.align``, ``server.archive_rewrite``) goes through them.
"""

from __future__ import annotations

import heapq
import io
import zlib
from collections.abc import Iterator
from typing import IO

import lz4.frame
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError, UnsupportedCompressionError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, ChunkIndex, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap.summary import Summary

try:  # as in mcap: zstd chunks are readable only with zstandard installed
    import zstandard
except ImportError:  # pragma: no cover
    zstandard = None

#: The most bytes a chunk may declare or hold once decompressed (32 MiB). The largest legitimate
#: chunk: the recorder (:class:`bridge.archive.ArchiveWriter`) closes a chunk once it passes
#: ``CHUNK_SIZE`` (256 KiB), so its largest is 256 KiB plus its largest message, a camera image
#: (``foxglove.CompressedImage``, base64 of a JPEG of at most ``bus.FRAME_DATA_MAX_BYTES``, about
#: 1.4 MB): about 1.7 MB. ``xneck camera align`` writes mcap's default 1 MiB chunks plus one video
#: frame as JPEG (a few MB at 4K). 32 MiB, 128 × ``CHUNK_SIZE``, leaves a factor of ten and more
#: for those and for other tools' larger chunk settings, and bounds what a hostile chunk costs.
MAX_CHUNK_BYTES = 32 * 1024 * 1024
#: How many times its file's size one read may decompress, chunks summed (:class:`BoundedReader`;
#: review of session 53). The chunk cap bounds one chunk, not a file of many: a 392 KB archive of
#: identical messages (LZ4 at about 250:1) decompressed to 98 MB and the console's start-up
#: recovery peaked at 464 MB decoding it. Real archives decompress to far less than 32 times
#: their size (measured: a 14 s control campaign of `xneck campaign control`, 5.9 MB: 2.3; console
#: campaigns with their Foxglove scene: 2.9-3.1; identifications with camera frames, 25 MB: 3.8;
#: the tests' small synthetic archives: at most 5.4): a margin of six over the most compressible,
#: since a refused archive is data the console cannot show.
MAX_EXPANSION = 32
#: The least one read may always decompress (16 MiB), whatever the file's size: a small file's
#: chunks read even if they compress better than real archives do; what a small bomb costs.
MIN_READ_BYTES = 16 * 1024 * 1024
#: The longest record read into memory: a chunk of :data:`MAX_CHUNK_BYTES` stored uncompressed or
#: as incompressible LZ4/zstd (a few hundred kB of framing over its size), with its fixed fields.
MAX_RECORD_BYTES = MAX_CHUNK_BYTES + 1024 * 1024


class ChunkRefused(McapError):
    """A chunk that decompresses to other than its declared size, or declares or holds more than
    :data:`MAX_CHUNK_BYTES`: damaged or hostile, never decompressed past its bound."""


class ReadRefused(McapError):
    """A read whose chunks decompress, summed, to more than :func:`read_limit` of its file:
    refused before the chunk that would pass the limit is decompressed."""


def read_limit(file_bytes: int) -> int:
    """The most bytes one read of a file of ``file_bytes`` bytes may decompress, chunks summed."""
    return max(MIN_READ_BYTES, MAX_EXPANSION * file_bytes)


class ReadBudget:
    """The bytes one read of a file of ``file_bytes`` bytes has decompressed (``spent``), against
    its :func:`read_limit` (``limit``, bytes)."""

    def __init__(self, file_bytes: int) -> None:
        self.file_bytes = file_bytes
        self.limit = read_limit(file_bytes)
        self.spent = 0

    def spend(self, chunk: Chunk) -> None:
        """Counts what ``chunk`` decompresses to (its declared size: :func:`chunk_data` refuses a
        chunk that holds more), or raises :class:`ReadRefused` if that passes the limit."""
        size = len(chunk.data) if chunk.compression == "" else chunk.uncompressed_size
        self.spent += size
        if self.spent > self.limit:
            raise ReadRefused(f"the file decompresses to more than {self.limit} bytes ({MAX_EXPANSION} times its "
                              f"{self.file_bytes} bytes, at least {MIN_READ_BYTES}): not read, a decompression "
                              f"bomb or not an archive of this software")


def chunk_data(chunk: Chunk, validate_crc: bool = False) -> bytes:
    """The records of ``chunk``, decompressed without ever producing more than its declared
    ``uncompressed_size`` (at most :data:`MAX_CHUNK_BYTES`) plus one byte. Raises
    :class:`ChunkRefused` if a compressed chunk holds other than it declares (an uncompressed one:
    if it is longer than the cap; it is in memory already), ``CRCValidationError`` (as mcap) on a
    bad CRC."""
    size = chunk.uncompressed_size
    if chunk.compression == "":
        data = chunk.data
        if len(data) > MAX_CHUNK_BYTES:
            raise ChunkRefused(f"uncompressed chunk of {len(data)} bytes, more than the {MAX_CHUNK_BYTES} allowed")
    elif size > MAX_CHUNK_BYTES:
        raise ChunkRefused(f"chunk declares {size} bytes uncompressed, more than the {MAX_CHUNK_BYTES} allowed")
    elif chunk.compression == "lz4":
        data = _lz4(chunk.data, size)
    elif chunk.compression == "zstd":
        data = _zstd(chunk.data, size)
    else:
        raise UnsupportedCompressionError(chunk.compression)
    if validate_crc and chunk.uncompressed_crc != 0:
        crc = zlib.crc32(data)
        if crc != chunk.uncompressed_crc:
            raise CRCValidationError(expected=chunk.uncompressed_crc, actual=crc, record=chunk)
    return data


def _lz4(data: bytes, size: int) -> bytes:
    # Only the first frame, as lz4.frame.decompress (what mcap calls) reads it.
    decompressor = lz4.frame.LZ4FrameDecompressor()
    out = decompressor.decompress(data, max_length=size)
    if not decompressor.eof and decompressor.decompress(b"", max_length=1):
        raise ChunkRefused(f"lz4 chunk decompresses to more than its declared {size} bytes")
    if not decompressor.eof or len(out) != size:
        raise ChunkRefused(f"lz4 chunk decompresses to {len(out)} bytes{'' if decompressor.eof else ' and ends early'}, "
                           f"its header declares {size}")
    return out


def _zstd(data: bytes, size: int) -> bytes:
    if zstandard is None:  # pragma: no cover
        raise UnsupportedCompressionError("zstd")
    # A window no larger than the cap (a frame may ask for up to 128 MiB by default); one read of
    # at most size + 1 bytes, which stops at the end of the first frame (zstandard.decompress
    # reads the first frame only, too).
    decompressor = zstandard.ZstdDecompressor(max_window_size=MAX_CHUNK_BYTES)
    with decompressor.stream_reader(data, read_across_frames=False) as reader:
        out = reader.read(size + 1)
    if len(out) > size:
        raise ChunkRefused(f"zstd chunk decompresses to more than its declared {size} bytes")
    if len(out) != size:
        raise ChunkRefused(f"zstd chunk decompresses to {len(out)} bytes, its header declares {size}")
    return out


def breakup_chunk(chunk: Chunk, validate_crc: bool = False) -> list[McapRecord]:
    """The schemas, channels and messages of ``chunk`` (mcap's ``breakup_chunk``, with the
    decompression of :func:`chunk_data`)."""
    data = chunk_data(chunk, validate_crc)
    stream = ReadDataStream(io.BytesIO(data))
    end = len(data)
    records: list[McapRecord] = []
    while stream.count < end:
        opcode = stream.read1()
        length = stream.read8()
        if opcode == Opcode.CHANNEL:
            records.append(Channel.read(stream))
        elif opcode == Opcode.MESSAGE:
            records.append(Message.read(stream, length))
        elif opcode == Opcode.SCHEMA:
            records.append(Schema.read(stream))
        else:  # a record type a chunk may hold that we do not read
            stream.read(length)
    return records


def stream_records(stream: IO[bytes], *, validate_crcs: bool = False) -> StreamReader:
    """mcap's ``StreamReader`` emitting chunks whole (break them up with :func:`breakup_chunk`),
    refusing a record longer than :data:`MAX_RECORD_BYTES` before reading it."""
    return StreamReader(stream, emit_chunks=True, validate_crcs=validate_crcs, record_size_limit=MAX_RECORD_BYTES)


MessageTuple = tuple[Schema | None, Channel, Message]


class BoundedReader:
    """mcap's ``SeekingReader`` for the queries the project makes (summary, metadata, messages in
    file or log-time order), every chunk decompressed by :func:`breakup_chunk`. Messages come in
    the order ``SeekingReader`` gives them: the chunks of the summary's index in file order, or
    merged by log time (ties by position in the file); a file without a chunk index is read
    sequentially, as ``SeekingReader`` falls back to doing. Each :meth:`iter_messages` decompresses
    at most :func:`read_limit` of the file's size (else :class:`ReadRefused`)."""

    def __init__(self, stream: IO[bytes], validate_crcs: bool = False) -> None:
        self._stream = stream
        self._validate_crcs = validate_crcs
        position = stream.tell()
        self._file_bytes = stream.seek(0, io.SEEK_END)
        stream.seek(position, io.SEEK_SET)
        self._reader = SeekingReader(stream, validate_crcs=validate_crcs, record_size_limit=MAX_RECORD_BYTES)

    def get_summary(self) -> Summary | None:
        return self._reader.get_summary()

    def iter_metadata(self) -> Iterator[Metadata]:
        if self.get_summary() is not None:
            yield from self._reader.iter_metadata()
            return
        # SeekingReader's fallback would break every chunk up with mcap's unbounded decompression.
        self._stream.seek(0, io.SEEK_SET)
        for record in stream_records(self._stream).records:
            if isinstance(record, Metadata):
                yield record

    def iter_messages(self, log_time_order: bool = True) -> Iterator[MessageTuple]:
        budget = ReadBudget(self._file_bytes)
        summary = self.get_summary()
        if summary is None or not summary.chunk_indexes:
            self._stream.seek(0, io.SEEK_SET)
            messages = self._iter_sequential(budget)
            yield from sorted(messages, key=_log_time) if log_time_order else messages
            return
        if not log_time_order:
            for index in summary.chunk_indexes:
                yield from self._chunk_messages(summary, index, budget)
            return
        # Merged by log time as mcap's queue does: a chunk enters at its first message's time, ties
        # go to the earlier position in the file (chunk offset, then place in the chunk); the fourth
        # field only keeps the heap from ever comparing records.
        heap: list[tuple[int, int, int, int, ChunkIndex | MessageTuple]] = [
            (index.message_start_time, index.chunk_start_offset, -1, n, index)
            for n, index in enumerate(summary.chunk_indexes)]
        heapq.heapify(heap)
        n = len(heap)
        while heap:
            _, offset, _, _, item = heapq.heappop(heap)
            if isinstance(item, ChunkIndex):
                for k, entry in enumerate(self._chunk_messages(summary, item, budget)):
                    heapq.heappush(heap, (entry[2].log_time, offset, k, n, entry))
                    n += 1
            else:
                yield item

    def _chunk_messages(self, summary: Summary, index: ChunkIndex, budget: ReadBudget) -> list[MessageTuple]:
        out: list[MessageTuple] = []
        chunk = self._read_chunk(index.chunk_start_offset)
        budget.spend(chunk)
        for record in breakup_chunk(chunk, self._validate_crcs):
            if isinstance(record, Message):
                channel = summary.channels.get(record.channel_id)
                if channel is None:
                    raise McapError(f"chunk at byte {index.chunk_start_offset}: no channel record with id {record.channel_id}")
                out.append((summary.schemas.get(channel.schema_id) if channel.schema_id else None, channel, record))
        return out

    def _read_chunk(self, offset: int) -> Chunk:
        """The chunk record at ``offset``, read whole only if at most :data:`MAX_RECORD_BYTES` long
        and parsed from those bytes (its inner lengths cannot make it read further)."""
        self._stream.seek(offset, io.SEEK_SET)
        head = self._stream.read(9)
        if len(head) != 9 or head[0] != Opcode.CHUNK:
            raise McapError(f"no chunk record at byte {offset}, where the chunk index points")
        length = int.from_bytes(head[1:], "little")
        if length > MAX_RECORD_BYTES:
            raise ChunkRefused(f"chunk record at byte {offset} is {length} bytes long, more than the "
                               f"{MAX_RECORD_BYTES} allowed")
        body = self._stream.read(length)
        if len(body) != length:
            raise McapError(f"chunk record at byte {offset} runs past the end of the file")
        return Chunk.read(ReadDataStream(io.BytesIO(body)))

    def _iter_sequential(self, budget: ReadBudget) -> Iterator[MessageTuple]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        for top in stream_records(self._stream).records:
            if isinstance(top, Chunk):
                budget.spend(top)
            for record in breakup_chunk(top, self._validate_crcs) if isinstance(top, Chunk) else (top,):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    if record.schema_id != 0 and record.schema_id not in schemas:
                        raise McapError(f"no schema record found with id {record.schema_id}")
                    channels[record.id] = record
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        raise McapError(f"no channel record found with id {record.channel_id}")
                    yield (schemas[channel.schema_id] if channel.schema_id else None, channel, record)


def _log_time(entry: MessageTuple) -> int:
    return entry[2].log_time


__all__ = ["MAX_CHUNK_BYTES", "MAX_EXPANSION", "MAX_RECORD_BYTES", "MIN_READ_BYTES", "BoundedReader", "ChunkRefused",
           "ReadBudget", "ReadRefused", "breakup_chunk", "chunk_data", "read_limit", "stream_records"]
