"""A live camera's stamps on the bridge's clock (docs/camera.md, "One clock").

On the robot the bridge stamps its states with the BeagleBone's wall clock (no RTC battery: off
by seconds or more until NTP syncs) and a USB camera grabs on the PC. :class:`BridgeClock` measures
the offset of the bridge's stamp clock (queryable ``xneck/bridge/clock``,
:mod:`bridge.clock_service`) from this process's ``time.monotonic()`` (a PC clock that no NTP
step moves) in bursts of :data:`BURST` queries (the shortest round trip of each:
:mod:`bridge.clock_sync`), once at start (:meth:`BridgeClock.sync`, which waits for a bridge up to
a few seconds) and then every :data:`PERIOD_S` on a thread of its own (:meth:`BridgeClock.start`).
An exposure grabbed at monotonic time t is stamped ``t − latency + offset_s``.

Which bridge: the one that answers at start (a name given, ``--clock bridge:NAME``: that instance
only). Several answering without a name is refused at start. From then on the camera follows that
bridge *instance*: a new run of it (a restart: a new ``epoch``, same name) is synchronised afresh
(``resyncs``), the offset of the old run forgotten; another instance's replies, beside the followed
one or alone (a twin bridge on the hub while the robot's link drops), are set aside (``foreign``),
never adopted: the last offset stays, with a warning. A run is also known by the Zenoh id of the
session that replies (``reply.replier_id``): a burst in which two peers claim one run (an impostor
reading the name and epoch off a ``MotorState``) is refused and said (``impostors``), and a peer
other than the followed run's claiming it alone is not followed. A bridge started without ``--instance`` has
a random name at each start: after its restart the camera must be restarted too. A step of the offset within one run (the board's clock set by NTP)
is taken at once and counted (``steps``), with a warning. When no burst succeeds, the last offset
is kept (``clock_age_s`` in the health says since when), its uncertainty growing by 100 ppm of its
age (``uncertainty_s``: a crystal's worst drift); after :data:`STALE_S` without a sync a warning
says so once and the health carries ``clock_stale`` = 1. Once the uncertainty passes
``max_uncertainty_s`` (:data:`MAX_UNCERTAINTY_S`, about 100 s without a sync) no frame is stamped
any more: :meth:`BridgeClock.offset_for` gives none (frames dropped and counted, a warning once,
``clock_uncertain`` = 1 in the health) until a burst succeeds (session 37: a stale clock had stamped
on for ever, its α_IP published as on time).

A clock set between two bursts (NTP's first sync on the board, a reboot) would leave the stamps on
the old offset until the next burst, up to :data:`PERIOD_S` later (audit of 2026-11-29: 78 of 108
α_IP 3 s off). So the sync thread also watches the followed bridge's ``MotorState`` (500 Hz, small):
``stamp_s`` − this process's monotonic time at its arrival is the offset less the state's delay
(≥ 0). A state more than the step threshold plus the uncertainty *ahead* of the offset (one suffices:
a delay only lowers it), or :data:`STATE_WINDOW` in a row all as far *behind* it (a delay spike
does not last that long), or a new ``epoch`` of the followed instance is a *jump*
(``clock_jumps``): a burst is run at once. From the jump (less :data:`JUMP_MARGIN_S`) until a burst
begun after it is used, :meth:`BridgeClock.offset_for` gives no offset: the camera drops those
frames and counts them (``rejected["clock_frames"]``) rather than stamping them with an offset known
wrong, and frames captured before that burst began are dropped too (their offset is the old one).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable

import zenoh

from bridge import bus
from bridge.clock_service import query_clock
from bridge.clock_sync import ClockSample, ClockTracker, OffsetEstimate

log = logging.getLogger("xneck.camera")

BURST = 8  # queries per burst
PERIOD_S = 10.0  # s between bursts after the first sync
WAIT_S = 3.0  # s the first sync waits for a bridge to answer
QUERY_TIMEOUT_S = 0.5  # s one query waits for replies
STATE_WINDOW = 10  # MotorStates (20 ms at 500 Hz) all behind the offset by more than a step: a jump back
JUMP_MARGIN_S = 0.01  # s before the last state on the old offset from which frames are not trusted
TRIGGER_MIN_S = 1.0  # s at least between two bursts that states triggered
STALE_S = 60.0  # s without a burst used: the offset is stale (warned once, clock_stale in the health)
#: s of offset uncertainty beyond which no frame is stamped (module docstring): 10 ms of a neck at the
#: trajectories' 86°/s is 0.9° of α_IP, and more than half a 30 Hz frame (16.7 ms) is what
#: ``xneck identify``'s timing check calls delayed.
MAX_UNCERTAINTY_S = 0.010


class ClockSyncError(RuntimeError):
    """No bridge clock to synchronise with; the message says why and what to do."""


def _fmt_offset(offset_s: float, uncertainty_s: float) -> str:
    """``+12.345 s ± 0.4 ms ahead of`` / ``3.000 s ± 0.4 ms behind``."""
    where = "ahead of" if offset_s >= 0 else "behind"
    return f"{'+' if offset_s >= 0 else ''}{abs(offset_s):.3f} s ± {uncertainty_s * 1e3:.1f} ms {where}"


class BridgeClock:
    """The offset of the bridge's stamp clock from ``local`` (module docstring).

    ``offset_s`` is bridge − local (s), replaced whole by each burst used (read it once per
    exposure; a burst worse than the current estimate aged and overlapping it leaves it:
    :class:`bridge.clock_sync.ClockTracker`, ``kept``).
    ``bridge``/``epoch`` name the run it follows. Counters: ``bursts`` used, ``missed`` (no usable
    reply), ``steps``, ``resyncs``, ``foreign`` (replies of another bridge), ``refused`` (invalid
    replies: undecodable, non-finite, a local clock that went back).
    """

    def __init__(self, session: zenoh.Session, bridge: str = "", burst: int = BURST, period_s: float = PERIOD_S,
                 query_timeout_s: float = QUERY_TIMEOUT_S, local: Callable[[], float] = time.monotonic,
                 max_uncertainty_s: float = MAX_UNCERTAINTY_S) -> None:
        if burst < 1 or not (period_s > 0 and query_timeout_s > 0 and max_uncertainty_s > 0):
            raise ValueError("burst must be >= 1, period_s, query_timeout_s and max_uncertainty_s > 0 s")
        self.max_uncertainty_s = max_uncertainty_s
        self._uncertain = False  # frames refused for the offset's uncertainty (said once per episode)
        self.session, self.name = session, bridge
        self.burst, self.period_s, self.query_timeout_s, self.local = burst, period_s, query_timeout_s, local
        self.tracker = ClockTracker()
        self.offset_s = math.nan  # bridge − local (s); NaN before the first sync
        self._uncertainty_s, self._measured_at = math.nan, -math.inf  # the estimate's, and its local time
        self._stale_said = False
        self.bridge = self.epoch = self.replier = ""  # the run followed, and the Zenoh id of its session
        self.impostors = 0  # bursts refused because another peer claimed the followed run
        self.bursts = self.missed = self.resyncs = self.foreign = self.refused = 0
        self.run_bursts = 0  # bursts used on the run followed now
        self.last_problem = ""
        self._synced_at = -math.inf  # local time of the last used burst
        # The followed bridge's states (module docstring): a jump of their stamps wakes the sync thread.
        self.jumps = 0  # jumps seen on the states
        self._behind = 0  # states in a row behind the offset by more than a step
        self._last_good_at = -math.inf  # local arrival of the last state on the offset
        self._suspect_since: float | None = None  # local time from which the offset is known wrong
        self._valid_from = -math.inf  # local time from which the present offset holds (a re-sync after a jump)
        self._burst_started = -math.inf  # local time the running burst began
        self._burst_refused = 0  # replies refused in the running burst
        self._states: zenoh.Subscriber | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    # --- one burst ------------------------------------------------------------------------------

    def _collect(self) -> dict[tuple[str, str, str], list[ClockSample]]:
        """One burst: the samples of each bridge run that answered (named one only, if named), by
        (bridge, epoch, replier's Zenoh id)."""
        runs: dict[tuple[str, str, str], list[ClockSample]] = {}
        for _ in range(self.burst):
            if self._stop.is_set():  # stopping: a burst takes up to burst × query_timeout_s
                break
            result = query_clock(self.session, self.query_timeout_s, self.local)
            self.refused += result.refused
            self._burst_refused += result.refused
            if result.rejected:
                self.last_problem = result.rejected[-1]
            for reply in result.replies:
                r = reply.reading
                if self.name and r.bridge != self.name:
                    continue
                runs.setdefault((r.bridge, r.epoch, reply.replier), []).append(reply.sample)
        return runs

    def burst_once(self) -> str:
        """Query a burst and take it; '' when the offset was updated, else why not (a sentence)."""
        self._burst_started = self.local()
        self._burst_refused = 0
        runs = self._collect()
        if not runs:
            self.missed += 1
            refused = f"{self._burst_refused} replies refused, last: {self.last_problem}"
            if self._burst_refused:  # something answered: not "no bridge"
                named = f" from bridge {self.name!r}" if self.name else ""
                return f"no valid reply{named} on {bus.BRIDGE_CLOCK} ({refused})"
            named = f"bridge {self.name!r}" if self.name else "no bridge"
            return f"{named} answered on {bus.BRIDGE_CLOCK}" if not self.name else f"{named} did not answer on {bus.BRIDGE_CLOCK}"

        claims: dict[tuple[str, str], list[str]] = {}
        for b, e, r in runs:
            claims.setdefault((b, e), []).append(r)
        for (b, e), repliers in sorted(claims.items()):
            if len(repliers) > 1:  # a run is one bridge's session: one of them is not the bridge
                self.missed += 1
                self.impostors += 1
                self.last_problem = (f"{len(repliers)} peers answer as bridge {b} run {e} (Zenoh ids "
                                     f"{', '.join(sorted(repliers))}): one is not that bridge; burst refused, the last "
                                     f"offset stays")
                return self.last_problem
        current = (self.bridge, self.epoch, self.replier)
        if current in runs:
            chosen = current
            self.foreign += sum(len(v) for k, v in runs.items() if k != current)
        elif len(runs) == 1:
            chosen = next(iter(runs))
            if self.bridge and chosen[:2] == (self.bridge, self.epoch):
                # the followed run from another session: a run never changes its session
                self.foreign += len(runs[chosen])
                self.missed += 1
                self.impostors += 1
                return (f"bridge {self.bridge} (Zenoh id {self.replier or '?'}) did not answer and a peer (Zenoh id "
                        f"{chosen[2] or '?'}) answers as bridge {self.bridge} run {self.epoch} from another peer: "
                        f"not followed")
            if self.bridge and chosen[0] != self.bridge:
                # Another instance alone is not a restart of the followed one (a twin bridge on the hub
                # while the robot's link drops): its clock is not the robot's; the last offset stays.
                self.foreign += len(runs[chosen])
                self.missed += 1
                return (f"bridge {self.bridge} (run {self.epoch}) did not answer on {bus.BRIDGE_CLOCK} and "
                        f"bridge {chosen[0]} (run {chosen[1]}) answers alone: not followed (only a new run of "
                        f"{self.bridge} is; restart the camera to follow another bridge)")
        else:
            self.missed += 1
            names = ", ".join(f"{b} (run {e})" for b, e, _r in sorted(runs))
            return (f"{len(runs)} bridges answer on {bus.BRIDGE_CLOCK}: {names}; name the robot's with "
                    f"--clock bridge:NAME (its --instance)")
        with self._lock:  # the tracker against health()'s reads on the camera's thread
            return self._follow(chosen, current, runs[chosen])

    def _follow(self, chosen: tuple[str, str, str], current: tuple[str, str, str], samples: list[ClockSample]) -> str:
        before = self.tracker.steps
        if chosen != current:
            self.tracker.reset()  # the old run's offset says nothing of this one's
        outcome = self.tracker.add_burst(samples)
        self.refused += sum(1 for s in samples if s.problem())
        if not outcome.used or outcome.estimate is None:
            self.missed += 1
            if self.tracker.last_invalid:
                self.last_problem = self.tracker.last_invalid
            return f"bridge {chosen[0]}: {outcome.reason}"
        taken = self.tracker.last  # the burst's, or the previous one kept (tighter, aged, and overlapping it)
        assert taken is not None
        self._take(chosen, taken)
        if self.tracker.steps != before and self.tracker.last_step is not None:
            old, new = self.tracker.last_step
            log.warning("camera clock: the offset to bridge %s stepped by %+.3f s (a clock was set: NTP on the board, "
                        "or this PC's): exposures are stamped with the new offset from now on", chosen[0], new - old)
        return ""

    def _take(self, key: tuple[str, ...], est: OffsetEstimate) -> None:
        run = (key[0], key[1])
        if run != (self.bridge, self.epoch):
            self.run_bursts = 0
            if self.bridge:
                self.resyncs += 1
                log.warning("camera clock: bridge %s: run %s no longer answers, run %s does (a restart): synchronised "
                            "with it afresh, %s this PC's wall clock", self.bridge, self.epoch, run[1],
                            _fmt_offset(self._to_wall(est.offset_s), est.uncertainty_s))
        self.bridge, self.epoch = run
        self.replier = key[2] if len(key) > 2 else ""
        if self._suspect_since is not None and self._burst_started >= self._suspect_since:
            self._suspect_since = None  # a burst begun after the jump: its offset holds from its start
            self._valid_from = self._burst_started
            self._behind = 0
            log.warning("camera clock: re-synchronised with bridge %s after the jump of its states' stamps: %s this PC's "
                        "wall clock", self.bridge, _fmt_offset(self._to_wall(est.offset_s), est.uncertainty_s))
        self.run_bursts += 1
        self._uncertainty_s, self._measured_at = est.uncertainty_s, est.at_s
        self._stale_said = False
        if self._uncertain:
            self._uncertain = False
            log.warning("camera clock: bridge %s synchronised again: α_IP is stamped again", self.bridge)
        self.offset_s = est.offset_s  # the one value an exposure reads
        self.bursts += 1
        self._synced_at = self.local()

    # --- life cycle -----------------------------------------------------------------------------

    def sync(self, wait_s: float = WAIT_S, stop: threading.Event | None = None) -> None:
        """The first sync: bursts until one is used, for up to ``wait_s`` (a bridge and its routes
        may still be coming up); :class:`ClockSyncError` naming why if none is. Logs the offset."""
        deadline = time.monotonic() + wait_s
        while True:
            why = self.burst_once()
            if not why:
                break
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                raise ClockSyncError(f"camera clock: {why} within {wait_s:g} s. {self._hint()}")
            time.sleep(0.1)
        log.info("camera clock: bridge %s (run %s) is %s this PC's wall clock (shortest round trip of %d "
                 "queries; re-synchronised every %g s)", self.bridge, self.epoch, self.describe_offset(), self.burst,
                 self.period_s)

    def _hint(self) -> str:
        """What to do when the first sync failed (its last burst says why)."""
        if self._burst_refused:
            return (f"A peer answers on {bus.BRIDGE_CLOCK} with replies the camera refuses (not a bridge, or "
                    f"another version): find it, or, if the bridge runs on this machine (one clock), use --clock local")
        alive = [b for b in self._alive_bridges() if not self.name or b == self.name]
        if alive:  # up, but not answering: a bridge of before the clock was served
            names = ", ".join(f"bridge {b}" for b in alive)
            return (f"{names} {'is' if len(alive) == 1 else 'are'} up but serves no clock: update it, or use --clock "
                    f"local (if it runs on this machine)")
        return ("The camera stamps its exposures on the bridge's clock (--clock bridge): start the bridge first, or, "
                "if the bridge runs on this machine (one clock), use --clock local")

    def _alive_bridges(self, timeout_s: float = 0.5) -> list[str]:
        """The bridge instances whose liveliness token is on the bus (``xneck/alive/bridge/*``)."""
        found: set[str] = set()
        try:
            for reply in self.session.liveliness().get(f"{bus.PREFIX}/alive/bridge/*", timeout=timeout_s):
                if reply.ok is not None:
                    with contextlib.suppress(ValueError):
                        found.add(bus.parse_liveliness_key(str(reply.ok.key_expr))[1])
        except Exception:  # noqa: BLE001 - only a hint: a closing session gives none
            return []
        return sorted(found)

    def describe_offset(self) -> str:
        """The offset against this PC's wall clock, e.g. ``+12.345 s ± 0.4 ms ahead of``."""
        return _fmt_offset(self.wall_offset_s(), self.uncertainty_s)

    def wall_offset_s(self) -> float:
        """bridge − this PC's ``time.time()`` (s), from ``offset_s`` (for people and health)."""
        return self._to_wall(self.offset_s)

    def _to_wall(self, offset_s: float) -> float:
        """An offset from ``local`` as one from this PC's ``time.time()`` (s)."""
        return offset_s - (time.time() - self.local()) if self.local is not time.time else offset_s

    def start(self, watch_states: bool = True) -> None:
        """Bursts every ``period_s`` on a daemon thread until :meth:`stop`, and at once when the
        followed bridge's states jump (``watch_states``, module docstring)."""
        if watch_states:
            self._states = self.session.declare_subscriber(bus.MOTOR_STATE, self._on_state)
        self._thread = threading.Thread(target=self._run, name="xneck-camera-clock", daemon=True)
        self._thread.start()

    # --- the followed bridge's states -------------------------------------------------------------

    def _on_state(self, sample: zenoh.Sample) -> None:
        # Zenoh thread, 500 Hz: decode, compare, at most wake the sync thread.
        now = self.local()
        try:
            bus.check_payload_size(bus.MotorState, len(sample.payload))
            state = bus.decode(bus.MotorState, sample.payload.to_bytes())
        except bus.BusDecodeError:
            return  # not the followed bridge's to judge: the console counts refused states
        self.note_state(state.bridge, state.epoch, state.stamp_s, now)

    def note_state(self, bridge: str, epoch: str, stamp_s: float, now_s: float) -> bool:
        """One state of ``bridge`` run ``epoch`` stamped ``stamp_s`` (its clock), arrived at local
        ``now_s``: True when it shows a jump (module docstring; the sync thread is woken)."""
        with self._lock:
            if not self.bridge or bridge != self.bridge or not math.isfinite(self.offset_s) or not math.isfinite(stamp_s):
                return False
            if self._suspect_since is not None:
                return False  # a burst is on its way
            if epoch != self.epoch:
                why = f"a new run {epoch} of bridge {bridge} (a restart)"
            else:
                seen = stamp_s - now_s - self.offset_s  # −(the state's delay) when the offset holds
                bound = self.tracker.step_s + self._uncertainty(now_s)
                self._behind = self._behind + 1 if seen < -bound else 0
                if seen > bound:
                    why = f"a state stamped {seen:+.3f} s off the offset"
                elif self._behind >= STATE_WINDOW:
                    why = f"{self._behind} states in a row stamped {seen:+.3f} s off the offset"
                else:
                    if self._behind == 0:
                        self._last_good_at = now_s
                    return False
            self.jumps += 1
            good = self._last_good_at if math.isfinite(self._last_good_at) else now_s
            self._suspect_since = min(now_s, good) - JUMP_MARGIN_S
        log.warning("camera clock: bridge %s: %s: its clock was set (or it restarted); no α_IP is published until the "
                    "camera is re-synchronised (now)", bridge, why)
        self._wake.set()
        return True

    def offset_for(self, capture_local_s: float) -> float | None:
        """The offset for a frame captured at local ``capture_local_s`` and published now; None
        while a jump waits for its re-sync, for a frame captured before the re-sync after one,
        and before the first sync (module docstring)."""
        with self._lock:
            if self._suspect_since is not None or capture_local_s < self._valid_from or not math.isfinite(self.offset_s):
                return None
            if self._uncertainty(capture_local_s) > self.max_uncertainty_s:
                if not self._uncertain:
                    self._uncertain = True
                    log.warning("camera clock: the offset to bridge %s is ± %.1f ms after %.0f s without a sync, "
                                "beyond %.0f ms: no α_IP is stamped until it answers again (frames dropped, "
                                "clock_uncertain in the health)", self.bridge,
                                self._uncertainty(capture_local_s) * 1e3, self.age_s(), self.max_uncertainty_s * 1e3)
                return None
            return self.offset_s

    def _uncertainty(self, now_s: float) -> float:
        u = self._uncertainty_s + self.tracker.drift_bound * max(0.0, now_s - self._measured_at)
        return u if math.isfinite(u) else 0.0

    @property
    def uncertainty_s(self) -> float:
        """± s of ``offset_s`` now: the estimate's, grown by the drift bound (100 ppm) × its age;
        NaN before the first sync."""
        u = self._uncertainty_s + self.tracker.drift_bound * max(0.0, self.local() - self._measured_at)
        return u if math.isfinite(u) else math.nan

    def stale(self) -> bool:
        """No burst used for more than :data:`STALE_S` (after a first sync)."""
        return math.isfinite(self.offset_s) and self.age_s() > STALE_S

    def check_stale(self) -> bool:
        """Warn once when the offset turns stale (again after each sync); True when it warned."""
        if not self.stale() or self._stale_said:
            return False
        self._stale_said = True
        log.warning("camera clock: no sync with bridge %s for %.0f s: α_IP is stamped on an offset %.0f s old, "
                    "± %.1f ms by now (100 ppm of drift a second); the camera's health says clock_stale",
                    self.bridge, self.age_s(), self.age_s(), self.uncertainty_s * 1e3)
        return True

    def _run(self) -> None:
        said = ""
        last = -math.inf
        while not self._stop.is_set():
            with self._lock:  # an offset known wrong is retried sooner than every period
                wait_s = self.period_s if self._suspect_since is None else min(self.period_s, TRIGGER_MIN_S)
            woken = self._wake.wait(wait_s)
            if woken:  # states jumped: at once, but not more often than TRIGGER_MIN_S
                self._stop.wait(max(0.0, last + TRIGGER_MIN_S - time.monotonic()))
                self._wake.clear()
            if self._stop.is_set():
                break
            last = time.monotonic()
            try:
                why = self.burst_once()
            except Exception as exc:  # noqa: BLE001 - a closing session: the offset stays, the camera goes on
                why = f"{type(exc).__name__}: {exc}"
            if self._stop.is_set():
                break
            if why and why != said:
                log.warning("camera clock: %s; the last offset (%s this PC's, %.0f s old) stays", why, self.describe_offset(),
                            self.age_s())
            elif not why and said:
                log.warning("camera clock: bridge %s answers again: %s this PC's", self.bridge, self.describe_offset())
            said = why
            self.check_stale()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._states is not None:
            with contextlib.suppress(Exception):  # the session may be closed already
                self._states.undeclare()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def age_s(self) -> float:
        """s since the last burst used."""
        return self.local() - self._synced_at

    def health(self) -> tuple[dict[str, int], dict[str, int]]:
        """(received, rejected) counters for the camera's ``Health`` (µs and counts, integers):
        the offset to this PC's wall clock and its uncertainty, the drift (ppb), the age of the
        last sync (s), the bursts, steps and re-syncs, and the run followed as
        ``clock_run/<bridge>/<epoch>`` (its bursts used); refused replies and missed bursts."""
        with self._lock:
            return self._health()

    def _health(self) -> tuple[dict[str, int], dict[str, int]]:
        received = {"clock_bursts": self.bursts, "clock_steps": self.tracker.steps, "clock_resyncs": self.resyncs,
                    "clock_foreign": self.foreign, "clock_jumps": self.jumps, "clock_kept": self.tracker.kept,
                    "clock_impostors": self.impostors,
                    "clock_resyncing": int(self._suspect_since is not None), "clock_stale": int(self.stale()),
                    "clock_uncertain": int(self._uncertain)}
        if math.isfinite(self.offset_s):
            drift = self.tracker.drift()
            received.update({"clock_offset_us": round(self.wall_offset_s() * 1e6),
                             "clock_uncertainty_us": round(self.uncertainty_s * 1e6),
                             "clock_age_s": int(self.age_s()),
                             f"clock_run/{self.bridge}/{self.epoch}": self.run_bursts})
            if drift is not None:
                received["clock_drift_ppb"] = round(drift * 1e9)
        return received, {"clock_replies": self.refused, "clock_bursts": self.missed}


__all__ = ["BURST", "MAX_UNCERTAINTY_S", "PERIOD_S", "STALE_S", "STATE_WINDOW", "WAIT_S", "BridgeClock", "ClockSyncError"]
