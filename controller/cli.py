"""`xneck controller` (the 500 Hz process) and `xneck campaign control|identification`."""

from __future__ import annotations

import json as jsonlib
import logging
from pathlib import Path
from typing import Optional

import typer

from bridge.runtime import CONNECT_OPTION, LISTEN_OPTION, VERBOSE_OPTION, check_truth
from twin.cli import PARAMS_OPTION, SET_OPTION, load_cli_params

campaign_app = typer.Typer(help="Run a campaign (identification or control), record it as MCAP, print its results.",
                           no_args_is_help=True)

LAW_OPTION = typer.Option(2, "--law", help="Control law: 1 (no friction), 2 (friction), 3 (friction + elastic cables).")
NO_PULLEYS_OPTION = typer.Option(False, "--no-pulleys", help="Neglect the pulleys in the controller's model (Table 3).")
TRAJECTORY_OPTION = typer.Option(
    None, "--trajectory", help="identification, control_test, or a JSON/TOML file of waypoints (degrees).")


def _law(law: int, no_pulleys: bool):
    from controller.laws import LawConfig

    try:
        return LawConfig(law=law, no_pulleys=no_pulleys)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--law") from None


def load_checked_trajectory(name_or_path: str, params, law_config):
    """A trajectory by name or file, validated against the joint limits and the forces on its
    nominal path; a clean CLI error naming the waypoint or segment otherwise."""
    from controller.laws import nominal_force_check
    from controller.trajectory import (NAMED_TRAJECTORIES, TrajectoryError, TrajectoryLimits, load_trajectory,
                                       trajectory_by_name, validate)
    import math

    try:
        traj = (trajectory_by_name(name_or_path) if name_or_path.replace("-", "_") in NAMED_TRAJECTORIES
                else load_trajectory(Path(name_or_path)))
        limits = TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg))
        validate(traj, limits, params.n_joints, nominal_force_check(params, law_config))
    except TrajectoryError as exc:
        typer.secho(f"error: trajectory rejected: {exc}", err=True, fg="red")
        raise typer.Exit(2) from None
    return traj


def controller(
    law: int = LAW_OPTION,
    no_pulleys: bool = NO_PULLEYS_OPTION,
    trajectory: Optional[str] = TRAJECTORY_OPTION,
    lockstep: bool = typer.Option(False, "--lockstep", help="Wait as long as needed for each state (lockstep twin)."),
    campaign_id: str = typer.Option("", "--campaign-id", help="Id in the campaign events (default: random)."),
    campaign_kind: str = typer.Option("control", "--campaign-kind"),
    idle_timeout: float = typer.Option(10.0, "--idle-timeout", help="Give up after this long without any state (s)."),
    listen: Optional[list[str]] = LISTEN_OPTION,
    connect: Optional[list[str]] = CONNECT_OPTION,
    params_file: Optional[Path] = PARAMS_OPTION,
    overrides: Optional[list[str]] = SET_OPTION,
    verbose: bool = VERBOSE_OPTION,
) -> None:
    """Run the controller on the bus: follows --trajectory, or holds the neck where it is."""
    from bridge.runtime import endpoints, raise_priority, setup_logging, stop_on_signals
    from bridge.session import open_session
    from controller.process import ControllerNode, ControllerProcessConfig

    setup_logging(verbose)
    params = load_cli_params(params_file, overrides)
    config = _law(law, no_pulleys)
    traj = load_checked_trajectory(trajectory, params, config) if trajectory else None
    stop = stop_on_signals()
    cfg = ControllerProcessConfig(campaign_id=campaign_id, campaign_kind=campaign_kind, lockstep=lockstep,
                                  idle_timeout_s=idle_timeout, exit_when_done=traj is not None)
    with open_session(endpoints(listen), endpoints(connect)) as session:
        node = ControllerNode(session, params, config, traj, cfg)
        if not lockstep:
            raise_priority()
        logging.getLogger("xneck.controller").info("controller %s up (%s)", node.instance, config.name)
        try:
            outcome = node.run(stop)
        finally:
            node.close()
        logging.getLogger("xneck.controller").info("controller %s: %s", node.instance, outcome)
    if outcome == "aborted":
        raise typer.Exit(1)


def campaign_control(
    law: int = LAW_OPTION,
    no_pulleys: bool = NO_PULLEYS_OPTION,
    twin: bool = typer.Option(True, "--twin/--robot", help="Against a lockstep twin started for the campaign, or "
                              "the robot's bridge already on the bus."),
    trajectory: str = typer.Option("control_test", "--trajectory", help="Trajectory name or file (degrees)."),
    out: Optional[Path] = typer.Option(None, "--out", help="MCAP file to write (default: campaign-<id>.mcap here)."),
    as_json: bool = typer.Option(False, "--json", help="Print the metrics as JSON."),
    seed: int = typer.Option(0, "--seed", help="Seed of the twin's sensor noise."),
    truth: str = typer.Option("model", "--truth", callback=check_truth, help="What the twin simulates: the "
                              "parameter file as it is (model) or with a real line's small cable damping (robot)."),
    timeout: float = typer.Option(600.0, "--timeout", help="Abort the campaign after this many seconds (wall)."),
    params_file: Optional[Path] = PARAMS_OPTION,
    overrides: Optional[list[str]] = SET_OPTION,
) -> None:
    """Run a control campaign (3-X paper §7), record it, print e, e_α, forces and saturation."""
    from controller.campaign import CampaignSpec, run_campaign

    params = load_cli_params(params_file, overrides)
    config = _law(law, no_pulleys)
    traj = load_checked_trajectory(trajectory, params, config)
    spec = CampaignSpec(kind="control", law=config, trajectory=traj, twin=twin, seed=seed, timeout_s=timeout,
                        params_file=params_file, overrides=tuple(overrides or ()), truth=truth)
    result = run_campaign(spec, params, out, progress=None if as_json else _print_progress)
    if as_json:
        typer.echo(jsonlib.dumps(result.summary(), indent=2))
    else:
        typer.echo(result.table())
    if result.outcome != "finished":
        raise typer.Exit(1)


def _print_progress(fraction: float, message: str) -> None:
    bar = "#" * int(30 * fraction)
    typer.echo(f"\r[{bar:<30s}] {100 * fraction:5.1f}% {message[:60]:<60s}", nl=False, err=True)
    if fraction >= 1.0:
        typer.echo("", err=True)


def campaign_identification(
    twin: bool = typer.Option(True, "--twin/--robot", help="Against a lockstep twin started for the campaign, or "
                              "the robot's bridge already on the bus."),
    out: Optional[Path] = typer.Option(None, "--out", help="MCAP file to write (default: campaign-<id>.mcap here)."),
    as_json: bool = typer.Option(False, "--json", help="Print the identification tables as JSON."),
    seed: int = typer.Option(0, "--seed", help="Seed of the twin's sensor noise."),
    truth: str = typer.Option("robot", "--truth", callback=check_truth, help="What the twin simulates: a real "
                              "line's small cable damping, unknown to the model (robot), or the parameter file as "
                              "it is (model, an identity check)."),
    timeout: float = typer.Option(900.0, "--timeout", help="Abort the campaign after this many seconds (wall)."),
    params_file: Optional[Path] = PARAMS_OPTION,
    overrides: Optional[list[str]] = SET_OPTION,
) -> None:
    """Run the identification trajectory (§5.2.2) in closed loop with law 1, record it, and
    identify friction and cable stiffness from the archive (Tables 1-2, Figs. 4-8)."""
    from controller.campaign import CampaignSpec, run_campaign
    from controller.trajectory import identification_trajectory
    from twin.identification import DEFAULT_THRESHOLD
    from twin.identification_cli import identify

    params = load_cli_params(params_file, overrides)
    config = _law(1, False)
    spec = CampaignSpec(kind="identification", law=config, trajectory=identification_trajectory(), twin=twin,
                        seed=seed, timeout_s=timeout, params_file=params_file, overrides=tuple(overrides or ()),
                        truth=truth)
    result = run_campaign(spec, params, out, progress=None if as_json else _print_progress)
    if result.outcome != "finished":
        typer.secho(f"error: campaign {result.campaign_id} {result.outcome}: {result.message}", err=True, fg="red")
        raise typer.Exit(1)
    if not as_json:
        typer.echo(f"campaign {result.campaign_id} recorded in {result.path}; identifying…")
    identify(result.path, json_out=as_json, out=None, params_file=params_file, cutoff_hz=None,
             threshold=DEFAULT_THRESHOLD, no_alpha_hat=False)
