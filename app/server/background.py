"""The background source: the built-in demo phone, or a replayed app log, while no phone streams.

- :func:`run_demo` and :func:`run_replay` produce samples at real-time speed and feed them
  through the very path a phone's samples take (``engine.feed``: count, reorder). A
  replayed log is decoded as the phone's lines are (:func:`~app.server.tcp_phone.feed_lines`),
  paced by its :class:`~app.sources.pacing.ReplayControl`. They run while
  ``engine.background_allowed`` is set; a phone that connects clears it, and the source
  waits until it is set again ("Resume demo").
- :class:`ReplayService` swaps the background source (the demo, or a replay of a recording
  of the folder) from the page and ``/api/replay``, and holds the control of the log on show.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from app.server.tcp_phone import feed_lines
from app.sources.pacing import ReplayControl, ReplayError
from app.sources.readers import ReaderError, detect_format
from app.sources.samples import Sample
from app.sources.simulate import Simulation, stream
from app.toolkit.errors import ToolError

TICK_S = 0.01   # how often a source hands over the lines due


async def run_demo(engine, seed: int = 0) -> None:
    """The simulated phone (see :mod:`app.sources.simulate`), looping its scenes forever."""
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
        while engine.background_allowed.is_set() and engine.core.session is session:
            due_ms = t0_ms + (time.monotonic() - t0_wall) * 1000.0
            samples = []
            while pending[0] <= due_ms:
                samples.append(Sample(*pending))
                pending = next(gen)
            if samples:
                engine.feed(session, samples)
            await asyncio.sleep(TICK_S)
        engine.close_session(session, "a phone took over")


async def run_replay(engine, path: str | Path, pause_s: float = 1.0,
                     control: ReplayControl | None = None) -> None:
    """Replay an app log: real time by default, under ``control`` (pause, speed, seek,
    loop); every loop and every seek is a new stream."""
    path = Path(path)
    ctl = control or ReplayControl(path.read_bytes().splitlines(), path.name)
    lines = ctl.lines
    while True:
        await engine.background_allowed.wait()
        ctl.restart = False
        session = engine.open_session("replay", f"{ctl.label} (from {ctl.position_s:.1f} s)")
        reason = "a phone took over"
        while engine.background_allowed.is_set() and engine.core.session is session:
            if ctl.restart:
                reason = f"seek to {ctl.position_s:.1f} s"
                break
            i, j = ctl.due(time.monotonic())
            if j > i:
                feed_lines(engine, session, lines[i:j])
            if ctl.at_end:
                reason = "end of log"
                if ctl.loop:
                    break
            await asyncio.sleep(TICK_S)
        engine.close_session(session, reason)
        if reason == "end of log":
            ctl.loops += 1
            await asyncio.sleep(pause_s)
            ctl.seek(0.0)


class ReplayService:
    """``engine``: the async shell (sessions, background sources); ``settings``: its
    ``replay_pause_s``, ``demo_seed`` and ``source`` (``"none"``: no demo to go back
    to); ``tasks``: the server's running tasks (the background source is ``"source"``);
    ``files(name)``: a recording's files (ToolError if none)."""

    def __init__(self, engine, settings, tasks: dict[str, asyncio.Task],
                 files: Callable[[str], dict]):
        self.engine = engine
        self.settings = settings
        self.tasks = tasks
        self.files = files
        self.control: ReplayControl | None = None     # the replayed log's, if any
        self.name: str | None = None

    def adopt(self, control: ReplayControl, name: str) -> None:
        """A replay started elsewhere (``--source LOG``): controlled from here too."""
        self.control, self.name = control, name

    def status(self) -> dict[str, Any]:
        return {"replaying": self.control is not None, "name": self.name,
                **({} if self.control is None else self.control.status())}

    def _set_source(self, coro) -> None:
        old = self.tasks.pop("source", None)
        if old is not None:
            old.cancel()
        s = self.engine.core.session
        if s is not None and s.open and s.kind in ("demo", "replay"):
            self.engine.close_session(s, "source changed from the page")
        if coro is not None:
            self.tasks["source"] = asyncio.get_running_loop().create_task(coro, name="source")

    def start(self, name: str) -> None:
        """Replay recording ``name`` of the folder (it replaces the demo or the replay on
        show; a connected phone still has priority)."""
        if not isinstance(name, str):
            raise ToolError("name", "must be a recording's name")
        path = self.files(name)["log"]
        try:
            if detect_format(path) != "applog":
                raise ToolError("name", f"{path.name} is not an app log (only logs can be replayed)")
        except ReaderError as e:
            raise ToolError("name", str(e)) from None
        if self.engine.phone_streaming():
            raise ToolError("name", "a phone is streaming: it has priority over a replay", 409)
        ctl = ReplayControl(path.read_bytes().splitlines(), path.name)
        self.control, self.name = ctl, name
        self.engine.resume_background()
        self._set_source(run_replay(self.engine, path, self.settings.replay_pause_s, control=ctl))

    def stop(self) -> None:
        """Back to the demo (or to waiting for a phone when started with --source none)."""
        self.control, self.name = None, None
        demo = self.settings.source != "none"
        self._set_source(run_demo(self.engine, self.settings.demo_seed) if demo else None)

    def set(self, **changes) -> None:
        """Pause, speed, seek or loop the log on show (None: unchanged); ToolError if
        nothing is replayed or a value is refused."""
        if self.control is None:
            raise ToolError("name", "nothing is replayed: give a recording's name", 409)
        try:
            self.control.set(**changes)
        except ReplayError as e:
            raise ToolError(e.field, e.reason) from None
