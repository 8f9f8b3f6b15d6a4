"""What a viewer costs: bytes per second each 3D-view client receives at the default view.

What it does
------------
- **30 viewers**: starts ``orientlab serve --source demo --open`` (the default view: the
  demo phone) as a separate process and connects ``--viewers`` (30) viewers, each what a
  browser tab of the page opens: a viser WebSocket client (the 3D view and controls) and
  a WS /ws/plots client (the page's live plots, new points 20 times a second); after a
  5 s warm-up each one's bytes are counted for ``--seconds`` (20); the filter's
  throughput is read from ``/api/stats`` before and with the viewers (the filter must be
  unaffected);
- **breakdown**: the same server in this process with one viewer; every message queued
  for the viewers is serialised and its size added up per message type (what is
  queued: viser merges some pose updates before sending, so the total is an upper
  bound), raw and zstd-compressed one message at a time (viser compresses a window of
  messages at once with zstd level 1: near what is received).

What it prints
--------------
kB/s per viewer (median, min, max; target <= 50 kB/s; the 3D view's and the plots' part),
the plots' messages a second (each one redraws every chart: target >= 10), the
samples/s processed without and with the viewers, the server's CPU, and the breakdown
by message type.

- **redraws** (``--browser``): the page in headless Chromium (``/usr/bin/chromium``), the
  demo streaming: how many times a second each chart gets new data and is redrawn in
  the same canvas (target >= 10).

Run: ``.venv/bin/python benchmarks/viewer_bandwidth.py [--viewers 30] [--seconds 20] [--browser]``.
"""

from __future__ import annotations

import argparse
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

from health_latency import free_port, server_ok, start_server, stop_server, wait_for, ws_readers  # noqa: E402


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def many_viewers(url: str, n: int, counters: list, stop_flag: threading.Event,
                 plots_url: str | None = None, plot_counters: list | None = None) -> threading.Thread:
    """``n`` viewers (and as many plot clients on ``plots_url``) counting what they receive."""
    clients = [(url, c) for c in counters[:n]]
    if plots_url is not None:
        clients += [(plots_url, c) for c in plot_counters[:n]]
    return ws_readers(clients, stop_flag)


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
        # the page answers while the filters still compile (a fresh numba cache): the
        # demo streams once they are ready
        wait_for(lambda: http.get("/api/stats").json()["samples"] > 0, 600.0, 0.5,
                 "the demo streaming")
        time.sleep(3.0)
        alone = rate(http, 5.0)
        counters = [[0] for _ in range(n)]
        plot_counters = [[0, 0] for _ in range(n)]
        stop = threading.Event()
        th = many_viewers(f"ws://127.0.0.1:{vport}", n, counters, stop,
                          f"ws://127.0.0.1:{port}/ws/plots", plot_counters)
        time.sleep(5.0)
        c0 = [c[0] for c in counters]
        p0 = [list(c) for c in plot_counters]
        cpu0, t0 = cpu_s(proc.pid), time.monotonic()
        with_viewers = rate(http, seconds)
        wall = time.monotonic() - t0
        cpu = 100 * (cpu_s(proc.pid) - cpu0) / wall
        view = np.array([(c[0] - b) / wall / 1e3 for c, b in zip(counters, c0)])
        plots = np.array([(c[0] - b[0]) / wall / 1e3 for c, b in zip(plot_counters, p0)])
        plot_msgs = np.array([(c[1] - b[1]) / wall for c, b in zip(plot_counters, p0)])
        per = view + plots
        stop.set()
        th.join(10)
    finally:
        http.close()
        stop_server(proc)
    print(f"viewer bandwidth: demo source, {n} viewers, {wall:.0f} s "
          f"(load average {os.getloadavg()[0]:.1f})")
    print(f"  per viewer       median {np.median(per):.1f} kB/s, min {per.min():.1f}, max {per.max():.1f} "
          f"(target <= 50 kB/s); all {per.sum():.0f} kB/s")
    print(f"    of which       3D view and controls {np.median(view):.1f} kB/s, "
          f"live plots {np.median(plots):.1f} kB/s")
    print(f"  plots            {np.median(plot_msgs):.1f} messages/s per viewer, min {plot_msgs.min():.1f} "
          f"(each redraws every chart: target >= 10)")
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


REDRAWS_JS = """(ms) => new Promise((done) => {
  const charts = window.orientlabPlots.charts, keys = Object.keys(charts);
  const canvas0 = Object.fromEntries(keys.map(k => [k, charts[k].u.root.querySelector('canvas')]));
  const last = {}, changes = Object.fromEntries(keys.map(k => [k, 0]));
  const t0 = performance.now();
  const tick = () => {
    for (const k of keys) {
      const x = charts[k].u.data[0], v = x.length ? x[x.length - 1] + ':' + x.length : null;
      if (v !== last[k]) { if (k in last) changes[k]++; last[k] = v; }
    }
    if (performance.now() - t0 < ms) setTimeout(tick, 5);
    else done({s: (performance.now() - t0) / 1000, changes,
               same: keys.every(k => charts[k].u.root.querySelector('canvas') === canvas0[k])});
  };
  tick();
})"""


def browser_redraws(seconds: float = 5.0) -> None:
    """The page in headless Chromium (the demo streaming): how often each chart of the
    Plots tab gets new data and is redrawn, and whether its canvas stays the same one."""
    from harness import CHROMIUM, chromium_page, running_server
    if CHROMIUM is None:
        print("  redraws          no Chromium: not measured")
        return
    import tempfile
    with running_server(source="demo") as srv, tempfile.TemporaryDirectory() as profile, \
            chromium_page(srv.url + "/", profile, viewer=False) as (page, _):
        page.locator("#panel-plots").wait_for(state="visible", timeout=60_000)
        page.wait_for_timeout(3000)
        got = page.evaluate(REDRAWS_JS, seconds * 1000)
    rates = {k: v / got["s"] for k, v in got["changes"].items()}
    print("  redraws (Chromium, 1600x900, the demo) per chart per second: "
          + ", ".join(f"{k} {v:.1f}" for k, v in rates.items())
          + f" (target >= 10); canvas kept: {got['same']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--viewers", type=int, default=30)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--browser", action="store_true",
                    help="also measure the live plots' redraws per second in headless Chromium")
    args = ap.parse_args()
    viewers_run(args.viewers, args.seconds)
    breakdown(min(args.seconds, 10.0))
    if args.browser:
        browser_redraws()
    return 0


if __name__ == "__main__":
    sys.exit(main())
