"""Issue 21, item 9: smaller defects found by a hostile pass, each replayed against the
real server (``harness.running_server``, or ``orientlab serve`` in a subprocess) with a
real HTTP or TCP client. Each failed before its fix."""

from __future__ import annotations

import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
import websockets
import websockets.sync.client

from app.server.net import lan_ipv4_all
from harness import free_port, log_lines, running_server, wait_for

TOKEN = "presenter-token-for-hostile-tests"
AUTH = {"X-Orientlab-Token": TOKEN}
STILL = "alekodu_activityrecognition/sensorLog_20221024T182616_standstill.txt"
FAST = "alekodu_activityrecognition/sensorLog_20221024T183036_walking_pocket_long_time.txt"


def _real_log(shared_dir: Path, name: str) -> Path:
    p = shared_dir / "data" / "sensorfusion-app" / name
    if not p.is_file():
        pytest.skip(f"{p} not present")
    return p


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    rec = tmp_path_factory.mktemp("recordings")
    shared = Path(__file__).resolve().parents[2].parent / "shared"
    src = shared / "data" / "sensorfusion-app" / STILL
    if src.is_file():
        shutil.copy(src, rec / "still.txt")
    with running_server(open_access=False, token=TOKEN, recordings=rec,
                        preset_dir=tmp_path_factory.mktemp("presets")) as s:
        yield s


@pytest.fixture()
def api(srv):
    with httpx.Client(base_url=srv.url, timeout=30.0, headers=AUTH) as c:
        yield c


# ---------------------------------------------------------------- (a) calibrate types

def test_calibrate_with_a_bad_stretch_is_422_naming_the_field(srv, api):
    """``from_s: "abc"`` or ``[1]`` was a 500 with a traceback (and the connection was
    reset): a 422 naming the field, and the server keeps its connection."""
    if not (srv.settings.recordings / "still.txt").is_file():
        pytest.skip("the real log is not present")
    for key, bad in (("from_s", "abc"), ("from_s", [1]), ("from_s", {"a": 1}),
                     ("from_s", True), ("to_s", "abc"), ("to_s", [1]), ("from_s", "1e400")):
        r = api.post("/api/calibrate", json={"recording": "still", key: bad})
        assert r.status_code == 422, (key, bad, r.status_code, r.text[:300])
        d = r.json()["detail"][0]
        assert key in d["loc"], (key, bad, d)
        assert "Traceback" not in r.text
    r = api.post("/api/calibrate", json={"recording": 5})
    assert r.status_code == 422 and "recording" in r.json()["detail"][0]["loc"], r.text[:300]
    # a good request still works on the same client (the connection was not reset)
    r = api.post("/api/calibrate", json={"recording": "still", "from_s": 0, "to_s": 5.0})
    assert r.status_code == 200, r.text[:300]


# ---------------------------------------------------------------- (b) recording name

def test_a_recording_name_with_a_trailing_newline_is_refused(srv, api):
    """``"x\\n"`` passed the name check (``$`` matches before a trailing newline)."""
    from app.toolkit.recording import RecordingError, check_name
    for bad in ("x\n", "still\n", "a\r\n"):
        with pytest.raises(RecordingError):
            check_name(bad)
    r = api.post("/api/recordings/start", json={"name": "x\n"})
    assert r.status_code in (409, 422), r.text[:300]
    if r.status_code == 409:     # no stream: the name must still be what is refused first
        pytest.fail(f"name not checked first: {r.text[:300]}")
    assert "name" in r.json()["detail"][0]["loc"]
    assert api.get("/api/recordings/still%0A/log").status_code in (404, 422)


# ---------------------------------------------------------------- (c) injection direction

def test_a_huge_injection_direction_is_not_a_zero_vector(srv, api):
    """``[1e308]*3`` overflowed to a zero vector and was accepted."""
    from app.toolkit.inject import InjectError, parse_request
    d = parse_request({"kind": "magnet", "strength_uT": 50, "direction": [1e308] * 3,
                       "seconds": 1})
    assert math.isclose(math.hypot(*d.direction), 1.0, rel_tol=1e-9), d.direction
    assert all(math.isclose(v, 1 / math.sqrt(3), rel_tol=1e-9) for v in d.direction)
    for bad in ([0, 0, 0], [1e-300] * 3, [math.inf, 0, 0], [1, 2], "up-ish"):
        with pytest.raises(InjectError):
            parse_request({"kind": "magnet", "strength_uT": 50, "direction": bad, "seconds": 1})
    r = api.post("/api/inject", json={"kind": "magnet", "strength_uT": 50,
                                      "direction": [1e308] * 3, "seconds": 0.5})
    if r.status_code == 200:
        act = r.json()
        dirs = [a["direction"] for a in act.get("active", [])] if isinstance(act, dict) else []
        for v in dirs:
            assert math.isclose(math.hypot(*v), 1.0, rel_tol=1e-6), v
    else:
        assert r.status_code in (409, 422), r.text[:300]


# ---------------------------------------------------------------- (d) SIGINT while streaming

def test_sigint_during_a_full_speed_stream_exits_cleanly(tmp_path, shared_dir):
    """Ctrl-C while a phone streams as fast as TCP carries printed a CancelledError
    traceback: exit 0, no traceback, and no hang (15 s at most; how fast: health_latency.py)."""
    lines = log_lines(_real_log(shared_dir, FAST))
    data = ("\n".join(lines) + "\n").encode()
    port, vport, pport = free_port(), free_port(), free_port()
    exe = Path(sys.executable).with_name("orientlab")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "app"]
    proc = subprocess.Popen(cmd + ["serve", "--host", "127.0.0.1", "--port", str(port),
                                   "--viewer-port", str(vport), "--phone-port", str(pport),
                                   "--source", "none", "--recordings", str(tmp_path / "rec"),
                                   "--presets-dir", str(tmp_path / "presets")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    stop = threading.Event()
    sent = [0]

    def stream():
        while not stop.is_set():
            try:
                with socket.create_connection(("127.0.0.1", pport), timeout=5) as s:
                    while not stop.is_set():
                        s.sendall(data)
                        sent[0] += len(data)
            except OSError:
                time.sleep(0.1)

    th = None
    try:
        wait_for(lambda: _answers(port) or proc.poll() is not None, timeout=300,
                 what="orientlab serve")
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        th = threading.Thread(target=stream, daemon=True)
        th.start()
        wait_for(lambda: _phone_streaming(port), timeout=300, what="the phone stream")   # compiling first?
        time.sleep(2.0)
        assert sent[0] > 1_000_000          # full speed: megabytes
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f"did not stop within 15 s after SIGINT: {err[-3000:]}")
        took = time.monotonic() - t0
    finally:
        stop.set()
        if th is not None:
            th.join(10)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert "Traceback" not in err and "CancelledError" not in err, err[-4000:]
    assert proc.returncode == 0, (proc.returncode, err[-3000:])
    print(f"Ctrl-C: the server ended {took:.1f} s after SIGINT")   # the figure: health_latency.py


def _answers(port: int) -> bool:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def _phone_streaming(port: int) -> bool:
    try:
        st = httpx.get(f"http://127.0.0.1:{port}/api/state", timeout=5).json()
        return st["source"] == "phone" and st["counts"]["samples"] > 1000
    except (httpx.HTTPError, KeyError, ValueError):
        return False


# ---------------------------------------------------------------- (e) Origin and Host

def test_an_origin_on_another_port_of_the_same_host_is_refused(srv, api):
    """Another port of the same host (another app on this PC, a student's server on
    the same machine) was accepted as this server's page."""
    port = srv.settings.port
    for origin in (f"http://127.0.0.1:{port + 1}", "http://127.0.0.1", f"https://127.0.0.1:{port}",
                   f"http://localhost:{port + 7}", f"http://evil.example:{port}"):
        r = api.post("/api/reset", headers={"Origin": origin})
        assert r.status_code == 403, (origin, r.status_code)
    url = f"ws://127.0.0.1:{port}/ws/state"
    with pytest.raises(websockets.exceptions.InvalidStatus):
        with websockets.sync.client.connect(url, origin=f"http://127.0.0.1:{port + 1}",
                                            open_timeout=10):
            pass


def test_dns_rebinding_host_is_refused(srv, api):
    """DNS rebinding: a page on evil.example (resolved to this PC) sends its own name
    as Host and Origin; it matched itself and was accepted."""
    port = srv.settings.port
    for host in (f"evil.example:{port}", "evil.example", f"attacker.test:{port}"):
        r = api.post("/api/reset", headers={"Host": host, "Origin": f"http://{host}"})
        assert r.status_code == 403, (host, r.status_code)
        r = api.post("/api/reset", headers={"Host": host})       # no Origin (a script)
        assert r.status_code == 403, (host, r.status_code)
    # watching stays free (GET), whatever the Host
    assert api.get("/api/health", headers={"Host": f"evil.example:{port}"}).status_code == 200


def test_the_presenters_page_still_works_from_every_name_of_this_pc(srv, api):
    """The presenter's page on http://localhost:PORT, http://127.0.0.1:PORT and
    http://<LAN IP>:PORT."""
    port = srv.settings.port
    hosts = ["localhost", "127.0.0.1"] + [ip for ip in lan_ipv4_all() if ip != "127.0.0.1"][:2]
    for h in hosts:
        r = api.post("/api/reset", headers={"Host": f"{h}:{port}", "Origin": f"http://{h}:{port}"})
        assert r.status_code == 200, (h, r.status_code, r.text[:200])
    r = api.post("/api/reset")                                    # a script: no Origin
    assert r.status_code == 200
    url = f"ws://127.0.0.1:{port}/ws/state"
    with websockets.sync.client.connect(url, origin=f"http://localhost:{port}",
                                        open_timeout=10) as ws:
        assert ws.recv(timeout=10)


# ---------------------------------------------------------------- (f) errors echo the input

def test_error_messages_do_not_echo_long_input(srv, api):
    """FastAPI's 422 ``input`` and messages repeating a long user string."""
    junk = "B" * 5000
    cases = [
        ("POST", "/api/inject", {"kind": junk}),
        ("POST", "/api/inject", {"kind": "magnet", "strength_uT": 50, "seconds": 1,
                                 "direction": junk}),
        ("POST", "/api/inject", {"kind": "magnet", "strength_uT": 50, "seconds": 1,
                                 "direction": [junk, 1, 2]}),
        ("POST", "/api/inject", {"kind": "magnet", junk: 1}),
        ("POST", "/api/calibrate", {junk: 1}),
        ("POST", "/api/recordings/start", {"name": junk}),
        ("PATCH", "/api/params", {"primary": junk}),
        ("POST", "/api/presets/save", {"name": junk}),
        ("POST", "/api/presets/load", {"name": junk}),
    ]
    for method, path, body in cases:
        r = api.request(method, path, json=body)
        assert 400 <= r.status_code < 500, (path, r.status_code, r.text[:300])
        assert "B" * 100 not in r.text, (path, r.text[:400])
        assert '"input"' not in r.text, (path, r.text[:400])
    # an invalid JSON body: FastAPI's own 422 (json_invalid) carried the input
    r = api.post("/api/inject", content=b'{"kind": "' + b"C" * 5000 + b'"',
                 headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and "C" * 100 not in r.text and '"input"' not in r.text, r.text[:300]
    # what the server lists is not input: a short name's closing quote opened a "value"
    # and the known names after it were cut ("(known: robust, lab, comp...' (83+ characters)")
    for name in ("robust-with-a-long-variant-name", "lab-with-another-long-variant-name"):
        assert api.post("/api/estimators", json={"name": name, "base": name.split("-")[0]}).status_code == 200
    for missing in ("nope", "nope-"):          # (a quote after "-" opened a "value" too)
        r = api.delete(f"/api/estimators/{missing}")
        assert r.status_code == 404 and "lab-with-another-long-variant-name" in r.text, r.text
    r = api.delete("/api/estimators/" + "B" * 3000)
    assert r.status_code in (404, 422) and "B" * 100 not in r.text, r.text[:300]
    for name in ("robust-with-a-long-variant-name", "lab-with-another-long-variant-name"):
        assert api.delete(f"/api/estimators/{name}").status_code == 200


def test_a_storm_of_primary_changes_settles():
    """Concurrent PATCHes of the primary (a presenter's script, a double click): the page's
    menu is set after each, and viser calls its callback for that too. It posted the value
    back, so two changes in flight swapped the primary for ever (thousands of parameter
    events a second in every recording). After the storm nothing may change."""
    import asyncio
    with running_server() as s:
        changes = []
        s.engine.param_listeners.append(lambda: changes.append(time.monotonic()))

        async def storm():
            async with httpx.AsyncClient(base_url=s.url, timeout=30,
                                         limits=httpx.Limits(max_connections=10)) as c:
                await asyncio.gather(*([c.post("/api/reset") for _ in range(20)]
                                       + [c.patch("/api/params", json={"primary": ("lab", "robust")[i % 2]})
                                          for i in range(20)]))
        asyncio.run(storm())
        time.sleep(2.0)
        n = len(changes)
        time.sleep(2.0)
        assert len(changes) == n, f"{len(changes) - n} parameter changes in 2 s after the storm"
        assert n <= 45            # the 40 requests' own changes, not more
        primary = httpx.get(s.url + "/api/params").json()["primary"]
        time.sleep(0.5)
        assert httpx.get(s.url + "/api/params").json()["primary"] == primary
