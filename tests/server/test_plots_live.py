"""The page's live plots in a real Chromium, while a real phone log streams over TCP into a
real server at the log's own pace: every chart keeps getting new data from deltas (one
snapshot, then only the new points), drawn into the same canvas (never re-created); the
legends show the newest values with no hover; every chart shows the same time window (s
since the stream started); an empty chart says why beside it.

How often they redraw (issue 21: at least 10 times a second) is a speed, measured by
``benchmarks/viewer_bandwidth.py --browser`` (docs/performance.md), not asserted here: on a
shared, loaded machine a rate in a test fails for the machine's sake (it did once, at
0.33 a second, beside a cold compile). This test prints the rate it saw.
"""

from __future__ import annotations

import re
import threading
from pathlib import Path

import pytest

from harness import ARTIFACTS, browser_test, chromium_page, log_lines, play_paced, running_server

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
FULL_LOG = (SHARED / "data" / "sensorfusion-app" / "alekodu_activityrecognition"
            / "sensorLog_20221024T182635_walking_hand.txt")

pytestmark = browser_test()

KEYS = ("euler", "error", "acc", "mag", "nis")
MIN_CHANGES = 3         # new data again and again, not once: a live chart (the rate: above)

# In the page, for `ms` milliseconds: per chart, how often its data changed (a new newest
# x), whether its canvas element stayed the same one, in the document.
MEASURE_JS = """(ms) => new Promise((done) => {
  const charts = window.orientlabPlots.charts;
  const keys = Object.keys(charts);
  const canvas0 = Object.fromEntries(keys.map(k => [k, charts[k].u.root.querySelector('canvas')]));
  const last = Object.fromEntries(keys.map(k => [k, null]));
  const changes = Object.fromEntries(keys.map(k => [k, 0]));
  const same = Object.fromEntries(keys.map(k => [k, true]));
  const stats = window.orientlabPlots.stats;
  const s0 = {messages: stats.messages, snapshots: stats.snapshots};
  const t0 = performance.now();
  const tick = () => {
    for (const k of keys) {
      const x = charts[k].u.data[0];
      const v = x.length ? x[x.length - 1] + ':' + x.length : null;
      if (v !== last[k]) { if (last[k] !== null) changes[k]++; last[k] = v; }
      const c = charts[k].u.root.querySelector('canvas');
      if (c !== canvas0[k] || !document.contains(c)) same[k] = false;
    }
    if (performance.now() - t0 < ms) setTimeout(tick, 5);
    else done({ms: performance.now() - t0, changes, same,
               messages: stats.messages - s0.messages, snapshots: stats.snapshots - s0.snapshots});
  };
  tick();
})"""

STATE_JS = """() => Object.fromEntries(Object.entries(window.orientlabPlots.charts).map(([k, c]) => [k, {
  x: [c.u.scales.x.min, c.u.scales.x.max],
  newest: c.u.data[0].length ? c.u.data[0][c.u.data[0].length - 1] : null,
  legend: Array.from(c.card.querySelectorAll('.legend .li')).filter(e => !e.hidden)
           .map(e => [e.querySelector('.name').textContent, e.querySelector('.val').textContent]),
  why: c.why.hidden ? null : c.why.textContent,
  finite: c.u.data.slice(1).map(col => col.filter(v => v !== null).length),
}]))"""


def test_live_plots_keep_drawing_new_points_in_the_same_canvas(tmp_path):
    if not FULL_LOG.is_file():
        pytest.skip(f"{FULL_LOG} not present")
    pytest.importorskip("playwright.sync_api")
    lines = log_lines(FULL_LOG)          # 16.7 s of a walk: acc, gyr, mag; no ORI, no truth
    stop = threading.Event()
    with running_server(source="none", preset_dir=tmp_path) as srv:
        phone = threading.Thread(target=play_paced, args=(srv.phone_port, lines, stop), daemon=True)
        try:
            with chromium_page(srv.url + "/", tmp_path / "profile") as (page, _):
                phone.start()
                # the Plots tab comes up by itself once a stream is on
                page.locator("#panel-plots").wait_for(state="visible", timeout=30_000)
                page.wait_for_function("window.orientlabPlots.charts.acc.u.data[0].length > 40",
                                       timeout=30_000)
                page.mouse.move(5, 895)                     # not over a chart: no hover
                got = page.evaluate(MEASURE_JS, 3000)
                seconds = got["ms"] / 1000.0
                rates = {k: got["changes"][k] / seconds for k in KEYS}
                print(f"redraws per second: {rates}; messages {got['messages']}")
                assert all(got["same"][k] for k in KEYS), got["same"]          # canvas kept
                assert all(got["changes"][k] >= MIN_CHANGES for k in KEYS), got["changes"]
                # only the new points: no whole window sent again while the stream goes on
                assert got["snapshots"] == 0 and got["messages"] >= MIN_CHANGES, got
                st = page.evaluate(STATE_JS)
                if ARTIFACTS.is_dir():
                    page.screenshot(path=str(ARTIFACTS / "plots_live.png"))
        finally:
            stop.set()
    # one clock, one window: every chart shows the same x range, which holds its newest x
    ranges = {k: tuple(st[k]["x"]) for k in KEYS}
    assert len({(round(a, 6), round(b, 6)) for a, b in ranges.values()}) == 1, ranges
    lo, hi = ranges["acc"]
    assert hi - lo == pytest.approx(20.0)
    newest = [st[k]["newest"] for k in KEYS if st[k]["newest"] is not None]
    assert newest and all(lo <= x <= hi for x in newest)
    assert max(newest) - min(newest) < 0.5                  # the same stream time
    # legends: the newest values with their units, without hover
    legend = {k: dict(st[k]["legend"]) for k in KEYS}
    assert re.fullmatch(r"-?\d+\.\d{2} m/s²", legend["acc"]["|acc|"]), legend["acc"]
    assert re.fullmatch(r"-?\d+\.\d µT", legend["mag"]["|mag|"]), legend["mag"]
    for angle in ("yaw", "pitch", "roll"):
        assert re.fullmatch(r"-?\d+\.\d°", legend["euler"][angle]), legend["euler"]
    assert re.fullmatch(r"[\d.]+", legend["nis"]["acc NIS"]), legend["nis"]
    assert legend["nis"]["acc gate"] not in ("", "–")
    # an empty chart says why, next to it; the others draw
    assert st["error"]["why"] is not None and "no reference" in st["error"]["why"]
    for k in ("euler", "acc", "mag", "nis"):
        assert st[k]["why"] is None and max(st[k]["finite"]) > 40, (k, st[k])
