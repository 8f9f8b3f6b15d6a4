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


# The header's box and its status badge's: their heights (one line: the header's own 44 px)
HEADER_JS = """() => {
  const h = document.querySelector('header'), b = document.querySelector('#source');
  return {header: h.getBoundingClientRect().height, header_scroll: h.scrollHeight,
          badge: b.getBoundingClientRect().height, line: parseFloat(getComputedStyle(b).lineHeight) ||
          1.2 * parseFloat(getComputedStyle(b).fontSize), text: b.textContent, title: b.title};
}"""


def test_on_a_projector_the_header_keeps_one_line_with_the_longest_status(tmp_path):
    """At 1280×720 (a classroom projector) the status of a phone that hung up, the longest
    there is, stays on the header's one line: the subtitle gives way first, and the badge
    shows its whole text on hover."""
    pytest.importorskip("playwright.sync_api")
    from harness import Phone, turns_log_lines, turns_session
    lines = turns_log_lines(*turns_session([(2, 1.0, 2.0)])[:4])
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        with Phone(srv.phone_port) as ph:
            ph.send_lines(lines)
            wait_for(lambda: api.get("/api/state").json()["source"] == "phone", 30.0, what="the phone")
        status = wait_for(lambda: (lambda st: st["status"] if st["source"] == "phone-disconnected"
                                   else None)(api.get("/api/state").json()), 30.0, what="the hang-up")
        assert len(status) > 80, status
        with chromium_page(srv.url + "/", tmp_path / "profile", size=(1280, 720)) as (page, _):
            got = wait_for(lambda: (lambda g: g if g["text"] == status else None)(
                page.evaluate(HEADER_JS)), 30.0, what="the status in the badge")
            assert got["header"] == got["header_scroll"] == 44, got
            assert got["badge"] < 2 * got["line"], got        # one line, not wrapped
            assert got["title"].startswith(status), got       # the whole text on hover


def test_a_connected_but_silent_phone_is_a_warning_in_the_header(tmp_path):
    """A phone whose app stopped sending without hanging up: the badge says so, in the
    warning colour, not the green of a live stream."""
    pytest.importorskip("playwright.sync_api")
    import threading
    from harness import play_paced, turns_log_lines, turns_session
    lines = turns_log_lines(*turns_session([(2, 1.0, 2.0)])[:4])
    badge = "() => { const b = document.querySelector('#source'); return [b.textContent, b.className]; }"
    stop = threading.Event()
    with running_server(preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api, \
            chromium_page(srv.url + "/", tmp_path / "profile") as (page, _):
        wait_for(lambda: "waiting" in page.evaluate(badge)[0], 30.0, what="the page")
        th = threading.Thread(target=play_paced, args=(srv.phone_port, lines, stop), daemon=True)
        th.start()          # at the phone's pace, then connected and silent
        try:
            text, cls = wait_for(lambda: (lambda b: b if "streaming" in b[0] else None)(
                page.evaluate(badge)), 30.0, what="the live badge")
            assert "phone" in cls.split() and "warn" not in cls.split()
            text, cls = wait_for(lambda: (lambda b: b if "no samples for" in b[0] else None)(
                page.evaluate(badge)), 60.0, what="the silent badge")
            assert "warn" in cls.split() and "phone" not in cls.split(), cls
            assert api.get("/api/state").json()["source"] == "phone"
        finally:
            stop.set()
            th.join(10)


def test_the_api_docs_work_on_a_network_without_internet(tmp_path):
    """The header's "API docs" link (/docs, Swagger UI) on a classroom network with no way
    out: every request that leaves the PC is refused, and the docs still draw, with their
    "Try it out" buttons, from orientlab's own files."""
    pytest.importorskip("playwright.sync_api")
    left: list[str] = []

    def only_this_pc(route):
        host = route.request.url.split("/")[2].split(":")[0]
        if host in ("127.0.0.1", "localhost"):
            return route.continue_()
        left.append(route.request.url)
        return route.abort()

    with running_server(source="none", preset_dir=tmp_path) as srv, \
            chromium_page(srv.url + "/", tmp_path / "profile", viewer=False) as (page, _):
        page.context.route("**/*", only_this_pc)
        page.goto(srv.url + "/docs")
        page.locator(".swagger-ui .info .title").filter(has_text="orientlab").wait_for(timeout=30_000)
        page.locator(".opblock-summary-path", has_text="/api/params").first.click()
        page.get_by_role("button", name="Try it out").first.wait_for(timeout=10_000)
        assert not left, left
