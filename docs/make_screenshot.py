"""Take the README's screenshots of the dashboard, from a real phone log streamed over TCP.

Starts the real server on free loopback ports (``tests/harness.py``, no demo), plays a
real Sensor Fusion app log from ``../shared/data/sensorfusion-app`` into its phone port
over TCP at the log's own pace (a thread plays the phone), opens the page in Debian's
headless Chromium (Playwright with ``executable_path``; no browser download) at
1600x900, and saves:

- ``docs/dashboard.png``: the page while the log streams (3D view, the control panel on
  its Tuning tab, the page's Plots tab);
- ``docs/dashboard-demo.png`` (with ``--demo``): the built-in demo at its magnet.

Run: ``.venv/bin/python docs/make_screenshot.py [--log PATH] [--seconds 8] [--demo]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the test harness (tests/harness.py)
from harness import (chromium_page, hide_notices, log_lines, play_paced,  # noqa: E402
                     running_server)

DEFAULT_LOG = (ROOT.parent / "shared" / "data" / "sensorfusion-app" / "alekodu_activityrecognition"
               / "sensorLog_20221024T182635_walking_hand.txt")


def shoot(url: str, out_main: Path, seconds: float, start=None) -> None:
    """Open the page, call ``start()`` (if given) once it shows, wait ``seconds``, shoot."""
    with tempfile.TemporaryDirectory() as profile, chromium_page(url, profile) as (page, _):
        if start is not None:
            start()
        page.wait_for_timeout(seconds * 1000)
        hide_notices(page.frames[1] if len(page.frames) > 1 else page.main_frame)
        page.mouse.move(5, 890)
        page.wait_for_timeout(1500)
        page.screenshot(path=str(out_main))
        print(f"saved {out_main}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, default=DEFAULT_LOG, help="a Sensor Fusion app log")
    ap.add_argument("--seconds", type=float, default=8.0,
                    help="seconds of streaming before the shot (the default log lasts 16.7 s)")
    ap.add_argument("--demo", action="store_true", help="also shoot the demo at its magnet")
    ap.add_argument("--outdir", type=Path, default=ROOT / "docs")
    args = ap.parse_args(argv)
    if not args.log.is_file():
        print(f"no such log: {args.log} (the real logs live in ../shared beside the repository)")
        return 2
    with running_server(source="none") as srv:
        stop = threading.Event()
        phone = threading.Thread(target=play_paced, args=(srv.phone_port, log_lines(args.log), stop),
                                 daemon=True)
        try:
            shoot(srv.url + "/", args.outdir / "dashboard.png", args.seconds, start=phone.start)
        finally:
            stop.set()
            phone.join(5.0)
    if args.demo:
        with running_server(source="demo") as srv:
            # the demo's magnet passes 26-32 s into its loop (the page takes a few s to open)
            shoot(srv.url + "/", args.outdir / "dashboard-demo.png", 22.0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
