"""Record a live session: the raw stream as a Sensor Fusion app log, and beside it the
estimates and the parameters in force.

A recording named ``NAME`` in the recordings folder is three files, and a fourth for one
begun while the filters were running on its stream:

``NAME.txt``
    The stream as it arrived, in the app's log format (the phone's lines, one per line,
    ``\\n`` ended; one begun into its stream starts with the samples that had arrived but
    were not filtered yet, in the order the filters take them): readable by ``orientlab estimate``,
    ``orientlab calibrate``, ``--source`` and the manual's MATLAB tools. Marks (a virtual
    magnet or shake injected from the page, a parameter change) are ``TXT`` lines of the
    same format (``<time_ms>\\tTXT\\torientlab: ...``); every reader skips them for the
    estimation. When disturbances are injected, the log holds the lines as the estimators
    got them (the injected field or acceleration included), so a re-run or a replay
    shows the same disturbance.
``NAME.estimates.csv.gz``
    gzip-compressed CSV: ``estimator,tag,`` followed by the columns of ``orientlab
    estimate`` (``t,qw,qx,qy,qz,gyr,acc,acc_value,...``, see :mod:`app.cli`). ``t`` is on
    the stream's reference clock (s). Compact: at most ``estimates_hz`` rows a second per
    estimator (the display rate, 20 by default; 0: every processed sample), the same
    rows for every estimator. The full rate is reproducible from the log by ``orientlab
    estimate`` (the log holds every line). A session with a known truth (the demo) adds
    rows of the estimator ``truth``, at the full rate (the what-if compares with it). An
    older recording's plain ``NAME.estimates.csv`` is read alike.
``NAME.events.jsonl``
    One JSON object per line: ``{"kind": "start", "params": {...}}`` with every
    estimator's parameters in force, then ``{"kind": "params", "t": ..., "params": ...}``
    at every change, ``{"kind": "inject", ...}``, and ``{"kind": "end", "reason": ...,
    "seconds": ..., "samples": ...}``. ``t`` is stream time (s), ``wall`` Unix time. The
    ``start`` event's ``t``/``warm_s`` say where the stream was, ``state`` whether the
    filters' state was kept.
``NAME.state.npz``
    Every filter's state as the recording began (:meth:`Recorder.write_state`), when they
    had filtered some of the stream already: a re-run goes on from it
    (:func:`app.toolkit.recorded.recorded_state`).

A stream ends the segment: if the phone disconnects while recording, the files are
closed cleanly (``end`` says why); when a stream starts again, the recording goes on in
a new segment ``NAME_2`` (a new clock, so a new log). A segment that got no sample (a
recording started as the stream ended) is removed, files and all: no empty log is left
or listed. A write that fails (full disk, folder removed or not writable) stops the
recording with :attr:`Recorder.error` saying why; it never raises into the live path.

Bounded (:class:`RecordingLimits`): the recording stops cleanly, with the reason in its
``end`` event and :attr:`Recorder.stop_reason`, at a duration cap (wall time), a size
cap (the bytes of every segment's files) or when the recordings' disk has less free
space than a floor. Its size and rate (bytes, bytes/s) are in :meth:`Recorder.summary`.
"""

from __future__ import annotations

import gzip
import json
import math
import os
import re
import shutil
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from app.estimators import FLAG_COLUMNS, Reason, TimeIssue
from app.sources.sensorfusion import format_line
from app.estimators.base import F_ACC, F_ACC_NIS, F_ACC_VAL, F_GYR, F_MAG, F_MAG_NIS, F_MAG_VAL, F_REST, F_TIME

LOG_SUFFIX = ".txt"
LOG_SUFFIXES = (LOG_SUFFIX, ".log", ".csv", ".npz")   # a recording's log: ours, then an app's
ESTIMATES_SUFFIX = ".estimates.csv.gz"
PLAIN_ESTIMATES_SUFFIX = ".estimates.csv"      # recordings made before the gzip
EVENTS_SUFFIX = ".events.jsonl"
# the live filters' state as a recording begun into its stream began (Recorder.write_state)
STATE_SUFFIX = ".state.npz"
SIBLING_SUFFIXES = (ESTIMATES_SUFFIX, PLAIN_ESTIMATES_SUFFIX, EVENTS_SUFFIX, STATE_SUFFIX)
MAX_STATE_BYTES = 1 << 20     # a state file is a few kB: a larger one is not read
CHECK_EVERY_S = 1.0      # the duration cap and the free space are checked this often
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


NAME_RULE = "letters, digits, '.', '_' or '-' (at most 120), not beginning with '.', '_' or '-'"


def name_ok(name: Any) -> bool:
    """A recording name: letters, digits, ``.``, ``_``, ``-`` (no path, no ``..``)."""
    return isinstance(name, str) and NAME_RE.match(name) is not None and ".." not in name


def check_name(name: str) -> str:
    """``name`` if it is a recording name (:func:`name_ok`), else RecordingError."""
    if not name_ok(name):
        raise RecordingError(f"invalid recording name {name!r}: use {NAME_RULE}")
    return name


def _log_rank(p: Path) -> tuple[int, int] | None:
    """How file ``p`` ranks as a recording's log, the best first: its extension exactly
    one of :data:`LOG_SUFFIXES` before one in other case (``X.TXT``), then in that tuple's
    order; None when it is not a log (a sibling, a hidden file, another extension)."""
    low = p.name.lower()
    if p.name.startswith(".") or any(low.endswith(s) for s in SIBLING_SUFFIXES):
        return None
    suffix = p.suffix.lower()
    if suffix not in LOG_SUFFIXES:
        return None
    return (int(p.suffix != suffix), LOG_SUFFIXES.index(suffix))


def recording_logs(folder: str | Path) -> tuple[dict[str, Path], list[dict[str, str]]]:
    """The recordings in ``folder``: ``{name: its log}``, newest first, one log per name
    (the best by :func:`_log_rank`: a name is one recording wherever it is listed,
    downloaded or replayed), and the files that look like logs but are left out, each with
    why (``{"file", "why"}``: a name that is not a recording name, another log of a listed
    name, an empty file). Reads the folder and each log's size and time, no file."""
    by_name: dict[str, list[tuple[tuple[int, int], Path]]] = {}
    modified: dict[Path, float] = {}
    left: list[dict[str, str]] = []
    try:
        files = list(Path(folder).iterdir())
    except OSError:
        return {}, []
    for p in files:
        rank = _log_rank(p)
        if rank is None:
            continue
        try:
            if not p.is_file():
                continue
            st = p.stat()
        except OSError:
            continue
        empty, modified[p] = st.st_size == 0, st.st_mtime
        if empty:       # nothing in it (a recording started as a stream ended)
            left.append({"file": shown_name(p), "why": "empty"})
        elif not name_ok(p.stem):
            left.append({"file": shown_name(p), "why": f"its name is not a recording name: use {NAME_RULE}"})
        else:
            by_name.setdefault(p.stem, []).append((rank, p))
    logs = {}
    for name, found in by_name.items():
        found.sort(key=lambda x: x[0])
        logs[name] = found[0][1]
        left += [{"file": p.name, "why": f"another log of the recording {name!r} "
                  f"({found[0][1].name}, listed): rename one"} for _, p in found[1:]]
    left.sort(key=lambda x: x["file"])
    return dict(sorted(logs.items(), key=lambda x: modified[x[1]], reverse=True)), left


def find_log(folder: str | Path, name: str) -> Path | None:
    """The log of recording ``name`` in ``folder`` (the one :func:`recording_logs` lists),
    or None. One pass over the folder's names, a file looked at only when its stem is
    ``name``: a request for a name that is not there costs no stat of every recording,
    and the file is the one on disk, whatever a case-insensitive disk would open for a
    name built here."""
    found: list[tuple[tuple[int, int], Path]] = []
    try:
        with os.scandir(folder) as entries:
            for e in entries:
                p = Path(e.path)
                if p.stem != name:
                    continue
                rank = _log_rank(p)
                try:
                    if rank is None or not e.is_file() or e.stat().st_size == 0:
                        continue
                except OSError:
                    continue
                found.append((rank, p))
    except OSError:
        return None
    return min(found, key=lambda x: x[0])[1] if found else None


def shown_name(p: Path) -> str:
    """A file's name as text any client can take: bytes that are not UTF-8 (a zip from
    another system) shown as U+FFFD, never as the lone surrogates Python reads them as."""
    return p.name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


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


@dataclass(frozen=True)
class RecordingLimits:
    """A recording's bounds and its estimates' density (``orientlab serve``'s settings
    ``recording_*``): it stops at ``max_seconds`` (wall time) or ``max_bytes`` (every
    segment's files), or when the folder's disk has less than ``min_free_bytes`` free;
    ``estimates_hz`` rows a second per estimator (0: every sample), gzip-compressed
    unless ``compress`` is False. None or 0 turns a cap off."""
    max_seconds: float | None = 3600.0
    max_bytes: int | None = 500_000_000
    min_free_bytes: int | None = 200_000_000
    estimates_hz: float = 20.0
    compress: bool = True

    @classmethod
    def from_settings(cls, settings) -> "RecordingLimits":
        d = cls()
        return cls(max_seconds=getattr(settings, "recording_max_s", d.max_seconds),
                   max_bytes=getattr(settings, "recording_max_bytes", d.max_bytes),
                   min_free_bytes=getattr(settings, "recording_min_free_bytes", d.min_free_bytes),
                   estimates_hz=getattr(settings, "recording_estimates_hz", d.estimates_hz),
                   compress=getattr(settings, "recording_gzip", d.compress))

    def as_dict(self) -> dict[str, Any]:
        return {"max_seconds": self.max_seconds, "max_bytes": self.max_bytes,
                "min_free_bytes": self.min_free_bytes, "estimates_hz": self.estimates_hz,
                "compressed": self.compress}


def free_bytes(folder: Path) -> int | None:
    """Free space (bytes) for a non-root user on the disk of ``folder``; None if unknown."""
    try:
        return int(shutil.disk_usage(folder).free)
    except OSError:
        return None


def _mb(n: float) -> str:
    return f"{n / 1e6:.1f} MB" if n < 1e9 else f"{n / 1e9:.2f} GB"


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
    written: int = 0            # samples written to the log (marks not counted)
    log_bytes: int = 0          # the log's bytes written (its end event says it: a copy cut short shows)
    bytes: int = 0              # its files' bytes (counted while open, measured at close)
    removed: bool = False       # it got no sample: its files were removed

    @property
    def seconds(self) -> float:
        if self.t_first is None or self.t_last is None:
            return 0.0
        return max(0.0, self.t_last - self.t_first)

    def summary(self) -> dict[str, Any]:
        return {"name": self.name, "path": str(self.path), "seconds": round(self.seconds, 3),
                "samples": self.samples, "lines": self.lines, "source": self.label,
                "bytes": self.bytes, "started": self.started, "ended": self.ended,
                "end_reason": self.end_reason}


class Recorder:
    """Writes one recording (possibly several segments) into ``folder``.

    Pure and synchronous: the live server calls :meth:`write_lines` with the raw lines
    of the stream on show, :meth:`write_estimates` with what the estimators made of
    them, :meth:`note` for parameter changes and injections, :meth:`end_segment` when the
    stream ends and :meth:`stop` at the end. None of them raises on a failed write:
    the recording stops and :attr:`error` says why (the live view keeps running).
    """

    def __init__(self, folder: str | Path, name: str | None = None,
                 clock: Callable[[], float] = time.time, flush_every_s: float = 1.0,
                 limits: RecordingLimits | None = None,
                 free_space: Callable[[Path], int | None] = free_bytes):
        self.folder = Path(folder)
        self.base = check_name(name) if name else default_name(clock())
        self.clock = clock
        self.flush_every_s = flush_every_s
        self.limits = limits or RecordingLimits()
        self.free_space = free_space
        self.segments: list[Segment] = []
        self.error: str | None = None
        self.stop_reason: str | None = None    # the cap or floor that stopped it
        self.active = False
        self._log = self._est = self._events = None
        self._est_raw = None                   # the gzip's file (its bytes on disk)
        self._last_flush = 0.0
        self._params: dict[str, Any] = {}
        self._started = clock()
        self._last_check = -math.inf
        self._rate: deque = deque(maxlen=8)    # (clock, bytes) at each check: the rate
        self._est_last: dict[str, float] = {}  # estimator -> last decimation bin written
        self._seg_bytes = 0                    # the open segment's log and events bytes

    # ----------------------------------------------------------------- life
    def start(self, params: dict[str, Any], label: str = "",
              phone: dict[str, Any] | None = None, at: dict[str, Any] | None = None) -> Segment:
        """Open the first segment; RecordingError (nothing written) if the folder
        cannot be created or written, or the name is taken. ``at``: more of the ``start``
        event (where the stream is: ``t``, ``warm_s``)."""
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise RecordingError(f"cannot create the recordings folder {self.folder}: "
                                 f"{e.strerror or e}") from None
        if not os.access(self.folder, os.W_OK):
            raise RecordingError(f"the recordings folder {self.folder} is not writable")
        if self._taken(self.base):
            raise RecordingError(f"a recording named {self.base!r} exists already")
        low = self._low_space()
        if low:
            raise RecordingError(low)
        self._params = params
        self._started = self.clock()
        self.active = True
        try:
            return self._open_segment(label, phone, at)
        except OSError as e:
            self.active = False
            raise RecordingError(_os_message(self.folder / self.base, e)) from None

    def _taken(self, name: str) -> bool:
        """Whether ``name`` is a recording's already: a log of any kind (:func:`find_log`),
        our own log even empty (a crash before the first write), or a state file (one left
        by a removed recording would be taken for the new one's)."""
        return (find_log(self.folder, name) is not None
                or any((self.folder / (name + sfx)).exists() for sfx in (LOG_SUFFIX, STATE_SUFFIX)))

    def _segment_name(self) -> str:
        k = sum(not s.removed for s in self.segments) + 1
        name = self.base if k == 1 else f"{self.base}_{k}"
        while self._taken(name):
            k += 1
            name = f"{self.base}_{k}"
        return name

    def _open_segment(self, label: str, phone: dict[str, Any] | None = None,
                      at: dict[str, Any] | None = None) -> Segment:
        name = self._segment_name()
        seg = Segment(name=name, path=self.folder / (name + LOG_SUFFIX), label=label,
                      started=self.clock())
        self._log = open(seg.path, "wb")
        head = ",".join(ESTIMATE_COLUMNS + OUTPUT_COLUMNS) + "\n"
        if self.limits.compress:
            self._est_raw = open(self.folder / (name + ESTIMATES_SUFFIX), "wb")
            self._est = gzip.GzipFile(fileobj=self._est_raw, mode="wb", compresslevel=6,
                                      filename="", mtime=0)
        else:
            self._est_raw = None
            self._est = open(self.folder / (name + PLAIN_ESTIMATES_SUFFIX), "wb")
        self._events = open(self.folder / (name + EVENTS_SUFFIX), "w")
        self.segments.append(seg)
        self._seg_bytes = 0
        self._est_last = {}
        self._est.write(head.encode())
        # the phone: its app, platform and sign convention, as the source detected them
        # a new stream goes on in NAME_2, NAME_3...: each says which recording it belongs to
        self._event({"kind": "start", **(at or {}), "recording": self.base, "name": name,
                     "segment": sum(not x.removed for x in self.segments),
                     "source": label, "phone": phone or None, "params": self._params})
        return seg

    @property
    def segment(self) -> Segment | None:
        return self.segments[-1] if self.segments and self._log is not None else None

    def new_segment(self, label: str = "", phone: dict[str, Any] | None = None,
                    at: dict[str, Any] | None = None) -> None:
        """A new stream started while recording: go on in a new segment."""
        if not self.active:
            return
        if self._log is not None:
            self.end_segment("a new stream started")
        self._guard(lambda: self._open_segment(label, phone, at), self.folder / self.base)

    def end_segment(self, reason: str) -> None:
        """The stream ended (phone disconnected, end of log): close the files cleanly;
        a segment that got no sample is removed (no empty log is left)."""
        seg = self.segment
        if seg is None:
            return
        seg.ended = self.clock()
        seg.end_reason = reason
        self._event({"kind": "end", "reason": reason, "seconds": round(seg.seconds, 3),
                     "samples": seg.samples, "lines": seg.lines, "log_bytes": seg.log_bytes})
        self._close_files()
        if seg.written == 0 and self.error is None:
            self._remove(seg)
        else:
            seg.bytes = sum(file_size(p) for p in self._files(seg))

    def _files(self, seg: Segment) -> list[Path]:
        return [seg.path] + [self.folder / (seg.name + sfx) for sfx in SIBLING_SUFFIXES]

    def _remove(self, seg: Segment) -> None:
        for p in self._files(seg):
            try:
                p.unlink()
            except FileNotFoundError:
                pass
            except OSError:
                return
        seg.removed, seg.bytes = True, 0

    def stop(self, reason: str = "stopped") -> dict[str, Any]:
        """End the recording: ``{name, path, seconds, samples, bytes, segments: [...],
        error, stop_reason}`` (name/path of the first segment kept; seconds, samples and
        bytes over all segments; ``empty`` when no segment got a sample)."""
        if self.segment is not None:
            self.end_segment(reason)
        self.active = False
        return self.summary()

    # ----------------------------------------------------------------- size and limits
    @property
    def bytes(self) -> int:
        """The recording's bytes so far: closed segments as on disk, the open one as
        written (the gzip's bytes as it has handed them to its file)."""
        done = sum(s.bytes for s in self.segments if s is not self.segment)
        return done + self._open_bytes()

    def _open_bytes(self) -> int:
        if self.segment is None:
            return 0
        est = 0
        try:
            if self._est_raw is not None:
                est = self._est_raw.tell()
            elif self._est is not None:
                est = self._est.tell()
        except (OSError, ValueError):
            pass
        return self._seg_bytes + est

    @property
    def elapsed_s(self) -> float:
        end = self.segments[-1].ended if (not self.active and self.segments) else None
        return max(0.0, (end if end is not None else self.clock()) - self._started)

    def bytes_per_s(self) -> float:
        """The write rate over the last few seconds (bytes/s)."""
        if len(self._rate) >= 2 and self._rate[-1][0] > self._rate[0][0]:
            (t0, b0), (t1, b1) = self._rate[0], self._rate[-1]
            return (b1 - b0) / (t1 - t0)
        el = self.elapsed_s     # the file's header over the first milliseconds is no rate
        return self.bytes / el if el >= 0.5 else 0.0

    def _low_space(self) -> str | None:
        floor = self.limits.min_free_bytes
        if not floor:
            return None
        free = self.free_space(self.folder)
        if free is not None and free < floor:
            return (f"free space low: {_mb(free)} left on the recordings' disk "
                    f"(the floor is {_mb(floor)})")
        return None

    def check(self, force: bool = False) -> str | None:
        """Stop at a cap or a low disk (at most every :data:`CHECK_EVERY_S`, the size at
        every call): the reason, also in :attr:`stop_reason` and the ``end`` event."""
        if not self.active:
            return self.stop_reason
        if self.segment is not None:    # a silent stream's files too: whole within a second
            self._maybe_flush()
        lim = self.limits
        size = self.bytes
        reason = None
        if lim.max_bytes and size >= lim.max_bytes:
            reason = f"size cap reached: {_mb(size)} (the cap is {_mb(lim.max_bytes)})"
        now = self.clock()
        if reason is None and (force or now - self._last_check >= CHECK_EVERY_S):
            self._last_check = now
            self._rate.append((now, size))
            if lim.max_seconds and now - self._started >= lim.max_seconds:
                reason = f"duration cap reached: {lim.max_seconds:g} s"
            else:
                reason = self._low_space()
        if reason is not None:
            self.stop_reason = reason
            self.end_segment(reason)
            self.active = False
        return reason

    def summary(self) -> dict[str, Any]:
        kept = [s for s in self.segments if not s.removed]
        segs = [s.summary() for s in kept]
        if segs:
            first = segs[0]
        else:   # nothing kept (yet): the name it has or would have
            first = {"name": self.base,
                     "path": str(self.folder / (self.base + LOG_SUFFIX)) if self.active else None}
        return {"name": first["name"], "path": first["path"],
                "seconds": round(sum(s.seconds for s in kept), 3),
                "samples": sum(s.samples for s in kept),
                "bytes": self.bytes, "bytes_per_s": round(self.bytes_per_s(), 1),
                "elapsed_s": round(self.elapsed_s, 3),
                "empty": not any(s.written for s in kept),
                "recording": self.active, "segments": segs, "error": self.error,
                "stop_reason": self.stop_reason, "limits": self.limits.as_dict()}

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
            seg.written += len(samples)
            seg.log_bytes += len(data)
            self._seg_bytes += len(data)
            self._maybe_flush()
            self.check()

    def write_state(self, arrays: dict[str, np.ndarray]) -> None:
        """The live filters' state as the segment begins (``NAME.state.npz``: the arrays of
        :meth:`app.live.ensemble.Ensemble.state_arrays`, ``instance/attribute``; no pickle),
        for a re-run that goes on from it (:func:`app.toolkit.recorded.read_state`)."""
        seg = self.segment
        if seg is None or not arrays:
            return
        path = self.folder / (seg.name + STATE_SUFFIX)

        def write():
            with open(path, "wb") as fh:
                np.savez(fh, **arrays)
            self._seg_bytes += file_size(path)
        self._guard(write, path)

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
        hz = self.limits.estimates_hz
        if hz and hz > 0 and name != "truth":
            # the first row of each 1/hz bin not written yet: the same rows for every
            # estimator of a chunk (they share t)
            b = np.floor(t * hz)
            prev = np.maximum.accumulate(np.concatenate(([self._est_last.get(name, -np.inf)], b[:-1])))
            keep = b > prev
            if not keep.any():
                return
            self._est_last[name] = float(max(prev[-1], b[-1]))
            t, q = t[keep], q[keep]
            if flags is not None:
                flags = np.asarray(flags, dtype=float)[keep]
            if not isinstance(tags, str):
                tags = [tg for tg, k in zip(tags, keep.tolist()) if k]
        if flags is None:  # no flag record (truth, phone): empty flag cells
            blank = "," * len(FLAG_COLUMNS)
            text = "".join(f"{a:.6f},{b:.9f},{c:.9f},{d:.9f},{e:.9f}{blank}\n"
                           for a, (b, c, d, e) in zip(t.tolist(), q.tolist()))
        else:
            text = format_rows(t, q, np.asarray(flags, dtype=float))
        if isinstance(tags, str):
            tags = [tags] * t.size
        rows = text.splitlines()
        out = "".join(f"{name},{tg},{r}\n" for tg, r in zip(tags, rows)).encode()
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
                seg.log_bytes += len(line) + 1
                self._seg_bytes += len(line) + 1

    def _event(self, obj: dict[str, Any]) -> None:
        obj = {**obj, "wall": round(self.clock(), 3)}
        text = json.dumps(_finite(obj), default=_json_default) + "\n"
        seg = self.segments[-1] if self.segments else None
        path = self.folder / ((seg.name if seg else self.base) + EVENTS_SUFFIX)
        if self._guard(lambda: self._events.write(text), path):
            self._seg_bytes += len(text.encode())

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
            for fh in (self._log, self._est, self._est_raw, self._events):
                if fh is not None and not self._guard(fh.flush, _path_of(fh)):
                    return

    def _close_files(self, quiet: bool = False) -> None:
        for attr in ("_log", "_est", "_est_raw", "_events"):   # the gzip before its file
            fh = getattr(self, attr)
            setattr(self, attr, None)
            if fh is None:
                continue
            try:
                fh.close()
            except OSError as e:  # the last flush failed (disk full)
                if not quiet and self.error is None:
                    self.error = _os_message(_path_of(fh), e)
                    self.active = False
            except ValueError:    # the gzip's file closed first after a failure
                pass


def _path_of(fh) -> Path:
    name = getattr(fh, "name", None)
    if not isinstance(name, str) or not name:
        name = getattr(getattr(fh, "fileobj", None), "name", "") or "?"
    return Path(name)


def file_size(p: Path) -> int:
    """A file's size in bytes, 0 if it cannot be read."""
    try:
        return p.stat().st_size
    except OSError:
        return 0


# Reading a recording back (its files, events, estimates, saved state; the folder's
# listing) is :mod:`app.toolkit.recorded`.
