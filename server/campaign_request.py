"""The body of ``POST /api/campaigns`` and its checks, down to a runnable ``CampaignSpec``.

Structural errors are pydantic's (422 naming the field). The semantic ones raised here
(:class:`RequestError`) use the same shape, ``{"loc": ["body", <field>...], "msg", "type"}``,
so a client handles one kind of 422. A trajectory is validated exactly as the controller does
(joint limits, speed, acceleration, forces on the nominal path) before anything moves.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from server.campaign_runner import CampaignSpec
from controller.laws import LawConfig, nominal_force_check
from controller.trajectory import (NAMED_TRAJECTORIES, Trajectory, TrajectoryError, TrajectoryLimits,
                                   load_trajectory, trajectory_by_name, validate)
from server.paramsets import ParameterStore, UnknownParameterSet
from server.settings import Settings
from twin.model.params import ParameterError, Params


class RequestError(ValueError):
    """A body that is well formed but not acceptable; ``loc`` names the field."""

    def __init__(self, loc: tuple[str, ...], msg: str) -> None:
        super().__init__(msg)
        self.loc = ("body", *loc)
        self.msg = msg

    def detail(self) -> list[dict[str, Any]]:
        return [{"loc": list(self.loc), "msg": self.msg, "type": "value_error"}]


class WaypointsIn(BaseModel):
    """A user trajectory: waypoints in degrees joined by cycloidal moves (see controller.trajectory)."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field("user", max_length=64)
    waypoints_deg: list[list[float]] = Field(min_length=1, description="Joint angles α1..αN per waypoint (deg).")
    durations_s: float | list[float] = Field(description="Duration of each move (s), one per move or one for all.")
    dwell_s: float | list[float] = Field(0.0, description="Hold at each waypoint (s), one per waypoint or one for all.")


class CampaignCreate(BaseModel):
    """Start a campaign. Defaults: control, law 2, the §7 control test, the active parameter set,
    the server's mode as target and its pace."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["identification", "control"] = "control"
    law: Literal[1, 2, 3] | None = Field(None, description="Control law 1, 2 or 3 (default: 2; 1 for identification).")
    no_pulleys: bool = Field(False, description="Neglect the pulleys in the controller's model (Table 3).")
    trajectory: str | None = Field(None, description=f"Built-in trajectory: {', '.join(NAMED_TRAJECTORIES)}.")
    waypoints: WaypointsIn | None = Field(None, description="A user trajectory instead of a built-in one.")
    parameter_set: str | None = Field(None, description="Parameter set name (default: the active one).")
    target: Literal["twin", "robot"] | None = Field(None, description="Default: the server's mode.")
    pace: Literal["lockstep", "realtime"] | None = Field(None, description="Twin pacing (default: the server's).")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed of the twin's sensor noise.")
    truth: Literal["model", "robot"] | None = Field(
        None, description="What a twin started for the campaign simulates (twin/sim/truth.py; default: robot for "
        "identification, model for control). The `xneck up` stack's twin keeps the truth it was started with.")


class PreparedCampaign(BaseModel):
    model_config = ConfigDict(arbitrary_types_allowed=True)
    spec: Any
    params: Any
    parameter_set: str
    pace: str


def check_trajectory(traj: Trajectory, params: Params, law: LawConfig) -> None:
    """The controller's own validation (``server.cli.campaign.load_checked_trajectory`` without the CLI)."""
    limits = TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg))
    validate(traj, limits, params.n_joints, nominal_force_check(params, law))


def prepare(req: CampaignCreate, store: ParameterStore, settings: Settings) -> PreparedCampaign:
    """Resolve defaults and validate everything; raises :class:`RequestError`."""
    if req.trajectory is not None and req.waypoints is not None:
        raise RequestError(("waypoints",), "give either trajectory (a built-in name) or waypoints, not both")
    name = req.parameter_set or store.active()
    try:
        params = store.load(name)
        params_file = store.path(name)
    except UnknownParameterSet:
        raise RequestError(("parameter_set",), f"unknown parameter set {name!r}; known: {', '.join(store.names())}") \
            from None
    except ParameterError as exc:
        raise RequestError(("parameter_set",), str(exc)) from None
    law = LawConfig(law=req.law if req.law is not None else (1 if req.kind == "identification" else 2),
                    no_pulleys=req.no_pulleys)
    if req.waypoints is not None:
        loc: tuple[str, ...] = ("waypoints",)
        try:
            traj = load_trajectory(req.waypoints.model_dump())
        except TrajectoryError as exc:
            raise RequestError(loc, str(exc)) from None
    else:
        loc = ("trajectory",)
        default = "identification" if req.kind == "identification" else "control_test"
        try:
            traj = trajectory_by_name(req.trajectory or default)
        except TrajectoryError as exc:
            raise RequestError(loc, str(exc)) from None
    try:
        check_trajectory(traj, params, law)
    except TrajectoryError as exc:
        raise RequestError(loc, f"trajectory rejected: {exc}") from None
    target = req.target or settings.mode
    pace = req.pace or settings.pace
    spec = CampaignSpec(
        kind=req.kind, law=law, trajectory=traj, twin=target == "twin", seed=req.seed,
        timeout_s=settings.campaign_timeout_s, params_file=params_file,
        connect=tuple(settings.connect) if target == "robot" else (), realtime=pace == "realtime",
        truth=req.truth or ("robot" if req.kind == "identification" else "model"),
    )
    return PreparedCampaign(spec=spec, params=params, parameter_set=name, pace=pace)
