"""Take the README's screenshot of the Connect tab while a phone streams.

Starts the real server on free loopback ports (``tests/harness.py``) with a presenter
token, plays an iPhone of the phones-tyrex data (``../shared/data/phones-tyrex``,
Michel et al., CeCILL 2.1) pushing to ``/sensorlogger`` as Sensor Logger does (1 s
batches, Standardise off), opens the presenter's page in Debian's headless Chromium at
1600x900 and saves the aside (the Connect tab: QR code, steps, the phone's status) as
``docs/connect.png``.

Run: ``.venv/bin/python docs/make_connect_screenshot.py``.
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "tests" / "sources")]
from harness import chromium_page, running_server, wait_for  # noqa: E402
from tyrex_sensorlogger import messages_ios  # noqa: E402

TRIAL = ROOT.parent / "shared" / "data" / "phones-tyrex" / "iPhone5_Guillaume_NoDist_texting.npz"
TOKEN = "screenshot-token"


def main() -> int:
    bodies = messages_ios(TRIAL, 1.0, standardise=False, seconds=40)
    stop = threading.Event()
    with running_server(open_access=False, token=TOKEN) as srv, tempfile.TemporaryDirectory() as tmp:
        def phone():
            with httpx.Client(base_url=srv.url, timeout=10.0) as c:
                for b in bodies:
                    if stop.is_set():
                        return
                    c.post("/sensorlogger", content=b)
                    time.sleep(1.0)
        th = threading.Thread(target=phone, daemon=True)
        th.start()
        try:
            with chromium_page(f"{srv.url}/?token={TOKEN}", tmp, viewer=False) as (page, _):
                wait_for(lambda: "orientation" in page.locator("#phone-status").inner_text(), 60,
                         what="the phone's status")
                time.sleep(6.0)
                page.locator("aside").screenshot(path=str(ROOT / "docs" / "connect.png"))
                print("wrote docs/connect.png")
        finally:
            stop.set()
    return 0


if __name__ == "__main__":
    sys.exit(main())
