"""``xneck excitation design``: a D-optimal identification excitation (twin/identification/excitation.py)
written as a trajectory file that ``xneck campaign identification --trajectory FILE`` runs.

The composition lives here because it joins two layers: the design (twin) is given the
controller's cycloidal path, the forces law 1 commands on it (the identification campaign's law)
and the controller's trajectory validation, the very checks a campaign applies to the file.
"""

from __future__ import annotations

import math
from pathlib import Path

import typer

from server.cli.options import (
    PARAMS_OPTION,
    SET_OPTION,
    atomic_write_text,
    check_output,
    echo_json,
    fail,
    law_config,
    load_cli_params,
    write_failed,
)

excitation_app = typer.Typer(help="Design identification excitations (D-optimal cycloids within the limits).",
                             no_args_is_help=True)


PRETENSION_MAX_N = 0.0  # default: no pretension. Measured (docs/identification.md, "Does the design
# model predict…"): a 40 N pretension design lowers the λ's σ by 25-45 % on the damping-only truth,
# but on the robot truth the load-dependent friction and creep grow with the tension, and the λ
# errors with them (λ(4) 14 % against the cycloids' 7 %)
PAPER_BOX_DEG = "40,30,20"  # the §5.2.2 amplitudes: the envelope law 1 is known to track (Fig. 10 of the paper)


def _box(box_deg: str, n_joints: int, alpha_max_deg: float):
    """--box-deg "a1,a2,a3" (or one value for all joints) as rad, within the joint limits."""
    from twin.identification.excitation import DesignError

    try:
        values = [float(v) for v in box_deg.split(",")]
    except ValueError:
        raise DesignError(f"--box-deg must be numbers separated by commas (deg), got {box_deg!r}") from None
    if len(values) == 1:
        values *= n_joints
    if len(values) != n_joints or not all(0.0 < v <= alpha_max_deg for v in values):
        raise DesignError(f"--box-deg needs one amplitude for every joint or {n_joints}, one per joint, each in "
                          f"(0, {alpha_max_deg:g}]° (the joint limit), got {box_deg!r}")
    return [math.radians(v) for v in values]


def _problem(params, duration_s: float, speed: float, criterion: str = "d", box_deg: str = PAPER_BOX_DEG,
             pretension_max_N: float = 0.0, holds: str = "none"):
    """The design problem for ``params`` with the controller's path, forces and validation; the
    waypoints stay in the ±``box_deg`` box (the joint limits are checked by the validation), the
    pretensions in [0, ``pretension_max_N``]."""
    import numpy as np

    from controller.laws import nominal_force_check, nominal_forces
    from controller.trajectory import Trajectory, TrajectoryLimits, validate
    from twin.identification.excitation import DesignProblem

    config = law_config(1, False)  # the identification campaign's law (xneck campaign identification)
    limits = TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg))
    a_max, v_max, acc_max = limits.per_joint(params.n_joints)
    force_check = nominal_force_check(params, config)

    def path(start, end, T, t):
        return Trajectory(np.vstack([start, end]), np.array([T]), np.zeros(2)).sample(t)

    def check(waypoints, durations, dwell, pretension) -> None:
        validate(Trajectory(waypoints, durations, dwell, "excitation", pretension), limits, params.n_joints, force_check)

    box = _box(box_deg, params.n_joints, params.limits.alpha_max_deg)
    return DesignProblem.create(params, duration_s=duration_s, alpha_max_rad=np.minimum(box, a_max), v_max_rad_s=v_max,
                                a_max_rad_s2=acc_max, path=path, forces=nominal_forces(params, config),
                                check=check, speed=speed, criterion=criterion, pretension_max_N=pretension_max_N,
                                pretension_rate_N_s=limits.pretension_rate_max_N_s, holds=holds)


def design_command(
    duration: float = typer.Option(97.0, "--duration", help="Duration of the trajectory (s), rests included; "
                                   "97 s is the §5.2.2 identification trajectory's."),
    out: Path = typer.Option(Path("excitation.json"), "--out", help="Trajectory file to write (.json, degrees); "
                             "the design's scores go to <stem>.design.json beside it. Refused if either "
                             "exists, unless --force."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the random starting designs (≥ 0)."),
    waypoints: int | None = typer.Option(None, "--waypoints", help="Number of waypoints, the straight start and "
                                         "end included (default: one every 4 s)."),
    speed: float = typer.Option(0.6, "--speed", help="Fraction of the speed and acceleration limits the moves "
                                "use (faster moves raise the filter cutoff, hence the camera noise let in)."),
    criterion: str = typer.Option("d", "--criterion", help="d: D-optimality on f_s, k, λ and c_a; ds: on f_s, "
                                  "k and λ only (the damping, barely identifiable, a nuisance)."),
    box_deg: str = typer.Option(PAPER_BOX_DEG, "--box-deg", help="Largest |α| per joint (deg), e.g. 40,30,20 (the "
                                "§5.2.2 amplitudes, the default), or one value for every joint: a design out to the joint limits (60°) asks law 1 "
                                "for poses where it loses track (a campaign aborted on a diverging α̂)."),
    pretension_max: float = typer.Option(PRETENSION_MAX_N, "--pretension-max", help="Largest pretension a waypoint "
                                         "may add to every cable's floor t_min (N), to sweep the tensions over "
                                         "eqs. 54-57's curve; 0 (default) designs the joints alone. Keep "
                                         "it below f_max minus the law's forces (the design checks them)."),
    holds: str = typer.Option("none", "--holds", help="none: the moves are stretched to fill the duration (a "
                              "still motor gives the identification no row); fill: the shortest moves, the "
                              "remaining time as holds at the waypoints (the §5.2.2 trajectory's stops)."),
    starts: int = typer.Option(2, "--starts", min=1, help="Random starting designs, each optimised."),
    maxiter: int = typer.Option(40, "--maxiter", min=0, help="L-BFGS-B iterations per start."),
    as_json: bool = typer.Option(False, "--json", help="Print the scores as JSON."),
    force: bool = typer.Option(False, "--force", help="Overwrite --out and its <stem>.design.json."),
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """Optimise an identification trajectory (D-optimal for friction and variable stiffness), compare
    it with the §5.2.2 cycloids, and write it for `xneck campaign identification --trajectory FILE`."""
    from controller.trajectory import Trajectory, TrajectoryLimits, identification_trajectory
    from twin.identification.excitation import MIN_MOVE_S, DesignError, design, score

    # What one campaign may run: a longer design (--duration 1e9, --waypoints 1000000) optimised for
    # hours before its campaign would be refused (audit of 2026-11-27).
    limits = TrajectoryLimits()
    if math.isfinite(duration) and duration > limits.duration_max_s:
        raise fail(f"--duration {duration:g} s: a campaign runs at most {limits.duration_max_s:g} s")
    if waypoints is not None and math.isfinite(duration) and waypoints > min(limits.waypoints_max, duration / MIN_MOVE_S + 1):
        raise fail(f"--waypoints {waypoints}: at most {int(min(limits.waypoints_max, duration / MIN_MOVE_S + 1))} "
                   f"in {duration:g} s (moves of at least {MIN_MOVE_S:g} s, {limits.waypoints_max} waypoints a campaign)")
    if out.suffix.lower() != ".json":  # --trajectory reads a file by its suffix: JSON in a .toml would not load
        raise fail(f"--out must be a .json file (the trajectory is written as JSON), got {out}")
    check_output(out)  # before the design, which takes minutes
    design_path = out.with_name(out.stem + ".design.json")
    # An earlier design and its scores (which docs cite) were replaced without a word, where
    # identify, campaign --out and twin calibrate refuse an existing output (input audit).
    for path in (out, design_path):
        if not force and (path.exists() or path.is_symlink()):
            raise fail(f"{path} exists: choose another --out or add --force")
    params = load_cli_params(params_file, overrides)
    try:
        problem = _problem(params, duration, speed, criterion, box_deg, pretension_max, holds)
        if waypoints is not None and waypoints < 3:
            raise DesignError(f"--waypoints must be at least 3 (straight, one pose, straight), got {waypoints}")
        # margin 1: the box is the bound asked for (the joint limits are the validation's). With as
        # many waypoints, the §5.2.2 cycloids are the first start: the design cannot lose to them.
        paper = identification_trajectory()
        k = waypoints if waypoints is not None else max(int(round(duration / 4.0)) + 1, 3)
        start = paper.waypoints_rad if k == paper.n_waypoints else None
        result = design(problem, n_waypoints=waypoints, seed=seed, starts=starts, maxiter=maxiter, margin=1.0,
                        start=start, progress=lambda line: typer.echo(f"design: {line}", err=True))
    except DesignError as exc:
        typer.secho(f"error: {exc}", err=True, fg="red")
        raise typer.Exit(2) from None
    baseline = score(problem, paper.waypoints_rad, paper.durations_s, paper.dwell_s)
    traj = Trajectory(result.waypoints_rad, result.durations_s, result.dwell_s, f"excitation-seed{seed}",
                      result.pretension_N)
    report = {
        "trajectory_file": str(out), "duration_s": traj.duration_s, "waypoints": traj.n_waypoints,
        "seed": seed, "speed": speed, "criterion": criterion, "box_deg": box_deg, "holds": holds,
        "started_from_the_cycloids": start is not None, "iterations": result.iterations,
        "pretension_max_N": pretension_max, "pretension_N": result.pretension_N.tolist(),
        "designed": result.score.to_dict(), "paper_4x6_cycloids": baseline.to_dict(),
        "gain": {"log_det": result.score.log_det - baseline.log_det,
                 "cond_friction_ratio": baseline.cond_friction / result.score.cond_friction,
                 "cond_variable_ratio": baseline.cond_variable / result.score.cond_variable,
                 # predicted σ(designed)/σ(cycloids) at equal duration and noise (√diag F⁻¹)
                 "predicted_sigma_ratio": {n: result.score.relative_sigma[n] / baseline.relative_sigma[n]
                                           for n in baseline.relative_sigma}},
    }
    try:
        from twin.jsonout import strict_json

        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out, strict_json(traj.to_dict(), indent=1) + "\n")
        atomic_write_text(design_path, strict_json(report, indent=2) + "\n")
    except OSError as exc:  # the disk filled or the folder went away since the check
        raise write_failed(out, exc) from None
    if as_json:
        echo_json(report)
        return
    d, b = result.score, baseline
    typer.echo(f"designed excitation: {traj.n_waypoints} waypoints, {traj.duration_s:.1f} s "
               f"(§5.2.2 cycloids: {paper.n_waypoints}, {paper.duration_s:.1f} s)")
    if traj.has_pretension:
        typer.echo(f"pretension: 0 … {traj.pretension_N.max():.1f} N over the waypoints (bound {pretension_max:g} N)")
    typer.echo(f"{'':34s}{'designed':>12s}{'4x6 cycloids':>14s}")
    for label, a, c in (("log det F (friction + variable)", d.log_det, b.log_det),
                        ("  log det F friction (eq. 38)", d.log_det_friction, b.log_det_friction),
                        ("  log det F variable (eqs. 54-57)", d.log_det_variable, b.log_det_variable),
                        ("cond, friction regressor", d.cond_friction, b.cond_friction),
                        ("cond, variable regressor", d.cond_variable, b.cond_variable)):
        typer.echo(f"{label:34s}{a:12.4g}{c:14.4g}")
    ratios = report["gain"]["predicted_sigma_ratio"]
    typer.echo("predicted σ(designed)/σ(cycloids), same duration and noise: "
               + ", ".join(f"{n} {r:.2f}" for n, r in ratios.items() if not n.startswith("c_a")))
    typer.echo(f"information ratio det F: ×{math.exp(d.log_det - b.log_det):.3g}; written {out} (scores {design_path.name})")
    typer.echo(f"run it: xneck campaign identification --trajectory {out}")


def bound_command(
    duration: float = typer.Option(97.0, "--duration", help="Duration the excitation may last (s), rests included; "
                                   "97 s is the §5.2.2 identification trajectory's."),
    target: float = typer.Option(0.5, "--target", help="σ ratio asked of every k and λ against the §5.2.2 "
                                 "cycloids (issue 17: 0.5, halved)."),
    t_max: float | None = typer.Option(None, "--t-max", help="Highest cable tension a design may use (N; default "
                                       "f_max, the law's clamp)."),
    trajectories: list[Path] | None = typer.Option(None, "--trajectory", help="A trajectory file (e.g. from "
                                                   "`xneck excitation design`) to score beside the bound; repeat "
                                                   "for several."),
    as_json: bool = typer.Option(False, "--json", help="Print the figures as JSON."),
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """The least σ of each k and λ any excitation of this duration could give, against the §5.2.2
    cycloids (design model; Elfving's c-optimal bound, twin/identification/excitation_bound.py):
    whether a σ ratio target is reachable at all, and the shortest record where it would be."""
    from controller.trajectory import TrajectoryError, identification_trajectory, load_trajectory
    from twin.identification.excitation import MIN_TENSION_N, REST_S, DesignError, score
    from twin.identification.excitation_bound import sigma_bound

    params = load_cli_params(params_file, overrides)
    t_hi = params.limits.f_max if t_max is None else t_max
    if not (math.isfinite(duration) and duration > 2 * REST_S):
        raise fail(f"--duration must be a number of seconds above the two {REST_S:g} s rests, got {duration}")
    if not (math.isfinite(target) and target > 0.0):
        raise fail(f"--target must be a positive σ ratio, got {target}")
    if not (math.isfinite(t_hi) and MIN_TENSION_N < t_hi <= 10 * params.limits.f_max):
        raise fail(f"--t-max must be above the {MIN_TENSION_N:g} N slack threshold and at most 10·f_max = "
                   f"{10 * params.limits.f_max:g} N, got {t_hi}")
    loaded = []  # before the bound, which takes seconds: an unreadable file is refused at once
    for path in trajectories or []:
        try:
            traj = load_trajectory(path)
        except TrajectoryError as exc:
            raise fail(str(exc)) from None
        if traj.n_joints != params.n_joints:
            raise fail(f"{path}: {traj.n_joints} joints, the robot has {params.n_joints}")
        loaded.append((path, traj))
    try:
        problem = _problem(params, duration, 0.6)
    except DesignError as exc:
        raise fail(str(exc)) from None
    paper = identification_trajectory()
    base = score(problem, paper.waypoints_rad, paper.durations_s, paper.dwell_s)
    moving = (duration - 2 * REST_S) / duration
    try:
        b = sigma_bound(problem.k, problem.lam, t_min_N=MIN_TENSION_N, t_max_N=t_hi, moving_fraction=moving)
    except ValueError as exc:
        raise fail(str(exc)) from None
    # Score.relative_sigma is per √s of record: σ over a record of D seconds is s/√D.
    scale = math.sqrt(base.duration_s / duration)
    nc = len(problem.k)
    rows: dict[str, dict[str, object]] = {}
    for name, s_b, design in ([(f"k({j + 1})", b.k[j], b.k_designs[j]) for j in range(nc)]
                              + [(f"lambda({j + 1})", b.lam[j], b.lam_designs[j]) for j in range(nc)]):
        ratio = s_b / base.relative_sigma[name] * scale
        # σ_bound(D) = √(variance/(D − 2·rest)): the record where the ratio falls to the target
        shortest = 2 * REST_S + design.variance * base.duration_s / (target * base.relative_sigma[name]) ** 2
        rows[name] = {"cycloids_relative_sigma_per_sqrt_s": base.relative_sigma[name],
                      "bound_relative_sigma_per_sqrt_s": float(s_b), "bound_ratio": float(ratio),
                      "reachable": bool(ratio <= target), "support_tensions_N": list(design.tensions_N),
                      "support_weights": list(design.weights), "shortest_duration_s": float(shortest)}
    scored: dict[str, dict[str, float]] = {}
    for path, traj in loaded:
        s = score(problem, traj.waypoints_rad, traj.durations_s, traj.dwell_s,
                  traj.pretension_N if traj.has_pretension else None)
        scored[str(path)] = {n: s.relative_sigma[n] / base.relative_sigma[n] * math.sqrt(base.duration_s / s.duration_s)
                             for n in rows}
    report = {"duration_s": duration, "cycloids_duration_s": base.duration_s, "target_ratio": target,
              "t_min_N": MIN_TENSION_N, "t_max_N": t_hi, "moving_fraction": moving,
              "reachable_all": all(r["reachable"] for r in rows.values()), "parameters": rows,
              "trajectories_predicted_ratio": scored}
    if as_json:
        echo_json(report)
        return
    typer.echo(f"least σ any {duration:g} s excitation could give, against the §5.2.2 cycloids ({base.duration_s:.1f} s), "
               f"design model: tensions anywhere in [{MIN_TENSION_N:g}, {t_hi:g}] N, every motor turning but the rests")
    typer.echo(f"{'':12s}{'bound ratio':>12s}{'reachable':>11s}{'support (N)':>16s}{'target needs':>15s}"
               + "".join(f"{Path(p).name[:14]:>16s}" for p in scored))
    for name, r in rows.items():
        t1, t2 = r["support_tensions_N"]  # type: ignore[misc]
        typer.echo(f"{name:12s}{r['bound_ratio']:12.3f}{('yes' if r['reachable'] else 'NO'):>11s}"
                   f"{f'{t1:.0f} / {t2:.0f}':>16s}{r['shortest_duration_s']:>13.0f} s"
                   + "".join(f"{v[name]:16.3f}" for v in scored.values()))
    verdict = "reachable on the design model" if report["reachable_all"] else "NOT reachable by any excitation"
    typer.echo(f"target σ ratio {target:g} for every k and λ at {duration:g} s: {verdict}")
