"""One tick of the computed-torque law as one compiled kernel (issue 21: controller step p99 ≤ 0.1 ms).

:func:`law_tick` is :meth:`controller.laws.ComputedTorque.step` from the encoders to the forces:
velocity filters, α̂ by eq. 35 with the stretch of eq. 58 (predictor-corrector on Z), the PID
outer loop (eq. 59), the model at α̂ and Z, Ż at α^d (eq. 66) and the tension distribution (eqs.
63-65). Everything is written into arrays allocated once (:func:`scratch`), so a tick creates no
Python object and the collector never runs inside it. The model's own kernels (jets, cables,
chain, friction) are called, not copied: one implementation of every equation.

Eqs. 35 and 58 are the model's kernel :func:`twin.model.estimation.pseudo_inverse_update` and
eqs. 63-65 the controller's :func:`controller.distribution.distribute_into`, the very functions the
numpy-facing ``PseudoInverseEstimator`` and ``distribute`` call; this module adds only the
velocity filters, the PID of eq. 59, the assembly of eq. 66 and the bound on the force rate
(:attr:`controller.laws.LawConfig.force_rate_max_N_s`, not from the paper).

Like every model kernel it is numba's ``njit`` when numba is there (:mod:`twin.model.compiled`),
plain Python otherwise (same numbers, slower).
"""

from __future__ import annotations

import numpy as np

from controller.distribution import distribute_into
from twin.model import xjoint
from twin.model.cables import cable_terms
from twin.model.compiled import njit
from twin.model.dynamics import chain_terms, friction_into, motor_terms
from twin.model.estimation import pseudo_inverse_update


@njit(cache=True)
def estimate(m, dt, gap, beta, accel_max, has_prev, theta, theta_prev, theta_dot, alpha_hat, alpha_hat_dot, est_theta,
             x_c, f_prev, tab, lc, Z, Zd, A, LU, vN, vN2, step, vc, rhs, zero):
    """α̂ from the encoders θ (eq. 35 with eq. 58's stretch over ``dt`` s, :func:`pseudo_inverse_update`)
    and the filtered θ̇ and α̂̇, all in place (the state arrays of :class:`controller.laws.ComputedTorque`).
    ``gap`` (s): the time since the state θ_prev was read, the divisor of the increments (the mean
    velocity over it, however long); ``beta`` the low-pass weight for that gap. α̂̇'s new sample
    differs from the filtered value by at most ``accel_max``·gap (rad/s², inf: no bound;
    :attr:`controller.laws.LawConfig.alpha_hat_accel_max_rad_s2`): an encoder jump is not a speed."""
    if has_prev:
        for j in range(m.n_cables):
            theta_dot[j] += beta * ((theta[j] - theta_prev[j]) / gap - theta_dot[j])
    pseudo_inverse_update(m, dt, theta, est_theta, x_c, alpha_hat, f_prev, theta_dot,
                          tab, lc, Z, Zd, A, LU, vN, vN2, step, vc, rhs, zero)
    dv_max = accel_max * gap
    for i in range(m.n_joints):
        dv = step[i] / gap - alpha_hat_dot[i]
        if dv > dv_max:
            dv = dv_max
        elif dv < -dv_max:
            dv = -dv_max
        alpha_hat_dot[i] += beta * dv
    for j in range(m.n_cables):
        theta_prev[j] = theta[j]


@njit(cache=True)
def law_tick(m, gains, short, long, has_prev, theta, a_d, a_d_dot, a_d_ddot, pretension, state, work, out):
    """One tick of eqs. 35, 58, 59, 63-66 (module docstring), all in place. ``pretension`` (N)
    raises every cable's floor t_min of eq. 65 (a trajectory's pretension, controller.trajectory).

    The forces then move from the last ones (``f_prev``: commanded, or applied while the law only
    observed) by at most ``df_max`` N (:attr:`controller.laws.LawConfig.force_rate_max_N_s`).

    ``gains`` = (k_p, k_v, k_i, dt, β of the velocity filters, df_max, gap, the bound on α̂̇'s
    change in rad/s² of :func:`estimate`): ``gap`` (s) the time
    since the last state the law took, over which it differentiates (:func:`estimate`), ``dt`` (s)
    that gap bounded, over which it integrates e and predicts the stretch (eq. 58), ``df_max`` (N)
    per command (:class:`controller.laws.ComputedTorque`, "Time step"); ``state`` = (θ_prev, θ̇, α̂,
    α̂̇, θ of the estimator, x_c, f_prev, ∫e) updated in place; ``out`` = (f, saturated, e, Γ^d)."""
    kp, kv, ki, dt, beta, df_max, gap = gains[0], gains[1], gains[2], gains[3], gains[4], gains[5], gains[6]
    accel_max = gains[7]
    theta_prev, theta_dot, alpha_hat, alpha_hat_dot, est_theta, x_c, f_prev, integral = state
    (tab, lc, Z, Zd, Mm, cm, g, M, c, A, LU, Z1, vN, vN2, step, p, nvec, w, vc, rhs, zero, ff, tdd, lower,
     Zdes, Zddes) = work
    f, saturated, e, gamma = out
    N, nc = m.n_joints, m.n_cables
    estimate(m, dt, gap, beta, accel_max, has_prev, theta, theta_prev, theta_dot, alpha_hat, alpha_hat_dot, est_theta, x_c, f_prev,
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
        lb = m.t_min + pretension + ff[j] + m.I_a * tdd[j] / m.rho
        lower[j] = lb if lb > m.f_min else m.f_min
    distribute_into(Z, gamma, lower, m.f_max, short, long, Z1, LU, vN, p, nvec, f, saturated)
    for j in range(nc):  # the rate bound, after eqs. 63-65 (LawConfig.force_rate_max_N_s)
        if f[j] > f_prev[j] + df_max:
            f[j] = f_prev[j] + df_max
        elif f[j] < f_prev[j] - df_max:
            f[j] = f_prev[j] - df_max
        f_prev[j] = f[j]


def scratch(n_joints: int, n_cables: int) -> tuple[np.ndarray, ...]:
    """The ``work`` arrays of :func:`law_tick`, allocated once per law."""
    N, nc = n_joints, n_cables
    return (np.empty((N, xjoint.N_ROWS, 3)), np.empty(nc), np.empty((N, nc)), np.empty((N, nc)),
            np.empty((N, N)), np.empty(N), np.empty(N), np.empty((N, N)), np.empty(N),
            np.empty((N, N)), np.empty((N, N)), np.empty((N, N)), np.empty(N), np.empty(N), np.empty(N),
            np.empty(N), np.empty(N), np.empty(N), np.empty(nc), np.empty(nc), np.zeros(N), np.empty(nc),
            np.empty(nc), np.empty(nc), np.empty((N, nc)), np.empty((N, nc)))


__all__ = ["estimate", "law_tick", "scratch"]
