"""`xneck study control|identification|design ... --out DIR`: many headless twin runs on Dask (issue 19).

The flags say the common things; a study file (TOML, keys as server.studies.spec.Study's fields)
says the rest, the flags given on top of it (``--vary`` adds to the file's). Every spec is checked
before a cluster starts. A rerun on the same DIR goes on where the last one stopped.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path

import typer

from server.cli.options import PARAMS_OPTION, SET_OPTION, check_input, check_output, echo_json, write_failed

study_app = typer.Typer(help="Studies: Monte Carlo robustness, identification and design sweeps on Dask "
                        "(docs/studies.md).", no_args_is_help=True)

OUT = typer.Option(..., "--out", help="Study directory: Parquet rows (runs/law=<n>/), summary.json, figures/. "
                   "A rerun resumes it.")
SAMPLES = typer.Option(None, "--samples", help="Random draws per grid point (default 1).")
VARY = typer.Option(None, "--vary", help="PATH=SPEC, repeatable: a parameter-file path (friction.f_s, "
                    "cables.variable.k[2], geometry.b) or truth.<effect>.<key>; SPEC 10% (relative spread, "
                    "U(0.9,1.1) x nominal), N(mu,sigma), U(a,b) or a grid first:last:n (n values, both ends included: n >= 2, or n = 1 with first = last).")
SEED = typer.Option(None, "--seed", help="Study seed: every run's draws and twin seed follow from it (default 0).")
WORKERS = typer.Option(None, "--workers", help="Local Dask worker processes (default and at most: the CPUs this process may use).")
SCHEDULER = typer.Option(None, "--scheduler", help="An existing Dask cluster, tcp://HOST:PORT (see docs/studies.md).")
AS_JSON = typer.Option(False, "--json", help="Print the summary as JSON.")
FILE = typer.Option(None, "--study", help="Study file (TOML) for anything the flags cannot say.")
TRUTH = typer.Option(None, "--truth", help="What the twin simulates: model, robot or a truth file (default: robot for an identification "
                     "study, model otherwise).")
ALPHA_IP = typer.Option(None, "--alpha-ip", help="The twin's α_IP: noise (default, fast) or camera.")
TRAJECTORY = typer.Option(None, "--trajectory", help="Trajectory name or file (default: control_test; "
                          "identification for an identification study).")
MODEL_FOLLOWS = typer.Option(None, "--model-follows/--model-nominal", help="The controller's model gets the "
                             "sampled values too (default: it keeps the nominal ones, the robustness question).")


def _run(kind: str, out: Path, as_json: bool, workers: int | None, scheduler: str | None, **fields) -> None:
    from server.studies.execute import run_study
    from server.studies.spec import StudyError, study_from

    if workers is not None and workers < 1:
        raise typer.BadParameter("must be >= 1", param_hint="--workers")
    check_output(out, directory=True)  # before a cluster starts and runs are lost
    if fields.get("file") is not None:
        check_input(fields["file"], "study file", "--study")
    if fields.get("params_file") is not None:
        check_input(Path(fields["params_file"]), "parameter file", "--params")
    line_open = [False]  # a progress line printed and not ended: an error starts on a line of its own

    def progress(done: int, total: int, message: str) -> None:
        line_open[0] = done < total
        _progress(done, total, message)

    stop = threading.Event()

    def interrupt(_signum: int, _frame: object) -> None:
        if stop.is_set():  # a second Ctrl-C: no summary, at once (the rows written so far are kept)
            raise KeyboardInterrupt
        stop.set()
        line_open[0] = False
        typer.secho("\nstopping: the runs in flight are cancelled, the finished rows kept and summarized "
                    "(Ctrl-C again to quit at once)", err=True, fg="yellow")

    previous = signal.signal(signal.SIGINT, interrupt)  # the workers never take it (execute._sigint_blocked)
    try:
        study = study_from(kind, **fields)
        summary = run_study(study, out, workers=workers, scheduler=scheduler, progress=progress, stop=stop)
    except StudyError as exc:
        if line_open[0]:
            typer.echo("", err=True)
        typer.secho(f"error: {exc}", err=True, fg="red")
        raise typer.Exit(2) from None
    except OSError as exc:  # the disk filled or the folder went away since the check; finished rows are kept
        if exc.filename is None:
            raise  # not a file: a scheduler's connection, not an output problem
        if line_open[0]:
            typer.echo("", err=True)
        raise write_failed(Path(exc.filename), exc) from None  # the file at fault (report.py names it), not DIR
    except KeyboardInterrupt:
        typer.secho(f"\ninterrupted: the rows finished so far are in {out} (no summary written); "
                    "run the same command again to go on", err=True, fg="yellow")
        raise typer.Exit(130) from None
    finally:
        signal.signal(signal.SIGINT, previous)
    if as_json:
        echo_json({k: v for k, v in summary.items() if k != "study"})
    else:
        typer.echo(_table(summary))
        typer.echo(f"rows: {out}/runs; summary: {out}/summary.json; figures: {out}/figures")
    if stop.is_set() and not summary["complete"]:
        typer.secho(f"interrupted: {summary['runs_done']}/{summary['runs_total']} runs finished, their rows and "
                    f"summary are in {out}; run the same command again to go on", err=True, fg="yellow")
        raise typer.Exit(130)


def _progress(done: int, total: int, message: str) -> None:
    from server.cli.campaign import _print_progress

    _print_progress(done / max(total, 1), f"{done}/{total} runs {message}")


def _table(summary: dict) -> str:
    lines = [f"{summary['kind']} study {summary['digest']}: {summary['runs_done']}/{summary['runs_total']} runs, "
             f"outcomes {summary['outcomes']}"]
    for law, metrics in summary["metrics"].items():
        lines.append("design" if law == "0" else f"law {law}")
        for name, s in metrics.items():
            if s:
                lines.append(f"  {name:<28s} median {s['median']:10.4g}  p5 {s['p5']:10.4g}  p95 {s['p95']:10.4g}  (n={s['n']})")
        for name, rhos in summary["sensitivity_spearman"].get(law, {}).items():
            strong = {k: v for k, v in rhos.items() if v is not None and abs(v) >= 0.3}
            if strong:
                lines.append(f"  {name:<28s} Spearman ρ " + ", ".join(f"{k} {v:+.2f}" for k, v in strong.items()))
    return "\n".join(lines)


def study_control(
    out: Path = OUT, samples: int | None = SAMPLES, vary: list[str] | None = VARY, seed: int | None = SEED,
    law: list[int] | None = typer.Option(None, "--law", help="Control law 1, 2 or 3; repeat to compare (default 2)."),
    no_pulleys: bool | None = typer.Option(None, "--no-pulleys/--pulleys", help="Neglect the pulleys in the controller's model."),
    trajectory: str | None = TRAJECTORY, truth: str | None = TRUTH, alpha_ip: str | None = ALPHA_IP,
    model_follows: bool | None = MODEL_FOLLOWS, workers: int | None = WORKERS, scheduler: str | None = SCHEDULER,
    as_json: bool = AS_JSON, study_file: Path | None = FILE, params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """The §7 control campaign per run (lockstep twin, no bus): e, e_α, forces per law, and their sensitivity."""
    _run("control", out, as_json, workers, scheduler, file=study_file, samples=samples, vary=tuple(vary or ()),
         seed=seed, laws=tuple(law or ()), no_pulleys=no_pulleys, trajectory=trajectory, truth=truth, alpha_ip=alpha_ip,
         model_follows=model_follows, params_file=str(params_file) if params_file else None, set=tuple(overrides or ()))


def study_identification(
    out: Path = OUT, samples: int | None = SAMPLES, vary: list[str] | None = VARY, seed: int | None = SEED,
    trajectory: str | None = TRAJECTORY, truth: str | None = TRUTH, alpha_ip: str | None = ALPHA_IP,
    estimator: str | None = typer.Option(None, "--estimator", help="Table 2's estimator, as `xneck identify "
                                         "--estimator` (default auto; iv, ols, wls, loadfriction, outputerror)."),
    workers: int | None = WORKERS, scheduler: str | None = SCHEDULER, as_json: bool = AS_JSON,
    study_file: Path | None = FILE, params_file: Path | None = PARAMS_OPTION, overrides: list[str] | None = SET_OPTION,
) -> None:
    """The §5.2.2 identification campaign and pipeline per run: identified f_s, k, λ against the twin's, their σ,
    and whether the ±2σ interval covers the truth (over many runs: the coverage test of issue 17)."""
    _run("identification", out, as_json, workers, scheduler, file=study_file, samples=samples, vary=tuple(vary or ()),
         seed=seed, trajectory=trajectory, truth=truth, alpha_ip=alpha_ip, estimator=estimator,
         params_file=str(params_file) if params_file else None, set=tuple(overrides or ()))


def study_design(
    out: Path = OUT, samples: int | None = SAMPLES, vary: list[str] | None = VARY, seed: int | None = SEED,
    configurations: int | None = typer.Option(None, "--configurations", help="Random configurations per design "
                                              "within the joint limit (default 2000)."),
    workers: int | None = WORKERS, scheduler: str | None = SCHEDULER, as_json: bool = AS_JSON,
    study_file: Path | None = FILE, params_file: Path | None = PARAMS_OPTION, overrides: list[str] | None = SET_OPTION,
) -> None:
    """Wrench-feasible workspace and stiffness of N-joint designs over a grid (geometry.b, springs.k_left,
    geometry.r, geometry.n_joints, ...): maps per design."""
    _run("design", out, as_json, workers, scheduler, file=study_file, samples=samples, vary=tuple(vary or ()),
         seed=seed, design_configurations=configurations, params_file=str(params_file) if params_file else None,
         set=tuple(overrides or ()))
