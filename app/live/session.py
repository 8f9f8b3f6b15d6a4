"""A stream on show and the counters that describe it.

A :class:`Session` is one stream: a phone connection, the demo, or one loop of a replayed
log. It holds the stream's :class:`~app.stream.SampleOrderer` (parse, count, reorder,
clock offsets) and its own counters; producers call its methods (:meth:`Session.push_lines`,
:meth:`Session.count_malformed`, :meth:`Session.close`), never its fields.
:class:`Totals` counts over every session (connections refused, lines too long, samples,
step errors).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..protocol import Sample
from ..stream import SampleOrderer


class Session:
    """One stream. ``truth`` (demo only) maps phone times in ms (array) to true
    orientations (N, 4)."""

    def __init__(self, kind: str, label: str, window_s: float,
                 truth: Callable[[np.ndarray], np.ndarray] | None = None):
        self.kind = kind            # "phone", "demo", "replay"
        self.label = label
        self.orderer = SampleOrderer(window=window_s)
        self.truth = truth
        self.lines = 0
        self.samples = 0            # processed by the estimators
        self.opened = time.time()
        self.closed: float | None = None
        self.close_reason = ""
        self.last_rx = time.monotonic()

    @property
    def open(self) -> bool:
        return self.closed is None

    def push_lines(self, lines: list) -> list[Sample]:
        """Lines of one received chunk (bytes or str, without line ends): parsed, counted,
        reordered; the samples released, in time order."""
        self.lines += len(lines)
        self.last_rx = time.monotonic()
        released: list[Sample] = []
        push = self.orderer.push_line
        for line in lines:
            released.extend(push(line))
        return released

    def close(self, reason: str = "end of stream") -> list[Sample]:
        """End the stream (the first reason given stays); what the reorder buffer holds."""
        if self.closed is None:
            self.closed = time.time()
            self.close_reason = reason
        return self.orderer.flush()

    def count_malformed(self, reason: str) -> None:
        self.orderer.counters.malformed[reason] += 1

    def count_processed(self, n: int) -> None:
        self.samples += n

    @property
    def buffered(self) -> int:
        return self.orderer.buffered

    def rates(self) -> dict[str, float]:
        return self.orderer.rates()

    @property
    def clock_offsets(self) -> dict[str, float]:
        return self.orderer.offsets

    def counts(self) -> dict[str, Any]:
        c = self.orderer.counters
        return {"lines": self.lines, "samples": self.samples,
                "malformed": int(sum(c.malformed.values())),
                "malformed_by_reason": dict(c.malformed), "late": c.late, "clamped": c.clamped,
                "tags": dict(c.tags), "buffered": self.orderer.buffered}

    def truth_at(self, t: float | None) -> np.ndarray | None:
        """The true orientation at stream time ``t`` (s), or None (no truth, no time)."""
        if self.truth is None or t is None:
            return None
        return np.asarray(self.truth(np.array([t * 1000.0])), dtype=float)[0]


@dataclass
class Totals:
    """Counts over every session since the start."""
    sessions: int = 0
    refused: int = 0            # phone connections refused (another phone streams)
    too_long: int = 0           # connections closed for a line without end
    samples: int = 0            # processed

    def count_refused(self) -> None:
        self.refused += 1

    def count_too_long(self) -> None:
        self.too_long += 1

    def as_dict(self) -> dict[str, int]:
        return {"sessions": self.sessions, "refused": self.refused, "too_long": self.too_long,
                "samples": self.samples}
