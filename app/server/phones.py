"""The phones that reach the dashboard over HTTP: Sensor Logger's and phyphox's pushes on
the dashboard's own port, and phyphox's remote access polled from here.

Each app's wire format is decoded by its source module (:mod:`app.sources.sensorlogger`,
:mod:`app.sources.phyphox`); this module only wires them to the engine through the
shared phone slot (:class:`~app.sources.slot.PhoneSlot`, the same the TCP receiver uses):

- a request is refused before it is decoded when another phone holds the slot (Sensor
  Logger gets a 499 with the reason, which the app shows; phyphox an error status, which
  it shows as a network error);
- a phone takes the slot with its first valid sample; its samples go to the engine as
  every source's do (``engine.feed``); the handler reads the body on a worker thread (the
  JSON; for Sensor Logger also its readings to arrays), then decodes the rest, enqueues
  and answers on the loop; it never filters on the request path;
- a push stream that has sent nothing for :data:`PUSH_END_S` seconds, or for 2.5 of its
  batch periods if they are longer (the app's batch period is the user's setting), has
  ended (the app stopped recording): its held messages are released and its stream is
  closed;
- a malformed request is answered 400 with the reason and counted per app.
"""

from __future__ import annotations

import asyncio
import logging
import statistics
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

from typing import Callable, Protocol

from app.sources.phyphox import PhyphoxPushStream
from app.sources.phyphox_poll import PhyphoxPoller
from app.sources.samples import DecodeError
from app.sources.sensorlogger import SensorLoggerStream
from app.sources.slot import PHONE_APPS, PhoneSlot

log = logging.getLogger("orientlab.phones")

PUSH_END_S = 5.0        # a push stream silent this long has ended ...
PUSH_END_PERIODS = 2.5  # ... or this many of its batch periods, if longer,
MAX_PUSH_END_S = 60.0   # but never longer than this
TICK_S = 0.2            # how often held messages and silent streams are looked at
POLL_WINDOW_S = 0.1     # phyphox polled: the reorder window (s)


class PushDecoder(Protocol):
    """What a push app's source module gives per phone (a stream's decoder): ``read`` the
    body (on a worker thread: JSON, arrays), ``take`` it on the loop (a batch with
    ``samples``, ``ended``, ``new_session``, ``late``), ``count_rejected`` a
    :class:`~app.sources.samples.DecodeError`, ``status`` for the page, ``waiting`` while it
    holds samples back, ``flush`` what it holds when the stream ends, ``due`` what it held
    that is due now. Optional: ``withheld`` and ``silent_hint`` (read by the session)."""
    waiting: bool

    def read(self, body: bytes) -> Any: ...
    def take(self, read: Any, now: float) -> Any: ...
    def count_rejected(self, e: DecodeError) -> None: ...
    def status(self) -> dict: ...
    def flush(self) -> list: ...
    def due(self, now: float) -> list: ...


@dataclass(frozen=True)
class PushApp:
    """A phone app that pushes over HTTP: everything the server needs of it, in one place
    (the route ``POST /{key}`` in :mod:`app.server.routers.push`; its label in
    :data:`~app.sources.slot.PHONE_APPS`; its wire format in its source module)."""
    key: str
    window_s: float                       # the reorder window (s)
    refused_status: int                   # the answer when another phone holds the slot
    decoder: Callable[[], PushDecoder]    # a new stream's decoder

    @property
    def path(self) -> str:
        return "/" + self.key


#: the push apps. Sensor Logger delivers in batches (0.05 s reorder window) and shows a 499's
#: reason; phyphox's POSTs overlap and may swap (0.3 s), and it shows an error status
PUSH_APPS = {a.key: a for a in (
    PushApp("sensorlogger", 0.05, 499, SensorLoggerStream),
    PushApp("phyphox", 0.3, 409, PhyphoxPushStream),
)}


def _push_app(phone_app: str) -> PushApp:
    """The push app ``phone_app`` (ValueError for another name: a route without a record)."""
    try:
        return PUSH_APPS[phone_app]
    except KeyError:
        raise ValueError(f"{phone_app!r} is no push app (PUSH_APPS)") from None


@dataclass
class Stream:
    """One HTTP phone's stream: its decoder and the engine's session."""
    phone_app: str
    key: str
    decoder: Any
    session: Any = None
    last_rx: float = field(default_factory=time.monotonic)   # a POST arrived (PC clock)
    details_at: float = -1e9
    # the phone's time each recent batch spanned (s): its batch period, roughly
    spans: deque = field(default_factory=lambda: deque(maxlen=5))

    def expected_gap_s(self) -> float:
        """The longest gap expected between two of its batches: 1.5 of its batch period (the
        median of the recent batches' spans); 0 before it has one. Another phone may not
        take over, nor is it called silent, within that (a Sensor Logger set to 5 s batches
        lost the slot between its own batches)."""
        return 1.5 * statistics.median(self.spans) if self.spans else 0.0

    def end_s(self) -> float:
        """How long it may be silent before it has ended: :data:`PUSH_END_S`, or
        :data:`PUSH_END_PERIODS` of its batch periods (the median of the recent batches'
        spans: one long catch-up batch does not count) if longer, at most
        :data:`MAX_PUSH_END_S`."""
        if not self.spans:
            return PUSH_END_S
        return min(MAX_PUSH_END_S, max(PUSH_END_S, PUSH_END_PERIODS * statistics.median(self.spans)))


@dataclass
class Reply:
    status: int
    text: str = ""


@dataclass
class PhoneAppCounts:
    requests: int = 0
    refused: int = 0
    bad: Counter = field(default_factory=Counter)

    def as_dict(self) -> dict:
        return {"requests": self.requests, "refused": self.refused, "bad": dict(self.bad),
                "bad_total": int(sum(self.bad.values()))}


class HttpPhones:
    """See the module doc. One per dashboard, built in the lifespan."""

    def __init__(self, engine, settings, slot: PhoneSlot):
        self.engine = engine
        self.settings = settings
        self.slot = slot
        self.streams: dict[tuple[str, str], Stream] = {}    # (phone_app, key) -> decoder state
        self.counts = {a: PhoneAppCounts() for a in (*PUSH_APPS, "phyphox-poll")}
        self.poller: PhyphoxPoller | None = None
        self.poll_task: asyncio.Task | None = None
        self.conventions: dict[str, str] = {}     # Sensor Logger: the presenter's choice
        self._reading = asyncio.Lock()

    # ------------------------------------------------------------------ pushes
    async def push(self, phone_app: str, body: bytes, client: str) -> Reply:
        """One POST of a push app (``sensorlogger`` or ``phyphox``) from ``client``. The
        body is read (the decoder's ``read``: the JSON, and Sensor Logger's readings to
        arrays) on a worker thread, so a long batch does not hold the server up while it is
        read; the stream's state sees it on the event loop (``take``)."""
        _push_app(phone_app)
        c = self.counts[phone_app]
        c.requests += 1
        now = time.time()
        refused = self._refused(phone_app, client)
        if refused is not None:
            return refused
        st = self._stream(phone_app, client)
        st.last_rx = time.monotonic()        # a sign of life while its body is read
        decoder = st.decoder
        try:
            async with self._reading:    # one body at a time: parallel reads are no faster
                read = await asyncio.to_thread(decoder.read, body)     # (the GIL), only larger
        except DecodeError as e:
            return self._malformed(self._stream(phone_app, client), e)
        # while it was read, another phone may have taken the slot, or this stream ended
        refused = self._refused(phone_app, client)
        if refused is not None:
            return refused
        st = self._stream(phone_app, client)
        try:
            batch = st.decoder.take(read, now)
        except DecodeError as e:
            return self._malformed(st, e)
        st.last_rx = time.monotonic()
        if len(batch.samples) > 1:
            times = [x.time_ms for x in batch.samples]
            st.spans.append((max(times) - min(times)) / 1000.0)
        if batch.ended and st.session is not None and st.session.open:   # the old recording's tail
            self.engine.feed(st.session, batch.ended, time.perf_counter())
        # samples held by the decoder (Sensor Logger's first ones, while the sign is unknown)
        # are this phone's data too: it takes the slot with them
        self._deliver(st, batch.samples, batch.new_session, st.decoder.waiting)
        if batch.late and st.session is not None:
            st.session.count_late(batch.late)
        return Reply(200, "")

    def refusal(self, phone_app: str, client: str) -> Reply | None:
        """A push the slot turns away, answered before its body is read (counted as a
        request and a refusal); None if it may go on (:meth:`push` asks again after the
        read: the slot may change meanwhile)."""
        _push_app(phone_app)
        reply = self._refused(phone_app, client)
        if reply is not None:
            self.counts[phone_app].requests += 1
        return reply

    def count_cut(self, phone_app: str) -> None:
        """A push whose body never arrived whole (the phone's connection dropped mid-body):
        counted among the app's bad requests as ``cut_off``."""
        c = self.counts[phone_app]
        c.requests += 1
        c.bad["cut_off"] += 1

    def _refused(self, phone_app: str, client: str) -> Reply | None:
        """The answer to a phone the slot turns away (counted), or None."""
        why = self.slot.refusal(phone_app, client)
        if why is None:
            return None
        self.counts[phone_app].refused += 1
        self.slot.count_refusal(why, phone_app, client)
        log.warning("refused phone %s (%s): %s", client, PHONE_APPS.get(phone_app, phone_app), why)
        self.engine.core.totals.count_refused()
        return Reply(_push_app(phone_app).refused_status, why)

    def _stream(self, phone_app: str, client: str) -> Stream:
        st = self.streams.get((phone_app, client))
        if st is None:
            st = Stream(phone_app, client, self._decoder(phone_app))
            self.streams[(phone_app, client)] = st
        return st

    def _malformed(self, st: Stream, e: DecodeError) -> Reply:
        """A body that cannot be used: counted, answered 400 with the reason."""
        st.decoder.count_rejected(e)
        self.counts[st.phone_app].bad[e.reason] += 1
        if st.session is not None:
            st.session.count_malformed(e.reason)
        return Reply(400, str(e)[:200])

    def _decoder(self, phone_app: str) -> PushDecoder:
        d = _push_app(phone_app).decoder()
        conv = self.conventions.get(phone_app)
        if conv:
            d.set_convention(conv)
        return d

    def _deliver(self, st: Stream, samples: list, new_session: bool = False,
                 waiting: bool = False) -> None:
        """Samples of a stream to the engine: the slot is taken with the first valid
        one (or one the decoder holds: ``waiting``); a new recording of the app starts a
        new stream."""
        if not samples and not waiting and st.session is None:
            return
        if not self.slot.holds(st.key):
            label = f"{st.key} ({PHONE_APPS[st.phone_app]})"
            if self.slot.take(st.phone_app, st.key, label, lambda why, s=st: self._end(s, why)) is not None:
                return              # taken meanwhile by another phone
            log.info("phone %s connected", label)     # as the TCP receiver says it
            new_session = True
        if new_session or st.session is None or not st.session.open:
            if st.session is not None and st.session.open:
                self.engine.close_session(st.session, "the phone started a new recording")
            st.session = self.engine.open_phone_session(
                f"{st.key} ({PHONE_APPS[st.phone_app]})", st.phone_app,
                window_s=PUSH_APPS[st.phone_app].window_s if st.phone_app in PUSH_APPS
                else POLL_WINDOW_S)
            st.session.withheld_by = getattr(st.decoder, "withheld", None)
            st.session.silent_hint_by = getattr(st.decoder, "silent_hint", None)
        if samples or waiting:
            self._details(st)
            gap = st.expected_gap_s()
            self.slot.touch(st.key, gap)
            st.session.expected_gap_s = gap
        if samples:
            self.engine.feed(st.session, samples, time.perf_counter())

    def _details(self, st: Stream) -> None:
        """What the decoder detected (platform, convention, device), on the session, for
        the recording's events; looked up at most once a second."""
        now = time.monotonic()
        if now - st.details_at < 1.0 and st.session.details:
            return
        st.details_at = now
        try:
            dec = st.decoder.status()
        except Exception:
            return
        keep = ("platform", "convention", "convention_source", "device_model", "model",
                "device_id", "url")
        st.session.details.update({k: dec[k] for k in keep if dec.get(k) is not None})

    def _end(self, st: Stream, reason: str) -> None:
        """End a stream: what its decoder holds goes in first, then the session closes."""
        if st.session is not None and st.session.open:
            rest = st.decoder.flush()
            if rest:
                self.engine.feed(st.session, rest, time.perf_counter())
            self.engine.close_session(st.session, reason)
            log.info("phone %s (%s) left: %s", st.key, PHONE_APPS[st.phone_app], reason)
        self.slot.leave(st.key)
        self.streams.pop((st.phone_app, st.key), None)
        if st.phone_app == "phyphox-poll" and self.poller is not None and reason.startswith("released"):
            self.stop_poll()

    def tick(self) -> None:
        """Release messages held for a missing one that timed out; end silent streams."""
        now_wall, now = time.time(), time.monotonic()
        for st in list(self.streams.values()):
            if st.phone_app == "phyphox-poll":
                continue
            if st.session is not None and st.session.open:
                rest = st.decoder.due(now_wall)
                if rest:
                    self.engine.feed(st.session, rest, time.perf_counter())
            end_s = st.end_s()
            if now - st.last_rx > end_s:
                self._end(st, f"no data for {end_s:.0f} s: the phone stopped streaming")

    # ------------------------------------------------------------------ phyphox polled
    def start_poll(self, url: str) -> None:
        """Poll a phyphox phone's remote access at ``url`` (ValueError for a bad URL)."""
        self.stop_poll()
        key = url

        def on_samples(samples, new_session=False):
            st = self.streams.get(("phyphox-poll", key))
            if st is None:
                st = self.streams[("phyphox-poll", key)] = Stream("phyphox-poll", key, self.poller)
            if self.slot.refusal("phyphox-poll", key) is not None:
                return          # another phone holds the slot: the poller's status says so
            st.last_rx = time.monotonic()
            self._deliver(st, samples, new_session)

        self.poller = PhyphoxPoller(url, on_samples)
        self.poll_task = asyncio.get_running_loop().create_task(self.poller.run(), name="phyphox-poll")

    def stop_poll(self) -> None:
        if self.poller is not None:
            self.poller.stop()
        if self.poll_task is not None:
            self.poll_task.cancel()
        st = next((s for (a, _), s in self.streams.items() if a == "phyphox-poll"), None)
        self.poller, self.poll_task = None, None
        if st is not None:
            self._end(st, "remote access stopped by the presenter")

    # ------------------------------------------------------------------ presenter
    def set_convention(self, value: str) -> None:
        """Sensor Logger's sign convention, for the stream now and the next ones."""
        SensorLoggerStream().set_convention(value)       # validates (ValueError)
        self.conventions["sensorlogger"] = value
        for (phone_app, _), st in self.streams.items():
            if phone_app == "sensorlogger":
                st.decoder.set_convention(value)

    def status(self) -> dict:
        out: dict[str, Any] = {"counts": {a: c.as_dict() for a, c in self.counts.items()},
                               "streams": []}
        for (phone_app, key), st in self.streams.items():
            try:
                dec = st.decoder.status()
            except Exception:      # a status must never fail the page
                dec = {}
            out["streams"].append({"app": phone_app, "app_name": PHONE_APPS[phone_app],
                                   "holder": self.slot.holds(key),
                                   "streaming": st.session is not None and st.session.open,
                                   **dec})
        out["poll"] = None if self.poller is None else self.poller.status()
        out["sensorlogger_convention"] = self.conventions.get("sensorlogger", "auto")
        return out
