"""Comparison of archived campaigns (issue 18): a Table-3-shaped table of their metrics with the
parameter set and truth each ran with, and their traces for overlaid plots.

Traces come from each MCAP archive, on the time of its first controller status (0 s): α^d, α̂ and
e = α^d − α̂ per joint from ``ControllerStatus``; the applied forces from ``MotorState``; α_IP and
e_α = α̂ − α_IP (α̂ interpolated at each frame's capture time, as :mod:`controller.metrics` does)
from ``CameraAlpha``. Angles in degrees (a report edge), forces in N, decimated to at most
``max_points`` samples per series so that four runs stay light in a browser.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from bridge import bus
from bridge.archive import read_campaign
from server.records import CampaignRecord

TABLE_COLUMNS = ["campaign", "control law", "parameter set", "truth", "trajectory", "status",
                 "e_α mean (deg)", "e mean (deg)", "e max (deg)", "force mean (N)", "saturated ticks"]


def _r(x: Any) -> float | None:
    return None if x is None else round(float(x), 3)


def compare_table(records: list[CampaignRecord]) -> dict[str, Any]:
    """Table 3 of the 3-X paper (§7) for the chosen runs: one row per campaign."""
    rows = []
    for rec in records:
        m = rec.metrics or {}
        e_max = max(m["e_max_deg"]) if m.get("e_max_deg") else None
        rows.append([rec.id, rec.law, rec.parameter_set, rec.truth or ("robot" if rec.target == "robot" else "–"),
                     rec.trajectory, rec.status, _r(m.get("e_alpha_mean_all_deg")), _r(m.get("e_mean_all_deg")),
                     _r(e_max), _r(m.get("force_mean_all_N")), m.get("saturated_ticks")])
    return {"title": "Table 3 (selected runs): mean errors", "columns": TABLE_COLUMNS, "rows": rows,
            "note": "e_α = |α̂ − α_IP| against the camera, e = |α^d − α̂| (3-X paper §7, Table 3); "
                    "truth: what the twin simulated."}


def _stride(n: int, max_points: int) -> slice:
    return slice(None, None, max(1, -(-n // max_points)))


def _deg(rows: list[list[float | None]]) -> list[list[float | None]]:
    """Per joint lists of degrees (rounded) from per sample lists of radians (None kept)."""
    arr = np.array(rows, dtype=float)
    return [[None if not np.isfinite(v) else round(float(np.degrees(v)), 4) for v in col] for col in arr.T]


def traces(mcap: Path, max_points: int = 800) -> dict[str, Any]:
    """The overlaid series of one archive (module docstring)."""
    campaign = read_campaign(mcap)
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
