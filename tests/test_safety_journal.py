"""The console's safety journal (server.safety_journal) and the bridge transitions it is fed
(server.bridge_transitions), without a bus: synthetic MotorStates on a fake clock, the file in a
temporary directory. The console's REST e-stops and a real bus's states: tests/test_server_api.py."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from busutil import wait_until

from bridge import bus
from server import bridge_transitions as bt
from server.bridge_transitions import BridgeTransitions
from server.safety_journal import SafetyJournal, read_journal


def state(seq: int, drive: str = "inactive", engaged: bool = False, reason: str = "", hold_reason: str = "",
          bridge: str = "bridge-a", epoch: str = "run-1") -> bus.MotorState:
    return bus.MotorState(seq=seq, stamp_s=seq * 0.002, theta_rad=[0.0] * 4, force_applied_N=[0.0] * 4,
                          drive=drive, hold_reason=hold_reason, epoch=epoch, bridge=bridge,  # pyright: ignore[reportArgumentType]
                          estop_engaged=engaged, estop_reason=reason)


class Detector:
    """A BridgeTransitions whose lines are kept in a list, on a clock the test moves."""

    def __init__(self, **kwargs) -> None:
        self.now = 0.0
        self.lines: list[dict] = []
        self.at: list[float] = []  # the clock's time of each line
        self.t = BridgeTransitions(self._emit, clock=lambda: self.now, **kwargs)

    def _emit(self, event: str, **fields) -> None:
        self.lines.append({"event": event, **fields})
        self.at.append(self.now)

    def see(self, *states: bus.MotorState, dt: float = 0.1) -> None:
        for s in states:
            self.now += dt
            self.t.observe(s)


@pytest.fixture
def journal(tmp_path: Path):
    j = SafetyJournal(tmp_path)
    yield j
    j.close()


def test_an_estop_engaged_and_released_is_one_line_each_and_a_state_seen_again_none() -> None:
    d = Detector()
    first = state(1)
    d.see(first, first, first, state(2), state(3))  # the same state again, and new ones saying the same
    assert [line["event"] for line in d.lines] == ["bridge_run"]
    assert d.lines[0]["previous_epoch"] == "" and d.lines[0]["drive"] == "inactive"
    engaged = state(4, "disabled", True, "console-1a2b3c: operator pressed Escape")
    d.see(engaged, engaged, state(5, "disabled", True, "console-1a2b3c: operator pressed Escape"),
          state(6), state(7))
    assert [line["event"] for line in d.lines] == ["bridge_run", "bridge_state", "bridge_state"]
    on, off = d.lines[1], d.lines[2]
    assert on["changed"] == ["estop", "estop_reason", "drive"] and on["estop_engaged"] is True
    assert on["estop_reason"] == "console-1a2b3c: operator pressed Escape" and on["was"]["drive"] == "inactive"
    assert off["changed"] == ["estop", "estop_reason", "drive"] and off["estop_engaged"] is False
    assert off["drive"] == "inactive" and off["was"]["estop_engaged"] is True
    assert all(line["bridge"] == "bridge-a" and line["epoch"] == "run-1" and line["suppressed"] == 0
               for line in d.lines)
    assert on["bridge_stamp_s"] == pytest.approx(4 * 0.002)


def test_drive_changes_name_the_hold_reason_and_a_restart_names_the_run_before() -> None:
    d = Detector()
    d.see(state(1), state(2, "active"), state(3, "hold", hold_reason="stale states"),
          state(4, "hold", hold_reason="no command"), state(1, epoch="run-2"))
    assert [line.get("changed") for line in d.lines] == [None, ["drive"], ["drive", "hold_reason"], ["hold_reason"],
                                                        None]
    assert d.lines[2]["hold_reason"] == "stale states" and d.lines[3]["was"]["hold_reason"] == "stale states"
    restart = d.lines[4]
    assert restart["event"] == "bridge_run" and restart["epoch"] == "run-2" and restart["previous_epoch"] == "run-1"


def test_a_flood_of_flipping_states_writes_a_bounded_number_of_lines_that_count_the_rest() -> None:
    """A forged peer flipping the e-stop at 500 Hz for 10 s, each state seen (the console sees at
    most 10 a second; the worst case): a few lines a second, and every transition accounted for."""
    d = Detector()
    n = 5000
    d.see(*(state(i, "disabled" if i % 2 else "inactive", engaged=bool(i % 2), reason="forged" if i % 2 else "")
            for i in range(n)), dt=0.002)
    flipped = n - 1
    seconds = n * 0.002
    assert len(d.lines) <= bt.BURST_LINES + seconds * bt.LINES_PER_S + 1, len(d.lines)
    d.now += 10.0
    d.t.observe(state(n - 1, "disabled", True, "forged"))  # the same look: no transition, the owed line goes
    shown = sum(1 for line in d.lines if line.get("changed"))
    assert shown + sum(line["suppressed"] for line in d.lines) == flipped
    assert d.t.suppressed == flipped - shown > 4000
    assert any(line["event"] == "bridge_state" and line["changed"] == [] and line["suppressed"] > 0
               for line in d.lines)  # flapped and back: said, with its count


def test_forged_runs_and_names_stay_bounded_and_their_text_is_cleaned() -> None:
    d = Detector()
    d.see(*(state(1, bridge=f"forger-{i}", epoch=f"e{i}") for i in range(200)), dt=0.001)
    assert len(d.t._runs) == bt.MAX_RUNS and d.t.runs_forgotten == 200 - bt.MAX_RUNS
    assert len(d.t._buckets) <= bt.MAX_RUNS
    assert len(d.lines) <= bt.ALL_BURST_LINES + 0.2 * bt.ALL_LINES_PER_S + 1
    d.see(state(2, "hold", bridge="b\x1b[2J\u202e" + "x" * 5000, epoch="e" * 5000, hold_reason="\n" + "r" * 5000),
          dt=100.0)
    line = d.lines[-1]
    assert len(line["bridge"]) <= bt.NAME_MAX_CHARS and "\x1b" not in line["bridge"] and "\u202e" not in line["bridge"]
    assert len(line["epoch"]) <= bt.NAME_MAX_CHARS
    assert len(line["hold_reason"]) <= bt.REASON_MAX_CHARS and "\n" not in line["hold_reason"]


def test_a_live_bridges_lines_are_written_among_forged_new_runs() -> None:
    """Review of session 43: owed lines were paid to the runs seen least recently first, so a bridge
    seen at every other sample (always the most recent) was starved by a forger announcing 5 new
    runs a second: its e-stop release was never written, nor counted. Now the oldest debt goes
    first, a known run's e-stop change before anything else, and the health says what is owed."""
    d = Detector()
    for k in range(700):  # 70 s, the sampler's 10 states a second: the real bridge's and a forger's in turn
        if k % 2:
            d.see(state(k, "inactive", bridge=f"forged-{k}", epoch=f"e{k}"))
            continue
        engaged = 100 <= k < 200  # engaged at 10 s, released at 20 s
        drive = "disabled" if engaged else "hold" if k >= 300 else "active"  # a hold at 30 s: no e-stop, no hurry
        d.see(state(k, drive, engaged, "operator" if engaged else "", "stale states" if k >= 300 else "",
                    bridge="real-bridge", epoch="real-run"))
    real = [(at, line) for at, line in zip(d.at, d.lines, strict=True) if line["bridge"] == "real-bridge"]
    changes = [(round(at, 1), line["changed"]) for at, line in real if line["event"] == "bridge_state"]
    on = [at for at, line in real if line.get("changed") and "estop" in line["changed"] and line["estop_engaged"]]
    off = [at for at, line in real if line.get("changed") and "estop" in line["changed"] and not line["estop_engaged"]]
    hold = [at for at, line in real if line.get("changed") and line["drive"] == "hold"]
    assert len(on) == 1 and 10.0 <= on[0] <= 11.0, changes
    assert len(off) == 1 and 20.0 <= off[0] <= 21.0, changes
    assert len(hold) == 1 and 30.0 <= hold[0] <= 30.0 + bt.MAX_RUNS / bt.ALL_LINES_PER_S + 1, changes
    assert all(line["suppressed"] == 0 for _, line in real)
    status = d.t.status()
    assert 0 < status["owed"] < bt.MAX_RUNS, status  # forged runs' first lines waiting, bounded
    assert 0 < status["oldest_owed_s"] <= bt.MAX_RUNS / bt.ALL_LINES_PER_S + 1, status


def test_a_forgotten_runs_owed_first_line_is_counted_as_suppressed() -> None:
    """Review of session 43: a run forgotten before its first line was written added 0 to
    ``suppressed``: every run seen is a line written, a line owed or a count."""
    d = Detector()
    d.see(*(state(1, bridge=f"forger-{i}", epoch=f"e{i}") for i in range(200)), dt=0.001)
    status = d.t.status()
    assert status["runs_forgotten"] == 200 - bt.MAX_RUNS and status["suppressed"] > 150, status
    assert len(d.lines) + status["suppressed"] + status["owed"] == 200, (len(d.lines), status)


def test_lines_are_read_back_newest_last_skipping_a_torn_line_and_garbage(journal: SafetyJournal) -> None:
    for i in range(5):
        journal.record("estop_sent", engaged=bool(i % 2), reason=f"r{i}")
    assert journal.flush(5)
    with open(journal.path, "ab") as f:
        f.write(b"not json\n[1, 2]\n{\"no\": \"event\"}\n{\"event\": \"x\", \"v\": NaN}\n\n")
        f.write(b'{"time": "2026-01-01T00:00:00+00:00", "event": "estop_sen')  # a crash mid-line
    events, skipped, _ = read_journal(journal, 100)
    assert [e["reason"] for e in events] == ["r0", "r1", "r2", "r3", "r4"] and skipped == 5
    assert all(e["event"] == "estop_sent" and isinstance(e["stamp_s"], float) and e["time"].endswith("+00:00")
               for e in events)
    assert [e["reason"] for e in read_journal(journal, 2)[0]] == ["r3", "r4"]
    journal.record("estop_sent", engaged=False, reason="after the crash")
    assert journal.flush(5)
    events, skipped, _ = read_journal(journal, 100)  # the torn line was ended: the next one is whole
    assert events[-1]["reason"] == "after the crash" and skipped == 5


def test_a_read_examines_a_bounded_number_of_lines(journal: SafetyJournal) -> None:
    """Review of session 43: 5 M short garbage lines (someone else's writes) cost 26 s of CPU a GET:
    a read gives up after READ_MAX_SKIPPED lines that are not events."""
    from server import safety_journal as sj

    journal.record("estop_sent", engaged=True, reason="before the garbage")
    assert journal.flush(5)
    with open(journal.path, "ab") as f:
        f.write(b"x\n" * 30_000)
    events, skipped, _ = read_journal(journal, 10)
    assert events == [] and skipped == sj.READ_MAX_SKIPPED


def test_the_journal_rotates_at_its_cap_and_keeps_one_previous_file(tmp_path: Path) -> None:
    j = SafetyJournal(tmp_path, max_bytes=4000)
    try:
        for i in range(200):
            j.record("bridge_state", i=i, reason="x" * 50)
        assert j.flush(10)
    finally:
        j.close()
    assert j.path.stat().st_size <= 4000 and j.previous.stat().st_size <= 4000
    assert sorted(p.name for p in j.dir.iterdir()) == ["journal.1.jsonl", "journal.jsonl"]
    events, skipped, _ = read_journal(j, 1000)
    assert skipped == 0 and [e["i"] for e in events] == list(range(200 - len(events), 200)) and len(events) > 40


def test_a_read_racing_a_rotation_has_neither_duplicates_nor_gaps(tmp_path: Path, monkeypatch) -> None:
    """Review of session 43: a read opened the current file, then the previous one; a rotation
    between them made it read the same file twice. The rotation here comes right after the read
    has read the current file."""
    from server import safety_journal as sj

    j = SafetyJournal(tmp_path, max_bytes=3000)
    try:
        for i in range(30):  # two files
            j.record("bridge_state", i=i, reason="x" * 50)
        assert j.flush(10) and j.previous.exists()
        read_back = sj._lines_backward
        rotated: list[bool] = []

        def rotate_after_the_first_file(*args):
            yield from read_back(*args)
            if not rotated:
                rotated.append(True)
                j.record("bridge_state", i=30, reason="x" * 3000)  # over the cap: the file rotates first
                assert j.flush(10)

        monkeypatch.setattr(sj, "_lines_backward", rotate_after_the_first_file)
        events = read_journal(j, 1000)[0]
    finally:
        j.close()
    assert rotated and [e["i"] for e in events] == list(range(30 - len(events), 30)) and len(events) > 20


def test_a_journal_path_that_is_no_regular_file_is_refused_never_waited_on(journal: SafetyJournal) -> None:
    """Review of session 43: a FIFO where the file should be blocked the read in ``open`` (a GET of
    no token held a worker thread for as long as no one wrote to it). A FIFO, a symbolic link, a
    directory: refused at once, and said."""
    import threading

    journal.dir.mkdir(parents=True)
    os.mkfifo(journal.path)
    answer: list = []
    reader = threading.Thread(target=lambda: answer.append(read_journal(journal, 10)), daemon=True)
    reader.start()
    reader.join(5)
    blocked = reader.is_alive()
    if blocked:  # the old read, stuck in open(): a writer lets it go
        os.close(os.open(journal.path, os.O_WRONLY | os.O_NONBLOCK))
        reader.join(5)
    assert not blocked, "the read waited on a FIFO"
    assert answer[0] == ([], 0, ["journal.jsonl: a FIFO, not a regular file: not read"]), answer
    os.unlink(journal.path)
    other = journal.dir / "elsewhere.jsonl"
    other.write_text('{"event": "estop_sent", "reason": "not the journal"}\n')
    os.symlink(other, journal.path)
    assert read_journal(journal, 10) == ([], 0, ["journal.jsonl: a symbolic link, not followed: not read"])
    os.unlink(journal.path)
    journal.path.mkdir()
    assert read_journal(journal, 10) == ([], 0, ["journal.jsonl: a directory, not a regular file: not read"])


def _route_app(journal: object, campaigns: object):
    """The system routes alone on an app whose state has what the e-stop and journal routes use."""
    from fastapi import FastAPI

    from server import routes_system

    class Transitions:
        def status(self) -> dict:
            return {"suppressed": 0, "runs_forgotten": 0, "owed": 0, "oldest_owed_s": None}

    app = FastAPI()
    app.include_router(routes_system.router)
    app.state.journal, app.state.transitions, app.state.campaigns, app.state.token = (
        journal, Transitions(), campaigns, "tok")
    return app


class _Campaigns:
    estop_holder = "console-test"

    def __init__(self) -> None:
        self.sent: list[tuple[bool, str]] = []

    def estop(self, engaged: bool, reason: str) -> None:
        self.sent.append((engaged, reason))


def test_journal_reads_never_take_the_threads_an_estop_needs(journal: SafetyJournal, monkeypatch) -> None:
    """Review of session 43: the journal's GET was a sync route: 40 reads stuck on the disk (or a
    FIFO) took every thread of the pool the e-stop's POST runs in, and it waited. Reads now run on
    a few threads of their own; the e-stop goes out while 40 of them wait."""
    import asyncio
    import threading

    import httpx

    from server import routes_system

    release = threading.Event()
    entered: list[int] = []
    read = routes_system.read_journal

    def stuck(journal: SafetyJournal, limit: int):
        entered.append(limit)
        release.wait(30)
        return read(journal, limit)

    monkeypatch.setattr(routes_system, "read_journal", stuck)
    campaigns = _Campaigns()
    app = _route_app(journal, campaigns)

    async def main() -> bool:
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as c:
            gets = [asyncio.create_task(c.get("/api/system/safety-journal")) for _ in range(40)]
            for _ in range(200):  # the reads under way
                await asyncio.sleep(0.01)
                if len(entered) >= 2:
                    break
            await asyncio.sleep(0.2)
            post = asyncio.create_task(c.post("/api/system/estop", json={"engaged": True, "reason": "x"},
                                              headers={"Authorization": "Bearer tok"}))
            done, _ = await asyncio.wait([post], timeout=10)
            release.set()
            answers = await asyncio.gather(*gets)
            await post
            assert all(r.status_code == 200 for r in answers)
            return bool(done)

    assert asyncio.run(main()), "the e-stop waited for the journal's reads"
    assert campaigns.sent == [(True, "x")] and len(entered) == 40


def test_an_estop_is_published_before_it_is_logged_or_journalled(caplog) -> None:
    """Review of session 43: the e-stop's route logged and built its journal line before it
    published: a log handler that blocks (a full pipe, a slow disk) delayed the e-stop. A
    publication that fails is still logged and journalled."""
    import asyncio
    import logging

    import httpx

    campaigns = _Campaigns()
    seen: list[tuple[str, int]] = []  # (what, e-stops published when it happened)

    class Journal:
        def record(self, event: str, **fields) -> None:
            seen.append((f"journal {fields['published']} {fields['error']}", len(campaigns.sent)))

        def status(self) -> dict:
            return {}

    class Watch(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.getMessage().startswith("e-stop"):
                seen.append(("log", len(campaigns.sent)))

    watch = Watch()
    logging.getLogger("xneck.server").addHandler(watch)
    app = _route_app(Journal(), campaigns)

    async def post(c: httpx.AsyncClient, engaged: bool) -> httpx.Response:
        return await c.post("/api/system/estop", json={"engaged": engaged, "reason": "x"},
                            headers={"Authorization": "Bearer tok"})

    async def main() -> httpx.Response:
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            assert (await post(c, True)).status_code == 200
            campaigns.estop = broken  # pyright: ignore[reportAttributeAccessIssue]
            return await post(c, False)

    def broken(engaged: bool, reason: str) -> None:
        raise RuntimeError("bus closed")

    try:
        failed = asyncio.run(main())
    finally:
        logging.getLogger("xneck.server").removeHandler(watch)
    assert failed.status_code == 500
    assert seen == [("log", 1), ("journal True ", 1), ("log", 1), ("journal False RuntimeError: bus closed", 1)], seen


def test_the_journals_route_says_a_file_it_refused(journal: SafetyJournal) -> None:
    import asyncio

    import httpx

    journal.record("estop_sent", engaged=True, reason="kept")
    assert journal.flush(5)
    os.replace(journal.path, journal.previous)
    os.mkfifo(journal.path)

    async def main() -> httpx.Response:
        app = _route_app(journal, _Campaigns())
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as c:
            return await asyncio.wait_for(c.get("/api/system/safety-journal"), 10)

    r = asyncio.run(main())
    assert r.status_code == 200, r.text
    body = r.json()
    assert [e["reason"] for e in body["events"]] == ["kept"]
    assert body["unreadable"] == ["journal.jsonl: a FIFO, not a regular file: not read"], body


def test_a_write_that_fails_is_counted_and_logged_never_raised(journal: SafetyJournal, caplog) -> None:
    journal.dir.mkdir(parents=True)
    journal.path.mkdir()  # a directory where the file should be
    for i in range(3):
        journal.record("estop_sent", engaged=True, reason=f"r{i}")  # does not raise
    assert journal.flush(5)
    assert journal.write_errors == 3 and "directory" in journal.last_error.lower()
    assert sum("safety journal" in r.getMessage() for r in caplog.records) == 1  # once a period
    assert read_journal(journal, 10) == ([], 0, ["journal.jsonl: a directory, not a regular file: not read"])
    os.rmdir(journal.path)
    journal.record("estop_sent", engaged=False, reason="disk back")
    assert journal.flush(5)
    assert [e["reason"] for e in read_journal(journal, 10)[0]] == ["disk back"] and journal.written == 1
    journal.record("estop_sent", value=float("nan"))  # no JSON carries it: counted, not raised
    assert journal.write_errors == 4
    assert json.loads(journal.path.read_text().splitlines()[-1])["reason"] == "disk back"


def test_the_writer_follows_no_link_writes_no_fifo_and_writes_whole_lines(journal: SafetyJournal, caplog,
                                                                         monkeypatch) -> None:
    """Review of session 43: the writer followed a symbolic link at the journal's path (appending to
    whatever it named) and wrote into a FIFO; a short ``os.write`` counted as a line written."""
    journal.dir.mkdir(parents=True)
    victim = journal.dir / "victim.txt"
    victim.write_text("someone else's file\n")
    os.symlink(victim, journal.path)
    journal.record("estop_sent", reason="through a link")
    assert journal.flush(5)
    assert victim.read_text() == "someone else's file\n"
    assert journal.write_errors == 1 and journal.written == 0 and "symbolic link" in journal.last_error
    os.unlink(journal.path)
    os.mkfifo(journal.path)
    for i in range(3):
        journal.record("estop_sent", n=i)
    assert journal.flush(5)
    assert journal.write_errors == 4 and journal.written == 0 and "FIFO" in journal.last_error, journal.status()
    assert sum("safety journal" in r.getMessage() for r in caplog.records) == 1  # once a period
    os.unlink(journal.path)

    write = os.write

    def short(fd: int, data) -> int:  # a line goes out in two writes (a signal, a full disk's last bytes)
        data = bytes(data)
        return write(fd, data[: len(data) // 2] if data.startswith(b'{"time"') else data)

    monkeypatch.setattr(os, "write", short)
    journal.record("estop_sent", reason="in two writes")
    assert journal.flush(5)
    monkeypatch.undo()
    assert [e["reason"] for e in read_journal(journal, 10)[0]] == ["in two writes"] and journal.written == 1


@pytest.mark.parametrize(("block", "line_max"), [(7, 30), (8, 16)])
def test_reading_back_in_blocks_finds_the_lines_a_forward_read_does(tmp_path: Path, monkeypatch, block: int,
                                                                    line_max: int) -> None:
    """Lines across block boundaries, blank lines, a torn end, lines too long to read: none longer
    than the cap is returned (review of session 43: with blocks shorter than the cap, a line up to
    twice the cap came through)."""
    import random

    from server import safety_journal as sj

    monkeypatch.setattr(sj, "READ_BLOCK_BYTES", block)
    monkeypatch.setattr(sj, "LINE_MAX_BYTES", line_max)
    rng = random.Random(0)
    path = tmp_path / "j"
    for _ in range(1000):
        lines = [b"x" * rng.choice([0, 1, 5, 6, 7, 8, 9, 15, 16, 17, 20, 23, 25, 30, 31, 40, 100])
                 for _ in range(rng.randint(0, 8))]
        data = b"\n".join(lines) + (b"\n" if rng.random() < 0.5 else b"")
        path.write_bytes(data)
        expected: list[bytes | None] = []
        *whole, last = data.split(b"\n")
        if last:
            expected.append(None)  # torn
        expected += [None if len(line) > line_max else line for line in reversed(whole) if line]
        with open(path, "rb") as f:
            assert list(sj._lines_backward(f)) == expected, data


# -- repeats coalesced (server.safety_journal.Repeats; review of session 46) ---------------------------

def _line(i: int, reason: str = "flood") -> dict:
    return {"time": f"t{i}", "event": "estop_sent", "reason": reason, "n": i}


def test_repeats_write_the_first_at_once_and_their_count_when_the_window_ends_or_another_comes() -> None:
    from server.safety_journal import Repeats

    r = Repeats(window_s=1.0)
    key = ("estop_sent", (True, "flood", "10.0.0.1"))
    assert r.offer(key, _line(0), 0.0) == [_line(0)]  # the first: at once
    assert all(r.offer(key, _line(i), i * 0.01) == [] for i in range(1, 51))  # 50 repeats: counted
    assert r.deadline() == 1.0 and r.expire(0.99) == []
    assert r.expire(1.0) == [{**_line(50), "repeated": 50, "repeated_since": "t1"}]  # the last one's fields
    # a flood going on: one line a window, not one an event
    assert all(r.offer(key, _line(i), 1.0 + i * 0.01) == [] for i in range(51, 61))
    other = ("estop_sent", (False, "clear", "10.0.0.1"))
    # a different event: the count first, then it, at once; never dropped, never reordered
    assert r.offer(other, _line(61, "clear"), 1.2) == [{**_line(60), "repeated": 10, "repeated_since": "t51"},
                                                       _line(61, "clear")]
    assert r.offer(key, _line(62), 1.3) == [_line(62)]  # a different event before it: not a repeat
    assert r.deadline() is None and r.expire(5.0) == []  # no repeat in its window: the group closes
    assert r.offer(key, _line(63), 5.1) == [_line(63)]  # so the next one is written at once
    # events without a key (the bridge's transitions) are never coalesced
    assert r.offer(None, _line(64, "bridge"), 5.2) == [_line(64, "bridge")]
    assert r.offer(None, _line(65, "bridge"), 5.2) == [_line(65, "bridge")]
    assert r.close() == []


def test_a_token_holders_estop_flood_acts_on_every_request_and_no_longer_rotates_older_lines_out(
        tmp_path: Path) -> None:
    """Review of session 46: each REST e-stop wrote a line (~320 bytes), so a token holder flooding
    the route (hundreds a second) rotated the journal within a minute or two and, at its second
    rotation, pushed out the previous file: here, a 16 kB journal (~50 lines) and 150 e-stops, the
    bridge's e-stop line written before them lost. Now the first is written at once, identical ones
    counted; every request still engages."""
    import asyncio

    import httpx

    now = [0.0]  # the repeats' clock: the flood within one window
    journal = SafetyJournal(tmp_path, max_bytes=16_000, clock=lambda: now[0])
    campaigns = _Campaigns()
    app = _route_app(journal, campaigns)
    auth = {"Authorization": "Bearer tok"}
    try:
        journal.record("bridge_state", bridge="robot", estop_engaged=True, estop_reason="pressed on the robot")

        async def main() -> None:
            async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as c:
                assert (await c.post("/api/system/estop", json={"reason": "flood"}, headers=auth)).status_code == 200
                assert journal.flush(5)  # the first e-stop's line: on disk at once, not at the window's end
                assert [e.get("reason") for e in read_journal(journal, 10)[0]] == [None, "flood"]
                for _ in range(149):
                    assert (await c.post("/api/system/estop", json={"reason": "flood"}, headers=auth)).status_code == 200
                await c.post("/api/system/estop", json={"engaged": False, "reason": "clear"}, headers=auth)

        asyncio.run(main())
    finally:
        journal.close()
    assert campaigns.sent == [(True, "flood")] * 150 + [(False, "clear")]  # every request acted
    events, skipped, _ = read_journal(journal, 1000)
    assert events[0]["event"] == "bridge_state", events[:3]  # the line before the flood: kept
    assert skipped == 0 and not journal.previous.exists()
    assert [(e["event"], e.get("reason"), e.get("repeated")) for e in events] == [
        ("bridge_state", None, None), ("estop_sent", "flood", None), ("estop_sent", "flood", 149),
        ("estop_sent", "clear", None)], events
    assert events[2]["engaged"] is True and events[2]["repeated_since"] <= events[2]["time"]


def test_a_window_of_repeats_that_ends_is_written_by_the_writer_unasked(tmp_path: Path) -> None:
    """No later event needed: the writer writes the count when the window ends."""
    journal = SafetyJournal(tmp_path, repeat_window_s=0.05)
    try:
        for i in range(5):
            journal.record("estop_sent", repeat_key="k", reason="flood", n=i)
        assert wait_until(lambda: len(read_journal(journal, 10)[0]) == 2, 5, 0.02), read_journal(journal, 10)
        first, count = read_journal(journal, 10)[0]
        assert first["n"] == 0 and "repeated" not in first and count["n"] == 4 and count["repeated"] == 4
    finally:
        journal.close()


def test_a_flood_of_one_process_fault_is_one_line_with_its_count(tmp_path: Path) -> None:
    """Session 46: ``POST /api/system/abort`` (a token holder's, as ``xneck up``'s) wrote a
    ``process_fault`` line each, as the e-stop route had: a flood rotated older lines out. The same
    cause from the same host within a second is counted in one line; another cause is written."""
    import asyncio

    import httpx

    from server.process_faults import ProcessFaults

    class Campaigns(_Campaigns):
        def abort(self, reason: str, ended_within_s: float | None, stack_stopping: bool = False) -> None:
            return None

    now = [0.0]
    journal = SafetyJournal(tmp_path, clock=lambda: now[0])
    app = _route_app(journal, Campaigns())
    app.state.process_faults = ProcessFaults()
    auth = {"Authorization": "Bearer tok"}
    try:
        async def main() -> None:
            async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as c:
                for reason in ["camera process exited (code 3)"] * 40 + ["controller process exited (code 1)"]:
                    assert (await c.post("/api/system/abort", json={"reason": reason}, headers=auth)).status_code == 200

        asyncio.run(main())
    finally:
        journal.close()
    events, _, _ = read_journal(journal, 1000)
    assert [(e["event"], e["reason"], e.get("repeated")) for e in events] == [
        ("process_fault", "camera process exited (code 3)", None), ("process_fault", "camera process exited (code 3)", 39),
        ("process_fault", "controller process exited (code 1)", None)], events
