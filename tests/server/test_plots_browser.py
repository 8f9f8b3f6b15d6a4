"""Every plot of the page's Plots tab (static/plots.js) draws its lines in a real Chromium,
with real phone logs streamed over TCP into a real server, with each estimator as
primary; and with the demo (ORI and truth).

What is checked is the pixels of each uPlot canvas (the colour of each series must be
drawn), not the data arrays: uPlot once drew an empty chart for data that was fine in
Python (a NaN first value blanks the whole chart; the feed sends gaps as null). An empty
chart says why beside it; every chart shows the same time window.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import httpx
import pytest

from harness import (ARTIFACTS, Phone, browser_test, chromium_page, log_lines, running_server,
                     view_xy, wait_for)

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
REAL = SHARED / "data" / "sensorfusion-app"
FULL_LOG = REAL / "alekodu_activityrecognition" / "sensorLog_20221024T182635_walking_hand.txt"
ACC_ONLY_LOG = REAL / "BaiLiping_WASP_IMU" / "data1.txt"

pytestmark = browser_test()

# Per chart of the page: how many pixels of each series' colour its canvas holds, the
# reason shown beside it (null: none) and its x range.
COUNT_JS = """() => {
  const hex = (h) => [1, 3, 5].map(i => parseInt(h.slice(i, i + 2), 16));
  const out = {};
  for (const [key, ch] of Object.entries(window.orientlabPlots.charts)) {
    const c = ch.u.root.querySelector('canvas');
    const series = ch.spec.series.map(s => [s[0], hex(s[1])]);
    const counts = Object.fromEntries(series.map(([l]) => [l, 0]));
    if (c && c.width && c.height) {
      const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
      for (let i = 0; i < d.length; i += 4) {
        if (d[i + 3] < 200) continue;
        for (const [l, w] of series)
          if (Math.abs(d[i] - w[0]) + Math.abs(d[i + 1] - w[1]) + Math.abs(d[i + 2] - w[2]) < 40) counts[l]++;
      }
    }
    out[key] = {counts, why: ch.why.hidden ? null : ch.why.textContent,
                x: [ch.u.scales.x.min, ch.u.scales.x.max], n: ch.u.data[0].length};
  }
  return out;
}"""

MIN_PIXELS = 25     # a drawn line across a chart has hundreds; noise has none


def wait_drawn(page, expect: dict[str, list[str]], absent: tuple = (), timeout: float = 30.0):
    """Wait until every expected series of every expected chart has drawn pixels, the
    ``absent`` charts draw nothing and say why, and every chart shows one x window."""
    last = {}

    def ok():
        nonlocal last
        last = page.evaluate(COUNT_JS)
        windows = {tuple(v["x"]) for v in last.values()}
        return all(all(last[key]["counts"][s] >= MIN_PIXELS for s in series)
                   for key, series in expect.items()) \
            and all(last[k]["why"] and max(last[k]["counts"].values()) < MIN_PIXELS
                    for k in absent) \
            and all(last[k]["why"] is None for k in expect) and len(windows) == 1
    try:
        wait_for(ok, timeout, interval=0.5, what="plots drawn")
    except TimeoutError:
        raise AssertionError(f"not drawn as expected {expect}, absent {absent}: {last}") from None
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


@contextlib.contextmanager
def open_plots(srv, tmp_path):
    """The page in Chromium, its Plots tab shown (the caller has imported Playwright)."""
    with chromium_page(srv.url + "/", tmp_path / "profile") as (page, _):
        page.locator("#tab-plots").click()
        yield page


def viewer_frame(page):
    return next(f for f in page.frames if f != page.main_frame)


def test_real_log_plots_draw_for_every_primary(tmp_path):
    pytest.importorskip("playwright.sync_api")
    if not FULL_LOG.is_file():
        pytest.skip(f"{FULL_LOG} not present")
    lines = log_lines(FULL_LOG)[:6000]          # ~17 s of a walk, no ORI, no truth
    with running_server(source="none", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, open_plots(srv, tmp_path) as page:
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
            # no reference in this log: the error plot is empty and says why
            got = wait_drawn(page, expect,
                             absent=("error",) + (("euler",) if primary == "phone" else ()))
            assert "no reference" in got["error"]["why"]
            if primary == "phone":
                assert "ORI" in got["euler"]["why"]
        if ARTIFACTS.is_dir():
            page.screenshot(path=str(ARTIFACTS / "plots_real_log.png"))


def test_acc_only_log_and_demo_plots_draw(tmp_path):
    pytest.importorskip("playwright.sync_api")
    if not ACC_ONLY_LOG.is_file():
        pytest.skip(f"{ACC_ONLY_LOG} not present")
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, open_plots(srv, tmp_path) as page:
        frame = viewer_frame(page)
        # the demo: the phone's own estimate (ORI) and the truth: both error series;
        # robust's |mag| band (grey) goes out as its two ends and spans the gaps
        wait_drawn(page, {"euler": ["yaw", "pitch", "roll"],
                                "error": ["vs phone's own", "to truth"],
                                "acc": ["|acc|"], "mag": ["|mag|", "band lo"],
                                "nis": ["acc NIS", "mag NIS"]}, timeout=60.0)
        # the Tuning tab: values in the user's unit with three significant digits,
        # a hover text with meaning, unit and effect; the bias button answers
        # (Tuning is the first tab of the control panel: the plots are the page's)
        field = frame.get_by_label("gyr_noise [deg/√s]", exact=True).first
        field.wait_for(state="visible", timeout=30_000)
        assert field.input_value() == "0.286"      # 0.005 rad/√s, not a log10
        field.hover()                                # viser's tooltip wraps the input
        tip = frame.get_by_text("Unit: deg/√s", exact=False).first
        tip.wait_for(state="visible", timeout=10_000)
        text = tip.inner_text()
        assert text.startswith("Gyroscope noise density") and "Raising it trusts the gyroscope less" in text
        assert "Default from shared trials (set with them in view; its source measured on them since): the gyroscope's attitude random walk" in text  # its source
        frame.get_by_role("button", name="Calibrate gyro bias (last N s at rest)").click()
        note = frame.get_by_text("Gyroscope bias set").or_(frame.get_by_text("Bias not set"))
        note.first.wait_for(state="visible", timeout=10_000)
        # a log with the accelerometer only: no magnetometer plot, the rest draws
        # (complementary: lab and robust wait for a magnetometer to align)
        api.patch("/api/params", json={"primary": "complementary"})
        play(srv, api, log_lines(ACC_ONLY_LOG))
        got = wait_drawn(page, {"euler": ["pitch", "roll"], "acc": ["|acc|"]},
                         absent=("mag", "error"))
        assert "no magnetometer" in got["mag"]["why"]


def test_a_sensor_that_stopped_shows_no_live_figure(tmp_path):
    """The magnetometer switched off 3 s into a real log while the rest goes on: its chart
    keeps the 3 s it had, but the legend's figure is "–", not its last value shown as
    if live (a reviewer's find), while the accelerometer's still reads."""
    pytest.importorskip("playwright.sync_api")
    if not FULL_LOG.is_file():
        pytest.skip(f"{FULL_LOG} not present")
    lines = log_lines(FULL_LOG)
    t0 = int(lines[0].split("\t")[0])
    cut = [ln for ln in lines if not (ln.split("\t")[1] in ("MAG", "RAWMAG")
                                      and int(ln.split("\t")[0]) - t0 > 3000)]
    with running_server(preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, open_plots(srv, tmp_path) as page:
        play(srv, api, cut)
        wait_drawn(page, {"acc": ["|acc|"], "mag": ["|mag|"]})
        legend = """(key) => window.orientlabPlots.charts[key].items[0].querySelector('.val').textContent"""
        wait_for(lambda: page.evaluate(legend, "mag") == "–", 10.0, what="no live |mag| figure")
        assert page.evaluate(legend, "acc").endswith("m/s²")


def test_on_a_phone_screen_the_plots_draw_below_the_3d_view(tmp_path):
    """A student opens the watch-only link on a phone (390×844): the 3D view fills most of
    the screen, the Plots tab follows below it (the page scrolls down, never sideways), and
    its charts draw."""
    pytest.importorskip("playwright.sync_api")
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            chromium_page(srv.url + "/", tmp_path / "profile", size=(390, 844)) as (page, _):
        page.locator("#tab-plots").click()
        page.locator("#plots").scroll_into_view_if_needed()
        wait_drawn(page, {"euler": ["yaw", "pitch", "roll"], "acc": ["|acc|"]}, timeout=60.0)
        box = page.evaluate("""() => {
          const r = (s) => document.querySelector(s).getBoundingClientRect();
          const v = r('#viewer'), a = r('aside');
          return {viewer: [v.top, v.bottom, v.width], aside: [a.top, a.width],
                  scroll_w: document.documentElement.scrollWidth}; }""")
        assert box["viewer"][1] <= box["aside"][0] + 1, box         # the plots below the view
        assert box["viewer"][1] - box["viewer"][0] >= 0.6 * 844, box  # the view keeps the screen
        assert box["viewer"][2] == box["aside"][1] == 390, box        # both the screen's width
        assert box["scroll_w"] <= 390, box                            # no sideways scrolling
        # the phone's camera: its view is narrower than a projector's, so the camera the
        # browser reports shows the phone in the top 40 % of the view, above viser's panel
        viewer = srv.app.state.viewer

        def phone_in_view():
            cams = [c.camera for c in viewer.get_clients().values()]
            return [view_xy((0.0, 0.0, 0.0), c.position, c.look_at, c.fov, c.aspect) for c in cams]

        def framed(what):
            return wait_for(lambda: (lambda v: v if v and all(y < 0.4 for _, y in v) else None)(
                phone_in_view()), 30.0, what=what)
        where = framed("the phone above the panel")
        assert all(0.2 < x < 0.8 for x, _ in where), where

        def moved_away():   # the viewer turns the view: the camera is theirs
            client = next(iter(viewer.get_clients().values()))
            with client.atomic():
                client.camera.position = (3.0, 3.0, 1.5)
                client.camera.look_at = (0.0, 0.0, 0.0)
            wait_for(lambda: (lambda v: v if v and all(abs(y - 0.5) < 0.05 for _, y in v) else None)(
                phone_in_view()), 30.0, what="the viewer's own camera")
        moved_away()
        # viser's "Reset View" (in its settings, kept in the page while folded) puts the camera
        # back at the initial one, the projector's framing: a phone's view is framed again
        page.frame_locator("#viewer").locator("button", has_text="Reset View").evaluate("b => b.click()")
        framed("the phone above the panel after Reset View")
        # viser's client resets its camera by itself when the scene's up direction arrives
        # (after this hook has framed it, on a loaded machine): framed again
        moved_away()
        viewer.scene.set_up_direction("+z")
        framed("the phone above the panel after the client reset its camera")
        if ARTIFACTS.is_dir():
            page.screenshot(path=str(ARTIFACTS / "page_390x844.png"), full_page=True)


def test_the_phones_own_yaw_and_roll_are_drawn_beside_the_estimates(tmp_path):
    """The phone's own yaw beside the estimate's, 3° apart, through a jump of about 180°
    (pitch passing ±90°): the estimate's jump of +179° unwraps upwards, the phone's of
    +185° (-175° wrapped) downwards. Unwrapped each on its own, the page drew them a turn
    apart (357°, the y axis stretched to ±400°); each phone value is now drawn nearest the
    estimate's at the same time."""
    pytest.importorskip("playwright.sync_api")
    wrap = lambda d: (d + 180.0) % 360.0 - 180.0   # noqa: E731 - as the estimators report
    t = [0.1 * i for i in range(40)]
    est = [0.0] * 20 + [179.0] * 20
    phone = [-3.0] * 20 + [wrap(182.0)] * 20
    null = [None] * 40
    ring = [t, est, [80.0] * 40, [wrap(v + 1.0) for v in est], phone, [80.0] * 40,
            [wrap(v + 1.0) for v in phone], null, null]
    with running_server(source="none", preset_dir=tmp_path) as srv, open_plots(srv, tmp_path) as page:
        cols = page.evaluate("""(ring) => {
            const p = window.orientlabPlots;
            p.store.rings.pose = ring;
            return p.columns("euler");
        }""", ring)
    for est_k, phone_k in ((1, 4), (3, 6)):                      # yaw, roll
        gaps = [abs(b - a) for a, b in zip(cols[est_k], cols[phone_k])]
        assert max(gaps) < 10.0, (est_k, cols[est_k], cols[phone_k])
    assert max(map(abs, cols[1] + cols[4])) <= 185.0             # no axis stretched to ±400


LAYOUT_JS = """() => Object.entries(window.orientlabPlots.charts).map(([key, c]) => {
  const body = c.card.querySelector('.plot-body').getBoundingClientRect();
  const why = c.why.getBoundingClientRect(), t = c.card.querySelector('.plot-title');
  return {key, why: c.why.hidden ? null : c.why.textContent,
          inside: why.top >= body.top - 1 && why.bottom <= body.bottom + 1,
          title: t.textContent, cut: t.scrollWidth > t.clientWidth + 1};
})"""


def test_on_a_projector_every_title_shows_whole_and_an_empty_charts_note_stays_on_it(tmp_path):
    """At 1280×720 (the teacher's guide's smaller projector) a phone without its own
    orientation: the error chart is empty and says why. Its note spilled over the next
    chart's title, and that chart's title was cut ("... the phone's ow")."""
    pytest.importorskip("playwright.sync_api")
    from app.sources.simulate import simulate
    lines = [ln for ln in simulate(("still", "turn_z"), seed=4).lines() if "\tORI\t" not in ln]
    assert lines and not any("\tORI\t" in ln for ln in lines)
    with running_server(source="none", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, \
            chromium_page(srv.url + "/", tmp_path / "profile", size=(1280, 720)) as (page, _):
        page.locator("#tab-plots").click()
        play(srv, api, lines)
        got = wait_for(lambda: (lambda g: g if any(c["key"] == "error" and c["why"] for c in g)
                                else None)(page.evaluate(LAYOUT_JS)), 30.0, what="the error chart's note")
        if ARTIFACTS.is_dir():
            page.screenshot(path=str(ARTIFACTS / "plots_1280x720.png"))
    assert all(c["inside"] for c in got if c["why"]), got
    assert not any(c["cut"] for c in got), got
