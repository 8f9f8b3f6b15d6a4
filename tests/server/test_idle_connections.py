"""Issue 21, item 3: one laptop holding idle TCP connections must not lock the class out.

Attack (replayed against the real server, ``harness.running_server``): connections
opened to a port and held without sending a byte, re-opened as soon as the server closes
them, from several loopback source addresses (127.0.0.2 ... 127.0.0.9, as a laptop on
the LAN with a few addresses). Before the fix, ~210 of them on the HTTP port made the
page and the API unreachable for everyone (250 idle: 0 of 139 health requests
answered in 30 s).

The attacker runs in a subprocess (:data:`HOLDER`), as another machine would: its
reconnect loop does not share the server's GIL. The presenter (this process, from
127.0.0.1) polls ``/api/health`` on a keep-alive connection and ``/`` on a new connection
every ~0.2 s; at least 95 % of the requests must be answered.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import httpx
import pytest
import websockets.sync.client

from harness import (ATTACK_SOURCES as SOURCES, Phone, log_lines, poll_presenter, raise_nofile,
                     running_server, sources_usable, wait_for)

IDLE = 250               # idle connections held
HOLD_S = 30.0            # for this long

# The attacker: hold N connections that send nothing, re-open each as soon as the
# server closes it, for D seconds; print what happened as one JSON line. Bounded: it
# ends after D s (and the test kills it after D + 30 s), and closes every socket.
HOLDER = r"""
import json, resource, selectors, socket, sys, time
port, n, dur = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
ips = sys.argv[4].split(",")
soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
need = n + 64
if soft != resource.RLIM_INFINITY and soft < need:
    resource.setrlimit(resource.RLIMIT_NOFILE, (need if hard == resource.RLIM_INFINITY
                                                else min(need, hard), hard))
sel = selectors.DefaultSelector()
st = {"opened": 0, "closed_by_server": 0, "connect_failed": 0, "min_open": n, "max_open": 0}
born = {}
lifetimes = []

def open_one(i):
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        s.bind((ips[i % len(ips)], 0))
        s.settimeout(1.0)
        s.connect(("127.0.0.1", port))
        s.setblocking(False)
    except OSError:
        st["connect_failed"] += 1
        s.close()
        return False
    sel.register(s, selectors.EVENT_READ, i)
    born[s] = time.monotonic()
    st["opened"] += 1
    return True

t_end = time.monotonic() + dur
for i in range(n):
    open_one(i)
missing = []
last_sample = 0.0
while time.monotonic() < t_end:
    for key, _ in sel.select(timeout=0.05):
        s = key.fileobj
        try:
            data = s.recv(4096)
        except (BlockingIOError, InterruptedError):
            continue
        except OSError:
            data = b""
        if data:
            continue          # (nothing is expected: the holder never asks)
        sel.unregister(s)
        lifetimes.append(time.monotonic() - born.pop(s))
        s.close()
        st["closed_by_server"] += 1
        missing.append(key.data)
    still = []
    for i in missing:
        if time.monotonic() >= t_end or not open_one(i):
            still.append(i)
    missing = still
    now = time.monotonic()
    if now - last_sample > 0.5 and now > t_end - dur + 1.0:
        k = len(sel.get_map())
        st["min_open"] = min(st["min_open"], k)
        st["max_open"] = max(st["max_open"], k)
        last_sample = now
for key in list(sel.get_map().values()):
    key.fileobj.close()
lifetimes.sort()
st["median_lifetime_s"] = lifetimes[len(lifetimes) // 2] if lifetimes else None
print(json.dumps(st), flush=True)
"""


class Holder:
    """The attacker's subprocess (see :data:`HOLDER`)."""

    def __init__(self, port: int, n: int = IDLE, seconds: float = HOLD_S):
        self.seconds = seconds
        self.proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(port), str(n),
                                      str(seconds), ",".join(SOURCES)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def result(self) -> dict:
        try:
            out, err = self.proc.communicate(timeout=self.seconds + 30.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate()
        assert self.proc.returncode == 0, err[-2000:]
        return json.loads(out.strip().splitlines()[-1])

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    sources_usable()
    raise_nofile(IDLE + 512)
    with running_server(preset_dir=tmp_path_factory.mktemp("presets")) as s:
        yield s


def test_idle_connections_do_not_lock_the_presenter_out(srv):
    """250 idle connections held on the HTTP port and re-opened for 30 s: health and
    the page still answer >= 95 % of the presenter's requests."""
    holder = Holder(srv.settings.port)
    try:
        time.sleep(1.0)                        # let the attacker fill the table first
        polled = poll_presenter(srv, HOLD_S - 2.0)
        held = holder.result()
    finally:
        holder.stop()
    print("presenter:", polled, "attacker:", held)
    assert held["opened"] >= IDLE and held["max_open"] >= 200, held   # the attack happened
    assert polled["ok"] >= 0.95 * polled["total"], (polled, held)
    # a connection that sends nothing does not stay: closed within seconds
    assert held["closed_by_server"] > 0 and held["median_lifetime_s"] < 6.0, held
    with httpx.Client(base_url=srv.url, timeout=5.0) as c:
        assert c.get("/api/health").json()["status"] == "ok"


def _closed(s: socket.socket, timeout: float) -> bool:
    s.settimeout(timeout)
    try:
        return s.recv(1) == b""
    except (ConnectionResetError, ConnectionAbortedError):
        return True
    except socket.timeout:
        return False


def test_a_silent_connection_is_closed_quickly(srv):
    """A connection that sends nothing is closed after ``first_byte_timeout_s`` (a few
    seconds), long before the header timeout; one that sends its request is served."""
    limit = srv.settings.first_byte_timeout_s
    assert limit <= 3.0 < srv.settings.header_timeout_s
    t0 = time.monotonic()
    with socket.create_connection(("127.0.0.1", srv.settings.port), timeout=10) as s:
        assert _closed(s, srv.settings.header_timeout_s)
    took = time.monotonic() - t0
    # not before its limit, and by it rather than by the (longer) header timeout (waited
    # for up to that long: a loaded machine may close it late, by the right timer still)
    assert limit - 0.5 <= took < srv.settings.header_timeout_s, took
    with socket.create_connection(("127.0.0.1", srv.settings.port), timeout=10) as s:
        time.sleep(0.2)
        s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        s.settimeout(10)
        assert s.recv(200).startswith(b"HTTP/1.1 200")


def test_connections_per_address_are_capped(srv):
    """One address holds at most ``max_connections_per_ip`` connections; another
    address is still served meanwhile."""
    cap = srv.settings.max_connections_per_ip
    assert 8 <= cap <= 64
    socks = []
    try:
        for _ in range(cap + 20):
            s = socket.socket()
            s.bind(("127.0.0.5", 0))
            s.settimeout(10)
            s.connect(("127.0.0.1", srv.settings.port))
            socks.append(s)
        time.sleep(0.5)
        closed = sum(_closed(s, 0.05) for s in socks)
        assert closed >= 20, closed          # no more than the cap stays open
        with httpx.Client(base_url=srv.url, timeout=5.0) as c:
            assert c.get("/api/health").status_code == 200
    finally:
        for s in socks:
            s.close()


def test_idle_connections_on_the_phone_port_do_not_keep_a_phone_out(srv, shared_dir):
    """The same attack on the phone receiver's port: a real phone still gets in."""
    path = shared_dir / "data" / "sensorfusion-app" / \
        "alekodu_activityrecognition/sensorLog_20221024T182616_standstill.txt"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    lines = log_lines(path)[:400]
    holder = Holder(srv.phone_port, seconds=12.0)
    try:
        time.sleep(2.0)
        with httpx.Client(base_url=srv.url, timeout=10.0) as api:
            n0 = api.get("/api/state").json()["counts"].get("total_sessions", 0)
            with Phone(srv.phone_port) as ph:
                ph.send_lines(lines)
                wait_for(lambda: api.get("/api/state").json()["counts"]["total_sessions"] > n0,
                         timeout=10.0, what="the phone session")
        held = holder.result()
    finally:
        holder.stop()
    print("attacker:", held)
    assert held["opened"] >= IDLE, held
    assert held["median_lifetime_s"] is not None and held["median_lifetime_s"] < 6.0, held


def test_idle_connections_on_the_viewer_port_do_not_keep_a_viewer_out(srv):
    """The same attack on viser's port: a viewer's WebSocket and the page still open
    (viser's server has no connection cap, so idle sockets do not lock it; websockets'
    ``open_timeout`` (10 s) closes them)."""
    holder = Holder(srv.viewer_port, seconds=15.0)
    ok = total = 0
    try:
        time.sleep(1.0)
        t_end = time.monotonic() + 10.0
        while time.monotonic() < t_end:
            total += 1
            try:
                with websockets.sync.client.connect(
                        f"ws://127.0.0.1:{srv.viewer_port}/",
                        subprotocols=["viser-v" + __import__("viser").__version__],
                        open_timeout=3.0):
                    ok += 1
            except Exception:
                pass
            time.sleep(0.5)
        held = holder.result()
    finally:
        holder.stop()
    print("viewer:", ok, "/", total, "attacker:", held)
    assert held["opened"] >= IDLE, held
    assert ok >= 0.95 * total, (ok, total)
