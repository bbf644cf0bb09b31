"""Workspace figures (twin/analysis/workspace.py): the memory bound of their grids and coarse grids
(audit of 2026-12). Small grids only: the bound is tested on its estimate, never by allocating."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import twin.analysis.workspace as ws
from twin.analysis.statics import prototype_2x
from twin.model.numeric import build
from twin.model.params import load_params


def test_the_grid_bound_follows_from_the_memory_estimate():
    assert ws.max_grid("3x") == 89 and ws.max_grid("2x") == 1123
    for design in ("2x", "3x"):
        m = ws.max_grid(design)
        assert ws.map_bytes(design, m) <= ws.MEMORY_BUDGET < ws.map_bytes(design, m + 1)
        assert ws.grid_problem(design, m) is None and ws.grid_problem(design, 2) is None
    assert ws.map_bytes("3x", 400) == 400**3 * ws.BYTES_PER_POINT["3x"]
    said = ws.grid_problem("3x", 400)
    assert said is not None and said.startswith("--n 400: a 3x map of 400³ points needs ~192 GB of memory; at most 89")
    assert "1.7 PB" in (ws.grid_problem("2x", 1_000_000) or "")


def test_write_refuses_a_grid_beyond_the_bound_before_computing(tmp_path, monkeypatch):
    def never(*a, **k):
        raise AssertionError("computed a map beyond the bound")

    monkeypatch.setattr(ws, "maps_3x", never)
    monkeypatch.setattr(ws, "cartesian_counts", never)
    with pytest.raises(ValueError, match="at most 89"):
        ws.write_3x_figures(tmp_path / "a", n=400)
    with pytest.raises(ValueError, match="at most 1123"):
        ws.write_2x_figures(tmp_path / "b", n=1_000_000)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("design, n", [("3x", 21), ("2x", 120)])
def test_the_estimate_bounds_the_arrays_the_maps_build(design, n):
    """The bytes per point are not an underestimate: the peak traced while the largest map of a
    design is computed (maps_3x; for 2x cartesian_counts, above joint_maps_2x) stays below them."""
    if design == "3x":
        p = load_params()
        m = build(p)
        tracemalloc.start()
        ws.maps_3x(m, p.limits.f_min, p.limits.f_max, n=n)
    else:
        tracemalloc.start()
        ws.cartesian_counts(1.0, 2 / 3, n)
        ws.joint_maps_2x(prototype_2x(), n)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < ws.map_bytes(design, n)


def _texts(fig) -> str:
    return " ".join(t.get_text() for ax in fig.axes for t in ax.texts)


@pytest.mark.parametrize("n", [2, 3])
def test_stiffness_figures_of_a_grid_without_feasible_points_say_so(n):
    """n = 2, 3: no grid point has a positive Cartesian stiffness in the four-cable WFW; before,
    np.percentile of the empty set raised an IndexError."""
    d = prototype_2x()
    with np.errstate(all="raise"):
        fig = ws.plot_cartesian_stiffness(d, n)
    assert "no grid point" in _texts(fig) and f"n = {n}" in _texts(fig)
    ws.plot_joint_stiffness(d, n)


def test_a_figure_that_fails_leaves_no_figure_written(tmp_path, monkeypatch):
    """The figures are drawn first and written after: an error while drawing leaves nothing."""
    def broken(*a, **k):
        raise RuntimeError("drawing failed")

    monkeypatch.setattr(ws, "plot_cartesian_stiffness", broken)
    out = tmp_path / "ws"
    with pytest.raises(RuntimeError, match="drawing failed"):
        ws.write_2x_figures(out, n=4)
    assert not out.exists() or not list(Path(out).iterdir())
