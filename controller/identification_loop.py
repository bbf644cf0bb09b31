"""The identification campaign's closed loop in one process, without the bus (3-X paper §5.2.2).

Computed torque on the twin's *true* α, the cable tensions kept at least ``floor_N`` through the
positive null vector of Z (raised by the trajectory's pretension, if any), the model's friction (eq. 37) compensated: smooth, rich forces, as §5.2.2
asks. It is not law 1 (law 1 runs on α̂; its campaigns are `xneck campaign identification`): it is
the known-answer loop of the identification tests, of the coverage benchmark
(benchmarks/identification.py) and of the docs' diagnosis scripts, one definition for all of them.
:func:`law1_campaign` is law 1's campaign itself, in process (docs/identification/law1_coverage.py,
docs/make_twin_fidelity.py).

:data:`DAMPING_ONLY_TRUTH` is the truth the identification tests were written for: the robot
truth's small cable damping alone (twin/sim/robot_truth.toml), the other unmodelled effects off.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from controller.trajectory import identification_trajectory
from twin.identification.processing import CampaignData
from twin.model import dynamics
from twin.sim.simulator import Twin, TwinConfig
from twin.sim.truth import RobotTruth, load_truth

DAMPING_ONLY_TRUTH = load_truth("robot").only("cables").replace("cables", creep_ratio=0.0)


def simulate_campaign(seed: int, duration_s: float | None = None, omega: float = 11.0, floor_N: float = 10.0,
                      still: bool = False, truth=DAMPING_ONLY_TRUTH, params=None,
                      trajectory=None) -> tuple[CampaignData, dict[str, np.ndarray]]:
    """Run the identification trajectory (or ``trajectory``) on a twin; returns the campaign and the
    twin's truth at every tick (α, cable tension, stretch, motor speed: docs/identification/
    diagnose_robot_truth.py fits against them). ``still``: hold the straight pose instead (motors
    never move). ``params``/``truth``: what the twin integrates (default: the 3-X prototype with the
    robot's damping)."""
    twin = Twin(params, TwinConfig(seed=seed, truth=truth))
    m = twin.model
    traj = trajectory or identification_trajectory()
    T = int(round((duration_s or traj.duration_s) / twin.dt))
    t = np.arange(1, T + 1) * twin.dt
    ref = traj.sample(np.zeros(T) if still else t - twin.dt)
    floor = floor_N + (np.zeros(T) if still else traj.pretension(t - twin.dt))  # a trajectory's pretension raises it
    kp, kv = 3 * omega**2, 3 * omega
    theta, force, alpha_true = np.empty((T, 4)), np.empty((T, 4)), np.empty((T, 3))
    tension, stretch, speed = np.empty((T, 4)), np.empty((T, 4)), np.empty((T, 4))
    stamp = np.empty(T)  # s, the twin's clock: with the truth's timing jitter its periods vary
    t_ip, a_ip = [], []
    alpha, alpha_dot, theta_dot = np.zeros(3), np.zeros(3), np.zeros(4)
    for k in range(T):
        w = ref.alpha_ddot[k] + kv * (ref.alpha_dot[k] - alpha_dot) + kp * (ref.alpha[k] - alpha)
        terms = dynamics.evaluate(m, alpha, alpha_dot)
        Z = terms.Z
        gamma = terms.M @ w + terms.c + terms.g
        null = np.append(-np.linalg.solve(Z[:, :3], Z[:, 3]), 1.0)  # positive (ERRATA)
        f_p = np.append(np.linalg.solve(Z[:, :3], gamma), 0.0)
        f_fr = dynamics.f_friction(m, theta_dot)
        # Both the tension and the motor force stay above the floor.
        s = max(np.max((floor[k] - f_p) / null), np.max((floor[k] - f_p - f_fr) / null))
        f = np.clip(f_p + s * null + f_fr, m.f_min, m.f_max)
        tick = twin.tick(f)
        alpha, alpha_dot, theta_dot = tick.alpha, tick.alpha_dot, tick.theta_dot
        theta[k], force[k], alpha_true[k], stamp[k] = tick.theta_meas, f, alpha, tick.t_s
        tension[k], stretch[k], speed[k] = tick.tension, tick.elongation, tick.theta_dot
        for capture, frame in tick.frames:
            t_ip.append(capture)
            a_ip.append(frame)
    data = CampaignData(stamp, theta, force, np.array(t_ip), np.array(a_ip), campaign=f"twin-seed{seed}",
                        excitation_alpha_rad=None if still else ref.alpha)
    return data, {"t": stamp, "alpha": alpha_true, "tension": tension, "stretch": stretch, "theta_dot": speed}


def law1_campaign(seed: int, truth: str | RobotTruth = "robot", params=None, trajectory=None,
                  alpha_ip: Literal["noise", "camera"] = "camera") -> CampaignData:
    """Law 1's identification campaign in process: what `xneck campaign identification` runs over
    the bus (law 1 on α̂, the §5.2.2 cycloids or ``trajectory``, a lockstep twin of ``truth`` whose
    α_IP is measured on rendered frames), through the offline closed loop
    (controller.offline.run_closed_loop, the lockstep campaign's loop), as a campaign record for the
    identification pipeline. Unlike :func:`simulate_campaign` nothing here knows the true α."""
    from controller.laws import LawConfig
    from controller.offline import run_closed_loop
    from twin.model.params import load_params

    params = params or load_params()
    traj = trajectory or identification_trajectory()
    run = run_closed_loop(params, LawConfig(law=1), traj, TwinConfig(truth=truth, seed=seed, alpha_ip=alpha_ip),
                          settle_s=0.0)
    seen = np.isfinite(run.alpha_ip).all(axis=1)
    return CampaignData(run.t_s, run.theta_meas, run.force_N, run.t_ip_s[seen], run.alpha_ip[seen],
                        campaign=f"law1-{seed}", excitation_alpha_rad=run.alpha_d)


def identify_campaign(seed: int, truth=DAMPING_ONLY_TRUTH, estimator: str = "iv", trajectory=None, params=None,
                      creep_time_s: float | None = None):
    """:func:`simulate_campaign` then the pipeline's Table 2 identification (friction first, then
    the variable-stiffness cables with ``estimator``): the coverage benchmark's and the docs'
    known-answer run. Returns the variable model's estimate (twin.identification.estimators).
    ``creep_time_s``: the line's creep time constant held in the load-friction fit (None: chosen)."""
    from twin.identification.pipeline import identify_friction, identify_variable, preprocess
    from twin.model.params import load_params

    params = params or load_params()
    proc = preprocess(simulate_campaign(seed, truth=truth, params=params, trajectory=trajectory)[0], params)
    return identify_variable(proc, params, identify_friction(proc, params).values, estimator=estimator,
                             creep_time_s=creep_time_s)

