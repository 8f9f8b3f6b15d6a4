"""Sensor Logger's push handler under a fast Android phone, while the filters run.

What it does: starts ``orientlab serve --source none`` as a separate process on free
loopback ports (with the two ready-made variants, as ``dashboard_load.py`` does), then
plays a 400 Hz Android phone pushing to ``POST /sensorlogger`` once a second: each
message one second of readings as the app sends them (gyroscope and
totalacceleration and accelerometer 400 Hz, gravity and orientation 200 Hz,
magnetometer 100 Hz: 1,700 readings, about 290 kB of JSON), for ``--seconds``.

What it prints:
- the decoder alone, in this process (no server): per 1 s message, the time
  :meth:`SensorLoggerStream.read` (JSON to arrays, on a worker thread in the server) and
  :meth:`SensorLoggerStream.take` (order and release, on the event loop) take;
- the handler's latency, client side (request sent -> 200 received): median and 99th
  percentile; the handler only parses, enqueues and answers;
- the engine's latency (arrival -> the primary's pose queued on viser, every sample, from
  ``/api/stats``) and the server's CPU (% of one core), to compare with
  ``dashboard_load.py``'s figures for the TCP phone;
- then **one long batch** (``--long`` seconds of the same phone in one message, near the
  16 MB push cap; a phone that was cut off and sends what it kept): its handler latency,
  and ``GET /api/health`` asked back to back meanwhile: how long the server was held up
  (the slowest health answer) while it read the batch.

Run: ``.venv/bin/python benchmarks/push_latency.py [--seconds 20] [--long 50]``. Loopback
only. For a before/after figure, run the script from another checkout (it serves the tree
it sits in).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
from dashboard_load import cpu_seconds, start_server  # noqa: E402
from harness import free_port, wait_for  # noqa: E402
from app.sources.simulate import SimConfig, Simulation  # noqa: E402
from app.quaternion import rotate_inv_many  # noqa: E402
from app.sources.sensorlogger import SensorLoggerStream  # noqa: E402

EPOCH_NS = 1_760_000_000_000_000_000
RATES = {"gyroscope": 400, "totalacceleration": 400, "accelerometer": 400, "gravity": 200,
         "orientation": 200, "magnetometer": 100}


def batch(sim: Simulation, k: int, msg_id: int) -> bytes:
    """Second ``k`` of the simulated phone as one Sensor Logger message."""
    payload = []
    for name, hz in RATES.items():
        t = k + (np.arange(hz) + 0.37) / hz
        q, w, a_lin, b = sim.motion(t)
        g_s = rotate_inv_many(q, np.tile([0.0, 0.0, 9.81], (hz, 1)))
        vals = {"gyroscope": w, "totalacceleration": rotate_inv_many(q, a_lin) + g_s,
                "accelerometer": rotate_inv_many(q, a_lin), "gravity": g_s,
                "magnetometer": rotate_inv_many(q, np.tile([0.0, 20.0, -45.0], (hz, 1)) + b)}.get(name)
        for i in range(hz):
            tn = EPOCH_NS + int(round(t[i] * 1e9))
            if name == "orientation":
                v = {"qw": q[i, 0], "qx": q[i, 1], "qy": q[i, 2], "qz": q[i, 3],
                     "yaw": 0.0, "pitch": 0.0, "roll": 0.0}
            else:
                v = {"x": vals[i, 0], "y": vals[i, 1], "z": vals[i, 2]}
            payload.append({"name": name, "time": tn, "accuracy": 3, "values": v})
    return json.dumps({"messageId": msg_id, "sessionId": "bench", "deviceId": "bench",
                       "payload": payload}).encode()


def long_batch(sim: Simulation, k0: int, seconds: int, msg_id: int) -> bytes:
    """Seconds ``k0`` .. ``k0 + seconds`` of the simulated phone as one message."""
    payload = []
    for k in range(k0, k0 + seconds):
        payload += json.loads(batch(sim, k, 0))["payload"]
    return json.dumps({"messageId": msg_id, "sessionId": "bench", "deviceId": "bench",
                       "payload": payload}).encode()


def decoder_alone(bodies: list[bytes]) -> None:
    """:meth:`SensorLoggerStream.read` and :meth:`~SensorLoggerStream.take` per message,
    in this process (the first three messages warm up)."""
    st = SensorLoggerStream(start_hold_s=0.0)
    read_ms, take_ms, n = [], [], 0
    for k, body in enumerate(bodies):
        s = time.perf_counter()
        r = st.read(body)
        m = time.perf_counter()
        b = st.take(r, float(k))
        e = time.perf_counter()
        n += len(b.samples)
        if k >= 3:
            read_ms.append((m - s) * 1000.0)
            take_ms.append((e - m) * 1000.0)
    print(f"decoder alone, {len(read_ms)} messages of 1 s ({n} samples released):")
    print(f"  read (JSON -> arrays): median {np.median(read_ms):.1f} ms, max {max(read_ms):.1f} ms")
    print(f"  take (order, release): median {np.median(take_ms):.1f} ms, max {max(take_ms):.1f} ms")


def held_up(http, body: bytes) -> tuple[float, list[float]]:
    """POST ``body`` while another client asks /api/health back to back: the POST's
    latency (ms) and each health answer's (ms) while it ran."""
    done = threading.Event()
    health: list[float] = []

    def poll():
        with httpx.Client(base_url=http.base_url, timeout=30.0) as h:
            while not done.is_set():
                s = time.perf_counter()
                h.get("/api/health")
                health.append((time.perf_counter() - s) * 1000.0)
                time.sleep(0.005)

    th = threading.Thread(target=poll)
    th.start()
    time.sleep(0.3)
    s = time.perf_counter()
    r = http.post("/sensorlogger", content=body, headers={"Content-Type": "application/json"})
    took = (time.perf_counter() - s) * 1000.0
    done.set()
    th.join()
    assert r.status_code == 200, r.text
    return took, health


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=int, default=20)
    ap.add_argument("--variants", type=int, default=2)
    ap.add_argument("--long", type=int, default=50, help="seconds in the long batch (0: none)")
    args = ap.parse_args()
    sim = Simulation(SimConfig())
    bodies = [batch(sim, k, k + 1) for k in range(args.seconds + 3)]
    long_body = long_batch(sim, len(bodies), args.long, len(bodies) + 1) if args.long else b""
    decoder_alone(bodies)
    port, vport, pport = free_port(), free_port(), free_port()
    proc = start_server(port, vport, pport, args.variants)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as http:
            wait_for(lambda: _ok(http), 300.0, 0.2, "server start")
            http.get("/api/stats", params={"reset": True})
            lat = []
            t0 = time.monotonic()
            cpu0 = None
            for k, body in enumerate(bodies):
                delay = t0 + k - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                if k == 3:          # after the warm-up
                    http.get("/api/stats", params={"reset": True})
                    cpu0, wall0 = cpu_seconds(proc.pid).sum(), time.monotonic()
                s = time.perf_counter()
                r = http.post("/sensorlogger", content=body,
                              headers={"Content-Type": "application/json"})
                if k >= 3:
                    lat.append((time.perf_counter() - s) * 1000.0)
                assert r.status_code == 200, r.text
            time.sleep(1.0)
            cpu = (cpu_seconds(proc.pid).sum() - cpu0) / (time.monotonic() - wall0) * 100.0
            st = http.get("/api/stats").json()
            lat = np.array(lat)
            print(f"push handler, a 1 s batch of a 400 Hz Android phone "
                  f"({len(bodies[0]) / 1000:.0f} kB, {sum(RATES.values())} readings), "
                  f"{len(lat)} requests:")
            print(f"  latency (request sent -> 200): p50 {np.percentile(lat, 50):.1f} ms, "
                  f"p99 {np.percentile(lat, 99):.1f} ms, max {lat.max():.1f} ms")
            e = st["latency_ms"]
            print(f"  engine (arrival -> pose on viser): p50 {e['median']:.2f} ms, "
                  f"p99 {e['p99']:.2f} ms over {e['n']} samples")
            print(f"  server CPU: {cpu:.1f} % of one core (with {args.variants} variants)")
            if long_body:
                took, health = held_up(http, long_body)
                h = np.array(health)
                print(f"one long batch: {args.long} s of the same phone in one message "
                      f"({len(long_body) / 1e6:.1f} MB):")
                print(f"  latency (request sent -> 200): {took:.0f} ms")
                print(f"  /api/health meanwhile: {len(h)} answers, slowest {h.max():.0f} ms, "
                      f"median {np.median(h):.0f} ms (the longest the server was held up)")
    finally:
        proc.send_signal(2)
        proc.wait(10)
    return 0


def _ok(http) -> bool:
    try:
        return http.get("/api/health").status_code == 200
    except httpx.HTTPError:
        return False


if __name__ == "__main__":
    sys.exit(main())
