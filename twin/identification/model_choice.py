"""Which Table 2 estimator a campaign needs: the paper's eqs. 54-55 or the load-friction model.

The load-friction model (twin.identification.loadfriction) contains eq. 54-55's as a special
case: with μ = 0 (no friction per newton of tension) and β = 0 (no creep) its tension rows are the
paper's, eq. 37's friction a·F₀ included. What breaks eq. 55's tension on a geared, pulley-routed
robot is the friction growing with the load its motor carries (μ > 0: pulley and gear losses).
So the choice is a test of H₀ "μ_j = 0 on every cable" against "μ > 0", on the load-friction fit
itself: the cables' μ pooled with their precision, one-sided::

    z = Σ_j (μ_j/σ_j²) / √(Σ_j 1/σ_j²),   p = 1 − Φ(z),

on the fit *without* the gear's meshing loss (``gear=(0, 0)``), in which eqs. 54-55 are the special
case μ = β = 0. The fit that holds the loss (the estimate `auto` then reports) does not contain
them: on forces of the paper's model its μ came out 4.5σ away from −(g_f + g_b)/2, the value that
would make its slopes the paper's, because the loss divides the winding rows' friction offset too.

σ_j the fit's HAC σ of μ_j (β, F₀, c_f, k, λ estimated beside it). The creep β is a nuisance of
the fit, not tested: under camera noise the fit can give a soft cable a spurious creep (β(4) at
4.4σ on a damping-only bus campaign with the white-noise camera, where eqs. 54-55 hold), while μ
stays at 0 there. Pooling asks one question of all cables, so one cable's outlier cannot decide.

Why a test and not one estimator for all: on a robot whose friction grows with the load (the
prototype's open-loop forces; the twin's robot truth) eq. 55's tension is wrong and IDIM-IV comes
out 10-23 % low in k, while the load-friction fit is within 10 % on most campaigns. Where the
paper's model holds (the damping-only truth) IDIM-IV is the better estimator: the load-friction
fit's extra parameters cost it k(4) +10…+20 % on some campaigns (docs/identification-coverage.md,
"The default estimator: `auto`", which gives the z measured on both truths).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from scipy import stats

from twin.identification.estimators import Estimate

P_THRESHOLD = 1e-3  # below it the paper's model is rejected: its friction does grow with the load
# The test's fit holds the creep time at one value of loadfriction.TAUS_S instead of choosing it: μ
# hardly depends on τ (docs/identification/model_choice_scan.py --tau-grid: z within 0.5 of the full
# fit's on damping-only and model-truth campaigns, 13.5 against 15.2 on a robot-truth one) and one τ
# costs a fifth of the grid: `auto` then fits the estimate itself,
# the gear's loss held, only after a rejection.
TEST_TAU_S = 2.0
# Above this damping force (N) on any cable the pose is not quasi-static and `auto` keeps the
# load-friction fit instead of the output error (:func:`damping_check`). Between what the test's fit
# finds on law 1's campaigns with a real line's damping (40 N·s/m: at most 0.6 N) and with the
# paper's 3000 N·s/m (2-5 N), where the output error's λ came out 50-80 % high
# (docs/identification-coverage.md, "`auto` takes the output error").
QUASI_STATIC_DAMPING_N = 1.0


@dataclass(frozen=True)
class ModelTest:
    """The one-sided test of H₀ "μ = 0 on every cable" (module docstring): ``mu`` the pooled μ
    (dimensionless: newtons of friction per newton of tension) and its ``sigma``, ``z`` = mu/sigma,
    ``p`` the probability of a z this large under H₀, ``cables`` how many cables had a σ."""

    mu: float
    sigma: float
    z: float
    p: float
    cables: int

    @property
    def rejects_paper_model(self) -> bool:
        return self.p < P_THRESHOLD

    def describe(self) -> str:
        verdict = "rejected" if self.rejects_paper_model else "kept"
        return (f"the paper's model (no friction growing with the load) {verdict}: pooled μ (fit without the gear's loss) = "
                f"{self.mu:.3f} ± {self.sigma:.3f} over {self.cables} cables, z = {self.z:.1f}, one-sided "
                f"p = {self.p:.2g} (threshold {P_THRESHOLD:g})")


def paper_model_test(load_friction: Estimate) -> ModelTest:
    """The test on a load-friction estimate fitted without the gear's loss
    (twin.identification.loadfriction.fit_load_friction(…, gear=(0, 0))'s ``estimate``). Raises
    ValueError when it has no μ with a σ (not a load-friction estimate)."""
    idx = [i for i, n in enumerate(load_friction.names) if n.split("(")[0] == "mu"]
    v, sd = load_friction.values[idx], load_friction.sigma[idx]
    ok = np.isfinite(v) & np.isfinite(sd) & (sd > 0)
    if not ok.any():
        raise ValueError(f"not a load-friction estimate: no 'mu' with a σ among {load_friction.names}")
    w = 1.0 / sd[ok] ** 2
    mu, sigma = float(np.sum(w * v[ok]) / np.sum(w)), float(1.0 / np.sqrt(np.sum(w)))
    z = mu / sigma
    return ModelTest(mu=mu, sigma=sigma, z=z, p=float(stats.norm.sf(z)), cables=int(ok.sum()))


@dataclass(frozen=True)
class DampingCheck:
    """Whether the neck's pose is quasi-static on this record, the output-error fit's assumption
    (twin.identification.outputerror: its equilibrium holds the line's damping at 0). ``force_N``
    per cable: the damping force the load-friction fit allows, its c_a's upper 2σ bound times the
    record's rms stretch rate ẋ_c (eq. 27), N."""

    force_N: tuple[float, ...]

    @property
    def quasi_static(self) -> bool:
        return max(self.force_N) <= QUASI_STATIC_DAMPING_N

    def describe(self) -> str:
        verdict = "quasi-static" if self.quasi_static else "not quasi-static"
        return (f"the line's damping force (c_a + 2σ)·rms ẋ_c ≤ {max(self.force_N):.2g} N, {verdict} "
                f"(threshold {QUASI_STATIC_DAMPING_N:g} N)")


def damping_check(load_friction: Estimate, x_c_dot: np.ndarray) -> DampingCheck:
    """:class:`DampingCheck` from a load-friction estimate (its c_a(j) and σ) and the record's stretch
    rates ``x_c_dot`` (m/s, (n, n_cables): processing.Processed.x_c_dot). A c_a without a finite σ
    counts as unbounded (not quasi-static). Raises ValueError when the estimate has no c_a."""
    idx = [i for i, n in enumerate(load_friction.names) if n.split("(")[0] == "c_a"]
    if not idx:
        raise ValueError(f"not a load-friction estimate: no 'c_a' among {load_friction.names}")
    upper = load_friction.values[idx] + 2 * np.where(np.isfinite(load_friction.sigma[idx]), load_friction.sigma[idx],
                                                     np.inf)
    rate = np.sqrt(np.mean(np.asarray(x_c_dot, dtype=float) ** 2, axis=0))
    return DampingCheck(tuple(float(f) for f in np.maximum(upper, 0.0) * rate))


def auto_choice(estimator_text: str) -> tuple[str, float | None]:
    """(the estimator ``"auto"`` chose, its test's z) read back from an Estimate's ``estimator`` text
    (pipeline._identify_variable_auto writes "auto → loadfriction (… z = 17.2 …)"; JSON reports keep
    only that text). Another estimator's text gives (its name before any parenthesis, None)."""
    if not estimator_text.startswith("auto → "):
        return estimator_text.split(" (")[0], None
    m = re.search(r"z = (-?[0-9.]+)", estimator_text)
    return estimator_text.split(" ", 3)[2], float(m.group(1)) if m else None
