"""Soak: a long phone stream with viewers and one stuck client; memory and lost samples.

What it does
------------
- starts ``orientlab serve --source none --open`` as a **separate process** on free
  loopback ports;
- connects **5 viewers** (viser WebSocket clients, what a browser tab of the 3D view
  opens; they read everything they are sent) and **1 stuck client**: a ``WS /ws/state``
  client that completes the handshake and then never reads (a laptop put to sleep);
- plays a phone streaming ACC, GYR and MAG at **500 Hz each** (1500 lines/s) at
  real-time speed for ``--seconds`` (default 120; ``--seconds 3600`` for the hour);
- every ``--every`` seconds records the server's RSS, ``/api/health`` and the samples
  processed.

What it prints
--------------
The RSS at the start (after a 10 s warm-up), at the end, its growth and its maximum
(target: growth < 20 MB over an hour); the samples sent, processed and lost after the
phone hangs up and the queue has drained (target: none lost); the health status at the
end; what each viewer received (kB/s).

Run: ``.venv/bin/python benchmarks/soak.py [--seconds 120] [--every 10]``. Loopback only.
"""

from __future__ import annotations

import argparse
import base64
import os
import socket
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from health_latency import (free_port, play_paced, rss_mb, server_ok, start_server,  # noqa: E402
                            stop_server, wait_for, ws_readers)

N_VIEWERS = 5


def stuck_client(port: int) -> socket.socket:
    """A WS /ws/state client that opens the connection and never reads again."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET /ws/state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
               "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    s.recv(1024)   # the 101 answer; from now on nothing is read
    return s


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--every", type=float, default=10.0)
    args = ap.parse_args()
    port, vport, pport = free_port(), free_port(), free_port()
    proc = start_server(port, vport, pport)
    http = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0)
    stuck = None
    try:
        wait_for(lambda: server_ok(http), 300.0, 0.2, "server start")
        counters = [[0] for _ in range(N_VIEWERS)]
        stop_viewers = threading.Event()
        vth = ws_readers([(f"ws://127.0.0.1:{vport}", c) for c in counters], stop_viewers)
        stuck = stuck_client(port)
        stop_phone, sent = threading.Event(), [0]
        phone = threading.Thread(target=play_paced, args=(pport, stop_phone, sent), daemon=True)
        phone.start()
        time.sleep(10.0)   # warm-up: caches, the plots' rings fill
        rss0, t0 = rss_mb(proc.pid), time.monotonic()
        recv0 = [c[0] for c in counters]
        rows = []
        while time.monotonic() - t0 < args.seconds:
            time.sleep(min(args.every, max(0.1, args.seconds - (time.monotonic() - t0))))
            t = time.perf_counter()
            ok = server_ok(http)
            rows.append((time.monotonic() - t0, rss_mb(proc.pid), ok, time.perf_counter() - t))
        wall = time.monotonic() - t0
        recv = [(c[0] - r0) / wall / 1e3 for c, r0 in zip(counters, recv0)]
        stop_phone.set()
        phone.join(10)

        def drained():
            st = http.get("/api/state").json()
            c = st["counts"]
            return st if st["source"] == "phone-disconnected" and c["queued"] == 0 \
                and c["buffered"] == 0 else None
        st = wait_for(drained, 120.0, 0.2, "the stream processed")
        health = http.get("/api/health").json()["status"]
        stop_viewers.set()
        vth.join(10)
    finally:
        http.close()
        if stuck is not None:
            stuck.close()
        stop_server(proc)
    c = st["counts"]
    processed = c["samples"]
    refused = c.get("malformed", 0) + c.get("late", 0)
    lost = sent[0] - processed - refused
    rss = np.array([r[1] for r in rows])
    print(f"soak: phone 500 Hz x ACC/GYR/MAG, {N_VIEWERS} viewers, 1 stuck /ws/state client, "
          f"{wall:.0f} s (load average {os.getloadavg()[0]:.1f})")
    print(f"  RSS              start {rss0:.1f} MB, end {rss[-1]:.1f} MB, growth {rss[-1] - rss0:+.1f} MB, "
          f"max {rss.max():.1f} MB (target growth < 20 MB over an hour)")
    print(f"  RSS every {args.every:g} s   " + " ".join(f"{x:.0f}" for x in rss))
    print(f"  samples          sent {sent[0]}, processed {processed}, refused {refused}, "
          f"lost {lost} (target 0)")
    print(f"  health           {sum(r[2] for r in rows)}/{len(rows)} checks ok, at the end: {health}; "
          f"slowest check {max(r[3] for r in rows) * 1e3:.0f} ms")
    print("  each viewer got  " + ", ".join(f"{x:.0f}" for x in recv) + " kB/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
