"""The dashboard in a real browser (playwright driving Debian's chromium): load it, start a
campaign from the form, see the live plots update and the viser canvas render; save a screenshot
under artifacts/."""

from __future__ import annotations

from pathlib import Path

import httpx
from browser_harness import ARTIFACTS, dashboard_page, needs_chromium
from server_harness import TOKEN, running_server, wait_until


@needs_chromium
def test_dashboard_starts_a_campaign_and_shows_it_live(tmp_path: Path) -> None:
    with running_server(tmp_path / "data") as (base, app), dashboard_page(base) as (page, errors):
        page.wait_for_function("document.querySelectorAll('#plot-joints .uplot').length === 3", timeout=15000)
        page.fill("#token", TOKEN)
        page.dispatch_event("#token", "change")
        page.select_option("select[name=pace]", "lockstep")
        page.click("#start")
        page.wait_for_function("window.xneckStats.points > 100", timeout=60000)
        points = page.evaluate("window.xneckStats.points")
        page.wait_for_function(f"window.xneckStats.points > {points + 50}", timeout=30000)

        # The viser view renders a WebGL canvas inside its iframe.
        frame = page.frame_locator("#viser")
        frame.locator("canvas").first.wait_for(state="attached", timeout=30000)
        assert wait_until(lambda: len(app.state.scene.server.get_clients()) >= 1, 20)
        assert app.state.scene.updates > 10

        # The campaign ends; the list shows it with its results table.
        with httpx.Client(base_url=base, timeout=10) as c:
            assert wait_until(lambda: c.get("/api/system/health").json()["running_campaign_id"] is None, 90, 0.5)
            rec = c.get("/api/campaigns").json()[0]
        assert rec["status"] == "finished", rec
        page.wait_for_selector("#results h3", timeout=20000)
        page.wait_for_timeout(1500)  # let the figures and the 3D view settle for the picture
        page.screenshot(path=str(ARTIFACTS / "dashboard.png"), full_page=True)
        assert "Table 3" in page.inner_text("#results")
        assert not errors, errors
