"""Background sources: the built-in demo phone and the replay of an app log.

Both produce the app's text lines at real-time speed and feed them through the very
path a phone's lines take (:meth:`Engine.feed_lines`: parse, count, reorder). They run
while :attr:`Engine.background_allowed` is set; a phone that connects clears it, and the
source waits until it is set again ("Resume demo").
"""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path

import numpy as np

from ..protocol import MalformedLine, parse_line
from ..simulate import Simulation, format_line, stream

log = logging.getLogger("orientlab.sources")
TICK_S = 0.01   # how often a source hands over the lines due


async def run_demo(engine, seed: int = 0) -> None:
    """The simulated phone (see :mod:`app.simulate`), looping its scenes forever."""
    sim = Simulation()
    boot_ms = sim.config.boot_ms

    def truth(time_ms):
        return sim.truth((np.asarray(time_ms, float) - boot_ms) / 1000.0)

    while True:
        await engine.background_allowed.wait()
        session = engine.open_session("demo", "simulated phone", truth=truth)
        gen = stream(seed)
        pending = next(gen)
        t0_wall = time.monotonic()
        t0_ms = pending[0]
        while engine.background_allowed.is_set() and engine.session is session:
            due_ms = t0_ms + (time.monotonic() - t0_wall) * 1000.0
            lines = []
            while pending[0] <= due_ms:
                lines.append(format_line(*pending))
                pending = next(gen)
            if lines:
                engine.feed_lines(session, lines)
            await asyncio.sleep(TICK_S)
        engine.close_session(session, "a phone took over")


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


async def run_replay(engine, path: str | Path, pause_s: float = 1.0) -> None:
    """Replay an app log at real-time speed, in a loop; every loop is a new stream."""
    path = Path(path)
    lines = path.read_bytes().splitlines()
    due = _pace_times(lines)
    loop_n = 0
    while True:
        await engine.background_allowed.wait()
        loop_n += 1
        session = engine.open_session("replay", f"{path.name} (loop {loop_n})")
        t0 = time.monotonic()
        i = 0
        while i < len(lines) and engine.background_allowed.is_set() and engine.session is session:
            now = time.monotonic() - t0
            j = i
            while j < len(lines) and due[j] <= now:
                j += 1
            if j > i:
                engine.feed_lines(session, lines[i:j])
                i = j
            await asyncio.sleep(TICK_S)
        engine.close_session(session, "end of log" if i >= len(lines) else "a phone took over")
        await asyncio.sleep(pause_s)
