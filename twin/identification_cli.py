"""``xneck identify CAMPAIGN.mcap [--json] [--out DIR]``: offline identification of a recorded
campaign (3-X paper §5), Tables 1-2 printed, Figs. 4-8 and the identified parameter set written.

The MCAP is read with :func:`server.archive.read_campaign`; encoder angles and applied forces come
from ``/xneck/motor/state`` (``theta_rad``, ``force_applied_N``, ``stamp_s``), α_IP from
``/xneck/camera/alpha_ip`` (``alpha_ip_rad``, ``capture_stamp_s``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from twin.identification import (
    DEFAULT_THRESHOLD, CampaignData, IdentificationError, identified_params, identify_all, make_provenance,
    preprocess, validate, write_identified,
)
from twin.params import ParameterError, load_params

MOTOR_TOPIC = "/xneck/motor/state"
CAMERA_TOPIC = "/xneck/camera/alpha_ip"


def campaign_data_from_mcap(path: str | Path) -> CampaignData:
    """Campaign arrays from an archived campaign. Raises :class:`IdentificationError` for a
    missing, truncated or damaged file and for missing or empty channels."""
    from server.archive import ArchiveError, read_campaign

    try:
        camp = read_campaign(path)
    except ArchiveError as exc:
        raise IdentificationError(f"cannot read campaign: {exc}") from None
    missing = [t for t in (MOTOR_TOPIC, CAMERA_TOPIC) if not camp.topics.get(t)]
    if missing:
        have = ", ".join(sorted(camp.topics)) or "none"
        raise IdentificationError(f"{path}: missing channel(s) {', '.join(missing)} (channels present: {have})")
    motor = [m for _, m in camp.topics[MOTOR_TOPIC]]
    frames = [m for _, m in camp.topics[CAMERA_TOPIC]]
    try:
        t = np.array([m.stamp_s for m in motor], dtype=float)
        theta = np.array([m.theta_rad for m in motor], dtype=float)
        force = np.array([m.force_applied_N for m in motor], dtype=float)
        t_ip = np.array([m.capture_stamp_s for m in frames], dtype=float)
        alpha = np.array([m.alpha_ip_rad for m in frames], dtype=float)
    except (AttributeError, ValueError) as exc:
        raise IdentificationError(f"{path}: motor or camera messages are malformed ({exc})") from None
    # Recorder order is receive order; the identification needs sample order. A lockstep twin
    # re-publishes its state while it waits for a command: keep one sample per time stamp.
    _, order = np.unique(t, return_index=True)
    _, order_ip = np.unique(t_ip, return_index=True)
    campaign = camp.info.get("campaign_id") or Path(path).stem
    return CampaignData(t[order], theta[order], force[order], t_ip[order_ip], alpha[order_ip], campaign=campaign,
                        excitation_alpha_rad=_excitation(camp.info.get("trajectory"), t[order]))


def _excitation(trajectory_json: str | None, t: np.ndarray) -> np.ndarray | None:
    """α^d of the campaign's recorded trajectory at the encoder rate (its spectrum sets the filter
    cutoff); None when the archive does not hold a readable trajectory (the cutoff then comes
    from the encoders)."""
    from controller.trajectory import TrajectoryError, load_trajectory

    if not trajectory_json or len(t) < 2:
        return None
    try:
        traj = load_trajectory(json.loads(trajectory_json))
    except (TrajectoryError, ValueError, TypeError):
        return None
    dt = float(np.median(np.diff(t)))
    return traj.sample(np.arange(0.0, traj.duration_s, dt)).alpha


def identify(
    campaign: Path = typer.Argument(..., help="Campaign MCAP file recorded on the identification trajectory."),
    json_out: bool = typer.Option(False, "--json", help="Print the tables and checks as JSON."),
    out: Optional[Path] = typer.Option(None, "--out", help="Directory for figures and the parameter set "
                                       "(default: <campaign stem>_identification next to the file)."),
    params_file: Optional[Path] = typer.Option(None, "--params", help="Base parameter file (default: prototype)."),
    cutoff_hz: Optional[float] = typer.Option(None, "--cutoff-hz", help="Override the filter cutoff rule (Hz)."),
    threshold: float = typer.Option(DEFAULT_THRESHOLD, "--threshold", help="Relative σ above which a parameter is badly identified."),
    no_alpha_hat: bool = typer.Option(False, "--no-alpha-hat", help="Skip the α̂ reconstruction (Fig. 8)."),
) -> None:
    """Identify friction and cable stiffness from a campaign (Tables 1-2, Figs. 4-8)."""
    from twin.identification_report import report_dict, tables_text, write_figures

    try:
        base = load_params(params_file)
        data = campaign_data_from_mcap(campaign)
        proc = preprocess(data, base, cutoff_hz)
        est = identify_all(proc, base, threshold=threshold)
        prov = make_provenance(f"{data.campaign} ({campaign})", proc, threshold=threshold)
        new, report, prov = identified_params(base, est, prov)
        val = validate(data, proc, new, est, alpha_hat=not no_alpha_hat)
    except (IdentificationError, ParameterError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    out_dir = out or campaign.with_name(campaign.stem + "_identification")
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = write_figures(val, out_dir)
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
