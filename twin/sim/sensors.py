"""The prototype's sensors as the twin simulates them (3-X paper §2.2 and §4.2).

- Motor encoders: θ at the motor shaft, quantised to whole counts (truncation towards −∞, as a
  quadrature counter does), sampled at every control tick (500 Hz).
- Camera, two kinds (:func:`make_camera`, ``TwinConfig.alpha_ip``): ``noise``, α_IP at 30 Hz as
  the true α plus Gaussian noise (σ = 1° by default) delivered after a latency (:class:`Camera`);
  ``camera``, α_IP measured by the robot's detector on 1280×720 frames rendered from the truth at
  each exposure (:class:`twin.camera.lockstep.LockstepCamera`, issue 15), the default of
  identification campaigns. The camera is offline on the prototype (§4.2); the twin offers it
  online, with its latency, so that identification and the console can show it live.
All randomness comes from seeded generators so lockstep runs repeat exactly.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from twin.model.numeric import Model
    from twin.model.params import Geometry, Sensors


def quantise_encoder(theta: np.ndarray, counts_per_rev: int) -> np.ndarray:
    """θ (rad) as an encoder reports it: floor(θ·cpr/2π)·2π/cpr."""
    q = 2.0 * math.pi / counts_per_rev
    return np.floor(np.asarray(theta) / q) * q


ALPHA_IP_KINDS = ("noise", "camera")
#: the ``CameraAlpha.source`` of each kind's α_IP (the rendered camera's, in the twin or in an
#: `xneck camera --source twin` process beside it: twin.camera)
ALPHA_IP_SOURCES = {"noise": "twin-noise", "camera": "twin-render"}


class AlphaCamera(Protocol):
    """What the simulator asks of a camera: ``update`` every tick with the true α, returning the
    frames delivered now as (capture time s, α_IP rad, NaN for a missing joint); ``confidence``,
    the per-joint confidence of those frames (empty when the camera does not grade them)."""

    source: str
    confidence: list[np.ndarray]

    def update(self, t_s: float, alpha: np.ndarray) -> list[tuple[float, np.ndarray]]: ...


def make_camera(kind: str, sensors: Sensors, seed: int, drawn: Model, measured: Geometry) -> AlphaCamera:
    """The twin's camera of ``kind`` (:data:`ALPHA_IP_KINDS`). ``drawn``: the robot simulated (what
    a rendered frame shows); ``measured``: the geometry the detector assumes (the parameter file's).
    OpenCV is loaded only for the rendered camera."""
    if kind == "noise":
        return Camera(sensors.camera_rate, math.radians(sensors.camera_noise_deg), sensors.camera_latency,
                      np.random.default_rng(seed))
    if kind == "camera":
        from twin.camera.lockstep import LockstepCamera

        return LockstepCamera(drawn, measured.L, measured.b, sensors.camera_rate, sensors.camera_latency, seed=seed)
    raise ValueError(f"alpha_ip must be one of {', '.join(ALPHA_IP_KINDS)}, got {kind!r}")


@dataclass
class Camera:
    """Frames of α_IP: captured every 1/rate s, delivered ``latency`` s later with noise."""

    rate_hz: float
    noise_rad: float
    latency_s: float
    rng: np.random.Generator
    _next_capture_s: float = 0.0
    _pending: deque = field(default_factory=deque)
    source = "twin-noise"
    confidence: list[np.ndarray] = field(default_factory=list)  # not graded: always empty

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
