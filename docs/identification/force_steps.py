"""Force steps in campaign archives: how many ticks change a motor's applied force by more than
``--over`` N, and the largest step (N per tick), per archive (docs/identification-coverage.md, "On
law 1's campaigns"). A bumpless control path keeps them few; law 1's slack cables do not.

    .venv/bin/python docs/identification/force_steps.py docs/identification/runs/paper-0.mcap [--over 20]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from twin.identification.record import campaign_data_from_mcap


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("archives", nargs="+", type=Path)
    ap.add_argument("--over", type=float, default=20.0, help="step (N per tick) counted")
    args = ap.parse_args()
    print(f"| archive | ticks with a step > {args.over:g} N | largest step (N) | ticks |")
    print("|---|---|---|---|")
    for path in args.archives:
        f = campaign_data_from_mcap(path).force_N
        step = np.abs(np.diff(f, axis=0)).max(axis=1)
        print(f"| {path} | {int((step > args.over).sum())} | {step.max():.1f} | {len(f)} |")


if __name__ == "__main__":
    main()
