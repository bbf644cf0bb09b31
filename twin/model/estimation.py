"""Estimation of the joint angles α̂ from the motor encoders (3-X paper §4.1 and eq. 58).

- :func:`alpha_hat_3` — eq. 33: α̂ from the N "short" cables only, joint by joint up the neck.
  Cable i's length depends on α_1..α_i and is monotone in α_i, so each α̂_i is the unique root of
  a one-dimensional equation, found by safeguarded Newton steps with exact derivatives (jets) to
  1e-12 rad, far below one encoder count (≈ 1e-4 rad of α).
- :class:`PseudoInverseEstimator` — eq. 35: the incremental pseudo-inverse over every cable,
  α̂⁺ = α̂ + (Zᵀ)⁺[(r_d/R)Δθ − Δx_c] (our sign of x_c, docs/model.md), with the stretch x_c
  predicted by eq. 58 for the linear or variable cable model, or zero for rigid cables.
- :func:`predict_elongation` — eq. 58, one explicit step of the cable model.
Angles in rad (θ at the motor shaft), lengths in m, forces in N.

Eqs. 35 and 58 exist once, as the kernels :func:`pseudo_inverse_update` and
:func:`elongation_into` (numba's ``njit`` or plain Python, :mod:`twin.model.compiled`): the
controller's tick (controller/kernel.py) calls them on its own arrays, and
:class:`PseudoInverseEstimator` and :func:`predict_elongation` are thin numpy-facing wrappers that
allocate and call them. :func:`solve_into` is the small linear solve they share with the tension
distribution (controller/distribution.py, eqs. 63-65).
"""

from __future__ import annotations

import math

import numpy as np

from twin.model import xjoint
from twin.model.cables import cable_terms
from twin.model.compiled import njit
from twin.model.dynamics import friction_into
from twin.model.numeric import RIGID, Model


def short_cables(model: Model) -> np.ndarray:
    """Index of the cable that ends at each joint (the paper's c1..c3), shape (N,).

    The controller needs, for every joint, one cable whose length depends on that joint and the
    ones below it only (the triangular Z1 of eq. 23); the remaining cable is the long one.
    """
    ends = [int(np.max(np.nonzero(row >= 0)[0])) for row in model.case_rows]
    chosen = []
    for i in range(model.n_joints):
        candidates = [j for j, e in enumerate(ends) if e == i and j not in chosen]
        if not candidates:
            raise ValueError(f"no cable ends at joint {i + 1}: eq. 33 needs one cable per joint")
        chosen.append(candidates[0])
    return np.array(chosen, dtype=np.int64)


def long_cable(model: Model) -> int:
    """Index of the one cable that is not short (the paper's c4, along every joint): the column
    Z2 of Z = [Z1 | Z2] (eq. 23) whose force is the redundancy t of eqs. 63-65."""
    short = set(short_cables(model).tolist())
    rest = [j for j in range(model.n_cables) if j not in short]
    if len(rest) != 1:
        raise ValueError(f"eqs. 63-65 need exactly one cable beside the short ones, got {len(rest)}")
    return rest[0]


@njit(cache=True)
def _solve_joint(m, cable, i, alpha, target, guess, tab_row):
    """α_i such that Σ_k≤i case_k(α_k) = target for ``cable``, with α_<i known (in ``alpha``)."""
    known = 0.0
    for k in range(i):
        row = m.case_rows[cable, k]
        if row >= 0:
            xjoint.joint_jets(m.L, m.b, m.r, alpha[k], tab_row)
            known += tab_row[row, 0]
    row = m.case_rows[cable, i]
    lo, hi = -math.pi + 1e-6, math.pi - 1e-6
    a = min(max(guess, lo), hi)
    for _ in range(60):
        xjoint.joint_jets(m.L, m.b, m.r, a, tab_row)
        r = known + tab_row[row, 0] - target
        d = tab_row[row, 1]
        # Keep a bracket [lo, hi] so a Newton step can never leave the monotone branch.
        if (r > 0) == (d > 0):
            hi = a
        else:
            lo = a
        step = r / d if d != 0.0 else 0.0
        nxt = a - step
        if not (lo < nxt < hi) or d == 0.0:
            nxt = 0.5 * (lo + hi)
        if abs(nxt - a) < 1e-13:
            return nxt
        a = nxt
    return a


@njit(cache=True)
def _alpha_hat_3(m, cables_idx, lengths, guess, out, tab_row):
    for i in range(m.n_joints):
        out[i] = _solve_joint(m, cables_idx[i], i, out, lengths[i], guess[i], tab_row)


def alpha_hat_3(model: Model, theta: np.ndarray, x_c: np.ndarray | None = None, guess: np.ndarray | None = None) -> np.ndarray:
    """Eq. 33: α̂ (rad) from the short cables' motor angles θ (rad) and stretch x_c (m, default 0).

    Variable lengths follow from x_c = l_c − l_c0 + (r_d/R)θ: l_c − l_c0 = x_c − (r_d/R)θ.
    """
    theta = np.asarray(theta, dtype=float)
    x = np.zeros(model.n_cables) if x_c is None else np.asarray(x_c, dtype=float)
    idx = short_cables(model)
    lengths = model.l_c0[idx] + x[idx] - model.rho * theta[idx]
    out = np.zeros(model.n_joints)
    g = np.zeros(model.n_joints) if guess is None else np.asarray(guess, dtype=float)
    _alpha_hat_3(model, idx, lengths, g, out, np.empty((xjoint.N_ROWS, 3)))
    return out


@njit(cache=True)
def solve_into(A, b, LU, x):
    """x = A⁻¹b for a small square A, by Gaussian elimination with partial pivoting in ``LU``
    (scratch of A's shape). Agrees with LAPACK's to rounding; a singular A gives non-finite x
    (the callers' divergence checks), not an exception."""
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
def elongation_into(m, x_c, f, theta_dot, dt, out):
    """Eq. 58 into ``out`` (see :func:`predict_elongation`): x_c(t+Δt) (m) from x_c (m), the
    forces f (N) over the step and the motor velocities θ̇ (rad/s); zeros for rigid cables."""
    if m.cable_model == RIGID:
        for j in range(m.n_cables):
            out[j] = 0.0
        return
    friction_into(m, theta_dot, out)
    for j in range(m.n_cables):
        t = f[j] - out[j]
        x = x_c[j] + dt / m.c_a[j] * (t - (m.k[j] + m.lam[j] * t) * x_c[j])
        out[j] = x if x > 0.0 else 0.0


@njit(cache=True)
def _z_at(m, alpha, tab, lc, Z, Zd, zero):
    """Z(α) of eq. 23 (the model's cable kernel) into ``Z``; ``zero`` is α̇ = 0 (Ż unused)."""
    for i in range(m.n_joints):
        xjoint.joint_jets(m.L, m.b, m.r, alpha[i], tab[i])
    cable_terms(m, tab, zero, lc, Z, Zd)


@njit(cache=True)
def _pinv_step(Z, rhs, A, LU, b, out):
    """out = (Zᵀ)⁺·rhs: the least-squares Δα of Zᵀ·Δα = rhs (eq. 35), by the normal equations
    Z·Zᵀ·Δα = Z·rhs (Z has full row rank wherever eq. 35 is used)."""
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
def pseudo_inverse_update(m, dt, theta, est_theta, x_c, alpha_hat, f_prev, theta_dot,
                          tab, lc, Z, Zd, A, LU, vN, vN2, step, vc, rhs, zero):
    """One tick of eq. 35 with eq. 58's stretch, in place: α̂⁺ = α̂ + (Zᵀ)⁺[(r_d/R)Δθ − Δx_c].

    ``theta`` the new encoder angles (rad), ``est_theta`` the previous ones and ``x_c`` the
    stretch (m), both advanced here; ``f_prev`` the forces (N) over the last period and
    ``theta_dot`` (rad/s) eq. 58's friction velocities. Z is taken at the middle of the step (a
    predictor with Z(α̂), as eq. 35 prints it, then the corrector), see
    :meth:`PseudoInverseEstimator.update`. On return ``step`` holds α̂⁺ − α̂ as applied. The rest
    are scratch: tab (N, N_ROWS, 3), lc (nc,), Z and Zd (N, nc), A and LU (N, N), vN, vN2 (N,),
    vc, rhs (nc,), and ``zero`` (N,) all zeros."""
    N, nc = m.n_joints, m.n_cables
    elongation_into(m, x_c, f_prev, theta_dot, dt, vc)
    for j in range(nc):
        rhs[j] = m.rho * (theta[j] - est_theta[j]) - (vc[j] - x_c[j])
    _z_at(m, alpha_hat, tab, lc, Z, Zd, zero)
    _pinv_step(Z, rhs, A, LU, vN, step)
    for i in range(N):
        vN2[i] = alpha_hat[i] + 0.5 * step[i]
    _z_at(m, vN2, tab, lc, Z, Zd, zero)
    _pinv_step(Z, rhs, A, LU, vN, step)
    for i in range(N):
        a_new = alpha_hat[i] + step[i]
        step[i] = a_new - alpha_hat[i]
        alpha_hat[i] = a_new
    for j in range(nc):
        est_theta[j] = theta[j]
        x_c[j] = vc[j]


def pseudo_inverse_scratch(n_joints: int, n_cables: int) -> tuple[np.ndarray, ...]:
    """The scratch arrays of :func:`pseudo_inverse_update` (tab … zero), allocated once."""
    N, nc = n_joints, n_cables
    return (np.empty((N, xjoint.N_ROWS, 3)), np.empty(nc), np.empty((N, nc)), np.empty((N, nc)), np.empty((N, N)),
            np.empty((N, N)), np.empty(N), np.empty(N), np.empty(N), np.empty(nc), np.empty(nc), np.zeros(N))


def _vector(x, n: int, name: str) -> np.ndarray:
    """``x`` as a fresh contiguous float vector of length n (the kernels trust their arguments)."""
    v = np.array(x, dtype=float).reshape(-1)
    if v.shape != (n,):
        raise ValueError(f"{name} must have {n} entries, got shape {np.shape(x)}")
    return v


def static_elongation(model: Model, f: np.ndarray) -> np.ndarray:
    """Eq. 58 at rest: the stretch x_c (m) at which a cable held at tension f (N) stops creeping,
    t/(k + λ·t) with t = f (no friction at rest), never below 0; zeros for rigid cables. What a
    controller joining a running bridge takes as the stretch its first state's forces hold."""
    if model.cable_model == RIGID:
        return np.zeros(model.n_cables)
    t = np.maximum(_vector(f, model.n_cables, "f"), 0.0)
    return t / (np.asarray(model.k, dtype=float) + np.asarray(model.lam, dtype=float) * t)


def predict_elongation(model: Model, x_c: np.ndarray, f: np.ndarray, theta_dot: np.ndarray, dt: float) -> np.ndarray:
    """Eq. 58: x_c(t+Δt) = x_c + Δt/c_a·(t − (k + λ·t)·x_c) with t = f − f_friction(θ̇), never
    below 0 (a cable does not push). Rigid cables: zeros. Vectors of n_cables; the work is
    :func:`elongation_into`.

    Eq. 58 as printed puts λ·f in the stiffness; eq. 54 has λ·t, and t = f − f_friction (eq. 41
    without the motor inertia) is as cheap and much closer: on law 3's §7 control test on the twin, off
    by 0.19 mm at most with λ·t, 3.1 mm with λ·f (docs/model.md; docs/model/stretch_prediction.py)."""
    nc = model.n_cables
    out = np.empty(nc)
    elongation_into(model, _vector(x_c, nc, "x_c"), _vector(f, nc, "f"), _vector(theta_dot, nc, "theta_dot"),
                    float(dt), out)
    return out


class PseudoInverseEstimator:
    """Eq. 35 run tick by tick. Starts at α̂ = 0 with θ = 0 and x_c = 0 (the straight, unloaded
    neck of eq. 20), or wherever :meth:`reset` puts it.

    ``model`` is the controller's model: its cable model decides the elongation (rigid: none;
    linear or variable: eq. 58) and its pulley radius the Z it inverts. The state arrays
    (``alpha_hat``, ``theta``, ``x_c``) are updated in place by :func:`pseudo_inverse_update`.
    """

    def __init__(self, model: Model, dt: float):
        self.model, self.dt = model, float(dt)
        self.reset()

    def reset(self, alpha: np.ndarray | None = None, theta: np.ndarray | None = None) -> None:
        m = self.model
        self.alpha_hat = np.zeros(m.n_joints) if alpha is None else _vector(alpha, m.n_joints, "alpha")
        self.theta = np.zeros(m.n_cables) if theta is None else _vector(theta, m.n_cables, "theta")
        self.x_c = np.zeros(m.n_cables)
        self._work = pseudo_inverse_scratch(m.n_joints, m.n_cables)

    def update(self, theta: np.ndarray, f_prev: np.ndarray, theta_dot: np.ndarray) -> np.ndarray:
        """New encoder angles θ (rad); ``f_prev`` the forces (N) applied over the last period and
        ``theta_dot`` (rad/s) the motor velocities for eq. 58's friction. Returns α̂ (rad), a copy.

        Eq. 34 holds along the motion, so Z is taken at the middle of the step (a predictor step
        with Z(α̂(t)) as eq. 35 prints it, then the corrector): the estimate no longer drifts by
        the first-order error of evaluating Z at the start of each step."""
        nc = self.model.n_cables
        pseudo_inverse_update(self.model, self.dt, _vector(theta, nc, "theta"), self.theta, self.x_c, self.alpha_hat,
                              _vector(f_prev, nc, "f_prev"), _vector(theta_dot, nc, "theta_dot"), *self._work)
        return self.alpha_hat.copy()
