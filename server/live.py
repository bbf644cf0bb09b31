"""Bus → browser fan-out: the latest value of every live series, broadcast at a fixed rate.

Decimated where the samples enter the console (issue 21): each series is a Zenoh subscriber with
a one-slot ring, which Zenoh's own (native) thread overwrites at 500 Hz without running any
Python; the console takes the newest sample only when it reads (30 Hz), so the loop's rates cost
it no interpreter time and no GIL, and nothing queues (the bridge's ``state`` alone is also taken
every :data:`STATE_SAMPLE_PERIOD_S`, so that its age is known whoever reads). A broadcaster coroutine builds one JSON frame per period
(``live_rate_hz``, 30 Hz) from the latest values and hands the *same bytes* to every client's
bounded queue, dropping that client's oldest frame when it is full. A slow or stalled browser
thus loses frames (it sees the newest state when it catches up) and never pushes back on the bus
or on other clients.
While no client is connected the broadcaster sleeps until one connects: it reads and decodes
nothing. The series only viewers need (``VIEW_ONLY``: the commands and the twin's truth, 500 Hz
each) are subscribed to while a viewer (a browser here, a viser client of the 3D view) is
connected, so the idle console takes no sample of them and their senders send them to nobody
(the idle stack's CPU, issue 21). The console's own checks read the other series at any time.

Frame (JSON, SI units; the dashboard converts to degrees)::

    {"type": "live", "seq": n, "wall_s": ..., "series": {
        "status":  {"stamp_s", "alpha_hat_rad", "alpha_d_rad", "e_rad", "holding", "hold_reason",
                    "law", "tick_s", "deadline_misses", "overruns"},
        "state":   {"stamp_s", "force_applied_N", "theta_rad", "drive", "estop_engaged", "estop_reason"},
        "command": {"stamp_s", "force_N"},
        "camera":  {"stamp_s", "alpha_ip_rad", "confidence", "source", "instance", "chosen"},
                   (alpha_ip_rad[i] null: joint missing)
        "truth":   {"stamp_s", "alpha_rad", "tension_N"},
        "campaign":{"campaign_id", "kind", "event", "progress", "message"},
        "estop":   {"engaged", "reason"}}}

A series appears once its first message arrived; ``stamp_s`` lets a client drop repeats.
``camera`` appears only while the camera is fresh (:func:`fresh_camera`, the rule of
``/api/camera``'s ``fresh``): the dashboard plots α_IP at each new status time, and a stale
camera's last α_IP had been drawn there as a live line (audit of 2026-11-29).

``camera`` is one camera's: two cameras may publish α_IP on one hub (`xneck up`'s and a second
`xneck camera --source twin` or ``usb:0``), and the series flipped between them at each read, the
dashboard's α_IP line jumping between two sources. A camera is told by its samples' attachment
(as the console's camera health tells them apart, :mod:`server.camera_feed`): the camera process
that names itself (:func:`bridge.session.camera_of`), else the bridge run whose twin published it
(:func:`~bridge.session.run_of`), else none (an older camera process, a replay); ``instance`` is
that name ('' for none; cut to :data:`INSTANCE_MAX_CHARS`: any peer may name itself), and
``chosen`` why that camera is the one followed (:data:`CHOSEN`). Their samples queue in a ring of
:data:`BY_RUN_RING_SAMPLES`, each camera's newest valid message kept (at most :data:`BY_CAMERA_MAX_CAMERAS`; a camera sending only
what the console refuses is never followed), and the series shows the newest of the camera followed: the one :attr:`LatestValues.prefer_camera` names while it is fresh (the
camera the running campaign records, else the stack's own: ``server.app``; ``TWIN_CAMERA``: the
twin of the run the truth follows), else the one followed so far while it sent within
:data:`CAMERA_FOLLOW_MAX_AGE_S`, else, among those that did, the one heard of first. A camera
gone silent thus hands over to a live one before the series goes stale. The dashboard says which
camera the α_IP drawn is of, and why (``web/app.js``).

``truth`` is one twin's: a ``Truth`` has no identity field, and a second twin on the hub made the
series flip between two twins' clocks and poses (audit of 2026-11-29). Its samples name their
bridge run in their attachment (:func:`bridge.session.run_of`); the series shows the newest truth
of the run the newest command answers (``ForceCommand.epoch``, what a campaign follows), else of
the run shown last while its truth keeps coming (a second twin's states had made the series flip
once the campaign's commands stopped), else of the newest state's run, each if under
:data:`RUN_FOLLOW_MAX_AGE_S` old; a truth naming no run (a
replay's) only when that run has none (the robot's bridge), any truth when no run is known.
``estop`` is what was last *sent* on ``xneck/estop`` (by anyone); whether the drives are really
stopped is the bridge's word, ``state.estop_engaged``/``estop_reason`` (:func:`bridge_estop`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar, cast

import msgspec
import zenoh

from bridge import bus
from bridge.session import camera_of, controller_of, replayed, run_of
from server.quality import TWIN_CAMERA, drive_estop

log = logging.getLogger("xneck.server")

#: Series name -> (key, fields forwarded to browsers).
SERIES: dict[str, tuple[str, tuple[str, ...]]] = {
    "status": (bus.CONTROLLER_STATUS, ("stamp_s", "alpha_hat_rad", "alpha_d_rad", "e_rad", "holding", "hold_reason",
                                       "law", "tick_s", "deadline_misses", "overruns")),
    "state": (bus.MOTOR_STATE, ("stamp_s", "force_applied_N", "theta_rad", "drive", "estop_engaged", "estop_reason")),
    "command": (bus.MOTOR_COMMAND, ("stamp_s", "force_N")),
    "camera": (bus.CAMERA_ALPHA, ("stamp_s", "alpha_ip_rad", "confidence", "source")),  # + "instance", "chosen": frame_of
    "truth": (bus.TWIN_TRUTH, ("stamp_s", "alpha_rad", "tension_N")),
    "campaign": (bus.CAMPAIGN_EVENTS, ("campaign_id", "kind", "event", "progress", "message")),
    "estop": (bus.ESTOP, ("engaged", "reason")),
}

#: Series that only viewers read (:meth:`LatestValues.watch`); the others feed the console's own
#: checks while nobody watches: the bridge's e-stop (``state``), jogs (``status``), the camera.
VIEW_ONLY = frozenset({"command", "truth"})

#: Series whose value is one bridge run's (module docstring): their samples queue in a ring this
#: long, read whole at each read, so that the followed run's newest is found among another's.
BY_RUN = frozenset({"truth"})
BY_RUN_RING_SAMPLES = 32
RUN_FOLLOW_MAX_AGE_S = 0.5  # s: an older command or state names no run to follow
BY_RUN_MAX_RUNS = 8  # runs remembered per series (a flood of forged runs stays bounded)
STATUS_MAX_CONTROLLERS = 8  # controllers whose newest live status is kept (LiveBus.live_statuses)

#: Series whose value is one camera's (module docstring): a ring of BY_RUN_RING_SAMPLES, each
#: camera's newest kept.
BY_CAMERA = frozenset({"camera"})
#: s: the camera followed hands over to another that sent within this (under CAMERA_MAX_AGE_S, so
#: that the series stays fresh through a hand-over; a camera sends at 30-60 Hz).
CAMERA_FOLLOW_MAX_AGE_S = 0.5
BY_CAMERA_MAX_CAMERAS = 8  # cameras remembered (a flood of forged names stays bounded)
#: Why the camera followed is the one the ``camera`` series shows (a live frame's ``camera.chosen``):
#: the one the running campaign records, the stack's own (the two :attr:`LatestValues.prefer_camera`
#: names), the first heard of among those sending (none was followed yet, or the one followed went
#: silent: a hand-over), or the one shown so far, kept (it was preferred and no longer is).
CHOSEN_CAMPAIGN, CHOSEN_STACK, CHOSEN_FIRST, CHOSEN_CURRENT = "campaign", "stack", "first", "current"
CHOSEN = (CHOSEN_CAMPAIGN, CHOSEN_STACK, CHOSEN_FIRST, CHOSEN_CURRENT)
#: characters of a camera's name a live frame carries: a peer naming itself with kilobytes sent
#: them to every browser 30 times a second
INSTANCE_MAX_CHARS = 64

#: s: a camera whose latest α_IP arrived longer ago than this is stale (:func:`fresh_camera`).
CAMERA_MAX_AGE_S = 1.0
#: Series a live frame carries only while fresh: name -> the age (s) beyond which it is left out.
LIVE_MAX_AGE_S: dict[str, float] = {"camera": CAMERA_MAX_AGE_S}

_K = TypeVar("_K")

CLIENT_QUEUE_FRAMES = 4  # frames buffered per browser before the oldest is dropped
#: live clients (WebSocket and SSE) at once: each costs a queue, an encode's share and a socket, and
#: anyone on the lab network may open them (review of session 53); more are refused (LiveFull)
LIVE_MAX_CLIENTS = 64
BRIDGE_STATE_MAX_AGE_S = 0.5  # s: an older MotorState says nothing about the drives now
#: s between two takes of the bridge's newest ``MotorState`` off its ring (:class:`LiveBus`), read
#: or not: a sample is stamped when it is taken, so its age (:func:`bridge_status`, the e-stop's
#: freshness) is known to within this, even while nobody else reads (the idle 3D view reads at 1 Hz).
STATE_SAMPLE_PERIOD_S = 0.1


def receiver_checks(n_motors: int, n_joints: int) -> dict[str, Callable[[Any], None]]:
    """The range checks (:mod:`bridge.bus`) the console applies to what it shows and trusts: a
    motor state of the robot's motor count with finite angles and non-negative finite forces (not
    bounded by this console's f_max, which may be another set's than the bridge's), a camera
    message of its joint count. Any peer may publish: a state with one force too many froze the
    dashboard's live view, camera confidences of another length its camera panel (audit of
    2026-11-27)."""
    return {"state": lambda m: bus.check_motor_state(m, n_motors, math.inf),
            "camera": lambda m: bus.check_camera_alpha(m, n_joints)}


class LatestValues:
    """Thread-safe store of the latest message per series, fed by Zenoh callbacks.

    Callbacks store raw payloads (500 Hz per key would otherwise cost a decode each); a payload is
    decoded only when read, at most once, so the cost follows the 30 Hz readers, not the bus.
    Payloads that fail to decode are counted in :attr:`rejected` and never shown.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sources: dict[str, Callable[[], Any]] = {}  # series -> try_recv of its one-slot ring
        self._run_sources: dict[str, Callable[[], Any]] = {}  # BY_RUN series -> try_recv of its ring
        # BY_RUN series -> bridge run ('' : none named) -> (time.monotonic() taken, its newest payload)
        self._by_run: dict[str, dict[str, tuple[float, bytes]]] = {}
        self._last_run: dict[str, str] = {}  # BY_RUN series -> the run it showed last
        self._camera_sources: dict[str, Callable[[], Any]] = {}  # BY_CAMERA series -> try_recv of its ring
        # BY_CAMERA series -> camera (:func:`_camera_key`) -> (time.monotonic() first taken, of its
        # newest valid payload, that payload, its message)
        self._by_camera: dict[str, dict[tuple[str, str], tuple[float, float, bytes, bus.BusMessage]]] = {}
        self._camera_followed: dict[str, tuple[str, str]] = {}  # BY_CAMERA series -> the camera shown
        self._camera_chosen: dict[str, str] = {}  # BY_CAMERA series -> why it is (:data:`CHOSEN`)
        self._named: dict[str, str] = {}  # BY_CAMERA series -> the camera its stored payload is of ('' : none named)
        #: The camera the ``camera`` series shows while it is fresh (module docstring) and why:
        #: (a camera process's instance, :data:`~server.quality.TWIN_CAMERA` (the twin's own) or ''
        #: (none); :data:`CHOSEN_CAMPAIGN` or :data:`CHOSEN_STACK`). Called at every read, under this
        #: store's lock: it must take no lock held while this store is read (a read of an attribute
        #: or two, not a call into a locked object).
        self.prefer_camera: Callable[[], tuple[str, str]] | None = None
        self._prefer_failed = False  # logged once
        self._raw: dict[str, bytes] = {}
        self._received_s: dict[str, float] = {}  # series -> time.monotonic() of its latest payload
        self._decoded: dict[str, tuple[bytes, bus.BusMessage | None]] = {}
        # series -> (time.monotonic() of its newest payload that decoded, that message)
        self._valid: dict[str, tuple[float, bus.BusMessage]] = {}
        self._version = 0
        self.rejected = 0
        # series -> the receiver's range check of a decoded message (:func:`receiver_checks`): one
        # that fails counts as rejected, as garbage does, and is never shown nor trusted
        self.checks: dict[str, Callable[[Any], None]] = {}
        self._watch_lock = threading.Lock()  # orders the watched/unwatched hand-overs
        self._viewers: set[str] = set()
        self._on_watched: Callable[[bool], None] | None = None

    def on_watched(self, hook: Callable[[bool], None]) -> None:
        """Call ``hook(True)`` when a first viewer starts watching and ``hook(False)`` when the last
        one stops (:meth:`watch`)."""
        self._on_watched = hook

    def watch(self, viewer: str, watching: bool) -> None:
        """``viewer`` (a name: the browsers' fan-out, the 3D view) starts or stops watching."""
        with self._watch_lock:
            before = bool(self._viewers)
            if watching:
                self._viewers.add(viewer)
            else:
                self._viewers.discard(viewer)
            if bool(self._viewers) != before and self._on_watched is not None:
                self._on_watched(not before)

    @property
    def watched(self) -> bool:
        return bool(self._viewers)

    def put_raw(self, series: str, payload: bytes) -> None:
        now = time.monotonic()
        with self._lock:
            self._store(series, payload, now)

    def _store(self, series: str, payload: bytes, now: float) -> None:
        self._raw[series] = payload
        self._received_s[series] = now
        self._version += 1

    def add_source(self, series: str, try_recv: Callable[[], Any], by_run: bool = False,
                   by_camera: bool = False) -> None:
        """Pull ``series`` from ``try_recv`` (a Zenoh ring's: the newest sample or None) whenever
        a value is read, instead of having it pushed by a callback per sample. ``by_run``: the
        ring holds several samples, all read, and the value is the followed run's; ``by_camera``:
        likewise, the followed camera's (module docstring)."""
        with self._lock:
            sources = self._run_sources if by_run else self._camera_sources if by_camera else self._sources
            sources[series] = try_recv

    def remove_source(self, series: str) -> None:
        """Stop pulling ``series`` and forget its value (a later viewer must not see a stale one)."""
        with self._lock:
            self._sources.pop(series, None)
            self._run_sources.pop(series, None)
            self._by_run.pop(series, None)
            self._camera_sources.pop(series, None)
            self._by_camera.pop(series, None)
            self._camera_followed.pop(series, None)
            self._camera_chosen.pop(series, None)
            self._named.pop(series, None)
            if self._raw.pop(series, None) is not None:
                self._version += 1
            self._received_s.pop(series, None)
            self._decoded.pop(series, None)
            self._valid.pop(series, None)

    def _pull(self, only: str | None = None) -> None:
        """(Under the lock.) Take the newest sample of every ring that has one (of ``only``'s, if
        given); its time of arrival is known to within a read period (what ``fresh`` allows for)."""
        now = time.monotonic()
        for series, try_recv in self._sources.items():
            if only is not None and series != only:
                continue
            try:
                sample = try_recv()
            except Exception:  # noqa: BLE001 - a closed subscriber: nothing new, ever
                continue
            if sample is not None:
                self._store(series, sample.payload.to_bytes(), now)
        for series, try_recv in self._run_sources.items():
            if only is None or series == only:
                self._pull_by_run(series, try_recv, now)
        for series, try_recv in self._camera_sources.items():
            if only is None or series == only:
                self._pull_by_camera(series, try_recv, now)

    def _pull_by_run(self, series: str, try_recv: Callable[[], Any], now: float) -> None:
        """(Under the lock, after the other series.) Read ``series``' ring whole, keep each run's
        newest payload, and store the followed run's newest if it changed (module docstring)."""
        runs = self._by_run.setdefault(series, {})
        for run, sample in _newest_by(try_recv, run_of).items():
            if run not in runs and len(runs) >= BY_RUN_MAX_RUNS:
                del runs[min(runs, key=lambda r: runs[r][0])]
            runs[run] = (now, sample.payload.to_bytes())
        followed, by_command = self._followed_run(now)
        last = self._last_run.get(series, "")
        if not by_command and last and last in runs and now - runs[last][0] <= RUN_FOLLOW_MAX_AGE_S:
            # No command names a run (a campaign ended, a jog stopped): the newest state is any
            # bridge's, and with a second twin on the hub the series flipped between the two (CI of
            # session 42); the run shown stays while its truth keeps coming.
            followed = last
        if followed:
            self._last_run[series] = followed
        chosen = runs.get(followed) if followed else None
        if chosen is None and followed:
            chosen = runs.get("")  # a truth naming no run (a replay's), when the run followed has none
        if chosen is None and not followed and runs:
            chosen = max(runs.values(), key=lambda item: item[0])
        if chosen is not None and chosen[1] is not self._raw.get(series):
            self._store(series, chosen[1], chosen[0])

    def _pull_by_camera(self, series: str, try_recv: Callable[[], Any], now: float) -> None:
        """(Under the lock, after the other series.) Read ``series``' ring whole, keep each camera's
        newest valid payload, and store the followed camera's newest if it changed (module
        docstring). Each camera's newest is decoded here, so that a camera sending only what is
        refused (counted in :attr:`rejected`) is never followed, and one that sends some keeps its
        last valid payload and its age; the one stored is decoded once."""
        cameras = self._by_camera.setdefault(series, {})
        followed = self._camera_followed.get(series)
        for camera, sample in _newest_by(try_recv, _camera_key).items():
            payload = sample.payload.to_bytes()
            msg = self._decode(series, payload)
            if msg is None:
                continue
            known = cameras.get(camera)
            if known is None and len(cameras) >= BY_CAMERA_MAX_CAMERAS:  # the one followed stays
                del cameras[min((c for c in cameras if c != followed), key=lambda c: cameras[c][1])]
            cameras[camera] = (now if known is None else known[0], now, payload, msg)
        if not cameras:
            return
        followed, self._camera_chosen[series] = self._follow_camera(cameras, followed,
                                                                    self._camera_chosen.get(series, CHOSEN_FIRST), now)
        self._camera_followed[series] = followed
        _, received, payload, msg = cameras[followed]
        if payload is not self._raw.get(series):
            self._store(series, payload, received)
            self._decoded[series] = (payload, msg)
            self._named[series] = followed[0] or followed[1]

    def _follow_camera(self, cameras: Mapping[tuple[str, str], tuple[float, float, bytes, bus.BusMessage]],
                       followed: tuple[str, str] | None, chosen: str, now: float) -> tuple[tuple[str, str], str]:
        """(Under the lock.) The camera to show (module docstring) and why (:data:`CHOSEN`;
        ``chosen``: why the one ``followed`` was): the one preferred, else the one ``followed``,
        each if it sent within :data:`CAMERA_FOLLOW_MAX_AGE_S`, else the first heard of among
        those that did; the one followed (else the newest) when none did."""
        fresh = [c for c, (_, received, _, _) in cameras.items() if now - received <= CAMERA_FOLLOW_MAX_AGE_S]
        try:
            prefer, why = self.prefer_camera() if self.prefer_camera is not None else ("", "")
        except Exception as exc:  # noqa: BLE001 - a hook that fails prefers nothing; reads go on
            prefer, why = "", ""
            if not self._prefer_failed:  # once: it runs at every read (helper's review, session 41)
                self._prefer_failed = True
                log.error("the live view's camera preference failed (%s: %s): following the first camera heard",
                          type(exc).__name__, exc)
        run = self._run_shown(now) if prefer == TWIN_CAMERA else ""
        preferred = [c for c in fresh if _prefers(prefer, run, c)]
        if preferred:
            return min(preferred, key=lambda c: cameras[c][0]), why
        if followed is not None and followed in cameras and (followed in fresh or not fresh):
            # kept: it is still the first heard of, or still the one preferred (silent a moment), or
            # it was preferred and is no longer (a campaign ended): the one shown so far
            if chosen in (CHOSEN_CAMPAIGN, CHOSEN_STACK) and not (chosen == why and _prefers(prefer, run, followed)):
                chosen = CHOSEN_CURRENT
            return followed, chosen
        if fresh:
            return min(fresh, key=lambda c: cameras[c][0]), CHOSEN_FIRST
        return max(cameras, key=lambda c: cameras[c][1]), CHOSEN_CURRENT

    def _run_shown(self, now: float) -> str:
        """(Under the lock, after the BY_RUN series were pulled.) The bridge run the truth shows
        (:meth:`_pull_by_run`: the one a command names, else the one shown while its truth keeps
        coming, else the newest state's), so that the twin's own camera follows the same twin: by
        the newest state alone it flipped between two twins once a campaign ended, as the truth had."""
        followed, by_command = self._followed_run(now)
        if by_command:
            return followed
        for series, last in self._last_run.items():
            runs = self._by_run.get(series, {})
            if last in runs and now - runs[last][0] <= RUN_FOLLOW_MAX_AGE_S:
                return last
        return followed

    def _followed_run(self, now: float) -> tuple[str, bool]:
        """(Under the lock.) The bridge run the newest command answers, else the newest state's,
        each if received within :data:`RUN_FOLLOW_MAX_AGE_S` ('' if none), and whether a command
        named it."""
        for series in ("command", "state"):
            payload, received = self._raw.get(series), self._received_s.get(series)
            if payload is None or received is None or now - received > RUN_FOLLOW_MAX_AGE_S:
                continue
            msg = self._decode(series, payload)
            if isinstance(msg, (bus.ForceCommand, bus.MotorState)):
                return msg.epoch, series == "command"
        return "", False

    def put(self, series: str, msg: bus.BusMessage) -> None:
        self.put_raw(series, bus.encode(msg))

    def _decode(self, series: str, payload: bytes) -> bus.BusMessage | None:
        cached = self._decoded.get(series)
        if cached is not None and cached[0] is payload:
            return cached[1]
        try:
            msg: bus.BusMessage | None = bus.decode(SERIES[series][0], payload)
            check = self.checks.get(series)
            if check is not None:
                check(msg)
        except bus.BusDecodeError:
            msg = None
            self.rejected += 1
        self._decoded[series] = (payload, msg)
        return msg

    def get(self, series: str) -> Any:
        with self._lock:
            self._pull()
            payload = self._raw.get(series)
        return None if payload is None else self._decode_locked(series, payload)

    def latest_valid(self, series: str) -> tuple[float, bus.BusMessage] | None:
        """(age in seconds on the monotonic clock, message) of the newest payload of ``series`` that
        decoded, or None if none did yet. Takes the ring's newest sample first (of this series
        only). A payload that does not decode (garbage on the key) leaves the last valid one and
        its age as they were: it says nothing about the sender being alive."""
        with self._lock:
            self._pull(series)
            payload, received = self._raw.get(series), self._received_s.get(series)
            if payload is not None and received is not None:
                msg = self._decode(series, payload)
                if msg is not None and received > self._valid.get(series, (-math.inf,))[0]:
                    self._valid[series] = (received, msg)
            valid = self._valid.get(series)
        return None if valid is None else (time.monotonic() - valid[0], valid[1])

    def age_s(self, series: str) -> float:
        """Seconds since ``series`` last received a payload (monotonic clock); inf if never."""
        with self._lock:
            self._pull()
            received = self._received_s.get(series)
        return math.inf if received is None else time.monotonic() - received

    def _decode_locked(self, series: str, payload: bytes) -> bus.BusMessage | None:
        with self._lock:
            return self._decode(series, payload)

    def _within(self, series: str, max_age_s: float, now: float) -> bool:
        """(Under the lock.) Whether ``series``' latest payload arrived within ``max_age_s`` of ``now``."""
        received = self._received_s.get(series)
        return received is not None and now - received <= max_age_s

    def snapshot(self, max_age_s: Mapping[str, float] | None = None) -> tuple[int, dict[str, bus.BusMessage]]:
        """(version, the latest message of every series that decodes); ``max_age_s``: series ->
        age (s) beyond which that series is left out, as :meth:`fresh` would answer None."""
        with self._lock:
            return self._snapshot(max_age_s)

    def live_series(self, max_age_s: Mapping[str, float] | None = None) -> tuple[int, dict[str, dict[str, Any]]]:
        """(version, the ``series`` part of a live frame): :func:`frame_of` of a :meth:`snapshot`,
        the camera's entry naming the camera it is of, taken in the same read."""
        with self._lock:
            version, latest = self._snapshot(max_age_s)
            named = {series: (self._named.get(series, ""), self._camera_chosen.get(series, CHOSEN_FIRST))
                     for series in BY_CAMERA if series in latest}
        return version, frame_of(latest, named)

    def _snapshot(self, max_age_s: Mapping[str, float] | None) -> tuple[int, dict[str, bus.BusMessage]]:
        """(Under the lock.) :meth:`snapshot`."""
        self._pull()
        now = time.monotonic()
        version, raw = self._version, dict(self._raw)
        out = {}
        for series, payload in raw.items():
            if max_age_s is not None and series in max_age_s and not self._within(series, max_age_s[series], now):
                continue
            msg = self._decode(series, payload)
            if msg is not None:
                out[series] = msg
        return version, out

    def version(self) -> int:
        with self._lock:
            self._pull()
            return self._version

    def fresh(self, series: str, max_age_s: float) -> Any:
        """The latest message of ``series`` if it arrived within ``max_age_s`` and decodes, else None."""
        with self._lock:
            self._pull()
            if not self._within(series, max_age_s, time.monotonic()):
                return None
        return self.get(series)


def fresh_camera(values: LatestValues) -> bus.CameraAlpha | None:
    """The latest α_IP message while the camera is fresh (it arrived within
    :data:`CAMERA_MAX_AGE_S` and is valid), else None. The one freshness rule of the camera:
    ``/api/camera``'s and the health's ``fresh``, the live frames' ``camera`` (:data:`LIVE_MAX_AGE_S`)
    and the 3D view's α_IP ghost."""
    return values.fresh("camera", CAMERA_MAX_AGE_S)


def bridge_estop(values: LatestValues, max_age_s: float = BRIDGE_STATE_MAX_AGE_S) -> dict[str, Any] | None:
    """The e-stop as the bridge reports it in its latest ``MotorState`` (``{"engaged", "reason",
    "drive", "source": "bridge"}``), or None when no bridge state arrived within ``max_age_s``.
    ``engaged`` is the bridge's latched e-stop; ``drive == "disabled"`` without it (a bridge
    stopping) also keeps campaigns from starting, with its own reason."""
    state = values.fresh("state", max_age_s)
    if state is None:
        return None
    engaged, reason = drive_estop(state)
    return {"engaged": engaged, "reason": reason, "drive": state.drive, "source": "bridge"}


def bus_campaign(live: LiveBus, max_age_s: float = BRIDGE_STATE_MAX_AGE_S) -> tuple[str, str] | None:
    """``(campaign id, controller)`` of the campaign a controller on the bus runs now, whoever
    started it, as its latest live ``ControllerStatus`` (arrived within ``max_age_s`` s, never a
    replay's: :meth:`LiveBus.live_statuses`) says: the status of the instance the bridge obeys in
    its fresh ``MotorState`` (``owner``: the one whose commands move the robot) if it names one,
    else another controller's; ``controller`` is the status's sender (its attachment,
    :func:`bridge.session.controller_of`), else that owner, "" if unknown. With a second, idle
    controller on the bus the newest status of either had been taken (session 40). None when no
    fresh live status names a campaign. A replay's
    statuses had made the console show a replayed campaign running on the controller that owned
    the bridge, refuse new campaigns and write so in its record (audit of 2026-11-29)."""
    running = {name: st for name, st in live.live_statuses(max_age_s).items() if st.campaign_id}
    if not running:
        return None
    state = live.values.fresh("state", max_age_s)
    owner = state.owner if state is not None else ""
    # the bridge's owner's first (the controller whose commands move the robot), then the others'
    name = owner if owner in running else "" if "" in running else sorted(running)[0]
    return running[name].campaign_id, name or owner


def bus_settled(live: LiveBus) -> bool:
    """Whether this console's bus can tell if a controller runs a campaign (:func:`bus_campaign`):
    the bridge's fresh state obeys no controller (``owner`` "", so none drives one), or the
    controller it obeys has been heard (its live status arrived since the start; a status naming
    no controller, from an older one, counts too); with no fresh state, any controller heard.
    Before, a controller that has not linked back to a restarted console looks like none
    (:meth:`server.campaigns.CampaignManager._await_bus`), and a second, idle controller heard
    first is not the one that may run it (review of session 40)."""
    state = live.values.fresh("state", BRIDGE_STATE_MAX_AGE_S)
    if state is None:
        return live.heard_status()
    return not state.owner or live.heard_from(state.owner) or live.heard_from("")


def bridge_status(values: LatestValues) -> dict[str, Any]:
    """The bridge as its latest valid ``MotorState`` shows it, for ``/api/system/health``:
    ``state_age_s``, seconds since that state arrived (monotonic clock, to within
    :data:`STATE_SAMPLE_PERIOD_S`; None before any state), so a silent bridge shows an age that
    grows; ``drive`` (active, hold, inactive, disabled), ``hold_reason`` (why it holds, "" unless
    ``drive == "hold"``), ``owner`` (the controller instance it obeys, "" for none) and
    ``instance`` (the bridge's), as of that state. All None before any."""
    latest = values.latest_valid("state")
    if latest is None:
        return {"state_age_s": None, "drive": None, "hold_reason": None, "owner": None, "instance": None}
    age_s, state = latest[0], cast(bus.MotorState, latest[1])  # SERIES["state"] decodes MotorState only
    return {"state_age_s": round(age_s, 3), "drive": state.drive, "hold_reason": state.hold_reason,
            "owner": state.owner, "instance": state.bridge}


def frame_of(values: dict[str, bus.BusMessage], instances: Mapping[str, tuple[str, str]] | None = None) -> dict[str, Any]:
    """The ``series`` part of a live frame from the latest messages; a camera's entry names its
    camera and why it is the one followed, ``instance`` and ``chosen``: ``instances``' (series ->
    (name, why), :meth:`LatestValues.live_series`), ('', :data:`CHOSEN_FIRST`) if none (module
    docstring). The name is cut to :data:`INSTANCE_MAX_CHARS`, an ellipsis ending one cut."""
    out: dict[str, Any] = {}
    for name, msg in values.items():
        fields = SERIES[name][1]
        out[name] = {f: getattr(msg, f) for f in fields}
        if name in BY_CAMERA:
            instance, chosen = (instances or {}).get(name, ("", CHOSEN_FIRST))
            if len(instance) > INSTANCE_MAX_CHARS:
                instance = instance[:INSTANCE_MAX_CHARS - 1] + "…"
            out[name]["instance"], out[name]["chosen"] = instance, chosen
    return out


class LiveBus:
    """Subscribes to the live series on a session and keeps only the newest message of each, in a
    one-slot ring per series read on demand (the bridge's state: the newest live one of a ring of
    :data:`BY_RUN_RING_SAMPLES`, behind a replay's); the ``VIEW_ONLY`` ones while a viewer watches
    (module docstring)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.values = LatestValues()
        self._session = session
        self._lock = threading.Lock()
        self._closed = False
        self._subs: dict[str, Any] = {}
        for name in SERIES:
            if name not in VIEW_ONLY:
                self._subscribe(name)
        self.values.on_watched(self._watched)
        # The controller's own word on what it runs (server.campaigns, unrecorded campaigns): the view's
        # "status" series shows a replay's statuses too. The newest kept as it comes (500 a second),
        # copied and decoded only when asked.
        # controller instance (its attachment, "" for none) -> (newest status, time.monotonic()):
        # a second controller's statuses must not hide the one the bridge obeys (session 40)
        self._live_status: dict[str, tuple[zenoh.Sample, float]] = {}
        self._status_lock = threading.Lock()  # Zenoh may call _on_status on several threads at once
        self._status_sub = session.declare_subscriber(bus.CONTROLLER_STATUS, self._on_status)
        # The bridge's state is taken off its ring every STATE_SAMPLE_PERIOD_S s (one sample, one
        # decode: 10 per second, not the bus's 500), so its age is right whoever reads it and when.
        self._stop_sampling = threading.Event()
        #: Called with each state sampled (the same object again while no newer came), on the
        #: sampler's thread: server.bridge_transitions for the safety journal. It must not block.
        self.on_state: Callable[[bus.MotorState], None] | None = None
        self._on_state_failed = False  # logged once
        self._sampler = threading.Thread(target=self._sample_state, name="live-state-sampler", daemon=True)
        self._sampler.start()

    def _on_status(self, sample: zenoh.Sample) -> None:
        if replayed(sample) or len(sample.payload) > bus.max_payload_bytes(bus.ControllerStatus):
            return
        name, statuses = controller_of(sample), self._live_status
        with self._status_lock:
            if name not in statuses and len(statuses) >= STATUS_MAX_CONTROLLERS:  # a flood of forged names
                statuses.pop(min(statuses, key=lambda k: statuses[k][1]))
            statuses[name] = (sample, time.monotonic())

    def heard_status(self) -> bool:
        """Whether a controller's live ``ControllerStatus`` (not a replay's) arrived since this
        console started: its bus has linked to a controller."""
        return bool(self._live_status)

    def heard_from(self, controller: str) -> bool:
        """Whether a live status of ``controller`` ("" : one naming none) arrived since this
        console started (kept while it is among the newest :data:`STATUS_MAX_CONTROLLERS`)."""
        with self._status_lock:
            return controller in self._live_status

    def live_statuses(self, max_age_s: float) -> dict[str, bus.ControllerStatus]:
        """Controller instance ("" for a status naming none) -> its newest ``ControllerStatus``
        (not a replay's) that arrived within ``max_age_s`` s and decodes."""
        now, out = time.monotonic(), {}
        with self._status_lock:
            latest = list(self._live_status.items())
        for name, (sample, at) in latest:
            if now - at <= max_age_s:
                with contextlib.suppress(bus.BusDecodeError):
                    out[name] = bus.decode(bus.ControllerStatus, sample.payload.to_bytes())
        return out

    def live_status(self, max_age_s: float) -> bus.ControllerStatus | None:
        """The newest ``ControllerStatus`` any controller published (not a replay), if it arrived
        within ``max_age_s`` s and decodes; else None."""
        with self._status_lock:
            latest = max(self._live_status.values(), key=lambda v: v[1], default=None)
        if latest is None or time.monotonic() - latest[1] > max_age_s:
            return None
        try:
            return bus.decode(bus.ControllerStatus, latest[0].payload.to_bytes())
        except bus.BusDecodeError:
            return None

    def _sample_state(self) -> None:
        while not self._stop_sampling.wait(STATE_SAMPLE_PERIOD_S):
            latest = self.values.latest_valid("state")
            hook = self.on_state
            if hook is None or latest is None:
                continue
            try:
                hook(cast(bus.MotorState, latest[1]))  # SERIES["state"] decodes MotorState only
            except Exception as exc:  # noqa: BLE001 - a failing hook must not stop the sampling (the state's age)
                if not self._on_state_failed:  # once: it runs 10 times a second
                    self._on_state_failed = True
                    log.error("the bridge state's hook failed (%s: %s): the safety journal misses transitions",
                              type(exc).__name__, exc)

    def _subscribe(self, name: str) -> None:
        ring = BY_RUN_RING_SAMPLES if name in BY_RUN or name in BY_CAMERA or name == "state" else 1
        sub = self._session.declare_subscriber(SERIES[name][0], zenoh.handlers.RingChannel(ring))
        self._subs[name] = sub
        if name == "state":  # the bridge's word (e-stop, drives, freshness): never a replayed state
            self.values.add_source(name, lambda: _newest_live(sub.try_recv, ring))
        else:
            self.values.add_source(name, sub.try_recv, by_run=name in BY_RUN, by_camera=name in BY_CAMERA)

    def _watched(self, watching: bool) -> None:
        with self._lock:
            if self._closed:
                return
            for name in sorted(VIEW_ONLY):
                if watching and name not in self._subs:
                    self._subscribe(name)
                elif not watching and name in self._subs:
                    self.values.remove_source(name)
                    with contextlib.suppress(Exception):
                        self._subs.pop(name).undeclare()

    def close(self) -> None:
        self._stop_sampling.set()
        self._sampler.join(5.0)
        with contextlib.suppress(Exception):
            self._status_sub.undeclare()
        with self._lock:
            self._closed = True
            subs, self._subs = list(self._subs.values()), {}
        for sub in subs:
            with contextlib.suppress(Exception):
                sub.undeclare()


def _newest_by(try_recv: Callable[[], Any], key: Callable[[Any], _K]) -> dict[_K, Any]:
    """The newest sample of each ``key(sample)`` among a ring's (at most :data:`BY_RUN_RING_SAMPLES`
    read; a closed subscriber has none)."""
    newest: dict[_K, Any] = {}
    for _ in range(BY_RUN_RING_SAMPLES):
        try:
            sample = try_recv()
        except Exception:  # noqa: BLE001 - a closed subscriber: nothing new, ever
            break
        if sample is None:
            break
        newest[key(sample)] = sample
    return newest


def _prefers(prefer: str, run: str, camera: tuple[str, str]) -> bool:
    """Whether ``prefer`` (:attr:`LatestValues.prefer_camera`'s camera) names ``camera``
    (:func:`_camera_key`); a twin's own (:data:`~server.quality.TWIN_CAMERA`): the one of the bridge
    run ``run`` (the one the truth shows, :meth:`LatestValues._run_shown`), any twin's if ''."""
    if not prefer:
        return False
    if prefer != TWIN_CAMERA:
        return camera[0] == prefer
    return not camera[0] and bool(camera[1]) and (camera[1] == run or not run)


def _camera_key(sample: zenoh.Sample) -> tuple[str, str]:
    """The camera an α_IP sample is of (module docstring): (the camera process it names, the bridge
    run it names), each '' if none."""
    return camera_of(sample), run_of(sample)


def _newest_live(try_recv: Callable[[], Any], limit: int) -> Any:
    """The newest sample of a ring (at most ``limit`` read) that no replay republished
    (bridge.session.REPLAYED); None if none is. A ring of one had lost the live state whenever a
    replayed one was newest when it was read, and a run of such reads made the bridge look silent
    (the health fell back to the console's e-stop: fresh-clone CI of session 39)."""
    newest = None
    for _ in range(limit):
        sample = try_recv()
        if sample is None:
            break
        if not replayed(sample):
            newest = sample
    return newest


@dataclass(eq=False)
class Client:
    """One browser connection: a bounded queue of encoded frames (newest kept)."""

    queue: asyncio.Queue[bytes] = field(default_factory=lambda: asyncio.Queue(CLIENT_QUEUE_FRAMES))
    dropped: int = 0

    def offer(self, frame: bytes) -> None:
        """Enqueue without ever waiting: on a full queue the oldest frame goes."""
        while True:
            try:
                self.queue.put_nowait(frame)
                return
            except asyncio.QueueFull:
                with contextlib.suppress(asyncio.QueueEmpty):
                    self.queue.get_nowait()
                    self.dropped += 1


class LiveFull(Exception):
    """:data:`LIVE_MAX_CLIENTS` are connected: the message says so, for the one refused."""


class Broadcaster:
    """Sends a frame to every connected client at ``rate_hz`` when something changed (runs on the
    server's event loop; :meth:`run` is its task)."""

    def __init__(self, values: LatestValues, rate_hz: float) -> None:
        self.values = values
        self.period_s = 1.0 / rate_hz
        self.clients: set[Client] = set()
        self.max_clients = LIVE_MAX_CLIENTS
        self.frames_sent = 0
        self._encoder = msgspec.json.Encoder()
        self._watched = asyncio.Event()  # set while a client is connected

    def full(self) -> bool:
        """Whether :data:`LIVE_MAX_CLIENTS` are connected (a new one would be refused)."""
        return len(self.clients) >= self.max_clients

    def connect(self) -> Client:
        """A new client; :class:`LiveFull` when :meth:`full`."""
        if self.full():
            raise LiveFull(f"the console serves at most {self.max_clients} live clients at once: close another view")
        client = Client()
        self.clients.add(client)
        self._watched.set()
        self.values.watch("browsers", True)
        # A new client gets the current state at once, not after the next change.
        _, latest = self.values.live_series(LIVE_MAX_AGE_S)
        if latest:
            client.offer(self._encode(latest))
        return client

    def disconnect(self, client: Client) -> None:
        self.clients.discard(client)
        if not self.clients:
            self._watched.clear()
            self.values.watch("browsers", False)

    def _encode(self, series: dict[str, dict[str, Any]]) -> bytes:
        self.frames_sent += 1
        return self._encoder.encode({"type": "live", "seq": self.frames_sent, "wall_s": time.time(),
                                     "series": series})

    async def run(self) -> None:
        last_version = -1
        next_t = time.monotonic()
        while True:
            if not self.clients:
                await self._watched.wait()  # nobody watches: no read, no decode, no wake-up
                next_t = time.monotonic()
            next_t += self.period_s
            version, latest = self.values.live_series(LIVE_MAX_AGE_S)
            if version != last_version and self.clients and latest:
                last_version = version
                frame = self._encode(latest)
                for client in list(self.clients):
                    client.offer(frame)
            delay = next_t - time.monotonic()
            if delay < 0:  # fell behind (loaded machine): skip, do not burst
                next_t = time.monotonic()
                delay = 0
            await asyncio.sleep(delay)
