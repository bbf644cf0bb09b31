"""Which robot-truth effect biases Table 2's estimate? (issues 16/17)

Runs the identification closed loop (controller/identification_loop.py) (the §5.2.2 trajectory, 97 s) on the robot truth with
one effect or one friction term switched off at a time, identifies Table 2 with the chosen
estimator and prints, per variant, the mean k and λ errors over the campaign seeds and the mean
of (estimate − truth)/σ. ``--true-camera`` replaces α_IP by the twin's true α at each frame's
capture time: the camera's noise and lag are gone, so what remains is the estimator's model error
(the same on every seed, which is why three seeds are enough there).

    nice -n 19 .venv/bin/python docs/identification/ablate_robot_truth.py --true-camera --seeds 21,22,23

``--law1`` runs law 1's campaign instead (controller.identification_loop.law1_campaign: what
`xneck campaign identification` runs, α_IP from rendered frames; ``--true-camera`` does not apply).

Variants: ``robot`` (twin/sim/robot_truth.toml, every effect on); ``no-<section>`` (one of
twin.sim.truth.EFFECTS off); ``only:<section>+<section>…`` (those on, the others off);
``<section>:<field>=<value>`` (one field replaced, e.g. ``friction:asymmetry=0,0,0,0``).
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from controller.identification_loop import law1_campaign, simulate_campaign
from twin.identification.pipeline import VARIABLE_ESTIMATORS, identify_friction, identify_variable, preprocess
from twin.model.params import load_params
from twin.sim.truth import RobotTruth, load_truth

DEFAULT_VARIANTS = (
    "robot",
    "no-friction", "no-actuation", "no-structure", "no-cables", "no-timing",
    "friction:asymmetry=0,0,0,0",
    "friction:gear_loss_forward=0;gear_loss_backward=0",
    "friction:pulley_friction_per_N=0,0,0,0",
    "friction:static_ratio=1",
    "cables:creep_ratio=0",
)


def variant(name: str, robot: RobotTruth) -> RobotTruth:
    """The robot truth with ``name``'s change (module docstring)."""
    if name == "robot":
        return robot
    if name.startswith("no-"):
        return robot.only(*[e for e in robot.enabled() if e != name[3:]])
    if name.startswith("only:"):
        return robot.only(*name[5:].split("+"))
    section, _, assignments = name.partition(":")
    values: dict[str, float | tuple[float, ...]] = {}
    for item in assignments.split(";"):
        key, _, text = item.partition("=")
        values[key] = tuple(float(v) for v in text.split(",")) if "," in text else float(text)
    return robot.replace(section, **values)


def errors(truth: RobotTruth, seed: int, estimator: str, true_camera: bool, law1: bool = False) -> np.ndarray:
    """(2, 2, n_cables): [k, λ] × [relative error, (estimate − truth)/σ] of one campaign."""
    params = load_params()
    if law1:
        data, tru = law1_campaign(seed, truth, params), None
    else:
        data, tru = simulate_campaign(seed, truth=truth)
    if true_camera and tru is not None:
        at = np.clip(np.searchsorted(tru["t"], data.t_ip_s), 0, len(tru["t"]) - 1)
        data = dataclasses.replace(data, alpha_ip_rad=tru["alpha"][at])
    proc = preprocess(data, params)
    est = identify_variable(proc, params, identify_friction(proc, params).values, estimator=estimator)
    out = []
    for symbol, true in (("k", params.cables.variable.k), ("lambda", params.cables.variable.lam)):
        idx = [i for i, n in enumerate(est.names) if n.startswith(f"{symbol}(")]
        v, s, t = est.values[idx], est.sigma[idx], np.asarray(true)
        out.append([v / t - 1, (v - t) / s])
    return np.asarray(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--seeds", default="21,22,23", help="campaign seeds, comma-separated")
    ap.add_argument("--estimator", default="loadfriction", choices=VARIABLE_ESTIMATORS)
    ap.add_argument("--true-camera", action="store_true", help="α_IP = the true α at each capture time")
    ap.add_argument("--law1", action="store_true", help="law 1's campaign (as `xneck campaign identification`), "
                    "not the known-answer loop")
    ap.add_argument("variants", nargs="*", default=list(DEFAULT_VARIANTS))
    args = ap.parse_args()
    if args.law1 and args.true_camera:
        ap.error("--true-camera applies to the known-answer loop, not to --law1")
    seeds = [int(s) for s in args.seeds.split(",")]
    robot = load_truth("robot")
    camera = "true α at the capture times" if args.true_camera else "the twin's camera"
    loop = "law 1's campaign" if args.law1 else "the known-answer loop"
    print(f"estimator `{args.estimator}`, {loop}, camera: {camera}, seeds {args.seeds}; means over the seeds\n")
    print("| robot truth | k error (%) | λ error (%) | k: (est − truth)/σ | λ: (est − truth)/σ |")
    print("|---|---|---|---|---|")
    for name in args.variants:
        e = np.mean([errors(variant(name, robot), s, args.estimator, args.true_camera, args.law1) for s in seeds], axis=0)
        pct = lambda a: ", ".join(f"{100 * x:+.1f}" for x in a)  # noqa: E731
        z = lambda a: ", ".join(f"{x:+.1f}" for x in a)  # noqa: E731
        print(f"| `{name}` | {pct(e[0, 0])} | {pct(e[1, 0])} | {z(e[0, 1])} | {z(e[1, 1])} |", flush=True)


if __name__ == "__main__":
    main()
