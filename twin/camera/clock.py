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
never adopted: the last offset stays, with a warning. A bridge started without ``--instance`` has
a random name at each start: after its restart the camera must be restarted too. A step of the offset within one run (the board's clock set by NTP)
is taken at once and counted (``steps``), with a warning. When no burst succeeds, the last offset
is kept (``clock_age_s`` in the health says since when).
"""

from __future__ import annotations

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


class ClockSyncError(RuntimeError):
    """No bridge clock to synchronise with; the message says why and what to do."""


def _fmt_offset(offset_s: float, uncertainty_s: float) -> str:
    """``+12.345 s ± 0.4 ms ahead of`` / ``3.000 s ± 0.4 ms behind``."""
    where = "ahead of" if offset_s >= 0 else "behind"
    return f"{'+' if offset_s >= 0 else ''}{abs(offset_s):.3f} s ± {uncertainty_s * 1e3:.1f} ms {where}"


class BridgeClock:
    """The offset of the bridge's stamp clock from ``local`` (module docstring).

    ``offset_s`` is bridge − local (s), replaced whole by each burst (read it once per exposure).
    ``bridge``/``epoch`` name the run it follows. Counters: ``bursts`` used, ``missed`` (no usable
    reply), ``steps``, ``resyncs``, ``foreign`` (replies of another bridge), ``refused`` (invalid
    replies: undecodable, non-finite, a local clock that went back).
    """

    def __init__(self, session: zenoh.Session, bridge: str = "", burst: int = BURST, period_s: float = PERIOD_S,
                 query_timeout_s: float = QUERY_TIMEOUT_S, local: Callable[[], float] = time.monotonic) -> None:
        if burst < 1 or not (period_s > 0 and query_timeout_s > 0):
            raise ValueError("burst must be >= 1, period_s and query_timeout_s > 0 s")
        self.session, self.name = session, bridge
        self.burst, self.period_s, self.query_timeout_s, self.local = burst, period_s, query_timeout_s, local
        self.tracker = ClockTracker()
        self.offset_s = math.nan  # bridge − local (s); NaN before the first sync
        self.uncertainty_s = math.nan
        self.bridge = self.epoch = ""
        self.bursts = self.missed = self.resyncs = self.foreign = self.refused = 0
        self.run_bursts = 0  # bursts used on the run followed now
        self.last_problem = ""
        self._synced_at = -math.inf  # local time of the last used burst
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    # --- one burst ------------------------------------------------------------------------------

    def _collect(self) -> dict[tuple[str, str], list[ClockSample]]:
        """One burst: the samples of each bridge run that answered (named one only, if named)."""
        runs: dict[tuple[str, str], list[ClockSample]] = {}
        for _ in range(self.burst):
            if self._stop.is_set():  # stopping: a burst takes up to burst × query_timeout_s
                break
            result = query_clock(self.session, self.query_timeout_s, self.local)
            self.refused += len(result.rejected)
            if result.rejected:
                self.last_problem = result.rejected[-1]
            for reply in result.replies:
                r = reply.reading
                if self.name and r.bridge != self.name:
                    continue
                runs.setdefault((r.bridge, r.epoch), []).append(reply.sample)
        return runs

    def burst_once(self) -> str:
        """Query a burst and take it; '' when the offset was updated, else why not (a sentence)."""
        runs = self._collect()
        if not runs:
            self.missed += 1
            named = f"bridge {self.name!r}" if self.name else "no bridge"
            why = f"{named} answered on {bus.BRIDGE_CLOCK}" if not self.name else f"{named} did not answer on {bus.BRIDGE_CLOCK}"
            return why + (f" ({self.refused} replies refused, last: {self.last_problem})" if self.refused else "")
        current = (self.bridge, self.epoch)
        if current in runs:
            chosen = current
            self.foreign += sum(len(v) for k, v in runs.items() if k != current)
        elif len(runs) == 1:
            chosen = next(iter(runs))
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
            names = ", ".join(f"{b} (run {e})" for b, e in sorted(runs))
            return (f"{len(runs)} bridges answer on {bus.BRIDGE_CLOCK}: {names}; name the robot's with "
                    f"--clock bridge:NAME (its --instance)")
        with self._lock:  # the tracker against health()'s reads on the camera's thread
            return self._follow(chosen, current, runs[chosen])

    def _follow(self, chosen: tuple[str, str], current: tuple[str, str], samples: list[ClockSample]) -> str:
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
        self._take(chosen, outcome.estimate)
        if self.tracker.steps != before and self.tracker.last_step is not None:
            old, new = self.tracker.last_step
            log.warning("camera clock: the offset to bridge %s stepped by %+.3f s (a clock was set: NTP on the board, "
                        "or this PC's): exposures are stamped with the new offset from now on", chosen[0], new - old)
        return ""

    def _take(self, run: tuple[str, str], est: OffsetEstimate) -> None:
        if run != (self.bridge, self.epoch):
            self.run_bursts = 0
            if self.bridge:
                self.resyncs += 1
                log.warning("camera clock: bridge %s: run %s no longer answers, run %s does (a restart): synchronised "
                            "with it afresh, %s this PC's wall clock", self.bridge, self.epoch, run[1],
                            _fmt_offset(self._to_wall(est.offset_s), est.uncertainty_s))
        self.bridge, self.epoch = run
        self.run_bursts += 1
        self.uncertainty_s = est.uncertainty_s
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
                raise ClockSyncError(f"camera clock: {why} within {wait_s:g} s. The camera stamps its exposures on "
                                     f"the bridge's clock (--clock bridge): start the bridge first, or, if the bridge "
                                     f"runs on this machine (one clock), use --clock local")
            time.sleep(0.1)
        log.info("camera clock: bridge %s (run %s) is %s this PC's wall clock (shortest round trip of %d "
                 "queries; re-synchronised every %g s)", self.bridge, self.epoch, self.describe_offset(), self.burst,
                 self.period_s)

    def describe_offset(self) -> str:
        """The offset against this PC's wall clock, e.g. ``+12.345 s ± 0.4 ms ahead of``."""
        return _fmt_offset(self.wall_offset_s(), self.uncertainty_s)

    def wall_offset_s(self) -> float:
        """bridge − this PC's ``time.time()`` (s), from ``offset_s`` (for people and health)."""
        return self._to_wall(self.offset_s)

    def _to_wall(self, offset_s: float) -> float:
        """An offset from ``local`` as one from this PC's ``time.time()`` (s)."""
        return offset_s - (time.time() - self.local()) if self.local is not time.time else offset_s

    def start(self) -> None:
        """Bursts every ``period_s`` on a daemon thread until :meth:`stop`."""
        self._thread = threading.Thread(target=self._run, name="xneck-camera-clock", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        said = ""
        while not self._stop.wait(self.period_s):
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

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
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
                    "clock_foreign": self.foreign}
        if math.isfinite(self.offset_s):
            drift = self.tracker.drift()
            received.update({"clock_offset_us": round(self.wall_offset_s() * 1e6),
                             "clock_uncertainty_us": round(self.uncertainty_s * 1e6),
                             "clock_age_s": int(self.age_s()),
                             f"clock_run/{self.bridge}/{self.epoch}": self.run_bursts})
            if drift is not None:
                received["clock_drift_ppb"] = round(drift * 1e9)
        return received, {"clock_replies": self.refused, "clock_bursts": self.missed}


__all__ = ["BURST", "PERIOD_S", "WAIT_S", "BridgeClock", "ClockSyncError"]
