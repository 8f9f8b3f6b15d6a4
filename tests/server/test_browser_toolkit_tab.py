"""The page's Lab tab in a real headless Chromium: one click adds the primary without
rejection beside it, another brings a virtual magnet; both reach the server. The
Presets tab's load brings a preset's magnetometer calibration back."""

from __future__ import annotations

import time

import httpx
import numpy as np
import pytest

from harness import ARTIFACTS, browser_test, chromium_page, click, running_server, wait_for

pytestmark = browser_test()

# The breaks uPlot draws in each NIS line (its path's gaps), as seconds of the x scale.
NIS_GAPS_JS = """() => {
  const u = window.orientlabPlots.charts.nis.u;
  const pxs = u.bbox.width / (u.scales.x.max - u.scales.x.min);
  return Object.fromEntries(u.series.slice(1, 3).map(s => [s.label,
    ((s._paths && s._paths.gaps) || []).map(([a, b]) => (b - a) / pxs)]));
}"""


def test_toolkit_tab_adds_the_no_rejection_variant_and_brings_a_magnet(tmp_path):
    pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    with running_server(source="demo", preset_dir=tmp_path, recordings=tmp_path / "rec") as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, \
            chromium_page(srv.url + "/", tmp_path / "profile", (1600, 1000)) as (page, frame):
        click(page, frame.get_by_role("tab", name="Lab"))
        click(page, frame.get_by_role("button", name="Add the primary without rejection"))
        wait_for(lambda: "robust-no-rejection" in [e["name"] for e in
                                                   api.get("/api/estimators").json()["estimators"]],
                 30.0, what="the variant added by the click")
        # robust has learned the field: the magnet is then a disturbance its pill shows
        wait_for(lambda: api.get("/api/state").json()["diagnostics"].get("mag_band"), 60.0,
                 what="robust's learned field")
        shake = frame.get_by_role("button", name="Shake", exact=True)
        follow = frame.get_by_text("Live heading plot", exact=True)   # under the disturbances
        where = [(shake.bounding_box(), follow.bounding_box())]
        click(page, frame.get_by_role("button", name="Bring a magnet"))
        wait_for(lambda: api.get("/api/inject").json()["marks"], 30.0, what="the magnet's start mark")
        # while the pills light up and go out (the heading plot meanwhile shows both
        # estimators), the controls under them stay where they are: a teacher's next
        # click lands on what they aimed at
        lit, deadline = 0, time.monotonic() + 4.0
        while time.monotonic() < deadline:
            where.append((shake.bounding_box(), follow.bounding_box()))
            lit += api.get("/api/state").json()["mag_rejected"]
            page.wait_for_timeout(100)
        assert lit, "robust never refused the magnet's field: the status never changed"
        for k, what in enumerate(("the Shake button", "the Live heading plot switch")):
            ys = sorted({(b[k]["x"], b[k]["y"]) for b in where})
            assert len(ys) == 1, f"{what} moved while the status changed: {ys}"
        page.screenshot(path=str(ARTIFACTS / "lab_magnet.png"))
        st = api.get("/api/state").json()
        assert "robust-no-rejection" in st["estimators"]


def test_loading_a_preset_from_the_page_applies_its_magnetometer_calibration(tmp_path):
    """The Presets tab: type a preset's name, click Load: its [magcal] (hard and soft
    iron) corrects the magnetometer again, as the API's load does."""
    pytest.importorskip("playwright.sync_api")
    (tmp_path / "withmag.toml").write_text(
        "[magcal]\noffset_uT = [15.0, -8.0, 25.0]\nmatrix = [1.1, 0, 0, 0, 0.9, 0, 0, 0, 1.0]\n")
    with running_server(source="demo", preset_dir=tmp_path, recordings=tmp_path / "rec") as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        assert api.get("/api/magcal").json()["applied"] is None
        with chromium_page(srv.url + "/", tmp_path / "profile", (1600, 1000)) as (page, frame):
            click(page, frame.get_by_role("tab", name="Presets"))
            # the text field after its label (the Lab tab's calibration has a "Preset
            # name" too, hidden here)
            fields = frame.get_by_text("Preset name", exact=True).locator("xpath=following::input[1]")
            name = wait_for(lambda: next((f for f in fields.all() if f.is_visible()), None), 30.0,
                            what="the Presets tab's name field")
            name.fill("withmag")
            name.press("Enter")
            page.wait_for_timeout(500)
            click(page, frame.get_by_role("button", name="Load preset", exact=True))
            applied = wait_for(lambda: api.get("/api/magcal").json()["applied"], 30.0,
                               what="the preset's magnetometer calibration")
            assert applied["offset_uT"] == [15.0, -8.0, 25.0]
            assert np.diag(applied["matrix"]) == pytest.approx([1.1, 0.9, 1.0])


def test_an_injected_magnet_and_shake_are_marked_in_the_plots_panel(tmp_path):
    """While a virtual magnet (shake) is on, the page's Plots tab's |mag| (|acc|) chart draws
    its samples over again in red: the disturbance is marked where it shows, not only in
    the Lab tab and the recording."""
    pytest.importorskip("playwright.sync_api")
    from test_plots_browser import COUNT_JS, MIN_PIXELS, open_plots, wait_drawn
    with running_server(source="demo", preset_dir=tmp_path, recordings=tmp_path / "rec") as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, \
            open_plots(srv, tmp_path) as page:     # the page's Plots tab
        before = wait_drawn(page, {"mag": ["|mag|"], "acc": ["|acc|"]}, timeout=60.0)
        assert before["mag"]["counts"]["magnet injected"] < MIN_PIXELS
        assert before["acc"]["counts"]["shake injected"] < MIN_PIXELS
        # robust has learned the field (its band is out): a magnet is then a disturbance,
        # before that the first field it sees
        page.wait_for_function("window.orientlabPlots.store.meta.mag_band", timeout=60_000)
        r = api.post("/api/inject", json={"kind": "magnet", "strength_uT": 50, "seconds": 8})
        assert r.status_code == 200, r.text
        r = api.post("/api/inject", json={"kind": "shake", "amplitude_ms2": 8, "seconds": 8})
        assert r.status_code == 200, r.text
        wait_drawn(page, {"mag": ["|mag|", "magnet injected"],
                          "acc": ["|acc|", "shake injected"]}, timeout=30.0)
        page.screenshot(path=str(ARTIFACTS / "plots_injected.png"))
        # the mark covers the injection only: the chart's own line still draws the rest
        d = page.evaluate(COUNT_JS)
        assert d["mag"]["counts"]["|mag|"] >= MIN_PIXELS
        # the NIS chart: the field refused while the magnet is on has no NIS, and its line
        # breaks there (no diagonal drawn across the refusal); the accelerometer's, never
        # refused, is joined across the bins where only the field's NIS is
        assert page.evaluate(NIS_GAPS_JS)["acc NIS"] == [], "acc NIS line broken before"
        gaps = wait_for(lambda: (lambda g: g if any(s > 2.0 for s in g["mag NIS"]) else None)(
            page.evaluate(NIS_GAPS_JS)), 30.0, what="a break in the mag NIS line")
        assert gaps["acc NIS"] == [], gaps
