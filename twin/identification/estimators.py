"""Estimators of the linear identification models W·v + ρ = Y (3-X paper eqs. 48-50).

Pure functions on (W, Y): they know nothing of cables or joints (twin.identification.regressors
builds W and Y).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from twin.identification.processing import IdentificationError

FloatArray = NDArray[np.float64]

DEFAULT_THRESHOLD = 0.10  # relative σ above which a parameter is badly identified
RANK_TOL = 1e-7  # relative singular value below which the (column-scaled) regressor is rank-deficient


@dataclass(frozen=True, eq=False)
class Estimate:
    """Least-squares estimate of one identification model (eqs. 48-50).

    names: parameter names like ``"f_s(1)"``, ``"k(2)"``, ``"lambda(3)"``, ``"c_a(4)"``;
    values, sigma: SI units of each parameter; relative_sigma: σ_i/|v_i| (fraction, eq. 50);
    condition_number: of the observation matrix W; residual_norm: ‖Y − Wv‖ (units of Y);
    n_rows: r, rows of W; n_samples: identification instants used.
    """

    method: str
    equations: str
    names: tuple[str, ...]
    values: FloatArray
    sigma: FloatArray
    relative_sigma: FloatArray
    condition_number: float
    residual_norm: float
    n_rows: int
    n_samples: int
    threshold: float = DEFAULT_THRESHOLD
    estimator: str = "least squares"

    @property
    def out_of_range(self) -> NDArray[np.bool_]:
        """Values no physical cable or motor can have: k ≤ 0, or f_s, λ, c_a < 0. A model that
        does not fit (the linear one on variable-stiffness cables) buys its fit with such values,
        often with a small σ: Table 1's c_a(3) = −218 N·s/m is one."""
        symbols = np.array([n.split("(")[0] for n in self.names])
        return np.where(symbols == "k", self.values <= 0.0, self.values < 0.0)

    @property
    def badly_identified(self) -> NDArray[np.bool_]:
        """Relative σ above the threshold (or not finite), or out of physical range: never used
        silently."""
        r = self.relative_sigma
        return ~np.isfinite(r) | (r > self.threshold) | self.out_of_range

    def reason(self, i: int) -> str:
        """Why parameter ``i`` is badly identified ("" if it is not)."""
        r = self.relative_sigma[i]
        if not np.isfinite(r) or r > self.threshold:
            return f"badly identified, relative σ {100 * r:.1f} % > {100 * self.threshold:g} %"
        if self.out_of_range[i]:
            return "outside its physical range"
        return ""

    def vector(self, symbol: str) -> FloatArray:
        """Values of one symbol in cable order, e.g. ``vector("k")`` -> (n_cables,)."""
        idx = [i for i, n in enumerate(self.names) if n.split("(")[0] == symbol]
        if not idx:
            raise KeyError(f"{self.method} estimate has no parameter {symbol!r} (has {sorted({n.split('(')[0] for n in self.names})})")
        return self.values[idx]

    def flags(self, symbol: str) -> NDArray[np.bool_]:
        idx = [i for i, n in enumerate(self.names) if n.split("(")[0] == symbol]
        return self.badly_identified[idx]

    def rows(self) -> list[dict[str, Any]]:
        """One dict per parameter: name, value, sigma, relative_sigma, badly_identified, reason."""
        return [
            {"name": n, "value": float(v), "sigma": float(s), "relative_sigma": float(r), "badly_identified": bool(b),
             "reason": self.reason(i)}
            for i, (n, v, s, r, b) in enumerate(zip(self.names, self.values, self.sigma, self.relative_sigma,
                                                    self.badly_identified))
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method, "equations": self.equations, "parameters": self.rows(),
            "condition_number": self.condition_number, "residual_norm": self.residual_norm,
            "n_rows": self.n_rows, "n_samples": self.n_samples, "threshold": self.threshold,
            "estimator": self.estimator,
        }


def least_squares(
    W: FloatArray, Y: FloatArray, names: tuple[str, ...], *, method: str, equations: str,
    n_samples: int, threshold: float = DEFAULT_THRESHOLD, instruments: FloatArray | None = None,
) -> Estimate:
    """Solve W·v + ρ = Y (eq. 48) by v = W⁺Y (eq. 49) with σ's from eq. 50.

    With ``instruments`` Φ (same shape as W) the instrumental-variable solution
    v = (ΦᵀW)⁻¹ΦᵀY is returned instead, with C_X = σ_ρ²(ΦᵀW)⁻¹ΦᵀΦ(ΦᵀW)⁻ᵀ (eq. 50's IV form).
    Raises :class:`IdentificationError` when r ≤ n_p, W or Y is not finite, or W is
    rank-deficient (a parameter, or a combination, that the trajectory does not excite); the
    message names the parameters involved.
    """
    r, n_p = W.shape
    if r <= n_p:
        raise IdentificationError(f"{method}: {r} equations for {n_p} parameters; need r > n_p (eq. 48)")
    if not (np.all(np.isfinite(W)) and np.all(np.isfinite(Y))):
        raise IdentificationError(f"{method}: the observation matrix or vector has NaN/inf entries")
    scale = np.linalg.norm(W, axis=0)
    dead = scale <= 1e-300
    if dead.any():
        raise IdentificationError(
            f"{method}: regressor is rank-deficient, {', '.join(np.array(names)[dead])} never excited "
            "(zero column: did the motors move / were the cables stretched?)"
        )
    # Rank on the column-scaled matrix: the raw W mixes metres and newtons.
    _, s_scaled, Vt_scaled = np.linalg.svd(W / scale, full_matrices=False)
    if s_scaled[-1] < RANK_TOL * s_scaled[0]:
        weak = np.abs(Vt_scaled[-1])
        involved = np.array(names)[weak > 0.3 * weak.max()]
        raise IdentificationError(
            f"{method}: regressor is rank-deficient (scaled condition number "
            f"{s_scaled[0] / max(s_scaled[-1], 1e-300):.3g}); the trajectory does not excite {', '.join(involved)}"
        )
    U, s, Vt = np.linalg.svd(W, full_matrices=False)
    if instruments is None:
        v = Vt.T @ ((U.T @ Y) / s)
        res = Y - W @ v
        cov_unit = (Vt.T / s**2) @ Vt  # (WᵀW)⁻¹ through the SVD
    else:
        Phi = instruments
        A = Phi.T @ W
        try:
            A_inv = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            raise IdentificationError(f"{method}: instruments are uncorrelated with the regressor (ΦᵀW singular)") from None
        v = A_inv @ (Phi.T @ Y)
        res = Y - W @ v
        cov_unit = A_inv @ (Phi.T @ Phi) @ A_inv.T
    sigma_rho2 = float(res @ res) / (r - n_p)
    sigma = np.sqrt(np.abs(np.diag(cov_unit)) * sigma_rho2)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = sigma / np.abs(v)
    return Estimate(
        method=method, equations=equations, names=names, values=v, sigma=sigma, relative_sigma=rel,
        condition_number=float(s[0] / s[-1]), residual_norm=float(np.sqrt(res @ res)),
        n_rows=r, n_samples=n_samples, threshold=threshold,
        estimator="least squares" if instruments is None else "instrumental variables",
    )
