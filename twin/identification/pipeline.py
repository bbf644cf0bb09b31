"""Identification of friction and cable stiffness (3-X paper §5), as pure functions on arrays.

Pipeline (every function takes and returns arrays in SI units; θ at the motor shaft in rad)::

    data = CampaignData(t_s, theta_rad, force_N, t_ip_s, alpha_ip_rad)   # checked on creation
    proc = preprocess(data, params)                  # §5.2.1: filter, differentiate, decimate
    fric = identify_friction(proc, params)           # eqs. 38 (rigid cables) -> f_s
    comp = identify_complete(proc, params)           # eqs. 43-45, W = 100 -> k, c_a, f_s
    var = identify_variable(proc, params, fric.values)   # eqs. 54-57 -> k, λ, c_a (friction-alone f_s)
    est = {"friction": fric, "complete": comp, "variable": var}   # or identify_all(proc, params)
    new_params, report, prov = identified_params(params, est, provenance)   # prov: + kept_base
    val = validate(data, proc, new_params, est)   # eqs. 51-53, 42, 33, 35 (Figs. 4-8)

twin.identification.record.identify_record runs it on an MCAP archive (xneck identify, the console).

Modules follow the pipeline: processing (CampaignData, preprocess), regressors (W and Y of each
model), estimators (Estimate, least squares), report (Tables 1-2, Figs. 4-8), record (MCAP);
this module composes them (identify_*, identified_params, validate) and re-exports their names.

Signs. We use the physical stretch x_c = l_c − l_c0 + (r_d/R)·θ (docs/model.md), so in our
sign eq. 32 reads M·α̈ + c + g = Z(f − f_friction − I_a(R/r_d)²·ẍ_c) and the joint rows of
eqs. 38/44 become  Z·diag(a)·f_s = Z(f − I_a(R/r_d)²ẍ_c) − M·α̈ − c − g  with
a = (2/π)·arctan(c_s·θ̇) (eq. 37). Eqs. 41/42/54-57 are written in θ̈ and t_c and do not change.

Eqs. 46-47 as extracted (y = f − (R/r_d)I_a·θ̈, D = diag(a)) cannot identify friction: y is the
cable tension plus friction, ~30 N against f_s ~15 N. The paper calls it "the model without cable
elasticity", i.e. the joint rows of eq. 38 with ẍ_c = 0; that is what :func:`identify_friction`
solves (three rows per sample, four parameters).

Estimation (eqs. 48-50, twin.identification.estimators): OLS (v = W⁺Y, eq. 49), WLS or, by
default, IV with instruments from the model re-simulated on the encoders (identify_variable),
bounded to the physical range (k, f_s > 0; λ, c_a ≥ 0; scipy.optimize.lsq_linear, the parameters
held at a bound reported); Table 2 alternatively with ``estimator="loadfriction"``
(twin.identification.loadfriction: motor friction growing with the load and cable creep, fitted on
the forces by nonlinear IDIM-IV, see docs/identification-coverage.md), or ``"auto"``, the default
of the user's commands (twin.identification.record): where the friction grows with the load (a test of
μ = 0, twin.identification.model_choice) the output error if the line's damping is light and no creep time
is held, else the load-friction fit; IDIM-IV where it does not. These functions keep "iv" as
their default: they are the paper's pipeline. σ: eq. 50's σ_ρ²(WᵀW)⁻¹ assumes white residuals and is several times
too small on filtered, decimated data; the default is the Newey-West HAC sandwich
(twin.identification.uncertainty), with ±2σ intervals. A parameter whose relative σ exceeds
``threshold`` (10 % by default), whose value is physically impossible, or which the bounded
solution holds at a bound is *badly identified*: it is flagged in the :class:`Estimate`, and
:func:`identified_params` keeps the base value for it (the paper's damping).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

from bridge.archive import atomic_write
from twin.identification.estimators import DEFAULT_THRESHOLD, Estimate, least_squares, physical_bounds
from twin.identification.instruments import Simulated, simulated_stretch
from twin.identification.options import (
    NONLINEAR_ESTIMATORS,
    VARIABLE_ESTIMATORS,
    check_estimator,
    check_variable_options,
    creep_refusal,
)
from twin.identification.processing import (
    DECIMATION,
    CampaignData,
    IdentificationError,
    Processed,
    cutoff_rule,
    preprocess,
)
from twin.identification.regressors import (
    W_JOINT,
    cable_tension,
    check_friction_excitation,
    friction_shape,
    ia_over_rho,
    joint_rows,
    masked_rows,
    moving_mask,
    param_names,
    stacked_rows,
    tension_mask,
)
from twin.jsonout import strict_json
from twin.model import dynamics
from twin.model.numeric import CableModelName, build
from twin.model.params import CABLE_K_MAX_N_M, Params, lambda_max_per_m, params_from_dict

__all__ = [
    "DECIMATION",
    "DEFAULT_THRESHOLD",
    "VARIABLE_ESTIMATORS",
    "W_JOINT",
    "AlphaHat",
    "CampaignData",
    "Estimate",
    "IdentificationError",
    "ParameterReport",
    "Processed",
    "Provenance",
    "Validation",
    "cable_tension",
    "check_variable_options",
    "cutoff_rule",
    "fitted_at",
    "identified_name",
    "identified_params",
    "identified_toml",
    "identify_complete",
    "identify_friction",
    "identify_variable",
    "least_squares",
    "preprocess",
    "validate",
    "write_identified",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]




def _solve(proc: Processed, W: FloatArray, Y: FloatArray, names: tuple[str, ...], rows: tuple[IntArray, IntArray], *,
           method: str, equations: str, threshold: float, estimator: str, sigma: str, bounded: bool,
           instruments: FloatArray | None = None) -> Estimate:
    """One model through :func:`least_squares`: physical bounds unless ``bounded`` is False, HAC σ
    with at least the filter's memory (rate / cutoff instants) as correlation lag."""
    sample_index, groups = rows
    return least_squares(
        W, Y, names, method=method, equations=equations, n_samples=int(proc.fitted.sum()), threshold=threshold,
        instruments=instruments, estimator=estimator, groups=groups, sample_index=sample_index,
        bounds=physical_bounds(names) if bounded else None, sigma=sigma,
        min_lag=int(np.ceil(HAC_MIN_LAG_PERIODS * proc.rate_hz / proc.cutoff_hz)),
    )


# Residuals share noise over the filter's memory, about one cutoff period; the lag of the HAC σ spans
# this many cutoff periods at least (3: chosen on camera-noise seeds 201-206 of campaign seed 0).
HAC_MIN_LAG_PERIODS = 3.0
IV_MAX_ITERATIONS = 10
IV_TOLERANCE = 1e-3  # relative change of k and λ between iterations at which IDIM-IV has converged


def _iterate_iv(proc: Processed, params: Params, cable_model: CableModelName, k: FloatArray, lam: FloatArray,
                solve: Callable[[Simulated | None], Estimate]) -> Estimate:
    """IDIM-IV: instruments from the model re-simulated on the encoders (twin.identification.
    instruments) with the current (k, λ), re-estimated until k and λ stop changing. Starts from
    the base parameter set's values; a value outside its physical range is not simulated (the
    previous one is kept)."""
    m = build(params, cable_model)
    sim = simulated_stretch(m, proc, k, lam)
    est = solve(sim)
    for it in range(1, IV_MAX_ITERATIONS + 1):
        k_new = np.where(est.vector("k") > 0, est.vector("k"), k)
        lam_new = np.maximum(est.vector("lambda"), 0.0) if cable_model != "linear" else lam
        change = max(np.max(np.abs(k_new / k - 1)), np.max(np.abs(lam_new - lam) / np.maximum(np.abs(lam), 1.0)))
        if change < IV_TOLERANCE:
            return dataclasses.replace(est, estimator=f"{est.estimator} (simulated model, {it} iterations)")
        k, lam = k_new, lam_new
        sim = simulated_stretch(m, proc, k, lam, sim.alpha, sim.jacobian)
        est = solve(sim)
    return dataclasses.replace(est, estimator=f"{est.estimator} (simulated model, not converged in {it} iterations)")


def identify_friction(proc: Processed, params: Params, *, threshold: float = DEFAULT_THRESHOLD,
                      estimator: str = "ols", sigma: str = "hac", bounded: bool = True) -> Estimate:
    """Dry friction f_s (N) alone, with rigid cables: eq. 38 with ẍ_c = 0 (the paper's eqs. 46-47
    "model without cable elasticity", see the module docstring). Rows: N per sample. Its
    regressor (friction shapes from the encoders) is noise-free: OLS or WLS, no instruments."""
    check_friction_excitation(proc, params)
    D, y = joint_rows(proc, params, elastic=False)
    nc = D.shape[-1]
    est = check_estimator(estimator)
    D, y = D[proc.fitted], y[proc.fitted]
    return _solve(proc, D.reshape(-1, nc), y.reshape(-1), param_names("f_s", nc), stacked_rows(proc.fitted, D.shape[1]),
                  method="friction", equations="eq. 38, rigid cables (eqs. 46-47)", threshold=threshold,
                  estimator="ols" if est == "iv" else est, sigma=sigma, bounded=bounded)


def identify_complete(
    proc: Processed, params: Params, *, weight: float = W_JOINT, threshold: float = DEFAULT_THRESHOLD,
    estimator: str = "iv", sigma: str = "hac", bounded: bool = True,
) -> Estimate:
    """Friction and linear cables together, eqs. 43-45: v = (k, c_a, f_s), 3·n_cables parameters.

    Per sample: n_cables tension rows (eq. 42) diag(x_c)k + diag(ẋ_c)c_a + diag(a)f_s =
    f − (R/r_d)I_a·θ̈, and N joint rows (eq. 38, our sign) weighted by W = ``weight``.
    Tension rows of a cable whose tension from the forces is below 2 N are dropped (slack), and
    those of a motor slower than 1/c_s (regressors.moving_mask: its friction is unknown there).
    ``estimator``: ``"iv"`` (default, see :func:`identify_variable`: instruments x_sim, ẋ_sim of
    the linear model re-simulated on the encoders), ``"ols"`` (eq. 49 as printed) or ``"wls"``.
    """
    check_friction_excitation(proc, params)
    nc = params.n_cables
    a = friction_shape(proc, params)
    y_t = proc.force - ia_over_rho(params) * proc.theta_ddot
    D_j, y_j = joint_rows(proc, params, elastic=True)
    D_j, y_j = D_j[proc.fitted], y_j[proc.fitted]
    N = D_j.shape[1]
    eye = np.eye(nc)

    def tension_rows(x: FloatArray, x_dot: FloatArray) -> FloatArray:
        return np.concatenate([x[:, :, None] * eye, x_dot[:, :, None] * eye, a[:, :, None] * eye], axis=2)

    bottom = np.concatenate([np.zeros((len(D_j), N, 2 * nc)), weight * D_j], axis=2).reshape(-1, 3 * nc)
    mask = tension_mask(y_t - a * np.asarray(params.friction.f_s)) & moving_mask(proc, params)
    W = np.concatenate([tension_rows(proc.x_c, proc.x_c_dot)[mask], bottom])
    Y = np.concatenate([y_t[mask], weight * y_j.reshape(-1)])
    est = check_estimator(estimator)
    (si_t, g_t), (si_j, g_j) = masked_rows(mask), stacked_rows(proc.fitted, N)
    rows = (np.concatenate([si_t, si_j]), np.concatenate([g_t, nc + g_j]))
    names = param_names("k", nc) + param_names("c_a", nc) + param_names("f_s", nc)

    def solve(sim: Simulated | None) -> Estimate:
        Phi = None if sim is None else np.concatenate([tension_rows(sim.x, sim.x_dot)[mask], bottom])
        return _solve(proc, W, Y, names, rows, method="complete", equations=f"eqs. 43-45, W = {weight:g}",
                      threshold=threshold, estimator=est, sigma=sigma, bounded=bounded, instruments=Phi)

    k0 = np.asarray(params.cables.linear.k, dtype=float)
    return solve(None) if est != "iv" else _iterate_iv(proc, params, "linear", k0, np.zeros(nc), solve)


def identify_variable(
    proc: Processed, params: Params, f_s: FloatArray, *, threshold: float = DEFAULT_THRESHOLD, estimator: str = "iv",
    sigma: str = "hac", bounded: bool = True, creep_time_s: float | None = None,
) -> Estimate:
    """Variable stiffness, eqs. 54-57: t_c = k·x_c + λ·x_c·t_c + c_a·ẋ_c with t_c from eq. 55
    using the friction ``f_s`` (N) identified before; v = (k, λ, c_a). Rows of slack cables and of
    motors slower than 1/c_s (regressors.moving_mask) are dropped.

    Why instrumental variables by default: x_c comes from α_IP (1° of camera noise, ≈ 0.2-0.4 mm
    of stretch after filtering, against a stretch of a few mm), so the regressors x_c, x_c·t_c and
    ẋ_c are noisy and plain least squares is biased towards zero (errors in variables). The
    instruments are x_sim, x_sim·t_sim, ẋ_sim of the model (k, λ) re-simulated on the encoders
    (twin.identification.instruments), iterated to a fixed point (IDIM-IV, Janot, Vandanjon &
    Gautier, IEEE TCST 2014): free of camera noise, and not built from the measured tension t_c,
    which is the fitted quantity (on the prototype the forces are open-loop current commands whose
    errors would be in the instruments and in the residual alike; this module's instruments before
    issue 17 were t_c, t_c², ṫ_c). ``estimator="ols"`` gives eq. 49 as printed, ``"wls"`` weights
    each cable's rows by its residual σ. ``"loadfriction"``: twin.identification.loadfriction (the
    motor friction growing with the load and a creep term fitted with k, λ, c_a on the motors'
    forces; ``f_s`` is not used, the bounds are always on); its Estimate also holds mu, F_0, beta, c_f.
    ``"outputerror"``: twin.identification.outputerror (the neck's equilibrium simulated on the
    encoders against α_IP, and the motor forces, fitted together with the springs' rates and the
    pulleys' radius: free of the friction model's errors that bias the force fits' λ).
    ``"auto"``: where that fit rejects eqs. 54-55, the output error if the line's damping is light,
    else the load-friction fit; ``"iv"`` where it does not (:func:`_identify_variable_auto`).
    ``creep_time_s``: the line's creep time constant τ (s) measured apart (a bench creep test of the
    line), held in the load-friction fit instead of chosen from the record (twin.identification.
    loadfriction.creep_taus); None (default): chosen.
    """
    name = check_estimator(estimator, VARIABLE_ESTIMATORS)
    if creep_time_s is not None and name not in ("loadfriction", "auto"):
        raise IdentificationError(f"a creep time applies to the load-friction fit (estimator loadfriction or auto); "
                                  f"estimator {name!r} {creep_refusal(name)}")
    if name == "outputerror":
        from twin.identification.outputerror import fit_output_error

        return fit_output_error(proc, params, threshold=threshold, sigma=sigma)
    if name == "loadfriction":
        from twin.identification.loadfriction import creep_taus, fit_load_friction

        return fit_load_friction(proc, params, threshold=threshold, sigma=sigma,
                                 taus_s=creep_taus(creep_time_s)).estimate
    if name == "auto":
        return _identify_variable_auto(proc, params, f_s, threshold=threshold, sigma=sigma, bounded=bounded,
                                       creep_time_s=creep_time_s)
    nc = params.n_cables
    f_s = np.asarray(f_s, dtype=float)
    if f_s.shape != (nc,) or not np.all(np.isfinite(f_s)):
        raise IdentificationError(f"f_s must be {nc} finite values (N), got {f_s}")
    t_c = cable_tension(proc, params, f_s)
    eye = np.eye(nc)

    def rows(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
        return np.concatenate([a[:, :, None] * eye, b[:, :, None] * eye, c[:, :, None] * eye], axis=2)

    mask = tension_mask(t_c) & moving_mask(proc, params)
    W = rows(proc.x_c, proc.x_c * t_c, proc.x_c_dot)[mask]
    est = check_estimator(estimator)
    names = param_names("k", nc) + param_names("lambda", nc) + param_names("c_a", nc)

    def solve(sim: Simulated | None) -> Estimate:
        Phi = None if sim is None else rows(sim.x, sim.x * sim.t, sim.x_dot)[mask]
        return _solve(proc, W, t_c[mask], names, masked_rows(mask), method="variable", equations="eqs. 54-57",
                      threshold=threshold, estimator=est, sigma=sigma, bounded=bounded, instruments=Phi)

    v = params.cables.variable
    k0, lam0 = np.asarray(v.k, dtype=float), np.asarray(v.lam, dtype=float)
    return solve(None) if est != "iv" else _iterate_iv(proc, params, "variable", k0, lam0, solve)


def _identify_variable_auto(proc: Processed, params: Params, f_s: FloatArray, *, threshold: float, sigma: str,
                            bounded: bool, creep_time_s: float | None = None) -> Estimate:
    """``estimator="auto"``: where the load-friction fit rejects eqs. 54-55 (its friction grows with the
    load: a one-sided test of the cables' pooled μ, twin.identification.model_choice), the output
    error (twin.identification.outputerror: the pose is free of the friction model's errors) if the
    same fit finds the line's damping light enough for a quasi-static pose
    (model_choice.damping_check) and no creep time is held, else the load-friction fit; where it does
    not reject them, IDIM-IV. The choice and its tests lead the estimator's text. A campaign whose
    motors never turned fast enough for the load-friction fit gets IDIM-IV, saying why."""
    from twin.identification.loadfriction import creep_taus, fit_load_friction, gear_losses
    from twin.identification.model_choice import TEST_TAU_S, damping_check, paper_model_test
    from twin.identification.outputerror import fit_output_error

    taus_s = creep_taus(creep_time_s)  # a bad τ is the caller's error, not a reason to fall back
    try:
        # the test's fit has no gear loss: the paper's model is its μ = β = 0 (model_choice); one τ
        # of the grid (model_choice.TEST_TAU_S) unless one is held, as μ hardly depends on it
        plain = fit_load_friction(proc, params, threshold=threshold, sigma=sigma, gear=(0.0, 0.0),
                                  taus_s=taus_s if len(taus_s) == 1 else (TEST_TAU_S,))
    except ValueError as exc:
        iv = identify_variable(proc, params, f_s, threshold=threshold, estimator="iv", sigma=sigma, bounded=bounded)
        return dataclasses.replace(iv, estimator=f"auto → iv (no load-friction fit: {exc}); {iv.estimator}")
    test = paper_model_test(plain.estimate)
    if test.rejects_paper_model:
        damping = damping_check(plain.estimate, proc.x_c_dot[proc.fitted])
        why = f"{test.describe()}; {damping.describe()}"
        if creep_time_s is not None:
            why += f"; the creep time held at {creep_time_s:g} s, which the output error fits itself"
        elif damping.quasi_static:
            try:
                oe = fit_output_error(proc, params, threshold=threshold, sigma=sigma,
                                      start=(plain.estimate.vector("k"), plain.estimate.vector("lambda")))
                return dataclasses.replace(oe, estimator=f"auto → outputerror ({why}); {oe.estimator}")
            except ValueError as exc:
                why += f"; no output-error fit: {exc}"
        gear = gear_losses(params)
        lf = plain.estimate if gear == (0.0, 0.0) and len(taus_s) == 1 else fit_load_friction(
            proc, params, threshold=threshold, sigma=sigma, taus_s=taus_s).estimate
        return dataclasses.replace(lf, estimator=f"auto → loadfriction ({why}); {lf.estimator}")
    iv = identify_variable(proc, params, f_s, threshold=threshold, estimator="iv", sigma=sigma, bounded=bounded)
    return dataclasses.replace(iv, estimator=f"auto → iv ({test.describe()}); {iv.estimator}")


def identify_all(
    proc: Processed, params: Params, *, threshold: float = DEFAULT_THRESHOLD, estimator: str = "iv",
    sigma: str = "hac", bounded: bool = True, creep_time_s: float | None = None,
) -> dict[str, Estimate]:
    """The three estimations of §5 in order: friction alone, complete (Table 1), variable (Table 2,
    with the f_s of the friction-alone estimate: it does not depend on the cable model, while the
    complete model's f_s absorbs the misfit of linear cables when the cables stiffen with tension).
    ``estimator="loadfriction"`` or ``"auto"`` is Table 2's alone: friction and Table 1 then use "iv".
    ``creep_time_s``: as :func:`identify_variable`."""
    linear = "iv" if check_estimator(estimator, VARIABLE_ESTIMATORS) in NONLINEAR_ESTIMATORS else estimator
    fric = identify_friction(proc, params, threshold=threshold, estimator=linear, sigma=sigma, bounded=bounded)
    comp = identify_complete(proc, params, threshold=threshold, estimator=linear, sigma=sigma, bounded=bounded)
    var = identify_variable(proc, params, fric.values, threshold=threshold, estimator=estimator, sigma=sigma,
                            bounded=bounded, creep_time_s=creep_time_s)
    return {"friction": fric, "complete": comp, "variable": var}


# --- identified parameter set with provenance ---------------------------------------------------


class Provenance(msgspec.Struct, frozen=True, kw_only=True):
    """Where an identified parameter set comes from. Written as ``<name>.provenance.json`` next to
    the TOML (and summarised in the TOML's header comments)."""

    campaign: str
    date: str
    method: str
    base_parameter_set: str = ""
    cutoff_hz: float = float("nan")
    threshold: float = DEFAULT_THRESHOLD
    software_version: str = ""
    parameters: list[dict[str, Any]] = msgspec.field(default_factory=list)  # per-parameter flags
    kept_base: list[str] = msgspec.field(default_factory=list)  # names of the parameters not used
    #: Why the set is not to be trusted as an identification ("" for none): e.g. fitted on a campaign
    #: that did not finish (``xneck identify --partial``). First in the TOML's header, where a reader
    #: of the set alone sees it.
    warning: str = ""


def warned(provenance: Provenance, warning: str) -> Provenance:
    """``provenance`` with ``warning`` added after its own (one line: the TOML's header holds it)."""
    line = " ".join(warning.split())
    return msgspec.structs.replace(provenance, warning=f"{provenance.warning}; {line}" if provenance.warning else line)


@dataclass(frozen=True)
class ParameterReport:
    """What :func:`identified_params` did with each estimate.

    used: parameter key (``"cables.variable.k(2)"``) -> value written; kept_base: key ->
    (base value kept, estimate refused, reason)."""

    used: dict[str, float] = field(default_factory=dict)
    kept_base: dict[str, tuple[float, float, str]] = field(default_factory=dict)

    def lines(self) -> list[str]:
        out = [f"kept base {k} = {b:g} (estimate {e:g}: {why})" for k, (b, e, why) in self.kept_base.items()]
        return out or ["every identified parameter was used"]


# (estimate method, symbol) -> (params section path, key in that section)
_TARGETS = (
    ("friction", "f_s", ("friction",), "f_s"),
    ("complete", "k", ("cables", "linear"), "k"),
    ("complete", "c_a", ("cables", "linear"), "c_a"),
    ("variable", "k", ("cables", "variable"), "k"),
    ("variable", "lambda", ("cables", "variable"), "lambda"),
    ("variable", "c_a", ("cables", "variable"), "c_a"),
)


#: Why the output error's structure is reported and not written (docs/identification/identified-set-control.md).
STRUCTURE_NOT_WRITTEN = ("reported, not written: an effective value of the output error (it absorbs the bar masses' "
                         "and free lengths' errors), not the physical one a parameter file holds")


def _structure(data: dict[str, Any], est: Estimate | None) -> list[dict[str, Any]]:
    """The output error's structure (twin.identification.outputerror): the spring rates as the
    file's × s_left(i), s_right(i), and the pulley radius r + δr, as provenance rows (``used``
    False, :data:`STRUCTURE_NOT_WRITTEN`; the set keeps the file's). The rates are effective ones
    (they absorb the bar masses' and free lengths' errors, which the fit holds), not the springs'
    physical rates that the workspace and stiffness analyses read; in the controller's set they
    changed tracking on the robot truth by a few hundredths of a degree
    (docs/identification/identified-set-control.md). A user applies them with the ``--set`` line
    :func:`write_identified` prints. ``relative_sigma`` of δr is σ(δr)/r (its own is large
    wherever δr is near 0, however well it is known)."""
    if est is None or "delta_r" not in est.names:
        return []
    rows: list[dict[str, Any]] = []
    for side in ("left", "right"):
        for j, factor in enumerate(est.vector(f"s_{side}")):
            i = est.names.index(f"s_{side}({j + 1})")
            rows.append({"name": f"springs.k_{side}({j + 1})", "estimate": float(data["springs"][f"k_{side}"][j] * factor),
                         "relative_sigma": float(est.relative_sigma[i]), "method": "variable", "used": False,
                         "reason": STRUCTURE_NOT_WRITTEN})
    i, r = est.names.index("delta_r"), float(data["geometry"]["r"])
    rows.append({"name": "geometry.r", "estimate": r + float(est.values[i]), "relative_sigma": float(est.sigma[i]) / r,
                 "method": "variable", "used": False, "reason": STRUCTURE_NOT_WRITTEN})
    return rows


def structure_overrides(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The ``--set`` values that apply the reported structure (:func:`_structure`'s rows), e.g.
    ``["springs.k_left=[631.2,190.3,223.0]", ..., "geometry.r=0.0047086"]``; [] without them."""
    values: dict[str, list[tuple[int, float]]] = {}
    for row in rows:
        if row.get("reason") != STRUCTURE_NOT_WRITTEN:
            continue
        key, _, index = str(row["name"]).partition("(")
        values.setdefault(key, []).append((int(index.rstrip(")") or 0), float(row["estimate"])))
    out = []
    for key, items in values.items():
        if len(items) == 1 and items[0][0] == 0:
            out.append(f"{key}={items[0][1]:.7g}")
        else:
            out.append(f"{key}=[{','.join(f'{v:.6g}' for _, v in sorted(items))}]")
    return out


def _beyond_checked(base: Params, data: dict[str, Any], key: str, j: int, value: float) -> str:
    """Why an estimate the estimator accepts cannot go into a parameter set ("" if it can): past
    the bounds :mod:`twin.model.params` checks (a motor's peak force, the stiffness the twin's step
    was checked with); written, the set would not load."""
    if key == "f_s" and value >= base.motor_peak_force_N:
        return f"above the motors' peak force at the cable, {base.motor_peak_force_N:.4g} N: no motor would move"
    if key == "k" and value > CABLE_K_MAX_N_M:
        return f"stiffer than the {CABLE_K_MAX_N_M:g} N/m the twin's step is checked with"
    if key == "lambda":
        top = lambda_max_per_m(float(data["cables"]["variable"]["k"][j]), base.limits.f_max)
        if value > top:
            return (f"the cable would stiffen past {CABLE_K_MAX_N_M:g} N/m at f_max (eq. 54): λ at most "
                    f"{top:.4g} 1/m with its k")
    return ""


def identified_params(
    base: Params, estimates: Mapping[str, Estimate], provenance: Provenance
) -> tuple[Params, ParameterReport, Provenance]:
    """A new parameter set: friction.f_s (friction-alone estimate), cables.linear k/c_a (complete
    model), cables.variable k/lambda/c_a (variable model) replaced by their estimates. The output
    error's spring rates and pulley radius are in the provenance's rows, not in the set
    (:func:`_structure`).

    A badly identified parameter (relative σ above the estimate's threshold), one outside its
    physical range (k ≤ 0, λ < 0, f_s < 0, c_a < 0), or one past the bounds a parameter set is
    checked against (:func:`_beyond_checked`) is NOT used: the base value stays and the
    parameter is listed in the report and in the returned provenance (``kept_base``).
    """
    data = base.to_dict()
    report = ParameterReport()
    rows: list[dict[str, Any]] = []
    for method, symbol, path, key in _TARGETS:
        est = estimates.get(method)
        if est is None:
            continue
        section = data
        for part in path:
            section = section[part]
        values = list(section[key])
        new = est.vector(symbol)
        idx = [i for i, n in enumerate(est.names) if n.split("(")[0] == symbol]
        for j, (value, i) in enumerate(zip(new, idx)):
            name = f"{'.'.join(path)}.{key}({j + 1})"
            reason = est.reason(i) or _beyond_checked(base, data, key, j, float(value))
            if reason:
                report.kept_base[name] = (float(values[j]), float(value), reason)
            else:
                values[j] = float(value)
                report.used[name] = float(value)
            rows.append({
                "name": name, "estimate": float(value), "relative_sigma": float(est.relative_sigma[i]),
                "method": method, "used": not reason, "reason": reason,
            })
        section[key] = values
    rows += _structure(data, estimates.get("variable"))
    data["name"] = identified_name(base.name)
    params = params_from_dict(data, f"identified from {provenance.campaign}")
    prov = msgspec.structs.replace(
        provenance, parameters=rows, kept_base=list(report.kept_base), base_parameter_set=base.name
    )
    return params, report, prov


def make_provenance(campaign: str, proc: Processed, *, method: str = "", threshold: float = DEFAULT_THRESHOLD,
                    estimates: Mapping[str, Estimate] | None = None) -> Provenance:
    """Provenance for a campaign processed now (ISO date in UTC); with ``estimates``, the method
    names each model's estimator and σ."""
    try:
        from importlib.metadata import version

        sw = version("xneck")
    except Exception:  # noqa: BLE001 - not installed: an editable checkout
        sw = "unknown"
    how = "".join(f"; {name}: {e.estimator}, σ {e.sigma_method}" for name, e in (estimates or {}).items())
    return Provenance(
        campaign=campaign,
        date=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        method=method or (
            f"3-X paper §5: Butterworth filtfilt {proc.cutoff_hz:.2f} Hz, decimation to {proc.rate_hz:.2f} Hz; "
            "f_s by eq. 38 (rigid cables); linear cables by eqs. 43-45 (W = 100); variable cables by eqs. 54-57; "
            "physical bounds k, f_s > 0, λ, c_a ≥ 0" + how
        ),
        cutoff_hz=proc.cutoff_hz, threshold=threshold, software_version=sw,
    )


def identified_toml(params: Params, provenance: Provenance, provenance_file: str = "") -> str:
    """The identified set as TOML that :func:`twin.model.params.load_params` reads, after a comment
    header naming the campaign, its warning if any, date, method, the parameters kept at their base value, the ``--set``
    line of the output error's structure, and ``provenance_file`` if given."""
    structure = structure_overrides(provenance.parameters)
    header = [
        f"# Identified parameter set (3-X paper §5) from campaign {provenance.campaign}",
        *([f"# WARNING: {provenance.warning}"] if provenance.warning else []),
        f"# date {provenance.date}, software {provenance.software_version}, base {provenance.base_parameter_set}",
        f"# method: {provenance.method}",
        f"# parameters kept at their base value (badly identified or not estimated): "
        f"{', '.join(provenance.kept_base) or 'none'}",
        *([f"# the output error's spring rates and pulley radius, {STRUCTURE_NOT_WRITTEN}; to apply them: "
           + " ".join(f"--set '{v}'" for v in structure)] if structure else []),
        *([f"# full provenance and per-parameter relative σ: {provenance_file}"] if provenance_file else []),
    ]
    return "\n".join(header) + "\n" + params.to_toml()


def identified_name(base_name: str) -> str:
    """The name (and file stem) of the parameter set identified from base set ``base_name``."""
    return f"{base_name}-identified"


def write_identified(path: str | Path, params: Params, provenance: Provenance) -> tuple[Path, Path]:
    """Write ``path`` (TOML, loadable by :func:`twin.model.params.load_params`, with a comment header
    naming the campaign, date, method and the parameters kept at their base value) and
    ``<stem>.provenance.json`` next to it. Returns both paths."""
    path = Path(path)
    prov_path = path.with_name(path.stem + ".provenance.json")
    # Atomic: a full disk or a Ctrl-C leaves the previous files or none, never a half-written set
    # that load_params would refuse or, worse, read with values missing.
    atomic_write(path, identified_toml(params, provenance, prov_path.name).encode())
    atomic_write(prov_path, (strict_json(msgspec.to_builtins(provenance), indent=2) + "\n").encode())
    return path, prov_path


# --- validation (§5.3-5.5) ----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class AlphaHat:
    """α̂ (rad) at the camera instants ``t_s`` for one method and cable model, and its mean
    absolute error against α_IP (deg, over joints and frames)."""

    method: str  # "eq33" or "eq35"
    cable_model: str  # "rigid", "linear", "variable"
    t_s: FloatArray
    alpha_hat: FloatArray
    mean_error_deg: float


@dataclass(frozen=True, eq=False)
class Validation:
    """Checks of the identified models (Figs. 4-8).

    Torques (N·m) at the identification instants: Γ_m = Z·f, Γ_rf and Γ_r (eqs. 51-53, our
    sign) and the mean absolute errors |Γ_m − Γ_rf|, |Γ_m − Γ_r| (every mean error over the
    instants and frames the fit uses, ``Processed.fitted``: not a gap's interpolation). Tension (N), both sides of
    eq. 42: ``tension_force[model]`` from the forces (RHS) and ``tension_stiffness[model]`` from
    the cable model (LHS, eq. 39 or 54), for "linear" and "variable", with mean absolute errors
    over non-slack samples. α̂ by eqs. 33 and 35 for the rigid, linear and variable cable models
    against α_IP (Fig. 8); ``t_ip_s``/``alpha_ip`` are the frames compared.
    """

    t_s: FloatArray
    gamma_m: FloatArray
    gamma_rf: FloatArray
    gamma_r: FloatArray
    gamma_rf_error: float
    gamma_r_error: float
    tension_force: dict[str, FloatArray]
    tension_stiffness: dict[str, FloatArray]
    tension_error: dict[str, float]
    alpha_hat: dict[tuple[str, str], AlphaHat]
    t_ip_s: FloatArray
    alpha_ip: FloatArray

    def alpha_errors_deg(self) -> dict[str, float]:
        return {f"{m}/{c}": a.mean_error_deg for (m, c), a in self.alpha_hat.items()}

    def summary(self) -> dict[str, Any]:
        return {
            "gamma_rf_mean_error": self.gamma_rf_error, "gamma_r_mean_error": self.gamma_r_error,
            "tension_mean_error_N": dict(self.tension_error), "alpha_hat_mean_error_deg": self.alpha_errors_deg(),
        }


def fitted_at(proc: Processed, t_s: FloatArray) -> NDArray[np.bool_]:
    """Which times ``t_s`` (e.g. camera frames) lie among instants the fit uses (``Processed.fitted``):
    not in a gap of the record nor within the filter's memory of a long one. Times before or after
    the processed instants count as fitted."""
    return np.interp(t_s, proc.t_s, proc.fitted.astype(float)) > 1.0 - 1e-9


def _alpha_hat_all(data: CampaignData, proc: Processed, params: Params, models: tuple[CableModelName, ...]) -> tuple[dict, FloatArray, FloatArray]:
    """α̂ by eqs. 33 and 35 (twin.model.estimation) on the 500 Hz record, compared at the camera
    frames inside it (the errors over those the fit would use: :func:`fitted_at`). The estimators
    start at α̂ = 0, x_c = 0 with the first encoder reading: the campaign starts straight and at
    rest (§5.2.2)."""
    from twin.model.estimation import PseudoInverseEstimator, alpha_hat_3

    t, theta, force, theta_dot = proc.fast_t_s, proc.fast_theta, proc.fast_force, proc.fast_theta_dot
    inside = (data.t_ip_s >= t[0]) & (data.t_ip_s <= t[-1])
    t_ip, a_ip = data.t_ip_s[inside], data.alpha_ip_rad[inside]
    k_ip = np.clip(np.searchsorted(t, t_ip - 1e-9), 0, len(t) - 1)  # the tick of each capture
    ok = fitted_at(proc, t_ip)  # the mean error leaves out the frames of the record's gaps
    out: dict[tuple[str, str], AlphaHat] = {}
    for name in models:
        m = build(params, name)
        est = PseudoInverseEstimator(m, float(np.median(np.diff(t))))
        est.reset(theta=theta[0])
        a35 = np.empty((len(k_ip), m.n_joints))
        a33 = np.empty_like(a35)
        j = 0
        guess = np.zeros(m.n_joints)
        ah = est.alpha_hat
        for k in range(len(t)):
            if k > 0:
                ah = est.update(theta[k], force[k], theta_dot[k])
            while j < len(k_ip) and k_ip[j] == k:
                a35[j] = ah
                guess = a33[j] = alpha_hat_3(m, theta[k], est.x_c, guess)
                j += 1
        for meth, arr in (("eq33", a33), ("eq35", a35)):
            err = float(np.degrees(np.mean(np.abs(arr - a_ip)[ok])))
            out[(meth, name)] = AlphaHat(meth, name, t_ip, arr, err)
    return out, t_ip, a_ip


def validate(
    data: CampaignData, proc: Processed, identified: Params, estimates: Mapping[str, Estimate],
    *, alpha_hat: bool = True,
) -> Validation:
    """Figs. 4-8 and their mean errors for the ``identified`` parameter set and ``estimates``.

    Γ_rf uses the identified f_s; the tension both ways (Figs. 5-7) uses each cable model's
    least-squares fit (eq. 49; "linear" with its own f_s, "variable" with the friction-alone f_s),
    badly identified damping included: this compares how well the two model forms fit. α̂ uses ``identified`` (so a
    badly identified damping is replaced by its base value there, as the controller would run).
    """
    g = identified.geometry
    iar2 = identified.motors.I_a * (g.R / g.r_d) ** 2
    a = friction_shape(proc, identified)
    f_s = np.asarray(identified.friction.f_s)
    Zx = np.einsum("nij,nj->ni", proc.Z, -iar2 * proc.x_c_ddot)
    rigid_part = Zx + np.einsum("nij,nj->ni", proc.M, proc.alpha_ddot) + proc.c + proc.g
    gamma_m = np.einsum("nij,nj->ni", proc.Z, proc.force)
    gamma_rf = np.einsum("nij,nj->ni", proc.Z, a * f_s) + rigid_part
    gamma_r = rigid_part

    tf: dict[str, FloatArray] = {}
    ts: dict[str, FloatArray] = {}
    te: dict[str, float] = {}
    comp, var, fric = estimates.get("complete"), estimates.get("variable"), estimates.get("friction")
    # Figs. 5-7 compare how well each cable model FITS the tension: use each model's least-squares
    # fit (eq. 49), as the paper does. The instrumental-variable estimates in the tables are closer
    # to the truth under camera noise in x_c but, by construction, do not minimise this residual.
    fs_var = fric.values if fric is not None else f_s
    if comp is not None:
        comp = identify_complete(proc, identified, estimator="ls")
        tf["linear"] = cable_tension(proc, identified, comp.vector("f_s"))
        ts["linear"] = dynamics.cable_tension_law(comp.vector("k"), 0.0, comp.vector("c_a"), proc.x_c, proc.x_c_dot)
    if var is not None:
        var = identify_variable(proc, identified, fs_var, estimator="ls")
        tf["variable"] = cable_tension(proc, identified, fs_var)
        k, lam, c_a = var.vector("k"), var.vector("lambda"), var.vector("c_a")
        ts["variable"] = dynamics.cable_tension_law(k, lam, c_a, proc.x_c, proc.x_c_dot)
    for name in tf:
        mask = tension_mask(tf[name]) & proc.fitted[:, None]
        te[name] = float(np.mean(np.abs(tf[name] - ts[name])[mask]))

    if alpha_hat:
        ah, t_ip, a_ip = _alpha_hat_all(data, proc, identified, ("rigid", "linear", "variable"))
    else:
        ah, t_ip, a_ip = {}, np.zeros(0), np.zeros((0, data.n_joints))
    return Validation(
        t_s=proc.t_s, gamma_m=gamma_m, gamma_rf=gamma_rf, gamma_r=gamma_r,
        gamma_rf_error=float(np.mean(np.abs(gamma_m - gamma_rf)[proc.fitted])),
        gamma_r_error=float(np.mean(np.abs(gamma_m - gamma_r)[proc.fitted])),
        tension_force=tf, tension_stiffness=ts, tension_error=te, alpha_hat=ah, t_ip_s=t_ip, alpha_ip=a_ip,
    )
