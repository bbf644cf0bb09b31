"""Dynamics of the X-joint neck (3-X paper §3.2-3.3 and §5): inertia, Coriolis, potential,
friction, cable tension and the full model with friction and elastic cables.

Frames and units: base frame at the middle of the first base bar, y up (gravity along −y), the
neck straight up at α = 0; α in rad, θ at the motor shaft in rad, forces f and tensions t in N
along the cables, generalised forces (torques conjugate to angles in rad) in N·m; N·m/rad is a
stiffness.

M_m and c_m come from the kinetic energy of every bar (two diagonals and the top bar of each
joint; bars are rigid bodies with a mass and an inertia about their centre of mass):
M_m = Σ m·J_pᵀJ_p + I·J_φᵀJ_φ and c_m = Σ m·J_pᵀ·a_bias + I·J_φ·φ̈_bias, where a_bias is the
acceleration of a bar's centre when α̈ = 0, propagated joint by joint up the chain.
With the geared motors (eqs. 24, 26): M = M_m + I_a(R/r_d)²·Z·Zᵀ and
c = c_m + I_a(R/r_d)²·Z·Żᵀ·α̇ (eq. 26 as printed omits the α̇ and swaps the transposes; this is
what the Lagrangian of ½·I_a·θ̇ᵀθ̇ with eq. 21 gives).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from twin.model import xjoint
from twin.model.cables import cable_terms
from twin.model.compiled import kernel_array, njit
from twin.model.numeric import RIGID, Model


@njit(cache=True)
def chain_terms(m, alpha, alpha_dot, tab, Mm, cm, g, inertia=True):
    """M_m, c_m and g (springs + gravity) from a filled jet table; returns the potential U (J).
    ``inertia`` False: g and U only (M_m, c_m left at 0), for statics (:func:`statics`)."""
    N = m.n_joints
    Mm[:, :] = 0.0
    cm[:] = 0.0
    g[:] = 0.0
    U = 0.0
    T = np.empty((N, 2))  # ∂O_{j+1}/∂α_j: world translation of joint j's top centre per radian
    On = np.empty((N, 2))  # O_{j+1}: world position of joint j's top centre
    Jx, Jy, Jp = np.zeros(N), np.zeros(N), np.zeros(N)
    ox = oy = ax0 = ay0 = 0.0  # origin of joint i and its bias acceleration
    beta = om = 0.0  # orientation of joint i's base bar and its rate
    for i in range(N):
        cb, sb = math.cos(beta), math.sin(beta)
        ad = alpha_dot[i]
        for k in range(xjoint.N_BODIES + 1):
            # k < N_BODIES: a bar; k == N_BODIES: the top centre P, which carries the next frame.
            if k < xjoint.N_BODIES:
                rx, ry, rphi = xjoint.BODY0 + 3 * k, xjoint.BODY0 + 3 * k + 1, xjoint.BODY0 + 3 * k + 2
            else:
                rx, ry, rphi = xjoint.P_X, xjoint.P_Y, -1
            q0x, q0y = cb * tab[i, rx, 0] - sb * tab[i, ry, 0], sb * tab[i, rx, 0] + cb * tab[i, ry, 0]
            q1x, q1y = cb * tab[i, rx, 1] - sb * tab[i, ry, 1], sb * tab[i, rx, 1] + cb * tab[i, ry, 1]
            q2x, q2y = cb * tab[i, rx, 2] - sb * tab[i, ry, 2], sb * tab[i, rx, 2] + cb * tab[i, ry, 2]
            px, py = ox + q0x, oy + q0y
            # Bias acceleration (α̈ = 0) of the point: frame term, centripetal, Coriolis, local.
            bx = ax0 - om * om * q0x - 2.0 * om * ad * q1y + q2x * ad * ad
            by = ay0 - om * om * q0y + 2.0 * om * ad * q1x + q2y * ad * ad
            if k == xjoint.N_BODIES:
                T[i, 0], T[i, 1] = q1x, q1y
                On[i, 0], On[i, 1] = px, py
                ox, oy, ax0, ay0 = px, py, bx, by
                break
            for j in range(i):
                # α_j moves joint j's top centre and turns everything above it about that centre.
                Jx[j] = T[j, 0] - (py - On[j, 1])
                Jy[j] = T[j, 1] + (px - On[j, 0])
                Jp[j] = 1.0
            Jx[i], Jy[i], Jp[i] = q1x, q1y, tab[i, rphi, 1]
            phib = tab[i, rphi, 2] * ad * ad
            mass, body_inertia = m.m_body[i, k], m.I_body[i, k]
            for a in range(i + 1):
                if inertia:
                    for c in range(i + 1):
                        Mm[a, c] += mass * (Jx[a] * Jx[c] + Jy[a] * Jy[c]) + body_inertia * Jp[a] * Jp[c]
                    cm[a] += mass * (Jx[a] * bx + Jy[a] * by) + body_inertia * Jp[a] * phib
                g[a] += mass * m.gravity * Jy[a]
            U += mass * m.gravity * py
        beta += alpha[i]
        om += ad
    for i in range(N):
        dl = tab[i, xjoint.L_LEFT, 0] - m.l0[i]
        dr = tab[i, xjoint.L_RIGHT, 0] - m.l0[i]
        g[i] += m.k_left[i] * dl * tab[i, xjoint.L_LEFT, 1] + m.k_right[i] * dr * tab[i, xjoint.L_RIGHT, 1]
        U += 0.5 * (m.k_left[i] * dl * dl + m.k_right[i] * dr * dr)
    return U


@njit(cache=True)
def evaluate_into(m, alpha, alpha_dot, tab, lc, Z, Zd, Mm, cm, g):
    """Every model term at one configuration, written into preallocated arrays; returns U (J)."""
    for i in range(m.n_joints):
        xjoint.joint_jets(m.L, m.b, m.r, alpha[i], tab[i])
    cable_terms(m, tab, alpha_dot, lc, Z, Zd)
    return chain_terms(m, alpha, alpha_dot, tab, Mm, cm, g)


@njit(cache=True)
def motor_terms(m, Z, Zd, alpha_dot, Mm, cm, M, c):
    """Eqs. 24 and 26: add the geared motors' inertia I_a(R/r_d)² seen through Z."""
    Ia = m.I_a / (m.rho * m.rho)
    M[:, :] = Mm + Ia * (Z @ Z.T)
    c[:] = cm + Ia * (Z @ (Zd.T @ alpha_dot))


@njit(cache=True)
def _evaluate_batch(m, alpha, alpha_dot):
    B, N, nc = alpha.shape[0], m.n_joints, m.n_cables
    lc, Z, Zd = np.empty((B, nc)), np.empty((B, N, nc)), np.empty((B, N, nc))
    Mm, cm, g = np.empty((B, N, N)), np.empty((B, N)), np.empty((B, N))
    M, c, U = np.empty((B, N, N)), np.empty((B, N)), np.empty(B)
    tab = np.empty((N, xjoint.N_ROWS, 3))
    for k in range(B):
        U[k] = evaluate_into(m, alpha[k], alpha_dot[k], tab, lc[k], Z[k], Zd[k], Mm[k], cm[k], g[k])
        motor_terms(m, Z[k], Zd[k], alpha_dot[k], Mm[k], cm[k], M[k], c[k])
    return lc, Z, Zd, Mm, cm, g, M, c, U


@njit(cache=True)
def _statics_batch(m, alpha):
    B, N, nc = alpha.shape[0], m.n_joints, m.n_cables
    lc, Z, Zd, g = np.empty((B, nc)), np.empty((B, N, nc)), np.empty((B, N, nc)), np.empty((B, N))
    Mm, cm, still = np.empty((N, N)), np.empty(N), np.zeros(N)
    tab = np.empty((N, xjoint.N_ROWS, 3))
    for k in range(B):
        for i in range(N):
            xjoint.joint_jets(m.L, m.b, m.r, alpha[k, i], tab[i])
        cable_terms(m, tab, still, lc[k], Z[k], Zd[k])
        chain_terms(m, alpha[k], still, tab, Mm, cm, g[k], False)
    return lc, Z, g


def statics(model: Model, alpha) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(l_c (..., n_cables) m, Z (..., N, n_cables) m/rad, g (..., N) N·m) at ``alpha`` (..., N)
    rad: the terms of the neck's equilibrium Z·t = g (eq. 32), without the inertia
    :func:`evaluate` computes too (a third of its cost: the identification's re-simulation of the
    neck, twin/identification/instruments.py, evaluates them about 500 times per fit)."""
    a2 = _as_batch(model, alpha, "alpha")
    lead = np.shape(alpha)[:-1]
    return tuple(v.reshape(lead + v.shape[1:]) for v in _statics_batch(model, a2))  # type: ignore[return-value]


class Terms(NamedTuple):
    """Model terms at one or a batch of configurations (leading dimensions of ``alpha``)."""

    l_c: np.ndarray  # (..., n_cables) m, eqs. 3-19
    Z: np.ndarray  # (..., N, n_cables) m/rad, eq. 22
    Z_dot: np.ndarray  # (..., N, n_cables) m/(rad·s)
    M_m: np.ndarray  # (..., N, N) kg·m², bars only
    c_m: np.ndarray  # (..., N) N·m, bars only
    g: np.ndarray  # (..., N) N·m, gradient of the potential (springs + gravity)
    M: np.ndarray  # (..., N, N) kg·m², eq. 24
    c: np.ndarray  # (..., N) N·m, eq. 26
    U: np.ndarray  # (...) J, potential energy (springs + gravity)


def _as_batch(model: Model, x, name: str, like=None) -> np.ndarray:
    n = model.n_joints
    if x is None:
        return np.zeros_like(like)
    arr = np.asarray(x, dtype=float)
    if arr.shape[-1:] != (n,):
        raise ValueError(f"{name} must have shape (..., {n}), got {arr.shape}")
    if like is not None and arr.shape != like.shape:
        arr = np.broadcast_to(arr, like.shape)
    return kernel_array(arr.reshape(-1, n))


def evaluate(model: Model, alpha, alpha_dot=None) -> Terms:
    """All model terms at ``alpha`` (..., N) rad with ``alpha_dot`` (..., N) rad/s (default 0).

    One call costs a few microseconds per configuration (``benchmarks/model.py``).
    """
    a2 = _as_batch(model, alpha, "alpha")
    ad2 = _as_batch(model, alpha_dot, "alpha_dot", like=a2)
    lead = np.shape(alpha)[:-1]
    out = _evaluate_batch(model, a2, ad2)
    return Terms(*(v.reshape(lead + v.shape[1:]) for v in out))


def M(model: Model, alpha) -> np.ndarray:
    return evaluate(model, alpha).M


def c(model: Model, alpha, alpha_dot) -> np.ndarray:
    return evaluate(model, alpha, alpha_dot).c


def g(model: Model, alpha) -> np.ndarray:
    return evaluate(model, alpha).g


def potential_energy(model: Model, alpha) -> np.ndarray:
    return evaluate(model, alpha).U


# --- friction and cable tension --------------------------------------------------------------


@njit(cache=True)
def friction_shape(c_s, sign_law, theta_dot):
    """Friction per newton of f_s at motor-shaft velocities θ̇ (rad/s, scalar or array):
    (2/π)·arctan(c_s·θ̇) (eq. 37), or sign(θ̇) (eq. 36) when ``sign_law``. The one implementation
    of eqs. 36-37: the twin, the controller, α̂'s eq. 58 and the identification regressor use it."""
    if sign_law:
        return np.sign(theta_dot)
    return (2.0 / math.pi) * np.arctan(c_s * theta_dot)


@njit(cache=True)
def friction_into(m, theta_dot, out):
    """Eq. 37 (or eq. 36 when m.friction_sign): friction force (N) opposing the motor motion."""
    for j in range(m.n_cables):
        out[j] = m.f_s[j] * friction_shape(m.c_s, m.friction_sign, theta_dot[j])


DIVISOR_MIN = 0.05  # floor of eq. 54's 1 − λ·x: no positive tension solves it past x = 1/λ


@njit(cache=True)
def tension_divisor(lam, x):
    """1 − λ·x of eq. 54 (scalar or array), floored at DIVISOR_MIN: the stiffness k/(1 − λ·x)
    grows without bound towards x = 1/λ, and the cap keeps the tension finite there."""
    return np.maximum(1.0 - lam * x, DIVISOR_MIN)


@njit(cache=True)
def cable_tension_law(k, lam, c_a, x, x_dot):
    """Eq. 39 (λ = 0) or eq. 54 solved for t: t = (k·x + c_a·ẋ)/(1 − λ·x), with x the stretch (m)
    and ẋ its rate (m/s); scalar or array, not yet clipped to a pulling cable."""
    return (k * x + c_a * x_dot) / tension_divisor(lam, x)


@njit(cache=True)
def tension_into(m, x, x_dot, out):
    """Cable tension (N) from stretch x (m) and its rate (m/s): eq. 39 (linear) or eq. 54
    (variable), see :func:`cable_tension_law`. A cable only pulls: t = 0 when slack (x <= 0) or
    when the damper would push. Returns the number of slack cables."""
    slack = 0
    for j in range(m.n_cables):
        if x[j] <= 0.0:
            out[j] = 0.0
            slack += 1
            continue
        t = cable_tension_law(m.k[j], m.lam[j], m.c_a[j], x[j], x_dot[j])
        out[j] = t if t > 0.0 else 0.0
    return slack


def friction_shapes(c_s: float, sign_law: bool, theta_dot) -> np.ndarray:
    """:func:`friction_shape` at motor-shaft velocities θ̇ of any shape (rad/s), through one compiled
    version of it whatever the shape and memory layout (twin.model.compiled.kernel_array)."""
    td = np.asarray(theta_dot, dtype=float)
    return friction_shape(float(c_s), bool(sign_law), kernel_array(td.reshape(-1))).reshape(td.shape)


def f_friction(model: Model, theta_dot) -> np.ndarray:
    """Friction forces (N) at motor-shaft velocities θ̇ (..., n_cables) rad/s, eqs. 36-37."""
    return model.f_s * friction_shapes(model.c_s, model.friction_sign, theta_dot)


def tension(model: Model, x_c, x_c_dot) -> np.ndarray:
    """Cable tensions (N) from stretch x_c (m) and rate (m/s), eqs. 39/54, zero when slack."""
    x = kernel_array(x_c)
    xd = kernel_array(np.broadcast_to(np.asarray(x_c_dot, dtype=float), x.shape))
    if model.cable_model == RIGID:
        raise ValueError("the rigid cable model has no tension law: tensions follow from eq. 29")
    t = np.maximum(cable_tension_law(model.k, model.lam, model.c_a, x, xd), 0.0)
    return np.where(x > 0.0, t, 0.0)


# --- the full model -------------------------------------------------------------------------


@njit(cache=True)
def accelerations_into(m, alpha, theta, alpha_dot, theta_dot, f, work, out_add, out_tdd, t_out):
    """Full model, eqs. 27-32: α̈ and θ̈ from the state and the motor forces f (N).

    Elastic cables (linear/variable): M_m·α̈ + c_m + g = Z·t (eq. 30) and
    I_a·θ̈ = (r_d/R)(f − f_friction − t) (eq. 29) with t from the stretch (eq. 27). Rigid cables:
    M·α̈ + c + g = Z(f − f_friction) (eq. 32 with ẍ_c = 0) and θ̈ = (Zᵀα̈ + Żᵀα̇)·R/r_d.
    ``work`` is a scratch tuple from :func:`scratch_buffers`. Returns the number of slack cables.
    """
    tab, lc, Z, Zd, Mm, cm, g, M, c, ff = work
    evaluate_into(m, alpha, alpha_dot, tab, lc, Z, Zd, Mm, cm, g)
    friction_into(m, theta_dot, ff)
    slack = 0
    if m.cable_model == RIGID:
        motor_terms(m, Z, Zd, alpha_dot, Mm, cm, M, c)
        out_add[:] = np.linalg.solve(M, Z @ (f - ff) - c - g)
        out_tdd[:] = (Z.T @ out_add + Zd.T @ alpha_dot) / m.rho
        # Tension the cables carry (eq. 29), for reporting.
        t_out[:] = f - ff - m.I_a * out_tdd / m.rho
    else:
        x = lc - m.l_c0 + m.rho * theta
        x_dot = m.rho * theta_dot - Z.T @ alpha_dot
        slack = tension_into(m, x, x_dot, t_out)
        out_add[:] = np.linalg.solve(Mm, Z @ t_out - cm - g)
        out_tdd[:] = m.rho * (f - ff - t_out) / m.I_a
    return slack


def scratch_buffers(model: Model):
    """Scratch arrays for the compiled kernels (allocated once per process, not per tick)."""
    N, nc = model.n_joints, model.n_cables
    return (
        np.empty((N, xjoint.N_ROWS, 3)),
        np.empty(nc),
        np.empty((N, nc)),
        np.empty((N, nc)),
        np.empty((N, N)),
        np.empty(N),
        np.empty(N),
        np.empty((N, N)),
        np.empty(N),
        np.empty(nc),
    )


class Accelerations(NamedTuple):
    alpha_ddot: np.ndarray  # (N,) rad/s²
    theta_ddot: np.ndarray  # (n_cables,) rad/s²
    tension: np.ndarray  # (n_cables,) N
    n_slack: int


def accelerations(model: Model, alpha, theta, alpha_dot, theta_dot, f) -> Accelerations:
    """The full model with friction and elastic cables (eqs. 27-32) at one state."""
    N, nc = model.n_joints, model.n_cables
    args = [kernel_array(v) for v in (alpha, theta, alpha_dot, theta_dot, f)]
    for name, v, n in zip(("alpha", "theta", "alpha_dot", "theta_dot", "f"), args, (N, nc, N, nc, nc)):
        if v.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), got {v.shape}")
    add, tdd, t = np.empty(N), np.empty(nc), np.empty(nc)
    a, th, ad, thd, f_ = args
    slack = accelerations_into(model, a, th, ad, thd, f_, scratch_buffers(model), add, tdd, t)
    return Accelerations(add, tdd, t, int(slack))
