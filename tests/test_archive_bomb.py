"""Decompression bombs in campaign archives (audit of 2026-11-28).

An archive is hostile input from disk. mcap 1.x decompressed a chunk whole, whatever its header
declared: a 17.7 MB file whose one LZ4 chunk declared 100 bytes and held 4 GiB of zeros took
2.4 GB in ``xneck identify``, 4.5 GB in ``recover`` and 5.2 GB in ``xneck server``'s start-up. Here
a bomb declares 100 bytes and holds 256 MiB of zeros (about 1 MB of LZ4, 8 kB of zstd): every
reader refuses it (reading: an ``ArchiveError``; recovery: the chunk skipped and counted) and its
process's peak memory grows far less than the bomb's size (measured in a child process).
"""

from __future__ import annotations

import functools
import json
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import lz4.frame
import numpy as np
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
)
from mcap.stream_reader import breakup_chunk as mcap_breakup_chunk
from mcap.writer import CompressionType, IndexType, Writer

from bridge import archive_chunks, bus
from bridge.archive import CAMPAIGN, CAMPAIGN_START, CHUNK_SIZE, MAGIC, ArchiveError, write_campaign
from bridge.archive_chunks import (
    MAX_CHUNK_BYTES,
    MAX_EXPANSION,
    BoundedReader,
    ChunkRefused,
    ReadRefused,
    breakup_chunk,
    read_limit,
)
from bridge.archive_read import read_campaign
from bridge.archive_recovery import recover

REPO = Path(__file__).resolve().parents[1]
BOMB_BYTES = 256 << 20  # what the bomb chunk really holds
DECLARED = 100  # what its header says
GROWTH_LIMIT = MAX_CHUNK_BYTES  # a reader's peak memory grows by less than the cap, an eighth of the bomb
PER_CHUNK = 30
T0 = 1_700_000_000_000_000_000
SCHEMA = Schema(id=1, name=bus.schema_name(bus.MotorState), encoding="jsonschema",
                data=bus.json_schema_bytes(bus.MotorState))
CHANNEL = Channel(id=1, topic=bus.mcap_topic(bus.MOTOR_STATE), message_encoding="json", schema_id=1,
                  metadata={"key": bus.MOTOR_STATE, "version": str(bus.schema_version(bus.MotorState))})


def motor_state(seq: int) -> bus.MotorState:
    return bus.MotorState(seq=seq, stamp_s=seq * 0.002, theta_rad=[0.001 * seq, 0.2, -0.3, 0.4],
                          force_applied_N=[5.0, 6.0, 7.0, 8.0], drive="active", epoch="e1", bridge="b1")


def _records(*records: McapRecord) -> bytes:
    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    return builder.end()


def _compress(compression: str, raw: bytes) -> bytes:
    return lz4.frame.compress(raw) if compression == "lz4" else zstandard.compress(raw)


def _good_chunk(first: int, compression: str = "lz4") -> Chunk:
    """``PER_CHUNK`` motor states from ``first``, with their schema and channel, as a writer makes them."""
    messages = [Message(channel_id=1, log_time=T0 + i * 2_000_000, data=bus.encode(motor_state(i)),
                        publish_time=i * 2_000_000, sequence=i) for i in range(first, first + PER_CHUNK)]
    raw = _records(SCHEMA, CHANNEL, *messages)
    return Chunk(compression=compression, data=_compress(compression, raw), message_start_time=messages[0].log_time,
                 message_end_time=messages[-1].log_time, uncompressed_crc=zlib.crc32(raw), uncompressed_size=len(raw))


@functools.cache
def _bomb_data(compression: str, real: int = BOMB_BYTES) -> bytes:
    """``real`` bytes, compressed a MiB at a time (the test never holds them): one record of a type
    readers skip, then zeros. Parsed, it is gone at once; mcap used to take 256 MiB to see that."""
    first = bytes([0x80]) + (real - 9).to_bytes(8, "little") + bytes((1 << 20) - 9)
    blocks = [first, *(bytes(1 << 20) for _ in range((real >> 20) - 1))]
    if compression == "lz4":
        compressor = lz4.frame.LZ4FrameCompressor()
        parts = [compressor.begin(), *(compressor.compress(b) for b in blocks), compressor.flush()]
    else:
        zcompressor = zstandard.ZstdCompressor().compressobj()
        parts = [*(zcompressor.compress(b) for b in blocks), zcompressor.flush()]
    return b"".join(parts)


def _bomb_chunk(compression: str = "lz4", declared: int = DECLARED, real: int = BOMB_BYTES) -> Chunk:
    t = T0 + PER_CHUNK * 2_000_000
    return Chunk(compression=compression, data=_bomb_data(compression, real), message_start_time=t, message_end_time=t,
                 uncompressed_crc=0, uncompressed_size=declared)  # no CRC, as the audit's bomb


def _archive(path: Path, chunks: list[Chunk], *, finished: bool = True, indexed: bool = True) -> Path:
    """An MCAP file of ``chunks`` and the campaign's records; ``finished``: with a footer,
    ``indexed``: and a summary (chunk and metadata indexes; without one readers read it through,
    like the audit's bomb)."""
    meta = {"campaign_id": path.stem, "law": "pid", "start_time": "2026-11-28T00:00:00Z"}
    out = bytearray(MAGIC + _records(Header(profile="xneck", library="test")))
    start = _records(Metadata(name=CAMPAIGN_START, metadata=meta))
    indexes: list[McapRecord] = [MetadataIndex(offset=len(out), length=len(start), name=CAMPAIGN_START)]
    out += start
    for chunk in chunks:
        record = _records(chunk)
        indexes.append(ChunkIndex(
            message_start_time=chunk.message_start_time, message_end_time=chunk.message_end_time,
            chunk_start_offset=len(out), chunk_length=len(record), message_index_offsets={}, message_index_length=0,
            compression=chunk.compression, compressed_size=len(chunk.data), uncompressed_size=chunk.uncompressed_size))
        out += record
    if finished:
        final = _records(Metadata(name=CAMPAIGN, metadata={**meta, "outcome": "finished"}))
        indexes.append(MetadataIndex(offset=len(out), length=len(final), name=CAMPAIGN))
        out += final + _records(DataEnd(data_section_crc=0))
        summary_start = len(out) if indexed else 0
        if indexed:
            out += _records(SCHEMA, CHANNEL, *indexes)
        out += _records(Footer(summary_start=summary_start, summary_offset_start=0, summary_crc=0)) + MAGIC
    path.write_bytes(bytes(out))
    return path


def _bombed(path: Path, compression: str = "lz4", **kw: bool) -> Path:
    """A good chunk, the bomb, a good chunk."""
    return _archive(path, [_good_chunk(0, compression), _bomb_chunk(compression), _good_chunk(2 * PER_CHUNK, compression)],
                    **kw)


def _in_child(setup: str, calls: dict[str, str]) -> dict[str, tuple[str, int]]:
    """Runs each call (an expression) in a fresh Python after ``setup``, in turn; returns per call
    its outcome (the repr of its value, or the exception it raised) and how much the process's peak
    memory (ru_maxrss) grew during it."""
    script = "\n".join([
        "import json, resource",
        textwrap.dedent(setup),
        "_out = {}",
        f"for _name, _call in {calls!r}.items():",
        "    _before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss",
        "    try:",
        "        _outcome = repr(eval(_call))",
        "    except Exception as exc:",
        "        _outcome = f'{type(exc).__name__}: {exc}'",
        "    _out[_name] = (_outcome[:400], (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - _before) * 1024)",
        "print(json.dumps(_out))",
    ])
    done = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300,
                          check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return {name: (outcome, grew) for name, (outcome, grew) in json.loads(done.stdout.splitlines()[-1]).items()}


def _mib(n: int) -> str:
    return f"{n / 2**20:.0f} MiB"


# --- the bounded decompression ----------------------------------------------------------------------


@pytest.mark.parametrize("compression", ["lz4", "zstd"])
def test_a_chunk_is_decompressed_no_further_than_it_declares(compression: str) -> None:
    good = _good_chunk(0, compression)
    assert breakup_chunk(good, validate_crc=True) == mcap_breakup_chunk(good, validate_crc=True)
    with pytest.raises(ChunkRefused, match=f"more than its declared {DECLARED} bytes"):
        breakup_chunk(_bomb_chunk(compression, real=4 << 20))
    # Holding less than it declares is damage too.
    short = Chunk(compression=compression, data=good.data, message_start_time=0, message_end_time=0,
                  uncompressed_crc=0, uncompressed_size=good.uncompressed_size + 1)
    with pytest.raises(ChunkRefused, match=f"its header declares {good.uncompressed_size + 1}"):
        breakup_chunk(short)
    # A declared size past the cap is refused before anything is decompressed.
    with pytest.raises(ChunkRefused, match=f"more than the {MAX_CHUNK_BYTES} allowed"):
        breakup_chunk(_bomb_chunk(compression, declared=4 << 30, real=1 << 20))
    # Honest but past the cap: refused as well.
    with pytest.raises(ChunkRefused, match=f"more than the {MAX_CHUNK_BYTES} allowed"):
        breakup_chunk(_bomb_chunk(compression, declared=MAX_CHUNK_BYTES + (1 << 20), real=MAX_CHUNK_BYTES + (1 << 20)))


def test_the_largest_legitimate_chunk_is_read(tmp_path: Path) -> None:
    """The recorder's largest chunk, ``CHUNK_SIZE`` of states and then a camera image of the
    largest JPEG the bus carries, is well inside the cap."""
    msgs: list[tuple[str, int, bus.BusMessage]] = [(bus.MOTOR_STATE, T0 + i, motor_state(i)) for i in range(600)]
    jpeg = b"\xff\xd8" + bytes(range(256)) * (bus.FRAME_DATA_MAX_BYTES // 256 - 1)
    msgs.append((bus.CAMERA_FRAME, T0 + 600, bus.CameraFrame(seq=1, stamp_s=1.0, capture_stamp_s=1.0, width=64, height=64,
                                                             data=jpeg)))
    path = write_campaign(tmp_path / "large.mcap", msgs, {"campaign_id": "large"}, chunk_size=CHUNK_SIZE)
    campaign = read_campaign(path)
    assert len(campaign.messages(bus.MOTOR_STATE)) == 600
    (_, image), = campaign.topics["/xneck/camera/image"]
    assert len(image["data"]) > bus.FRAME_DATA_MAX_BYTES  # base64
    assert 8 * (CHUNK_SIZE + len(image["data"]) + 4096) < MAX_CHUNK_BYTES


@pytest.mark.parametrize("indexed", [True, False])
def test_the_bounded_reader_gives_what_mcaps_readers_give(tmp_path: Path, indexed: bool) -> None:
    """Same messages, same order as mcap's own readers (log-time order: time, then position in the
    file), on a file whose clock stepped back across chunks, with ties; and the same metadata."""
    path = tmp_path / "stepped.mcap"
    rng = np.random.default_rng(3)
    times = T0 + np.cumsum(rng.integers(0, 3, 300)) * 1_000_000
    times[120:] -= 50_000_000
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=2048, compression=CompressionType.LZ4,
                        index_types=IndexType.ALL if indexed else IndexType.METADATA)
        writer.start(profile="xneck")
        writer.add_metadata(CAMPAIGN_START, {"campaign_id": "stepped"})
        schema = writer.register_schema(SCHEMA.name, SCHEMA.encoding, SCHEMA.data)
        states = writer.register_channel(CHANNEL.topic, "json", schema)
        other = writer.register_channel("/other", "json", 0)
        for i, t in enumerate(times):
            writer.add_message(states, int(t), bus.encode(motor_state(i)), i, i)
            if i % 5 == 0:
                writer.add_message(other, int(t), b"{}", i, i)
        writer.add_metadata(CAMPAIGN, {"campaign_id": "stepped", "outcome": "finished"})
        writer.finish()

    def listed(messages):
        return [(channel.topic, message.log_time, message.sequence, schema.name if schema else None)
                for schema, channel, message in messages]

    for log_time_order in (False, True):
        with open(path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            assert bool(reader.get_summary().chunk_indexes) == indexed  # type: ignore[union-attr]
            expected = listed(reader.iter_messages(log_time_order=log_time_order))
            f.seek(0)
            got = listed(BoundedReader(f, validate_crcs=True).iter_messages(log_time_order=log_time_order))
        assert got == expected and len(got) == 360
        times_read = [t for _, t, _, _ in got]
        assert (times_read == sorted(times_read)) == log_time_order  # the step shows in file order
    with open(path, "rb") as f:
        expected_meta = [(m.name, m.metadata) for m in make_reader(f).iter_metadata()]
        f.seek(0)
        assert [(m.name, m.metadata) for m in BoundedReader(f).iter_metadata()] == expected_meta
        assert len(expected_meta) == 2


def test_a_file_without_summary_is_read_through(tmp_path: Path) -> None:
    """No summary (like the audit's bomb): metadata and messages are read sequentially, as mcap's
    SeekingReader falls back to, chunks broken up within bounds."""
    path = _archive(tmp_path / "flat.mcap", [_good_chunk(0), _good_chunk(PER_CHUNK, "zstd")], indexed=False)
    campaign = read_campaign(path)
    assert [m.seq for _, m in campaign.messages(bus.MOTOR_STATE)] == list(range(2 * PER_CHUNK))
    assert set(campaign.metadata) == {CAMPAIGN_START, CAMPAIGN} and campaign.info["outcome"] == "finished"


# --- many honest chunks (review of session 53) --------------------------------------------------


def _many_chunks(path: Path, n: int = 40, chunk_bytes: int = 4 << 20, **kw: bool) -> Path:
    """``n`` LZ4 chunks of ``chunk_bytes`` each, one motor state repeated (about 250:1): each honest
    and within the chunk cap, together 160 MiB in a file of 0.7 MB (the review's: 98 MB in 392 KB)."""
    message = _records(Message(channel_id=1, log_time=T0, data=bus.encode(motor_state(0)), publish_time=0, sequence=0))
    raw = _records(SCHEMA, CHANNEL) + message * (chunk_bytes // len(message))
    chunk = Chunk(compression="lz4", data=lz4.frame.compress(raw), message_start_time=T0, message_end_time=T0,
                  uncompressed_crc=zlib.crc32(raw), uncompressed_size=len(raw))
    return _archive(path, [chunk] * n, **kw)


def _count_decompressed(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The sizes of the chunks decompressed from now on, in a list that grows."""
    sizes: list[int] = []
    real = archive_chunks.chunk_data

    def counted(chunk: Chunk, validate_crc: bool = False) -> bytes:
        sizes.append(chunk.uncompressed_size)
        return real(chunk, validate_crc)

    monkeypatch.setattr(archive_chunks, "chunk_data", counted)
    return sizes


def test_a_read_decompresses_no_more_than_its_limit_whatever_the_chunks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Review of session 53: the chunk cap bounded each chunk, nothing a read of many: the console's
    start-up took 464 MB decoding a 392 KB archive. A read now decompresses at most
    ``read_limit`` of its file's size and says so; a realistic archive is far inside it."""
    decompressed = _count_decompressed(monkeypatch)
    for indexed in (True, False):
        path = _many_chunks(tmp_path / f"many-{indexed}.mcap", indexed=indexed)
        limit = read_limit(path.stat().st_size)
        with pytest.raises(ArchiveError, match=f"decompresses to more than {limit} bytes .*: not read"):
            read_campaign(path, keys=(bus.CAMPAIGN_EVENTS,))  # what the console's start-up reads
        assert 0 < sum(decompressed) <= limit, (indexed, sum(decompressed))
        decompressed.clear()
        with open(path, "rb") as f, pytest.raises(ReadRefused):  # in log-time order too (archive rewrites)
            for _ in BoundedReader(f).iter_messages(log_time_order=True):
                pass
        assert sum(decompressed) <= limit
        decompressed.clear()
    # A recorder's archive reads on its ratio alone (no floor), with room to spare.
    monkeypatch.setattr(archive_chunks, "MIN_READ_BYTES", 0)
    msgs = [(bus.MOTOR_STATE, T0 + i * 2_000_000, motor_state(i)) for i in range(3000)]
    path = write_campaign(tmp_path / "real.mcap", msgs, {"campaign_id": "real"}, chunk_size=CHUNK_SIZE)
    assert [m.seq for _, m in read_campaign(path).messages(bus.MOTOR_STATE)] == list(range(3000))
    assert sum(decompressed) < MAX_EXPANSION / 2 * path.stat().st_size, sum(decompressed) / path.stat().st_size


def test_recovery_copies_no_more_than_a_read_takes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same archive unfinished: recovery copied all of it, and its copy, made larger by its
    message indexes, passed a read's limit (the review's 98 MB of events read at 11 times the
    copy's size). Now the chunks past the original's limit are skipped as damaged, the original
    kept."""
    decompressed = _count_decompressed(monkeypatch)
    path = _many_chunks(tmp_path / "many.mcap", finished=False)
    original = path.read_bytes()
    limit = read_limit(len(original))
    report = recover(path)
    assert report.status == "recovered" and report.messages > 0, report
    assert "skipped damaged chunks from byte" in report.reason and f"more than {limit} bytes" in report.reason
    assert report.corrupt_copy is not None and report.corrupt_copy.read_bytes() == original
    assert sum(decompressed) <= limit
    campaign = read_campaign(path, keys=())
    assert campaign.counts == {CHANNEL.topic: report.messages} and campaign.info["outcome"] == "interrupted"


# --- every reader of archives -------------------------------------------------------------------


def test_reading_refuses_a_bomb_chunk_in_bounded_memory(tmp_path: Path) -> None:
    files = {
        "lz4 indexed": _bombed(tmp_path / "lz4.mcap"),
        "lz4 not indexed": _bombed(tmp_path / "lz4-flat.mcap", indexed=False),
        "zstd indexed": _bombed(tmp_path / "zstd.mcap", "zstd"),
    }
    got = _in_child("from bridge.archive_read import read_campaign",
                    {name: f"read_campaign({str(path)!r})" for name, path in files.items()})
    for name, (outcome, grew) in got.items():
        assert grew < GROWTH_LIMIT, f"{name}: peak memory grew {_mib(grew)} ({outcome})"
        assert outcome.startswith("ArchiveError") and f"more than its declared {DECLARED} bytes" in outcome, (name, outcome)


def test_recovery_skips_a_bomb_chunk_in_bounded_memory(tmp_path: Path) -> None:
    files = {
        "unfinished lz4": _bombed(tmp_path / "unfinished.mcap", finished=False),
        "unfinished zstd": _bombed(tmp_path / "unfinished-zstd.mcap", "zstd", finished=False),
        "finished lz4": _bombed(tmp_path / "finished.mcap"),  # its footer is no reason to trust its chunks
    }
    got = _in_child("from bridge.archive_recovery import recover",
                    {name: f"recover({str(path)!r})" for name, path in files.items()})
    for name, (outcome, grew) in got.items():
        assert grew < GROWTH_LIMIT, f"{name}: peak memory grew {_mib(grew)} ({outcome})"
        assert outcome.startswith("RecoveryReport") and "status='recovered'" in outcome, (name, outcome)
        assert f"messages={2 * PER_CHUNK}" in outcome and "skipped damaged chunk" in outcome, (name, outcome)
        assert "ChunkRefused" in outcome, (name, outcome)
    for path in files.values():
        campaign = read_campaign(path)
        seqs = [m.seq for _, m in campaign.messages(bus.MOTOR_STATE)]
        assert seqs == [*range(PER_CHUNK), *range(2 * PER_CHUNK, 3 * PER_CHUNK)]
        assert campaign.info["outcome"] == "interrupted"  # messages were lost
        assert path.with_name(path.name + ".corrupt").exists()  # the original is kept


def test_console_start_up_recovers_a_bomb_in_bounded_memory(tmp_path: Path) -> None:
    campaigns = tmp_path / "data" / "campaigns"
    campaigns.mkdir(parents=True)
    path = _bombed(campaigns / "control-bomb.mcap", finished=False)
    setup = f"""
        from pathlib import Path
        from bridge.session import free_tcp_port, open_session
        from server.campaigns import CampaignManager
        def start_up():
            hub = f"tcp/127.0.0.1:{{free_tcp_port()}}"
            with open_session(listen=[hub]) as s:
                manager = CampaignManager(Path({str(tmp_path / 'data')!r}), s, hub)
                try:
                    return manager.recover_all(), manager.recovery_errors, manager.get("control-bomb").message
                finally:
                    manager.close()
    """
    (outcome, grew), = _in_child(setup, {"start-up": "start_up()"}).values()
    assert grew < GROWTH_LIMIT, f"peak memory grew {_mib(grew)} ({outcome})"
    assert outcome.startswith("(['control-bomb'], {}, ") and "skipped damaged chunk" in outcome, outcome
    assert len(read_campaign(path).messages(bus.MOTOR_STATE)) == 2 * PER_CHUNK


def test_alignment_and_rewrites_refuse_a_bomb_in_bounded_memory(tmp_path: Path) -> None:
    files = {"indexed": _bombed(tmp_path / "lz4.mcap"), "not indexed": _bombed(tmp_path / "lz4-flat.mcap", indexed=False)}
    original = {name: path.read_bytes() for name, path in files.items()}
    calls = {}
    for name, path in files.items():
        calls[f"align {name}"] = f"campaign_reference({str(path)!r})"
        calls[f"rewrite {name}"] = f"rewrite_archive({str(path)!r})"
    got = _in_child("from twin.camera.align import campaign_reference\nfrom server.archive_rewrite import rewrite_archive",
                    calls)
    for name, (outcome, grew) in got.items():
        assert grew < GROWTH_LIMIT, f"{name}: peak memory grew {_mib(grew)} ({outcome})"
        assert f"more than its declared {DECLARED} bytes" in outcome, (name, outcome)
        assert outcome.startswith("AlignmentError" if name.startswith("align") else "ChunkRefused"), (name, outcome)
    assert {name: path.read_bytes() for name, path in files.items()} == original
