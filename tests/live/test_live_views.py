"""app/live/views.py: the latency tapes and their figures, without a server."""

from __future__ import annotations

import numpy as np
import pytest

from app.live.views import Latency, Tape


def test_a_tape_keeps_the_last_rows_in_order_in_memory_made_up_front():
    tape = Tape(4, 3)
    data_before = tape.data
    assert len(tape) == 0 and np.asarray(tape).shape == (0, 3)
    for k in range(10):
        tape.append((k, 10 * k, 100 * k))
        kept = np.asarray(tape)
        first = max(0, k - 3)
        np.testing.assert_array_equal(kept[:, 0], np.arange(first, k + 1))
        np.testing.assert_array_equal(kept[:, 2], 100 * np.arange(first, k + 1))
    assert tape.data is data_before                 # no growth: the same array throughout
    kept[0, 0] = -1.0                               # a copy: the tape is not changed
    assert np.asarray(tape)[0, 0] == 6.0
    tape.clear()
    assert len(tape) == 0 and np.asarray(tape).size == 0
    one = Tape(3)                                   # one column: a flat array
    for v in (0.1, 0.2, 0.3, 0.4):
        one.append(v)
    np.testing.assert_allclose(np.asarray(one), [0.2, 0.3, 0.4])


def test_latency_figures_count_each_chunk_once_per_sample():
    lat = Latency(maxlen=100)
    # two chunks: 0.001 s for 99 samples, 0.5 s for 1: the median is 1 ms, the max 500 ms
    lat.chunks.append((0.001, 0.0005, 99))
    lat.chunks.append((0.5, 0.25, 1))
    for v in (0.002, 0.004):
        lat.loop_lag.append(v)
    f = lat.figures()
    ref = np.repeat([0.001, 0.5], [99, 1]) * 1e3
    assert f["latency_ms"]["n"] == 100
    assert f["latency_ms"]["median"] == pytest.approx(np.median(ref))
    assert f["latency_ms"]["p99"] == pytest.approx(np.percentile(ref, 99))
    assert f["latency_ms"]["max"] == pytest.approx(500.0)
    assert f["wait_ms"]["max"] == pytest.approx(250.0)
    assert f["loop_lag_ms"]["median"] == pytest.approx(3.0)
    lat.clear()
    assert lat.figures()["latency_ms"]["n"] == 0
