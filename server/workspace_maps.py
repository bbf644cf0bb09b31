"""Workspace maps for the console, rendered once per parameter set and cached on disk.

3-X: the prototype's wrench-feasible workspace (configurations α with Z(α) f = g(α) for some
f_min <= f <= f_max) and its joint stiffness range over the force redundancy, from
:func:`twin.analysis.workspace.maps_3x` on a regular α grid over ±90°. 2-X: the paper's figures
(:func:`twin.analysis.workspace.write_2x_figures`), which do not depend on any parameter set.

Cache layout: ``<root>/<design>-<key>/`` holds the PNGs and ``summary.json``. An entry is drawn
in a temporary directory and renamed into place, so it is either complete or absent. The 3-X key
is a hash of the set's canonical TOML (its ``name`` blanked: a renamed copy reuses the maps), of
the grid and of :data:`RENDER_VERSION`; the least recently used entries beyond ``max_entries``
are removed. Everything here blocks (≈1-2 s for a 3-X entry on 2 cores, ≈5 s for the 2-X set):
call it from a worker thread.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import msgspec
import numpy as np

from server.results import PYPLOT_LOCK
from twin.analysis.workspace import CAPTIONS, Maps3X
from twin.model.params import Params

log = logging.getLogger("xneck.server.workspace")

DesignName = Literal["3x", "2x"]

# Bump when the figures or the summary change, so caches written by older code are not served.
RENDER_VERSION = 1
GRID_3X = 31  # points per α axis over ±90°: 6° steps, the α3 = 0 slice on the grid (odd count)
GRID_2X = 150  # points per axis of the 2-X maps: ≈5 s for all nine figures on 2 cores
ALPHA_MAX_3X = np.pi / 2  # rad, half-width of the mapped α cube (the X-joint's flat configuration)
MAX_ENTRIES = 16

# URL name -> file name written by twin.analysis.workspace.
FIGURES: dict[str, dict[str, str]] = {
    "3x": {"wfw": "3x_wfw.png", "stiffness": "3x_stiffness.png"},
    "2x": {f[len("2x_"):-len(".png")]: f for f in CAPTIONS if f.startswith("2x_")},
}
SUMMARY = "summary.json"


class UnsupportedParameterSet(ValueError):
    """The set is not a three-joint, four-cable neck, the only design the 3-X maps cover."""


@dataclass(frozen=True)
class Entry:
    """A complete cache entry: its directory, its summary, and whether it was already on disk."""

    path: Path
    summary: dict[str, Any]
    hit: bool
    render_s: float

    def figure(self, design: DesignName, name: str) -> Path:
        """PNG of figure ``name``; :class:`KeyError` for a name :data:`FIGURES` does not list."""
        return self.path / FIGURES[design][name]


def caption(design: DesignName, name: str, summary: dict[str, Any] | None = None) -> str:
    """One-line caption; the 3-X ones state the force bounds of the set they were drawn for."""
    text = CAPTIONS[FIGURES[design][name]]
    if design == "3x" and summary is not None:
        text = text.replace("[f_min, f_max]", f"[{summary['f_min_N']:g}, {summary['f_max_N']:g}] N")
    return text


def params_key(params: Params, grid: int) -> str:
    """Cache key of a 3-X entry: 16 hex digits of SHA-256 over the canonical TOML and the grid."""
    canonical = msgspec.structs.replace(params, name="").to_toml()
    h = hashlib.sha256(f"xneck-workspace-3x v{RENDER_VERSION} n={grid}\n".encode())
    h.update(canonical.encode())
    return h.hexdigest()[:16]


def summarize_3x(mp: Maps3X, params: Params) -> dict[str, Any]:
    """Numbers of the 3-X maps (SI, angles in degrees where the key says so).

    ``joint_stiffness_N_m_per_rad``: per joint, the least diagonal stiffness K_ii over the
    feasible set at the lowest antagonistic tension and the greatest at the highest tension;
    a negative ``min`` marks configurations that no admissible tension stabilises.
    """
    lim = params.limits
    feasible = mp.feasible
    within = _within(mp.alpha, lim.alpha_max_deg)
    n = mp.alpha.size
    mid = (n // 2,) * 3
    rest_ok = bool(feasible[mid])

    def per_joint(values: np.ndarray, reduce: Any) -> list[float] | None:
        if not feasible.any():
            return None
        return [float(reduce(values[..., j][feasible])) for j in range(values.shape[-1])]

    return {
        "design": "3x",
        "render_version": RENDER_VERSION,
        "grid": {
            "points_per_axis": int(n),
            "alpha_max_deg": round(float(np.degrees(mp.alpha[-1])), 6),
            "step_deg": round(float(np.degrees(mp.alpha[1] - mp.alpha[0])), 6),
            "configurations": int(feasible.size),
        },
        "f_min_N": float(lim.f_min),
        "f_max_N": float(lim.f_max),
        "feasible_fraction": float(feasible.mean()),
        "joint_limit_deg": float(lim.alpha_max_deg),
        "feasible_fraction_within_joint_limit": float(feasible[within].mean()) if within.any() else None,
        "joint_stiffness_N_m_per_rad": {
            "min": per_joint(mp.K_lo, np.min),
            "max": per_joint(mp.K_hi, np.max),
        },
        "straight_neck": {
            "feasible": rest_ok,
            "stiffness_lowest_tension_N_m_per_rad": [float(k) for k in mp.K_lo[mid]] if rest_ok else None,
            "stiffness_highest_tension_N_m_per_rad": [float(k) for k in mp.K_hi[mid]] if rest_ok else None,
        },
    }


def _within(alpha: np.ndarray, limit_deg: float) -> np.ndarray:
    """(n, n, n) mask of grid configurations with every |α_i| <= limit_deg."""
    ok = np.abs(np.degrees(alpha)) <= limit_deg + 1e-9
    return ok[:, None, None] & ok[None, :, None] & ok[None, None, :]


class WorkspaceCache:
    """Renders and caches workspace entries under ``root``; thread-safe, one render per key at a time."""

    def __init__(self, root: Path, grid_3x: int = GRID_3X, grid_2x: int = GRID_2X,
                 max_entries: int = MAX_ENTRIES) -> None:
        from twin.analysis.workspace import grid_problem

        if grid_3x < 3 or grid_3x % 2 == 0:
            raise ValueError(f"grid_3x must be odd and >= 3 (α3 = 0 on the grid), got {grid_3x}")
        # The CLI's memory bound (the maps of a grid too large for it never fit), checked here
        # before the directory is made; the settings cap grid_3x at 61 already.
        for design, grid in (("3x", grid_3x), ("2x", grid_2x)):
            if (problem := grid_problem(design, grid)) is not None:
                raise ValueError(f"grid_{design}: {problem.removeprefix(f'--n {grid}: ')}")
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.grid_3x = grid_3x
        self.grid_2x = grid_2x
        self.max_entries = max_entries
        self._locks: dict[str, threading.Lock] = {}
        self._locks_lock = threading.Lock()

    # -- public -----------------------------------------------------------------------------------

    def key_2x(self) -> str:
        return hashlib.sha256(f"xneck-workspace-2x v{RENDER_VERSION} n={self.grid_2x}".encode()).hexdigest()[:16]

    def peek(self, design: DesignName, key: str) -> Entry | None:
        """The entry if it is on disk, without rendering."""
        path = self.root / f"{design}-{key}"
        try:
            summary = json.loads((path / SUMMARY).read_text())
        except (OSError, ValueError):
            return None
        return Entry(path, summary, hit=True, render_s=0.0)

    def ensure_3x(self, params: Params) -> Entry:
        """The 3-X entry of ``params``, rendered now if it is not cached."""
        if params.n_joints != 3 or params.n_cables != 4:
            raise UnsupportedParameterSet(
                f"the workspace maps cover the 3-X neck (3 joints, 4 cables); this set has "
                f"{params.n_joints} joints and {params.n_cables} cables")
        return self._ensure("3x", params_key(params, self.grid_3x), lambda out: self._render_3x(params, out))

    def ensure_2x(self) -> Entry:
        """The 2-X paper's figures (independent of the parameter set), rendered now if not cached."""
        return self._ensure("2x", self.key_2x(), self._render_2x)

    # -- rendering --------------------------------------------------------------------------------

    def _ensure(self, design: DesignName, key: str, render: Any) -> Entry:
        with self._key_lock(f"{design}-{key}"):
            cached = self.peek(design, key)
            if cached is not None:
                os.utime(cached.path)  # least recently *used* is what pruning removes
                return cached
            t0 = time.perf_counter()
            final = self.root / f"{design}-{key}"
            tmp = Path(tempfile.mkdtemp(prefix=f".{design}-{key}-", dir=self.root))
            try:
                summary = {**render(tmp), "key": key}
                (tmp / SUMMARY).write_text(json.dumps(summary, indent=1))
                try:
                    os.replace(tmp, final)
                except OSError:
                    # Another server process on this data dir finished the same entry first.
                    if (theirs := self.peek(design, key)) is None:
                        raise
                    return theirs
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            dt = time.perf_counter() - t0
            log.info("workspace %s-%s rendered in %.2f s", design, key, dt)
            self._prune(design, keep=final)
            return Entry(final, summary, hit=False, render_s=dt)

    def _render_3x(self, params: Params, out: Path) -> dict[str, Any]:
        from twin.analysis.workspace import maps_3x, write_3x_figures
        from twin.model.numeric import build

        lim = params.limits
        mp = maps_3x(build(params), lim.f_min, lim.f_max, n=self.grid_3x, alpha_max=ALPHA_MAX_3X)
        with PYPLOT_LOCK:
            write_3x_figures(out, params=params, maps=mp)
        return summarize_3x(mp, params)

    def _render_2x(self, out: Path) -> dict[str, Any]:
        from twin.analysis.workspace import write_2x_figures

        with PYPLOT_LOCK:
            write_2x_figures(out, n=self.grid_2x)
        return {"design": "2x", "render_version": RENDER_VERSION, "grid": {"points_per_axis": self.grid_2x}}

    # -- bookkeeping ------------------------------------------------------------------------------

    def _key_lock(self, name: str) -> threading.Lock:
        with self._locks_lock:
            return self._locks.setdefault(name, threading.Lock())

    def _prune(self, design: DesignName, keep: Path) -> None:
        entries = sorted((p for p in self.root.glob(f"{design}-*") if p.is_dir() and p != keep),
                         key=lambda p: p.stat().st_mtime, reverse=True)
        for old in entries[self.max_entries - 1:]:
            shutil.rmtree(old, ignore_errors=True)
