"""Camera moved after its calibration: how far the base plate's reference markers move, and what
α_IP it costs (docs/camera.md, "Camera moved"; the threshold ``twin.camera.detect.MOVED_PX``).

Frames rendered by the twin's camera at its calibrated pose (several noise and blur levels, a
tracked 30 fps path, so that the windowed search is measured too) and at poses turned or shifted
from it, measured with the calibration of the unmoved camera and the check disabled: per case the
largest shift of a reference marker from where the calibration projects it (max over the four,
then median and max over the frames), and |α_IP − α| (mean, max).
Run: ``.venv/bin/python benchmarks/camera_moved.py [--quick]``.
"""

from __future__ import annotations

import math
import sys

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import numpy as np

from twin.camera.calibration import look_at_pose, twin_calibration
from twin.camera.detect import Detector, DetectorConfig
from twin.camera.render import Renderer, RenderOptions
from twin.model.numeric import build
from twin.model.params import load_params

NOMINAL = dict(tilt_deg=4.0, pan_deg=-3.0, roll_deg=0.5)  # twin_calibration()'s pose
LEVELS = [(2.0, 0.8), (4.0, 0.8), (2.0, 1.6), (6.0, 1.6)]  # (noise σ grey levels, blur σ px), as benchmarks/camera.py
MOVES = [("panned 0.25°", dict(pan_deg=-3.25)), ("panned 0.5°", dict(pan_deg=-3.5)), ("panned 1°", dict(pan_deg=-4.0)),
         ("panned 2°", dict(pan_deg=-5.0)), ("panned 3°", dict(pan_deg=-6.0)), ("panned 5°", dict(pan_deg=-8.0)),
         ("tilted 1°", dict(tilt_deg=5.0)), ("tilted 3°", dict(tilt_deg=7.0)), ("rolled 1°", dict(roll_deg=1.5))]


def measure(model, params, cal_drawn, configs, options: RenderOptions, seed: int, tracked: bool) -> dict[str, float]:
    cal = twin_calibration()
    renderer = Renderer(model, cal_drawn, options=options, seed=seed)
    det = Detector(params.n_joints, params.geometry.L, params.geometry.b, cal, config=DetectorConfig(moved_px=math.inf))
    shifts, errs, missing = [], [], 0
    for alpha in configs:
        if not tracked:
            det.reset()
        found = det.detect(renderer.render(alpha))
        if found.reference_shift_px is not None:
            shifts.append(found.reference_shift_px)
        for a, truth in zip(found.alpha_rad, alpha):
            if a is None:
                missing += 1
            else:
                errs.append(abs(math.degrees(a - truth)))
    s, e = np.array(shifts), np.array(errs)
    return {"frames": len(configs), "checked": len(s), "shift_median": float(np.median(s)) if len(s) else math.nan,
            "shift_max": float(s.max()) if len(s) else math.nan, "err_mean": float(e.mean()), "err_max": float(e.max()),
            "missing": missing, "windowed": det.windowed_frames}


def main() -> None:
    quick = "--quick" in sys.argv
    params = load_params()
    model = build(params)
    lim = math.radians(params.limits.alpha_max_deg)
    n = 20 if quick else 100
    rng = np.random.default_rng(0)
    configs = rng.uniform(-lim, lim, size=(n, params.n_joints))
    path = np.radians(np.linspace([0.0, 0.0, 0.0], [40.0, -50.0, 55.0], 60 if quick else 300))  # 30 fps, tracked
    cal = twin_calibration()
    rows = []
    for noise, blur in LEVELS:
        options = RenderOptions(noise_dn=noise, blur_px=blur)
        rows.append((f"unmoved, noise {noise:g}, blur {blur:g}", measure(model, params, cal, configs, options, 1, False)))
    rows.append(("unmoved, tracked path", measure(model, params, cal, path, RenderOptions(), 2, True)))
    for label, change in MOVES:
        rvec, tvec = look_at_pose((0.0, 0.115), 0.52, **{**NOMINAL, **change})
        rows.append((label, measure(model, params, cal.with_pose(rvec, tvec), configs[:20], RenderOptions(), 1, False)))
    print("| camera | frames (checked, windowed) | reference shift median | max | α error mean | max | missing |")
    print("|---|---|---|---|---|---|---|")
    for label, r in rows:
        print(f"| {label} | {r['frames']} ({r['checked']}, {r['windowed']}) | {r['shift_median']:.2f} px | "
              f"{r['shift_max']:.2f} px | {r['err_mean']:.3f}° | {r['err_max']:.3f}° | {r['missing']} |")


if __name__ == "__main__":
    main()
