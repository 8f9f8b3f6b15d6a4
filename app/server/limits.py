"""Bounded resources for the HTTP side: what one client can cost the server.

- :class:`BodyLimit` (ASGI middleware): a request body longer than
  ``Settings.max_body_bytes`` (1 MB; a phone's push, ``max_push_bytes``: 16 MB) is
  answered **413** before it is read: at once from
  ``Content-Length``, or as soon as a chunked body passes the limit.
- :func:`install_error_handlers`: a 422 names the field and the reason, never echoes
  the input (FastAPI's default puts the whole body in ``input``); and every 4xx JSON
  answer passes :func:`no_echo` in :class:`BodyLimit` (a message quoting a long value the
  client sent is cut to an excerpt, whoever raised it).
- :func:`guarded_protocol`: uvicorn's HTTP protocol with
  a **first-byte timeout** (``first_byte_timeout_s``, 2.5 s: a connection that has sent
  nothing is closed), a **header timeout** (``header_timeout_s``: a connection that has
  not sent a complete request head in time is closed; slow-loris), a **cap per client
  address** (``max_connections_per_ip``) and a **connection cap** (``max_connections``).
  A connection over a cap takes the place of an idle one (sent nothing yet, then a slow
  request head, then keep-alive), from the address holding the most connections. So
  idle sockets held by one laptop (issue 21: 250 of them locked everyone out) cost that
  laptop its own connections, never the presenter's request. At the connection cap with
  none idle, a newcomer takes a busy connection (WebSocket, trickling body) of an
  address holding at least two more than its own: a few laptops holding open WebSockets
  cannot lock the presenter out either; the presenter's own address (its token seen,
  ``Access.presenter_host``) is never taken from. A request body must come at
  ``min_body_bytes_per_s`` (1000 B/s) or faster, and an answer the client leaves unread
  for ``write_stall_s`` (30 s) is closed. uvicorn's own ``limit_concurrency`` answers 503 only after
  reading a request (and counts idle connections), its ``timeout_keep_alive`` only
  starts after a first response.
- :class:`RateLimitFilter`: the same log line at most ``burst`` times per ``period``
  seconds, then one summary of how many were suppressed.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from typing import Callable

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.requests import ClientDisconnect

log = logging.getLogger("orientlab.limits")


class BodyLimit:
    """ASGI middleware: 413 for a request body over ``max_bytes`` (``paths``: a larger
    cap for the given paths, the phones' pushes); every 4xx JSON answer passed through
    :func:`no_echo` (no input repeated, whoever raised the error)."""

    def __init__(self, app, max_bytes: int, paths: dict[str, int] | None = None):
        self.app = app
        self.default_bytes = int(max_bytes)
        self.paths = {k: int(v) for k, v in (paths or {}).items()}

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        max_bytes = self.paths.get(scope.get("path", ""), self.default_bytes)
        for k, v in scope.get("headers", ()):
            if k == b"content-length":
                try:
                    n = int(v)
                except ValueError:
                    return await _too_large(send, max_bytes, "bad Content-Length")
                if n > max_bytes:
                    return await _too_large(send, max_bytes)
        seen = 0
        refused = False     # 413 sent: whatever the app answers after it is dropped
        held: list = []     # a 4xx JSON answer, held until whole to be cut (no_echo)

        async def send_wrapper(message):
            if refused:
                return
            if message["type"] == "http.response.start" and 400 <= message.get("status", 200) < 500 \
                    and _is_json(message.get("headers", ())):
                held.append(message)
                return
            if held and message["type"] == "http.response.body":
                held.append(message)
                if message.get("more_body", False):
                    return
                start, body = held[0], b"".join(m.get("body", b"") for m in held[1:])
                held.clear()
                body = no_echo(body)
                headers = [(k, v) for k, v in start.get("headers", ()) if k.lower() != b"content-length"]
                headers.append((b"content-length", str(len(body)).encode()))
                await send({**start, "headers": headers})
                await send({"type": "http.response.body", "body": body})
                return
            await send(message)

        async def limited_receive():
            nonlocal seen, refused
            if refused:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > max_bytes:
                    refused = True
                    await _too_large(send, max_bytes)
                    return {"type": "http.disconnect"}   # the app stops reading
            return message

        try:
            await self.app(scope, limited_receive, send_wrapper)
        except ClientDisconnect:
            if not refused:
                raise
            # the 413 is sent; the app stopped reading at the disconnect it was handed:
            # that is the refusal working, not an error to log with a traceback


def _is_json(headers) -> bool:
    return any(k.lower() == b"content-type" and b"json" in v.lower() for k, v in headers)


_OPEN = re.compile(r"(?<!\w)['\"]")       # a quote that can open a value: not after a letter
_RUN = re.compile(r"[^\s'\"]{81,}")        # a long run without a space or a quote
MAX_MSG = 300         # characters of one string in an error answer
MAX_QUOTE = 48        # characters of a long quoted (or unbroken) value kept in a message
LONG_QUOTE = 65       # a quoted value this long is cut


def _cut_quotes(text: str) -> str:
    """A value quoted in a message (``got 'AAAA...'``) cut to an excerpt and its length.
    Quotes are paired from the left: a quote that closes a value never opens the next, so
    the names a message lists after a short quoted one (``'nope-' (known: ...)``) are kept
    whole; a value whose closing quote is missing (a message cut short) runs to the line's
    end."""
    out, i = [], 0
    while True:
        m = _OPEN.search(text, i)
        if m is None:
            out.append(text[i:])
            break
        q, start = m.group(0), m.end()
        end = text.find(q, start)
        nl = text.find("\n", start)
        stop = len(text) if nl < 0 else nl
        close = end if 0 <= end < stop else stop
        v = text[start:close]
        out.append(text[i:m.start()])
        if len(v) >= LONG_QUOTE:
            out.append(f"{q}{v[:MAX_QUOTE]}...{q} ({len(v)}+ characters)")
        else:
            out.append(text[m.start():close + (1 if close == end else 0)])
        i = close + (1 if close == end else 0)
    text = "".join(out)
    return _RUN.sub(lambda m: f"{m.group(0)[:MAX_QUOTE]}... ({len(m.group(0))}+ characters)", text)


def _cut(x, depth: int = 0):
    if depth > 6:
        return "..."
    if isinstance(x, dict):
        return {str(k)[:64]: ([str(e)[:64] if isinstance(e, str) else e for e in v[:8]]
                              if k == "loc" and isinstance(v, list) else _cut(v, depth + 1))
                for k, v in list(x.items())[:20] if k not in ("input", "ctx")}
    if isinstance(x, list):
        return [_cut(v, depth + 1) for v in x[:20]]
    if isinstance(x, str):
        x = _cut_quotes(x)
        return x if len(x) <= MAX_MSG else x[:MAX_MSG] + "..."
    return x


def no_echo(body: bytes) -> bytes:
    """An error answer (4xx JSON) without the input it may repeat (docs/api.md: "the
    input is never echoed"): FastAPI's ``input`` and ``ctx`` dropped, a quoted value in a
    message cut to an excerpt and its length, every string at most :data:`MAX_MSG`
    characters. Whatever raised it (a 422 of FastAPI, a tool's refusal, an
    HTTPException): one place for all."""
    if len(body) > 1 << 20:
        return json.dumps({"detail": "refused (the answer repeated too much of the request)"}).encode()
    try:
        data = json.loads(body)
    except ValueError:
        return body
    return json.dumps(_cut(data), separators=(",", ":")).encode()


async def _too_large(send, max_bytes: int, why: str = "") -> None:
    body = json.dumps({"detail": why or f"request body larger than {max_bytes} bytes"}).encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


def install_error_handlers(app: FastAPI) -> None:
    """422 without the input: the field's location, the reason, the error type."""

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        detail = [{"loc": [str(x)[:64] for x in e.get("loc", ())][:8],
                   "msg": str(e.get("msg", ""))[:200], "type": e.get("type", "value_error")}
                  for e in exc.errors()[:10]]
        return JSONResponse({"detail": detail}, status_code=422)


def guarded_protocol(max_connections: int, header_timeout_s: float,
                     first_byte_timeout_s: float | None = None,
                     max_per_ip: int | None = None,
                     min_body_bytes_per_s: float = 0.0,
                     write_stall_s: float = 0.0,
                     protected: Callable[[str], bool] | None = None):
    """uvicorn's h11 protocol class with a connection cap, a cap per client address, a
    first-byte timeout and a header timeout (see the module doc).

    A connection over a cap does not simply bounce (that let idle sockets lock everyone
    out, issue 21): it takes the place of an *idle* connection (one that sent nothing
    yet first, then one whose request head is still coming, then a keep-alive one
    between requests), taken from the address holding the most connections, and only
    from one holding more than the newcomer's (for the per-address cap: from its own
    address). When none is idle at the connection cap, the
    newcomer takes a busy connection (a body still arriving, then a WebSocket, then a
    request being answered) of the address holding the most connections, provided it
    holds at least two more than the newcomer's own address: a few addresses holding
    WebSockets or trickling bodies cannot fill the table and lock the presenter out (a
    browser holds a handful). Only when no address holds that many is it closed at once.

    ``min_body_bytes_per_s``: a request body must come at least this fast, judged over
    each ``header_timeout_s`` (a body sent a byte at a time is closed; one the server is
    not reading yet is not judged). ``write_stall_s``: a response the client has not read
    from for this long (the socket's buffer full the whole time) is closed. 0 turns
    either off. ``protected(address)``: an address whose connections are never taken for
    another address's at the connection cap (the presenter's)."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    first_byte_s = header_timeout_s if first_byte_timeout_s is None \
        else min(float(first_byte_timeout_s), header_timeout_s)
    by_addr: dict = {}        # client address -> {protocol: None}, oldest first
    count = [0]               # connections counted (HTTP, and WebSockets upgraded from them)
    stats = {"refused": 0, "evicted": 0, "silent_closed": 0, "head_timeouts": 0,
             "shared": 0, "slow_bodies": 0, "write_stalls": 0}
    body_period_s = float(header_timeout_s)
    min_body_bytes = float(min_body_bytes_per_s) * body_period_s

    def _rank(p) -> int | None:
        """Eviction order (lower first); None: not to be taken (busy, or a WebSocket)."""
        if p._upgraded:
            return None
        if not p._got_bytes:
            return 0                        # connected, sent nothing
        cyc = p.cycle
        if cyc is None:
            return 1                        # a request head still on its way
        if cyc.response_complete:
            return 2                        # keep-alive, between two requests
        return None

    def _idle_of(addrs, ranks=(0, 1, 2)):
        """The idle connection of ``addrs`` (in that order) to close first, by its
        :func:`_rank` in the order ``ranks`` gives (by default one that sent nothing yet,
        then a slow request head, then a keep-alive one); None if none."""
        best = None
        for a in addrs:
            for p in by_addr.get(a, ()):
                r = _rank(p)
                if r is None or r not in ranks:
                    continue
                k = ranks.index(r)
                if k == 0:
                    return p
                if best is None or k < best[0]:
                    best = (k, p)
        return None if best is None else best[1]

    def _victim(addr):
        """At the per-address cap: an idle connection of that address, or None."""
        return _idle_of([addr])

    def _cap_victim(newcomer):
        """At the connection cap: ``(connection to close, busy)`` for a newcomer from
        address ``newcomer``, or ``(None, False)``. In order: an idle connection of an
        address holding more than the newcomer's (the most first); one of its own; a
        keep-alive one of any address (closing it costs nobody a request); a busy one of
        the address holding the most (:func:`_fair_victim`); and, for the presenter only,
        any idle one. No address the presenter's token came from is taken from. (An idle
        connection of an address holding no more than the newcomer's is taken only as the
        last two: a flood of newcomers from a few addresses must not take a student's or
        the presenter's connection in the moment before its request arrives.)"""
        own = len(by_addr.get(newcomer, ()))
        others = [a for a in sorted(by_addr, key=lambda a: len(by_addr[a]), reverse=True)
                  if a != newcomer and not _protected(a)]
        bigger = [a for a in others if len(by_addr[a]) > own]
        # its own: a keep-alive one first (a browser's fresh one is about to ask)
        for pick in (lambda: _idle_of(bigger), lambda: _idle_of([newcomer], ranks=(2, 1, 0)),
                     lambda: _idle_of(others, ranks=(2,))):
            p = pick()
            if p is not None:
                return p, False
        presenter = _protected(newcomer)
        p = _fair_victim(newcomer, presenter)
        if p is not None:
            return p, True
        if presenter:
            p = _idle_of(others)
            if p is not None:
                return p, False
        return None, False

    def _protected(a) -> bool:
        try:
            return bool(protected and protected(a))
        except Exception:   # the guard must not fail on its helper
            return False

    def _busy_rank(p) -> int:
        """Which of a busy address's connections a newcomer takes first (lower first)."""
        cyc = p.cycle
        if not p._upgraded and cyc is not None and not cyc.response_complete and cyc.more_body:
            return 0                        # a request body still arriving
        return 1 if p._upgraded else 2      # a WebSocket; a request being answered

    def _fair_victim(addr, presenter: bool = False):
        """At the connection cap with none idle: a busy connection of the address holding
        the most, if it holds at least two more than ``addr`` (any, for the presenter; see
        above), else None."""
        candidates = [a for a in by_addr if a != addr and not _protected(a)]
        if not candidates:
            return None
        hog = max(candidates, key=lambda a: len(by_addr[a]))
        if not presenter and len(by_addr[hog]) < len(by_addr.get(addr, ())) + 2:
            return None
        return min(by_addr[hog], key=_busy_rank)     # oldest first among equals

    class GuardedH11Protocol(H11Protocol):
        _head_timer = None
        _head_cycle = None      # the request cycle current when the timer started
        _first_timer = None
        _addr = None
        _counted = False
        _got_bytes = False
        _upgraded = False
        _body_timer = None      # judges a request body's pace (min_body_bytes_per_s)
        _body_cycle = None
        _body_bytes = 0         # bytes received since the last judgement
        _write_timer = None     # a response the client does not read (write_stall_s)
        _stall_size = 0         # unsent bytes when that timer was set
        _drained = False        # the client read since (the buffer fell below its low mark)
        _body_paused = False    # the server paused reading in this judging period

        guard_stats = stats     # for tests and the log

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._addr = self.client[0] if self.client else "?"
            if max_per_ip and len(by_addr.get(self._addr, ())) >= max_per_ip:
                victim = _victim(self._addr)
                if victim is None:
                    return self._refuse(f"{max_per_ip} connections from {self._addr}")
                victim._drop(evicted=True)
            if count[0] >= max_connections:
                victim, busy = _cap_victim(self._addr)
                if victim is None:
                    return self._refuse(f"{count[0]} connections open (cap {max_connections})")
                if busy:
                    stats["shared"] += 1
                    _limited_log("HTTP connection cap (%d) reached: closed a busy connection "
                                 "of %s, which holds %d", max_connections, victim._addr,
                                 len(by_addr.get(victim._addr, ())))
                    victim._drop(evicted=True, hard=True)
                else:
                    victim._drop(evicted=True)
            by_addr.setdefault(self._addr, {})[self] = None
            count[0] += 1
            self._counted = True
            self._arm()
            self._first_timer = self.loop.call_later(first_byte_s, self._silent_timeout)

        def _refuse(self, why: str) -> None:
            stats["refused"] += 1
            _limited_log("HTTP connection refused: %s, none idle", why)
            self.transport.abort()

        def _release(self) -> None:
            if self._counted:
                self._counted = False
                count[0] -= 1
                conns = by_addr.get(self._addr)
                if conns is not None:
                    conns.pop(self, None)
                    if not conns:
                        del by_addr[self._addr]

        def _drop(self, evicted: bool = False, hard: bool = False) -> None:
            """Close this connection now; it stops counting at once. ``hard``: reset it
            (a busy one: nothing it has in flight is waited for)."""
            silent = hard or not self._got_bytes or self.cycle is None
            self._release()
            self._disarm()
            if evicted:
                stats["evicted"] += 1
            if silent or self.transport.get_write_buffer_size():
                # nothing to flush (a reset, no TIME_WAIT here), or an answer its client
                # is not reading: close() would wait for it for ever, the socket uncounted
                self.transport.abort()
            elif not self.transport.is_closing():
                self.transport.close()

        def _arm(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
            self._head_cycle = self.cycle
            self._head_timer = self.loop.call_later(header_timeout_s, self._head_timeout)

        def _disarm(self) -> None:
            for name in ("_head_timer", "_first_timer", "_body_timer", "_write_timer"):
                timer = getattr(self, name)
                if timer is not None:
                    timer.cancel()
                    setattr(self, name, None)

        def _silent_timeout(self) -> None:
            self._first_timer = None
            if not self._got_bytes and not self.transport.is_closing():
                stats["silent_closed"] += 1
                self._drop()

        def _head_timeout(self) -> None:
            self._head_timer = None
            # no new request head since the timer started: a slow or idle client
            if self.cycle is self._head_cycle and not self.transport.is_closing():
                stats["head_timeouts"] += 1
                self._drop()

        def _arm_body(self) -> None:
            self._body_cycle = self.cycle
            self._body_bytes = 0
            self._body_paused = self.flow.read_paused
            self._body_timer = self.loop.call_later(body_period_s, self._body_check)

        def _body_check(self) -> None:
            """Every ``body_period_s`` while a request body is arriving: too few bytes
            (the server reading all the while) closes the connection."""
            self._body_timer = None
            cyc = self.cycle
            if cyc is not self._body_cycle or cyc is None or cyc.response_complete \
                    or not cyc.more_body or self.transport.is_closing():
                return
            if self._body_bytes < min_body_bytes and not self.flow.read_paused \
                    and not self._body_paused:
                stats["slow_bodies"] += 1
                _limited_log("HTTP request body from %s too slow (%d bytes in %.0f s): closed",
                             self._addr, self._body_bytes, body_period_s)
                self._drop()
                return
            self._arm_body()

        def data_received(self, data: bytes) -> None:
            if not self._got_bytes and data:
                self._got_bytes = True
                if self._first_timer is not None:
                    self._first_timer.cancel()
                    self._first_timer = None
            self._body_bytes += len(data)
            super().data_received(data)

        def handle_events(self) -> None:
            super().handle_events()
            if self._head_timer is not None and self.cycle is not self._head_cycle:
                self._head_timer.cancel()       # a request head arrived in time
                self._head_timer = None
            if self.flow.read_paused:
                self._body_paused = True        # not the client's slowness: not judged
            cyc = self.cycle
            if min_body_bytes > 0 and cyc is not None and cyc is not self._body_cycle \
                    and cyc.more_body and not cyc.response_complete and not self._upgraded:
                if self._body_timer is not None:
                    self._body_timer.cancel()
                self._arm_body()                # a new request: its body's pace is judged

        def _arm_stall(self) -> None:
            """Judge, ``write_stall_s`` from now, whether the client reads what it is sent."""
            if write_stall_s > 0 and self._write_timer is None:
                self._stall_size = self.transport.get_write_buffer_size()
                self._drained = False
                self._write_timer = self.loop.call_later(write_stall_s, self._write_stalled)

        def pause_writing(self) -> None:
            super().pause_writing()
            self._arm_stall()

        def resume_writing(self) -> None:
            self._drained = True            # the client read some: progress
            super().resume_writing()

        def _write_stalled(self) -> None:
            """Unsent bytes and no progress for ``write_stall_s`` (no drain below the low
            mark, the buffer no smaller), whether the answer is still being written or was
            complete and its connection is closing: closed, uncounted at once."""
            self._write_timer = None
            size = self.transport.get_write_buffer_size()
            if not size:
                return
            if self._drained or size < self._stall_size:
                self._arm_stall()           # the client reads: judge the next period
                return
            stats["write_stalls"] += 1
            _limited_log("HTTP client %s has not read its answer for %.0f s: closed",
                         self._addr, write_stall_s)
            self._release()
            self._disarm()
            self.transport.abort()

        def handle_websocket_upgrade(self, event) -> None:
            self._disarm()          # the WebSocket protocol owns the connection now
            self._upgraded = True   # still counted (its address, the cap) until it ends
            super().handle_websocket_upgrade(event)
            ws = self.transport.get_protocol()
            if ws is self:
                return
            lost = ws.connection_lost

            def connection_lost(exc, _lost=lost, _http=self):
                _http._release()
                return _lost(exc)
            ws.connection_lost = connection_lost

        def on_response_complete(self) -> None:
            if not self.transport.is_closing():
                self._arm()         # the next request head must come in time too
            super().on_response_complete()
            if self.transport.get_write_buffer_size():
                self._arm_stall()   # an answer not yet read: it must be, in time

        def connection_lost(self, exc) -> None:
            self._release()
            self._disarm()
            super().connection_lost(exc)

    return GuardedH11Protocol


class RateLimitFilter(logging.Filter):
    """Let the same message (logger + format string) through at most ``burst`` times
    per ``period`` s; then one line saying how many were suppressed."""

    def __init__(self, burst: int = 5, period: float = 10.0):
        super().__init__()
        self.burst = burst
        self.period = period
        self._seen: dict[tuple, list] = {}
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        # one decision per record: it is shown to the filter once per handler (and once more
        # on its own logger), and each showing counted, so two handlers halved the burst
        done = getattr(record, "_orientlab_rate_ok", None)
        if done is not None:
            return done
        ok = self._judge(record)
        record._orientlab_rate_ok = ok
        return ok

    def reset(self) -> None:
        """Forget every line seen (a new run in the same process: the tests)."""
        with self._lock:
            self._seen.clear()

    def _judge(self, record: logging.LogRecord) -> bool:
        key = (record.name, record.msg if isinstance(record.msg, str) else repr(record.msg)[:80])
        now = time.monotonic()
        with self._lock:
            st = self._seen.get(key)
            if st is None or now - st[0] > self.period:
                suppressed = st[2] if st else 0
                self._seen[key] = [now, 1, 0]
                if len(self._seen) > 1000:   # bounded: forget the oldest keys
                    for k in sorted(self._seen, key=lambda k: self._seen[k][0])[:500]:
                        del self._seen[k]
                if suppressed:
                    record.msg = f"{record.msg} ({suppressed} similar lines suppressed)"
                return True
            if st[1] < self.burst:
                st[1] += 1
                return True
            st[2] += 1
            return False


_limiter = RateLimitFilter()


def reset_log_limits() -> None:
    """Forget the lines the log's rate limit has seen (it is one per process)."""
    _limiter.reset()


def _limited_log(msg: str, *args) -> None:
    log.warning(msg, *args)


def install_log_limits() -> None:
    """Rate-limit the loggers a hostile client can make talk (idempotent)."""
    for name in ("orientlab", "uvicorn.error", "uvicorn.access", "websockets", "viser"):
        lg = logging.getLogger(name)
        if _limiter not in lg.filters:
            lg.addFilter(_limiter)
    # a filter on a logger does not see its children's records: add it to the handlers
    for h in logging.getLogger().handlers:
        if _limiter not in h.filters:
            h.addFilter(_limiter)
