"""`xneck kinematics ...` and `xneck workspace`: the 2-X paper's analyses from the command line.

Angles are printed in degrees (SI radians inside); lengths are in whatever unit L and b are given.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from server.cli.options import check_output, echo_json, fail, write_failed
from twin.analysis.kinematics import FLAT, check_design, cuspidal_threshold, det_jacobian_2x, fk, ik_2x, is_cuspidal
from twin.analysis.workspace import MEMORY_BUDGET, max_grid

kinematics_app = typer.Typer(
    help="Kinematics of the 2-X manipulator (Furet & Wenger 2019): inverse kinematics, cuspidality.",
    no_args_is_help=True,
    add_completion=False,
)


def _design(L: float, b: float) -> tuple[float, float]:
    try:
        return check_design(L, b)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None


@kinematics_app.command("ik")
def ik(
    L: float = typer.Option(..., "--L", help="Diagonal bar length (any unit: x, y and the outputs are in it)."),
    b: float = typer.Option(..., "--b", help="Base/top bar length, 0 < b < L (the unit of L)."),
    x: float = typer.Option(..., "--x", help="Target x of the top-bar middle (unit of L)."),
    y: float = typer.Option(..., "--y", help="Target y of the top-bar middle (unit of L)."),
    json_out: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """Every inverse kinematic solution (θ1, θ2) at (x, y), from the quartic of eqs. (7)-(9)."""
    L, b = _design(L, b)
    if not (np.isfinite(x) and np.isfinite(y)):
        raise typer.BadParameter(f"x and y must be finite, got x = {x}, y = {y}")
    # Solved in units of L (the angles do not depend on the unit): L = 1e100 or 1e-200 overflowed
    # or underflowed the quartic's terms, a traceback or a wrong aspect.
    _, b1 = _design(1.0, b / L)
    x1, y1 = x / L, y / L
    sols = ik_2x(x1, y1, 1.0, b1)
    rows = []
    for th in sols:
        res = float(np.linalg.norm(fk(th, 1.0, b1) - (x1, y1))) * L
        rows.append(
            {
                "theta_deg": [round(float(v), 6) for v in np.degrees(th)],
                "theta_rad": [float(v) for v in th],
                "up": [bool(abs(v) < FLAT) for v in th],
                "aspect": int(np.sign(det_jacobian_2x(th[0], th[1], 1.0, b1))),
                "fk_residual": res,
            }
        )
    if json_out:
        echo_json({"L": L, "b": b, "x": x, "y": y, "count": len(rows), "solutions": rows})
        return
    typer.echo(f"2-X IK at (x, y) = ({x:g}, {y:g}), L = {L:g}, b = {b:g}: {len(rows)} solution(s)")
    if not rows:
        typer.echo("  (point outside the workspace)")
        return
    typer.echo(f"  {'#':>2}  {'θ1 (deg)':>10}  {'θ2 (deg)':>10}  {'joints':>9}  {'aspect':>6}  {'|FK−p|':>9}")
    for i, r in enumerate(rows, 1):
        ups = "/".join("up" if u else "down" for u in r["up"])
        t1, t2 = r["theta_deg"]
        typer.echo(f"  {i:>2}  {t1:>10.3f}  {t2:>10.3f}  {ups:>9}  {r['aspect']:>+6d}  {r['fk_residual']:>9.1e}")


@kinematics_app.command("cuspidal")
def cuspidal(
    L: float = typer.Option(..., "--L", help="Diagonal bar length (any unit: x, y and the outputs are in it)."),
    b: float = typer.Option(..., "--b", help="Base/top bar length, 0 < b < L (the unit of L)."),
    json_out: bool = typer.Option(False, "--json", help="Print JSON instead of text."),
) -> None:
    """Is the 2-X chain cuspidal? Closed form b < L < b√6 (section 2.6), checked by counting IK
    solutions numerically along the symmetry axis, and the threshold found by a sweep of b."""
    from twin.analysis.workspace import cuspidality_threshold_numeric, max_solutions_on_axis

    L, b = _design(L, b)
    _, b1 = _design(1.0, b / L)  # in units of L, as ik: the numerical sweep overflowed for L = 1e200
    result = {
        "L": L,
        "b": b,
        "cuspidal": is_cuspidal(1.0, b1),
        "condition": "b < L < b*sqrt(6)",
        "b_threshold": cuspidal_threshold(1.0) * L,
        "b_threshold_numeric": cuspidality_threshold_numeric(1.0) * L,
        "max_ik_solutions_found": max_solutions_on_axis(1.0, b1),
    }
    if json_out:
        echo_json(result)
        return
    verdict = "cuspidal (four IK solutions in two regions)" if result["cuspidal"] else "not cuspidal (two IK solutions)"
    typer.echo(f"L = {L:g}, b = {b:g} (b/L = {b / L:.4g}): {verdict}")
    typer.echo(f"  condition b < L < b√6  <=>  b > L/√6 = {result['b_threshold']:.6g}")
    typer.echo(f"  threshold from a numerical sweep of b: {result['b_threshold_numeric']:.6g}")
    typer.echo(f"  most IK solutions found on the axis x = 0: {result['max_ik_solutions_found']}")


_DEFAULT_GRID = {"2x": 300, "3x": 31}
_N_HELP = (f"Grid points per axis, >= 2 (0: {_DEFAULT_GRID['2x']} for 2x, {_DEFAULT_GRID['3x']} for 3x); "
           f"at most {max_grid('2x')} for 2x and {max_grid('3x')} for 3x, the grids whose maps fit in "
           f"~{MEMORY_BUDGET / 1e9:.1f} GB of memory (n² points for 2x, n³ for 3x). A coarse grid is a "
           "quick preview: a panel with no grid point in the workspace says so.")


def workspace(
    design: str = typer.Option("2x", "--design", help="2x (the 2-X paper's figures) or 3x (the prototype)."),
    out: Path = typer.Option(Path("artifacts/workspace"), "--out", help="Directory for the PNG files."),
    n: int = typer.Option(0, "--n", help=_N_HELP),
) -> None:
    """Write workspace, wrench-feasible workspace and stiffness maps as PNG files."""
    from twin.analysis.workspace import grid_problem, write_2x_figures, write_3x_figures

    if design not in ("2x", "3x"):
        raise typer.BadParameter(f"--design must be 2x or 3x, got {design!r}")
    if n < 0 or n == 1:
        raise fail(f"--n {n}: 0 (the default) or >= 2 points per axis")
    n = n or _DEFAULT_GRID[design]
    # From the estimated bytes of the maps, before any array and before --out is made: the 3-X
    # maps grow with n³ (--n 400 ran into the OOM killer at 22 GB).
    if (problem := grid_problem(design, n)) is not None:
        raise fail(problem)
    check_output(out, directory=True)  # before the maps are computed
    try:
        paths = write_2x_figures(out, n=n) if design == "2x" else write_3x_figures(out, n=n)
    except OSError as exc:
        raise write_failed(out, exc) from None
    for p in paths:
        typer.echo(str(p))
