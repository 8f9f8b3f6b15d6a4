"""Recorded sensor data in, estimator rows out: app logs, CSV and npz.

:func:`read_log_data` reads a whole file into one :class:`LogData`;
:func:`iter_chunks` yields it in pieces of at most ``rows`` rows so a long log
(an hour at 100 Hz, or an app log of a million lines) streams with bounded memory.
The format is told from the content, not the extension:

``applog``
    The Sensor Fusion app's log (``shared/protocols/sensorfusion-app.md``): every tag
    is parsed, lines are put in time order and on one clock by
    :class:`app.sources.ordering.SampleOrderer` (window :data:`LOG_WINDOW`), corrupted lines are
    counted by reason and skipped, ``\\n``, ``\\r\\n`` and ``\\r`` all end a line. One
    row per ACC, GYR, MAG or ORI sample, in time order; ``t`` is on the reference clock.
``csv``
    A header naming ``t`` (s) and any of ``acc_x..acc_z`` (m/s²), ``gyr_x..gyr_z``
    (rad/s), ``mag_x..mag_z`` (µT), optionally ``ori_w..ori_z``; other columns are
    ignored. An empty cell is missing (NaN); ``nan`` passes through (the estimator
    flags it); a physically impossible reading (``inf``, a gyro beyond 100 rad/s: the
    limits of :data:`app.sources.sensorfusion.VALUE_LIMITS`, as for app logs and the live stream)
    becomes NaN, counted as ``impossible``. A row with the wrong number of cells or text in a number cell is
    counted (``counts["malformed"]``) and skipped. One row per (good) line, in order.
``npz``
    ``numpy.savez`` archive with ``acc``, ``gyr`` and optionally ``mag`` (N, 3) and
    ``ori`` (N, 4), and ``t`` (N,) in s or ``fs`` (Hz, then ``t = k / fs``). Other keys
    (the BROAD files' ``opt_quat``, ``movement``) are ignored. The arrays are loaded
    whole (an npz member cannot be read in parts), then handed out in chunks.

A file in an unknown format, or without a time column or any of acc/gyr/mag, raises
:class:`ReaderError` with a one-line message.
"""

from __future__ import annotations

import csv
import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Iterable, Iterator

import numpy as np

from app.sources.samples import MOTION_TAGS, VALUE_LIMITS, impossible_rows, quaternion_rows
from app.sources.sensorfusion import TAG_ARITY, LineSplitter, MalformedLine, parse_line
from app.sources.ordering import RATE_HISTORY, Rows, SampleOrderer, samples_to_rows

# Reorder window for logs (s). Files are read at leisure, so the window can be far wider
# than a live receiver's: it also puts back in place a block of lines written ~1 s out
# of order (seen in a real log).
LOG_WINDOW = 2.0
DEFAULT_CHUNK_ROWS = 50_000
# A "line" longer than this is not a line of any known format: it is skipped and counted.
MAX_LINE_BYTES = 1 << 16
SENSORS = ("acc", "gyr", "mag")
CSV_COLUMNS = {s: tuple(f"{s}_{a}" for a in "xyz") for s in SENSORS}
CSV_COLUMNS["ori"] = ("ori_w", "ori_x", "ori_y", "ori_z")
_MOTION = frozenset(MOTION_TAGS)


class ReaderError(ValueError):
    """The file cannot be read as a log (the message says why, in one line)."""


@dataclass
class LogData:
    """Rows of sensor data. ``gyr``/``acc``/``mag`` are (N, 3) with NaN where missing,
    ``ori`` (N, 4) or None, ``t`` (N,) s. ``counts`` says what was skipped or noticed:
    ``malformed`` (reason -> lines); for app logs also ``lines``, ``tags``, ``late``,
    ``clamped``, ``offsets_s`` and ``rates_hz`` (see :mod:`app.sources.ordering`); for CSV and
    npz ``rows`` and ``columns`` (the sensors present). In a chunk from :func:`iter_chunks`,
    ``counts`` are totals up to the end of that chunk (the last chunk holds the file's
    totals) and ``done`` is the fraction of the input consumed."""
    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    ori: np.ndarray | None
    kind: str
    counts: dict[str, Any] = field(default_factory=dict)
    done: float = 1.0

    def __len__(self) -> int:
        return int(self.t.shape[0])


# ---------------------------------------------------------------- public API

def detect_format(path: str | Path) -> str:
    """``"applog"``, ``"csv"`` or ``"npz"`` from the file's content; ReaderError if
    none fits (or the file is missing or empty)."""
    path = Path(path)
    if not path.exists():
        raise ReaderError(f"{path}: no such file")
    if not path.is_file():
        raise ReaderError(f"{path}: not a file")
    with open(path, "rb") as fh:
        head = fh.read(8192)
    if not head.strip():
        raise ReaderError(f"{path}: empty file")
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        return "npz"
    lines = [ln for ln in head.splitlines() if ln.strip()][:20]
    if len(head) == 8192 and len(lines) > 1:
        lines = lines[:-1]  # the last one may be cut
    if _csv_header(lines[0]) is not None:
        return "csv"
    for ln in lines:
        try:
            parse_line(ln)
            return "applog"
        except MalformedLine:
            continue
    raise ReaderError(f"{path}: unknown format (expected a Sensor Fusion app log, "
                      f"a CSV with a 't' column, or an .npz)")


def iter_chunks(path: str | Path, rows: int = DEFAULT_CHUNK_ROWS) -> Iterator[LogData]:
    """The log at ``path`` in chunks of at most ``rows`` rows, in order (always at
    least one chunk, possibly empty). ReaderError for a file that cannot be read."""
    if rows < 1:
        raise ValueError("rows must be >= 1")
    kind = detect_format(path)
    reader = {"applog": _applog_chunks, "csv": _csv_chunks, "npz": _npz_chunks}[kind]
    return reader(Path(path), rows)


def read_log_data(path: str | Path) -> LogData:
    """The whole log at ``path`` (see the module doc for formats). An app log is
    read at once with numpy when it fits (:func:`_applog_whole`: the same rows and
    counts as reading it line by line, several times faster)."""
    path = Path(path)
    if detect_format(path) == "applog" and path.stat().st_size <= WHOLE_FILE_MAX_BYTES:
        rec = _applog_whole(path)
        if rec is not None:
            return rec
    chunks = list(iter_chunks(path))
    return concat(chunks)


def rows_of_lines(lines: Iterable[bytes], window: float = LOG_WINDOW) -> Rows:
    """The estimator rows of an app log held as its lines (one with a disturbance
    injected, :func:`app.toolkit.inject.inject_at`), put in order as a file is read."""
    orderer = SampleOrderer(window=window)
    return samples_to_rows([x for ln in lines for x in orderer.push_line(ln)] + orderer.flush())


def concat(chunks: list[LogData]) -> LogData:
    """Chunks of one file joined (counts and ``done`` of the last)."""
    if len(chunks) == 1:
        return chunks[0]
    last = chunks[-1]
    has_ori = any(c.ori is not None for c in chunks)
    ori = (np.concatenate([c.ori if c.ori is not None else np.full((len(c), 4), np.nan)
                           for c in chunks]) if has_ori else None)
    return LogData(t=np.concatenate([c.t for c in chunks]),
                     gyr=np.concatenate([c.gyr for c in chunks]),
                     acc=np.concatenate([c.acc for c in chunks]),
                     mag=np.concatenate([c.mag for c in chunks]),
                     ori=ori, kind=last.kind, counts=last.counts, done=last.done)


# ---------------------------------------------------------------- lines

def iter_lines(fh: BinaryIO, splitter: LineSplitter) -> Iterator[tuple[bytes, int]]:
    """The lines of a binary file (the format's framing, :class:`LineSplitter`), each
    with about the number of bytes consumed up to it (for progress). A run of more than
    :data:`MAX_LINE_BYTES` without a line end is skipped and counted in
    ``splitter.overflows``."""
    read = pos = 0
    while True:
        block = fh.read(1 << 20)
        if not block:
            break
        read += len(block)
        for ln in splitter.feed(block):
            pos = min(pos + len(ln) + 1, read)  # +1: the line end
            yield ln, pos
    if splitter.pending:
        yield splitter.pending, read


def _fraction(consumed: int, size: int) -> float:
    return min(1.0, consumed / size) if size > 0 else 1.0


# ---------------------------------------------------------------- app log

def _applog_chunks(path: Path, rows: int) -> Iterator[LogData]:
    orderer = SampleOrderer(window=LOG_WINDOW)
    size = path.stat().st_size
    motion: list = []
    lines = 0

    def chunk(samples: list, done: float) -> LogData:
        r = samples_to_rows(samples)
        ori = r.ori if not np.isnan(r.ori).all() else None
        counts = {**orderer.summary(), "lines": lines}
        if splitter.overflows:
            counts["malformed"] = {**counts["malformed"], "too_long": splitter.overflows}
        return LogData(t=r.t, gyr=r.gyr, acc=r.acc, mag=r.mag, ori=ori, kind="applog",
                         counts=counts, done=done)

    emitted = False
    splitter = LineSplitter(MAX_LINE_BYTES)
    with open(path, "rb") as fh:
        for line, consumed in iter_lines(fh, splitter):
            lines += 1
            motion.extend(s for s in orderer.push_line(line) if s.tag in _MOTION)
            while len(motion) >= rows:
                yield chunk(motion[:rows], _fraction(consumed, size))
                del motion[:rows]
                emitted = True
    motion.extend(s for s in orderer.flush() if s.tag in _MOTION)
    while len(motion) > rows:
        yield chunk(motion[:rows], 1.0)
        del motion[:rows]
    if motion or not emitted:
        yield chunk(motion, 1.0)


# ---------------------------------------------------------------- CSV

def _csv_header(line: bytes) -> list[str] | None:
    """The column names if ``line`` looks like our CSV header, else None."""
    text = line.decode("utf-8", errors="replace").lstrip("\ufeff").strip()
    if "," not in text and text.lower() != "t":
        return None
    names = [c.strip().strip('"').strip().lower() for c in text.split(",")]
    known = {"t"} | {c for cols in CSV_COLUMNS.values() for c in cols}
    return names if any(n in known for n in names) else None


def _cell(text: str) -> float:
    s = text.strip()
    if not s:
        return math.nan
    return float(s)  # accepts nan, inf, -inf, Infinity, 1e-3


def _csv_chunks(path: Path, rows: int) -> Iterator[LogData]:
    size = path.stat().st_size
    splitter = LineSplitter(MAX_LINE_BYTES)
    with open(path, "rb") as fh:
        line_iter = iter_lines(fh, splitter)
        consumed = 0
        header = None
        for first, consumed in line_iter:
            if first.strip():
                header = _csv_header(first)
                break
        if header is None:
            raise ReaderError(f"{path}: not a CSV with a header naming 't'")
        if "t" not in header:
            raise ReaderError(f"{path}: CSV has no 't' column (time in s)")
        index = {name: i for i, name in enumerate(header)}
        present = {key: [index[c] for c in cols] for key, cols in CSV_COLUMNS.items()
                   if all(c in index for c in cols)}
        if not any(s in present for s in SENSORS):
            raise ReaderError(f"{path}: CSV has none of acc_x..acc_z, gyr_x..gyr_z, "
                              f"mag_x..mag_z (all three axes needed)")
        ncols = len(header)
        it = index["t"]
        wanted = [it] + [i for key in ("gyr", "acc", "mag", "ori") for i in present.get(key, ())]
        malformed: dict[str, int] = {}
        counts = {"malformed": malformed, "columns": sorted(present)}
        block: list[list[float]] = []
        n_rows = 0

        def chunk(done: float) -> LogData:
            a = np.array(block, dtype=float).reshape(len(block), len(wanted))
            out, col = {}, 1
            for key, width in (("gyr", 3), ("acc", 3), ("mag", 3), ("ori", 4)):
                if key in present:
                    out[key] = a[:, col:col + width]
                    col += width
                else:
                    out[key] = None if key == "ori" else np.full((len(a), 3), np.nan)
            _refuse_impossible(out, counts)
            counts["rows"] = n_rows
            if splitter.overflows:
                malformed["too_long"] = splitter.overflows
            return LogData(t=a[:, 0].copy(), gyr=out["gyr"], acc=out["acc"], mag=out["mag"],
                             ori=out["ori"], kind="csv",
                             counts={**counts, "malformed": dict(malformed)}, done=done)

        emitted = False
        for raw, consumed in line_iter:
            text = raw.decode("utf-8", errors="replace").rstrip("\r\n")
            if not text.strip():
                continue
            cells = next(csv.reader([text])) if '"' in text else text.split(",")
            if len(cells) != ncols:
                malformed["wrong_count"] = malformed.get("wrong_count", 0) + 1
                continue
            try:
                block.append([_cell(cells[i]) for i in wanted])
            except ValueError:
                malformed["not_numeric"] = malformed.get("not_numeric", 0) + 1
                continue
            n_rows += 1
            if len(block) >= rows:
                yield chunk(_fraction(consumed, size))
                block = []
                emitted = True
        if block or not emitted:
            yield chunk(1.0)


def _refuse_impossible(arrays: dict, counts: dict) -> None:
    """A row's physically impossible reading (:data:`app.sources.samples.VALUE_LIMITS`, the
    same limits as the app-log parser's) is refused, its row kept: made infinite, so an
    estimator flags that sensor ``invalid`` in that row, as an infinite reading is; counted
    in ``counts["impossible"]`` (readings, not lines: the row's other sensors are used)."""
    for key, tag in (("gyr", "GYR"), ("acc", "ACC"), ("mag", "MAG")):
        a = arrays.get(key)
        if a is None or not len(a):
            continue
        bad = impossible_rows(tag, a)
        if bad.any():
            a[bad] = np.inf
            counts["impossible"] = counts.get("impossible", 0) + int(bad.sum())


# ---------------------------------------------------------------- npz

def _npz_numbers(path: Path, data, key: str) -> np.ndarray:
    """The npz's array ``key`` as floats; ReaderError naming it if it holds anything else
    (text, objects: those are not loaded, no pickle)."""
    try:
        return np.asarray(data[key], dtype=float)
    except (ValueError, TypeError) as e:
        raise ReaderError(f"{path}: npz array {key!r} does not hold numbers ({str(e)[:120]})") from None


def _npz_chunks(path: Path, rows: int) -> Iterator[LogData]:
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise ReaderError(f"{path}: not a readable .npz ({e})") from None
    with data:
        keys = set(data.files)
        if not keys & set(SENSORS):
            raise ReaderError(f"{path}: npz has none of the arrays acc, gyr, mag")
        arrays: dict[str, np.ndarray | None] = {}
        n = None
        for key, width in (("gyr", 3), ("acc", 3), ("mag", 3), ("ori", 4)):
            if key not in keys:
                arrays[key] = None
                continue
            a = _npz_numbers(path, data, key)
            if a.ndim != 2 or a.shape[1] != width:
                raise ReaderError(f"{path}: npz array {key!r} has shape {a.shape}, "
                                  f"expected (N, {width})")
            if n is not None and a.shape[0] != n:
                raise ReaderError(f"{path}: npz arrays have different lengths "
                                  f"({key!r} has {a.shape[0]}, expected {n})")
            n = a.shape[0]
            arrays[key] = a
        if "t" in keys:
            t = _npz_numbers(path, data, "t").reshape(-1)
            if t.shape[0] != n:
                raise ReaderError(f"{path}: npz 't' has {t.shape[0]} values for {n} rows")
        elif "fs" in keys:
            fs = _npz_numbers(path, data, "fs").reshape(-1)
            if fs.shape[0] != 1:
                raise ReaderError(f"{path}: npz 'fs' must be one rate in Hz, got {fs.shape[0]} values")
            fs = float(fs[0])
            if not (math.isfinite(fs) and fs > 0):
                raise ReaderError(f"{path}: npz 'fs' must be a positive rate in Hz, got {fs}")
            t = np.arange(n) / fs
        else:
            raise ReaderError(f"{path}: npz has neither 't' (s) nor 'fs' (Hz)")
    counts = {"malformed": {}, "rows": 0, "columns": sorted(k for k in arrays if arrays[k] is not None)}
    _refuse_impossible(arrays, counts)
    start = 0
    while True:
        stop = min(n, start + rows)
        sl = slice(start, stop)

        def part(key):
            a = arrays[key]
            if a is None:
                return None if key == "ori" else np.full((stop - start, 3), np.nan)
            return a[sl]
        counts["rows"] = stop
        yield LogData(t=t[sl], gyr=part("gyr"), acc=part("acc"), mag=part("mag"),
                        ori=part("ori"), kind="npz", counts=dict(counts),
                        done=stop / n if n else 1.0)
        start = stop
        if start >= n:
            break



# ---------------------------------------------------------------- app log, whole file at once

# A whole-file read (:func:`read_log_data`) of an app log takes the vectorised path
# below when the file is not too large for memory; a log it cannot put in order exactly
# as :class:`app.sources.ordering.SampleOrderer` would falls back to the line-by-line reader.
WHOLE_FILE_MAX_BYTES = 1 << 30
_FAST_TAGS = {b"ACC": 3, b"GYR": 3, b"MAG": 3, b"ORI": 4}   # tag -> values on the fast path
_FAST_MAX_FIELD = 32        # a wider number goes the line-by-line way
_FAST_MAX_TS_DIGITS = 14    # below MAX_TIME_MS (1e14): every such time stamp is valid
_TAGS = tuple(TAG_ARITY)
_TAG_ID = {t: i for i, t in enumerate(_TAGS)}
_MOTION_IDS = np.array([_TAG_ID[t] for t in MOTION_TAGS])


# bytes that may stand in a plain number line besides its 3-letter tag: digits, .eE+-,
# the tab between fields and the line end
_NOT_PLAIN = np.ones(256, dtype=bool)
_NOT_PLAIN[np.frombuffer(b"0123456789.eE+-\t\n", dtype=np.uint8)] = False


def _gather(buf: np.ndarray, lo: np.ndarray, hi: np.ndarray, width: int) -> np.ndarray:
    """The byte ranges [lo, hi) (each at most ``width`` long) as a (..., width) uint8
    array, NUL after each range's end."""
    k = np.arange(width)
    chars = buf[np.minimum(lo[..., None] + k, len(buf) - 1)]
    chars[k >= (hi - lo)[..., None]] = 0
    return chars


def _digits(chars: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, W) NUL-padded fields -> (int64 values, ok) where ``ok`` marks fields of
    1 to W decimal digits only (at most 18, so they fit)."""
    v = np.zeros(len(chars), dtype=np.int64)
    ok = chars[:, 0] != 0
    for k in range(chars.shape[1]):
        c = chars[:, k].astype(np.int64)
        more = c != 0
        ok &= ~more | ((c >= 48) & (c <= 57))
        v = np.where(more, v * 10 + (c - 48), v)
    return v, ok


def _to_float(fields: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Python's ``float`` of each field of an ``S`` array (values, bad) where ``bad``
    marks the fields float() refuses. (float() through map is faster than numpy's own
    cast from bytes, which gives the same bits.)"""
    flat = fields.reshape(-1).tolist()
    try:
        out = np.fromiter(map(float, flat), dtype=np.float64, count=len(flat))
        return out.reshape(fields.shape), np.zeros(fields.shape, dtype=bool)
    except ValueError:
        out = np.empty(len(flat))
        bad = np.zeros(len(flat), dtype=bool)
        for i, x in enumerate(flat):
            try:
                out[i] = float(x)
            except ValueError:
                bad[i] = True
        return out.reshape(fields.shape), bad.reshape(fields.shape)


def _applog_whole(path: Path, window: float = LOG_WINDOW) -> LogData | None:
    """The app log at ``path`` read at once with numpy: the same rows and counts as the
    line-by-line reader (:func:`_applog_chunks`), or None when the file needs it.

    Lines of the usual shape (``<digits>\\t<ACC|GYR|MAG|ORI>\\t<number>...`` with the
    tag's count of plain numbers) are split and converted in bulk; every other line
    (other tags, NaN or Infinity, spaces, a wrong count, text, non-ASCII) goes through
    :func:`app.sources.sensorfusion.parse_line`, so each is accepted or counted exactly as there.
    The samples are then put in order on one clock as :class:`~app.sources.ordering.SampleOrderer`
    does: offsets from each tag's first sample against the newest time, then a stable
    sort on time. That equals the orderer's output when no sample is late or jumps
    (each within the window of the newest time before it), which is checked; otherwise
    None (the orderer's clamping, dropping and re-anchoring are left to it)."""
    data = path.read_bytes()
    if b"\r" in data:   # LineSplitter's framing: \r\n and a lone \r end a line too
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    buf = np.frombuffer(data, dtype=np.uint8)
    nl = np.flatnonzero(buf == 10)
    starts = np.concatenate(([0], nl + 1))
    ends = np.concatenate((nl, [len(buf)]))
    if starts[-1] == len(buf):          # the file ends with a line end: no last piece
        starts, ends = starts[:-1], ends[:-1]
    # per line, how many bytes cannot be in a plain number line (the tag's 3 letters)
    odd = np.add.reduceat(_NOT_PLAIN[buf].view(np.uint8), starts, dtype=np.int64) \
        if len(starts) else np.zeros(0, dtype=np.int64)
    length = ends - starts
    odd[length == 0] = 0
    too_long = length > MAX_LINE_BYTES
    overflows = int(too_long.sum())
    if overflows:
        keep = ~too_long
        starts, ends, length, odd = starts[keep], ends[keep], length[keep], odd[keep]
    n_lines = len(starts)

    tabs = np.flatnonzero(buf == 9)
    k0 = np.searchsorted(tabs, starts)
    n_tabs = np.searchsorted(tabs, ends) - k0
    tabs_x = np.concatenate((tabs, np.full(6, len(buf))))     # look-ups past the end
    t1 = tabs_x[k0]
    t2 = tabs_x[k0 + 1]
    ts_len = t1 - starts
    plain = ((odd == 3) & (n_tabs >= 2) & (t2 - t1 == 4) & (ts_len >= 1)
             & (ts_len <= _FAST_MAX_TS_DIGITS))
    tag_code = np.zeros(n_lines, dtype=np.int64)
    if plain.any():
        tb = buf[t1[plain, None] + np.arange(1, 4)].astype(np.int64)
        tag_code[plain] = (tb[:, 0] << 16) | (tb[:, 1] << 8) | tb[:, 2]

    # per line: -1 malformed / not a sample, else the row in the arrays below
    line_tag = np.full(n_lines, -1, dtype=np.int64)
    line_time = np.zeros(n_lines, dtype=np.float64)   # ms; a fraction kept (sub-ms stamps)
    line_vals = np.full((n_lines, 4), np.nan)
    reasons: dict[str, list[int]] = {}
    done = np.zeros(n_lines, dtype=bool)       # taken (or refused) on the fast path
    if (length == 0).any():
        reasons["empty"] = np.flatnonzero(length == 0).tolist()
    for tag, nv in _FAST_TAGS.items():
        code = (tag[0] << 16) | (tag[1] << 8) | tag[2]
        rows = np.flatnonzero(plain & (tag_code == code) & (n_tabs == nv + 1))
        if not rows.size:
            continue
        ts, ts_ok = _digits(_gather(buf, starts[rows], t1[rows], _FAST_MAX_TS_DIGITS))
        kk = k0[rows]
        lo = tabs_x[kk[:, None] + np.arange(1, nv + 1)] + 1
        hi = np.concatenate((tabs_x[kk[:, None] + np.arange(2, nv + 1)], ends[rows, None]), axis=1)
        w = hi - lo
        fit = ts_ok & (w >= 1).all(axis=1) & (w <= _FAST_MAX_FIELD).all(axis=1)
        rows, lo, hi, ts = rows[fit], lo[fit], hi[fit], ts[fit]
        if not rows.size:
            continue
        width = int((hi - lo).max())
        fields = np.ascontiguousarray(_gather(buf, lo, hi, width)).view(f"S{width}")[..., 0]
        vals, bad = _to_float(fields)
        good = ~bad.any(axis=1)
        rows, vals, ts = rows[good], vals[good], ts[good]
        done[rows] = True
        name = tag.decode()
        imp = None
        if name in VALUE_LIMITS:
            imp = impossible_rows(name, vals[:, :3])
        elif name == "ORI":       # quaternion_reading's rule: a unit quaternion, w >= 0
            vals, imp = quaternion_rows(vals)
        if imp is not None:
            if imp.any():
                reasons.setdefault("impossible", []).extend(rows[imp].tolist())
                rows, vals, ts = rows[~imp], vals[~imp], ts[~imp]
        line_tag[rows] = _TAG_ID[name]
        line_time[rows] = ts
        line_vals[rows, :nv] = vals
    for i in np.flatnonzero(~done & (length > 0)).tolist():
        try:
            s = parse_line(data[starts[i]:ends[i]])
        except MalformedLine as e:
            reasons.setdefault(e.reason, []).append(i)
            continue
        line_tag[i] = _TAG_ID[s.tag]
        line_time[i] = s.time_ms
        if s.tag in _MOTION:
            line_vals[i, :len(s.values)] = s.values

    ok = line_tag >= 0
    tag_id, raw_t, vals = line_tag[ok], line_time[ok], line_vals[ok]
    orderer = SampleOrderer(window=window)
    ordered = _order_like_orderer(tag_id, raw_t, orderer)
    if ordered is None:
        return None     # late samples or clock jumps: the orderer's own rules apply
    mapped, glitch, offsets, first, popped_at = ordered
    # a clock standing still fills the orderer's buffer past its bound (it then releases
    # early, counted as forced): more samples than that within the span a sample may be
    # held leaves the file to the orderer
    held_ms = (orderer.window + orderer.max_delay) * 1000.0
    srt = np.sort(mapped[~glitch])
    if srt.size > orderer.max_buffered and \
            (np.searchsorted(srt, srt + held_ms, side="right") - np.arange(srt.size)).max() \
            > orderer.max_buffered:
        return None
    if glitch.any():    # counted when the tag's next sample came (or at the end)
        line_of = np.concatenate((np.flatnonzero(ok), [n_lines]))
        reasons["time_jump"] = line_of[popped_at].tolist()
    keep = ~glitch & np.isin(tag_id, _MOTION_IDS)
    order = np.flatnonzero(keep)[np.argsort(mapped[keep], kind="stable")]

    t = mapped[order].astype(float) / 1000.0
    tid = tag_id[order]
    v = vals[order]
    cols = {}
    for name, (fld, width) in (("GYR", ("gyr", 3)), ("ACC", ("acc", 3)), ("MAG", ("mag", 3)),
                               ("ORI", ("ori", 4))):
        a = np.full((len(order), width), np.nan)
        m = tid == _TAG_ID[name]
        a[m] = v[m, :width]
        cols[fld] = a
    ori = cols["ori"] if (tid == _TAG_ID["ORI"]).any() else None

    malformed = {r: len(ix) for r, ix in sorted(reasons.items(), key=lambda kv: min(kv[1]))}
    counts_tags = {_TAGS[i]: int(np.count_nonzero(tag_id == i)) for i in first}
    rates = {}
    for i in first:
        times = mapped[(tag_id == i) & ~glitch][-RATE_HISTORY:].tolist()
        span = (times[-1] - times[0]) / 1000.0 if len(times) > 1 else 0.0
        rates[_TAGS[i]] = (len(times) - 1) / span if span > 0.0 else math.nan
    counts = {"malformed": malformed, "tags": counts_tags, "late": 0, "clamped": 0, "jumps": 0,
              "back_ms": 0, "forced": 0,
              "offsets_s": {_TAGS[i]: off / 1000.0 for i, off in offsets.items()},
              "rates_hz": rates, "lines": n_lines}
    if overflows:
        counts["malformed"] = {**malformed, "too_long": overflows}
    return LogData(t=t, gyr=cols["gyr"], acc=cols["acc"], mag=cols["mag"], ori=ori,
                     kind="applog", counts=counts, done=1.0)


def _num(x):
    """A time (ms) as the orderer holds it: int when whole, else float."""
    x = float(x)
    return int(x) if x.is_integer() else x


def _order_like_orderer(tag_id: np.ndarray, raw_t: np.ndarray, orderer: SampleOrderer):
    """What ``orderer`` (fresh) makes of these samples (arrival order; ``raw_t`` in ms),
    computed at once: ``(mapped, glitch, offsets, first, popped_at)`` with the times on
    the reference clock, the lone time stamps it drops as glitches (``time_jump``), the
    offsets per tag id (in the orderer's order), each tag's first sample, and per glitch
    the sample at which it is counted (``len(raw_t)``: at the end). None where its
    result is not that simple: a sample late for the window, or a time jump that two
    samples of a tag in a row confirm (a re-anchored clock, a new offset).

    The orderer puts each sample in a buffer released in (time, arrival) order; when
    every sample lies within its window of the newest time before it, nothing is ever
    released ahead of a later-arriving sample, so its output is the stable sort on time.
    A sample beyond ``jump_s`` of that newest time is held aside and dropped when the
    tag's next sample is back on the clock."""
    n = len(tag_id)
    empty = np.zeros(0, dtype=np.int64)
    if n == 0:
        return raw_t, np.zeros(0, dtype=bool), {}, {}, empty
    ids, first_at = np.unique(tag_id, return_index=True)
    first = {int(i): int(f) for f, i in sorted(zip(first_at, ids))}
    mot = np.flatnonzero(np.isin(tag_id, _MOTION_IDS))
    # the reference: the first motion sample, unless too many others came before it
    ref = int(mot[0]) if mot.size and mot[0] <= orderer.max_pending else 0
    newest0 = _num(raw_t[ref])
    jump = orderer.jump_ms
    glitch = np.zeros(n, dtype=bool)
    for _ in range(8):   # glitches and offsets depend on each other: to a fixed point
        offsets = {int(tag_id[ref]): 0}
        mapped = raw_t.copy()
        placed = np.where(glitch, -np.inf, mapped)
        for tid, f in first.items():
            if tid not in offsets:
                before = placed[:f].max() if f else newest0
                diff = _num(raw_t[f]) - max(newest0, _num(before))
                offsets[tid] = diff if abs(diff) > orderer.offset_threshold * 1000.0 else 0
            if offsets[tid]:
                sel = tag_id == tid
                mapped[sel] -= offsets[tid]
                placed[sel & ~glitch] = mapped[sel & ~glitch]
        newest = np.maximum(np.concatenate(([newest0], np.maximum.accumulate(placed)[:-1])), newest0)
        gap = mapped - newest
        now = np.abs(gap) > jump
        if np.array_equal(now, glitch):
            break
        glitch = now
    else:
        return None
    if (gap[~glitch] < -orderer.window * 1000.0).any():
        return None                                    # late: clamped or dropped
    popped_at = empty
    if glitch.any():
        if orderer.jump_confirm < 2 or glitch[list(first.values())].any():
            return None
        popped = []
        for tid in np.unique(tag_id[glitch]).tolist():
            idx = np.flatnonzero(tag_id == tid)
            g = glitch[idx]
            if (g[:-1] & g[1:]).any():
                return None                            # two in a row: maybe a real jump
            nxt = np.concatenate((idx[1:], [n]))
            popped.append(nxt[g])
        popped_at = np.sort(np.concatenate(popped))
    return mapped, glitch, offsets, first, popped_at
