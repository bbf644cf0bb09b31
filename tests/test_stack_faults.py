"""Issue 13, the console side, on the real processes and bus: honest outcomes of real-time
campaigns (finding 7), judged from deadlines, so this module runs alone. What times nothing (the
e-stop truth, a failed analysis, the thresholds) is tests/test_console_outcomes.py's; ``xneck up``'s
refusals (finding 5) are tests/test_up_refusals.py's."""

from __future__ import annotations

import contextlib
import json
import signal
import time
from pathlib import Path

import httpx
import pytest
from server_harness import AUTH, wait_until
from test_stack import _alive_kinds, _healthy, _procs

from bridge import bus
from bridge.archive_read import read_campaign
from bridge.session import free_tcp_port

pytestmark = pytest.mark.realtime  # stalls and campaign quality judged from deadlines


# -- a robot-mode stack: console, twin bridge and controller service (also tests/test_console_outcomes.py)

CONTROL = {"kind": "control", "law": 2, "trajectory": "control_test"}
# Slow and short: a stall of the controller is a large part of it, and no joint goes far.
GENTLE = {"kind": "control", "law": 2, "waypoints": {"name": "gentle", "waypoints_deg": [[0, 0, 0], [8, 6, 4], [0, 0, 0]],
                                                     "durations_s": 2.0, "dwell_s": 0.3}}


@contextlib.contextmanager
def _robot_stack(tmp_path: Path):
    """Console (robot mode), twin bridge and controller service as separate processes on one hub;
    yields (base URL, hub endpoint, {name: process})."""
    port, hub_port = free_tcp_port(), free_tcp_port()
    hub = f"tcp/127.0.0.1:{hub_port}"
    base = f"http://127.0.0.1:{port}"
    with _procs() as spawn:
        procs = {"server": spawn(["server", "--port", str(port), "--data-dir", str(tmp_path / "d"), "--hub", hub,
                                  "--mode", "robot"], tmp_path / "s.log")}
        assert wait_until(lambda: _healthy(base), 60, 0.3), (tmp_path / "s.log").read_text()[-2000:]
        procs["bridge"] = spawn(["bridge", "--driver", "twin", "--listen", "tcp/127.0.0.1:0", "--connect", hub],
                                tmp_path / "b.log", place=True)
        procs["controller"] = spawn(["controller", "--law", "2", "--listen", "tcp/127.0.0.1:0", "--connect", hub],
                                    tmp_path / "c.log", place=True)
        assert wait_until(lambda: {"bridge", "campaign-service"} <= _alive_kinds(base), 120, 0.3)
        yield base, hub, procs


def _estop(base: str) -> dict:
    return httpx.get(base + "/api/system/health", timeout=2).json()["estop"]


def _wait_end(base: str, cid: str, timeout_s: float) -> dict:
    rec: dict = {}

    def ended() -> bool:
        nonlocal rec
        try:  # a loaded machine may keep the console busy (an analysis) past one read's timeout
            rec = httpx.get(f"{base}/api/campaigns/{cid}", timeout=10).json()
        except httpx.TimeoutException:
            return False
        return rec.get("status") != "running"

    assert wait_until(ended, timeout_s, 0.3), rec
    return rec


# -- finding 7: honest outcomes -------------------------------------------------------------------

@pytest.fixture(scope="module")
def robot_stack(tmp_path_factory: pytest.TempPathFactory):
    """One robot-mode stack for the two campaigns below: each starts its own campaign and judges
    only that campaign's record, results and archive (by its id; the controller's timing by its
    campaign id), so they share the stack's start-up and shutdown. The healthy campaign runs first,
    on the fresh stack; the stall (SIGSTOP, then SIGCONT a second later) comes after it. Yields
    (base URL, {name: process}, data directory)."""
    tmp = tmp_path_factory.mktemp("stack-faults")
    with _robot_stack(tmp) as (base, _hub, procs):
        yield base, procs, tmp / "d"


def test_a_healthy_real_time_campaign_finishes_with_its_quality_on_record(robot_stack) -> None:
    base, _, data = robot_stack
    cid = httpx.post(base + "/api/campaigns", json=GENTLE, headers=AUTH, timeout=90).json()["id"]
    rec = _wait_end(base, cid, 60)
    # A loaded test machine may miss deadlines: then it is degraded, and must say why.
    assert rec["status"] in ("finished", "degraded"), rec
    q = rec["quality"]
    assert q["realtime"] and q["ticks"] > 1000 and q["thresholds"]["rate_min_fraction"] == 0.95
    assert (rec["status"] == "degraded") == bool(q["reasons"])
    # Issue 21: the controller's own latency of this campaign on record, its histograms in the MCAP.
    assert 0 < q["latency_p50_ms"] <= q["latency_p99_ms"] and q["skipped_states"] >= 0, q
    timing = [m for _, m in read_campaign(data / "campaigns" / f"{cid}.mcap").messages(bus.CONTROLLER_TIMING)
              if m.campaign_id == cid]
    assert timing and timing[-1].campaign_ticks == q["controller_ticks"], (timing[-1:], q)
    assert sum(timing[-1].campaign_latency_counts) >= 0.9 * q["controller_ticks"]
    assert len(timing[-1].campaign_period_counts) == len(timing[-1].bin_edges_ms) - 1


def test_a_campaign_whose_controller_stalls_ends_degraded_with_its_reasons(robot_stack) -> None:
    """Finding 7: a real-time run that fell well below 500 Hz was recorded ``finished``."""
    base, procs, data = robot_stack
    r = httpx.post(base + "/api/campaigns", json=GENTLE, headers=AUTH, timeout=90)
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    assert wait_until(lambda: httpx.get(f"{base}/api/campaigns/{cid}").json().get("progress", 0) > 0.1, 60, 0.05)
    procs["controller"].send_signal(signal.SIGSTOP)  # a stalled real-time process (the bridge holds)
    time.sleep(1.0)
    procs["controller"].send_signal(signal.SIGCONT)
    rec = _wait_end(base, cid, 60)
    results = httpx.get(f"{base}/api/campaigns/{cid}/results", timeout=10).json()
    assert rec["status"] == "degraded", rec
    reasons = rec["quality"]["reasons"]
    assert any(r.startswith("rate ") for r in reasons), rec["quality"]
    assert rec["quality"]["rate_hz"] < 0.95 * 500
    assert results["status"] == "degraded" and results["quality"]["reasons"] == reasons
    shown = [t for t in results["tables"] if t["title"].startswith("Real-time quality")]  # the dashboard's table
    assert shown and shown[0]["note"] == "degraded: " + "; ".join(reasons)
    info = read_campaign(data / "campaigns" / f"{cid}.mcap").info
    assert info["outcome"] == "degraded" and info["degraded_reasons"] == "; ".join(reasons)
    assert json.loads(info["quality"])["reasons"] == reasons
