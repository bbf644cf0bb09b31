"""``xneck identify CAMPAIGN.mcap [--json] [--out DIR]``: offline identification of a recorded
campaign (3-X paper §5), Tables 1-2 printed, Figs. 4-8 and the identified parameter set written."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from server.cli.options import POSITIVE, check_output, echo_json, fail, input_problem, write_failed

if TYPE_CHECKING:  # the command line starts without numpy (every command module is imported)
    import numpy as np

#: The archive outcomes (``xneck.campaign``'s ``outcome``) whose record is the whole campaign, as the
#: console judges them: it identifies a finished or degraded campaign (server/campaign_runner.py),
#: ``analysis_failed`` is one of those whose analysis failed (refit here, e.g. with --window), and ''
#: an archive without the field. Any other (aborted, interrupted, failed) holds a campaign cut short:
#: the console saves no parameter set from it (409), and xneck identify fits it only with --partial.
WHOLE_OUTCOMES = ("finished", "degraded", "analysis_failed", "")


def identify(
    campaign: Path = typer.Argument(..., help="Campaign MCAP file recorded on the identification trajectory."),
    json_out: bool = typer.Option(False, "--json", help="Print the tables and checks as JSON."),
    out: Path | None = typer.Option(None, "--out", help="Directory for figures and the parameter set "
                                       "(default: <campaign stem>_identification next to the file)."),
    params_file: Path | None = typer.Option(None, "--params", help="Base parameter file (default: the set the "
                                            "campaign ran with, recorded in its archive; else the prototype's)."),
    overrides: list[str] | None = typer.Option(None, "--set", help="Override one value of the base parameter "
                                               "file, e.g. --set motors.gear_loss_forward=0.05."),
    cutoff_hz: float | None = typer.Option(None, "--cutoff-hz", callback=POSITIVE,
                                           help="Override the filter cutoff rule (Hz), within what the record allows: "
                                           "from about 4/(its duration − 2 s), as the filter edges dropped at each "
                                           "end must leave 64 instants, to below the Nyquist frequency (≈ 15 Hz); "
                                           "one out of range is refused, the record's range stated."),
    threshold: float | None = typer.Option(None, "--threshold", callback=POSITIVE, help="Relative σ above which "
                                           "a parameter is badly identified (a fraction > 0; default: the "
                                           "pipeline's, 0.10)."),
    no_alpha_hat: bool = typer.Option(False, "--no-alpha-hat", help="Skip the α̂ reconstruction (Fig. 8)."),
    validate: Path | None = typer.Option(None, "--validate", help="Another campaign MCAP (e.g. a §7 control "
                                         "test): Figs. 4-8 and the errors on it with the models fitted here, "
                                         "beside the in-sample ones (figures in <out>/validation)."),
    estimator: str = typer.Option("auto", "--estimator", help="auto (default): where the campaign's motor "
                                  "friction grows with the load (a one-sided test of the load-friction fit's pooled "
                                  "μ), outputerror if that fit finds the line's damping light (a quasi-static pose), "
                                  "else loadfriction; iv where it does not; iv: instrumental "
                                  "variables from the model re-simulated on the encoders, consistent under camera "
                                  "noise; ols: eq. 49 as printed; wls: rows weighted by their residual σ; "
                                  "loadfriction: Table 2 with the motor friction growing with the load and a cable "
                                  "creep term (docs/identification-coverage.md); outputerror: the neck's pose "
                                  "simulated from the encoders against α_IP and the motor forces, fitted together "
                                  "with the springs' rates and the pulleys' radius (free of the friction model's "
                                  "errors). Table 1 is always by iv or the linear estimator named."),
    sigma: str = typer.Option("hac", "--sigma", help="hac (default): Newey-West σ for correlated residuals; "
                              "white: eq. 50 as printed (too small on filtered data)."),
    no_bounds: bool = typer.Option(False, "--no-bounds", help="Unbounded least squares (default: k, f_s > 0 and "
                                   "λ, c_a ≥ 0, the parameters held at a bound reported)."),
    creep_time_s: float | None = typer.Option(None, "--creep-time-s", help="The cable line's creep time constant "
                                              "(s), measured apart (a weight hung on a sample of the line, its "
                                              "elongation recorded): held in the load-friction fit instead of "
                                              "estimated from the campaign (default; on the twin the estimate does "
                                              "as well: docs/identification-coverage.md, \"The creep element and "
                                              "its time constant\")."),
    alpha_ip_source: str | None = typer.Option(None, "--alpha-ip-source", help="The camera whose α_IP is read "
                                               "(its CameraAlpha source: twin-render, twin-noise, usb:0, "
                                               "file:NAME), in this campaign and --validate's: an archive holding "
                                               "the α_IP of several cameras is refused without it, naming them."),
    window: str | None = typer.Option(None, "--window", help="START:END (s, on the record's clock, as its "
                                      "error or report gives times): fit only this span, e.g. the one without gaps "
                                      "that a refused campaign's error names."),
    force: bool = typer.Option(False, "--force", help="Replace the files an earlier identification wrote in --out, "
                               "its parameter set and figures (default: refused, as archives are never overwritten)."),
    partial: bool = typer.Option(False, "--partial", help="Fit a campaign that did not finish (its archive's "
                                 "outcome aborted, interrupted or failed; refused by default, as the console "
                                 "saves no set from it): its excitation was cut short, so its estimates and their "
                                 "σ can be far off. The output and the set's header say so."),
) -> None:
    """Identify friction and cable stiffness from a campaign (Tables 1-2, Figs. 4-8)."""
    problem = input_problem(campaign, "campaign file")
    if problem:  # '.' or '/' have no name to derive the default --out from: say why now
        raise fail(f"cannot read campaign: {problem}")
    out_dir = out or campaign.with_name(campaign.stem + "_identification")
    check_output(out_dir, directory=True)  # before the fit, which would otherwise be lost at its end
    from bridge.archive import ArchiveError
    from bridge.archive_read import check_finished, read_campaign_info
    from twin.identification.options import check_sigma, check_variable_options

    try:  # the options and the files, before the archive is read and the fit runs
        check_variable_options(estimator, creep_time_s)
        check_sigma(sigma)
        window_s = _window(window) if window is not None else None
    except ValueError as exc:
        raise fail(str(exc)) from None
    for what, path in (("campaign", campaign), ("validation campaign", validate)):
        try:
            if path is not None:
                check_finished(path)
        except ArchiveError as exc:
            raise fail(f"cannot read {what}: {exc}") from None
    try:
        info = read_campaign_info(campaign)
    except ArchiveError as exc:
        raise fail(f"cannot read campaign: {exc}") from None
    ended = _how_it_ended(info)
    if validate is not None:
        try:
            info_b = read_campaign_info(validate)
        except ArchiveError as exc:
            raise fail(f"cannot read validation campaign: {exc}") from None
        if validate.resolve() == campaign.resolve() or info_b.get("campaign_id", "") == info.get("campaign_id", "") != "":
            # its errors "on B" are the in-sample ones, and read as a validation (audit of session 49)
            typer.echo(f"warning: validation campaign {validate} is the identified campaign "
                       f"({info.get('campaign_id') or campaign}): its errors are in-sample, not a validation; "
                       "validate on another campaign (e.g. a §7 control test)", err=True)
        if info_b.get("outcome", "") not in WHOLE_OUTCOMES:  # a check on part of a run: said, not refused
            typer.echo(f"warning: validation campaign {validate} did not finish ({_how_it_ended(info_b)}): the "
                       "errors are of the part it recorded", err=True)
    if info.get("outcome", "") not in WHOLE_OUTCOMES and not partial:
        # before the fit: an aborted campaign's set was written with exit 0 and no word, 20-25 % off
        # the truth with ±2σ missing it (user audit of 2026-11-30)
        raise fail(f"campaign {campaign} did not finish ({ended}): its record is partial; the console "
                   f"saves no parameter set from it; --partial to fit it anyway")
    if info.get("outcome") == "degraded":  # identified, as the console does, but said
        typer.echo(f"warning: campaign {campaign} ran below the real-time quality thresholds ({ended}): its "
                   f"identification may suffer from it", err=True)
    # After the checks: the pipeline's imports (scipy.signal, numba) take 2 s a refusal need not wait.
    from controller.trajectory import recorded_excitation
    from twin.identification.pipeline import (
        DEFAULT_THRESHOLD,
        IdentificationError,
        identified_name,
        write_identified,
    )
    from twin.identification.record import identify_record
    from twin.identification.report import report_dict, tables_text, write_figures
    from twin.model.params import ParameterError, differing_keys, load_params, params_from_toml, parse_override

    data_b = _validation_campaign(validate, alpha_ip_source) if validate is not None else None
    try:
        changes = dict(parse_override(o) for o in overrides or [])
        recorded = info.get("parameters_toml", "")
        if params_file is None and recorded:
            # the set the campaign ran with, as the console refits it: the prototype's had been taken
            # for an archive of another robot's set, without a word (audit of session 49)
            base = params_from_toml(recorded, f"the parameter set recorded in {campaign} (--params FILE for "
                                    f"another)", changes)
            typer.echo(f"note: base parameter set {base.name!r}, the one the campaign ran with (its archive's); "
                       f"--params FILE for another", err=True)
        else:
            base = load_params(params_file, changes)
            try:
                ran = params_from_toml(recorded, f"the set recorded in {campaign}", changes) if recorded else None
            except ParameterError as exc:  # an archive is hostile input: said, the set chosen is used
                typer.echo(f"warning: not compared with the campaign's own set: {exc}", err=True)
                ran = None
            if ran is not None and (keys := differing_keys(base, ran)):
                typer.echo(f"warning: the base set differs from the one {campaign} ran with (its archive's), in "
                           f"{len(keys)} value(s): {', '.join(keys[:8])}{', ...' if len(keys) > 8 else ''}", err=True)
        if not re.fullmatch(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,63}", base.name):
            # it names the files written into --out: "/x/y" or "../z" wrote them elsewhere (audit of 2026-11-28)
            raise ParameterError(f"parameter set name {base.name!r} cannot name a file in --out: use 1-64 letters, "
                                 f"digits, '_', '.' or '-', not starting with '.' (--set name=...)")
        earlier = out_dir / f"{identified_name(base.name)}.toml"
        if earlier.exists() and not force:
            # before the fit: an earlier identification's set (another estimator, another campaign's
            # analysis) had been replaced without a word (user audit of session 45)
            raise ParameterError(f"{earlier} exists: an earlier identification's parameter set; --out another "
                                 f"directory, or --force to replace it")
        if (files := _earlier_outputs(out_dir)) and not force:
            # its figures would be replaced beside its set, then of another fit (audit of session 49:
            # --set name=other rewrote fig4-7 next to the first set)
            raise ParameterError(f"{out_dir} holds an earlier identification's files ({', '.join(files)}): --out "
                                 f"another directory, or --force to replace them")
        if data_b is not None:  # before the fit: it was refused after A's fit and files (audit of 2026-11-27)
            sizes = {"motors": (data_b.theta_rad.shape[1], base.n_cables),
                     "joints": (data_b.alpha_ip_rad.shape[1], base.n_joints)}
            for what, (got, want) in sizes.items():
                if got != want:
                    raise IdentificationError(f"--validate {validate}: its record has {got} {what}, the parameter "
                                              f"set {base.name!r} {want}: it is another robot's campaign")
        ident = identify_record(campaign, base, excitation=recorded_excitation, cutoff_hz=cutoff_hz,
                                threshold=DEFAULT_THRESHOLD if threshold is None else threshold,
                                alpha_hat=not no_alpha_hat, estimator=estimator, sigma=sigma, bounded=not no_bounds,
                                creep_time_s=creep_time_s, alpha_ip_source=alpha_ip_source, window_s=window_s)
    except (IdentificationError, ParameterError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    # What the reader set aside (stray messages), on stderr: --json's stdout stays one document.
    for what, data in (("", ident.data), (f"--validate {validate}: ", data_b)):
        for note in data.notes if data is not None else ():
            typer.echo(f"note: {what}{note}", err=True)
    for note in ident.processed.notes:  # the record's gaps, bridged and not fitted
        typer.echo(f"note: {note}", err=True)
    est, proc, val, prov, new, report = (ident.estimate, ident.processed, ident.validation, ident.provenance,
                                         ident.params, ident.report)
    from twin.identification.timing import alpha_ip_timing

    if ident.data.kind not in ("", "identification"):
        # allowed (a researcher may), but said: nothing but an identification campaign's excitation
        # was designed to identify k and λ (user audit of session 45: silent)
        typer.echo(f"warning: {campaign} is a {ident.data.kind} campaign, not an identification one: its "
                   f"trajectory was not chosen to excite the friction and stiffness models (their σ below say how "
                   f"well it did); validate on it instead (--validate)", err=True)
    from twin.identification.pipeline import warned

    partial_fit = info.get("outcome", "") not in WHOLE_OUTCOMES
    if partial_fit:  # --partial: said on stderr, stdout, JSON, TOML
        warning = _partial_warning(ended, ident.data.t_s, info.get("trajectory", ""))
        prov = warned(prov, warning)
        typer.secho(f"warning: {warning}", err=True, fg="yellow")
    timing = alpha_ip_timing(ident.data)
    if timing.warn:  # also under --json: the fit used shifted α_IP
        typer.echo(f"warning: {timing.text()}", err=True)
        # and in the set: one whose camera was 2 s late was written with f_s 2.6 times off and
        # nothing in the file said so (audit of session 49)
        prov = warned(prov, timing.text())
    # B validated before anything is written: its failure (e.g. too little left fitted across its
    # gaps) had come after A's set and figures (review of session 51)
    cv = _cross_validation(ident, data_b, alpha_hat=not no_alpha_hat) if data_b is not None else None
    for note in cv.processed.notes if cv is not None else ():
        typer.echo(f"note: --validate {validate}: {note}", err=True)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        if force:  # replaced, not mixed: a figure or validation/ this run does not write stayed (review of session 49)
            _remove_earlier_outputs(out_dir)
        figures = write_figures(val, out_dir) if val is not None else []
        toml_path, prov_path = write_identified(out_dir / f"{new.name}.toml", new, prov)
        cross = (_write_cross_validation(cv, ident, validate, out_dir)
                 if validate is not None and cv is not None else None)
    except OSError as exc:  # the disk filled or the folder went away since the check
        raise write_failed(out_dir, exc) from None
    if json_out:
        doc = report_dict(est, proc, val, prov)
        doc["record_notes"] = list(ident.data.notes)
        doc["alpha_ip_timing"] = timing.as_dict()
        doc["campaign_outcome"] = {"outcome": info.get("outcome", ""), "message": info.get("message", ""),
                                   "partial": partial_fit}
        doc["warning"] = prov.warning
        doc["files"] = [str(p) for p in (*figures, toml_path, prov_path)]
        if cross is not None:
            doc["cross_validation"] = cross[0]
        echo_json(doc)
    else:
        if prov.warning:  # first, where a reader of the tables starts
            typer.echo(f"WARNING: {prov.warning}\n")
        typer.echo(tables_text(est, proc, val, prov.kept_base))
        typer.echo("")
        typer.echo("\n".join(report.lines()))
        typer.echo(timing.text())
        typer.echo(f"parameter set: {toml_path} (provenance {prov_path.name}); figures: {out_dir}"
                   + (" (see WARNING above)" if prov.warning else ""))
        if cross is not None:
            typer.echo("")
            typer.echo(cross[1])


#: What an identification writes in --out besides its set (twin/identification/report.write_figures,
#: and --validate's folder): a second run there would replace them under another run's set.
EARLIER_OUTPUTS = ("*-identified.toml", "*-identified.provenance.json", "fig[4-8]_*.png", "validation")


def _earlier_outputs(out_dir: Path) -> list[str]:
    """The names of an earlier identification's files in ``out_dir`` (none if it does not exist)."""
    if not out_dir.is_dir():
        return []
    # files, and the validation folder: a folder named like a figure is no identification's output
    return sorted({p.name for pattern in EARLIER_OUTPUTS for p in out_dir.glob(pattern)
                   if (p.is_dir() and not p.is_symlink()) == (pattern == "validation")})


def _remove_earlier_outputs(out_dir: Path) -> None:
    """Remove an earlier identification's files from ``out_dir`` (:data:`EARLIER_OUTPUTS`), for ``--force``."""
    import shutil

    for name in _earlier_outputs(out_dir):
        path = out_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)


def _how_it_ended(info: dict[str, str]) -> str:
    """A campaign's outcome and its message as the archive's ``xneck.campaign`` record gives them,
    e.g. "outcome aborted: stopped by the user"."""
    outcome, message = info.get("outcome", "") or "unknown", info.get("message", "")
    return f"outcome {outcome}" + (f": {message}" if message else "")


def _partial_warning(ended: str, t_s: np.ndarray, trajectory_json: str) -> str:
    """What a set fitted on a campaign that did not finish (``ended``: :func:`_how_it_ended`) must
    say: how much of its trajectory it recorded, the span of the motor states ``t_s`` (s) against
    the trajectory's duration (s) in the archive, when that can be read."""
    from controller.trajectory import trajectory_from_json

    recorded_s = float(t_s[-1] - t_s[0]) if len(t_s) >= 2 else 0.0
    try:
        planned_s = trajectory_from_json(trajectory_json).duration_s if trajectory_json else 0.0
    except Exception:  # noqa: BLE001 - an unreadable trajectory only loses the progress from the warning
        planned_s = 0.0
    progress = (f"{recorded_s:.1f} s recorded of its trajectory's {planned_s:.1f} s (about "
                f"{100 * min(recorded_s / planned_s, 1.0):.0f} %)" if planned_s > 0 else f"{recorded_s:.1f} s recorded")
    return (f"fitted on a PARTIAL campaign that did not finish ({ended}; {progress}): its excitation may be "
            f"incomplete, so these estimates and their ±2σ can be far off the truth (--partial)")


def _validation_campaign(path: Path, alpha_ip_source: str | None):
    """``--validate B`` read before anything is fitted: a bad B fails fast with its reason."""
    from controller.trajectory import recorded_excitation
    from twin.identification.pipeline import IdentificationError
    from twin.identification.processing import check_gaps
    from twin.identification.validation import load_validation_campaign

    try:
        data = load_validation_campaign(path, recorded_excitation, alpha_ip_source=alpha_ip_source)
    except IdentificationError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    try:
        check_gaps(data)  # here, before A's fit and files: it was found after them (audit of 2026-11-29)
    except IdentificationError as exc:
        typer.echo(f"error: validation campaign {data.campaign}: {_not_for_validation(str(exc))}", err=True)
        raise typer.Exit(2) from None
    return data


def _not_for_validation(message: str) -> str:
    """A pipeline error about the --validate campaign, whose hint to fit a span alone (--window) is
    for the identified campaign: following it windowed A and refused B again."""
    return re.sub(r"identify it alone with --window \S+",
                  "--window applies to the identified campaign, not to --validate's: validate on another campaign",
                  message)


def _cross_validation(ident, data_b, *, alpha_hat: bool):
    """A's models on campaign B (twin/identification/validation.py); a clean exit if B is unusable."""
    from twin.identification.pipeline import IdentificationError
    from twin.identification.validation import cross_validate

    try:
        return cross_validate(ident, data_b, alpha_hat=alpha_hat)
    except IdentificationError as exc:
        typer.echo(f"error: {_not_for_validation(str(exc))}", err=True)
        raise typer.Exit(2) from None


def _write_cross_validation(cv, ident, campaign_b: Path, out_dir: Path) -> tuple[dict, str]:
    """B's Figs. 4-8 in ``out_dir/validation``; returns the JSON summary and the text table."""
    from twin.identification.report import write_figures
    from twin.identification.validation import comparison_text, summary

    doc = summary(cv)
    figures = write_figures(cv.validation, out_dir / "validation")
    doc["files"] = [str(p) for p in figures]
    text = comparison_text(doc["errors"], f"{ident.data.campaign}", f"{cv.data.campaign} ({campaign_b})")
    return doc, text + f"\nfigures on the validation campaign: {out_dir / 'validation'}"


def _window(text: str) -> tuple[float, float]:
    """``--window START:END`` as two finite times (s), the start first; ValueError says why."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        t0, t1 = float(parts[0]), float(parts[1])
    except ValueError:
        raise ValueError(f"--window {text!r}: give START:END in seconds, e.g. --window 1.5:77.5") from None
    if not (math.isfinite(t0) and math.isfinite(t1) and t0 < t1):
        raise ValueError(f"--window {text!r}: START must be a finite time before END")
    return t0, t1
