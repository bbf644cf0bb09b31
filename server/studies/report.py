"""A study's summary (JSON) and figures (PNG, matplotlib Agg) from its Parquet rows.

- distributions: each metric per law (box plots; design: histograms);
- sensitivity: Spearman rank correlation of each metric with each varied input, per law (a rank
  correlation suits monotone, non-linear effects and is robust to outliers);
- design maps: a design study's metrics over its first two grid inputs (mean over the others).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from server.studies.execute import read_rows
from server.studies.spec import Study, StudyError

METRICS = {
    "control": ("e_mean_all_deg", "e_max_all_deg", "e_alpha_mean_all_deg", "force_mean_all_N", "force_max_all_N",
                "saturated_ticks", "tension_min_N"),
    "identification": ("f_s_rel_error_max", "k_rel_error_max", "lambda_rel_error_max", "f_s_rel_sigma_max",
                       "k_rel_sigma_max", "lambda_rel_sigma_max", "k_covered_fraction", "lambda_covered_fraction",
                       "k_within_10pct_fraction", "lambda_within_10pct_fraction"),
    "design": ("feasible_fraction", "stable_fraction", "k_min_median_N_m_per_rad", "k_max_median_N_m_per_rad"),
}
FIGURES = ("distributions.png", "sensitivity.png", "design_maps.png")


def _column(rows: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in rows], dtype=float)


def _stats(x: np.ndarray, of: int | None = None) -> dict[str, float | int] | None:
    """Statistics of the finite values; ``n`` of them, out of ``of`` runs (all outcomes) when given."""
    x = x[np.isfinite(x)]
    if x.size == 0:
        return None
    return {"n": int(x.size), **({"of": of} if of is not None else {}), "mean": float(x.mean()), "median": float(np.median(x)), "p5": float(np.percentile(x, 5)),
            "p95": float(np.percentile(x, 95)), "min": float(x.min()), "max": float(x.max())}


def _ranks(x: np.ndarray) -> np.ndarray:
    """Ranks from 0, ties sharing their mean rank (numpy only: scipy's import costs a study more than its use)."""
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(len(x))
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    sums = np.bincount(inverse, weights=ranks)
    return (sums / counts)[inverse]


def spearman(x: np.ndarray, y: np.ndarray) -> float | None:
    """Spearman's rank correlation of the finite pairs (Pearson's of their ranks); None when either
    side is constant or there are fewer than 3 pairs."""
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return None
    rho = float(np.corrcoef(_ranks(x[ok]), _ranks(y[ok]))[0, 1])
    return rho if math.isfinite(rho) else None


def summarize(study: Study, rows: list[dict[str, Any]], total: int) -> dict[str, Any]:
    """Counts, outcomes (all, and per law), per-law metric statistics, sensitivities, timing.

    A law's statistics are over its finished runs with a finite value: each says how many (``n``) of
    how many runs of that law (``of``, every outcome), so a law whose diverged half is left out does not
    read like a law that lost none (``outcomes_per_law`` says what became of the others)."""
    inputs = [f"x:{v.label}" for v in study.varies()]
    metrics = METRICS[study.kind]
    ok = [r for r in rows if r.get("outcome") == "finished"]
    laws = sorted({int(r["law"]) for r in rows})
    outcomes: dict[str, int] = {}
    per_law_outcomes: dict[str, dict[str, int]] = {str(law): {} for law in laws}
    for r in rows:
        outcomes[r["outcome"]] = outcomes.get(r["outcome"], 0) + 1
        mine = per_law_outcomes[str(int(r["law"]))]
        mine[r["outcome"]] = mine.get(r["outcome"], 0) + 1
    per_law: dict[str, Any] = {}
    sens: dict[str, Any] = {}
    for law in laws:
        lr = [r for r in ok if int(r["law"]) == law]
        runs = sum(per_law_outcomes[str(law)].values())
        per_law[str(law)] = {m: _stats(_column(lr, m), runs) for m in metrics}
        sens[str(law)] = {m: {i[2:]: spearman(_column(lr, i), _column(lr, m)) for i in inputs} for m in metrics}
    run_s = _column(rows, "run_s")
    failures = [{"run_id": r["run_id"], "outcome": r["outcome"], "message": r.get("message", "")}
                for r in rows if r.get("outcome") != "finished"][:20]
    return {
        "digest": study.digest(), "kind": study.kind, "study": study.canonical(),
        "runs_total": total, "runs_done": len(rows), "complete": len(rows) >= total,
        "outcomes": outcomes, "outcomes_per_law": per_law_outcomes, "metrics": per_law, "sensitivity_spearman": sens,
        "run_s": _stats(run_s), "failures": failures,
        "versions": sorted({str(r.get("version")) for r in rows}),
    }


def check_outputs(out: Path) -> None:
    """:class:`StudyError` naming what stands where the summary or the figures go (a file named
    ``figures``, a folder named ``summary.json``): said before the runs, not after them."""
    out = Path(out)
    if (out / "figures").exists() and not (out / "figures").is_dir():
        raise StudyError(f"{out / 'figures'}: a file where the study's figures folder goes; move it away")
    if (out / "summary.json").is_dir():
        raise StudyError(f"{out / 'summary.json'}: a folder where the study's summary goes; move it away")


@contextlib.contextmanager
def _writing(path: Path) -> Iterator[None]:
    """An OSError of writing ``path`` (through a hidden temp file, or its folder) names ``path``: the file
    the user knows, not the temp file (os.replace's error names both) nor the study directory."""
    try:
        yield
    except OSError as exc:
        if exc.errno is None or (exc.filename == str(path) and exc.filename2 is None):
            raise
        raise type(exc)(exc.errno, exc.strerror, str(path)) from exc


def write_outputs(out: Path, study: Study, total: int) -> dict[str, Any]:
    """summary.json and figures/ of the rows so far (atomically replaced: a reader never sees half a file).
    An OSError names the file that could not be written."""
    rows = read_rows(out)
    summary = summarize(study, rows, total)
    summary["figures"] = write_figures(out / "figures", study, rows, summary) if rows else []
    tmp = out / ".summary.json.tmp"
    with _writing(out / "summary.json"):
        tmp.write_text(json.dumps(summary, indent=2, allow_nan=False, default=_none_for_nan))
        os.replace(tmp, out / "summary.json")
    return summary


def _none_for_nan(x: Any) -> Any:
    return None


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> str:
    tmp = path.with_name(f".{path.name}.tmp.png")
    try:
        with _writing(path):
            fig.savefig(tmp, dpi=90)
            os.replace(tmp, path)
    finally:
        _plt().close(fig)
    return path.name


def write_figures(folder: Path, study: Study, rows: list[dict[str, Any]], summary: dict[str, Any]) -> list[str]:
    with _writing(folder):
        folder.mkdir(parents=True, exist_ok=True)
    plt = _plt()
    ok = [r for r in rows if r.get("outcome") == "finished"]
    metrics = METRICS[study.kind]
    laws = sorted({int(r["law"]) for r in ok})
    names: list[str] = []
    if not ok:
        return names
    # distributions per law
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.2 * len(metrics), 3.2), squeeze=False)
    for ax, m in zip(axes[0], metrics):
        data = [_column([r for r in ok if int(r["law"]) == law], m) for law in laws]
        data = [d[np.isfinite(d)] for d in data]
        if study.kind == "design":
            ax.hist(np.concatenate(data) if data else [], bins=20)
        else:
            ax.boxplot([d if d.size else [np.nan] for d in data], tick_labels=[f"law {law}" for law in laws])
        ax.set_title(m, fontsize=8)
    fig.suptitle(f"{study.kind} study {study.digest()}: {len(ok)} runs", fontsize=9)
    fig.tight_layout()
    names.append(_save(fig, folder / "distributions.png"))
    # sensitivity (Spearman) per law
    inputs = [v.label for v in study.varies()]
    if inputs:
        fig, axes = plt.subplots(1, len(laws), figsize=(1.2 + 1.1 * len(inputs) * len(laws) + 2, 0.45 * len(metrics) + 1.8),
                                 squeeze=False)
        for ax, law in zip(axes[0], laws):
            s = summary["sensitivity_spearman"][str(law)]
            grid = np.array([[np.nan if s[m][i] is None else s[m][i] for i in inputs] for m in metrics])
            im = ax.imshow(grid, vmin=-1, vmax=1, cmap="coolwarm", aspect="auto")
            ax.set_xticks(range(len(inputs)), inputs, rotation=30, ha="right", fontsize=7)
            ax.set_yticks(range(len(metrics)), metrics, fontsize=7)
            for (a, b), v in np.ndenumerate(grid):
                if np.isfinite(v):
                    ax.text(b, a, f"{v:+.2f}", ha="center", va="center", fontsize=6)
            ax.set_title("design" if law == 0 else f"law {law}", fontsize=8)
            fig.colorbar(im, ax=ax, label="Spearman ρ")
        fig.tight_layout()
        names.append(_save(fig, folder / "sensitivity.png"))
    grids = [v.label for v in study.varies() if v.kind == "grid"]
    if study.kind == "design" and grids:
        names.append(_design_maps(plt, folder, ok, grids, metrics))
    return names


def _design_maps(plt: Any, folder: Path, ok: list[dict[str, Any]], grids: list[str], metrics: tuple[str, ...]) -> str:
    """Mean of each metric over the first two grid inputs (a line over one when there is one)."""
    xs = _column(ok, f"x:{grids[0]}")
    ux = np.unique(xs)
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.4 * len(metrics), 3.0), squeeze=False)
    for ax, m in zip(axes[0], metrics):
        z = _column(ok, m)
        if len(grids) >= 2:
            ys = _column(ok, f"x:{grids[1]}")
            uy = np.unique(ys)
            img = np.full((len(uy), len(ux)), np.nan)
            for i, y in enumerate(uy):
                for j, x in enumerate(ux):
                    sel = (xs == x) & (ys == y) & np.isfinite(z)
                    if sel.any():
                        img[i, j] = z[sel].mean()
            mesh = ax.pcolormesh(ux, uy, img, shading="nearest")
            fig.colorbar(mesh, ax=ax)
            ax.set_ylabel(grids[1], fontsize=7)
        else:
            ax.plot(ux, [z[(xs == x) & np.isfinite(z)].mean() if ((xs == x) & np.isfinite(z)).any() else np.nan for x in ux], "o-")
        ax.set_xlabel(grids[0], fontsize=7)
        ax.set_title(m, fontsize=8)
    fig.tight_layout()
    return _save(fig, folder / "design_maps.png")
