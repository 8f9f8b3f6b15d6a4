"""A recording read back: which files a recording has, its events, its estimates, the
filters' state it began with, and what a re-run takes from them (the settings it began
with, the magnetometer calibration as it changed, the state to go on from); the listing
of the recordings folder. The files' format and their writing are
:mod:`app.toolkit.recording`'s.
"""

from __future__ import annotations

import gzip
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from app.toolkit.recording import (ESTIMATES_SUFFIX, EVENTS_SUFFIX, MAX_STATE_BYTES,
                                   PLAIN_ESTIMATES_SUFFIX, STATE_SUFFIX, RecordingError,
                                   check_name, file_size, find_log, recording_logs)


def recording_files(folder: str | Path, name: str) -> dict[str, Path | None]:
    """The files of recording ``name``: ``log`` (required; the one the listing shows,
    :func:`~app.toolkit.recording.find_log`), ``estimates``, ``events``, ``state`` (None
    when absent). RecordingError if there is no such log."""
    folder = Path(folder)
    check_name(name)
    log = find_log(folder, name)
    if log is None:
        # the folder by its name only: a watcher may read this (never the presenter's paths)
        raise RecordingError(f"no recording named {name!r} in the folder {folder.name or str(folder)!r}")
    ev = folder / (name + EVENTS_SUFFIX)
    st = folder / (name + STATE_SUFFIX)
    return {"log": log, "estimates": estimates_file(folder, name),
            "events": ev if ev.is_file() else None, "state": st if st.is_file() else None}


def read_recording_log(log: Path, field: str = "name"):
    """The rows of a recording's log (:func:`app.sources.readers.read_log_data`); a file
    dropped in the folder that is no log is a ToolError naming ``field``, the file by its
    name (never its folder's path)."""
    from app.sources.readers import ReaderError, read_log_data
    from app.toolkit.errors import ToolError
    try:
        return read_log_data(log)
    except ReaderError as e:
        raise ToolError(field, str(e).replace(str(log), log.name)) from None


def read_state(path: str | Path | None) -> dict[str, dict[str, np.ndarray]]:
    """The live filters' state a recording began with (:meth:`Recorder.write_state`), per
    instance: ``{instance: {attribute: array}}``; {} when there is none. RecordingError
    for a file that is not one (too large, not an npz, objects in it)."""
    if path is None or not Path(path).is_file():
        return {}
    path = Path(path)
    if file_size(path) > MAX_STATE_BYTES:
        raise RecordingError(f"{path.name}: larger than {MAX_STATE_BYTES} bytes: not a state file")
    out: dict[str, dict[str, np.ndarray]] = {}
    try:
        with zipfile.ZipFile(path) as zf:     # what it holds unpacked, before unpacking it
            if sum(i.file_size for i in zf.infolist()) > MAX_STATE_BYTES:
                raise ValueError(f"it unpacks to more than {MAX_STATE_BYTES} bytes")
        with np.load(path, allow_pickle=False) as z:
            for key in z.files:
                inst, sep, attr = key.partition("/")
                if sep:
                    out.setdefault(inst, {})[attr] = np.asarray(z[key], dtype=float)
    except Exception as e:   # whatever a damaged file raises (zip, npy, EOF): not used
        raise RecordingError(f"{path.name}: not a state file ({type(e).__name__}: "
                             f"{str(e)[:120]})") from None
    return out


def event(events: list[dict[str, Any]], kind: str, last: bool = False) -> dict[str, Any] | None:
    """The first (``last``: the last) event of ``kind`` (``start``, ``end``...), or None."""
    return next((e for e in (reversed(events) if last else events) if e.get("kind") == kind), None)


def _start_with_params(events: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The ``start`` event, if it holds the parameters the recording began with."""
    start = event(events, "start")
    return start if start is not None and isinstance(start.get("params"), dict) else None


def recorded_state(files: dict[str, Path | None], events: list[dict[str, Any]]
                   ) -> tuple[dict[str, tuple[str, dict[str, Any], dict[str, np.ndarray]]],
                              str | None]:
    """The live filters' state a recording began with, when its ``start`` event says it
    kept one and the file is that one (each instance's ``_last_t`` at the event's ``t``):
    ``({instance: (its estimator, its parameters then, its state)}, None)``. Else ``({}, why)``: why a
    re-run starts cold, or None when the recording began with its stream (none to keep)."""
    start = event(events, "start")
    path = files.get("state")
    if start is None and path is not None:
        if "events" in files and files["events"] is None:
            return {}, f"its events file is missing: {path.name} cannot be checked: not used"
        return {}, (f"the events file has no readable start event (damaged?): {path.name} "
                    "cannot be checked against it: not used")
    start = start or {}
    if not start.get("state"):
        return {}, (f"{path.name} is not this recording's (its start event names none): "
                    "not used" if path is not None else None)
    if path is None:
        return {}, "its state file is missing"
    try:
        state = read_state(path)
    except RecordingError as e:
        return {}, str(e)
    t, params = start.get("t"), start.get("params") or {}
    out = {}
    for inst, arrays in state.items():
        lt = arrays.get("_last_t")
        if t is None or lt is None or np.ndim(lt) or abs(float(lt) - float(t)) > 1e-6:
            return {}, f"{path.name} is not the state this recording began with: not used"
        p = params.get(inst)
        if isinstance(p, dict):
            out[inst] = (str(p.get("base", inst)),
                         {k: v for k, v in p.items() if k != "base" and v is not None}, arrays)
    return out, None


def estimates_file(folder: str | Path, name: str) -> Path | None:
    """The estimates file of recording ``name`` (gzip, or an older plain CSV), or None."""
    for sfx in (ESTIMATES_SUFFIX, PLAIN_ESTIMATES_SUFFIX):
        p = Path(folder) / (name + sfx)
        if p.is_file():
            return p
    return None


def read_events(path: str | Path | None) -> list[dict[str, Any]]:
    """The events of a recording (bad lines skipped)."""
    out = []
    if path is None or not Path(path).is_file():
        return out
    for line in Path(path).read_text(errors="replace").splitlines():
        try:
            event = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(event, dict):      # a line that is JSON but no event ("x", [1, 2]): skipped
            out.append(event)
    return out


def settings_of(events: list[dict[str, Any]]) -> dict[str, Any]:
    """The settings a recording began with (its ``start`` event), as a preset table
    (:func:`app.config.validate_config` checks it): ``primary``, each estimator's
    parameters (the instances named as their estimator; variants are left out) and the
    magnetometer calibration in force (``magcal``), if any. ValueError when there is no
    ``start`` event with parameters."""
    start = _start_with_params(events)
    if start is None:
        raise ValueError("no 'start' event with the parameters (not an orientlab recording's "
                         "events file?)")
    out: dict[str, Any] = {}
    params = start["params"]
    for key, value in params.items():
        if key == "primary":       # a variant on show (robust-no-rejection): its estimator
            inst = params.get(value)
            out[key] = inst.get("base", value) if isinstance(inst, dict) else value
        elif key == "magcal":
            out[key] = value
        elif isinstance(value, dict) and value.get("base", key) == key:
            out[key] = {k: v for k, v in value.items() if k != "base" and v is not None}
    return out


def variants_of(events: list[dict[str, Any]]) -> tuple[dict[str, tuple[str, dict[str, Any]]], str | None]:
    """The variants a recording began with (instances named otherwise than their estimator,
    ``lab-approx``), ``{name: (estimator, parameters)}``, and the instance it showed as the
    primary (a variant's own name; None without a ``start`` event): :func:`settings_of`
    leaves them out, a preset has none, but a re-run of the recording must be able to
    reproduce one."""
    start = _start_with_params(events)
    if start is None:
        return {}, None
    from app.estimators import NAMES
    out = {}
    for key, value in start["params"].items():
        if isinstance(value, dict) and value.get("base") in NAMES and value["base"] != key:
            out[key] = (value["base"], {k: v for k, v in value.items() if k != "base" and v is not None})
    primary = start["params"].get("primary")
    return out, primary if isinstance(primary, str) else None


def warm_estimator(base: str, params: dict[str, Any], saved) -> Any:
    """A new ``base`` estimator with ``params``, going on from a recording's saved state
    (``saved``: a :func:`recorded_state` entry, or None) as the live one would have: made
    with the parameters it was recorded with, its state taken up, then ``params`` set (a
    live change's order: a changed window resized, a changed reference field applied).
    Returns ``(estimator, warm)``; cold (``warm`` False) when the state does not fit."""
    from app.estimators import make_estimator
    from app.params import ParamError
    if saved is not None and saved[0] == base:
        try:
            est = make_estimator(base, saved[1])
            est.restore_arrays(saved[2])
            est.set_params(**params)
            return est, True
        except (ValueError, ParamError):
            pass
    return make_estimator(base, params), False


def warm_start_s(events: list[dict[str, Any]]) -> float:
    """How long the live filters had run on the stream when the recording began (its
    ``start`` event's ``warm_s``; 0 when it does not say)."""
    start = event(events, "start")
    try:
        return float((start or {}).get("warm_s") or 0.0)
    except (TypeError, ValueError):
        return 0.0


WARM_NOTE_S = 0.5    # a recording begun later than this into its stream is said to be warm


def warm_note(warm_s: float, warm: bool = False, why: str | None = None) -> str | None:
    """What a re-run of a recording begun ``warm_s`` into its stream should say, or None.
    ``warm``: the re-run goes on from the live filters' state as the recording began (its
    state file was read); ``why``: why not (:func:`recorded_state`)."""
    if why is not None and not warm:
        return (f"{why}; the re-run starts cold at the recording's first line" if warm_s <= WARM_NOTE_S
                else f"{why}; " + warm_note(warm_s))
    if warm_s <= WARM_NOTE_S:
        return None
    if warm:
        return (f"the recording began {warm_s:.1f} s into its stream: the re-run goes on from "
                "the live filters' state at its first line (gyroscope bias and field as they "
                "had learned them)")
    return (f"the recording began {warm_s:.1f} s into its stream: a re-run starts cold at its "
            "first line, where the live filters had been running; it differs from what they "
            "showed until it has learned the gyroscope's bias and the field again (the heading "
            "can take tens of seconds). To reproduce a recording, press Record before the "
            "phone streams")


def magcal_changes(events: list[dict[str, Any]]) -> list[tuple[float | None, dict | None]]:
    """The magnetometer calibration in force over a recording, as it changed:
    ``[(after t, its [magcal] table or None), ...]``, the first from the start (``None``),
    then one per ``params`` event that changed it, for the MAG samples after its
    ``magcal_from_t`` (the last one corrected the old way: the correction is applied as
    samples arrive), or after the event's ``t`` in a recording that does not have it. A
    change before the stream's first field sample (``None``) replaces those before it.
    The log holds the raw field; the live filters got it corrected by these."""
    out: list[tuple[float | None, dict | None]] = []
    for e in events:
        params = e.get("params")
        if not isinstance(params, dict) or e.get("kind") not in ("start", "params"):
            continue
        table = params.get("magcal") or None
        if e["kind"] == "start":
            out = [(None, table)]
        elif not out or out[-1][1] != table:
            t = params["magcal_from_t"] if "magcal_from_t" in params else e.get("t")
            if t is None:          # before any field sample of the stream: it is the first
                out = [(None, table)]
            else:
                out.append((float(t), table))
    return out


EVENTS_HEAD_BYTES = 1 << 20    # the start event (the parameters: some kB) is in this much
EVENTS_TAIL_BYTES = 1 << 16    # the end event (a few hundred bytes) is in this much


def _first_and_last_event(path: Path) -> tuple[dict | None, dict | None]:
    """The first event of an events file and its ``end`` event, if it ended: read from
    its head and its tail only (a long recording's file holds every change; the
    listing reads it twice a second)."""
    try:
        with open(path, "rb") as fh:
            head = fh.readline(EVENTS_HEAD_BYTES)
            size = os.fstat(fh.fileno()).st_size
            fh.seek(max(0, size - EVENTS_TAIL_BYTES))
            tail = fh.read()
    except OSError:
        return None, None

    def parsed(line: bytes) -> dict | None:
        try:
            v = json.loads(line)
        except ValueError:
            return None
        return v if isinstance(v, dict) else None

    first = parsed(head)
    last = next((v for v in (parsed(x) for x in reversed(tail.splitlines()) if x.strip())
                 if v is not None), None)
    return first, (last if last is not None and last.get("kind") == "end" else None)


def cut_short(size: int, end: dict | None) -> str | None:
    """Why a recording's log of ``size`` bytes is not all its recording wrote (its ``end``
    event's ``log_bytes``: a copy or a download that did not finish), or None."""
    want = (end or {}).get("log_bytes")
    if not isinstance(want, int) or isinstance(want, bool) or size >= want:
        return None
    return (f"the log holds {size} of the {want} bytes its recording wrote: it was cut short "
            "(a copy or a download that did not finish?); a re-run covers the part there is")


def scan_recordings(folder: str | Path) -> tuple[list[dict[str, Any]], list[dict[str, str]]]:
    """Every recording in ``folder``, newest first, and the files left out with why
    (:func:`~app.toolkit.recording.recording_logs`). A recording is our own (log and
    siblings) or any app log, CSV or npz dropped in (its name: the file's stem).
    ``seconds``/``samples`` come from the events file's end (None without one: the log
    is not read here); ``recording``/``segment``: the recording a later segment
    (``NAME_2``) belongs to, and which part it is."""
    folder = Path(folder)
    if not folder.is_dir():
        return [], []
    logs, left = recording_logs(folder)
    out = []
    for name, p in logs.items():
        try:
            st = p.stat()
        except OSError:
            continue
        ev = folder / (name + EVENTS_SUFFIX)
        start, end = _first_and_last_event(ev) if ev.is_file() else (None, None)
        events = start is not None
        cut = cut_short(st.st_size, end)
        out.append({"name": name, "path": str(p), "bytes": st.st_size, "modified": st.st_mtime,
                    "orientlab": events,
                    "has_events": ev.is_file(),
                    "has_estimates": estimates_file(folder, name) is not None,
                    "has_state": (folder / (name + STATE_SUFFIX)).is_file(),
                    "recording": start.get("recording", name) if events else name,
                    "segment": start.get("segment", 1) if events else 1,
                    "seconds": end.get("seconds") if end else None,
                    "samples": end.get("samples") if end else None,
                    "end_reason": end.get("reason") if end else None,
                    "cut_short": cut,
                    "complete": (end is not None and cut is None) or not events})
    out.sort(key=lambda r: r["modified"], reverse=True)
    return out, left


def _estimate_lines(path: Path, cut: list[str] | None = None):
    """The text lines of an estimates file, gzip or plain; a gzip still being written
    (or cut short) gives the lines up to where it was flushed, and says why in ``cut``."""
    with open(path, "rb") as fh:
        gz = fh.read(2) == b"\x1f\x8b"
    if not gz:
        with open(path, newline="") as fh:
            yield from fh
        return
    rest = b""
    with gzip.open(path, "rb") as fh:
        while True:
            try:
                block = fh.read(1 << 16)
            except (EOFError, gzip.BadGzipFile, OSError) as e:
                if cut is not None:
                    cut.append(str(e) or type(e).__name__)
                block = b""
            if not block:
                break
            lines = (rest + block).split(b"\n")
            rest = lines.pop()
            for ln in lines:
                yield ln.decode("utf-8", "replace") + "\n"
    # a last line without its newline was cut short: dropped


def read_estimates(path: str | Path, warn: bool = True,
                   said: list[str] | None = None) -> dict[str, dict[str, np.ndarray]]:
    """A recording's estimates file (``.estimates.csv.gz`` or an older plain
    ``.estimates.csv``): per estimator ``{"t": (N,), "q": (N, 4)}``. A gzip that ends
    early (a recording still being written, or a file cut short) gives the rows up to
    there, with a warning (``EstimatesCutShort``) saying so, unless ``warn`` is False;
    ``said`` gets that text too (a worker thread's way: warnings are process-wide)."""
    import csv
    import warnings
    per: dict[str, tuple[list, list]] = {}
    cut: list[str] = []
    try:
        return _read_estimate_rows(csv.reader(_estimate_lines(Path(path), cut)), per)
    finally:
        if cut:
            n = sum(len(v[0]) for v in per.values())
            why = (f"the file ends early ({cut[0]}): {n} rows read, the rest is missing (a "
                   "recording still being written, or a file cut short)")
            if said is not None:
                said.append(why)
            if warn:
                warnings.warn(f"{path}: {why}", EstimatesCutShort, stacklevel=2)


class EstimatesCutShort(UserWarning):
    """An estimates file that ends early: :func:`read_estimates` read what is there."""


def _read_estimate_rows(rd, per: dict[str, tuple[list, list]]) -> dict[str, dict[str, np.ndarray]]:
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
