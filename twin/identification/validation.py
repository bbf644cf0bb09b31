"""Cross-validation (3-X paper §5.3-5.5 on data not fitted): the models identified on one campaign
(A) predict another (B), e.g. the §7 control test; Figs. 4-8 and their errors on B beside A's own.

In-sample figures (the pipeline's :func:`validate` on A) say how well the model forms fit; only
out-of-sample ones say whether the identified parameters predict: a model that fits its noise, or
a trajectory that excites one motion only, looks good in-sample and not on B.

On B, with A's identification and nothing fitted to B:

* Fig. 4: Γ_m = Z·f against Γ_rf (A's identified f_s) and Γ_r (eqs. 51-53);
* Figs. 5-7: the tension from B's forces (eq. 42 RHS, A's f_s) against the tension A's cable
  models predict from B's stretch (eq. 42 LHS): the least-squares fits of A (eq. 49), the same
  fits the in-sample figures use, so the two columns compare like with like;
* Fig. 8: α̂ by eqs. 33 and 35 with A's identified parameter set against B's α_IP.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from twin.identification.pipeline import (
    CampaignData,
    IdentificationError,
    Processed,
    Validation,
    identify_complete,
    identify_variable,
    preprocess,
    validate,
)
from twin.identification.record import Excitation, Identification, campaign_data_from_mcap
from twin.identification.regressors import cable_tension, tension_mask
from twin.model import dynamics

__all__ = [
    "CrossValidation", "comparison", "comparison_text", "cross_validate", "load_validation_campaign", "out_of_sample",
    "summary",
]


class CrossValidation(NamedTuple):
    """A fit on campaign A and its validation on campaign B."""

    fit: Identification  # A: tables, identified parameters, in-sample validation
    data: CampaignData  # B as recorded
    processed: Processed  # B processed (its own cutoff, from its own excitation)
    validation: Validation  # Figs. 4-8 on B with A's models


def _tension_fits(fit: Identification) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """A's least-squares cable fits (eq. 49), as the in-sample Figs. 5-7 use them:
    model -> (f_s, k, λ, c_a)."""
    proc, params, est = fit.processed, fit.params, fit.estimate
    out: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
    if "complete" in est:
        comp = identify_complete(proc, params, estimator="ls")
        out["linear"] = (comp.vector("f_s"), comp.vector("k"), np.zeros(params.n_cables), comp.vector("c_a"))
    if "variable" in est:
        f_s = est["friction"].values if "friction" in est else np.asarray(params.friction.f_s)
        var = identify_variable(proc, params, f_s, estimator="ls")
        out["variable"] = (f_s, var.vector("k"), var.vector("lambda"), var.vector("c_a"))
    return out


def out_of_sample(fit: Identification, data: CampaignData, proc: Processed, *, alpha_hat: bool = True) -> Validation:
    """Figs. 4-8 on campaign B (``data``, ``proc``) with the models identified on A (module docstring)."""
    params = fit.params
    val = validate(data, proc, params, {}, alpha_hat=alpha_hat)  # torques and α̂ with A's parameter set
    tf: dict[str, np.ndarray] = {}
    ts: dict[str, np.ndarray] = {}
    te: dict[str, float] = {}
    for name, (f_s, k, lam, c_a) in _tension_fits(fit).items():
        tf[name] = cable_tension(proc, params, f_s)
        ts[name] = dynamics.cable_tension_law(k, lam, c_a, proc.x_c, proc.x_c_dot)
        mask = tension_mask(tf[name]) & proc.fitted[:, None]
        te[name] = float(np.mean(np.abs(tf[name] - ts[name])[mask])) if mask.any() else math.nan
    return dataclasses.replace(val, tension_force=tf, tension_stiffness=ts, tension_error=te)


def load_validation_campaign(campaign_b: str | Path, excitation: Excitation | None = None, *,
                             alpha_ip_source: str | None = None) -> CampaignData:
    """Campaign B read and checked, before anything is fitted on A (a bad B fails fast); its α_IP
    of ``alpha_ip_source`` (:func:`campaign_data_from_mcap`). Raises :class:`IdentificationError` naming B."""
    try:
        return campaign_data_from_mcap(campaign_b, excitation, alpha_ip_source=alpha_ip_source)
    except IdentificationError as exc:
        raise IdentificationError(f"validation campaign {campaign_b}: {exc}") from None


def cross_validate(fit: Identification, data: CampaignData, *, cutoff_hz: float | None = None,
                   alpha_hat: bool = True) -> CrossValidation:
    """Validate ``fit`` (an identification of campaign A, with its in-sample validation) on
    campaign B (``data``, e.g. from :func:`load_validation_campaign`). B is processed with its own
    filter cutoff (from its recorded trajectory, unless ``cutoff_hz``). Raises
    :class:`IdentificationError` naming B when it cannot be processed or does not match A's robot."""
    try:
        proc = preprocess(data, fit.params, cutoff_hz)
    except IdentificationError as exc:
        raise IdentificationError(f"validation campaign {data.campaign}: {exc}") from None
    return CrossValidation(fit, data, proc, out_of_sample(fit, data, proc, alpha_hat=alpha_hat))


_ROWS = (
    ("torque |Γ_m − Γ_rf| (N·m), eqs. 51-53", lambda v: v.gamma_rf_error),
    ("torque |Γ_m − Γ_r| (N·m), no friction", lambda v: v.gamma_r_error),
)


def comparison(in_sample: Validation, out_sample: Validation) -> dict[str, dict[str, float]]:
    """Mean errors side by side: metric -> {"in_sample": …, "out_of_sample": …} (units in the name)."""
    rows: dict[str, dict[str, float]] = {}

    def add(name: str, a: float, b: float) -> None:
        rows[name] = {"in_sample": float(a), "out_of_sample": float(b)}

    for name, get in _ROWS:
        add(name, get(in_sample), get(out_sample))
    for model in in_sample.tension_error:
        add(f"tension ({model} cables, eq. 42) (N)", in_sample.tension_error[model],
            out_sample.tension_error.get(model, math.nan))
    for key, a in in_sample.alpha_hat.items():
        b = out_sample.alpha_hat.get(key)
        add(f"α̂ by eq. {key[0][2:]}, {key[1]} cables (deg)", a.mean_error_deg, b.mean_error_deg if b else math.nan)
    return rows


def comparison_text(rows: Mapping[str, Mapping[str, float]], fitted_on: str, validated_on: str) -> str:
    """The comparison as a text table: in-sample (A) and out-of-sample (B) columns."""
    width = max(len(n) for n in rows) + 2 if rows else 40
    lines = [f"Cross-validation: fitted on {fitted_on}, validated on {validated_on} (mean errors)",
             f"{'':{width}s}{'in-sample (A)':>16s}{'on B':>12s}", "-" * (width + 28)]
    for name, r in rows.items():
        lines.append(f"{name:{width}s}{r['in_sample']:16.3f}{r['out_of_sample']:12.3f}")
    return "\n".join(lines)


def summary(cv: CrossValidation) -> dict[str, Any]:
    """JSON-ready: the campaigns, B's processing and the side-by-side errors."""
    in_sample = cv.fit.validation
    if in_sample is None:
        raise IdentificationError("cross-validation needs the in-sample validation of the fit (with_validation)")
    return {
        "fitted_on": cv.fit.data.campaign, "validated_on": cv.data.campaign,
        "validation_processing": {"cutoff_hz": cv.processed.cutoff_hz, "rate_hz": cv.processed.rate_hz,
                                  "n": cv.processed.n, "n_fitted": int(cv.processed.fitted.sum()),
                                  "notes": list(cv.processed.notes), "bandwidth_from": cv.processed.bandwidth_from},
        "errors": comparison(in_sample, cv.validation),
    }
