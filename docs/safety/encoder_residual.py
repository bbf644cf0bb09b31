"""The encoder consistency residual measured on the robot truth, and a stuck encoder's detection
time (docs/safety.md, "Stuck encoder"; controller/encoder_check.py).

    .venv/bin/python docs/safety/encoder_residual.py            # about 95 s on the 2-CPU machine
    .venv/bin/python docs/safety/encoder_residual.py --quick    # law 2, seed 0, control test only

What runs: the controller's campaign service (controller.service.CampaignService, the state
machine the controller process runs on the bus) closed on the twin (twin.sim.simulator.Twin) in
one process, one state per 2 ms, as the lockstep campaign does (tests/test_controller_service.py's
loop), with the twin on the robot truth (``--truth robot``: unmodelled friction and stiction,
pulley radius error, backlash, creep, delay and jitter; twin/sim/robot_truth.toml). The check is
called as the suggested wiring in ``CampaignService._encoder_fault`` would call it: before the law
runs, with the encoders of the new state, the law's last α̂, the forces it sent over the last
period and its filtered motor speeds.

1. Normal runs: laws 1, 2, 3 × the §7 control test and the §5.2.2 identification trajectory ×
   seeds: the parity |s| and each encoder's residual |r_j| (mm of cable), max and p99.9, and the
   detector's false alarms with the threshold given.
2. Stuck encoder: the same runs with one encoder's reading frozen from a time on (each motor in
   turn, several times per trajectory, during moves and during stops), fed to the law as the bus
   would: the time from the freeze to the detector's fault, whom it names, how far the joints
   were from α̂ then, and which check came first when the service's own did.
3. The check's cost per tick (µs, :meth:`EncoderConsistency.update`, measured inside the runs).
4. Sensitivity: the normal residual with the robot truth's guessed values at the ends of their ranges.
5. What sets the threshold: one normal run's parity recomputed with the twin's true tension and stretch.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.encoder_check import PERSISTENCE_S, THRESHOLD_M, EncoderConsistency, detector_model, residuals
from controller.laws import LawConfig
from controller.service import CampaignService
from controller.trajectory import Trajectory, trajectory_by_name
from twin.model.numeric import build
from twin.model.params import Params, load_params
from twin.sim.simulator import Twin, TwinConfig
from twin.sim.truth import RobotTruth, load_truth

SETTLE_S = 1.0  # s held at the last waypoint, as a campaign does (CampaignService.settle_s)


@dataclass
class Result:
    t: np.ndarray  # (T,) s, stamps of the states
    s: np.ndarray  # (T,) m, parity
    r: np.ndarray  # (T, nc) m, per-encoder residual
    alpha_err: np.ndarray  # (T,) rad, max |α̂ − α| over the joints (α the twin's truth)
    alpha_abs: np.ndarray  # (T,) rad, max |α| over the joints (the twin's truth)
    flat: np.ndarray  # (T,) bool, the twin refused the step at a joint's flat configuration
    fault_at: float  # s, the detector's first fault (nan: none)
    reason: str  # the detector's reason
    suspects: list[int]  # the detector's suspects at its first fault, most likely first
    service: str  # the service's own hold reason, when it latched first (or at all)
    service_at: float  # s
    outcome: str
    cost_us: np.ndarray  # per update
    inputs: dict[str, np.ndarray]  # per tick: what the check was given, and the twin's true tension and stretch


def run(params: Params, law: int, traj: Trajectory, seed: int, truth: str | RobotTruth = "robot",
        freeze: tuple[int, float] | None = None,
        threshold_m: float = THRESHOLD_M, persistence_s: float = PERSISTENCE_S, stop_on_fault: bool = False,
        after_s: float = 0.5) -> Result:
    """One campaign of ``traj`` with ``law`` on a twin of ``truth``; ``freeze`` = (encoder index,
    time s): its reading stays at what it read then. ``stop_on_fault``: end ``after_s`` after the
    detector's first fault (the service, once wired, would latch a hold there)."""
    twin = Twin(params, TwinConfig(truth=truth, seed=seed, camera=False))
    svc = CampaignService(params, LawConfig(law=law), service=False, settle_s=SETTLE_S)
    check = EncoderConsistency(params, threshold_m, persistence_s)
    tick = twin.tick(np.zeros(params.n_cables))
    svc.initialise(tick.theta_meas)
    svc.begin(traj, tick.t_s)
    n = int(math.ceil((traj.duration_s + SETTLE_S) * 500)) + 50
    T = []
    S, R, AE, AA, FL, cost = [], [], [], [], [], []
    fault_at, reason, service, service_at = math.nan, "", "", math.nan
    suspects: list[int] = []
    frozen = None
    rec: dict[str, list] = {k: [] for k in ("theta", "alpha_hat", "force", "theta_dot", "tension", "stretch")}
    for _ in range(n):
        theta = tick.theta_meas.copy()
        if freeze is not None and tick.t_s >= freeze[1]:
            if frozen is None:
                frozen = float(theta[freeze[0]])
            theta[freeze[0]] = frozen
        ctl = svc.ctl
        t0 = time.perf_counter_ns()
        why = check.update(theta, ctl.estimator.alpha_hat, ctl.f_prev, ctl.theta_dot, tick.t_s,
                           active=svc.drive == "active")
        cost.append(time.perf_counter_ns() - t0)
        for key, value in (("theta", theta), ("alpha_hat", ctl.estimator.alpha_hat), ("force", ctl.f_prev),
                           ("theta_dot", ctl.theta_dot), ("tension", tick.tension), ("stretch", tick.elongation)):
            rec[key].append(np.array(value, dtype=float))
        if why and math.isnan(fault_at):
            fault_at, reason, suspects = tick.t_s, why, list(check.suspects)
        out = svc.control(theta, tick.t_s)
        if out.law_ran:
            svc.advance(tick.t_s)
        svc.drain_events()
        if svc.latched and not service:
            service, service_at = svc.hold_reason, tick.t_s
        T.append(tick.t_s)
        S.append(check.s)
        R.append(check.r.copy())
        AE.append(float(np.max(np.abs(out.alpha_hat_rad - tick.alpha))))
        AA.append(float(np.max(np.abs(tick.alpha))))
        FL.append(tick.flat)
        if stop_on_fault and not math.isnan(fault_at) and tick.t_s >= fault_at + after_s:
            break
        if svc.phase in ("finished", "aborted") and not svc.running:
            break
        tick = twin.tick(out.force_N)
    return Result(np.array(T), np.array(S), np.array(R), np.array(AE), np.array(AA), np.array(FL), fault_at, reason, suspects, service, service_at,
                  svc.outcome or svc.phase, np.array(cost) / 1e3, {k: np.array(v) for k, v in rec.items()})


def _mm(x) -> str:
    return f"{1e3 * float(x):.2f}"


def normal_runs(params, laws, trajectories, seeds, threshold_m, persistence_s) -> tuple[float, np.ndarray]:
    """Part 1: prints one row per run; returns the largest |s| (m) and every update's cost (µs)."""
    print("## 1. Normal runs (robot truth): residuals in mm of cable")
    print()
    print("|α̂ − α|: the largest joint error of the law's estimate (deg, α the twin's truth), for comparison with part 2.")
    print()
    print("| trajectory | law | seed | outcome | |s| max | |s| p99.9 | |r_j| max (enc 1-4) | |r_j| p99.9 (enc 1-4) | "
          "|α̂ − α| (deg) | false alarms |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    worst, worst_at, costs = 0.0, "", []
    per_max, per_p = [], []
    for name, traj in trajectories:
        for law in laws:
            for seed in seeds:
                res = run(params, law, traj, seed, threshold_m=threshold_m, persistence_s=persistence_s)
                s, r = np.abs(res.s), np.abs(res.r)
                if s.max() > worst:
                    worst, worst_at = float(s.max()), f"{name}, law {law}, seed {seed}, at {res.t[s.argmax()]:.3f} s"
                per_max.append(r.max(axis=0))
                per_p.append(np.quantile(r, 0.999, axis=0))
                costs.append(res.cost_us[50:])  # past the first calls
                alarm = "none" if math.isnan(res.fault_at) else f"at {res.fault_at:.2f} s: {res.reason}"
                print(f"| {name} | {law} | {seed} | {res.outcome} | {_mm(s.max())} | {_mm(np.quantile(s, 0.999))} | "
                      f"{' / '.join(_mm(v) for v in r.max(axis=0))} | "
                      f"{' / '.join(_mm(v) for v in np.quantile(r, 0.999, axis=0))} | "
                      f"{math.degrees(float(res.alpha_err.max())):.1f} | {alarm} |", flush=True)
    print()
    pm, pp = np.max(per_max, axis=0), np.max(per_p, axis=0)
    print(f"Over all normal runs: |s| max {_mm(worst)} mm ({worst_at}); per encoder |r_j| max {' / '.join(_mm(v) for v in pm)} mm "
          f"(p99.9 at most {' / '.join(_mm(v) for v in pp)} mm); threshold {_mm(threshold_m)} mm = "
          f"{threshold_m / worst:.2f} × the largest |s|.")
    print()
    return worst, np.concatenate(costs)


def stuck_runs(params, laws, trajectories, seeds, threshold_m, persistence_s, freeze_fractions,
               without: set[str]) -> None:
    """Part 2: one row per frozen encoder and freeze time; the trajectories in ``without`` run on
    to the campaign's end (the check observes only), what the neck does without it."""
    print(f"## 2. Stuck encoder (robot truth): threshold {_mm(threshold_m)} mm, persistence {persistence_s * 1e3:.0f} ms")
    print()
    print("|α̂ − α|: the largest joint error of the estimate (deg, α the twin's truth) from the freeze to the fault. "
          "Without the check: the same from the freeze to the campaign's end, the largest true |α| then (flat steps: "
          "steps the twin refused at a joint's flat configuration, 180°), and the campaign's outcome.")
    print()
    print("| trajectory | law | seed | encoder | frozen at (s) | detected after (s) | named | r_j then (mm) | "
          "|α̂ − α| (deg) | service's own check | without the check |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    delays, errors, missed, first, named_in, total = [], [], 0, 0, 0, 0
    worst_alone: list[float] = []
    by: dict[str, list[tuple[float, float, float]]] = {}  # trajectory or encoder → (delay s, |α̂ − α| deg, |r_j| mm)
    outcomes_alone: list[str] = []
    flat_runs = 0
    for name, traj in trajectories:
        for law in laws:
            for seed in seeds:
                for frac in freeze_fractions:
                    t_f = round(frac * traj.duration_s, 2)
                    for j in range(params.n_cables):
                        total += 1
                        # The check only observes (the service is not wired to it here): run on past its fault,
                        # to the campaign's end, the run is what the neck does without the check.
                        res = run(params, law, traj, seed, freeze=(j, t_f), threshold_m=threshold_m,
                                  persistence_s=persistence_s, stop_on_fault=name not in without)
                        end = res.fault_at if not math.isnan(res.fault_at) else res.t[-1]
                        window = (res.t >= t_f) & (res.t <= end)
                        err = math.degrees(float(res.alpha_err[window].max())) if window.any() else math.nan
                        own = "none"
                        if res.service:
                            when = "first" if math.isnan(res.fault_at) or res.service_at < res.fault_at else "later"
                            own = f"{when}, after {res.service_at - t_f:.2f} s: {res.service[:50]}"
                        alone = "-"
                        if name in without:
                            after = res.t >= t_f
                            alone = (f"{math.degrees(float(res.alpha_err[after].max())):.0f}°, |α| up to "
                                     f"{math.degrees(float(res.alpha_abs[after].max())):.0f}°"
                                     + (f" ({int(res.flat[after].sum())} flat steps)" if res.flat[after].any() else "")
                                     + f", {res.outcome}")
                            worst_alone.append(float(res.alpha_abs[after].max()))
                            flat_runs += int(res.flat[after].any())
                            outcomes_alone.append(res.outcome)
                        if math.isnan(res.fault_at):
                            missed += 1
                            grown = np.nanmax(np.abs(res.s[res.t >= t_f]))
                            print(f"| {name} | {law} | {seed} | {j + 1} | {t_f:.2f} | not detected by "
                                  f"{res.t[-1] - t_f:.1f} s (|s| max {_mm(grown)} mm) | - | - | {err:.1f} | {own} | {alone} |",
                                  flush=True)
                            continue
                        first += int(bool(res.suspects) and res.suspects[0] == j)
                        named_in += int(j in res.suspects)
                        delays.append(res.fault_at - t_f)
                        errors.append(err)
                        missed_mm = 1e3 * float(res.r[int(np.searchsorted(res.t, res.fault_at)), j])
                        by.setdefault(name, []).append((res.fault_at - t_f, err, abs(missed_mm)))
                        by.setdefault(f"encoder {j + 1}", []).append((res.fault_at - t_f, err, abs(missed_mm)))
                        named = " or ".join(str(k + 1) for k in res.suspects) or "unknown"
                        mark = "" if res.suspects and res.suspects[0] == j else (" (also)" if j in res.suspects
                                                                                  else " (wrong)")
                        print(f"| {name} | {law} | {seed} | {j + 1} | {t_f:.2f} | {res.fault_at - t_f:.2f} | "
                              f"{named}{mark} | {missed_mm:+.1f} | {err:.1f} | {own} | {alone} |", flush=True)
    print()
    if delays:
        d, e = np.array(delays), np.array(errors)
        print(f"Detected {len(d)} of {total} stuck encoders; the frozen one named first {first} times, among the named "
              f"{named_in} times. Time from the freeze to the fault: median {np.median(d):.2f} s, p90 "
              f"{np.quantile(d, 0.9):.2f} s, max {d.max():.2f} s; |α̂ − α| by then median {np.median(e):.1f}°, "
              f"max {e.max():.1f}°.")
    for key, rows in by.items():
        a = np.array(rows)
        print(f"- {key}: detected after {a[:, 0].min():.2f}-{a[:, 0].max():.2f} s (median {np.median(a[:, 0]):.2f} s), "
              f"|α̂ − α| then {a[:, 1].min():.1f}-{a[:, 1].max():.1f}°, the frozen cable's |r_j| "
              f"{a[:, 2].min():.1f}-{a[:, 2].max():.1f} mm")
    if worst_alone:
        print(f"Without the check ({len(worst_alone)} runs to the end): the true |α| reached "
              f"{math.degrees(min(worst_alone)):.0f}-{math.degrees(max(worst_alone)):.0f}°, {flat_runs} runs at a joint's "
              f"flat configuration; outcomes: {outcomes_alone.count('finished')} finished, "
              f"{outcomes_alone.count('aborted')} aborted (the service's own checks).")
    print()


def truth_variants(params, threshold_m, persistence_s) -> None:
    """Part 4: the normal residual of law 2 on the control test when the robot truth's guessed
    values are at the ends of the ranges docs/twin-fidelity.md gives them."""
    print("## 4. Sensitivity: law 2, control test, seed 0, robot truth with one value changed")
    print()
    print("| truth | |s| max (mm) | |s| p99.9 (mm) | false alarm |")
    print("|---|---|---|---|")
    robot = load_truth("robot")
    variants = [("robot", robot),
                ("friction.static_ratio = 1.5", robot.replace("friction", static_ratio=1.5)),
                ("friction.static_ratio = 1.1", robot.replace("friction", static_ratio=1.1)),
                ("friction.stribeck_velocity_rad_s = 0.5", robot.replace("friction", stribeck_velocity_rad_s=0.5)),
                ("friction.stribeck_velocity_rad_s = 5", robot.replace("friction", stribeck_velocity_rad_s=5.0)),
                ("cables.creep_ratio = 0.10", robot.replace("cables", creep_ratio=0.10)),
                ("structure.pulley_radius_offset_m = 0.0002", robot.replace("structure", pulley_radius_offset_m=0.0002)),
                ("model (the parameter file, c_a = 3000 N·s/m)", "model")]
    traj = trajectory_by_name("control_test")
    for label, truth in variants:
        res = run(params, 2, traj, 0, truth=truth, threshold_m=threshold_m, persistence_s=persistence_s)
        s = np.abs(res.s)
        alarm = "none" if math.isnan(res.fault_at) else f"at {res.fault_at:.2f} s"
        print(f"| {label} | {_mm(s.max())} | {_mm(np.quantile(s, 0.999))} | {alarm} |", flush=True)
    print()


def what_limits_it(params) -> None:
    """Part 5: the parity of one normal run recomputed with better knowledge than the controller
    has, to show which error sets the threshold."""
    res = run(params, 2, trajectory_by_name("control_test"), 0)
    d = res.inputs
    m = detector_model(params)
    x = d["stretch"]
    as_force = m.k * x / np.maximum(1.0 - m.lam * x, 0.05)  # eq. 54 at rest: the tension of the true stretch
    rows = [
        ("rigid cables (x = 0)", residuals(build(params, "rigid"), d["theta"], d["alpha_hat"], d["force"])[0]),
        ("x from the motor forces, no friction", residuals(m, d["theta"], d["alpha_hat"], d["force"])[0]),
        ("x from the motor forces less eq. 37's friction (the check)",
         residuals(m, d["theta"], d["alpha_hat"], d["force"], d["theta_dot"])[0]),
        ("x from the twin's true tension (eq. 54 at rest)", residuals(m, d["theta"], d["alpha_hat"], d["tension"])[0]),
        ("the twin's true stretch", residuals(m, d["theta"], d["alpha_hat"], as_force)[0]),
    ]
    print("## 5. What sets the threshold: law 2, control test, seed 0, robot truth; the parity |s| with the stretch")
    print()
    print("| stretch x in the residual | |s| max (mm) | |s| p99.9 (mm) |")
    print("|---|---|---|")
    for label, s in rows:
        print(f"| {label} | {_mm(np.abs(s).max())} | {_mm(np.quantile(np.abs(s), 0.999))} |")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--laws", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--trajectories", nargs="+", default=["control_test", "identification"])
    ap.add_argument("--stuck-seeds", type=int, nargs="+", default=[0], help="seeds of the stuck-encoder runs")
    ap.add_argument("--freeze-fractions", type=float, nargs="+", default=[0.1, 0.3, 0.5, 0.7],
                    help="freeze times as fractions of the trajectory's duration")
    ap.add_argument("--threshold-mm", type=float, default=THRESHOLD_M * 1e3)
    ap.add_argument("--persistence-ms", type=float, default=PERSISTENCE_S * 1e3)
    ap.add_argument("--without-check", nargs="*", default=["control_test"],
                    help="trajectories whose stuck runs are also run without the check, to the end")
    ap.add_argument("--no-variants", action="store_true", help="skip parts 4 and 5")
    ap.add_argument("--quick", action="store_true", help="law 2, seed 0, the control test only")
    args = ap.parse_args()
    if args.quick:
        args.laws, args.seeds, args.stuck_seeds, args.trajectories = [2], [0], [0], ["control_test"]
    params = load_params()
    trajectories = [(name, trajectory_by_name(name)) for name in args.trajectories]
    threshold, persistence = args.threshold_mm * 1e-3, args.persistence_ms * 1e-3
    print(f"Command: .venv/bin/python docs/safety/encoder_residual.py {' '.join(sys.argv[1:])}".rstrip())
    print()
    t0 = time.perf_counter()
    _, cost = normal_runs(params, args.laws, trajectories, args.seeds, threshold, persistence)
    stuck_runs(params, args.laws, trajectories, args.stuck_seeds, threshold, persistence, args.freeze_fractions,
               set(args.without_check))
    print(f"## 3. Cost of EncoderConsistency.update per tick: median {np.median(cost):.1f} µs, "
          f"p99 {np.quantile(cost, 0.99):.1f} µs over {cost.size} ticks (wall clock, this machine)")
    print()
    if not args.no_variants:
        truth_variants(params, threshold, persistence)
        what_limits_it(params)
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
