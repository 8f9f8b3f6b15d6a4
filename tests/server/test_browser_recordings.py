"""The page's Recordings tab in a real headless Chromium: a student's browser (no token)
lists the recordings the presenter made, with the one being recorded marked, and
downloads each file, byte for byte what the server wrote."""

from __future__ import annotations

import httpx
import pytest

from harness import ARTIFACTS, browser_test, chromium_page, running_server, wait_for

pytestmark = browser_test()

TOKEN = "recordings-test-token"
ITEMS = "() => [...document.querySelectorAll('#recordings li')].map(li => li.textContent)"


def test_a_student_downloads_the_recordings_files_from_the_page(tmp_path):
    pytest.importorskip("playwright.sync_api")
    folder = tmp_path / "rec"
    with running_server(source="demo", open_access=False, token=TOKEN, preset_dir=tmp_path,
                        recordings=folder) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0,
                         headers={"Authorization": f"Bearer {TOKEN}"}) as api:
        wait_for(lambda: api.get("/api/state").json()["t"] is not None, 60.0, what="the demo")
        assert api.post("/api/recordings/start", json={"name": "lesson-1"}).status_code == 200
        wait_for(lambda: api.get("/api/recordings").json()["status"].get("samples", 0) > 200,
                 30.0, what="samples recorded")
        assert api.post("/api/recordings/stop").status_code == 200
        assert api.post("/api/recordings/start", json={"name": "lesson-2"}).status_code == 200
        with chromium_page(srv.url + "/", tmp_path / "profile", viewer=False) as (page, _):
            wait_for(lambda: page.evaluate("() => document.body.classList.contains('watch-only')"),
                     30.0, what="a watcher's page")
            page.click("#tab-recordings")
            items = wait_for(lambda: (lambda x: x if len(x) == 2 else None)(page.evaluate(ITEMS)),
                             30.0, what="two recordings listed")
            assert "recording…" in items[0] and items[0].startswith("lesson-2"), items
            assert items[1].startswith("lesson-1") and "samples" in items[1], items
            assert "recording lesson-2 now" in page.text_content("#recordings-status")
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "recordings.png"))
            done = page.locator("#recordings li", has_text="lesson-1")
            files = done.locator("a").evaluate_all("as => as.map(a => a.dataset.file)")
            assert files == ["log", "estimates", "events", "state"], files
            for file, on_disk in (("log", "lesson-1.txt"), ("estimates", "lesson-1.estimates.csv.gz"),
                                  ("events", "lesson-1.events.jsonl"), ("state", "lesson-1.state.npz")):
                with page.expect_download() as dl:
                    done.locator(f"a[data-file={file}]").click()
                got = dl.value
                assert got.suggested_filename == on_disk, (file, got.suggested_filename)
                assert open(got.path(), "rb").read() == (folder / on_disk).read_bytes(), file
        api.post("/api/recordings/stop")
