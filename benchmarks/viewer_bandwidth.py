"""What a viewer costs: bytes per second each 3D-view client receives at the default view.

What it does
------------
- **30 viewers**: starts ``orientlab serve --source demo --open`` (the default view: the
  demo phone) as a separate process and connects ``--viewers`` (30) viser WebSocket
  clients (what a browser tab of the page opens); after a 5 s warm-up each one's bytes
  are counted for ``--seconds`` (20); the filter's throughput is read from
  ``/api/stats`` before and with the viewers (the filter must be unaffected);
- **breakdown**: the same server in this process with one viewer; every message queued
  for the viewers is serialised and its size added up per message type (what is
  queued: viser merges some pose updates before sending, so the total is an upper
  bound), raw and zstd-compressed one message at a time (viser compresses a window of
  messages at once with zstd level 1: near what is received).

What it prints
--------------
kB/s per viewer (median, min, max; target <= 50 kB/s), the samples/s processed without
and with the viewers, the server's CPU, and the breakdown by message type.

Run: ``.venv/bin/python benchmarks/viewer_bandwidth.py [--viewers 30] [--seconds 20]``.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import os
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from health_latency import free_port, server_ok, start_server, stop_server, wait_for  # noqa: E402
from soak import _viewer  # noqa: E402


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def many_viewers(url: str, n: int, counters: list, stop_flag: threading.Event) -> threading.Thread:
    async def main():
        stop = asyncio.Event()
        tasks = [asyncio.create_task(_viewer(url, c, stop)) for c in counters[:n]]
        while not stop_flag.is_set():
            await asyncio.sleep(0.1)
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)

    th = threading.Thread(target=lambda: asyncio.run(main()), daemon=True)
    th.start()
    return th


def rate(http: httpx.Client, seconds: float) -> float:
    s0, t0 = http.get("/api/stats").json()["samples"], time.monotonic()
    time.sleep(seconds)
    return (http.get("/api/stats").json()["samples"] - s0) / (time.monotonic() - t0)


def viewers_run(n: int, seconds: float) -> None:
    port, vport, pport = free_port(), free_port(), free_port()
    proc = start_server(port, vport, pport, source="demo")
    http = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0)
    try:
        wait_for(lambda: server_ok(http), 300.0, 0.2, "server start")
        time.sleep(3.0)
        alone = rate(http, 5.0)
        counters = [[0] for _ in range(n)]
        stop = threading.Event()
        th = many_viewers(f"ws://127.0.0.1:{vport}", n, counters, stop)
        time.sleep(5.0)
        c0 = [c[0] for c in counters]
        cpu0, t0 = cpu_s(proc.pid), time.monotonic()
        with_viewers = rate(http, seconds)
        wall = time.monotonic() - t0
        cpu = 100 * (cpu_s(proc.pid) - cpu0) / wall
        per = np.array([(c[0] - b) / wall / 1e3 for c, b in zip(counters, c0)])
        stop.set()
        th.join(10)
    finally:
        http.close()
        stop_server(proc)
    print(f"viewer bandwidth: demo source, {n} viewers, {wall:.0f} s "
          f"(load average {os.getloadavg()[0]:.1f})")
    print(f"  per viewer       median {np.median(per):.1f} kB/s, min {per.min():.1f}, max {per.max():.1f} "
          f"(target <= 50 kB/s); all {per.sum():.0f} kB/s")
    print(f"  filter           {alone:.0f} samples/s alone, {with_viewers:.0f} samples/s with the viewers")
    print(f"  server CPU       {cpu:.0f} % of one core with the viewers")


def _labels(gui) -> dict:
    """uuid -> a readable name for the GUI handles held by the dashboard's Gui."""
    out = {}
    for attr, v in vars(gui).items():
        items = v.items() if isinstance(v, dict) else enumerate(v) if isinstance(v, list) else [(None, v)]
        for k, h in items:
            h = getattr(h, "handle", h)
            impl = getattr(h, "_impl", None)
            if impl is not None and hasattr(impl, "uuid"):
                label = getattr(impl, "label", None) or getattr(h, "title", None) or ""
                out[impl.uuid] = f"{attr}{'' if k is None else f'[{k}]'}{':' + str(label)[:20] if label else ''}"
            for a2 in ("plot", "handle", "uplot"):
                sub = getattr(h, a2, None)
                si = getattr(sub, "_impl", None)
                if si is not None and hasattr(si, "uuid"):
                    out[si.uuid] = f"{attr}{'' if k is None else f'[{k}]'}.{a2}"
    return out


def _plot_labels(gui) -> dict:
    out = {}
    for p in getattr(gui, "plots", {}).values() if isinstance(getattr(gui, "plots", None), dict) \
            else getattr(gui, "plots", []) or []:
        h = getattr(p, "handle", None)
        if h is not None:
            out[h._impl.uuid] = f"plot:{getattr(p, 'title', '')}"
    return out


def breakdown(seconds: float) -> None:
    import msgspec
    import zstandard
    from harness import running_server

    zstd = zstandard.ZstdCompressor(level=1)

    tally: dict[str, list] = collections.defaultdict(lambda: [0, 0, 0])
    with running_server(source="demo") as srv:
        ws = srv.app.state.viewer._websock_server
        original = ws.queue_message
        labels = {**_labels(srv.app.state.toolkit_tab), **_labels(srv.app.state.gui),
                  **_plot_labels(srv.app.state.gui)}

        def counting(message):
            try:
                raw = msgspec.msgpack.encode(message.as_serializable_dict())
                n, nz = len(raw), len(zstd.compress(raw))
            except Exception:
                n = nz = 0
            name = type(message).__name__
            if name == "GuiUpdateMessage":
                name = f"GuiUpdate {labels.get(message.uuid, message.uuid[:8])}.{','.join(message.updates)}"
            t = tally[name]
            t[0] += 1
            t[1] += n
            t[2] += nz
            return original(message)
        counters = [[0]]
        stop = threading.Event()
        th = many_viewers(f"ws://127.0.0.1:{srv.viewer_port}", 1, counters, stop)
        time.sleep(5.0)
        tally.clear()
        c0, t0 = counters[0][0], time.monotonic()
        ws.queue_message = counting
        time.sleep(seconds)
        ws.queue_message = original
        wall = time.monotonic() - t0
        got = (counters[0][0] - c0) / wall / 1e3
        stop.set()
        th.join(10)
    total = sum(v[1] for v in tally.values()) / wall / 1e3
    total_z = sum(v[2] for v in tally.values()) / wall / 1e3
    print(f"  breakdown (1 viewer, queued, {wall:.0f} s): {total:.1f} kB/s queued "
          f"({total_z:.1f} kB/s compressed), {got:.1f} kB/s received")
    print(f"    {'message (GuiUpdate: handle.fields)':60s} {'msg/s':>7s} {'kB/s':>8s} {'zstd':>8s}")
    for name, (k, b, bz) in sorted(tally.items(), key=lambda kv: -kv[1][2])[:14]:
        print(f"    {name[:60]:60s} {k / wall:7.1f} msg/s {b / wall / 1e3:8.1f} kB/s "
              f"{bz / wall / 1e3:8.1f} kB/s")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--viewers", type=int, default=30)
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    viewers_run(args.viewers, args.seconds)
    breakdown(min(args.seconds, 10.0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
