"""A fake phyphox phone for tests: a real HTTP server on a loopback port that behaves
like phyphox's remote access (``shared/protocols/phyphox.md``, A).

It serves ``/config`` for an experiment with the buffer names given, ``/get`` with the
real single/full/partial/``T|ref`` semantics (threshold nudged up by 1e-7·T, unknown
buffers skipped, unknown ref 400, bad threshold 500, "full" after a clear), ``status``
(session, measuring), ``/control?cmd=start|stop|clear``, ``/time`` and ``/meta``.

Data come from arrays (e.g. a tyrex trial); what is visible grows with wall time while
measuring (``speed`` experiment seconds per second) and/or stepwise (:meth:`advance`).
Switches: ``ios`` (one buffer of a sensor one element longer in a reply, full-precision
numbers, partial requests after a clear stay partial; otherwise Android's 8-digit
scientific notation), :meth:`new_session`,
:meth:`go_away` / :meth:`come_back` (same port), ``delay_s`` (slow replies).
``max_in_flight`` records the most requests handled at once.
"""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import unquote

import numpy as np


def java_float(v: float) -> str:
    """Android's number format: 8 significant digits, scientific (9.8066502E0)."""
    if v != v or v in (float("inf"), float("-inf")):
        return "null"
    m, e = f"{v:.7E}".split("E")
    return f"{m}E{int(e)}"


def ios_float(v: float) -> str:
    if v != v or v in (float("inf"), float("-inf")):
        return "null"
    return repr(float(v))


class FakeSensor:
    """One phyphox sensor input: ``names`` component -> buffer name (t, x, y, z, abs),
    ``t`` (N,) experiment seconds, ``values`` component -> (N,) array."""

    def __init__(self, source: str, names: dict[str, str], t, values: dict[str, np.ndarray]):
        self.source = source
        self.names = dict(names)
        self.t = np.asarray(t, dtype=float)
        self.values = {c: np.asarray(v, dtype=float) for c, v in values.items()}
        self.lo = 0          # first index still in the buffers (after a clear)

    def column(self, comp: str) -> np.ndarray:
        return self.t if comp == "t" else self.values[comp]


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, *args):   # quiet
        pass

    def do_GET(self):
        fake: FakePhyphox = self.server.fake
        with fake._lock:
            fake._in_flight += 1
            fake.max_in_flight = max(fake.max_in_flight, fake._in_flight)
            fake.requests.append(self.path)
        # "in flight" = from the request to its reply (not the thread's tear-down
        # after it, which a fast client may legitimately overlap with its next one)
        done = False
        try:
            if fake.delay_s:
                time.sleep(fake.delay_s)
            code, body = fake._route(self.path)
            data = body.encode()
            with fake._lock:
                fake._in_flight -= 1
                done = True
            self.send_response(code)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(data)
            self.close_connection = True
        except OSError:
            pass
        finally:
            if not done:
                with fake._lock:
                    fake._in_flight -= 1


class FakePhyphox:
    def __init__(self, sensors: list[FakeSensor], *, title: str = "fake experiment",
                 model: str = "Pixel 7", session: str = "3fa91c", measuring: bool = False,
                 speed: float = 0.0, ios: bool = False, sizes: dict[str, int] | None = None,
                 delay_s: float = 0.0):
        self.sensors = sensors
        self.title, self.model, self.session = title, model, session
        self.speed, self.ios, self.delay_s = speed, ios, delay_s
        self.sizes = dict(sizes or {})
        self.requests: list[str] = []
        self.max_in_flight = 0
        self.starts = 0
        self._in_flight = 0
        self._lock = threading.RLock()
        self._base = 0.0                  # experiment time visible when not measuring
        self._since = 0.0                 # monotonic time measuring (re)started
        self.measuring = False
        self._full_next = False
        self._uneven_turn = 0
        self.events: list[dict] = []
        self._server: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None
        self.port = 0
        if measuring:
            self._start()

    # ---------------------------------------------------------------- server
    def __enter__(self):
        self.serve()
        return self

    def __exit__(self, *exc):
        self.go_away()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def serve(self) -> None:
        srv = ThreadingHTTPServer(("127.0.0.1", self.port), _Handler)
        srv.daemon_threads = True
        srv.fake = self
        self.port = srv.server_address[1]
        self._server = srv
        self._thread = threading.Thread(target=srv.serve_forever,
                                        kwargs={"poll_interval": 0.05}, daemon=True)
        self._thread.start()

    def go_away(self) -> None:
        """The phone leaves (app switched, locked): server closed; Android also stops
        the measurement."""
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
        with self._lock:
            self._stop()

    def come_back(self) -> None:
        """The server restarts on the same port, same session, not measuring."""
        for _ in range(50):
            try:
                self.serve()
                return
            except OSError:
                time.sleep(0.05)
        self.serve()

    # ---------------------------------------------------------------- control
    def horizon(self) -> float:
        with self._lock:
            if self.measuring and self.speed:
                return self._base + (time.monotonic() - self._since) * self.speed
            return self._base

    def advance(self, dt: float) -> None:
        with self._lock:
            self._base += dt

    def _start(self) -> None:
        if not self.measuring:
            self._since = time.monotonic()
            self.measuring = True
            self.starts += 1
            self.events.append({"event": "START", "experimentTime": self._base,
                                "systemTime": time.time()})

    def _stop(self) -> None:
        if self.measuring:
            self._base = self.horizon()
            self.measuring = False
            self.events.append({"event": "PAUSE", "experimentTime": self._base,
                                "systemTime": time.time()})

    def clear(self) -> None:
        """Buffers emptied and experiment time back to 0 (the data arrays play again
        from their start); the next partial request is answered "full"."""
        with self._lock:
            self._base = 0.0
            self._since = time.monotonic()
            for s in self.sensors:
                s.lo = 0
            self.events = [{"event": "START", "experimentTime": 0.0,
                            "systemTime": time.time()}] if self.measuring else []
            self._full_next = True

    def new_session(self, session: str, sensors: list[FakeSensor] | None = None) -> None:
        """A new remote server (new experiment / access re-enabled): new id, buffers
        empty, time from 0, not measuring."""
        with self._lock:
            self.session = session
            self._stop()
            self._base = 0.0
            self.events = []
            if sensors is not None:
                self.sensors = sensors
            for s in self.sensors:
                s.lo = 0

    def total_visible(self) -> int:
        h = self.horizon()
        return sum(int(np.searchsorted(s.t, h, side="right")) - s.lo for s in self.sensors)

    # ---------------------------------------------------------------- routes
    def _route(self, target: str) -> tuple[int, str]:
        path, _, query = target.partition("?")
        with self._lock:
            if path == "/config":
                return 200, json.dumps(self._config())
            if path == "/meta":
                return 200, json.dumps({"version": "1.2.0", "build": "1020099",
                                        "fileFormat": "1.19", "deviceModel": self.model})
            if path == "/time":
                return 200, json.dumps(self.events)
            if path == "/control":
                cmd = dict(p.partition("=")[::2] for p in query.split("&")).get("cmd")
                if cmd == "start":
                    self._start()
                elif cmd == "stop":
                    self._stop()
                elif cmd == "clear":
                    self.clear()
                else:
                    return 200, '{"result": false}'
                return 200, '{"result": true}'
            if path == "/get":
                return self._get(query)
        return 404, '{"error": "not found"}'

    def _config(self) -> dict:
        buffers, inputs = [], []
        for s in self.sensors:
            outs = []
            for comp, name in s.names.items():
                buffers.append({"name": name, "size": self.sizes.get(name, 0)})
                outs.append({comp: name})
            inputs.append({"source": s.source, "outputs": outs})
        return {"crc32": "1a2b3c4d", "title": self.title, "localTitle": self.title,
                "category": "test", "localCategory": "test", "buffers": buffers,
                "inputs": inputs, "export": []}

    def _find(self, name: str):
        for s in self.sensors:
            for comp, n in s.names.items():
                if n == name:
                    return s, comp
        return None

    def _get(self, query: str) -> tuple[int, str]:
        fmt = ios_float if self.ios else java_float
        h = self.horizon()
        params = []
        for part in query.split("&") if query else []:
            k, _, v = part.partition("=")
            params.append((unquote(k), unquote(v)))
        # iOS: which sensor component gets one element more in this reply
        uneven: dict[int, str] = {}
        if self.ios:
            self._uneven_turn += 1
            for i, s in enumerate(self.sensors):
                comps = list(s.names)
                uneven[id(s)] = comps[(self._uneven_turn + i) % len(comps)]
        out = {}
        full_next = self._full_next
        for name, value in params:
            found = self._find(name)
            if found is None:
                continue                                  # unknown buffers are skipped
            s, comp = found
            size = self.sizes.get(name, 0)
            hi = int(np.searchsorted(s.t, h, side="right"))
            lo = s.lo if not size else max(s.lo, hi - size)
            col = s.column(comp)
            extra = (self.ios and uneven.get(id(s)) == comp and hi < len(s.t)
                     and self.measuring)
            if value == "":
                mode, idx = "single", list(range(max(lo, hi - 1), hi))
            elif value == "full" or (full_next and value and (
                    not self.ios or value == "partial")):   # iOS: only literal "partial"
                mode, idx = "full", list(range(lo, hi + (1 if extra else 0)))
            else:
                thr_s, _, ref = value.partition("|")
                try:
                    thr = float(thr_s)
                except ValueError:
                    return 500, '{"error": "bad threshold"}'
                thr += abs(thr) * 1e-7
                if ref:
                    rf = self._find(ref)
                    if rf is None:
                        return 400, '{"error": "unknown ref"}'
                    refcol = rf[0].column(rf[1])
                else:
                    refcol = col
                hi_e = min(hi + (1 if extra else 0), len(col))
                idx = [i for i in range(lo, hi_e) if refcol[i] > thr]
                mode = "partial"
            out[name] = {"size": size, "updateMode": mode,
                         "buffer": [fmt(col[i]) for i in idx]}
        self._full_next = False
        parts = ", ".join(
            f'{json.dumps(n)}: {{"size": {b["size"]}, "updateMode": "{b["updateMode"]}", '
            f'"buffer": [{",".join(b["buffer"])}]}}' for n, b in out.items())
        status = json.dumps({"session": self.session, "measuring": self.measuring,
                             "timedRun": False, "countDown": 0})
        return 200, f'{{"buffer": {{{parts}}}, "status": {status}}}'
