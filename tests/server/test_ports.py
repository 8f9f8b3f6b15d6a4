"""A taken port, any of the three, gives one line naming it and its option, a non-zero
exit status and no traceback: ``orientlab serve`` run as a user runs it, against a
port really held by a listening socket on the loopback interface."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from harness import free_port

OPTIONS = ("--port", "--viewer-port", "--phone-port")


def serve_cli(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "app.cli", "serve", *args],
                          capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


def one_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one line on stderr, got:\n{stderr}"
    assert "Traceback" not in stderr
    return lines[0]


@pytest.mark.parametrize("option", OPTIONS)
def test_taken_port_is_one_line_naming_it(option):
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        ports = {opt: str(free_port()) for opt in OPTIONS}
        ports[option] = str(taken)
        r = serve_cli("--host", "127.0.0.1", "--source", "none",
                      *[x for opt in OPTIONS for x in (opt, ports[opt])])
        # the holder still owns the port: nothing of ours took it
        assert holder.getsockname()[1] == taken
    assert r.returncode == 1
    line = one_line(r.stderr)
    assert line == (f"orientlab serve: port {taken} ({option}) is already in use; "
                    f"choose another with {option} N")
    assert r.stdout == ""


def test_same_port_twice_is_refused():
    p = str(free_port())
    r = serve_cli("--host", "127.0.0.1", "--source", "none", "--port", p,
                  "--viewer-port", p, "--phone-port", str(free_port()))
    assert r.returncode == 1
    line = one_line(r.stderr)
    assert f"--port and --viewer-port are both {p}" in line


def test_out_of_range_port_is_refused():
    r = serve_cli("--host", "127.0.0.1", "--source", "none", "--port", str(free_port()),
                  "--viewer-port", str(free_port()), "--phone-port", "70000")
    assert r.returncode == 1
    assert "port 70000 (--phone-port) is not a TCP port" in one_line(r.stderr)


def test_check_ports_passes_free_ports_and_any_port():
    from app.server.run import check_ports
    from app.server.settings import Settings
    check_ports(Settings(host="127.0.0.1", port=free_port(), viewer_port=0, phone_port=free_port(),
                         phone_host="127.0.0.1"))


def test_the_tests_ports_are_free_distinct_and_below_the_ephemeral_range():
    """The harness chooses a server's ports below the range the system hands out to
    clients and to sockets bound to port 0, so none of the run's own sockets can take one
    between its choice and the server's bind; a chosen port binds and listens."""
    from harness import _ephemeral_low, free_ports

    lo = _ephemeral_low()
    if lo - 1024 < 1000:
        pytest.skip(f"the ephemeral range starts at {lo}: no room below it, the system chooses")
    for _ in range(20):
        ports = free_ports(3)
        assert len(set(ports)) == 3
        assert all(1024 <= p < lo for p in ports), (ports, lo)
    with socket.socket() as s:
        s.bind(("127.0.0.1", ports[0]))
        s.listen()
        client = socket.create_connection(("127.0.0.1", ports[0]), timeout=5)
        assert client.getsockname()[1] >= lo      # what the run's clients are handed
        client.close()


def _listening(port: int) -> set[str]:
    """The local addresses (hex, as /proc/net/tcp* write them) listening on ``port``."""
    out = set()
    for name in ("tcp", "tcp6"):
        path = Path("/proc/net") / name
        if not path.is_file():
            continue
        for line in path.read_text().splitlines()[1:]:
            f = line.split()
            addr, p = f[1].rsplit(":", 1)
            if f[3] == "0A" and int(p, 16) == port:
                out.add(addr)
    return out


@pytest.mark.skipif(not Path("/proc/net/tcp").is_file(), reason="Linux's /proc/net/tcp needed")
def test_host_loopback_binds_every_port_on_loopback_only():
    """``--host 127.0.0.1`` is "this PC only": the Sensor Fusion app's TCP port too (it was
    bound on every interface, open to the room while the page was not)."""
    ports = {opt: free_port() for opt in OPTIONS}
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "serve", "--host", "127.0.0.1",
                             "--source", "none", *[x for o, p in ports.items() for x in (o, str(p))]],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            stdin=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not all(_listening(p) for p in ports.values()):
            assert proc.poll() is None, proc.stdout.read()
            time.sleep(0.2)
        for opt, port in ports.items():
            assert _listening(port) == {"0100007F"}, (opt, _listening(port))
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)


def test_a_source_that_is_no_app_log_is_refused(tmp_path):
    """``serve --source FILE`` with a CSV (or npz): it was replayed as lines of an app log,
    an empty 0 s log looping for ever while /api/health said ok. Now one line, exit 2."""
    csv_file = tmp_path / "semi.csv"
    csv_file.write_text("t;ax;ay;az\n0;0;0;9.81\n")
    r = serve_cli("--host", "127.0.0.1", "--source", str(csv_file))
    assert r.returncode == 2, r.stderr
    line = one_line(r.stderr)
    assert str(csv_file) in line and ("unknown format" in line or "app log" in line), line
    good = tmp_path / "real.csv"
    good.write_text("t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n0,0,0,0,0,0,9.81\n")
    r = serve_cli("--host", "127.0.0.1", "--source", str(good))
    assert r.returncode == 2 and "is a csv file" in one_line(r.stderr), r.stderr
