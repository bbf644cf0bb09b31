"""The controller as a bus process (`xneck controller`): motor state in, force command out.

Each new ``MotorState`` triggers one tick of the law (:class:`controller.laws.ComputedTorque`):
α̂ from the encoders, α^d from the trajectory at the state's time stamp, forces from the
distribution; then a ``ForceCommand`` and a ``ControllerStatus`` (tick period, compute time,
overruns, deadline misses, saturation, α̂, α^d, e). With the bridge or the real-time twin that is
500 Hz; with the lockstep twin it is as fast as both go.

Safety: it commands the hold forces (Z f = g(α̂) with every cable at t_min, or at the last sane
α̂) and says why in the status when
- no valid state arrived for ``stale_s`` (10 ms; malformed, NaN, forged or foreign states are
  rejected by the subscriber, so they count as missing) — the law re-starts when states come back;
- the bridge's drives are not active (e-stop, not yet enabled, the bridge's watchdog hold) — α̂
  follows the encoders, nothing winds up, and the law re-starts bumplessly when they are;
- the estimate diverges (non-finite, or beyond the joint limit plus a margin) — latched: the
  campaign is aborted with the reason.
Time and identity: the trajectory runs on the states' stamps (the twin's simulated time or the
bridge's clock), from the start of the campaign. Only states of the bridge run the controller is
bound to are taken, with stamps that neither go back nor run ahead of its own clock
(:class:`controller.state_gate.StateGate`); a restarted bridge (new epoch) is taken at once and
the estimate starts again from it. Every command, holds included, carries the stamp and epoch of
the state it answers and this controller's instance (the bridge obeys one owner). The neck must
be straight when the bridge starts (eq. 20's zero: θ = 0 there).
Untrusted input: campaign requests are bounded when decoded, prepared (parsed, validated within a
time budget) by a worker thread while the loop keeps commanding, and refused with the reason as
an ``aborted`` event; rejections are counted on ``xneck/health/controller/<instance>``.

Two ways to run: with ``--trajectory`` it runs that one campaign and exits; without, it is a
service (what `xneck up` starts): it holds the neck where it is and runs the campaigns asked for
on ``xneck/campaign/request`` or addressed to it (``.../request/<instance>``, as the console
sends them), one at a time, approaching each trajectory's first waypoint
gently and continuing the estimate across laws.

This module is only the bus shell: the campaign life cycle, the holds and the law live in the pure
state machine :class:`controller.service.CampaignService`.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import gc
import logging
import math
import os
import queue
import sys
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np
import zenoh

from bridge import bus
from bridge.log_limit import LogLimit
from bridge.runtime import SystemdNotify, arrange_thread, take_loop_priority
from bridge.session import controller_attachment, liveliness_token, payload_of, publisher, subscribe_latest
from controller.laws import LawConfig
from controller.prepare import GivenUp, Prepared, Refused, prepare, start_pose_when_known
from controller.service import CampaignService, Output
from controller.state_gate import StateGate
from controller.timing import TickTimes, timing_message
from controller.trajectory import Trajectory
from twin.model.params import Params

log = logging.getLogger("xneck.controller")

LOCKSTEP_RESEND_S = 0.1  # s without a new state before the last command is sent again
LAG_FLOOR_RELAX_NS = 2_000  # ns per state the floor of arrival − stamp lets up (clock drift up to 1 ms/s)
# Start requests waiting for the loop, per key (the bare one, this service's own): a flood on one
# key is rejected beyond this, and cannot crowd out the other key's requests, nor any stop.
REQUEST_QUEUE = 16


def below_the_tick() -> None:
    """This thread one real-time priority below the tick's, when it has one (`xneck up` gives the
    controller's threads SCHED_FIFO, :mod:`server.child_processes`). The tick runs on Zenoh's
    threads; this process's own threads (the loop's housekeeping, the campaign preparation) at
    the same FIFO priority on the same CPU would keep a state's tick waiting until they block
    (FIFO does not share a CPU between equals), and a waiting tick cannot even ask them for the
    GIL. One below, the tick preempts them and gets the GIL within the switch interval."""
    tid = threading.get_native_id()
    arrange_thread(-1)  # and one below a real-time priority the process takes later
    with contextlib.suppress(AttributeError, OSError):  # not Linux, or not allowed: carry on as is
        if os.sched_getscheduler(tid) == os.SCHED_FIFO:
            prio = os.sched_getparam(tid).sched_priority
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(max(prio - 1, 1)))


def _finite_list(x: np.ndarray) -> list[float]:
    """``x`` as plain floats, a non-finite one as 0.0 (the status must encode). ``tolist`` and one
    pass of ``math.isfinite``: a quarter of the per-element numpy scalars' cost, at 500 Hz."""
    v = x.tolist()
    return v if all(map(math.isfinite, v)) else [a if math.isfinite(a) else 0.0 for a in v]


@dataclass(frozen=True)
class ControllerProcessConfig:
    campaign_id: str = ""
    campaign_kind: str = "control"
    settle_s: float = 1.0  # hold at the last waypoint this long before "finished"
    stale_s: float = 0.010  # real time: no new state for this long -> hold
    lockstep: bool = False
    idle_timeout_s: float = 10.0  # no new state for this long once running -> give up (twin gone)
    startup_timeout_s: float = 120.0  # for the first state: peers may still be starting
    exit_when_done: bool = True
    instance: str = ""
    skew_s: float = 0.05  # how far a state's stamp may run ahead of the controller's clock
    health_period_s: float = 1.0


class ControllerNode:
    """The bus shell around :class:`controller.service.CampaignService`: states and requests in,
    commands, status, health and campaign events out (module docstring)."""

    def __init__(self, session: zenoh.Session, params: Params, law: LawConfig, trajectory: Trajectory | None,
                 config: ControllerProcessConfig):
        self.config = config
        # Service mode: no trajectory of its own; campaigns come as requests on the bus.
        self._service = trajectory is None and not config.exit_when_done
        self.service = CampaignService(params, law, service=self._service, settle_s=config.settle_s,
                                       campaign_id=config.campaign_id or f"c-{uuid.uuid4().hex[:8]}",
                                       kind=config.campaign_kind)
        self._robot, self._own_trajectory = params, trajectory
        n_motors, f_max = self.service.ctl.model.n_cables, float(params.limits.f_max)
        self.instance = config.instance or f"controller-{uuid.uuid4().hex[:6]}"
        self.gate = StateGate(skew_s=config.skew_s, rate_hz=None if config.lockstep else law.rate_hz)
        self._gate_lock = threading.Lock()

        def check_state(msg: bus.MotorState) -> None:
            # Zenoh's callback thread: a state that fails here never becomes the latest one, so a
            # forged or foreign state cannot stand in for the bridge's (counted with its reason).
            bus.check_motor_state(msg, n_motors, f_max)
            with self._gate_lock:
                reason = self.gate.admit(msg, time.monotonic())
                if self.gate.stepped_s is not None:
                    self._clock_step = self.gate.stepped_s  # for the tick on this state (_on_state)
            if reason:
                raise bus.BusDecodeError(reason)

        # The tick runs in the subscriber's callback, on Zenoh's network thread (:meth:`_on_state`);
        # the lock keeps it and this process's loop thread (holds, requests) apart.
        self._tick_lock = threading.Lock()
        self._ticked = threading.Event()
        self._live = self._done = False
        self._error: Exception | None = None
        self._last_key: tuple[str, float] = ("", -math.inf)
        self._clock_step: float | None = None  # s the bound run's clock stepped (StateGate.stepped_s)
        self._last_wall = 0.0
        self._state: bus.MotorState | None = None
        self.times = TickTimes()
        self._timed_id = ""  # the campaign whose ticks the timing histograms hold
        self._lag_floor, self._floor_epoch, self._last_done_ns = 0.0, "", 0  # see _stale_in_burst
        self.states = subscribe_latest(session, bus.MOTOR_STATE, validate=check_state, on_message=self._on_state,
                                       direct=True)
        self._cmd = publisher(session, bus.MOTOR_COMMAND, block=config.lockstep)
        self._status = publisher(session, bus.CONTROLLER_STATUS, block=config.lockstep)
        self._named = controller_attachment(self.instance)  # its statuses name it (server.live.bus_campaign)
        self._timing = publisher(session, bus.CONTROLLER_TIMING)
        # A campaign's final timing, once per campaign, is what its archive and quality keep: it
        # waits out congestion as its end event does; a periodic window may drop (CI of 2026-12-02).
        self._timing_final = publisher(session, bus.CONTROLLER_TIMING, block=True)
        self._events = publisher(session, bus.CAMPAIGN_EVENTS)
        self._health = publisher(session, bus.health_key("controller", self.instance))
        self._token = liveliness_token(session, "controller", self.instance)
        self._seq = {"cmd": 0, "status": 0, "event": 0, "health": 0, "timing": 0}
        self._last_cmd: bus.ForceCommand | None = None
        self._started = time.monotonic()
        # Requests: decoded and bounded in the callback, prepared by a worker thread (parsing and
        # validating a trajectory may take seconds), started by the loop between two ticks.
        self._req_lock = threading.Lock()
        self.requests_received = self.requests_rejected = self._states_rejected_seen = 0
        self._rejects_logged = LogLimit(1.0)
        self.last_reject = ""  # the latest reason a state or a request was rejected
        # Start requests wait for the loop in one queue per key, as (arrival number, request): a
        # flood on the bare key (any peer may put there) cannot crowd out the console's requests
        # addressed to this service (audit of 2026-11-30: ~70 000 starts/s on the bare key, and the
        # console's one stop was rejected "too many requests waiting", its campaign never ended).
        self._arrivals = 0
        self._starts: dict[bool, collections.deque[tuple[int, bus.CampaignRequest]]] = {
            False: collections.deque(), True: collections.deque()}  # by "addressed to this service"
        # Stops never queue behind starts: the latest arrival number of a stop per campaign id,
        # kept only for an id a stop can concern (:meth:`_stop_may_matter`), so at most a few.
        self._stops: dict[str, int] = {}
        self._stoppable: frozenset[str] = frozenset()  # ids the service may stop (set by the loop)
        self.preparations_skipped = 0  # start requests stopped or superseded before the worker came to them
        self.preparations_cut = 0  # ... or while it prepared them (given up at a look at the budget)
        self._to_prepare: queue.Queue[bus.CampaignRequest | None] = queue.Queue(maxsize=4)
        self._prepared: queue.Queue[tuple[bus.CampaignRequest, Prepared | Refused]] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._systemd: SystemdNotify | None = None  # run()'s watchdog, pinged by both threads (_ping)
        self._next_ping = 0.0
        if self._service:
            self._worker = threading.Thread(target=self._prepare_forever, name="campaign-prepare", daemon=True)
            self._worker.start()
        # Bare requests (any service) and those addressed to this one; never a peer's (audit of 2026-11-28).
        self._request_subs = [session.declare_subscriber(key, functools.partial(self._on_request, addressed=addressed))
                              for key, addressed in ((bus.CAMPAIGN_REQUEST, False),
                                                     (bus.campaign_request_key(self.instance), True))
                              ] if self._service else []
        self._service_token = liveliness_token(session, "campaign-service", self.instance) if self._service else None

    @property
    def outcome(self) -> str:
        return self.service.outcome

    def _next(self, name: str) -> int:
        self._seq[name] += 1
        return self._seq[name]

    # -- bus out ------------------------------------------------------------------------------
    def publish_events(self) -> None:
        """The service's campaign events (a campaign that ended gets its final timing first);
        drained under the tick lock, published outside it (the events key may block)."""
        with self._tick_lock:
            events = self.service.drain_events()
            if self.service.running:
                self._timed_id = self.service.campaign_id
        for ev in events:
            if ev.event in ("finished", "aborted") and ev.campaign_id == self._timed_id:
                self.publish_timing(time.time(), (ev.campaign_id, ev.ticks, ev.deadline_misses, ev.overruns))
                self._timed_id = ""
                self.times.reset_campaign()
            self._events.put(bus.CampaignEvent(
                seq=self._next("event"), stamp_s=time.time(), campaign_id=ev.campaign_id, kind=ev.kind,
                event=ev.event, progress=ev.progress, message=ev.message, ticks=ev.ticks, overruns=ev.overruns,
                deadline_misses=ev.deadline_misses))

    def _encode_command(self, f: np.ndarray, state: bus.MotorState) -> bytes:
        """Forces answering ``state``: its stamp and epoch, so every command is on the bridge's
        clock (holds included) and a command for a previous bridge run is refused by the bridge."""
        self._last_cmd = bus.ForceCommand(seq=self._next("cmd"), stamp_s=state.stamp_s, force_N=f.tolist(),
                                          source=self.service.law.name, sender=self.instance, epoch=state.epoch)
        return bus.encode(self._last_cmd)

    def command(self, f: np.ndarray, state: bus.MotorState) -> None:
        """:meth:`_encode_command`, published."""
        self._cmd.put_bytes(self._encode_command(f, state))

    def publish_timing(self, stamp_s: float, ended: tuple[str, int, int, int] | None = None) -> None:
        """The ticks since the last call as a ``ControllerTiming``: stages, latency and period, and
        the campaign's histograms; ``ended`` = (id, ticks, misses, overruns) of a campaign that
        just ended (its final figures), else the running campaign's so far."""
        final = ended is not None  # waits out congestion (the final publisher's comment)
        with self._tick_lock:
            stages, period = self.times.window()
            svc = self.service
            if ended is None:
                ended = (svc.campaign_id if svc.running else "", svc.ticks, svc.deadline_misses, svc.overruns)
        campaign_id, ticks, misses, overruns = ended
        (self._timing_final if final else self._timing).put(timing_message(
            self._next("timing"), stamp_s, campaign_id, stages, period, self.times, ticks, misses, overruns))

    def status(self, stamp_s: float, tick_s: float, compute_s: float, out: Output) -> None:
        svc = self.service
        self._status.put(bus.ControllerStatus(
            seq=self._next("status"), stamp_s=stamp_s, law=svc.law.name, tick_s=tick_s, compute_s=compute_s,
            overruns=svc.overruns, deadline_misses=svc.deadline_misses, saturated=out.saturated.tolist(),
            alpha_hat_rad=_finite_list(out.alpha_hat_rad), alpha_d_rad=out.alpha_d_rad.tolist(),
            e_rad=_finite_list(out.e_rad),
            holding=not out.law_ran, hold_reason="" if out.law_ran else svc.hold_reason,
            campaign_id=svc.campaign_id if svc.running else "", ticks=svc.ticks), attachment=self._named)

    def publish_health(self, stamp_s: float) -> None:
        """Counters on ``xneck/health/controller/<instance>``: states and requests received and
        rejected, and the latest reason (a forged state, a malformed request...)."""
        states = self.states.stats
        with self._req_lock:
            received, rejected = self.requests_received, self.requests_rejected
            if states.rejected > self._states_rejected_seen:
                self.last_reject = states.last_reject_reason
            self._states_rejected_seen = states.rejected
            reason = self.last_reject
        self._health.put(bus.Health(
            seq=self._next("health"), stamp_s=stamp_s, process="controller", instance=self.instance,
            uptime_s=time.monotonic() - self._started,
            received={bus.MOTOR_STATE: states.received, bus.CAMPAIGN_REQUEST: received, "ticks": self._seq["status"]},
            rejected={bus.MOTOR_STATE: states.rejected, bus.CAMPAIGN_REQUEST: rejected},
            last_reject_reason=reason))

    # -- bus in -------------------------------------------------------------------------------
    def _reject_request(self, reason: str) -> None:
        with self._req_lock:
            self.requests_rejected += 1
            self.last_reject = f"{bus.CAMPAIGN_REQUEST}: {reason}"
        # A flood must not turn into a flood of log lines (CPU the loop needs): at most one
        # line a second, with how many were rejected since; Health has every count.
        if (held := self._rejects_logged.allow()) is not None:
            log.warning("campaign request rejected: %s%s", reason, LogLimit.tail(held))

    def _on_request(self, sample: zenoh.Sample, addressed: bool) -> None:
        """A campaign request on the bare key or, ``addressed``, on this service's own: a start
        waits in that key's queue (rejected when it is full), a stop is kept aside for the loop,
        where no start can crowd it out (module docstring of :mod:`controller.process`)."""
        # Zenoh's callback thread: bounded work only, and nothing may escape (a raise here would
        # be a stack trace in Zenoh's thread, and a flood of them a dead service).
        try:
            with self._req_lock:
                self.requests_received += 1
            req = bus.decode(bus.CampaignRequest, payload_of(sample, bus.CampaignRequest))
            with self._req_lock:
                self._arrivals += 1
                if req.action == "stop":
                    if self._stop_may_matter(req.campaign_id):
                        self._stops[req.campaign_id] = self._arrivals
                    return
                starts = self._starts[addressed]
                full = len(starts) >= REQUEST_QUEUE
                if not full:
                    starts.append((self._arrivals, req))
            if full:
                self._reject_request("too many requests waiting" + ("" if addressed else " on the bare key"))
        except bus.BusDecodeError as exc:
            self._reject_request(exc.reason)
        except Exception as exc:  # noqa: BLE001 - see above
            self._reject_request(f"{type(exc).__name__}: {exc}")

    def _stop_may_matter(self, campaign_id: str) -> bool:
        """Whether a stop of ``campaign_id`` may stop anything (under the request lock): a campaign
        the service runs, prepares or holds waiting, as the loop last saw it, or a start waiting
        in a queue. Any other stop changes nothing (:meth:`CampaignService.stop`), and a flood of
        them is not kept: what is kept is bounded by those ids."""
        return campaign_id in self._stoppable or any(
            r.campaign_id == campaign_id for starts in self._starts.values() for _, r in starts)

    def _prepare_forever(self) -> None:
        """Worker thread: parse and validate start requests off the 500 Hz loop (within the
        service's time budget), hand the result to the loop. A request no longer wanted (stopped,
        or superseded by a later one) is not prepared, or given up at the preparation's next look
        at its budget: the loop would drop its result anyway, and preparing it held the GIL for
        seconds (audit of 2026-11-30: 20 start/stop pairs of a big request while idle, the bridge
        held 13 % of its states and a campaign asked for 9 s later waited behind them)."""
        below_the_tick()
        while True:
            req = self._to_prepare.get()
            if req is None:
                return
            # One attribute read of the service's, without the tick lock: at worst a loop turn late.
            wanted = functools.partial(self.service.wants, req)
            if not wanted():
                with self._req_lock:
                    self.preparations_skipped += 1
                continue
            try:
                start_from = start_pose_when_known(self.service.start_pose, wanted)
                result: Prepared | Refused = prepare(req, self._robot, self.service.law, wanted=wanted,
                                                      alpha_from_rad=start_from)
            except GivenUp:
                with self._req_lock:
                    self.preparations_cut += 1
                log.info("campaign %s: its preparation given up (stopped or superseded meanwhile)", req.campaign_id)
                continue
            except Refused as exc:
                result = exc
            except Exception as exc:  # noqa: BLE001 - prepare refuses everything: a backstop
                result = Refused(f"refused: {type(exc).__name__}: {exc}")
            self._prepared.put((req, result))

    def _serve_requests(self, stamp_s: float) -> None:
        """Service mode, between two ticks (under the tick lock): prepared campaigns started, then
        the requests that arrived since the last turn in the order they arrived, stops at once,
        starts to the worker."""
        svc = self.service
        while True:
            try:
                req, result = self._prepared.get_nowait()
            except queue.Empty:
                break
            if isinstance(result, Refused):
                log.warning("campaign %s: %s", req.campaign_id, result.reason)
                self._reject_request(f"{req.campaign_id}: {result.reason}")
            svc.prepared(result, req, stamp_s)
        with self._req_lock:
            starts = [*self._starts[False], *self._starts[True]]
            for waiting in self._starts.values():
                waiting.clear()
            stops, self._stops = self._stops, {}
            # Until the service has seen them, a stop of these may matter too.
            self._stoppable |= {r.campaign_id for _, r in starts}
        # In the order they arrived: a stop stops the start of its id before it, not one after
        # (an id may be asked again once stopped).
        todo: list[tuple[int, bus.CampaignRequest | str]] = [*starts, *((n, cid) for cid, n in stops.items())]
        for _, req in sorted(todo, key=lambda item: item[0]):
            if isinstance(req, str):
                svc.stop(req, stamp_s)
                continue
            duplicates = svc.duplicate_starts
            if svc.request_start(req):
                try:
                    self._to_prepare.put_nowait(req)
                except queue.Full:
                    svc.prepared(Refused("refused: the controller is busy preparing other campaigns"), req, stamp_s)
            elif svc.duplicate_starts > duplicates:  # ignored, not answered: counted in Health
                self._reject_request(f"{req.campaign_id}: a start of a campaign already running, being prepared or "
                                     "waiting: ignored (the request delivered twice, or re-published)")
        stoppable = svc.stoppable()  # what a stop may concern from now on (the tick keeps it a superset)
        with self._req_lock:
            self._stoppable = stoppable

    # -- the loop -----------------------------------------------------------------------------
    def run(self, stop: threading.Event, systemd: SystemdNotify | None = None) -> str:
        """Run until the trajectory is done (then "finished"), the estimate diverges ("aborted"),
        the states stop for good ("aborted") or ``stop`` is set ("stopped"). In service mode
        (``exit_when_done`` False) it holds between campaigns and serves campaign requests.
        ``systemd``: its watchdog is pinged every ``ping_period_s`` (``WATCHDOG=1``) by this thread
        (also while it waits for the first state) and by the ticks, whichever runs: ``xneck up``
        stands in for systemd and takes a controller silent on both (SIGSTOP, a deadlock on the
        tick's lock) for a dead one (server/cli/up.py). Either alone would not do: a console that
        hangs holds this thread up to 5 s in a blocking put (docs/safety.md, "Peers that stop
        reading"), and the ticks stop with the bridge's states.

        Each new state is answered in the subscriber's callback itself (:meth:`_on_state`): no
        queue, no thread hand-over and no polling between its arrival and the command. This
        thread does the rest, between ticks: holds on stale states, lockstep re-sends, campaign
        requests, events, health and timing."""
        below_the_tick()
        self.service.warm_up()  # numba's caches, LAPACK: before a real-time priority asked for
        if why := take_loop_priority():  # the supervisor's (bridge.runtime), this thread one below
            log.warning("real-time loop: %s", why)
        # Everything allocated so far lives for the whole run: keep the collector off it, so a
        # full collection cannot land in the middle of a 2 ms tick.
        gc.collect()
        gc.freeze()
        # Zenoh's network thread needs the GIL to run the tick: this thread hands it over every
        # 0.5 ms rather than every 5 ms when it is busy (it mostly sleeps).
        sys.setswitchinterval(0.0005)
        self._systemd, self._next_ping = systemd, 0.0
        try:
            return self._loop(stop)
        finally:
            with self._tick_lock:
                self._live = False  # no command after run() returned
                self._systemd = None  # nor a ping: the caller closes its socket
            self.publish_events()
            if self._worker is not None:
                with contextlib.suppress(queue.Full):
                    self._to_prepare.put_nowait(None)

    def _loop(self, stop: threading.Event) -> str:
        cfg, svc = self.config, self.service
        # In slices, so that a stop (SIGTERM, its supervisor gone) while waiting for the bridge is
        # honoured at once, not after the whole start-up timeout (audit of 2026-11-26).
        deadline, first = time.monotonic() + cfg.startup_timeout_s, None
        while first is None and not stop.is_set() and time.monotonic() < deadline:
            self._ping()
            first = self.states.wait(min(0.1, max(0.0, deadline - time.monotonic())), lambda _state: True)
        if first is None and stop.is_set():
            return "stopped"
        if first is None:
            svc.outcome = "aborted"
            svc.refuse(svc.campaign_id, svc.kind, f"no motor state within {cfg.startup_timeout_s} s of start")
            return svc.outcome
        with self._tick_lock:
            svc.initialise(np.asarray(first.theta_rad), np.asarray(first.force_applied_N))
            if self._own_trajectory is not None:
                svc.begin_own(self._own_trajectory, first.stamp_s)
            self._last_key, self._last_wall = (first.epoch, first.stamp_s), time.perf_counter()
            self._state = first
            self._clock_step = None  # a step seen while waiting for the first state is no step of this run
            if self._service:
                self._serve_requests(first.stamp_s)
            received_ns = self.states.latest_with_time()[1]  # monotonic: the wall clock's arrival time
            arrival_ns = time.time_ns() - (time.monotonic_ns() - received_ns if received_ns else 0)
            self._stale_in_burst(first, arrival_ns)  # the floor of arrival − stamp starts with it
            self._react(first, arrival_ns, time.time_ns(), 0.0)
            self._live = True
        next_health = time.monotonic()
        wait_s = LOCKSTEP_RESEND_S if cfg.lockstep else cfg.stale_s
        timeout_s = wait_s
        while not stop.is_set():
            self._ping()
            self.publish_events()
            if time.monotonic() >= next_health:
                self.publish_health(self._state.stamp_s)
                self.publish_timing(self._state.stamp_s)
                next_health = time.monotonic() + cfg.health_period_s
            # Woken early only when the run is over: ticks do not wake this thread (it would
            # compete with the next one for the GIL), it looks at the time of the last one.
            self._ticked.wait(timeout_s)
            self._ticked.clear()
            with self._tick_lock:
                if self._error is not None:
                    raise self._error
                if self._done:
                    return svc.outcome
                if self._service:
                    self._serve_requests(self._state.stamp_s)
                stale_for = time.perf_counter() - self._last_wall
                timeout_s = max(wait_s - stale_for, 0.001) if stale_for < wait_s else wait_s
                if stale_for < wait_s:
                    continue
                if stale_for > cfg.idle_timeout_s and cfg.exit_when_done:
                    svc.outcome = "aborted"
                    svc.refuse(svc.campaign_id, svc.kind, f"no motor state for {stale_for:.1f} s")
                    self._done = True
                    return svc.outcome
                if cfg.lockstep:
                    # The bus may drop a message: resend the same command (same seq, so a twin
                    # that already stepped on it ignores it) instead of stalling.
                    if self._last_cmd is not None:
                        self._cmd.put(self._last_cmd)
                elif self._last_cmd is not None:
                    if not svc.hold_reason.startswith("stale state"):
                        log.warning("holding: stale state")
                    # On the last state's clock and epoch: one clock on the command key.
                    out = svc.stale(f"stale state: none for {stale_for * 1e3:.0f} ms", stale_for)
                    self.command(out.force_N, self._state)
        return svc.outcome or "stopped"

    def _ping(self) -> None:
        """The watchdog's ping when it is due (:meth:`run`; from either thread, whose race costs at
        most one ping more); a few ns otherwise."""
        if self._systemd is not None and time.monotonic() >= self._next_ping:
            self._systemd.ping()
            self._next_ping = time.monotonic() + self._systemd.ping_period_s

    def _on_state(self, state: bus.MotorState, arrival_ns: int) -> None:
        """Zenoh's callback, for each state the gate took: the tick, at once. Nothing escapes
        (an error is handed to the loop, which raises it: the process ends, the bridge holds)."""
        decoded_ns = time.time_ns()
        self._ping()  # before the lock: a tick that cannot take it pings no more (run)
        try:
            with self._tick_lock:
                if not self._live or self._done:
                    return
                key = (state.epoch, state.stamp_s)
                if key == self._last_key:  # a waiting lockstep twin re-publishes the same state
                    return
                if self._stale_in_burst(state, arrival_ns):
                    return
                step_s, self._clock_step = self._clock_step, None
                if state.epoch != self._last_key[0]:
                    log.warning("bridge %s restarted (epoch %s): re-initialising from its state", state.bridge,
                                state.epoch)
                    self.service.new_bridge_run(np.asarray(state.theta_rad), state.stamp_s, state.bridge,
                                                np.asarray(state.force_applied_N))
                elif step_s is not None:
                    log.warning("the clock of bridge %s stepped by %+.3g s", state.bridge, step_s)
                    self.service.clock_stepped(step_s, state.stamp_s)
                wall = time.perf_counter()
                tick_s, self._last_wall, self._last_key, self._state = wall - self._last_wall, wall, key, state
                self._react(state, arrival_ns, decoded_ns, tick_s)
        except Exception as exc:  # noqa: BLE001 - see the docstring
            self._error, self._done = exc, True
        if self._done:
            self._ticked.set()

    def _stale_in_burst(self, state: bus.MotorState, arrival_ns: int) -> bool:
        """Whether ``state`` is a stale one of a burst, not to be answered: after this process was
        held up (a loaded machine), Zenoh delivers the states that queued meanwhile back to back,
        and answering each would put the loop further behind. A state is stale when it arrives more
        than a period later, relative to its stamp, than the best state of this bridge run did
        (the floor of arrival − stamp, let up slowly so the clocks may drift); it is in a burst
        when it arrives within a quarter period of the end of the last tick. The first state after
        the hold-up is answered (what the bridge waits for), the stale rest skipped (counted),
        the next fresh one answered. Not in lockstep, where stamps are not on the wall clock."""
        if self.config.lockstep:
            return False
        period_ns = 1e9 / self.service.law.rate_hz
        lag = arrival_ns - state.stamp_s * 1e9
        if state.epoch != self._floor_epoch:
            self._lag_floor, self._floor_epoch = lag, state.epoch
        else:
            self._lag_floor = min(lag, self._lag_floor + LAG_FLOOR_RELAX_NS)
        if lag - self._lag_floor > period_ns and arrival_ns - self._last_done_ns < period_ns / 4:
            self.times.skipped += 1
            return True
        return False

    def _react(self, state: bus.MotorState, arrival_ns: int, decoded_ns: int, tick_s: float) -> None:
        """One tick on ``state`` (under the tick lock), and whether the run is over."""
        cfg, svc = self.config, self.service
        if svc.outcome in ("aborted", "finished") and cfg.exit_when_done:
            self._done = True
            return
        if not self._tick(state, arrival_ns, decoded_ns, tick_s) and cfg.exit_when_done:
            self._done = True
        if not svc.running and svc.outcome == "finished" and cfg.exit_when_done:
            self._done = True

    def _tick(self, state: bus.MotorState, arrival_ns: int, decoded_ns: int, tick_s: float) -> bool:
        """One tick on ``state``; False when the campaign had to be aborted by a diverging estimate."""
        svc = self.service
        period_ns = 1e9 / svc.law.rate_hz
        was_latched, reason_before = svc.latched, svc.hold_reason
        svc.drive_reason = state.estop_reason if state.drive == "disabled" else state.hold_reason
        obeyed = not state.owner or state.owner == self.instance
        if not obeyed:
            svc.drive_reason = f"the bridge obeys controller {state.owner}, not this one"
        out = svc.control(np.asarray(state.theta_rad), state.stamp_s, state.drive, np.asarray(state.force_applied_N),
                          obeyed)
        law_ns = time.time_ns()
        data = self._encode_command(out.force_N, state)
        encoded_ns = time.time_ns()
        self._cmd.put_bytes(data)
        put_ns = time.time_ns()
        if not out.law_ran and svc.hold_reason.split(":")[0] != reason_before.split(":")[0]:
            log.warning("holding: %s", svc.hold_reason)
        latency_ns = self.times.record(arrival_ns, decoded_ns, law_ns, encoded_ns, put_ns)
        self._last_done_ns = put_ns
        compute_s = (law_ns - decoded_ns) * 1e-9
        # A deadline miss: the command left more than one period after its state arrived.
        missed = not self.config.lockstep and latency_ns > period_ns
        svc.count_timing(compute_s * 1e9 > period_ns, missed)
        self.status(state.stamp_s, tick_s, compute_s, out)
        if out.law_ran:
            svc.advance(state.stamp_s)
        return not (svc.latched and not was_latched)

    def close(self) -> None:
        closers = [self.states.close, self._cmd.close, self._status.close, self._events.close, self._health.close,
                   self._timing.close, self._timing_final.close, self._token.undeclare]
        closers += [x.undeclare for x in (*self._request_subs, self._service_token) if x is not None]
        for closer in closers:
            with contextlib.suppress(Exception):  # the session may already be gone
                closer()
        if self._worker is not None:
            with contextlib.suppress(queue.Full):
                self._to_prepare.put_nowait(None)
