"""The identification's options, checked before anything runs: the estimator's name and the
line's creep time, as a command line, a REST body or a study gives them. Kept apart from
twin.identification.pipeline, whose import costs scipy.signal (seconds), so that refusing a bad
option costs nothing and happens before the robot moves."""

from __future__ import annotations

import math

# The linear estimators of W·v + ρ = Y (3-X paper eqs. 48-50; twin.identification.estimators).
ESTIMATORS = ("ols", "wls", "iv")
ESTIMATOR_NAMES = {"ols": "ordinary least squares", "wls": "weighted least squares",
                   "iv": "instrumental variables"}
ESTIMATOR_ALIASES = {"ls": "ols", "load-friction": "loadfriction"}  # "ls": eq. 49's name before issue 17
# Table 2 only: eq. 55's friction replaced by one growing with the load, plus cable creep
# (twin.identification.loadfriction, issues 16/17); Table 1 and f_s then use the default "iv".
VARIABLE_ESTIMATORS = (*ESTIMATORS, "loadfriction", "outputerror", "auto")
# "auto": where the load-friction fit rejects the paper's model (twin.identification.model_choice), the output
# error if that fit finds the line's damping light and no creep time is held, else the load-friction fit; "iv"
# where it keeps the paper's model (pipeline._identify_variable_auto). The default of the user's commands
# (xneck identify, campaigns, the console).
NONLINEAR_ESTIMATORS = ("loadfriction", "outputerror", "auto")  # Table 2's alone: Table 1 and f_s then use "iv"
# σ of the estimates: Newey-West HAC for correlated residuals (twin.identification.uncertainty), or
# eq. 50 as printed (white residuals; too small on filtered data).
SIGMA_METHODS = ("hac", "white")


def check_estimator(estimator: str, allowed: tuple[str, ...] = ESTIMATORS) -> str:
    """The estimator's name, aliases resolved; ValueError naming the choices if it is not one of ``allowed``."""
    name = ESTIMATOR_ALIASES.get(estimator, estimator)
    if name not in allowed:
        raise ValueError(f"estimator must be one of {', '.join(allowed)}, got {estimator!r}")
    return name


def check_sigma(sigma: str) -> str:
    """``sigma`` if it is one of :data:`SIGMA_METHODS`, else ValueError naming them."""
    if sigma not in SIGMA_METHODS:
        raise ValueError(f"sigma must be one of {', '.join(SIGMA_METHODS)}, got {sigma!r}")
    return sigma


def check_creep_time(creep_time_s: float | None) -> float | None:
    """The line's creep time constant τ (s) measured apart, or None (τ chosen from the record);
    ValueError for a τ that is not a finite positive number of seconds."""
    if creep_time_s is None:
        return None
    try:
        tau = float(creep_time_s)
    except (TypeError, ValueError):
        tau = math.nan
    if not (math.isfinite(tau) and tau > 0):
        raise ValueError(f"creep time constant must be a positive number of seconds, got {creep_time_s!r}")
    return tau


def creep_refusal(name: str) -> str:
    """Why estimator ``name`` takes no creep time held: outputerror fits its own, the linear ones have no creep."""
    return "fits its own creep time" if name == "outputerror" else "has no creep term"


def check_variable_options(estimator: str, creep_time_s: float | None = None) -> str:
    """Table 2's estimator name (aliases resolved) and the creep time checked together, before any
    data is read: what a campaign request (CLI, REST) validates before the robot moves. Raises
    ValueError saying which value is wrong and why."""
    name = check_estimator(estimator, VARIABLE_ESTIMATORS)
    check_creep_time(creep_time_s)
    if creep_time_s is not None and name not in ("loadfriction", "auto"):
        raise ValueError(f"a creep time applies to the load-friction fit (estimator loadfriction or auto); "
                         f"estimator {name!r} {creep_refusal(name)}")
    return name
