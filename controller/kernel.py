"""One tick of the computed-torque law as one compiled kernel (issue 21: controller step p99 ≤ 0.1 ms).

:func:`law_tick` is :meth:`controller.laws.ComputedTorque.step` from the encoders to the forces:
velocity filters, α̂ by eq. 35 with the stretch of eq. 58 (predictor-corrector on Z), the PID
outer loop (eq. 59), the model at α̂ and Z, Ż at α^d (eq. 66) and the tension distribution (eqs.
63-65). Everything is written into arrays allocated once (:func:`scratch`), so a tick creates no
Python object and the collector never runs inside it. The model's own kernels (jets, cables,
chain, friction) are called, not copied: one implementation of every equation.

Like every model kernel it is numba's ``njit`` when numba is there (:mod:`twin.model.compiled`),
plain Python otherwise (same numbers, slower).

Least squares and solves are written out for these small systems (N = 3): (Zᵀ)⁺·rhs by the normal
equations (Z·Zᵀ)·Δα = Z·rhs (Z has full row rank wherever eq. 35 is used), and Z1 by Gaussian
elimination with partial pivoting. Both agree with LAPACK's to rounding.
"""

from __future__ import annotations

import numpy as np

from twin.model import xjoint
from twin.model.cables import cable_terms
from twin.model.compiled import njit
from twin.model.dynamics import chain_terms, friction_into, motor_terms
from twin.model.numeric import RIGID


@njit(cache=True)
def solve_into(A, b, LU, x):
    """x = A⁻¹b for a small square A, by Gaussian elimination with partial pivoting in ``LU``
    (scratch of A's shape). A singular A gives non-finite x (the caller's divergence check)."""
    n = A.shape[0]
    LU[:, :] = A
    x[:] = b
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(LU[i, k]) > abs(LU[p, k]):
                p = i
        if p != k:
            for j in range(n):
                LU[k, j], LU[p, j] = LU[p, j], LU[k, j]
            x[k], x[p] = x[p], x[k]
        piv = LU[k, k]
        for i in range(k + 1, n):
            f = LU[i, k] / piv
            for j in range(k, n):
                LU[i, j] -= f * LU[k, j]
            x[i] -= f * x[k]
    for k in range(n - 1, -1, -1):
        acc = x[k]
        for j in range(k + 1, n):
            acc -= LU[k, j] * x[j]
        x[k] = acc / LU[k, k]


@njit(cache=True)
def _z_at(m, alpha, tab, lc, Z, Zd, zero):
    for i in range(m.n_joints):
        xjoint.joint_jets(m.L, m.b, m.r, alpha[i], tab[i])
    cable_terms(m, tab, zero, lc, Z, Zd)


@njit(cache=True)
def _pinv_step(Z, rhs, A, LU, b, out):
    """out = (Zᵀ)⁺·rhs: the least-squares Δα of Zᵀ·Δα = rhs (eq. 35), via Z·Zᵀ·Δα = Z·rhs."""
    N, nc = Z.shape
    for i in range(N):
        acc = 0.0
        for j in range(nc):
            acc += Z[i, j] * rhs[j]
        b[i] = acc
        for k in range(N):
            acc = 0.0
            for j in range(nc):
                acc += Z[i, j] * Z[k, j]
            A[i, k] = acc
    solve_into(A, b, LU, out)


@njit(cache=True)
def estimate(m, dt, beta, has_prev, theta, theta_prev, theta_dot, alpha_hat, alpha_hat_dot, est_theta, x_c, f_prev,
             tab, lc, Z, Zd, A, LU, vN, vN2, step, vc, rhs, zero):
    """α̂ from the encoders θ (eq. 35 with eq. 58's stretch) and the filtered θ̇ and α̂̇, all in
    place (the state arrays of :class:`controller.laws.ComputedTorque`)."""
    N, nc = m.n_joints, m.n_cables
    if has_prev:
        for j in range(nc):
            theta_dot[j] += beta * ((theta[j] - theta_prev[j]) / dt - theta_dot[j])
    # eq. 58 (docs in twin.model.estimation.predict_elongation): x_next into vc.
    if m.cable_model == RIGID:
        for j in range(nc):
            vc[j] = 0.0
    else:
        friction_into(m, theta_dot, vc)
        for j in range(nc):
            t = f_prev[j] - vc[j]
            x = x_c[j] + dt / m.c_a[j] * (t - (m.k[j] + m.lam[j] * t) * x_c[j])
            vc[j] = x if x > 0.0 else 0.0
    for j in range(nc):
        rhs[j] = m.rho * (theta[j] - est_theta[j]) - (vc[j] - x_c[j])
    # Predictor with Z(α̂), corrector with Z at the middle of the step.
    _z_at(m, alpha_hat, tab, lc, Z, Zd, zero)
    _pinv_step(Z, rhs, A, LU, vN, step)
    for i in range(N):
        vN2[i] = alpha_hat[i] + 0.5 * step[i]
    _z_at(m, vN2, tab, lc, Z, Zd, zero)
    _pinv_step(Z, rhs, A, LU, vN, step)
    for i in range(N):
        a_new = alpha_hat[i] + step[i]
        alpha_hat_dot[i] += beta * ((a_new - alpha_hat[i]) / dt - alpha_hat_dot[i])
        alpha_hat[i] = a_new
    for j in range(nc):
        est_theta[j] = theta[j]
        theta_prev[j] = theta[j]
        x_c[j] = vc[j]


@njit(cache=True)
def distribute_into(Z, gamma, lower, f_max, short, long, Z1, LU, vN, p, nvec, f, saturated):
    """Eqs. 63-65 (:func:`controller.distribution.distribute`) into ``f`` and ``saturated``;
    returns whether n = −Z1⁻¹Z2 > 0 (the region where eq. 63 works)."""
    N = Z.shape[0]
    for i in range(N):
        for k in range(N):
            Z1[i, k] = Z[i, short[k]]
    solve_into(Z1, gamma, LU, p)
    for i in range(N):
        vN[i] = -Z[i, long]
    solve_into(Z1, vN, LU, nvec)
    feasible = True
    f_long = lower[long]
    for i in range(N):
        if nvec[i] > 0.0:
            cand = (lower[short[i]] - p[i]) / nvec[i]
            if cand > f_long:
                f_long = cand
        else:
            feasible = False
    for i in range(N):
        f[short[i]] = p[i] + nvec[i] * f_long
    f[long] = f_long
    for j in range(f.shape[0]):
        saturated[j] = f[j] > f_max
        if saturated[j]:
            f[j] = f_max
    return feasible


@njit(cache=True)
def law_tick(m, gains, short, long, has_prev, theta, a_d, a_d_dot, a_d_ddot, state, work, out):
    """One tick of eqs. 35, 58, 59, 63-66 (module docstring), all in place.

    ``gains`` = (k_p, k_v, k_i, dt, β of the velocity filters); ``state`` = (θ_prev, θ̇, α̂, α̂̇,
    θ of the estimator, x_c, f_prev, ∫e) updated in place; ``out`` = (f, saturated, e, Γ^d)."""
    kp, kv, ki, dt, beta = gains[0], gains[1], gains[2], gains[3], gains[4]
    theta_prev, theta_dot, alpha_hat, alpha_hat_dot, est_theta, x_c, f_prev, integral = state
    (tab, lc, Z, Zd, Mm, cm, g, M, c, A, LU, Z1, vN, vN2, step, p, nvec, w, vc, rhs, zero, ff, tdd, lower,
     Zdes, Zddes) = work
    f, saturated, e, gamma = out
    N, nc = m.n_joints, m.n_cables
    estimate(m, dt, beta, has_prev, theta, theta_prev, theta_dot, alpha_hat, alpha_hat_dot, est_theta, x_c, f_prev,
             tab, lc, Z, Zd, A, LU, vN, vN2, step, vc, rhs, zero)
    for i in range(N):
        e[i] = a_d[i] - alpha_hat[i]
        integral[i] += e[i] * dt
        w[i] = a_d_ddot[i] + kv * (a_d_dot[i] - alpha_hat_dot[i]) + kp * e[i] + ki * integral[i]
    # Z and Ż at α^d (the friction and inertia terms of §6.2), then the model at α̂ (eq. 66).
    for i in range(N):
        xjoint.joint_jets(m.L, m.b, m.r, a_d[i], tab[i])
    cable_terms(m, tab, a_d_dot, lc, Zdes, Zddes)
    for j in range(nc):
        acc1 = 0.0
        acc2 = 0.0
        for i in range(N):
            acc1 += Zdes[i, j] * a_d_dot[i]
            acc2 += Zdes[i, j] * a_d_ddot[i] + Zddes[i, j] * a_d_dot[i]
        vc[j] = acc1 / m.rho  # θ̇^d
        tdd[j] = acc2 / m.rho  # θ̈^d
    friction_into(m, vc, ff)  # zero for law 1, whose model has no friction
    for i in range(N):
        xjoint.joint_jets(m.L, m.b, m.r, alpha_hat[i], tab[i])
    cable_terms(m, tab, zero, lc, Z, Zd)
    chain_terms(m, alpha_hat, zero, tab, Mm, cm, g)
    motor_terms(m, Z, Zd, zero, Mm, cm, M, c)
    for i in range(N):
        acc = g[i]
        for k in range(N):
            acc += M[i, k] * w[k]
        for j in range(nc):
            acc += Z[i, j] * ff[j]
        gamma[i] = acc
    for j in range(nc):
        lb = m.t_min + ff[j] + m.I_a * tdd[j] / m.rho
        lower[j] = lb if lb > m.f_min else m.f_min
    distribute_into(Z, gamma, lower, m.f_max, short, long, Z1, LU, vN, p, nvec, f, saturated)
    for j in range(nc):
        f_prev[j] = f[j]


def scratch(n_joints: int, n_cables: int) -> tuple[np.ndarray, ...]:
    """The ``work`` arrays of :func:`law_tick`, allocated once per law."""
    N, nc = n_joints, n_cables
    return (np.empty((N, xjoint.N_ROWS, 3)), np.empty(nc), np.empty((N, nc)), np.empty((N, nc)),
            np.empty((N, N)), np.empty(N), np.empty(N), np.empty((N, N)), np.empty(N),
            np.empty((N, N)), np.empty((N, N)), np.empty((N, N)), np.empty(N), np.empty(N), np.empty(N),
            np.empty(N), np.empty(N), np.empty(N), np.empty(nc), np.empty(nc), np.zeros(N), np.empty(nc),
            np.empty(nc), np.empty(nc), np.empty((N, nc)), np.empty((N, nc)))


__all__ = ["distribute_into", "estimate", "law_tick", "scratch", "solve_into"]
