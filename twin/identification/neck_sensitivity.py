"""The neck re-simulated on the encoders, with the line's creep, and its exact parameter derivatives.

The output-error fit (twin.identification.outputerror) compares the neck's quasi-static
equilibrium, simulated on the recorded motor angles θ, with the camera's α_IP. At each instant

    F(α, c; p) = Z(α)·T(x) − g(α; s) = 0,   x = l_c(α) − l_c0 + ρ·θ − c,   T(x) = k·x/(1 − λ·x) ≥ 0

(eqs. 32, 27, 54) and the creep c of each cable relaxes towards β·x/(1 − λx) with time constant τ
(a Kelvin element, the creep stretch of loadfriction's). The creep is found by fixed-point passes:
pass m solves α^m with c^(m−1), then runs the creep recursion on X^m = x^m + c^(m−1) (c⁰ = 0).

Derivatives: finite differences of the whole simulation cost one re-simulation per parameter
(17 of them, each three Newton solves over the record). Here the implicit function theorem gives
them from the solution: per pass, ∂F/∂α·dα = −(∂F/∂p·dp + ∂F/∂c·dc^(m−1)), and dc^m follows the
creep recursion's own derivative (compiled, :func:`creep_stretch_jacobian`). ∂F/∂α and ∂l_c/∂α
come from central differences of the statics at the solution (N evaluations each way), the spring
and pulley terms from one or two statics evaluations each; everything else is closed form. Derivatives
are with respect to the fit's parameters q: log k, log λ per cable, β, log τ, log s per spring and
δr in mm (outputerror's layout).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from twin.identification.instruments import _stretch
from twin.model.numeric import Model

FloatArray = NDArray[np.float64]

ALPHA_STEP_RAD = 1e-5  # central differences of the statics in α: the model is smooth, round-off 1e-16/1e-5
SPRING_STEP = 1e-3  # relative: g is linear in each spring's rate, so any step is exact but for round-off
PULLEY_STEP_M = 1e-6  # δr's step: l_c, l_c0 and Z are smooth in the radius


@njit(cache=True)
def creep_stretch_kernel(x_total: FloatArray, lam: FloatArray, beta: float, gain: float, floor: float) -> FloatArray:
    """c (m, (n, n_cables)) of :func:`twin.identification.outputerror.creep_stretch`, compiled: at its
    equilibrium at the first sample, then c ← c + (β·ψ(X − c) − c)·gain, ψ(u) = max(u/max(1 − λu, floor), 0)."""
    n, nc = x_total.shape
    out = np.empty((n, nc))
    for j in range(nc):
        c = 0.0
        for _ in range(50):
            xx = x_total[0, j] - c
            c = beta * max(xx / max(1.0 - lam[j] * xx, floor), 0.0)
        for i in range(n):
            out[i, j] = c
            xx = x_total[i, j] - c
            c += (beta * max(xx / max(1.0 - lam[j] * xx, floor), 0.0) - c) * gain
    return out


@njit(cache=True)
def _psi(u: float, lam: float, floor: float) -> tuple[float, float, float]:
    """ψ(u) = max(u/max(1 − λu, floor), 0) and its derivatives in u and λ."""
    den = 1.0 - lam * u
    if den > floor:
        v = u / den
        if v <= 0.0:
            return 0.0, 0.0, 0.0
        return v, 1.0 / (den * den), u * u / (den * den)
    v = u / floor
    if v <= 0.0:
        return 0.0, 0.0, 0.0
    return v, 1.0 / floor, 0.0


@njit(cache=True)
def creep_stretch_jacobian(x_total: FloatArray, dx_total: FloatArray, lam: FloatArray, beta: float, gain: float,
                           dgain_dlogtau: float, floor: float, i_lam: int, i_beta: int, i_tau: int) -> FloatArray:
    """dc/dq ((n, n_cables, P)) of :func:`creep_stretch_kernel`'s c, given dX/dq (``dx_total``) and
    that q holds log λ_j at ``i_lam`` + j, β at ``i_beta`` and log τ at ``i_tau``
    (dgain/dlog τ = ``dgain_dlogtau``). The initial fixed point by the implicit function theorem,
    then the recursion's own derivative, step by step."""
    n, nc, P = dx_total.shape
    dout = np.empty((n, nc, P))
    for j in range(nc):
        lj = lam[j]
        c = 0.0
        for _ in range(50):
            xx = x_total[0, j] - c
            c = beta * max(xx / max(1.0 - lj * xx, floor), 0.0)
        # c = β·ψ(X₀ − c): dc·(1 + β·ψ') = β·ψ'·dX₀ + ψ·dβ + β·ψ_λ·dλ
        psi, dpsi, dpsi_l = _psi(x_total[0, j] - c, lj, floor)
        dc = beta * dpsi * dx_total[0, j, :]
        dc[i_beta] += psi
        dc[i_lam + j] += beta * dpsi_l * lj
        dc /= 1.0 + beta * dpsi
        for i in range(n):
            dout[i, j, :] = dc
            psi, dpsi, dpsi_l = _psi(x_total[i, j] - c, lj, floor)
            drive = beta * psi - c
            ddrive = beta * dpsi * (dx_total[i, j, :] - dc) - dc
            ddrive[i_beta] += psi
            ddrive[i_lam + j] += beta * dpsi_l * lj
            dc = dc + ddrive * gain
            dc[i_tau] += drive * dgain_dlogtau
            c += drive * gain
    return dout


class Pass(NamedTuple):
    """One fixed-point pass of the simulation: its equilibrium α (n, N), the creep c (n, n_cables)
    it was solved with, and the total stretch X = x + c it produced."""

    alpha: FloatArray
    c_before: FloatArray
    x_total: FloatArray


class Layout(NamedTuple):
    """Where the neck's parameters sit in q (outputerror's layout)."""

    n_cables: int
    n_joints: int

    @property
    def i_lam(self) -> int:
        return self.n_cables

    @property
    def i_beta(self) -> int:
        return 2 * self.n_cables

    @property
    def i_tau(self) -> int:
        return 2 * self.n_cables + 1

    @property
    def i_s(self) -> int:
        return 2 * self.n_cables + 2

    @property
    def i_r(self) -> int:
        return 2 * self.n_cables + 2 + 2 * self.n_joints

    @property
    def size(self) -> int:
        return self.i_r + 1


def _tension(k: FloatArray, lam: FloatArray, x: FloatArray, floor: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """T(x) = max(k·x/max(1 − λx, floor), 0) (N) and its derivatives in x and in log λ."""
    den = 1.0 - lam * x
    free = den > floor
    d = np.where(free, den, floor)
    t = k * x / d
    on = t > 0
    dt_dx = np.where(on, np.where(free, k / (d * d), k / floor), 0.0)
    dt_dloglam = np.where(on & free, k * x * x / (d * d) * lam, 0.0)
    return np.maximum(t, 0.0), dt_dx, dt_dloglam


def sensitivities(m: Model, pulley_models: tuple[Model, Model], theta: FloatArray, k: FloatArray, lam: FloatArray, beta: float,
                  tau_s: float, springs: FloatArray, passes: list[Pass], h: float, floor: float,
                  ) -> tuple[FloatArray, FloatArray]:
    """(dα/dq (n, N, P) rad, dt/dq (n, n_cables, P) N) of the simulation whose passes are ``passes``,
    ``m`` its model (springs and pulleys applied), ``pulley_models`` the same with the pulley radius
    larger and smaller by PULLEY_STEP_M (l_c0 too), ``h`` the sample step (s). q: :class:`Layout`."""
    n, N = passes[0].alpha.shape
    nc = m.n_cables
    lay = Layout(nc, N)
    P = lay.size
    dc_prev = np.zeros((n, nc, P))
    dalpha = np.zeros((n, N, P))
    x = np.zeros((n, nc))
    for p_i, ps in enumerate(passes):
        a, c = ps.alpha, ps.c_before
        x, Z, g = _stretch(m, a, theta)
        x = x - c
        t, dt_dx, dt_dloglam = _tension(k, lam, x, floor)
        # ∂F/∂α and ∂l_c/∂α (= ∂x/∂α) by central differences
        J = np.empty((n, N, N))
        L = np.empty((n, nc, N))
        for i in range(N):
            da = np.zeros(N)
            da[i] = ALPHA_STEP_RAD
            xp, Zp, gp = _stretch(m, a + da, theta)
            xm, Zm, gm = _stretch(m, a - da, theta)
            tp = _tension(k, lam, xp - c, floor)[0]
            tm = _tension(k, lam, xm - c, floor)[0]
            Fp = np.einsum("nij,nj->ni", Zp, tp) - gp
            Fm = np.einsum("nij,nj->ni", Zm, tm) - gm
            J[:, :, i] = (Fp - Fm) / (2 * ALPHA_STEP_RAD)
            L[:, :, i] = (xp - xm) / (2 * ALPHA_STEP_RAD)
        # ∂F/∂q at fixed α and c
        Fq = np.zeros((n, N, P))
        Fq[:, :, :nc] = Z * t[:, None, :]  # ∂T/∂log k = T
        Fq[:, :, lay.i_lam:lay.i_lam + nc] = Z * dt_dloglam[:, None, :]
        for i in range(2 * N):  # g is linear in each spring's rate: ∂g/∂log s_i = s_i·∂g/∂s_i
            f = np.ones(2 * N)
            f[i] += SPRING_STEP
            ms = m._replace(k_left=m.k_left * f[:N], k_right=m.k_right * f[N:])
            Fq[:, :, lay.i_s + i] = -(_stretch(ms, a, theta)[2] - g) / SPRING_STEP
        # δr in mm, by central differences (g does not depend on the radius)
        (xr, Zr, _), (xl, Zl, _) = (_stretch(pm, a, theta) for pm in pulley_models)
        tr, tl = _tension(k, lam, xr - c, floor)[0], _tension(k, lam, xl - c, floor)[0]
        step_mm = 2e3 * PULLEY_STEP_M
        Fq[:, :, lay.i_r] = (np.einsum("nij,nj->ni", Zr, tr) - np.einsum("nij,nj->ni", Zl, tl)) / step_mm
        dX_dr = (xr - xl) / step_mm
        # the creep enters F as −Z·T'·dc
        Fq -= np.einsum("nij,nj,njp->nip", Z, dt_dx, dc_prev)
        dalpha = -np.linalg.solve(J, Fq)
        dX = np.einsum("njk,nkp->njp", L, dalpha)
        dX[:, :, lay.i_r] += dX_dr
        if p_i == len(passes) - 1:
            dx = dX - dc_prev
            dt = dt_dx[:, :, None] * dx
            dt[:, :, :nc] += np.eye(nc)[None] * t[:, :, None]
            dt[:, :, lay.i_lam:lay.i_lam + nc] += np.eye(nc)[None] * dt_dloglam[:, :, None]
            return dalpha, dt
        gain = 1.0 - np.exp(-h / tau_s)
        dgain = -np.exp(-h / tau_s) * h / tau_s
        dc_prev = creep_stretch_jacobian(ps.x_total, np.ascontiguousarray(dX), lam, beta, gain, dgain, floor,
                                         lay.i_lam, lay.i_beta, lay.i_tau)
    raise ValueError("sensitivities needs at least one pass")  # pragma: no cover
