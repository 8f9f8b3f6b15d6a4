"""A stretch of the live stream collected for a calibration (still phone or turning
phone), with its countdown; shared by :mod:`app.toolkit.calibration`'s and
:mod:`app.toolkit.magcal`'s services.

A collection is bounded whatever the phone's clock does (a frozen clock never reaches
the requested seconds, and grew memory by 390 MB in 20 s): at most :data:`MAX_ROWS`
samples are kept and the wall time is capped at the requested seconds +
:data:`WALL_GRACE_S`. At either cap the collection stops with a message (:meth:`Capture.capped`):
a clock that advanced less than :data:`MIN_CLOCK_SHARE` of the wall time is refused (its
samples' times are not to be trusted), else the samples so far are used."""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.toolkit.errors import ToolError

MAX_ROWS = 60_000          # samples kept at most (~1.4 MB per sensor as float64 rows)
WALL_GRACE_S = 5.0         # wall time allowed beyond the requested seconds
MIN_CLOCK_SHARE = 0.5      # a stream clock slower than half the wall clock is not trusted
STOPPED_S = 2.0            # no sample for this long at a cap: the stream stopped


def check_seconds(seconds: Any, lo: float, hi: float) -> float:
    """``seconds`` as a float in ``[lo, hi]``, else ToolError("seconds")."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) \
            or not math.isfinite(seconds) or not lo <= seconds <= hi:
        raise ToolError("seconds", f"must be a number of seconds in [{lo:g}, {hi:g}]")
    return float(seconds)


def check_streaming(core, field_name: str = "seconds",
                    text: str = "no stream: connect the phone (or run the demo) first") -> None:
    """ToolError (409) unless a stream is on show in ``core``."""
    if core.session is None or not core.session.open:
        raise ToolError(field_name, text, 409)


@dataclass
class Capture:
    """Samples collected over ``seconds`` of the stream (calibration)."""
    kind: str                   # "still" or "magcal"
    seconds: float
    started_wall: float = field(default_factory=time.monotonic)
    ended_wall: float | None = None    # when it got its result or failed (:meth:`end`)
    t0: float | None = None     # stream time of the first sample (s)
    t_last: float | None = None
    t: list = field(default_factory=list)
    acc: list = field(default_factory=list)
    gyr: list = field(default_factory=list)
    mag: list = field(default_factory=list)
    done: asyncio.Future | None = None
    result: dict | None = None
    error: str | None = None
    rows: int = 0               # samples kept
    last_wall: float | None = None   # wall time of the last sample offered
    note: str | None = None     # why it stopped before its seconds (a cap), if it did

    @property
    def elapsed(self) -> float:
        if self.t0 is None or self.t_last is None:
            return 0.0
        return self.t_last - self.t0

    @property
    def remaining(self) -> float:
        return max(0.0, self.seconds - self.elapsed)

    @property
    def running(self) -> bool:
        return self.result is None and self.error is None

    @property
    def wall_elapsed(self) -> float:
        """Wall time from the start to the end (to now while it runs)."""
        end = self.ended_wall if self.ended_wall is not None else time.monotonic()
        return end - self.started_wall

    def end(self, result: dict | None = None, error: str | None = None) -> None:
        """It is over: with its result, or why it failed; its wall time stops."""
        self.result, self.error = result, error
        if self.ended_wall is None:
            self.ended_wall = time.monotonic()

    def capped(self) -> str | None:
        """None while the collection is within its bounds; else why it must stop now:
        :data:`MAX_ROWS` samples kept, or the wall time beyond its seconds +
        :data:`WALL_GRACE_S` (sets :attr:`note`)."""
        wall = self.wall_elapsed
        if self.rows >= MAX_ROWS:
            self.note = (f"stopped at the cap of {MAX_ROWS} samples after {wall:.1f} s "
                         f"({self.elapsed:.1f} s of the phone's clock)")
        elif wall > self.seconds + WALL_GRACE_S:
            self.note = (f"stopped after {wall:.1f} s (the {self.seconds:g} s asked + "
                         f"{WALL_GRACE_S:g} s): the phone's clock advanced {self.elapsed:.1f} s")
        else:
            return None
        return self.note

    def clock_untrusted(self) -> str | None:
        """Once :meth:`capped`: why the samples cannot be used (the stream stopped; a
        clock frozen, gone back or far slower than the wall clock), or None."""
        if self.last_wall is None or time.monotonic() - self.last_wall > STOPPED_S:
            quiet = "" if self.last_wall is None else f" for {time.monotonic() - self.last_wall:.0f} s"
            return (f"no samples came{quiet}: the phone stopped streaming, or its clock froze "
                    "(samples without a new time are not used)")
        wall = max(self.wall_elapsed, 1e-9)
        if self.elapsed < MIN_CLOCK_SHARE * min(wall, self.seconds):
            return (f"{self.note}: the phone's clock is frozen or far behind "
                    f"(nothing collected is used; check the phone's time stamps)")
        return None

    def add(self, t: np.ndarray, kind: np.ndarray, values: np.ndarray) -> bool:
        """Append a chunk of rows (up to :data:`MAX_ROWS` in all); True when the capture
        has its seconds or reached a cap (:meth:`capped`)."""
        if not len(t):
            return self.elapsed >= self.seconds or self.capped() is not None
        self.last_wall = time.monotonic()
        if self.t0 is None:
            self.t0 = float(t[0])
        end = self.t0 + self.seconds
        sel = t <= end
        t, kind, values = t[sel], kind[sel], values[sel]
        room = MAX_ROWS - self.rows
        t, kind, values = t[:room], kind[:room], values[:room]
        self.rows += len(t)
        self.t.append(t)
        for k, arr in ((0, self.gyr), (1, self.acc), (2, self.mag)):
            v = np.full((len(t), 3), np.nan)
            m = kind == k
            v[m] = values[m, :3]
            arr.append(v)
        if len(t):
            self.t_last = float(t[-1])
        if not sel.all() or self.elapsed >= self.seconds:
            return True
        return self.capped() is not None     # full: rows at MAX_ROWS, said by capped()

    def arrays(self):
        cat = (lambda xs: np.concatenate(xs) if xs else np.zeros((0, 3)))
        t = np.concatenate(self.t) if self.t else np.zeros(0)
        return t, cat(self.gyr), cat(self.acc), cat(self.mag)

    def succeed(self, result: dict) -> None:
        self.end(result=result)
        if self.done is not None and not self.done.done():
            self.done.set_result(result)

    def fail(self, error: str) -> None:
        self.end(error=error)
        if self.done is not None and not self.done.done():
            self.done.set_exception(ToolError("seconds", error, 409))

    def check_stalled(self) -> bool:
        """Called a few times a second: True when the wall-time cap has passed (the
        owner ends the capture: with no sample at all, :meth:`fail` is called here)."""
        if not self.running or self.capped() is None:
            return False
        if not self.rows:
            self.fail("no stream: the samples stopped coming (is the phone streaming?)")
        return True

    def status(self) -> dict[str, Any]:
        return {"kind": self.kind, "seconds": self.seconds, "elapsed_s": round(self.elapsed, 2),
                "remaining_s": round(self.remaining, 2), "rows": self.rows,
                "wall_s": round(self.wall_elapsed, 2), "max_rows": MAX_ROWS,
                "done": self.result is not None or self.error is not None, "error": self.error,
                "note": self.note}
