"""Recorded sensor data in, estimator rows out: app logs, CSV and npz.

:func:`read_recording` reads a whole file into one :class:`Recording`;
:func:`iter_chunks` yields it in pieces of at most ``rows`` rows so a long recording
(an hour at 100 Hz, or an app log of a million lines) streams with bounded memory.
The format is told from the content, not the extension:

``applog``
    The Sensor Fusion app's log (``shared/protocols/sensorfusion-app.md``): every tag
    is parsed, lines are put in time order and on one clock by
    :class:`app.stream.SampleOrderer` (window :data:`LOG_WINDOW`), corrupted lines are
    counted by reason and skipped, ``\\n``, ``\\r\\n`` and ``\\r`` all end a line. One
    row per ACC, GYR, MAG or ORI sample, in time order; ``t`` is on the reference clock.
``csv``
    A header naming ``t`` (s) and any of ``acc_x..acc_z`` (m/s²), ``gyr_x..gyr_z``
    (rad/s), ``mag_x..mag_z`` (µT), optionally ``ori_w..ori_z``; other columns are
    ignored. An empty cell is missing (NaN); ``nan`` passes through (the estimator
    flags it); a physically impossible reading (``inf``, a gyro beyond 100 rad/s: the
    limits of :data:`app.protocol.VALUE_LIMITS`, as for app logs and the live stream)
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
from typing import Any, BinaryIO, Iterator

import numpy as np

from .protocol import MOTION_TAGS, LineSplitter, MalformedLine, impossible_rows, parse_line
from .stream import SampleOrderer, samples_to_rows

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
    """The file cannot be read as a recording (the message says why, in one line)."""


@dataclass
class Recording:
    """Rows of sensor data. ``gyr``/``acc``/``mag`` are (N, 3) with NaN where missing,
    ``ori`` (N, 4) or None, ``t`` (N,) s. ``counts`` says what was skipped or noticed:
    ``malformed`` (reason -> lines); for app logs also ``lines``, ``tags``, ``late``,
    ``clamped``, ``offsets_s`` and ``rates_hz`` (see :mod:`app.stream`); for CSV and
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


def iter_chunks(path: str | Path, rows: int = DEFAULT_CHUNK_ROWS) -> Iterator[Recording]:
    """The recording at ``path`` in chunks of at most ``rows`` rows, in order (always at
    least one chunk, possibly empty). ReaderError for a file that cannot be read."""
    if rows < 1:
        raise ValueError("rows must be >= 1")
    kind = detect_format(path)
    reader = {"applog": _applog_chunks, "csv": _csv_chunks, "npz": _npz_chunks}[kind]
    return reader(Path(path), rows)


def read_recording(path: str | Path) -> Recording:
    """The whole recording at ``path`` (see the module doc for formats)."""
    chunks = list(iter_chunks(path))
    return concat(chunks)


def concat(chunks: list[Recording]) -> Recording:
    """Chunks of one file joined (counts and ``done`` of the last)."""
    if len(chunks) == 1:
        return chunks[0]
    last = chunks[-1]
    has_ori = any(c.ori is not None for c in chunks)
    ori = (np.concatenate([c.ori if c.ori is not None else np.full((len(c), 4), np.nan)
                           for c in chunks]) if has_ori else None)
    return Recording(t=np.concatenate([c.t for c in chunks]),
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

def _applog_chunks(path: Path, rows: int) -> Iterator[Recording]:
    orderer = SampleOrderer(window=LOG_WINDOW)
    size = path.stat().st_size
    motion: list = []
    lines = 0

    def chunk(samples: list, done: float) -> Recording:
        r = samples_to_rows(samples)
        ori = r.ori if not np.isnan(r.ori).all() else None
        counts = {**orderer.summary(), "lines": lines}
        if splitter.overflows:
            counts["malformed"] = {**counts["malformed"], "too_long": splitter.overflows}
        return Recording(t=r.t, gyr=r.gyr, acc=r.acc, mag=r.mag, ori=ori, kind="applog",
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


def _csv_chunks(path: Path, rows: int) -> Iterator[Recording]:
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

        def chunk(done: float) -> Recording:
            a = np.array(block, dtype=float).reshape(len(block), len(wanted))
            out, col = {}, 1
            for key, width in (("gyr", 3), ("acc", 3), ("mag", 3), ("ori", 4)):
                if key in present:
                    out[key] = a[:, col:col + width]
                    col += width
                else:
                    out[key] = None if key == "ori" else np.full((len(a), 3), np.nan)
            _refuse_impossible(out, malformed)
            counts["rows"] = n_rows
            if splitter.overflows:
                malformed["too_long"] = splitter.overflows
            return Recording(t=a[:, 0].copy(), gyr=out["gyr"], acc=out["acc"], mag=out["mag"],
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


def _refuse_impossible(arrays: dict, malformed: dict) -> None:
    """Physically impossible readings (:data:`app.protocol.VALUE_LIMITS`, the same limits
    as the app-log parser's) become missing (NaN), counted as ``impossible``."""
    for key, tag in (("gyr", "GYR"), ("acc", "ACC"), ("mag", "MAG")):
        a = arrays.get(key)
        if a is None or not len(a):
            continue
        bad = impossible_rows(tag, a)
        if bad.any():
            a[bad] = np.nan
            malformed["impossible"] = malformed.get("impossible", 0) + int(bad.sum())


# ---------------------------------------------------------------- npz

def _npz_chunks(path: Path, rows: int) -> Iterator[Recording]:
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
            a = np.asarray(data[key], dtype=float)
            if a.ndim != 2 or a.shape[1] != width:
                raise ReaderError(f"{path}: npz array {key!r} has shape {a.shape}, "
                                  f"expected (N, {width})")
            if n is not None and a.shape[0] != n:
                raise ReaderError(f"{path}: npz arrays have different lengths "
                                  f"({key!r} has {a.shape[0]}, expected {n})")
            n = a.shape[0]
            arrays[key] = a
        if "t" in keys:
            t = np.asarray(data["t"], dtype=float).reshape(-1)
            if t.shape[0] != n:
                raise ReaderError(f"{path}: npz 't' has {t.shape[0]} values for {n} rows")
        elif "fs" in keys:
            fs = float(np.asarray(data["fs"]).reshape(-1)[0])
            if not (math.isfinite(fs) and fs > 0):
                raise ReaderError(f"{path}: npz 'fs' must be a positive rate in Hz, got {fs}")
            t = np.arange(n) / fs
        else:
            raise ReaderError(f"{path}: npz has neither 't' (s) nor 'fs' (Hz)")
    counts = {"malformed": {}, "rows": 0, "columns": sorted(k for k in arrays if arrays[k] is not None)}
    _refuse_impossible(arrays, counts["malformed"])
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
        yield Recording(t=t[sl], gyr=part("gyr"), acc=part("acc"), mag=part("mag"),
                        ori=part("ori"), kind="npz", counts=dict(counts),
                        done=stop / n if n else 1.0)
        start = stop
        if start >= n:
            break

