"""Does the phone stream starve the API? /api/health and PATCH latency during a stream.

What it does
------------
- starts ``orientlab serve --source none --open`` as a **separate process** on free
  loopback ports (as :mod:`benchmarks.dashboard_load` does);
- phase **paced**: a phone streams ACC, GYR and MAG at 500 Hz each (1500 lines/s) at
  real-time speed for ``--seconds`` (default 15);
- phase **flood**: a phone sends a recording as fast as TCP carries it (no pacing: the
  worst a phone, or a hostile script on the phone port, can do) for ``--seconds``;
- meanwhile a client asks ``GET /api/health`` back to back (one at a time, 20 ms apart)
  and sends a ``PATCH /api/params`` every 0.5 s; each request's wall time is recorded;
- phase **inject**: another server, ``--source demo``, with the most virtual disturbances
  it allows on at once (magnets and shakes, world frame, posted until one is refused, at
  most ``--max-injections``, default 100), while the demo streams; ``/api/health`` polled
  as above; then Ctrl-C (SIGINT) and the time the server takes to exit.

What it prints
--------------
Per phase: the samples processed per second, and ``/api/health`` and PATCH latency
(median, 99th percentile, max; target: health p99 < 50 ms); for **inject**, how many
disturbances were on and the seconds Ctrl-C took.

Run: ``.venv/bin/python benchmarks/health_latency.py [--seconds 15] [--only-inject]
[--root TREE]`` (``--root``: serve another checkout, e.g. the committed version
exported with ``git archive HEAD | tar -x -C /tmp/before``, for a before/after figure).
Loopback only.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "tests"))  # the test harness (tests/harness.py)
from harness import free_port, wait_for  # noqa: E402
from app.sources.sensorfusion import format_line
from app.sources.simulate import SimConfig, simulate, stream

RATE_HZ = 500


def start_server(port: int, viewer_port: int, phone_port: int, root: Path = ROOT,
                 **extra) -> subprocess.Popen:
    """``orientlab serve --source none --open`` in its own process (stdout/err dropped),
    from the tree ``root``."""
    kw = dict(host="127.0.0.1", port=port, viewer_port=viewer_port, phone_port=phone_port,
              config=None, source="none", open=True)
    kw.update(extra)
    code = ("import types, sys; from app.server.run import serve; "
            f"sys.exit(serve(types.SimpleNamespace(**{kw!r})))")
    return subprocess.Popen([sys.executable, "-c", code], cwd=root,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


async def ws_reader(url: str, counter: list, stop) -> None:
    """A WebSocket client that counts what it receives until ``stop`` (an asyncio.Event) is
    set: ``counter[0]`` bytes and, when the list has a second slot, ``counter[1]`` messages.
    The server's own WebSockets (``/ws/state``, ``/ws/plots``) are opened with the page's
    Origin; anything else is a viser viewer (its subprotocol)."""
    import asyncio

    import viser
    import websockets
    api = "/ws/" in url
    origin = url.replace("ws://", "http://").rsplit("/ws/", 1)[0] if api else None
    proto = None if api else [f"viser-v{viser.__version__}"]
    async with websockets.connect(url, max_size=None, subprotocols=proto, origin=origin) as ws:
        while not stop.is_set():
            try:
                msg = await asyncio.wait_for(ws.recv(), 0.5)
            except asyncio.TimeoutError:
                continue
            counter[0] += len(msg)
            if len(counter) > 1:
                counter[1] += 1


def ws_readers(clients: list[tuple[str, list]], stop_flag) -> "threading.Thread":
    """:func:`ws_reader` for every ``(url, counter)`` of ``clients``, all in one asyncio loop
    on a daemon thread (started), until ``stop_flag`` (a threading.Event) is set."""
    import asyncio
    import threading

    async def main():
        stop = asyncio.Event()
        tasks = [asyncio.create_task(ws_reader(u, c, stop)) for u, c in clients]
        while not stop_flag.is_set():
            await asyncio.sleep(0.1)
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)

    th = threading.Thread(target=lambda: asyncio.run(main()), daemon=True)
    th.start()
    return th


def stop_server(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()


def server_ok(http: httpx.Client) -> bool:
    try:
        return http.get("/api/health").json().get("status") == "ok"
    except (httpx.HTTPError, ValueError):
        return False


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def phone_config() -> SimConfig:
    p = 1000 // RATE_HZ
    return SimConfig(acc_period_ms=p, gyr_period_ms=p, mag_period_ms=p, ori_period_ms=10_000_000)


def endless_lines():
    """(time_ms, line) of a phone at 500 Hz x ACC/GYR/MAG, forever (no ORI)."""
    for s in stream(seed=0, config=phone_config()):
        if s[1] != "ORI":
            yield s[0], format_line(*s)


def play_paced(port: int, stop: threading.Event, sent: list) -> None:
    """Stream at real-time speed in 10 ms chunks until ``stop``; ``sent[0]`` counts lines."""
    gen = endless_lines()
    with socket.create_connection(("127.0.0.1", port)) as sock:
        pending = next(gen)
        t0_ms, t0 = pending[0], time.monotonic()
        while not stop.is_set():
            due = t0_ms + (time.monotonic() - t0) * 1000.0
            out = []
            while pending[0] <= due:
                out.append(pending[1])
                pending = next(gen)
            if out:
                sock.sendall(("\n".join(out) + "\n").encode())
                sent[0] += len(out)
            time.sleep(0.01)


def play_flood(port: int, stop: threading.Event, sent: list) -> None:
    """Send a 60 s recording over and over as fast as TCP carries it."""
    sim = simulate(duration_s=60.0, config=phone_config(), seed=1)
    lines = [format_line(*s) for s in sim.samples if s[1] != "ORI"]
    span_ms = sim.samples[-1][0] - sim.samples[0][0] + 2
    with socket.create_connection(("127.0.0.1", port)) as sock:
        k = 0
        while not stop.is_set():
            shift = k * span_ms   # each loop continues the clock
            for i in range(0, len(lines), 2000):
                if stop.is_set():
                    break
                block = lines[i:i + 2000]
                if shift:
                    block = [_shift(ln, shift) for ln in block]
                sock.sendall(("\n".join(block) + "\n").encode())
                sent[0] += len(block)
            k += 1


def _shift(line: str, shift: int) -> str:
    t, rest = line.split("\t", 1)
    return f"{int(t) + shift}\t{rest}"


def poll(base: str, stop: threading.Event, health: list, patch: list) -> None:
    with httpx.Client(base_url=base, timeout=30.0) as c:
        last_patch = 0.0
        flip = False
        while not stop.is_set():
            t = time.perf_counter()
            c.get("/api/health")
            health.append(time.perf_counter() - t)
            if t - last_patch > 0.5:
                flip = not flip
                t = time.perf_counter()
                c.patch("/api/params", json={"estimators": {"lab": {"acc_noise": 0.5 if flip else 0.6}}})
                patch.append(time.perf_counter() - t)
                last_patch = t
            time.sleep(0.02)


def pct(x: list) -> str:
    if not x:
        return "no requests"
    ms = np.array(x) * 1e3
    return (f"median {np.median(ms):6.1f} ms, p99 {np.percentile(ms, 99):6.1f} ms, "
            f"max {ms.max():6.1f} ms ({ms.size} requests)")


def run_phase(name: str, player, args, base: str, pport: int, http: httpx.Client) -> None:
    stop = threading.Event()
    sent = [0]
    th = threading.Thread(target=player, args=(pport, stop, sent), daemon=True)
    th.start()
    time.sleep(2.0)   # the phone is on
    s0 = http.get("/api/stats").json()["samples"]
    t0 = time.monotonic()
    health, patch = [], []
    stop_poll = threading.Event()
    poller = threading.Thread(target=poll, args=(base, stop_poll, health, patch), daemon=True)
    poller.start()
    time.sleep(args.seconds)
    stop_poll.set()
    poller.join(30)
    wall = time.monotonic() - t0
    s1 = http.get("/api/stats").json()["samples"]
    stop.set()
    th.join(30)
    print(f"  {name:6s} processed {(s1 - s0) / wall:8.0f} samples/s "
          f"(load average {os.getloadavg()[0]:.1f})")
    print(f"         GET /api/health  {pct(health)}  (target p99 < 50 ms)")
    print(f"         PATCH /api/params {pct(patch)}")
    time.sleep(1.5)   # the phone has left (the next phase's phone is not refused)


INJECTIONS = ({"kind": "magnet", "strength_uT": 40, "direction": "east", "seconds": 600},
              {"kind": "shake", "amplitude_ms2": 3, "seconds": 600, "frame": "world"})


def inject_phase(args) -> None:
    """The demo with the most disturbances allowed on: health latency, then Ctrl-C."""
    import tempfile
    port, vport, pport = free_port(), free_port(), free_port()
    with tempfile.TemporaryDirectory() as tmp:
        proc = start_server(port, vport, pport, root=Path(args.root), source="demo",
                            recordings=str(Path(tmp) / "rec"))
        base = f"http://127.0.0.1:{port}"
        http = httpx.Client(base_url=base, timeout=60.0)
        try:
            wait_for(lambda: server_ok(http), 300.0, 0.2, "server start")
            wait_for(lambda: http.get("/api/stats").json()["samples"] > 100, 60.0, 0.2, "demo")
            on, refusal = 0, ""
            for k in range(args.max_injections):
                r = http.post("/api/inject", json=INJECTIONS[k % 2])
                if r.status_code != 200:
                    try:
                        d = r.json().get("detail", r.text)
                        refusal = d[0].get("msg", d) if isinstance(d, list) and d else d
                    except ValueError:
                        refusal = r.text
                    break
                on += 1
            time.sleep(2.0)
            s0, t0 = http.get("/api/stats").json()["samples"], time.monotonic()
            health, patch = [], []
            stop_poll = threading.Event()
            poller = threading.Thread(target=poll, args=(base, stop_poll, health, patch),
                                      daemon=True)
            poller.start()
            time.sleep(args.seconds)
            stop_poll.set()
            poller.join(60)
            s1 = http.get("/api/stats").json()["samples"]
            rate = (s1 - s0) / (time.monotonic() - t0)
            print(f"  inject {on} disturbances on (the next: {f'refused, {str(refusal)[:90]!r}' if refusal else 'accepted'}); "
                  f"demo {rate:.0f} samples/s (load average {os.getloadavg()[0]:.1f})")
            print(f"         GET /api/health  {pct(health)}  (target p99 < 50 ms)")
            print(f"         PATCH /api/params {pct(patch)}")
        finally:
            http.close()
            t = time.monotonic()
            proc.send_signal(signal.SIGINT)
            try:
                rc = proc.wait(30)
                print(f"         Ctrl-C: exited {rc} after {time.monotonic() - t:.2f} s")
            except subprocess.TimeoutExpired:
                print("         Ctrl-C: still running after 30 s (killed)")
                proc.kill()
                proc.wait(10)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--only-inject", action="store_true", help="only the inject phase")
    ap.add_argument("--max-injections", type=int, default=100,
                    help="post at most this many disturbances (the server refuses beyond its cap)")
    ap.add_argument("--root", default=str(ROOT), help="the tree to serve (default this one)")
    args = ap.parse_args()
    if args.only_inject:
        print(f"health latency with the most disturbances on ({args.seconds:g} s, "
              f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; tree {args.root})")
        inject_phase(args)
        return 0
    port, vport, pport = free_port(), free_port(), free_port()
    proc = start_server(port, vport, pport)
    base = f"http://127.0.0.1:{port}"
    http = httpx.Client(base_url=base, timeout=30.0)
    try:
        wait_for(lambda: server_ok(http), 300.0, 0.2, "server start")
        print(f"health latency during a phone stream ({args.seconds:g} s per phase, "
              f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start)")
        run_phase("paced", play_paced, args, base, pport, http)
        run_phase("flood", play_flood, args, base, pport, http)
    finally:
        http.close()
        stop_server(proc)
    inject_phase(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
