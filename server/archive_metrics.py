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


class _Rows:
    """Rows of float (or int8) values kept per width: ``widths`` -> group, each group's rows flat.
    A message of another width is kept in its own group, an error only if it is used (the ticks a
    command answers): a stray one, or an unanswered status of another controller, is harmless."""

    def __init__(self, typecodes: tuple[str, ...]) -> None:
        self.typecodes = typecodes
        self.groups: dict[tuple[int, ...], int] = {}
        self.columns: list[tuple[array, ...]] = []
        self.rows: list[int] = []

    def add(self, *values: list) -> tuple[int, int]:
        """(group, row) of ``values`` (one list per column)."""
        key = tuple(len(v) for v in values)
        g = self.groups.setdefault(key, len(self.groups))
        if g == len(self.columns):
            self.columns.append(tuple(array(c) for c in self.typecodes))
            self.rows.append(0)
        for column, v in zip(self.columns[g], values, strict=True):
            column.extend(v)
        self.rows[g] += 1
        return g, self.rows[g] - 1

    def gather(self, group: np.ndarray, row: np.ndarray, what: str) -> list[np.ndarray]:
        """The columns of the rows ``(group, row)``, all of one width, else ValueError naming ``what``."""
        used = np.unique(group)
        if len(used) > 1:
            widths = sorted({k for k, g in self.groups.items() if g in used})
            raise ValueError(f"{what} of different widths ({', '.join(map(str, widths))}) in the ticks measured")
        if not len(used):
            return [np.zeros((0, 0)) for _ in self.typecodes]
        width = next(k for k, g in self.groups.items() if g == used[0])
        dtypes = {"d": float, "b": np.int8}
        return [np.frombuffer(c, dtype=dtypes[t]).reshape(self.rows[used[0]], w)[row]
                for c, t, w in zip(self.columns[used[0]], self.typecodes, width, strict=True)]


class _Statuses:
    """The controller statuses not holding, as columns: log time, stamp (s), and per width group
    α̂ and α^d (rad) and saturation flags."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.log_ns, self.stamp_s, self.group, self.row = array("Q"), array("d"), array("q"), array("q")
        self.values = _Rows(("d", "d", "b"))

    def add(self, log_ns: int, m: Any) -> None:
        if not isinstance(m, bus.ControllerStatus):
            raise FoldError(ValueError(f"{self.path}: a {type(m).__name__} on the controller's status topic"))
        if m.holding:
            return
        g, r = self.values.add(m.alpha_hat_rad, m.alpha_d_rad, [bool(s) for s in m.saturated])
        self.log_ns.append(log_ns)
        self.stamp_s.append(m.stamp_s)
        self.group.append(g)
        self.row.append(r)


class _Commands:
    """The motor commands as columns: log time, stamp (s), and per width group the forces (N)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.log_ns, self.stamp_s, self.group, self.row = array("Q"), array("d"), array("q"), array("q")
        self.values = _Rows(("d",))

    def add(self, log_ns: int, m: Any) -> None:
        if not isinstance(m, bus.ForceCommand):
            raise FoldError(ValueError(f"{self.path}: a {type(m).__name__} on the motor command topic"))
        g, r = self.values.add(m.force_N)
        self.log_ns.append(log_ns)
        self.stamp_s.append(m.stamp_s)
        self.group.append(g)
        self.row.append(r)

    def last_by_stamp(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps sorted, the index of each one's command): for each stamp, the command logged last
        (ties: the later in the file), as a dict filled in log-time order keeps it."""
        if not len(self.stamp_s):
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        log = np.frombuffer(self.log_ns, dtype=np.uint64)
        stamp = np.frombuffer(self.stamp_s, dtype=float)
        order = np.argsort(log, kind="stable")[::-1]  # the last logged first
        stamps, first = np.unique(stamp[order], return_index=True)
        return stamps, order[first]


def _folding(path: Path, add: Any) -> Any:
    """``add`` whose own errors (a MemoryError, a bug) say the campaign's metrics, not a damaged file."""
    def fold(log_ns: int, m: Any) -> None:
        try:
            add(log_ns, m)
        except FoldError:
            raise
        except Exception as exc:  # read_campaign would call it a damaged file
            raise FoldError(ValueError(f"{path}: metrics: {type(exc).__name__}: {exc}")) from exc
    return fold


def metrics_from_archive(path: Path) -> dict[str, object]:
    """The paper's metrics (controller.metrics) from a recorded campaign: the controller's ticks not
    holding that a motor command answers (matched by stamp), and the camera's frames measuring every
    joint. Raises ValueError without such ticks or for ticks and commands of mixed widths among
    them (:class:`bridge.archive.ArchiveError` for a damaged file)."""
    statuses, commands = _Statuses(path), _Commands(path)
    campaign = read_campaign(path, keys=(bus.CAMERA_ALPHA,), fold={
        bus.CONTROLLER_STATUS: _folding(path, statuses.add), bus.MOTOR_COMMAND: _folding(path, commands.add)})
    if not len(statuses.stamp_s):
        raise ValueError(f"{path}: no controller status recorded")
    order = np.argsort(np.frombuffer(statuses.log_ns, dtype=np.uint64), kind="stable")
    t = np.frombuffer(statuses.stamp_s, dtype=float)[order]
    stamps, chosen = commands.last_by_stamp()
    at = np.minimum(np.searchsorted(stamps, t), max(len(stamps) - 1, 0))
    answered = (stamps[at] == t) if len(stamps) else np.zeros(len(t), dtype=bool)
    keep, command = order[answered], chosen[at[answered]] if len(stamps) else np.zeros(0, dtype=np.int64)
    alpha_hat, alpha_d, saturated = statuses.values.gather(
        np.frombuffer(statuses.group, dtype=np.int64)[keep], np.frombuffer(statuses.row, dtype=np.int64)[keep],
        f"{path}: controller statuses")
    (force,) = commands.values.gather(
        np.frombuffer(commands.group, dtype=np.int64)[command], np.frombuffer(commands.row, dtype=np.int64)[command],
        f"{path}: motor commands")
    # A frame with a missing joint (the rendered camera's occlusions) measured nothing to compare with.
    # One camera: the recorder keeps one source (server.quality); of an archive recorded before it
    # did, the first source's, as the recorder would have chosen.
    alphas = [m for _, m in campaign.messages(bus.CAMERA_ALPHA)]
    frames = [m for m in alphas if m.source == alphas[0].source and None not in m.alpha_ip_rad]
    if alpha_hat.shape != alpha_d.shape:  # numpy would broadcast one α^d over every joint's α̂
        raise ValueError(f"{path}: controller statuses of {alpha_hat.shape[1]} estimated and {alpha_d.shape[1]} "
                         "desired joint angles")
    return campaign_metrics(
        t_s=t[answered], alpha_hat=alpha_hat, alpha_d=alpha_d, force_N=force, saturated=saturated.astype(bool),
        t_ip_s=np.array([m.capture_stamp_s for m in frames], dtype=float),
        # no camera (a campaign without α_IP): no frames, not an error ("cannot reshape array of size 0")
        alpha_ip=np.array([m.alpha_ip_rad for m in frames]).reshape(len(frames), -1) if frames
        else np.zeros((0, alpha_hat.shape[1])),
    )
