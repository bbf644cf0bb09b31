"""Command-line checks of the model: ``xneck model --alpha 40 30 20 [--json]``."""

from __future__ import annotations

import json as jsonlib
from pathlib import Path

import numpy as np
import typer

from server.cli.options import PARAMS_OPTION, SET_OPTION, load_cli_params


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
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """Print l_c, θ, Z, M, g and the spring lengths at one configuration: a first check of the
    model against the real robot."""
    from twin.model import cables, dynamics, xjoint
    from twin.model.numeric import build

    params = load_cli_params(params_file, overrides)
    m = build(params)
    a = _alpha_from_cli(alpha, ctx.args, m.n_joints)
    terms = dynamics.evaluate(m, a)
    theta = cables.theta_rigid(m, a)
    ll, lr = xjoint.side_lengths(m.L, m.b, a)
    out = {
        "params": params.name,
        "alpha_rad": a.tolist(),
        "delta_l_c_m": (terms.l_c - m.l_c0).tolist(),  # l_c − l_c0
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
    typer.echo(f"g, springs + gravity (N·m)          : {fmt(terms.g, 1, 4)}")
    typer.echo("Z = −∂l_c/∂α (mm/rad), rows = joints, columns = cables")
    for row in terms.Z:
        typer.echo("    " + fmt(row, 1e3, 2))
    typer.echo("M with geared motors (kg·m²)")
    for row in terms.M:
        typer.echo("    " + fmt(row, 1, 5))
