"""Take the README's lab-session screenshots from the real page (Lab tab).

Starts the real server on free loopback ports (``tests/harness.py``) with the demo and
a temporary recordings folder holding a copy of a real still phone's log
(``../shared``) and a minute of the simulated phone, opens the page in Debian's headless
Chromium (Playwright with ``executable_path``; no browser download) and saves

- ``docs/lab_magnet.png``: the primary and "the primary without rejection" (added with
  its button) on the replayed still phone, with a 50 µT virtual magnet (its button);
- ``docs/lab_whatif.png``: the minute of the simulated phone re-run with the primary's
  gates off (``POST /api/recordings/{name}/rerun``), before vs after;
- ``docs/lab_calibration.png``: 5 s of the real still phone (replayed) calibrated
  (``POST /api/calibrate``; the log's phone is touched at 6 s): histograms per axis
  with the fitted Gaussian.

Run: ``.venv/bin/python docs/make_lab_screenshots.py``.
"""

from __future__ import annotations

import asyncio
import shutil
import sys
import tempfile
import threading
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
from harness import (chromium_page, click, hide_notices, running_server,  # noqa: E402
                     wait_for)

STILL = (ROOT.parent / "shared" / "data" / "sensorfusion-app" / "alekodu_activityrecognition"
         / "sensorLog_20221024T182616_standstill.txt")


def demo_log(path: Path, seconds: float) -> None:
    from app.sources.sensorfusion import format_line
    from app.sources.simulate import Simulation, stream
    boot = Simulation().config.boot_ms
    with open(path, "w") as fh:
        for ms, tag, vals in stream(5):
            if ms - boot > seconds * 1000:
                break
            fh.write(format_line(ms, tag, vals) + "\n")


def main() -> int:
    out = ROOT / "docs"
    with tempfile.TemporaryDirectory() as d:
        rec = Path(d) / "recordings"
        rec.mkdir()
        shutil.copy(STILL, rec / "still_phone.txt")
        demo_log(rec / "demo_minute.txt", 60.0)
        with running_server(source="demo", recordings=rec, preset_dir=Path(d)) as srv, \
                httpx.Client(base_url=srv.url, timeout=120.0) as api, \
                chromium_page(srv.url + "/", Path(d) / "profile", (1600, 1000),
                              timeout_ms=120_000) as (page, frame):
            hide_notices(page.frames[1] if len(page.frames) > 1 else page.main_frame)
            click(page, frame.get_by_role("tab", name="Lab"))
            # 1. calibration of the real still phone, replayed
            api.post("/api/replay", json={"name": "still_phone"})
            wait_for(lambda: api.get("/api/state").json()["source"] == "replay", 30.0)
            r = api.post("/api/calibrate", json={"seconds": 5})
            r.raise_for_status()
            click(page, frame.get_by_text("Calibrate (keep the phone still)"))
            page.wait_for_timeout(2000)
            frame.get_by_text("z histogram and fitted Gaussian").scroll_into_view_if_needed()
            page.screenshot(path=str(out / "lab_calibration.png"))
            click(page, frame.get_by_text("Calibrate (keep the phone still)"))
            # 2. the magnet on the still phone, with and without rejection
            click(page, frame.get_by_role("button", name="Add the primary without rejection"))
            wait_for(lambda: len(api.get("/api/estimators").json()["estimators"]) > 4, 30.0)
            api.post("/api/replay", json={"seek_s": 0.0, "loop": True})
            page.wait_for_timeout(5000)
            click(page, frame.get_by_role("button", name="Bring a magnet"))
            # the page says the magnet is on (it lags the server on a busy machine): 4 of
            # its 5 s in the heading plot, the status still on
            frame.get_by_text("of at most").first.wait_for(state="visible", timeout=120_000)
            page.wait_for_timeout(3000)
            frame.get_by_text("Record", exact=True).first.scroll_into_view_if_needed(timeout=20_000)
            page.screenshot(path=str(out / "lab_magnet.png"))
            api.post("/api/replay", json={"stop": True})
            # 3. what-if: the minute of the simulated phone with the primary's gates off
            tk, toolkit_tab, loop = srv.app.state.toolkit, srv.app.state.toolkit_tab, srv.engine.loop
            patch = {"robust": tk.variants.no_rejection()[2]}
            # once unseen: a user's second click (the first in a process also loads the
            # compiled batch runs from numba's cache), then the one shown
            asyncio.run_coroutine_threadsafe(tk.whatif.rerun("demo_minute", patch), loop).result(120)
            res = asyncio.run_coroutine_threadsafe(tk.whatif.rerun("demo_minute", patch), loop).result(120)
            done = threading.Event()

            def show():
                toolkit_tab.whatif.result = res
                toolkit_tab.whatif.est.value = "robust"
                toolkit_tab.whatif.draw()
                done.set()
            loop.call_soon_threadsafe(show)
            done.wait(10)
            click(page, frame.get_by_text("What-if (re-run a recording)"))
            page.wait_for_timeout(1500)
            frame.get_by_text("Variants", exact=True).first.scroll_into_view_if_needed(timeout=20_000)
            page.screenshot(path=str(out / "lab_whatif.png"))
            click(page, frame.get_by_text("What-if (re-run a recording)"))
    print("wrote docs/lab_magnet.png, docs/lab_whatif.png, docs/lab_calibration.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
