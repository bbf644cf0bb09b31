"""The prototype's sensors as the twin simulates them (3-X paper §2.2 and §4.2).

- Motor encoders: θ at the motor shaft, quantised to whole counts (truncation towards −∞, as a
  quadrature counter does), sampled at every control tick (500 Hz).
- Camera: α_IP at 30 Hz with Gaussian noise (σ = 1° by default) delivered after a latency.
  The camera is offline on the prototype (§4.2); the twin offers it online, with its latency, so
  that identification and the console can show it live.
All randomness comes from one seeded generator so lockstep runs repeat exactly.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np


def quantise_encoder(theta: np.ndarray, counts_per_rev: int) -> np.ndarray:
    """θ (rad) as an encoder reports it: floor(θ·cpr/2π)·2π/cpr."""
    q = 2.0 * math.pi / counts_per_rev
    return np.floor(np.asarray(theta) / q) * q


@dataclass
class Camera:
    """Frames of α_IP: captured every 1/rate s, delivered ``latency`` s later with noise."""

    rate_hz: float
    noise_rad: float
    latency_s: float
    rng: np.random.Generator
    _next_capture_s: float = 0.0
    _pending: deque = field(default_factory=deque)

    def update(self, t_s: float, alpha: np.ndarray) -> list[tuple[float, np.ndarray]]:
        """Feed the true α at time ``t_s``; returns the frames (capture time, α_IP) delivered now."""
        if t_s + 1e-12 >= self._next_capture_s:
            noisy = alpha + self.rng.normal(0.0, self.noise_rad, size=alpha.shape)
            self._pending.append((t_s, noisy))
            self._next_capture_s += 1.0 / self.rate_hz
        out = []
        while self._pending and self._pending[0][0] + self.latency_s <= t_s + 1e-12:
            out.append(self._pending.popleft())
        return out
