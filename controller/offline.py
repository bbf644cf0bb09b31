"""Closed loop of a law and the twin in one process, without the bus.

For tests, benchmarks and the results report: the same :class:`ComputedTorque` and
:class:`Twin` that the bus processes wrap, stepped alternately (state → command → tick), which is
exactly what the lockstep bus mode does. :class:`ServiceLoop` closes the controller's campaign
service on the twin through the bridge's safety rules instead, as the three processes do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bridge import bus
from bridge.motor_speed import MotorSpeed
from bridge.safety import Inputs, Safety, SafetyConfig
from controller.laws import ComputedTorque, LawConfig, encoder_hold_forces
from controller.metrics import campaign_metrics
from controller.service import CampaignService
from controller.trajectory import Trajectory
from twin.model.params import Params
from twin.sim.simulator import Twin, TwinConfig


@dataclass
class Run:
    t_s: np.ndarray  # (T,) s
    alpha_d: np.ndarray  # (T, N) rad
    alpha_hat: np.ndarray  # (T, N) rad
    alpha: np.ndarray  # (T, N) rad, twin truth
    theta_meas: np.ndarray  # (T, n_cables) rad, the encoders as the bridge reports them
    force_N: np.ndarray  # (T, n_cables)
    tension_N: np.ndarray  # (T, n_cables), twin truth
    saturated: np.ndarray  # (T, n_cables) bool
    t_ip_s: np.ndarray  # (K,) capture times
    alpha_ip: np.ndarray  # (K, N) rad, NaN for a joint the camera did not measure
    ip_stamp_s: np.ndarray  # (K,) when each frame was delivered (capture + the camera's latency)
    ip_confidence: np.ndarray  # (K, N) per joint in [0, 1]; NaN when the camera does not grade (white noise)
    ip_source: str = ""  # the twin camera's CameraAlpha.source
    flat_steps: int = 0  # steps the twin refused at a joint's flat singularity (the run left the model's range)

    def metrics(self) -> dict[str, object]:
        seen = np.isfinite(self.alpha_ip).all(axis=1)  # a frame with a missing joint compares with nothing
        return campaign_metrics(self.t_s, self.alpha_hat, self.alpha_d, self.force_N, self.saturated,
                                self.t_ip_s[seen], self.alpha_ip[seen])

    def messages(self) -> list[tuple[str, int, bus.BusMessage]]:
        """The run as the bus would have carried it — ``MotorState`` every tick (encoders, the
        forces applied), ``CameraAlpha`` per frame — for :func:`bridge.archive.write_campaign`,
        so the archive readers (``xneck identify``) read a closed loop run here as a bus campaign."""
        out: list[tuple[str, int, bus.BusMessage]] = []
        for k, t in enumerate(self.t_s.tolist()):
            out.append((bus.MOTOR_STATE, round(t * 1e9), bus.MotorState(
                seq=k + 1, stamp_s=t, theta_rad=self.theta_meas[k].tolist(), force_applied_N=self.force_N[k].tolist(),
                drive="active", epoch="offline", bridge="offline")))
        for k, (t, a, c) in enumerate(zip(self.t_ip_s.tolist(), self.alpha_ip, self.ip_confidence, strict=True)):
            stamp = float(self.ip_stamp_s[k])
            out.append((bus.CAMERA_ALPHA, round(stamp * 1e9) + 1, bus.CameraAlpha(
                seq=k + 1, stamp_s=stamp, capture_stamp_s=t, source=self.ip_source,
                alpha_ip_rad=[None if np.isnan(x) else float(x) for x in a],
                confidence=[] if np.isnan(c).all() else c.tolist())))
        return sorted(out, key=lambda m: m[1])


def run_closed_loop(
    params: Params, law: LawConfig, trajectory: Trajectory, twin_config: TwinConfig = TwinConfig(), settle_s: float = 1.0,
    model: Params | None = None,
) -> Run:
    """Run ``trajectory`` (plus ``settle_s`` of hold at its end) with ``law`` against a twin of
    ``params``; the controller holds ``model`` (default: the same set; a study's robot differs from it).

    On the twin's clock, as on the bus: each tick's α^d is the trajectory at the stamp of the state
    the law acts on, and ``t_s`` holds those stamps, the clock of the camera frames too (with the
    robot's timing jitter the periods vary, and a nominal k·dt drifts from the frames). The law is
    told each stamp (``ComputedTorque.step``'s ``stamp_s``), as in ``controller.service``: it
    differentiates and integrates over the twin's actual period, so an offline run and a bus run
    do the same arithmetic; on a steady clock (no jitter) that is the fixed period, bit for bit."""
    twin = Twin(params, twin_config)
    ctl = ComputedTorque(params if model is None else model, law)
    n = int(round((trajectory.duration_s + settle_s) * twin_config.rate_hz))
    t = np.empty(n)
    N, nc = twin.model.n_joints, twin.model.n_cables
    alpha_d = np.empty((n, N))
    out = {k: np.empty((n, w)) for k, w in (("alpha_hat", N), ("alpha", N), ("force_N", nc), ("tension_N", nc),
                                            ("theta_meas", nc))}
    saturated = np.zeros((n, nc), dtype=bool)
    frames_t, frames_a, frames_stamp, frames_c = [], [], [], []
    tick = twin.tick(np.zeros(nc))  # the first state the controller sees
    flat_steps = int(tick.flat)
    for k in range(n):
        t[k] = tick.t_s
        a_d, a_d_dot, a_d_ddot = trajectory.sample_at(t[k])
        alpha_d[k] = a_d
        # the stamp as the service gives it: the law spans the twin's real period (jitter included)
        cmd = ctl.step(tick.theta_meas, a_d, a_d_dot, a_d_ddot, trajectory.pretension_at(t[k]), t[k])
        tick = twin.tick(cmd.f)
        flat_steps += int(tick.flat)
        out["alpha_hat"][k], out["force_N"][k], saturated[k] = cmd.alpha_hat, cmd.f, cmd.saturated
        out["alpha"][k], out["tension_N"][k], out["theta_meas"][k] = tick.alpha, tick.tension, tick.theta_meas
        for j, (capture, alpha_ip) in enumerate(tick.frames):
            frames_t.append(capture)
            frames_a.append(alpha_ip)
            frames_stamp.append(tick.t_s)
            frames_c.append(tick.frame_confidence[j] if j < len(tick.frame_confidence) else np.full(N, np.nan))
    return Run(
        t_s=t, alpha_d=alpha_d, saturated=saturated,
        t_ip_s=np.array(frames_t), alpha_ip=np.array(frames_a).reshape(-1, N), ip_stamp_s=np.array(frames_stamp),
        ip_confidence=np.array(frames_c).reshape(-1, N), ip_source=twin.camera.source if twin.camera else "",
        flat_steps=flat_steps, **out,
    )


class ServiceLoop:
    """The controller's campaign service (:class:`controller.service.CampaignService`) closed on a
    twin of ``params`` through the bridge's safety rules (:class:`bridge.safety.Safety`, the hold
    rule of the encoders and the motors' speeds as :class:`bridge.node.BridgeNode` gives them),
    one state per tick, every command answered and delivered at once: what the bridge, the
    controller and the twin do on the bus, in one process. :attr:`tick` is the last state."""

    def __init__(self, params: Params, law: LawConfig, twin_config: TwinConfig, settle_s: float = 0.5) -> None:
        self.twin = Twin(params, twin_config)
        self.svc = CampaignService(params, law, settle_s=settle_s, service=True)
        self.safety = Safety(SafetyConfig(n_motors=params.n_cables, f_min_N=params.limits.f_min,
                                          f_max_N=params.limits.f_max))
        self.hold_rule = encoder_hold_forces(params)
        self.speed = MotorSpeed(params.n_cables, 1.0 / law.rate_hz)
        self.tick = self.twin.tick(np.zeros(params.n_cables))
        self.speed.update(self.tick.theta_meas.tolist())
        self.svc.initialise(self.tick.theta_meas)

    def start(self, trajectory: Trajectory, kind: str = "campaign", campaign_id: str = "c") -> None:
        """Ask the service to run ``trajectory`` (``kind`` "campaign" or "jog") from the current state."""
        self.svc.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id=campaign_id, action="start",
                                            law=self.svc.law.law, kind=kind,  # type: ignore[arg-type]
                                            trajectory_json=trajectory.to_json()), self.tick.t_s)

    def step(self) -> np.ndarray:
        """One state → the service's command → the bridge's rules → the twin's tick; returns the
        forces applied (N)."""
        tick, safety = self.tick, self.safety
        out = self.svc.control(tick.theta_meas, tick.t_s, safety.drive, np.asarray(safety.force))
        if out.law_ran:
            self.svc.advance(tick.t_s)
        self.svc.drain_events()
        d = safety.step(Inputs(command_N=out.force_N.tolist(), command_age_s=0.0, states_unanswered=0, estop=(),
                               hold_N=self.hold_rule(tick.theta_meas).tolist(), sender="c", speed_rad_s=self.speed.rad_s))
        applied = np.asarray(d.force_N, dtype=float)
        self.last_alpha_d = out.alpha_d_rad
        self.tick = self.twin.tick(applied)
        self.speed.update(self.tick.theta_meas.tolist())
        return applied
