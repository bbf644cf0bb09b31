"""The motors' shaft speeds from the encoders, low-passed, for the damping of the bridge's holds.

A hold's forces are those that keep the neck still where the encoders say it is (eq. 33 and eqs.
63-65, :func:`controller.laws.encoder_hold_forces`). On cables an e-stop left slack, what the
encoders say is not where the neck is, and the hold's forces break the stiction of the slack
cables' drums, which then wind in without load: with the controller gone during the take-up of an
e-stop's slack (``controller.take_up``), the neck snapped up at 494-599°/s on the robot truth
(session 37; the trajectories' bound is 86°/s). :class:`bridge.safety.Safety` damps each motor
while it holds, from these speeds.

The speed is the difference of successive readings over the period, through a first-order
low-pass (``cutoff_hz``): one encoder count (2π/2048 rad) in one 2 ms tick is 1.5 rad/s, which
the damping must not turn into chatter. Plain floats, not numpy: this runs in every tick of the
BeagleBone's loop (benchmarks/bridge_tick.py). Angles in rad at the motor shaft, speeds in rad/s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

#: Hz of the low-pass: the damping's speeds (robot truth, session 37: 50 Hz and 20 Hz held the
#: snap to the same 57-66°/s in its tuning runs; 20 Hz leaves less of the counts' flicker).
CUTOFF_HZ = 20.0
#: rad/s at the motor shaft no reading can mean (the EC-max 40 turns about 785 rad/s without load,
#: twice that for margin: controller.service's MOTOR_SPEED_MAX_RAD_S): a change of the
#: reading faster than this is a bad reading (an encoder glitch, a jump of its count), not a speed,
#: and the filter starts again at zero. Session 37's audit: one reading 1e4 rad off had the hold's
#: damping push a cable 33 N for 168 ms and move the neck 3.7°.
MAX_SPEED_RAD_S = 1600.0
#: Readings after a bad one (its own included) before the angles are trusted again
#: (:attr:`MotorSpeed.trusted`): a glitch may hold its wrong count for a few ticks, each consistent
#: with the last, and the reading back to normal is itself a jump (audit of 2026-11-29: motor 1 read
#: 1e4 rad off for 3 ticks, and the bridge's hold forces were computed there). 5 readings: 10 ms at
#: 500 Hz, the command timeout.
TRUST_AFTER_READINGS = 5
#: s between two readings beyond which the filter starts again rather than divide by it: the
#: hardware's stamps are the wall clock, which NTP may step (the BeagleBone has no RTC battery), and
#: the loop watchdog trips after a 0.5 s stall anyway (bridge.loop_watchdog).
MAX_GAP_S = 0.5


class MotorSpeed:
    """Low-passed motor speeds (rad/s) from the encoder reading of each tick (:meth:`update`)."""

    def __init__(self, n_motors: int, dt_s: float, cutoff_hz: float = CUTOFF_HZ) -> None:
        if n_motors < 1:
            raise ValueError(f"n_motors must be >= 1, got {n_motors}")
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a positive period (s), got {dt_s}")
        if not (math.isfinite(cutoff_hz) and cutoff_hz > 0):
            raise ValueError(f"cutoff_hz must be a positive frequency (Hz), got {cutoff_hz}")
        self.dt_s, self.cutoff_hz = dt_s, cutoff_hz
        self._gain = self._gain_of(dt_s)
        self._zeros = [0.0] * n_motors  # shared, never mutated
        self.rad_s: list[float] = self._zeros  # never mutated in place: a reader keeps its list
        self.bad_readings = 0  # readings that restarted the filter (non-finite, or beyond MAX_SPEED_RAD_S)
        self._since_bad = TRUST_AFTER_READINGS  # readings since the last bad one
        self._last: list[float] | None = None
        self._last_stamp_s = math.nan

    @property
    def trusted(self) -> bool:
        """Whether the last reading is one to compute from: finite, and neither it nor any of the
        :data:`TRUST_AFTER_READINGS` - 1 readings before it was bad (non-finite, or a change faster
        than :data:`MAX_SPEED_RAD_S`). The bridge computes its hold forces from trusted readings
        only (bridge.node.HoldWorker)."""
        return self._since_bad >= TRUST_AFTER_READINGS

    def _gain_of(self, dt_s: float) -> float:
        return 1.0 - math.exp(-2.0 * math.pi * self.cutoff_hz * dt_s)

    def update(self, theta_rad: Sequence[float], stamp_s: float | None = None) -> list[float]:
        """Take this tick's reading (``stamp_s``: its time on the driver's clock, s; None: one
        period after the last); returns the speeds. A late tick (the loop skips whole periods after
        one, bridge.node.run_realtime) is divided by the time that passed, not by one period. A
        reading that is not finite, or that moved faster than :data:`MAX_SPEED_RAD_S`, restarts the
        filter at zero speed rather than carry it into the forces."""
        last = self._last
        theta = theta_rad if isinstance(theta_rad, list) else list(theta_rad)  # the node's: a new list each tick
        dt = self.dt_s
        if stamp_s is not None:
            dt = stamp_s - self._last_stamp_s
            self._last_stamp_s = stamp_s
        self._last = theta
        self._since_bad += 1
        if last is None or len(theta) != len(last) or not (0.0 < dt <= MAX_GAP_S):  # NaN: the first stamp
            return self._restart(theta)
        g = self._gain if dt == self.dt_s else self._gain_of(dt)
        lim = MAX_SPEED_RAD_S * dt
        out = []
        for v, t, p in zip(self.rad_s, theta, last):  # one loop, no temporaries: every tick on a Cortex-A8
            d = t - p
            if not -lim <= d <= lim:  # beyond a motor's speed, or NaN
                self.bad_readings += 1
                self._since_bad = 0
                return self._restart(theta)
            out.append(v + g * (d / dt - v))
        self.rad_s = out
        return out

    def _restart(self, theta: list[float]) -> list[float]:
        if not all(map(math.isfinite, theta)):
            self._last = None
            self._since_bad = 0
        self.rad_s = self._zeros
        return self.rad_s
