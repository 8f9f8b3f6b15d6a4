"""The phone receiver: a TCP server for the Sensor Fusion app's stream.

The phone is the TCP client and only sends lines (see
``shared/protocols/sensorfusion-app.md``). Each connection becomes a
:class:`~app.server.engine.Session` of the engine; its lines go through the same
path as the demo's and a replayed log's (:meth:`Engine.feed_lines`).

Robustness:

- **bounded line buffer**: a line longer than ``max_line_bytes`` without a newline
  closes that connection (counted as ``too_long``); the server carries on;
- **end of stream** (EOF or a reset) is noticed at once; the last state stays on show
  and the next connection is accepted without a restart;
- **disconnect mid-line**: the unterminated tail is counted as malformed
  (``truncated``) and dropped: a cut number would otherwise parse as a wrong value;
- malformed lines are counted by reason and skipped (by the stream's orderer).

**A second phone while one streams is refused** (its connection is closed at once and
counted as ``refused``): a stray phone in a classroom must not hijack the projector.
Exception: if the streaming phone has sent nothing for ``phone_idle_s`` seconds (a
connection that died without a FIN, e.g. the phone lost Wi-Fi), the new phone takes
over and the silent connection is closed.

When a phone connects, the demo (or log replay) stops. When the phone leaves, the
dashboard keeps the phone's last state and says so; the demo does **not** resume by
itself (a teacher may be about to reconnect): the GUI's "Resume demo" button or
``POST /api/source/resume`` restarts it.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time

from ..protocol import LineSplitter

log = logging.getLogger("orientlab.receiver")

READ_CHUNK = 65536


def quick_ack(sock: socket.socket | None) -> None:
    """Acknowledge received data at once (Linux ``TCP_QUICKACK``; elsewhere nothing).

    A phone that writes small chunks with Nagle's algorithm on holds each chunk
    until the previous one is acknowledged, and Linux delays an ACK by up to 40 ms:
    the stream would arrive in 40 ms clumps (60 samples at 500 Hz x 3) instead of
    as it is made. The kernel drops quick-ack mode by itself, so this is renewed
    after every read."""
    opt = getattr(socket, "TCP_QUICKACK", None)
    if sock is None or opt is None:
        return
    try:
        sock.setsockopt(socket.IPPROTO_TCP, opt, 1)
    except OSError:
        pass


class PhoneServer:
    """asyncio TCP server feeding phone connections into the engine."""

    def __init__(self, engine, settings):
        self.engine = engine
        self.settings = settings
        self.server: asyncio.base_events.Server | None = None
        self.current: tuple | None = None          # (session, writer) of the streaming phone
        self._writers: set = set()

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._handle, self.settings.phone_bind,
                                                 self.settings.phone_port)

    @property
    def port(self) -> int:
        return self.server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        if self.server is not None:
            self.server.close()
        for w in list(self._writers):
            w.close()

    def _busy(self) -> bool:
        if self.current is None:
            return False
        session, _ = self.current
        return session.open and time.monotonic() - session.last_rx < self.settings.phone_idle_s

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        label = f"{peer[0]}:{peer[1]}" if peer else "?"
        eng = self.engine
        if self._busy():
            eng.counts_total["refused"] += 1
            log.warning("refused phone %s: another phone is streaming", label)
            writer.close()
            return
        if self.current is not None:  # a silent connection: the new phone takes over
            old_session, old_writer = self.current
            eng.close_session(old_session, f"silent for {self.settings.phone_idle_s:g} s, "
                                           f"taken over by {label}")
            old_writer.close()
        eng.pause_background()
        session = eng.open_session("phone", label)
        self.current = (session, writer)
        self._writers.add(writer)
        log.info("phone %s connected", label)
        splitter = LineSplitter(self.settings.max_line_bytes)
        reason = "end of stream"
        sock = writer.get_extra_info("socket")
        try:
            while True:
                quick_ack(sock)
                chunk = await reader.read(READ_CHUNK)
                if not chunk:
                    break
                t_arr = time.perf_counter()
                lines = splitter.feed(chunk)
                if session is not eng.session:  # replaced meanwhile
                    reason = "replaced"
                    break
                if lines:
                    eng.feed_lines(session, lines, t_arr)
                if splitter.overflows:  # not this format: the lines before it are kept
                    eng.counts_total["too_long"] += 1
                    session.count_malformed("too_long")
                    reason = f"a line longer than {splitter.max_line} bytes without a newline"
                    break
        except (ConnectionError, OSError) as e:
            reason = f"connection lost ({type(e).__name__})"
        except asyncio.CancelledError:
            reason = "server stopping"
            raise
        finally:
            if splitter.pending.strip():
                session.count_malformed("truncated")
            eng.close_session(session, reason)
            if self.current is not None and self.current[0] is session:
                self.current = None
            self._writers.discard(writer)
            writer.close()
            log.info("phone %s left: %s", label, reason)
