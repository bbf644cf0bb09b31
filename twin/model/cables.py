"""Cable transmission of the X-joint neck (3-X paper §3.1, eqs. 3-23, with ERRATA.md).

The variable length of cable j is the sum, over the joints it runs along, of the length of its
routing case (a)-(d) at that joint's angle; hence Z_ij = −∂l_cj/∂α_i (eq. 22) depends on α_i only
and its time derivative is Ż_ij = −(∂²l_cj/∂α_i²)·α̇_i. All exact (jets, see ``twin.model.jet``).

Elongation sign: we use x_c = l_c − l_c0 + (r_d/R)·θ, the physical stretch (> 0 under tension,
so t = k·x_c of eqs. 39/54 is positive). Eq. 27 as printed has −(r_d/R)·θ, which contradicts
eq. 20's θ convention (θ > 0 winds the cable in); eqs. 28-35 use the opposite sign of x_c to ours.
"""

from __future__ import annotations

import numpy as np

from twin.model import xjoint
from twin.model.compiled import kernel_array, njit
from twin.model.numeric import Model


@njit(cache=True)
def cable_terms(m, tab, alpha_dot, lc, Z, Zd):
    """From a filled jet table ``tab`` (N, N_ROWS, 3): l_c (n_cables,), Z and Ż (N, n_cables)."""
    for j in range(m.n_cables):
        lc[j] = 0.0
        for i in range(m.n_joints):
            row = m.case_rows[j, i]
            if row >= 0:
                lc[j] += tab[i, row, 0]
                Z[i, j] = -tab[i, row, 1]
                Zd[i, j] = -tab[i, row, 2] * alpha_dot[i]
            else:
                Z[i, j] = 0.0
                Zd[i, j] = 0.0


@njit(cache=True)
def _cables_batch(m, alpha, alpha_dot):
    B = alpha.shape[0]
    lc = np.empty((B, m.n_cables))
    Z = np.empty((B, m.n_joints, m.n_cables))
    Zd = np.empty((B, m.n_joints, m.n_cables))
    tab = np.empty((m.n_joints, xjoint.N_ROWS, 3))
    for k in range(B):
        for i in range(m.n_joints):
            xjoint.joint_jets(m.L, m.b, m.r, alpha[k, i], tab[i])
        cable_terms(m, tab, alpha_dot[k], lc[k], Z[k], Zd[k])
    return lc, Z, Zd


def batch(model: Model, alpha, alpha_dot=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(l_c, Z, Ż) for ``alpha`` of shape (..., N) rad and ``alpha_dot`` rad/s (default 0)."""
    alpha = np.asarray(alpha, dtype=float)
    if alpha.shape[-1:] != (model.n_joints,):
        raise ValueError(f"alpha must have shape (..., {model.n_joints}), got {alpha.shape}")
    lead = alpha.shape[:-1]
    a2 = kernel_array(alpha.reshape(-1, model.n_joints))
    ad2 = np.zeros_like(a2) if alpha_dot is None else kernel_array(
        np.broadcast_to(np.asarray(alpha_dot, dtype=float), alpha.shape).reshape(-1, model.n_joints))
    lc, Z_, Zd = _cables_batch(model, a2, ad2)
    return (lc.reshape(lead + (model.n_cables,)), Z_.reshape(lead + Z_.shape[1:]), Zd.reshape(lead + Zd.shape[1:]))


def l_c(model: Model, alpha) -> np.ndarray:
    """Variable cable lengths (m), eqs. 3-19; shape (..., n_cables)."""
    return batch(model, alpha)[0]


def Z(model: Model, alpha) -> np.ndarray:
    """Cable transmission matrix Z = −∂l_c/∂α (eq. 22), m/rad; shape (..., N, n_cables)."""
    return batch(model, alpha)[1]


def Z_dot(model: Model, alpha, alpha_dot) -> np.ndarray:
    """Time derivative of Z along α̇ (rad/s), m/s per rad; shape (..., N, n_cables)."""
    return batch(model, alpha, alpha_dot)[2]


def theta_rigid(model: Model, alpha) -> np.ndarray:
    """Motor-shaft angles (rad) of inextensible cables, eq. 20: θ = −(R/r_d)(l_c − l_c0)."""
    return -(l_c(model, alpha) - model.l_c0) / model.rho
