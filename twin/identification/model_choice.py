"""Which Table 2 estimator a campaign needs: the paper's eqs. 54-55 or the load-friction model.

The load-friction model (twin.identification.loadfriction) contains eq. 54-55's as a special
case: with μ = 0 (no friction per newton of tension) and β = 0 (no creep) its tension rows are the
paper's, eq. 37's friction a·F₀ included. So whether a campaign needs it is a test of the nested
hypothesis H₀: μ(j) = β(j) = 0 for every cable, on the load-friction fit itself (a Wald test)::

    χ² = Σ_j (μ_j/σ_μj)² + (β_j/σ_βj)²,   on 2·n_cables degrees of freedom,

σ the fit's HAC σ (the cross-covariance of μ and β is left out: the Estimate keeps σ only). β is
bounded at 0, so a β held there adds 0 and its degree of freedom makes the test conservative.

Why a test and not one estimator for all: on a robot whose friction grows with the load (the
prototype's open-loop forces; the twin's robot truth) eq. 55's tension is wrong and IDIM-IV comes
out 10-23 % low in k, while the load-friction fit is within 10 % on most campaigns. Where the
paper's model holds (the damping-only truth) IDIM-IV is the better estimator: the load-friction fit's
extra parameters cost it k(4) +10…+20 % on some campaigns (docs/identification-coverage.md).
Measured χ²: 5 - 16 on damping-only campaigns, 270 - 5200 on the robot truth's; the threshold
(p = 0.001, 26.1 on 8 dof) lies between with a wide margin on both sides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from twin.identification.estimators import Estimate

P_THRESHOLD = 1e-3  # below it the paper's model is rejected: its omissions are not the noise
TESTED = ("mu", "beta")  # loadfriction.SYMBOLS that are 0 in the paper's model


@dataclass(frozen=True)
class ModelTest:
    """The Wald test of H₀ "μ = β = 0 on every cable" (module docstring). ``chi2`` the statistic,
    ``dof`` its degrees of freedom, ``p`` the probability of a χ² this large under H₀."""

    chi2: float
    dof: int
    p: float

    @property
    def rejects_paper_model(self) -> bool:
        return self.p < P_THRESHOLD

    def describe(self) -> str:
        verdict = "rejected" if self.rejects_paper_model else "kept"
        return (f"the paper's model (μ = β = 0: no friction growing with the load, no creep) {verdict}: "
                f"χ² = {self.chi2:.1f} on {self.dof} dof, p = {self.p:.2g} (threshold {P_THRESHOLD:g})")


def paper_model_test(load_friction: Estimate) -> ModelTest:
    """The test on a load-friction estimate (twin.identification.loadfriction.fit_load_friction's
    ``estimate``). Raises ValueError when it lacks μ or β (not a load-friction estimate)."""
    z2, dof = 0.0, 0
    for symbol in TESTED:
        idx = [i for i, n in enumerate(load_friction.names) if n.split("(")[0] == symbol]
        if not idx:
            raise ValueError(f"not a load-friction estimate: no {symbol!r} among {load_friction.names}")
        v, sd = load_friction.values[idx], load_friction.sigma[idx]
        ok = np.isfinite(v) & np.isfinite(sd) & (sd > 0)
        # a parameter with no σ (held at a bound, not estimated) tells nothing: 0 to χ², its dof kept
        z2 += float(np.sum((v[ok] / sd[ok]) ** 2))
        dof += len(idx)
    return ModelTest(chi2=z2, dof=dof, p=float(stats.chi2.sf(z2, dof)))
