"""Dashboard under load: a phone streaming 500 Hz per sensor with 5 browsers connected.

What it does
------------
- starts ``orientlab serve --source none`` (``app.server.run.serve``) as a **separate
  process** on free loopback ports, so its CPU time can be read from ``/proc``;
- connects **5 viser WebSocket clients** (what a browser tab of the viewer opens: they
  receive every scene, GUI and plot update) **and 5 ``WS /ws/state`` clients** (every
  estimate); all ten read everything they are sent;
- plays a phone over TCP on loopback: ACC, GYR and MAG at **500 Hz each** (1500 lines/s,
  simulated with :mod:`app.sources.simulate`), sent in 10 ms chunks at real-time speed, for
  ``--seconds`` (default 20) after a 3 s warm-up; Nagle's algorithm stays on, as in a
  phone app that does not set ``TCP_NODELAY`` (the receiver acknowledges at once so
  the chunks are not held back);
- polls ``GET /api/stats`` once a second.

What it prints
--------------
- **backlog**: samples queued for the engine and its inbox length, first vs. last
  third of the run (a growing queue means the server does not keep up);
- **latency** from the arrival of the chunk holding a line (the receiver's read
  returned) to the moment the primary's pose after processing it has been queued on
  viser (engine instrumentation, every sample; see :mod:`app.server.engine`): median
  and 99th percentile (target p99 < 5 ms). The reorder buffer's deliberate hold
  (50 ms of stream time) is not included: a sample is timed from the chunk that
  released it. Also printed: the part before the engine task took the chunk, and the
  event loop's lag (how late the display timers ran): a chunk arriving while the loop
  is busy waits in the socket that long, unseen by the latency figure;
- **CPU** of the server process (user + system) in % of one core (target < 15 % with the
  four estimators and the two variants of ``--variants 2``, the default), and per thread
  (from ``/proc``: the event loop's, and the others', of which viser's sender is the
  busiest);
- **Ctrl-C**: at the end the server gets SIGINT, as from a terminal, and the time until
  its process has ended is printed (target: within a second).

Run: ``.venv/bin/python benchmarks/dashboard_load.py [--seconds 20]``. Only loopback
addresses are used.
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
from health_latency import ws_readers  # noqa: E402
from app.sources.sensorfusion import format_line
from app.sources.simulate import SimConfig, simulate

RATE_HZ = 500
CHUNK_S = 0.01
N_VIEWERS = 5
N_STATE = 5


def cpu_seconds(pid: int) -> np.ndarray:
    """[user, system] CPU seconds of a process (all its threads)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    tck = os.sysconf("SC_CLK_TCK")
    return np.array([int(fields[11]), int(fields[12])]) / tck   # utime, stime


# The server process: ``orientlab serve``; with variants, they are put on the ensemble as the
# live core is built (the two ready-made ones of app/toolkit/variants.py, as a lab would run them).
SERVER_CODE = """
import sys, types
from app.live import core
from app.server.run import serve
from app.toolkit.variants import ready_made

N_VARIANTS = {variants}
_init = core.LiveCore.__init__

def init_with_variants(self, *args, **kwargs):
    _init(self, *args, **kwargs)
    for name, (base, params) in list(ready_made(self.ensemble.primary).items())[:N_VARIANTS]:
        self.ensemble.add(name, base, params)

core.LiveCore.__init__ = init_with_variants
args = types.SimpleNamespace(host="127.0.0.1", port={port}, viewer_port={viewer_port},
                             phone_port={phone_port}, config=None, source="none", open=True)
if {profile!r}:
    import cProfile
    cProfile.run("rc = serve(args)", {profile!r})
    sys.exit(0)
sys.exit(serve(args))
"""


def thread_cpu_seconds(pid: int) -> dict[int, float]:
    """CPU seconds (user + system) of each thread of a process, by thread id."""
    tck = os.sysconf("SC_CLK_TCK")
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[int(tid)] = (int(fields[11]) + int(fields[12])) / tck
    return out


def start_server(port: int, viewer_port: int, phone_port: int, variants: int,
                 profile: str = "") -> subprocess.Popen:
    code = SERVER_CODE.format(port=port, viewer_port=viewer_port, phone_port=phone_port,
                              variants=variants, profile=profile)
    return subprocess.Popen([sys.executable, "-c", code], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def phone_lines(seconds: float) -> list[tuple[int, str]]:
    cfg = SimConfig(acc_period_ms=1000 // RATE_HZ, gyr_period_ms=1000 // RATE_HZ,
                    mag_period_ms=1000 // RATE_HZ, ori_period_ms=10_000)
    sim = simulate(duration_s=seconds, config=cfg, seed=0)
    return [(s[0], format_line(*s)) for s in sim.samples if s[1] != "ORI"]


def play(port: int, lines: list[tuple[int, str]], stop: threading.Event) -> None:
    with socket.create_connection(("127.0.0.1", port)) as sock:
        t0_ms = lines[0][0]
        t0 = time.monotonic()
        i = 0
        while i < len(lines) and not stop.is_set():
            due = t0_ms + (time.monotonic() - t0) * 1000.0
            j = i
            while j < len(lines) and lines[j][0] <= due:
                j += 1
            if j > i:
                sock.sendall(("\n".join(ln for _, ln in lines[i:j]) + "\n").encode())
                i = j
            time.sleep(CHUNK_S)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--variants", type=int, default=2, choices=(0, 1, 2),
                    help="variants running beside the four estimators (default 2: "
                         "<primary>-no-rejection and lab-approx)")
    ap.add_argument("--profile", default="", metavar="FILE",
                    help="write a cProfile of the server's event-loop thread to FILE")
    args = ap.parse_args()
    warm = 3.0
    port, vport, pport = free_port(), free_port(), free_port()
    proc = start_server(port, vport, pport, args.variants, args.profile)
    base = f"http://127.0.0.1:{port}"
    http = httpx.Client(base_url=base, timeout=10.0)
    try:
        wait_for(lambda: _ok(http), 300.0, 0.2, "server start")
        names = list(http.get("/api/params").json()["estimators"])
        urls = [f"ws://127.0.0.1:{vport}"] * N_VIEWERS + [f"ws://127.0.0.1:{port}/ws/state"] * N_STATE
        counters = [[0] for _ in urls]
        stop_clients = threading.Event()
        clients = ws_readers(list(zip(urls, counters)), stop_clients)
        lines = phone_lines(warm + args.seconds + 1.0)
        stop_phone = threading.Event()
        phone = threading.Thread(target=play, args=(pport, lines, stop_phone), daemon=True)
        phone.start()
        time.sleep(warm)
        http.get("/api/stats", params={"reset": True})
        cpu0, wall0 = cpu_seconds(proc.pid), time.monotonic()
        threads0 = thread_cpu_seconds(proc.pid)
        samples0 = http.get("/api/stats").json()["samples"]
        backlog = []
        while time.monotonic() - wall0 < args.seconds:
            time.sleep(1.0)
            s = http.get("/api/stats").json()
            backlog.append((s["queued_samples"], s["backlog_now"]))
        cpu1, wall1 = cpu_seconds(proc.pid), time.monotonic()
        threads1 = thread_cpu_seconds(proc.pid)
        stats = http.get("/api/stats").json()
        stop_phone.set()
        stop_clients.set()
        phone.join(5)
        clients.join(5)
    finally:
        http.close()
        t_int = time.perf_counter()
        proc.send_signal(signal.SIGINT)        # Ctrl-C, as a user stops it
        try:
            proc.wait(10)
            stop_s = time.perf_counter() - t_int
        except subprocess.TimeoutExpired:
            proc.kill()
            stop_s = float("nan")
    wall = wall1 - wall0
    rate = (stats["samples"] - samples0) / wall
    b = np.array(backlog)
    third = max(1, len(b) // 3)
    lat = stats["latency_ms"]
    print(f"dashboard load: phone {RATE_HZ} Hz x ACC/GYR/MAG on loopback, "
          f"{N_VIEWERS} viser clients + {N_STATE} /ws/state clients, {wall:.1f} s")
    print(f"  estimators       {len(names)}: {', '.join(names)}")
    print(f"  processed        {rate:8.0f} samples/s (sent {3 * RATE_HZ}/s)")
    print(f"  backlog          queued samples first third mean {b[:third, 0].mean():.1f}, "
          f"last third mean {b[-third:, 0].mean():.1f}, max {b[:, 0].max()}; "
          f"inbox max {stats['backlog_max_items']} items")
    print(f"  latency          median {lat['median']:.2f} ms, p99 {lat['p99']:.2f} ms, "
          f"max {lat['max']:.2f} ms over {lat['n']} samples (target p99 < 5 ms)")
    w = stats["wait_ms"]
    print(f"  of which waiting median {w['median']:.2f} ms, p99 {w['p99']:.2f} ms, max {w['max']:.2f} ms "
          "(arrival -> the engine task took the chunk)")
    g = stats["loop_lag_ms"]
    print(f"  event-loop lag   median {g['median']:.2f} ms, p99 {g['p99']:.2f} ms, max {g['max']:.2f} ms "
          f"over {g['n']} timer runs (data waiting in the socket meanwhile is not in the latency)")
    cpu = 100 * (cpu1 - cpu0) / wall
    print(f"  server CPU       {cpu.sum():.1f} % of one core (user {cpu[0]:.1f} %, system {cpu[1]:.1f} %; "
          "target < 15 % with 4 estimators + 2 variants)")
    per_thread = {tid: 100 * (c - threads0.get(tid, 0.0)) / wall for tid, c in threads1.items()}
    others = sorted((v for tid, v in per_thread.items() if tid != proc.pid), reverse=True)
    print(f"  by thread        event loop (main thread) {per_thread.get(proc.pid, 0.0):.1f} %, "
          f"the {len(others)} others {sum(others):.1f} % (the busiest {others[0] if others else 0.0:.1f} %: "
          "viser's sender)")
    print(f"  received         viser clients {sum(c[0] for c in counters[:N_VIEWERS]) / wall / 1e3:.0f} kB/s, "
          f"/ws/state clients {sum(c[0] for c in counters[N_VIEWERS:]) / wall / 1e3:.0f} kB/s (all)")
    print(f"  Ctrl-C           the server process ended {stop_s:.2f} s after SIGINT "
          "(target: within a second)")
    return 0


def _ok(http: httpx.Client) -> bool:
    try:
        return http.get("/api/health").json().get("status") == "ok"
    except httpx.HTTPError:
        return False


if __name__ == "__main__":
    sys.exit(main())
