"""The dashboard in a real browser for tests: playwright driving Debian's chromium (bash .ci/setup
installs both), one page on a running console, its uncaught page errors collected."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run", "--disable-quic"]
ARTIFACTS = Path(__file__).resolve().parent.parent / "artifacts"  # screenshots for a person to look at
#: The console's Content-Security-Policy (server.guard.CSP) forbids eval, which playwright's string
#: predicates (wait_for_function) use: test pages bypass it. The page under the policy itself, with
#: no violation, is tests/test_dashboard_browser.py's CSP test.
BYPASS_CSP = True

needs_chromium = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason="Debian chromium not installed (bash .ci/setup)")


@contextlib.contextmanager
def dashboard_page(base: str, *, block: Callable[[str], bool] | None = None) -> Iterator[tuple[Any, list[str]]]:
    """(page, page errors) with the dashboard of the console at ``base`` loaded; ``block(url)``: requests
    to refuse (parts of the page a test leaves out)."""
    sync_api = pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1300}, bypass_csp=BYPASS_CSP)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            if block is not None:
                page.route(block, lambda route: route.abort())
            page.goto(base + "/", wait_until="load")
            yield page, errors
        finally:
            browser.close()
