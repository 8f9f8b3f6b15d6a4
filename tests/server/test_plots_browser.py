"""Every plot draws its lines in a real Chromium, with real phone logs streamed over TCP
into a real server, with each estimator as primary; and with the demo (ORI and truth).

What is checked is the pixels of each uPlot canvas (the colour of each series must be
drawn), not the data arrays: uPlot once drew an empty chart for data that was fine in
Python (a NaN first value blanks the whole chart; see app/server/gui/plots.py).
"""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from harness import (ARTIFACTS, CHROMIUM, CHROMIUM_ARGS, Phone, log_lines, running_server,
                     wait_for)

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
REAL = SHARED / "data" / "sensorfusion-app"
FULL_LOG = REAL / "alekodu_activityrecognition" / "sensorLog_20221024T182635_walking_hand.txt"
ACC_ONLY_LOG = REAL / "BaiLiping_WASP_IMU" / "data1.txt"

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="NO CHROMIUM FOUND: browser test SKIPPED"),
]

# Per canvas: the chart title and how many pixels of each colour it holds.
COUNT_JS = """(colors) => {
  const hex = (h) => [1, 3, 5].map(i => parseInt(h.slice(i, i + 2), 16));
  const want = colors.map(hex);
  return Array.from(document.querySelectorAll('.uplot')).map(u => {
    const title = (u.querySelector('.u-title') || {}).textContent || '';
    const c = u.querySelector('canvas');
    if (!c || c.width === 0 || c.height === 0) return {title: '', counts: {}, w: 0, h: 0};
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    const n = want.map(() => 0);
    for (let i = 0; i < d.length; i += 4) {
      if (d[i + 3] < 200) continue;
      for (let k = 0; k < want.length; k++) {
        const w = want[k];
        if (Math.abs(d[i] - w[0]) + Math.abs(d[i + 1] - w[1]) + Math.abs(d[i + 2] - w[2]) < 40) n[k]++;
      }
    }
    const out = {};
    colors.forEach((h, k) => out[h] = n[k]);
    return {title, counts: out, w: c.width, h: c.height};
  });
}"""

# What uPlot itself holds per chart (viser's E2E testpoint): for a failure message.
STATE_JS = """() => Object.values((window.__viserTestpoints || {}).uplots || {}).map(({chart, createCount}) => ({
  title: chart.root.querySelector('.u-title') ? chart.root.querySelector('.u-title').textContent : '',
  created: createCount, width: chart.width, height: chart.height,
  scales: Object.fromEntries(Object.entries(chart.scales).map(([k, v]) => [k, [v.min, v.max]])),
  n: chart.data[0].length, x: [chart.data[0][0], chart.data[0][chart.data[0].length - 1]],
  finite: chart.data.slice(1).map(col => Array.from(col).filter(v => v !== null && isFinite(v)).length),
}))"""

MIN_PIXELS = 25     # a drawn line across a chart has hundreds; noise has none


def drawn(frame, gui) -> dict[str, dict[str, int]]:
    """{plot key: {series label: pixels of its colour}} for the charts on show."""
    plots = {p.title: p for p in gui.plots}
    colors = sorted({c for p in gui.plots for c in p.colors})
    out = {}
    for row in frame.evaluate(COUNT_JS, colors):
        p = plots.get(row["title"])
        if p is not None and row["w"] > 0:
            out[p.key] = {spec[0]: row["counts"][spec[1]] for spec in p.specs}
    return out


def windows_agree(frame, gui, keys) -> bool:
    """Each chart of ``keys`` shows on the page the x range the server set for it
    (app.server.gui.plots.Plot.x_range): the window is the server's, not left to the client."""
    by_title = {p.title: p for p in gui.plots}
    shown = {by_title[row["title"]].key: row["scales"]["x"] for row in frame.evaluate(STATE_JS)
             if row["title"] in by_title}
    want = {p.key: p.x_range for p in gui.plots}
    return all(k in shown and None not in shown[k]
               and max(abs(a - b) for a, b in zip(shown[k], want[k])) < 1e-6 for k in keys)


def wait_drawn(frame, gui, expect: dict[str, list[str]], absent: tuple = (), timeout: float = 30.0):
    """Wait until every expected series of every expected plot has drawn pixels and the
    ``absent`` plots draw nothing (empty axes; the note says why)."""
    last = {}

    def ok():
        nonlocal last
        last = drawn(frame, gui)
        return all(key in last and all(last[key][s] >= MIN_PIXELS for s in series)
                   for key, series in expect.items()) and \
            not any(k in last and any(v >= MIN_PIXELS for v in last[k].values()) for k in absent) \
            and windows_agree(frame, gui, expect)
    try:
        wait_for(ok, timeout, interval=0.5, what="plots drawn")
    except TimeoutError:
        raise AssertionError(f"not drawn as expected {expect}: {last}\n"
                             f"uPlot state: {frame.evaluate(STATE_JS)}") from None
    return last


def play(srv, api, lines):
    n = api.get("/api/state").json()["counts"]["total_sessions"]
    with Phone(srv.phone_port) as ph:
        ph.send_lines(lines)   # a connection is a phone once it sends a valid sample
        wait_for(lambda: api.get("/api/state").json()["counts"]["total_sessions"] > n,
                 what="the phone session")
    wait_for(lambda: (lambda st: st["source"] == "phone-disconnected" and st["counts"]["queued"] == 0
                      and st["counts"]["buffered"] == 0)(api.get("/api/state").json()),
             what="the end of the stream")


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as pw:
        yield pw


def open_page(pw, srv, tmp_path):
    ctx = pw.chromium.launch_persistent_context(
        str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS,
        viewport={"width": 1600, "height": 900})
    page = ctx.new_page()
    page.goto(srv.url + "/")
    frame = page.frame_locator("iframe#viewer")
    frame.locator("canvas").first.wait_for(state="visible", timeout=60_000)
    return ctx, page, page.frames[1] if len(page.frames) > 1 else page.main_frame


def viewer_frame(page):
    return next(f for f in page.frames if f != page.main_frame)


def test_real_log_plots_draw_for_every_primary(tmp_path, browser):
    if not FULL_LOG.is_file():
        pytest.skip(f"{FULL_LOG} not present")
    lines = log_lines(FULL_LOG)[:6000]          # ~17 s of a walk, no ORI, no truth
    with running_server(source="none", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        gui = srv.app.state.gui
        ctx, page, _ = open_page(browser, srv, tmp_path)
        try:
            frame = viewer_frame(page)
            for primary in srv.engine.core.ensemble.names:
                assert api.patch("/api/params", json={"primary": primary}).status_code == 200
                play(srv, api, lines)
                expect = {"acc": ["|acc|"], "mag": ["|mag|"]}
                if primary != "phone":                   # phone: no ORI, no estimate
                    expect["euler"] = ["yaw", "pitch", "roll"]
                if primary == "lab":
                    expect["mag"].append("L_k")
                if primary in ("lab", "robust"):
                    expect["nis"] = ["acc NIS", "mag NIS"]
                # no reference in this log: the error plot is hidden and the note says why
                wait_drawn(frame, gui, expect,
                           absent=("error",) + (("euler",) if primary == "phone" else ()))
                assert "no reference" in gui.plot_note.content
                if primary == "phone":
                    assert "ORI" in gui.plot_note.content
            page.screenshot(path=str(ARTIFACTS / "plots_real_log.png")) if ARTIFACTS.is_dir() else None
        finally:
            ctx.close()


def test_acc_only_log_and_demo_plots_draw(tmp_path, browser):
    if not ACC_ONLY_LOG.is_file():
        pytest.skip(f"{ACC_ONLY_LOG} not present")
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        gui = srv.app.state.gui
        ctx, page, _ = open_page(browser, srv, tmp_path)
        try:
            frame = viewer_frame(page)
            # the demo: the phone's own estimate (ORI) and the truth: both error series;
            # robust's |mag| band (grey) goes out as its two ends and spans the gaps
            wait_drawn(frame, gui, {"euler": ["yaw", "pitch", "roll"],
                                    "error": ["to phone's own", "to truth"],
                                    "acc": ["|acc|"], "mag": ["|mag|", "band lo"],
                                    "nis": ["acc NIS", "mag NIS"]}, timeout=60.0)
            # the Tuning tab: values in the user's unit with three significant digits,
            # a hover text with meaning, unit and effect; the bias button answers
            # (Tuning is the first tab of the control panel: the plots have their own panel)
            field = frame.get_by_label("gyr_noise [deg/√s]", exact=True).first
            field.wait_for(state="visible", timeout=30_000)
            assert field.input_value() == "0.286"      # 0.005 rad/√s, not a log10
            field.hover()                                # viser's tooltip wraps the input
            tip = frame.get_by_text("Unit: deg/√s", exact=False).first
            tip.wait_for(state="visible", timeout=10_000)
            text = tip.inner_text()
            assert text.startswith("Gyroscope noise density") and "Raising it trusts the gyroscope less" in text
            frame.get_by_role("button", name="Calibrate gyro bias (last N s at rest)").click()
            note = frame.get_by_text("Gyroscope bias set").or_(frame.get_by_text("Bias not set"))
            note.first.wait_for(state="visible", timeout=10_000)
            # a log with the accelerometer only: no magnetometer plot, the rest draws
            # (complementary: lab and robust wait for a magnetometer to align)
            api.patch("/api/params", json={"primary": "complementary"})
            play(srv, api, log_lines(ACC_ONLY_LOG))
            wait_drawn(frame, gui, {"euler": ["pitch", "roll"], "acc": ["|acc|"]},
                       absent=("mag", "error"))
            assert "no magnetometer" in gui.plot_note.content
        finally:
            ctx.close()
