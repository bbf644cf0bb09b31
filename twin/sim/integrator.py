"""One integration step of the full model (3-X paper eqs. 27-32, tension eq. 39 or 54).

Why a linearly implicit step: the bars are light (smallest eigenvalue of M_m ≈ 1e-5 kg·m²) and the
cables stiff and heavily damped (k ≈ 5e3 N/m, c_a = 3e3 N·s/m), so the elongation dynamics have
eigenvalues near −c_a·Z²/M_m ≈ −3e5 1/s: an explicit method would need steps of a few µs. We take
semi-implicit Euler steps in which the cable tension (linearised in the stretch and its rate) and
the friction (linearised in θ̇) are implicit, and the smooth, slow terms (springs, gravity,
Coriolis) explicit:

    [𝕄 + h·G(h·K + D)Gᵀ + h·ρ·diag(∂f_fr/∂θ̇)] v⁺ = 𝕄v + h[−G(t − D·Gᵀv) + F] + h·ρ·(∂f_fr/∂θ̇)θ̇
    q⁺ = q + h·v⁺

with q = (α, θ), v = (α̇, θ̇), 𝕄 = diag(M_m, I_a·1), G = [−Z; ρ·1] (so ẋ_c = Gᵀv and the tension's
generalised force is −G·t), K = ∂t/∂x_c, D = ∂t/∂ẋ_c and F = (−c_m − g, ρ(f − f_friction)).
The step is L-stable for the stiff cable modes and first-order accurate for the slow motion; with
two substeps per 2 ms tick it stays within 0.01° of scipy's Radau at tight tolerances
(tests/test_sim.py). Rigid cables: the same step on M·α̈ + c + g = Z(f − f_friction) (eq. 32).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from twin.model.dynamics import evaluate_into, friction_into, motor_terms, tension_divisor
from twin.model.numeric import LINEAR, RIGID

ALPHA_FLAT = math.pi  # rad: an X-joint is flat (singular) at α = ±π, i.e. θ = α/2 = ±90° (2-X paper)


@njit(cache=True)
def _friction_slope(m, theta_dot, out):
    for j in range(m.n_cables):
        if m.friction_sign:
            out[j] = 0.0  # eq. 36 is discontinuous at 0: treat it explicitly
        else:
            u = m.c_s * theta_dot[j]
            out[j] = m.f_s[j] * (2.0 / math.pi) * m.c_s / (1.0 + u * u)


@njit(cache=True)
def _tension_and_slopes(m, x, x_dot, t, K, D):
    """Tension (N) with its slopes K = ∂t/∂x (N/m) and D = ∂t/∂ẋ (N·s/m); zero on slack cables."""
    slack = 0
    for j in range(m.n_cables):
        t[j] = K[j] = D[j] = 0.0
        if x[j] <= 0.0:
            slack += 1
            continue
        den = 1.0
        if m.cable_model != LINEAR:
            den = tension_divisor(m.lam[j], x[j])
        tj = (m.k[j] * x[j] + m.c_a[j] * x_dot[j]) / den
        if tj > 0.0:
            t[j] = tj
            K[j] = (m.k[j] + m.lam[j] * tj) / den
            D[j] = m.c_a[j] / den
    return slack


@njit(cache=True)
def step(m, s, f, h, n_sub, work, t_out, x_out):
    """Advance state ``s`` = (α, θ, α̇, θ̇) in place by ``n_sub`` substeps of ``h`` seconds with the
    motor forces ``f`` (N) held. Writes the cable tensions of the last substep into ``t_out`` and
    the cable stretch at the end (m, zero for rigid cables) into ``x_out``.

    Returns a bit field: bit j set if cable j is slack at the end; bit 62 set if a joint reached
    the flat singularity (the step is then not taken and the state is left unchanged).
    """
    tab, lc, Z, Zd, Mm, cm, g, M, c, ff = work
    N, nc = m.n_joints, m.n_cables
    n = N + nc
    alpha, theta, alpha_dot, theta_dot = s[:N], s[N:n], s[n : n + N], s[n + N :]
    x, xd, K, D, dff = np.empty(nc), np.empty(nc), np.empty(nc), np.empty(nc), np.empty(nc)
    A = np.zeros((n, n))
    rhs = np.empty(n)
    s0 = s.copy()
    for _ in range(n_sub):
        evaluate_into(m, alpha, alpha_dot, tab, lc, Z, Zd, Mm, cm, g)
        if m.cable_model == RIGID:
            theta[:] = -(lc - m.l_c0) / m.rho
            theta_dot[:] = (Z.T @ alpha_dot) / m.rho
        friction_into(m, theta_dot, ff)
        _friction_slope(m, theta_dot, dff)
        if m.cable_model == RIGID:
            motor_terms(m, Z, Zd, alpha_dot, Mm, cm, M, c)
            W = Z * (dff / m.rho)  # friction torque slope through the cables, Z·diag(∂f/∂θ̇)·Zᵀ/ρ
            Af = M + h * (W @ Z.T)
            rf = M @ alpha_dot + h * (Z @ (f - ff) - c - g) + h * (W @ (Z.T @ alpha_dot))
            new_dot = np.linalg.solve(Af, rf)
            theta_ddot = (Z.T @ new_dot - Z.T @ alpha_dot) / (h * m.rho)
            t_out[:] = f - ff - m.I_a * theta_ddot / m.rho
            alpha_dot[:] = new_dot
            alpha += h * alpha_dot
        else:
            for j in range(nc):
                x[j] = lc[j] - m.l_c0[j] + m.rho * theta[j]
                xd[j] = m.rho * theta_dot[j]
                for i in range(N):
                    xd[j] -= Z[i, j] * alpha_dot[i]
            _tension_and_slopes(m, x, xd, t_out, K, D)
            # A = 𝕄 + h·G·diag(hK + D)·Gᵀ (+ friction), assembled blockwise with G = [−Z; ρ·1].
            A[:, :] = 0.0
            A[:N, :N] = Mm
            for j in range(nc):
                w = h * (h * K[j] + D[j])
                for a in range(N):
                    for b in range(N):
                        A[a, b] += w * Z[a, j] * Z[b, j]
                    A[a, N + j] -= w * m.rho * Z[a, j]
                    A[N + j, a] -= w * m.rho * Z[a, j]
                A[N + j, N + j] = m.I_a + w * m.rho * m.rho + h * m.rho * dff[j]
            # rhs = 𝕄v + h[−G(t − D·ẋ) + F] + h·ρ·dff·θ̇
            for a in range(N):
                acc = 0.0
                for b in range(N):
                    acc += Mm[a, b] * alpha_dot[b]
                for j in range(nc):
                    acc += h * Z[a, j] * (t_out[j] - D[j] * xd[j])
                rhs[a] = acc - h * (cm[a] + g[a])
            for j in range(nc):
                rhs[N + j] = m.I_a * theta_dot[j] + h * m.rho * (
                    -(t_out[j] - D[j] * xd[j]) + f[j] - ff[j] + dff[j] * theta_dot[j]
                )
            v = np.linalg.solve(A, rhs)
            alpha_dot[:] = v[:N]
            theta_dot[:] = v[N:]
            alpha += h * alpha_dot
            theta += h * theta_dot
        for i in range(N):
            if abs(alpha[i]) >= ALPHA_FLAT:
                s[:] = s0
                return np.int64(1) << 62
    evaluate_into(m, alpha, alpha_dot, tab, lc, Z, Zd, Mm, cm, g)
    if m.cable_model == RIGID:
        theta[:] = -(lc - m.l_c0) / m.rho
        theta_dot[:] = (Z.T @ alpha_dot) / m.rho
        x_out[:] = 0.0
    else:
        x_out[:] = lc - m.l_c0 + m.rho * theta
    bits = np.int64(0)
    for j in range(nc):
        if t_out[j] <= 0.0:
            bits |= np.int64(1) << j
    return bits
