"""The Tuning tab's number boxes in a real headless Chromium, typed as a student types
(a key every 80 ms), found by a review:

- a box took only the decimals it showed: 0.001 typed in ``heading_noise`` (showing 5.73
  deg·√s) arrived as 0 and was refused, so the low end of a noise range could not be
  reached from the page, and 0.2865 became 0.286;
- a value typed outside the range was clamped by the box on leaving it, without a word
  (100 in ``mag_dip_gate`` became 91.7 and was applied; -5 became 0, the gate off);
- a band's two fields were judged one at a time, and the first set back while the
  student typed the second: 35 then 55 in ``mag_band_uT`` applied [0, 55].
"""

from __future__ import annotations

import math
import time

import httpx
import pytest

from app.server.gui.main import REFUSAL_SETTLE_S
from harness import browser_test, chromium_page, click, running_server, wait_for

pytestmark = browser_test()

DEG = 180.0 / math.pi


def _type(page, box, text: str, delay: float = 80) -> None:
    click(page, box)
    box.press("Control+a")
    box.type(text, delay=delay)
    box.press("Tab")


def test_number_boxes_take_what_is_typed_and_refuse_out_of_range_in_the_users_unit(tmp_path):
    pytest.importorskip("playwright.sync_api")
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        params = lambda: api.get("/api/params").json()["estimators"]  # noqa: E731
        with chromium_page(srv.url + "/", tmp_path / "profile", (1600, 1000)) as (page, frame):
            click(page, frame.get_by_role("tab", name="Tuning"))
            # robust (the primary: its folder open): a noise density to its range's low
            # end, and more digits than the box showed
            box = frame.get_by_label("heading_noise [deg·√s]", exact=True)
            _type(page, box, "0.001")
            wait_for(lambda: params()["robust"]["heading_noise"] == pytest.approx(0.001 / DEG, rel=1e-6),
                     15.0, what=f"heading_noise 0.001 deg·√s applied (is {params()['robust']['heading_noise']})")
            # typed slowly, to more digits than the box shows: each key is applied, and the
            # value written back must not change the next keys' number (0.28654 became
            # 0.2864 when the box was set to 3 digits between two keys)
            box = frame.get_by_label("gyr_noise [deg/√s]", exact=True)
            _type(page, box, "0.28654", delay=300)
            page.wait_for_timeout(1000)
            assert box.input_value() == "0.28654"
            wait_for(lambda: params()["robust"]["gyr_noise"] == pytest.approx(0.28654 / DEG, rel=1e-6),
                     15.0, what=f"gyr_noise 0.28654 deg/√s applied (is {params()['robust']['gyr_noise']})")
            # a range that starts at 0, where 0 is "off": 0.05 must not arrive as 0
            box = frame.get_by_label("mag_turn_gate [deg/s]", exact=True)
            _type(page, box, "0.05")
            wait_for(lambda: params()["robust"]["mag_turn_gate"] == pytest.approx(0.05 / DEG, rel=1e-6),
                     15.0, what=f"mag_turn_gate 0.05 deg/s applied (is {params()['robust']['mag_turn_gate']})")
            # out of range (every key of "-5" is: each key is sent): refused in degrees,
            # nothing applied, the box set back
            before = params()["robust"]["mag_dip_gate"]
            box = frame.get_by_label("mag_dip_gate [deg]", exact=True)
            _type(page, box, "-5")
            note = frame.locator(".mantine-Notification-root", has_text="mag_dip_gate")
            note.first.wait_for(state="visible", timeout=15_000)
            said = note.first.inner_text()
            assert "-5 deg is below the minimum 0 deg" in said, said
            wait_for(lambda: box.input_value() == "10", 15.0, what="the box set back to 10")
            assert params()["robust"]["mag_dip_gate"] == before
            # lab (made the primary, the page opened again: its folder open): the band's
            # low field, a pause longer than a refusal's set-back, then the high field
            assert api.patch("/api/params", json={"primary": "lab"}).status_code == 200
            page.reload()
            click(page, frame.get_by_role("tab", name="Tuning"))
            band = frame.locator("xpath=//label[normalize-space()='mag_band_uT [µT]']/following::input")
            lo, hi = band.nth(0), band.nth(1)
            _type(page, lo, "35")
            time.sleep(REFUSAL_SETTLE_S + 1.0)      # longer than a refusal's set-back
            assert lo.input_value() == "35", "the band's first field was set back while typing"
            _type(page, hi, "55")
            wait_for(lambda: params()["lab"]["mag_band_uT"] == [35.0, 55.0], 15.0,
                     what=f"the band [35, 55] applied (is {params()['lab']['mag_band_uT']})")
            # a vector's field out of its range is set back (no other field can mend it)
            scale = frame.locator("xpath=//label[normalize-space()='gyr_scale']/following::input")
            _type(page, scale.nth(0), "0.5")
            note = frame.locator(".mantine-Notification-root", has_text="gyr_scale: 0.5 is above the maximum 0.1")
            note.first.wait_for(state="visible", timeout=15_000)
            wait_for(lambda: scale.nth(0).input_value() == "0", 15.0, what="gyr_scale's x set back")
            assert params()["lab"]["gyr_scale"] == [0.0, 0.0, 0.0]
