"""The page's Recordings tab in a real headless Chromium: a student's browser (no token)
lists the recordings the presenter made, marks the part being recorded, and downloads each
file, byte for byte what the server wrote; the files of the folder the listing leaves out
are named to the presenter. Logs dropped in the folder by hand, two of one name among them, leave the
viewer's Lab tab working."""

from __future__ import annotations

import httpx
import pytest

from harness import (ARTIFACTS, Phone, browser_test, chromium_page, click, running_server,
                     turns_log_lines, turns_session, wait_for)

pytestmark = browser_test()

TOKEN = "recordings-test-token"
ITEMS = "() => [...document.querySelectorAll('#recordings li')].map(li => li.textContent)"
LEFT = "() => [...document.querySelectorAll('#recordings-left li')].map(li => li.textContent)"
FOCUSED = "() => document.activeElement && document.activeElement.dataset.file"


def test_a_student_downloads_the_recordings_files_from_the_page(tmp_path):
    pytest.importorskip("playwright.sync_api")
    folder = tmp_path / "rec"
    folder.mkdir()
    line = "1000\tACC\t0\t0\t9.81\n"
    for f in ("dup.txt", "dup.csv", "My Log.txt"):      # dropped in by hand
        (folder / f).write_text(line)
    phone = turns_log_lines(*turns_session([(2, 1.0, 1.0)])[:4])
    with running_server(source="demo", open_access=False, token=TOKEN, preset_dir=tmp_path,
                        recordings=folder) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0,
                         headers={"Authorization": f"Bearer {TOKEN}"}) as api:
        def status():
            return api.get("/api/recordings").json()["status"]

        wait_for(lambda: api.get("/api/state").json()["t"] is not None, 60.0, what="the demo")
        assert api.post("/api/recordings/start", json={"name": "lesson-1"}).status_code == 200
        wait_for(lambda: status().get("samples", 0) > 200, 30.0, what="samples recorded")
        assert api.post("/api/recordings/stop").status_code == 200
        r = api.post("/api/recordings/start", json={"name": "dup"})
        assert r.status_code == 409 and "exists already" in r.text      # a dropped log's name
        assert api.post("/api/recordings/start", json={"name": "lesson-2"}).status_code == 200
        wait_for(lambda: status().get("samples", 0) > 100, 30.0, what="the demo recorded")
        # a phone takes over: the recording goes on in its second part, lesson-2_2
        with Phone(srv.phone_port) as ph:
            ph.send_lines(phone)
            wait_for(lambda: [g["name"] for g in status()["segments"]] == ["lesson-2", "lesson-2_2"],
                     30.0, what="the phone's part of the recording")
            with chromium_page(srv.url + "/", tmp_path / "profile") as (page, frame):
                wait_for(lambda: page.evaluate(
                    "() => document.body.classList.contains('watch-only')"), 30.0,
                    what="a watcher's page")
                # every tab says why the controls are greyed, not the Connect tab alone
                badge = page.locator("#watch-badge")
                assert badge.is_visible() and badge.text_content() == "watch-only"
                assert "presenter's link" in badge.get_attribute("title")
                # two logs of one name had crashed the viewer's menus (the whole panel)
                click(page, frame.get_by_role("tab", name="Lab"))
                frame.get_by_text("Record", exact=True).first.wait_for(state="visible")
                page.click("#tab-recordings")
                # (its events file is written within a second: then it says whose part it is)
                items = wait_for(lambda: (lambda x: x if len(x) == 4 and "part 2" in x[0] else None)(
                    page.evaluate(ITEMS)), 30.0, what="four recordings listed")
                assert [x.split(" ")[0] for x in items] == ["lesson-2_2", "lesson-2", "lesson-1", "dup"], items
                assert "recording…" in items[0] and "part 2 of lesson-2" in items[0], items
                assert "recording…" not in items[1] and "samples" in items[2], items
                assert "recording lesson-2_2 now" in page.text_content("#recordings-status")
                # the files left out are named to the presenter (who can rename them) only
                assert page.evaluate(LEFT) == []
                left = [f"{x['file']}: {x['why']}" for x in api.get("/api/recordings").json()["left_out"]]
                assert len(left) == 2 and left[0].startswith("My Log.txt: its name is not"), left
                assert left[1].startswith("dup.csv: another log of the recording 'dup' (dup.txt"), left
                live = page.locator("#recordings li", has_text="lesson-2_2")
                # a new stream's part begins cold (no state); the estimates once it is whole
                assert live.locator("a").evaluate_all("as => as.map(a => a.dataset.file)") == \
                    ["log", "events"]
                ARTIFACTS.mkdir(exist_ok=True)
                page.screenshot(path=str(ARTIFACTS / "recordings.png"))
                done = page.locator("#recordings li", has_text="lesson-1")
                files = done.locator("a").evaluate_all("as => as.map(a => a.dataset.file)")
                assert files == ["log", "estimates", "events", "state"], files
                for file, on_disk in (("log", "lesson-1.txt"),
                                      ("estimates", "lesson-1.estimates.csv.gz"),
                                      ("events", "lesson-1.events.jsonl"),
                                      ("state", "lesson-1.state.npz")):
                    with page.expect_download() as dl:
                        done.locator(f"a[data-file={file}]").click()
                    got = dl.value
                    assert got.suggested_filename == on_disk, (file, got.suggested_filename)
                    assert open(got.path(), "rb").read() == (folder / on_disk).read_bytes(), file
                # the list is asked again every 3 s: a link the keyboard is on stays focused
                done.locator("a[data-file=events]").focus()
                page.wait_for_timeout(4000)
                assert page.evaluate(FOCUSED) == "events"
        api.post("/api/recordings/stop")
        # the phone that took over is named by its app in every file, never by its address
        for f in ("lesson-2.events.jsonl", "lesson-2_2.events.jsonl"):
            text = (folder / f).read_text()
            assert "127.0.0.1" not in text, (f, text[-400:])
