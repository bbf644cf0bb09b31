"""Workspace maps on a real console: the summary of the active parameter set, PNG figures, 404 for
an unknown figure, the on-disk cache, rendering off the event loop, and a change of the active set
(an uploaded variant with f_max = 40 N) re-rendering maps with a smaller wrench-feasible workspace."""

from __future__ import annotations

import io
import threading
import time
from pathlib import Path

import httpx
import matplotlib.image as mpimg
import pytest
from server_harness import AUTH, running_server

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("workspace") / "data"
    with running_server(data, viser=False) as (base, _app), httpx.Client(base_url=base, timeout=60) as c:
        yield c, data


def _png(r: httpx.Response) -> tuple[int, int]:
    """(height, width) of a PNG response, read back with matplotlib."""
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    assert r.content.startswith(PNG_SIGNATURE)
    image = mpimg.imread(io.BytesIO(r.content), format="png")
    return image.shape[0], image.shape[1]


def test_summary_figures_and_cache_for_the_default_set(server) -> None:
    c, data = server
    s = c.get("/api/workspace").json()
    assert s["parameter_set"] == "prototype_3x" and s["design"] == "3x"
    assert 0.0 < s["feasible_fraction"] < 1.0  # bounded forces cut the ±90° cube
    assert s["f_min_N"] == 2.0 and s["f_max_N"] == 100.0
    assert s["grid"]["points_per_axis"] == 31 and s["grid"]["alpha_max_deg"] == pytest.approx(90.0)
    k = s["joint_stiffness_N_m_per_rad"]
    assert len(k["min"]) == len(k["max"]) == 3 and all(lo < hi for lo, hi in zip(k["min"], k["max"]))
    assert s["straight_neck"]["feasible"] is True
    assert {f["name"] for f in s["figures"]} == {"wfw", "stiffness"}
    assert all(f["caption"] and f["url"].startswith("/api/workspace/") for f in s["figures"])

    entry = data / "workspace" / f"3x-{s['key']}"
    assert (entry / "3x_wfw.png").is_file() and (entry / "3x_stiffness.png").is_file()
    for f in s["figures"]:
        r = c.get(f["url"])
        assert r.headers["x-xneck-cache"] == "hit"
        h, w = _png(r)
        assert h > 300 and w > 800, (f["name"], h, w)

    again = c.get("/api/workspace").json()
    assert again["cached"] is True and again["feasible_fraction"] == s["feasible_fraction"]


def test_unknown_figure_is_404_and_unknown_design_422(server) -> None:
    c, _ = server
    r = c.get("/api/workspace/nope.png")
    assert r.status_code == 404 and "wfw" in r.json()["detail"] and "stiffness" in r.json()["detail"]
    assert c.get("/api/workspace/wfw.png", params={"design": "2x"}).status_code == 404
    assert c.get("/api/workspace", params={"design": "4x"}).status_code == 422


def test_a_new_active_set_renders_once_off_the_event_loop_and_changes_the_maps(server) -> None:
    c, data = server
    before = c.get("/api/workspace").json()
    text = c.get("/api/params/prototype_3x").text
    assert "f_max = 100.0" in text
    weaker = text.replace("f_max = 100.0", "f_max = 40.0")
    assert c.put("/api/params/weak-motors", content=weaker.encode(), headers=AUTH).status_code == 201
    assert c.put("/api/params/active", json={"name": "weak-motors"}, headers=AUTH).status_code == 200
    try:
        # Two browsers ask for the new set's figures at once: one render, the other waits for it.
        results: dict[str, httpx.Response] = {}

        def fetch(name: str) -> None:
            results[name] = c.get(f"/api/workspace/{name}.png")

        threads = [threading.Thread(target=fetch, args=(n,)) for n in ("wfw", "stiffness")]
        for t in threads:
            t.start()
        # The render runs off the event loop: health answers while the figures are still coming.
        answered_during_render = 0
        while any(t.is_alive() for t in threads):
            assert c.get("/api/system/health").status_code == 200
            answered_during_render += any(t.is_alive() for t in threads)
            time.sleep(0.05)
        for t in threads:
            t.join()
        assert answered_during_render >= 2
        assert sorted(r.headers["x-xneck-cache"] for r in results.values()) == ["hit", "miss"]
        for r in results.values():
            _png(r)

        after = c.get("/api/workspace").json()
        assert after["parameter_set"] == "weak-motors" and after["f_max_N"] == 40.0 and after["cached"] is True
        assert after["key"] != before["key"]
        assert 0.0 < after["feasible_fraction"] < before["feasible_fraction"] - 0.1
        assert len(list((data / "workspace").glob("3x-*"))) == 2
    finally:
        c.put("/api/params/active", json={"name": "prototype_3x"}, headers=AUTH)
    restored = c.get("/api/workspace").json()
    assert restored["cached"] is True and restored["feasible_fraction"] == before["feasible_fraction"]


def test_2x_paper_figures(server) -> None:
    c, data = server
    s = c.get("/api/workspace", params={"design": "2x"}).json()
    assert s["parameter_set"] is None and len(s["figures"]) == 9
    assert "aspects" in {f["name"] for f in s["figures"]}
    url = next(f["url"] for f in s["figures"] if f["name"] == "aspects")
    r = c.get(url)
    h, w = _png(r)
    assert h > 300 and w > 300 and r.headers["x-xneck-cache"] == "miss"
    assert c.get(url).headers["x-xneck-cache"] == "hit"
    assert c.get("/api/workspace", params={"design": "2x"}).json()["rendered"] is True
    assert len(list(Path(data, "workspace").glob("2x-*/2x_*.png"))) == 9


def test_dashboard_shows_the_maps_and_follows_the_active_set(tmp_path: Path) -> None:
    """The Workspace card in a real browser (skipped without playwright and Debian's chromium)."""
    import os

    sync_api = pytest.importorskip("playwright.sync_api")
    chromium = "/usr/bin/chromium"
    if not os.path.exists(chromium):
        pytest.skip("Debian chromium not installed (bash .ci/setup)")
    all_loaded = ("(sel) => { const im = [...document.querySelectorAll(sel)]; "
                  "return im.length > 0 && im.every((i) => i.complete && i.naturalWidth > 0); }")
    with running_server(tmp_path / "data", viser=False) as (base, _app), sync_api.sync_playwright() as pw, \
            httpx.Client(base_url=base, timeout=60) as c:
        text = c.get("/api/params/prototype_3x").text
        c.put("/api/params/weak-motors", content=text.replace("f_max = 100.0", "f_max = 40.0").encode(), headers=AUTH)
        browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                     args=["--no-sandbox", "--disable-gpu", "--no-first-run"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1600}, bypass_csp=True)  # server.guard.CSP forbids eval (tests/browser_harness.py)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(base + "/", wait_until="load")
            page.wait_for_function("window.xneckWorkspace.loads >= 1", timeout=30000)
            page.wait_for_function(all_loaded, arg="#ws-figures img", timeout=30000)
            assert page.locator("#ws-figures figure").count() == 2
            assert "prototype_3x" in page.inner_text("#ws-summary") and "100 N" in page.inner_text("#ws-summary")
            # Changed by another client: the page notices on its next poll and redraws.
            c.put("/api/params/active", json={"name": "weak-motors"}, headers=AUTH)
            page.wait_for_function("window.xneckWorkspace.tried === 'weak-motors' && window.xneckWorkspace.loads >= 2",
                                   timeout=30000)
            page.wait_for_function(all_loaded, arg="#ws-figures img", timeout=30000)
            assert "40 N" in page.inner_text("#ws-summary")
            assert "[2, 40] N" in page.inner_text("#ws-figures")
            assert errors == []
        finally:
            browser.close()


def test_the_console_grids_are_within_the_memory_bound_of_the_cli(tmp_path) -> None:
    """Audit of 2026-12 (`xneck workspace --n 400` OOM-killed): the console's maps take no grid from a
    request; their grids come from the settings (3x, 5..61) and GRID_2X, within the CLI's bound,
    and a WorkspaceCache built with a grid beyond it is refused before any map is computed."""
    from pydantic import ValidationError

    from server.settings import Settings
    from server.workspace_maps import GRID_2X, WorkspaceCache
    from twin.analysis.workspace import max_grid

    with pytest.raises(ValidationError, match="workspace_grid"):
        Settings.model_validate({"workspace_grid": 401})
    highest = max(m.le for m in Settings.model_fields["workspace_grid"].metadata if hasattr(m, "le"))
    assert highest <= max_grid("3x") and max_grid("2x") >= GRID_2X
    with pytest.raises(ValueError, match="at most 89"):
        WorkspaceCache(tmp_path / "a", grid_3x=91)
    with pytest.raises(ValueError, match="at most 1123"):
        WorkspaceCache(tmp_path / "b", grid_2x=2000)
    assert not list(tmp_path.iterdir())
