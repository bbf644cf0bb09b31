"""The controller's campaign service closed on the twin through the bridge's safety rules, in one
process: each state carries the bridge's drive state and the forces it applied over the last
period, as ``controller/process.py`` passes them (what ``test_controller_service.Loop`` leaves out:
the bridge's enable ramp, its e-stop and its watchdog hold)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from bridge.motor_speed import MotorSpeed
from bridge.safety import Inputs, Safety, SafetyConfig
from controller.laws import LawConfig, encoder_hold_forces
from controller.service import CampaignService
from twin.sim.simulator import Twin, TwinConfig


class BridgeLoop:
    def __init__(self, params, truth: str = "robot", seed: int = 0, law: int = 2):
        self.params = params
        self.twin = Twin(params, TwinConfig(camera=False, seed=seed, truth=truth))
        self.svc = CampaignService(params, LawConfig(law=law), settle_s=0.5)
        self.safety = Safety(SafetyConfig(n_motors=params.n_cables, f_min_N=params.limits.f_min,
                                          f_max_N=params.limits.f_max, max_force_step_N=1.0))
        self.tick = self.twin.tick(np.zeros(params.n_cables))
        self.svc.initialise(self.tick.theta_meas)
        # the bridge's hold as its node makes it: the rule of the encoders' angles, each motor
        # damped on its speed (bridge/safety.py, "Hold damping")
        self.hold_rule = encoder_hold_forces(params)
        self.speed = MotorSpeed(params.n_cables, 0.002)
        self.speed.update(self.tick.theta_meas.tolist())
        self.events: list = []
        self.outputs: list = []
        self.applied: list = []

    @property
    def stamp_s(self) -> float:
        return self.tick.t_s

    def run(self, seconds: float, estop: tuple = (), drop_commands: bool = False,
            stuck: dict[int, float] | None = None, unanswered: Callable[[int], bool] | None = None) -> None:
        """``seconds`` of 2 ms ticks; ``estop``: (engaged, reason) pairs for the first tick;
        ``drop_commands``: the bridge gets none (its watchdog holds); ``stuck``: encoder index →
        the reading (rad) it is frozen at, for the controller (a stuck encoder); ``unanswered``:
        tick index (from 0 in this call) → whether the controller never sees that state (the
        process skipping a burst's stale states, the state gate or Zenoh dropping one): the bridge
        re-applies the last command meanwhile, its age and the states unanswered counting up."""
        pending = list(estop)
        since = 0  # states unanswered since the last command
        for k in range(round(seconds * 500)):
            if unanswered is not None and unanswered(k) and self.outputs:
                since += 1
                self._bridge_tick(self.outputs[-1].force_N.tolist(), 0.002 * since, since, tuple(pending))
                pending = []
                continue
            since = 0
            drive = self.safety.drive
            self.svc.drive_reason = self.safety.estop_reason if drive == "disabled" else self.safety.hold_reason
            theta = self.tick.theta_meas
            if stuck:
                theta = theta.copy()
                for j, reading in stuck.items():
                    theta[j] = reading
            out = self.svc.control(theta, self.stamp_s, drive, np.asarray(self.safety.force))
            self.outputs.append(out)
            if out.law_ran:
                self.svc.advance(self.stamp_s)
            self.events += self.svc.drain_events()
            self._bridge_tick(None if drop_commands else out.force_N.tolist(), 0.02 if drop_commands else 0.0,
                              5 if drop_commands else 0, tuple(pending))
            pending = []

    def _bridge_tick(self, command: list[float] | None, age_s: float, unanswered: int, estop: tuple) -> None:
        """The bridge's safety rules on ``command`` (None: none came), then one twin period."""
        hold = self.hold_rule(self.tick.theta_meas).tolist()
        d = self.safety.step(Inputs(command_N=command, command_age_s=age_s, states_unanswered=unanswered,
                                    estop=estop, hold_N=hold, sender="c", speed_rad_s=self.speed.rad_s))
        self.applied.append(np.asarray(d.force_N, dtype=float))
        self.tick = self.twin.tick(np.asarray(d.force_N))
        self.speed.update(self.tick.theta_meas.tolist())
