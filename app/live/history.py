"""The plots' history: rings of the last rows, with named columns.

A :class:`Ring` holds the last ``capacity`` rows of a fixed set of named columns
(``{"t": 1, "q": 4, ...}``; ``t``, the stream time in s, always first). Rows are
appended a block at a time (one block per processed chunk); :meth:`Ring.window` returns
a :class:`Window`, a copy of at most ``max_points`` rows evenly spread over the last
``seconds`` of stream time, read by column name (``w["q"]``, (n, 4); ``w["t"]``, (n,)).
"""

from __future__ import annotations

import bisect

import numpy as np


class Window:
    """Rows copied out of a ring, oldest first; columns by name."""

    def __init__(self, data: np.ndarray, cols: dict[str, slice]):
        self.data = data
        self._cols = cols

    def __len__(self) -> int:
        return self.data.shape[0]

    def __getitem__(self, name: str) -> np.ndarray:
        sl = self._cols[name]
        return self.data[:, sl.start] if sl.stop - sl.start == 1 else self.data[:, sl]

    def tail(self, k: int) -> "Window":
        """The newest ``k`` rows."""
        return Window(self.data[max(0, len(self) - k):], self._cols)


class Ring:
    """The last ``capacity`` rows of the named ``columns`` (name -> width)."""

    def __init__(self, capacity: int, columns: dict[str, int]):
        if next(iter(columns)) != "t":
            raise ValueError("the first column of a ring is t")
        self.cols: dict[str, slice] = {}
        i = 0
        for name, width in columns.items():
            self.cols[name] = slice(i, i + width)
            i += width
        self.data = np.full((capacity, i), np.nan)
        self.n = 0                  # rows written in total

    @property
    def capacity(self) -> int:
        return self.data.shape[0]

    def clear(self) -> None:
        self.data[:] = np.nan
        self.n = 0

    def block(self, k: int) -> np.ndarray:
        """A NaN-filled block of ``k`` rows to fill by column (:meth:`put`) and append."""
        return np.full((k, self.data.shape[1]), np.nan)

    def put(self, block: np.ndarray, name: str, values) -> None:
        """Set column ``name`` of a block (values (k,) or (k, width))."""
        sl = self.cols[name]
        if sl.stop - sl.start == 1:
            block[:, sl.start] = values
        else:
            block[:, sl] = values

    def extend(self, *columns) -> None:
        """Append rows given column by column, every column of the ring in order (each
        (k,) or (k, width)): :meth:`block`, :meth:`put` and :meth:`append` in one."""
        k = len(columns[0])
        block = np.empty((k, self.data.shape[1]))
        for sl, values in zip(self.cols.values(), columns):
            if sl.stop - sl.start == 1:
                block[:, sl.start] = values
            else:
                block[:, sl] = values
        self.append(block)

    def append(self, block: np.ndarray) -> None:
        """Append rows (oldest first); only the last ``capacity`` are kept."""
        cap = self.capacity
        k = block.shape[0]
        if k == 0:
            return
        if k > cap:
            self.n += k - cap
            block = block[-cap:]
            k = cap
        i = self.n % cap
        first = min(k, cap - i)
        self.data[i:i + first] = block[:first]
        if first < k:
            self.data[:k - first] = block[first:]
        self.n += k

    def window(self, seconds: float, max_points: int) -> Window:
        """At most ``max_points`` rows, evenly spread over the last ``seconds`` s of
        stream time, oldest first (the newest row always included). O(max_points)."""
        cap = self.capacity
        first = max(0, self.n - cap)
        if self.n == first:
            return Window(self.data[:0].copy(), self.cols)
        t = self.data[:, 0]
        t_from = t[(self.n - 1) % cap] - seconds
        # the first logical index whose time is >= t_from (times rise with the index)
        lo = bisect.bisect_left(range(first, self.n), t_from, key=lambda i: t[i % cap]) + first
        k = min(self.n - lo, max_points)
        idx = np.linspace(lo, self.n - 1, k).astype(np.int64) % cap
        return Window(self.data[idx], self.cols)


POSE_COLUMNS = {"t": 1, "q": 4, "phone_q": 4}            # every motion sample: primary, phone
ACC_COLUMNS = {"t": 1, "norm": 1, "nis": 1}               # every accelerometer sample
MAG_COLUMNS = {"t": 1, "norm": 1, "L_k": 1, "nis": 1}     # every magnetometer sample
GYR_COLUMNS = {"t": 1, "w": 3}                            # every gyroscope sample (rad/s)


class History:
    """The plots' rings of processed samples: ``pose`` (t, the primary's q, NaN before it
    is initialised, the phone's own q), ``acc`` (t, |acc|, NIS), ``mag`` (t, |mag|, L_k,
    NIS) and ``gyr`` (t, the raw rate: the GUI's bias calibration)."""

    def __init__(self, capacity: int):
        self.pose = Ring(capacity, POSE_COLUMNS)
        self.acc = Ring(capacity, ACC_COLUMNS)
        self.mag = Ring(capacity, MAG_COLUMNS)
        self.gyr = Ring(capacity, GYR_COLUMNS)

    def clear(self) -> None:
        for r in (self.pose, self.acc, self.mag, self.gyr):
            r.clear()
