"""Run the real dashboard on free loopback ports, and play a phone: for tests and benchmarks.

``with running_server(source="none") as srv:`` starts uvicorn (with viser, the phone
receiver and the engine) in a thread on 127.0.0.1; ``srv.url``, ``srv.phone_port``,
``srv.viewer_port`` and ``srv.app`` (the FastAPI app, its ``state`` holds the engine)
are available; leaving the block stops everything. :class:`Phone` is a TCP client that
sends lines as the Sensor Fusion app does; :func:`play_paced` plays a log through it at the
log's own pace. :func:`sim_rows` gives the simulator's samples as the rows a phone sends.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import random
import resource
import shutil
import socket
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

from collections import Counter

import httpx
import pytest

from app.server.run import make_server
from app.sources.sensorfusion import MalformedLine, decode_lines, parse_line
from app.server.settings import Settings

START_TIMEOUT_S = 300.0   # the first start may compile the estimators (numba)
START_TRIES = 3           # a server that did not start is started again on fresh ports (running_server)

# ---- the browser (Debian's chromium driven by Playwright; no browser download)
CHROMIUM = next((p for p in ("/usr/bin/chromium", shutil.which("chromium") or "",
                             shutil.which("chromium-browser") or "") if p and Path(p).exists()), None)
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
ARTIFACTS = Path(__file__).resolve().parent / "artifacts"   # screenshots of failed browser tests


def browser_test() -> list:
    """Every browser test module's marks (``pytestmark = browser_test()``): marked ``browser``,
    skipped with the reason when there is no Chromium. (pytest imported here: the benchmarks
    use this module without the test tools.)"""
    import pytest
    return [pytest.mark.browser,
            pytest.mark.skipif(CHROMIUM is None, reason="NO CHROMIUM FOUND: the browser test is "
                               "SKIPPED (install Debian's chromium to run it)")]


def click(page, locator, timeout: float = 60_000) -> None:
    """A mouse click at the element's centre: Playwright's own click waits for the
    element to be "stable", which a viewer re-rendering at a few FPS on a loaded machine
    may never give it."""
    locator.wait_for(state="visible", timeout=timeout)
    locator.scroll_into_view_if_needed(timeout=timeout)
    bb = locator.bounding_box()
    page.mouse.click(bb["x"] + bb["width"] / 2, bb["y"] + bb["height"] / 2)


def hide_notices(frame) -> None:
    """Hide viser's notices (the software-WebGL one covers the 3D view in headless
    Chromium), e.g. for a picture."""
    frame.locator("body").evaluate(
        "b => { const s = document.createElement('style');"
        " s.textContent = '.mantine-Notifications-root { display: none !important; }';"
        " b.appendChild(s); }")


def console_errors(page) -> list[str]:
    """The errors in the console of ``page`` and its frames (the viewer's among them) from now
    on, filled as they come: a script's uncaught exception, an error it logs, a resource
    the server refused."""
    errors: list[str] = []
    page.on("console", lambda m: errors.append(f"{m.text} ({m.location.get('url', '')})")
            if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(f"uncaught: {e}"))
    return errors


@contextlib.contextmanager
def chromium_page(url: str, profile: str | Path, size: tuple[int, int] = (1600, 900),
                  viewer: bool = True, timeout_ms: int = 60_000,
                  console_errors_ok: tuple[str, ...] = ()):
    """A page of Debian's headless Chromium (Playwright, no browser download; its profile in
    the folder ``profile``) opened on ``url``, at ``size``; with ``viewer``, once the
    embedded 3D view (``iframe#viewer``) draws. Yields ``(page, frame)``: the page and the
    viewer's frame locator. The browser is closed on leaving, whatever happened.
    An error in the console of the page or of its viewer (a script's exception, an error it
    logs, a resource refused) fails the test when it leaves without an exception of its own,
    unless the error's text holds one of ``console_errors_ok``: ``page.console_errors`` lists
    them meanwhile. (The caller has checked ``CHROMIUM`` and imported Playwright with
    ``importorskip``.)"""
    from playwright.sync_api import sync_playwright
    with sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            str(profile), executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS,
            viewport={"width": size[0], "height": size[1]})
        try:
            page = ctx.new_page()
            page.console_errors = errors = console_errors(page)
            page.goto(url)
            frame = page.frame_locator("iframe#viewer")
            if viewer:
                frame.locator("canvas").first.wait_for(state="visible", timeout=timeout_ms)
            yield page, frame
            unexpected = [e for e in errors if not any(ok in e for ok in console_errors_ok)]
            assert not unexpected, f"errors in the browser's console: {unexpected}"
        finally:
            ctx.close()


def free_port() -> int:
    return free_ports(1)[0]


def _ephemeral_low() -> int:
    """The lowest port the system hands out to a socket bound to port 0 or a client's
    connection (Linux's ``ip_local_port_range``; 32768 where it cannot be read)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_ports(n: int) -> list[int]:
    """``n`` distinct free loopback ports, chosen at random BELOW the system's ephemeral
    range: a port is chosen here and bound by the server a moment later, and in between
    nothing else of the run can be handed it (a client's connection, a socket bound to
    port 0, another test's fake phone all take ephemeral ports). Every socket is held until
    all are chosen."""
    hi = _ephemeral_low()
    lo = max(1024, hi - 12000)
    rng = random.SystemRandom()
    socks: list[socket.socket] = []
    try:
        for _ in range(50 * n):
            if len(socks) == n:
                break
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            try:
                # no room below the range (it starts at 1024 here): the system's choice
                s.bind(("127.0.0.1", rng.randrange(lo, hi) if hi - lo >= 1000 else 0))
            except OSError:
                s.close()
                continue
            socks.append(s)
        if len(socks) < n:
            raise RuntimeError(f"no {n} free loopback ports between {lo} and {hi}")
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def wait_for(pred: Callable[[], object], timeout: float = 30.0, interval: float = 0.05,
             what: str = "condition"):
    """Poll ``pred`` until it returns something truthy; that value, or TimeoutError."""
    deadline = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(interval)


@dataclasses.dataclass
class RunningServer:
    settings: Settings
    server: object
    thread: threading.Thread

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.settings.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.settings.port}"

    @property
    def app(self):
        return self.server.config.app

    @property
    def engine(self):
        return self.app.state.engine

    @property
    def phone_port(self) -> int:
        return self.app.state.sensorfusion.port

    @property
    def viewer_port(self) -> int:
        return self.app.state.viewer.get_port()


@contextlib.contextmanager
def running_server(**overrides) -> Iterator[RunningServer]:
    """The dashboard on free loopback ports (``source="none"`` unless told).

    ``open_access=True`` unless told (tests of other concerns need no token); tests of
    the access rules pass ``open_access=False`` (and ``token=...``).

    The ports come from :func:`free_ports`, below the ephemeral range, where nothing of the
    run is handed them between choosing and binding; should something outside the run take
    one (a service started on it meanwhile) and the server not start, it is started again
    on fresh ports, at most START_TRIES times in all (only when the ports were chosen here)."""
    chosen_here = not any(k in overrides for k in ("port", "viewer_port", "phone_port"))
    for _ in range(START_TRIES if chosen_here else 1):
        port, viewer_port, phone_port = free_ports(3)
        kw = dict(host="127.0.0.1", port=port, viewer_host="127.0.0.1",
                  viewer_port=viewer_port, phone_host="127.0.0.1", phone_port=phone_port,
                  source="none", verbose=False, open_access=True)
        kw.update(overrides)
        settings = Settings(**kw)
        server = make_server(settings)
        thread = threading.Thread(target=server.run, name="uvicorn", daemon=True)
        thread.start()
        wait_for(lambda: server.started or not thread.is_alive(), START_TIMEOUT_S, what="server start")
        if server.started:
            break
        server.should_exit = True
        thread.join(10.0)
    else:
        raise RuntimeError("the dashboard did not start (see the log above)")
    try:
        yield RunningServer(settings, server, thread)
    finally:
        server.should_exit = True
        thread.join(10.0)


class Phone:
    """A TCP client that plays the Sensor Fusion app (it only sends)."""

    def __init__(self, port: int, host: str = "127.0.0.1"):
        self.sock = socket.create_connection((host, port), timeout=10.0)
        # sendall's timeout bounds a whole send: a long log on a loaded machine (the
        # server reads only as fast as its filters keep up) takes longer than a connect
        self.sock.settimeout(60.0)

    def send_lines(self, lines, end: str = "\n") -> None:
        data = "".join(ln + end for ln in lines).encode()
        self.sock.sendall(data)

    def send_bytes(self, data: bytes) -> None:
        self.sock.sendall(data)

    def closed_by_server(self, timeout: float = 10.0) -> bool:
        """True once the server has closed this connection (EOF or reset)."""
        self.sock.settimeout(timeout)
        try:
            while True:
                chunk = self.sock.recv(4096)
                if not chunk:
                    return True
        except (ConnectionResetError, BrokenPipeError):
            return True
        except socket.timeout:
            return False

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()

    def __enter__(self) -> "Phone":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def play_paced(port: int, lines: list[str], stop: threading.Event) -> None:
    """Play the Sensor Fusion app: send ``lines`` to the phone port at the pace of their
    timestamps (each sensor tag on its own clock, as the app stamps them), then keep the
    connection open until ``stop`` is set (run it in a thread)."""
    first: dict[str, int] = {}
    due, prev = [], 0.0
    for ln in lines:
        try:
            s = parse_line(ln)
            prev = max(0.0, (s.time_ms - first.setdefault(s.tag, s.time_ms)) / 1000.0)
        except MalformedLine:
            pass
        due.append(prev)
    with Phone(port) as ph:
        t0, i = time.monotonic(), 0
        while i < len(lines) and not stop.is_set():
            now = time.monotonic() - t0
            j = i
            while j < len(lines) and due[j] <= now:
                j += 1
            if j > i:
                ph.send_lines(lines[i:j])
                i = j
            time.sleep(0.02)
        stop.wait()


def log_lines(path: str | Path) -> list[str]:
    """The lines of an app log (text, without line ends)."""
    return Path(path).read_text(errors="replace").splitlines()


def feed_lines(core, session, lines) -> list:
    """Lines of the Sensor Fusion app's format into a live core as the TCP source feeds
    them: decoded, the malformed ones counted in the session; the samples released."""
    bad: Counter = Counter()
    samples = decode_lines(lines, bad)
    for reason, n in bad.items():
        session.count_malformed(reason, n)
    return core.feed(session, samples)


def sim_rows(scenes, seed=0, config=None):
    """The simulator's samples as rows (one per sample, as a phone sends them, time from 0)
    and the truth at each row."""
    from app.sources.ordering import samples_to_rows
    from app.sources.samples import Sample
    from app.sources.simulate import simulate
    res = simulate(scenes, seed=seed, config=config)
    rows = samples_to_rows([Sample(m, tag, tuple(v)) for m, tag, v in res.samples])
    truth = res.truth_at_ms(rows.t * 1000.0)
    rows.t = rows.t - rows.t[0]
    return rows, truth


# ---- a magnet stuck on the simulator's turning phone (tests/estimators/test_hard_iron.py,
# benchmarks/hard_iron.py): turns about each axis, a 0.5 °/s gyroscope bias about z the field
# must correct; from MAGNET_ON_S to MAGNET_OFF_S a constant offset in the *sensor* frame
MAGNET_TURNS = ("turn_x", "turn_y", "turn_z") * 7        # 126 s of turning
MAGNET_ON_S, MAGNET_OFF_S = 30.0, 100.0
MAGNET_OFFSET_UT = (18.0, -12.0, 20.0)                    # |o| = 29.5 µT


def magnet_rows(size_ut=None, scenes=MAGNET_TURNS, seed=3):
    """``sim_rows`` of the turning phone with a magnet on it from MAGNET_ON_S to MAGNET_OFF_S:
    MAGNET_OFFSET_UT, or that direction scaled to ``size_ut`` µT; 0: no magnet."""
    import numpy as np
    from app.sources.simulate import SimConfig
    rows, truth = sim_rows(scenes, seed=seed, config=SimConfig(gyr_bias=(0.0, 0.0, np.radians(0.5))))
    offset = np.asarray(MAGNET_OFFSET_UT)
    if size_ut is not None:
        offset = offset * (size_ut / np.linalg.norm(offset))
    on = (rows.t >= MAGNET_ON_S) & (rows.t < MAGNET_OFF_S) & np.isfinite(rows.mag[:, 0])
    rows.mag[on] += offset
    return rows, truth


# ---- a phone that lies on a laptop when the stream starts (tests/estimators/test_field_reference.py,
# benchmarks/first_field.py): lying still 8 s, then turned about each axis; until LAPTOP_LIFT_S a
# field fixed in the *world* frame is added (the laptop's), then the room's field alone
LAPTOP_SCENES = ("still", "still") + MAGNET_TURNS[:12]   # 8 s still, 72 s of turning
LAPTOP_LIFT_S = 10.0
LAPTOP_FIELD_UT = (30.0, 0.0, -20.0)                     # with the earth's 50 µT: 75 µT


def laptop_rows(field_ut=LAPTOP_FIELD_UT, lift_s=LAPTOP_LIFT_S, seed=5):
    """``sim_rows`` of the phone picked up from a laptop at ``lift_s`` (it starts turning at
    8 s, on the laptop still): ``field_ut`` (world frame, µT) added to the field until then."""
    import numpy as np
    from app.quaternion import rotate_inv_many
    rows, truth = sim_rows(LAPTOP_SCENES, seed=seed)
    on = (rows.t < lift_s) & np.isfinite(rows.mag[:, 0])
    rows.mag[on] += rotate_inv_many(truth[on], np.tile(np.asarray(field_ut, float), (int(on.sum()), 1)))
    return rows, truth


# ---- the 3D viewer's WebSocket, as a script (or a browser tab) speaks it

def viser_messages(raw: bytes) -> list[dict]:
    """The messages of one frame viser sends a client (two lengths, zstd-compressed msgpack,
    then binary buffers), as dicts with their ``type``."""
    import msgspec
    import zstandard
    size, clen = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(raw[16:16 + clen], max_output_size=size)
    return msgspec.msgpack.decode(inner)["messages"]


class ViserClient:
    """A bare viser client (what a 20-line script does): viser's WebSocket protocol, blocking."""

    def __init__(self, port: int, token: str | None = None, origin: str | None = None):
        import viser
        import websockets.sync.client
        from viser import _messages as vm
        url = f"ws://127.0.0.1:{port}/" + (f"?token={token}" if token else "")
        self.ws = websockets.sync.client.connect(
            url, subprotocols=[f"viser-v{viser.__version__}"], origin=origin,
            open_timeout=10, max_size=None)
        self.send(vm.ViewerCameraMessage(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, 1.0),
                                         fov=1.0, near=0.01, far=100.0, image_height=400,
                                         image_width=600, look_at=(0.0, 0.0, 0.0),
                                         up_direction=(0.0, 0.0, 1.0)))

    def send(self, msg) -> None:
        import msgspec
        import websockets
        try:
            self.ws.send(msgspec.msgpack.encode(msg.as_serializable_dict()))
        except websockets.exceptions.ConnectionClosed:
            pass   # closed by the server: closed() says so

    def click(self, handle) -> None:
        """What a browser sends when a GUI button (or a checkbox) is clicked."""
        from viser import _messages as vm
        self.send(vm.GuiUpdateMessage(handle._impl.uuid, {"value": True}))

    def closed(self, timeout: float = 10.0) -> bool:
        import websockets
        deadline = time.monotonic() + timeout
        try:
            while time.monotonic() < deadline:
                self.ws.recv(timeout=deadline - time.monotonic())
        except websockets.exceptions.ConnectionClosed:
            return True
        except TimeoutError:
            return False
        return False

    def receive(self, timeout: float) -> tuple[int, list[dict]] | None:
        """The next frame the server sends: its size in bytes and its messages; None when
        nothing came within ``timeout`` s (``ConnectionClosed`` once the server closed)."""
        try:
            raw = self.ws.recv(timeout=timeout)
        except TimeoutError:
            return None
        return len(raw), viser_messages(raw)

    def gui_updates(self, uuid: str, seconds: float) -> list[dict]:
        """Every GuiUpdateMessage's ``updates`` for ``uuid`` this client receives in the next
        ``seconds``."""
        out, deadline = [], time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            if (frame := self.receive(left)) is None:
                break
            out += [m["updates"] for m in frame[1]
                    if m.get("type") == "GuiUpdateMessage" and m.get("uuid") == uuid]
        return out

    def close(self) -> None:
        self.ws.close()


# ---- a phone with a gyroscope scale error turned whole turns between rests (orientlab
# gyro-scale: tests/toolkit/test_gyro_scale.py, tests/server/test_toolkit_server.py)
FS = 100.0
G_WORLD = (0.0, 0.0, 9.81)
M_WORLD = (0.0, 20.0, -45.0)
SCALE = (0.015, -0.010, 0.020)       # the simulated gyroscope reads (1 + s) × the turn
BIAS = (0.03, -0.02, 0.04)
TURN = 2.0 * math.pi
# (body axis, angle, seconds): whole turns about x and y while the phone lies flat, a quarter
# turn about x that stands it on its long edge, whole turns about z (now level), and back
ALL_AXES = [(0, 2 * TURN, 4.0), (1, 2 * TURN, 4.0), (0, TURN / 4, 1.5), (2, 2 * TURN, 4.0),
            (2, -2 * TURN, 4.0), (0, -TURN / 4, 1.5), (0, -2 * TURN, 4.0), (1, -2 * TURN, 4.0)]
FLAT = [(0, 2 * TURN, 4.0), (2, 3 * TURN, 4.0), (1, 2 * TURN, 4.0), (2, -3 * TURN, 4.0),
        (0, -2 * TURN, 4.0), (1, -2 * TURN, 4.0)]


def turns_session(moves, scale=SCALE, rest_s=2.5, seed=1):
    """A phone lying still, then each move (a smooth turn about a body axis) followed by a rest:
    rows of (t, gyr, acc, mag) at FS with every sensor, and the true attitude."""
    import numpy as np
    from app import quaternion as qm
    rng = np.random.default_rng(seed)
    rates = [np.zeros((int(rest_s * FS), 3))]
    for axis, angle, secs in moves:
        n = int(secs * FS)
        u = (np.arange(n) + 0.5) / n
        w = np.zeros((n, 3))
        w[:, axis] = angle / secs * (1.0 - np.cos(2.0 * np.pi * u))     # integrates to the angle
        rates += [w, np.zeros((int(rest_s * FS), 3))]
    w = np.concatenate(rates)
    q = qm.integrate_many((1.0, 0.0, 0.0, 0.0), w / FS)
    t = np.arange(len(w)) / FS + 0.01
    gyr = w * (1.0 + np.asarray(scale)) + np.asarray(BIAS) + 0.003 * rng.standard_normal(w.shape)
    acc = qm.rotate_inv_many(q, np.tile(G_WORLD, (len(w), 1))) + 0.03 * rng.standard_normal(w.shape)
    mag = qm.rotate_inv_many(q, np.tile(M_WORLD, (len(w), 1))) + 0.3 * rng.standard_normal(w.shape)
    return t, gyr, acc, mag, q


def turns_log_lines(t, gyr, acc, mag) -> list[str]:
    """The rows as the Sensor Fusion app's log lines, one sensor per line (ms stamps)."""
    from app.sources.sensorfusion import format_line
    return [format_line(round(1000.0 * tk, 3), tag, v) for k, tk in enumerate(t)
            for tag, v in (("ACC", acc[k]), ("GYR", gyr[k]), ("MAG", mag[k]))]


def view_xy(p, position, look_at, fov, aspect):
    """Where the world point ``p`` shows in a view of a camera at ``position`` looking at
    ``look_at`` (up +z): (x, y) as shares of the view's width and height from its top-left."""
    import numpy as np
    f = np.asarray(look_at, float) - np.asarray(position, float)
    f /= np.linalg.norm(f)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    d = np.asarray(p, float) - np.asarray(position, float)
    z = d @ f
    t = np.tan(fov / 2.0)
    return 0.5 + 0.5 * (d @ right) / (z * t * aspect), 0.5 - 0.5 * (d @ up) / (z * t)


# ------------------------------------------------------------- attacks on the HTTP port

ATTACK_SOURCES = [f"127.0.0.{i}" for i in range(2, 10)]   # a laptop with a few addresses
PRESENTER_POLL_S = 0.2    # the presenter's poll interval (poll_presenter)


def raise_nofile(need: int) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < need:
        new = need if hard == resource.RLIM_INFINITY else min(need, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < need:
        pytest.skip(f"RLIMIT_NOFILE {soft} < {need}: cannot hold the connections")


def sources_usable() -> None:
    """127.0.0.2-9 are loopback addresses on Linux; elsewhere skip."""
    try:
        with socket.socket() as s:
            s.bind((ATTACK_SOURCES[-1], 0))
    except OSError:
        pytest.skip("cannot bind 127.0.0.x source addresses on this system")


def poll_presenter(srv, seconds: float) -> dict:
    """The presenter's requests for ``seconds``: health on a keep-alive connection, the
    page on a new connection each time (each given 10 s: served or not is the question
    here, how fast is benchmarks/health_latency.py's)."""
    ok = total = 0
    worst = 0.0
    failures: dict[str, int] = {}
    t_end = time.monotonic() + seconds
    with httpx.Client(base_url=srv.url, timeout=10.0) as keep:
        while time.monotonic() < t_end:
            t0 = time.monotonic()
            for path, client in (("/api/health", keep), ("/", None)):
                total += 1
                t1 = time.monotonic()
                try:
                    if client is None:
                        with httpx.Client(base_url=srv.url, timeout=10.0) as fresh:
                            r = fresh.get(path)
                    else:
                        r = client.get(path)
                    if r.status_code == 200:
                        ok += 1
                    else:
                        failures[str(r.status_code)] = failures.get(str(r.status_code), 0) + 1
                except httpx.HTTPError as e:
                    failures[type(e).__name__] = failures.get(type(e).__name__, 0) + 1
                worst = max(worst, time.monotonic() - t1)
            time.sleep(max(0.0, PRESENTER_POLL_S - (time.monotonic() - t0)))
    return {"ok": ok, "total": total, "worst_s": round(worst, 3), "failures": failures}
