"""Take the teacher guide's projector screenshots: the page at 1600x900 and 1280x720.

Starts the real server on free loopback ports (``tests/harness.py``, no demo), plays a
real Sensor Fusion app log from ``../shared/data/sensorfusion-app`` into its phone port
over TCP at the log's own pace (a thread plays the phone), opens the page in Debian's
headless Chromium (Playwright with ``executable_path``; no browser download) at each
size, and saves what a class sees on a projector:

- ``docs/projector-1600x900.png``
- ``docs/projector-1280x720.png``

(the 3D phone beside the control panel, the live plots in the page's Plots tab; the
default log has no Orientation sensor, so the error plot is empty and says why).

Run: ``.venv/bin/python docs/make_projector_screenshots.py [--log PATH] [--seconds 7]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "docs"))
sys.path.insert(0, str(ROOT / "tests"))  # the test harness (tests/harness.py)
from harness import (CHROMIUM, chromium_page, hide_notices, log_lines, play_paced,  # noqa: E402
                     running_server)
from make_screenshot import DEFAULT_LOG  # noqa: E402

SIZES = ((1600, 900), (1280, 720))


def shoot(url: str, out: Path, size: tuple[int, int], seconds: float, start=None) -> None:
    """Open the page at ``size``, call ``start()`` (if given) once it shows, wait
    ``seconds`` of streaming, take the picture."""
    with tempfile.TemporaryDirectory() as profile, chromium_page(url, profile, size) as (page, _):
        if start is not None:
            start()
        page.wait_for_timeout(seconds * 1000)
        hide_notices(next(f for f in page.frames if f != page.main_frame))
        page.mouse.move(size[0] // 3, size[1] - 3)        # no hover on a chart or control
        page.wait_for_timeout(1000)
        page.screenshot(path=str(out))
        print(f"saved {out}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, default=DEFAULT_LOG, help="a Sensor Fusion app log")
    ap.add_argument("--seconds", type=float, default=7.0,
                    help="seconds of streaming before each shot (the default log lasts 16.7 s)")
    ap.add_argument("--outdir", type=Path, default=ROOT / "docs")
    args = ap.parse_args(argv)
    if CHROMIUM is None:
        print("no Chromium found (/usr/bin/chromium)")
        return 2
    if not args.log.is_file():
        print(f"no such log: {args.log} (the real logs live in ../shared beside the repository)")
        return 2
    lines = log_lines(args.log)
    for w, h in SIZES:
        with running_server(source="none") as srv:
            stop = threading.Event()
            phone = threading.Thread(target=play_paced, args=(srv.phone_port, lines, stop),
                                     daemon=True)
            try:
                shoot(srv.url + "/", args.outdir / f"projector-{w}x{h}.png", (w, h),
                      args.seconds, start=phone.start)
            finally:
                stop.set()
                phone.join(5.0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
