"""One run of a study: a pure, picklable function of (:class:`RunConfig`, :class:`RunSpec`) → a row.

- control: the §7 campaign in process and lockstep (controller.offline.run_closed_loop, the loop
  ``xneck campaign control --twin`` runs over the bus), the twin on the sampled parameters, the
  controller on the nominal ones (unless ``model_follows``); metrics as the campaign results report
  them (controller.metrics: e, e_α, forces, saturation).
- identification: the §5.2.2 campaign the same way, written as MCAP and identified by
  :func:`twin.identification.record.identify_record` (what ``xneck identify`` runs); metrics: the
  identified values' relative error against the twin's and their relative σ (eq. 50).
- design: the N-joint neck's wrench-feasible workspace and stiffness (twin.analysis.statics) on
  random configurations within the joint limit.

Workers never read files: the base parameter set and truth travel as data in the config.
Errors of a sampled robot (an invalid parameter set, an unstable run) become the row's
``outcome`` and ``message``: only a dead worker makes Dask run a task again.
"""

from __future__ import annotations

import copy
import math
import tempfile
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from bridge import toml_text
from server.studies.spec import RunSpec, Study, StudyError, Vary

ROUTE_SHORT, ROUTE_LONG = "b", "a"  # cases of eqs. 3-6 where a short cable ends / the long one ends (prototype routing)
TENSION_FROM_S = 0.2  # s: tension_min_N leaves out the first ticks, before the controller has tensioned the cables
N_JOINTS = "geometry.n_joints"
N_JOINTS_RANGE = (1, 12)  # the necks with_joints builds
_N_JOINTS_HOW = f"vary it by a grid of whole numbers within {N_JOINTS_RANGE[0]} to {N_JOINTS_RANGE[1]} joints, e.g. {N_JOINTS}=2:5:4"


@dataclass(frozen=True)
class RunConfig:
    """Everything a worker needs, as plain data (picklable, no file paths)."""

    study: Study
    params: dict[str, Any]  # the base parameter file with --set applied, Params.to_dict()
    truth: str | dict[str, Any]  # "model" or the truth file's TOML document
    trajectory_json: str  # control/identification
    version: str


# --- parameter paths ------------------------------------------------------------------------------


def _node(doc: dict[str, Any], path: str, where: str) -> tuple[dict[str, Any], str]:
    from twin.model.params import dotted_parent

    try:
        return dotted_parent(doc, path)
    except ValueError as exc:
        raise StudyError(f"{where}: {exc}") from None


def _set(doc: dict[str, Any], v: Vary, value: float, where: str, wrapped: bool) -> None:
    node, key = _node(doc, v.path, where)
    holder, slot = (node[key], "value") if wrapped and isinstance(node[key], dict) else (node, key)
    current = holder[slot]
    values = list(current) if isinstance(current, list | tuple) else None
    if values is None and v.index is not None:
        raise StudyError(f"{where}: {v.path} is a single value, it has no element [{v.index}]")
    if values is not None and v.index is not None and v.index > len(values):
        raise StudyError(f"{where}: {v.path} has {len(values)} elements, no [{v.index}]")
    items = values if values is not None else [current]
    if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in items):
        raise StudyError(f"{where}: {v.path} is not numeric ({current!r})")

    def new(old: Any) -> float | int:
        x = old * value if v.kind == "relative" else value
        return int(round(x)) if isinstance(old, int) and not isinstance(old, bool) else float(x)

    if values is None:
        holder[slot] = new(current)
    else:
        holder[slot] = [new(x) if v.index in (None, i + 1) else x for i, x in enumerate(values)]


def with_joints(doc: dict[str, Any], n: int) -> dict[str, Any]:
    """The parameter document for an ``n``-joint neck of the same design: per-joint values of the
    last joint repeated (or cut), one short cable per joint and one long cable (the prototype's
    routing: short cable i runs along 1d…(i−1)d ib, the long one 1c…(n−1)c na), per-cable values
    of the prototype's short cables repeated and its long cable's kept."""
    lo, hi = N_JOINTS_RANGE
    if not lo <= n <= hi:
        raise StudyError(f"{N_JOINTS} = {n}: choose {lo} to {hi} joints")
    out = copy.deepcopy(doc)
    out["geometry"]["n_joints"] = n

    def per_joint(values: list[Any]) -> list[Any]:
        return [values[min(i, len(values) - 1)] for i in range(n)]

    for section in ("springs", "bars"):
        out[section] = {k: per_joint(list(v)) if isinstance(v, list | tuple) else v for k, v in out[section].items()}
    routes = [" ".join([f"{j}d" for j in range(1, i)] + [f"{i}{ROUTE_SHORT}"]) for i in range(1, n + 1)]
    routes.append(" ".join([f"{j}c" for j in range(1, n)] + [f"{n}{ROUTE_LONG}"]))
    old_routes = out["cables"]["routing"]
    long_old = next((j for j, r in enumerate(old_routes) if r.split()[-1].endswith(ROUTE_LONG)), len(old_routes) - 1)
    short_old = [j for j in range(len(old_routes)) if j != long_old] or [long_old]

    def per_cable(values: list[Any]) -> list[Any]:
        values = list(values)
        shorts = [values[short_old[min(i, len(short_old) - 1)]] for i in range(n)]
        return shorts + [values[long_old]]

    out["cables"]["routing"] = routes
    out["friction"]["f_s"] = per_cable(out["friction"]["f_s"])
    for model, keys in (("linear", ("k", "c_a")), ("variable", ("k", "lambda", "c_a"))):
        for key in keys:
            out["cables"][model][key] = per_cable(out["cables"][model][key])
    return out


def apply_values(cfg: RunConfig, values: dict[str, float]) -> tuple[Any, Any]:
    """(Params, truth) of a run: the base ones with the run's values; StudyError/ParameterError/
    TruthError name what does not hold."""
    from twin.model.params import params_from_dict
    from twin.sim.truth import parse_truth

    doc = copy.deepcopy(cfg.params)
    truth_doc = copy.deepcopy(cfg.truth) if isinstance(cfg.truth, dict) else None
    varies = {v.label: v for v in cfg.study.varies()}
    for label in sorted(values, key=lambda k: k != N_JOINTS):  # resize first, then vary the joints
        v, value = varies[label], values[label]
        where = f"--vary {v.text}"
        if v.path == N_JOINTS:
            if not float(value).is_integer():  # never rounded: the row's x must be the neck that ran
                raise StudyError(f"{where}: {value:g} is not a whole number of joints; {_N_JOINTS_HOW}")
            doc = with_joints(doc, int(value))
        elif v.path.startswith("truth."):
            if truth_doc is None:
                raise StudyError(f"{where}: truth paths need --truth robot or a truth file (the model truth has no values)")
            _set(truth_doc, Vary(v.path[6:], v.index, v.kind, v.a, v.b, v.n), value, where, wrapped=True)
        else:
            _set(doc, v, value, where, wrapped=False)
    params = params_from_dict(doc, "study")
    truth = parse_truth(truth_doc, str(truth_doc.get("name", "truth"))) if truth_doc is not None else "model"
    return params, truth


def check_study(cfg: RunConfig) -> None:
    """Every varied path exists, is numeric and gives a valid robot at its extreme values, before anything runs."""
    from twin.model.params import ParameterError
    from twin.sim.truth import TruthError

    for v in cfg.study.varies():
        if v.path == N_JOINTS:
            check_n_joints(v)
        for x in v.extremes():
            try:
                apply_values(cfg, {v.label: x})
            except (ParameterError, TruthError) as exc:
                raise StudyError(f"--vary {v.text}: at {x:g}{' (factor)' if v.kind == 'relative' else ''}: {exc}") from None


def check_n_joints(v: Vary) -> None:
    """The number of joints takes whole values from a grid only, each a neck :func:`with_joints`
    builds: a spread's factor (0.9-1.1) or a draw is no number of joints, and a grid point such as
    2.5 would be rounded to another neck than the one its row names."""
    lo, hi = N_JOINTS_RANGE
    where = f"--vary {v.text}"
    if v.kind != "grid":
        what = {"relative": "a relative spread", "normal": "a normal draw", "uniform": "a uniform draw"}[v.kind]
        raise StudyError(f"{where}: {what} gives no whole number of joints; {_N_JOINTS_HOW}")
    points = v.grid().tolist()
    fractional = [x for x in points if not float(x).is_integer()]
    if fractional:
        shown = ", ".join(f"{x:g}" for x in fractional[:5]) + (", ..." if len(fractional) > 5 else "")
        raise StudyError(f"{where}: the grid's points {shown} are not whole numbers of joints; {_N_JOINTS_HOW}")
    outside = [int(x) for x in points if not lo <= x <= hi]
    if outside:
        raise StudyError(f"{where}: {outside[0]} joints is outside the necks a study builds; {_N_JOINTS_HOW}")


# --- one run --------------------------------------------------------------------------------------


@lru_cache(maxsize=4)
def _trajectory(text: str) -> Any:
    from controller.trajectory import trajectory_from_json

    return trajectory_from_json(text)


def run_one(cfg: RunConfig, run: RunSpec) -> dict[str, Any]:
    """The row of one run: id, law, seed, ``x:<path>`` inputs, metrics, outcome, message, timing, version."""
    from twin.identification.pipeline import IdentificationError
    from twin.model.params import ParameterError
    from twin.sim.truth import TruthError

    t0 = time.perf_counter()
    row: dict[str, Any] = {"run_id": run.run_id, "law": run.law, "seed": run.seed}
    row.update({f"x:{k}": float(v) for k, v in run.values.items()})
    try:
        params, truth = apply_values(cfg, run.values)
        kind = cfg.study.kind
        metrics = (_control(cfg, run, params, truth) if kind == "control" else
                   _identification(cfg, run, params, truth) if kind == "identification" else _design(cfg, run, params))
        unfinite = non_finite(metrics)
        row.update(metrics)
        flat = int(metrics.get("flat_steps", 0) or 0)
        row["outcome"], row["message"] = (
            ("diverged", f"non-finite metrics: {', '.join(unfinite[:5])}{', ...' if len(unfinite) > 5 else ''}")
            if unfinite else
            # the twin stood still at a joint's flat singularity: its metrics are not the robot's
            ("diverged", f"the twin refused {flat} step(s) at a joint's flat singularity (α = ±180°)") if flat else
            ("finished", ""))
    except (ParameterError, TruthError, StudyError) as exc:
        row["outcome"], row["message"] = "invalid", str(exc)
    except (IdentificationError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        # ArithmeticError: FloatingPointError, and a ZeroDivisionError or OverflowError of a robot with
        # absurd values (geometry.R = 6e299 divided by zero in the dynamics: a traceback ended the study)
        row["outcome"], row["message"] = "failed", f"{type(exc).__name__}: {exc}"
    row["run_s"] = time.perf_counter() - t0
    row["version"] = cfg.version
    return row


def non_finite(metrics: dict[str, Any]) -> list[str]:
    """Names of the metrics that are NaN or ±inf: Python and numpy numbers alike (a numpy float32
    is no ``float``). None is an undefined metric (identification_metrics), not a non-finite one."""
    return [k for k, v in metrics.items()
            if isinstance(v, float | np.floating) and not math.isfinite(float(v))]


def _flat(metrics: dict[str, object]) -> dict[str, Any]:
    """Scalars as they are, per-joint/per-cable lists as ``name[i]`` columns (from 1), None as NaN."""
    out: dict[str, Any] = {}
    for k, v in metrics.items():
        if isinstance(v, list):
            out.update({f"{k}[{i + 1}]": float(x) for i, x in enumerate(v)})
        elif v is None:
            out[k] = math.nan
        elif isinstance(v, bool):
            out[k] = v
        else:
            out[k] = float(v) if isinstance(v, float) else v
    return out


def _closed_loop(cfg: RunConfig, run: RunSpec, params: Any, truth: Any, law: int, trajectory: Any) -> Any:
    from controller.laws import LawConfig
    from controller.offline import run_closed_loop
    from twin.model.params import params_from_dict
    from twin.sim.simulator import TwinConfig

    s = cfg.study
    model = params if s.model_follows else params_from_dict(cfg.params, "study")
    twin_config = TwinConfig(seed=run.seed % 2**32, truth=truth, alpha_ip=s.alpha_ip)  # type: ignore[arg-type]
    return run_closed_loop(params, LawConfig(law=law, no_pulleys=s.no_pulleys), trajectory, twin_config,
                           settle_s=s.settle_s, model=model)


def _control(cfg: RunConfig, run: RunSpec, params: Any, truth: Any) -> dict[str, Any]:
    res = _closed_loop(cfg, run, params, truth, run.law, _trajectory(cfg.trajectory_json))
    m = res.metrics()
    out = _flat(m)
    out["e_max_all_deg"] = float(np.max(m["e_max_deg"]))  # type: ignore[arg-type]
    out["force_max_all_N"] = float(np.max(m["force_max_N"]))  # type: ignore[arg-type]
    settled = res.t_s >= TENSION_FROM_S  # from rest the cables start slack: the pretension is the controller's first act
    out["tension_min_N"] = float(np.min(res.tension_N[settled] if settled.any() else res.tension_N))
    out["flat_steps"] = res.flat_steps
    return out


def _identification(cfg: RunConfig, run: RunSpec, params: Any, truth: Any) -> dict[str, Any]:
    from bridge.archive import write_campaign
    from controller.trajectory import recorded_excitation
    from twin.identification.record import identify_record
    from twin.model.params import params_from_dict

    traj = _trajectory(cfg.trajectory_json)
    res = _closed_loop(cfg, run, params, truth, 1, traj)
    if res.flat_steps:
        return {"flat_steps": res.flat_steps}  # nothing to identify on a twin that stood still
    base = params_from_dict(cfg.params, "study")
    with tempfile.TemporaryDirectory(prefix="xneck-study-") as tmp:
        path = write_campaign(Path(tmp) / f"{run.run_id}.mcap", res.messages(),
                              {"campaign_id": run.run_id, "kind": "identification", "trajectory": traj.to_json()})
        est = identify_record(path, base, excitation=recorded_excitation, with_validation=False,
                              estimator=cfg.study.estimator).estimate
    return identification_metrics(est, params)


def _defined(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def identification_metrics(est: dict[str, Any], params: Any) -> dict[str, Any]:
    """An identification run's row metrics: the identified f_s, k, λ against the twin's
    (``params``), their relative σ, and whether the ±2σ interval the report gives covers the twin's
    value. Undefined values are None (Parquet null, left out of the summary), not NaN, which would
    make the run ``diverged``: a relative error where the twin's value is 0 (λ of a linear cable,
    a friction-free motor), a relative σ where the estimate is 0 (held at its bound), and the
    maxima and fractions over them."""
    truths = {"f_s": ("friction", np.asarray(params.friction.f_s)), "k": ("variable", np.asarray(params.cables.variable.k)),
              "lambda": ("variable", np.asarray(params.cables.variable.lam))}
    out: dict[str, Any] = {}
    for name, (model, true) in truths.items():
        e = est[model]
        idx = [i for i, n in enumerate(e.names) if n.split("(")[0] == name]
        values, sigma, rsig = (np.asarray(a, dtype=float)[idx] for a in (e.values, e.sigma, e.relative_sigma))
        if len(values) != len(true):  # not the twin's cables: nothing to compare, a non-finite row
            out[f"{name}_rel_error_max"] = math.nan
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            err = [_defined(x) for x in np.abs(values - true) / np.abs(true)]
        rs = [_defined(x) for x in rsig]
        known = [x for x in err if x is not None]
        out[f"{name}_rel_error_max"] = max(known) if known else None
        defined = [x for x in rs if x is not None]
        # an undefined one may be the largest: no maximum then
        out[f"{name}_rel_sigma_max"] = max(defined) if len(defined) == len(rs) and defined else None
        out.update({f"{name}_rel_error[{i + 1}]": x for i, x in enumerate(err)})
        # covered: the truth within the ±2σ the report gives (value ± 2σ), issue 17's coverage test
        covered = np.abs(values - true) <= 2.0 * sigma
        out.update({f"{name}_covered[{i + 1}]": float(c) for i, c in enumerate(covered)})
        out[f"{name}_covered_fraction"] = float(np.mean(covered))
        out[f"{name}_within_10pct_fraction"] = float(np.mean([x <= 0.10 for x in known])) if known else None
    return out


def _design(cfg: RunConfig, run: RunSpec, params: Any) -> dict[str, Any]:
    """Workspace and stiffness of the sampled design on random configurations within |α_i| <= alpha_max_deg:
    ``feasible_fraction`` (Z f = g with f_min <= f <= f_max, eq. 63-65), ``stable_fraction`` (feasible and the
    joint stiffness at the lowest admissible tension positive definite), ``k_min_median_N_m_per_rad`` (the
    least eigenvalue of that stiffness, median over feasible configurations) and ``k_max_median_N_m_per_rad``
    (the greatest, at the highest tension), and the straight neck's feasibility and least stiffness."""
    from twin.analysis.statics import statics_3x, stiffness_3x
    from twin.model.numeric import build

    m = build(params)
    n, lim = params.n_joints, params.limits
    a_max = math.radians(lim.alpha_max_deg)
    rng = np.random.default_rng(run.seed)
    A = np.vstack([np.zeros((1, n)), rng.uniform(-a_max, a_max, (cfg.study.design_configurations, n))])
    st = statics_3x(m, A, lim.f_min, lim.f_max)
    feas = st.feasible
    out: dict[str, Any] = {"n_joints": float(n), "b_over_L": params.geometry.b / params.geometry.L,
                           "feasible_fraction": float(feas[1:].mean()), "straight_feasible": float(feas[0])}
    k_lo = np.full(len(A), np.nan)
    k_hi = np.full(len(A), np.nan)
    if feas.any():
        Af = A[feas]
        f_lo = st.f_p[feas] + st.n[feas] * st.t_lo[feas][:, None]
        f_hi = st.f_p[feas] + st.n[feas] * st.t_hi[feas][:, None]
        k_lo[feas] = np.linalg.eigvalsh(stiffness_3x(m, Af, f_lo))[:, 0]
        k_hi[feas] = np.linalg.eigvalsh(stiffness_3x(m, Af, f_hi))[:, -1]
    stable = feas & (k_lo > 0)
    out["stable_fraction"] = float(stable[1:].mean())
    with np.errstate(all="ignore"):
        out["k_min_median_N_m_per_rad"] = float(np.nanmedian(k_lo[1:])) if feas[1:].any() else math.nan
        out["k_max_median_N_m_per_rad"] = float(np.nanmedian(k_hi[1:])) if feas[1:].any() else math.nan
    out["straight_k_min_N_m_per_rad"] = float(k_lo[0])
    return out


def config_for(study: Study, version: str) -> RunConfig:
    """The run config of a study, loaded on the client (files read here, never on workers), and checked."""
    from controller.trajectory import (
        NAMED_TRAJECTORIES,
        TrajectoryError,
        identification_trajectory,
        load_trajectory,
        trajectory_by_name,
    )
    from twin.model.params import ParameterError, load_params, parse_override
    from twin.sim.truth import ROBOT_TRUTH_FILE, TRUTHS, TruthError, load_truth

    try:
        params = load_params(study.params_file, dict(parse_override(o) for o in study.set))
    except ParameterError as exc:  # a --set value's own fault is said as such, not as the parameter file's
        raise StudyError(str(exc) if str(exc).startswith("--set ") else f"parameter file: {exc}") from None
    try:
        load_truth(study.truth)
    except TruthError as exc:
        raise StudyError(f"--truth {study.truth!r}: {exc} (choose {' or '.join(TRUTHS)} or a truth file)") from None
    truth: str | dict[str, Any] = "model"
    if study.truth != "model":
        truth = toml_text.loads((ROBOT_TRUTH_FILE if study.truth == "robot" else Path(study.truth)).read_text())
    traj_json = ""
    if study.kind != "design":
        name = study.trajectory
        try:
            if study.kind == "identification" and name == "identification":
                traj = identification_trajectory()
            elif name.replace("-", "_") in NAMED_TRAJECTORIES:
                traj = trajectory_by_name(name)
            else:
                traj = load_trajectory(Path(name))
        except (TrajectoryError, OSError) as exc:
            raise StudyError(f"--trajectory {name!r}: {exc}") from None
        if traj.n_joints != params.n_joints:
            raise StudyError(f"--trajectory {name!r} moves {traj.n_joints} joints, the parameter set has {params.n_joints}")
        traj_json = traj.to_json()
    cfg = RunConfig(study, params.to_dict(), truth, traj_json, version)
    check_study(cfg)
    return cfg
