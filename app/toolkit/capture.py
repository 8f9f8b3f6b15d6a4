"""A stretch of the live stream collected for a calibration (still phone or turning
phone), with its countdown; shared by :mod:`app.toolkit.calibration`'s and
:mod:`app.toolkit.magcal`'s services."""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.toolkit.errors import ToolError

STALL_FACTOR, STALL_GRACE_S = 3.0, 10.0   # a capture gives up after 3x its seconds + 10 s


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
    t0: float | None = None     # stream time of the first sample (s)
    t_last: float | None = None
    t: list = field(default_factory=list)
    acc: list = field(default_factory=list)
    gyr: list = field(default_factory=list)
    mag: list = field(default_factory=list)
    done: asyncio.Future | None = None
    result: dict | None = None
    error: str | None = None

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

    def add(self, t: np.ndarray, kind: np.ndarray, values: np.ndarray) -> bool:
        """Append a chunk of rows; True when the capture has its seconds."""
        if not len(t):
            return self.elapsed >= self.seconds
        if self.t0 is None:
            self.t0 = float(t[0])
        end = self.t0 + self.seconds
        sel = t <= end
        t, kind, values = t[sel], kind[sel], values[sel]
        self.t.append(t)
        for k, arr in ((0, self.gyr), (1, self.acc), (2, self.mag)):
            v = np.full((len(t), 3), np.nan)
            m = kind == k
            v[m] = values[m, :3]
            arr.append(v)
        if len(t):
            self.t_last = float(t[-1])
        return not sel.all() or self.elapsed >= self.seconds

    def arrays(self):
        cat = (lambda xs: np.concatenate(xs) if xs else np.zeros((0, 3)))
        t = np.concatenate(self.t) if self.t else np.zeros(0)
        return t, cat(self.gyr), cat(self.acc), cat(self.mag)

    def succeed(self, result: dict) -> None:
        self.result = result
        if self.done is not None and not self.done.done():
            self.done.set_result(result)

    def fail(self, error: str) -> None:
        self.error = error
        if self.done is not None and not self.done.done():
            self.done.set_exception(ToolError("seconds", error, 409))

    def check_stalled(self) -> None:
        """Give up when the samples stopped coming (called a few times a second)."""
        if self.running and time.monotonic() - self.started_wall > \
                self.seconds * STALL_FACTOR + STALL_GRACE_S:
            self.fail("no stream: the samples stopped coming (is the phone streaming?)")

    def status(self) -> dict[str, Any]:
        n = sum(len(x) for x in self.t)
        return {"kind": self.kind, "seconds": self.seconds, "elapsed_s": round(self.elapsed, 2),
                "remaining_s": round(self.remaining, 2), "rows": n,
                "done": self.result is not None or self.error is not None, "error": self.error}
