"""The dashboard in a real browser (playwright driving Debian's chromium): load it, start a
campaign from the form, see the live plots update and the viser canvas render; save a screenshot
under artifacts/."""

from __future__ import annotations

from pathlib import Path
from typing import Any

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


#: a peer's camera name: markup that runs a script if written as HTML, and kilobytes
HOSTILE_CAMERA = '<img src=x onerror="window.pwned = 1">' + "x" * 4000


@needs_chromium
def test_hostile_bus_values_neither_freeze_the_live_view_nor_push_the_estop_out_of_sight(tmp_path: Path) -> None:
    """Anyone on the bus may publish: a peer posing as a bridge sends a MotorState with one force
    too many and reasons of several kB (the bridge's own are cut to 200 characters, a peer's are
    not), a Health with a huge last reject reason, and a camera naming itself with markup and
    kilobytes grades one joint of three and sends a JPEG whose header is right and whose picture is
    cut. The page must keep its live view
    (before: every frame threw in onFrame, no frame reached the safety code and it claimed LIVE
    STREAM LOST while frames came), its camera panel (before: "console unreachable", and the α_IP
    rows after the throw missing) and its e-stop button in sight and working on a laptop's screen
    (before: the header grew taller than the window and hid the button); the live panel names the
camera as text, cut. The states with a force
    too many and the camera grades of one joint alternate with good ones: the console now rejects
    them (server.live.receiver_checks) and the page shows the good ones."""
    import threading
    import time

    import cv2
    import numpy as np

    from bridge import bus
    from bridge.session import camera_attachment, liveliness_token, open_session, publisher

    with running_server(tmp_path / "data", viser=False) as (base, app_):
        app: Any = app_
        n_motors, n_joints = app.state.default_params.n_cables, app.state.default_params.n_joints
        session = open_session(connect=[app.state.hub])
        token = liveliness_token(session, "bridge", "posing")
        pubs = {key: publisher(session, key) for key in (bus.MOTOR_STATE, bus.CONTROLLER_STATUS, bus.CAMERA_ALPHA,
                                                          bus.CAMERA_FRAME)}
        jpeg = cv2.imencode(".jpg", np.full((48, 64, 3), 128, np.uint8))[1].tobytes()
        cut = jpeg[:len(jpeg) // 2]  # the header (and the size it declares) intact, the picture not
        health = session.declare_publisher(bus.health_key("bridge", "posing"))
        stop = threading.Event()

        def peer() -> None:
            seq = 0
            while not stop.is_set():
                seq += 1
                now = time.time()
                pubs[bus.MOTOR_STATE].put(bus.MotorState(
                    seq=seq, stamp_s=now, theta_rad=[0.0] * n_motors, force_applied_N=[10.0] * (n_motors + seq % 2),
                    drive="hold", hold_reason="held " * 400, epoch="e", bridge="posing", estop_engaged=True,
                    estop_reason="because " * 500))
                pubs[bus.CONTROLLER_STATUS].put(bus.ControllerStatus(
                    seq=seq, stamp_s=now, law="law2", tick_s=0.002, compute_s=1e-4, overruns=0, deadline_misses=0,
                    saturated=[False] * n_motors, alpha_hat_rad=[0.01] * n_joints, alpha_d_rad=[0.02] * n_joints,
                    e_rad=[0.01] * n_joints, holding=False))
                pubs[bus.CAMERA_ALPHA].put(bus.CameraAlpha(
                    seq=seq, stamp_s=now, capture_stamp_s=now, alpha_ip_rad=[0.1] * n_joints, confidence=[0.5] * (1 if seq % 2 else n_joints),
                    source="posing"), attachment=camera_attachment(HOSTILE_CAMERA))
                if seq % 25 == 1:
                    pubs[bus.CAMERA_FRAME].put(bus.CameraFrame(seq=seq, stamp_s=now, capture_stamp_s=now, width=64,
                                                               height=48, data=cut))
                    health.put(bus.encode(bus.Health(seq=seq, stamp_s=now, process="bridge", instance="posing",
                                                     uptime_s=1.0, received={"ticks": seq}, rejected={},
                                                     last_reject_reason="refused " * 6000)))
                time.sleep(0.02)

        thread = threading.Thread(target=peer, daemon=True)
        thread.start()
        try:
            with dashboard_page(base) as (page, errors):
                page.set_viewport_size({"width": 1280, "height": 720})
                page.fill("#token", TOKEN)
                page.dispatch_event("#token", "change")
                page.wait_for_function("document.querySelector('#bridge-health').textContent.includes('refused refused')",
                                       timeout=15000)
                page.wait_for_function("window.xneckStats.points > 50", timeout=15000)
                page.wait_for_timeout(2500)  # longer than the page waits before it calls the stream lost
                # Before the fix the banner said LIVE STREAM LOST for good from here. One look in the page, and
                # waited for: a loaded machine may starve the posing peer's thread past 1.5 s once, and the
                # page then rightly says the bridge is silent until its next state.
                page.wait_for_function("""() => window.xneckSafety.banner === ''
                    && window.xneckSafety.liveStateFresh()
                    && document.querySelector('#estop-state').textContent.includes('E-STOP ENGAGED: because')""",
                                       timeout=15000)  # the bridge's word reaches the banner and the e-stop state
                page.wait_for_function("document.querySelector('#camera-state').textContent.includes('damaged')",
                                       timeout=5000)
                assert "unreachable" not in page.inner_text("#camera-state")
                # The page lists α_IP only while the camera is fresh: a loaded machine (fresh-clone CI runs,
                # 2026-11-27 and -28) starved this process's publishing thread past that, and the list was
                # empty between two looks. One look in the page: n_joints rows, each with its text.
                page.wait_for_function(f"""() => {{ const el = document.querySelector('#camera-alpha');
                    return el.children.length === {n_joints}
                        && el.innerText.split('\\n').filter(l => l.trim().startsWith('α')).length === {n_joints}; }}""",
                                       timeout=15000)
                # The camera the α_IP is of, its name written as text (no element made of it), cut.
                page.wait_for_function("document.querySelector('#live-camera').textContent"
                                       ".startsWith('α_IP: camera <img src=x')", timeout=15000)
                camera_text = page.inner_text("#live-camera")
                assert camera_text.endswith("… (first seen)") and len(camera_text) < 80, camera_text
                assert page.evaluate("document.querySelector('#live-camera').children.length === 0"
                                     " && window.pwned === undefined")
                for scroll in ("0", "document.body.scrollHeight"):
                    page.evaluate(f"window.scrollTo(0, {scroll})")
                    page.wait_for_timeout(200)
                    box = page.locator("#estop").bounding_box()
                    assert box is not None and box["y"] + box["height"] <= 720, box
                    assert page.evaluate("""() => { const b = document.querySelector('#estop').getBoundingClientRect();
                        return document.elementFromPoint(b.x + b.width / 2, b.y + b.height / 2).closest('#estop') !== null; }""")
                assert app.state.live.values.rejected > 0  # the wrong-sized ones never reached the page
                page.screenshot(path=str(ARTIFACTS / "dashboard_hostile_bus.png"))
                page.click("#estop")
                assert wait_until(lambda: app.state.campaigns.estop_engaged, 10)
                assert not errors, errors
        finally:
            stop.set()
            thread.join(2)
            for pub in pubs.values():
                pub.close()
            health.undeclare()
            token.undeclare()
            session.close()


@needs_chromium
def test_the_dashboard_works_under_its_script_policy_and_an_injected_handler_runs_nothing(tmp_path: Path) -> None:
    """server.guard.CSP (script-src 'self', no plugins, no <base>; audit of 2026-11-27): the page as
    served, not bypassed, loads its plots, its 3D view and its live stream with no violation, and
    markup injected as HTML (which the page never does: it writes values as text) runs no script."""
    import time

    from browser_harness import ARGS, CHROMIUM
    from playwright.sync_api import sync_playwright

    with running_server(tmp_path / "data") as (base, _app), sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1300})  # the policy in force
            console: list[str] = []
            errors: list[str] = []
            page.on("console", lambda m: console.append(m.text))
            page.on("pageerror", lambda e: errors.append(str(e)))
            r = page.goto(base + "/", wait_until="load")
            assert r is not None and "script-src 'self'" in r.headers["content-security-policy"]

            def until(expression: str, timeout_s: float) -> bool:  # page.evaluate: not eval in the page
                end = time.monotonic() + timeout_s
                while time.monotonic() < end:
                    if page.evaluate(expression):
                        return True
                    time.sleep(0.2)
                return False

            assert until("document.querySelectorAll('#plot-joints .uplot').length === 3", 15)
            page.fill("#token", TOKEN)
            page.dispatch_event("#token", "change")
            page.select_option("select[name=pace]", "lockstep")
            page.click("#start")
            assert until("window.xneckStats.points > 100", 60), page.evaluate("window.xneckStats")
            page.frame_locator("#viser").locator("canvas").first.wait_for(state="attached", timeout=30000)
            page.evaluate("""() => {
                const d = document.createElement('div');
                d.innerHTML = '<img src="data:," onerror="window.injected = 1"><a id="js" href="javascript:window.injected = 2">x</a>';
                document.body.appendChild(d);
            }""")
            page.click("#js")
            page.wait_for_timeout(500)
            assert page.evaluate("window.injected") is None
            refused = [m for m in console if "Content Security Policy" in m]
            assert len(refused) >= 2 and all("inline" in m or "javascript:" in m.lower() or "'self'" in m
                                             for m in refused), refused  # the injected ones only
            assert not errors, errors
        finally:
            browser.close()
        with httpx.Client(base_url=base, timeout=10) as c:
            assert wait_until(lambda: c.get("/api/system/health").json()["running_campaign_id"] is None, 90, 0.5)
            assert "script-src" not in c.get("/docs").headers["content-security-policy"]  # its CDN scripts run
