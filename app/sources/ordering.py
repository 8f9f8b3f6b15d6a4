"""Time ordering of the Sensor Fusion app's sample stream.

The app sends one sample per line in *arrival* order, which is not time order:
timestamps of different tags step back by a few milliseconds, and different tags may
run on different clocks (GPS/RSS in Unix-epoch milliseconds, and on one phone ACC ran a
constant 131 072 s ahead of GYR/MAG). :class:`SampleOrderer` turns the arrival-ordered
stream into a time-ordered one on a single clock; both the log reader
(:mod:`app.sources.readers`) and the live receiver use it, so a recorded log and a live stream
are processed identically.

Typical use::

    orderer = SampleOrderer(window=0.05)
    for line in lines:
        for sample in orderer.push_line(line):     # parse, count, reorder
            ...                                    # time-ordered, reference clock
    for sample in orderer.flush():                 # end of stream
        ...
    rows = samples_to_rows(samples)                # -> estimator rows

How it works
------------
*Clocks.* The **reference clock** is the clock of the first motion tag
(ACC/GYR/MAG/ORI) seen. When a tag shows up for the first time, its time is compared
with the newest time seen so far on the reference clock; if they differ by more than
``offset_threshold`` (2 s) the tag runs on its own clock and its **offset** is that
difference: every later sample of the tag is mapped by subtracting it. Offsets are
exposed in :attr:`SampleOrderer.offsets` (seconds). Samples of non-motion tags that
arrive before any motion tag are held (at most ``max_pending``) until the reference
clock is known; if none comes, the first tag seen becomes the reference. Limitation: a
tag that first appears after a pause of the stream longer than the threshold is taken
for a tag on another clock.

*Reordering.* Samples wait in a buffer (a heap keyed on time, then arrival). Each
motion tag is nearly in order by itself, but one tag may be stamped well ahead of the
others when it arrives (in a real log MAG ran up to 0.2 s ahead of ACC/GYR). So a
sample is released once every *active* motion tag has reached a time more than
``window`` seconds past it: the release limit is ``min(latest time of each motion tag)
- window``, where a tag silent for more than ``max_delay`` (0.5 s) is not waited for.
The delay a sample may spend in the buffer is thus at most ``max_delay + window``, and
only ``window`` when the tags are in step. Non-motion tags (GPS, RAWGYR, ...) are
ordered too but never waited for. Equal times keep their arrival order.

*Late samples.* A sample older than the last released time cannot be put in its place
any more. It is never dropped silently:

- late by at most ``late_tolerance`` (0.1 s): released at once with its time
  **clamped** to the last released time (a few ms of time error, no data lost);
  counted in ``counters.clamped``;
- later than that: **dropped** and counted in ``counters.late`` (placing it seconds
  away from its true time would corrupt the integration more than losing it).

*Clock jumps.* A sample more than ``jump_s`` (2 s) away from the newest time seen
(forward or back; after clock mapping) is not let into the buffer at once: it waits
aside. A single wrong time stamp (a digit flip, +10 s) is followed by samples of its tag
back on the old clock: it is then dropped and counted (``malformed["time_jump"]``), and
nothing else is touched. If ``jump_confirm`` (3) samples of a motion tag in a row agree
on the new time, the clock really jumped: the buffer is released in order, the clock is
**re-anchored** on the new time (nothing later counts as late) and ``counters.jumps``
goes up; a non-motion tag that moves for good gets a new offset instead. A clock that
jumped *back* is moved on by the step (every tag's offset; summed in ``counters.back_ms``):
the stream's time goes on 1 ms after the last sample released, as the filters, the plots
and a recording need (a filter skips a row older than its last). Before, one
sample 10 s ahead made the buffer drop seconds of good samples as late.

*A wrong first stamp.* A tag's offset is read from its first sample, so a wrong first
stamp looks like a sensor on another clock. When a tag whose offset came from that one
sample then confirms a jump, the one stamp was wrong: its offset is read again from the
samples that confirmed it, and nothing is re-anchored. When the stream's very first
sample (the reference) was the wrong one, the other tags' offsets were read against it:
at the re-anchoring every motion tag stamped on the same clock as the jumping tag's new
samples (within ``offset_threshold``) takes its offset. Before, ACC and GYR stayed 10 s
apart for the whole session, and each sample was a new jump.

Released samples are new :class:`~app.sources.sensorfusion.Sample` objects whose ``time_ms`` is on
the reference clock (offset removed, possibly clamped).
"""

from __future__ import annotations

import heapq
import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from app.sources.samples import MOTION_TAGS, Sample
from app.sources.sensorfusion import MalformedLine, parse_line

# how many recent timestamps of each tag the rate estimate uses
RATE_HISTORY = 64
# a sensor silent this long (stream time) while the others go on has stopped (a phone app
# batches a sensor by up to a second: three is no batch)
STOPPED_S = 3.0


@dataclass
class StreamCounters:
    """What the orderer has seen. ``malformed`` counts skipped lines by reason
    (:class:`~app.sources.sensorfusion.MalformedLine` reasons); ``tags`` counts accepted samples
    per tag (before ordering, so dropped late samples are in it too)."""
    malformed: Counter = field(default_factory=Counter)
    tags: Counter = field(default_factory=Counter)
    late: int = 0          # dropped: too late to be put in order
    clamped: int = 0       # released with their time clamped (slightly late)
    jumps: int = 0         # clock jumps confirmed (re-anchored)
    back_ms: int = 0       # how far clocks that jumped back were moved on (ms, in total)
    forced: int = 0        # released early: the buffer was full (a clock standing still)

    def as_dict(self) -> dict:
        return {"malformed": dict(self.malformed), "tags": dict(self.tags),
                "late": self.late, "clamped": self.clamped, "jumps": self.jumps,
                "back_ms": self.back_ms, "forced": self.forced}


class SampleOrderer:
    """Reorder buffer and clock mapper for one stream (see the module doc).

    Parameters (seconds): ``window`` how long a sample waits for earlier ones once
    all motion tags are past it; ``max_delay`` how long a silent motion tag is waited
    for;
    ``late_tolerance`` up to how late a sample is clamped rather than dropped;
    ``offset_threshold`` the clock difference above which a tag gets an offset;
    ``max_pending`` how many samples may wait for the reference clock;
    ``jump_s`` the distance from the newest time beyond which a time stamp is a jump,
    ``jump_confirm`` how many samples of a tag in a row confirm it; ``max_buffered`` the
    most samples the buffer holds (a clock that stands still never releases them: beyond
    this the oldest go on, counted in ``counters.forced``).
    """

    def __init__(self, window: float = 0.05, *, max_delay: float = 0.5,
                 late_tolerance: float = 0.1, offset_threshold: float = 2.0,
                 max_pending: int = 256, jump_s: float = 2.0, jump_confirm: int = 3,
                 max_buffered: int = 20000):
        if not (window >= 0.0 and max_delay >= 0.0 and late_tolerance >= 0.0
                and offset_threshold > 0.0):
            raise ValueError("window, max_delay and late_tolerance must be >= 0, "
                             "offset_threshold > 0")
        self.window = float(window)
        self.max_delay = float(max_delay)
        self.late_tolerance = float(late_tolerance)
        self.offset_threshold = float(offset_threshold)
        self.max_pending = int(max_pending)
        self.max_buffered = max(1, int(max_buffered))
        self.jump_ms = float(jump_s) * 1000.0
        self.jump_confirm = max(1, int(jump_confirm))
        self.counters = StreamCounters()
        self.reset()

    # ------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the clocks and drop the buffer (a new stream starts); the counters
        are kept (make a new orderer to zero them)."""
        self._offsets_ms: dict[str, int] = {}
        self._reference: str | None = None
        self._pending: list[Sample] = []
        self._heap: list[tuple[int, int, Sample]] = []
        self._seq = 0
        self._newest: int | None = None         # newest mapped time seen (ms)
        self._released: int | None = None       # last released time (ms)
        self._latest: dict[str, int] = {}       # motion tag -> its newest mapped time
        self._raw: dict[str, int] = {}          # motion tag -> its newest time as stamped
        self._recent: dict[str, deque] = {}
        # tag -> samples waiting aside after a time jump: [(arrival seq, mapped t, sample)]
        self._aside: dict[str, list[tuple[int, int, Sample]]] = {}

    @property
    def reference_tag(self) -> str | None:
        """The tag whose clock all times are mapped to (None until known)."""
        return self._reference

    @property
    def offsets(self) -> dict[str, float]:
        """Per tag, seconds subtracted from its times to put them on the reference
        clock (0.0 for tags on the reference clock)."""
        return {tag: off / 1000.0 for tag, off in self._offsets_ms.items()}

    @property
    def buffered(self) -> int:
        """Samples waiting in the buffer (and for the reference clock)."""
        return len(self._heap) + len(self._pending) + sum(map(len, self._aside.values()))

    @property
    def last_released(self) -> float | None:
        """Time (s, reference clock) of the last released sample."""
        return None if self._released is None else self._released / 1000.0

    def held(self) -> list[Sample]:
        """What the buffer holds, in the order it will release it, each on its own
        sensor's clock as it came in (a copy; nothing is released): the buffer in time
        order, then what waits for the reference clock or aside after a time jump."""
        out = self.unmapped([s for _, _, s in sorted(self._heap, key=lambda x: (x[0], x[1]))])
        out.extend(self._pending)
        out.extend(s for aside in self._aside.values() for _, _, s in aside)
        return out

    def unmapped(self, samples: list[Sample]) -> list[Sample]:
        """Released (or held) samples put back on their own sensor's clock, as they came
        in: each tag's offset to the reference clock added back."""
        out = []
        for s in samples:
            off = self._offsets_ms.get(s.tag, 0)
            out.append(s if not off else Sample(s.time_ms + off, s.tag, s.values))
        return out

    def _rates(self) -> dict[str, float]:
        out = {}
        for tag, times in self._recent.items():
            span = (times[-1] - times[0]) / 1000.0 if len(times) > 1 else 0.0
            out[tag] = (len(times) - 1) / span if span > 0.0 else math.nan
        return out

    def rates(self) -> dict[str, float]:
        """Per tag, the sample rate (Hz) over its recent timestamps (NaN until two
        samples with distinct times; 0.0 once it has :meth:`stopped`)."""
        gone = self.stopped()
        return {tag: 0.0 if tag in gone else r for tag, r in self._rates().items()}

    def stopped(self) -> frozenset[str]:
        """The motion tags that stopped while the stream goes on (a sensor switched off in
        the app): their newest time lags the stream's newest by more than
        :data:`STOPPED_S` s, or 5 of their sample periods if that is longer (a tag with
        one sample so far has no period yet and is not judged: a slow sensor's first
        sample is no stop). A whole stream going quiet is not seen here (its time stands
        still): that is the arrival clock's business
        (:attr:`app.live.session.Session.silent_s`)."""
        if self._newest is None or not self._latest:
            return frozenset()
        rates = self._rates()
        out = set()
        for tag, t in self._latest.items():
            r = rates.get(tag, math.nan)
            if not r > 0.0:
                continue
            limit = max(STOPPED_S, 5.0 / r) * 1000.0
            if self._newest - t > limit:
                out.add(tag)
        return frozenset(out)

    def summary(self) -> dict:
        """Counters, offsets (s) and rates (Hz: each sensor's last rate, stopped or not)
        in one plain dict."""
        return {**self.counters.as_dict(), "offsets_s": self.offsets, "rates_hz": self._rates()}

    # ------------------------------------------------------------ input
    def push_line(self, line: str | bytes) -> list[Sample]:
        """Parse one line and :meth:`push` it; a malformed line is counted by reason
        and skipped (returns [])."""
        try:
            sample = parse_line(line)
        except MalformedLine as e:
            self.counters.malformed[e.reason] += 1
            return []
        return self.push(sample)

    def push_lines(self, lines: Iterable[str | bytes]) -> list[Sample]:
        """:meth:`push_line` for each line; all samples released on the way."""
        out: list[Sample] = []
        for line in lines:
            out.extend(self.push_line(line))
        return out

    def push(self, sample: Sample) -> list[Sample]:
        """Add one sample (arrival order); return the samples now safe to release,
        in time order on the reference clock."""
        self.counters.tags[sample.tag] += 1
        if self._reference is None:
            if sample.tag in MOTION_TAGS:
                return self._set_reference(sample.tag, sample.time_ms, [sample])
            self._pending.append(sample)
            if len(self._pending) > self.max_pending:
                first = self._pending[0]
                return self._set_reference(first.tag, first.time_ms, [])
            return []
        return self._insert(sample)

    def release_held(self) -> list[Sample]:
        """The stream went quiet, still open: release, in time order, the samples that wait
        out the reorder window only (up to the time every active motion tag has reached),
        since nothing newer will come soon to release them. A tag stamped ahead of the
        others keeps its lead buffered: after a stall the others' queued samples come on
        in order, none of them late."""
        out: list[Sample] = []
        if self._newest is None:
            return out
        limit = self._release_limit() + self.window * 1000.0
        while self._heap and self._heap[0][0] <= limit:
            out.append(self._pop())
        return out

    def flush(self) -> list[Sample]:
        """Release everything (end of stream), in time order."""
        out: list[Sample] = []
        if self._reference is None and self._pending:
            first = self._pending[0]
            out.extend(self._set_reference(first.tag, first.time_ms, []))
        while self._heap:
            out.append(self._pop())
        for aside in self._aside.values():   # jumps never confirmed
            self.counters.malformed["time_jump"] += len(aside)
        self._aside = {}
        return out

    # ------------------------------------------------------------ internals
    def _set_reference(self, tag: str, time_ms: int, extra: list[Sample]) -> list[Sample]:
        self._reference = tag
        self._offsets_ms[tag] = 0
        self._newest = time_ms
        waiting, self._pending = self._pending + extra, []
        out: list[Sample] = []
        for s in waiting:
            out.extend(self._insert(s))
        return out

    def _offset_of(self, sample: Sample) -> int:
        off = self._offsets_ms.get(sample.tag)
        if off is None:
            diff = sample.time_ms - self._newest
            off = diff if abs(diff) > self.offset_threshold * 1000.0 else 0
            self._offsets_ms[sample.tag] = off
        return off

    def _insert(self, sample: Sample) -> list[Sample]:
        if sample.tag in MOTION_TAGS:
            self._raw[sample.tag] = sample.time_ms
        t = sample.time_ms - self._offset_of(sample)
        if abs(t - self._newest) > self.jump_ms:
            return self._set_aside(sample, t)
        aside = self._aside.pop(sample.tag, None)
        if aside:  # the tag is back on its clock: what was set aside was a glitch
            self.counters.malformed["time_jump"] += len(aside)
        return self._place(sample, t)

    def _set_aside(self, sample: Sample, t: int) -> list[Sample]:
        """A time jump: hold the sample until its tag confirms the new clock (then
        re-anchor) or goes back to the old one (then it was a glitch: dropped)."""
        aside = self._aside.setdefault(sample.tag, [])
        if aside and abs(t - aside[-1][1]) > self.jump_ms:  # not even the same new clock
            self.counters.malformed["time_jump"] += len(aside)
            aside.clear()
        aside.append((self._seq, t, sample))
        self._seq += 1
        if len(aside) < self.jump_confirm:
            return []
        lone_first = (sample.tag != self._reference
                      and self.counters.tags[sample.tag] - len(aside) <= 1)
        if sample.tag not in MOTION_TAGS or lone_first:
            # this tag's clock moved (a non-motion tag), or its offset was read from its
            # first sample alone and the tag has been elsewhere ever since (that one stamp
            # was wrong): a new offset for this tag, read again as on its first sample
            del self._aside[sample.tag]
            diff = aside[0][2].time_ms - self._newest
            self._offsets_ms[sample.tag] = (diff if sample.tag not in MOTION_TAGS
                                            or abs(diff) > self.offset_threshold * 1000.0 else 0)
            out: list[Sample] = []
            for _, _, s in aside:
                out.extend(self._insert(s))
            return out
        return self._reanchor(aside[0][1], sample.tag, aside[0][2].time_ms)

    def _reanchor(self, t_new: int, tag: str, raw_new: int) -> list[Sample]:
        """The stream's clock jumped to ``t_new`` (``tag``'s samples, stamped ``raw_new``
        on their own clock, say so): release the buffer in order, start the new clock,
        then place what was waiting aside (in arrival order). A clock that went back is
        moved on by the step (every tag's offset), so the stream's time goes on just after
        the last sample released: the filters, the plots and a recording need a time that
        never goes back (the filters skip a row older than the last). A motion tag whose
        own stamps are on the same clock as ``tag``'s new ones (within
        ``offset_threshold``) takes ``tag``'s offset: its own was read against a wrong
        stamp (the stream's first sample stamped 10 s off made every other sensor look
        10 s off, and each of their samples a new jump)."""
        self.counters.jumps += 1
        out: list[Sample] = []
        while self._heap:
            out.append(self._pop())
        held = sorted((x for aside in self._aside.values() for x in aside), key=lambda x: x[0])
        self._aside = {}
        if t_new <= self._newest:       # the newest time placed: nothing released is later
            step = self._newest - t_new + 1
            for other in self._offsets_ms:
                self._offsets_ms[other] -= step
            self.counters.back_ms += step
            t_new += step
        off = self._offsets_ms.get(tag, 0)
        for other, raw in self._raw.items():
            if other != tag and abs(raw - raw_new) <= self.offset_threshold * 1000.0:
                self._offsets_ms[other] = off
        self._newest = t_new
        self._released = None
        self._latest = {}
        self._recent = {}
        for _, _, s in held:
            out.extend(self._insert(s))
        return out

    def _place(self, sample: Sample, t: int) -> list[Sample]:
        times = self._recent.get(sample.tag)
        if times is None:
            times = self._recent[sample.tag] = deque(maxlen=RATE_HISTORY)
        times.append(t)
        if self._released is not None and t < self._released:
            if (self._released - t) > self.late_tolerance * 1000.0:
                self.counters.late += 1
                return []
            self.counters.clamped += 1
            return [Sample(self._released, sample.tag, sample.values)]
        if t > self._newest:
            self._newest = t
        if sample.tag in MOTION_TAGS and t > self._latest.get(sample.tag, t - 1):
            self._latest[sample.tag] = t
        mapped = sample if t == sample.time_ms else Sample(t, sample.tag, sample.values)
        heapq.heappush(self._heap, (t, self._seq, mapped))
        self._seq += 1
        out: list[Sample] = []
        limit = self._release_limit()
        while self._heap and self._heap[0][0] <= limit:
            out.append(self._pop())
        # a clock that stands still (a frozen phone clock) never moves the release limit:
        # the buffer is bounded, its oldest samples go on in order (counted)
        while len(self._heap) > self.max_buffered:
            out.append(self._pop())
            self.counters.forced += 1
        return out

    def _release_limit(self) -> float:
        """Time (ms) up to which buffered samples are safe to release."""
        oldest_active = self._newest - self.max_delay * 1000.0
        active = [lt for lt in self._latest.values() if lt >= oldest_active]
        watermark = min(active) if active else self._newest
        return watermark - self.window * 1000.0

    def _pop(self) -> Sample:
        t, _, s = heapq.heappop(self._heap)
        self._released = t
        return s


# ---------------------------------------------------------------- estimator rows

@dataclass
class Rows:
    """Estimator input: one row per motion sample. ``gyr``/``acc``/``mag`` (N, 3)
    and ``ori`` (N, 4) are NaN where the row has no such sample; ``t`` in s."""
    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    ori: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])


# sample tag -> (Rows field, width)
_ROW_FIELDS = {"GYR": ("gyr", 3), "ACC": ("acc", 3), "MAG": ("mag", 3), "ORI": ("ori", 4)}


def samples_to_rows(samples: Iterable[Sample]) -> Rows:
    """Time-ordered samples -> estimator rows: each ACC/GYR/MAG/ORI sample is one row
    ``(t, gyr, acc, mag, ori)`` holding that sample and NaN elsewhere; other tags are
    left out (the orderer has counted them)."""
    motion = [s for s in samples if s.tag in _ROW_FIELDS]
    n = len(motion)
    cols = {name: np.full((n, width), np.nan) for name, width in _ROW_FIELDS.values()}
    t = np.fromiter((s.time_ms for s in motion), dtype=float, count=n) / 1000.0
    for tag, (name, width) in _ROW_FIELDS.items():
        idx = [i for i, s in enumerate(motion) if s.tag == tag]
        if idx:
            cols[name][idx] = np.array([motion[i].values for i in idx], dtype=float)
    return Rows(t=t, **cols)
