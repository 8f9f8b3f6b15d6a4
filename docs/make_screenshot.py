"""Take the README's screenshot (docs/dashboard.png) of the dashboard running the demo.

Starts the real server on free loopback ports (``app.server.harness``), opens the page
in Debian's headless Chromium (Playwright with ``executable_path``; no browser
download), lets the demo run into its magnet scene so the disturbance shows, closes
the software-rendering notice and saves the page at 1600x900.
Run: ``.venv/bin/python docs/make_screenshot.py [--seconds 40]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.server.harness import running_server  # noqa: E402

ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=40.0, help="demo time before the shot")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "dashboard.png")
    args = ap.parse_args(argv)
    from playwright.sync_api import sync_playwright
    import tempfile
    with running_server(source="demo") as srv, sync_playwright() as pw, \
            tempfile.TemporaryDirectory() as profile:
        ctx = pw.chromium.launch_persistent_context(
            profile, executable_path="/usr/bin/chromium", headless=True, args=ARGS,
            viewport={"width": 1600, "height": 900})
        page = ctx.new_page()
        page.goto(srv.url + "/")
        frame = page.frame_locator("iframe#viewer")
        frame.locator("canvas").first.wait_for(state="visible", timeout=60_000)
        page.wait_for_timeout(args.seconds * 1000)
        for button in frame.locator("button.mantine-Notification-closeButton, "
                                    "[class*=Notification] button").all():
            try:
                button.click(timeout=1000)
            except Exception:
                pass
        page.mouse.move(5, 890)
        page.wait_for_timeout(1500)
        page.screenshot(path=str(args.out))
        ctx.close()
    print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
