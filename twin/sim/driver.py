"""The digital twin as a motor driver: :class:`twin.sim.simulator.Twin` behind the driver interface.

The bridge's safety logic then runs unchanged against the simulated robot, so the watchdog, the
e-stop and the exit behaviour are tested on the twin exactly as they run on the BeagleBone.

- :meth:`read` returns the twin's quantised encoder angles (what the Blue's counters report).
- :meth:`write` holds forces for the next :meth:`step`; while the drives are not active the motors
  are unpowered and the twin is stepped with zero force (the neck sags onto its springs, as the
  real one does with the ESCONs disabled).
- :meth:`step` integrates one control period; :meth:`stamp_s` is simulated time.
- :meth:`extra_messages` carries the twin-only ``Truth`` and the camera frames, so a bridge on the
  twin publishes every topic ``xneck twin`` does.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Literal

import numpy as np

from bridge import bus
from bridge.driver import Driver, DriverConfig, Lifecycle
from twin.model.params import Params
from twin.sim.sensors import quantise_encoder
from twin.sim.simulator import Tick, Twin, TwinConfig
from twin.sim.truth import believed_differently, check_truth, load_truth, robot_base

log = logging.getLogger("xneck.bridge.twin")


class TwinDriverConfig(DriverConfig, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """What the twin simulates (see :class:`twin.sim.simulator.TwinConfig`): cable model (None: the
    parameter file's), motor friction, integration substeps per tick, sensor-noise seed, camera,
    truth ("model": the parameter file as it is; "robot": the shipped robot truth with every
    unmodelled effect; or the path of a truth file, twin/sim/truth.py), α_IP ("noise": the true α
    plus white noise; "camera": measured on frames rendered from the truth, twin.sim.sensors)."""

    cable_model: Literal["rigid", "linear", "variable"] | None = None
    friction: bool = True
    substeps: int = 2
    seed: int = 0
    camera: bool = True
    truth: str = "model"
    alpha_ip: Literal["noise", "camera"] = "noise"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_truth(self.truth)  # a TruthError (ValueError) names what is wrong
        if self.substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {self.substeps}")


class TwinDriver(Driver):
    name = "twin"

    def __init__(self, config: TwinDriverConfig, params: Params) -> None:
        super().__init__(config)
        self.config: TwinDriverConfig = config
        if params.n_cables != config.n_motors:
            raise ValueError(f"the parameter set has {params.n_cables} cables, the driver config {config.n_motors} motors")
        # The robot: the truth's own parameter file where it names one (the robot truth: the
        # prototype), so a parameter set given to the controller does not rebuild the robot.
        truth = load_truth(config.truth)
        self.truth_name = bus.plain_text(truth.name, 64)  # in every Truth message: what is simulated
        self.params = robot_base(truth, params)
        differ = believed_differently(self.params, params) if self.params is not params else []
        if differ:
            # Loud: a lab that gave its own robot's file with the shipped robot truth would
            # otherwise run a twin of the 3-X prototype without being told.
            log.warning("twin: truth %r is a robot built from %s; the controller's parameter set %r believes "
                        "otherwise in %s. A twin of another robot needs a truth file whose robot_params names "
                        "its parameter file (README, \"What the twin simulates\"; twin/sim/truth.py)", config.truth,
                        self.params.name, params.name, ", ".join(differ[:8]) + (", ..." if len(differ) > 8 else ""))
        self.twin: Twin | None = None
        self.last_tick: Tick | None = None
        self._force = np.zeros(config.n_motors)
        self._extra: list[tuple[str, bus.BusMessage]] = []
        self._seq = {"camera": 0, "truth": 0}
        self._slack = np.zeros(config.n_motors, dtype=bool)
        self._flat_refused, self._flat_logged_s = 0, -math.inf  # refused steps since the last report, when

    def _on_configure(self) -> None:
        c = self.config
        twin_config = TwinConfig(cable_model=c.cable_model, friction=c.friction, rate_hz=c.rate_hz,
                                 substeps=c.substeps, seed=c.seed, camera=c.camera, truth=c.truth, alpha_ip=c.alpha_ip)
        # One step of a throwaway twin loads the compiled integrator now (about 80 ms), so the
        # bridge's first real tick does not overrun.
        Twin(self.params, replace(twin_config, camera=False)).tick(np.zeros(self.n_motors))
        self.twin = Twin(self.params, twin_config)

    def _on_activate(self) -> None:
        self._force[:] = 0.0

    def _on_deactivate(self) -> None:
        self._force[:] = 0.0

    def _on_close(self) -> None:
        self._force[:] = 0.0

    def _on_read(self) -> np.ndarray:
        tick = self.last_tick
        if tick:
            return tick.theta_meas.copy()
        assert self.twin is not None, "read() before configure()"  # the Lifecycle allows read only when configured
        return quantise_encoder(self.twin.theta, self.twin.counts_per_rev)

    def _on_write(self, force_N: np.ndarray) -> np.ndarray:
        self._force = force_N.copy()
        return self._force.copy()

    def step(self) -> None:
        """One control period with the forces written since the last step (zero unless active)."""
        if self.state not in (Lifecycle.INACTIVE, Lifecycle.ACTIVE):
            return
        force = self._force if self.state is Lifecycle.ACTIVE else np.zeros(self.n_motors)
        assert self.twin is not None  # INACTIVE/ACTIVE come after configure(), which builds it
        tick = self.twin.tick(force)
        self.last_tick = tick
        if tick.flat:
            # Once a second, with the count: a twin held at the singularity refuses every step
            # (audit of 2026-11-26: 2999 warnings in 6 s, one per tick).
            self._flat_refused += 1
            if tick.t_s - self._flat_logged_s >= 1.0:
                log.warning("t = %.3f s: a joint is at its flat singularity (α = ±180°): %d step(s) refused since "
                            "the last report; Truth.near_singular is set", tick.t_s, self._flat_refused)
                self._flat_refused, self._flat_logged_s = 0, tick.t_s
        if np.any(tick.slack != self._slack):
            log.info("t = %.3f s: slack cables %s", tick.t_s, (np.nonzero(tick.slack)[0] + 1).tolist())
            self._slack = tick.slack
        extra: list[tuple[str, bus.BusMessage]] = []
        camera = self.twin.camera
        for k, (capture, alpha_ip) in enumerate(tick.frames):
            self._seq["camera"] += 1
            confidence = tick.frame_confidence[k].tolist() if k < len(tick.frame_confidence) else []
            extra.append((bus.CAMERA_ALPHA, bus.CameraAlpha(
                seq=self._seq["camera"], stamp_s=tick.t_s, capture_stamp_s=capture,
                alpha_ip_rad=[None if np.isnan(a) else float(a) for a in alpha_ip],  # a missing joint is null
                confidence=confidence, source=camera.source if camera is not None else "twin-noise")))
        self._seq["truth"] += 1
        extra.append((bus.TWIN_TRUTH, bus.Truth(
            seq=self._seq["truth"], stamp_s=tick.t_s, alpha_rad=tick.alpha.tolist(),
            alpha_dot_rad_s=tick.alpha_dot.tolist(), theta_rad=tick.theta.tolist(),
            theta_dot_rad_s=tick.theta_dot.tolist(), tension_N=tick.tension.tolist(),
            elongation_m=tick.elongation.tolist(), slack=tick.slack.tolist(), near_singular=tick.near_singular,
            truth=self.truth_name)))
        self._extra = extra

    def stamp_s(self) -> float:
        return self.twin.t_s if self.twin is not None else 0.0

    def steady_s(self) -> float:
        return self.stamp_s()  # simulated time: a lockstep twin runs faster than the wall clock

    def extra_messages(self) -> list[tuple[str, bus.BusMessage]]:
        out, self._extra = self._extra, []
        return out


__all__ = ["TwinDriver", "TwinDriverConfig"]
