"""Taking up the slack an e-stop leaves, before the law holds the pose again.

With the drives off the neck falls under its weight and springs; the cables whose path shortens
go slack while the others back-drive their motors. When the drives come back, the hold's forces
(t_min = 8.5 N, eq. 65) are below the geared motors' breakaway friction (1.1-1.5·f_s, 19-24 N on
the robot truth; twin/sim/robot_truth.toml ``static_ratio``), so the drums of the slack cables
never turn: the cables stayed slack for more than 10 s and α̂, counted from the encoders'
increments (eq. 35), 5-13° off the neck (audit of 2026-11-28). A law holding that α̂ holds a pose
the neck is not in.

So after a release the controller raises every cable's floor (the tension distribution's lower
bound, eqs. 63-65, as a trajectory's pretension does) past the friction at a bounded rate, holds
the neck at α̂ (no servo: α̂ is what is wrong) while the motors wind the slack in, and hands over
to the law once every motor has stopped turning: the cables are taut, and α̂ is back within the
law's usual error, since the drums wound in exactly the slack the increments missed. The floor
is then let go at ``controller.service.PRETENSION_RELEASE_N_S``. Each motor is damped meanwhile
(``DAMPING_N_S_RAD``) so that a drum breaking free does not race to the end of its slack.

The neck moves while this happens: the hold is computed at α̂, which the fall left off the neck,
and the cables come taut one after the other. On the robot truth (``docs/safety/take_up.py``: the
audit's e-stop 4.5 s into the §7 control test, seeds 0-2) joint 1 rose 18° at up to 53°/s (the
trajectories' bound is 86°/s), the cables were taut 1.4 s after the release and the law held the
neck from 2.0 s, α̂ 3.5° off (law 2 tracked the same test 1-5° off before the e-stop; without the
take-up, 12-13° off after 6 s), and no force applied changed by more than 1 N a tick. Holding at
the pose the neck fell to instead (known on the twin only) still moved it 7-9°: most of the
motion is the cables coming taut, not α̂'s error.

The floor's peak follows the friction the controller knows (Table 1's f_s, ``[friction]``):
``TAKE_UP_FRICTION_FACTOR``·max f_s, minus t_min, since the breakaway ratio of geared drives is
1.1-1.5 (Armstrong-Helouvry, Dupont, Canudas de Wit, Automatica 1994) and the margin above it
sets how fast a drum winds in. Forces in N, times in s, motor speeds in rad/s at the shaft.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from controller.laws import _hold_model  # pyright: ignore[reportPrivateUsage]
from twin.model import dynamics
from twin.model.params import Params

#: The floor's peak over the largest f_s (module docstring): above the 1.5 breakaway ratio with a
#: margin that winds 20 mm of slack in within a few tenths of a second on the robot truth.
TAKE_UP_FRICTION_FACTOR = 2.0
#: rad/s at the motor shaft below which every motor counts as still, read low-passed
#: (``DAMPING_FILTER_HZ``): a drum winding slack in turns at 5-10 rad/s; 0.5 rad/s is 0.4 mm/s of
#: cable at r_d/R = 0.8 mm, and the damping then adds at most 1 N, so the law's hand-over does not
#: step.
STILL_RAD_S = 0.5
STILL_FOR_S = 0.1  # s every motor must stay still at the peak: the cables are taut
#: s at the peak after which the take-up ends even if a motor still turns (a neck swinging for
#: long, a motor that cannot stop): the law then holds wherever α̂ is, as before this module.
PEAK_MAX_S = 2.0
#: N/s at which the floor rises: the slower, the less the neck moves as the drums break free one
#: after the other (robot truth, seeds 0-1, factor 2: 20 N/s moved the neck at up to 54°/s,
#: 50 N/s at 64°/s).
TAKE_UP_RATE_N_S = 20.0
#: N·s/rad of damping on each motor while the slack is taken up (:meth:`TakeUp.damping_N`): a
#: drum that breaks free winds in at (f − friction)/c; without it drums reached 220 rad/s and
#: snapped the neck up at 180°/s (robot truth). Higher is not gentler: at 3-4 N·s/rad the
#: filtered, rate-bounded damping oscillated and the neck reached 117-176°/s.
DAMPING_N_S_RAD = 2.0
#: Hz of the low-pass on the law's θ̇ (itself filtered at 50 Hz) that the damping and the
#: stillness test read: on the law's θ̇ alone the encoders' counts made the damping chatter
#: (668 steps above 1 N in 3 s) and the motors never looked still.
DAMPING_FILTER_HZ = 50.0
#: The largest force the hold may ask of any cable at the take-up's floor, over f_max: the
#: distribution loads the other cables 1.7-2.7× the floor, and the 37.5 N floor drove cables to
#: f_max at 357 of 729 poses of a ±60° grid (audit of 2026-11-29; the peak of a 30° pose reached
#: it). The rest (20 N) is room for the damping, which adds to a back-driven motor's cable.
PEAK_FORCE_FRACTION = 0.8
#: N per tick the take-up's command may change by (the bridge's enable ramp, 1 N a tick): the
#: law's own bound (10 N) let the damping step the cables.
FORCE_STEP_N = 1.0


def take_up_peak_N(params: Params) -> float:
    """The floor added to t_min at the take-up's peak (N, module docstring): 0 when t_min alone
    is already past ``TAKE_UP_FRICTION_FACTOR``·max f_s, and the floor never above half of
    f_max (an identified set with a large f_s must not ask for f_max). The distribution loads
    other cables above the floor, 1.7-2.7× at tilted poses: :func:`floor_cap_N` lowers it where
    they would pass ``PEAK_FORCE_FRACTION``·f_max."""
    f_s = params.friction.f_s
    floor = min(TAKE_UP_FRICTION_FACTOR * max(f_s, default=0.0), 0.5 * params.limits.f_max)
    return max(0.0, floor - params.limits.t_min)


def floor_cap_N(params: Params, alpha_rad: np.ndarray) -> float:
    """The largest floor added to t_min (N, >= 0) at which the hold at α
    (:func:`controller.laws.hold_forces`) asks no cable above ``PEAK_FORCE_FRACTION``·f_max; 0 at
    a pose where the distribution is not possible (n <= 0, eq. 63).

    In closed form, from the distribution (eqs. 63-65, :func:`controller.distribution.distribute`):
    with p = Z₁⁻¹g and n = −Z₁⁻¹Z₂, the short cables carry p + n·f_long and the long one
    f_long = max(L, maxᵢ (L − pᵢ)/nᵢ) at a floor L, so every force is at most M iff f_long <= F* =
    min(M, minᵢ (M − pᵢ)/nᵢ), i.e. L <= min(F*, minᵢ pᵢ + nᵢF*). One model evaluation and two
    3×3 solves: as cheap as the hold itself, so it runs every tick at α̂."""
    m, short, long = _hold_model(params)
    terms = dynamics.evaluate(m, np.asarray(alpha_rad, dtype=float))
    Z = terms.Z
    Z1 = Z[:, short]
    try:
        pn = np.linalg.solve(Z1, np.column_stack((terms.g, -Z[:, long])))
    except np.linalg.LinAlgError:
        return 0.0
    p, n = pn[:, 0], pn[:, 1]
    if not (np.all(n > 0.0) and np.all(np.isfinite(p))):
        return 0.0
    top = PEAK_FORCE_FRACTION * m.f_max
    f_long = min(top, float(np.min((top - p) / n)))
    floor = min(f_long, float(np.min(p + n * f_long)))
    return max(0.0, floor - max(m.t_min, m.f_min))


@dataclass
class TakeUp:
    """One take-up, stepped once per state with the drives active (module docstring).

    ``level_N`` is the floor added to t_min this tick: it starts at ``start_N`` (the floor in
    force, so nothing steps), rises at ``rate_N_s`` to ``peak_N``, and the take-up is done once
    every motor has been still for ``STILL_FOR_S`` at the peak, or after ``PEAK_MAX_S`` there.
    Times are sums of the positive steps between the states' stamps (a clock stepping back had
    held a take-up for as long as it stepped: audit of 2026-11-29), and a step the controller is
    told of (:meth:`clock_stepped`) is no time spent.
    """

    peak_N: float
    rate_N_s: float
    start_N: float = 0.0
    level_N: float = field(init=False)
    _last_s: float = field(init=False, default=math.nan)
    _at_peak_s: float = field(init=False, default=math.nan)  # s since the peak was reached (nan: not yet)
    _still_s: float = field(init=False, default=math.nan)  # s every motor has been still (nan: one turns)
    done_reason: str = field(init=False, default="")
    _theta_dot_f: np.ndarray | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        if not (self.peak_N >= 0 and math.isfinite(self.peak_N)):
            raise ValueError(f"peak_N must be a force >= 0 (N), got {self.peak_N}")
        if not (self.rate_N_s > 0 and math.isfinite(self.rate_N_s)):
            raise ValueError(f"rate_N_s must be a positive rate (N/s), got {self.rate_N_s}")
        self.level_N = max(0.0, float(self.start_N))

    def damp(self, theta_dot_rad_s: np.ndarray, dt_s: float) -> None:
        """Take the motors' speeds θ̇ (rad/s, the law's filtered ones) of a state ``dt_s`` after
        the last: low-passed at ``DAMPING_FILTER_HZ``, they set :attr:`damping_N` and what
        :meth:`step` calls still."""
        theta_dot = np.asarray(theta_dot_rad_s, dtype=float)
        if self._theta_dot_f is None:
            self._theta_dot_f = theta_dot.copy()
        else:
            beta = 1.0 - math.exp(-2.0 * math.pi * DAMPING_FILTER_HZ * dt_s)
            self._theta_dot_f += beta * (theta_dot - self._theta_dot_f)

    @property
    def damping_N(self) -> np.ndarray:
        """Per cable, the force (N) that damps its motor's speed, −c·θ̇ (θ̇ > 0 winding in, eq. 20;
        a zero that broadcasts before :meth:`damp`): a drum breaking free of its stiction on a
        slack cable otherwise races to the end of the slack and snaps the neck with it (module
        docstring)."""
        return np.zeros(1) if self._theta_dot_f is None else -DAMPING_N_S_RAD * self._theta_dot_f

    @property
    def done(self) -> bool:
        return bool(self.done_reason)

    def clock_stepped(self, step_s: float) -> None:
        """The states' clock stepped by ``step_s`` (s) since the last state: not time spent here."""
        self._last_s += step_s

    def step(self, stamp_s: float, cap_N: float = math.inf) -> bool:
        """One state at ``stamp_s``, after :meth:`damp` took its motor speeds: raise the floor,
        and say whether the take-up goes on (False once done). ``cap_N``: the floor at which the
        hold at α̂ reaches ``PEAK_FORCE_FRACTION``·f_max (:func:`floor_cap_N`); the floor never
        stays above it, and reaching it counts as the peak."""
        if self.done:
            return False
        dt = 0.0 if math.isnan(self._last_s) else max(0.0, stamp_s - self._last_s)
        self._last_s = stamp_s
        target = max(0.0, min(self.peak_N, cap_N))
        if self.level_N > target:
            self.level_N = target  # the command follows at FORCE_STEP_N a tick (the service's hold)
        elif self.level_N < target:
            self.level_N = min(target, self.level_N + self.rate_N_s * dt)
        if self.level_N < target and math.isnan(self._at_peak_s):
            return True
        self._at_peak_s = 0.0 if math.isnan(self._at_peak_s) else self._at_peak_s + dt
        still = self._theta_dot_f is not None and bool(np.all(np.abs(self._theta_dot_f) < STILL_RAD_S))
        if not still:
            self._still_s = math.nan
        else:
            self._still_s = 0.0 if math.isnan(self._still_s) else self._still_s + dt
        if still and self._still_s >= STILL_FOR_S:
            self.done_reason = "taut"
        elif self._at_peak_s >= PEAK_MAX_S:
            self.done_reason = f"a motor still turned after {PEAK_MAX_S:g} s at the peak"
        if self.done and target < self.peak_N:
            # Capped by f_max's margin at this pose (floor_cap_N): motors that stopped there may
            # have stopped on their friction, not on taut cables (audit of 2026-11-29: the cap sits
            # under the breakaway at 384 of 729 poses of a ±60° grid). Said, not hidden as "taut".
            self.done_reason = (f"the floor was capped at t_min + {target:.0f} N by f_max's margin at this pose, "
                                f"under the t_min + {self.peak_N:.0f} N the motors' friction asks: a cable may still be "
                                f"slack (check α̂ against the camera; a move towards the straight neck takes it up)")
        return not self.done
