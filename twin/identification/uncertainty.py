"""Standard deviations of identified parameters that survive coloured residuals.

Eq. 50 (σ_ρ²(WᵀW)⁻¹) assumes white, independent residuals. The identification's residuals are
not: the data are low-pass filtered (1-2 Hz) and decimated to 31.25 Hz, so neighbouring samples
share their noise, and what the model leaves out (friction shape, creep) follows the trajectory,
i.e. is correlated over seconds. Eq. 50 then reports a σ several times too small (issue 17:
errors of 2.4-5.4 σ). The heteroskedasticity and autocorrelation consistent (HAC) covariance of
Newey & West (Econometrica 1987) keeps the sandwich form of any linear estimator v = B·Y,

    C = B·S·Bᵀ,   S = Σ_{|l| ≤ L} w_l Σ_t g_t g_{t−l}ᵀ,   w_l = 1 − |l|/(L + 1) (Bartlett),

with g_t the sum of b_r·ρ_r over the rows r of identification instant t (several equations per
instant: joints, cables). L is the number of lags over which residuals are correlated: chosen
from the residuals themselves (:func:`correlation_lag`), at least the filter's memory.
Pure functions on arrays.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# L stays below this fraction of the instants (unless min_lag, the filter's memory, is longer: the
# Estimate then flags its σ as unreliable, estimators.Estimate.sigma_unreliable): the sum needs many lags' worth of data.
MAX_LAG_FRACTION = 0.2
CORRELATION_FLOOR = 0.1  # residual autocorrelation below which two instants count as independent
LAG_FACTOR = 2  # Bartlett weights halve the covariance at half the lag: sum over twice the correlation length


def instant_sums(rows: FloatArray, sample_index: IntArray, n_samples: int) -> FloatArray:
    """Σ of ``rows`` (r, p) over the rows of each instant: (n_samples, p)."""
    out = np.zeros((n_samples, rows.shape[1]))
    np.add.at(out, sample_index, rows)
    return out


def correlation_lag(residual: FloatArray, sample_index: IntArray, n_samples: int, min_lag: int = 1,
                    n_used: int | None = None) -> int:
    """Lags (instants) until the residuals' autocorrelation first drops below 0.1, each equation
    (row position within its instant) taken separately and the largest kept; at least ``min_lag``,
    at most :data:`MAX_LAG_FRACTION` of the instants (or ``min_lag`` if it is more): of the
    ``n_samples`` the indices run over, or of ``n_used`` if fewer are used (a record's gaps)."""
    cap = max(min_lag, int(MAX_LAG_FRACTION * min(n_samples, n_samples if n_used is None else n_used)))
    order = np.argsort(sample_index, kind="stable")
    idx, res = sample_index[order], residual[order]
    # position of each row within its instant: equation j of instant t
    starts = np.r_[0, np.flatnonzero(np.diff(idx)) + 1]
    pos = np.arange(len(idx)) - np.repeat(starts, np.diff(np.r_[starts, len(idx)]))
    lag = min_lag
    for j in np.unique(pos):
        series = np.zeros(n_samples)
        series[idx[pos == j]] = res[pos == j]
        series -= series.mean()
        var = float(series @ series)
        if var <= 0:
            continue
        spec = np.fft.rfft(series, 2 * n_samples)
        acf = np.fft.irfft(spec * np.conj(spec))[: cap + 1] / var
        below = np.flatnonzero(acf < CORRELATION_FLOOR)
        lag = max(lag, LAG_FACTOR * int(below[0]) if len(below) else cap)
    return int(min(lag, cap))


def newey_west(scores: FloatArray, lag: int) -> FloatArray:
    """S = Σ_{|l| ≤ L} (1 − |l|/(L + 1)) Σ_t g_t g_{t−l}ᵀ for per-instant scores g (n, p)."""
    S = scores.T @ scores
    for lag_i in range(1, lag + 1):
        G = scores[lag_i:].T @ scores[:-lag_i]
        S += (1.0 - lag_i / (lag + 1.0)) * (G + G.T)
    return S


def hac_covariance(B: FloatArray, residual: FloatArray, sample_index: IntArray, n_samples: int,
                   lag: int | None = None, min_lag: int = 1, n_used: int | None = None) -> tuple[FloatArray, int]:
    """Covariance of v = B·Y (B: (p, r)) with residuals ρ (r,) correlated within and across
    instants, and the lag used. ``lag`` None: :func:`correlation_lag` (at least ``min_lag``; its
    cap on ``n_used`` instants if given)."""
    if lag is None:
        lag = correlation_lag(residual, sample_index, n_samples, min_lag, n_used)
    scores = instant_sums((B * residual).T, sample_index, n_samples)
    dof = len(residual) / max(len(residual) - B.shape[0], 1)  # small-sample correction, as eq. 50's r − n_p
    return dof * newey_west(scores, lag), int(lag)  # v − v_true = Σ_t g_t


def white_covariance(B: FloatArray, residual: FloatArray) -> FloatArray:
    """Eq. 50's assumption for a linear estimator v = B·Y: residuals white with one variance,
    C = σ_ρ²·B·Bᵀ (σ_ρ² = ‖ρ‖²/(r − n_p)); for least squares B·Bᵀ = (WᵀW)⁻¹."""
    r, p = len(residual), B.shape[0]
    return float(residual @ residual) / (r - p) * (B @ B.T)


def interval(values: FloatArray, sigma: FloatArray, k: float = 2.0) -> tuple[FloatArray, FloatArray]:
    """±k·σ confidence interval (k = 2: about 95 % for a normal estimate)."""
    return values - k * sigma, values + k * sigma

