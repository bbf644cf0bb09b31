"""The MCAP campaign archive: recording from a real bus, reading back, and crash recovery."""

from __future__ import annotations

import builtins
import errno
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest
import zenoh
from busutil import wait_until
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

import bridge.archive
from bridge import bus
from bridge.archive import CAMPAIGN, CHUNK_SIZE, ArchiveError, CampaignRecorder, write_campaign
from bridge.archive_read import is_complete, read_campaign
from bridge.archive_recovery import finish_in_place, recover
from bridge.session import free_tcp_port, open_session, publisher

REPO = Path(__file__).resolve().parents[1]


def motor_state(seq: int) -> bus.MotorState:
    return bus.MotorState(
        seq=seq, stamp_s=seq * 0.002, theta_rad=[0.001 * seq, 0.2, -0.3, 0.4],
        force_applied_N=[5.0, 6.0, 7.0, 8.0], drive="active", epoch="e1", bridge="b1",
    )


class LosslessPublisher:
    """Publishes with congestion control BLOCK, so that a test can expect every message: the
    contract's publishers DROP on motor keys (newest value wins), which may lose one now and then."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self._pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)

    def put(self, msg: bus.BusMessage) -> None:
        self._pub.put(bus.encode(msg))

    def close(self) -> None:
        self._pub.undeclare()


class Heard:
    """What a recorder's session hears besides the recorder: every sample (``samples``) and the
    seqs of those that decode, by key. A test that put its seed until the recorder heard one (extra
    copies of it arrive late) waits with :meth:`caught_up` for the last message it put, not for a
    count those copies reach while the burst's tail is still on its way."""

    def __init__(self, session: zenoh.Session) -> None:
        self.samples = 0
        self.seqs: dict[str, set[int]] = {}
        self._sub = session.declare_subscriber(bus.ALL, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.samples += 1  # before the seq: a seq heard is counted in ``samples``
        key = str(sample.key_expr)
        if bus.message_type(key) is None:
            return
        try:
            msg = bus.decode(key, sample.payload.to_bytes())
        except bus.BusDecodeError:
            return
        self.seqs.setdefault(key, set()).add(msg.seq)

    def caught_up(self, recorder: CampaignRecorder, *last: tuple[str, int]) -> bool:
        """Each ``(key, seq)`` of ``last`` heard, the recorder received all this heard, and its
        writer dealt with all it received (recorded, skipped or rejected)."""
        if not all(seq in self.seqs.get(key, ()) for key, seq in last):
            return False
        s = recorder.stats
        return (s.received + s.dropped >= self.samples
                and s.recorded + s.skipped + sum(s.rejected.values()) == s.received)

    def close(self) -> None:
        self._sub.undeclare()


# --- writing and reading -------------------------------------------------------------------------


def test_offline_campaign_round_trips_with_schemas(tmp_path: Path) -> None:
    path = tmp_path / "offline.mcap"
    t0 = 1_700_000_000_000_000_000
    msgs: list[tuple[str, int, bus.BusMessage]] = [(bus.MOTOR_STATE, t0 + i * 2_000_000, motor_state(i)) for i in range(50)]
    msgs.append((bus.ESTOP, t0 + 200_000_000, bus.EStop(seq=0, stamp_s=0.2, engaged=True, reason="test")))
    write_campaign(path, msgs, {"campaign_id": "c-0", "law": "pid"})
    campaign = read_campaign(path)
    assert [m for _, m in campaign.messages(bus.MOTOR_STATE)] == [motor_state(i) for i in range(50)]
    assert campaign.messages("/" + bus.ESTOP)[0][1].reason == "test"
    assert campaign.info["campaign_id"] == "c-0" and campaign.info["outcome"] == "finished"
    t, theta = campaign.series(bus.MOTOR_STATE, "theta_rad")
    assert t.shape == (50,) and theta.shape == (50, 4) and t[1] - t[0] == 2_000_000
    # Schemas are the contract's JSON Schemas, as Foxglove will see them.
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) >= 1
    by_topic = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
    schema = by_topic["/" + bus.MOTOR_STATE]
    assert schema.encoding == "jsonschema" and schema.name == "xneck.MotorState"
    assert msgspec.json.decode(schema.data) == bus.json_schema(bus.MotorState)
    # Idempotent recovery of a finished file: untouched.
    before = path.read_bytes()
    report = recover(path)
    assert report.status == "valid" and report.messages == 51 and path.read_bytes() == before


def test_messages_come_back_in_log_time_order_as_mcap_orders_them(tmp_path: Path) -> None:
    """A wall clock stepped back mid-campaign (NTP) leaves log times out of file order, across
    chunks, with ties: read_campaign gives each topic in the order mcap's own log-time ordering
    gives (time, then position in the file), which it no longer uses (its heap took half the read)."""
    path = tmp_path / "stepped.mcap"
    t0 = 1_700_000_000_000_000_000
    rng = np.random.default_rng(7)
    times = t0 + np.cumsum(rng.integers(0, 3, 400)) * 1_000_000  # ties where a step is 0
    times[150:] -= 60_000_000  # the clock steps back 60 ms: 30-odd messages overlap
    msgs: list[tuple[str, int, bus.BusMessage]] = []
    for i, t in enumerate(times):
        msgs.append((bus.MOTOR_STATE, int(t), motor_state(i)))
        if i % 7 == 0:
            msgs.append((bus.ESTOP, int(t), bus.EStop(seq=i, stamp_s=0.0, engaged=False, reason=str(i))))
    write_campaign(path, msgs, {"campaign_id": "c-1"}, chunk_size=2048)
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert len(reader.get_summary().chunk_indexes) > 5  # type: ignore[union-attr]
        expected: dict[str, list[tuple[int, int]]] = {}
        for _, channel, message in reader.iter_messages(log_time_order=True):
            expected.setdefault(channel.topic, []).append((message.log_time, message.sequence))
    campaign = read_campaign(path)
    got = {topic: [(t, m.seq) for t, m in msgs] for topic, msgs in campaign.topics.items()}
    assert got == expected
    assert [s for _, s in got["/" + bus.MOTOR_STATE]] != sorted(s for _, s in got["/" + bus.MOTOR_STATE])  # the step shows


def test_a_reader_that_names_its_keys_decodes_only_those(tmp_path: Path) -> None:
    """A 600 s campaign decoded whole would take ~2.5 GB, half of it a Foxglove scene no
    computation reads: ``keys=`` decodes the named topics alone, counts the others, and a topic
    left out is an error, not an empty list (it would read as "not recorded")."""
    path = tmp_path / "scene.mcap"
    with open(path, "wb") as f:
        writer, channel = _raw_writer(f, "sel")
        scene = writer.register_channel("/xneck/scene", "json", 0)
        estop = writer.register_channel("/" + bus.ESTOP, "json", writer.register_schema(
            "xneck.EStop", "jsonschema", bus.json_schema_bytes(bus.EStop)))
        for i in range(20):
            writer.add_message(channel, 10**18 + i * 2_000_000, bus.encode(motor_state(i)), i * 2_000_000, i)
            writer.add_message(scene, 10**18 + i * 2_000_000 + 1, b"{not json", i * 2_000_000, i)
        writer.add_message(estop, 10**18 + 5, b'{"seq": "x"}', 5, 0)  # not an EStop
        writer.finish()
    with pytest.raises(ArchiveError, match=r"/xneck/scene: invalid JSON"):
        read_campaign(path)  # whole: the damaged messages are refused
    campaign = read_campaign(path, keys=(bus.MOTOR_STATE,))
    assert [m for _, m in campaign.messages(bus.MOTOR_STATE)] == [motor_state(i) for i in range(20)]
    assert campaign.counts == {"/" + bus.MOTOR_STATE: 20, "/xneck/scene": 20, "/" + bus.ESTOP: 1}
    assert list(campaign.topics) == ["/" + bus.MOTOR_STATE]
    with pytest.raises(KeyError, match="scene was not read"):
        campaign.messages("/xneck/scene")
    with pytest.raises(KeyError, match="estop"):
        campaign.messages(bus.ESTOP)
    assert campaign.info["campaign_id"] == "sel"  # metadata is always read
    # A key named but not recorded is recorded as nothing, not refused.
    assert read_campaign(path, keys=(bus.MOTOR_STATE, bus.CAMERA_ALPHA)).messages(bus.CAMERA_ALPHA) == []
    # A test of the topic selects as well; one key given as a string is refused, not read per letter.
    assert list(read_campaign(path, keys=lambda topic: topic.endswith("state")).topics) == ["/" + bus.MOTOR_STATE]
    with pytest.raises(TypeError, match="not one key"):
        read_campaign(path, keys=bus.MOTOR_STATE)


def test_a_folded_topic_is_handed_over_message_by_message_and_not_kept(tmp_path: Path) -> None:
    """``fold=``: each message of the topic, decoded and checked, goes to its function in file order
    (``xneck identify`` keeps a few numbers of each motor state: 806 → 431 MB on a 577 s campaign);
    the campaign does not keep them, and says so if asked; a FoldError's own error goes through."""
    from bridge.archive_read import FoldError

    path = tmp_path / "fold.mcap"
    t0 = 1_700_000_000_000_000_000
    msgs: list[tuple[str, int, bus.BusMessage]] = [(bus.MOTOR_STATE, t0 + i * 2_000_000, motor_state(i)) for i in range(30)]
    msgs.append((bus.ESTOP, t0 + 5, bus.EStop(seq=0, stamp_s=0.0, engaged=False, reason="r")))
    write_campaign(path, msgs, {"campaign_id": "fold"}, chunk_size=512)
    seen: list[tuple[int, int]] = []
    campaign = read_campaign(path, keys=(bus.ESTOP,), fold={bus.MOTOR_STATE: lambda t, m: seen.append((t, m.seq))})
    assert sorted(seen) == [(t0 + i * 2_000_000, i) for i in range(30)]
    assert campaign.counts["/" + bus.MOTOR_STATE] == 30 and campaign.messages(bus.ESTOP)[0][1].reason == "r"
    with pytest.raises(KeyError, match="folded"):
        campaign.messages(bus.MOTOR_STATE)

    class Refused(Exception):
        pass

    def refuse(_t: int, m: bus.MotorState) -> None:
        if m.seq == 7:
            raise FoldError(Refused("seq 7"))

    with pytest.raises(Refused, match="seq 7"):
        read_campaign(path, fold={bus.MOTOR_STATE: refuse})
    def fails(_t: int, _m: bus.MotorState) -> None:
        raise ZeroDivisionError("a bug")

    with pytest.raises(ArchiveError, match="damaged MCAP file"):  # anything else a function raises
        read_campaign(path, fold={bus.MOTOR_STATE: fails})


def test_bad_files_give_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ArchiveError, match="no such file"):
        read_campaign(tmp_path / "missing.mcap")
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording at all")
    with pytest.raises(ArchiveError, match="not an MCAP file") as err:
        read_campaign(text)
    assert err.value.path == text and str(text) in str(err.value)
    with pytest.raises(ArchiveError, match="not an MCAP file"):
        recover(text)
    existing = tmp_path / "existing.mcap"
    write_campaign(existing, [], {"campaign_id": "x"})
    with pytest.raises(ArchiveError, match="cannot create"):
        write_campaign(existing, [], {"campaign_id": "x"})
    with pytest.raises(ArchiveError, match="strings"):
        write_campaign(tmp_path / "meta.mcap", [], {"attempt": 3})  # type: ignore[dict-item]


def test_recorder_archives_every_channel_from_the_bus(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path,
) -> None:
    a, b = sessions
    path = tmp_path / "campaign.mcap"
    events = publisher(a, bus.CAMPAIGN_EVENTS)
    states = LosslessPublisher(a, bus.MOTOR_STATE)
    commands = LosslessPublisher(a, bus.MOTOR_COMMAND)
    heard = Heard(b)
    recorder = CampaignRecorder(b, path, {"campaign_id": "c-1", "kind": "tracking", "law": "pid"}, flush_period_s=0.2)
    try:
        start = bus.CampaignEvent(seq=0, stamp_s=0.0, campaign_id="c-1", kind="tracking", event="started")
        assert wait_until(lambda: (events.put(start), recorder.stats.recorded > 0)[1]), "recorder never got data"
        for i in range(200):
            states.put(motor_state(i))
            if i % 10 == 0:
                commands.put(bus.ForceCommand(seq=i // 10, stamp_s=i * 0.002, force_N=[1.0, 2.0, 3.0, 4.0], source="pid", sender="c", epoch="e1"))
            time.sleep(0.0005)
        a.put(bus.MOTOR_STATE, b'{"v": 1, "broken": true}', congestion_control=zenoh.CongestionControl.BLOCK)
        a.put("xneck/not/in/contract", b"{}", congestion_control=zenoh.CongestionControl.BLOCK)
        # the last ones put, not a count: late copies of the start event (put until the recorder
        # heard one) make a count reach 220 past the first with the states' tail still on its way
        assert wait_until(lambda: heard.caught_up(recorder, (bus.MOTOR_STATE, 199), (bus.MOTOR_COMMAND, 19))
                          and sum(recorder.stats.rejected.values()) >= 2, 10), recorder.stats
    finally:
        recorder.stop("finished", {"trajectory": "step"})
        heard.close()
        for p in (events, states, commands):
            p.close()

    campaign = read_campaign(path)
    assert [m.seq for _, m in campaign.messages(bus.MOTOR_STATE)] == list(range(200))
    assert len(campaign.messages(bus.MOTOR_COMMAND)) == 20
    assert campaign.messages(bus.CAMPAIGN_EVENTS)[0][1].event == "started"
    assert campaign.schemas == {
        "/" + bus.MOTOR_STATE: "xneck.MotorState",
        "/" + bus.MOTOR_COMMAND: "xneck.ForceCommand",
        "/" + bus.CAMPAIGN_EVENTS: "xneck.CampaignEvent",
    }
    info = campaign.info
    assert (info["campaign_id"], info["law"], info["trajectory"], info["outcome"]) == ("c-1", "pid", "step", "finished")
    assert info["start_time"] < info["end_time"] and info["software_version"]
    rejected = msgspec.json.decode(campaign.metadata["xneck.recorder"]["rejected"])
    assert rejected == {bus.MOTOR_STATE: 1, "xneck/not/in/contract": 1}
    times = [t for t, _ in campaign.messages(bus.MOTOR_STATE)]
    assert times == sorted(times) and abs(times[0] / 1e9 - time.time()) < 60


def test_a_truth_archived_before_runs_were_named_still_reads(tmp_path: Path) -> None:
    """The twin's identity went into the Zenoh attachment (bridge.session.RUN_PREFIX), not into
    Truth: a Truth v2 would have made every archive recorded before unreadable (one version per
    reader). A truth as recorded then, bytes for bytes, reads as it did."""
    recorded = (b'{"seq":7,"stamp_s":1.25,"v":1,"alpha_rad":[0.1,0.2,0.3],"alpha_dot_rad_s":[0.0,0.0,0.0],'
                b'"theta_rad":[1.0,2.0,3.0,4.0],"theta_dot_rad_s":[0.0,0.0,0.0,0.0],"tension_N":[5.0,6.0,7.0,8.0],'
                b'"elongation_m":[0.0,0.0,0.0,0.0],"slack":[false,false,false,false],"near_singular":false}')
    path = tmp_path / "old.mcap"
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.LZ4)
        writer.start(profile="xneck")
        writer.add_metadata("xneck.campaign.start", {"campaign_id": "old"})
        schema = writer.register_schema("xneck.Truth", "jsonschema", bus.json_schema_bytes(bus.Truth))
        channel = writer.register_channel("/" + bus.TWIN_TRUTH, "json", schema)
        writer.add_message(channel, 10**18, recorded, 10**18, 0)
        writer.finish()
    ((_, truth),) = read_campaign(path).messages(bus.TWIN_TRUTH)
    assert (truth.seq, truth.stamp_s, truth.tension_N) == (7, 1.25, [5.0, 6.0, 7.0, 8.0])


# --- crash recovery ------------------------------------------------------------------------------

PER_CHUNK = 40


def _raw_writer(f, campaign_id: str) -> tuple[Writer, int]:
    """A started raw MCAP writer with the recorder's start record and a MotorState channel."""
    writer = Writer(f, chunk_size=1 << 30, compression=CompressionType.LZ4)
    writer.start(profile="xneck")
    writer.add_metadata("xneck.campaign.start", {"campaign_id": campaign_id, "law": "pid"})
    schema = writer.register_schema("xneck.MotorState", "jsonschema", bus.json_schema_bytes(bus.MotorState))
    return writer, writer.register_channel("/" + bus.MOTOR_STATE, "json", schema)


def _crashing_file(path: Path, n_chunks: int) -> list[tuple[int, int]]:
    """Write ``n_chunks`` chunks of ``PER_CHUNK`` messages with the raw writer, flushing after each
    like the recorder does, then finish; returns each chunk's (start, end) byte offsets. A prefix
    of this file is what a recorder killed after that many bytes leaves on disk."""
    with open(path, "wb") as f:
        writer, channel = _raw_writer(f, "crash")
        for k in range(n_chunks):
            for i in range(k * PER_CHUNK, (k + 1) * PER_CHUNK):
                writer.add_message(channel, 10**18 + i * 2_000_000, bus.encode(motor_state(i)), i * 2_000_000, i)
            writer.flush()
        writer.finish()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) == n_chunks
    return [(c.chunk_start_offset, c.chunk_start_offset + c.chunk_length) for c in summary.chunk_indexes]


def _cut_points(chunks: list[tuple[int, int]], size: int) -> list[int]:
    """Where a crash may cut a file of four chunks: inside a chunk's header, in its middle, one
    byte short of its end, at its end, in the message indexes, the summary and the footer."""
    return sorted({chunks[0][0] + 3, chunks[1][0] + 20, (chunks[1][0] + chunks[1][1]) // 2, chunks[2][1] - 1,
                   chunks[2][1], chunks[3][1] + 5, size - 30, size - 1})


def test_truncated_files_are_rejected_then_recovered(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    chunks = _crashing_file(full, 4)
    data = full.read_bytes()
    for cut in _cut_points(chunks, len(data)):
        path = tmp_path / f"cut-{cut}.mcap"
        path.write_bytes(data[:cut])
        with pytest.raises(ArchiveError, match="truncated or unfinished"):
            read_campaign(path)
        complete = sum(1 for _, end in chunks if end <= cut)
        report = recover(path)
        assert report.status == "recovered" and report.messages == complete * PER_CHUNK, cut
        assert report.corrupt_copy is None and report.bytes_discarded < cut
        campaign = read_campaign(path)
        assert [m for _, m in campaign.messages(bus.MOTOR_STATE)] == [motor_state(i) for i in range(complete * PER_CHUNK)]
        assert campaign.info["outcome"] == "interrupted" and campaign.info["campaign_id"] == "crash"
        assert "xneck.recovery" in campaign.metadata
        assert recover(path).status == "valid"  # idempotent


def test_an_unfinished_file_is_finished_in_place_with_the_outcome_given(tmp_path: Path) -> None:
    """What the console does to the archive of a campaign that failed on a full disk (audit of
    2026-11-28): the file is cut after its last complete record and finished where it lies, no
    copy; every complete chunk is kept byte for byte, the summary indexes them, and the final
    record says the outcome and message given. Cut anywhere, the summary and footer included."""
    full = tmp_path / "full.mcap"
    chunks = _crashing_file(full, 4)
    data = full.read_bytes()
    for cut in _cut_points(chunks, len(data)):
        path = tmp_path / f"cut-{cut}.mcap"
        path.write_bytes(data[:cut])
        complete = sum(1 for _, end in chunks if end <= cut)
        report = finish_in_place(path, "failed", {"message": "recording failed: No space left on device (ENOSPC)"})
        assert report.status == "recovered" and report.messages == complete * PER_CHUNK, cut
        kept = cut - report.bytes_discarded
        assert path.read_bytes()[:kept] == data[:kept] and kept >= (chunks[complete - 1][1] if complete else 0)
        campaign = read_campaign(path)
        assert [m for _, m in campaign.messages(bus.MOTOR_STATE)] == [motor_state(i) for i in range(complete * PER_CHUNK)]
        assert campaign.info["outcome"] == "failed" and "ENOSPC" in campaign.info["message"], cut
        assert campaign.info["campaign_id"] == "crash" and campaign.metadata["xneck.recovery"]["method"] == "in place"
        with open(path, "rb") as f:  # indexed as a writer indexes: the summary is what readers seek with
            summary = make_reader(f).get_summary()
        assert summary is not None and len(summary.chunk_indexes) == complete, cut
        assert summary.statistics is not None and summary.statistics.message_count == complete * PER_CHUNK
        assert recover(path).status == "valid"  # finished: nothing left to repair


def test_a_file_damaged_inside_is_not_finished_in_place(tmp_path: Path) -> None:
    """Damage is :func:`recover`'s work (it salvages around it and keeps the original): finishing
    in place refuses it and leaves the file as it was."""
    path = tmp_path / "damaged.mcap"
    chunks = _crashing_file(path, 3)
    data = bytearray(path.read_bytes()[: chunks[2][1]])
    data[(chunks[1][0] + chunks[1][1]) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ArchiveError, match="damaged record"):
        finish_in_place(path, "failed", {"message": "m"})
    assert path.read_bytes() == bytes(data)


def test_damage_inside_the_file_keeps_the_original(tmp_path: Path) -> None:
    path = tmp_path / "damaged.mcap"
    chunks = _crashing_file(path, 3)
    data = bytearray(path.read_bytes()[: chunks[2][1]])  # unfinished, and...
    start, end = chunks[1]
    data[(start + end) // 2] ^= 0xFF  # ...a flipped byte in the second chunk
    path.write_bytes(bytes(data))
    report = recover(path)
    # The damaged chunk is skipped (its framing is intact), the ones around it are kept.
    assert report.status == "recovered" and report.messages == 2 * PER_CHUNK
    assert "skipped damaged chunk" in report.reason and report.corrupt_copy is not None
    assert report.corrupt_copy.read_bytes() == bytes(data)
    seqs = [m.seq for _, m in read_campaign(path).messages(bus.MOTOR_STATE)]
    assert seqs == [*range(PER_CHUNK), *range(2 * PER_CHUNK, 3 * PER_CHUNK)]
    # Damaged again after its recovery (a failing disk): both originals are kept, none replaced.
    first_copy = report.corrupt_copy
    again = bytearray(path.read_bytes())
    again[len(again) // 3] ^= 0xFF
    path.write_bytes(bytes(again))
    second = recover(path)
    assert second.status == "recovered" and second.corrupt_copy is not None, second
    assert second.corrupt_copy != first_copy and first_copy.read_bytes() == bytes(data)
    assert second.corrupt_copy.read_bytes() == bytes(again)
    assert recover(path).status == "valid"


def test_a_damaged_first_chunk_loses_only_its_own_messages(tmp_path: Path) -> None:
    """Audit of 2026-11-26: schemas and channels are written in the chunk where a key first
    appears, so a flipped byte in the first chunk lost every later message of those keys too
    (0 of 1316 intact messages kept). Recovery now tells a lost channel's key from its messages
    (each payload decodes as exactly one type of the bus contract)."""
    path = tmp_path / "damaged-first.mcap"
    chunks = _crashing_file(path, 3)
    data = bytearray(path.read_bytes()[: chunks[2][1]])  # unfinished, and...
    end = chunks[0][1]
    data[end - 20] ^= 0xFF  # ...a flipped byte in the first chunk, which holds the channel
    path.write_bytes(bytes(data))
    report = recover(path)
    assert report.status == "recovered" and report.messages == 2 * PER_CHUNK, report
    assert "skipped damaged chunk" in report.reason and "channel" in report.reason
    campaign = read_campaign(path)
    assert [m.seq for _, m in campaign.messages(bus.MOTOR_STATE)] == list(range(PER_CHUNK, 3 * PER_CHUNK))
    assert campaign.schemas == {"/" + bus.MOTOR_STATE: "xneck.MotorState"}


class _FullOnce:
    """A file whose first write of a chunk fails with ENOSPC (a disk full for a moment: the
    writes after it succeed). The rest is the real file's."""

    def __init__(self, f) -> None:
        self._f = f
        self.failed = False

    def write(self, data: bytes) -> int:
        if not self.failed and data[:1] == bytes([Opcode.CHUNK]):
            self.failed = True
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self._f.write(data)

    def __getattr__(self, name: str):
        return getattr(self._f, name)


def test_a_full_disk_while_writing_the_copy_is_not_damage_of_the_original(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Review of session 53: an ENOSPC writing the recovered copy was taken for "damaged record at
    byte N" of the original; the writes after it succeeded, and a copy whose statistics counted
    messages its index lacked replaced the intact original (kept only as ``.corrupt``). Now the
    error is the copy's: recovery fails, the file is left as it was (the console then finishes it
    in place), and with room again it recovers every message."""
    path = tmp_path / "crash.mcap"
    n_chunks = 3 * CHUNK_SIZE // (PER_CHUNK * len(bus.encode(motor_state(0)))) + 1  # the copy writes 2 chunks
    chunks = _crashing_file(path, n_chunks)
    data = path.read_bytes()[: chunks[-1][1]]  # killed after its last chunk: no summary, no footer
    path.write_bytes(data)
    copies: list[_FullOnce] = []

    def full_once(file, mode="r", *args, **kwargs):
        f = builtins.open(file, mode, *args, **kwargs)  # noqa: SIM115 - ArchiveWriter closes it
        if "x" in mode:  # the recovered copy (ArchiveWriter never overwrites)
            copies.append(_FullOnce(f))
            return copies[-1]
        return f

    monkeypatch.setattr(bridge.archive, "open", full_once, raising=False)
    with pytest.raises(ArchiveError, match=r"cannot write its recovered copy \(No space left on device \(ENOSPC\)\)"):
        recover(path)
    assert [c.failed for c in copies] == [True]  # the copy's first chunk, while the original was read
    assert path.read_bytes() == data
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no copy left, no .corrupt
    monkeypatch.undo()
    report = recover(path)
    assert report.messages == n_chunks * PER_CHUNK and report.corrupt_copy is None, report
    assert len(read_campaign(path).messages(bus.MOTOR_STATE)) == n_chunks * PER_CHUNK


def test_a_final_record_written_before_a_lost_chunk_is_not_believed(tmp_path: Path) -> None:
    """Audit of 2026-11-26: stop() wrote the final ``xneck.campaign`` record (outcome finished,
    recorded 2000) while the last chunk was still open; the disk filled, the chunk never came, and
    the recovered file said finished with 1008 of 2000 messages. Recovery now calls a file
    ``interrupted`` when its recorder counted more messages than it kept."""
    path = tmp_path / "lost-tail.mcap"
    with open(path, "wb") as f:
        writer, channel = _raw_writer(f, "tail")
        for i in range(2 * PER_CHUNK):
            writer.add_message(channel, 10**18 + i * 2_000_000, bus.encode(motor_state(i)), i * 2_000_000, i)
            if i == PER_CHUNK - 1:
                writer.flush()
        # the old order: the final records go out while the second chunk is still open
        writer.add_metadata(CAMPAIGN, {"campaign_id": "tail", "law": "pid", "outcome": "finished"})
        writer.add_metadata("xneck.recorder", {"received": str(2 * PER_CHUNK), "recorded": str(2 * PER_CHUNK)})
        f.flush()
        cut = f.tell()  # the disk is full here: the open chunk, the summary and the footer never land
    path.write_bytes(path.read_bytes()[:cut])
    report = recover(path)
    assert report.messages == PER_CHUNK
    info = read_campaign(path).info
    assert info["outcome"] == "interrupted", info
    assert read_campaign(path).metadata["xneck.recovery"]["outcome_before"] == "finished"


def test_the_recorder_writes_its_last_chunk_before_its_final_records(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With the disk full at finish(), every recorded message is on disk before the final records:
    recovery keeps them all and the outcome recorded stands."""
    a, b = sessions
    path = tmp_path / "full-at-stop.mcap"
    states = LosslessPublisher(a, bus.MOTOR_STATE)
    heard = Heard(b)
    recorder = CampaignRecorder(b, path, {"campaign_id": "c-1"}, flush_period_s=60.0)  # one open chunk
    try:
        assert wait_until(lambda: (states.put(motor_state(0)), recorder.stats.recorded > 0)[1])
        for i in range(1, 300):
            states.put(motor_state(i))
        # the last one recorded, not a count: the seed's late copies reach 300 with the tail still queued
        assert wait_until(lambda: heard.caught_up(recorder, (bus.MOTOR_STATE, 299)), 10), recorder.stats
        recorded = recorder.stats.recorded

        def disk_full() -> None:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(recorder._out, "finish", disk_full)
        with pytest.raises(ArchiveError, match="finishing failed"):
            recorder.stop("finished")
    finally:
        heard.close()
        states.close()
    monkeypatch.undo()
    report = recover(path)
    assert report.messages == recorded
    assert read_campaign(path).info["outcome"] == "finished"


def test_final_metadata_is_asked_once_the_writer_has_written_its_last_message(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path,
) -> None:
    """What says what the file holds (a campaign's α_IP recorded, user audit of session 42) is asked
    after the backlog, not before: here a writer slowed by its filter still has messages queued."""
    a, b = sessions
    path = tmp_path / "backlog.mcap"
    states = LosslessPublisher(a, bus.MOTOR_STATE)
    kept = [0]

    def keep(_key: str, _msg: bus.BusMessage, _run: str, _camera: str, _controller: str = "") -> bool:
        time.sleep(0.002)
        kept[0] += 1
        return True

    recorder = CampaignRecorder(b, path, {"campaign_id": "c-1"}, flush_period_s=0.2, keep=keep)
    try:
        assert wait_until(lambda: (states.put(motor_state(0)), recorder.stats.received > 0)[1])
        for i in range(1, 300):
            states.put(motor_state(i))
        assert wait_until(lambda: recorder.stats.received >= 300)
    finally:
        recorder.stop("finished", {"kept": "at the stop"}, final_metadata=lambda: {"kept": str(kept[0])})
        states.close()
    campaign = read_campaign(path)
    assert campaign.info["kept"] == str(len(campaign.messages(bus.MOTOR_STATE))) == str(recorder.stats.recorded)


def test_a_stop_on_the_campaigns_end_event_keeps_all_that_came_before_it(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The official CI of stop 64: a campaign's MCAP lacked its final ControllerTiming, put before
    its end event. Each Zenoh subscriber's callback runs in its own thread (zenoh-python's default),
    so the runner heard the end event and stopped the recorder while the recorder's own thread still
    had what came before it. Here that thread is slowed (2 ms a sample): the stop that names the
    campaign whose end it heard still records everything put before the end event."""
    a, b = sessions
    path = tmp_path / "end.mcap"
    states, events = LosslessPublisher(a, bus.MOTOR_STATE), LosslessPublisher(a, bus.CAMPAIGN_EVENTS)
    heard_end = threading.Event()

    def on_event(sample: zenoh.Sample) -> None:
        if bus.decode(bus.CampaignEvent, sample.payload.to_bytes()).event == "finished":
            heard_end.set()

    sub = b.declare_subscriber(bus.CAMPAIGN_EVENTS, on_event)
    recorder = CampaignRecorder(b, path, {"campaign_id": "c-1"}, flush_period_s=0.2, keep=lambda *_: True)
    try:
        assert wait_until(lambda: (states.put(motor_state(0)), recorder.stats.received > 0)[1])
        slow_run_of = bridge.archive.run_of
        monkeypatch.setattr(bridge.archive, "run_of", lambda sample: (time.sleep(0.002), slow_run_of(sample))[1])
        for i in range(1, 300):
            states.put(motor_state(i))
        events.put(bus.CampaignEvent(seq=1, stamp_s=1.0, campaign_id="c-1", kind="control", event="finished"))
        assert heard_end.wait(10)
        assert recorder.stats.received < 300  # the race is there: the recorder's thread is behind
    finally:
        recorder.stop("finished", end_of="c-1")
        sub.undeclare()
        states.close()
        events.close()
    campaign = read_campaign(path)
    # every state (the seed's repeats of 0 aside) and the end event
    assert {m.seq for _, m in campaign.messages(bus.MOTOR_STATE)} == set(range(300))
    assert len(campaign.messages(bus.CAMPAIGN_EVENTS)) == 1


def test_a_stamp_beyond_any_clock_is_recorded_at_its_receive_time(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path,
) -> None:
    """Audit of 2026-11-26: one valid message stamped 1e300 s overflowed the publish time and
    killed the writer thread: the campaign failed with a storage fault, 1000 messages unrecorded."""
    a, b = sessions
    path = tmp_path / "stamps.mcap"
    states = LosslessPublisher(a, bus.MOTOR_STATE)
    frames = LosslessPublisher(a, bus.CAMERA_FRAME)
    heard = Heard(b)
    recorder = CampaignRecorder(b, path, {"campaign_id": "c-1"}, flush_period_s=0.2)
    try:
        assert wait_until(lambda: (states.put(motor_state(0)), recorder.stats.recorded > 0)[1])
        states.put(msgspec.structs.replace(motor_state(1), stamp_s=1e300))
        jpeg = cv2.imencode(".jpg", np.zeros((2, 2, 3), np.uint8))[1].tobytes()
        frames.put(bus.CameraFrame(seq=1, stamp_s=1e300, capture_stamp_s=1e300, frame_id="cam", format="jpeg",
                                   data=jpeg, width=2, height=2))
        for i in range(2, 100):
            states.put(motor_state(i))
        assert wait_until(lambda: heard.caught_up(recorder, (bus.MOTOR_STATE, 99), (bus.CAMERA_FRAME, 1)), 10), \
            recorder.stats
    finally:
        recorder.stop("finished")
        heard.close()
        states.close()
        frames.close()
    seqs = [m.seq for _, m in read_campaign(path).messages(bus.MOTOR_STATE)]
    assert seqs[-99:] == list(range(1, 100))


def test_an_alpha_ip_captured_after_its_publication_is_rejected_not_recorded(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path,
) -> None:
    """Audit of 2026-11-29: a stray α_IP stamped capture 1e9 s was archived mid-campaign and the
    identification then refused the whole record for a clock step. The recorder rejects it (counted,
    with the reason) and records the camera's other frames."""
    a, b = sessions
    path = tmp_path / "alpha.mcap"
    alphas = LosslessPublisher(a, bus.CAMERA_ALPHA)

    def alpha(seq: int, **changes) -> bus.CameraAlpha:
        msg = bus.CameraAlpha(seq=seq, stamp_s=seq / 30 + 0.05, capture_stamp_s=seq / 30, alpha_ip_rad=[0.1, 0.2, 0.3],
                              source="twin-render")
        return msgspec.structs.replace(msg, **changes)

    heard = Heard(b)
    recorder = CampaignRecorder(b, path, {"campaign_id": "c-1"}, flush_period_s=0.2)
    try:
        assert wait_until(lambda: (alphas.put(alpha(0)), recorder.stats.recorded > 0)[1])
        for i in range(1, 30):
            alphas.put(alpha(i))
            if i == 10:
                alphas.put(alpha(1, capture_stamp_s=1e9, source="stray"))
                alphas.put(alpha(2, capture_stamp_s=1e300, source="stray"))
        assert wait_until(lambda: heard.caught_up(recorder, (bus.CAMERA_ALPHA, 29)), 10), recorder.stats
    finally:
        recorder.stop("finished")
        heard.close()
        alphas.close()
    campaign = read_campaign(path)
    frames = [m for _, m in campaign.messages(bus.CAMERA_ALPHA)]
    assert {m.source for m in frames} == {"twin-render"} and [m.seq for m in frames][-29:] == list(range(1, 30))
    assert msgspec.json.decode(campaign.metadata["xneck.recorder"]["rejected"]) == {bus.CAMERA_ALPHA: 2}
    assert "after its publication" in campaign.metadata["xneck.recorder"]["last_reject_reason"]


RECORDER_SCRIPT = """
import sys, time
from bridge.session import open_session
from bridge.archive import CampaignRecorder
port, path = sys.argv[1], sys.argv[2]
with open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session:
    recorder = CampaignRecorder(session, path, {"campaign_id": "killed", "law": "pid"}, flush_period_s=0.2)
    print("ready", flush=True)
    deadline = time.monotonic() + 30  # never outlive a broken test
    while time.monotonic() < deadline:
        time.sleep(0.05)
        print(recorder.stats.recorded, flush=True)
"""


def test_killed_recorder_leaves_a_recoverable_file(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    port = free_tcp_port()
    with open_session(listen=[f"tcp/127.0.0.1:{port}"], connect=[]) as session:
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        proc = subprocess.Popen(
            [sys.executable, "-c", RECORDER_SCRIPT, str(port), str(path)],
            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )
        lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=lambda: [lines.put(line.strip()) for line in proc.stdout], daemon=True).start()  # type: ignore[union-attr]
        recorded = [0]

        def recorder_has(n: int) -> bool:
            while not lines.empty():
                line = lines.get_nowait()
                if line.isdigit():
                    recorded[0] = int(line)
            return recorded[0] >= n

        try:
            assert lines.get(timeout=15) == "ready"
            states = LosslessPublisher(session, bus.MOTOR_STATE)
            seq = 0
            deadline = time.monotonic() + 10
            # Publish at about 1 kHz until the recorder has flushed a few chunks' worth, then kill it mid-stream.
            while not recorder_has(600) and time.monotonic() < deadline:
                states.put(motor_state(seq))
                seq += 1
                time.sleep(0.001)
            time.sleep(0.5)  # keep streaming a little: the kill must land with a chunk open
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=5)
            states.close()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=5)
    assert proc.returncode == -signal.SIGKILL
    assert not is_complete(path)
    with pytest.raises(ArchiveError, match="truncated or unfinished"):
        read_campaign(path)
    report = recover(path)
    assert report.status == "recovered" and report.messages >= 300, report
    campaign = read_campaign(path)
    seqs = [m.seq for _, m in campaign.messages(bus.MOTOR_STATE)]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # a contiguous stream, no holes
    assert campaign.info["outcome"] == "interrupted" and campaign.info["campaign_id"] == "killed"
    assert campaign.metadata.get(CAMPAIGN, {}).get("end_time")
