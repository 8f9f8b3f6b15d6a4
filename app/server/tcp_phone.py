"""The Sensor Fusion app's TCP receiver, wired to the engine.

The phone is the TCP client and only sends lines (see
``shared/protocols/sensorfusion-app.md``). Each connection becomes a session of the
engine; its lines are decoded by the app's source module
(:func:`~app.sources.sensorfusion.decode_lines`: what does not parse is counted by
reason) and the samples go the way every source's go (``engine.feed``). This is the
network edge, as :mod:`app.server.phones` is for the apps that push over HTTP: the wire
format stays in :mod:`app.sources.sensorfusion`, which knows nothing of the engine.

Robustness:

- **bounded line buffer**: a line longer than ``max_line_bytes`` without a newline
  closes that connection (counted as ``too_long``); the server carries on;
- **end of stream** (EOF or a reset) is noticed at once; the last state stays on show
  and the next connection is accepted without a restart;
- **disconnect mid-line**: the unterminated tail is counted as malformed
  (``truncated``) and dropped: a cut number would otherwise parse as a wrong value;
- malformed lines are counted by reason and skipped (by the stream's orderer).

**A connection takes the slot only with valid sensor data**: until its first valid
motion sample (ACC/GYR/MAG/ORI, parsed, finite, within the physical limits) it changes
nothing: the demo goes on, the filters are not reset, the phone on show stays. A
connection that sends no valid sample within ``phone_hello_s`` (3 s) is closed and
counted (``no_data``): an empty connect, a port scan or a stray script never stops the
demo. The lines before the first valid sample are kept and fed with it.

**One phone at a time, across every app** (:class:`~app.sources.slot.PhoneSlot`, shared
with the HTTP sources): a second phone while one streams is refused (its connection is
closed at once and counted as ``refused``); a phone silent for ``phone_idle_s`` seconds
may be taken over (its connection is closed). The presenter may lock the slot (no new
phone at all) and release the phone streaming now (its connection is closed, and the
same peer is kept out for a while).

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
from collections import Counter

from app.sources.slot import PhoneSlot
from app.sources.sensorfusion import LineSplitter, decode_lines, valid_sample_line

log = logging.getLogger("orientlab.receiver")

# Fairness: the phone's data is parsed on the event loop that also answers the API. A
# read returns at most READ_CHUNK bytes (~55 lines: under a millisecond of parsing, a
# few of filtering; a real phone's 10 ms is ~600 bytes); after each chunk
# the receiver yields the loop, and while the engine has more than MAX_BACKLOG samples
# waiting it stops reading (TCP flow control then holds the phone back: nothing is
# lost). So a phone sending as fast as TCP carries it cannot starve the API or grow the
# queue without bound: each turn of the loop holds little of its work, and the API's
# turns come between.
READ_CHUNK = 2048
MAX_BACKLOG = 256


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


PHONE_APP = "sensorfusion"   # this source's key in the phone slot (app.sources.slot.PHONE_APPS)
HELLO_MAX_LINES = 2000     # lines without a valid sample before a connection is dropped


def feed_lines(engine, session, lines: list, t_arrival: float | None = None) -> None:
    """Lines of one received chunk (or a replayed log's) into the engine as samples; the
    lines that do not parse are counted in the session by reason."""
    bad: Counter = Counter()
    samples = decode_lines(lines, bad)
    for reason, n in bad.items():
        session.count_malformed(reason, n)
    engine.feed(session, samples, t_arrival)


def _n_samples(session) -> int:
    """Samples the session's stream has accepted so far (parsed and valid)."""
    try:
        return sum(session.orderer.counters.tags.values())
    except AttributeError:
        return session.lines


class SensorFusionServer:
    """asyncio TCP server feeding phone connections into the engine."""

    def __init__(self, engine, settings, slot: PhoneSlot | None = None):
        self.engine = engine
        self.settings = settings
        self.slot = slot if slot is not None else PhoneSlot(settings.phone_idle_s)
        self.server: asyncio.base_events.Server | None = None
        self.current = None                        # the session of the streaming phone
        self.counts = {"no_data": 0, "refused_locked": 0}
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

    def status(self) -> dict:
        cur = self.current
        return {"locked": self.slot.locked,
                "streaming": cur.label if cur is not None and cur.open else None,
                "refused": self.engine.core.totals.refused, **self.counts}

    async def _hello(self, reader, splitter: LineSplitter) -> list | None:
        """The lines up to and including the first valid sample, or None if none comes
        within ``phone_hello_s`` (or the connection ends, or sends junk only)."""
        held: list = []
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.settings.phone_hello_s
        while len(held) < HELLO_MAX_LINES:
            remaining = deadline - loop.time()
            if remaining <= 0:
                return None
            try:
                chunk = await asyncio.wait_for(reader.read(READ_CHUNK), remaining)
            except (asyncio.TimeoutError, ConnectionError, OSError):
                return None
            if not chunk:
                return None
            lines = splitter.feed(chunk)
            held.extend(lines)
            if splitter.overflows:
                return None
            if any(valid_sample_line(ln) for ln in lines):
                return held
        return None

    async def _let_others_run(self, session, reader=None) -> None:
        """Yield the event loop after a chunk; wait while the engine is behind. When the
        reader holds nothing more, the next read waits for the socket and so yields the
        loop itself: no extra loop turn then (one less per chunk of a real phone)."""
        eng = self.engine
        if getattr(eng, "queued", 0) <= MAX_BACKLOG:
            if reader is None or getattr(reader, "_buffer", True):
                await asyncio.sleep(0)
            return
        while getattr(eng, "queued", 0) > MAX_BACKLOG // 2 and session is eng.core.session:
            await asyncio.sleep(0.002)

    def _refuse(self, writer, label: str, why: str, counted: bool = False,
                host: str = "") -> None:
        """Turn a phone away; the slot counts it for the Connect tab (``take`` already has)."""
        self.engine.core.totals.count_refused()
        if not counted:
            self.slot.count_refusal(why, PHONE_APP, host or label)
        log.warning("refused phone %s: %s", label, why)
        writer.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        label = f"{peer[0]}:{peer[1]}" if peer else "?"
        eng = self.engine
        host = peer[0] if peer else label       # a release keeps the phone out, any port
        why = self.slot.refusal(PHONE_APP, label, host)
        if why is not None:
            if self.slot.locked:
                self.counts["refused_locked"] += 1
            return self._refuse(writer, label, why, host=host)
        splitter = LineSplitter(self.settings.max_line_bytes)
        self._writers.add(writer)
        try:
            held = await self._hello(reader, splitter)
        except asyncio.CancelledError:
            self._writers.discard(writer)
            writer.close()
            raise
        if held is None:   # nothing valid: this connection never takes the slot
            self._writers.discard(writer)
            self.counts["no_data"] += 1
            log.info("phone %s closed: no valid sample within %g s", label,
                     self.settings.phone_hello_s)
            writer.close()
            return
        conn: dict = {"session": None}

        def on_release(reason: str) -> None:     # released, or taken over while silent
            conn["released"] = reason
            if conn["session"] is not None:
                eng.close_session(conn["session"], reason)
            writer.close()

        why = self.slot.take(PHONE_APP, label, f"{label} (Sensor Fusion app)", on_release,
                             who=host)
        if why is not None:   # another phone got in meanwhile
            self._writers.discard(writer)
            return self._refuse(writer, label, why, counted=True)
        session = eng.open_phone_session(label, PHONE_APP)
        conn["session"] = session
        self.current = session
        log.info("phone %s connected", label)
        reason = "end of stream"
        sock = writer.get_extra_info("socket")
        try:
            feed_lines(eng, session, held, time.perf_counter())
            while True:
                quick_ack(sock)
                chunk = await reader.read(READ_CHUNK)
                if not chunk:
                    break
                t_arr = time.perf_counter()
                lines = splitter.feed(chunk)
                if session is not eng.core.session:  # replaced meanwhile
                    reason = "replaced"
                    break
                if lines:
                    n0 = _n_samples(session)
                    feed_lines(eng, session, lines, t_arr)
                    if _n_samples(session) > n0:
                        self.slot.touch(label)
                if splitter.overflows:  # not this format: the lines before it are kept
                    eng.core.totals.count_too_long()
                    session.count_malformed("too_long")
                    reason = f"a line longer than {splitter.max_line} bytes without a newline"
                    break
                await self._let_others_run(session, reader)
        except (ConnectionError, OSError) as e:
            reason = f"connection lost ({type(e).__name__})"
        except asyncio.CancelledError:
            reason = "server stopping"
            raise
        finally:
            reason = conn.get("released", reason)     # the socket closed by the release
            if splitter.pending.strip():
                session.count_malformed("truncated")
            eng.close_session(session, reason)
            if self.current is session:
                self.current = None
                self.slot.leave(label)
            self._writers.discard(writer)
            writer.close()
            log.info("phone %s left: %s", label, reason)
