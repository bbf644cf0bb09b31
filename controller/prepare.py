"""A campaign request turned into what the controller runs, or refused with the reason: the
untrusted input of :class:`controller.service.CampaignService` (JSON text only, bounded waypoint
count and duration, a time budget for the force check), validated off the control loop.
"""

from __future__ import annotations

import dataclasses
import math
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass

import msgspec
import numpy as np

from bridge import bus, toml_text
from controller.laws import LawConfig, nominal_force_check
from controller.trajectory import (
    ForceCheck,
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    approach,
    trajectory_from_json,
    validate,
)
from twin.model.params import Limits, Params, params_from_dict

VALIDATION_BUDGET_S = 8.0  # s a request's validation may take (the console waits 10 s for an answer)
FORCE_CHECK_CHUNK = 256  # samples of the force check between two looks at the budget
#: s a request waits for the pose it would start from while an e-stop's slack is taken up (a
#: take-up lasts a few seconds; one the bridge holds meanwhile waits with it)
START_POSE_WAIT_S = 30.0


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


class GivenUp(Refused):
    """A preparation given up because its request is no longer wanted (stopped, superseded):
    nobody waits for its answer (the stop answered the request)."""


def _budgeted(check: ForceCheck, deadline: float, clock: Callable[[], float],
              wanted: Callable[[], bool] | None = None) -> ForceCheck:
    """``check`` run in chunks, refusing once ``clock()`` passes ``deadline``, and giving up once
    ``wanted()`` says the request is no longer wanted: a validation whose cost grows with the
    trajectory cannot hold the worker (or the GIL) for long, nor for nothing."""

    def run(alpha: np.ndarray, alpha_dot: np.ndarray, alpha_ddot: np.ndarray,
            pretension: np.ndarray) -> tuple[np.ndarray, str]:
        ok = np.ones(len(alpha), dtype=bool)
        for k in range(0, len(alpha), FORCE_CHECK_CHUNK):
            if wanted is not None and not wanted():
                raise GivenUp("given up: the request was stopped or superseded while it was prepared")
            if clock() > deadline:
                raise Refused("refused: the force check did not finish within its time budget; "
                              "ask for a shorter trajectory")
            part = slice(k, k + FORCE_CHECK_CHUNK)
            ok[part], reason = check(alpha[part], alpha_dot[part], alpha_ddot[part], pretension[part])
            if not ok[part].all():
                return ok, reason
        return ok, ""

    return run


def within_robot_limits(params: Params, robot: Params) -> Params:
    """The parameter set ``params`` (a campaign's) with each limit no wider than ``robot``'s (the
    process's ``--params``): alpha_max_deg and f_max no larger, t_min and f_min no smaller. The
    service adopts the campaign's set, its joint limit (the divergence latch, validation) and its
    forces: a set with alpha_max_deg 85 and f_max 400 N had taken the neck to 72° against the
    robot's 60° (audit of 2026-11-29). Taken, not refused: a console whose active set is not the
    robot's file (`xneck up --params` passes it to the bridge and controller only) sends its own
    with every campaign, and a tighter robot file had made every campaign refused (review of
    session 40)."""
    a, b = params.limits, robot.limits
    limits = Limits(t_min=max(a.t_min, b.t_min), f_min=max(a.f_min, b.f_min), f_max=min(a.f_max, b.f_max),
                    alpha_max_deg=min(a.alpha_max_deg, b.alpha_max_deg))
    return params if limits == a else msgspec.structs.replace(params, limits=limits)


def approach_move(traj: Trajectory, alpha_from_rad: np.ndarray,
                  alpha_max_rad: float | tuple[float, ...] | np.ndarray) -> Trajectory | None:
    """The move :func:`controller.trajectory.approach` prepends to ``traj`` from ``alpha_from_rad``
    (clipped to ±``alpha_max_rad``: an estimate a little past the limit is where the neck is), as
    a trajectory of its own; None if the neck is already at the first waypoint. Two poses that each
    pass validation may not be joined by a straight move: 14 of 399 random pairs asked a cable more
    than f_max on the way, up to 118 N (audit of 2026-11-29)."""
    start = np.clip(np.asarray(alpha_from_rad, dtype=np.float64), -np.asarray(alpha_max_rad), np.asarray(alpha_max_rad))
    first = Trajectory(waypoints_rad=traj.waypoints_rad[:1], durations_s=np.zeros(0), dwell_s=np.zeros(1),
                       name=traj.name, pretension_N=traj.pretension_N[:1])
    lead = approach(first, start)
    return None if lead is first else lead


def start_pose_when_known(start_pose: Callable[[], np.ndarray | None], wanted: Callable[[], bool],
                          max_wait_s: float = START_POSE_WAIT_S, clock: Callable[[], float] = time.monotonic,
                          sleep: Callable[[float], None] = time.sleep, poll_s: float = 0.02) -> np.ndarray:
    """The pose a campaign asked for now will start from (``start_pose``:
    :meth:`controller.service.CampaignService.start_pose`), once it is known: while the slack of
    an e-stop is taken up it is not (α̂ is off by the slack), and the approach validated from the
    slack α̂ was not the move the campaign then made from where the take-up left the neck
    (session 41). Raises :class:`GivenUp` once ``wanted`` says False meanwhile, :class:`Refused`
    after ``max_wait_s`` s (by ``clock``) without a pose."""
    give_up = clock() + max_wait_s
    while True:
        pose = start_pose()
        if pose is not None:
            return pose
        if not wanted():
            raise GivenUp("stopped or superseded while the cables' slack was taken up")
        if clock() >= give_up:
            raise Refused(f"refused: the cables' slack after the e-stop was still being taken up after {max_wait_s:g} s "
                          "(the pose the campaign would start from is not known): ask again once the neck holds")
        sleep(poll_s)


def prepare(req: bus.CampaignRequest, robot: Params, law: LawConfig, limits: TrajectoryLimits | None = None,
            budget_s: float = VALIDATION_BUDGET_S, clock: Callable[[], float] = time.monotonic,
            wanted: Callable[[], bool] | None = None, alpha_from_rad: np.ndarray | None = None) -> Prepared:
    """Parse and validate a start request against the robot's parameter set ``robot``; ``law``
    gives the gains and rate kept from the process's own law (a jog's law and set are the
    service's own, ``law`` and ``robot``: it runs on them). Runs off the control loop (it may
    take seconds), never longer than ``budget_s`` by ``clock``; ``wanted`` is asked at each look
    at the budget (every ``FORCE_CHECK_CHUNK`` samples, about 15 ms): once it says False, the
    preparation ends with :class:`GivenUp`. ``alpha_from_rad``: the pose the campaign will start
    from (α̂, or the target of the jog it waits for); the approach the service prepends from it
    (:func:`controller.trajectory.approach`) is validated too (:func:`approach_move`). Raises
    :class:`Refused` with the reason for anything wrong, never another exception."""
    deadline = clock() + budget_s
    try:
        if not req.trajectory_json:
            raise ValueError("the request has no trajectory (trajectory_json is empty)")
        params = robot
        if req.kind == "jog" and req.parameters_toml:
            # A jog runs on the service's own set and law (controller.service: it keeps them), so
            # it is checked on them: a made-up set (masses zeroed) had passed a pose the robot's
            # refuses (107.9 N > f_max), then been held with the robot's (review of session 53).
            raise ValueError("a jog runs on the controller's own parameter set: the request's parameters_toml must "
                             "be empty")
        if req.parameters_toml:
            params = params_from_dict(toml_text.loads(req.parameters_toml), f"campaign {req.campaign_id}")
            if (params.n_joints, params.n_cables) != (robot.n_joints, robot.n_cables):
                raise ValueError(f"parameter set {params.name!r} is for {params.n_joints} joints and "
                                 f"{params.n_cables} cables, the robot has {robot.n_joints} and {robot.n_cables}")
            params = within_robot_limits(params, robot)
        new_law = law if req.kind == "jog" else dataclasses.replace(law, law=req.law, no_pulleys=req.no_pulleys)
        traj = trajectory_from_json(req.trajectory_json)
        base = limits or TrajectoryLimits()
        limits = TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg),
                                  alpha_dot_max_rad_s=base.alpha_dot_max_rad_s,
                                  alpha_ddot_max_rad_s2=base.alpha_ddot_max_rad_s2,
                                  duration_max_s=base.duration_max_s, waypoints_max=base.waypoints_max)
        check = _budgeted(nominal_force_check(params, new_law), deadline, clock, wanted)
        validate(traj, limits, params.n_joints, check)
        lead = None if alpha_from_rad is None else approach_move(traj, alpha_from_rad, limits.alpha_max_rad)
        if lead is not None:
            try:
                validate(lead, limits, params.n_joints, check)
            except TrajectoryError as exc:
                raise Refused(f"refused: the move from the present pose "
                              f"{np.round(np.degrees(lead.waypoints_rad[0]), 1).tolist()}° to the first waypoint: "
                              f"{exc}; go there through a pose in between") from None
    except Refused:
        raise
    except (ValueError, TrajectoryError, tomllib.TOMLDecodeError) as exc:
        raise Refused(f"refused: {exc}") from None
    except RecursionError:
        raise Refused("refused: the parameter set is nested too deeply") from None
    except Exception as exc:  # noqa: BLE001 - hostile input: any failure is a refusal, never a crash
        raise Refused(f"refused: {type(exc).__name__}: {exc}") from None
    return Prepared(req.campaign_id, req.kind, params, new_law, traj)


__all__ = ["FORCE_CHECK_CHUNK", "START_POSE_WAIT_S", "VALIDATION_BUDGET_S", "GivenUp", "Prepared", "Refused",
           "approach_move", "prepare", "start_pose_when_known",
           "within_robot_limits"]
