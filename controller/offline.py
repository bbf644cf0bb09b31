"""Closed loop of a law and the twin in one process, without the bus.

For tests, benchmarks and the results report: the same :class:`ComputedTorque` and
:class:`Twin` that the bus processes wrap, stepped alternately (state → command → tick), which is
exactly what the lockstep bus mode does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controller.laws import ComputedTorque, LawConfig
from controller.metrics import campaign_metrics
from controller.trajectory import Trajectory
from twin.model.params import Params
from twin.sim.simulator import Twin, TwinConfig


@dataclass
class Run:
    t_s: np.ndarray  # (T,) s
    alpha_d: np.ndarray  # (T, N) rad
    alpha_hat: np.ndarray  # (T, N) rad
    alpha: np.ndarray  # (T, N) rad, twin truth
    force_N: np.ndarray  # (T, n_cables)
    tension_N: np.ndarray  # (T, n_cables), twin truth
    saturated: np.ndarray  # (T, n_cables) bool
    t_ip_s: np.ndarray  # (K,) capture times
    alpha_ip: np.ndarray  # (K, N) rad

    def metrics(self) -> dict[str, object]:
        return campaign_metrics(self.t_s, self.alpha_hat, self.alpha_d, self.force_N, self.saturated, self.t_ip_s, self.alpha_ip)


def run_closed_loop(
    params: Params, law: LawConfig, trajectory: Trajectory, twin_config: TwinConfig = TwinConfig(), settle_s: float = 1.0
) -> Run:
    """Run ``trajectory`` (plus ``settle_s`` of hold at its end) with ``law`` against a twin."""
    twin = Twin(params, twin_config)
    ctl = ComputedTorque(params, law)
    n = int(round((trajectory.duration_s + settle_s) * twin_config.rate_hz))
    t = np.arange(1, n + 1) / twin_config.rate_hz
    ref = trajectory.sample(t)
    N, nc = twin.model.n_joints, twin.model.n_cables
    out = {k: np.empty((n, w)) for k, w in (("alpha_hat", N), ("alpha", N), ("force_N", nc), ("tension_N", nc))}
    saturated = np.zeros((n, nc), dtype=bool)
    frames_t, frames_a = [], []
    tick = twin.tick(np.zeros(nc))  # the first state the controller sees
    for k in range(n):
        cmd = ctl.step(tick.theta_meas, ref.alpha[k], ref.alpha_dot[k], ref.alpha_ddot[k])
        tick = twin.tick(cmd.f)
        out["alpha_hat"][k], out["force_N"][k], saturated[k] = cmd.alpha_hat, cmd.f, cmd.saturated
        out["alpha"][k], out["tension_N"][k] = tick.alpha, tick.tension
        for capture, alpha_ip in tick.frames:
            frames_t.append(capture)
            frames_a.append(alpha_ip)
    return Run(
        t_s=t, alpha_d=ref.alpha, saturated=saturated,
        t_ip_s=np.array(frames_t), alpha_ip=np.array(frames_a).reshape(-1, N), **out,
    )
