"""The page's Lab tab in a real headless Chromium: one click adds the primary without
rejection beside it, another brings a virtual magnet; both reach the server."""

from __future__ import annotations

import httpx
import pytest

from harness import running_server, wait_for
from test_browser import ARGS, ARTIFACTS, CHROMIUM

def click(page, locator, timeout: float = 60_000) -> None:
    """A mouse click at the element's centre: Playwright's own click waits for the
    element to be "stable", which a viewer re-rendering at a few FPS on a loaded machine
    may never give it."""
    locator.wait_for(state="visible", timeout=timeout)
    locator.scroll_into_view_if_needed(timeout=timeout)
    bb = locator.bounding_box()
    page.mouse.click(bb["x"] + bb["width"] / 2, bb["y"] + bb["height"] / 2)


pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="NO CHROMIUM FOUND: the browser test is SKIPPED"),
]


def test_lab_tab_adds_the_no_rejection_variant_and_brings_a_magnet(tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    with running_server(source="demo", preset_dir=tmp_path, recordings=tmp_path / "rec") as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, \
            sync_api.sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True, args=ARGS,
            viewport={"width": 1600, "height": 1000})
        try:
            page = ctx.new_page()
            page.goto(srv.url + "/")
            frame = page.frame_locator("iframe#viewer")
            frame.locator("canvas").first.wait_for(state="visible", timeout=60_000)
            click(page, frame.get_by_role("tab", name="Lab"))
            click(page, frame.get_by_role("button", name="Add the primary without rejection"))
            wait_for(lambda: "robust-no-rejection" in [e["name"] for e in
                                                       api.get("/api/estimators").json()["estimators"]],
                     30.0, what="the variant added by the click")
            click(page, frame.get_by_role("button", name="Bring a magnet"))
            wait_for(lambda: api.get("/api/inject").json()["marks"], 30.0, what="the magnet's start mark")
            page.wait_for_timeout(4000)     # the heading plot shows both estimators
            page.screenshot(path=str(ARTIFACTS / "lab_magnet.png"))
            st = api.get("/api/state").json()
            assert "robust-no-rejection" in st["estimators"]
        finally:
            ctx.close()
