"""Pacing a recorded app log at real time: :class:`ReplayControl`, the playhead of a replay
(pause, speed, seek, loop). Pure: it says which lines are due at a monotonic time; the
server's background task (:mod:`app.server.background`) hands them to the engine."""

from __future__ import annotations

import bisect
import itertools
import math

from app.sources.sensorfusion import MalformedLine, parse_line


def _pace_times(lines: list[bytes]) -> list[float]:
    """Seconds after the start at which each line of a log is due. Each tag is paced on
    its own clock (tags may run on different clocks); unparsable lines go with the
    line before them."""
    first: dict[str, int] = {}
    out = []
    prev = 0.0
    for line in lines:
        try:
            s = parse_line(line)
        except MalformedLine:
            out.append(prev)
            continue
        t0 = first.setdefault(s.tag, s.time_ms)
        prev = max(0.0, (s.time_ms - t0) / 1000.0)
        out.append(prev)
    return out


class ReplayError(ValueError):
    """A refused replay request; ``field`` names the key."""

    def __init__(self, field_name: str, reason: str):
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason


SPEED_MIN, SPEED_MAX = 0.1, 10.0


class ReplayControl:
    """Where a replayed log is: a playhead in seconds of the log, paused or running at
    ``speed`` times real time, looping or stopping at the end. Pure (the runner asks
    :meth:`due` which lines are due at a monotonic time); :meth:`set` is the API's and
    the page's one entry. A seek asks the runner for a new stream (every estimator
    restarts cleanly: the samples before the seek are not integrated across the jump)."""

    def __init__(self, lines: list[bytes], label: str, loop: bool = True):
        self.lines = lines
        self.label = label
        # a line is due once every line before it is (as the phone sent them)
        self.times = list(itertools.accumulate(_pace_times(lines), max))
        self.duration_s = self.times[-1] if self.times else 0.0
        self.loop = loop
        self.paused = False
        self.speed = 1.0
        self.index = 0                  # next line to hand over
        self.position_s = 0.0           # playhead (s of the log)
        self.restart = False            # a seek happened: the runner opens a new stream
        self.loops = 0                  # times the log played to its end and started again
        self._wall: float | None = None

    def set(self, paused=None, speed=None, seek_s=None, loop=None) -> None:
        """Validate everything first (ReplayError names the field), then apply."""
        if paused is not None and not isinstance(paused, bool):
            raise ReplayError("paused", f"must be true or false, got {paused!r}")
        if loop is not None and not isinstance(loop, bool):
            raise ReplayError("loop", f"must be true or false, got {loop!r}")
        if speed is not None:
            if isinstance(speed, bool) or not isinstance(speed, (int, float)) \
                    or not math.isfinite(speed) or not SPEED_MIN <= speed <= SPEED_MAX:
                raise ReplayError("speed", f"must be a number in [{SPEED_MIN:g}, {SPEED_MAX:g}], "
                                           f"got {speed!r}")
        if seek_s is not None:
            if isinstance(seek_s, bool) or not isinstance(seek_s, (int, float)) \
                    or not math.isfinite(seek_s) or not 0.0 <= seek_s <= self.duration_s:
                raise ReplayError("seek_s", f"must be a time in [0, {self.duration_s:.3f}] s "
                                            f"of the log, got {seek_s!r}")
        if speed is not None:
            self.speed = float(speed)
        if loop is not None:
            self.loop = loop
        if paused is not None:
            self.paused = paused
        if seek_s is not None:
            self.seek(float(seek_s))
        self._wall = None               # re-anchor the clock at the next due()

    def seek(self, seconds: float) -> None:
        self.position_s = seconds
        self.index = bisect.bisect_left(self.times, seconds)
        self.restart = True

    @property
    def at_end(self) -> bool:
        return self.index >= len(self.lines)

    def due(self, now: float) -> tuple[int, int]:
        """The lines ``[i, j)`` due at monotonic time ``now`` (empty while paused)."""
        if self.paused or self.at_end:
            self._wall = None
            return self.index, self.index
        if self._wall is None:
            self._wall = now
            return self.index, self.index
        self.position_s = min(self.duration_s, self.position_s + (now - self._wall) * self.speed)
        self._wall = now
        i = self.index
        j = bisect.bisect_right(self.times, self.position_s, lo=i)
        self.index = j
        return i, j

    def status(self) -> dict:
        return {"file": self.label, "position_s": round(self.position_s, 3),
                "duration_s": round(self.duration_s, 3), "paused": self.paused,
                "speed": self.speed, "loop": self.loop, "loops": self.loops,
                "at_end": self.at_end}
