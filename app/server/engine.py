"""The async shell around the live core: the inbox, the throttle, publishing, the supervisor.

Everything the filter does lives in :class:`app.live.LiveCore` (pure and synchronous:
sessions, the ensemble of estimators, changes, history, read models). This module only
moves work onto the event loop and results off it:

- **the inbox** (:class:`Inbox`): one queue, in posting order. Streams (a phone of any app, the
  demo, a replayed log) call :meth:`Engine.feed` with samples from the event loop; the
  core's session counts and reorders, and the released samples are queued with the
  arrival time of their chunk. Parameter changes are validated first
  (:meth:`LiveCore.validate`, from the HTTP API or viser's GUI threads) and posted with
  ``loop.call_soon_threadsafe`` (:meth:`Engine.post`). Session starts are queued too.
- **the filter task** takes everything queued at once, applies the changes first (a
  change is in effect from the next sample on), then hands each chunk of samples to
  :meth:`LiveCore.process` (one batch run per estimator), and **publishes**: the primary's
  pose to the scene after every batch (that moment ends the latency measurement), the
  rest of the scene at most ``scene_hz``, the WebSocket subscribers at most ``ws_hz``
  times a second and the live plots' (WS /ws/plots: only the new points) at most
  :data:`PLOT_HZ` (:class:`Throttle`, in their own loop turns).
- **it cannot die**: an exception in a step is caught by the ensemble (the sample is logged,
  counted and skipped); anything else failing on an item is logged and counted
  (``loop_errors``) and the loop goes on; a supervisor restarts the task if it ever ends
  (``restarts``, shown by /api/health and the status line). A WebSocket subscriber that
  stops reading is dropped once :data:`SUBSCRIBER_BACKLOG` messages wait for it; no
  subscriber can block or raise into the loop.

Latency (:meth:`Engine.stats`, printed by ``benchmarks/dashboard_load.py``): for every
processed sample, the time from the **arrival** of the chunk holding the line that
released it (``time.perf_counter()`` when the receiver's read returned) to the moment
the primary's pose after the batch has been **queued on viser**. The reorder buffer's
deliberate hold is not part of it. Also recorded: the part before the task took the
chunk (``wait_ms``) and how late the display timers ran (``loop_lag_ms``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from typing import Any, Callable

import msgspec
import numpy as np

from app.config import load_config
from app.live import Change, LiveCore, PatchError, Session, Snapshot
from app.live.views import Latency
from app.live.ensemble import TAG_OF_KIND
from app.params import GRAVITY
from app.sources.samples import Sample

log = logging.getLogger("orientlab.engine")


class Inbox:
    """The filter task's queue, in posting order, on one event loop: ``put_nowait``,
    ``await get()``, ``get_nowait``, ``empty``, ``qsize`` as :class:`asyncio.Queue`, and
    :meth:`items`, what waits, in order (a recording begun mid-stream takes the samples
    not yet filtered). Its own deque, so nothing reads a private attribute of asyncio's."""

    def __init__(self) -> None:
        self._items: deque = deque()
        self._ready = asyncio.Event()

    def put_nowait(self, item) -> None:
        self._items.append(item)
        self._ready.set()

    async def get(self):
        while not self._items:
            self._ready.clear()
            await self._ready.wait()
        return self._items.popleft()

    def get_nowait(self):
        if not self._items:
            raise asyncio.QueueEmpty
        return self._items.popleft()

    def empty(self) -> bool:
        return not self._items

    def qsize(self) -> int:
        return len(self._items)

    def items(self) -> list:
        return list(self._items)


SLICE_SAMPLES = 32    # samples per turn of the filter task before it yields the loop

PLOT_HZ = 20.0                # WS /ws/plots messages a second at most (the plots redraw as often)
SUBSCRIBER_BACKLOG = 200      # WS messages (20 s at 10 Hz) waiting for one client: dropped
RESTART_PAUSE_S = 0.1
_JSON = msgspec.json.Encoder()

__all__ = ["Change", "Engine", "EngineBusy", "PatchError", "Session", "Snapshot", "Subscriber", "Throttle"]


class Throttle:
    """Run ``fn`` on the event loop at most once per ``interval`` seconds.

    :meth:`poke` asks for a run; it happens in a later loop turn (never inside the
    caller, so the caller is not delayed), as soon as ``interval`` has passed since
    the last run. Pokes before that run are merged into it."""

    def __init__(self, interval: float, fn: Callable[[], None],
                 loop: asyncio.AbstractEventLoop | None = None, lag: deque | None = None):
        self.interval = float(interval)
        self.fn = fn
        self.loop = loop
        self.lag = lag              # if given: how late each run started (s), the loop's lag
        self._last = -math.inf
        self._due = 0.0
        self._handle: asyncio.TimerHandle | None = None

    def poke(self) -> None:
        if self._handle is None:
            self._due = max(self._last + self.interval, self.loop.time())
            self._handle = self.loop.call_at(self._due, self._run)

    def cancel(self) -> None:
        """Drop a pending run."""
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None

    def _run(self) -> None:
        self._handle = None
        self._last = self.loop.time()
        if self.lag is not None:
            self.lag.append(self._last - self._due)
        try:
            self.fn()
        except Exception:  # a display bug must not stop the filter
            log.exception("%s failed", getattr(self.fn, "__name__", "throttled call"))


class Subscriber:
    """One WS /ws/state (or /ws/plots) client's outbox: bounded; a client this far behind is dropped
    (:attr:`dropped`), never blocking or failing the publisher."""

    def __init__(self, backlog: int = SUBSCRIBER_BACKLOG):
        self.backlog = backlog
        self.msgs: deque[str] = deque()
        self.dropped = False
        self.closed = False         # the client went (not dropped for falling behind)
        self._ready = asyncio.Event()

    def offer(self, msg: str) -> bool:
        if self.dropped:
            return False
        if len(self.msgs) >= self.backlog:
            self.dropped = True
            self.msgs.clear()
        else:
            self.msgs.append(msg)
        self._ready.set()
        return not self.dropped

    def close(self) -> None:
        self.dropped = True
        self.closed = True
        self._ready.set()

    async def next(self) -> str | None:
        """The next message, or None once dropped or closed."""
        while not self.msgs:
            if self.dropped:
                return None
            self._ready.clear()
            await self._ready.wait()
        return None if self.dropped else self.msgs.popleft()


class EngineBusy(Exception):
    """The filter task did not take a change in time: nothing was applied (the change is
    dropped, not left to apply later behind the caller's back). Its text says why."""


class Engine:
    """The async shell (see the module doc); ``core`` is the :class:`LiveCore`.
    ``config``: :func:`app.config.load_config`'s dict (read once, by the app)."""

    def __init__(self, settings, config: dict[str, Any] | None = None,
                 loop: asyncio.AbstractEventLoop | None = None):
        self.settings = settings
        if config is None:
            config = load_config(settings.config)
        self.core = LiveCore(config, history_s=settings.history_s,
                             reorder_window_s=settings.reorder_window_s)
        self.loop = loop
        self.inbox: Inbox | None = None
        self.background_allowed: asyncio.Event | None = None
        self.pose_listeners: list[Callable[[np.ndarray], None]] = []  # after every batch
        self.listeners: list[Callable[[Snapshot], None]] = []       # at most scene_hz
        self.change_listeners: list[Callable[[Change], None]] = []  # each change applied
        self.param_listeners: list[Callable[[], None]] = []         # after every change
        self.preset_parts: list[Callable[[], dict]] = []            # more tables for a saved preset
        self.subscribers: set[Subscriber] = set()                   # WS /ws/state
        self.plot_subscribers: set[Subscriber] = set()              # WS /ws/plots
        self.filtering = False      # True once the filters are ready and the task runs
        self.plot_feed = None       # the plots' feed (app.server.gui.plots.PlotFeed), set by the GUI
        # the viewer's grouping (viser's ``server.atomic``): the scene's listeners' updates
        # go out together, waking viser's sender once per refresh instead of once each
        self.atomic: Callable[[], Any] = contextlib.nullcontext
        self.latency = Latency()
        self.queued = 0                     # samples waiting in the inbox
        self.restarts = 0                   # the filter task ended and was restarted
        self.loop_errors = 0                # an item failed outside the estimators' steps
        self.dropped_subscribers = 0
        self.subscriber_backlog = SUBSCRIBER_BACKLOG
        self._t_taken = 0.0
        self._ws_pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []   # (t, kind, q) per chunk
        self._scene_timer = Throttle(1.0 / settings.scene_hz, self._draw_scene,
                                     lag=self.latency.loop_lag)
        self._ws_timer = Throttle(1.0 / settings.ws_hz, self._flush_ws, lag=self.latency.loop_lag)
        self._plot_timer = Throttle(1.0 / PLOT_HZ, self._flush_plots, lag=self.latency.loop_lag)

    # ----------------------------------------------------------------- lifecycle
    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """Attach to the running loop (called in the FastAPI lifespan)."""
        self.loop = loop
        self.inbox = Inbox()
        self._scene_timer.loop = self._ws_timer.loop = self._plot_timer.loop = loop
        self.background_allowed = asyncio.Event()
        self.background_allowed.set()

    def warm_up(self) -> None:
        """Run every estimator through a few rows (the batch path the stream takes) and
        reset them, so numba's compilation or cache loading happens before the first
        real sample."""
        fed = []
        for k in range(4):
            t = 10 * k
            fed += [Sample(t, "GYR", (0.01, 0.0, 0.0)), Sample(t + 2, "ACC", (0.0, 0.0, GRAVITY)),
                    Sample(t + 4, "MAG", (0.0, 20.0, -45.0)), Sample(t + 6, "ORI", (1.0, 0.0, 0.0, 0.0))]
        core = self.core
        s = Session("warm-up", "warm-up", 0.0)
        samples = s.push(fed) + s.close()
        core.ensemble.step(samples)
        for n in core.ensemble.names:
            est = core.ensemble.estimator(n)
            est.save_state()
            est.diagnostics()
            est.attitude_cov()
        core.ensemble.reset()

    async def run_when_ready(self, warmup=None) -> None:
        """:meth:`run`, once every filter is compiled or loaded (``warmup``: an
        :class:`app.warmup.Warmup` working in the background while the page already
        answers; None: :meth:`warm_up` was done before). Until then nothing is filtered:
        a stream's samples wait in the inbox, in order, and every filter processes all
        of them once ready (a second or so of catching up), so the filters' comparisons
        start from the same first sample. A failed warm-up leaves it waiting (the
        server is being stopped)."""
        if warmup is not None:
            if not await warmup.wait_ready():
                await asyncio.Event().wait()
            self.warm_up()   # all loaded by now: milliseconds, and no thread races the streams
        self.filtering = True
        await self.run()

    # ----------------------------------------------------------------- sessions
    def open_session(self, kind: str, label: str, truth=None, phone_app: str = "",
                     window_s: float | None = None) -> Session:
        """Start a stream; it replaces the one on show (the estimators start afresh)."""
        s = self.core.open_session(kind, label, truth, phone_app=phone_app, window_s=window_s)
        self.inbox.put_nowait(("session", s))
        return s

    def open_phone_session(self, label: str, phone_app: str, window_s: float | None = None) -> Session:
        """A phone that took the slot (any app's receiver): the demo or a replayed log
        pauses (until "Resume demo"), and the phone's stream replaces the one on show."""
        self.pause_background()
        return self.open_session("phone", label, phone_app=phone_app, window_s=window_s)

    def close_session(self, s: Session, reason: str = "end of stream") -> None:
        """End a stream: release what the reorder buffer holds; the last state stays."""
        self._queue(s, self.core.close_session(s, reason))

    def release_quiet(self) -> None:
        """The stream on show went quiet, still open (:meth:`Session.quiet`: a phone paused,
        an app stopped without hanging up, a replay paused): the samples its reorder window
        holds back are processed now, not when it sends again or ends."""
        s = self.core.session
        if s is None or not s.quiet():
            return
        self._queue(s, s.release_held())

    def feed(self, s: Session, samples: list[Sample], t_arrival: float | None = None) -> None:
        """Samples of one received chunk (arrival order) into the stream."""
        if t_arrival is None:
            t_arrival = time.perf_counter()
        self._queue(s, self.core.feed(s, samples), t_arrival)

    def _queue(self, s: Session, samples: list[Sample], t_arrival: float | None = None) -> None:
        """Released samples of stream ``s`` to the filter task (none: nothing)."""
        if samples:
            self.queued += len(samples)
            self.inbox.put_nowait(("samples", s, samples,
                                   time.perf_counter() if t_arrival is None else t_arrival))

    def queued_samples(self, s: Session) -> list[Sample]:
        """The samples of stream ``s`` queued for the filter task, not yet filtered (in the
        order they will be); on the loop only."""
        items = self.inbox.items() if self.inbox is not None else ()
        return [x for it in items if it[0] == "samples" and it[1] is s for x in it[2]]

    def pause_background(self) -> None:
        self.background_allowed.clear()

    @property
    def background_paused(self) -> bool:
        """A phone has paused the demo (or log replay), and no one has resumed it yet."""
        return self.background_allowed is not None and not self.background_allowed.is_set()

    def phone_streaming(self) -> bool:
        """A phone's stream is on show (it has priority over the demo and a replay)."""
        s = self.core.session
        return s is not None and s.open and s.kind == "phone"

    def resume_background(self) -> bool:
        """Let the demo (or log replay) run again after a phone has left; False (nothing
        done) while a phone streams: the demo would take the stream from it."""
        if self.phone_streaming():
            return False
        if self.loop is not None:
            self.loop.call_soon_threadsafe(self.background_allowed.set)
        return True

    # ----------------------------------------------------------------- changes
    def post(self, change: Change, done: asyncio.Future | None = None) -> None:
        """Queue a validated change for the filter task; callable from any thread.
        ``done`` (a future of the engine's loop) gets the new parameters, or PatchError."""
        self.loop.call_soon_threadsafe(self.inbox.put_nowait, ("change", change, done))

    async def apply(self, change: Change, timeout: float) -> dict:
        """Post ``change`` and wait for the filter task to apply it: the parameters in force,
        or PatchError (nothing applied). After ``timeout`` s, :class:`EngineBusy` and the
        change is dropped: a client told it failed must not see it happen later (on a
        first start the filters compile for a minute or two before the task takes any)."""
        done = self.loop.create_future()
        self.post(change, done)
        try:
            return await asyncio.wait_for(done, timeout)
        except asyncio.TimeoutError:
            if not self.filtering:
                raise EngineBusy("the filters are still being compiled (a first start after an "
                                 "install takes a minute or two; GET /api/health says when they "
                                 "are ready): nothing was applied, try again then") from None
            raise EngineBusy(f"the filter task did not take the change within {timeout:g} s: "
                             "nothing was applied, try again") from None

    def _apply(self, ch: Change, done: asyncio.Future | None) -> None:
        if done is not None and done.cancelled():
            return          # its caller gave up waiting (EngineBusy) and said nothing applied
        try:
            view = self.core.apply(ch)
        except PatchError as e:  # raced with another change: nothing applied
            if done is not None and not done.done():
                done.set_exception(e)
            return
        if done is not None and not done.done():
            done.set_result(view)
        for on_change in self.change_listeners:   # before the parameter listeners
            try:
                on_change(ch)
            except Exception:  # a listener's bug must not stop the filter
                log.exception("change listener failed")
        for cb in self.param_listeners:
            try:
                cb()
            except Exception:
                log.exception("parameter listener failed")

    # ----------------------------------------------------------------- the task
    async def run(self) -> None:
        """The filter task under its supervisor: restarted if it ever ends."""
        try:
            while True:
                try:
                    await self._loop_forever()
                    log.error("the filter task ended: restarting it")
                except asyncio.CancelledError:
                    raise
                except Exception:
                    log.exception("the filter task failed: restarting it")
                self.restarts += 1
                await asyncio.sleep(RESTART_PAUSE_S)
        finally:  # nothing is drawn after the task has stopped (viser stops next)
            self._scene_timer.cancel()
            self._ws_timer.cancel()
            self._plot_timer.cancel()

    async def _loop_forever(self) -> None:
        inbox = self.inbox
        while True:
            items = [await inbox.get()]
            self._t_taken = time.perf_counter()
            # a slice of about SLICE_SAMPLES samples (about a ms of filtering), then the
            # loop is yielded: the API and the receiver never wait for a long backlog
            n = len(items[0][2]) if items[0][0] == "samples" else 0
            while not inbox.empty() and n < SLICE_SAMPLES:
                it = inbox.get_nowait()
                items.append(it)
                if it[0] == "samples":
                    n += len(it[2])
            self.latency.backlog_max = max(self.latency.backlog_max, len(items))
            self._take(items)
            if not inbox.empty():   # more waiting: let the loop run between slices (an
                await asyncio.sleep(0)   # empty inbox yields in get(), one loop turn fewer)

    def _take(self, items: list) -> None:
        """One turn of the filter task: changes first, then sessions and samples."""
        if any(it[0] != "samples" for it in items):
            self._guarded(self._flush_ws)   # what was estimated before goes out first
        for it in items:
            if it[0] == "change":
                self._guarded(self._apply, it[1], it[2])
        arrivals = []
        for it in items:
            if it[0] == "session":
                self._guarded(self.core.start, it[1])
            elif it[0] == "samples":
                _, s, samples, t_arr = it
                self.queued -= len(samples)
                if self._guarded(self._process, s, samples):
                    arrivals.append((t_arr, len(samples)))
        if arrivals:
            self._guarded(self._publish, arrivals)

    def _guarded(self, fn, *args):
        """``fn(*args)``; an exception is logged and counted (``loop_errors``): None."""
        try:
            return fn(*args)
        except Exception:
            self.loop_errors += 1
            log.exception("filter task: %s failed (item skipped)", getattr(fn, "__name__", fn))
            return None

    def _process(self, s: Session, samples: list[Sample]) -> bool:
        """Samples of the stream on show through the core (others: False, skipped)."""
        rec = self.core.process(s, samples)
        if rec is None:
            return False
        if self.subscribers and len(rec):   # as arrays: made into JSON rows at the flush
            self._ws_pending.append((rec.t, rec.kind, rec.primary_q))
        return True

    def _publish(self, arrivals: list[tuple[float, int]]) -> None:
        """Hand the primary's new pose to the scene (every batch: that moment ends the
        latency measurement), then let the rest follow at display rate."""
        self.latency.batches += 1
        if self.pose_listeners:
            q = self.core.ensemble.estimator(self.core.ensemble.primary).q
            for cb in self.pose_listeners:
                try:
                    cb(q)
                except Exception:
                    log.exception("pose listener failed")
        now = time.perf_counter()
        for t_arr, n in arrivals:
            self.latency.chunks.append((now - t_arr, self._t_taken - t_arr, n))
        self._scene_timer.poke()
        if self._ws_pending:
            self._ws_timer.poke()
        if self.plot_subscribers:
            self._plot_timer.poke()

    def _draw_scene(self) -> None:
        """Everything else in the scene (cones, arrows, other phones, indicators)."""
        if not self.listeners:
            return
        snap = self.core.snapshot()
        with self.atomic():
            for cb in self.listeners:
                try:
                    cb(snap)
                except Exception:
                    log.exception("scene listener failed")

    def subscribe(self) -> Subscriber:
        sub = Subscriber(self.subscriber_backlog)
        self.subscribers.add(sub)
        return sub

    def unsubscribe(self, sub: Subscriber) -> None:
        self.subscribers.discard(sub)
        sub.close()

    def _flush_ws(self) -> None:
        """Send the estimates made since the last flush, one message encoded once for
        every subscriber (none is skipped; a subscriber too far behind is dropped)."""
        pending = self._ws_pending
        if not pending:
            return
        self._ws_pending = []
        if not self.subscribers:
            return
        # msgspec: 10x faster than json.dumps here (the same JSON, without spaces; a
        # non-finite number is null, valid JSON, where json.dumps wrote NaN)
        t = np.concatenate([p[0] for p in pending]).tolist()
        kind = np.concatenate([p[1] for p in pending]).tolist()
        q = np.concatenate([p[2] for p in pending]).tolist()
        msg = _JSON.encode({"primary": self.core.ensemble.primary, "source": self.core.source_kind(),
                            "estimates": [{"t": a, "tag": TAG_OF_KIND[k], "q": b}
                                          for a, k, b in zip(t, kind, q)]}).decode()
        for sub in list(self.subscribers):
            if not sub.offer(msg):
                self.subscribers.discard(sub)
                self.dropped_subscribers += 1
                log.warning("a /ws/state client fell %d messages behind: dropped", sub.backlog)

    def subscribe_plots(self) -> Subscriber:
        """A WS /ws/plots client: its first message is the plots' whole window, then
        only new points (:class:`app.server.gui.plots.PlotFeed`). On the loop."""
        sub = Subscriber(self.subscriber_backlog)
        if self.plot_feed is not None:
            self._flush_plots(always=True)      # the others get what is new first
            sub.offer(self.plot_feed.snapshot().decode())
        self.plot_subscribers.add(sub)
        return sub

    def unsubscribe_plots(self, sub: Subscriber) -> None:
        self.plot_subscribers.discard(sub)
        sub.close()

    def _flush_plots(self, always: bool = False) -> None:
        """The plots' new points since the last flush, one message encoded once for
        every /ws/plots client (a client too far behind is dropped); ``always``: read
        the rings even without a client (one is about to join)."""
        feed = self.plot_feed
        if feed is None or not (self.plot_subscribers or always):
            return
        raw = feed.delta()
        if raw is None:
            return
        msg = raw.decode()
        for sub in list(self.plot_subscribers):
            if sub.closed:                      # gone: its handler unsubscribes it
                self.plot_subscribers.discard(sub)
                continue
            if not sub.offer(msg):
                self.plot_subscribers.discard(sub)
                self.dropped_subscribers += 1
                log.warning("a /ws/plots client fell %d messages behind: dropped", sub.backlog)

    # ----------------------------------------------------------------- read-outs
    def health(self, task: asyncio.Task | None) -> dict[str, Any]:
        ok = task is not None and not task.done()
        return {"status": "ok" if ok else "stopped", "restarts": self.restarts,
                "loop_errors": self.loop_errors, "step_errors": self.core.ensemble.step_errors(),
                "dropped_subscribers": self.dropped_subscribers,
                "restored": self.core.ensemble.restored()}

    def state(self) -> dict[str, Any]:
        st = self.core.state()
        st["counts"]["queued"] = self.queued
        st["counts"]["total_loop_errors"] = self.loop_errors
        st["counts"]["total_restarts"] = self.restarts
        if self.restarts:
            st["status"] += f" (the filter task was restarted {self.restarts}×)"
        return st

    def stats(self, reset: bool = False) -> dict[str, Any]:
        """GET /api/stats: backlog and latency figures (for the load benchmark)."""
        s = self.core.session
        out = {"batches": self.latency.batches,
               "backlog_now": self.inbox.qsize() if self.inbox else 0,
               "queued_samples": self.queued,
               "backlog_max_items": self.latency.backlog_max,
               "buffered": s.buffered if s else 0,
               "samples": self.core.totals.samples,
               **self.latency.figures()}
        if reset:
            self.latency.clear()
        return out
