"""The Studies card (issue 19) in a real browser: playwright driving Debian's chromium on a console
running as its own process (its Dask LocalCluster lives there, not in the test process). The card
refuses a bad spec with the server's message, starts a small study, shows its progress live, then
its summary and figures. Screenshot: artifacts/studies_card.png.

Why the card once waited forever: it polls only while the list says a study is running, and the
list only held studies whose thread had already written ``study.json``; a refresh right after the
POST could find the list empty and stop polling for good (the study ran, the card never showed it).
"""

from __future__ import annotations

import fcntl
from pathlib import Path

from browser_harness import ARTIFACTS, dashboard_page, needs_chromium
from server_harness import TOKEN, server_process, wait_until

from server.studies.service import StudyManager, study_or_error

SMALL = {"kind": "design", "samples": 1, "vary": ("geometry.b=0.04:0.06:2",), "design_configurations": 10}


def test_a_created_study_is_listed_at_once_even_if_it_fails_before_writing_its_directory(tmp_path: Path) -> None:
    """The list the card polls names every study the console started, from the moment it is created."""
    manager = StudyManager(tmp_path / "studies")
    study = study_or_error(**SMALL)
    folder = tmp_path / "studies" / f"design-{study.digest()}"
    folder.mkdir(parents=True)
    with open(folder / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # as `xneck study --out` on the same directory holds it: no study.json yet
        study_id, total = manager.create(study, workers=1)
        assert study_id in manager.ids()
        assert wait_until(lambda: manager.progress(study_id)["state"] != "running", 30)
    p = manager.progress(study_id)
    assert (p["state"], total) == ("failed", 2) and "another process is running this study" in p["error"], p
    assert manager.ids() == [study_id]  # still listed, with its error, though its directory holds no study


@needs_chromium
def test_the_studies_card_runs_a_study_live_and_shows_its_summary_and_figures(tmp_path: Path) -> None:
    # The card alone: no 3D view (software WebGL on 2 cores takes a core from the study's workers) and
    # no workspace maps (the console would draw them while the study runs); other tests cover both.
    with server_process(tmp_path / "data") as (base, _proc), \
            dashboard_page(base, block=lambda url: not url.startswith(base) or "/api/workspace" in url) as (page, errors):
        page.fill("#token", TOKEN)
        page.dispatch_event("#token", "change")
        # Every text the list's rows take, as the card renders them (progress is live only if seen).
        page.evaluate("""() => { window.rowsSeen = [];
            new MutationObserver(() => { const t = document.querySelector('#st-list tbody').innerText.trim();
              if (t && window.rowsSeen[window.rowsSeen.length - 1] !== t) window.rowsSeen.push(t); })
            .observe(document.querySelector('#st-list tbody'), {childList: true, subtree: true, characterData: true}); }""")

        # The truth follows the kind, as the API's default does (truth audit of 2026-12-01).
        page.select_option("#st-kind", "identification")
        assert page.input_value("#st-truth") == "robot"
        page.select_option("#st-kind", "control")
        assert page.input_value("#st-truth") == "model"

        # A bad spec: refused with the checker's message, nothing created.
        page.fill("#st-samples", "3")
        page.fill("#st-laws", "2")
        page.fill("#st-vary", "friction.nope=10%")
        page.click("#st-start")
        page.wait_for_function("document.querySelector('#st-error').textContent !== ''", timeout=30000)
        assert "422" in page.inner_text("#st-error") and "unknown key 'nope'" in page.inner_text("#st-error")
        assert page.evaluate("window.rowsSeen") == []
        assert page.inner_text("#st-list tbody").strip() == ""

        # A small control study: 3 runs of law 2 on robots with friction 10 % off (3: the fewest with a rank correlation).
        page.fill("#st-vary", "friction.f_s=10%")
        page.click("#st-start")
        page.wait_for_function("document.querySelector('#st-list tbody').innerText.includes('complete')",
                               timeout=240000)  # bounds a hang only: ~25 s on a quiet 2-core machine
        assert page.inner_text("#st-error") == ""
        seen = page.evaluate("window.rowsSeen")
        assert any("running" in t and "0/3" in t for t in seen), seen  # shown while it ran
        assert "3/3" in seen[-1] and "complete" in seen[-1], seen
        assert page.eval_on_selector("#st-list tbody progress", "p => p.value") == 100
        page.wait_for_selector("#st-out table.ws-summary", timeout=30000)
        summary = page.inner_text("#st-out table.ws-summary")
        assert "law 2" in summary and "e_mean_all_deg" in summary, summary
        page.wait_for_function("[...document.querySelectorAll('#st-out img')].length > 0 && "
                               "[...document.querySelectorAll('#st-out img')].every(i => i.complete && i.naturalWidth > 0)",
                               timeout=30000)
        assert page.evaluate("window.xneckStudies.polls") >= 3  # it polled while the study ran
        page.locator("#studies").screenshot(path=str(ARTIFACTS / "studies_card.png"))
        assert not errors, errors
