"""The controller as a bus process (`xneck controller`): motor state in, force command out.

Each new ``MotorState`` triggers one tick of the law (:class:`controller.laws.ComputedTorque`):
α̂ from the encoders, α^d from the trajectory at the state's time stamp, forces from the
distribution; then a ``ForceCommand`` and a ``ControllerStatus`` (tick period, compute time,
overruns, deadline misses, saturation, α̂, α^d, e). With the bridge or the real-time twin that is
500 Hz; with the lockstep twin it is as fast as both go.

Safety: it commands the hold forces (Z f = g(α̂) with every cable at t_min, or at the last sane
α̂) and says why in the status when
- no valid state arrived for ``stale_s`` (10 ms; malformed or NaN states are rejected by the
  subscriber, so they count as missing) — it resumes when states come back;
- the estimate diverges (non-finite, or beyond the joint limit plus a margin) — latched: the
  campaign is aborted with the reason.
Time: the trajectory runs on the states' stamps (the twin's simulated time or the bridge's
clock), from the start of the campaign. The neck must be straight when the controller starts
(eq. 20's zero: θ = 0 there).

Two ways to run: with ``--trajectory`` it runs that one campaign and exits; without, it is a
service (what `xneck up` starts): it holds the neck where it is and runs the campaigns asked for
on ``xneck/campaign/request``, one at a time, approaching each trajectory's first waypoint
gently and continuing the estimate across laws.

This module is only the bus shell: the campaign life cycle, the holds and the law live in the pure
state machine :class:`controller.service.CampaignService`.
"""

from __future__ import annotations

import gc
import logging
import math
import queue
import sys
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np
import zenoh

from bridge import bus
from bridge.session import liveliness_token, publisher, subscribe_latest
from controller.laws import LawConfig
from controller.service import CampaignService, Output
from controller.trajectory import Trajectory
from twin.model.params import Params

log = logging.getLogger("xneck.controller")

LOCKSTEP_RESEND_S = 0.1  # s without a new state before the last command is sent again


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


class ControllerNode:
    """The bus shell around :class:`controller.service.CampaignService`: states and requests in,
    commands, status and campaign events out (module docstring)."""

    def __init__(self, session: zenoh.Session, params: Params, law: LawConfig, trajectory: Trajectory | None,
                 config: ControllerProcessConfig):
        self.config = config
        # Service mode: no trajectory of its own; campaigns come as requests on the bus.
        self._service = trajectory is None and not config.exit_when_done
        self.service = CampaignService(params, law, service=self._service, settle_s=config.settle_s,
                                       campaign_id=config.campaign_id or f"c-{uuid.uuid4().hex[:8]}",
                                       kind=config.campaign_kind)
        self._own_trajectory = trajectory
        n_motors = self.service.ctl.model.n_cables
        self.instance = config.instance or f"controller-{uuid.uuid4().hex[:6]}"

        def check_state(msg: bus.MotorState) -> None:
            if len(msg.theta_rad) != n_motors:
                raise bus.BusDecodeError(f"MotorState: {len(msg.theta_rad)} angles for {n_motors} motors")

        self.states = subscribe_latest(session, bus.MOTOR_STATE, validate=check_state)
        self._cmd = publisher(session, bus.MOTOR_COMMAND)
        self._status = publisher(session, bus.CONTROLLER_STATUS)
        self._events = publisher(session, bus.CAMPAIGN_EVENTS)
        self._token = liveliness_token(session, "controller", self.instance)
        self._seq = {"cmd": 0, "status": 0, "event": 0}
        self._last_cmd: bus.ForceCommand | None = None
        self._requests: queue.Queue[bus.CampaignRequest] = queue.Queue(maxsize=16)
        self._request_sub = session.declare_subscriber(bus.CAMPAIGN_REQUEST, self._on_request) if self._service else None
        self._service_token = liveliness_token(session, "campaign-service", self.instance) if self._service else None

    @property
    def outcome(self) -> str:
        return self.service.outcome

    def _next(self, name: str) -> int:
        self._seq[name] += 1
        return self._seq[name]

    # -- bus out ------------------------------------------------------------------------------
    def publish_events(self) -> None:
        for ev in self.service.drain_events():
            self._events.put(bus.CampaignEvent(seq=self._next("event"), stamp_s=time.time(), campaign_id=ev.campaign_id,
                                               kind=ev.kind, event=ev.event, progress=ev.progress, message=ev.message))

    def command(self, f: np.ndarray, stamp_s: float) -> None:
        state = self.states.latest()  # the bridge run it answers (issue 13: the bridge refuses other epochs)
        self._last_cmd = bus.ForceCommand(seq=self._next("cmd"), stamp_s=stamp_s, force_N=f.tolist(),
                                          source=self.service.law.name, sender=self.instance,
                                          epoch=state.epoch if state is not None else "")
        self._cmd.put(self._last_cmd)

    def hold(self, reason: str, stamp_s: float) -> None:
        if reason != self.service.hold_reason:
            log.warning("holding: %s", reason)
        self.command(self.service.hold(reason).force_N, stamp_s)

    def status(self, stamp_s: float, tick_s: float, compute_s: float, out: Output) -> None:
        svc = self.service
        self._status.put(bus.ControllerStatus(
            seq=self._next("status"), stamp_s=stamp_s, law=svc.law.name, tick_s=tick_s, compute_s=compute_s,
            overruns=svc.overruns, deadline_misses=svc.deadline_misses, saturated=[bool(s) for s in out.saturated],
            alpha_hat_rad=[float(a) if math.isfinite(a) else 0.0 for a in out.alpha_hat_rad],
            alpha_d_rad=list(map(float, out.alpha_d_rad)),
            e_rad=[float(x) if math.isfinite(x) else 0.0 for x in out.e_rad],
            holding=bool(svc.hold_reason), hold_reason=svc.hold_reason))

    # -- bus in -------------------------------------------------------------------------------
    def _on_request(self, sample: zenoh.Sample) -> None:
        try:
            self._requests.put_nowait(bus.decode(bus.CampaignRequest, sample.payload.to_bytes()))
        except (bus.BusDecodeError, queue.Full) as exc:
            log.warning("campaign request rejected: %s", getattr(exc, "reason", exc))

    def _serve_requests(self, state: bus.MotorState) -> None:
        """Service mode: start or stop campaigns asked for on the bus (between two ticks)."""
        while True:
            try:
                req = self._requests.get_nowait()
            except queue.Empty:
                return
            self.service.handle(req, state.stamp_s)
            for ev in self.service.events:
                if ev.event == "aborted" and ev.campaign_id == req.campaign_id and req.action == "start":
                    log.warning("campaign %s: %s", req.campaign_id, ev.message)

    # -- the loop -----------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> str:
        """Run until the trajectory is done (then "finished"), the estimate diverges ("aborted"),
        the states stop for good ("aborted") or ``stop`` is set ("stopped"). In service mode
        (``exit_when_done`` False) it holds between campaigns and serves campaign requests."""
        cfg, svc = self.config, self.service
        svc.warm_up()
        # Everything allocated so far lives for the whole run: keep the collector off it, so a
        # full collection cannot land in the middle of a 2 ms tick.
        gc.collect()
        gc.freeze()
        # Zenoh's callback threads share the GIL with this loop: hand it over every 0.5 ms rather
        # than every 5 ms, so a state waiting in a callback is not held up for a whole period.
        sys.setswitchinterval(0.0005)
        first = self.states.wait(cfg.startup_timeout_s)
        if first is None:
            svc.outcome = "aborted"
            svc.refuse(svc.campaign_id, svc.kind, f"no motor state within {cfg.startup_timeout_s} s of start")
            self.publish_events()
            return svc.outcome
        svc.initialise(np.asarray(first.theta_rad))
        if self._own_trajectory is not None:
            svc.begin(self._own_trajectory, first.stamp_s)
        # A state is new when its stamp is: a waiting lockstep twin re-publishes the same state.
        last_stamp, last_wall = None, time.perf_counter()
        state = first
        try:
            while not stop.is_set():
                self.publish_events()
                if last_stamp is not None:
                    state = self.states.wait(LOCKSTEP_RESEND_S if cfg.lockstep else cfg.stale_s,
                                             lambda s: s.stamp_s > last_stamp)
                    if state is None or state.stamp_s <= last_stamp:
                        stale_for = time.perf_counter() - last_wall
                        if stale_for > cfg.idle_timeout_s and cfg.exit_when_done:
                            svc.outcome = "aborted"
                            svc.refuse(svc.campaign_id, svc.kind, f"no motor state for {stale_for:.1f} s")
                            return svc.outcome
                        if cfg.lockstep:
                            # The bus may drop a message: resend the same command (same seq, so a twin
                            # that already stepped on it ignores it) instead of stalling.
                            if self._last_cmd is not None:
                                self._cmd.put(self._last_cmd)
                        elif self._last_cmd is not None:
                            self.hold(f"stale state: none for {stale_for * 1e3:.0f} ms", time.time())
                        continue
                wall = time.perf_counter()
                tick_s, last_wall, last_stamp = wall - last_wall, wall, state.stamp_s
                if self._service:
                    self._serve_requests(state)
                if svc.outcome in ("aborted", "finished") and cfg.exit_when_done:
                    return svc.outcome
                if not self._tick(state, wall, tick_s) and cfg.exit_when_done:
                    return svc.outcome
                if not svc.running and svc.outcome == "finished" and cfg.exit_when_done:
                    return svc.outcome
            return svc.outcome or "stopped"
        finally:
            self.publish_events()

    def _tick(self, state: bus.MotorState, wall: float, tick_s: float) -> bool:
        """One law tick on ``state``; False when the campaign had to be aborted."""
        svc = self.service
        period = 1.0 / svc.law.rate_hz
        was_latched, reason_before = svc.latched, svc.hold_reason
        out = svc.control(np.asarray(state.theta_rad), state.stamp_s)
        if not out.law_ran:
            if svc.hold_reason != reason_before:
                log.warning("holding: %s", svc.hold_reason)
            self.command(out.force_N, state.stamp_s)
            return was_latched
        self.command(out.force_N, state.stamp_s)
        compute_s = time.perf_counter() - wall
        # A deadline miss: the command left more than one period after its state arrived.
        missed = not self.config.lockstep and time.time_ns() - self.states.latest_with_time()[1] > period * 1e9
        svc.count_timing(compute_s > period, missed)
        self.status(state.stamp_s, tick_s, compute_s, out)
        svc.advance(state.stamp_s)
        return True

    def close(self) -> None:
        closers = [self.states.close, self._cmd.close, self._status.close, self._events.close, self._token.undeclare]
        if self._service:
            closers += [self._request_sub.undeclare, self._service_token.undeclare]
        for closer in closers:
            try:
                closer()
            except Exception:  # noqa: BLE001
                pass
