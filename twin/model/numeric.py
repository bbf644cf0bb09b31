"""The numeric model: a parameter set flattened into arrays for the compiled kernels.

``build(params)`` is called once; every model function then takes the resulting :class:`Model`
(an immutable NamedTuple that numba passes by value) and state arrays, and returns arrays.
Variants the papers compare are built from the same parameters: another cable model, friction
off, or pulleys neglected (r = 0, the controller variant of 3-X paper Table 3).
"""

from __future__ import annotations

from typing import Any, Literal, NamedTuple

import numpy as np

from twin.model import xjoint
from twin.model.params import Params

CABLE_MODELS = ("rigid", "linear", "variable")
RIGID, LINEAR, VARIABLE = 0, 1, 2


CableModelName = Literal["rigid", "linear", "variable"]  # the index into CABLE_MODELS is Model.cable_model

class Model(NamedTuple):
    L: float  # m, diagonal bar length
    b: float  # m, base/top bar length
    r: float  # m, pulley radius (0 when pulleys are neglected)
    rho: float  # m/rad, r_d / R: cable length per motor-shaft radian
    n_joints: int
    n_cables: int
    case_rows: np.ndarray  # (n_cables, n_joints) int64: jet-table row of the routing case, −1 if none
    k_left: np.ndarray  # (N,) N/m
    k_right: np.ndarray  # (N,) N/m
    l0: np.ndarray  # (N,) m, spring rest lengths
    m_body: np.ndarray  # (N, 3) kg: diagonal A–D, diagonal B–C, top bar of each joint
    I_body: np.ndarray  # (N, 3) kg·m² about each centre of mass
    gravity: float  # m/s², along −y of the base frame
    I_a: float  # kg·m², geared motor inertia at the motor shaft
    f_s: np.ndarray  # (n_cables,) N, dry friction (zeros when friction is off)
    c_s: float  # s/rad
    friction_sign: bool  # eq. 36 instead of eq. 37
    cable_model: int  # RIGID, LINEAR or VARIABLE
    k: np.ndarray  # (n_cables,) N/m, cable stiffness of the chosen model
    lam: np.ndarray  # (n_cables,) 1/m, eq. 54 (zeros for the linear model)
    c_a: np.ndarray  # (n_cables,) N·s/m
    l_c0: np.ndarray  # (n_cables,) m, variable cable lengths at α = 0 (eq. 20)
    t_min: float  # N
    f_min: float  # N
    f_max: float  # N


def build(
    params: Params,
    cable_model: CableModelName | None = None,
    *,
    friction: bool = True,
    pulleys: bool = True,
) -> Model:
    """Flatten ``params`` into a :class:`Model` (see the module docstring for the variants)."""
    g, n, nc = params.geometry, params.n_joints, params.n_cables
    name = cable_model or params.cables.model
    if name not in CABLE_MODELS:
        raise ValueError(f"cable_model must be one of {CABLE_MODELS}, got {name!r}")
    case_rows = np.full((nc, n), -1, dtype=np.int64)
    for j, route in enumerate(params.routes):
        for joint, case in route:
            case_rows[j, joint] = xjoint.CASE_ROW[case]
    bars = params.bars
    cable = params.cables.variable if name == "variable" else params.cables.linear
    lam = np.asarray(params.cables.variable.lam if name == "variable" else (0.0,) * nc, dtype=float)
    r = g.r if pulleys else 0.0
    partial: dict[str, Any] = dict(
        L=g.L,
        b=g.b,
        r=r,
        rho=g.r_d / g.R,
        n_joints=n,
        n_cables=nc,
        case_rows=case_rows,
        k_left=np.asarray(params.springs.k_left, dtype=float),
        k_right=np.asarray(params.springs.k_right, dtype=float),
        l0=np.asarray(params.springs.l0, dtype=float),
        m_body=np.column_stack([bars.m_diagonal, bars.m_diagonal, bars.m_top]).astype(float),
        I_body=np.column_stack([bars.I_diagonal, bars.I_diagonal, bars.I_top]).astype(float),
        gravity=params.environment.gravity,
        I_a=params.motors.I_a,
        f_s=np.asarray(params.friction.f_s if friction else (0.0,) * nc, dtype=float),
        c_s=params.friction.c_s,
        friction_sign=params.friction.model == "sign",
        cable_model=CABLE_MODELS.index(name),
        k=np.asarray(cable.k, dtype=float),
        lam=lam,
        c_a=np.asarray(cable.c_a, dtype=float),
        t_min=params.limits.t_min,
        f_min=params.limits.f_min,
        f_max=params.limits.f_max,
    )
    table = xjoint.jets(g.L, g.b, r, np.zeros(n))
    l_c0 = np.array([sum(table[i, row, 0] for i, row in enumerate(rows) if row >= 0) for rows in case_rows])
    return Model(l_c0=l_c0, **partial)
