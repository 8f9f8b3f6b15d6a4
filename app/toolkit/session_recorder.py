"""Recording the live session: :class:`RecordingService` keeps the one
:class:`~app.toolkit.recording.Recorder` of the dashboard (start, stop, segments when a
stream ends and another starts) and feeds it from the live core's hooks: the samples as
the estimators get them (a sample stage after the injection's, before the magnetometer
calibration's), every estimator's estimates (a record listener), the parameters at each
change and the injections' marks. The files' format is :mod:`app.toolkit.recording`'s.

Bounded by ``limits`` (:class:`~app.toolkit.recording.RecordingLimits`, from ``orientlab
serve``'s settings): at a cap or a low disk the recording stops cleanly, and
:meth:`RecordingService.status` says why (``last.stop_reason``); while it runs, the status
holds its size and rate (``bytes``, ``bytes_per_s``).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from app.params import to_dict
from app.toolkit.errors import ToolError
from app.toolkit.recording import (Recorder, RecordingError, RecordingLimits, file_size,
                                   recording_logs)
from app.toolkit.recorded import recording_files, scan_recordings

log = logging.getLogger("orientlab.recording")
LEFT_OUT_SHOWN = 50     # files left out of the listing named, at most
NAMES_FRESH_S = 10.0    # the recordings' names are read again at least this often


def params_in_force(ensemble, parts: list[Callable[[], dict]] = ()) -> dict[str, Any]:
    """Every instance's base and parameters, the primary, and the tables ``parts`` add
    (the magnetometer calibration in force): what a recording notes at each change."""
    out: dict[str, Any] = {n: {"base": ensemble.base_of(n), **to_dict(ensemble.params_of(n))}
                           for n in ensemble.names}
    out["primary"] = ensemble.primary
    for part in parts:
        out.update(part())
    return out


class RecordingService:
    """See the module doc. ``core``: the live core; ``folder``: the recordings folder;
    ``parts``: more tables of the parameters in force (``engine.preset_parts``)."""

    def __init__(self, core, folder: str | Path, parts: list[Callable[[], dict]] | None = None,
                 limits: RecordingLimits | None = None):
        self.core = core
        self.folder = Path(folder)
        self.limits = limits or RecordingLimits()
        self.parts = parts if parts is not None else []
        # what only a recording notes beside them (not a preset's: where a magnetometer
        # calibration took over, MagCalService.record_part)
        self.record_parts: list[Callable[[], dict]] = []
        # the samples of a stream the filters have not stepped yet (queued for them, the
        # reorder buffer's), and what undoes the sample stages after this one (the
        # magnetometer calibration's): wired by the server (Toolkit.build)
        self.queued: Callable[[Any], list] | None = None
        self.undo_later_stages: Callable[[list], list] | None = None
        self.recorder: Recorder | None = None
        self.last: dict[str, Any] | None = None      # the last recording's summary
        self._session = None                         # the stream being recorded
        self._names: tuple[tuple, list[str]] = ((), [])   # (when read, the names): names()
        core.sample_stages.append(self.stage)
        core.record_listeners.append(self.on_records)

    @property
    def recording(self) -> bool:
        return self.recorder is not None

    def params_in_force(self) -> dict[str, Any]:
        return params_in_force(self.core.ensemble, [*self.parts, *self.record_parts])

    # ----------------------------------------------------------------- the hooks
    def stage(self, session, samples: list) -> list:
        """The sample stage: the recorder's copy (samples unchanged)."""
        rec = self.recorder
        if rec is None:
            return samples
        if session is not self._session:
            if self._session is not None:     # a stream that starts now: the filters too
                rec.new_segment(session.source_text(), session.describe(), {"t": None, "warm_s": 0.0})
            else:                              # recording before any stream: this is its source
                rec.note("stream", source=session.source_text(), phone=session.describe())
            self._session = session
        rec.write_samples(samples)
        self._check()
        return samples

    def on_records(self, session, rec) -> None:
        """The record listener: every estimator's estimates (and the demo's truth)."""
        r = self.recorder
        if r is None or not len(rec) or session is not self._session:
            return
        sel = rec.kind < 3
        r.count_samples(rec.t[sel])
        tags = rec.tags
        for name in rec.q:
            r.write_estimates(name, rec.t, tags, rec.q[name], rec.flags[name])
        if session.truth is not None:
            try:
                tq = np.asarray(session.truth(rec.t * 1000.0), dtype=float)
                r.write_estimates("truth", rec.t, tags, tq)
            except Exception:
                log.exception("truth for the recording failed")
        self._check()

    def note_params(self) -> None:
        """The parameters changed (the engine's parameter listener; a magnetometer
        calibration applied): noted in the events and marked in the log."""
        if self.recorder is not None:
            t = self.core.t_sent
            self.recorder.note("params", t=t, params=self.params_in_force(),
                               mark=None if t is None else (int(t * 1000), "parameters changed"))

    def note_mark(self, m: dict[str, Any], t: float) -> None:
        """An injection's mark (:attr:`InjectionService.mark_listeners`)."""
        if self.recorder is not None:
            self.recorder.note("inject", t=m["time_ms"] / 1000.0, event=m["event"], id=m["id"],
                               text=m["text"])

    def tick(self) -> None:
        """Called a few times a second: end the segment whose stream ended."""
        s = self._session
        if self.recorder is not None and s is not None and not s.open \
                and self.recorder.segment is not None:
            self.recorder.end_segment(s.close_reason or "end of stream")
        if self.recorder is not None:
            self.recorder.check()       # the duration cap and the disk, with no stream too
        self._check()

    def _check(self) -> None:
        rec = self.recorder
        if rec is None:
            return
        if rec.error is not None:
            self.last = rec.stop("write failed")
            self.recorder = None
            self._session = None
            log.error("recording stopped: %s", self.last["error"])
        elif rec.stop_reason is not None:
            self.last = rec.stop(rec.stop_reason)
            self.recorder = None
            self._session = None
            log.warning("recording %r stopped: %s", rec.base, rec.stop_reason)

    # ----------------------------------------------------------------- the requests
    def start(self, name: str | None = None) -> dict[str, Any]:
        if self.recorder is not None:
            raise ToolError("recording", f"already recording {self.recorder.base!r}", 409)
        try:
            rec = Recorder(self.folder, name, limits=self.limits)
            s = self.core.session
            at = self._warm()
            state = self.core.ensemble.state_arrays() if at["warm_s"] > 0 else {}
            rec.start(self.params_in_force(), label="" if s is None else s.source_text(),
                      phone=None if s is None else s.describe(), at={**at, "state": bool(state)})
            if s is not None and s.open:
                self._begin(rec, s, state)
        except RecordingError as e:
            msg = str(e)
            status = 409 if "exists" in msg else 507 if msg.startswith("free space") else 422
            raise ToolError("name" if "name" in msg else "folder", msg, status) from None
        self.recorder = rec
        self._session = self.core.session
        return rec.summary()

    def _begin(self, rec: Recorder, s, state: dict[str, np.ndarray]) -> None:
        """A recording begun while a stream is on: first in the log the samples that
        reached the server before Record but that the filters have not stepped yet (queued,
        in the reorder buffer), as they came to this stage; and, when the filters have
        stepped some of the stream already (``state``), their state now. A re-run (from
        that state) then steps what the live filters stepped after it."""
        queued = list(self.queued(s)) if self.queued is not None else []
        pending = s.unmapped(queued) + s.held()       # each on its sensor's own clock
        if pending and self.undo_later_stages is not None:
            pending = self.undo_later_stages(pending)
        rec.write_samples(pending)
        rec.write_state(state)

    def _warm(self) -> dict[str, Any]:
        """Where the stream on show is as a recording begins: its time ``t`` (s, the last
        sample the filters stepped; None: none yet) and ``warm_s``, how long the filters
        have run on it. A re-run starts cold at the log's first line: it reproduces the
        live estimates when ``warm_s`` is 0."""
        c = self.core
        s = c.session
        # (a stream just opened whose filters have not been reset for it yet: cold)
        if s is None or not s.open or c.t_sent is None or c.t_first is None \
                or c.stepping is not s:
            return {"t": None, "warm_s": 0.0}
        return {"t": c.t_sent, "warm_s": round(max(0.0, c.t_sent - c.t_first), 3)}

    def stop(self) -> dict[str, Any]:
        if self.recorder is None:
            if self.last is not None:
                return self.last
            raise ToolError("recording", "not recording", 409)
        self.last = self.recorder.stop("stopped")
        self.recorder = None
        self._session = None
        return self.last

    def status(self) -> dict[str, Any]:
        """While recording: its summary (``bytes``, ``bytes_per_s``, ``elapsed_s``,
        ``limits``, ...); else ``{"recording": False, "last"}`` (``last.stop_reason``:
        the cap that stopped it, if one did)."""
        if self.recorder is not None:
            return {**self.recorder.summary(), "recording": True}
        return {"recording": False, "last": self.last, "limits": self.limits.as_dict()}

    def scan(self) -> tuple[list[dict[str, Any]], list[dict[str, str]]]:
        """The recordings and the files of the folder left out, with why (at most
        :data:`LEFT_OUT_SHOWN`, then one line saying how many more); the log being
        written, empty until its first flush, is not among them."""
        listed, left = scan_recordings(self.folder)
        rec = self.recorder
        seg = rec.segment if rec is not None else None
        if seg is not None:
            left = [x for x in left if x["file"] != seg.path.name]
        if len(left) > LEFT_OUT_SHOWN:
            more = len(left) - LEFT_OUT_SHOWN
            left = left[:LEFT_OUT_SHOWN] + [{"file": f"... and {more} more", "why": "not shown"}]
        return listed, left

    def names(self) -> list[str]:
        """The recordings' names, newest first, each once (the page's menus, asked twice a
        second on the loop): read again (the folder's names, the logs' sizes and times)
        only when the folder changed, the recording being made got its first bytes, or
        :data:`NAMES_FRESH_S` passed (a file copied in is made empty, then written)."""
        seg = self.recorder.segment if self.recorder is not None else None
        try:
            changed = self.folder.stat().st_mtime_ns
        except OSError:
            changed = None
        key = (changed, None if seg is None else (seg.name, file_size(seg.path) > 0),
               int(time.monotonic() // NAMES_FRESH_S))
        if key != self._names[0]:
            self._names = (key, list(recording_logs(self.folder)[0]))
        return list(self._names[1])

    def files(self, name: str, field: str = "name") -> dict[str, Path | None]:
        """The files of recording ``name``; ToolError (404, naming the request's ``field``)
        if there is none."""
        try:
            return recording_files(self.folder, name)
        except RecordingError as e:
            raise ToolError(field, str(e), 404) from None
