"""Which input biases loadfriction on a twin campaign: the archive's fit as recorded, then with the
twin's truth (its ``xneck/twin/truth`` channel) swapped in for one input at a time: the true α at
the frames' capture times in place of α_IP (the camera), and the true cable tension in place of the
motors' forces (the friction model). Prints k and λ errors against Table 2 (docs/identification-
coverage.md, "What biases λ(3) on law 1's campaigns").

    .venv/bin/python docs/identification/truth_swaps.py docs/identification/runs/paper-0.mcap [...]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bridge import bus
from bridge.archive_read import read_campaign
from twin.identification import loadfriction
from twin.identification.processing import preprocess
from twin.identification.record import campaign_data_from_mcap
from twin.model.params import load_params


def _errors(proc, params, y=None) -> str:
    """k and λ errors (%) of loadfriction on ``proc``; ``y``: the fitted force replaced."""
    fit_rows = loadfriction.fit_rows
    if y is not None:
        rows = fit_rows(proc, params)[1]
        loadfriction.fit_rows = lambda _p, _q: (y, rows)
    try:
        est = loadfriction.fit_load_friction(proc, params).estimate
    finally:
        loadfriction.fit_rows = fit_rows
    k_true, lam_true = np.asarray(params.cables.variable.k), np.asarray(params.cables.variable.lam)
    fmt = lambda a: ", ".join(f"{100 * x:+.1f}" for x in a)  # noqa: E731
    return f"{fmt(est.vector('k') / k_true - 1)} | {fmt(est.vector('lambda') / lam_true - 1)}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("archives", nargs="+", type=Path, help="twin campaign archives with the truth channel")
    args = ap.parse_args()
    params = load_params()
    print("| archive | input | k error (%) | λ error (%) |")
    print("|---|---|---|---|")
    for path in args.archives:
        data = campaign_data_from_mcap(path)
        truth = [m for _, m in read_campaign(path).messages(bus.TWIN_TRUTH)]
        if not truth:
            sys.exit(f"{path}: no {bus.TWIN_TRUTH} channel (not a twin campaign)")
        stamp, order = np.unique([m.stamp_s for m in truth], return_index=True)
        alpha = np.array([m.alpha_rad for m in truth])[order]
        tension = np.array([m.tension_N for m in truth])[order]
        proc = preprocess(data, params)
        print(f"| {path.name} | as recorded | {_errors(proc, params)} |", flush=True)
        a_true = np.column_stack([np.interp(data.t_ip_s, stamp, alpha[:, i]) for i in range(alpha.shape[1])])
        proc_cam = preprocess(dataclasses.replace(data, alpha_ip_rad=a_true), params)
        print(f"| {path.name} | true α for α_IP | {_errors(proc_cam, params)} |", flush=True)
        t_full = np.column_stack([np.interp(data.t_s, stamp, tension[:, j]) for j in range(tension.shape[1])])
        proc_t = preprocess(dataclasses.replace(data, force_N=t_full), params)
        print(f"| {path.name} | true tension for the forces | {_errors(proc, params, proc_t.force)} |", flush=True)


if __name__ == "__main__":
    main()
