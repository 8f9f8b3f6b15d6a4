"""Bounded resources for the HTTP side: what one client can cost the server.

- :class:`BodyLimit` (ASGI middleware): a request body longer than
  ``Settings.max_body_bytes`` (1 MB) is answered **413** before it is read: at once from
  ``Content-Length``, or as soon as a chunked body passes the limit.
- :func:`install_error_handlers`: a 422 names the field and the reason, never echoes
  the input (FastAPI's default puts the whole body in ``input``).
- :func:`guarded_protocol`: uvicorn's HTTP protocol with a **connection cap**
  (``max_connections``: a connection beyond it is closed at once, before anything is
  read) and a **header timeout** (``header_timeout_s``: a connection that has not sent
  a complete request head in time is closed; slow-loris). uvicorn's own
  ``limit_concurrency`` answers 503 only after reading a request and its
  ``timeout_keep_alive`` only starts after a first response.
- :class:`RateLimitFilter`: the same log line at most ``burst`` times per ``period``
  seconds, then one summary of how many were suppressed.
"""

from __future__ import annotations

import json
import logging
import threading
import time

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

log = logging.getLogger("orientlab.limits")


class BodyLimit:
    """ASGI middleware: 413 for a request body over ``max_bytes`` (``paths``: a larger
    cap for the given paths, the phones' pushes)."""

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

        async def send_wrapper(message):
            if not refused:
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

        await self.app(scope, limited_receive, send_wrapper)


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


def guarded_protocol(max_connections: int, header_timeout_s: float):
    """uvicorn's h11 protocol class with a connection cap and a header timeout."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class GuardedH11Protocol(H11Protocol):
        _head_timer = None
        _head_cycle = None      # the request cycle current when the timer started

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            if len(self.connections) > max_connections:
                _limited_log("HTTP connection refused: %d connections open (cap %d)",
                             len(self.connections), max_connections)
                transport.close()
                return
            self._arm()

        def _arm(self) -> None:
            self._disarm()
            self._head_cycle = self.cycle
            self._head_timer = self.loop.call_later(header_timeout_s, self._head_timeout)

        def _disarm(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _head_timeout(self) -> None:
            self._head_timer = None
            # no new request head since the timer started: a slow or idle client
            if self.cycle is self._head_cycle and not self.transport.is_closing():
                self.transport.close()

        def handle_events(self) -> None:
            super().handle_events()
            if self._head_timer is not None and self.cycle is not self._head_cycle:
                self._disarm()      # a request head arrived in time

        def handle_websocket_upgrade(self, event) -> None:
            self._disarm()          # the WebSocket protocol owns the connection now
            super().handle_websocket_upgrade(event)

        def on_response_complete(self) -> None:
            if not self.transport.is_closing():
                self._arm()         # the next request head must come in time too
            super().on_response_complete()

        def connection_lost(self, exc) -> None:
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
