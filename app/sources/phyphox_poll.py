"""phyphox remote access: the PC polls the phone (``shared/protocols/phyphox.md``, A).

:class:`PhyphoxPoller` works with any experiment that records the accelerometer
(gyroscope, magnetometer and attitude when present), whatever its buffer names: it
reads them from ``/config``. Like the official web client it keeps exactly one request
in flight, on a new connection each (``Connection: close``), polls ``/get``
incrementally (``t=T&x=T|t...``) 30 ms after a reply while measuring and 250 ms when
idle, and starts the measurement once per connection if it is not running.

Typical use (in the server's event loop)::

    poller = PhyphoxPoller("http://192.168.1.5:8080", on_samples, on_status)
    task = asyncio.create_task(poller.run())     # never raises; retries by itself
    ...
    poller.status()                              # JSON-safe, for the UI
    poller.stop(); await task                    # returns within a fraction of a second
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import time
from collections import Counter, deque
from typing import Any, Callable
from urllib.parse import quote, urlsplit

from app.sources.phyphox import (COMPONENTS, SENSOR_TAGS, PhyphoxError, Sample,
                                 session_key, buffers_to_samples, time_reference)

log = logging.getLogger(__name__)

MAX_REPLY = 64 * 1024 * 1024      # bytes; a /get "full" of a long unlimited buffer is big
RATE_HISTORY = 200                # sample times per tag for the rate estimate


class Unreachable(Exception):
    """The phone did not answer (the message says why, in words)."""


def parse_base_url(url: str) -> tuple[str, int]:
    """(host, port) of a phone address ``http://HOST[:PORT][/]`` (``HOST[:PORT]``
    alone is taken as http). Anything else (https, a path, a query, user info) is a
    ValueError saying what is wrong."""
    if not isinstance(url, str) or not url.strip():
        raise ValueError("phone address is empty; expected http://PHONE-IP:PORT")
    u = url.strip()
    if "://" not in u:
        u = "http://" + u
    try:
        p = urlsplit(u)
        port = p.port
    except ValueError as exc:
        raise ValueError(f"phone address {url[:100]!r} is not valid ({exc}); "
                         "expected http://PHONE-IP:PORT") from None
    if p.scheme != "http":
        raise ValueError(f"phone address must start with http:// (phyphox remote access "
                         f"has no https), got {url[:100]!r}")
    if not p.hostname:
        raise ValueError(f"phone address {url[:100]!r} has no host; "
                         "expected http://PHONE-IP:PORT")
    if p.username or p.password or p.query or p.fragment or p.path not in ("", "/"):
        raise ValueError(f"phone address {url[:100]!r} must be only http://HOST:PORT "
                         "(no path, query or user name)")
    return p.hostname, (port if port is not None else 80)


def _reason(exc: BaseException, timeout: float) -> str:
    if isinstance(exc, (asyncio.TimeoutError, TimeoutError)):
        return f"no reply within {timeout:g} s"
    if isinstance(exc, ConnectionRefusedError):
        return ("connection refused (is remote access on, and the port right? A locked "
                "screen or another app in front stops phyphox's server on Android: keep it on)")
    if isinstance(exc, socket.gaierror):
        return "unknown host name"
    if isinstance(exc, (ConnectionResetError, asyncio.IncompleteReadError, BrokenPipeError)):
        return "connection closed by the phone"
    if isinstance(exc, OSError):
        msg = exc.strerror or str(exc) or type(exc).__name__
        return msg[:120].lower()
    return str(exc)[:120] or type(exc).__name__


def _dechunk(body: bytes) -> bytes:
    out = bytearray()
    pos = 0
    while True:
        end = body.find(b"\r\n", pos)
        if end < 0:
            raise Unreachable("truncated chunked reply")
        size = int(body[pos:end].split(b";")[0].strip() or b"0", 16)
        if size == 0:
            return bytes(out)
        out += body[end + 2:end + 2 + size]
        pos = end + 2 + size + 2


def _content_end(head: bytes, body_start: int) -> int | None:
    """Where a reply with this head ends (Content-Length, not chunked), else None
    (read to the end of the connection): a server that keeps the connection open
    despite ``Connection: close`` does not make the request wait for its timeout."""
    low = head.lower()
    if b"transfer-encoding:" in low and b"chunked" in low:
        return None
    for ln in low.split(b"\r\n")[1:]:
        k, _, v = ln.partition(b":")
        if k.strip() == b"content-length":
            try:
                return body_start + int(v.strip())
            except ValueError:
                return None
    return None


async def http_get(host: str, port: int, target: str, timeout: float) -> tuple[int, bytes]:
    """One GET on a new connection (``Connection: close``): (status, body). Raises
    :class:`Unreachable` (with the reason in words) when there is no usable reply."""
    async def go() -> bytes:
        reader, writer = await asyncio.open_connection(host, port)
        try:
            hosthdr = f"[{host}]" if ":" in host else host
            writer.write(f"GET {target} HTTP/1.1\r\nHost: {hosthdr}:{port}\r\n"
                         "Connection: close\r\nAccept: application/json\r\n"
                         "User-Agent: orientlab\r\n\r\n".encode("ascii"))
            await writer.drain()
            buf = bytearray()
            need: int | None = None       # total length once Content-Length is known
            while need is None or len(buf) < need:
                chunk = await reader.read(65536)
                if not chunk:
                    break                 # the server closed: the reply is complete
                buf += chunk
                if len(buf) > MAX_REPLY:
                    raise Unreachable(f"reply larger than {MAX_REPLY >> 20} MB "
                                      "(clear the experiment on the phone)")
                if need is None:
                    end = buf.find(b"\r\n\r\n")
                    if end >= 0:
                        need = _content_end(bytes(buf[:end]), end + 4)
            return bytes(buf)
        finally:
            writer.close()
            try:
                await writer.wait_closed()
            except (OSError, asyncio.CancelledError):
                pass
    try:
        raw = await asyncio.wait_for(go(), timeout)
    except Unreachable:
        raise
    except (OSError, asyncio.TimeoutError, asyncio.IncompleteReadError) as exc:
        raise Unreachable(_reason(exc, timeout)) from None
    head, sep, body = raw.partition(b"\r\n\r\n")
    if not sep:
        raise Unreachable("no HTTP reply" if not raw else "incomplete HTTP reply")
    lines = head.split(b"\r\n")
    try:
        status = int(lines[0].split()[1])
    except (IndexError, ValueError):
        raise Unreachable("not an HTTP reply") from None
    headers = {}
    for ln in lines[1:]:
        k, _, v = ln.partition(b":")
        headers[k.strip().lower()] = v.strip()
    if b"chunked" in headers.get(b"transfer-encoding", b"").lower():
        try:
            body = _dechunk(body)
        except ValueError:
            raise Unreachable("bad chunked reply") from None
    elif b"content-length" in headers:
        try:
            n = int(headers[b"content-length"])
        except ValueError:
            raise Unreachable("bad Content-Length") from None
        if len(body) < n:
            raise Unreachable("reply cut short")
        body = body[:n]
    return status, body


def parse_config(cfg: Any) -> tuple[dict[str, dict[str, str]], dict[str, int], list[str]]:
    """From a ``/config`` reply: per tag (ACC/GYR/MAG/ORI) the buffer name of each
    component (``t``, ``x``, ``y``, ``z``, ``abs``), the buffer sizes, and the tags
    missing (in words). A sensor is usable with t, x, y, z (ORI: abs optional)."""
    if not isinstance(cfg, dict):
        raise PhyphoxError("bad_config", "/config is not a JSON object")
    sizes: dict[str, int] = {}
    for b in cfg.get("buffers") or []:
        if isinstance(b, dict) and isinstance(b.get("name"), str):
            try:
                sizes[b["name"]] = int(b.get("size") or 0)
            except (TypeError, ValueError):
                sizes[b["name"]] = 0
    found: dict[str, dict[str, str]] = {}
    for inp in cfg.get("inputs") or []:
        if not isinstance(inp, dict):
            continue
        tag = SENSOR_TAGS.get(inp.get("source"))
        if tag is None or tag in found:
            continue
        outs = inp.get("outputs")
        comp: dict[str, str] = {}
        items = outs.items() if isinstance(outs, dict) else (
            kv for o in (outs or []) if isinstance(o, dict) for kv in o.items())
        for k, v in items:
            if isinstance(k, str) and isinstance(v, str) and v:
                comp.setdefault(k, v)
        need = ("t", "x", "y", "z")
        if all(c in comp for c in need):
            found[tag] = {c: comp[c] for c in (*need, "abs") if c in comp}
    missing = [s for s, tag in SENSOR_TAGS.items() if tag not in found]
    return found, sizes, missing


class _Stopped(Exception):
    pass


class _SessionChanged(Exception):
    pass


class PhyphoxPoller:
    """Poll one phone's phyphox remote access (see the module doc).

    ``on_samples(samples, new_session)`` gets every new sample once, time-sorted per
    reply (``new_session`` True on the first batch of each session: the consumer
    resets); ``on_status(dict)`` (optional) gets :meth:`status` whenever the state
    changes. Both are called from the loop running :meth:`run`. ``auto_start``: send
    ``/control?cmd=start`` when the experiment is not measuring (once per session and
    connection, so a user's stop on the phone is respected)."""

    def __init__(self, base_url: str,
                 on_samples: Callable[[list[Sample], bool], None],
                 on_status: Callable[[dict], None] | None = None, *,
                 auto_start: bool = True,
                 poll_s: float = 0.03, idle_s: float = 0.25,
                 timeout_s: float = 3.0, get_timeout_s: float = 10.0,
                 retry_min_s: float = 0.25, retry_max_s: float = 3.0):
        self.host, self.port = parse_base_url(base_url)
        self.url = f"http://{self.host}:{self.port}" if ":" not in self.host \
            else f"http://[{self.host}]:{self.port}"
        self.on_samples = on_samples
        self.on_status = on_status
        self.auto_start = auto_start
        self.poll_s, self.idle_s = poll_s, idle_s
        self.timeout_s, self.get_timeout_s = timeout_s, get_timeout_s
        self.retry_min_s, self.retry_max_s = retry_min_s, retry_max_s
        self._stop_flag = False
        self._stop_ev: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.state = "idle"
        self.detail = ""
        self.last_error: str | None = None
        self.session: str | None = None
        self.measuring: bool | None = None
        self.title: str | None = None
        self.model: str | None = None
        self.sensors: dict[str, dict[str, str]] = {}
        self.missing: list[str] = []
        self.sizes: dict[str, int] = {}
        self.counts: Counter = Counter()          # reasons (truncated, null, gap, ...)
        self.samples_by_tag: Counter = Counter()
        self.requests = 0
        self.in_flight = 0
        self.max_in_flight = 0
        self.sessions = 0
        self.unix_base_s: float | None = None
        self.last_data_time: float | None = None  # experiment time of the newest sample (s)
        self.last_data_wall: float | None = None  # PC time it arrived
        self._times: dict[str, deque[float]] = {}
        self._threshold: dict[str, float | None] = {}
        self._new_session = True
        self._start_sent = False
        self._time_key: float | None = None      # first START of /time (clear check)
        self._time_read = 0.0
        self.time_check_s = 2.0

    # ------------------------------------------------------------ control
    def flush(self) -> list:
        """What it holds when its stream ends: nothing (every poll's samples go at once)."""
        return []

    def stop(self) -> None:
        """End :meth:`run` promptly (callable from any thread)."""
        self._stop_flag = True
        loop, ev = self._loop, self._stop_ev
        if loop is None or ev is None:
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            ev.set()
        else:
            try:
                loop.call_soon_threadsafe(ev.set)
            except RuntimeError:      # loop closed
                pass

    def lacking(self) -> str:
        """The sensors the experiment on the phone does not record, in words ('' if none):
        phyphox's own experiments record one sensor each."""
        if not self.missing:
            return ""
        words = {"magnetic_field": "magnetometer", "attitude": "attitude (the phone's own estimate)"}
        return (f"this experiment records no {', '.join(words.get(m, m) for m in self.missing)}: "
                "orientlab's experiment (the QR code) records them all")

    def silent_hint(self) -> str | None:
        """Why no samples come, when the phone says (its measurement paused), else None."""
        if self.state == "not measuring":     # the phone answers, and says so
            return "the measurement is paused on the phone: press ▶ in phyphox"
        return None

    def status(self) -> dict:
        """JSON-safe state for the UI."""
        rates = {}
        for tag, q in self._times.items():
            if len(q) > 1 and q[-1] > q[0]:
                rates[tag] = round((len(q) - 1) / (q[-1] - q[0]), 1)
        return {
            "url": self.url, "state": self.state, "detail": self.detail,
            "status": f"{self.state}: {self.detail}" if self.detail else self.state,
            "title": self.title, "device_model": self.model, "session": self.session,
            "measuring": self.measuring,
            "sensors": {TAG_NAME[t]: dict(b) for t, b in self.sensors.items()},
            "missing": list(self.missing),
            "samples": dict(self.samples_by_tag), "rate_hz": rates,
            "counts": dict(self.counts),
            "gaps": self.counts.get("gap", 0), "truncated": self.counts.get("truncated", 0),
            "last_data_time": self.last_data_time,
            "last_data_age_s": (None if self.last_data_wall is None
                                else round(time.time() - self.last_data_wall, 3)),
            "last_error": self.last_error, "requests": self.requests,
            "max_in_flight": self.max_in_flight, "sessions": self.sessions,
            "unix_base_s": self.unix_base_s,
        }

    def _set_state(self, state: str, detail: str = "") -> None:
        if (state, detail) == (self.state, self.detail):
            return
        self.state, self.detail = state, detail
        text = f"phyphox {self.url}: {state}" + (f": {detail}" if detail else "")
        if state in ("unreachable", "error", "no accelerometer"):
            self.last_error = f"{state}: {detail}" if detail else state
            log.warning(text)
        else:
            if state == "measuring":    # data flows again: an old error is no news
                self.last_error = None
            log.info(text)
        if self.on_status is not None:
            try:
                self.on_status(self.status())
            except Exception as exc:                  # the consumer's bug, not ours
                log.warning("phyphox on_status callback failed: %s: %s",
                            type(exc).__name__, str(exc)[:120])

    # ------------------------------------------------------------ plumbing
    async def _until_stop(self, aw):
        if self._stop_flag:
            if asyncio.iscoroutine(aw):
                aw.close()
            raise _Stopped
        task = asyncio.ensure_future(aw)
        stopper = asyncio.ensure_future(self._stop_ev.wait())
        try:
            done, _ = await asyncio.wait({task, stopper},
                                         return_when=asyncio.FIRST_COMPLETED)
        finally:
            stopper.cancel()
        if task in done:
            return task.result()
        task.cancel()
        try:
            await task
        except BaseException:
            pass
        raise _Stopped

    async def _sleep(self, s: float) -> None:
        if self._stop_flag:
            raise _Stopped
        try:
            await asyncio.wait_for(self._stop_ev.wait(), s)
        except asyncio.TimeoutError:
            return
        raise _Stopped

    async def _get(self, target: str, timeout: float) -> tuple[int, bytes]:
        self.in_flight += 1
        self.max_in_flight = max(self.max_in_flight, self.in_flight)
        self.requests += 1
        try:
            return await self._until_stop(http_get(self.host, self.port, target, timeout))
        finally:
            self.in_flight -= 1

    async def _get_json(self, target: str, timeout: float | None = None) -> Any:
        status, body = await self._get(target, timeout or self.timeout_s)
        if status != 200:
            raise PhyphoxError("http_status", f"HTTP {status} for {target.split('?')[0]}")
        try:
            return json.loads(body)
        except (UnicodeDecodeError, ValueError):
            raise PhyphoxError("bad_reply", f"{target.split('?')[0]} did not answer "
                                            "JSON (is this phyphox?)") from None

    # ------------------------------------------------------------ run
    async def run(self) -> None:
        """Poll until :meth:`stop`; never raises (errors are states, with retries)."""
        self._loop = asyncio.get_running_loop()
        self._stop_ev = asyncio.Event()
        if self._stop_flag:
            self._stop_ev.set()
        delay = self.retry_min_s
        try:
            while not self._stop_flag:
                try:
                    await self._connection()
                    delay = self.retry_min_s
                except _SessionChanged:
                    delay = self.retry_min_s
                    continue
                except Unreachable as exc:
                    self._set_state("unreachable", str(exc))
                    self._start_sent = False     # Android stops measuring when it goes away
                    await self._sleep(delay)
                    delay = min(self.retry_max_s, delay * 2)
                except PhyphoxError as exc:
                    if exc.reason == "no_accelerometer":
                        self._set_state("no accelerometer", str(exc).split(": ", 1)[-1])
                    else:
                        self._set_state("error", str(exc))
                    await self._sleep(max(1.0, delay))
                    delay = min(self.retry_max_s, delay * 2)
                except _Stopped:
                    raise
                except Exception as exc:          # never a traceback out of run()
                    self._set_state("error", f"{type(exc).__name__}: {str(exc)[:120]}")
                    await self._sleep(max(1.0, delay))
                    delay = min(self.retry_max_s, delay * 2)
        except _Stopped:
            pass
        self._set_state("stopped")

    async def _connection(self) -> None:
        """Read /config (and /meta), then poll until the session changes."""
        if self.state not in ("unreachable",):
            self._set_state("connecting")
        cfg = await self._get_json("/config")
        sensors, sizes, missing = parse_config(cfg)
        self.title = str(cfg.get("title"))[:200] if cfg.get("title") is not None else None
        self.sensors, self.sizes, self.missing = sensors, sizes, missing
        if "ACC" not in sensors:
            raise PhyphoxError("no_accelerometer",
                               "the experiment on the phone records no accelerometer "
                               f"(found: {', '.join(TAG_NAME[t] for t in sensors) or 'none'})")
        if missing:
            log.info("phyphox %s: experiment %r lacks %s", self.url, self.title,
                     ", ".join(missing))
        if self.model is None:
            try:
                meta = await self._get_json("/meta")
                if isinstance(meta, dict) and isinstance(meta.get("deviceModel"), str):
                    self.model = meta["deviceModel"][:100]
            except PhyphoxError:
                pass                              # before app 1.1.8: no /meta
        await self._poll_loop()

    def _query(self) -> str:
        parts = []
        for tag, bufs in self.sensors.items():
            thr = self._threshold.get(tag)
            tq = quote(bufs["t"], safe="")
            if thr is None:
                parts.append(f"{tq}=full")
                val = "full"
            else:
                T = repr(max(0.0, thr))
                parts.append(f"{tq}={T}")
                val = f"{T}%7C{tq}"
            for c in COMPONENTS[tag]:
                if c in bufs:
                    parts.append(f"{quote(bufs[c], safe='')}={val}")
        return "/get?" + "&".join(parts)

    async def _read_time(self) -> None:
        """/time: the Unix time base, and a clear noticed by its first START changing
        (iOS answers a partial request after a clear as partial, not "full")."""
        self._time_read = time.monotonic()
        try:
            ev = await self._get_json("/time")
        except PhyphoxError:
            return                                # before app 1.1.8
        ref = time_reference(ev)
        if ref is not None:
            self.unix_base_s = ref[0] - ref[1]
        key = session_key(ev)
        if key is not None:
            if self._time_key is not None and abs(key - self._time_key) > 1e-3:
                self._cleared()
            self._time_key = key

    async def _poll_loop(self) -> None:
        first = True
        while True:
            requested = dict(self._threshold)
            reply = await self._get_json(self._query(), self.get_timeout_s)
            if not isinstance(reply, dict) or not isinstance(reply.get("buffer"), dict):
                raise PhyphoxError("bad_reply", "/get reply has no buffer object")
            st = reply.get("status") if isinstance(reply.get("status"), dict) else {}
            session = st.get("session")
            session = None if session is None else str(session)[:64]
            if session != self.session:
                if self.session is not None:
                    # the phone restarted its server: new experiment, app switched...
                    self.counts["session_changes"] += 1
                    self.session = session
                    self._reset_session()
                    log.info("phyphox %s: new session %s", self.url, session)
                    raise _SessionChanged
                self.session = session
            measuring = bool(st.get("measuring"))
            self.measuring = measuring
            if measuring:       # measuring already (the user started it): a later stop is
                self._start_sent = True      # the user's too, and no start is sent
            if first:
                first = False
                await self._read_time()
            self._take(reply["buffer"], requested)
            if not measuring and self.auto_start and not self._start_sent:
                self._start_sent = True
                self._set_state("starting")
                res = await self._get_json("/control?cmd=start")
                if not (isinstance(res, dict) and res.get("result") is True):
                    self.last_error = "the phone refused to start the measurement"
                await self._read_time()
                await self._sleep(self.poll_s)
                continue
            self._set_state("measuring" if measuring else "not measuring", self.lacking())
            await self._sleep(self.poll_s if measuring else self.idle_s)
            if measuring and time.monotonic() - self._time_read > self.time_check_s:
                await self._read_time()
                await self._sleep(self.poll_s)

    def _reset_session(self) -> None:
        self._threshold = {}
        self._times = {}
        self._new_session = True
        self._start_sent = False
        self._time_key = None
        self.sessions += 1

    def _cleared(self) -> None:
        """The phone's buffers were cleared (experiment time restarts at 0): request
        everything again; the next samples start a new session."""
        self.counts["cleared"] += 1
        self._threshold = {}
        self._times = {}
        self._new_session = True
        self._time_key = None
        self.sessions += 1

    def _take(self, buffers: dict, requested: dict[str, float | None]) -> None:
        """Samples of one /get reply; advances the thresholds."""
        out: list[Sample] = []
        replies: dict[str, tuple[list, list[list], bool]] = {}
        for tag, bufs in self.sensors.items():
            comps = [c for c in COMPONENTS[tag] if c in bufs]
            entries = [buffers.get(bufs[c]) for c in ("t", *comps)]
            if not all(isinstance(e, dict) and isinstance(e.get("buffer"), list)
                       for e in entries):
                continue
            arrays = [e["buffer"] for e in entries]
            size = entries[0].get("size")
            if isinstance(size, int) and size > 0:
                for i, a in enumerate(arrays):
                    if len(a) > size:
                        arrays[i] = a[-size:]
            full = entries[0].get("updateMode") == "full"
            replies[tag] = (arrays[0], arrays[1:], full)
        # a "full" reply to a partial request: the phone's buffers were cleared
        # (experiment time restarted): a new session of data
        # (Android answers "full" to a partial request only after a clear)
        cleared = any(full and requested.get(tag) is not None
                      for tag, (_, _, full) in replies.items())
        if cleared:
            self._cleared()
        for tag, (t, comps, full) in replies.items():
            conv = buffers_to_samples(tag, t, comps, self.counts)
            thr = self._threshold.get(tag)
            samples = conv.samples
            if thr is not None:
                n0 = len(samples)
                samples = [s for s in samples if s.time_ms > thr * 1000.0]
                self.counts["duplicate"] += n0 - len(samples)
            if conv.last_t is not None and (thr is None or conv.last_t > thr):
                self._threshold[tag] = conv.last_t
            if samples:
                q = self._times.setdefault(tag, deque(maxlen=RATE_HISTORY))
                if q:
                    dt = samples[0].time_ms / 1000.0 - q[-1]
                    period = (q[-1] - q[0]) / (len(q) - 1) if len(q) > 1 else 0.0
                    if period > 0 and dt > max(0.1, 10 * period):
                        self.counts["gap"] += 1
                for s in samples:
                    q.append(s.time_ms / 1000.0)
                self.samples_by_tag[tag] += len(samples)
                out.extend(samples)
        if out:
            out.sort(key=lambda s: s.time_ms)
            self.last_data_time = max(s.time_ms for s in out) / 1000.0
            self.last_data_wall = time.time()
            new = self._new_session
            self._new_session = False
            self.on_samples(out, new)


TAG_NAME = {v: k for k, v in SENSOR_TAGS.items()}
