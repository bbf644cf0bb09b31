"""``xneck identify CAMPAIGN.mcap [--json] [--out DIR]``: offline identification of a recorded
campaign (3-X paper §5), Tables 1-2 printed, Figs. 4-8 and the identified parameter set written."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def identify(
    campaign: Path = typer.Argument(..., help="Campaign MCAP file recorded on the identification trajectory."),
    json_out: bool = typer.Option(False, "--json", help="Print the tables and checks as JSON."),
    out: Path | None = typer.Option(None, "--out", help="Directory for figures and the parameter set "
                                       "(default: <campaign stem>_identification next to the file)."),
    params_file: Path | None = typer.Option(None, "--params", help="Base parameter file (default: prototype)."),
    cutoff_hz: float | None = typer.Option(None, "--cutoff-hz", help="Override the filter cutoff rule (Hz)."),
    threshold: float | None = typer.Option(None, "--threshold", help="Relative σ above which a parameter is "
                                              "badly identified (default: the pipeline's, 0.10)."),
    no_alpha_hat: bool = typer.Option(False, "--no-alpha-hat", help="Skip the α̂ reconstruction (Fig. 8)."),
) -> None:
    """Identify friction and cable stiffness from a campaign (Tables 1-2, Figs. 4-8)."""
    from controller.trajectory import recorded_excitation
    from twin.identification.pipeline import DEFAULT_THRESHOLD, IdentificationError, write_identified
    from twin.identification.record import identify_record
    from twin.identification.report import report_dict, tables_text, write_figures
    from twin.model.params import ParameterError, load_params

    try:
        base = load_params(params_file)
        ident = identify_record(campaign, base, excitation=recorded_excitation, cutoff_hz=cutoff_hz,
                                threshold=DEFAULT_THRESHOLD if threshold is None else threshold,
                                alpha_hat=not no_alpha_hat)
    except (IdentificationError, ParameterError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    out_dir = out or campaign.with_name(campaign.stem + "_identification")
    out_dir.mkdir(parents=True, exist_ok=True)
    est, proc, val, prov, new, report = (ident.estimate, ident.processed, ident.validation, ident.provenance,
                                         ident.params, ident.report)
    figures = write_figures(val, out_dir) if val is not None else []
    toml_path, prov_path = write_identified(out_dir / f"{new.name}.toml", new, prov)
    if json_out:
        doc = report_dict(est, proc, val, prov)
        doc["files"] = [str(p) for p in (*figures, toml_path, prov_path)]
        typer.echo(json.dumps(doc, indent=2, default=float))
    else:
        typer.echo(tables_text(est, proc, val, prov.kept_base))
        typer.echo("")
        typer.echo("\n".join(report.lines()))
        typer.echo(f"parameter set: {toml_path} (provenance {prov_path.name}); figures: {out_dir}")
