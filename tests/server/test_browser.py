"""A real headless Chromium opens the landing page, sees the 3D canvas and the controls
inside the embedded viewer, and switches the magnetometer off by clicking it."""

from __future__ import annotations


import httpx
import pytest

from harness import ARTIFACTS, browser_test, chromium_page, running_server, wait_for


pytestmark = browser_test()


def test_page_shows_viewer_and_magnetometer_switch_works(tmp_path):
    pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, \
            chromium_page(srv.url + "/", tmp_path / "profile") as (page, frame):
        mag = frame.get_by_label("Magnetometer", exact=True)
        mag.wait_for(state="visible", timeout=60_000)
        assert frame.get_by_label("Gyroscope", exact=True).is_visible()
        assert frame.get_by_label("Accelerometer", exact=True).is_visible()
        assert page.locator("#sf-port").text_content() == str(srv.phone_port)
        assert api.get("/api/params").json()["use_mag"] is True
        mag.click()
        wait_for(lambda: api.get("/api/params").json()["use_mag"] is False, 30.0,
                 what="use_mag false after the click")
        page.wait_for_timeout(2500)    # let the plots fill for the screenshot
        page.screenshot(path=str(ARTIFACTS / "dashboard.png"))
