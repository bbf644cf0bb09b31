"""A stuck encoder told by the fourth cable: the consistency of the four encoders with α̂.

The 3-X neck has four cables for three joints, so the four motor angles θ over-determine α: the
lengths measured through the encoders must agree with the lengths of the geometry at α̂, up to the
cables' stretch and the model's errors. An encoder whose reading freezes while its motor turns
(stuck) breaks that agreement by the length its cable really moved, which the speed check of
``controller.service`` (``MOTOR_SPEED_MAX_RAD_S``) cannot see.

The residual (m of cable), for every cable j, from eq. 27 in our sign (docs/model.md)::

    e_j = l_cj(α̂) − l_c0j + (r_d/R)·θ_j − x_j(f)

is zero when the encoders, α̂ and the stretch agree: l_c(α̂) of eqs. 3-19 (routing, pulleys),
θ at the motor shaft with eq. 20's sign (θ > 0 winds the cable in), and x_j the stretch of eq. 54
at rest (ẋ = 0) solved for x, x = t/(k + λ·t), with the tension t = f − f_friction(θ̇) (eq. 41
without the motor inertia, the friction of eq. 37), never below 0 (a rigid cable model gives
x = 0, the linear one λ = 0).

α̂ is a fit of those lengths (eq. 33 or eq. 35), so part of any error goes into α̂: what is left
is the component of e along the null vector n of Z(α̂) (eqs. 22-23; n ∝ (−Z1⁻¹Z2, 1), the
internal tension direction of eqs. 63-65, positive for the prototype, ERRATA), the *parity*

    s = nᵀe / |n|   (m)

which an error δα of α̂ does not change to first order (nᵀZᵀδα = 0): s means the same for every
law's α̂ (rigid or elastic), even one tick old. One parity equation detects one faulty encoder
but cannot tell which: each hypothesis "encoder j alone is wrong" explains s exactly, by

    r_j = s·|n|/n_j   (m of cable j; r_j/(r_d/R) rad at the motor)

the length cable j's encoder would have missed (for a stuck encoder j, r_j grows by the length
its cable moved since the freeze, with the sign of measured − true). :class:`EncoderConsistency`
names the suspect from what the parity cannot give: a stuck reading does not change.

Slack: the parity assumes every cable taut, carrying the stretch its force gives. A slack cable j
is longer than its path by δ_j ≥ 0 and carries no stretch, so its e_j is −δ_j, and without the
stretch term (the parity of the lengths alone, s_l = s + nᵀx/|n|) slack only ever lowers s_l, n
being positive (a neck the cables can hold, eqs. 63-65). After an e-stop dropped a moving neck,
three cables stayed slack (up to 20 mm of parity) for more than 10 s on the robot truth: the
motors' stiction (19-24 N) exceeds the hold's forces (t_min = 8.5 N), so nothing wound them in
until a move did, and a check blind to slack named a healthy encoder stuck 0.56 s after the
release (audit of 2026-11-28). (The controller now winds them in after a release,
``controller.take_up``, in about 1.4 s: the check allows the slack meanwhile.) The drives only wind the slack in, so the service tells the check
when they come back (``settling``): the check measures the slack then (the largest −s_l) and
allows it, and only it, below −threshold while it lasts, shrinking it as s_l shows it taken up.
A stuck encoder still grows the parity past that allowance (or above +threshold, where slack
never goes) by the length its cable moves; once the slack is gone (s_l ≥ 0) the check looks
away for ``SLACK_SETTLE_S`` (the cable's snap) and judges as always.

What limits the threshold (docs/safety.md, "Stuck encoder", measured by
``docs/safety/encoder_residual.py``): the tension behind x is known only up to the motors'
friction (stiction at rest: ± 1.3·f_s ≈ ±20 N, a few mm of stretch on the soft long cable), not
the encoders' counts (2.5 µm of cable).

Units: angles in rad (θ at the motor shaft), lengths in m, forces in N, times in s.
"""

from __future__ import annotations

import math

import numpy as np

from twin.model import xjoint
from twin.model.cables import cable_terms
from twin.model.compiled import bind, kernel_array, njit
from twin.model.dynamics import friction_into
from twin.model.estimation import long_cable, short_cables, solve_into
from twin.model.numeric import RIGID, Model, build
from twin.model.params import Params

# Measured, not guessed (docs/safety.md, "Stuck encoder"; docs/safety/encoder_residual.py): the
# largest |s| of laws 1-3 on the robot truth over the §7 control test and the §5.2.2 trajectory,
# seeds 0-2, was 5.83 mm; the threshold is 1.5 times that, rounded up to the next 0.5 mm.
THRESHOLD_M = 9.0e-3
# The parity must stay beyond the threshold this long before it is a fault: one tick's spike (an
# encoder crossing the gear backlash, a friction estimate flipping sign) is not. 25 ticks at 500 Hz.
PERSISTENCE_S = 0.05
# Encoders whose frozen readings account for the parity's growth within this fraction of the
# threshold are named together: the one parity equation cannot tell them apart (module docstring).
SUSPECT_TIE = 0.25
# s the check looks away once the slack it allowed is taken up (module docstring, "Slack"): the
# cable that snaps taut overshoots the stretch at rest (audit of 2026-11-28: the parity went from
# −25 mm to +8.6 mm within 0.4 s, 20 ms of it above 8 mm, as a campaign's first move took up the
# slack of an e-stop's fall), as the bridge's ramp does when the drives come back
# (controller.service.ENCODER_CHECK_SETTLE_S, the same 0.5 s).
SLACK_SETTLE_S = 0.5


def detector_model(params: Params) -> Model:
    """The model the check runs on, whatever the law: the parameter file's cable model (Table 2's
    variable stiffness for the prototype), its friction (eq. 37) and pulleys. A law's own model
    may be rigid (laws 1-2), which would leave the whole stretch in the residual; so would a
    parameter set that says its cables are rigid (a campaign's own set: every campaign aborted
    on a stuck-encoder fault within 0.05-11.5 s, audit of session 43): the real cables stretch
    whatever a set says, and the check then takes the set's variable-stiffness section."""
    model = "variable" if params.cables.model == "rigid" else None
    return build(params, model, friction=True, pulleys=True)


@njit(cache=True)
def parity_into(m, short, long, theta, alpha_hat, force, theta_dot, tab, lc, Z, Zd, zero, Z1, LU, y, rhs, x, n, r):
    """The parity s (m, returned) and the per-encoder residual r (m, into ``r``) of one tick
    (module docstring). ``theta`` (rad), ``alpha_hat`` (rad), ``force`` (N) and ``theta_dot``
    (rad/s) as the controller has them; the rest is scratch: tab (N, N_ROWS, 3), lc, x, n (nc,),
    Z, Zd (N, nc), zero (N,) all zeros, Z1, LU (N, N), y, rhs (N,). A non-finite input gives
    s = NaN and r all NaN (the caller's fault), never an exception."""
    N, nc = m.n_joints, m.n_cables
    ok = True
    for i in range(N):
        ok = ok and math.isfinite(alpha_hat[i])
    for j in range(nc):
        ok = ok and math.isfinite(theta[j]) and math.isfinite(force[j]) and math.isfinite(theta_dot[j])
    if not ok:
        for j in range(nc):
            r[j] = math.nan
        return math.nan
    # l_c(α̂) and Z(α̂): eqs. 3-19 and 22.
    for i in range(N):
        xjoint.joint_jets(m.L, m.b, m.r, alpha_hat[i], tab[i])
    cable_terms(m, tab, zero, lc, Z, Zd)
    # Stretch at rest from the tension (eq. 54 with ẋ = 0; eqs. 37, 41).
    friction_into(m, theta_dot, x)
    for j in range(nc):
        t = force[j] - x[j]
        if m.cable_model == RIGID or t <= 0.0:
            x[j] = 0.0
        else:
            x[j] = t / (m.k[j] + m.lam[j] * t)
    # Null vector of Z (eq. 23: Z1·n_short + Z2·n_long = 0 with n_long = 1).
    for i in range(N):
        for k in range(N):
            Z1[i, k] = Z[i, short[k]]
        rhs[i] = -Z[i, long]
    solve_into(Z1, rhs, LU, y)
    norm = 1.0
    for k in range(N):
        n[short[k]] = y[k]
        norm += y[k] * y[k]
    n[long] = 1.0
    norm = math.sqrt(norm)
    s = 0.0
    for j in range(nc):
        e = lc[j] - m.l_c0[j] + m.rho * theta[j] - x[j]
        s += n[j] * e
    s /= norm
    for j in range(nc):
        nj = n[j] / norm
        r[j] = s / nj if nj != 0.0 else math.copysign(math.inf, s)
    return s


def _scratch(N: int, nc: int) -> tuple[np.ndarray, ...]:
    """Scratch of :func:`parity_into` after its inputs: tab … r."""
    return (np.empty((N, xjoint.N_ROWS, 3)), np.empty(nc), np.empty((N, nc)), np.empty((N, nc)), np.zeros(N),
            np.empty((N, N)), np.empty((N, N)), np.empty(N), np.empty(N), np.empty(nc), np.empty(nc), np.empty(nc))


@njit(cache=True)
def _batch(m, short, long, theta, alpha_hat, force, theta_dot, s, r, tab, lc, Z, Zd, zero, Z1, LU, y, rhs, x, n, rk):
    for b in range(theta.shape[0]):
        s[b] = parity_into(m, short, long, theta[b], alpha_hat[b], force[b], theta_dot[b], tab, lc, Z, Zd, zero, Z1,
                           LU, y, rhs, x, n, rk)
        for j in range(rk.shape[0]):
            r[b, j] = rk[j]


def _rows(x, n: int, name: str, lead: tuple[int, ...] | None) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.shape[-1:] != (n,) or (lead is not None and a.shape[:-1] != lead):
        raise ValueError(f"{name} must have shape (..., {n}) like the others, got {a.shape}")
    return kernel_array(a.reshape(-1, n))


def residuals(model: Model, theta_rad, alpha_hat_rad, force_N, theta_dot_rad_s=None) -> tuple[np.ndarray, np.ndarray]:
    """(s, r) of the module docstring for any number of ticks: θ (..., n_cables) rad at the motor,
    α̂ (..., N) rad, the forces over the last period (..., n_cables) N and the motor velocities
    θ̇ (..., n_cables) rad/s for eq. 37's friction (None: zero, the tension is the force). Returns
    the parity s (...,) m and the per-encoder residual r (..., n_cables) m; NaN where an input is
    not finite. ``model``: :func:`detector_model` (any cable model; rigid gives no stretch)."""
    theta = np.asarray(theta_rad, dtype=float)
    lead = theta.shape[:-1]
    nc, N = model.n_cables, model.n_joints
    th = _rows(theta, nc, "theta_rad", None)
    al = _rows(alpha_hat_rad, N, "alpha_hat_rad", lead)
    f = _rows(force_N, nc, "force_N", lead)
    td = np.zeros_like(th) if theta_dot_rad_s is None else _rows(theta_dot_rad_s, nc, "theta_dot_rad_s", lead)
    s, r = np.empty(th.shape[0]), np.empty_like(th)
    _batch(model, short_cables(model), long_cable(model), th, al, f, td, s, r, *_scratch(N, nc))
    return s.reshape(lead), r.reshape(lead + (nc,))


def encoder_residual(model: Model, theta_rad, alpha_hat_rad, force_N, theta_dot_rad_s=None) -> np.ndarray:
    """Per-encoder residual r (..., n_cables) in m of cable (÷ r_d/R for rad at the motor): the
    length encoder j would have missed if it alone were wrong, r_j = s·|n|/n_j (module docstring;
    eqs. 3-23, 27, 37, 41, 54). Inputs as :func:`residuals`."""
    return residuals(model, theta_rad, alpha_hat_rad, force_N, theta_dot_rad_s)[1]


class EncoderConsistency:
    """The stuck-encoder check, one call per motor state (:meth:`update`).

    A fault when the parity |s| (module docstring) stays beyond ``threshold_m`` for
    ``persistence_s`` of the states' clock, or at once when an input is not finite. Only states
    with the cables under the forces given count (``active``: the drives active and obeying this
    controller); otherwise the persistence starts again (the cables of a disabled neck go slack,
    and its encoders say nothing about α). ``settling`` states (the drives just came back) are
    not judged either: they measure the slack the check then allows (``slack_m``, m of parity,
    module docstring "Slack") until the cables show it taken up.

    Suspects (``suspects``, encoder indices, most likely first): a stuck reading is constant, so
    among the encoders whose reading has not changed for ``persistence_s``, those whose freeze
    accounts for the most growth of s (|s now − s when the reading last changed|), within
    ``SUSPECT_TIE`` of the threshold of the largest. A motor genuinely at rest froze through the
    same growth only by coincidence; when one did, both are named. None frozen: suspect unknown.

    After :meth:`update`, ``s`` (m) and ``r`` (m, per encoder) hold the tick's residuals.
    """

    def __init__(self, params: Params, threshold_m: float = THRESHOLD_M, persistence_s: float = PERSISTENCE_S):
        if not (threshold_m > 0 and math.isfinite(threshold_m)):
            raise ValueError(f"threshold_m must be a positive length (m), got {threshold_m}")
        if not (persistence_s >= 0 and math.isfinite(persistence_s)):
            raise ValueError(f"persistence_s must be a duration (s) >= 0, got {persistence_s}")
        self.model = detector_model(params)
        self.threshold_m, self.persistence_s = float(threshold_m), float(persistence_s)
        N, nc = self.model.n_joints, self.model.n_cables
        self._theta, self._alpha, self._force, self._theta_dot = np.zeros(nc), np.zeros(N), np.zeros(nc), np.zeros(nc)
        work = _scratch(N, nc)
        self._x, self._n, self.r = work[-3:]  # written by the kernel: stretch, null vector, residuals
        self._parity = bind(parity_into, self.model, short_cables(self.model), long_cable(self.model), self._theta,
                            self._alpha, self._force, self._theta_dot, *work)
        self.slack_m = 0.0  # m of parity allowed below −threshold as the cables' slack (module docstring)
        self._settling = False  # the last state was a settling one
        self._taut_at = math.nan  # stamp at which the slack allowed was taken up (SLACK_SETTLE_S)
        self.reset()

    def keep_slack(self, other: EncoderConsistency) -> None:
        """Go on with the slack ``other`` allowed (module docstring, "Slack"): a check built anew
        for a campaign's parameter set watches the same cables (audit of 2026-11-28: a campaign
        started on slack cables from the console, which sends its set, latched "encoder 1 or 3
        stuck" 50 ms in with the allowance left behind)."""
        self.slack_m, self._settling, self._taut_at = other.slack_m, other._settling, other._taut_at

    def clock_stepped(self, step_s: float) -> None:
        """The states' clock stepped by ``step_s`` (s) since the last state: not time that passed,
        so the times kept on it move with it (a step forward had counted as the persistence of a
        residual, or as the settling after a snap; review of session 53)."""
        if self._above_since is not None:
            self._above_since += step_s
        self._taut_at += step_s  # NaN stays NaN
        self._changed_at = [t + step_s for t in self._changed_at]

    def reset(self) -> None:
        """Forget the history (a new bridge run, a new estimate). The slack allowed stays: it is
        the cables', not the readings' (the next settling state measures it afresh)."""
        nc = self.model.n_cables
        self.s = math.nan
        self.r[:] = math.nan
        self._above_since: float | None = None
        self._last: list[float] | None = None
        self._changed_at = [0.0] * nc  # s, stamp of each encoder's last change
        self._s_at_change = [math.nan] * nc  # m, the parity then
        self.suspects: list[int] = []

    def update(self, theta_rad, alpha_hat_rad, force_N, theta_dot_rad_s, stamp_s: float, active: bool = True,
               settling: bool = False) -> str:
        """One motor state: encoders θ (rad), α̂ (rad; the last estimate will do, even one tick
        old: the parity ignores α̂'s errors to first order), the forces applied over the last period
        (N), the motor velocities θ̇ (rad/s, the law's filtered ones) and the state's stamp (s).
        ``settling``: the drives are back but the cables may still be slack: not judged, the slack
        is measured (the first of a run of them starts the measure afresh). Returns why the
        encoders cannot be right, "" when they can (class docstring)."""
        self._theta[:] = theta_rad
        self._alpha[:] = alpha_hat_rad
        self._force[:] = force_N
        self._theta_dot[:] = theta_dot_rad_s
        s = self.s = float(self._parity())
        theta = self._theta.tolist()
        stamp = float(stamp_s)
        if self._last is None:
            self._changed_at = [stamp] * len(theta)
            self._s_at_change = [s] * len(theta)
        else:
            for j, (a, b) in enumerate(zip(self._last, theta, strict=True)):
                if a != b:
                    self._changed_at[j], self._s_at_change[j] = stamp, s
        self._last = theta
        if not math.isfinite(s) or not math.isfinite(stamp):
            self._above_since = None
            return "encoder consistency: non-finite encoder angle, α̂, force, motor speed or stamp: encoder fault"
        if settling:
            if not self._settling:
                self.slack_m, self._taut_at = 0.0, math.nan
            self._settling = True
            self.slack_m = max(self.slack_m, -self._lengths_parity(s))
            self._above_since = None
            return ""
        self._settling = False
        low = s  # the parity the lower bound judges
        if active and self.slack_m > 0.0:
            s_l = self._lengths_parity(s)
            self.slack_m = min(self.slack_m, max(0.0, -s_l))  # the drives only take slack up
            if self.slack_m == 0.0:
                self._taut_at = stamp  # taut again: the snap's overshoot (SLACK_SETTLE_S)
            else:
                low = s_l + self.slack_m
        # (a difference, not a deadline: a step of the bridge's clock back does not prolong it)
        snap = 0.0 <= stamp - self._taut_at < SLACK_SETTLE_S
        if not active or snap or (-self.threshold_m <= low and s <= self.threshold_m):
            self._above_since = None
            return ""
        if self._above_since is None:
            self._above_since = stamp
        if stamp - self._above_since < self.persistence_s:
            return ""
        return self._reason(s, stamp)

    def _lengths_parity(self, s: float) -> float:
        """The parity of the lengths alone, s_l = s + nᵀx/|n| (m; module docstring, "Slack"), from
        the kernel's last stretch x and null vector n."""
        nx = nn = 0.0
        for a, b in zip(self._n.tolist(), self._x.tolist(), strict=True):
            nx += a * b
            nn += a * a
        return s + nx / math.sqrt(nn)

    def _reason(self, s: float, stamp: float) -> str:
        """The fault's reason, naming ``suspects`` (class docstring)."""
        growth = [abs(s - s0) if stamp - t >= self.persistence_s and math.isfinite(s0) else -math.inf
                  for t, s0 in zip(self._changed_at, self._s_at_change, strict=True)]
        best = max(growth)
        order = sorted(range(len(growth)), key=lambda j: -growth[j])
        self.suspects = [j for j in order if growth[j] > -math.inf and growth[j] >= best - SUSPECT_TIE * self.threshold_m]
        slack = (f", past the {self.slack_m * 1e3:.1f} mm allowed for the slack the cables had when the drives came back"
                 if self.slack_m > 0.0 and s < 0.0 else "")
        what = (f"the four encoders disagree by {s * 1e3:+.1f} mm of cable (parity) "
                f"(beyond {self.threshold_m * 1e3:.1f} mm for {self.persistence_s * 1e3:.0f} ms{slack})")
        if not self.suspects:
            return f"{what}; no encoder reading froze, suspect unknown: encoder fault"
        j = self.suspects[0]
        r = float(self.r[j])
        others = "".join(f" or {k + 1}" for k in self.suspects[1:])
        return (f"encoder {j + 1}{others} stuck: its reading has not changed for {stamp - self._changed_at[j]:.2f} s "
                f"while the other three put it {r * 1e3:+.1f} mm of cable ({r / self.model.rho:+.1f} rad at the motor) "
                f"off; {what}: encoder fault")


__all__ = ["PERSISTENCE_S", "SLACK_SETTLE_S", "SUSPECT_TIE", "THRESHOLD_M", "EncoderConsistency", "detector_model", "encoder_residual", "parity_into",
           "residuals"]
