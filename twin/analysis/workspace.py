"""Workspace, wrench-feasible workspace and stiffness maps (2-X paper Figs. 4-19; 3-X prototype).

Maps are plain arrays on regular grids (computed vectorised, one LAPACK batch per map); the
``plot_*`` functions turn them into matplotlib figures and ``write_*_figures`` save PNGs with the
Agg backend. Units: SI (m, rad, N, N·m/rad, N/m); figure axes are in degrees and in units of L.
The 2-X paper's joint angle θ_i = α_i/2 is ``half_alpha`` in the code (θ is the motor angle elsewhere).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from twin.analysis.kinematics import (
    FLAT,
    check_design,
    det_jacobian_2x,
    fk,
    foldback_half_alpha1,
    ik_2x_batch,
    singular_half_alpha1,
)
from twin.analysis.statics import Design, prototype_2x, stiffness_extremes, wrench_feasible_two_cables

__all__ = [
    "BYTES_PER_POINT",
    "CAPTIONS",
    "MEMORY_BUDGET",
    "CartesianCounts",
    "JointMaps2X",
    "Maps3X",
    "cartesian_counts",
    "cuspidality_threshold_numeric",
    "grid_problem",
    "joint_grid",
    "joint_maps_2x",
    "map_bytes",
    "maps_3x",
    "max_grid",
    "max_solutions_on_axis",
    "plot_3x_stiffness",
    "plot_3x_wfw",
    "singularity_polylines",
    "write_2x_figures",
    "write_3x_figures",
]

# One-line caption per figure file, shared by docs/workspace.md and the console.
CAPTIONS: dict[str, str] = {
    "2x_ik_example.png": "The four IK solutions at (0.03, 1.6) for L = 1, b = 2/3 (paper Fig. 3).",
    "2x_aspects.png": "Singularity curves (eq. 13 and θ1 = −θ2 ± π) and the two aspects, sign of det J, b = 2/3 (Fig. 4).",
    "2x_workspace.png": "Number of IK solutions without joint limits for b/L = 2/5, 2/3, 9/10; lines: images of the singularity curves (Fig. 5).",
    "2x_workspace_types.png": "Solutions per pair of X-joint configurations, up M or down M̄, b = 2/3 (Fig. 8).",
    "2x_workspace_limits.png": "Number of IK solutions with −90° < θ_i < 90° for b/L = 2/5, 2/3, 9/10 (Fig. 9).",
    "2x_workspace_prototype.png": "Workspace of the 2-X prototype (L = 0.1 m, b = 0.05 m) with joint limits (Fig. 11).",
    "2x_wfw_two_cables.png": "Two-cable wrench-feasible workspace, prototype and identical springs, joint and Cartesian space (Figs. 13-14).",
    "2x_joint_stiffness.png": "Minimal and maximal joint stiffness over the four-cable force redundancy (Figs. 16-17).",
    "2x_cartesian_stiffness.png": "Minimal and maximal Cartesian stiffness K_x, K_y over the four-cable WFW (Figs. 18-19).",
    "3x_wfw.png": "3-X prototype: configurations with Z(α) f = g(α) for f in [f_min, f_max], slices and head positions.",
    "3x_stiffness.png": "3-X prototype: joint stiffness at the lowest and the highest antagonistic tension, slice α3 = 0.",
}


# --- grid size bound -------------------------------------------------------------------------------

# Peak bytes per grid point while a design's figures are computed and drawn (numpy arrays and the
# points handed to matplotlib), measured with tracemalloc and ru_maxrss over write_*_figures at
# several n: ≈2.7 kB per α configuration for 3x (statics_3x's batched (n, n, n, 4, ...) LAPACK
# arrays, the two stiffness_3x finite-difference batches), ≈1.5 kB per grid point for 2x
# (cartesian_counts' (n, n, 4, 2) IK candidates and their Gauss-Newton steps). Rounded up.
BYTES_PER_POINT: dict[str, int] = {"2x": 1700, "3x": 3000}
# The largest estimate a grid may have: about 2 GB, so the stated maximum is the same on every
# machine and a grid within it fits beside a running stack (the 3-X maps cost n³: 22 GB and an
# OOM kill for --n 400 before the bound).
MEMORY_BUDGET = 2 * 1024**3
_DIMS = {"2x": 2, "3x": 3}


def map_bytes(design: str, n: int) -> int:
    """Estimated peak bytes of the maps and figures of ``design`` ("2x" or "3x") on an n-point grid
    per axis (n² points for 2x, n³ for 3x)."""
    return BYTES_PER_POINT[design] * n ** _DIMS[design]


def max_grid(design: str, budget: int = MEMORY_BUDGET) -> int:
    """Largest n whose :func:`map_bytes` is within ``budget``."""
    n = int(round((budget / BYTES_PER_POINT[design]) ** (1.0 / _DIMS[design])))
    while map_bytes(design, n) > budget:
        n -= 1
    while map_bytes(design, n + 1) <= budget:
        n += 1
    return n


def _size(nbytes: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if nbytes < 999.5:
            return f"{nbytes:.3g} {unit}"
        nbytes /= 1000.0
    return f"{nbytes:.3g} PB"


def grid_problem(design: str, n: int) -> str | None:
    """Why an n-point grid is refused for ``design`` (one line naming ``--n``), or None.

    Checked from :func:`map_bytes` alone, before any array is built."""
    if n < 2:
        return f"--n {n}: a grid needs >= 2 points per axis"
    m = max_grid(design)
    if n <= m:
        return None
    power = "²" if _DIMS[design] == 2 else "³"
    return (f"--n {n}: a {design} map of {n}{power} points needs ~{_size(map_bytes(design, n))} of memory; "
            f"at most {m} for this design (~{_size(map_bytes(design, m))})")


def _check_grid(design: str, n: int) -> None:
    if (problem := grid_problem(design, n)) is not None:
        raise ValueError(problem)


# --- solution counting ---------------------------------------------------------------------------


class CartesianCounts(NamedTuple):
    """Number of IK solutions on a Cartesian grid (Figs. 5, 8, 9, 11).

    x, y: (ny, nx) grid (unit of L). total: all solutions over θ in (−π, π]². limited: those with
    |θ_1|, |θ_2| < π/2 (both joints "up"). by_type: (ny, nx, 2, 2) count per (joint 1 up?,
    joint 2 up?), index 1 meaning up.
    """

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    total: NDArray[np.int64]
    limited: NDArray[np.int64]
    by_type: NDArray[np.int64]


def cartesian_counts(L: float, b: float, n: int = 300, extent: float | None = None) -> CartesianCounts:
    """Count IK solutions on an n x n grid over [−extent, extent]² (default 2.05 L, the reach)."""
    L, b = check_design(L, b)
    if n < 2:
        raise ValueError(f"n (grid size) must be >= 2, got {n}")
    extent = 2.05 * L if extent is None else float(extent)
    # An even grid keeps x = 0 off the grid: the symmetry axis carries boundary points.
    u = np.linspace(-extent, extent, n)
    X, Y = np.meshgrid(u, u, indexing="xy")
    sol = ik_2x_batch(X, Y, L, b)  # (n, n, 4, 2)
    valid = ~np.isnan(sol[..., 0])
    up = np.abs(sol) < FLAT
    total = valid.sum(-1)
    by_type = np.zeros(X.shape + (2, 2), dtype=np.int64)
    for i in (0, 1):
        for j in (0, 1):
            by_type[..., i, j] = (valid & (up[..., 0] == bool(i)) & (up[..., 1] == bool(j))).sum(-1)
    return CartesianCounts(X, Y, total, by_type[..., 1, 1], by_type)


def max_solutions_on_axis(L: float, b: float, samples: int = 2000) -> int:
    """Most IK solutions found on the symmetry axis x = 0 (without joint limits).

    The four-solution regions are born at x = 0 from a swallowtail at the straight configuration
    θ = 0 (a singular point, p = (0, 2√(L² − b²)), section 2.6), and they are thin near the
    threshold, so the sweep samples y at log-spaced offsets on both sides of that point.
    """
    L, b = check_design(L, b)
    y0 = 2.0 * np.sqrt(L * L - b * b)
    off = L * np.logspace(-10.0, 0.5, samples // 2)
    y = np.concatenate([y0 + off, y0 - off])
    sol = ik_2x_batch(np.zeros_like(y), y, L, b)
    return int((~np.isnan(sol[..., 0])).sum(-1).max())


def cuspidality_threshold_numeric(L: float = 1.0, tol: float = 1e-5) -> float:
    """Bisect b in (0, L) for the onset of four IK solutions (section 2.6: expect L/√6).

    Uses :func:`max_solutions_on_axis` as the predicate; the returned b has four solutions.
    """
    lo, hi = 0.05 * L, 0.95 * L
    if max_solutions_on_axis(L, lo) >= 4 or max_solutions_on_axis(L, hi) < 4:
        raise RuntimeError("the solution count does not change over the b sweep")
    while hi - lo > tol * L:
        mid = 0.5 * (lo + hi)
        if max_solutions_on_axis(L, mid) >= 4:
            hi = mid
        else:
            lo = mid
    return hi


def singularity_polylines(L: float, b: float, n: int = 721) -> dict[str, NDArray[np.float64]]:
    """Singularity curves in joint space (rad), each (n, 2) (θ_1, θ_2), with NaN where the curve
    wraps around the square (so they plot without spurious segments).

    "general": eq. (13); "foldback": θ_1 = −θ_2 ± π; "flat1"/"flat2": θ_i = ±π/2 (X-joint flat).
    """
    t2 = np.linspace(-np.pi, np.pi, n)

    def _break(t1: NDArray[np.float64]) -> NDArray[np.float64]:
        pts = np.stack([t1, t2], axis=-1)
        jump = np.abs(np.diff(t1)) > np.pi
        pts = np.insert(pts, np.nonzero(jump)[0] + 1, np.nan, axis=0)
        return pts

    out = {"general": _break(singular_half_alpha1(t2, L, b)), "foldback": _break(foldback_half_alpha1(t2))}
    line = np.linspace(-np.pi, np.pi, n)
    sep = np.full((1, 2), np.nan)
    out["flat1"] = np.concatenate(
        [np.stack([np.full(n, FLAT), line], -1), sep, np.stack([np.full(n, -FLAT), line], -1)]
    )
    out["flat2"] = np.concatenate(
        [np.stack([line, np.full(n, FLAT)], -1), sep, np.stack([line, np.full(n, -FLAT)], -1)]
    )
    return out


# --- wrench-feasible and stiffness maps ----------------------------------------------------------


def joint_grid(n: int, limit: float = FLAT, margin: float = 1e-3) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(1-D axis, (n, n, 2) grid) of θ in [−limit + margin, limit − margin] (rad).

    The flat singularity θ = ±π/2 is excluded: side-length derivatives vanish there and the
    cable forces of a configuration become unbounded.
    """
    if n < 2:
        raise ValueError(f"n (grid size) must be >= 2, got {n}")
    t = np.linspace(-limit + margin, limit - margin, n)
    return t, np.stack(np.meshgrid(t, t, indexing="ij"), axis=-1)


class JointMaps2X(NamedTuple):
    """Joint-space maps of a 2-X design (Figs. 13-19) on an (n, n) grid indexed [θ_1, θ_2].

    wfw2: two-cable wrench feasibility (eqs. 20-21). wfw4: four-cable feasibility (eq. 22).
    K_joint_min/max: (n, n, 2) diagonal K_θ1, K_θ2 (N·m/rad). K_c_min/max: (n, n, 2) diagonal
    K_x, K_y (N/m). xy: (n, n, 2) end point (m). All NaN where infeasible.
    """

    half_alpha: NDArray[np.float64]
    wfw2: NDArray[np.bool_]
    wfw4: NDArray[np.bool_]
    K_joint_min: NDArray[np.float64]
    K_joint_max: NDArray[np.float64]
    K_c_min: NDArray[np.float64]
    K_c_max: NDArray[np.float64]
    xy: NDArray[np.float64]


def joint_maps_2x(d: Design, n: int = 400) -> JointMaps2X:
    """Wrench-feasible workspaces and extreme stiffness of a 2-X design over |θ_i| < π/2."""
    if d.n_joints != 2:
        raise ValueError(f"design must have 2 joints, got {d.n_joints}")
    t, T = joint_grid(n)
    se = stiffness_extremes(d, T)
    diag = lambda K: np.diagonal(K, axis1=-2, axis2=-1)  # noqa: E731
    return JointMaps2X(
        half_alpha=t,
        wfw2=wrench_feasible_two_cables(d, T),
        wfw4=se.feasible,
        K_joint_min=diag(se.K_joint_min),
        K_joint_max=diag(se.K_joint_max),
        K_c_min=diag(se.K_c_min),
        K_c_max=diag(se.K_c_max),
        xy=fk(T, d.L, d.b),
    )


class Maps3X(NamedTuple):
    """3-X prototype over a grid of α (rad), shape (n, n, n) indexed [α_1, α_2, α_3].

    feasible: Z(α) f = g(α) has a solution with f_min <= f <= f_max. t_lo/t_hi: range of the long
    cable force f_4 (N). K_lo/K_hi: (n, n, n, 3) joint stiffness diagonal (N·m/rad) at the lowest
    and the highest antagonistic tension. xy: (n, n, n, 2) head position (m).
    """

    alpha: NDArray[np.float64]
    feasible: NDArray[np.bool_]
    t_lo: NDArray[np.float64]
    t_hi: NDArray[np.float64]
    K_lo: NDArray[np.float64]
    K_hi: NDArray[np.float64]
    xy: NDArray[np.float64]


def maps_3x(m: Any, f_min: float, f_max: float, n: int = 31, alpha_max: float = np.pi / 2) -> Maps3X:
    """Reachable configurations and stiffness range of the 3-X prototype (model ``m``)."""
    from twin.analysis.statics import statics_3x, stiffness_3x
    from twin.model.chain import head

    if n < 2:
        raise ValueError(f"n (grid size) must be >= 2, got {n}")
    a = np.linspace(-alpha_max, alpha_max, n)
    A = np.stack(np.meshgrid(a, a, a, indexing="ij"), axis=-1)
    st = statics_3x(m, A, f_min, f_max)
    nan = np.where(st.feasible, 0.0, np.nan)
    t_lo, t_hi = st.t_lo + nan, st.t_hi + nan
    f_lo = st.f_p + st.n * np.nan_to_num(t_lo)[..., None]
    f_hi = st.f_p + st.n * np.nan_to_num(t_hi)[..., None]
    K_lo = np.diagonal(stiffness_3x(m, A, f_lo), axis1=-2, axis2=-1) + nan[..., None]
    K_hi = np.diagonal(stiffness_3x(m, A, f_hi), axis1=-2, axis2=-1) + nan[..., None]
    return Maps3X(a, st.feasible, t_lo, t_hi, K_lo, K_hi, head(m, A))


# --- figures ---------------------------------------------------------------------------------------


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # headless: figures are only ever written to files
    import matplotlib.pyplot as plt

    return plt


_COUNT_COLORS = ["white", "#dddddd", "#9e9e9e", "#d95f5f", "#4c72b0"]  # 0..4 solutions


def _count_image(ax: Any, cc: CartesianCounts, counts: NDArray[np.int64], L: float) -> None:
    from matplotlib.colors import BoundaryNorm, ListedColormap

    cmap = ListedColormap(_COUNT_COLORS)
    ext = [cc.x.min() / L, cc.x.max() / L, cc.y.min() / L, cc.y.max() / L]
    im = ax.imshow(counts, origin="lower", extent=ext, cmap=cmap, norm=BoundaryNorm(np.arange(-0.5, 5), 5),
                   interpolation="nearest")
    ax.set_aspect("equal")
    ax.set_xlabel("x / L")
    ax.set_ylabel("y / L")
    return im


def _boundary_curves(ax: Any, L: float, b: float, flats: bool) -> None:
    """Images of the singularity curves (and of θ_i = ±π/2 when ``flats``): the region borders."""
    for key, pts in singularity_polylines(L, b).items():
        if key.startswith("flat") and not flats:
            continue
        xy = fk(pts, L, b) / L
        ax.plot(xy[:, 0], xy[:, 1], lw=0.6, color="k" if key == "general" else "tab:green")


def plot_counts(Ls_bs: list[tuple[float, float]], limited: bool, n: int = 300) -> Any:
    """Figs. 5 (``limited=False``) and 9 (``limited=True``): solution counts per region."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(Ls_bs), figsize=(4.2 * len(Ls_bs), 4.4), constrained_layout=True)
    for ax, (L, b) in zip(np.atleast_1d(axes), Ls_bs):
        cc = cartesian_counts(L, b, n)
        im = _count_image(ax, cc, cc.limited if limited else cc.total, L)
        _boundary_curves(ax, L, b, flats=limited)
        ax.set_title(f"b/L = {b / L:.3g}" + (",  |θ_i| < 90°" if limited else ""))
    cb = fig.colorbar(im, ax=axes, ticks=range(5), shrink=0.8)
    cb.set_label("number of IK solutions")
    return fig


def plot_types(L: float, b: float, n: int = 300) -> Any:
    """Fig. 8: solutions per pair of X-joint configurations (up M_i / down M̄_i)."""
    plt = _plt()
    cc = cartesian_counts(L, b, n)
    fig, axes = plt.subplots(2, 2, figsize=(8, 8), constrained_layout=True)
    names = {1: "M", 0: "M̄"}
    for i in (1, 0):
        for j in (1, 0):
            ax = axes[1 - i, 1 - j]
            im = _count_image(ax, cc, cc.by_type[..., i, j], L)
            _boundary_curves(ax, L, b, flats=True)
            ax.set_title(f"{names[i]}1 {names[j]}2")
    fig.colorbar(im, ax=axes, ticks=range(5), shrink=0.6, label="solutions of this type")
    fig.suptitle(f"b/L = {b / L:.3g}: M = X-joint up (|θ| < 90°), M̄ = down")
    return fig


def plot_aspects(L: float, b: float, n: int = 400) -> Any:
    """Fig. 4: singularity curves in joint space and the two aspects (sign of det J)."""
    plt = _plt()
    t = np.linspace(-np.pi, np.pi, n)
    T1, T2 = np.meshgrid(t, t, indexing="xy")
    fig, ax = plt.subplots(figsize=(5, 5), constrained_layout=True)
    ax.contourf(np.degrees(T1), np.degrees(T2), np.sign(det_jacobian_2x(T1, T2, L, b)), levels=[-2, 0, 2],
                colors=["#f3d9b1", "#b9d3ee"])
    curves = singularity_polylines(L, b)
    for key, style in (("general", "k-"), ("foldback", "r-")):
        p = np.degrees(curves[key])
        ax.plot(p[:, 0], p[:, 1], style, lw=1.2, label={"general": "eq. (13)", "foldback": "θ1 = −θ2 ± π"}[key])
    ax.set_xlabel("θ1 (deg)")
    ax.set_ylabel("θ2 (deg)")
    ax.set_title(f"aspects (det J > 0 blue, < 0 orange), b/L = {b / L:.3g}")
    ax.legend(loc="lower left", fontsize=8)
    return fig


def plot_ik_example(L: float = 1.0, b: float = 2.0 / 3.0, x: float = 0.03, y: float = 1.6) -> Any:
    """Fig. 3: the IK solutions at one point, drawn as bars."""
    from twin.analysis.kinematics import bar_nodes, ik_2x

    plt = _plt()
    sols = ik_2x(x, y, L, b)
    fig, axes = plt.subplots(1, max(len(sols), 1), figsize=(3 * max(len(sols), 1), 3.6), constrained_layout=True)
    for ax, th in zip(np.atleast_1d(axes), sols):
        nodes = bar_nodes(th, L, b)
        for i in range(nodes.shape[0]):
            ax.plot(nodes[i, :, 0], nodes[i, :, 1], "k-", lw=2.5)
            if i:
                for lo, hi in ((0, 1), (1, 0)):
                    ax.plot([nodes[i - 1, lo, 0], nodes[i, hi, 0]], [nodes[i - 1, lo, 1], nodes[i, hi, 1]], "b-")
        ax.plot([x], [y], "r*", ms=10)
        ax.set_aspect("equal")
        ax.set_title(f"θ = ({np.degrees(th[0]):.1f}°, {np.degrees(th[1]):.1f}°)", fontsize=9)
        ax.set_xlim(-2 * L, 2 * L)
        ax.set_ylim(-1.2 * L, 2.1 * L)
    fig.suptitle(f"IK solutions at ({x}, {y}), L = {L}, b = {b:.4g}")
    return fig


def _no_data(ax: Any, what: str, n: int) -> None:
    """An empty panel saying why: a coarse grid (or a design, or force bounds) that leaves no grid
    point where the map is defined is a result, not an error."""
    ax.text(0.5, 0.5, f"no grid point {what}\n(n = {n} per axis: a finer grid may find some)",
            ha="center", va="center", transform=ax.transAxes, fontsize=8, color="0.35")
    ax.set_xticks([])
    ax.set_yticks([])


def _joint_image(ax: Any, t: NDArray[np.float64], z: NDArray[np.float64], title: str, **kw: Any) -> Any:
    deg = np.degrees(t)
    im = ax.pcolormesh(deg, deg, z.T, shading="nearest", **kw)
    ax.set_aspect("equal")
    ax.set_xlabel("θ1 (deg)")
    ax.set_ylabel("θ2 (deg)")
    ax.set_title(title, fontsize=9)
    return im


def plot_wfw_two_cables(designs: dict[str, Design], n: int = 300) -> Any:
    """Figs. 13-14: two-cable wrench-feasible workspace in joint and Cartesian space."""
    plt = _plt()
    fig, axes = plt.subplots(len(designs), 2, figsize=(9, 4.3 * len(designs)), constrained_layout=True,
                             squeeze=False)
    for row, (name, d) in zip(axes, designs.items()):
        maps = joint_maps_2x(d, n)
        t, T = joint_grid(n)
        from twin.analysis.statics import forces_two_cables

        f = forces_two_cables(d, T)
        taut = np.all(f >= d.f_min, axis=-1)
        z = np.where(maps.wfw2, 2, np.where(taut, 1, 0)).astype(float)
        from matplotlib.colors import ListedColormap

        cmap = ListedColormap(["white", "#cccccc", "#1f5fbf"])
        _joint_image(row[0], t, z, f"{name}: two cables, joint space", cmap=cmap, vmin=0, vmax=2)
        xy = maps.xy / d.L
        for level, color in ((1, "#cccccc"), (2, "#1f5fbf")):
            sel = z == level
            row[1].plot(xy[sel, 0], xy[sel, 1], ".", ms=1, color=color)
        row[1].set_aspect("equal")
        row[1].set_xlabel("x / L")
        row[1].set_ylabel("y / L")
        row[1].set_title(f"blue: {d.f_min:g} <= f <= {d.f_max:g} N; grey: only f >= {d.f_min:g} N", fontsize=9)
    return fig


def plot_joint_stiffness(d: Design, n: int = 300) -> Any:
    """Figs. 16-17: minimal and maximal joint stiffness K_θ1, K_θ2 over the four-cable WFW."""
    plt = _plt()
    maps = joint_maps_2x(d, n)
    fig, axes = plt.subplots(2, 2, figsize=(9, 8.5), constrained_layout=True)
    for col, i in enumerate((0, 1)):
        vals = np.concatenate([maps.K_joint_min[..., i].ravel(), maps.K_joint_max[..., i].ravel()])
        vals = vals[np.isfinite(vals)]
        lim = float(np.abs(vals).max()) if vals.size else 0.0
        for row, (kind, K) in enumerate((("min", maps.K_joint_min), ("max", maps.K_joint_max))):
            if not vals.size:
                axes[row, col].set_title(f"{kind} K_θ{i + 1} (N·m/rad)", fontsize=9)
                _no_data(axes[row, col], "in the four-cable WFW", n)
                continue
            im = _joint_image(axes[row, col], maps.half_alpha, K[..., i], f"{kind} K_θ{i + 1} (N·m/rad)",
                              cmap="RdBu_r", vmin=-lim, vmax=lim)
            fig.colorbar(im, ax=axes[row, col], shrink=0.8)
    fig.suptitle(f"four cables, {d.f_min:g} <= f <= {d.f_max:g} N (blank: not wrench-feasible; red: unstable < 0)")
    return fig


def plot_cartesian_stiffness(d: Design, n: int = 300) -> Any:
    """Figs. 18-19: minimal and maximal Cartesian stiffness K_x, K_y over the WFW (log scale)."""
    from matplotlib.colors import LogNorm

    plt = _plt()
    maps = joint_maps_2x(d, n)
    fig, axes = plt.subplots(2, 2, figsize=(9, 8.5), constrained_layout=True)
    xy = maps.xy / d.L
    for col, (i, name) in enumerate(((0, "K_x"), (1, "K_y"))):
        vals = np.concatenate([maps.K_c_min[..., i].ravel(), maps.K_c_max[..., i].ravel()])
        pos = vals[np.isfinite(vals) & (vals > 0)]
        if pos.size:
            lo, hi = np.percentile(pos, [2, 98])
            hi = max(hi, lo * (1.0 + 1e-9))  # one value: LogNorm needs vmin < vmax
        for row, (kind, K) in enumerate((("min", maps.K_c_min), ("max", maps.K_c_max))):
            k = K[..., i]
            sel = np.isfinite(k) & (k > 0)
            ax = axes[row, col]
            ax.set_title(f"{kind} {name} (N/m)", fontsize=9)
            if not pos.size:
                _no_data(ax, "in the four-cable WFW with a positive stiffness", n)
                continue
            sc = ax.scatter(xy[sel, 0], xy[sel, 1], c=k[sel], s=1, norm=LogNorm(lo, hi), cmap="viridis")
            ax.set_aspect("equal")
            ax.set_xlabel("x / L")
            ax.set_ylabel("y / L")
            fig.colorbar(sc, ax=ax, shrink=0.8)
    fig.suptitle("Cartesian stiffness over the four-cable WFW (non-positive and singular points omitted)")
    return fig


def _png(plt: Any, make: Any) -> bytes:
    """The figure ``make()`` draws, as PNG bytes (the figure closed)."""
    fig = make()
    buffer = io.BytesIO()
    try:
        fig.savefig(buffer, dpi=110, format="png")
    finally:
        plt.close(fig)
    return buffer.getvalue()


def _write_all(plt: Any, out: Path, jobs: dict[str, Any]) -> list[Path]:
    """Draw every figure of ``jobs`` (file name -> drawing function) first, then write them, each
    whole (bridge.archive.atomic_write): an error while drawing leaves no figure of the set written
    (before, 8 of 9 PNGs were left behind), a full disk or a Ctrl-C the previous file or none,
    never a truncated one. ``out`` is made only once the figures are drawn."""
    from bridge.archive import atomic_write

    drawn = {name: _png(plt, make) for name, make in jobs.items()}
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, data in drawn.items():
        atomic_write(out / name, data)
        written.append(out / name)
    return written


def write_2x_figures(out: Path, n: int = 300, design: Design | None = None) -> list[Path]:
    """Write the 2-X paper's figures (3, 4, 5, 8, 9, 11, 13-19) as PNGs into ``out``.

    :class:`ValueError` for a grid :func:`grid_problem` refuses, before anything is computed."""
    _check_grid("2x", n)
    plt = _plt()
    d = prototype_2x() if design is None else design
    same = Design(**{**_fields(d), "k_l": (90.0, 90.0), "k_r": (90.0, 90.0)})
    designs = [(1.0, 2 / 5), (1.0, 2 / 3), (1.0, 9 / 10)]
    jobs = {
        "2x_ik_example.png": lambda: plot_ik_example(),
        "2x_aspects.png": lambda: plot_aspects(1.0, 2 / 3),
        "2x_workspace.png": lambda: plot_counts(designs, limited=False, n=n),
        "2x_workspace_types.png": lambda: plot_types(1.0, 2 / 3, n=n),
        "2x_workspace_limits.png": lambda: plot_counts(designs, limited=True, n=n),
        "2x_workspace_prototype.png": lambda: plot_counts([(d.L, d.b)], limited=True, n=n),
        "2x_wfw_two_cables.png": lambda: plot_wfw_two_cables({"prototype springs": d, "identical springs": same}, n),
        "2x_joint_stiffness.png": lambda: plot_joint_stiffness(d, n),
        "2x_cartesian_stiffness.png": lambda: plot_cartesian_stiffness(d, n),
    }
    return _write_all(plt, Path(out), jobs)


def _fields(d: Design) -> dict[str, Any]:
    from dataclasses import fields

    return {f.name: getattr(d, f.name) for f in fields(d)}


def plot_3x_wfw(mp: Maps3X, f_min: float, f_max: float) -> Any:
    """Reachable set of the 3-X prototype: feasibility on the slices α3 = −α_max, 0, α_max
    (grid ends and middle) and the head positions (m) of all grid configurations."""
    plt = _plt()
    a = np.degrees(mp.alpha)
    n = a.size
    fig, axes = plt.subplots(1, 4, figsize=(17, 4.8), constrained_layout=True)
    for ax, k in zip(axes[:3], (0, n // 2, n - 1)):
        ax.pcolormesh(a, a, mp.feasible[:, :, k].T.astype(float), shading="nearest", cmap="Blues", vmin=0, vmax=1.3)
        ax.set_aspect("equal")
        ax.set_xlabel("α1 (deg)")
        ax.set_ylabel("α2 (deg)")
        ax.set_title(f"feasible (blue), α3 = {a[k]:.0f}°", fontsize=9)
    xy = mp.xy
    ax = axes[3]
    ax.plot(xy[~mp.feasible][:, 0], xy[~mp.feasible][:, 1], ".", ms=0.5, color="#dddddd", label="not feasible")
    ax.plot(xy[mp.feasible][:, 0], xy[mp.feasible][:, 1], ".", ms=0.5, color="#1f5fbf", label="feasible")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("head positions", fontsize=9)
    ax.legend(markerscale=10, fontsize=8)
    fig.suptitle(f"3-X prototype: Z(α) f = g(α) with {f_min:g} <= f <= {f_max:g} N "
                 f"({100 * mp.feasible.mean():.0f}% of |α_i| <= {a[-1]:.0f}°)")
    return fig


def plot_3x_stiffness(mp: Maps3X) -> Any:
    """Joint stiffness diagonal K_ii (N·m/rad) of the 3-X prototype on the middle α3 slice (α3 = 0
    for an odd grid), at the lowest and the highest antagonistic tension."""
    plt = _plt()
    a = np.degrees(mp.alpha)
    k = a.size // 2
    fig, axes = plt.subplots(2, 3, figsize=(13, 8), constrained_layout=True)
    for j in range(3):
        lo, hi = mp.K_lo[:, :, k, j], mp.K_hi[:, :, k, j]
        feasible = bool(np.isfinite(hi).any() and np.isfinite(lo).any())
        vmax = float(np.nanmax(hi)) if feasible else 0.0
        vmin = min(float(np.nanmin(lo)), 0.0) if feasible else 0.0
        for row, (name, z) in enumerate((("lowest tension", lo), ("highest tension", hi))):
            ax = axes[row, j]
            if not feasible:
                ax.set_title(f"K_{j + 1}{j + 1}, {name} (N·m/rad)", fontsize=9)
                _no_data(ax, f"wrench-feasible at α3 = {a[k]:.0f}°", a.size)
                continue
            im = ax.pcolormesh(a, a, z.T, shading="nearest", cmap="viridis", vmin=vmin, vmax=vmax)
            ax.set_aspect("equal")
            ax.set_xlabel("α1 (deg)")
            ax.set_ylabel("α2 (deg)")
            ax.set_title(f"K_{j + 1}{j + 1}, {name} (N·m/rad)", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"3-X joint stiffness at α3 = {a[k]:.0f}° over the force redundancy f = f_p + n t")
    return fig


def write_3x_figures(out: Path, n: int = 31, params: Any = None, maps: Maps3X | None = None) -> list[Path]:
    """Write the 3-X prototype's maps: reachable configurations for f in [f_min, f_max], and the
    joint stiffness range that raising the antagonistic tension gives.

    ``maps``: already computed :func:`maps_3x` output for ``params`` (then ``n`` is ignored), so
    a caller that also needs the numbers computes them once. :class:`ValueError` for a grid
    :func:`grid_problem` refuses, before anything is computed.
    """
    _check_grid("3x", n if maps is None else maps.alpha.size)
    from twin.model.numeric import build
    from twin.model.params import load_params

    plt = _plt()
    params = load_params() if params is None else params
    lim = params.limits
    mp = maps_3x(build(params), lim.f_min, lim.f_max, n=n) if maps is None else maps
    return _write_all(plt, Path(out), {"3x_wfw.png": lambda: plot_3x_wfw(mp, lim.f_min, lim.f_max),
                                       "3x_stiffness.png": lambda: plot_3x_stiffness(mp)})
