"""The paper's metrics (:func:`controller.metrics.campaign_metrics`) of a recorded campaign.

The controller's statuses and the motor commands come at 500 Hz: decoded into Python objects and
kept, those of a 600 s campaign took the console's analysis to 690 MB for the metrics alone (audit
of 2026-11-30, docs/console.md "Long campaigns"). They are folded into columns as they are read
(``read_campaign(fold=...)``, as ``xneck identify`` folds its motor states), the camera's 30 Hz
frames kept as messages.
"""

from __future__ import annotations

from array import array
from pathlib import Path
from typing import Any

import numpy as np

from bridge import bus
from bridge.archive_read import FoldError, read_campaign
from controller.metrics import campaign_metrics


class _Statuses:
    """The controller statuses not holding, as columns: log time, stamp (s), α̂ and α^d (rad),
    saturation flags."""

    def __init__(self, path: Path) -> None:
        self.path, self.width = path, -1
        self.log_ns, self.stamp_s = array("Q"), array("d")
        self.alpha_hat, self.alpha_d, self.saturated = array("d"), array("d"), array("b")
        self.n_cables = -1

    def add(self, log_ns: int, m: Any) -> None:
        if not isinstance(m, bus.ControllerStatus):
            raise FoldError(ValueError(f"{self.path}: a {type(m).__name__} on the controller's status topic"))
        if m.holding:
            return
        if self.width < 0:
            self.width, self.n_cables = len(m.alpha_hat_rad), len(m.saturated)
        if not (len(m.alpha_hat_rad) == len(m.alpha_d_rad) == self.width and len(m.saturated) == self.n_cables):
            raise FoldError(ValueError(
                f"{self.path}: controller statuses of {self.width} and {len(m.alpha_hat_rad)} joints (or as many "
                f"cables: {self.n_cables}, {len(m.saturated)}): not one controller's campaign"))
        self.log_ns.append(log_ns)
        self.stamp_s.append(m.stamp_s)
        self.alpha_hat.extend(m.alpha_hat_rad)
        self.alpha_d.extend(m.alpha_d_rad)
        self.saturated.extend(bool(s) for s in m.saturated)


class _Commands:
    """The motor commands as columns: log time, stamp (s) and forces (N); a command of another
    width than the first is kept as a row of NaN (an error only if a status answers it)."""

    def __init__(self, path: Path) -> None:
        self.path, self.width = path, -1
        self.log_ns, self.stamp_s, self.force_N = array("Q"), array("d"), array("d")

    def add(self, log_ns: int, m: Any) -> None:
        if not isinstance(m, bus.ForceCommand):
            raise FoldError(ValueError(f"{self.path}: a {type(m).__name__} on the motor command topic"))
        if self.width < 0:
            self.width = len(m.force_N)
        self.log_ns.append(log_ns)
        self.stamp_s.append(m.stamp_s)
        self.force_N.extend(m.force_N if len(m.force_N) == self.width else [np.nan] * self.width)

    def last_by_stamp(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps sorted, forces (n, width)): for each stamp, the command logged last (ties: the
        later in the file), as a dict filled in log-time order keeps it."""
        n = len(self.stamp_s)
        if n == 0:
            return np.zeros(0), np.zeros((0, max(self.width, 0)))
        log = np.frombuffer(self.log_ns, dtype=np.uint64)
        stamp = np.frombuffer(self.stamp_s, dtype=float)
        order = np.argsort(log, kind="stable")[::-1]  # the last logged first
        stamps, first = np.unique(stamp[order], return_index=True)
        return stamps, np.frombuffer(self.force_N, dtype=float).reshape(n, self.width)[order[first]]


def metrics_from_archive(path: Path) -> dict[str, object]:
    """The paper's metrics (controller.metrics) from a recorded campaign: the controller's ticks not
    holding that a motor command answers (matched by stamp), and the camera's frames measuring every
    joint. Raises ValueError without such ticks or for statuses and commands of mixed widths."""
    statuses, commands = _Statuses(path), _Commands(path)
    campaign = read_campaign(path, keys=(bus.CAMERA_ALPHA,),
                             fold={bus.CONTROLLER_STATUS: statuses.add, bus.MOTOR_COMMAND: commands.add})
    if not len(statuses.stamp_s):
        raise ValueError(f"{path}: no controller status recorded")
    n, joints = len(statuses.stamp_s), statuses.width
    order = np.argsort(np.frombuffer(statuses.log_ns, dtype=np.uint64), kind="stable")
    t = np.frombuffer(statuses.stamp_s, dtype=float)[order]
    stamps, forces = commands.last_by_stamp()
    at = np.minimum(np.searchsorted(stamps, t), max(len(stamps) - 1, 0))
    answered = (at < len(stamps)) & (stamps[at] == t) if len(stamps) else np.zeros(n, dtype=bool)
    force = forces[at[answered]] if len(stamps) else np.zeros((0, 0))
    if np.isnan(force).any():
        raise ValueError(f"{path}: motor commands of different widths answer the controller's ticks")
    # A frame with a missing joint (the rendered camera's occlusions) measured nothing to compare with.
    # One camera: the recorder keeps one source (server.quality); of an archive recorded before it
    # did, the first source's, as the recorder would have chosen.
    alphas = [m for _, m in campaign.messages(bus.CAMERA_ALPHA)]
    frames = [m for m in alphas if m.source == alphas[0].source and None not in m.alpha_ip_rad]
    keep = order[answered]
    return campaign_metrics(
        t_s=t[answered],
        alpha_hat=np.frombuffer(statuses.alpha_hat, dtype=float).reshape(n, joints)[keep],
        alpha_d=np.frombuffer(statuses.alpha_d, dtype=float).reshape(n, joints)[keep],
        force_N=force,
        saturated=np.frombuffer(statuses.saturated, dtype=np.int8).reshape(n, statuses.n_cables)[keep].astype(bool),
        t_ip_s=np.array([m.capture_stamp_s for m in frames]),
        alpha_ip=np.array([m.alpha_ip_rad for m in frames]).reshape(len(frames), -1),
    )
