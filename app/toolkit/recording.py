"""Record a live session: the raw stream as a Sensor Fusion app log, and beside it the
estimates and the parameters in force.

A recording named ``NAME`` in the recordings folder is three files:

``NAME.txt``
    The stream exactly as it arrived, in the app's log format (the phone's lines,
    byte for byte, one per line, ``\\n`` ended): readable by ``orientlab estimate``,
    ``orientlab calibrate``, ``--source`` and the manual's MATLAB tools. Marks (a virtual
    magnet or shake injected from the page, a parameter change) are ``TXT`` lines of the
    same format (``<time_ms>\\tTXT\\torientlab: ...``); every reader skips them for the
    estimation. When disturbances are injected, the log holds the lines as the estimators
    got them (the injected field or acceleration included), so a re-run or a replay
    shows the same disturbance.
``NAME.estimates.csv``
    One row per processed sample and estimator: ``estimator,tag,`` followed by the
    columns of ``orientlab estimate`` (``t,qw,qx,qy,qz,gyr,acc,acc_value,...``, see
    :mod:`app.cli`). ``t`` is on the stream's reference clock (s). A session with a known
    truth (the demo) adds rows of the estimator ``truth``.
``NAME.events.jsonl``
    One JSON object per line: ``{"kind": "start", "params": {...}}`` with every
    estimator's parameters in force, then ``{"kind": "params", "t": ..., "params": ...}``
    at every change, ``{"kind": "inject", ...}``, and ``{"kind": "end", "reason": ...,
    "seconds": ..., "samples": ...}``. ``t`` is stream time (s), ``wall`` Unix time.

A stream ends the segment: if the phone disconnects while recording, the files are
closed cleanly (``end`` says why); when a stream starts again, the recording goes on in
a new segment ``NAME_2`` (a new clock, so a new log). A write that fails (full disk,
folder removed or not writable) stops the recording with :attr:`Recorder.error`
saying why; it never raises into the live path.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from app.estimators import FLAG_COLUMNS, Reason, TimeIssue
from app.sources.sensorfusion import format_line
from app.estimators.base import F_ACC, F_ACC_NIS, F_ACC_VAL, F_GYR, F_MAG, F_MAG_NIS, F_MAG_VAL, F_REST, F_TIME

LOG_SUFFIX = ".txt"
ESTIMATES_SUFFIX = ".estimates.csv"
EVENTS_SUFFIX = ".events.jsonl"
SIBLING_SUFFIXES = (ESTIMATES_SUFFIX, EVENTS_SUFFIX)
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,119}\Z")   # \Z: "$" also matches before a final "\n"
ESTIMATE_COLUMNS = ("estimator", "tag")  # + OUTPUT_COLUMNS

# ---------------------------------------------------------------- the estimates CSV format
# (written by ``orientlab estimate`` and by a recording's estimates file)
OUTPUT_COLUMNS = ("t", "qw", "qx", "qy", "qz") + FLAG_COLUMNS
_REASON_LABELS = {int(r): r.label for r in Reason}
_TIME_LABELS = {int(r): r.name.lower() for r in TimeIssue}


def _labels(col: np.ndarray, table: dict[int, str]) -> list[str]:
    return [table.get(v, str(v)) for v in col.astype(int).tolist()]


def _numbers(col: np.ndarray, fmt: str) -> list[str]:
    return ["" if v != v else fmt % v for v in col.tolist()]


def format_rows(t: np.ndarray, q: np.ndarray, flags: np.ndarray) -> str:
    """CSV text (no header) of estimates and flag records, see the module doc."""
    cols = [_numbers(t, "%.6f")] + [_numbers(q[:, i], "%.9f") for i in range(4)]
    for j in range(flags.shape[1]):
        if j in (F_GYR, F_ACC, F_MAG):
            cols.append(_labels(flags[:, j], _REASON_LABELS))
        elif j == F_TIME:
            cols.append(_labels(flags[:, j], _TIME_LABELS))
        elif j == F_REST:
            cols.append(["1" if v > 0.5 else "0" for v in flags[:, j].tolist()])
        elif j in (F_ACC_VAL, F_ACC_NIS, F_MAG_VAL, F_MAG_NIS):
            cols.append(_numbers(flags[:, j], "%.6g"))
    if not cols[0]:
        return ""
    return "\n".join(",".join(r) for r in zip(*cols)) + "\n"


class RecordingError(Exception):
    """A recording cannot be started, read or written (the message says why)."""


def check_name(name: str) -> str:
    """A recording name: letters, digits, ``.``, ``_``, ``-`` (no path)."""
    if not isinstance(name, str) or not NAME_RE.match(name) or ".." in name:
        raise RecordingError(f"invalid recording name {name!r}: use letters, digits, '.', '_' "
                             f"or '-' (at most 120)")
    return name


def default_name(now: float | None = None) -> str:
    """``orientlab_YYYYMMDDTHHMMSS`` (UTC), as the app names its logs."""
    return "orientlab_" + time.strftime("%Y%m%dT%H%M%S", time.gmtime(now or time.time()))


def _os_message(path: Path, e: OSError) -> str:
    why = e.strerror or str(e)
    if getattr(e, "errno", None) == 28:
        why = "the disk is full"
    return f"cannot write {path}: {why}"


def _json_default(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, (set, tuple)):
        return list(x)
    return str(x)


def _finite(x):
    """JSON-safe: NaN/inf become None (json.dumps would write NaN, which is not JSON)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


@dataclass
class Segment:
    """One stream's part of a recording: a log and its sibling files."""
    name: str
    path: Path
    label: str = ""
    lines: int = 0
    samples: int = 0            # motion samples processed while recording
    t_first: float | None = None
    t_last: float | None = None
    started: float = field(default_factory=time.time)
    ended: float | None = None
    end_reason: str = ""

    @property
    def seconds(self) -> float:
        if self.t_first is None or self.t_last is None:
            return 0.0
        return max(0.0, self.t_last - self.t_first)

    def summary(self) -> dict[str, Any]:
        return {"name": self.name, "path": str(self.path), "seconds": round(self.seconds, 3),
                "samples": self.samples, "lines": self.lines, "source": self.label,
                "started": self.started, "ended": self.ended, "end_reason": self.end_reason}


class Recorder:
    """Writes one recording (possibly several segments) into ``folder``.

    Pure and synchronous: the live server calls :meth:`write_lines` with the raw lines
    of the stream on show, :meth:`write_estimates` with what the estimators made of
    them, :meth:`note` for parameter changes and injections, :meth:`end_segment` when the
    stream ends and :meth:`stop` at the end. None of them raises on a failed write:
    the recording stops and :attr:`error` says why (the live view keeps running).
    """

    def __init__(self, folder: str | Path, name: str | None = None,
                 clock: Callable[[], float] = time.time, flush_every_s: float = 1.0):
        self.folder = Path(folder)
        self.base = check_name(name) if name else default_name(clock())
        self.clock = clock
        self.flush_every_s = flush_every_s
        self.segments: list[Segment] = []
        self.error: str | None = None
        self.active = False
        self._log = self._est = self._events = None
        self._last_flush = 0.0
        self._params: dict[str, Any] = {}

    # ----------------------------------------------------------------- life
    def start(self, params: dict[str, Any], label: str = "",
              phone: dict[str, Any] | None = None) -> Segment:
        """Open the first segment; RecordingError (nothing written) if the folder
        cannot be created or written, or the name is taken."""
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise RecordingError(f"cannot create the recordings folder {self.folder}: "
                                 f"{e.strerror or e}") from None
        if not os.access(self.folder, os.W_OK):
            raise RecordingError(f"the recordings folder {self.folder} is not writable")
        if (self.folder / (self.base + LOG_SUFFIX)).exists():
            raise RecordingError(f"a recording named {self.base!r} exists already")
        self._params = params
        self.active = True
        try:
            return self._open_segment(label, phone)
        except OSError as e:
            self.active = False
            raise RecordingError(_os_message(self.folder / self.base, e)) from None

    def _segment_name(self) -> str:
        k = len(self.segments) + 1
        name = self.base if k == 1 else f"{self.base}_{k}"
        while (self.folder / (name + LOG_SUFFIX)).exists():
            k += 1
            name = f"{self.base}_{k}"
        return name

    def _open_segment(self, label: str, phone: dict[str, Any] | None = None) -> Segment:
        name = self._segment_name()
        seg = Segment(name=name, path=self.folder / (name + LOG_SUFFIX), label=label,
                      started=self.clock())
        self._log = open(seg.path, "wb")
        self._est = open(self.folder / (name + ESTIMATES_SUFFIX), "w", newline="")
        self._events = open(self.folder / (name + EVENTS_SUFFIX), "w")
        self.segments.append(seg)
        self._est.write(",".join(ESTIMATE_COLUMNS + OUTPUT_COLUMNS) + "\n")
        # the phone: its app, platform and sign convention, as the source detected them
        self._event({"kind": "start", "source": label, "phone": phone or None,
                     "params": self._params})
        return seg

    @property
    def segment(self) -> Segment | None:
        return self.segments[-1] if self.segments and self._log is not None else None

    def new_segment(self, label: str = "", phone: dict[str, Any] | None = None) -> None:
        """A new stream started while recording: go on in a new segment."""
        if not self.active:
            return
        if self._log is not None:
            self.end_segment("a new stream started")
        self._guard(lambda: self._open_segment(label, phone), self.folder / self.base)

    def end_segment(self, reason: str) -> None:
        """The stream ended (phone disconnected, end of log): close the files cleanly."""
        seg = self.segment
        if seg is None:
            return
        seg.ended = self.clock()
        seg.end_reason = reason
        self._event({"kind": "end", "reason": reason, "seconds": round(seg.seconds, 3),
                     "samples": seg.samples, "lines": seg.lines})
        self._close_files()

    def stop(self, reason: str = "stopped") -> dict[str, Any]:
        """End the recording: ``{name, path, seconds, samples, segments: [...], error}``
        (name/path of the first segment; seconds and samples over all segments)."""
        if self.segment is not None:
            self.end_segment(reason)
        self.active = False
        return self.summary()

    def summary(self) -> dict[str, Any]:
        segs = [s.summary() for s in self.segments]
        first = segs[0] if segs else {"name": self.base, "path": str(self.folder / (self.base + LOG_SUFFIX))}
        return {"name": first["name"], "path": first["path"],
                "seconds": round(sum(s.seconds for s in self.segments), 3),
                "samples": sum(s.samples for s in self.segments),
                "recording": self.active, "segments": segs, "error": self.error}

    # ----------------------------------------------------------------- writing
    def write_samples(self, samples: list) -> None:
        """The stream's samples (of any source), as received, in the Sensor Fusion app's
        log format: a recording of any app replays as a log."""
        seg = self.segment
        if seg is None or not samples:
            return
        data = ("\n".join(format_line(s.time_ms, s.tag, s.values) for s in samples)
                + "\n").encode()
        if self._guard(lambda: self._log.write(data), seg.path):
            seg.lines += len(samples)
            self._maybe_flush()

    def write_estimates(self, name: str, t: np.ndarray, tags: list[str] | str,
                        q: np.ndarray, flags: np.ndarray | None = None) -> None:
        """Estimates of estimator ``name`` after the samples at times ``t`` (s) with
        tags ``tags``; ``flags`` (N, NFLAGS) or None (then the flag cells are empty)."""
        seg = self.segment
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if seg is None or t.size == 0:
            return
        from app.estimators import FLAG_COLUMNS
        q = np.asarray(q, dtype=float).reshape(-1, 4)
        if flags is None:  # no flag record (truth, phone): empty flag cells
            blank = "," * len(FLAG_COLUMNS)
            text = "".join(f"{a:.6f},{b:.9f},{c:.9f},{d:.9f},{e:.9f}{blank}\n"
                           for a, (b, c, d, e) in zip(t.tolist(), q.tolist()))
        else:
            text = format_rows(t, q, np.asarray(flags, dtype=float))
        if isinstance(tags, str):
            tags = [tags] * t.size
        rows = text.splitlines()
        out = "".join(f"{name},{tg},{r}\n" for tg, r in zip(tags, rows))
        self._guard(lambda: self._est.write(out), self.folder / (seg.name + ESTIMATES_SUFFIX))

    def count_samples(self, t: np.ndarray) -> None:
        """Motion samples processed (once per sample, not per estimator): the segment's
        ``samples`` and ``seconds``."""
        seg = self.segment
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if seg is None or t.size == 0:
            return
        seg.samples += int(t.size)
        if seg.t_first is None:
            seg.t_first = float(t[0])
        seg.t_last = float(t[-1])

    def note(self, kind: str, t: float | None = None, mark: tuple[int, str] | None = None,
             **data: Any) -> None:
        """An event (``params`` with the parameters now in force, ``inject``, ...);
        ``mark = (time_ms, text)`` also puts a TXT line in the log."""
        if kind == "params" and "params" in data:
            self._params = data["params"]
        seg = self.segment
        if seg is None:
            return
        self._event({"kind": kind, "t": t, **data})
        if mark is not None:
            ms, text = mark
            line = f"{int(ms)}\tTXT\torientlab: {text}".replace("\n", " ").encode()
            if self._guard(lambda: self._log.write(line + b"\n"), seg.path):
                seg.lines += 1

    def _event(self, obj: dict[str, Any]) -> None:
        obj = {**obj, "wall": round(self.clock(), 3)}
        text = json.dumps(_finite(obj), default=_json_default) + "\n"
        seg = self.segments[-1] if self.segments else None
        path = self.folder / ((seg.name if seg else self.base) + EVENTS_SUFFIX)
        self._guard(lambda: self._events.write(text), path)

    # ----------------------------------------------------------------- failures
    def _guard(self, fn: Callable[[], Any], path: Path) -> bool:
        """Run a write; on OSError stop the recording with a clear message."""
        if self.error is not None:
            return False
        try:
            fn()
            return True
        except OSError as e:
            self.error = _os_message(path, e)
            self.active = False
            seg = self.segments[-1] if self.segments else None
            if seg is not None:
                seg.ended, seg.end_reason = self.clock(), f"write failed: {self.error}"
            self._close_files(quiet=True)
            return False

    def _maybe_flush(self) -> None:
        now = self.clock()
        if now - self._last_flush >= self.flush_every_s:
            self._last_flush = now
            for fh in (self._log, self._est, self._events):
                if fh is not None and not self._guard(fh.flush, Path(fh.name)):
                    return

    def _close_files(self, quiet: bool = False) -> None:
        for attr in ("_log", "_est", "_events"):
            fh = getattr(self, attr)
            setattr(self, attr, None)
            if fh is None:
                continue
            try:
                fh.close()
            except OSError as e:  # the last flush failed (disk full)
                if not quiet and self.error is None:
                    self.error = _os_message(Path(fh.name), e)
                    self.active = False


# ---------------------------------------------------------------- the folder

def recording_files(folder: str | Path, name: str) -> dict[str, Path | None]:
    """The files of recording ``name``: ``log`` (required), ``estimates``, ``events``
    (None when absent). RecordingError if there is no such log."""
    folder = Path(folder)
    check_name(name)
    log = None
    for suffix in (LOG_SUFFIX, ".log", ".csv", ".npz", ""):
        p = folder / (name + suffix)
        if p.is_file() and not any(p.name.endswith(s) for s in SIBLING_SUFFIXES):
            log = p
            break
    if log is None:
        raise RecordingError(f"no recording named {name!r} in {folder}")
    est, ev = folder / (name + ESTIMATES_SUFFIX), folder / (name + EVENTS_SUFFIX)
    return {"log": log, "estimates": est if est.is_file() else None,
            "events": ev if ev.is_file() else None}


def read_events(path: str | Path | None) -> list[dict[str, Any]]:
    """The events of a recording (bad lines skipped)."""
    out = []
    if path is None or not Path(path).is_file():
        return out
    for line in Path(path).read_text(errors="replace").splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def list_recordings(folder: str | Path) -> list[dict[str, Any]]:
    """Every recording in ``folder``, newest first: our own (log + siblings) and any app
    log, CSV or npz dropped in it (name = file stem). ``seconds``/``samples`` come from the
    events file when there is one (else None: the log is not read here)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    out = []
    for p in folder.iterdir():
        if not p.is_file() or p.name.startswith("."):
            continue
        if any(p.name.endswith(s) for s in SIBLING_SUFFIXES):
            continue
        if p.suffix.lower() not in (".txt", ".log", ".csv", ".npz"):
            continue
        name = p.stem
        if not NAME_RE.match(name):
            continue
        ev = folder / (name + EVENTS_SUFFIX)
        events = read_events(ev) if ev.is_file() else []
        end = next((e for e in reversed(events) if e.get("kind") == "end"), None)
        st = p.stat()
        out.append({"name": name, "path": str(p), "bytes": st.st_size, "modified": st.st_mtime,
                    "orientlab": bool(events),
                    "has_estimates": (folder / (name + ESTIMATES_SUFFIX)).is_file(),
                    "seconds": end.get("seconds") if end else None,
                    "samples": end.get("samples") if end else None,
                    "end_reason": end.get("reason") if end else None,
                    "complete": end is not None or not events})
    out.sort(key=lambda r: r["modified"], reverse=True)
    return out


def read_estimates(path: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """A recording's estimates file: per estimator ``{"t": (N,), "q": (N, 4)}``."""
    import csv
    per: dict[str, tuple[list, list]] = {}
    with open(path, newline="") as fh:
        rd = csv.reader(fh)
        header = next(rd, None)
        if not header:
            return {}
        ix = {c: i for i, c in enumerate(header)}
        it, iq = ix["t"], [ix[c] for c in ("qw", "qx", "qy", "qz")]
        ie = ix["estimator"]
        for row in rd:
            try:
                tt = float(row[it])
                q = [float(row[i]) for i in iq]
            except (ValueError, IndexError):
                continue
            ts, qs = per.setdefault(row[ie], ([], []))
            ts.append(tt)
            qs.append(q)
    return {k: {"t": np.array(v[0]), "q": np.array(v[1]).reshape(-1, 4)} for k, v in per.items()}
