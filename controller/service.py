"""The controller's campaign service as a pure state machine: no bus, no clock, no threads.

:class:`controller.process.ControllerNode` is the shell around it: it turns bus messages into
calls of :class:`CampaignService` and the answers back into bus messages. Everything that decides
what the neck does lives here, so it is tested without Zenoh (tests/test_controller_service.py).

Life cycle of one campaign::

    idle --request--> starting --prepared--> running --trajectory + settle_s--> finished
                         |                      |--estimate diverges / stop request--> aborted
                         '--refused-----------> aborted (with the reason)

``finished`` and ``aborted`` are idle again for the next request. Between campaigns the law holds
the neck at ``hold_target`` (the last waypoint, or where it was when the service started).

Holds: :meth:`CampaignService.hold` commands Z f = g(α) with every cable at t_min
(:func:`controller.laws.hold_forces`) at α̂, or at the last sane α̂ when the estimate is not
(non-finite or beyond the joint limits). A diverging estimate latches the hold until the next
campaign starts.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np

from bridge import bus
from controller.laws import ComputedTorque, LawConfig, hold_forces, nominal_force_check
from controller.trajectory import Trajectory, TrajectoryError, TrajectoryLimits, approach, validate
from twin.model.params import Params, params_from_dict

DIVERGENCE_MARGIN = math.radians(20.0)  # rad beyond the joint limit that counts as diverging
PROGRESS_PERIOD_S = 0.5  # s of campaign time between two progress events

Phase = Literal["idle", "starting", "running", "finished", "aborted"]


@dataclass(frozen=True)
class Event:
    """A campaign event for the shell to publish (a :class:`bridge.bus.CampaignEvent`)."""

    campaign_id: str
    kind: str
    event: bus.CampaignEventKind
    progress: float = 0.0
    message: str = ""


class Output(NamedTuple):
    """What to command for one state, and what to report in the status."""

    force_N: np.ndarray  # (n_cables,) N
    alpha_hat_rad: np.ndarray  # (N,)
    alpha_d_rad: np.ndarray  # (N,)
    e_rad: np.ndarray  # (N,)
    saturated: np.ndarray  # (n_cables,) bool
    law_ran: bool  # False for a hold (no status is published for it)


@dataclass(frozen=True)
class Prepared:
    """A campaign request turned into what the service runs: parameters, law and a validated
    trajectory (before the approach from the present pose is prepended)."""

    campaign_id: str
    kind: str
    params: Params
    law: LawConfig
    trajectory: Trajectory


class Refused(Exception):
    """A campaign request the service will not run; ``reason`` says why."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def prepare(req: bus.CampaignRequest, robot: Params, law: LawConfig) -> Prepared:
    """Parse and validate a start request against the robot's parameter set ``robot``; ``law``
    gives the gains and rate kept from the process's own law. Raises :class:`Refused`."""
    try:
        params = robot
        if req.parameters_toml:
            params = params_from_dict(tomllib.loads(req.parameters_toml), f"campaign {req.campaign_id}")
            if (params.n_joints, params.n_cables) != (robot.n_joints, robot.n_cables):
                raise ValueError(f"parameter set {params.name!r} is for {params.n_joints} joints and "
                                 f"{params.n_cables} cables, the robot has {robot.n_joints} and {robot.n_cables}")
        new_law = LawConfig(law=req.law, no_pulleys=req.no_pulleys, omega=law.omega, rate_hz=law.rate_hz)
        traj = Trajectory.from_dict(json.loads(req.trajectory_json))
        validate(traj, TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg)),
                 params.n_joints, nominal_force_check(params, new_law))
    except (ValueError, TrajectoryError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise Refused(f"refused: {exc}") from None
    return Prepared(req.campaign_id, req.kind, params, new_law, traj)


@dataclass
class CampaignService:
    """The campaign life cycle and the law around one robot (module docstring).

    ``service``: campaigns come as requests (``xneck controller`` without ``--trajectory``); else
    the one campaign given to :meth:`begin` is the process's whole job. ``settle_s``: hold at the
    last waypoint this long before ``finished``.
    """

    params: Params
    law: LawConfig
    service: bool = True
    settle_s: float = 1.0
    campaign_id: str = ""
    kind: str = "control"
    phase: Phase = "idle"
    outcome: str = ""
    hold_reason: str = ""
    latched: bool = False
    overruns: int = 0
    deadline_misses: int = 0
    trajectory: Trajectory | None = None
    events: list[Event] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.ctl = ComputedTorque(self.params, self.law)
        n_joints = self.ctl.model.n_joints
        self.last_sane = np.zeros(n_joints)
        self.hold_target = np.zeros(n_joints)
        self._t0, self._total, self._next_progress = 0.0, math.inf, 0.0
        self._limit = math.radians(self.params.limits.alpha_max_deg) + DIVERGENCE_MARGIN

    # -- outputs to the shell -----------------------------------------------------------------
    def drain_events(self) -> list[Event]:
        out, self.events = self.events, []
        return out

    def _event(self, event: bus.CampaignEventKind, progress: float = 0.0, message: str = "") -> None:
        self.events.append(Event(self.campaign_id, self.kind, event, progress, message))

    @property
    def running(self) -> bool:
        return self.trajectory is not None

    # -- start-up -----------------------------------------------------------------------------
    def warm_up(self) -> None:
        """One throw-away tick so the first real one does not pay for first calls (LAPACK, caches)."""
        z = np.zeros(self.ctl.model.n_joints)
        self.ctl.step(np.zeros(self.ctl.model.n_cables), z, z, z)

    def initialise(self, theta_rad: np.ndarray) -> None:
        """The first state: the estimate starts from the encoders (the neck straight, eq. 20's zero)."""
        self.ctl.reset(theta=np.asarray(theta_rad, dtype=float))

    # -- campaigns ----------------------------------------------------------------------------
    def begin(self, trajectory: Trajectory, stamp_s: float) -> None:
        """Run ``trajectory`` from ``stamp_s`` (the states' clock) on."""
        self.trajectory = trajectory
        self.phase = "running"
        self._t0 = stamp_s
        self._total = trajectory.duration_s + self.settle_s
        self._next_progress = 0.0
        self.outcome = ""
        self.latched = False
        self._event("started", message=f"{self.law.name}, trajectory {trajectory.name}")

    def _end(self, outcome: Literal["finished", "aborted"], message: str, progress: float, hold_at: np.ndarray) -> None:
        self.outcome = outcome
        self.phase = outcome
        self._event(outcome, progress, message)
        self.trajectory = None
        self.hold_target = np.array(hold_at, dtype=float)

    def _progress(self, stamp_s: float) -> float:
        return min((stamp_s - self._t0) / self._total, 1.0)

    def stop(self, campaign_id: str, stamp_s: float) -> None:
        """A stop request: aborts the running campaign if it is ``campaign_id``."""
        if self.running and campaign_id == self.campaign_id:
            self._end("aborted", "stopped by the user", self._progress(stamp_s), self.ctl.estimator.alpha_hat)

    def refuse(self, campaign_id: str, kind: str, message: str) -> None:
        """Answer a request the service will not run with an ``aborted`` event of its id."""
        self.events.append(Event(campaign_id, kind, "aborted", 0.0, message))

    def busy_reason(self) -> str:
        """Why a new campaign cannot start now ("" if it can)."""
        return f"the controller is running campaign {self.campaign_id}" if self.running else ""

    def start(self, prepared: Prepared, stamp_s: float) -> None:
        """Start a prepared campaign, approaching its first waypoint gently from α̂."""
        busy = self.busy_reason()
        if busy:
            self.refuse(prepared.campaign_id, prepared.kind, busy)
            return
        self.params = prepared.params
        self._switch_law(prepared.law)
        self.campaign_id, self.kind = prepared.campaign_id, prepared.kind
        self.begin(approach(prepared.trajectory, self.ctl.estimator.alpha_hat), stamp_s)

    def handle(self, req: bus.CampaignRequest, stamp_s: float) -> None:
        """A campaign request, prepared here and now (between two ticks)."""
        if req.action == "stop":
            self.stop(req.campaign_id, stamp_s)
            return
        busy = self.busy_reason()
        if busy:
            self.refuse(req.campaign_id, req.kind, busy)
            return
        try:
            prepared = prepare(req, self.params, self.law)
        except Refused as exc:
            self.refuse(req.campaign_id, req.kind, exc.reason)
            return
        self.start(prepared, stamp_s)

    def _switch_law(self, law: LawConfig) -> None:
        """A new law continues from the current estimate (α̂, θ and, when both models are
        elastic, the predicted stretch), with a fresh integral."""
        old, old_ctl = self.ctl.estimator, self.ctl
        ctl = ComputedTorque(self.params, law)
        ctl.reset(alpha=old.alpha_hat, theta=old.theta)
        if ctl.model.cable_model == old_ctl.model.cable_model:
            ctl.estimator.x_c = old.x_c.copy()
        ctl.theta_dot = old_ctl.theta_dot.copy()
        self.ctl, self.law = ctl, law
        self._limit = math.radians(self.params.limits.alpha_max_deg) + DIVERGENCE_MARGIN

    # -- one tick -----------------------------------------------------------------------------
    def hold_alpha(self) -> np.ndarray:
        """α̂, or the last sane α̂ when the estimate is not (non-finite or beyond the joint limits)."""
        alpha = self.ctl.estimator.alpha_hat
        if not np.all(np.isfinite(alpha)) or np.any(np.abs(alpha) > math.radians(self.params.limits.alpha_max_deg)):
            return self.last_sane
        return alpha

    def hold(self, reason: str) -> Output:
        """The forces that hold the neck still where it is (module docstring), with ``reason``."""
        self.hold_reason = reason
        alpha = self.hold_alpha()
        f = hold_forces(self.params, alpha)
        zeros = np.zeros_like(alpha)
        return Output(f, alpha, alpha, zeros, np.zeros(len(f), dtype=bool), False)

    def reference(self, stamp_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """α^d, α̇^d, α̈^d at ``stamp_s``: the campaign's trajectory, or the hold target."""
        if self.trajectory is not None:
            ref = self.trajectory.sample(np.array([stamp_s - self._t0]))
            return ref.alpha[0], ref.alpha_dot[0], ref.alpha_ddot[0]
        z = np.zeros_like(self.hold_target)
        return self.hold_target, z, z

    def control(self, theta_rad: np.ndarray, stamp_s: float) -> Output:
        """One law tick on a new state (encoders θ at ``stamp_s``). A diverging estimate
        (non-finite, or beyond the joint limit plus a margin) latches a hold and aborts the campaign."""
        a_d, a_d_dot, a_d_ddot = self.reference(stamp_s)
        if self.latched:
            return self.hold(self.hold_reason)
        cmd = self.ctl.step(np.asarray(theta_rad), a_d, a_d_dot, a_d_ddot)
        if not np.all(np.isfinite(cmd.alpha_hat)) or np.any(np.abs(cmd.alpha_hat) > self._limit) \
                or not np.all(np.isfinite(cmd.f)):
            self.latched = True
            out = self.hold(f"diverging estimate α̂ = {np.round(np.degrees(cmd.alpha_hat), 1).tolist()}°")
            if self.running or not self.service:
                self._end("aborted", self.hold_reason, self._progress(stamp_s) if self.running else 0.0,
                          self.last_sane)
            return out
        self.last_sane = cmd.alpha_hat.copy()
        self.hold_reason = ""
        return Output(cmd.f, cmd.alpha_hat, a_d, cmd.e, cmd.saturated, True)

    def count_timing(self, overrun: bool, deadline_missed: bool) -> None:
        """The shell's measure of the tick just commanded: compute over the period, command late."""
        self.overruns += int(overrun)
        self.deadline_misses += int(deadline_missed)

    def advance(self, stamp_s: float) -> None:
        """Progress events every 0.5 s of campaign time, ``finished`` after the settle time."""
        if self.trajectory is None:
            return
        t = stamp_s - self._t0
        if t >= self._next_progress:
            self._event("progress", min(t / self._total, 1.0))
            self._next_progress += PROGRESS_PERIOD_S
        if t >= self._total:
            self._end("finished", f"overruns {self.overruns}, deadline misses {self.deadline_misses}", 1.0,
                      self.trajectory.waypoints_rad[-1])
