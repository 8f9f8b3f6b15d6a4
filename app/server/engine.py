"""The filter task: every estimator steps on every sample; one of them is primary.

Inputs arrive on one asyncio queue (:attr:`Engine.inbox`), in the order they were
posted, from three kinds of producers:

- **streams** (the phone receiver, the demo, a replayed log) call :meth:`Engine.feed_lines`
  from the event loop: each line goes through the stream's :class:`Session` (its
  :class:`app.stream.SampleOrderer` parses, counts and reorders), and the samples it
  releases are queued with the arrival time of the chunk that released them;
- **parameter changes** from the HTTP API (event loop) and from GUI callbacks (viser's
  threads) are validated *first*, on copies (:meth:`Engine.validate_patch`, using
  :func:`app.params.replace_params`), so a bad value is refused with the field's name
  and nothing is applied; a valid :class:`Change` is posted with
  ``loop.call_soon_threadsafe(queue.put_nowait, change)`` (:meth:`Engine.post`);
- **session events** (a stream starts or ends).

The engine task takes everything queued at once, applies the changes first (so a
change is in effect from the next sample on), then steps every estimator on each
sample in order, and finally hands the primary's new pose to the viser scene (every
batch: viser merges poses and sends at most 60 a second). The rest of the scene
(cones, arrows, the other phones, indicators) follows at most ``scene_hz`` times a
second and the WebSocket subscribers get one message at most ``ws_hz`` times a second
holding every estimate since the last (none is skipped); both run from timers in their
own loop turns (:class:`Throttle`), so they never delay a pose. The plots read
:class:`Ring` buffers at ``plot_hz`` (see :mod:`app.server.gui`). The estimators'
parameters are the one source of truth: the API reads them, the GUI is synchronised
from them after a change.

Latency instrumentation (:meth:`Engine.stats`, printed by ``benchmarks/dashboard_load.py``):
for every processed sample, the time from the **arrival** of the chunk holding the line
that released it (``time.perf_counter()`` when the receiver's read returned) to the
moment the primary's pose after the batch has been **queued on viser**
(``handle.wxyz = q`` returned). The reorder buffer's deliberate hold
(``reorder_window_s`` of stream time) is not part of that figure: a sample is timed from
the chunk that released it. Also recorded: the part spent before the engine task took
the chunk (``wait_ms``) and how late the display timers ran (``loop_lag_ms``), an
estimate of how long a chunk can sit in the socket while the loop is busy, which the
latency cannot see.
"""

from __future__ import annotations

import asyncio
import bisect
import json
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..config import load_config
from ..estimators import NAMES, Reason, REASON_TEXT, REJECTIONS, StepFlags, make_estimator
from ..params import ParamError, fields_of, replace_params, to_dict
from ..protocol import Sample
from ..quaternion import angle_between, q2euler
from ..stream import SampleOrderer

log = logging.getLogger("orientlab.engine")

SENSOR_OF_TAG = {"GYR": "gyr", "ACC": "acc", "MAG": "mag"}
SENSORS = ("gyr", "acc", "mag")
# history columns: pose ring (every motion sample), acc ring, mag ring; column 0 is t
H_T = 0
H_Q, H_P, P_COLS = 1, 5, 9                  # pose: t, q (primary), phone q
H_NORM = 1                                  # acc and mag: |v|
H_NIS_A, A_COLS = 2, 3                      # acc: t, |acc|, NIS
H_LK, H_NIS_M, M_COLS = 2, 3, 4             # mag: t, |mag|, L_k, NIS


class PatchError(ValueError):
    """A refused change; ``loc`` is the path of the offending field in the request body."""

    def __init__(self, loc: tuple, reason: str):
        super().__init__(f"{'.'.join(map(str, loc))}: {reason}")
        self.loc = tuple(loc)
        self.reason = reason


@dataclass
class Change:
    """A validated change, applied by the engine between two samples."""
    params: dict[str, dict[str, Any]] = field(default_factory=dict)   # estimator -> changes
    primary: str | None = None
    reset: bool = False
    done: asyncio.Future | None = None      # resolved with the new parameters once applied


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


class Session:
    """One stream: a phone connection, the demo, or one loop of a replayed log.

    Holds the stream's :class:`~app.stream.SampleOrderer` (parse, count, reorder, clock
    offsets) and its own counters, so the read-outs describe the stream on show.
    ``truth`` (demo only) maps phone times in ms (array) to true orientations (N, 4).
    """

    def __init__(self, kind: str, label: str, window_s: float,
                 truth: Callable[[float], np.ndarray] | None = None):
        self.kind = kind            # "phone", "demo", "replay"
        self.label = label
        self.orderer = SampleOrderer(window=window_s)
        self.truth = truth
        self.lines = 0
        self.samples = 0            # processed by the engine
        self.opened = time.time()
        self.closed: float | None = None
        self.close_reason = ""
        self.last_rx = time.monotonic()

    @property
    def open(self) -> bool:
        return self.closed is None

    def count_malformed(self, reason: str) -> None:
        self.orderer.counters.malformed[reason] += 1

    def counts(self) -> dict[str, Any]:
        c = self.orderer.counters
        return {"lines": self.lines, "samples": self.samples,
                "malformed": int(sum(c.malformed.values())),
                "malformed_by_reason": dict(c.malformed), "late": c.late, "clamped": c.clamped,
                "tags": dict(c.tags), "buffered": self.orderer.buffered}


class Ring:
    """The last ``capacity`` rows of ``cols`` floats, column 0 the stream time (s).

    Written by the engine on the event loop, read by the plots on the same loop:
    :meth:`window` costs O(``max_points``), whatever the capacity, and returns a copy.
    """

    def __init__(self, capacity: int, cols: int):
        self.data = np.full((capacity, cols), np.nan)
        self.n = 0                  # rows written in total

    def clear(self) -> None:
        self.data[:] = np.nan
        self.n = 0

    def next_row(self) -> np.ndarray:
        """The row to fill next (a view, NaN-filled); it counts as written."""
        row = self.data[self.n % self.data.shape[0]]
        row[:] = np.nan
        self.n += 1
        return row

    def window(self, seconds: float, max_points: int) -> np.ndarray:
        """At most ``max_points`` rows, evenly spread over the last ``seconds`` s of
        stream time, oldest first (the newest row always included)."""
        cap = self.data.shape[0]
        first = max(0, self.n - cap)
        if self.n == first:
            return self.data[:0].copy()
        t = self.data[:, 0]
        t_from = t[(self.n - 1) % cap] - seconds
        # the first logical index whose time is >= t_from (times rise with the index)
        lo = bisect.bisect_left(range(first, self.n), t_from, key=lambda i: t[i % cap]) + first
        k = min(self.n - lo, max_points)
        idx = np.linspace(lo, self.n - 1, k).astype(np.int64) % cap
        return self.data[idx]


class History:
    """The plots' rings of processed motion samples: ``pose`` (every motion sample:
    t, q, phone q), ``acc`` (t, |acc|, NIS) and ``mag`` (t, |mag|, L_k, NIS)."""

    def __init__(self, capacity: int):
        self.pose = Ring(capacity, P_COLS)
        self.acc = Ring(capacity, A_COLS)
        self.mag = Ring(capacity, M_COLS)

    def clear(self) -> None:
        for r in (self.pose, self.acc, self.mag):
            r.clear()


@dataclass
class Snapshot:
    """What the scene draws: the state after the last processed sample."""
    t: float | None
    primary: str
    q: np.ndarray
    initialized: bool
    phone_q: np.ndarray | None
    truth_q: np.ndarray | None
    cov: np.ndarray | None
    acc: np.ndarray | None          # last accelerometer sample (sensor frame)
    mag: np.ndarray | None          # last magnetometer sample (sensor frame)
    acc_flags: StepFlags | None     # primary's flags of the last accelerometer row
    mag_flags: StepFlags | None
    rest: bool
    diag: dict
    estimators: dict[str, np.ndarray]


def _num(x) -> float | None:
    """A JSON-safe float (NaN and inf become None)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _qlist(q) -> list[float] | None:
    return None if q is None else [float(v) for v in q]


def decision_dict(f: StepFlags | None, sensor: str) -> dict[str, Any]:
    """How the primary estimator treated the last sample of ``sensor``."""
    if f is None:
        return {"reason": "absent", "text": REASON_TEXT[Reason.ABSENT], "rejected": False,
                "value": None, "nis": None, "t": None}
    r: Reason = getattr(f, sensor)
    return {"reason": r.label, "text": REASON_TEXT[r], "rejected": r in REJECTIONS,
            "value": _num(getattr(f, f"{sensor}_value", None)),
            "nis": _num(getattr(f, f"{sensor}_nis", None)), "t": _num(f.t)}


class Engine:
    """Owns the estimators and everything derived from the stream (see module doc)."""

    def __init__(self, settings, loop: asyncio.AbstractEventLoop | None = None):
        self.settings = settings
        config = load_config(settings.config)
        self.estimators = {}
        for name in NAMES:
            try:
                self.estimators[name] = make_estimator(name, config.get(name))
            except ImportError as e:  # an estimator not written yet: run the others
                log.warning("estimator %s unavailable: %s", name, e)
        if not self.estimators:
            raise RuntimeError("no estimator available")
        self.primary = config["primary"] if config["primary"] in self.estimators \
            else next(iter(self.estimators))
        self.loop = loop
        self.inbox: asyncio.Queue | None = None
        self.session: Session | None = None
        self.background_allowed: asyncio.Event | None = None
        self.history = History(int(settings.history_s * 2000) + 1)
        self.pose_listeners: list[Callable[[np.ndarray], None]] = []  # after every batch
        self.listeners: list[Callable[[Snapshot], None]] = []       # at most scene_hz
        self.param_listeners: list[Callable[[], None]] = []         # after every change
        self.subscribers: set[asyncio.Queue] = set()                # WS /ws/state
        self.counts_total = {"sessions": 0, "refused": 0, "too_long": 0, "samples": 0}
        # per processed chunk: (arrival -> pose queued, arrival -> engine took it, n samples)
        self.latency: deque = deque(maxlen=200_000)
        self.backlog_max = 0
        self.batches = 0
        self.queued = 0                     # samples waiting in the inbox
        self._t_taken = 0.0                 # when the engine took the current batch
        self._ws_pending: list[tuple[float, str, list[float]]] = []
        # how late the display timers ran: the event loop's lag, which also delays the
        # receiver's reads (a chunk waiting in the socket is not in the latency figure)
        self.loop_lag: deque = deque(maxlen=100_000)
        self._scene_timer = Throttle(1.0 / settings.scene_hz, self._draw_scene, lag=self.loop_lag)
        self._ws_timer = Throttle(1.0 / settings.ws_hz, self._flush_ws, lag=self.loop_lag)
        self._has_lk = {n: "L_k" in e.diagnostics() for n, e in self.estimators.items()}
        self._reset_stream_state()

    # ----------------------------------------------------------------- lifecycle
    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """Attach to the running loop (called in the FastAPI lifespan)."""
        self.loop = loop
        self.inbox = asyncio.Queue()
        self._scene_timer.loop = self._ws_timer.loop = loop
        self.background_allowed = asyncio.Event()
        self.background_allowed.set()

    def warm_up(self) -> None:
        """Step every estimator through a few rows and reset it, so numba's compilation
        (or loading its cache) happens before the first real sample, not during it."""
        g, a, m = np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 9.81]), np.array([0.0, 20.0, -45.0])
        for est in self.estimators.values():
            for k in range(4):
                t = 0.01 * k
                est.step(t, gyr=g)
                est.step(t + 0.002, acc=a)
                est.step(t + 0.004, mag=m)
                est.step(t + 0.006, ori=np.array([1.0, 0.0, 0.0, 0.0]))
            est.snapshot()
            est.diagnostics()
            est.attitude_cov()
            est.reset()

    def _reset_stream_state(self) -> None:
        self.t_sent: float | None = None
        self.last_vec: dict[str, np.ndarray | None] = {"acc": None, "mag": None}
        self.last_flags: dict[str, dict[str, StepFlags | None]] = {
            name: {s: None for s in SENSORS} for name in self.estimators}
        # per estimator: [sensor][reason] -> count (plain lists: cheap to bump per sample)
        self.reason_counts = {name: [[0] * len(Reason) for _ in SENSORS] for name in self.estimators}
        self.history.clear()

    # ----------------------------------------------------------------- sessions
    def open_session(self, kind: str, label: str, truth=None) -> Session:
        """Start a stream; it replaces the one on show (the estimators start afresh:
        a new stream has a new clock)."""
        s = Session(kind, label, self.settings.reorder_window_s, truth)
        if self.session is not None and self.session.open:
            self.session.closed = time.time()
            self.session.close_reason = f"replaced by {kind} {label}"
        self.session = s
        self.counts_total["sessions"] += 1
        self.inbox.put_nowait(("session", s))
        return s

    def close_session(self, s: Session, reason: str = "end of stream") -> None:
        """End a stream: release what the reorder buffer holds; the last state stays."""
        if s.closed is None:
            s.closed = time.time()
            s.close_reason = reason
        rest = s.orderer.flush()
        if rest:
            self.queued += len(rest)
            self.inbox.put_nowait(("samples", s, rest, time.perf_counter()))

    def feed_lines(self, s: Session, lines: list, t_arrival: float | None = None) -> None:
        """Lines of one received chunk (bytes or str, without line ends) into the stream."""
        if t_arrival is None:
            t_arrival = time.perf_counter()
        s.lines += len(lines)
        s.last_rx = time.monotonic()
        released = []
        push_line = s.orderer.push_line
        for line in lines:
            released.extend(push_line(line))
        if released:
            self.queued += len(released)
            self.inbox.put_nowait(("samples", s, released, t_arrival))

    def pause_background(self) -> None:
        self.background_allowed.clear()

    def resume_background(self) -> None:
        """Let the demo (or log replay) run again after a phone has left."""
        if self.loop is not None:
            self.loop.call_soon_threadsafe(self.background_allowed.set)

    # ----------------------------------------------------------------- changes
    @property
    def phone_q(self) -> np.ndarray | None:
        """The phone's own estimate (ORI): the ``phone`` estimator's, which validates and
        holds it; None before the stream's first good ORI."""
        est = self.estimators.get("phone")
        return est.q if est is not None and est.initialized else None

    def params_of(self, name: str):
        return self.estimators[name].params

    def common_keys(self) -> list[str]:
        """Parameters every running estimator has (a top-level PATCH key sets them all)."""
        sets = [set(fields_of(e.params)) for e in self.estimators.values()]
        return sorted(set.intersection(*sets)) if sets else []

    def validate_patch(self, body: Any) -> Change:
        """Check a PATCH body against copies of the current parameters.

        ``{"use_mag": false, "primary": "lab", "estimators": {"lab": {"acc_noise": 0.3}}}``:
        a top-level parameter applies to every estimator that has it; ``primary`` picks
        the primary estimator; ``estimators.<name>`` holds one estimator's own changes
        (they win over top-level ones). Raises :class:`PatchError` naming the field;
        nothing is applied unless every field passes."""
        if not isinstance(body, dict):
            raise PatchError(("body",), "must be a JSON object")
        changes: dict[str, dict[str, Any]] = {n: {} for n in self.estimators}
        origin: dict[tuple[str, str], tuple] = {}
        ch = Change()
        for key, value in body.items():
            if key == "primary":
                if value not in self.estimators:
                    raise PatchError(("primary",), f"must be one of {', '.join(self.estimators)}; "
                                     f"got {value!r}")
                ch.primary = value
            elif key == "reset":
                if not isinstance(value, bool):
                    raise PatchError(("reset",), "must be true or false")
                ch.reset = value
            elif key == "estimators":
                if not isinstance(value, dict):
                    raise PatchError(("estimators",), "must be an object {estimator: {param: value}}")
                for name, sub in value.items():
                    if name not in self.estimators:
                        raise PatchError(("estimators", name), "unknown estimator (known: "
                                         f"{', '.join(self.estimators)})")
                    if not isinstance(sub, dict):
                        raise PatchError(("estimators", name), "must be an object {param: value}")
                    for k, v in sub.items():
                        changes[name][k] = v
                        origin[(name, k)] = ("estimators", name, k)
            else:
                owners = [n for n, e in self.estimators.items() if key in fields_of(e.params)]
                if not owners:
                    raise PatchError((key,), "unknown parameter (not a parameter of any estimator; "
                                     "estimator-specific ones go under \"estimators\")")
                for n in owners:
                    if (n, key) not in origin:
                        changes[n][key] = value
                        origin[(n, key)] = (key,)
        for name, c in changes.items():
            if not c:
                continue
            try:
                replace_params(self.params_of(name), c)
            except ParamError as e:
                raise PatchError(origin.get((name, e.field), ("estimators", name, e.field)),
                                 e.reason) from None
        ch.params = {n: c for n, c in changes.items() if c}
        return ch

    def change_from_config(self, config: dict[str, Any]) -> Change:
        """A change that sets every estimator to defaults + the preset (load_config's dict)."""
        ch = Change(primary=config.get("primary") if config.get("primary") in self.estimators else None)
        for name, est in self.estimators.items():
            p = replace_params(type(est.params)(), config.get(name, {}))
            ch.params[name] = to_dict(p)
        return ch

    def post(self, change: Change) -> None:
        """Queue a validated change for the engine; callable from any thread."""
        self.loop.call_soon_threadsafe(self.inbox.put_nowait, ("change", change))

    def _apply(self, ch: Change) -> None:
        try:
            new = {n: replace_params(self.estimators[n].params, c) for n, c in ch.params.items()}
        except ParamError as e:  # raced with another change: refuse the whole change
            if ch.done is not None and not ch.done.done():
                ch.done.set_exception(PatchError((e.field,), e.reason))
            return
        for n, p in new.items():
            est = self.estimators[n]
            est.set_params(**{k: getattr(p, k) for k in ch.params[n]})
        if ch.primary is not None:
            self.primary = ch.primary
        if ch.reset:
            for est in self.estimators.values():
                est.reset()
            self._reset_stream_state()
        if ch.done is not None and not ch.done.done():
            ch.done.set_result(self.params_view())
        for cb in self.param_listeners:
            try:
                cb()
            except Exception:  # a listener's bug must not stop the filter
                log.exception("parameter listener failed")

    def params_view(self) -> dict[str, Any]:
        """GET /api/params: the primary, the common switches (primary's values) and
        every estimator's parameters (SI units)."""
        prim = self.estimators[self.primary].params_dict()
        out: dict[str, Any] = {"primary": self.primary}
        for k in self.common_keys():
            out[k] = prim[k]
        out["estimators"] = {n: e.params_dict() for n, e in self.estimators.items()}
        return out

    # ----------------------------------------------------------------- the task
    async def run(self) -> None:
        """The engine task: forever take what is queued and process it."""
        try:
            await self._loop_forever()
        finally:  # nothing is drawn after the task has stopped (viser stops next)
            self._scene_timer.cancel()
            self._ws_timer.cancel()

    async def _loop_forever(self) -> None:
        inbox = self.inbox
        while True:
            items = [await inbox.get()]
            self._t_taken = time.perf_counter()
            while not inbox.empty():
                items.append(inbox.get_nowait())
            self.backlog_max = max(self.backlog_max, len(items))
            if any(it[0] != "samples" for it in items):
                self._flush_ws()    # what was estimated before goes out under the old settings
            for kind, *rest in items:
                if kind == "change":
                    self._apply(rest[0])
            arrivals = []
            for kind, *rest in items:
                if kind == "session":
                    self._start(rest[0])
                elif kind == "samples":
                    s, samples, t_arr = rest
                    self.queued -= len(samples)
                    if s is self.session:
                        self._process(s, samples)
                        arrivals.append((t_arr, len(samples)))
            if arrivals:
                self._publish(arrivals)

    def _start(self, s: Session) -> None:
        for est in self.estimators.values():
            est.reset()
        self._reset_stream_state()

    def _process(self, s: Session, samples: list[Sample]) -> None:
        """Step every estimator on each sample, in order; record the plots' rows and the
        WebSocket's estimates (sent later, batched: :meth:`_flush_ws`)."""
        primary = self.primary
        # per estimator, looked up once per batch: (is primary, estimator, its counts,
        # its last flags, whether it reports L_k)
        ests = [(name == primary, est, self.reason_counts[name], self.last_flags[name],
                 self._has_lk[name]) for name, est in self.estimators.items()]
        pose, acc_ring, mag_ring = self.history.pose, self.history.acc, self.history.mag
        records = self._ws_pending if self.subscribers else None
        phone_q = self.phone_q
        n = 0
        for smp in samples:
            tag = smp.tag
            t = smp.time_ms / 1000.0
            self.t_sent = t
            n += 1
            sensor = SENSOR_OF_TAG.get(tag)
            if sensor is not None:
                v = np.array(smp.values, dtype=float)
                if sensor != "gyr":
                    self.last_vec[sensor] = v
                kw = {sensor: v}
                si = SENSORS.index(sensor)
            elif tag == "ORI":  # the phone estimator checks and holds it (see phone_q)
                kw = {"ori": np.array(smp.values, dtype=float)}
            else:
                continue
            for is_primary, est, counts, lf, has_lk in ests:
                f = est.step(t, **kw)
                if sensor is not None:
                    counts[si][getattr(f, sensor)] += 1
                    lf[sensor] = f
                    if si == 0:
                        lf["rest"] = f
                if is_primary:
                    q = est.q
                    if sensor == "acc":
                        row = acc_ring.next_row()
                        row[0], row[H_NORM], row[H_NIS_A] = t, math.sqrt(float(v @ v)), f.acc_nis
                    elif sensor == "mag":
                        row = mag_ring.next_row()
                        row[0], row[H_NORM], row[H_NIS_M] = t, math.sqrt(float(v @ v)), f.mag_nis
                        lk = _num(est.diagnostics().get("L_k")) if has_lk else None
                        if lk is not None:
                            row[H_LK] = lk
            if tag == "ORI":
                phone_q = self.phone_q
            row = pose.next_row()
            row[0] = t
            row[H_Q:H_Q + 4] = q
            if phone_q is not None:
                row[H_P:H_P + 4] = phone_q
            if records is not None:
                records.append((t, tag, q.tolist()))
        s.samples += n
        self.counts_total["samples"] += n

    def _publish(self, arrivals: list[tuple[float, int]]) -> None:
        """Hand the primary's new pose to the scene (every batch: that moment ends the
        latency measurement), then let the rest follow at display rate."""
        self.batches += 1
        if self.pose_listeners:
            q = self.estimators[self.primary].q
            for cb in self.pose_listeners:
                try:
                    cb(q)
                except Exception:
                    log.exception("pose listener failed")
        now = time.perf_counter()
        for t_arr, n in arrivals:
            self.latency.append((now - t_arr, self._t_taken - t_arr, n))
        self._scene_timer.poke()
        if self._ws_pending:
            self._ws_timer.poke()

    def _draw_scene(self) -> None:
        """Everything else in the scene (cones, arrows, other phones, indicators)."""
        if not self.listeners:
            return
        snap = self.snapshot()
        for cb in self.listeners:
            try:
                cb(snap)
            except Exception:
                log.exception("scene listener failed")

    def _flush_ws(self) -> None:
        """Send the estimates made since the last flush, one message encoded once for
        every subscriber (none is skipped)."""
        pending = self._ws_pending
        if not pending:
            return
        self._ws_pending = []
        if not self.subscribers:
            return
        msg = json.dumps({"primary": self.primary, "source": self.source_kind(),
                          "estimates": [{"t": t, "tag": tag, "q": q} for t, tag, q in pending]})
        for sub in list(self.subscribers):
            sub.put_nowait(msg)

    # ----------------------------------------------------------------- read-outs
    def truth_q(self) -> np.ndarray | None:
        s = self.session
        if s is None or s.truth is None or self.t_sent is None:
            return None
        return np.asarray(s.truth(np.array([self.t_sent * 1000.0])), dtype=float)[0]

    def snapshot(self) -> Snapshot:
        est = self.estimators[self.primary]
        lf = self.last_flags[self.primary]
        rest = lf.get("rest")
        return Snapshot(t=self.t_sent, primary=self.primary, q=est.q, initialized=est.initialized,
                        phone_q=self.phone_q, truth_q=self.truth_q(), cov=est.attitude_cov(),
                        acc=self.last_vec["acc"], mag=self.last_vec["mag"],
                        acc_flags=lf.get("acc"), mag_flags=lf.get("mag"),
                        rest=bool(rest.rest) if rest is not None else False,
                        diag=est.diagnostics(),
                        estimators={n: e.q for n, e in self.estimators.items()})

    def source_kind(self) -> str:
        s = self.session
        if s is None:
            return "none"
        if s.kind == "phone" and not s.open:
            return "phone-disconnected"
        return s.kind

    def status_text(self) -> str:
        s = self.session
        if s is None:
            return "waiting for a phone"
        if s.kind == "demo":
            return "demo: simulated phone (a phone that connects takes over)"
        if s.kind == "replay":
            return f"replaying log {s.label}" + ("" if s.open else " (ended)")
        if s.open:
            return f"phone {s.label} streaming"
        return (f"phone {s.label} disconnected ({s.close_reason}): showing its last state; "
                "waiting for a phone")

    def rates(self) -> dict[str, float | None]:
        if self.session is None:
            return {}
        return {k: _num(v) for k, v in self.session.orderer.rates().items()}

    def counts(self) -> dict[str, Any]:
        c = self.session.counts() if self.session else {"lines": 0, "samples": 0, "malformed": 0}
        c.update({f"total_{k}": v for k, v in self.counts_total.items()})
        c["queued"] = self.queued
        c["updates"] = {n: {s: {Reason(i).label: int(x) for i, x in enumerate(row) if x}
                            for s, row in zip(SENSORS, arr)}
                        for n, arr in self.reason_counts.items()}
        return c

    def estimator_state(self, name: str) -> dict[str, Any]:
        est = self.estimators[name]
        q = est.q
        err = None if self.phone_q is None else math.degrees(angle_between(self.phone_q, q))
        tq = self.truth_q()
        lf = self.last_flags[name]
        return {"q": _qlist(q), "euler_deg": [float(np.degrees(a)) for a in q2euler(q)],
                "initialized": bool(est.initialized), "error_to_phone_deg": _num(err),
                "error_to_truth_deg": None if tq is None else _num(math.degrees(angle_between(tq, q))),
                "acc": decision_dict(lf.get("acc"), "acc"), "mag": decision_dict(lf.get("mag"), "mag"),
                "gyr_bias": None if est.gyr_bias is None else _qlist(est.gyr_bias)}

    def state(self) -> dict[str, Any]:
        """GET /api/state (see :class:`app.server.models.State`)."""
        prim = self.estimator_state(self.primary)
        lf = self.last_flags[self.primary]
        rest = lf.get("rest")
        diag = {k: (list(v) if isinstance(v, (tuple, list)) else v)
                for k, v in self.estimators[self.primary].diagnostics().items()}
        cov = self.estimators[self.primary].attitude_cov()
        sigma = None if cov is None else [_num(math.degrees(math.sqrt(max(c, 0.0))))
                                          for c in np.diag(cov)]
        return {
            "t": self.t_sent, "source": self.source_kind(), "status": self.status_text(),
            "primary": self.primary, "q": prim["q"], "euler_deg": prim["euler_deg"],
            "initialized": prim["initialized"],
            "phone_q": _qlist(self.phone_q),
            "phone_euler_deg": None if self.phone_q is None
            else [float(np.degrees(a)) for a in q2euler(self.phone_q)],
            "truth_q": _qlist(self.truth_q()),
            "error_to_phone_deg": prim["error_to_phone_deg"],
            "error_to_truth_deg": prim["error_to_truth_deg"],
            "acc_rejected": prim["acc"]["rejected"], "mag_rejected": prim["mag"]["rejected"],
            "acc": prim["acc"], "mag": prim["mag"],
            "standstill": bool(rest.rest) if rest is not None else False,
            "sigma_deg": sigma,
            "diagnostics": _json_safe(diag),
            "rates_hz": self.rates(), "counts": self.counts(),
            "clock_offsets_s": self.session.orderer.offsets if self.session else {},
            "estimators": {n: self.estimator_state(n) for n in self.estimators},
        }

    def stats(self, reset: bool = False) -> dict[str, Any]:
        """GET /api/stats: backlog and latency figures (for the load benchmark)."""
        # vectorised: this runs on the event loop, it must not hold it up
        chunks = np.array(self.latency, dtype=float).reshape(-1, 3)
        rows = np.repeat(chunks[:, :2], chunks[:, 2].astype(np.int64), axis=0)
        out = {"batches": self.batches, "backlog_now": self.inbox.qsize() if self.inbox else 0,
               "queued_samples": self.queued,
               "backlog_max_items": self.backlog_max,
               "buffered": self.session.orderer.buffered if self.session else 0,
               "samples": self.counts_total["samples"],
               # arrival of the chunk -> the primary's pose handed to viser (every sample)
               "latency_ms": _percentiles(rows[:, 0]),
               # of which: arrival -> the engine task took the chunk (the loop was busy)
               "wait_ms": _percentiles(rows[:, 1]),
               "loop_lag_ms": _percentiles(np.array(self.loop_lag, dtype=float))}
        if reset:
            self.latency.clear()
            self.loop_lag.clear()
            self.backlog_max = 0
        return out


def _percentiles(x: np.ndarray) -> dict[str, Any]:
    """Median, 99th percentile and max of durations in seconds, in ms."""
    if not x.size:
        return {"n": 0, "median": None, "p99": None, "max": None}
    ms = x * 1e3
    return {"n": int(ms.size), "median": _num(np.median(ms)), "p99": _num(np.percentile(ms, 99)),
            "max": _num(ms.max())}


def _json_safe(x):
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return _json_safe(x.tolist())
    if isinstance(x, (float, np.floating)):
        return _num(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    return x
