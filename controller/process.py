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
"""

from __future__ import annotations

import gc
import json
import logging
import math
import queue
import sys
import threading
import time
import tomllib
import uuid
from dataclasses import dataclass

import numpy as np
import zenoh

from bridge import bus
from bridge.session import liveliness_token, publisher, subscribe_latest
from controller.laws import ComputedTorque, LawConfig, hold_forces, nominal_force_check
from controller.trajectory import Trajectory, TrajectoryError, TrajectoryLimits, approach, validate
from twin.model.params import Params, params_from_dict

log = logging.getLogger("xneck.controller")

DIVERGENCE_MARGIN = math.radians(20.0)  # rad beyond the joint limit that counts as diverging
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
    def __init__(self, session: zenoh.Session, params: Params, law: LawConfig, trajectory: Trajectory | None,
                 config: ControllerProcessConfig):
        self.params, self.law, self.trajectory, self.config = params, law, trajectory, config
        self.ctl = ComputedTorque(params, law)
        n_motors = self.ctl.model.n_cables
        self.instance = config.instance or f"controller-{uuid.uuid4().hex[:6]}"
        self.campaign_id = config.campaign_id or f"c-{uuid.uuid4().hex[:8]}"

        def check_state(msg: bus.MotorState) -> None:
            if len(msg.theta_rad) != n_motors:
                raise bus.BusDecodeError(f"MotorState: {len(msg.theta_rad)} angles for {n_motors} motors")

        self.states = subscribe_latest(session, bus.MOTOR_STATE, validate=check_state)
        self._cmd = publisher(session, bus.MOTOR_COMMAND)
        self._status = publisher(session, bus.CONTROLLER_STATUS)
        self._events = publisher(session, bus.CAMPAIGN_EVENTS)
        self._token = liveliness_token(session, "controller", self.instance)
        self._seq = {"cmd": 0, "status": 0, "event": 0}
        self.overruns = self.deadline_misses = 0
        self.hold_reason = ""
        self.latched = False
        self.outcome = ""
        self._last_cmd: bus.ForceCommand | None = None
        self.campaign_kind = config.campaign_kind
        self._t0, self._total, self._next_progress = 0.0, math.inf, 0.0
        # Service mode: no trajectory of its own; campaigns come as requests on the bus.
        self._service = trajectory is None and not config.exit_when_done
        self._requests: queue.Queue[bus.CampaignRequest] = queue.Queue(maxsize=16)
        self._request_sub = session.declare_subscriber(bus.CAMPAIGN_REQUEST, self._on_request) if self._service else None
        self._service_token = liveliness_token(session, "campaign-service", self.instance) if self._service else None

    def _next(self, name: str) -> int:
        self._seq[name] += 1
        return self._seq[name]

    def event(self, event: str, progress: float = 0.0, message: str = "") -> None:
        self._events.put(bus.CampaignEvent(seq=self._next("event"), stamp_s=time.time(), campaign_id=self.campaign_id,
                                           kind=self.campaign_kind, event=event, progress=progress,
                                           message=message))

    def command(self, f: np.ndarray, stamp_s: float) -> None:
        self._last_cmd = bus.ForceCommand(seq=self._next("cmd"), stamp_s=stamp_s, force_N=f.tolist(),
                                          source=self.law.name)
        self._cmd.put(self._last_cmd)

    def hold(self, reason: str, stamp_s: float) -> None:
        if reason != self.hold_reason:
            log.warning("holding: %s", reason)
        self.hold_reason = reason
        alpha = self.ctl.estimator.alpha_hat
        if not np.all(np.isfinite(alpha)) or np.any(np.abs(alpha) > math.radians(self.params.limits.alpha_max_deg)):
            alpha = self._last_sane
        self.command(hold_forces(self.params, alpha), stamp_s)

    def status(self, stamp_s: float, tick_s: float, compute_s: float, sat, alpha_hat, alpha_d, e) -> None:
        self._status.put(bus.ControllerStatus(
            seq=self._next("status"), stamp_s=stamp_s, law=self.law.name, tick_s=tick_s, compute_s=compute_s,
            overruns=self.overruns, deadline_misses=self.deadline_misses, saturated=[bool(s) for s in sat],
            alpha_hat_rad=[float(a) if math.isfinite(a) else 0.0 for a in alpha_hat],
            alpha_d_rad=list(map(float, alpha_d)), e_rad=[float(x) if math.isfinite(x) else 0.0 for x in e],
            holding=bool(self.hold_reason), hold_reason=self.hold_reason))

    # -- campaigns --------------------------------------------------------------------------
    def _begin(self, trajectory: Trajectory, stamp_s: float) -> None:
        self.trajectory = trajectory
        self._t0 = stamp_s
        self._total = trajectory.duration_s + self.config.settle_s
        self._next_progress = 0.0
        self.outcome = ""
        self.latched = False
        self.event("started", message=f"{self.law.name}, trajectory {trajectory.name}")

    def _end(self, outcome: str, message: str, progress: float, hold_at: np.ndarray) -> None:
        self.outcome = outcome
        self.event(outcome, progress, message)
        self.trajectory = None
        self.hold_target = np.array(hold_at, dtype=float)

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
            if req.action == "stop":
                if self.trajectory is not None and req.campaign_id == self.campaign_id:
                    t = state.stamp_s - self._t0
                    self._end("aborted", "stopped by the user", min(t / self._total, 1.0), self.ctl.estimator.alpha_hat)
                continue
            if self.trajectory is not None:
                self._refuse(req, f"the controller is running campaign {self.campaign_id}")
                continue
            try:
                params = self.params
                if req.parameters_toml:
                    params = params_from_dict(tomllib.loads(req.parameters_toml), f"campaign {req.campaign_id}")
                    if (params.n_joints, params.n_cables) != (self.params.n_joints, self.params.n_cables):
                        raise ValueError(f"parameter set {params.name!r} is for {params.n_joints} joints and "
                                         f"{params.n_cables} cables, the robot has {self.params.n_joints} and "
                                         f"{self.params.n_cables}")
                law = LawConfig(law=req.law, no_pulleys=req.no_pulleys, omega=self.law.omega, rate_hz=self.law.rate_hz)
                traj = Trajectory.from_dict(json.loads(req.trajectory_json))
                validate(traj, TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg)),
                         params.n_joints, nominal_force_check(params, law))
            except (ValueError, TrajectoryError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
                self._refuse(req, f"refused: {exc}")
                continue
            self.params = params
            self._switch_law(law)
            self.campaign_id, self.campaign_kind = req.campaign_id, req.kind
            self._begin(approach(traj, self.ctl.estimator.alpha_hat), state.stamp_s)

    def _refuse(self, req: bus.CampaignRequest, message: str) -> None:
        log.warning("campaign %s: %s", req.campaign_id, message)
        self._events.put(bus.CampaignEvent(seq=self._next("event"), stamp_s=time.time(), campaign_id=req.campaign_id,
                                           kind=req.kind, event="aborted", message=message))

    def _switch_law(self, law: LawConfig) -> None:
        """A new law continues from the current estimate (α̂, θ and, when both models are
        elastic, the predicted stretch), with a fresh integral."""
        old = self.ctl.estimator
        ctl = ComputedTorque(self.params, law)
        ctl.reset(alpha=old.alpha_hat, theta=old.theta)
        if ctl.model.cable_model == self.ctl.model.cable_model:
            ctl.estimator.x_c = old.x_c.copy()
        ctl.theta_dot = self.ctl.theta_dot.copy()
        self.ctl, self.law = ctl, law

    # -- the loop -----------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> str:
        """Run until the trajectory is done (then "finished"), the estimate diverges ("aborted"),
        the states stop for good ("aborted") or ``stop`` is set ("stopped"). In service mode
        (``exit_when_done`` False) it holds between campaigns and serves campaign requests."""
        cfg = self.config
        n_joints = self.ctl.model.n_joints
        limit = math.radians(self.params.limits.alpha_max_deg) + DIVERGENCE_MARGIN
        self._last_sane = np.zeros(n_joints)
        self.hold_target = np.zeros(n_joints)
        # One throw-away tick so the first real one does not pay for first calls (LAPACK, caches).
        z = np.zeros(n_joints)
        self.ctl.step(np.zeros(self.ctl.model.n_cables), z, z, z)
        # Everything allocated so far lives for the whole run: keep the collector off it, so a
        # full collection cannot land in the middle of a 2 ms tick.
        gc.collect()
        gc.freeze()
        # Zenoh's callback threads share the GIL with this loop: hand it over every 0.5 ms rather
        # than every 5 ms, so a state waiting in a callback is not held up for a whole period.
        sys.setswitchinterval(0.0005)
        first = self.states.wait(cfg.startup_timeout_s)
        if first is None:
            self.outcome = "aborted"
            self.event("aborted", message=f"no motor state within {cfg.startup_timeout_s} s of start")
            return self.outcome
        self.ctl.reset(theta=np.asarray(first.theta_rad))
        if self.trajectory is not None:
            self._begin(self.trajectory, first.stamp_s)
        # A state is new when its stamp is: a waiting lockstep twin re-publishes the same state.
        last_stamp, last_wall = None, time.perf_counter()
        state = first
        while not stop.is_set():
            if last_stamp is not None:
                state = self.states.wait(LOCKSTEP_RESEND_S if cfg.lockstep else cfg.stale_s,
                                         lambda s: s.stamp_s > last_stamp)
                if state is None or state.stamp_s <= last_stamp:
                    stale_for = time.perf_counter() - last_wall
                    if stale_for > cfg.idle_timeout_s and cfg.exit_when_done:
                        self.outcome = "aborted"
                        self.event("aborted", message=f"no motor state for {stale_for:.1f} s")
                        return self.outcome
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
            if self.outcome in ("aborted", "finished") and cfg.exit_when_done:
                return self.outcome
            if not self._tick(state, wall, tick_s, limit) and cfg.exit_when_done:
                return self.outcome
            if self.trajectory is None and self.outcome == "finished" and cfg.exit_when_done:
                return self.outcome
        return self.outcome or "stopped"

    def _tick(self, state: bus.MotorState, wall: float, tick_s: float, limit: float) -> bool:
        """One law tick on ``state``; False when the campaign had to be aborted."""
        period, n_joints = 1.0 / self.law.rate_hz, self.ctl.model.n_joints
        t = state.stamp_s - self._t0 if self.trajectory is not None else 0.0
        if self.trajectory is not None:
            ref = self.trajectory.sample(np.array([t]))
            a_d, a_d_dot, a_d_ddot = ref.alpha[0], ref.alpha_dot[0], ref.alpha_ddot[0]
        else:
            a_d, a_d_dot, a_d_ddot = self.hold_target, np.zeros(n_joints), np.zeros(n_joints)
        if self.latched:
            self.hold(self.hold_reason, state.stamp_s)
            return True
        cmd = self.ctl.step(np.asarray(state.theta_rad), a_d, a_d_dot, a_d_ddot)
        if not np.all(np.isfinite(cmd.alpha_hat)) or np.any(np.abs(cmd.alpha_hat) > limit) \
                or not np.all(np.isfinite(cmd.f)):
            self.latched = True
            self.hold(f"diverging estimate α̂ = {np.round(np.degrees(cmd.alpha_hat), 1).tolist()}°", state.stamp_s)
            if self.trajectory is not None or not self._service:
                self._end("aborted", self.hold_reason, min(t / self._total, 1.0) if self.trajectory else 0.0,
                          self._last_sane)
            return False
        self._last_sane = cmd.alpha_hat.copy()
        self.hold_reason = ""
        self.command(cmd.f, state.stamp_s)
        compute_s = time.perf_counter() - wall
        if compute_s > period:
            self.overruns += 1
        # A deadline miss: the command left more than one period after its state arrived.
        if not self.config.lockstep and time.time_ns() - self.states.latest_with_time()[1] > period * 1e9:
            self.deadline_misses += 1
        self.status(state.stamp_s, tick_s, compute_s, cmd.saturated, cmd.alpha_hat, a_d, cmd.e)
        if self.trajectory is not None:
            if t >= self._next_progress:
                self.event("progress", min(t / self._total, 1.0))
                self._next_progress += 0.5
            if t >= self._total:
                self._end("finished", f"overruns {self.overruns}, deadline misses {self.deadline_misses}", 1.0,
                          self.trajectory.waypoints_rad[-1])
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
