"""The motors' shaft speeds from the encoders, low-passed, for the damping of the bridge's holds.

A hold's forces are those that keep the neck still where the encoders say it is (eq. 33 and eqs.
63-65, :func:`controller.laws.encoder_hold_forces`). On cables an e-stop left slack, what the
encoders say is not where the neck is, and the hold's forces break the stiction of the slack
cables' drums, which then wind in without load: with the controller gone during the take-up of an
e-stop's slack (``controller.take_up``), the neck snapped up at 224-600°/s on the robot truth
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
#: snap to the same 57-66°/s; 20 Hz leaves less of the counts' flicker).
CUTOFF_HZ = 20.0


class MotorSpeed:
    """Low-passed motor speeds (rad/s) from the encoder reading of each tick (:meth:`update`)."""

    def __init__(self, n_motors: int, dt_s: float, cutoff_hz: float = CUTOFF_HZ) -> None:
        if n_motors < 1:
            raise ValueError(f"n_motors must be >= 1, got {n_motors}")
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a positive period (s), got {dt_s}")
        if not (math.isfinite(cutoff_hz) and cutoff_hz > 0):
            raise ValueError(f"cutoff_hz must be a positive frequency (Hz), got {cutoff_hz}")
        self.dt_s = dt_s
        self._gain = 1.0 - math.exp(-2.0 * math.pi * cutoff_hz * dt_s)
        self.rad_s: list[float] = [0.0] * n_motors  # never mutated in place: a reader keeps its list
        self._last: list[float] | None = None

    def update(self, theta_rad: Sequence[float]) -> list[float]:
        """Take this tick's reading; returns the speeds. A reading that is not finite (a failing
        encoder) restarts the filter at zero speed rather than carrying NaN into the forces."""
        last = self._last
        theta = list(theta_rad)
        if last is None or len(theta) != len(last) or not all(map(math.isfinite, theta)):
            self._last = theta if all(map(math.isfinite, theta)) else None
            self.rad_s = [0.0] * len(self.rad_s)
            return self.rad_s
        g, dt = self._gain, self.dt_s
        self.rad_s = [v + g * ((t - p) / dt - v) for v, t, p in zip(self.rad_s, theta, last, strict=True)]
        self._last = theta
        return self.rad_s
