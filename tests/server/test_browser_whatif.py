"""The Lab tab's what-if in a real headless Chromium at 1600×900 (issue 21, item 4):
estimator, parameter and value picked from lists (the value in the unit shown), the
re-run started by a click, and its table fits the panel (no cell wraps)."""

from __future__ import annotations

import math

import httpx
import pytest

from harness import ARTIFACTS, browser_test, chromium_page, click, running_server, wait_for
from toolkit.test_whatif_first_try import demo_recording

pytestmark = browser_test()

# every row of the what-if's table (its header too) and its width against the panel
TABLE_JS = """() => {
  const t = [...document.querySelectorAll('table')].find(
      x => x.innerText.includes('estimator') && x.innerText.includes('before'));
  if (!t || t.offsetParent === null) return null;
  const rows = [...t.querySelectorAll('tr')].map(r => r.getBoundingClientRect().height);
  const cells = [...t.querySelectorAll('td, th')].map(c => c.innerText);
  return {rows, cells, width: t.scrollWidth, room: t.parentElement.clientWidth,
          lineHeight: parseFloat(getComputedStyle(t.querySelector('td')).lineHeight) || 0};
}"""


def _field(frame, label):
    """The visible input after a control's label."""
    fields = frame.get_by_text(label, exact=True).locator("xpath=following::input[1]")
    return wait_for(lambda: next((f for f in fields.all() if f.is_visible()), None), 60.0,
                    what=f"the field {label!r}")


def _pick(page, frame, label, option):
    click(page, _field(frame, label))
    click(page, frame.get_by_role("option", name=option, exact=True))
    page.wait_for_timeout(300)


def test_whatif_from_lists_and_its_table_fits_at_1600x900(tmp_path):
    pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    rec = tmp_path / "rec"
    rec.mkdir()
    demo_recording(rec, "lesson", warm_s=38.0, seconds=20.0)
    with running_server(source="demo", preset_dir=tmp_path, recordings=rec) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0), \
            chromium_page(srv.url + "/", tmp_path / "profile") as (page, frame):
        click(page, frame.get_by_role("tab", name="Lab"))
        click(page, frame.get_by_text("What-if (re-run a recording)", exact=True))
        _pick(page, frame, "Recording", "lesson")
        _pick(page, frame, "Estimator", "robust")
        _pick(page, frame, "Parameter", "gyr_noise [deg/√s]")
        value = _field(frame, "Value")
        value.fill("2.9")              # deg/√s: ten times the default 0.286
        value.press("Tab")
        page.wait_for_timeout(500)
        click(page, frame.get_by_role("button", name="Re-run before/after"))
        tab = srv.app.state.toolkit_tab
        out = wait_for(lambda: tab.whatif.result, 120.0, what="the re-run's result")
        got = out["estimators"]["robust"]["patch"]
        assert set(got) == {"gyr_noise"} and got["gyr_noise"] == pytest.approx(
            2.9 / (180 / math.pi), rel=1e-3)
        t = wait_for(lambda: frame.locator("body").evaluate(TABLE_JS), 60.0, what="the table")
        page.screenshot(path=str(ARTIFACTS / "lab_whatif_1600x900.png"))
        print(t)
        assert "robust" in t["cells"]
        # no cell wraps: every row one line high (the header's height), no overflow
        assert max(t["rows"]) <= 1.3 * min(t["rows"]), t
        assert t["width"] <= t["room"] + 1, t
