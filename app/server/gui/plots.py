"""The live plots' data: the feed of WS /ws/plots, and helpers for viser's uPlot charts.

**The dashboard's plots** (Euler angles, error angle, |acc|, |mag| and L_k, NIS) are drawn
by the landing page (``static/plots.js``, uPlot vendored under ``static/vendor/``) beside
the 3D view. :class:`PlotFeed` reads the live core's history rings and sends, over
WS /ws/plots, the whole window once, then only the new points, up to 20 times a second
(:data:`app.server.engine.PLOT_HZ`); the page appends them and redraws each chart in its
canvas (viser 1.1's uPlot handle takes whole data only: every refresh resent every window
and re-created the chart). Every x is seconds since the stream started (one clock for all
plots); values are rounded to what the sensors tell; gaps are ``null``. The page unwraps
yaw and roll over its window as :func:`unwrap_deg` does (no vertical strokes at ±180°,
no comb when the phone faces south).

**viser's charts** (the Lab tab's heading plots, unwrapped by :func:`unwrap_deg` here)
use :func:`send_data`. Why the data goes
out as lists with ``null`` and not as arrays with NaN: viser sends a float array as a
``Float64Array``, where a missing value can only be NaN, and uPlot does not treat NaN as
a gap: a series whose first value in view is NaN (or that is NaN throughout) turns its
chart's y range into NaN and the *whole chart* is drawn empty, every series of it.
uPlot's own gap marker is ``null``; viser's handle would cast a list back to a float
array (``plot.data = ...``), so :func:`send_data` queues the update itself with plain
lists (``None`` for every non-finite value), each value put on a binary grid
(:func:`quantize`: x to :data:`X_STEP`, y to 1/2^:data:`Y_BITS` of its column's span, or
to :data:`Y_BITS` significant bits on a log scale). The grid is far finer than a pixel,
and a float on it ends in zero bytes, which viser's zstd compression then nearly
removes. A constant line (a gate band) goes out as its two ends with gaps between
(:func:`ends`; its series spans gaps).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Iterable, Sequence

import numpy as np

try:
    import msgspec
except ImportError:  # pragma: no cover - viser depends on it
    msgspec = None

from app.quaternion import angle_between_many, q2euler_many
from app.sources.ordering import STOPPED_S
from app.server import viser_adapter as va

_JSON = msgspec.json.Encoder() if msgspec is not None else None

EULER_COLORS = ("#d62728", "#2ca02c", "#1f77b4")


X_STEP = 2.0 ** -14   # s: 61 µs, far finer than a pixel of a 20 s window
Y_BITS = 12           # a y value to 1/4096 of its column's span: sub-pixel at any chart height


def quantize(a: np.ndarray, log: bool = False, step: float | None = None) -> np.ndarray:
    """``a`` rounded to a binary grid: multiples of ``step`` if given (a power of two),
    else of the power of two nearest below 1/2^:data:`Y_BITS` of the finite values'
    span (their magnitude if they are all equal); with ``log``, each value to
    :data:`Y_BITS` significant bits (a log scale shows relative size; no positive value
    becomes zero). Non-finite values stay as they are. The result differs from ``a``
    by at most half a step, and its floats end in zero bits (they compress well)."""
    a = np.asarray(a, dtype=float)
    ok = np.isfinite(a)
    if not ok.any():
        return a.copy()
    if log:
        m, e = np.frexp(np.where(ok, a, 0.0))
        out = np.ldexp(np.round(m * 2.0 ** Y_BITS) / 2.0 ** Y_BITS, e)
        return np.where(ok, out, a)
    if step is None:
        fin = a[ok]
        span = float(fin.max() - fin.min()) or float(np.abs(fin).max())
        if span == 0.0:
            return a.copy()
        step = 2.0 ** (math.floor(math.log2(span)) - Y_BITS)
    return np.round(a / step) * step


def wire(a: np.ndarray, log: bool = False, step: float | None = None) -> list:
    """A float array as a list for uPlot: ``None`` (a gap) where it is not finite,
    finite values on :func:`quantize`'s grid (the chart cannot show more; the wire
    carries less)."""
    a = quantize(a, log, step)
    ok = np.isfinite(a)
    out = a.tolist()
    if not ok.all():
        for i in np.flatnonzero(~ok).tolist():
            out[i] = None
    return out


def send_data(handle, columns: Sequence[np.ndarray], log: bool = False) -> None:
    """Replace a uPlot chart's data (x, then the series; ``log``: a log y scale);
    NaN and inf become gaps (see the module doc). Queued by the handle's own update
    path, without its setter's cast (:func:`app.server.viser_adapter.queue_update`)."""
    cols = (wire(columns[0], step=X_STEP),) + tuple(wire(c, log) for c in columns[1:])
    va.queue_update(handle, "data", packed(cols))


def packed(value):
    """``value`` encoded as msgpack once, here: viser's sender otherwise walks a list
    element by element, for every viewer, before encoding it (a third of the server's
    Python time with five viewers); a ``msgspec.Raw`` goes into each message as it is.
    The bytes are the same either way (viser encodes with msgspec)."""
    if msgspec is None:  # pragma: no cover - viser always brings msgspec
        return value
    return msgspec.Raw(msgspec.msgpack.encode(value))


def ends(x: np.ndarray, v: float | None) -> np.ndarray:
    """A constant line over ``x`` as its two ends (NaN between; NaN throughout when
    ``v`` is None): drawn whole by a series that spans gaps, two numbers on the wire."""
    out = np.full(np.shape(x), np.nan)
    if v is not None and out.size:
        out[0] = out[-1] = float(v)
    return out


def during(t: np.ndarray, y: np.ndarray, spans: Iterable[tuple[float, float]]) -> np.ndarray:
    """``y`` where ``t`` lies in one of the ``spans`` (start, end), NaN (a gap) elsewhere:
    a series drawn over another while something (an injected disturbance) was on."""
    on = np.zeros(np.shape(t), dtype=bool)
    for a, b in spans:
        on |= (t >= a) & (t <= b)
    return np.where(on, y, np.nan)


def break_wraps(deg: np.ndarray, jump: float = 180.0) -> np.ndarray:
    """An angle series (deg, rows) with NaN put where it wraps around (a jump of more
    than ``jump`` between neighbours), so the chart shows a break, not a spike."""
    out = np.array(deg, dtype=float, copy=True)
    if out.shape[0] < 2:
        return out
    d = np.abs(np.diff(out, axis=0))
    wrap = np.zeros(out.shape, dtype=bool)
    wrap[1:] = d > jump
    out[wrap] = np.nan
    return out


def unwrap_deg(deg: np.ndarray, max_span: float = 540.0, align: bool = False) -> np.ndarray:
    """Angle columns (deg, ±180) unwrapped over the window (no jump of 360° between
    neighbours, across NaN gaps too), shifted by whole turns so that each column's
    newest value lies in [-180, 180]: a phone facing south draws a calm line near 180°
    instead of a comb between +180 and -180. A column that turned more than
    ``max_span`` degrees in the window (a phone spun round and round) stays in ±180
    with a break (a gap) where it wraps, so the chart keeps a readable scale.

    ``align``: one angle in every column (the estimators' headings, before and after):
    each unwrapped column is shifted, row by row, by whole turns to lie nearest the first
    unwrapped one, so two headings at +179° and -179° are drawn 2° apart, not 358°. Row by
    row: through pitch ±90° yaw and roll jump by 180°, and two columns unwrapped alone may
    take that jump in opposite directions (aligned at one row, the rest of the window was
    still drawn a turn apart)."""
    out = np.array(deg, dtype=float, copy=True)
    unwrapped = np.zeros(out.shape[1], dtype=bool)
    for k in range(out.shape[1]):
        col = out[:, k]
        ok = np.flatnonzero(np.isfinite(col))
        if ok.size < 2:
            continue
        u = np.degrees(np.unwrap(np.radians(col[ok])))
        u -= 360.0 * np.round(u[-1] / 360.0)
        if np.ptp(u) <= max_span:
            col[ok] = u
            unwrapped[k] = True
        else:
            out[:, k] = break_wraps(col)
    cols = np.flatnonzero(unwrapped)
    if align and cols.size > 1:
        ref = out[:, cols[0]]
        for k in cols[1:]:
            both = np.isfinite(ref) & np.isfinite(out[:, k])
            out[both, k] -= 360.0 * np.round((out[both, k] - ref[both]) / 360.0)
    return out


def angle_deg(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Row-wise angle between two arrays of unit quaternions (deg): formula 2c."""
    return np.degrees(angle_between_many(qa, qb))


# --------------------------------------------------------------------------- live feed
# The dashboard's plots are drawn by the landing page (static/plots.js, uPlot vendored
# under static/vendor/), fed by WS /ws/plots: a first message with the whole window, then
# only the new points, STREAM_HZ times a second. viser 1.1's uPlot handle takes whole
# data only (every refresh resent every window and re-created the chart's canvas).

STREAM_HZ = 20.0        # /ws/plots messages a second (at most; only while samples come)
POINTS_PER_S = 25.0     # per ring: at most one row per 1/POINTS_PER_S s of stream time
NIS_FLOOR = 1e-3        # the NIS plot's lowest value (a log axis labels 1e-4 as "0")

# decimals on the wire: what the sensors can tell (and what a chart can show)
_DEC_X = 3              # s (1 ms)
_DEC_DEG = 2            # deg
_DEC_ACC = 3            # m/s²
_DEC_MAG = 2            # µT

POSE_SERIES = ("yaw", "pitch", "roll", "phone yaw", "phone pitch", "phone roll",
               "vs phone's own", "to truth")


def _r(a: np.ndarray, d: int) -> list:
    """Rounded to ``d`` decimals, as a list (NaN: null in msgspec's JSON)."""
    return np.round(np.asarray(a, dtype=float), d).tolist()


def _sig(a, digits: int = 3) -> list:
    """To ``digits`` significant digits (a log scale), as a list; not positive: null."""
    return [float(f"{v:.{digits}g}") if v > 0 and math.isfinite(v) else None
            for v in np.asarray(a, dtype=float).tolist()]


class PlotFeed:
    """What WS /ws/plots sends: the plots' rows, from the live core's history rings.

    One feed per dashboard, on the event loop (the engine calls :meth:`delta` at most
    :data:`STREAM_HZ` times a second, and :meth:`snapshot` for a new client: both read
    the rings up to the same cursors, so a client gets every row once). Per ring, one
    row per 1/:data:`POINTS_PER_S` s of stream time goes out (a time bin, sent once it is
    complete: :meth:`_decimate`): a plot's cost does not grow with the phone's rate.

    Messages (JSON): ``{"k": "s"|"d", "now": x, "pose": [x, yaw, pitch, roll, phone yaw,
    phone pitch, phone roll, difference from the phone's own, error to truth], "acc": [x, |acc|,
    NIS], "mag": [x, |mag|, L_k, NIS], "meta": {...}}``; columns as lists, ``null`` a
    gap; every ``x`` in s since the stream started (one clock for every plot). ``"s"``
    (a snapshot: the whole window, a new stream) replaces what a client holds; ``"d"``
    appends. ``meta`` (in a delta only its keys that changed): the window ``span`` (s),
    ``stale_s`` (a legend's figure further behind the newest is not shown as live),
    the ``primary``, the gate bands and NIS gates, the injected disturbances (``spans``:
    kind, from, to or null while on) and, per plot, why it may be empty (``why``).
    """

    def __init__(self, core, span_s: float, injections: Callable[[Any], list] | None = None):
        self.core = core
        self.span_s = float(span_s)
        self.injections = injections          # (session) -> [(kind, start, end)] stream s
        self.dt = 1.0 / POINTS_PER_S
        self._reset()

    def _reset(self) -> None:
        self.session = self.core.session
        h = self.core.history
        self.rings = {"pose": h.pose, "acc": h.acc, "mag": h.mag}
        self.cursor = {k: r.n for k, r in self.rings.items()}     # rows read (logical)
        self._meta: dict[str, Any] = {}        # the meta last sent (a delta sends what changed)
        self.messages = 0

    # ------------------------------------------------------------------ reading
    def _rows(self, name: str, lo: int, hi: int) -> np.ndarray:
        ring = self.rings[name]
        lo = max(lo, ring.n - ring.capacity, 0)
        if hi <= lo:
            return ring.data[:0]
        return ring.data[np.arange(lo, hi) % ring.capacity]

    def _bins(self, rows: np.ndarray) -> np.ndarray:
        return np.floor(rows[:, 0] / self.dt)

    def _decimate(self, rows: np.ndarray) -> np.ndarray:
        """One row per time bin (1/:data:`POINTS_PER_S` s): the time of the bin's first
        row and, per column, the first finite value in the bin (a sensor whose NIS is
        made on every other sample still has one in each bin)."""
        if len(rows) < 2:
            return rows
        b = self._bins(rows)
        new = np.concatenate(([True], b[1:] != b[:-1]))
        gid = np.cumsum(new) - 1
        out = np.full((int(gid[-1]) + 1, rows.shape[1]), np.nan)
        out[:, 0] = rows[new, 0]
        for c in range(1, rows.shape[1]):
            v = rows[:, c]
            idx = np.flatnonzero(np.isfinite(v))
            if idx.size:
                g, first = np.unique(gid[idx], return_index=True)
                out[g, c] = v[idx[first]]
        return out

    def _complete(self, name: str) -> np.ndarray:
        """The rows since the cursor whose time bin is complete (a later row exists),
        the cursor moved past them."""
        ring = self.rings[name]
        rows = self._rows(name, self.cursor[name], ring.n)
        if not len(rows):
            return rows
        b = self._bins(rows)
        k = int(np.searchsorted(b, b[-1], side="left"))   # times rise: a prefix is complete
        if self.cursor[name] < ring.n - ring.capacity:      # fell out of the ring meanwhile
            self.cursor[name] = ring.n - ring.capacity
        self.cursor[name] = max(self.cursor[name], ring.n - len(rows)) + k
        return rows[:k]

    def _t0(self) -> float | None:
        return self.core.t_first

    def _columns(self, name: str, rows: np.ndarray, t0: float) -> list:
        ring = self.rings[name]
        x = _r(rows[:, 0] - t0, _DEC_X)

        def col(c):
            sl = ring.cols[c]
            return rows[:, sl.start] if sl.stop - sl.start == 1 else rows[:, sl]
        if name == "pose":
            q, pq = col("q"), col("phone_q")
            ours = np.degrees(q2euler_many(q)) if len(rows) else np.zeros((0, 3))
            has_q = np.isfinite(q[:, 0])
            ours[~has_q] = np.nan
            has_p = np.isfinite(pq[:, 0])
            phone = np.full_like(ours, np.nan)
            err_p = np.full(len(rows), np.nan)
            if has_p.any():
                phone[has_p] = np.degrees(q2euler_many(pq[has_p]))
                ok = has_p & has_q
                if ok.any():
                    err_p[ok] = angle_deg(q[ok], pq[ok])
            err_t = np.full(len(rows), np.nan)
            truth = self.session.truth if self.session is not None else None
            if truth is not None and has_q.any():
                err_t[has_q] = angle_deg(q[has_q], truth(rows[has_q, 0] * 1000.0))
            return [x, *(_r(ours[:, k], _DEC_DEG) for k in range(3)),
                    *(_r(phone[:, k], _DEC_DEG) for k in range(3)),
                    _r(err_p, _DEC_DEG), _r(err_t, _DEC_DEG)]
        nis = np.asarray(col("nis"), dtype=float).copy()
        nis[~(nis > 0)] = np.nan       # a zero (exact fit) cannot sit on a log scale
        np.maximum(nis, NIS_FLOOR, out=nis, where=np.isfinite(nis))
        if name == "acc":
            return [x, _r(col("norm"), _DEC_ACC), _sig(nis)]
        return [x, _r(col("norm"), _DEC_MAG), _r(col("L_k"), _DEC_MAG), _sig(nis)]

    # ------------------------------------------------------------------ meta
    def meta(self) -> dict[str, Any]:
        core = self.core
        primary = core.ensemble.primary
        diag = core.ensemble.estimator(primary).diagnostics()
        t0 = self._t0()
        spans = []
        s = self.session
        if self.injections is not None and s is not None and t0 is not None:
            for kind, a, b in self.injections(s):
                spans.append([kind, round(a - t0, _DEC_X),
                              None if not math.isfinite(b) else round(b - t0, _DEC_X)])
        band = lambda b: None if b is None else [round(float(b[0]), 2), round(float(b[1]), 2)]  # noqa: E731
        gate = lambda g: None if not g or not math.isfinite(float(g)) else float(_sig([g])[0])  # noqa: E731
        ori = " (it needs the phone's Orientation sensor, ORI)" if core.ensemble.is_reference(primary) else ""
        live = core.session
        gone = live.stopped() if live is not None else frozenset()
        held = live.withheld if live is not None else {}

        def none_of(tag: str, what: str) -> str:
            if tag in held:
                return f"the phone sends its {what}, held back: {held[tag]}"
            if tag in gone:
                return f"the {what} stopped sending while the stream goes on (switched off in the app?)"
            return f"no {what} samples in this stream"
        return {
            "span": self.span_s, "primary": primary,
            # a legend's newest figure further behind the stream than this is no live
            # value (its sensor stopped): the orderer's own limit
            "stale_s": STOPPED_S,
            # the gates: robust's learned |mag| band moves a little all the time (0.1 µT:
            # what a magnetometer can tell)
            "acc_band": band(diag.acc_band), "mag_band": band(diag.mag_band),
            "acc_gate": gate(diag.acc_nis_gate), "mag_gate": gate(diag.mag_nis_gate),
            "spans": spans,
            "why": {
                "euler": f"{primary} has no estimate yet{ori}",
                "error": none_of("ORI", "orientation (ORI)") if "ORI" in held else
                         "no reference in this stream (the phone's Orientation sensor, ORI, "
                         "or the demo's truth)",
                "acc": none_of("ACC", "accelerometer"),
                "mag": none_of("MAG", "magnetometer"),
                "nis": f"{primary} makes no Kalman update to test",
            },
        }

    # ------------------------------------------------------------------ messages
    def _stream_changed(self) -> bool:
        return self.core.session is not self.session or any(
            r.n < self.cursor[k] for k, r in self.rings.items())

    def _message(self, kind: str, parts: dict[str, np.ndarray], meta: dict | None) -> bytes:
        t0 = self._t0()
        msg: dict[str, Any] = {"k": kind}
        newest = None
        for name, rows in parts.items():
            if t0 is None or not len(rows):
                msg[name] = None
                continue
            msg[name] = self._columns(name, rows, t0)
            newest = max(newest if newest is not None else -math.inf, float(rows[-1, 0]) - t0)
        if newest is None and t0 is not None and self.core.t_sent is not None:
            newest = self.core.t_sent - t0
        msg["now"] = None if newest is None else round(newest, _DEC_X)
        if meta is not None:
            msg["meta"] = meta
        self.messages += 1
        return _JSON.encode(msg)

    def snapshot(self) -> bytes:
        """The whole window up to the feed's cursors (a new client's first message)."""
        parts = {}       # (the engine calls delta() first: a new stream is taken in)
        for name, ring in self.rings.items():
            hi = self.cursor[name]
            rows = self._rows(name, hi - ring.capacity, hi)
            if len(rows):
                rows = rows[rows[:, 0] >= rows[-1, 0] - self.span_s]
            parts[name] = self._decimate(rows)
        meta = self.meta()
        return self._message("s", parts, meta)

    def delta(self) -> bytes | None:
        """The rows since the last call (None: nothing new, nothing changed); after a new
        stream began, a snapshot of it (``"k": "s"``)."""
        kind = "d"
        if self._stream_changed():
            self._reset()
            self.cursor = {k: 0 for k in self.rings}
            kind = "s"
        parts = {name: self._decimate(self._complete(name)) for name in self.rings}
        meta = self.meta()
        if kind == "s":
            self._meta = meta
            return self._message(kind, parts, meta)
        changed = {k: v for k, v in meta.items() if self._meta.get(k) != v}
        self._meta = meta
        if not changed and not any(len(p) for p in parts.values()):
            return None
        return self._message(kind, parts, changed or None)
