"""The body of ``POST /api/campaigns`` and its checks, down to a runnable ``CampaignSpec``.

Structural errors are pydantic's (422 naming the field). The semantic ones raised here
(:class:`RequestError`) use the same shape, ``{"loc": ["body", <field>...], "msg", "type"}``,
so a client handles one kind of 422. A trajectory is validated exactly as the controller does
(joint limits, speed, acceleration, forces on the nominal path) before anything moves.

A request is honoured or refused, never silently changed (issue 14, finding 6). Omitted fields take
the documented defaults; a given one that this console cannot honour is a 422 naming it. With a
controller service on the bus (``xneck up``) the stack's bridge is what campaigns drive: its target
is the server's ``mode``, a twin bridge runs in real time with the truth and seed it was started
with (``--twin-truth``/``--twin-seed``, passed by ``xneck up``). The robot runs in real time and
has no truth or seed to choose. What was resolved here is what the record and the MCAP say.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import msgspec
from pydantic import BaseModel, ConfigDict, Field, field_validator

from controller.laws import LawConfig, nominal_force_check
from controller.trajectory import (
    NAMED_TRAJECTORIES,
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    load_trajectory,
    trajectory_by_name,
    validate,
)
from server.campaign_runner import CampaignSpec, check_timeout
from server.paramsets import ParameterStore, UnknownParameterSet
from server.settings import Settings
from server.truthstore import TruthStore, UnknownTruth, truth_label
from twin.model.params import ParameterError, Params
from twin.sim.sensors import ALPHA_IP_SOURCES
from twin.sim.truth import TruthError

Target = Literal["twin", "robot"]
Pace = Literal["lockstep", "realtime"]
Truth = str  # "model", "robot", a stored truth's name (server.truthstore), the stack twin's file; "" on the robot


class RequestError(ValueError):
    """A body that is well formed but not acceptable; ``loc`` names the field."""

    def __init__(self, loc: tuple[str, ...], msg: str) -> None:
        super().__init__(msg)
        self.loc = ("body", *loc)
        self.msg = msg

    def detail(self) -> list[dict[str, Any]]:
        return [{"loc": list(self.loc), "msg": self.msg, "type": "value_error"}]


class WaypointsIn(BaseModel):
    """A user trajectory: waypoints in degrees joined by cycloidal moves (see controller.trajectory).
    Strict, as ``/api/trajectories`` reads the same body: ``true`` was taken as 1°, ``"8"`` as 8°
    and ``"durations_s": "3"`` as 3 s, and the campaign started (input audit)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    name: str = Field("user", max_length=64)
    waypoints_deg: list[list[float]] = Field(min_length=1, description="Joint angles α1..αN per waypoint (deg).")
    durations_s: float | list[float] = Field(description="Duration of each move (s), one per move or one for all.")
    dwell_s: float | list[float] = Field(0.0, description="Hold at each waypoint (s), one per waypoint or one for all.")


class CampaignCreate(BaseModel):
    """Start a campaign. Defaults: control, law 2, the §7 control test, the active parameter set,
    the server's mode as target and its pace. Strict (module docstring: never silently changed):
    ``"no_pulleys": "true"``, ``"seed": "5"`` or ``"creep_time_s": true`` are a 422, not coerced."""

    model_config = ConfigDict(extra="forbid", strict=True)
    kind: Literal["identification", "control"] = "control"
    law: Literal[1, 2, 3] | None = Field(None, description="Control law 1, 2 or 3 (default: 2; 1 for identification).")
    no_pulleys: bool = Field(False, description="Neglect the pulleys in the controller's model (Table 3).")
    trajectory: str | None = Field(None, description=f"Built-in trajectory ({', '.join(NAMED_TRAJECTORIES)}) or "
                                   "one saved in the console's library (PUT /api/trajectories/{name}).")
    waypoints: WaypointsIn | None = Field(None, description="A user trajectory instead of a built-in one.")
    parameter_set: str | None = Field(None, description="Parameter set name (default: the active one).")
    target: Literal["twin", "robot"] | None = Field(None, description="Default: the server's mode.")
    pace: Literal["lockstep", "realtime"] | None = Field(None, description="Twin pacing (default: the server's).")
    seed: int | None = Field(None, ge=0, le=2**31 - 1, description="Seed of the twin's sensor noise (default 0; "
                             "under `xneck up` the stack twin's seed, which cannot be changed per campaign).")
    truth: str | None = Field(
        None, max_length=64, pattern=r"^[A-Za-z0-9_.\-]{1,64}$",
        description="What a twin started for the campaign simulates (twin/sim/truth.py): model, robot, or the name of "
        "a truth file the console knows (GET /api/truths; e.g. calibrated by `xneck twin calibrate`). Default: robot "
        "for identification, model for control. Under `xneck up` the stack's twin keeps the truth it was started "
        "with: another one is refused.")
    alpha_ip: Literal["camera", "noise"] | None = Field(
        None, description="A twin started for the campaign: its α_IP, measured on frames rendered from its truth by "
        "the robot's detector (camera, 30 fps, with the exposure latency) or the true α plus the camera's white noise "
        "(noise, cheaper), as `xneck campaign --alpha-ip`. Default: camera for identification, noise for control. "
        "Under `xneck up` the stack's twin keeps its own (`xneck up --alpha-ip`).")
    estimator: str | None = Field(
        None, max_length=32, description="Identification only: Table 2's estimator of the campaign's analysis, as "
        "`xneck identify --estimator`: auto (the default: where the campaign's motor friction grows with the load, "
        "i.e. it rejects the paper's model, outputerror if the load-friction fit finds the line's damping light "
        "enough for a quasi-static pose and no creep_time_s is held, else loadfriction; iv where it keeps the "
        "paper's model), iv, ols, wls, loadfriction or outputerror.")
    creep_time_s: float | None = Field(
        None, description="Identification only: the cable line's creep time constant (s) measured apart (a bench "
        "creep test), held in the load-friction fit instead of estimated from the record; with estimator auto or "
        "loadfriction.")

    @field_validator("law", mode="before")
    @classmethod
    def _law_not_bool(cls, value: Any) -> Any:
        """true equals 1 to Python, so strict Literal[1, 2, 3] took it as law 1."""
        if isinstance(value, bool):
            raise ValueError(f"law must be the integer 1, 2 or 3, got {str(value).lower()}")
        return value


class PreparedCampaign(BaseModel):
    """A request resolved: every choice explicit, as the record and the MCAP metadata state it."""

    model_config = ConfigDict(arbitrary_types_allowed=True)
    spec: Any
    params: Any
    parameter_set: str
    pace: Pace
    target: Target
    truth: Truth


def check_trajectory(traj: Trajectory, params: Params, law: LawConfig) -> None:
    """The controller's own validation (``server.cli.campaign.load_checked_trajectory`` without the CLI)."""
    limits = TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg))
    validate(traj, limits, params.n_joints, nominal_force_check(params, law))


def _resolve_target(req: CampaignCreate, settings: Settings, service: bool) -> tuple[Target, Pace, Truth, int]:
    """(target, pace, truth, seed) as given or defaulted, or :class:`RequestError` for one that
    cannot be honoured (module docstring)."""
    target = req.target or settings.mode
    if service and target != settings.mode:
        raise RequestError(("target",), f"this console's stack drives the {settings.mode} (the bridge `xneck up` "
                           f"started); a {target} campaign needs a stack started for it")
    if target == "robot":
        if req.pace == "lockstep":
            raise RequestError(("pace",), "the robot runs in real time: lockstep is for the twin only")
        for name in ("truth", "seed", "alpha_ip"):
            if getattr(req, name) is not None:
                raise RequestError((name,), f"{name} applies to the twin only; the robot is the real thing")
        return target, "realtime", "", 0
    default_truth: Truth = "robot" if req.kind == "identification" else "model"
    if not service:
        return target, req.pace or settings.pace, _known_truth(req.truth or default_truth, settings), req.seed or 0
    if req.pace == "lockstep":
        raise RequestError(("pace",), "the `xneck up` stack's twin runs in real time (500 Hz); lockstep is only for "
                           "campaigns that start their own twin (`xneck server` without a controller service)")
    if req.truth is not None and req.truth not in (settings.twin_truth, truth_label(settings.twin_truth)):
        raise RequestError(("truth",), f"the stack's twin simulates the {truth_label(settings.twin_truth)} truth "
                           f"(`xneck up --truth`); it cannot change per campaign")
    if req.seed is not None and req.seed != settings.twin_seed:
        raise RequestError(("seed",), f"the stack's twin runs with seed {settings.twin_seed} (`xneck up --seed`); it "
                           f"cannot change per campaign")
    if req.alpha_ip is not None:
        raise RequestError(("alpha_ip",), "the stack's twin measures α_IP as it was started (`xneck up --alpha-ip`); "
                           "it cannot change per campaign")
    return target, "realtime", settings.twin_truth, settings.twin_seed


def _known_truth(name: str, settings: Settings) -> Truth:
    """The truth a spawned twin runs for the request's name: "model", "robot" or a stored file's
    absolute path (server.truthstore), or :class:`RequestError` saying why not."""
    store = TruthStore(Path(settings.data_dir))
    try:
        return store.resolve(name)
    except UnknownTruth:
        raise RequestError(("truth",), f"unknown truth {name!r}; known: {', '.join(store.names())} "
                           "(upload a truth file with PUT /api/truths/{name})") from None
    except TruthError as exc:
        raise RequestError(("truth",), f"truth {name!r} does not load: {exc}") from None


def _named_trajectory(name: str, settings: Settings) -> Trajectory:
    """A built-in trajectory or one of the console's library (``PUT /api/trajectories/{name}``), or
    :class:`RequestError` on ``trajectory``. A library name starts what its waypoints sent inline
    would: the caller runs the same checks (audit of 2026-11-29: a saved trajectory was "unknown")."""
    from server.trajectory_library import NAME, LibraryError, NotInLibrary, TrajectoryLibrary

    loc = ("trajectory",)
    if name in NAMED_TRAJECTORIES:
        try:
            return trajectory_by_name(name)
        except TrajectoryError as exc:
            raise RequestError(loc, str(exc)) from None
    library = TrajectoryLibrary(settings.data_dir)
    if NAME.fullmatch(name):  # else no file of the library can have it
        try:
            return library.get(name)
        except NotInLibrary:
            pass
        except (LibraryError, TrajectoryError, OSError) as exc:  # there, but it does not read
            raise RequestError(loc, f"stored trajectory {name!r}: {exc}") from None
    try:
        saved = library.names()
    except OSError:
        saved = []
    raise RequestError(loc, f"unknown trajectory {name!r}; built in: {', '.join(NAMED_TRAJECTORIES)}; in the "
                       f"library: {', '.join(saved) or 'none'}")


def _analysis_options(req: CampaignCreate) -> str:
    """The identification analysis's estimator (default auto) with its creep time checked
    (twin.identification.options.check_variable_options), or :class:`RequestError` naming the field."""
    from twin.identification.options import check_variable_options

    if req.kind != "identification":
        for name in ("estimator", "creep_time_s"):
            if getattr(req, name) is not None:
                raise RequestError((name,), f"{name} applies to identification campaigns (their analysis), "
                                   f"not to a {req.kind} campaign")
        return "auto"
    estimator = req.estimator or "auto"
    try:
        check_variable_options(estimator, None)
    except ValueError as exc:
        raise RequestError(("estimator",), str(exc)) from None
    try:
        return check_variable_options(estimator, req.creep_time_s)
    except ValueError as exc:
        raise RequestError(("creep_time_s",), str(exc)) from None


def prepare(req: CampaignCreate, store: ParameterStore, settings: Settings, service: bool = False) -> PreparedCampaign:
    """Resolve defaults and validate everything; raises :class:`RequestError`. ``service``: a
    controller service is on the bus (campaigns are requests to it, driving the stack's bridge)."""
    target, pace, truth, seed = _resolve_target(req, settings, service)
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
    # One name for the set everywhere: the console's (REST, record, MCAP metadata, TOML sent on).
    params = msgspec.structs.replace(params, name=name)
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
        traj = _named_trajectory(req.trajectory or default, settings)
    try:
        check_trajectory(traj, params, law)
    except TrajectoryError as exc:
        raise RequestError(loc, f"trajectory rejected: {exc}") from None
    try:
        check_timeout(traj.duration_s, settings.campaign_timeout_s, pace == "realtime" or service or target == "robot")
    except ValueError as exc:
        raise RequestError(loc, f"trajectory rejected: {exc}") from None
    estimator = _analysis_options(req)
    spec = CampaignSpec(
        kind=req.kind, law=law, trajectory=traj, twin=target == "twin", seed=seed,
        timeout_s=settings.campaign_timeout_s, params_file=params_file,
        connect=tuple(settings.connect) if target == "robot" else (), realtime=pace == "realtime",
        truth=truth or "model", service=service, estimator=estimator, creep_time_s=req.creep_time_s,
        alpha_ip=req.alpha_ip,
        # `xneck up`'s twin: the camera it was started with is the one its campaigns record
        camera_source=ALPHA_IP_SOURCES[settings.twin_alpha_ip] if service and target == "twin" and settings.twin_alpha_ip
        else None,
        camera_instance=(settings.twin_camera or "") if service and target == "twin" else "",
    )
    # The record names the truth ("model", "robot", a stored truth's name); the spec carries what the twin loads.
    return PreparedCampaign(spec=spec, params=params, parameter_set=name, pace=pace, target=target,
                            truth=truth_label(truth) if truth else "")
