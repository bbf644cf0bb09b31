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
"""

from __future__ import annotations

import math

import numpy as np

from twin.model import xjoint
from twin.model.compiled import njit
from twin.model.dynamics import f_friction
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


def predict_elongation(model: Model, x_c: np.ndarray, f: np.ndarray, theta_dot: np.ndarray, dt: float) -> np.ndarray:
    """Eq. 58: x_c(t+Δt) = x_c + Δt/c_a·(t − (k + λ·t)·x_c) with t = f − f_friction(θ̇), never
    below 0 (a cable does not push). Rigid cables: zeros.

    Eq. 58 as printed puts λ·f in the stiffness; eq. 54 has λ·t, and t = f − f_friction (eq. 41
    without the motor inertia) is as cheap and much closer: with λ·f the predicted stretch is off by
    0.3-1 mm where friction is large, with λ·t by about 0.01 mm (measured on the twin)."""
    if model.cable_model == RIGID:
        return np.zeros(model.n_cables)
    t = f - f_friction(model, theta_dot)
    x_next = x_c + dt / model.c_a * (t - (model.k + model.lam * t) * x_c)
    return np.maximum(x_next, 0.0)


class PseudoInverseEstimator:
    """Eq. 35 run tick by tick. Starts at α̂ = 0 with θ = 0 and x_c = 0 (the straight, unloaded
    neck of eq. 20), or wherever :meth:`reset` puts it.

    ``model`` is the controller's model: its cable model decides the elongation (rigid: none;
    linear or variable: eq. 58) and its pulley radius the Z it inverts.
    """

    def __init__(self, model: Model, dt: float):
        self.model, self.dt = model, dt
        self.reset()

    def reset(self, alpha: np.ndarray | None = None, theta: np.ndarray | None = None) -> None:
        m = self.model
        self.alpha_hat = np.zeros(m.n_joints) if alpha is None else np.array(alpha, dtype=float)
        self.theta = np.zeros(m.n_cables) if theta is None else np.array(theta, dtype=float)
        self.x_c = np.zeros(m.n_cables)
        self._tab = np.empty((m.n_joints, xjoint.N_ROWS, 3))
        self._Z = np.empty((m.n_joints, m.n_cables))

    def _Z_at(self, alpha: np.ndarray) -> np.ndarray:
        m, Z = self.model, self._Z
        for i in range(m.n_joints):
            xjoint.joint_jets(m.L, m.b, m.r, alpha[i], self._tab[i])
        for j in range(m.n_cables):
            for i in range(m.n_joints):
                row = m.case_rows[j, i]
                Z[i, j] = -self._tab[i, row, 1] if row >= 0 else 0.0
        return Z

    def update(self, theta: np.ndarray, f_prev: np.ndarray, theta_dot: np.ndarray) -> np.ndarray:
        """New encoder angles θ (rad); ``f_prev`` the forces (N) applied over the last period and
        ``theta_dot`` (rad/s) the motor velocities for eq. 58's friction. Returns α̂ (rad).

        Eq. 34 holds along the motion, so Z is taken at the middle of the step (a predictor step
        with Z(α̂(t)) as eq. 35 prints it, then the corrector): the estimate no longer drifts by
        the first-order error of evaluating Z at the start of each step."""
        m = self.model
        x_next = predict_elongation(m, self.x_c, f_prev, theta_dot, self.dt)
        rhs = m.rho * (theta - self.theta) - (x_next - self.x_c)
        # (Zᵀ)⁺ applied to rhs: the least-squares Δα of Zᵀ·Δα = rhs.
        step = np.linalg.lstsq(self._Z_at(self.alpha_hat).T, rhs, rcond=None)[0]
        step = np.linalg.lstsq(self._Z_at(self.alpha_hat + 0.5 * step).T, rhs, rcond=None)[0]
        self.alpha_hat = self.alpha_hat + step
        self.theta = np.array(theta, dtype=float)
        self.x_c = x_next
        return self.alpha_hat
