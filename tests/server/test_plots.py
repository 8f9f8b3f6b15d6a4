"""What the plots put on the wire (app/server/gui/plots.py): values on a binary grid finer
than a pixel, gaps as null, a constant line as its two ends."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import zstandard

from app.server.gui.plots import X_HOP_S, X_STEP, Y_BITS, ends, quantize, wire, x_window


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


def test_the_x_window_moves_in_whole_hops_and_starts_at_zero():
    assert X_HOP_S == 5.0
    assert x_window(np.array([0.0, 0.1]), 20.0) == (0.0, 5.0)
    assert x_window(np.array([0.0, 5.0]), 20.0) == (0.0, 5.0)          # 5.0 is inside
    assert x_window(np.array([0.0, 7.3]), 20.0) == (0.0, 10.0)
    assert x_window(np.array([3.0, 23.0]), 20.0) == (5.0, 25.0)
    # the window holds the newest data whatever the refresh: only every 5 s a new range
    ranges = {x_window(np.array([max(0.0, t - 20.0), t]), 20.0) for t in np.arange(0.1, 60, 0.5)}
    assert len(ranges) == 12
    for t in np.arange(0.1, 60, 0.37):
        lo, hi = x_window(np.array([max(0.0, t - 20.0), t]), 20.0)
        assert lo <= max(0.0, t - 20.0) + 5.0 and t <= hi and hi - lo <= 20.0
    # a chart whose data start later (NIS: the newest half) shows the same window
    assert x_window(np.array([27.0, 33.0]), 20.0) == (15.0, 35.0)
    # a stream that starts before 0 (an estimator's rows before the first motion sample)
    assert x_window(np.array([-1.0, 3.0]), 20.0) == (-5.0, 5.0)
    # nothing finite yet: the first hop
    assert x_window(np.array([np.nan, np.nan]), 20.0) == (0.0, 5.0)


def test_a_constant_line_is_its_two_ends():
    x = np.linspace(0.0, 20.0, 300)
    assert wire(ends(x, 3.5)) == [3.5] + [None] * 298 + [3.5]
    assert wire(ends(x, None)) == [None] * 300


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
