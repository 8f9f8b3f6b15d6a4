"""app.live.history: rings with named columns, appended a block at a time."""

from __future__ import annotations

import numpy as np

from app.live.history import History, Ring


def fill(ring: Ring, ks) -> None:
    ks = np.asarray(list(ks), dtype=float)
    blk = ring.block(len(ks))
    ring.put(blk, "t", ks / 100.0)
    ring.put(blk, "k", ks)
    ring.append(blk)


def test_ring_window_spans_the_time_window_across_the_wrap():
    ring = Ring(100, {"t": 1, "k": 1})
    for start in range(0, 250, 30):           # wrapped twice, in blocks; times 0.00 .. 2.49 s
        fill(ring, range(start, min(start + 30, 250)))
    w = ring.window(0.505, 1000)              # every row of the last ~0.5 s, oldest first
    assert w["k"].tolist() == list(range(199, 250))
    w = ring.window(10.0, 7)                  # longer than held: the whole ring, thinned
    assert len(w) == 7 and w["k"][0] == 150 and w["k"][-1] == 249
    assert np.all(np.diff(w["t"]) > 0)
    w.data[:] = -1                            # a copy: the ring is untouched
    assert ring.window(0.0, 5)["k"].tolist() == [249]
    assert ring.window(10.0, 100).tail(3)["k"].tolist() == [247, 248, 249]
    ring.clear()
    assert len(ring.window(1.0, 5)) == 0


def test_a_block_longer_than_the_ring_keeps_its_newest_rows():
    ring = Ring(10, {"t": 1, "k": 1})
    fill(ring, range(25))
    assert ring.n == 25
    assert ring.window(100.0, 100)["k"].tolist() == list(range(15, 25))


def test_history_columns_by_name():
    h = History(50)
    blk = h.pose.block(2)
    h.pose.put(blk, "t", [1.0, 2.0])
    h.pose.put(blk, "q", [[1, 0, 0, 0], [0, 1, 0, 0]])
    h.pose.append(blk)
    w = h.pose.window(10.0, 10)
    assert w["q"].shape == (2, 4) and np.isnan(w["phone_q"]).all()
    assert set(h.mag.cols) == {"t", "norm", "L_k", "nis"}
