"""The live core: the stream on show, the ensemble, the history; synchronous and pure.

One :class:`LiveCore` per dashboard. The async shell (:mod:`app.server.engine`) calls:

- :meth:`LiveCore.open_session` / :meth:`close_session` / :meth:`feed`: a stream's samples
  in (any source: the sources decode their own wire formats), the samples it releases
  out (count, reorder; the sample stages see every chunk first: the lab toolkit's
  injection, recorder and magnetometer calibration);
- :meth:`LiveCore.start` (a new stream: the estimators start afresh) and
  :meth:`LiveCore.process` (released samples -> every instance steps; the plots' rings,
  counters and the record listeners follow);
- :meth:`LiveCore.validate` / :meth:`apply`: a PATCH body or a preset -> a validated
  change -> applied between two chunks;
- the read models: :meth:`snapshot`, :meth:`state`, :meth:`params_view`, :meth:`counts`,
  :meth:`status_text`, :meth:`source_kind`.

Nothing here knows asyncio, viser or FastAPI; tests build one and feed it samples.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Callable

import numpy as np

from app.estimators.base import F_ACC_NIS, F_MAG_NIS
from app.params import describe, to_dict
from app.quaternion import not_estimated
from app.sources.samples import Sample
from app.live import views
from app.live.ensemble import Ensemble, Records
from app.live.changes import Change, apply_change, change_from_config, common_names, validate_patch
from app.live.history import History
from app.live.session import Session, Totals

log = logging.getLogger("orientlab.live")

RecordListener = Callable[[Session, Records], None]    # (session, what one chunk made)


class LiveCore:
    """See the module doc. ``config``: :func:`app.config.load_config`'s dict (read once)."""

    def __init__(self, config: dict[str, Any] | None = None, *, history_s: float = 20.0,
                 reorder_window_s: float = 0.05, history_rate_hz: float = 2000.0):
        self.ensemble = Ensemble(config)
        self.history = History(int(history_s * history_rate_hz) + 1)
        self.reorder_window_s = reorder_window_s
        self.totals = Totals()
        self.session: Session | None = None
        # sample stages run first and may rewrite a chunk's samples (the lab toolkit:
        # virtual disturbances, the recorder's copy, the magnetometer calibration):
        # (session, samples) -> samples
        self.sample_stages: list[Callable[[Session, list[Sample]], list[Sample]]] = []
        self.record_listeners: list[RecordListener] = []
        self._reset_stream_state()

    def _reset_stream_state(self) -> None:
        self.stepping: Session | None = None      # the stream whose samples they stepped
        self.t_sent: float | None = None          # time of the last processed sample (s)
        self.t_first: float | None = None         # the stream's first motion sample (s)
        self.last_vec: list[np.ndarray | None] = [None, None, None]   # gyr, acc, mag
        self.history.clear()

    # ----------------------------------------------------------------- streams
    def open_session(self, kind: str, label: str, truth=None, phone_app: str = "",
                     window_s: float | None = None) -> Session:
        """A new stream replaces the one on show (which is closed). ``window_s``: its
        reorder window (default the core's; a source that delivers in batches may ask
        for more)."""
        s = Session(kind, label, self.reorder_window_s if window_s is None else window_s,
                    truth, phone_app=phone_app)
        if self.session is not None and self.session.open:
            # (a phone by its app: the reason goes into recordings the class downloads)
            self.session.close(f"replaced by {s.source_text()}")
        self.session = s
        self.totals.sessions += 1
        return s

    def close_session(self, s: Session, reason: str = "end of stream") -> list[Sample]:
        """End a stream; the samples its reorder buffer still held (to process)."""
        return s.close(reason)

    def feed(self, s: Session, samples: list[Sample]) -> list[Sample]:
        """Samples of one received chunk (arrival order) into the stream; the samples it
        releases, in time order."""
        for f in self.sample_stages:
            try:
                samples = f(s, samples)
            except Exception:  # a stage's bug must not stop the stream
                log.exception("sample stage failed")
        return s.push(samples)

    def start(self, s: Session) -> None:
        """A new stream is on: every instance starts afresh (a new clock)."""
        self.ensemble.reset()
        self._reset_stream_state()
        self.stepping = s           # the stream the estimators' state belongs to

    def process(self, s: Session, samples: list[Sample]) -> Records | None:
        """Step every instance on the samples of the stream on show (others: None)."""
        if s is not self.session or not samples:
            return None
        lk0 = self._primary_lk()
        rec = self.ensemble.step(samples)
        # a sensor switched off while the stream goes on: its last decision and vector
        # are no longer news (the phone's own estimate expires in its estimator)
        gone = s.stopped()
        self.ensemble.set_stopped(gone)
        self._record(rec, lk0)
        for k, tag in ((1, "ACC"), (2, "MAG")):
            if tag in gone:
                self.last_vec[k] = None
        s.count_processed(rec.n_samples)
        self.totals.samples += rec.n_samples
        for cb in self.record_listeners:
            try:
                cb(s, rec)
            except Exception:
                log.exception("record listener failed")
        return rec

    def _record(self, rec: Records, lk0: float) -> None:
        """The plots' rows (primary) and the last sensor vectors; ``lk0``: the primary's
        L_k before the chunk."""
        if rec.t_last is not None:
            self.t_sent = rec.t_last
        n = len(rec)
        if not n:
            return
        if self.t_first is None:
            self.t_first = float(rec.t[0])
        h = self.history
        q = rec.primary_q
        q = np.where(not_estimated(q)[:, None], np.nan, q)   # before the alignment: a gap
        h.pose.extend(rec.t, q, rec.phone_q)
        kind = rec.kind
        sel = np.flatnonzero(kind == 0)
        if sel.size:
            h.gyr.extend(rec.t[sel], rec.values[sel, :3])
        flags = rec.flags[rec.primary]
        est = self.ensemble.estimator(rec.primary)
        for k, ring, nis_col in ((1, h.acc, F_ACC_NIS), (2, h.mag, F_MAG_NIS)):
            sel = np.flatnonzero(kind == k)
            if not sel.size:
                continue
            v = rec.values[sel, :3]
            self.last_vec[k] = v[-1].copy()
            norm = np.sqrt(np.einsum("ij,ij->i", v, v))
            if k == 1:
                ring.extend(rec.t[sel], norm, flags[sel, nis_col])
            else:
                lk = est.field_strength_rows(flags[sel], lk0)
                ring.extend(rec.t[sel], norm, np.nan if lk is None else lk, flags[sel, nis_col])

    def _primary_lk(self) -> float:
        lk = self.ensemble.estimator(self.ensemble.primary).field_strength()
        return math.nan if lk is None else float(lk)

    # ----------------------------------------------------------------- changes
    def validate(self, body: Any) -> Change:
        """A PATCH body -> a validated change (PatchError naming the field)."""
        return validate_patch(self.ensemble, body)

    def change_from_config(self, config: dict[str, Any]) -> Change:
        return change_from_config(self.ensemble, config)

    def apply(self, ch: Change) -> dict[str, Any]:
        """Apply a validated change (PatchError if it no longer fits); the new parameters."""
        apply_change(self.ensemble, ch)
        if ch.reset:
            self._reset_stream_state()
        return self.params_view()

    # ----------------------------------------------------------------- read models
    def snapshot(self) -> views.Snapshot:
        return views.snapshot(self)

    def state(self) -> dict[str, Any]:
        return views.state(self)

    def params_view(self) -> dict[str, Any]:
        """GET /api/params: the primary, the switches every instance has (the primary's
        values), each instance's parameters (SI units) and its base kind."""
        b = self.ensemble
        prim = to_dict(b.params_of(b.primary))
        out: dict[str, Any] = {"primary": b.primary}
        for k in common_names(b):
            out[k] = prim[k]
        out["estimators"] = {n: to_dict(b.params_of(n)) for n in b.names}
        out["bases"] = {n: b.base_of(n) for n in b.names}
        return out

    def preset_sections(self) -> dict[str, Any]:
        """The builtins' parameters and the primary (its base if it is a variant), as a
        preset's tables (variants are not part of a preset)."""
        b = self.ensemble
        out: dict[str, Any] = {"primary": b.base_of(b.primary)}
        for n, inst in b.instances.items():
            if inst.builtin:
                out[n] = to_dict(inst.estimator.params)
        return out

    def params_schema(self) -> dict[str, Any]:
        return {n: describe(type(self.ensemble.params_of(n))) for n in self.ensemble.names}

    def truth_q(self) -> np.ndarray | None:
        s = self.session
        return None if s is None else s.truth_at(self.t_sent)

    def source_kind(self) -> str:
        s = self.session
        if s is None:
            return "none"
        if s.kind == "phone" and not s.open:
            return "phone-disconnected"
        return s.kind

    def status_text(self) -> str:
        s = self.session
        if s is None:
            return "waiting for a phone"
        if s.kind == "demo":
            return "demo: simulated phone (a phone that connects takes over)"
        if s.kind == "replay":
            return f"replaying log {s.label}" + ("" if s.open else " (ended)")
        # the phone's address is the presenter's business (GET /api/connect), not every
        # watcher's: the status names its app only
        who = f"phone ({s.app_name})" if s.app_name else "phone"
        if s.open:
            silent = s.silent()
            if silent is not None:
                why = s.silent_hint() or "is the app still sending?"
                return (f"{who} connected, but no samples for {silent:.0f} s: {why} "
                        "(showing its last state)")
            return f"{who} streaming"
        return (f"{who} disconnected ({s.close_reason}): showing its last state; "
                "waiting for a phone")

    def counts(self) -> dict[str, Any]:
        c = self.session.counts() if self.session else {"lines": 0, "samples": 0, "malformed": 0}
        tot = self.totals.as_dict()
        tot["step_errors"] = self.ensemble.step_errors()
        tot["restored"] = self.ensemble.restored()
        c.update({f"total_{k}": v for k, v in tot.items()})
        c["updates"] = {n: i.updates() for n, i in self.ensemble.instances.items()}
        return c
