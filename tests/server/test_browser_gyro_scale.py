"""The Lab tab's gyroscope scale in a real headless Chromium: a recording of a phone turned whole
turns between rests picked from the list, measured by a click, its report on the page, and
"apply" setting gyr_scale in the estimators."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from harness import (ALL_AXES, ARTIFACTS, SCALE, browser_test, chromium_page, click, running_server,
                     turns_log_lines, turns_session, wait_for)

pytestmark = browser_test()


def test_measure_and_apply_the_gyroscope_scale_from_the_lab_tab(tmp_path):
    pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    rec = tmp_path / "rec"
    rec.mkdir()
    t, gyr, acc, mag, _ = turns_session(ALL_AXES)
    (rec / "turns.txt").write_text("\n".join(turns_log_lines(t, gyr, acc, mag)) + "\n", encoding="utf-8")
    with running_server(source="demo", preset_dir=tmp_path, recordings=rec) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, \
            chromium_page(srv.url + "/", tmp_path / "profile") as (page, frame):
        click(page, frame.get_by_role("tab", name="Lab"))
        click(page, frame.get_by_text("Gyroscope scale (from a recording)", exact=True))
        fields = frame.get_by_text("Turns recording", exact=True).locator("xpath=following::input[1]")
        field = wait_for(lambda: next((f for f in fields.all() if f.is_visible()), None), 60.0,
                         what="the recording's field")
        click(page, field)
        click(page, frame.get_by_role("option", name="turns", exact=True))
        page.wait_for_timeout(300)
        apply = frame.get_by_role("button", name="Apply gyr_scale to the estimators")
        assert apply.is_disabled()                      # nothing measured yet
        click(page, frame.get_by_role("button", name="Measure the scale"))
        tk = srv.app.state.toolkit
        out = wait_for(lambda: tk.gyro_scale.last, 120.0, what="the fit")
        np.testing.assert_allclose(out["scale"], SCALE, atol=5e-4)
        wait_for(lambda: frame.get_by_text("spans between rests", exact=False).first.is_visible(), 30.0,
                 what="the report on the page")
        wait_for(lambda: not apply.is_disabled(), 30.0, what="apply enabled")
        apply.scroll_into_view_if_needed()
        page.screenshot(path=str(ARTIFACTS / "lab_gyro_scale_1600x900.png"))
        click(page, apply)
        got = wait_for(lambda: (lambda p: p if p["robust"]["gyr_scale"][0] != 0.0 else None)(
            api.get("/api/params").json()["estimators"]), 30.0, what="gyr_scale applied")
        for est in ("robust", "lab"):
            np.testing.assert_allclose(got[est]["gyr_scale"], out["preset_scale"], atol=1e-12)
