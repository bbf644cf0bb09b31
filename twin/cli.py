"""Command-line checks of the model: ``xneck model --alpha 40 30 20 [--json]``."""

from __future__ import annotations

import json as jsonlib
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from twin import cables, dynamics, xjoint
from twin.model import build
from bridge.runtime import (
    CABLE_MODEL_OPTION,
    CONNECT_OPTION,
    IDLE_TIMEOUT_OPTION,
    INSTANCE_OPTION,
    LISTEN_OPTION,
    LOCKSTEP_OPTION,
    MAX_TICKS_OPTION,
    NO_FRICTION_OPTION,
    TRUTH_OPTION,
    SEED_OPTION,
    STARTUP_TIMEOUT_OPTION,
    VERBOSE_OPTION,
)
from twin.params import ParameterError, Params, load_params, parse_override

PARAMS_OPTION = typer.Option(None, "--params", help="Parameter file (TOML); default: the 3-X prototype.")
SET_OPTION = typer.Option(None, "--set", help="Override one value, e.g. --set springs.l0=[0.05,0.05,0.05].")


def load_cli_params(params_file: Optional[Path], overrides: Optional[list[str]]) -> Params:
    """Parameters for a command, or a clean exit with the reason (no traceback)."""
    try:
        return load_params(params_file, dict(parse_override(o) for o in overrides or []))
    except ParameterError as exc:
        typer.secho(f"error: {exc}", err=True, fg="red")
        raise typer.Exit(2) from None


def _alpha_from_cli(first: float, extra: list[str], n: int) -> np.ndarray:
    values = [first]
    for token in extra:
        try:
            values.append(float(token))
        except ValueError:
            raise typer.BadParameter(f"unexpected argument {token!r}", param_hint="--alpha") from None
    if len(values) != n or not np.all(np.isfinite(values)):
        raise typer.BadParameter(f"needs {n} finite angles in degrees (one per joint), got {values}", param_hint="--alpha")
    if np.any(np.abs(values) >= 180):
        raise typer.BadParameter("angles must lie in (−180°, 180°): the joint is flat at ±180°", param_hint="--alpha")
    return np.radians(values)


def model(
    ctx: typer.Context,
    alpha: float = typer.Option(..., "--alpha", help="Joint angles in degrees, one per joint: --alpha 40 30 20."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output (SI units)."),
    params_file: Optional[Path] = PARAMS_OPTION,
    overrides: Optional[list[str]] = SET_OPTION,
) -> None:
    """Print l_c, θ, Z, M, g and the spring lengths at one configuration: a first check of the
    model against the real robot."""
    params = load_cli_params(params_file, overrides)
    m = build(params)
    a = _alpha_from_cli(alpha, ctx.args, m.n_joints)
    terms = dynamics.evaluate(m, a)
    theta = cables.theta_rigid(m, a)
    ll, lr = xjoint.side_lengths(m.L, m.b, a)
    out = {
        "params": params.name,
        "alpha_rad": a.tolist(),
        "l_c_m": (terms.l_c - m.l_c0).tolist(),
        "theta_rad": theta.tolist(),
        "Z_m_per_rad": terms.Z.tolist(),
        "M_kg_m2": terms.M.tolist(),
        "M_m_kg_m2": terms.M_m.tolist(),
        "g_N_m": terms.g.tolist(),
        "spring_left_m": ll.tolist(),
        "spring_right_m": lr.tolist(),
    }
    if as_json:
        typer.echo(jsonlib.dumps(out, indent=2))
        return
    fmt = lambda v, k=1.0, p=3: "  ".join(f"{x * k:9.{p}f}" for x in np.atleast_1d(v))  # noqa: E731
    typer.echo(f"parameter set {params.name}, α = ({', '.join(f'{x:g}' for x in np.degrees(a))})°")
    typer.echo(f"cable length change l_c − l_c0 (mm) : {fmt(terms.l_c - m.l_c0, 1e3)}")
    typer.echo(f"motor angles θ, rigid cables (rad)  : {fmt(theta)}")
    typer.echo(f"spring lengths left  (mm)           : {fmt(ll, 1e3)}")
    typer.echo(f"spring lengths right (mm)           : {fmt(lr, 1e3)}")
    typer.echo(f"g, springs + gravity (N·m/rad)      : {fmt(terms.g, 1, 4)}")
    typer.echo("Z = −∂l_c/∂α (mm/rad), rows = joints, columns = cables")
    for row in terms.Z:
        typer.echo("    " + fmt(row, 1e3, 2))
    typer.echo("M with geared motors (kg·m²)")
    for row in terms.M:
        typer.echo("    " + fmt(row, 1, 5))




def twin(
    lockstep: bool = LOCKSTEP_OPTION,
    seed: int = SEED_OPTION,
    cable_model: Optional[str] = CABLE_MODEL_OPTION,
    no_friction: bool = NO_FRICTION_OPTION,
    truth: str = TRUTH_OPTION,
    max_ticks: Optional[int] = MAX_TICKS_OPTION,
    idle_timeout: Optional[float] = IDLE_TIMEOUT_OPTION,
    startup_timeout: Optional[float] = STARTUP_TIMEOUT_OPTION,
    instance: str = INSTANCE_OPTION,
    listen: Optional[list[str]] = LISTEN_OPTION,
    connect: Optional[list[str]] = CONNECT_OPTION,
    params_file: Optional[Path] = PARAMS_OPTION,
    overrides: Optional[list[str]] = SET_OPTION,
    verbose: bool = VERBOSE_OPTION,
) -> None:
    """Run the simulated robot on the bus: the bridge with the twin as its driver, so it speaks
    exactly the bridge's topics and applies the bridge's safety rules (`xneck bridge --driver twin`)."""
    from bridge.cli import bridge

    bridge(driver="twin", replay=None, loop=False, driver_config=None, lockstep=lockstep, command_timeout=0.010,
           hold_ramp=0.010, seed=seed, cable_model=cable_model, no_friction=no_friction, truth=truth, max_ticks=max_ticks,
           idle_timeout=idle_timeout, startup_timeout=startup_timeout, instance=instance, listen=listen,
           connect=connect, params_file=params_file, overrides=overrides, verbose=verbose)
