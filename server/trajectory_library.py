"""The console's library of user trajectories: ``<data_dir>/trajectories/<name>.json``.

A stored trajectory is the user-file schema of :mod:`controller.trajectory` (``waypoints_deg``,
``durations_s``, ``dwell_s``, ``name``; JSON or TOML in, as ``--trajectory FILE`` accepts), kept
as the JSON of :meth:`Trajectory.to_dict`. Names are checked before any path is built (letters,
digits, ``_ . -``, not starting with a dot, at most 64 characters): no traversal, no hidden file.
The built-in trajectories are listed beside them, read-only. Writes go through a temporary file
and a rename, so a crash never leaves half a file in the library.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from bridge import toml_text
from controller.trajectory import NAMED_TRAJECTORIES, Trajectory, TrajectoryError, load_trajectory, trajectory_by_name

NAME = re.compile(r"^[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,63}$")
MAX_BYTES = 256 * 1024
PREVIEW_HZ = 20.0  # samples per second of a preview
PREVIEW_MAX_POINTS = 4000
#: Joints a preview draws at most: a refused trajectory's preview of 10,000 joints was 160 MB and
#: 2.5 GB of the console's memory (audit of 2026-11-28); necks have a few.
PREVIEW_MAX_JOINTS = 16


class LibraryError(ValueError):
    """A name or a trajectory the library refuses; the message says why."""


class NotInLibrary(KeyError):
    pass


def check_name(name: str) -> str:
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise LibraryError(f"trajectory name {name!r}: use 1-64 letters, digits, '_', '.', '-', not starting with '.'")
    return name


def parse(body: bytes, content_type: str = "application/json") -> Trajectory:
    """A trajectory from an uploaded body: JSON, or TOML when ``content_type`` says so."""
    if len(body) > MAX_BYTES:
        raise LibraryError(f"{len(body)} bytes: more than {MAX_BYTES} for a trajectory")
    try:
        text = body.decode("utf-8")
        data = toml_text.loads(text) if "toml" in content_type.lower() else json.loads(text)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise LibraryError(f"not a {'TOML' if 'toml' in content_type.lower() else 'JSON'} trajectory: {exc}") from None
    if not isinstance(data, dict):
        raise LibraryError("a trajectory is an object with waypoints_deg, durations_s, dwell_s and name")
    return load_trajectory(data)


def preview(traj: Trajectory) -> dict[str, Any] | None:
    """α^d(t) of ``traj`` for a plot: ``t_s`` and ``alpha_deg`` (one list per joint), a grid of at
    most ``PREVIEW_MAX_POINTS`` samples plus every waypoint's arrival and departure (so at most
    4000 + 2 × 2000, the validation's waypoint limit); None beyond ``PREVIEW_MAX_JOINTS`` joints."""
    if traj.n_joints > PREVIEW_MAX_JOINTS:
        return None
    dt = max(1.0 / PREVIEW_HZ, traj.duration_s / PREVIEW_MAX_POINTS)
    t = traj.time_grid(dt) if traj.duration_s > 0 else np.zeros(1)
    alpha = np.degrees(traj.sample(t).alpha)
    return {"t_s": np.round(t, 4).tolist(), "alpha_deg": np.round(alpha.T, 4).tolist(),
            "waypoint_times_s": traj.waypoint_times().tolist(), "duration_s": traj.duration_s}


class TrajectoryLibrary:
    def __init__(self, data_dir: Path) -> None:
        self.dir = Path(data_dir) / "trajectories"

    def _path(self, name: str) -> Path:
        return self.dir / f"{check_name(name)}.json"

    def names(self) -> list[str]:
        if not self.dir.is_dir():
            return []
        return sorted(p.stem for p in self.dir.glob("*.json") if NAME.fullmatch(p.stem))

    def list(self) -> list[dict[str, Any]]:
        out = [{"name": n, "builtin": True} for n in NAMED_TRAJECTORIES]
        for name in self.names():
            try:
                traj = self.get(name)
                out.append({"name": name, "builtin": False, "waypoints": traj.n_waypoints,
                            "duration_s": traj.duration_s})
            except (LibraryError, TrajectoryError, OSError) as exc:
                out.append({"name": name, "builtin": False, "error": str(exc)})
        return out

    def get(self, name: str) -> Trajectory:
        if name in NAMED_TRAJECTORIES:
            return trajectory_by_name(name)
        path = self._path(name)
        if not path.is_file():
            raise NotInLibrary(name)
        return parse(path.read_bytes())

    def put(self, name: str, traj: Trajectory) -> None:
        if name in NAMED_TRAJECTORIES:
            raise LibraryError(f"{name!r} is a built-in trajectory: choose another name")
        path = self._path(name)
        self.dir.mkdir(parents=True, exist_ok=True)
        data = {**traj.to_dict(), "name": name}
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(data, indent=1))
        os.replace(tmp, path)

    def delete(self, name: str) -> None:
        if name in NAMED_TRAJECTORIES:
            raise LibraryError(f"{name!r} is a built-in trajectory: it cannot be deleted")
        path = self._path(name)
        if not path.is_file():
            raise NotInLibrary(name)
        path.unlink()
