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

The robot truth's friction (twin.sim.truth) is not a smooth function of θ̇: a motor at rest
holds against any load below its static level. It enters the same step as an unknown force λ
per motor, bounded by the static level when the motor ends the substep at rest and equal to the
kinetic (Stribeck) level when it slides; the 4 unknowns are found by projected Gauss-Seidel on
θ̇⁺ = θ̇_free − W·λ with W = h·ρ·(A⁻¹)_θθ (time stepping with set-valued friction, Moreau/Jean).
Its levels depend on the motor force and the cable tension (gear losses, pulley friction), taken
at the start of the substep.
"""

from __future__ import annotations

import math

import numpy as np

from twin.model import xjoint
from twin.model.cables import cable_terms
from twin.model.compiled import njit
from twin.model.dynamics import chain_terms, evaluate_into, friction_into, motor_terms, tension_divisor
from twin.model.numeric import LINEAR, RIGID
from twin.model.xjoint import joint_jets

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


# Columns of the robot-friction table ``rf`` (one row per cable), see twin.sim.truth.FrictionTruth.
RF_F_PLUS, RF_F_MINUS, RF_STATIC, RF_V_S, RF_VISCOUS, RF_LOSS_FWD, RF_LOSS_BWD, RF_PULLEY, RF_T_REF = range(9)
RF_COLUMNS = 9
PGS_SWEEPS = 12  # projected Gauss-Seidel sweeps: the 4x4 Delassus matrix is well conditioned


@njit(cache=True)
def _coulomb_level(rf, j, direction, f_j, t_j):
    """Kinetic Coulomb level (N) of cable j's motor resisting motion in ``direction`` (±1), floored
    at 0: Table 1's f_s (scaled, with its asymmetry), which holds at the reference load T_ref, plus
    what the load adds beyond it: pulley friction ∝ tension, and the gear's meshing loss ∝ the
    driving load (the motor force when it winds, θ̇ > 0; the tension when the cable drives it back)."""
    if direction > 0:
        base, gear = rf[j, RF_F_PLUS], rf[j, RF_LOSS_FWD] * (f_j - rf[j, RF_T_REF])
    else:
        base, gear = rf[j, RF_F_MINUS], rf[j, RF_LOSS_BWD] * (t_j - rf[j, RF_T_REF])
    return max(base + rf[j, RF_PULLEY] * (t_j - rf[j, RF_T_REF]) + gear, 0.0)


@njit(cache=True)
def _set_valued_friction(rf, h, rho, X, theta_dot, f, t, lam, W):
    """Friction forces ``lam`` (N, positive resisting θ̇ > 0) of the linearly implicit step, with
    stiction: X = A⁻¹[rhs | E_θ]. A motor whose friction can hold it (|λ| ≤ static level) ends
    the substep at rest exactly; otherwise it slides against the kinetic (Stribeck) level. The
    4x4 complementarity problem is solved by projected Gauss-Seidel (Moreau/Jean time stepping).
    ``W``: scratch (n_cables × n_cables) for the Delassus matrix."""
    nc = lam.shape[0]
    N = X.shape[0] - nc
    for i in range(nc):
        for j in range(nc):
            W[i, j] = h * rho * X[N + i, j + 1]
    lam[:] = 0.0
    for _ in range(PGS_SWEEPS):
        for j in range(nc):
            v = X[N + j, 0]  # θ̇_j after the substep with every friction but its own
            for i in range(nc):
                if i != j:
                    v -= W[j, i] * lam[i]
            need = v / W[j, j]  # the friction that would stop motor j exactly
            up = _coulomb_level(rf, j, 1.0, f[j], t[j]) * rf[j, RF_STATIC]
            lo = _coulomb_level(rf, j, -1.0, f[j], t[j]) * rf[j, RF_STATIC]
            if -lo <= need <= up:
                lam[j] = need  # sticks
            else:
                d = 1.0 if need > 0 else -1.0
                u = theta_dot[j] / rf[j, RF_V_S]
                stribeck = 1.0 + (rf[j, RF_STATIC] - 1.0) * math.exp(-u * u)
                lam[j] = d * _coulomb_level(rf, j, d, f[j], t[j]) * stribeck


@njit(cache=True)
def _cholesky_solve(A, L, X, ncols):
    """Solve A·Y = X for the first ``ncols`` columns of ``X`` in place, A symmetric positive definite
    (the step's matrix is 𝕄 plus positive semi-definite cable and friction terms), by Cholesky
    A = L·Lᵀ from A's lower triangle (``L``: scratch of A's shape). Why not LAPACK: for 7 unknowns
    its call and allocations cost more than the arithmetic. Returns False, X unsolved, if a pivot
    is not positive (a non-finite state): the caller then solves by LU."""
    n = A.shape[0]
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return False
        ljj = math.sqrt(d)
        L[j, j] = ljj
        for i in range(j + 1, n):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / ljj
    for c in range(ncols):
        for i in range(n):  # L·y = x
            acc = X[i, c]
            for k in range(i):
                acc -= L[i, k] * X[k, c]
            X[i, c] = acc / L[i, i]
        for i in range(n - 1, -1, -1):  # Lᵀ·y' = y
            acc = X[i, c]
            for k in range(i + 1, n):
                acc -= L[k, i] * X[k, c]
            X[i, c] = acc / L[i, i]
    return True


@njit(cache=True)
def carve(pool, N, nc):
    """The scratch arrays of one twin as views of one array ``pool`` (one array crosses into the
    compiled call instead of 23: numba unboxes each argument array on every call). Returns the
    model's scratch (as twin.model.dynamics.scratch_buffers), :func:`step`'s, and the length used.

    :func:`step`'s: stretch x, its rate ẋ, K, D, ∂f_fr/∂θ̇, λ per cable; A and its Cholesky factor,
    rhs, X = A⁻¹[rhs | E_θ] (solved in place); the Delassus matrix W; the state at the start of the
    step; the α at which the jet table was filled at the end of the last step, and 1.0 after it if
    the table is still valid (so ``pool`` starts zeroed)."""
    n = N + nc
    o = N * xjoint.N_ROWS * 3
    tab = pool[:o].reshape((N, xjoint.N_ROWS, 3))
    # Per cable: lc, ff (the model's), x, xd, K, D, dff, λ (the step's).
    lc, ff, x, xd = pool[o : o + nc], pool[o + nc : o + 2 * nc], pool[o + 2 * nc : o + 3 * nc], pool[o + 3 * nc : o + 4 * nc]
    o += 4 * nc
    K, D, dff, lam = pool[o : o + nc], pool[o + nc : o + 2 * nc], pool[o + 2 * nc : o + 3 * nc], pool[o + 3 * nc : o + 4 * nc]
    o += 4 * nc
    Z, Zd = pool[o : o + N * nc].reshape((N, nc)), pool[o + N * nc : o + 2 * N * nc].reshape((N, nc))
    o += 2 * N * nc
    Mm, M = pool[o : o + N * N].reshape((N, N)), pool[o + N * N : o + 2 * N * N].reshape((N, N))
    o += 2 * N * N
    cm, g, c = pool[o : o + N], pool[o + N : o + 2 * N], pool[o + 2 * N : o + 3 * N]
    o += 3 * N
    A, LA = pool[o : o + n * n].reshape((n, n)), pool[o + n * n : o + 2 * n * n].reshape((n, n))
    o += 2 * n * n
    rhs = pool[o : o + n]
    o += n
    X = pool[o : o + n * (nc + 1)].reshape((n, nc + 1))
    o += n * (nc + 1)
    W = pool[o : o + nc * nc].reshape((nc, nc))
    o += nc * nc
    s0 = pool[o : o + 2 * n]
    o += 2 * n
    tab_at = pool[o : o + N + 1]
    o += N + 1
    work = (tab, lc, Z, Zd, Mm, cm, g, M, c, ff)
    scr = (x, xd, K, D, dff, lam, A, LA, rhs, X, W, s0, tab_at)
    return work, scr, o


def scratch(n_joints: int, n_cables: int) -> np.ndarray:
    """The zeroed ``pool`` of :func:`carve` for a twin of ``n_joints`` joints and ``n_cables`` cables."""
    return np.zeros(carve(np.empty(1 << 14), n_joints, n_cables)[2])


@njit(cache=True)
def step(m, s, f, h, n_sub, work, scr, t_out, x_out, fr_table, x_off):
    """Advance state ``s`` = (α, θ, α̇, θ̇) in place by ``n_sub`` substeps of ``h`` seconds with the
    motor forces ``f`` (N) held. Writes the cable tensions of the last substep into ``t_out`` and
    the cable stretch at the end (m, zero for rigid cables) into ``x_out``. ``work``: the model's
    scratch (twin.model.dynamics.scratch_buffers); ``scr``: this step's (:func:`scratch`).

    ``fr_table``: the robot truth's friction table (n_cables × RF_COLUMNS, elastic cables only), used
    instead of the model's eq. 37 (build the model with friction off), or an empty (0, RF_COLUMNS)
    table. ``x_off``: creep stretch (m) per cable that the elastic law does not carry.

    Returns a bit field: bit j set if cable j is slack at the end; bit 62 set if a joint reached
    the flat singularity (the step is then not taken and the state is left unchanged).
    """
    tab, lc, Z, Zd, Mm, cm, g, M, c, ff = work
    x, xd, K, D, dff, lam, A, LA, rhs, X, W, s0, tab_at = scr
    N, nc = m.n_joints, m.n_cables
    n = N + nc
    alpha, theta, alpha_dot, theta_dot = s[:N], s[N:n], s[n : n + N], s[n + N :]
    robot = fr_table.shape[0] == nc
    s0[:] = s
    # The last step ended by filling the jet table at its final α; unless the state was changed
    # since, the first substep starts there and needs no new jets.
    cached = tab_at[N] == 1.0
    for i in range(N):
        cached = cached and tab_at[i] == alpha[i]
    tab_at[N] = 0.0  # the substeps overwrite the table
    for sub in range(n_sub):
        if sub == 0 and cached:
            cable_terms(m, tab, alpha_dot, lc, Z, Zd)
            chain_terms(m, alpha, alpha_dot, tab, Mm, cm, g)  # = evaluate_into with the jets already there
        else:
            evaluate_into(m, alpha, alpha_dot, tab, lc, Z, Zd, Mm, cm, g)
        if m.cable_model == RIGID:
            theta[:] = -(lc - m.l_c0) / m.rho
            theta_dot[:] = (Z.T @ alpha_dot) / m.rho
        friction_into(m, theta_dot, ff)
        _friction_slope(m, theta_dot, dff)
        if m.cable_model == RIGID:
            motor_terms(m, Z, Zd, alpha_dot, Mm, cm, M, c)
            Wr = Z * (dff / m.rho)  # friction torque slope through the cables, Z·diag(∂f/∂θ̇)·Zᵀ/ρ
            Af = M + h * (Wr @ Z.T)
            rf = M @ alpha_dot + h * (Z @ (f - ff) - c - g) + h * (Wr @ (Z.T @ alpha_dot))
            new_dot = np.linalg.solve(Af, rf)
            theta_ddot = (Z.T @ new_dot - Z.T @ alpha_dot) / (h * m.rho)
            t_out[:] = f - ff - m.I_a * theta_ddot / m.rho
            alpha_dot[:] = new_dot
            alpha += h * alpha_dot
        else:
            for j in range(nc):
                x[j] = lc[j] - m.l_c0[j] + m.rho * theta[j] - x_off[j]
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
            ncols = 1
            if robot:
                for j in range(nc):
                    A[N + j, N + j] += h * m.rho * fr_table[j, RF_VISCOUS]  # viscous friction, implicit
                ncols = nc + 1
                X[:, 1:] = 0.0
                for j in range(nc):
                    X[N + j, j + 1] = 1.0
            X[:, 0] = rhs
            if not _cholesky_solve(A, LA, X, ncols):
                X[:, :ncols] = np.linalg.solve(A, X[:, :ncols])
            if robot:
                _set_valued_friction(fr_table, h, m.rho, X, theta_dot, f, t_out, lam, W)
                for a in range(n):
                    v = X[a, 0]
                    for j in range(nc):
                        v -= (h * m.rho * lam[j]) * X[a, j + 1]
                    rhs[a] = v
            else:
                rhs[:] = X[:, 0]
            alpha_dot[:] = rhs[:N]
            theta_dot[:] = rhs[N:]
            alpha += h * alpha_dot
            theta += h * theta_dot
        for i in range(N):
            if abs(alpha[i]) >= ALPHA_FLAT:
                s[:] = s0
                return np.int64(1) << 62
    # The cable lengths (and, for rigid cables, Z) at the end: no chain terms needed.
    for i in range(N):
        joint_jets(m.L, m.b, m.r, alpha[i], tab[i])
        tab_at[i] = alpha[i]
    tab_at[N] = 1.0
    cable_terms(m, tab, alpha_dot, lc, Z, Zd)
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


ACT_K_T, ACT_RHO, ACT_I_MAX, ACT_DECAY, ACT_MEAN_GAIN, ACT_RIPPLE, ACT_RIPPLE_N, ACT_COGGING, ACT_COGGING_N = range(9)


@njit(cache=True)
def actuate(f, theta, current, kt_factor, act, out):
    """Force at the cable (N) for the commanded forces ``f`` over one period: the driver's current
    I = f·ρ/k_t saturated at I_max, a first-order current loop (``current`` is its state, A;
    act[ACT_DECAY] = e^(−T/τ), act[ACT_MEAN_GAIN] = τ/T·(1 − e^(−T/τ)) its mean over the held
    period), the motor's true torque constant, block-commutation ripple and cogging (functions of
    the motor angle θ). ``act``: the ACT_* values."""
    k_t, rho, i_max = act[ACT_K_T], act[ACT_RHO], act[ACT_I_MAX]
    for j in range(f.shape[0]):
        i_cmd = min(max(f[j] * rho / k_t, -i_max), i_max)
        mean = i_cmd + (current[j] - i_cmd) * act[ACT_MEAN_GAIN]
        current[j] = i_cmd + (current[j] - i_cmd) * act[ACT_DECAY]
        torque = k_t * kt_factor[j] * mean * (1.0 + act[ACT_RIPPLE] * math.cos(act[ACT_RIPPLE_N] * theta[j]))
        out[j] = torque / rho + act[ACT_COGGING] * math.sin(act[ACT_COGGING_N] * theta[j])


@njit(cache=True)
def creep_update(creep, tension, k, ratio, gain):
    """Kelvin creep element in series with the elastic law: its stretch (m) relaxes towards
    ratio·t/k with ``gain`` = 1 − e^(−T/τ) per period."""
    for j in range(creep.shape[0]):
        creep[j] += (ratio * tension[j] / k[j] - creep[j]) * gain


# Slots of the ``io`` array of :func:`advance` (what varies per tick or per twin, as numbers, so the
# kernel's arguments are the same arrays every call).
IO_H, IO_SUBSTEPS, IO_ACTUATION, IO_CREEP, IO_CREEP_RATIO, IO_CREEP_GAIN, IO_BACKLASH, IO_RAD_PER_COUNT = range(8)
IO_SIZE = 8
NEAR_FLAT = math.radians(160.0)  # rad: a joint within 20° of its flat singularity is reported


def observation_size(n_joints: int, n_cables: int) -> int:
    """Length of :func:`advance`'s ``obs``: α, θ, α̇, θ̇, tension, stretch, encoders, near_singular."""
    return 2 * n_joints + 5 * n_cables + 1


@njit(cache=True)
def advance(m, s, cmd, io, pool, t_out, x_out, fr_table, creep, current, kt_factor, act, force, obs):
    """One control period of the twin in one call: the motors' applied force for the command
    ``cmd`` (:func:`actuate`, when io[IO_ACTUATION]), :func:`step` with io[IO_SUBSTEPS] substeps of
    io[IO_H] s, the creep element (:func:`creep_update`, when io[IO_CREEP]), and what the bridge
    and the truth report, written into ``obs`` (:func:`observation_size`): the state, tensions,
    stretch, the encoder readings (θ through the gear backlash on slack cables, truncated to
    whole counts of io[IO_RAD_PER_COUNT] rad) and 1.0 if a joint is near its flat singularity.
    Returns :func:`step`'s bit field."""
    N, nc = m.n_joints, m.n_cables
    n = N + nc
    f = cmd
    if io[IO_ACTUATION] != 0.0:
        actuate(cmd, s[N:n], current, kt_factor, act, force)
        f = force
    work, scr, _ = carve(pool, N, nc)
    bits = step(m, s, f, io[IO_H], int(io[IO_SUBSTEPS]), work, scr, t_out, x_out, fr_table, creep)
    if io[IO_CREEP] != 0.0:
        creep_update(creep, t_out, m.k, io[IO_CREEP_RATIO], io[IO_CREEP_GAIN])
    flat = (bits >> 62) & 1
    obs[: 2 * n] = s
    obs[2 * n : 2 * n + nc] = t_out
    obs[2 * n + nc : 2 * n + 2 * nc] = x_out
    q, backlash = io[IO_RAD_PER_COUNT], io[IO_BACKLASH]
    near = 1.0 if flat else 0.0
    for j in range(nc):
        seen = s[N + j]
        if backlash != 0.0 and not flat and (bits >> j) & 1:
            seen -= backlash  # a slack cable lets the motor shaft turn through the backlash
        obs[2 * n + 2 * nc + j] = math.floor(seen / q) * q  # = twin.sim.sensors.quantise_encoder
    for i in range(N):
        if abs(s[i]) >= NEAR_FLAT:
            near = 1.0
    obs[2 * n + 3 * nc] = near
    return bits
