"""How well a truth predicts a recording, replayed open loop and re-started every ``--horizon``
(docs/twin-fidelity.md, "Why the replay re-starts every 0.25 s (`--horizon`)").

    .venv/bin/xneck campaign control --twin --truth docs/twin-fidelity-hidden.toml --law 2 --seed 11 --out law2.mcap
    .venv/bin/python docs/twin_fidelity/replay_horizon.py law2.mcap --truth docs/twin-fidelity-hidden.toml

What runs: the replay `xneck twin calibrate` fits with (twin.sim.calibrate.replay: the twin of
``--truth`` held at the recording's applied forces, in process) and its prediction errors
(twin.sim.calibrate.prediction_errors: RMS of replay − recording, θ every 10th tick, α_IP at each
camera frame; with ``--use-twin-truth``, tensions from the twin's Truth topic, and the replay starts at
its true α, as ``xneck twin calibrate --use-twin-truth`` does), for each horizon: the
calibration's default 0.25 s and ``inf``, one open-loop replay from the recording's start. Nothing is
fitted. With the truth that made the recording, what is left is what the forces alone do not
determine (stiction) and the sensors' noise. About 2.5 s for the 14 s law 2 recording on the 2-CPU
machine (0.2 s a replay; numba's cache warm), 2026-11-26.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from twin.model.params import load_params
from twin.sim import calibrate as cal
from twin.sim.truth import TruthError, load_truth


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("recordings", nargs="+", type=Path, help="Campaign MCAP files (e.g. law2.mcap).")
    parser.add_argument("--truth", default="robot",
                        help="Truth replayed: robot, model or a truth FILE (the one that made the recording).")
    parser.add_argument("--use-twin-truth", action="store_true",
                        help="Also compare the tensions of the twin's Truth topic and start at its true α "
                             "(twin recordings only; off by default, as in xneck twin calibrate).")
    parser.add_argument("--horizon", type=float, action="append",
                        help="Re-start the motors from the encoders this often (s; inf: never). Repeatable; "
                             "default: 0.25 and inf.")
    args = parser.parse_args()
    horizons = args.horizon or [0.25, math.inf]
    params = load_params()
    truth = load_truth(args.truth)
    print(f"truth: {args.truth}; RMS of replay − recording (θ in rad, α_IP in °, tension in N)")
    print(f"{'recording':24s} {'horizon (s)':>11s} {'θ':>9s} {'α_IP':>9s} {'tension':>9s} {'wall (s)':>9s}")
    for path in args.recordings:
        rec = cal.load_recording(path, params, use_twin_truth=args.use_twin_truth)
        for h in horizons:
            start = time.perf_counter()
            errors = cal.prediction_errors(rec, params, truth, cal.Weights(horizon_s=h))
            wall = time.perf_counter() - start
            if "replay_failed" in errors:
                print(f"{rec.name:24s} {h:11g} the replay left the model's domain (flat joint or non-finite state)")
                continue
            cells = "".join(f"{errors[k]:9.3f} " if k in errors else f"{'–':>9s} "
                            for k in ("theta_rad", "alpha_ip_deg", "tension_N"))
            print(f"{rec.name:24s} {h:11g} {cells}{wall:9.1f}")


if __name__ == "__main__":
    try:
        main()
    except (cal.CalibrationError, TruthError) as exc:  # a bad recording or truth: one line, no traceback
        raise SystemExit(f"error: {exc}") from None
