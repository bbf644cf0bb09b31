"""Campaigns started by the console: one at a time, run in a worker thread, archived and indexed.

The worker calls :func:`server.campaign_runner.run_campaign` with the server's own Zenoh session and
hub endpoint, so the twin/controller processes it spawns publish where the console's live views
already listen. Progress comes from the controller's campaign events; stop sets the event
``run_campaign`` polls (it then stops the children within bounded time and finishes the MCAP).

After a campaign: a Foxglove scene channel is added to the archive, the metrics (and for an
identification campaign the identification tables, from the runner's analysis: a failed one is
``analysis_failed``) are computed, and the JSON record is final.

At start-up :meth:`CampaignManager.recover_all` repairs what a crash left: an unfinished MCAP is
recovered (:func:`bridge.archive_recovery.recover`) and its record marked ``interrupted``. It never touches
an archive whose writer is alive (:func:`bridge.archive.writer_alive`), and a file it cannot
repair (full or read-only disk, I/O error) is reported in :attr:`CampaignManager.recovery_errors`
and on the record, never an exception: start-up goes on.

A campaign that a controller service runs on by itself after this console crashed (the console's
requests only started it) is one the console no longer records: its record is recovered
``interrupted`` like any other, and :meth:`CampaignManager.unrecorded` tells, from the
controller's status on the bus, that it is still running on that controller. While it is, the
record says so (``running_on``, its message), a new campaign is refused with
:class:`RunningElsewhere`, and :meth:`CampaignManager.stop` sends the controller the stop request
the console's own campaigns send, and waits for its answer (:class:`NotStopped` if none comes).

A campaign ended by a cause the console cannot see itself (a child of ``xneck up`` that died: the
supervisor knows which and how) is named by :meth:`CampaignManager.abort`: the running campaign is
stopped and ends ``aborted`` with the cause first in its record and in its archive's
``xneck.campaign`` message, what the runner saw after it (a side effect: the controller service
vanished, the drives disabled, the bridge silent) kept behind it. A campaign that saw the side
effect and ended before the cause was told is named too, if it ended within the window the caller
gives (the time since the supervisor last saw the child alive).

Storage faults are campaign outcomes, not server states: a campaign starts only where it can be
recorded (:class:`StorageError`, a 507), one that hits ENOSPC/EROFS/EIO ends ``failed`` with the
reason, and the robot is free again whatever happened. A small reserve file
(``campaigns/.reserve``) is given up on such a fault so that the final record can still be
written on a full disk. The failed campaign's archive, which the recorder could not finish, is
finished at once where it lies (:func:`bridge.archive_recovery.finish_in_place`: the final records,
summary and footer written over its torn end, about 20 kB, where a copy would need the archive's
size again), its ``xneck.campaign`` saying ``failed`` with the record's message and quality; one
that cannot be finished yet (a read-only disk, no room at all) is named by :meth:`CampaignManager.
archive_problem`, its download refused with that reason, and repaired at the next start, which
writes the record's ``failed`` and message into it too.
"""

from __future__ import annotations

import contextlib
import glob
import json
import logging
import math
import os
import re
import shutil
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import zenoh

from bridge import bus
from bridge.archive import CAMPAIGN, ArchiveError, atomic_write, iso_time, storage_reason, writer_alive
from bridge.archive_read import Campaign, is_complete, read_campaign
from bridge.archive_recovery import finish_in_place, recover
from bridge.estop_holder import EStopHolder
from bridge.session import payload_of, publisher
from server.analysis_process import run_in_child
from server.archive_rewrite import rewrite_archive
from server.campaign_request import PreparedCampaign
from server.campaign_runner import (
    STOPPED_BY_USER,
    CausedStop,
    RecordingFailed,
    metrics_from_archive,
    new_campaign_id,
    run_campaign,
    sweep_console_workdirs,
)
from server.datadir import storage_problem
from server.foxglove_scene import add_scene_channel
from server.identified_sets import CACHE_NAME
from server.quality import CampaignMonitor
from server.records import CampaignIndex, CampaignRecord
from server.replay import Replay

log = logging.getLogger("xneck.campaigns")

RESERVE_BYTES = 512 * 1024  # given up on a storage fault, room for the final records
DEFAULT_MIN_FREE_BYTES = 64_000_000
ABORT_WAIT_S = 10.0  # s :meth:`CampaignManager.abort` waits for the stopped campaign's record to be final
# s a controller gets to answer the stop of a campaign it runs unrecorded: it answers on its next
# tick (2 ms); the rest is a loaded machine's and the bus's. The request is sent again every
# STOP_RESEND_S (the bus may drop one; a second stop of the same campaign changes nothing).
STOP_ANSWER_S = 3.0
STOP_RESEND_S = 0.5
#: s from the console's start within which a campaign recovered ``interrupted`` may still turn out
#: to run on a controller that has not linked back yet (bridge.session.CONNECT_RETRY_MS; a restart):
#: a stop of it, or a new campaign, waits until a live controller status was heard or this passed.
BUS_SETTLE_S = 8.0
#: s since its last change after which a half-written copy beside an archive is a crash's leftover.
HALF_COPY_AGE_S = 60.0


REPLAY_OF = "replay of"  # a Busy's ``what`` when a replay holds the robot (its 409 says so: routes_campaigns)


class Busy(Exception):
    """Another campaign (or a replay) holds the robot; ``running_id`` names it."""

    def __init__(self, running_id: str, what: str = "campaign") -> None:
        super().__init__(f"{what} {running_id} is running")
        self.running_id = running_id
        self.what = what


class DrivesDisabled(Exception):
    """The drives a campaign would use are disabled (the bridge's e-stop); ``reason`` is the bridge's.
    Not a :class:`Busy`: no campaign holds the robot (it was one named ``estop``, a fake id the
    409 reported while the health said none ran: audit of 2026-11-29)."""

    def __init__(self, reason: str) -> None:
        super().__init__(f"the drives are disabled ({reason or 'e-stop engaged'})")
        self.reason = reason


class RunningElsewhere(Busy):
    """A campaign of this console's runs on the controller service ``controller`` unrecorded (the
    console was restarted during it): the robot is that campaign's until it ends or is stopped."""

    def __init__(self, running_id: str, controller: str) -> None:
        super().__init__(running_id)
        self.controller = controller


class NotStopped(Exception):
    """A stop the console could not carry out; the message says why and what still runs."""


class NotFound(KeyError):
    pass


class StorageError(Exception):
    """A campaign cannot be recorded (no space, read-only, I/O error); the message has the figures."""


def archived_progress(campaign: Campaign, campaign_id: str) -> float:
    """How far (0-1) the campaign ``campaign_id`` got as its archive's ``/xneck/campaign/events``
    say: the largest progress of its own events, 0.0 without any. A campaign a crash interrupted is
    recorded with it (user audit: one whose events reached 0.0758 was shown at 0.0, its record
    never saved after the start)."""
    seen = [float(ev.progress) for _, ev in campaign.messages(bus.CAMPAIGN_EVENTS)
            if isinstance(ev, bus.CampaignEvent) and ev.campaign_id == campaign_id and math.isfinite(ev.progress)]
    return min(max([0.0, *seen]), 1.0)


#: The runner's word for a campaign :meth:`CampaignManager.abort` stopped (it had said "stopped by
#: the user", whom nobody was: fresh-user audit of 2026-12-01).
STOPPED_FOR_CAUSE = "stopped by the console for that cause"


def _with_cause(cause: str, seen: str, stopped_for_it: bool) -> str:
    """A campaign's message with ``cause`` first, then what the campaign itself ``seen`` (the
    runner's word for the stop the cause asked for dropped, ``stopped_for_it``, and the notes
    after it kept: an identification's saturation note); a message that names the cause already
    is kept as it is."""
    if seen.startswith(cause):  # named already (a retry)
        return seen
    if stopped_for_it:
        for word in (STOPPED_FOR_CAUSE, STOPPED_BY_USER):
            if seen == word:
                seen = ""
            elif seen.startswith(word + "; "):
                seen = seen[len(word) + 2:]
    if not seen:
        return cause[:2000]
    return f"{cause}; the campaign saw: {seen}"[:2000]


class CampaignManager:
    def __init__(self, data_dir: Path, session: zenoh.Session, hub: str,
                 on_finish: Callable[[CampaignRecord], None] | None = None,
                 service_alive: Callable[[], bool] = lambda: False,
                 min_free_bytes: int = DEFAULT_MIN_FREE_BYTES,
                 bridge_estop: Callable[[], dict[str, object] | None] = lambda: None,
                 bus_campaign: Callable[[], tuple[str, str] | None] = lambda: None,
                 bus_heard: Callable[[], bool] = lambda: True) -> None:
        self.index = CampaignIndex(Path(data_dir) / "campaigns")
        self.session = session
        self.hub = hub
        self._on_finish = on_finish
        # With a controller service on the bus (`xneck up`) campaigns are requests to it, driving the
        # bridge that is already there; otherwise each campaign starts its own processes.
        self.service_alive = service_alive
        self.min_free_bytes = min_free_bytes
        self.recovery_errors: dict[str, str] = {}  # file name -> why it could not be repaired
        self._unfinished: dict[str, str] = {}  # campaign id -> why its archive could not be finished after a fault
        self._lock = threading.Lock()
        self._records: dict[str, CampaignRecord] = {}
        self._running: str | None = None
        self._stop = CausedStop()
        self._closing = threading.Event()  # the console closing (not a campaign's stop: a stopped one gets its scene)
        # The running campaign's scene is not added (or cut short): the console closes, or the stack
        # stops after the campaign's abort (:meth:`abort`'s ``stack_stopping``). One per campaign.
        self._scene_stop = threading.Event()
        self._worker: threading.Thread | None = None
        # Serialises the last steps of a campaign's record (its final fields, the cause named in it
        # and its archive) with :meth:`abort`'s naming of a cause; taken before ``_lock``, never inside.
        self._final_lock = threading.Lock()
        # campaign id -> (cause, whether abort's stop ended it), until its worker writes its final record
        self._causes: dict[str, tuple[str, bool]] = {}
        # (id, time.monotonic()) when the latest campaign's run ended (before its record was final)
        self._last_end: tuple[str, float] | None = None
        self._replay: Replay | None = None
        # (campaign id, speed, cancelled) of a replay whose archive is being read: it holds the robot
        # already, so that no campaign or second replay starts in the second the read takes.
        self._replay_starting: tuple[str, float, threading.Event] | None = None
        self._estop_lock = threading.Lock()  # never with _lock held: publishing may block
        self.estop_engaged = False  # what this console last sent; the bridge's word is bridge_estop()
        self.estop_reason = ""
        # This console's hold on the e-stop it engaged (bridge.estop_holder): a liveliness token from
        # the engage to the release, so a bridge that starts or links back meanwhile starts latched
        # (the EStop message reaches only the bridges linked when it goes out: audit S3).
        self.estop_holder = f"console-{uuid.uuid4().hex[:6]}"
        self._estop = EStopHolder(session, self.estop_holder)
        self._holders_lock = threading.Lock()
        self._estop_others: set[str] = set()  # the other holders alive on the bus (another console)
        self._estop_holders_sub = session.liveliness().declare_subscriber(
            bus.ESTOP_ENGAGED_ALL, self._on_estop_token, history=True)
        self._bridge_estop = bridge_estop  # server.live.bridge_estop: the bridge's latched e-stop, if fresh
        self._bus_campaign = bus_campaign  # server.live.bus_campaign: (id, controller) a controller runs now
        self._noted_elsewhere: set[str] = set()  # ids whose record says already that a controller went on with them
        # server.live.LiveBus.heard_status: a live controller status arrived since the start, so
        # :meth:`unrecorded` knows whether a controller runs a campaign recovered at this start
        self._bus_heard = bus_heard
        self._started_s = time.monotonic()
        self._recovered_now: set[str] = set()  # ids recover_all marked interrupted at this start
        self._monitor: CampaignMonitor | None = None  # the running campaign's (its runner's), while it has one

    # -- start-up ---------------------------------------------------------------------------
    def recover_all(self) -> list[str]:
        """Recover unfinished archives and records left by a crash; returns the ids marked
        interrupted. Per-file problems go to :attr:`recovery_errors` (and the log), never up."""
        interrupted = []
        for rec in self.index.load_all(self.recovery_errors):
            self._records[rec.id] = rec
        try:
            archives = sorted(self.index.dir.glob("*.mcap"))
        except OSError as exc:
            self.recovery_errors[str(self.index.dir)] = storage_reason(exc)
            archives = []
        for mcap in archives:
            try:
                if self._recover_one(mcap):
                    interrupted.append(mcap.stem)
            except Exception as exc:  # noqa: BLE001 - one bad file must not stop the console
                self._recovery_failed(mcap, exc)
        # A record still "running" without its MCAP: the crash came before the first byte.
        for rec in self._records.values():
            if rec.status == "running" and not writer_alive(self.index.mcap(rec.id)):
                rec.status = "interrupted"
                rec.message = rec.message or "the server stopped before anything was recorded"
                self._save_quietly(rec)
                interrupted.append(rec.id)
        self.release_reserve(keep=True)
        self._recovered_now.update(interrupted)
        self._sweep_workdirs()
        self._sweep_half_copies()
        return interrupted

    def _sweep_half_copies(self) -> None:
        """Remove the copies a rewrite or a recovery killed half-way left (``NAME.mcap.rewrite``,
        ``.recovering``: each about the size of its archive, and nothing else removed them; review
        of session 53). This console holds the data folder; one untouched for a minute is no
        command's work in progress."""
        try:
            leftovers = [*self.index.dir.glob("*.mcap.rewrite"), *self.index.dir.glob("*.mcap.recovering")]
        except OSError:
            return
        for p in leftovers:
            try:
                if p.is_file() and not p.is_symlink() and time.time() - p.stat().st_mtime > HALF_COPY_AGE_S:
                    p.unlink()
                    log.info("removed %s, a copy left half-way by a crash", p.name)
            except OSError as exc:
                log.warning("%s, a copy left half-way, not removed: %s", p.name, storage_reason(exc))

    def _sweep_workdirs(self) -> None:
        """Remove the temporary folders of this console's campaigns that ended (a crash, or a
        version that kept those of unfinished campaigns, left them: hundreds, user audit), and
        console campaigns' folders a day old (server.campaign_runner.sweep_console_workdirs)."""
        def ended(cid: str) -> bool:
            rec = self._records.get(cid)
            return rec is not None and rec.status != "running"

        try:
            removed = sweep_console_workdirs(ended)
        except Exception as exc:  # noqa: BLE001 - a leftover folder never stops the console
            log.warning("temporary folders of earlier campaigns not swept: %s", exc)
            return
        if removed:
            log.info("removed %d temporary folders of ended campaigns", len(removed))

    def _await_bus(self) -> None:
        """Wait, after a start that recovered campaigns a crash interrupted, until a live controller
        status was heard or :data:`BUS_SETTLE_S` s passed since the start: before, a controller still
        running one of them may not have linked back yet, and :meth:`unrecorded` would say that
        none runs (a stop answered 200 doing nothing while the neck moved on; session 39)."""
        if not self._recovered_now:
            return
        deadline = self._started_s + BUS_SETTLE_S
        if not self._bus_heard() and time.monotonic() < deadline:
            log.info("waiting up to %.1f s for a controller on the bus: it may still run %s", deadline - time.monotonic(),
                     ", ".join(sorted(self._recovered_now)))
        while not self._bus_heard() and time.monotonic() < deadline:
            time.sleep(0.05)
        self._recovered_now.clear()  # heard, or waited for long enough: no later call waits

    def _recover_one(self, mcap: Path) -> bool:
        cid = mcap.stem
        rec = self._records.get(cid)
        if rec is None and self.index.json(cid).exists():
            # Its record is there but was not read (load_all said why): a record rebuilt from the
            # archive had been saved over it, losing its metrics, tables and status (a downgrade, a
            # hand edit; review of session 53). Both files are left as they are, and said.
            why = self.recovery_errors.get(self.index.json(cid).name, "it cannot be read")
            self.recovery_errors[mcap.name] = (f"its record {cid}.json was not loaded ({why}): the archive and the "
                                               f"record are left as they are; fix or move the record, then restart")
            log.error("not recovering %s: %s", mcap, self.recovery_errors[mcap.name])
            return False
        if writer_alive(mcap):  # another process records it now: not a crash's leftover
            log.warning("not recovering %s: its writer is alive", mcap)
            return False
        try:
            complete = is_complete(mcap)
        except ArchiveError as exc:
            log.warning("skipping %s: %s", mcap, exc)
            return False
        if complete and rec is not None and rec.status != "running":
            return False
        outcome, fields = None, None
        if rec is not None and rec.status == "failed":  # how it ended is known: its archive says it too
            outcome, fields = "failed", self._failed_fields(rec.message, rec.quality)
        try:
            report = recover(mcap, outcome, fields)
        except (ArchiveError, OSError) as exc:  # e.g. no room for a copy on a full disk: finished where it lies
            try:
                report = finish_in_place(mcap, outcome, fields)
            except ArchiveError:
                raise exc from None
        with self._lock:
            self._unfinished.pop(cid, None)
        info, progress = {}, 0.0
        with contextlib.suppress(ArchiveError):
            archived = read_campaign(mcap, keys=(bus.CAMPAIGN_EVENTS,))
            info, progress = archived.info, archived_progress(archived, cid)
        rec = rec or self._record_from_archive(cid, info)
        note = f"recovered after a crash ({report.status}: {report.messages} messages kept" + \
               (f"; {report.reason}" if report.reason else "") + ")"
        if rec.status == "running":
            rec.status = "interrupted"
            rec.ended_at = info.get("end_time", iso_time())
            rec.message = note
            rec.progress = max(rec.progress, progress)  # the record's own is its last save's, often the start's
        else:  # e.g. failed on a full disk: keep the outcome, say the archive was repaired since
            rec.message = f"{rec.message}; archive {note}"[:2000]
        with contextlib.suppress(Exception):
            rec.metrics = metrics_from_archive(mcap)
        rec.mcap_bytes = mcap.stat().st_size
        self._records[cid] = rec
        self._save_quietly(rec)
        return rec.status == "interrupted"

    @staticmethod
    def _failed_fields(message: str, quality: dict[str, object] | None) -> dict[str, str]:
        """The ``xneck.campaign`` fields of a failed campaign's archive, as its record has them."""
        fields = {"message": message[:2000]}
        if quality:
            fields["quality"] = json.dumps(quality)
        return fields

    def archive_problem(self, campaign_id: str) -> str:
        """Why the archive of an ended campaign could not be finished or repaired ('' if none is known)."""
        with self._lock:
            why = self._unfinished.get(campaign_id, "")
        return why or self.recovery_errors.get(f"{campaign_id}.mcap", "")

    def _finish_failed_archive(self, cid: str, path: Path, message: str, quality: dict[str, object] | None) -> bool:
        """Finish the archive of a campaign that failed on a storage fault, with outcome ``failed``
        and its record's message and quality (module docstring); whether it is readable now, never
        raises. In place first (the disk is full: it needs no copy), the copying :func:`recover` for
        a file damaged inside; an archive finished already (the fault came after the recording) gets
        only its final record amended, which needs a copy (:func:`server.archive_rewrite.rewrite_archive`)."""
        fields = self._failed_fields(message, quality)
        try:
            if not path.exists():
                return False
            if is_complete(path):
                try:
                    rewrite_archive(path, amend={CAMPAIGN: {**fields, "outcome": "failed"}})
                except Exception as exc:  # noqa: BLE001 - readable still, only its outcome not amended
                    log.error("cannot write the outcome failed into the finished archive of %s: %s", cid,
                              storage_reason(exc) if isinstance(exc, OSError) else exc)
                return True
            try:
                report = finish_in_place(path, "failed", fields)
            except ArchiveError as in_place:
                try:
                    report = recover(path, "failed", fields)
                except Exception:  # noqa: BLE001 - the in-place attempt's reason is the one to tell
                    raise in_place from None
            log.warning("the archive of %s was finished after the fault (%s: %d messages kept; %s)", cid,
                        report.status, report.messages, report.reason)
            return True
        except Exception as exc:  # noqa: BLE001 - the record is written whatever the archive allows
            why = exc.reason if isinstance(exc, ArchiveError) else storage_reason(exc)
            log.error("the archive of %s cannot be finished now (it is repaired at the next start): %s", cid, why)
            with self._lock:
                self._unfinished[cid] = why
            return False

    @staticmethod
    def _record_from_archive(cid: str, info: dict[str, str]) -> CampaignRecord:
        from twin.identification.options import VARIABLE_ESTIMATORS

        estimator = info.get("estimator", "")  # from disk: kept only if it names an estimator
        return CampaignRecord(
            id=cid, kind="identification" if info.get("kind") == "identification" else "control",
            law=info.get("law", ""), trajectory="", parameter_set=info.get("parameter_set", ""),
            target="robot" if info.get("target") == "robot" else "twin",
            estimator=estimator if estimator in VARIABLE_ESTIMATORS else "",
            created_at=info.get("start_time", ""), status="running")

    def _recovery_failed(self, mcap: Path, exc: Exception) -> None:
        reason = exc.reason if isinstance(exc, ArchiveError) else storage_reason(exc)
        log.error("cannot recover %s: %s", mcap, reason)
        self.recovery_errors[mcap.name] = reason
        rec = self._records.get(mcap.stem)
        if rec is None:
            rec = self._records[mcap.stem] = self._record_from_archive(mcap.stem, {})
        if rec.status == "running":
            rec.status = "interrupted"
            rec.message = f"interrupted by a crash; the archive could not be repaired yet ({reason}): it is kept " \
                          f"as it is and repaired at the next start"
            self._save_quietly(rec)

    def _save_quietly(self, rec: CampaignRecord) -> bool:
        """Save a record; a storage fault is logged (the record in memory stays right)."""
        try:
            self.index.save(rec)
            return True
        except OSError as exc:
            log.error("cannot save the record of %s: %s", rec.id, storage_reason(exc))
            return False

    # -- storage reserve --------------------------------------------------------------------
    @property
    def _reserve(self) -> Path:
        return self.index.dir / ".reserve"

    def release_reserve(self, keep: bool = False) -> None:
        """``keep=False``: give the reserve up (a storage fault); ``keep=True``: (re)create it if
        there is room (after start-up and after each campaign)."""
        with contextlib.suppress(OSError):
            if not keep:
                self._reserve.unlink(missing_ok=True)
            elif not self._reserve.exists() and not storage_problem(self.index.dir, self.min_free_bytes):
                with open(self._reserve, "wb") as f:
                    os.posix_fallocate(f.fileno(), 0, RESERVE_BYTES)

    # -- queries ----------------------------------------------------------------------------
    @property
    def running_id(self) -> str | None:
        return self._running

    def recorded_camera(self) -> str:
        """The camera whose α_IP the running campaign records (:meth:`CampaignMonitor.recorded_camera`:
        an instance, :data:`~server.quality.TWIN_CAMERA`), '' when none runs or it knows none yet.
        Takes no lock: the live view asks it at every read under its own
        (:attr:`server.live.LatestValues.prefer_camera`), and this manager reads the live view
        under its lock (the bridge's e-stop)."""
        monitor = self._monitor
        return monitor.recorded_camera() if monitor is not None else ""

    def _on_monitor(self, monitor: CampaignMonitor | None) -> None:
        self._monitor = monitor

    def unrecorded(self) -> tuple[str, str] | None:
        """``(id, controller)`` of a campaign of this console's that a controller on the bus runs
        now while this console does not record it: one it was running when it crashed (recovered
        ``interrupted``), which the controller service went on with. None if there is none (a
        replay of the campaign republishes its statuses: not the controller's word). The first time
        it is seen, its record says for good that the controller went on with it."""
        seen = self._bus_campaign()
        if seen is None:
            return None
        cid, controller = seen
        with self._lock:
            rec = self._records.get(cid)
            replayed = (self._replay is not None and self._replay.campaign_id == cid and self._replay.running) or \
                (self._replay_starting is not None and self._replay_starting[0] == cid)
            if rec is None or rec.status != "interrupted" or cid == self._running or replayed:
                return None
            first = cid not in self._noted_elsewhere
            self._noted_elsewhere.add(cid)
            message = rec.message
        if first:
            self._update(cid, message=f"{message}; the controller {controller or '(unknown)'} went on running it "
                                      f"after the console's restart, not recorded"[:2000])
        return seen

    @staticmethod
    def _running_on(rec: CampaignRecord, elsewhere: tuple[str, str] | None) -> CampaignRecord:
        """``rec`` as shown while ``elsewhere`` (:meth:`unrecorded`) is that campaign: ``running_on``
        and its message say that it runs on; never stored (it is true only while it runs)."""
        if elsewhere is not None and elsewhere[0] == rec.id:
            rec.running_on = elsewhere[1] or "(unknown)"
            rec.message = f"still running on controller {rec.running_on}, not recorded since the console's " \
                          f"restart: stop it here; {rec.message}"[:2000]
        return rec

    def get(self, campaign_id: str) -> CampaignRecord:
        with self._lock:
            rec = self._records.get(campaign_id)
        if rec is None:
            raise NotFound(campaign_id)
        return self._running_on(rec.model_copy(), self.unrecorded())

    def list(self, status: str | None = None, kind: str | None = None, law: str | None = None,
             limit: int = 100) -> list[CampaignRecord]:
        elsewhere = self.unrecorded()
        with self._lock:
            recs = [self._running_on(r.model_copy(), elsewhere) for r in self._records.values()]
        recs = [r for r in recs if (status is None or r.status == status) and (kind is None or r.kind == kind)
                and (law is None or r.law == law)]
        recs.sort(key=lambda r: r.created_at, reverse=True)
        return recs[:limit]

    def mcap_path(self, campaign_id: str) -> Path:
        self.get(campaign_id)
        return self.index.mcap(campaign_id)

    # -- life cycle -------------------------------------------------------------------------
    def storage_problem(self, duration_s: float = 0.0) -> str:
        """Why no campaign (of ``duration_s`` seconds) can be recorded now ('' if one can); see
        :mod:`server.datadir`."""
        return storage_problem(self.index.dir, self.min_free_bytes, duration_s)

    def _holder(self) -> Busy | None:
        """What holds the robot now (None if nothing does): a campaign, a replay, or a replay whose
        archive is being read. Call it under ``_lock``."""
        if self._running is not None:
            return Busy(self._running)
        if self._replay_starting is not None:
            return Busy(self._replay_starting[0], REPLAY_OF)
        if self._replay is not None and self._replay.running:
            return Busy(self._replay.campaign_id, REPLAY_OF)
        return None

    def start(self, prepared: PreparedCampaign) -> CampaignRecord:
        """Start a campaign as prepared (nothing is changed here: the request was resolved and
        checked by :func:`server.campaign_request.prepare`). Raises :class:`Busy` or
        :class:`StorageError`."""
        spec = prepared.spec
        self._await_bus()
        elsewhere = self.unrecorded()  # outside the lock: it may write the record
        with self._lock:
            busy = self._holder()
            if busy is not None:
                raise busy
            if elsewhere is not None:  # the controller would refuse it; this names why, and nothing is recorded
                raise RunningElsewhere(*elsewhere)
            # Armed before the e-stop is checked: an e-stop whose publication is under way now sets
            # this event when it returns, so the campaign it missed at the check ends at once (one
            # armed after the record was written let it run: audit of 2026-11-27).
            stop = self._stop = CausedStop()
            scene_stop = self._scene_stop = threading.Event()
            if self._closing.is_set():
                scene_stop.set()
            disabled = self._drives_disabled(spec.twin and not spec.service)  # a service drives the bus bridge
            if disabled:
                raise DrivesDisabled(disabled)
            problem = self.storage_problem(spec.trajectory.duration_s)
            if problem:
                raise StorageError(problem)
            cid = new_campaign_id(spec.kind)
            rec = CampaignRecord(
                id=cid, kind=spec.kind, law=spec.law.name, trajectory=spec.trajectory.name,
                trajectory_spec=spec.trajectory.to_dict(), duration_s=spec.trajectory.duration_s,
                parameter_set=prepared.parameter_set, target=prepared.target, pace=prepared.pace,
                seed=spec.seed, truth=prepared.truth, created_at=iso_time(),
                estimator=spec.estimator if spec.kind == "identification" else "",
                creep_time_s=spec.creep_time_s)
            try:
                self.index.save(rec)  # before the robot is taken: a refused start leaves nothing behind
            except OSError as exc:
                raise StorageError(f"cannot write the campaign record: {storage_reason(exc)}") from None
            self._records[cid] = rec
            self._running = cid
            self._worker = threading.Thread(target=self._run, args=(cid, prepared, stop, scene_stop),
                                            name=f"campaign:{cid}", daemon=True)
            self._worker.start()
        return rec.model_copy()

    def _update(self, cid: str, **fields: object) -> CampaignRecord:
        """Change a record in memory and on disk; never raises. On a storage fault the reserve is
        given up and the save tried once more; if that fails too the record in memory says so."""
        with self._lock:
            rec = self._records[cid]
            for k, v in fields.items():
                setattr(rec, k, v)
            snapshot = rec.model_copy()
        if not self._save_quietly(snapshot):
            self.release_reserve()
            if not self._save_quietly(snapshot):
                with self._lock:
                    rec.message = f"{rec.message} (this record could not be saved: storage fault)"[:2000]
        return snapshot

    def _run(self, cid: str, prepared: PreparedCampaign, stop: threading.Event, scene_stop: threading.Event) -> None:
        try:
            self._record_campaign(cid, prepared, stop, scene_stop)
        finally:  # whatever happened, the robot is free again
            self._monitor = None
            with self._lock:
                if self._running == cid:
                    self._running = None
                self._causes.pop(cid, None)
            self.release_reserve(keep=True)

    def _record_campaign(self, cid: str, prepared: PreparedCampaign, stop: threading.Event,
                         scene_stop: threading.Event) -> None:
        path = self.index.mcap(cid)
        spec = prepared.spec

        def progress(fraction: float, message: str) -> None:
            with self._lock:
                rec = self._records[cid]
                rec.progress = max(rec.progress, min(max(float(fraction), 0.0), 1.0))
                rec.message = message[:300]

        storage_fault = False
        try:
            try:
                result = run_campaign(spec, prepared.params, path, progress=progress, campaign_id=cid,
                                      session=self.session, hub=self.hub, stop=stop, on_monitor=self._on_monitor,
                                      console=True)
            finally:
                with self._lock:
                    self._last_end = (cid, time.monotonic())
            status = result.outcome if result.outcome in ("finished", "degraded", "aborted", "analysis_failed") \
                else "failed"
            fields: dict[str, object] = {"status": status, "message": result.message[:2000],
                                         "metrics": result.metrics or None, "quality": result.quality or None}
            if result.analysis:  # an identification campaign, analysed by the runner (issue 17: never finished if it failed)
                fields["identification"], fields["identification_status"] = result.identification, result.analysis
            if result.truth_seen:  # the twin's messages named another truth than the console was told
                fields["truth"] = result.truth_seen
            if result.identified_set is not None:
                self._keep_identified_set(cid, result.identified_set)
            if status in ("finished", "degraded"):
                fields["progress"] = 1.0
        except (ArchiveError, OSError) as exc:  # a storage fault: an outcome, not a server state
            reason = exc.reason if isinstance(exc, ArchiveError) else storage_reason(exc)
            log.error("campaign %s failed: storage fault: %s", cid, reason)
            self.release_reserve()
            storage_fault = True
            # The counters of the run as far as it got (a record without them read as "no data").
            quality = exc.quality if isinstance(exc, RecordingFailed) and exc.quality else None
            fields = {"status": "failed", "message": f"storage fault while recording {path.name}: {reason}",
                      "quality": quality}
            if self._finish_failed_archive(cid, path, str(fields["message"]), quality):
                with contextlib.suppress(Exception):  # the metrics of what was recorded, as for an interrupted one
                    fields["metrics"] = metrics_from_archive(path)
        except Exception as exc:  # the record says what went wrong
            log.exception("campaign %s failed", cid)
            fields = {"status": "failed", "message": f"{type(exc).__name__}: {exc}"}
        try:  # not after a storage fault: the scene is added by a copy of the archive, on a disk that refused a write
            if scene_stop.is_set():  # the stack stops: its record final at once, not after a scene cut short
                log.info("no Foxglove scene for %s: the console or its stack is stopping", cid)
            elif not storage_fault and path.exists() and is_complete(path):
                # in a child as the identification (server.analysis_process): 11 s of a 600 s campaign
                fields["scene_messages"] = run_in_child(add_scene_channel, path, prepared.params, what="scene",
                                                        stop=scene_stop)
        except Exception as exc:  # noqa: BLE001 - the archive itself is fine without the scene
            log.warning("no Foxglove scene for %s: %s", cid, exc)
            path.with_name(path.name + ".rewrite").unlink(missing_ok=True)  # a rewrite killed half-way
        fields["ended_at"] = iso_time()
        with self._final_lock:  # a cause told from now on finds this record final (abort)
            with self._lock:
                self._running = None
                cause = self._causes.pop(cid, None)
            if cause is not None and fields["status"] == "aborted":
                fields["message"] = _with_cause(cause[0], str(fields["message"]), cause[1])
                self._name_in_archive(path, str(fields["message"]))
            elif cause is not None and STOPPED_FOR_CAUSE in str(fields["message"]):
                # recorded, then its analysis cut by the cause ("identification not done: … (stopped
                # by the console for that cause)"): which cause, said (review of this session's diff)
                fields["message"] = str(fields["message"]).replace(STOPPED_FOR_CAUSE, f"stopped for: {cause[0]}")[:2000]
            fields["mcap_bytes"] = path.stat().st_size if path.exists() else 0
            rec = self._update(cid, **fields)
        if self._on_finish is not None:
            self._on_finish(rec)

    def _name_in_archive(self, path: Path, message: str) -> None:
        """The archive's ``xneck.campaign`` message becomes ``message`` (a rewrite of the finished
        file: :func:`server.archive_rewrite.rewrite_archive`); a fault is logged, the record says it."""
        try:
            if path.exists() and is_complete(path):
                rewrite_archive(path, amend={CAMPAIGN: {"message": message[:2000]}})
        except Exception as exc:  # noqa: BLE001 - the record names the cause whatever the file allows
            log.error("cannot name the cause in %s: %s", path.name,
                      storage_reason(exc) if isinstance(exc, OSError) else exc)

    def abort(self, reason: str, ended_within_s: float | None = None,
              timeout_s: float = ABORT_WAIT_S, stack_stopping: bool = False) -> CampaignRecord | None:
        """Stop the running campaign because of ``reason`` (a cause the console cannot see, e.g.
        ``"bridge process exited (signal SIGKILL)"`` from ``xneck up``): it ends ``aborted`` with
        ``reason`` first in its record's and its archive's message, and what the runner itself saw
        after it (module docstring). Waits at most ``timeout_s`` seconds for that record to be final.

        ``ended_within_s`` (seconds before this call): a campaign whose run ended within that window
        (it saw the cause's side effect before the cause was told) is named too, if it ended
        ``aborted``; without it only a campaign still running is. Returns the record named (None
        if none was): its status says whether the cause was written (``aborted``) or not.

        ``stack_stopping``: the console is stopped next (``xneck up`` stopping its stack), so the
        campaign's Foxglove scene is not added, or is cut short: its 8-11 s had outlasted this
        wait, and ``xneck up`` printed the campaign still running (fresh-user audit of 2026-12-01);
        the scene would have been stopped with the console anyway."""
        now = time.monotonic()
        with self._final_lock:
            with self._lock:
                last = self._last_end
                target = self._running or (last[0] if last is not None else None)
                ended_s = last[1] if last is not None and last[0] == target else None  # None: still running
                if target is None or (ended_s is not None and (ended_within_s is None
                                                               or ended_s < now - ended_within_s)):
                    return None  # nothing running, or it had ended before the cause
                if target == self._running:  # its worker names the cause when it writes the final record
                    # the first cause told stays (a second had replaced it), and a stop that came
                    # first (the user's) keeps its word (review of this session's diff)
                    self._causes.setdefault(target, (reason, ended_s is None and not self._stop.is_set()))
                    self._stop.stop(STOPPED_FOR_CAUSE)
                    if stack_stopping:
                        self._scene_stop.set()
                    late = None
                else:
                    rec = self._records.get(target)
                    if rec is None:  # deleted since it ended
                        return None
                    late = rec.model_copy()
            if late is not None and late.status == "aborted":  # final already: named here
                message = _with_cause(reason, late.message, False)
                path = self.index.mcap(target)
                self._name_in_archive(path, message)
                self._update(target, message=message, mcap_bytes=path.stat().st_size if path.exists() else 0)
        if late is None:
            worker = self._worker
            if worker is not None and worker.name == f"campaign:{target}":
                worker.join(timeout_s)
        try:
            return self.get(target)
        except NotFound:  # deleted meanwhile
            return None

    def stop(self, campaign_id: str) -> CampaignRecord:
        """Stop ``campaign_id``: this console's running campaign or replay, or a campaign of its
        that a controller runs unrecorded (:meth:`unrecorded`; raises :class:`NotStopped` if that
        controller does not answer). A campaign that runs nowhere is left as it is. Right after a
        start that recovered it, this first waits for the bus (:meth:`_await_bus`)."""
        if campaign_id in self._recovered_now:
            self._await_bus()
        rec = self.get(campaign_id)
        with self._lock:
            starting = self._replay_starting
            # That campaign's own stop event, taken with the check under the lock: read apart, a
            # campaign B started between them (a new ``_stop``) was stopped by a stop of A (review).
            own = self._stop if self._running == campaign_id else None
        if own is not None:
            own.stop(STOPPED_BY_USER)  # the first cause stays (an abort after it had renamed the user's stop)
        elif starting is not None and starting[0] == campaign_id:
            starting[2].set()  # it never starts
        elif self._replay is not None and self._replay.campaign_id == campaign_id and self._replay.running:
            self._replay.stop()
        elif rec.running_on:
            return self._stop_elsewhere(campaign_id, "" if rec.running_on == "(unknown)" else rec.running_on)
        return rec

    def _stop_elsewhere(self, campaign_id: str, controller: str) -> CampaignRecord:
        """Stop the campaign ``controller`` runs unrecorded with the stop request this console's own
        campaigns send (server.campaign_runner), addressed to it (bare when it is unknown: a
        service stops only the campaign it runs), and wait up to :data:`STOP_ANSWER_S` s for its
        end event. The record then says how it ended; :class:`NotStopped` if nothing answered
        and the controller's status still names the campaign."""
        answer: list[bus.CampaignEvent] = []
        answered = threading.Event()

        def on_event(sample: zenoh.Sample) -> None:
            try:
                ev = bus.decode(bus.CampaignEvent, payload_of(sample, bus.CampaignEvent))
            except bus.BusDecodeError:
                return
            if ev.campaign_id == campaign_id and ev.event in ("finished", "aborted"):
                answer.append(ev)
                answered.set()

        sub = self.session.declare_subscriber(bus.CAMPAIGN_EVENTS, on_event)
        requests = publisher(self.session, bus.campaign_request_key(controller) if controller else bus.CAMPAIGN_REQUEST)
        try:
            give_up = time.monotonic() + STOP_ANSWER_S
            seq = 0
            while not answered.is_set() and time.monotonic() < give_up:
                seq += 1
                requests.put(bus.CampaignRequest(seq=seq, stamp_s=time.time(), campaign_id=campaign_id,
                                                 action="stop"))
                answered.wait(STOP_RESEND_S)
        finally:
            requests.close()
            sub.undeclare()
        name = controller or "(unknown)"
        if answer:
            said = f"{answer[0].event}" + (f": {answer[0].message}" if answer[0].message else "")
            note = f"stopped on controller {name} from this console after its restart ({said})"
        elif self.unrecorded() is None:  # it ended meanwhile, its end event before the subscription
            note = f"ended on controller {name} as this console asked it to stop after its restart"
        else:
            raise NotStopped(f"campaign {campaign_id} is still running on controller {name}, unrecorded: the "
                             f"controller did not answer the stop within {STOP_ANSWER_S:.0f} s; use the e-stop")
        with self._lock:
            message = self._records[campaign_id].message  # as stored: not get()'s "still running"
        return self._update(campaign_id, message=f"{note}; {message}"[:2000])

    def wait_idle(self, timeout_s: float) -> bool:
        worker = self._worker
        if worker is not None:
            worker.join(timeout_s)
            return not worker.is_alive()
        return True

    def delete(self, campaign_id: str) -> None:
        running_on = self.get(campaign_id).running_on  # one a controller runs unrecorded: stopped first
        with self._final_lock:  # not while abort names a cause in its record and archive
            with self._lock:
                if self._running == campaign_id:
                    raise Busy(campaign_id)
                if running_on:
                    raise RunningElsewhere(campaign_id, running_on)
                if self._replay is not None and self._replay.campaign_id == campaign_id and self._replay.running:
                    raise Busy(campaign_id, REPLAY_OF)
                if self._replay_starting is not None and self._replay_starting[0] == campaign_id:
                    raise Busy(campaign_id, REPLAY_OF)
                self._records.pop(campaign_id, None)
                self._unfinished.pop(campaign_id, None)
            for p in (self.index.mcap(campaign_id), self.index.json(campaign_id)):
                p.unlink(missing_ok=True)
            self._remove_leftovers(campaign_id)
        figs = self.index.figures(campaign_id)
        try:
            if figs.is_symlink():  # the link, not what it points to (review of session 53: emptied)
                figs.unlink()
            elif figs.is_dir():
                shutil.rmtree(figs)  # links inside it are unlinked, never followed
        except OSError as exc:  # the campaign is deleted; a leftover folder is said, not a 500
            log.warning("campaign %s deleted, its folder %s not wholly: %s", campaign_id, figs.name,
                        storage_reason(exc))

    def _remove_leftovers(self, campaign_id: str) -> None:
        """The copies an archive leaves beside it: a damaged original kept by a recovery
        (``.corrupt``, ``.corrupt.1``, …: as large as the archive) and a rewrite or recovery
        killed half-way (``.rewrite``, ``.recovering``). Deleting a campaign had kept them, so
        the room a full disk's advice ("delete archives") promised was not freed."""
        mcap = self.index.mcap(campaign_id)
        # only NAME.corrupt and NAME.corrupt.<n> (bridge.archive_recovery): ids may hold dots, so a
        # glob's "*" took another campaign's "<id>.mcap.corrupt_b.json" too (review of session 53's diff)
        copy = re.compile(re.escape(mcap.name) + r"\.corrupt(?:\.[0-9]+)?")
        corrupt = [p for p in mcap.parent.glob(glob.escape(mcap.name) + ".corrupt*") if copy.fullmatch(p.name)]
        for p in [*corrupt,
                  mcap.with_name(mcap.name + ".rewrite"), mcap.with_name(mcap.name + ".recovering")]:
            with contextlib.suppress(OSError):
                if not p.is_dir():
                    p.unlink(missing_ok=True)

    def _keep_identified_set(self, cid: str, identified: dict[str, object]) -> None:
        """The set the analysis identified, for a save to copy (server.identified_sets): derived
        data, so a storage fault only costs that save an identification of its own."""
        try:
            folder = self.index.figures(cid)
            folder.mkdir(exist_ok=True)
            atomic_write(folder / CACHE_NAME, json.dumps(identified).encode())
        except OSError as exc:
            log.warning("campaign %s: its identified set not kept (%s): a save identifies it again", cid,
                        storage_reason(exc))
        except (TypeError, ValueError) as exc:  # not JSON: never the campaign's failure
            log.warning("campaign %s: its identified set not kept (%s): a save identifies it again", cid, exc)

    # -- replay -----------------------------------------------------------------------------
    def replay(self, campaign_id: str, speed: float) -> dict[str, object]:
        """Publish an archived campaign onto the bus at ``speed`` (recorded time per wall-clock
        time); its status. The robot is claimed for it before its archive is read, in the same
        critical section as the check, so a campaign or a second replay asked for meanwhile gets
        :class:`Busy`; a stop or e-stop during the read means it never starts (``running`` false).
        Raises :class:`Busy`, or what reading the archive raises (the claim then released)."""
        rec = self.get(campaign_id)
        cancelled = threading.Event()
        with self._lock:
            busy = self._holder()
            if busy is not None:
                raise busy
            if rec.status == "running":
                raise Busy(campaign_id)
            self._replay_starting = (campaign_id, speed, cancelled)
        try:
            replay = Replay(self.session, campaign_id, self.index.mcap(campaign_id), speed)
        except BaseException:
            with self._lock:
                self._replay_starting = None
            raise
        with self._lock:
            self._replay_starting = None
            if not cancelled.is_set():
                self._replay = replay
                replay.start()
        return replay.status()

    def replay_status(self) -> dict[str, object] | None:
        with self._lock:
            starting, replay = self._replay_starting, self._replay
        if starting is not None:  # its archive is being read: it holds the robot already
            return {"campaign_id": starting[0], "running": True, "starting": True, "progress": 0.0, "published": 0,
                    "total": 0, "speed": starting[1], "error": ""}
        return replay.status() if replay is not None else None

    # -- e-stop -----------------------------------------------------------------------------
    def _on_estop_token(self, sample: zenoh.Sample) -> None:
        # Zenoh callback thread: another holder's e-stop token appeared or vanished.
        try:
            holder = bus.parse_estop_token_key(str(sample.key_expr))
        except ValueError:
            return
        if holder == self.estop_holder:  # this console's own: estop_engaged says it, without a lag
            return
        with self._holders_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._estop_others.add(holder[:64])
            else:
                self._estop_others.discard(holder[:64])

    def _held_elsewhere(self) -> str:
        """'' unless another holder keeps an e-stop engaged on the bus; then the reason, naming it."""
        with self._holders_lock:
            others = sorted(self._estop_others)
        return f"e-stop engaged by {', '.join(others)} (it holds the e-stop token)" if others else ""

    def estop_status(self) -> dict[str, object]:
        """The e-stop as the console shows it: the bridge's latched state from its latest
        ``MotorState`` when one is fresh (the one truth: it also counts e-stops engaged by others
        or by a malformed message), else what this console last sent, or an e-stop another holds
        on the bus (its token: the next bridge starts latched) (``source`` says which)."""
        truth = self._bridge_estop()
        if truth is not None:
            return truth
        elsewhere = "" if self.estop_engaged else self._held_elsewhere()
        return {"engaged": self.estop_engaged or bool(elsewhere),
                "reason": self.estop_reason if self.estop_engaged else elsewhere,
                "drive": None, "source": "console"}

    def _drives_disabled(self, own_twin: bool) -> str:
        """Why a campaign cannot start on the drives (''if it can): the bridge's disabled drives
        when it drives the bridge on the bus, else this console's e-stop or one another holds on
        the bus (the twin it would start would start latched: bridge.bus.ESTOP_ENGAGED_ALL)."""
        truth = None if own_twin else self._bridge_estop()
        if truth is not None:
            return str(truth["reason"]) if truth["engaged"] or truth["drive"] == "disabled" else ""
        return (self.estop_reason or "e-stop engaged") if self.estop_engaged else self._held_elsewhere()

    def estop(self, engaged: bool, reason: str) -> None:
        """Publish the e-stop (the bridge holds and ignores commands while engaged) and, when
        engaging, abort the running campaign and any replay. An engage whose publication raises
        still holds its token (bridge.estop_holder) and still aborts, then raises."""
        try:
            with self._estop_lock:  # two at once: what this console says is what it sent last
                try:
                    (self._estop.engage if engaged else self._estop.release)(bus.plain_text(reason))
                finally:
                    self.estop_engaged, self.estop_reason = engaged, bus.plain_text(reason)
        finally:
            if engaged:  # the campaign start() armed meanwhile too (it arms before it checks the e-stop)
                self._stop.stop(STOPPED_BY_USER)
                self._cancel_starting_replay()
                if self._replay is not None:
                    self._replay.stop()

    def _cancel_starting_replay(self) -> None:
        with self._lock:
            if self._replay_starting is not None:
                self._replay_starting[2].set()

    def close(self, timeout_s: float = 20.0) -> bool:
        """Stop the running campaign and replay, wait up to ``timeout_s`` for the campaign's
        worker, let go of the e-stop token. True if the worker has ended; False if it still runs
        (its children take up to 10 s each to stop, its recorder 10 s to close): it may still
        write the data folder, so the folder's lock waits for it (:meth:`when_idle`)."""
        self._closing.set()
        self._stop.stop(STOPPED_BY_USER)
        self._scene_stop.set()
        self._cancel_starting_replay()
        if self._replay is not None:
            self._replay.stop()
        idle = self.wait_idle(timeout_s)
        # The token goes with this console (as in a crash): bridges latched stay latched until a release.
        for closer in (self._estop.close, self._estop_holders_sub.undeclare):
            with contextlib.suppress(Exception):
                closer()
        return idle

    def when_idle(self, then: Callable[[], None]) -> None:
        """Call ``then`` once the campaign's worker has ended: at once if none runs, else from a
        thread of its own. What the data folder's lock is released by after a :meth:`close` that
        timed out: released at once, a console restarted meanwhile had recovered the archive the
        worker was still writing (review of session 53)."""
        worker = self._worker
        if worker is None or not worker.is_alive():
            then()
            return

        def wait_then() -> None:
            worker.join()
            then()

        threading.Thread(target=wait_then, name="data-dir-release", daemon=True).start()
