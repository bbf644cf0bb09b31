"""The twin's simulator: the full model stepped at the control rate, with the prototype's sensors.

``Twin.tick(f)`` holds the motor forces f (N) for one control period (2 ms at 500 Hz), integrates
the full model (``twin.sim.integrator``) and returns what the bridge would report (quantised encoder
angles) plus the camera frames due now and the twin-only truth. Pure Python shell around the
compiled step; deterministic for a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from twin.model import cables, dynamics
from twin.sim.integrator import step
from twin.model.numeric import Model, build
from twin.model.params import Params, load_params
from twin.sim.sensors import Camera, quantise_encoder
from twin.sim.truth import TRUTHS, TruthName, truth_params

NEAR_FLAT = math.radians(160.0)  # rad: warn when a joint comes within 20° of its flat singularity


@dataclass(frozen=True)
class TwinConfig:
    """What the twin simulates. Defaults: the paper's identified robot (Table 1 friction, Table 2
    variable-stiffness cables), 500 Hz, two integration substeps per tick. ``truth``: "model"
    integrates the parameter file as it is, "robot" with a real line's small cable damping
    (``twin.sim.truth``)."""

    cable_model: Literal["rigid", "linear", "variable"] | None = None  # None: the parameter file's
    friction: bool = True
    rate_hz: float = 500.0
    substeps: int = 2
    seed: int = 0
    camera: bool = True
    truth: TruthName = "model"

    def __post_init__(self) -> None:
        if self.truth not in TRUTHS:
            raise ValueError(f"truth must be one of {', '.join(TRUTHS)}, got {self.truth!r}")
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"rate_hz must be a positive number, got {self.rate_hz}")
        if self.substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {self.substeps}")


@dataclass(frozen=True)
class Tick:
    """One control period's output. Times in s (simulated), angles in rad, forces in N."""

    seq: int
    t_s: float
    theta_meas: np.ndarray  # encoder angles (quantised), as the bridge reports them
    frames: list[tuple[float, np.ndarray]]  # camera frames delivered now: (capture time, α_IP)
    alpha: np.ndarray  # truth from here on (twin-only)
    alpha_dot: np.ndarray
    theta: np.ndarray
    theta_dot: np.ndarray
    tension: np.ndarray
    elongation: np.ndarray
    slack: np.ndarray  # bool per cable
    near_singular: bool
    flat: bool  # a joint reached its flat configuration: the step was refused


class Twin:
    """The simulated robot. State (α, θ, α̇, θ̇) starts straight and at rest with slack-free,
    unstretched cables (θ = 0 at α = 0, eq. 20). ``params`` is the model; ``self.params`` is what
    is integrated (the same unless ``config.truth`` is "robot")."""

    def __init__(self, params: Params | None = None, config: TwinConfig = TwinConfig()):
        self.params = truth_params(params or load_params(), config.truth)
        self.config = config
        self.model: Model = build(self.params, config.cable_model, friction=config.friction)
        self.dt = 1.0 / config.rate_hz
        n, nc = self.model.n_joints, self.model.n_cables
        self._n, self._nc = n, nc
        self.state = np.zeros(2 * (n + nc))
        self._work = dynamics.scratch_buffers(self.model)
        self._tension = np.zeros(nc)
        self._stretch = np.zeros(nc)
        self.seq = 0
        self.t_s = 0.0
        sensors = self.params.sensors
        rng = np.random.default_rng(config.seed)
        self.camera = (
            Camera(sensors.camera_rate, math.radians(sensors.camera_noise_deg), sensors.camera_latency, rng)
            if config.camera
            else None
        )
        self.counts_per_rev = sensors.encoder_counts_per_rev

    # -- state views (copies, so callers cannot corrupt the integrator's state) -----------------
    @property
    def alpha(self) -> np.ndarray:
        return self.state[: self._n].copy()

    @property
    def theta(self) -> np.ndarray:
        return self.state[self._n : self._n + self._nc].copy()

    def reset(self, alpha: np.ndarray | None = None, theta: np.ndarray | None = None) -> None:
        """Put the robot at rest at ``alpha`` (rad) with motor angles ``theta`` (default: rigid
        cables, no stretch)."""
        n, nc = self._n, self._nc
        a = np.zeros(n) if alpha is None else np.asarray(alpha, dtype=float)
        if a.shape != (n,) or not np.all(np.isfinite(a)) or np.any(np.abs(a) >= NEAR_FLAT):
            raise ValueError(f"alpha must be {n} finite angles within ±{math.degrees(NEAR_FLAT):.0f}°, got {a}")
        th = cables.theta_rigid(self.model, a) if theta is None else np.asarray(theta, dtype=float)
        self.state[:] = 0.0
        self.state[:n], self.state[n : n + nc] = a, th
        self.seq, self.t_s = 0, 0.0

    def tick(self, f: np.ndarray) -> Tick:
        """Hold forces ``f`` (N, one per cable, assumed validated) for one period and step."""
        h = self.dt / self.config.substeps
        bits = int(step(self.model, self.state, np.asarray(f, dtype=float), h, self.config.substeps, self._work,
                        self._tension, self._stretch))
        flat = bool(bits >> 62 & 1)
        self.seq += 1
        self.t_s = self.seq * self.dt
        n, nc = self._n, self._nc
        s = self.state.copy()
        alpha, theta = s[:n], s[n : n + nc]
        frames = self.camera.update(self.t_s, alpha) if self.camera else []
        return Tick(
            seq=self.seq,
            t_s=self.t_s,
            theta_meas=quantise_encoder(theta, self.counts_per_rev),
            frames=frames,
            alpha=alpha,
            alpha_dot=s[n + nc : 2 * n + nc],
            theta=theta,
            theta_dot=s[2 * n + nc :],
            tension=self._tension.copy(),
            elongation=self._stretch.copy(),
            slack=(bits >> np.arange(nc)) & 1 == 1 if not flat else np.zeros(nc, bool),
            near_singular=flat or bool(np.abs(alpha).max() >= NEAR_FLAT),
            flat=flat,
        )
