"""Estimators of the linear identification models W·v + ρ = Y (3-X paper eqs. 48-50).

Pure functions on (W, Y): they know nothing of cables or joints (twin.identification.regressors
builds W and Y).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from twin.identification import uncertainty
from twin.identification.options import ESTIMATOR_NAMES, ESTIMATORS, check_sigma
from twin.identification.processing import IdentificationError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

DEFAULT_THRESHOLD = 0.10  # relative σ above which a parameter is badly identified
#: Relative σ (a fraction) from which it is shown as ">1000%": none of its digits means anything
#: then, and printed whole (1e29 % for a parameter the record does not determine, 30 characters)
#: it broke the tables' columns (user audit of 2026-11-30).
RELATIVE_SIGMA_SHOWN_MAX = 10.0


def relative_sigma_percent(r: float) -> str:
    """A relative σ ``r`` (a fraction, eq. 50) as a percentage of at most 7 characters for the
    tables' fixed columns: "9.94%", "260.32%", ">1000%" from :data:`RELATIVE_SIGMA_SHOWN_MAX` on,
    "inf%" (held at a bound of 0), "nan%"."""
    if math.isfinite(r) and r >= RELATIVE_SIGMA_SHOWN_MAX:
        return f">{100 * RELATIVE_SIGMA_SHOWN_MAX:.0f}%"
    return f"{100 * r:.2f}%"
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
    estimator: str = "ordinary least squares"
    sigma_method: str = "eq. 50 (white residuals)"
    hac_lag: int = 0  # instants over which residuals were taken as correlated (0: white)
    active_bounds: tuple[str, ...] = ()  # parameters the bounded solution holds at a physical bound

    @property
    def ci_low(self) -> FloatArray:
        """Lower end of the ±2σ confidence interval (about 95 %)."""
        return self.values - 2.0 * self.sigma

    @property
    def ci_high(self) -> FloatArray:
        return self.values + 2.0 * self.sigma

    @property
    def at_bound(self) -> NDArray[np.bool_]:
        return np.array([n in self.active_bounds for n in self.names], dtype=bool)

    @property
    def out_of_range(self) -> NDArray[np.bool_]:
        """Values no physical cable or motor can have: k ≤ 0, or f_s, λ, c_a < 0. A model that
        does not fit (the linear one on variable-stiffness cables) buys its fit with such values,
        often with a small σ: Table 1's c_a(3) = −218 N·s/m is one."""
        symbols = np.array([n.split("(")[0] for n in self.names])
        physical = np.isin(symbols, list(_LOWER))  # others (a friction offset F_0, a slope mu) may be < 0
        return physical & np.where(symbols == "k", self.values <= 0.0, self.values < 0.0)

    @property
    def sigma_unreliable(self) -> bool:
        """The HAC lag spans more than uncertainty.MAX_LAG_FRACTION of the instants: the filter's
        memory (the lag's floor, rate/cutoff) is long for the record. Newey-West's σ is then biased
        low whatever the residuals (about half the true σ at a lag of half the instants: the
        weighted sums of the scores over windows that long nearly cancel), so no σ of this
        estimate can be trusted."""
        return self.hac_lag > uncertainty.MAX_LAG_FRACTION * self.n_samples

    @property
    def badly_identified(self) -> NDArray[np.bool_]:
        """Relative σ above the threshold (or not finite), out of physical range, or a σ that
        cannot be trusted (:attr:`sigma_unreliable`): never used silently."""
        r = self.relative_sigma
        return ~np.isfinite(r) | (r > self.threshold) | self.out_of_range | self.at_bound | self.sigma_unreliable

    def reason(self, i: int) -> str:
        """Why parameter ``i`` is badly identified ("" if it is not)."""
        r = self.relative_sigma[i]
        if self.values[i] == 0.0 and self.sigma[i] == 0.0:  # e.g. the output error's c_a, quasi-static
            return "not estimated: this estimator holds it at 0"
        if self.sigma_unreliable:
            return (f"σ unreliable: residuals taken as correlated over {self.hac_lag} of {self.n_samples} instants "
                    f"(> {100 * uncertainty.MAX_LAG_FRACTION:g} %), the σ would be too small; record longer or "
                    "with a higher filter cutoff")
        if self.at_bound[i]:  # first: at a bound of 0 its relative σ is infinite by construction
            return "held at its physical bound (the data pull it beyond)"
        if not np.isfinite(r) or r > self.threshold:
            shown = f"{100 * r:.1f}" if not r >= RELATIVE_SIGMA_SHOWN_MAX else f"{100 * r:.3g}"  # 1.56e+29, not 30 digits
            return f"badly identified, relative σ {shown} % > {100 * self.threshold:g} %"
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
        """One dict per parameter: name, value, sigma, relative_sigma, ±2σ interval (ci_low, ci_high),
        at_bound, badly_identified, reason."""
        return [
            {"name": n, "value": float(v), "sigma": float(s), "relative_sigma": float(r), "badly_identified": bool(b),
             "ci_low": float(v - 2 * s), "ci_high": float(v + 2 * s), "at_bound": n in self.active_bounds,
             "reason": self.reason(i)}
            for i, (n, v, s, r, b) in enumerate(zip(self.names, self.values, self.sigma, self.relative_sigma,
                                                    self.badly_identified))
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method, "equations": self.equations, "parameters": self.rows(),
            "condition_number": self.condition_number, "residual_norm": self.residual_norm,
            "n_rows": self.n_rows, "n_samples": self.n_samples, "threshold": self.threshold,
            "estimator": self.estimator, "sigma_method": self.sigma_method, "hac_lag": self.hac_lag,
            "active_bounds": list(self.active_bounds),
        }


POSITIVE = 1e-9  # lower bound standing for "> 0" (k, f_s) in lsq_linear, which needs closed bounds

# Physical range of each symbol: k > 0, f_s > 0; λ, c_a ≥ 0 (issue 17). Others are free.
_LOWER = {"k": POSITIVE, "f_s": POSITIVE, "lambda": 0.0, "c_a": 0.0}


def physical_bounds(names: tuple[str, ...]) -> tuple[FloatArray, FloatArray]:
    """(lower, upper) bounds of each parameter from its symbol (``"k(2)"`` → k > 0)."""
    lower = np.array([_LOWER.get(n.split("(")[0], -np.inf) for n in names])
    return lower, np.full(len(names), np.inf)


def _check_regressor(W: FloatArray, Y: FloatArray, names: tuple[str, ...], method: str) -> None:
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


def _group_weights(W: FloatArray, Y: FloatArray, groups: IntArray) -> FloatArray:
    """IDIM-WLS row weights (Gautier & Poignet 2001, BIRDy): each group of equations (a joint's, a
    cable's) weighted by the inverse of its residual standard deviation in an OLS fit, so that
    equations in newtons and in newton-metres, or a noisy cable and a quiet one, count alike."""
    v = np.linalg.lstsq(W, Y, rcond=None)[0]
    res = Y - W @ v
    w = np.ones(len(Y))
    for g in np.unique(groups):
        sel = groups == g
        sd = float(np.sqrt(np.mean(res[sel] ** 2)))
        w[sel] = 1.0 / sd if sd > 0 else 1.0
    return w


def least_squares(
    W: FloatArray, Y: FloatArray, names: tuple[str, ...], *, method: str, equations: str,
    n_samples: int, threshold: float = DEFAULT_THRESHOLD, instruments: FloatArray | None = None,
    estimator: str | None = None, groups: IntArray | None = None, sample_index: IntArray | None = None,
    bounds: tuple[FloatArray, FloatArray] | None = None, sigma: str = "hac", min_lag: int = 1,
) -> Estimate:
    """Solve W·v + ρ = Y (eq. 48) with one of :data:`ESTIMATORS`, within ``bounds``.

    - ``"ols"``: v = W⁺Y (eq. 49).
    - ``"wls"``: rows scaled by the inverse residual σ of their ``groups`` (:func:`_group_weights`).
    - ``"iv"``: v = (ΦᵀW)⁻¹ΦᵀY with ``instruments`` Φ (same shape as W), consistent when W is
      noisy as long as Φ is correlated with W and not with ρ.
    ``estimator`` None: "iv" with instruments, else "ols". Every estimator is linear, v = B·Y, so
    its covariance is the sandwich of :mod:`twin.identification.uncertainty`: ``sigma="hac"``
    (default) with residuals correlated within an instant (``sample_index``: the instant of each
    row) and over ``min_lag``+ instants, or ``"white"`` (eq. 50 as printed). ``bounds`` (lower,
    upper): a solution outside them is replaced by the bounded one (scipy.optimize.lsq_linear on
    the weighted rows, or on the rows projected onto the instruments for IV: two-stage least
    squares); the parameters it holds at a bound are listed in ``Estimate.active_bounds`` and
    flagged. Raises :class:`IdentificationError` when r ≤ n_p, W or Y is not finite, or W is
    rank-deficient (a parameter, or a combination, that the trajectory does not excite); the
    message names the parameters involved.
    """
    est_name = estimator or ("iv" if instruments is not None else "ols")
    if est_name not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {est_name!r}")
    check_sigma(sigma)
    if est_name == "iv" and (instruments is None or instruments.shape != W.shape):
        raise ValueError("the IV estimator needs instruments shaped like W")
    _check_regressor(W, Y, names, method)
    r = W.shape[0]
    w = _group_weights(W, Y, groups) if est_name == "wls" and groups is not None else np.ones(r)
    Ww, Yw = W * w[:, None], Y * w
    if est_name == "iv":
        assert instruments is not None
        Phi = instruments * w[:, None]
        try:
            A_inv = np.linalg.inv(Phi.T @ Ww)
        except np.linalg.LinAlgError:
            raise IdentificationError(f"{method}: instruments are uncorrelated with the regressor (ΦᵀW singular)") from None
        B = A_inv @ Phi.T
    else:
        U, s_w, Vt = np.linalg.svd(Ww, full_matrices=False)
        B = (Vt.T / s_w) @ U.T  # W⁺ through the SVD
    v = B @ Yw
    active: tuple[str, ...] = ()
    if bounds is not None:
        lo, hi = (np.asarray(b, dtype=float) for b in bounds)
        if np.any(v < lo) or np.any(v > hi):
            from scipy.optimize import lsq_linear

            A, b = Ww, Yw
            if est_name == "iv":
                Q, _ = np.linalg.qr(Phi)
                A, b = Q.T @ Ww, Q.T @ Yw
            col = np.linalg.norm(A, axis=0)  # scaled columns: metres and newtons in one solve
            sol = lsq_linear(A / col, b, bounds=(lo * col, hi * col), method="bvls", tol=1e-12)
            v = sol.x / col
            active = tuple(n for n, a in zip(names, sol.active_mask) if a != 0)
    res_w = Yw - Ww @ v
    idx = np.arange(r) if sample_index is None else np.asarray(sample_index)
    if sigma == "hac":
        cov, lag = uncertainty.hac_covariance(B, res_w, idx, int(idx.max()) + 1, min_lag=min_lag, n_used=n_samples)
        sigma_method = f"HAC (Newey-West, Bartlett, {lag} lags)"
    else:
        cov, lag = uncertainty.white_covariance(B, res_w), 0
        sigma_method = "eq. 50 (white residuals)"
    sd = np.sqrt(np.abs(np.diag(cov)))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = sd / np.abs(v)
    s_raw = np.linalg.svd(W, compute_uv=False)
    res = Y - W @ v
    return Estimate(
        method=method, equations=equations, names=names, values=v, sigma=sd, relative_sigma=rel,
        condition_number=float(s_raw[0] / s_raw[-1]), residual_norm=float(np.sqrt(res @ res)),
        n_rows=r, n_samples=n_samples, threshold=threshold, estimator=ESTIMATOR_NAMES[est_name],
        sigma_method=sigma_method, hac_lag=lag, active_bounds=active,
    )
