"""The Foxglove scene the console adds to a finished archive (server/foxglove_scene.py): its cables
coloured by the tension of the last truth before each drawn pose, which is decoded only when a
pose is drawn (decoding every truth at 500 Hz took 11 s of a 600 s campaign's analysis; audit of
2026-11-30)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bridge import bus
from bridge.archive import write_campaign
from bridge.archive_read import read_campaign
from server.foxglove_scene import SCENE_TOPIC, add_scene_channel, tension_colors
from twin.model.params import load_params


def _truth(seq: int, tension: float) -> bus.Truth:
    return bus.Truth(seq=seq, stamp_s=seq * 0.002, alpha_rad=[0.1] * 3, alpha_dot_rad_s=[0.0] * 3, theta_rad=[0.0] * 4,
                     theta_dot_rad_s=[0.0] * 4, tension_N=[tension] * 4, elongation_m=[0.0] * 4, slack=[False] * 4,
                     near_singular=False)


def _status(seq: int) -> bus.ControllerStatus:
    return bus.ControllerStatus(seq=seq, stamp_s=seq * 0.002, law="law2", tick_s=0.002, compute_s=1e-4, overruns=0,
                                deadline_misses=0, saturated=[False] * 4, alpha_hat_rad=[0.1] * 3,
                                alpha_d_rad=[0.1] * 3, e_rad=[0.0] * 3, holding=False)


def test_each_scene_colours_the_cables_by_the_last_truth_before_it(tmp_path: Path) -> None:
    params = load_params()
    f_max = float(params.limits.f_max)
    t0, msgs = 10**18, []
    tension = lambda i: f_max * ((i // 10) % 2)  # noqa: E731 - 0 N, then f_max, every 10 ticks
    for i in range(100):
        msgs.append((bus.TWIN_TRUTH, t0 + i * 2_000_000, _truth(i, tension(i))))
        msgs.append((bus.CONTROLLER_STATUS, t0 + i * 2_000_000 + 1000, _status(i)))
    path = write_campaign(tmp_path / "c.mcap", msgs, {"campaign_id": "scene"})
    assert add_scene_channel(path, params, rate_hz=50.0) == 10  # one pose per 20 ms of log time
    scenes = read_campaign(path, keys=(SCENE_TOPIC,)).messages(SCENE_TOPIC)
    for k, (_, update) in enumerate(scenes):
        cables = update["entities"][0]["lines"][3:7]
        expected = tension_colors(np.full(4, tension(10 * k)), f_max)
        assert [c["color"]["r"] for c in cables] == [float(rgb[0]) / 255.0 for rgb in expected], k
    assert len({str(u["entities"][0]["lines"][3]["color"]) for _, u in scenes}) == 2  # both tensions drawn
