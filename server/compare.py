"""Comparison of archived campaigns (issue 18): a Table-3-shaped table of their metrics with the
parameter set and truth each ran with, and their traces for overlaid plots.

Traces come from each MCAP archive, on the time of its first controller status (0 s): α^d, α̂ and
e = α^d − α̂ per joint from ``ControllerStatus``; the applied forces from ``MotorState``; α_IP and
e_α = α̂ − α_IP (α̂ interpolated at each frame's capture time, as :mod:`controller.metrics` does)
from ``CameraAlpha``. Angles in degrees (a report edge), forces in N, decimated to at most
``max_points`` samples per series so that four runs stay light in a browser.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from bridge import bus
from bridge.archive import atomic_write
from bridge.archive_read import read_campaign
from server.records import CampaignRecord

TABLE_COLUMNS = ["campaign", "control law", "parameter set", "truth", "trajectory", "status",
                 "e_α mean (deg)", "e mean (deg)", "e max (deg)", "force mean (N)", "saturated ticks"]


class UnreadableMetrics(ValueError):
    """A record whose metrics are not what a campaign writes (edited by hand); the message names
    the campaign and the metric."""


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _r(x: Any) -> float | None:
    # NaN would make the JSON answer itself fail: an unknown value is shown as none.
    return None if x is None or not math.isfinite(x) else round(float(x), 3)


def _metric(rec: CampaignRecord, m: dict[str, Any], key: str, per_joint: bool = False) -> float | None:
    """``metrics[key]`` of ``rec`` (its largest element when ``per_joint``), None when absent; raises
    :class:`UnreadableMetrics` when it is not a number (a list of numbers when ``per_joint``)."""
    value = m.get(key)
    if value is None:
        return None
    if per_joint:
        if not isinstance(value, list) or not all(_number(v) for v in value):
            raise UnreadableMetrics(f"campaign {rec.id}: metrics.{key} is {str(value)[:60]}, not a list of numbers "
                                    "(one per joint)")
        # One joint's value unknown: so is their largest (max() with a NaN depends on the order).
        return _r(max(value)) if value and all(math.isfinite(v) for v in value) else None
    if not _number(value):
        raise UnreadableMetrics(f"campaign {rec.id}: metrics.{key} is {str(value)[:60]!r}, not a number")
    return _r(value)


def compare_table(records: list[CampaignRecord]) -> dict[str, Any]:
    """Table 3 of the 3-X paper (§7) for the chosen runs: one row per campaign. Raises
    :class:`UnreadableMetrics` for a record whose metrics are not numbers."""
    rows = []
    for rec in records:
        m = rec.metrics if isinstance(rec.metrics, dict) else {}
        saturated = m.get("saturated_ticks")
        if saturated is not None and not _number(saturated):
            raise UnreadableMetrics(f"campaign {rec.id}: metrics.saturated_ticks is {str(saturated)[:60]!r}, "
                                    "not a number")
        rows.append([rec.id, rec.law, rec.parameter_set, rec.truth or ("robot" if rec.target == "robot" else "–"),
                     rec.trajectory, rec.status, _metric(rec, m, "e_alpha_mean_all_deg"),
                     _metric(rec, m, "e_mean_all_deg"), _metric(rec, m, "e_max_deg", per_joint=True),
                     _metric(rec, m, "force_mean_all_N"), saturated])
    return {"title": "Table 3 (selected runs): mean errors", "columns": TABLE_COLUMNS, "rows": rows,
            "note": "e_α = |α̂ − α_IP| against the camera, e = |α^d − α̂| (3-X paper §7, Table 3); "
                    "truth: what the twin simulated."}


def _stride(n: int, max_points: int) -> slice:
    return slice(None, None, max(1, -(-n // max_points)))


def _deg(rows: list[list[float | None]]) -> list[list[float | None]]:
    """Per joint lists of degrees (rounded) from per sample lists of radians (None kept)."""
    arr = np.array(rows, dtype=float)
    return [[None if not np.isfinite(v) else round(float(np.degrees(v)), 4) for v in col] for col in arr.T]


log = logging.getLogger("xneck.compare")
TRACE_KEYS = frozenset({"t_s", "alpha_d_deg", "alpha_hat_deg", "e_deg", "force", "camera"})
#: Changed with what :func:`traces` computes: traces kept by another version are computed again.
TRACES_VERSION = 1


def cached_traces(mcap: Path, folder: Path, max_points: int = 800) -> dict[str, Any]:
    """:func:`traces` of ``mcap``, kept in ``folder`` (the campaign's figures folder) as JSON with
    the archive's size and modification time, and read from there while the archive has both: a
    600 s campaign's took 13-15 s and ~0.8 GB per request, every time a comparison was opened (audit
    of 2026-11-30). A kept file that does not read as traces is computed again; one that cannot be
    written (a full disk) is not kept."""
    cache = folder / f"traces-{max_points}.json"
    st = mcap.stat()  # a missing archive is the caller's error, as traces() raises it
    of = {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "version": TRACES_VERSION}
    try:
        doc = json.loads(cache.read_text(encoding="utf-8"))
        if isinstance(doc, dict) and doc.get("mcap") == of and isinstance(doc.get("traces"), dict) \
                and set(doc["traces"]) == TRACE_KEYS:
            return doc["traces"]
    except (OSError, ValueError, RecursionError):  # absent, damaged: computed again
        pass
    out = traces(mcap, max_points)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write(cache, json.dumps({"mcap": of, "traces": out}, allow_nan=False).encode())
    except (OSError, ValueError) as exc:
        log.warning("traces of %s not kept: %s", mcap.name, exc)
    return out


def traces(mcap: Path, max_points: int = 800) -> dict[str, Any]:
    """The overlaid series of one archive (module docstring)."""
    campaign = read_campaign(mcap, keys=(bus.CONTROLLER_STATUS, bus.MOTOR_STATE, bus.CAMERA_ALPHA))
    status = [m for _, m in campaign.messages(bus.CONTROLLER_STATUS)]
    if not status:
        return {"t_s": [], "alpha_d_deg": [], "alpha_hat_deg": [], "e_deg": [], "force": {"t_s": [], "force_N": []},
                "camera": {"t_s": [], "alpha_ip_deg": [], "e_alpha_deg": []}}
    t0 = status[0].stamp_s
    t = np.array([m.stamp_s for m in status]) - t0
    hat = np.array([m.alpha_hat_rad for m in status])
    pick = _stride(len(status), max_points)
    out: dict[str, Any] = {
        "t_s": np.round(t[pick], 4).tolist(),
        "alpha_d_deg": _deg([m.alpha_d_rad for m in status[pick]]),
        "alpha_hat_deg": _deg(hat[pick].tolist()),
        "e_deg": _deg([m.e_rad for m in status[pick]]),
    }
    states = [m for _, m in campaign.messages(bus.MOTOR_STATE) if t0 <= m.stamp_s <= t0 + t[-1]]
    sp = _stride(len(states), max_points)
    out["force"] = {"t_s": [round(m.stamp_s - t0, 4) for m in states[sp]],
                    "force_N": np.round(np.array([m.force_applied_N for m in states[sp]]).T, 3).tolist()
                    if states else []}
    frames = [m for _, m in campaign.messages(bus.CAMERA_ALPHA) if t0 <= m.capture_stamp_s <= t0 + t[-1]]
    frames = frames[_stride(len(frames), max_points)]
    t_ip = np.array([m.capture_stamp_s - t0 for m in frames])
    ip = np.array([[np.nan if a is None else a for a in m.alpha_ip_rad] for m in frames], dtype=float)
    if len(frames):
        at = np.column_stack([np.interp(t_ip, t, hat[:, j]) for j in range(hat.shape[1])])
        out["camera"] = {"t_s": np.round(t_ip, 4).tolist(), "alpha_ip_deg": _deg(ip.tolist()),
                         "e_alpha_deg": _deg((at - ip).tolist())}
    else:
        out["camera"] = {"t_s": [], "alpha_ip_deg": [], "e_alpha_deg": []}
    return out
