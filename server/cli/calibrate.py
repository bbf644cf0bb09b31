"""``xneck twin calibrate CAMPAIGN.mcap [...] --out truth.toml [--validate B.mcap ...]``: fit a
truth's unknown values to recorded campaigns (twin/sim/calibrate.py) and write a truth file that
``--truth FILE`` loads everywhere. Progress goes to stderr, the result table to stdout."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import typer

from server.cli.options import (
    PARAMS_OPTION,
    POSITIVE,
    SET_OPTION,
    check_output,
    check_truth,
    echo_json,
    fail,
    load_cli_params,
    number,
    write_failed,
)


def calibrate(
    campaigns: list[Path] = typer.Argument(..., help="Campaign MCAP files to fit (e.g. a law 2 run)."),
    out: Path = typer.Option(..., "--out", help="Truth file to write (TOML; refused if it exists, unless --force)."),
    fit: list[str] | None = typer.Option(
        None, "--fit", help="A value to fit (repeatable), e.g. friction.static_ratio or "
        "actuation.torque_constant_factor[2]; default: static ratio, viscous friction, current-loop bandwidth, "
        "the four torque constants and the cable damping."),
    base: str = typer.Option("robot", "--base", callback=check_truth, help="Truth the fit starts from and keeps "
                             "for every value it does not fit: robot (twin/sim/robot_truth.toml) or a truth FILE."),
    validate: list[Path] | None = typer.Option(
        None, "--validate", help="Held-out campaign MCAP (repeatable): report how well the calibrated truth "
        "predicts it, beside the base truth."),
    delays: list[int] | None = typer.Option(
        None, "--delay", help="Command delays (ticks) to try (repeatable): the fit is run for each and the best "
        "kept. Default: the base truth's."),
    span: float | None = typer.Option(None, "--span", callback=POSITIVE,
                                      help="Use only the first SPAN seconds of each recording (s)."),
    horizon: float = typer.Option(0.25, "--horizon", callback=number(inf=True), help="Prediction horizon (s): the "
                                  "replay re-starts the motors from the encoders this often (inf: one open-loop replay)."),
    max_evaluations: int = typer.Option(
        200, "--max-evaluations", min=1, help="Cost evaluations of the fit at most (scipy's max_nfev), each a replay "
        "of every recording; the finite-difference Jacobians are not counted, and cost one replay more per fitted "
        "value: with the 8 default values, 1 runs 9 replays, 10 about 66, plus the --starts screen's (17 by "
        "default; the count run is printed). A fit stopped by this limit is still written, marked not converged."),
    starts: int = typer.Option(
        16, "--starts", min=0, max=1024, help="Points of the fitted values' bounds screened for the fit's start "
        "besides the base truth's values, each one replay of every recording (0: start from the base alone); "
        "the replays' mismatch has local minima."),
    use_twin_truth: bool = typer.Option(
        False, "--use-twin-truth", help="Twin recordings only, for diagnosing the twin: also fit the true "
        "tensions of the twin's Truth topic and start each replay at its true α. Off by default: a prototype's "
        "recording has no such topic, and a calibration that reads it sees the answer."),
    force: bool = typer.Option(False, "--force", help="Overwrite --out."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """Fit the truth's unknown values to recorded campaigns and write a truth file with provenance."""
    from twin.sim import calibrate as cal
    from twin.sim.truth import TruthError, believed_differently, load_truth, robot_base

    params = load_cli_params(params_file, overrides)
    if out.exists() and not force:
        raise fail(f"{out} exists: choose another --out or add --force")
    if out.suffix != ".toml":
        raise fail(f"--out must be a .toml file (what --truth loads), got {out}")
    check_output(out)  # before the fit, which would otherwise be lost at its end
    weights = cal.Weights(horizon_s=horizon)
    try:
        base_truth = load_truth(base)
        fitted = cal.unknowns(fit or cal.DEFAULT_FIT, params.n_cables)
        recordings = [cal.load_recording(p, params, span, use_twin_truth) for p in campaigns]
        held_out = [cal.load_recording(p, params, span, use_twin_truth) for p in validate or ()]
        for d in delays or ():
            base_truth.replace("timing", delay_ticks=d)  # a bad delay is refused before any fit
        robot = robot_base(base_truth, params)
    except (cal.CalibrationError, TruthError) as exc:
        raise fail(str(exc)) from None
    differ = believed_differently(robot, params) if robot is not params else []
    if differ:  # the replays run the base truth's robot, not --params/--set (twin/sim/truth.py)
        typer.echo(f"warning: the base truth {base!r} is a robot built from {robot.name}; the parameter set given "
                   f"differs in {', '.join(differ[:8])}{', ...' if len(differ) > 8 else ''}, which the replays do "
                   "not use: for another robot, start from a truth whose robot_params names its file", err=True)

    def progress(message: str) -> None:
        typer.echo(message, err=True)

    for rec in recordings:
        progress(f"{rec.name}: {rec.duration_s:.1f} s, {len(rec.t_s)} motor states, {len(rec.t_ip)} camera frames, "
                 f"tensions {'fitted (the twin Truth topic, --use-twin-truth)' if rec.tension is not None else 'not used'}")
    command = "xneck twin calibrate " + " ".join(shlex.quote(a) for a in sys.argv[3:]) \
        if sys.argv[1:3] == ["twin", "calibrate"] else ""
    results = []
    for d in delays or [None]:
        start = base_truth if d is None else base_truth.replace("timing", enabled=True, delay_ticks=d)
        if d is not None:
            progress(f"-- delay {d} tick(s)")
        results.append(cal.fit(recordings, params, start, fitted, weights, progress, max_evaluations,
                               command=command, base_name=base, starts=starts))
    result = min(results, key=lambda r: r.cost)
    truth = result.truth
    if delays:
        import msgspec

        costs = ", ".join(f"{d}: {r.cost:.4g}" for d, r in zip(delays, results, strict=True))
        truth = msgspec.structs.replace(truth, sources={**truth.sources, "timing.delay_ticks": (
            f"measurement: the delay of least cost among those tried by xneck twin calibrate (cost by delay {costs})")})
    validation = {}
    for rec in held_out:
        progress(f"validating on {rec.name}")
        validation[rec.name] = {f"base_{k}": v for k, v in cal.prediction_errors(rec, params, base_truth, weights).items()}
        validation[rec.name].update(cal.prediction_errors(rec, params, truth, weights))
    if validation:
        truth = cal.with_validation(truth, validation)
    header = (f"A truth calibrated by `xneck twin calibrate` (twin/sim/calibrate.py) on {', '.join(r.name for r in recordings)}.\n"
              f"Values not fitted are the base truth's ({base}); see [calibration] for the fit.")
    if not result.converged:
        header += (f"\nThe fit is {cal.NOT_CONVERGED} (--max-evaluations {max_evaluations}): the fitted values are "
                   "where it stopped, not a converged measurement.")
        typer.secho(f"warning: the fit is {cal.NOT_CONVERGED} (--max-evaluations {max_evaluations}, "
                    f"{result.evaluations} replays): the truth written is marked so; raise --max-evaluations for a "
                    "converged fit", err=True, fg="yellow")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        cal.check_loadable(cal.truth_toml(truth, header), out)
    except cal.CalibrationError as exc:
        raise fail(str(exc)) from None
    except OSError as exc:  # the disk filled or the folder went away since the check
        raise write_failed(out, exc) from None
    summary = {
        "out": str(out), "fitted": {u.name: {"value": float(v), "sigma": float(s)}
                                    for u, v, s in zip(result.fitted, result.values, result.sigma, strict=True)},
        "delay_ticks": truth.timing.delay_ticks if truth.timing.enabled else 0,
        "residual_rms": result.residual_rms, "per_recording": result.per_recording,
        "evaluations": sum(r.evaluations for r in results), "validation": validation,
        "converged": result.converged,
        "status": "converged" if result.converged else cal.NOT_CONVERGED,
    }
    if as_json:
        echo_json(summary)
        return
    typer.echo(f"calibrated truth written to {out} (load it with --truth {out})")
    typer.echo(f"{'value':42s} {'fitted':>10s} {'± 1 σ':>10s} {'base':>10s}")
    for u, v, s in zip(result.fitted, result.values, result.sigma, strict=True):
        typer.echo(f"{u.name:42s} {v:10.4g} {s:10.2g} {cal.current_value(base_truth, u, params.n_cables):10.4g}")
    typer.echo(f"delay: {summary['delay_ticks']} tick(s); {summary['evaluations']} replays of every recording")
    typer.echo(_errors_table("fit residuals (RMS, replay − recording)", result.per_recording))
    if validation:
        typer.echo(_errors_table("held-out predictions (RMS; base → calibrated)", validation))


def _errors_table(title: str, rows: dict[str, dict[str, float]]) -> str:
    kinds = (("theta_rad", "θ (rad)"), ("alpha_ip_deg", "α_IP (°)"), ("tension_N", "tension (N)"))
    lines = [title, f"  {'recording':40s}" + "".join(f"{label:>22s}" for _, label in kinds)]
    for name, errors in rows.items():
        cells = []
        for kind, _ in kinds:
            if kind not in errors:
                cells.append(f"{'–':>22s}")
            elif f"base_{kind}" in errors:
                cells.append(f"{errors[f'base_{kind}']:10.3f} → {errors[kind]:8.3f}")
            else:
                cells.append(f"{errors[kind]:22.3f}")
        lines.append(f"  {name:40s}" + "".join(cells))
    return "\n".join(lines)
