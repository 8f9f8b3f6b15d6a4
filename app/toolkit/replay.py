"""Replaying a recording on the live server: :class:`ReplayService` swaps the background
source (the demo, or a replay of a recording of the folder) and holds the control of the
log on show (:class:`app.sources.runners.ReplayControl`: pause, speed, seek, loop)."""

from __future__ import annotations

import asyncio
from typing import Any, Callable

from app.sources.readers import ReaderError, detect_format
from app.sources.runners import ReplayControl, ReplayError, run_demo, run_replay
from app.toolkit.errors import ToolError


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
