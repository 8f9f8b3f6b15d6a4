"""A stream on show and the counters that describe it.

A :class:`Session` is one stream: a phone connection (of any app), the demo, or one loop of
a replayed log. It holds the stream's :class:`~app.sources.ordering.SampleOrderer` (count,
reorder, clock offsets) and its own counters; producers call its methods
(:meth:`Session.push`, :meth:`Session.count_malformed`, :meth:`Session.close`), never its
fields. A session sees samples only: each source decodes its own wire format and counts
what it could not use with :meth:`Session.count_malformed`.
:class:`Totals` counts over every session (connections refused, lines too long, samples,
step errors).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from app.sources.samples import Sample
from app.sources.ordering import SampleOrderer
from app.sources.slot import PHONE_APPS


SILENT_S = 3.0     # a connected phone sending nothing this long is said to be silent (s)
# A stream sending nothing this long (s, PC clock) has gone quiet: the samples its reorder
# window holds are processed then (:meth:`Session.quiet`), not when it sends again or ends
QUIET_S = 1.0

# a phone's stream without one of the motion sensors after this long (s) did not tick it
MISSING_AFTER_S = 3.0


class Session:
    """One stream. ``truth`` (demo only) maps phone times in ms (array) to true
    orientations (N, 4)."""

    def __init__(self, kind: str, label: str, window_s: float,
                 truth: Callable[[np.ndarray], np.ndarray] | None = None, phone_app: str = ""):
        self.kind = kind            # "phone", "demo", "replay"
        self.label = label
        self.phone_app = phone_app  # the phone app feeding a "phone" stream (slot.PHONE_APPS)
        self.details: dict[str, Any] = {}   # what its source detected: platform, convention
        # the source's account of the sensors it receives but holds back (:attr:`withheld`)
        self.withheld_by: Callable[[], dict[str, str]] | None = None
        # the source's account of why no samples come, when it knows (a paused phone)
        self.silent_hint_by: Callable[[], str | None] | None = None
        # the longest gap its source expects between two deliveries (s; a push app's batch
        # period): no longer than that, it is not silent
        self.expected_gap_s = 0.0
        self.orderer = SampleOrderer(window=window_s)
        self.truth = truth
        self.lines = 0              # readings received (samples and malformed ones)
        self.samples = 0            # processed by the estimators
        self.opened = time.time()
        self.closed: float | None = None
        self.close_reason = ""
        self.last_rx = time.monotonic()

    @property
    def app_name(self) -> str:
        """The phone app's name ("Sensor Logger"), "" when not a phone app's stream."""
        return PHONE_APPS.get(self.phone_app, "")

    def public_label(self) -> str:
        """The stream's label as anyone may read it: a phone by its app, never by its
        address (the presenter's business, ``GET /api/connect``)."""
        if self.kind != "phone":
            return self.label
        return f"a phone ({self.app_name})" if self.app_name else "a phone"

    def source_text(self) -> str:
        """The stream in a few words anyone may read: its kind and label, a phone by its
        app ("demo simulated phone", "a phone (Sensor Logger)")."""
        return self.public_label() if self.kind == "phone" else f"{self.kind} {self.label}"

    def describe(self) -> dict[str, Any]:
        """The stream's source for a recording's events: kind, app and what was detected.
        A recording is shared with the class (the page's Recordings tab): a phone is named
        by its app and what was detected, not by its address."""
        return {"kind": self.kind, "label": self.public_label(), "app": self.phone_app or None,
                **{k: v for k, v in self.details.items() if k != "url"}}   # url: its address

    @property
    def open(self) -> bool:
        return self.closed is None

    def push(self, samples: list[Sample]) -> list[Sample]:
        """Samples of one received chunk (arrival order): counted, reordered; the samples
        released, in time order."""
        self.lines += len(samples)
        if samples:                 # a chunk of malformed lines only is no sign of life
            self.last_rx = time.monotonic()
        released: list[Sample] = []
        push = self.orderer.push
        for smp in samples:
            released.extend(push(smp))
        return released

    def close(self, reason: str = "end of stream") -> list[Sample]:
        """End the stream (the first reason given stays); what the reorder buffer holds."""
        if self.closed is None:
            self.closed = time.time()
            self.close_reason = reason
        return self.orderer.flush()

    def held(self) -> list[Sample]:
        """What the reorder buffer holds, in the order it will release it, on each
        sensor's own clock (a copy)."""
        return self.orderer.held()

    def unmapped(self, samples: list[Sample]) -> list[Sample]:
        """Samples this stream released, back on each sensor's own clock."""
        return self.orderer.unmapped(samples)

    def quiet(self) -> bool:
        """Open, with samples buffered, and nothing received for :data:`QUIET_S` or more."""
        return self.open and self.orderer.buffered > 0 and self.silent_s >= QUIET_S

    def release_held(self) -> list[Sample]:
        """The stream went quiet, still open: the samples its reorder window holds back
        (:meth:`SampleOrderer.release_held`)."""
        return self.orderer.release_held()

    def count_malformed(self, reason: str, n: int = 1) -> None:
        """A reading the source could not use (``reason``: a short key)."""
        if n:
            self.orderer.counters.malformed[reason] += n
            self.lines += n

    def count_late(self, n: int) -> None:
        """Samples the source dropped as too late to be put in order (``counts.late``, as
        the orderer counts its own)."""
        self.orderer.counters.late += n

    def count_processed(self, n: int) -> None:
        self.samples += n

    @property
    def buffered(self) -> int:
        return self.orderer.buffered

    @property
    def withheld(self) -> dict[str, str]:
        """The sensors the phone sends and its source holds back, and why (Sensor Logger's
        orientation while its convention is checked): neither "stopped" nor a rate."""
        return {} if self.withheld_by is None else self.withheld_by()

    def rates(self) -> dict[str, float]:
        """Per sensor tag, its rate (Hz; 0.0: it stopped while the others go on); a tag the
        source holds back (:attr:`withheld`) has none."""
        held = self.withheld
        return {k: v for k, v in self.orderer.rates().items() if k not in held}

    def missing(self) -> list[str]:
        """The motion sensors (ACC, GYR, MAG) a phone's stream has sent none of, once it has
        streamed :data:`MISSING_AFTER_S` s: not ticked in its app, whichever app (a sensor
        that stopped while the others go on is :meth:`stopped`)."""
        tags = self.orderer.counters.tags
        if self.kind != "phone" or not tags or time.time() - self.opened < MISSING_AFTER_S:
            return []
        return [t for t in ("ACC", "GYR", "MAG") if not tags.get(t)]

    def stopped(self) -> frozenset[str]:
        """The sensor tags that stopped while the stream goes on (a sensor switched off);
        not one the source holds back while the phone still sends it (:attr:`withheld`)."""
        return self.orderer.stopped() - self.withheld.keys()

    @property
    def silent_s(self) -> float:
        """Seconds (PC clock) since the last samples arrived."""
        return time.monotonic() - self.last_rx

    def silent(self) -> float | None:
        """An open phone stream that has sent no samples for :data:`SILENT_S` or more: for
        how long (s); else None (streaming, or not a connected phone)."""
        if self.kind != "phone" or not self.open:
            return None
        s = self.silent_s
        return s if s >= max(SILENT_S, self.expected_gap_s) else None

    def silent_hint(self) -> str | None:
        """Why a silent stream sends nothing, when its source knows (:attr:`silent_hint_by`)."""
        return None if self.silent_hint_by is None else self.silent_hint_by()

    @property
    def clock_offsets(self) -> dict[str, float]:
        return self.orderer.offsets

    def counts(self) -> dict[str, Any]:
        c = self.orderer.counters
        return {"lines": self.lines, "samples": self.samples,
                "malformed": int(sum(c.malformed.values())),
                "malformed_by_reason": dict(c.malformed), "late": c.late, "clamped": c.clamped,
                "jumps": c.jumps, "tags": dict(c.tags), "buffered": self.orderer.buffered}

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
