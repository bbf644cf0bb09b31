"""A real-time identification campaign on the twin measures α_IP with a separate camera process
(issue 15): the real processes on a real bus, paced by the clock, so this module runs alone
(tests/conftest.py, ``_cpu_turn``): the renderer drops the frames it cannot keep up with."""

from __future__ import annotations

import pytest

from bridge import bus
from bridge.archive_read import read_campaign
from controller.laws import LawConfig
from controller.trajectory import load_trajectory

pytestmark = pytest.mark.realtime  # a real-time campaign: a loaded machine drops frames
NOD = {"name": "nod", "waypoints_deg": [[0, 0, 0], [5, 5, 5], [0, 0, 0]], "durations_s": 1.0, "dwell_s": 0.2}


@pytest.mark.e2e
def test_a_real_time_identification_campaign_measures_alpha_ip_with_a_camera_process(params, tmp_path) -> None:
    """A real-time twin cannot wait for the renderer: the runner starts it without its white-noise
    camera and a separate `xneck camera --source twin` beside it, which renders the truth as it
    comes (frames the renderer cannot keep up with are dropped and counted, never invented)."""
    from server.campaign_runner import CampaignSpec, run_campaign

    result = run_campaign(CampaignSpec("identification", LawConfig(law=1), load_trajectory(NOD), seed=1,
                                       timeout_s=180, realtime=True), params, tmp_path / "rt.mcap")
    assert result.outcome == "analysis_failed", (result.outcome, result.message)  # a nod identifies nothing
    campaign = read_campaign(result.path)
    frames = [m for _, m in campaign.messages(bus.CAMERA_ALPHA)]
    assert campaign.info["alpha_ip"] == "camera" and {m.source for m in frames} == {"twin-render"}
    assert len(frames) > 30 and all(m.stamp_s - m.capture_stamp_s >= params.sensors.camera_latency - 1e-6 for m in frames)
