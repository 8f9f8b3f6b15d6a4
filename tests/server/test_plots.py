"""What the plots put on the wire (app/server/gui/plots.py): the live feed of WS /ws/plots
(the whole window once, then only new points, every row once, at most POINTS_PER_S rows a
second per sensor, one clock); and for the Lab tab's viser chart, values on a binary grid
finer than a pixel, gaps as null, a constant line as its two ends, angles unwrapped."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import zstandard

import json
from pathlib import Path

import pytest

from app.live import LiveCore
from app.server.gui.plots import (POINTS_PER_S, X_STEP, Y_BITS, PlotFeed, ends, quantize, unwrap_deg,
                                  wire)
from app.sources.ordering import STOPPED_S
from app.sources.simulate import simulate
from harness import feed_lines, log_lines

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "sensorfusion-app"
FULL_LOG = REAL / "alekodu_activityrecognition" / "sensorLog_20221024T182635_walking_hand.txt"


def test_quantize_stays_within_half_a_step_of_the_span():
    rng = np.random.default_rng(1)
    y = 40.0 + np.cumsum(rng.normal(0.0, 1.0, 300))
    q = quantize(y)
    span = y.max() - y.min()
    step = 2.0 ** (math.floor(math.log2(span)) - Y_BITS)
    assert np.max(np.abs(q - y)) <= step / 2 + 1e-12
    assert step <= span / 2 ** Y_BITS            # finer than 1/4096 of the chart's range
    assert np.all(np.round(q / step) * step == q)   # exactly on the grid


def test_quantize_keeps_small_spans_and_constants_and_log_values():
    still = 9.81 + np.array([0.0, 1e-4, -2e-4, 3e-4])      # a phone lying still
    q = quantize(still)
    assert np.max(np.abs(q - still)) <= (still.max() - still.min()) / 2 ** Y_BITS
    assert quantize(np.array([2.5, 2.5])).tolist() == [2.5, 2.5]
    assert quantize(np.zeros(3)).tolist() == [0.0, 0.0, 0.0]
    nis = np.array([1e-4, 0.5, 3.0, 2000.0])                 # a log scale: relative precision
    ql = quantize(nis, log=True)
    assert np.all(ql > 0)
    assert np.max(np.abs(ql / nis - 1.0)) <= 2.0 ** -Y_BITS


def test_wire_gaps_are_null_and_x_stays_within_half_a_step():
    assert wire(np.array([1.0, np.nan, np.inf, -np.inf, 2.0])) == [1.0, None, None, None, 2.0]
    assert wire(np.full(3, np.nan)) == [None, None, None]
    x = np.array([100.0, 100.5, 101.0001])
    assert np.max(np.abs(np.array(wire(x, step=X_STEP)) - x)) <= X_STEP / 2


def test_a_constant_line_is_its_two_ends():
    x = np.linspace(0.0, 20.0, 300)
    assert wire(ends(x, 3.5)) == [3.5] + [None] * 298 + [3.5]
    assert wire(ends(x, None)) == [None] * 300


def test_angles_unwrap_to_calm_lines_and_stay_together_when_aligned():
    rng = np.random.default_rng(1)
    wrap = lambda d: (d + 180.0) % 360.0 - 180.0   # noqa: E731 - as the estimators report
    south = 179.0 + rng.normal(0.0, 1.5, 200)          # a phone facing south: a comb at ±180
    south[-1] = 179.0                                   # ends at +179, the other at -179
    other = south + 2.0                                 # a second estimator, 2° off
    cols = np.column_stack((wrap(south), wrap(other)))
    cols[50:60, 0] = np.nan                             # a gap: unwrapped across it
    assert np.nanmax(np.abs(np.diff(cols[:, 0]))) > 300.0
    out = unwrap_deg(cols)
    for k in range(2):
        assert np.nanmax(np.abs(np.diff(out[:, k]))) < 20.0
        assert -180.0 <= out[-1, k] <= 180.0           # the newest value in ±180
    assert np.isnan(out[50:60, 0]).all()
    both = unwrap_deg(cols, align=True)
    np.testing.assert_allclose(both[:, 0], out[:, 0], equal_nan=True)   # the first as alone
    assert np.nanmax(np.abs(both[:, 1] - both[:, 0] - 2.0)) < 1e-9   # together
    assert abs(out[-1, 1] - out[-1, 0]) > 300.0        # unwrapped alone: drawn a turn apart
    # a phone spun round and round stays in ±180 with a gap where it wraps
    spin = wrap(np.linspace(0.0, 1080.0, 300))[:, None]
    spun = unwrap_deg(np.column_stack((spin[:, 0], spin[:, 0])), align=True)
    assert np.nanmax(np.abs(spun)) <= 180.0 and np.isnan(spun[:, 0]).sum() >= 2
    assert np.nanmax(np.abs(np.diff(spun[:, 0]))) < 20.0
    untouched = unwrap_deg(np.array([[np.nan], [10.0]]))   # one value: nothing to unwrap
    assert untouched[1, 0] == 10.0


def test_quantized_plot_data_compresses_to_a_fraction():
    """What viser does with a chart's update (msgpack, then zstd level 1): values on the
    grid cost less than a third of the raw floats."""
    rng = np.random.default_rng(0)
    x = 100.0 + np.cumsum(rng.uniform(0.05, 0.08, 300))
    ys = [np.cumsum(rng.normal(0.0, 1.0, 300)) * 3.0 for _ in range(3)]
    z = zstandard.ZstdCompressor(level=1)

    def size(cols):
        return len(z.compress(msgspec.msgpack.encode(cols)))
    raw = size([x.tolist()] + [y.tolist() for y in ys])
    grid = size([wire(x, step=X_STEP)] + [wire(y) for y in ys])
    assert grid < raw / 3


# ---------------------------------------------------------------- the live feed (WS /ws/plots)

def _stream(core, lines, feed, size=40, start=True):
    """Lines into the core chunk by chunk, the feed's delta after each; the messages."""
    s = core.open_session("phone", "test")
    core.start(s)
    out = []
    for i in range(0, len(lines), size):
        core.process(s, feed_lines(core, s, lines[i:i + size]))
        m = feed.delta()
        if m is not None:
            out.append(json.loads(m))
    return s, out


def _merge(msgs, name):
    """The rows of ``name`` a client holds after these messages (a snapshot replaces)."""
    cols = None
    for m in msgs:
        if m["k"] == "s":
            cols = None
        part = m.get(name)
        if part:
            cols = part if cols is None else [a + b for a, b in zip(cols, part)]
    return cols


def test_the_feed_sends_every_bin_once_at_a_bounded_rate_on_one_clock():
    if not FULL_LOG.is_file():
        pytest.skip(f"{FULL_LOG} not present")
    core = LiveCore(None, history_s=20.0)
    feed = PlotFeed(core, 20.0)
    lines = log_lines(FULL_LOG)[:4000]
    _, msgs = _stream(core, lines, feed)
    assert msgs[0]["k"] == "s" and all(m["k"] == "d" for m in msgs[1:])
    assert msgs[0]["meta"]["span"] == 20.0 and "why" in msgs[0]["meta"]
    assert msgs[0]["meta"]["stale_s"] == STOPPED_S     # the legend's limit: the orderer's
    for name, ncols in (("pose", 9), ("acc", 3), ("mag", 4)):
        cols = _merge(msgs, name)
        assert cols is not None and len(cols) == ncols
        x = np.array(cols[0])
        assert np.all(np.diff(x) > 0), name                  # every row once, in order
        # one row per 1/POINTS_PER_S s of stream time at most, whatever the phone's rate
        bins = np.floor((x + core.t_first) * POINTS_PER_S + 1e-6)
        assert len(np.unique(bins)) == len(bins), name
        assert len(x) <= (x[-1] - x[0]) * POINTS_PER_S + 2
        assert len(x) >= 0.8 * (x[-1] - x[0]) * POINTS_PER_S, name   # and not fewer
        assert x[0] >= 0.0 and x[0] < 1.0                    # s since the stream started
    # one clock: the newest x of every sensor within a bin or two of the others
    newest = [_merge(msgs, n)[0][-1] for n in ("pose", "acc", "mag")]
    assert max(newest) - min(newest) < 0.2
    # a new client's snapshot holds what the deltas gave, up to the same rows
    snap = json.loads(feed.snapshot())
    for name in ("pose", "acc", "mag"):
        got = _merge(msgs, name)
        s = snap[name]
        k = len(s[0])
        assert k > 0 and s[0] == got[0][-k:], name
    # values rounded to what the sensors tell: degrees to 0.01, |acc| to 1 mm/s², µT to 0.01
    pose = _merge(msgs, "pose")
    assert all(v is None or round(v, 2) == v for v in pose[1])
    acc = _merge(msgs, "acc")
    assert all(v is None or round(v, 3) == v for v in acc[1])


def test_a_new_stream_starts_with_a_snapshot_and_the_reasons_for_empty_plots():
    core = LiveCore(None, history_s=20.0)
    feed = PlotFeed(core, 20.0)
    lines = simulate(("still",), seed=1).lines()[:600]
    _, first = _stream(core, lines, feed)
    assert first and first[0]["k"] == "s"
    _, second = _stream(core, lines, feed)
    assert second[0]["k"] == "s"                   # the client drops the old stream's rows
    x = _merge(second, "pose")[0]
    assert x[0] < 1.0                              # the new stream's clock
    why = second[0]["meta"]["why"]
    assert "no reference" in why["error"] and "no magnetometer" in why["mag"]
    assert "no accelerometer" in why["acc"] and "Kalman" in why["nis"]
    # nothing new: nothing sent
    assert feed.delta() is None
