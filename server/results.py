"""Results of a campaign for people: tables shaped like the 3-X paper's and PNG figures.

- Control campaigns: Table 3's quantities for this run — mean estimation error e_α = |α̂ − α_IP|
  and tracking error e = |α^d − α̂| (deg), overall and per joint — plus forces and saturation.
- Identification campaigns: Tables 1 and 2 (identified friction/stiffness with σ), from
  :mod:`twin.identification.pipeline` when it can process the archive; otherwise the control metrics.

Figures (matplotlib, Agg): ``tracking`` (α̂, α^d, α_IP per joint, deg, against time) and
``forces`` (commanded forces per motor, N), computed from the archive on first request and cached.
"""

from __future__ import annotations

import logging
import math
import threading
from pathlib import Path
from typing import Any

import numpy as np

from bridge import bus
from bridge.archive_read import read_campaign
from server.quality import SATURATION_NOTE_FRACTION
from server.record_gaps import GAP_KEYS, explain_gaps

log = logging.getLogger(__name__)

FIGURES = ("tracking", "forces")
FIGURE_KEYS = {"tracking": (bus.CONTROLLER_STATUS, bus.CAMERA_ALPHA), "forces": (bus.MOTOR_COMMAND,)}
PYPLOT_LOCK = threading.Lock()  # pyplot's state machine is not thread-safe; every server figure takes it


def _table(title: str, columns: list[str], rows: list[list[Any]], note: str = "") -> dict[str, Any]:
    return {"title": title, "columns": columns, "rows": rows, "note": note}


def control_tables(law: str, metrics: dict[str, Any] | None) -> list[dict[str, Any]]:
    """Tables (title, columns, rows) from :func:`controller.metrics.campaign_metrics` output."""
    m = metrics or {}
    if not m.get("ticks"):
        return []
    r = lambda x: None if x is None else round(float(x), 3)  # noqa: E731
    n = len(m["e_mean_deg"])
    tables = [
        _table("Table 3 (this run): mean errors", ["control law", "e_α mean (deg)", "e mean (deg)"],
               [[law, r(m.get("e_alpha_mean_all_deg")), r(m["e_mean_all_deg"])]],
               "e_α = |α̂ − α_IP| against the camera, e = |α^d − α̂| (3-X paper §7, Table 3)."),
        _table("Errors per joint (deg)", ["", *[f"α{i + 1}" for i in range(n)]], [
            ["mean e", *map(r, m["e_mean_deg"])], ["max e", *map(r, m["e_max_deg"])],
            ["mean e_α", *map(r, m.get("e_alpha_mean_deg") or [None] * n)],
            ["max e_α", *map(r, m.get("e_alpha_max_deg") or [None] * n)],
        ]),
        _table("Forces (N)", ["", *[f"f{i + 1}" for i in range(len(m["force_mean_N"]))]], [
            ["mean", *map(r, m["force_mean_N"])], ["max", *map(r, m["force_max_N"])],
        ], f"{m['ticks']} ticks over {m['duration_s']:.2f} s, {m['saturated_ticks']} with a saturated cable, "
           f"{m.get('camera_frames', 0)} camera frames."),
    ]
    return tables


def quality_tables(quality: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The real-time quality of a run (``server.quality``) against its thresholds; the note says
    why it is degraded, if it is."""
    q = quality or {}
    if "ticks" not in q:
        return []
    t = q.get("thresholds", {})
    rt = "" if q.get("realtime") else " (lockstep: not applied)"
    rows = [
        ["command rate (Hz, wall clock)", q.get("rate_hz"), f"≥ {100 * t.get('rate_min_fraction', 0):.0f} % of "
         f"{t.get('nominal_rate_hz', 0):.0f} Hz{rt}"],
        ["deadline misses / ticks", f"{q.get('deadline_misses')} / {q.get('controller_ticks') or q['ticks']}",
         f"≤ {100 * t.get('deadline_miss_rate_max', 0):.0f} %{rt}"],
        ["messages lost (gaps)", f"{q.get('messages_lost')} ({q.get('record_gaps')})",
         f"≤ {100 * t.get('lost_fraction_max', 0):.1f} % of the messages"],
        ["overruns", q.get("overruns"), ""],
        ["state-to-command latency p50 / p99 (ms)", f"{q.get('latency_p50_ms', '–')} / {q.get('latency_p99_ms', '–')}",
         "the controller's own, upper bin edges"],
    ]
    if "law_ticks" in q:  # recorded since the count (user audit of session 42)
        rows.append(["law ticks with a cable at f_max", f"{q.get('saturated_ticks')} / {q['law_ticks']}",
                     f"an identification's message notes more than {100 * SATURATION_NOTE_FRACTION:g} %"])
    reasons = q.get("reasons") or []
    return [_table("Real-time quality (server.quality)", ["", "this run", "threshold"], rows,
                   ("degraded: " + "; ".join(reasons)) if reasons else "within the thresholds")]


def _finite(x: Any) -> Any:
    """``x``, or None for a non-finite number (a cutoff given: no f_99), which JSON cannot carry."""
    return x if not isinstance(x, float) or math.isfinite(x) else None


def _percent(x: Any) -> float | None:
    """A relative σ as a percentage to 2 decimals; None where there is none (a parameter held at
    its bound has no σ: its null was a TypeError, the whole results a 500; fresh-user audit of 2026-12-01)."""
    return round(100 * x, 2) if isinstance(x, (int, float)) and math.isfinite(x) else None


def identification_tables(report: dict[str, Any] | None) -> list[dict[str, Any]]:
    """Tables 1 and 2 from ``twin.identification.report.report_dict`` output."""
    if not report:
        return []
    out = []

    def rows(est: dict[str, Any]) -> list[list[Any]]:
        return [[p["name"], _finite(p["value"]), _finite(p["sigma"]), _percent(p["relative_sigma"]),
                 p.get("reason") or ("badly identified" if p["badly_identified"] else "")] for p in est["parameters"]]

    proc = report.get("processing") or {}
    if proc:  # what was fitted: a record's gaps leave instants out (twin.identification.processing)
        out.append(_table("Identification data (3-X paper §5.2.1)", ["", "value"], [
            ["filter cutoff (Hz)", _finite(proc.get("cutoff_hz"))], ["motion bandwidth f_99 (Hz)", _finite(proc.get("f_99_hz"))],
            ["instants (decimated)", proc.get("n")], ["instants fitted", proc.get("n_fitted", proc.get("n"))],
        ], "; ".join(proc.get("notes") or []) or "every instant fitted: no gap in the record"))
    cols = ["parameter", "value (SI)", "σ", "σ/|value| (%)", ""]
    t1 = report.get("table_1", {})
    for key, title in (("complete", "Table 1: identified parameters (friction + elastic cables)"),
                       ("friction", "Table 1: identified parameters (friction only)")):
        if key in t1:
            out.append(_table(title, cols, rows(t1[key]), t1[key].get("equations", "")))
    if "table_2" in report:
        t2 = report["table_2"]
        # which estimator made Table 2 ("auto → loadfriction (…)" names the test that chose it)
        note = "; ".join(x for x in (t2.get("equations", ""), f"estimator: {t2['estimator']}" if t2.get("estimator") else "") if x)
        out.append(_table("Table 2: identified parameters, variable cable stiffness", cols, rows(t2), note))
    return out


def identify_archive(path: Path, params_file: Path | None, *, estimator: str = "auto",
                     creep_time_s: float | None = None, overrides: tuple[str, ...] = ()) -> tuple[dict[str, Any] | None, str]:
    """Run the offline identification (twin.identification.pipeline; Table 2 by ``estimator``, the
    line's creep time held at ``creep_time_s`` s if given) on an archive: (report, status text).
    Never raises: an identification problem is a result to show, not a server error; the status of
    a failed one ends with the record's gaps explained (:mod:`server.record_gaps`), if it has any."""
    report, text, _ = analyse_archive(path, params_file, estimator=estimator, creep_time_s=creep_time_s,
                                      overrides=overrides)
    return report, text


def analyse_archive(path: Path, params_file: Path | None, *, estimator: str = "auto", creep_time_s: float | None = None,
                    overrides: tuple[str, ...] = (), base_name: str = "") -> tuple[dict[str, Any] | None, str,
                                                                                     dict[str, Any] | None]:
    """:func:`identify_archive`, and the parameter set it identified as a save stores it
    (:func:`server.identified_sets.identified_set`; None when it failed). ``base_name``: the name
    the campaign ran its set under (the console's, which its archive records), if not the file's."""
    import msgspec

    from controller.trajectory import recorded_excitation
    from server.identified_sets import identified_set
    from twin.identification.record import identify_record
    from twin.identification.report import report_dict
    from twin.identification.timing import alpha_ip_timing
    from twin.model.params import load_params, parse_override

    try:
        base = load_params(params_file, dict(parse_override(o) for o in overrides))
        if base_name:
            base = msgspec.structs.replace(base, name=base_name)
        ident = identify_record(path, base, excitation=recorded_excitation, with_validation=False,
                                estimator=estimator, creep_time_s=creep_time_s)
        report = report_dict(ident.estimate, ident.processed)
        report["record_notes"] = list(ident.data.notes)  # stray messages the reader dropped, if any
        report["alpha_ip_timing"] = alpha_ip_timing(ident.data).as_dict()  # α_IP's delay against the encoders
    except Exception as exc:  # noqa: BLE001 - reported to the user
        text = f"identification failed: {type(exc).__name__}: {exc}"
    else:
        try:  # a save's convenience: never the analysis' failure (a save then identifies again)
            kept = identified_set(ident, base.name)
        except Exception:
            log.warning("%s: the identified set not kept for a save", path, exc_info=True)
            kept = None
        return report, "identified", kept
    if "gap(s) in the record" not in text:  # the fit bridges short gaps: they did not break this one
        return None, text, None
    try:  # the gaps that broke it, explained (issue 17): which topic, which messages, what happened then
        gaps = explain_gaps(read_campaign(path, keys=GAP_KEYS))
    except Exception as exc:  # noqa: BLE001 - an unreadable archive: its reason is the failure above
        gaps = f"(record gaps not examined: {type(exc).__name__}: {exc})"
    return None, f"{text}; {gaps}" if gaps else text, None


#: Joints a figure draws at most (one axis each): an archive is hostile input, and a status of
#: 2,000 angles drew for 32 s under ``PYPLOT_LOCK``, every other figure waiting (audit of 2026-11-28).
FIGURE_MAX_JOINTS = 16


def render_figure(mcap: Path, name: str, out: Path) -> Path:
    """Write figure ``name`` (one of :data:`FIGURES`) of an archive to ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # What the figure draws only: the forces of a 600 s campaign took 247 MB read so, 610 MB with
    # the statuses and frames the tracking figure needs (audit of 2026-11-30).
    campaign = read_campaign(mcap, keys=FIGURE_KEYS.get(name, ()))
    status = [m for _, m in campaign.messages(bus.CONTROLLER_STATUS)] if name == "tracking" else []
    out.parent.mkdir(parents=True, exist_ok=True)
    with PYPLOT_LOCK:
        if name == "tracking":
            frames = [m for _, m in campaign.messages(bus.CAMERA_ALPHA)]
            n = len(status[0].alpha_hat_rad) if status else 3
            if not 1 <= n <= FIGURE_MAX_JOINTS:  # the archive's word: 2,000 axes took 32 s and held the lock
                raise ValueError(f"the record's controller status has {n} joints: no neck this console draws "
                                 f"(at most {FIGURE_MAX_JOINTS})")
            fig, axes = plt.subplots(n, 1, figsize=(8, 2.2 * n), sharex=True, squeeze=False)
            t0 = status[0].stamp_s if status else 0.0
            t = np.array([m.stamp_s for m in status]) - t0
            for j in range(n):
                ax = axes[j, 0]
                if status:
                    ax.plot(t, np.degrees([m.alpha_d_rad[j] for m in status]), "g-", lw=1, label="α^d")
                    ax.plot(t, np.degrees([m.alpha_hat_rad[j] for m in status]), "b-", lw=1, label="α̂")
                if frames:
                    ax.plot(np.array([m.capture_stamp_s for m in frames]) - t0,
                            np.degrees(np.array([m.alpha_ip_rad[j] for m in frames], dtype=float)), ".", color="orange", ms=2, label="α_IP")
                ax.set_ylabel(f"α{j + 1} (deg)")
                ax.grid(alpha=0.3)
            axes[0, 0].legend(loc="upper right", fontsize=8)
            axes[-1, 0].set_xlabel("t (s)")
        elif name == "forces":
            cmds = [m for _, m in campaign.messages(bus.MOTOR_COMMAND)]
            fig, ax = plt.subplots(figsize=(8, 3.5))
            if cmds:
                t = np.array([m.stamp_s for m in cmds])
                f = np.array([m.force_N for m in cmds])
                for i in range(f.shape[1]):
                    ax.plot(t - t[0], f[:, i], lw=1, label=f"f{i + 1}")
                ax.legend(loc="upper right", fontsize=8)
            ax.set_xlabel("t (s)")
            ax.set_ylabel("force (N)")
            ax.grid(alpha=0.3)
        else:
            raise KeyError(name)
        fig.suptitle(f"{campaign.info.get('campaign_id', mcap.stem)}: {name}", fontsize=10)
        fig.tight_layout()
        tmp = out.with_name(out.name + ".tmp.png")
        fig.savefig(tmp, dpi=90)
        plt.close(fig)
        tmp.replace(out)
    return out
