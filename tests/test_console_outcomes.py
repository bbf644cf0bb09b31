"""Issue 13, the console side, on the real processes and bus, for what times nothing: one e-stop
truth in the console and the dashboard (finding 4), an identification whose analysis failed is
not finished and the quality thresholds name each breach (finding 7). The stalls and the quality of
real-time campaigns, judged from deadlines, are tests/test_stack_faults.py's (realtime)."""

from __future__ import annotations

import os
from pathlib import Path

import httpx
import pytest
from server_harness import AUTH, running_server, wait_until
from test_stack_faults import CONTROL, _estop, _robot_stack, _wait_end

from bridge import bus
from bridge.archive_read import read_campaign
from bridge.session import open_session
from server.quality import THRESHOLDS, assess

pytestmark = pytest.mark.e2e


# -- finding 4: one e-stop truth ------------------------------------------------------------------

def test_the_console_shows_the_bridges_estop_and_campaigns_follow_it(tmp_path: Path) -> None:
    """Finding 4: garbage on xneck/estop disabled the drives (fail safe) while the console still
    showed the e-stop off; a campaign then ran against disabled drives and was recorded finished."""
    with _robot_stack(tmp_path) as (base, hub, _), open_session(listen=["tcp/127.0.0.1:0"], connect=[hub]) as s:
        assert wait_until(lambda: _estop(base).get("source") == "bridge", 30, 0.2), _estop(base)
        assert _estop(base)["engaged"] is False
        s.put(bus.ESTOP, b"\x00 not an e-stop")  # not the console: someone else on the bus
        assert wait_until(lambda: _estop(base)["engaged"], 10, 0.1), _estop(base)
        shown = _estop(base)
        assert shown["source"] == "bridge" and shown["reason"], shown

        r = httpx.post(base + "/api/campaigns", json=CONTROL, headers=AUTH, timeout=90)
        assert r.status_code == 409, r.text
        assert shown["reason"] in r.json()["detail"]

        assert httpx.post(base + "/api/system/estop", json={"engaged": False, "reason": "test"}, headers=AUTH,
                          timeout=5).status_code == 200
        assert wait_until(lambda: not _estop(base)["engaged"], 10, 0.1), _estop(base)
        r = httpx.post(base + "/api/campaigns", json=CONTROL, headers=AUTH, timeout=90)
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        assert wait_until(lambda: httpx.get(f"{base}/api/campaigns/{cid}").json().get("progress", 0) > 0.15, 60, 0.2)
        s.put(bus.ESTOP, b"{\"v\": 1}")  # malformed again, mid-campaign
        rec = _wait_end(base, cid, 30)
    # Aborted with the bridge's reason, whoever noticed first (the runner following the states, or
    # the controller seeing its drives disabled).
    assert rec["status"] == "aborted", rec
    assert "disabled" in rec["message"] and "malformed e-stop" in rec["message"], rec
    info = read_campaign(tmp_path / "d" / "campaigns" / f"{cid}.mcap").info
    assert info["outcome"] == "aborted" and info["message"] == rec["message"]


def test_the_dashboard_shows_the_bridges_estop_and_its_reason(tmp_path: Path) -> None:
    """Finding 4, the dashboard: the e-stop banner comes from the bridge's MotorState, so an e-stop
    engaged by someone else on the bus (here a malformed message) shows, with its reason."""
    sync_api = pytest.importorskip("playwright.sync_api")
    if not os.path.exists("/usr/bin/chromium"):
        pytest.skip("Debian chromium not installed (bash .ci/setup)")
    with _robot_stack(tmp_path) as (base, hub, _), open_session(listen=["tcp/127.0.0.1:0"], connect=[hub]) as s, \
            sync_api.sync_playwright() as pw:
        assert wait_until(lambda: _estop(base).get("source") == "bridge", 30, 0.2), _estop(base)
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox", "--disable-gpu"],
                                     headless=True)
        try:
            page = browser.new_page(bypass_csp=True)  # server.guard.CSP forbids eval (tests/browser_harness.py)
            page.goto(base + "/", wait_until="load")
            page.wait_for_function("document.querySelector('#sys').textContent.startsWith('mode')", timeout=20000)
            page.wait_for_function("document.querySelector('#sys').textContent.includes('bridge: state')", timeout=20000)
            assert page.is_hidden("#estop-state")
            s.put(bus.ESTOP, b"not json")
            page.wait_for_selector("#estop-state:not([hidden])", timeout=20000)
            banner = page.text_content("#estop-state")
        finally:
            browser.close()
    assert banner.startswith("E-STOP ENGAGED: malformed e-stop message"), banner


# -- finding 7: honest outcomes -------------------------------------------------------------------

def test_a_failed_identification_analysis_is_analysis_failed_not_finished(tmp_path: Path) -> None:
    """Finding 7: an identification whose analysis failed was ``finished``. A 2.6 s nod is no
    identification excitation: the run records fine, its analysis cannot succeed."""
    nod = {"kind": "identification", "waypoints": {"name": "nod", "waypoints_deg": [[0, 0, 0], [5, 5, 5], [0, 0, 0]],
                                                   "durations_s": 1.0, "dwell_s": 0.2}}
    with running_server(tmp_path / "d") as (base, _app):
        r = httpx.post(base + "/api/campaigns", json=nod, headers=AUTH, timeout=90)
        assert r.status_code == 201, r.text
        rec = _wait_end(base, r.json()["id"], 180)
    assert rec["status"] == "analysis_failed", rec
    assert rec["identification_status"].startswith("identification failed") and rec["identification"] is None
    assert rec["identification_status"] in rec["message"]


# -- the thresholds, defined once (server.quality) ------------------------------------------------

def test_quality_thresholds_name_each_breach() -> None:
    ok = {"ticks": 5000, "states": 5000, "rate_hz": 499.0, "deadline_misses": 10, "record_gaps": 0, "messages_lost": 0}
    assert assess(ok, realtime=True) == []
    slow = assess({**ok, "rate_hz": 178.0}, realtime=True)
    assert len(slow) == 1 and slow[0].startswith("rate 178 Hz below 95 %")
    assert assess({**ok, "rate_hz": 178.0}, realtime=False) == []  # lockstep has no wall-clock rate
    late = assess({**ok, "deadline_misses": 51}, realtime=True)
    assert len(late) == 1 and late[0].startswith("deadline misses: 51 in 5000 ticks")
    gaps = assess({**ok, "record_gaps": 37, "messages_lost": 40}, realtime=False)
    assert len(gaps) == 1 and "40 of 10040 messages lost in 37 gap(s)" in gaps[0]
    assert THRESHOLDS.rate_min_fraction == 0.95 and THRESHOLDS.nominal_rate_hz == 500.0
