"""The live plots: uPlot charts in viser's panel, fed from the engine's history rings.

Why the data goes out as lists with ``null`` and not as arrays with NaN: viser sends a
float array as a ``Float64Array``, where a missing value can only be NaN, and uPlot
does not treat NaN as a gap: a series whose first value in view is NaN (or that is NaN
throughout) turns its chart's y range into NaN and the *whole chart* is drawn empty,
every series of it. uPlot's own gap marker is ``null``; viser's handle would cast a
list back to a float array (``plot.data = ...``), so :func:`send_data` queues the
update itself with plain lists (``None`` for every non-finite value). Checked with
viser 1.1.1 in Chromium (``tests/server/test_plots_browser.py`` looks at the pixels).

What a viewer receives (every chart is resent whole: viser has no append): at most
:data:`~app.server.gui.main.MAX_POINTS` rows per chart (about the chart's width in pixels),
a few times a second, each value put on a binary grid (:func:`quantize`: x to
:data:`X_STEP`, y to 1/2^:data:`Y_BITS` of its column's span, or to :data:`Y_BITS`
significant bits on a log scale). The grid is far finer than a pixel, and a float on
it ends in zero bytes, which viser's zstd compression then nearly removes: a value
costs about 2 bytes on the wire instead of 8. A constant line (a gate band) goes out
as its two ends with gaps between (:func:`ends`; its series spans gaps).

Every x axis is seconds since the stream started. Angles are kept in their usual
ranges only when the phone spun round: yaw and roll are unwrapped over the window
(no vertical strokes at ±180°, no comb when the phone faces south), see
:func:`unwrap_deg`.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Sequence

import numpy as np

try:
    import msgspec
except ImportError:  # pragma: no cover - viser depends on it
    msgspec = None

from app.quaternion import angle_between_many
from app.server import viser_adapter as va

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


def unwrap_deg(deg: np.ndarray, max_span: float = 540.0) -> np.ndarray:
    """Angle columns (deg, ±180) unwrapped over the window (no jump of 360° between
    neighbours, across NaN gaps too), shifted by whole turns so that each column's
    newest value lies in [-180, 180]: a phone facing south draws a calm line near 180°
    instead of a comb between +180 and -180. A column that turned more than
    ``max_span`` degrees in the window (a phone spun round and round) stays in ±180
    with a break (a gap) where it wraps, so the chart keeps a readable scale."""
    out = np.array(deg, dtype=float, copy=True)
    for k in range(out.shape[1]):
        col = out[:, k]
        ok = np.flatnonzero(np.isfinite(col))
        if ok.size < 2:
            continue
        u = np.degrees(np.unwrap(np.radians(col[ok])))
        u -= 360.0 * np.round(u[-1] / 360.0)
        if np.ptp(u) <= max_span:
            col[ok] = u
        else:
            out[:, k] = break_wraps(col)
    return out


def angle_deg(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Row-wise angle between two arrays of unit quaternions (deg): formula 2c."""
    return np.degrees(angle_between_many(qa, qb))


def series(specs: Iterable[tuple], x_label: str = "t [s]") -> tuple[dict[str, Any], ...]:
    """uPlot series: the x series, then one per ``(label, colour, dashed, span_gaps,
    width)`` (the last two optional)."""
    out: list[dict[str, Any]] = [{"label": x_label}]
    for spec in specs:
        label, color, dash = spec[:3]
        span = spec[3] if len(spec) > 3 else False
        width = spec[4] if len(spec) > 4 else 1.5
        s: dict[str, Any] = {"label": label, "stroke": color, "width": width}
        if dash:
            s["dash"] = [6, 4]
        if span:
            s["spanGaps"] = True
        out.append(s)
    return tuple(out)


X_HOP_S = 5.0   # s: the x window moves in whole steps of this (a chart is rebuilt then)


def x_window(x: np.ndarray, span_s: float, hop_s: float = X_HOP_S) -> tuple[float, float]:
    """The x range a chart shows for data ``x`` (s since the stream started): ``span_s``
    wide, its right end the newest x rounded up to a whole ``hop_s`` (so the range
    changes only every ``hop_s``), its left end not left of 0 (nor of the whole hop
    below the oldest x, when that is negative), so a young stream fills its chart and
    every chart of one stream shows the same window: [0, 5], [0, 10], ..., [5, 25],
    [10, 30] for a 20 s span."""
    fin = np.asarray(x, dtype=float)
    fin = fin[np.isfinite(fin)]
    if not fin.size:
        return 0.0, hop_s
    hi = hop_s * max(1.0, math.ceil(float(fin.max()) / hop_s - 1e-9))
    lo = max(hi - span_s, min(0.0, hop_s * math.floor(float(fin.min()) / hop_s)))
    return lo, hi


class Plot:
    """One chart and what it needs to be worth showing.

    Its x range is set here, explicitly (:func:`x_window`), not left to the browser:
    viser's chart keeps its x scale across data updates and re-ranges it only from a
    React effect that runs when the data's x extent changes; when the extent did not
    change between two renders the client drew (updates coalesced under load) the
    scale stayed on an early window, and a chart showed only its first seconds: nothing
    of a filter that had not yet aligned there (the plot test's intermittent failure).
    A fixed range (a tuple, which viser keeps through every redraw) makes the chart
    rebuild itself when the window moves, every :data:`X_HOP_S`; the y scales re-range
    from the data at every update (uPlot's redraw)."""

    def __init__(self, gui, key: str, title: str, specs: list[tuple], *, height: int = 150,
                 y_scale: dict | None = None, span_s: float = 20.0):
        self.key = key
        self.title = title
        self.specs = specs
        self.span_s = float(span_s)
        self._y_scale = dict(y_scale) if y_scale else None
        self._x_range = (0.0, X_HOP_S)
        s = series(specs)
        self.log = bool(y_scale and y_scale.get("distr") == 3)   # a log y scale
        self.handle = gui.add_uplot(data=tuple(np.zeros(2) for _ in s), series=s, title=title,
                                    scales=self._scales(), height=height, aspect=2.0)
        self.visible = True
        self.has_data = False          # something finite was drawn at the last update

    def _scales(self) -> dict[str, Any]:
        scales: dict[str, Any] = {"x": {"time": False, "range": list(self._x_range)}}
        if self._y_scale:
            scales["y"] = self._y_scale
        return scales

    @property
    def x_range(self) -> tuple[float, float]:
        """The x range on show (s since the stream started)."""
        return self._x_range

    @property
    def colors(self) -> list[str]:
        return [s[1] for s in self.specs]

    def update(self, x: np.ndarray, *ys: np.ndarray) -> None:
        """New data, and a new x range when the window has moved on (see the class doc)."""
        send_data(self.handle, (x, *ys), self.log)
        rng = x_window(x, self.span_s)
        if rng != self._x_range:
            self._x_range = rng
            self.handle.scales = self._scales()
        self.has_data = any(np.isfinite(np.asarray(y, float)).any() for y in ys)

    def show(self, on: bool) -> None:
        """Whether the chart has something to show. It stays on the page either way
        (empty axes, the note under the plots says why): a chart mounted again by
        viser's client starts at zero width and keeps a broken x window (drawn empty)
        when data are already there."""
        self.visible = on
