"""Campaign metrics as the 3-X paper reports them (§7, Table 3), from recorded arrays.

- e = α^d − α̂, the tracking error the controller sees (Fig. 16);
- e_α = α̂ − α_IP, the estimation error against the camera (Fig. 15): α̂ is interpolated to
  each frame's capture time;
- forces (Fig. 14) and the number of ticks with a saturated cable.
Angles in the returned dict are in degrees (a report edge); inputs are SI.
"""

from __future__ import annotations

import numpy as np


def campaign_metrics(
    t_s: np.ndarray,
    alpha_hat: np.ndarray,
    alpha_d: np.ndarray,
    force_N: np.ndarray,
    saturated: np.ndarray,
    t_ip_s: np.ndarray,
    alpha_ip: np.ndarray,
) -> dict[str, object]:
    """Mean and max |e| and |e_α| per joint (deg), force statistics (N), saturation count."""
    t_s, alpha_hat, alpha_d = np.asarray(t_s), np.asarray(alpha_hat), np.asarray(alpha_d)
    if len(t_s) == 0:
        raise ValueError("no controller ticks recorded: cannot compute metrics")
    e = np.degrees(np.abs(alpha_d - alpha_hat))
    out: dict[str, object] = {
        "ticks": int(len(t_s)),
        "duration_s": float(t_s[-1] - t_s[0]),
        "e_mean_deg": e.mean(axis=0).tolist(),
        "e_max_deg": e.max(axis=0).tolist(),
        "e_mean_all_deg": float(e.mean()),
        "force_mean_N": np.asarray(force_N).mean(axis=0).tolist(),
        "force_max_N": np.asarray(force_N).max(axis=0).tolist(),
        "force_mean_all_N": float(np.asarray(force_N).mean()),
        "saturated_ticks": int(np.asarray(saturated).any(axis=1).sum()),
    }
    inside = (t_ip_s >= t_s[0]) & (t_ip_s <= t_s[-1])
    if np.any(inside):
        at = np.column_stack([np.interp(t_ip_s[inside], t_s, alpha_hat[:, i]) for i in range(alpha_hat.shape[1])])
        ea = np.degrees(np.abs(at - np.asarray(alpha_ip)[inside]))
        out.update(
            e_alpha_mean_deg=ea.mean(axis=0).tolist(),
            e_alpha_max_deg=ea.max(axis=0).tolist(),
            e_alpha_mean_all_deg=float(ea.mean()),
            camera_frames=int(inside.sum()),
        )
    else:
        out.update(e_alpha_mean_deg=None, e_alpha_max_deg=None, e_alpha_mean_all_deg=None, camera_frames=0)
    return out
