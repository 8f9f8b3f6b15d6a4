"""The lab session toolkit on the live server: recording, calibration, magnetometer
calibration, replay control, what-if, variants and disturbance injection.

One :class:`LabTools` per dashboard (on ``app.state.lab``), built in the lifespan. It
hangs on the live core's hooks and owns the toolkit's state; the routers
(:mod:`app.server.routers.recordings`, ``calibrate``, ``replay``, ``estimators``,
``inject``) and the page (:mod:`app.server.gui.lab`) call its methods. Everything here
runs on the server's event loop (the page's callbacks hand over with
``run_coroutine_threadsafe``); CPU-heavy work (a what-if re-run, statistics) runs in a
worker thread on copies.

The stream's samples (of any source) pass, in order: the injector (a virtual magnet or
shake, marked by TXT samples) -> the recorder (the log is what the estimators got, before
the magnetometer calibration) -> the magnetometer calibration (hard and soft iron, applied
to MAG) -> the core (reorder, estimators).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.toolkit import calibration as calmod
from app.toolkit import magcal
from app.toolkit.inject import Disturbance, Injector, parse_request
from app.params import to_dict
from app.toolkit.recording import (Recorder, RecordingError, list_recordings, read_estimates,
    recording_files)
from app.toolkit.variants import no_rejection_changes
from app.toolkit.whatif import rerun

log = logging.getLogger("orientlab.lab")

CAL_MIN_S, CAL_MAX_S = 1.0, 600.0
MAGCAL_MAX_S = 300.0


class LabError(ValueError):
    """A refused request: ``field`` names the key, ``status`` the HTTP status."""

    def __init__(self, field_name: str, reason: str, status: int = 422):
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason
        self.status = status


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

    def status(self) -> dict[str, Any]:
        n = sum(len(x) for x in self.t)
        return {"kind": self.kind, "seconds": self.seconds, "elapsed_s": round(self.elapsed, 2),
                "remaining_s": round(self.remaining, 2), "rows": n,
                "done": self.result is not None or self.error is not None, "error": self.error}


class LabTools:
    """See the module doc. ``engine``: the async shell (``engine.core`` the live core)."""

    def __init__(self, engine, settings, config: dict[str, Any] | None = None):
        self.engine = engine
        self.core = engine.core
        self.settings = settings
        self.folder = Path(getattr(settings, "recordings", None) or "recordings")
        self.injector = Injector(orientation=self._orientation)
        self.magcal: magcal.MagCalibration | None = None
        if config and config.get("magcal"):
            try:
                self.magcal = magcal.from_preset(config["magcal"])
            except magcal.MagCalError as e:
                log.warning("preset: %s", e)
        self.recorder: Recorder | None = None
        self.last_recording: dict[str, Any] | None = None
        self.capture: Capture | None = None
        self.last_calibration: dict[str, Any] | None = None
        self.last_calibration_stats = None
        self.mag_capture: Capture | None = None
        self.mag_result: magcal.MagCalibration | None = None
        self.replay = None              # sources.ReplayControl of the replayed log, if any
        self.replay_name: str | None = None
        self.marks: list[dict[str, Any]] = []   # injection marks for the plots (stream s)
        self._spans: dict[int, list] = {}       # injection id -> [session, kind, start_s, end_s]
        self.last_rerun: dict[str, Any] | None = None
        self.engine_server = None       # the viser server (the variants' ghosts), set in the lifespan
        self.app_state = None           # the app's state (tasks: the source), set in the lifespan
        self._rec_session = None
        self._raw_mag: list[np.ndarray] = []
        self._recording_cache: dict = {}
        self.core.record_listeners.append(self._on_records)
        engine.change_listeners.append(self._on_change)
        engine.param_listeners.append(self._on_params)
        engine.preset_parts.append(self._preset_part)
        self.core.sample_stages.append(self.sample_stage)

    # ----------------------------------------------------------------- the stream
    def _orientation(self) -> np.ndarray | None:
        """The phone's orientation for world-frame disturbances: the truth (demo), else
        the phone's own estimate, else the primary's (before the disturbance shows)."""
        q = self.core.truth_q()
        if q is None:
            q = self.core.bench.phone_q
        if q is None:
            b = self.core.bench
            est = b.estimator(b.primary)
            q = est.q if est.initialized else None
        return q

    def sample_stage(self, session, samples: list) -> list:
        """The sample stage before the core: injection, then (after the recorder's copy)
        the magnetometer calibration. Never raises (a bug passes the samples unchanged)."""
        try:
            if self.injector.busy:
                samples, marks = self.injector.feed(samples)
                for m in marks:
                    self._on_mark(m, session)
            if self.recorder is not None:
                self._record_samples(session, samples)
            if self.mag_capture is not None and self.mag_capture.result is None:
                self._collect_raw_mag(samples)
            if self.magcal is not None:
                samples = magcal.correct_samples(self.magcal, samples)
        except Exception:
            log.exception("lab sample stage failed (samples passed unchanged)")
        return samples

    def _record_samples(self, session, samples: list) -> None:
        rec = self.recorder
        if session is not self._rec_session:
            if self._rec_session is not None:
                rec.new_segment(session.label, session.describe())
            self._rec_session = session
        rec.write_samples(samples)
        self._check_recorder()

    def _on_mark(self, m: dict[str, Any], session=None) -> None:
        self.marks.append({**m, "t": m["time_ms"] / 1000.0, "line": None})
        del self.marks[:-40]
        # the span on the stream's reference clock (the plots' time axis): the mark is
        # on the clock of the sensor disturbed, which may run with an offset
        tag = "MAG" if m["kind"] == "magnet" else "ACC"
        off = session.orderer.offsets.get(tag, 0.0) if session is not None else 0.0
        t = m["time_ms"] / 1000.0 - off
        if m["event"] == "start":
            self._spans[m["id"]] = [session, m["kind"], t, math.inf]
            while len(self._spans) > 20:
                del self._spans[next(iter(self._spans))]
        elif m["id"] in self._spans and self._spans[m["id"]][0] is session:
            self._spans[m["id"]][3] = t
        if self.recorder is not None:
            self.recorder.note("inject", t=m["time_ms"] / 1000.0, event=m["event"], id=m["id"],
                               text=m["text"])

    def _on_records(self, session, rec) -> None:
        if not len(rec):
            return
        if self.recorder is not None and session is self._rec_session:
            r = self.recorder
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
            self._check_recorder()
        cap = self.capture
        if cap is not None and cap.result is None and cap.error is None:
            if cap.add(rec.t, rec.kind, rec.values):
                self._finish_capture(cap)

    def _on_change(self, ch) -> None:
        """A preset loaded (page or API): its magnetometer calibration, or none."""
        if not getattr(ch, "magcal_set", False):
            return
        try:
            self.magcal = magcal.from_preset(ch.magcal) if ch.magcal else None
        except magcal.MagCalError as e:    # load_config validated it: not expected
            log.error("preset's [magcal] not applied: %s", e)

    def _preset_part(self) -> dict[str, Any]:
        return {} if self.magcal is None else {"magcal": self.magcal.preset()}

    def _on_params(self) -> None:
        if self.recorder is not None:
            self.recorder.note("params", t=self.core.t_sent, params=self.params_in_force(),
                               mark=None if self.core.t_sent is None
                               else (int(self.core.t_sent * 1000), "parameters changed"))

    def params_in_force(self) -> dict[str, Any]:
        b = self.core.bench
        out = {n: {"base": b.base_of(n), **to_dict(b.params_of(n))} for n in b.names}
        out["primary"] = b.primary
        if self.magcal is not None:
            out["magcal"] = self.magcal.preset()
        return out

    def tick(self) -> None:
        """Called a few times a second: end a recording segment whose stream ended,
        give up a calibration whose stream stopped."""
        s = self._rec_session
        if self.recorder is not None and s is not None and not s.open and self.recorder.segment is not None:
            self.recorder.end_segment(s.close_reason or "end of stream")
        self._check_recorder()
        for cap in (self.capture, self.mag_capture):
            if cap is None or cap.result is not None or cap.error is not None:
                continue
            if time.monotonic() - cap.started_wall > cap.seconds * 3 + 10.0:
                cap.error = "no stream: the samples stopped coming (is the phone streaming?)"
                if cap.done is not None and not cap.done.done():
                    cap.done.set_exception(LabError("seconds", cap.error, 409))

    def _check_recorder(self) -> None:
        rec = self.recorder
        if rec is not None and rec.error is not None:
            self.last_recording = rec.stop("write failed")
            self.recorder = None
            self._rec_session = None
            log.error("recording stopped: %s", self.last_recording["error"])

    # ----------------------------------------------------------------- recording
    def start_recording(self, name: str | None = None) -> dict[str, Any]:
        if self.recorder is not None:
            raise LabError("recording", f"already recording {self.recorder.base!r}", 409)
        try:
            rec = Recorder(self.folder, name)
            s = self.core.session
            rec.start(self.params_in_force(), label="" if s is None else f"{s.kind} {s.label}",
                      phone=None if s is None else s.describe())
        except RecordingError as e:
            raise LabError("name" if "name" in str(e) else "folder", str(e),
                           409 if "exists" in str(e) else 422) from None
        self.recorder = rec
        self._rec_session = self.core.session
        return rec.summary()

    def stop_recording(self) -> dict[str, Any]:
        if self.recorder is None:
            if self.last_recording is not None:
                return self.last_recording
            raise LabError("recording", "not recording", 409)
        self.last_recording = self.recorder.stop("stopped")
        self.recorder = None
        self._rec_session = None
        return self.last_recording

    def recording_status(self) -> dict[str, Any]:
        if self.recorder is not None:
            return {**self.recorder.summary(), "recording": True}
        return {"recording": False, "last": self.last_recording}

    def recordings(self) -> list[dict[str, Any]]:
        return list_recordings(self.folder)

    def files(self, name: str) -> dict[str, Path | None]:
        try:
            return recording_files(self.folder, name)
        except RecordingError as e:
            raise LabError("name", str(e), 404) from None

    # ----------------------------------------------------------------- what-if
    def specs(self) -> dict[str, tuple[str, dict[str, Any]]]:
        b = self.core.bench
        return {n: (b.base_of(n), to_dict(b.params_of(n))) for n in b.names}

    async def rerun(self, name: str, patch: dict[str, Any] | None) -> dict[str, Any]:
        files = self.files(name)
        if patch is not None and not isinstance(patch, dict):
            raise LabError("patch", "must be an object {estimator: {param: value}}")
        truth = None
        if files["estimates"] is not None:
            truth = read_estimates(files["estimates"]).get("truth")
        specs = self.specs()
        from app.toolkit.whatif import WhatIfError
        loop = asyncio.get_running_loop()

        def run():
            return rerun(self._read_cached(files["log"]), specs, patch, truth)
        try:
            out = await loop.run_in_executor(None, run)
        except WhatIfError as e:
            raise LabError(e.field, e.reason) from None
        except ValueError as e:  # a file that cannot be read
            raise LabError("name", str(e)) from None
        out["name"] = name
        self.last_rerun = out
        return out

    def _read_cached(self, path: Path):
        """The recording at ``path``, parsed once: a what-if is re-run again and again
        with new parameters (reading a 10-minute log costs more than re-running it).
        Keyed on the file's size and time, so a rewritten file is read again; two kept."""
        from app.sources.readers import read_recording
        st = path.stat()
        key = (str(path), st.st_size, st.st_mtime_ns)
        cache = self._recording_cache
        if key in cache:
            cache[key] = cache.pop(key)
            return cache[key]
        rec = read_recording(path)
        cache[key] = rec
        while len(cache) > 2:
            cache.pop(next(iter(cache)))
        return rec

    # ----------------------------------------------------------------- calibration
    async def calibrate(self, seconds: float) -> dict[str, Any]:
        """Statistics of the next ``seconds`` of the live stream (keep the phone still)."""
        if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) \
                or not math.isfinite(seconds) or not CAL_MIN_S <= seconds <= CAL_MAX_S:
            raise LabError("seconds", f"must be a number of seconds in [{CAL_MIN_S:g}, {CAL_MAX_S:g}]")
        if self.capture is not None and self.capture.result is None and self.capture.error is None:
            raise LabError("seconds", "a calibration is already running", 409)
        if self.core.session is None or not self.core.session.open:
            raise LabError("seconds", "no stream: connect the phone (or run the demo) first", 409)
        cap = Capture("still", float(seconds))
        cap.done = asyncio.get_running_loop().create_future()
        self.capture = cap
        await cap.done
        return cap.result

    def _finish_capture(self, cap: Capture) -> None:
        t, g, a, m = cap.arrays()
        try:
            st = calmod.calibrate(t, g, a, m)
            if not st.sensors:
                raise ValueError("no accelerometer, gyroscope or magnetometer samples")
            cap.result = calmod.to_json(st, t, {"acc": a, "gyr": g, "mag": m})
            self.last_calibration = cap.result
            self.last_calibration_stats = st
            if cap.done is not None and not cap.done.done():
                cap.done.set_result(cap.result)
        except Exception as e:
            cap.error = str(e)
            if cap.done is not None and not cap.done.done():
                cap.done.set_exception(LabError("seconds", cap.error, 409))

    def calibrate_recording(self, name: str, from_s: float = 0.0, to_s: float | None = None) -> dict[str, Any]:
        """The statistics of a stretch of a recording (seconds from its start)."""
        from app.sources.readers import read_recording
        rec = read_recording(self.files(name)["log"])
        if not len(rec):
            raise LabError("name", "the recording has no samples")
        t = rec.t - rec.t[0]
        hi = t[-1] if to_s is None else float(to_s)
        sel = (t >= float(from_s)) & (t <= hi)
        if sel.sum() < 2:
            raise LabError("from_s", "the stretch holds fewer than 2 samples")
        st = calmod.calibrate(rec.t[sel], rec.gyr[sel], rec.acc[sel], rec.mag[sel])
        out = calmod.to_json(st, rec.t[sel], {"acc": rec.acc[sel], "gyr": rec.gyr[sel],
                                              "mag": rec.mag[sel]})
        self.last_calibration, self.last_calibration_stats = out, st
        return out

    def calibration_change(self) -> dict[str, dict[str, Any]]:
        """What "apply" sets: per builtin estimator the preset values (validated)."""
        if self.last_calibration is None:
            raise LabError("calibration", "no calibration yet: POST /api/calibrate first", 409)
        b = self.core.bench
        return {k: v for k, v in self.last_calibration["apply"].items() if k in b.names and v}

    def save_calibration_preset(self, name: str) -> Path:
        """The current parameters with the calibration's values and the magnetometer
        calibration, as a preset (what "apply" then "save" gives). Saved by the one save
        path of every preset (:func:`app.server.presets.save_preset`: name rules, no
        shipped name, the cap, an atomic write); PatchError (a refused name) or
        :class:`~app.server.presets.PresetWriteError` (the folder refused the write)."""
        from app.server.presets import save_preset
        header = "orientlab preset from a calibration on the page"
        if self.last_calibration is not None:
            header += "\n\n" + self.last_calibration["report"].rstrip("\n")
        # the builtins' parameters, the primary and (engine.preset_parts) the
        # magnetometer calibration in force
        return save_preset(self.engine, name, header=header)

    # ----------------------------------------------------------------- magnetometer
    def magcal_start(self, seconds: float) -> dict[str, Any]:
        if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) \
                or not math.isfinite(seconds) or not 5.0 <= seconds <= MAGCAL_MAX_S:
            raise LabError("seconds", f"must be a number of seconds in [5, {MAGCAL_MAX_S:g}]")
        if self.core.session is None or not self.core.session.open:
            raise LabError("seconds", "no stream: connect the phone (or run the demo) first", 409)
        self.mag_capture = Capture("magcal", float(seconds))
        self._raw_mag = []
        self.mag_result = None
        return self.magcal_status()

    def _collect_raw_mag(self, samples: list) -> None:
        cap = self.mag_capture
        for s in samples:
            if s.tag != "MAG":
                continue
            t = s.time_ms / 1000.0
            if cap.t0 is None:
                cap.t0 = t
            cap.t_last = t
            self._raw_mag.append(np.array(s.values[:3], dtype=float))
        if cap.elapsed >= cap.seconds:
            self._finish_magcal()

    def _finish_magcal(self) -> None:
        cap = self.mag_capture
        try:
            self.mag_result = magcal.fit(np.array(self._raw_mag).reshape(-1, 3))
            cap.result = self.mag_result.as_dict()
        except magcal.MagCalError as e:
            cap.error = str(e)

    def magcal_status(self) -> dict[str, Any]:
        cap = self.mag_capture
        out: dict[str, Any] = {"applied": None if self.magcal is None else self.magcal.as_dict()}
        if cap is None:
            return {**out, "capture": None}
        m = np.array(self._raw_mag).reshape(-1, 3)
        cov, counts = magcal.coverage(m) if len(m) else (0.0, [0] * magcal.N_DIRECTIONS)
        out["capture"] = {**cap.status(), "coverage": cov, "per_direction": [int(c) for c in counts],
                          "samples": int(len(m))}
        out["result"] = None if self.mag_result is None else self.mag_result.as_dict()
        return out

    def magcal_apply(self, clear: bool = False) -> dict[str, Any]:
        if clear:
            self.magcal = None
        else:
            if self.mag_result is None:
                raise LabError("magcal", "no fit yet: turn the phone in all directions first", 409)
            self.magcal = self.mag_result
        self._on_params()
        return self.magcal_status()

    # ----------------------------------------------------------------- variants
    def variant_change(self, name: str, base: str, params: dict[str, Any] | None):
        from app.live.changes import Change, Variant
        b = self.core.bench
        try:
            b.check_new(name, base, params)
        except Exception as e:  # BenchError or ParamError: both name the field
            fld = getattr(e, "field", "params")
            if fld not in ("name", "base", "params"):
                fld = f"params.{fld}"
            raise LabError(fld, getattr(e, "reason", str(e))) from None
        return Change(add=[Variant(name, base, dict(params or {}))])

    def no_rejection(self) -> tuple[str, str, dict[str, Any]]:
        base = self.core.bench.base_of(self.core.bench.primary)
        return f"{base}-no-rejection", base, no_rejection_changes(base)

    def remove_change(self, name: str):
        from app.live.changes import Change
        b = self.core.bench
        if name not in b.names:
            raise LabError("name", f"no estimator {name!r} (known: {', '.join(b.names)})", 404)
        if b.base_of(name) == name:
            raise LabError("name", f"{name} is built in and cannot be removed", 409)
        return Change(remove=[name])

    # ----------------------------------------------------------------- injection
    def inject(self, body: dict[str, Any]) -> dict[str, Any]:
        from app.toolkit.inject import InjectError
        try:
            d: Disturbance = parse_request(body)
        except InjectError as e:
            raise LabError(e.field, e.reason) from None
        if self.core.session is None or not self.core.session.open:
            raise LabError("kind", "no stream to disturb: connect the phone or run the demo", 409)
        a = self.injector.start(d, wall=time.time())
        return {"id": a.id, **d.as_dict(), "text": d.describe()}

    def injected_spans(self, session) -> list[tuple[str, float, float]]:
        """``(kind, start_s, end_s)`` of the disturbances injected into ``session``, in
        its stream time (reference clock, as the plots' history); ``end_s`` is inf while
        one is on."""
        return [(k, a, b) for s, k, a, b in self._spans.values() if s is session]

    def inject_status(self) -> dict[str, Any]:
        return {**self.injector.status(), "marks": [
            {k: v for k, v in m.items() if k != "line"} for m in self.marks[-20:]]}

    # ----------------------------------------------------------------- replay
    def replay_status(self) -> dict[str, Any]:
        return {"replaying": self.replay is not None, "name": self.replay_name,
                **({} if self.replay is None else self.replay.status())}

    def _set_source(self, app_state, coro) -> None:
        tasks = app_state.tasks
        old = tasks.pop("source", None)
        if old is not None:
            old.cancel()
        s = self.core.session
        if s is not None and s.open and s.kind in ("demo", "replay"):
            self.engine.close_session(s, "source changed from the page")
        if coro is not None:
            tasks["source"] = asyncio.get_running_loop().create_task(coro, name="source")

    def start_replay(self, app_state, name: str) -> None:
        """Replay recording ``name`` of the folder (it replaces the demo or the replay on
        show; a connected phone still has priority)."""
        from app.sources.runners import ReplayControl, run_replay
        if not isinstance(name, str):
            raise LabError("name", "must be a recording's name")
        path = self.files(name)["log"]
        from app.sources.readers import detect_format, ReaderError
        try:
            if detect_format(path) != "applog":
                raise LabError("name", f"{path.name} is not an app log (only logs can be replayed)")
        except ReaderError as e:
            raise LabError("name", str(e)) from None
        s = self.core.session
        if s is not None and s.open and s.kind == "phone":
            raise LabError("name", "a phone is streaming: it has priority over a replay", 409)
        ctl = ReplayControl(path.read_bytes().splitlines(), path.name)
        self.replay, self.replay_name = ctl, name
        self.engine.resume_background()
        self._set_source(app_state, run_replay(self.engine, path, self.settings.replay_pause_s,
                                               control=ctl))

    def stop_replay(self, app_state) -> None:
        """Back to the demo (or to waiting for a phone when started with --source none)."""
        from app.sources.runners import run_demo
        self.replay, self.replay_name = None, None
        demo = self.settings.source != "none"
        self._set_source(app_state, run_demo(self.engine, self.settings.demo_seed) if demo else None)
