"""Variants of the load-friction fit tried and not shipped, over the same campaigns as the shipped fit
(docs/identification-coverage.md, "Variants tried, not shipped, by one command").

Per seed: the identification closed loop (controller/identification_loop.py, the §5.2.2 cycloids)
on the truth, then Table 2 by `loadfriction` (twin/identification/loadfriction.py) as shipped and
with each variant swapped in for the duration of its fit. Prints, per variant, the mean error and
the ±2σ coverage of every k and λ over the seeds, and the totals (issue 17's targets: within 10 %,
covered in ≥ 85 % of cases). The variants:

- ``shipped``: the estimator as it is.
- ``elastic-creep``: the creep element as shipped until 2026-11-26, a low-pass of the elastic
  tension of the whole stretch, instead of driven by the model's own tension t (as the robot
  truth's, twin/sim/integrator.py ``creep_update``).
- ``full-drive``: the creep driven by the whole tension it leaves, the damping's c_a·ẋ included
  (as the robot truth's element), instead of its elastic part.
- ``cluster-5s``, ``cluster-10s``, ``cluster-20s``: σ by the cluster covariance over blocks of
  record of that length (the block bootstrap's linearised form) instead of the HAC sandwich.
- ``bartlett-150``, ``bartlett-300``: the HAC sandwich with that many lags instead of the chosen.
- ``min-force-12``: only rows whose force is above 12 N (the shipped fit: 2 N).
- ``tau-2s`` (any ``tau-Xs``): the creep time constant held at X s (the robot truth's is 2 s)
  instead of chosen from the grid.
- ``beta-0.05`` (any ``beta-X``): the creep ratio β held at X on every cable (the robot truth's
  is 0.05) instead of fitted.
- ``residual-tau``: τ per cable at the camera residual's minimum (as shipped until 2026-11-26)
  instead of at the root of its instrument's moment.
- ``shared-tau``: one τ for the four cables (one line), picked by the sum of their log camera
  residuals.
- ``A+B``: variants A and B together, e.g. ``elastic-creep+tau-2s``.
- ``force-offset-1.5`` (any ``force-offset-C``): the fitted force less C newtons on every cable, a
  friction offset that does not reverse with the motion (the direction asymmetry's), held known.
- ``gear-F-B``: the gear's meshing losses held at F (winding) and B (back-driven) instead of the
  parameter file's 0.08 and 0.09; ``gear-0-0`` is the fit without them (as shipped until 2026-11-26).
- ``gear-undivided``: the gear's loss on the tension's slopes only, the winding rows' friction
  offset F₀ not divided by 1 − g_f.
- ``reversal-guard-0.2s`` (any ``reversal-guard-Ss``): rows within S seconds of a reversal of
  their motor dropped (the filtered force smears the friction's jump at a reversal over the
  filter's memory, the model puts it at the filtered speed's zero).
- ``offset-free``: an eighth parameter per cable, F_a (N, bounds ±10 N), a friction offset that
  does not reverse with the motion (the direction asymmetry's): y = ((1 + a·μ)·t + a·F₀ + |a|·F_a
  − g_b·a⁻·t)/(1 − g_f·a⁺), started at 0.
- ``filtered-shape``: eq. 37's shape a = (2/π)·arctan(c_f·θ̇) computed at 500 Hz on the encoders'
  speed, then filtered and decimated as the force was (processing.preprocess), instead of taken
  at the filtered, decimated speed; tabulated over 41 values of c_f, interpolated in log c_f.

    .venv/bin/python docs/identification/estimator_variants.py --truth robot --first 21 --seeds 20
    .venv/bin/python docs/identification/estimator_variants.py --variants shipped elastic-creep --seeds 3
    .venv/bin/python docs/identification/estimator_variants.py --only friction --first 0 --seeds 3 \
        --variants shipped full-drive
    .venv/bin/python docs/identification/estimator_variants.py --archive docs/identification/runs/paper-0.mcap \
        --variants shipped force-offset-1 force-offset-2
    .venv/bin/python docs/identification/estimator_variants.py --campaign law1 --first 21 --seeds 6 \
        --truth-set friction.gear_loss_forward=0 friction.gear_loss_backward=0 --variants shipped gear-0-0

Each campaign is simulated once and every variant fits the same processed record; ``--cache DIR``
keeps the processed records (pickles, one per truth and seed) for a second run.
"""

from __future__ import annotations

import argparse
import contextlib
import pickle
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
from numba import njit
from scipy import signal

from controller.identification_loop import DAMPING_ONLY_TRUTH, law1_campaign, simulate_campaign
from controller.trajectory import recorded_excitation
from twin.identification import loadfriction, uncertainty
from twin.identification.pipeline import identify_friction, identify_variable, preprocess
from twin.identification.record import campaign_data_from_mcap
from twin.model.params import load_params
from twin.sim.truth import EFFECTS, load_truth


def _elastic_creep_tension(p, x, xd, tau_s, h):
    """The creep as shipped until 2026-11-26: a first-order low-pass (τ) of the elastic tension of
    the whole stretch, k·x/(1 − λx), at equilibrium at the first sample."""
    k, lam, c_a, beta, floor = p[0], p[1], p[2], p[5], loadfriction.MIN_STRETCH_FACTOR
    elastic = k * x / np.maximum(1 - lam * x, floor)
    a = np.exp(-h / tau_s)
    xx = x - beta * (signal.lfilter([1 - a], [1, -a], elastic - elastic[0]) + elastic[0]) / k
    return np.maximum((k * xx + c_a * xd) / np.maximum(1 - lam * xx, floor), 0.0)


@njit(cache=True)
def _full_drive(k, lam, c_a, beta, x, xd, gain, floor):
    """As the shipped recursion, the creep driven by the whole tension it leaves, damping
    included, as the robot truth's element (twin/sim/integrator.py ``creep_update``)."""
    n = x.shape[0]
    out = np.empty(n)
    c = 0.0
    for _ in range(50):
        xx = x[0] - c
        c = beta * max((k * xx + c_a * xd[0]) / max(1.0 - lam * xx, floor), 0.0) / k
    for i in range(n):
        xx = x[i] - c
        t = max((k * xx + c_a * xd[i]) / max(1.0 - lam * xx, floor), 0.0)
        out[i] = t
        c += (beta * t / k - c) * gain
    return out


def _full_drive_tension(p, x, xd, tau_s, h):
    return _full_drive(p[0], p[1], p[2], p[5], np.ascontiguousarray(x, dtype=float),
                          np.ascontiguousarray(xd, dtype=float), 1.0 - np.exp(-h / tau_s), loadfriction.MIN_STRETCH_FACTOR)


def _cluster_covariance(block_s: float, rate_hz: float) -> Callable:
    def cov(B, residual, sample_index, n_samples, lag=None, min_lag=1):
        scores = uncertainty.instant_sums((B * residual).T, sample_index, n_samples)
        size = max(int(round(block_s * rate_hz)), 1)
        sums = np.array([scores[i:i + size].sum(axis=0) for i in range(0, n_samples, size)])
        sums = sums[np.any(sums != 0, axis=1)]
        g = len(sums)
        return g / max(g - 1, 1) * sums.T @ sums, size

    return cov


def _fixed_lag(lag: int) -> Callable:
    hac = uncertainty.hac_covariance

    def cov(B, residual, sample_index, n_samples, lag_=None, min_lag=1):
        return hac(B, residual, sample_index, n_samples, lag=min(lag, int(0.2 * n_samples)))

    return cov


@contextlib.contextmanager
def _patched(obj, name: str, value) -> Iterator[None]:
    """``obj.name`` replaced by ``value`` while in the block. A variant of the load-friction fit's
    residual or tension also gets the Jacobian by finite differences of it: the fit's exact one
    (loadfriction._jacobian) is the shipped model's derivative only."""
    swaps = [(name, value)]
    if obj is loadfriction and name in ("_residual", "_tension"):
        swaps.append(("_jacobian", loadfriction._fd_jacobian))
    olds = [(n, getattr(obj, n)) for n, _ in swaps]
    for n, v in swaps:
        setattr(obj, n, v)
    try:
        yield
    finally:
        for n, v in olds:
            setattr(obj, n, v)


@contextlib.contextmanager
def _offset_free() -> Iterator[None]:
    """``offset-free``: F_a appended to every cable's parameters (bounds, scale, start, residual)."""
    cables_of, least_squares_of = loadfriction._cables, loadfriction._least_squares

    def cables(*args, **kw):
        out = cables_of(*args, **kw)
        for c in out:
            c.lo, c.hi, c.scale = np.append(c.lo, -10.0), np.append(c.hi, 10.0), np.append(c.scale, 1.0)
        return out

    def residual(p, x, xd, theta_dot, y, rows, tau_s, h, g_f=0.0, g_b=0.0):
        a = loadfriction._shape(p[6], theta_dot[rows])
        t = loadfriction._tension(p, x, xd, tau_s, h)[rows]
        return (((1 + a * p[3]) * t + a * p[4] + np.abs(a) * p[7] - g_b * np.maximum(-a, 0.0) * t)
                / (1 - g_f * np.maximum(a, 0.0)) - y[rows])

    def least_squares(c, starts, taus_s, free=None):
        return least_squares_of(c, [np.append(p0, 0.0) for p0 in starts], taus_s, free)

    with (_patched(loadfriction, "SYMBOLS", (*loadfriction.SYMBOLS, "F_a")), _patched(loadfriction, "_cables", cables),
          _patched(loadfriction, "_residual", residual), _patched(loadfriction, "_least_squares", least_squares)):
        yield


@contextlib.contextmanager
def _filtered_shape() -> Iterator[None]:
    """``filtered-shape``: the friction shape of every cable's rows from a table over c_f of
    eq. 37 at 500 Hz, filtered and decimated as the force (tables keyed by the cable's θ̇ array)."""
    from twin.identification.processing import DECIMATION, _butter

    grid = np.geomspace(loadfriction.C_F_BOUNDS[0], loadfriction.C_F_BOUNDS[1], 41)
    tables: dict[int, np.ndarray] = {}
    cables_of = loadfriction._cables

    def cables(proc, params, *args, **kw):
        out = cables_of(proc, params, *args, **kw)
        rate = 1.0 / float(np.median(np.diff(proc.fast_t_s)))
        at = np.searchsorted(proc.fast_t_s[::DECIMATION], proc.t_s - 1e-9)
        table = np.stack([signal.decimate(_butter(loadfriction._shape(cf, proc.fast_theta_dot), proc.cutoff_hz, rate),
                                          DECIMATION, ftype="fir", axis=0, zero_phase=True)[at] for cf in grid])
        for j, c in enumerate(out):
            tables[id(c.theta_dot)] = table[:, :, j]
        return out

    def residual(p, x, xd, theta_dot, y, rows, tau_s, h, g_f=0.0, g_b=0.0):
        u, lg = np.log(np.clip(p[6], grid[0], grid[-1])), np.log(grid)
        i = int(np.clip(np.searchsorted(lg, u) - 1, 0, len(grid) - 2))
        w = (u - lg[i]) / (lg[i + 1] - lg[i])
        a = (1 - w) * tables[id(theta_dot)][i, rows] + w * tables[id(theta_dot)][i + 1, rows]
        t = loadfriction._tension(p, x, xd, tau_s, h)[rows]
        return ((1 + a * p[3]) * t + a * p[4] - g_b * np.maximum(-a, 0.0) * t) / (1 - g_f * np.maximum(a, 0.0)) - y[rows]

    with _patched(loadfriction, "_cables", cables), _patched(loadfriction, "_residual", residual):
        yield


def _variant(name: str, rate_hz: float) -> contextlib.AbstractContextManager:
    if "+" in name:  # several variants at once, e.g. elastic-creep+tau-2s
        stack = contextlib.ExitStack()
        for part in name.split("+"):
            stack.enter_context(_variant(part, rate_hz))
        return stack
    if name == "shipped":
        return contextlib.nullcontext()
    if name == "full-drive":
        return _patched(loadfriction, "_tension", _full_drive_tension)
    if name == "elastic-creep":
        return _patched(loadfriction, "_tension", _elastic_creep_tension)
    if name.startswith("cluster-"):
        return _patched(uncertainty, "hac_covariance", _cluster_covariance(float(name[8:-1]), rate_hz))
    if name.startswith("bartlett-"):
        return _patched(uncertainty, "hac_covariance", _fixed_lag(int(name[9:])))
    if name.startswith("min-force-"):
        return _patched(loadfriction, "MIN_FORCE_N", float(name[10:]))
    if name.startswith("force-offset-"):
        rows_of, offset = loadfriction.fit_rows, float(name[13:])

        def shifted(proc, params):
            y, rows = rows_of(proc, params)
            return y - offset, rows

        return _patched(loadfriction, "fit_rows", shifted)
    if name == "gear-undivided":  # the gear's loss on the slopes only, the friction offset ±F₀ left undivided
        def undivided(p, x, xd, theta_dot, y, rows, tau_s, h, g_f=0.0, g_b=0.0):
            mu, f0, a = p[3], p[4], loadfriction._shape(p[6], theta_dot[rows])
            t = loadfriction._tension(p, x, xd, tau_s, h)[rows]
            return ((1 + a * mu) * t - g_b * np.maximum(-a, 0.0) * t) / (1 - g_f * np.maximum(a, 0.0)) + a * f0 - y[rows]

        return _patched(loadfriction, "_residual", undivided)
    if name.startswith("gear-"):  # gear-F-B: the gear's meshing losses held at F (winding) and B (back-driven)
        g_f, g_b = (float(v) for v in name[5:].split("-", 1))
        return _patched(loadfriction, "gear_losses", lambda _params: (g_f, g_b))
    if name.startswith("reversal-guard-"):  # rows within S s of a reversal of their motor dropped
        rows_of, guard_s = loadfriction.fit_rows, float(name[15:-1])

        def guarded(proc, params):
            y, rows = rows_of(proc, params)
            w = int(round(guard_s * proc.rate_hz))
            flips = np.zeros(rows.shape, dtype=bool)
            flips[1:] = np.sign(proc.theta_dot[1:]) != np.sign(proc.theta_dot[:-1])
            near = np.stack([np.convolve(flips[:, j], np.ones(2 * w + 1), mode="same") > 0
                             for j in range(rows.shape[1])], axis=1)
            return y, rows & ~near

        return _patched(loadfriction, "fit_rows", guarded)
    if name == "offset-free":
        return _offset_free()
    if name == "filtered-shape":
        return _filtered_shape()
    if name == "residual-tau":
        return _patched(loadfriction, "TAU_CHOICE", "residual")
    if name == "shared-tau":
        refine = loadfriction.refine_tau

        def shared(grid_s, costs):
            return np.full(costs.shape[1], refine(grid_s, np.log(costs).sum(axis=1, keepdims=True))[0])

        return _patched(loadfriction, "refine_tau", shared)
    if name.startswith("beta-"):
        fit, ratio = loadfriction.fit_load_friction, float(name[5:])
        return _patched(loadfriction, "fit_load_friction", lambda *a, **kw: fit(*a, **kw, creep_ratio=ratio))
    if name.startswith("tau-"):
        tau = float(name[4:-1])  # as `xneck identify --creep-time-s`
        return _patched(loadfriction, "creep_taus", lambda _given: loadfriction.TAUS_S[:0] + (tau,))
    raise SystemExit(f"unknown variant {name!r}; known: {', '.join(VARIANTS)}")


VARIANTS = ("shipped", "residual-tau", "elastic-creep", "full-drive", "cluster-5s", "cluster-10s", "cluster-20s", "bartlett-150",
            "bartlett-300", "min-force-12", "tau-2s", "force-offset-1.5",
            "shared-tau", "beta-0.05", "tau-2s+beta-0.05", "gear-0-0", "gear-0.04-0.045", "gear-0.12-0.135", "gear-undivided",
            "reversal-guard-0.2s", "reversal-guard-0.4s", "filtered-shape", "offset-free")


def _truth_changes(items: list[str] | None) -> dict[str, dict[str, object]]:
    """``EFFECT.KEY=VALUE`` (a number, or comma-separated numbers for a per-cable value) by section."""
    out: dict[str, dict[str, object]] = {}
    for item in items or []:
        path, _, value = item.partition("=")
        section, _, key = path.partition(".")
        if not (section and key and value):
            raise SystemExit(f"--truth-set {item!r}: write EFFECT.KEY=VALUE, e.g. friction.gear_loss_forward=0")
        numbers = tuple(float(v) for v in value.split(","))
        out.setdefault(section, {})[key] = numbers if "," in value else numbers[0]
    return out


def _processed(truth_name: str, seed: int, params, cache: Path | None, only: list[str] | None = None,
               campaign: str = "loop", truth_set: list[str] | None = None):
    tag = (Path(truth_name).stem + ("" if not only else "-only-" + "-".join(only))
           + ("" if campaign == "loop" else f"-{campaign}")
           + "".join(f"-{x.replace('=', '_').replace(',', '_')}" for x in truth_set or []))
    path = None if cache is None else cache / f"{tag}-{seed}.pkl"
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    truth = DAMPING_ONLY_TRUTH if truth_name == "pipeline" else load_truth(truth_name)
    if only:
        truth = truth.only(*only)
    for section, values in _truth_changes(truth_set).items():
        truth = truth.replace(section, **values)
    data = (law1_campaign(seed, truth, params) if campaign == "law1"
            else simulate_campaign(seed, truth=truth, params=params)[0])
    proc = preprocess(data, params)
    out = (proc, identify_friction(proc, params).values)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(out))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--truth", default="robot", help="robot (default), pipeline (damping only), or a truth file")
    ap.add_argument("--first", type=int, default=21, help="first campaign seed (default 21)")
    ap.add_argument("--seeds", type=int, default=20, help="how many seeds (default 20)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), metavar="NAME", help=f"of {', '.join(VARIANTS)}")
    ap.add_argument("--only", nargs="+", metavar="EFFECT", help=f"the truth with only these effects on "
                    f"({', '.join(EFFECTS)})")
    ap.add_argument("--archive", nargs="+", type=Path, metavar="MCAP", help="recorded campaigns instead of simulated "
                    "ones, processed as `xneck identify` does")
    ap.add_argument("--cache", type=Path, help="directory keeping the processed campaigns between runs")
    ap.add_argument("--truth-set", nargs="+", metavar="EFFECT.KEY=VALUE", help="change values of the truth, e.g. "
                    "friction.gear_loss_forward=0 friction.asymmetry=0,0,0,0 (twin/sim/robot_truth.toml's keys)")
    ap.add_argument("--campaign", choices=("loop", "law1"), default="loop", help="loop (default): the known-answer "
                    "loop (controller/identification_loop.py); law1: law 1's campaign, what `xneck campaign "
                    "identification` runs (as docs/identification/law1_coverage.py)")
    a = ap.parse_args()
    if a.seeds < 1:
        ap.error("--seeds must be at least 1")
    for name in a.variants:
        _variant(name, 1.0)  # unknown names fail before any campaign runs
    try:
        truth = DAMPING_ONLY_TRUTH if a.truth == "pipeline" else load_truth(a.truth)
        for section, values in _truth_changes(a.truth_set).items():
            truth.replace(section, **values)  # a bad key or value fails before any campaign runs
    except (TypeError, ValueError) as exc:
        raise SystemExit(f"--truth-set: {exc}") from None
    params = load_params()
    k_true, lam_true = np.asarray(params.cables.variable.k), np.asarray(params.cables.variable.lam)
    truth_v = np.r_[k_true, lam_true]
    seeds = range(a.first, a.first + a.seeds)
    runs = a.archive or list(seeds)
    err = {v: [] for v in a.variants}
    cov = {v: [] for v in a.variants}
    for seed in runs:
        if isinstance(seed, Path):
            proc = preprocess(campaign_data_from_mcap(seed, recorded_excitation), params)
            friction = identify_friction(proc, params).values
        else:
            proc, friction = _processed(a.truth, seed, params, a.cache, a.only, a.campaign, a.truth_set)
        for name in a.variants:
            with _variant(name, proc.rate_hz):
                est = identify_variable(proc, params, friction, estimator="loadfriction")
            names = list(est.names)
            idx = [names.index(f"{s}({j + 1})") for s in ("k", "lambda") for j in range(len(k_true))]
            v, sd = est.values[idx], est.sigma[idx]
            err[name].append(100 * (v / truth_v - 1))
            cov[name].append(np.abs(v - truth_v) <= 2 * sd)
            print(f"{seed if isinstance(seed, Path) else f'seed {seed}'} {name}: error (%) " + ", ".join(f"{e:+.1f}" for e in err[name][-1]), file=sys.stderr,
                  flush=True)
    labels = [f"{s}({j + 1})" for s in ("k", "λ") for j in range(len(k_true))]
    what = (", ".join(p.name for p in a.archive) if a.archive
            else f"truth `{a.truth}`{' with only ' + ', '.join(a.only) if a.only else ''}"
                 f"{' with ' + ' '.join(a.truth_set) if a.truth_set else ''}, "
                 f"{'law 1' if a.campaign == 'law1' else 'loop'} campaign seeds {seeds[0]}-{seeds[-1]}")
    print(f"{what}, `loadfriction` and its variants; per parameter: mean error (%) / covered by ±2σ (of the "
          f"{len(runs)} campaigns)\n")
    print("| variant | " + " | ".join(labels) + " | covered | within 10 % |")
    print("|---|" + "---|" * (len(labels) + 2))
    for name in a.variants:
        e, c = np.asarray(err[name]), np.asarray(cov[name])
        cells = [f"{m:+.1f} / {n}" for m, n in zip(e.mean(axis=0), c.sum(axis=0), strict=True)]
        print(f"| `{name}` | " + " | ".join(cells) + f" | {int(c.sum())}/{c.size} | {int(np.sum(np.abs(e) < 10))}/{e.size} |")


if __name__ == "__main__":
    main()
