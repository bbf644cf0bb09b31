"""What the values a calibration does not fit cost a replay (docs/twin-fidelity.md, Calibration,
"Demonstration"): prediction errors of truths that are right in some values and wrong in others.

    .venv/bin/xneck campaign control --twin --truth docs/twin-fidelity-hidden.toml --law N --seed 11 --out lawN.mcap   # N = 1, 2, 3
    .venv/bin/python docs/twin_fidelity/unfitted_values.py law2.mcap law1.mcap law3.mcap

For each recording, the replay of `xneck twin calibrate` (twin.sim.calibrate.prediction_errors: RMS
of replay − recording over one 0.25 s horizon, θ every 10th tick, α_IP at each camera frame; the
twin's Truth topic not read) with

- ``hidden``: the truth that made the recording (``--hidden``, default docs/twin-fidelity-hidden.toml):
  what the forces and sensors leave whatever the values;
- ``base + answer``: the base truth (``--base``, default the robot truth) with the hidden truth's
  values of the calibration's default fitted set (twin.sim.calibrate.DEFAULT_FIT): the best a
  calibration of those values could find if it found them exactly;
- ``hidden, base's <group>``: the hidden truth with one group of the values the calibration does not
  fit put back to the base truth's (only groups in which the two truths differ);
- ``base``: the base truth, where the calibration starts.

Nothing is fitted; a few seconds for the three 14 s §7 recordings.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from twin.model.params import load_params
from twin.sim import calibrate as cal
from twin.sim.truth import RobotTruth, TruthError, load_truth

# The values `xneck twin calibrate` does not fit by default, in groups (section, key).
GROUPS: dict[str, list[tuple[str, str]]] = {
    "friction shape (Stribeck velocity, asymmetry)": [("friction", "stribeck_velocity_rad_s"), ("friction", "asymmetry")],
    "creep (ratio, time)": [("cables", "creep_ratio"), ("cables", "creep_time_s")],
    "cogging": [("actuation", "cogging_N")],
    "structure (masses, springs, free lengths)": [
        ("structure", k) for k in ("mass_factor", "spring_factor_left", "spring_factor_right", "l0_offset_m")],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("recordings", nargs="+", type=Path, help="Campaign MCAP files made with --hidden.")
    parser.add_argument("--hidden", default="docs/twin-fidelity-hidden.toml", help="Truth that made the recordings.")
    parser.add_argument("--base", default="robot", help="Truth the calibration starts from.")
    args = parser.parse_args()
    params = load_params()
    hidden, base = load_truth(args.hidden), load_truth(args.base)
    fitted = cal.unknowns(cal.DEFAULT_FIT, params.n_cables)
    answer = cal.with_values(base, fitted, [cal.current_value(hidden, u, params.n_cables) for u in fitted],
                             params.n_cables)
    truths: list[tuple[str, RobotTruth]] = [("hidden", hidden), ("base + answer", answer)]
    for group, keys in GROUPS.items():
        if all(getattr(getattr(hidden, s), k) == getattr(getattr(base, s), k) for s, k in keys):
            continue
        t = hidden
        for s, k in keys:
            t = t.replace(s, **{k: getattr(getattr(base, s), k)})
        truths.append((f"hidden, base's {group}", t))
    truths.append(("base", base))
    print(f"hidden: {args.hidden}; base: {args.base}; RMS of replay − recording over 0.25 s (θ in rad, α_IP in °)")
    print(f"{'recording':12s} {'truth replayed':58s} {'θ':>8s} {'α_IP':>8s}")
    for path in args.recordings:
        rec = cal.load_recording(path, params)
        for label, truth in truths:
            errors = cal.prediction_errors(rec, params, truth)
            if "replay_failed" in errors:
                print(f"{rec.name:12s} {label:58s} the replay left the model's domain")
                continue
            print(f"{rec.name:12s} {label:58s} {errors['theta_rad']:8.3f} {errors['alpha_ip_deg']:8.3f}")


if __name__ == "__main__":
    try:
        main()
    except (cal.CalibrationError, TruthError) as exc:
        raise SystemExit(f"error: {exc}") from None
