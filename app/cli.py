"""The ``orientlab`` command: estimate orientation from a recording, calibrate, serve.

``orientlab estimate INPUT --out OUT.csv``
    Reads INPUT (a Sensor Fusion app log, a CSV or an npz: see :mod:`app.sources.readers`),
    runs one estimator over it in chunks (memory stays bounded; the estimator's state
    carries over from chunk to chunk) and writes a CSV with the header
    ``t,qw,qx,qy,qz,`` followed by the flag columns of
    :data:`app.estimators.FLAG_COLUMNS`:

    - ``gyr``, ``acc``, ``mag``: the :class:`~app.estimators.Reason` as its lowercase
      name (``used``, ``absent``, ``norm``, ``nis``, ...);
    - ``time``: the :class:`~app.estimators.TimeIssue` as its lowercase name (``ok``,
      ``first``, ``repeated``, ``backward``, ``gap``);
    - ``rest``: 1 or 0;
    - ``acc_value``, ``acc_nis``, ``mag_value``, ``mag_nis``: numbers, an empty cell
      where there is no value (the output never holds the text ``nan``).

    Rows: for CSV and npz input exactly one output row per input row, in order; a CSV
    line that cannot be parsed at all (wrong number of cells, text in a number cell) is
    skipped and counted, but a row with NaN, inf or empty cells is kept (the estimator
    flags it). ``t`` is copied from the input (to the microsecond). For an app log, one row per ACC, GYR,
    MAG or ORI sample in time order, ``t`` on the log's reference clock.

    The output is written to a temporary file renamed to OUT at the end, so a failed
    run leaves no half-written OUT. On stderr: a progress line for long inputs (only
    if stderr is a terminal or the input is large), a summary of skipped input and
    refused updates, and as the last line ``N samples in S s (R samples/s)`` (S counts
    the estimation only, not reading or writing). ``--quiet`` keeps only that last line.

``orientlab calibrate INPUT --out PRESET.toml [--force]``
    Statistics of a stationary recording (lab manual exercise 2, :mod:`app.toolkit.calibration`):
    prints the report and writes a preset for ``--config``. A recording that does not
    look stationary (the phone moved...) writes no preset: the reasons on stderr, exit
    status 1; ``--force`` writes it anyway.

``orientlab gyro-scale INPUT... --out PRESET.toml``
    The gyroscope's scale-factor error per axis from recordings with rests
    (:mod:`app.toolkit.gyro_scale`), written as a preset's ``gyr_scale``.

``orientlab params [--toml]``
    Every estimator's parameters (units, ranges, defaults); ``--toml`` prints
    ``configs/default.toml``.

``orientlab serve``
    The live dashboard (:mod:`app.server.run`). A taken port gives one line naming it
    and its option, exit status 1. The page answers at once; on a cold numba cache the
    filters compile in the background (one process each), said on stderr with a line
    per filter as it becomes ready, shown by ``/api/health`` and the page.

``orientlab compile``
    Compile every estimator now (numba's on-disk cache, :mod:`app.warmup`), so the
    first ``serve`` or ``estimate`` does not wait for it; ``make run`` does this once
    after installing. ``serve`` and ``estimate`` say so when they compile. Whether
    stderr is a terminal or not, a line per estimator when it is ready and a progress
    line at least every 10 s between.

Exit status: 0 on success, 2 on a usage error, an unreadable input, or a refused
parameter or preset (one line on stderr says which).
"""

from __future__ import annotations

import argparse
import io
import itertools
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, TextIO

from app.config import ConfigError, load_config
from app.estimators import DEFAULT, NAMES, estimator_class, make_estimator
from app.estimators.base import count_flags
from app.params import ParamError
from app.sources.readers import DEFAULT_CHUNK_ROWS, ReaderError, iter_chunks
from app.toolkit.recording import OUTPUT_COLUMNS, format_rows
from app.warmup import prepare

PROG = "orientlab"
# inputs at least this large show a progress line even when stderr is not a terminal
PROGRESS_MIN_BYTES = 20_000_000


class CliError(Exception):
    """A failure reported as one line on stderr, exit status 2."""


# ---------------------------------------------------------------- argument parsing

def parse_set(items: list[str] | None) -> dict[str, Any]:
    """``key=value`` pairs; a value is JSON when it parses (numbers, true/false,
    lists), else a string."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise CliError(f"--set {item!r}: expected key=value")
        try:
            out[key] = json.loads(text)
        except json.JSONDecodeError:
            out[key] = text
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="orientlab: orientation estimation from phone IMU data "
                    "(Sensor Fusion app logs and streams, CSV, npz).",
        epilog=f"Run '{PROG} COMMAND --help' for a command's options.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    e = sub.add_parser(
        "estimate", help="estimate the orientation of every row of a recording",
        description="Estimate the orientation of every row of a recording and write "
                    "it with the per-row flags to a CSV.",
        epilog="Output columns: " + ",".join(OUTPUT_COLUMNS) + ". Reasons and time issues "
               "are written as lowercase names (used, norm, nis, ...; ok, backward, ...), "
               "missing values as empty cells. CSV/npz input: one output row per input "
               "row (CSV lines that cannot be parsed are skipped and counted; rows with "
               "NaN values are kept). App log: one row per ACC/GYR/MAG/ORI sample, in "
               "time order.")
    e.add_argument("input", metavar="INPUT",
                   help="Sensor Fusion app log, CSV (header t,acc_x,...) or .npz")
    e.add_argument("--out", "-o", required=True, metavar="OUT.csv", help="output CSV")
    e.add_argument("--filter", "-f", default=None, metavar="NAME",
                   help=f"estimator: {', '.join(NAMES)}, or a variant the recording's events "
                        f"file (--config) holds (default: the preset's or the recording's "
                        f"primary, else {DEFAULT})")
    e.add_argument("--config", "-c", metavar="FILE",
                   help="preset TOML (a path or a name in configs/), or a recording's "
                        "NAME.events.jsonl: the settings it began with and the magnetometer "
                        "calibration in force while it was made (the log holds the raw field)")
    e.add_argument("--set", "-s", action="append", metavar="KEY=VALUE", dest="set",
                   help="override one parameter of the estimator (repeatable); VALUE is "
                        "JSON when it parses (0.01, true, [0,0,9.81]), else text")
    e.add_argument("--chunk", type=int, default=DEFAULT_CHUNK_ROWS, metavar="ROWS",
                   help=f"rows per processing chunk (default {DEFAULT_CHUNK_ROWS})")
    e.add_argument("--quiet", "-q", action="store_true",
                   help="no progress line and no bad-input summary (the final "
                        "samples/s line stays)")
    e.set_defaults(func=cmd_estimate)

    c = sub.add_parser(
        "calibrate", help="statistics of a stationary recording -> report and preset",
        description="Compute mean, covariance, normality, trend and histograms per sensor "
                    "from a recording of the phone lying still (any pose), print the "
                    "report and write a preset (TOML) for --config.")
    c.add_argument("input", metavar="INPUT", help="stationary recording (log, CSV or npz)")
    c.add_argument("--out", "-o", required=True, metavar="PRESET.toml",
                   help="where to write the preset")
    c.add_argument("--force", action="store_true",
                   help="write the preset even if the recording does not look stationary "
                        "(its bias and noise would then mislead the filters)")
    c.set_defaults(func=cmd_calibrate)

    g = sub.add_parser(
        "gyro-scale", help="the gyroscope's scale factor from recordings with rests -> preset",
        description="Measure the gyroscope's scale-factor error per axis from recordings in which "
                    "the phone turns whole turns between rests, print the fit and write a preset "
                    "(TOML, gyr_scale) for --config. Record: lay the phone still for 2 s, turn it "
                    "whole turns in one direction about one of its axes while that axis is level "
                    "(flip it end over end: x; roll it over its long edge: y; stand it on its long "
                    "edge and turn it like a wheel: z), lay it still again; repeat for each axis, "
                    "in both directions. Each recording needs three rests or more.")
    g.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="recordings of one phone (log, CSV or npz)")
    g.add_argument("--out", "-o", required=True, metavar="PRESET.toml",
                   help="where to write the preset")
    g.set_defaults(func=cmd_gyro_scale)

    s = sub.add_parser(
        "serve", help="run the live dashboard (phone receiver + browser view)",
        description="Serve the live dashboard: a phone streams to it (the Sensor Fusion app "
                    "over TCP, Sensor Logger or phyphox over HTTP), the browser shows the "
                    "estimates and the controls.")
    s.add_argument("--host", default="0.0.0.0",
                   help="address to listen on (default 0.0.0.0 so the phone can connect)")
    s.add_argument("--port", type=int, default=8000, help="HTTP port of the dashboard (8000)")
    s.add_argument("--viewer-port", type=int, default=8080, help="port of the 3D viewer (8080)")
    s.add_argument("--phone-port", type=int, default=3400,
                   help="TCP port the phone streams to (3400, the app's default)")
    s.add_argument("--config", "-c", metavar="FILE", help="preset TOML")
    s.add_argument("--source", default="demo", metavar="SOURCE",
                   help="'demo' (simulated phone), 'none' (wait for a phone), "
                        "'phyphox:http://PHONE:PORT' (poll a phyphox phone's remote access) "
                        "or a recording to replay (default demo)")
    s.add_argument("--open", action="store_true",
                   help="trusted network: no presenter token, anyone may change the session "
                        "(default: only the link printed at start, which holds a token)")
    s.add_argument("--recordings", metavar="DIR", default=None,
                   help="folder of the lab's recordings (default recordings/ in the working "
                        "directory); app logs dropped in it are listed too")
    s.add_argument("--presets-dir", metavar="DIR",
                   help="folder for saved presets (default ~/.local/share/orientlab/presets)")
    s.set_defaults(func=cmd_serve)

    w = sub.add_parser(
        "compile", help="compile the filters now (numba cache) so the first start is quick",
        description="Compile every estimator with numba and fill its on-disk cache, one "
                    "process per estimator. serve and estimate then start in about a "
                    "second instead of compiling for about a minute.")
    w.add_argument("--jobs", "-j", type=int, default=None,
                   help="estimators compiled at once (default: the number of cores)")
    w.set_defaults(func=cmd_compile)

    m = sub.add_parser(
        "params", help="list every estimator's parameters (units, ranges, defaults)",
        description="Print the parameter table, or with --toml the defaults as a preset.")
    m.add_argument("--toml", action="store_true", help="print configs/default.toml")
    m.set_defaults(func=cmd_params)
    return p


# ---------------------------------------------------------------- estimate

def _merge_counts(total: dict, part: dict) -> None:
    for key, sub in part.items():
        dst = total.setdefault(key, {})
        for k, v in sub.items():
            dst[k] = dst.get(k, 0) + v


class Progress:
    """A plain-text progress line on stderr, rewritten with ``\\r``."""

    def __init__(self, stream: TextIO, enabled: bool):
        self.stream, self.enabled, self.shown = stream, enabled, False
        self._last = -1

    def update(self, done: float, rows: int) -> None:
        pct = int(done * 100)
        if not self.enabled or pct == self._last:
            return
        self._last = pct
        bar = "#" * (pct // 5) + "." * (20 - pct // 5)
        self.stream.write(f"\r{PROG}: [{bar}] {pct:3d}% {rows} rows")
        self.stream.flush()
        self.shown = True

    def close(self) -> None:
        if self.shown:
            self.stream.write("\n")
            self.stream.flush()


def input_summary(counts: dict) -> list[str]:
    """Lines about skipped or rearranged input, from a LogData's counts."""
    out = []
    bad = counts.get("malformed") or {}
    if bad:
        detail = ", ".join(f"{k}: {v}" for k, v in sorted(bad.items()))
        out.append(f"input: {sum(bad.values())} malformed lines skipped ({detail})")
    if counts.get("impossible"):
        n = counts["impossible"]
        out.append(f"input: {n} impossible reading{'s' if n != 1 else ''} refused (flagged "
                   f"invalid, their rows kept)")
    if counts.get("late"):
        out.append(f"input: {counts['late']} samples too late to order, skipped")
    if counts.get("clamped"):
        out.append(f"input: {counts['clamped']} slightly late samples, time clamped")
    offsets = {k: v for k, v in (counts.get("offsets_s") or {}).items() if v}
    if offsets:
        out.append("input: clock offsets " + ", ".join(f"{k} {v:+.3f} s"
                                                         for k, v in offsets.items()))
    return out


def flag_summary(flags: dict) -> list[str]:
    """Lines about refused updates and time issues, from merged :func:`count_flags`."""
    out = []
    for key in ("gyr", "acc", "mag"):
        c = {k: v for k, v in (flags.get(key) or {}).items() if k != "used"}
        if c:
            out.append(f"{key}: used {flags[key].get('used', 0)}, "
                       + ", ".join(f"{k} {v}" for k, v in sorted(c.items())))
    if flags.get("time"):
        out.append("time: " + ", ".join(f"{k} {v}" for k, v in sorted(flags["time"].items())))
    return out


def load_settings(config_path: str | None) -> tuple[dict[str, Any], list, dict[str, Any]]:
    """``--config``: a preset (TOML), or a recording's events file (``NAME.events.jsonl``:
    the settings it began with). Returns the checked config, the magnetometer
    calibration to apply to the field's rows, as it changed over time
    (:func:`app.toolkit.recorded.magcal_changes`; a preset's ``[magcal]`` from the start),
    and for a recording ``{"warm_s", "state"}``: how far into its stream it began and the
    live filters' state then (``NAME.state.npz``, per instance; {} if none).
    CliError on a refused file or value."""
    from app.config import config_from
    from app.toolkit.recording import EVENTS_SUFFIX, STATE_SUFFIX
    from app.toolkit.recorded import (event, magcal_changes, read_events, recorded_state,
                                      settings_of, variants_of, warm_start_s)
    try:
        if config_path is not None and str(config_path).endswith(EVENTS_SUFFIX):
            if not Path(config_path).is_file():
                raise CliError(f"{config_path}: no such file")
            events = read_events(config_path)
            try:
                table = settings_of(events)
            except ValueError as e:           # no start event: not a recording's
                raise CliError(f"{config_path}: {e}") from None
            config = config_from(table, str(config_path))     # ConfigError: below
            def tuned(e):     # the estimators' settings, not the calibration
                return {k: v for k, v in (e.get("params") or {}).items()
                        if k not in ("magcal", "magcal_from_t")}
            seq = [tuned(e) for e in events if e.get("kind") in ("start", "params")]
            changed = sum(1 for a, b in zip(seq, seq[1:]) if a != b)
            notes = []
            state_path = Path(str(config_path)[:-len(EVENTS_SUFFIX)] + STATE_SUFFIX)
            state, why = recorded_state({"state": state_path if state_path.is_file() else None},
                                        events)
            if changed:
                notes.append(f"the settings changed {changed}× during the recording: these are "
                             "the ones it began with (the magnetometer calibration follows its "
                             "changes)")
            for note in filter(None, notes):
                print(f"{PROG}: {config_path}: {note}", file=sys.stderr)
            variants, shown = variants_of(events)
            start = event(events, "start") or {}
            return config, magcal_changes(events), {
                "warm_s": warm_start_s(events), "why": why, "state": state,
                "path": str(config_path), "variants": variants, "primary": shown,
                "t": start.get("t"), "end": event(events, "end", last=True)}
        config = load_config(config_path)
    except ConfigError as e:
        raise CliError(str(e)) from None
    return config, [(None, config["magcal"])] if config.get("magcal") else [], {}


# a recording's log begins within this of where its events' recording began (the state's
# last sample): samples the reorder window held, a phone's batch; another recording's log
# (another phone, another stream, the same phone a minute later) is farther off
SAME_LOG_S = 5.0


def _not_this_log(recording: dict[str, Any], first) -> str | None:
    """Why the saved state of ``recording`` (its events file) does not fit the log whose first
    chunk is ``first``: the log begins far from where the recording began. None if it does
    (or there is no state or no time to compare)."""
    t = recording.get("t")
    if not recording.get("state") or not isinstance(t, (int, float)) or not len(first.t):
        return None
    t0 = float(first.t[0])
    if abs(t0 - float(t)) <= SAME_LOG_S:
        return None
    return (f"the log begins {t0 - float(t):+.1f} s from where the events' recording began "
            f"(not this log's events file?): its saved state is not used")


def take_up_state(est, recording: dict[str, Any], instance: str | None = None):
    """A recording begun into its stream: ``est``'s like, going on from the live filter's
    state as it began (its instance ``instance``, by default of the same name; ``est``'s
    parameters set after, as a live change), and it says so; else ``est``, and it says why
    the re-run starts cold (:func:`app.toolkit.recorded.warm_note`)."""
    from app.params import to_dict
    from app.toolkit.recorded import warm_estimator, warm_note
    if not recording:
        return est
    saved = (recording.get("state") or {}).get(instance or est.name)
    warm = False
    if saved is not None:
        est, warm = warm_estimator(est.name, to_dict(est.params), saved)
    why = recording.get("why") or (None if warm or saved is None else
                                   "the saved state does not fit this estimator")
    note = warm_note(recording.get("warm_s") or 0.0, warm, why)
    if note:
        print(f"{PROG}: {recording['path']}: {note}", file=sys.stderr)
    return est


def configured(name: str | None, config: dict[str, Any], sets: list[str] | None,
               recording: dict[str, Any] | None = None):
    """``(estimator, instance)``: the estimator ``name`` (or ``config``'s primary) with
    ``config``'s parameters then the ``--set`` overrides; and the instance of a recording
    it stands for. A recording's variant (``lab-approx``: ``--filter`` names it, or it was
    the recording's primary) is its estimator with the variant's parameters. CliError on a
    refused value or an unknown name."""
    overrides = parse_set(sets)
    variants = (recording or {}).get("variants") or {}
    instance = name or (recording or {}).get("primary") or config.get("primary", DEFAULT)
    if instance in variants:
        from app.config import translate_renamed     # an older recording's names, read as new
        name = variants[instance][0]
        params = {**translate_renamed(name, estimator_class(name).Params, variants[instance][1],
                                      f"{instance} (a variant of {name})"), **overrides}
    elif instance in NAMES:
        name, params = instance, {**config.get(instance, {}), **overrides}
    else:
        known = ", ".join(list(NAMES) + list(variants))
        raise CliError(f"--filter: no estimator {instance!r} (known: {known}; a variant is known "
                       "from the recording's events file given as --config)")
    if name != instance:
        print(f"{PROG}: {instance}: the recording's variant of {name}, with its parameters",
              file=sys.stderr)
    return _make(name, params), instance


def _make(name: str, params: dict[str, Any]):
    """The estimator ``name`` with ``params``; CliError on a refused value."""
    try:
        return make_estimator(name, params)
    except ParamError as e:
        raise CliError(f"{name}: --set/--config {e}") from None
    except ImportError as e:
        raise CliError(f"estimator {name!r} is not available ({e})") from None


def _umask() -> int:
    """The process's umask (read by setting it, then set back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def refuse_out_over_input(out: str, *inputs: str | None) -> None:
    """CliError when ``--out`` names one of the files read (the recording, its events file):
    it would replace it with the output, and the recording would be gone."""
    for path in inputs:
        if path is None:
            continue
        try:
            same = os.path.samefile(out, path)
        except OSError:           # either does not exist (yet): not the same file
            continue
        if same:
            raise CliError(f"--out {out} is the file read ({path}): it would be replaced by the "
                           "output; write to another file")


def cmd_estimate(args: argparse.Namespace) -> int:
    import numpy as np
    err = sys.stderr
    from app.toolkit.recorded import cut_short
    from app.toolkit.recording import ESTIMATES_SUFFIX, EVENTS_SUFFIX, STATE_SUFFIX
    siblings = []          # a recording's other files, read or not: never the output
    if args.config is not None and str(args.config).endswith(EVENTS_SUFFIX):
        stem = str(args.config)[:-len(EVENTS_SUFFIX)]
        siblings = [stem + STATE_SUFFIX, stem + ESTIMATES_SUFFIX]
    refuse_out_over_input(args.out, args.input, args.config, *siblings)
    config, magcal, recording = load_settings(args.config)
    est, instance = configured(args.filter, config, args.set, recording)
    if args.chunk < 1:
        raise CliError("--chunk must be at least 1")
    chunks = iter_chunks(args.input, rows=args.chunk)
    first = next(chunks)
    chunks = itertools.chain((first,), chunks)
    if recording:
        mismatch = _not_this_log(recording, first)
        if mismatch:
            recording = {**recording, "why": mismatch, "state": {}}
        cut = None if mismatch else cut_short(os.path.getsize(args.input), recording.get("end"))
        if cut:
            print(f"{PROG}: {args.input}: {cut}", file=err)
    est = take_up_state(est, recording, instance)
    if magcal:
        from app.toolkit.magcal import correct_rows
    try:
        size = os.path.getsize(args.input)
    except OSError:
        size = 0
    progress = Progress(err, not args.quiet and (err.isatty() or size >= PROGRESS_MIN_BYTES))
    # compile (or load from numba's cache) before timing: says so when it compiles
    prepare(out=io.StringIO() if args.quiet else err, prog=f"{PROG} estimate",
            only=(est.name,), live=False, batch=True)
    out_path = Path(args.out)
    n_rows, spent = 0, 0.0
    flags_total: dict = {}
    counts: dict = {}
    has_ori = False
    try:
        fd, tmp = tempfile.mkstemp(prefix=".orientlab-", suffix=".csv",
                                   dir=str(out_path.parent) if str(out_path.parent) else ".")
    except OSError as e:
        raise CliError(f"{out_path}: cannot write ({e.strerror or e})") from None
    try:
        with os.fdopen(fd, "w", newline="") as fh:
            fh.write(",".join(OUTPUT_COLUMNS) + "\n")
            for chunk in chunks:
                t0 = time.perf_counter()
                mag = correct_rows(chunk.t, chunk.mag, magcal) if magcal else chunk.mag
                res = est.run(chunk.t, chunk.gyr, chunk.acc, mag, chunk.ori)
                spent += time.perf_counter() - t0
                fh.write(format_rows(res.t, res.q, res.flags))
                n_rows += len(chunk)
                counts = chunk.counts
                has_ori = has_ori or (chunk.ori is not None and bool(np.isfinite(chunk.ori).any()))
                if len(chunk):
                    _merge_counts(flags_total, count_flags(res.flags))
                progress.update(chunk.done, n_rows)
        os.chmod(tmp, 0o666 & ~_umask())      # as open() would (mkstemp makes it 0600)
        try:
            os.replace(tmp, out_path)
        except OSError as e:                  # a folder, no permission: one line, exit 2
            raise CliError(f"{out_path}: cannot write ({e.strerror or e})") from None
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    finally:
        progress.close()
    if not args.quiet:
        for line in input_summary(counts) + flag_summary(flags_total):
            print(f"{PROG}: {line}", file=err)
    if est.reference and not has_ori and n_rows:
        # said even with --quiet: every row is the identity, which is no estimate
        print(f"{PROG}: the recording has no ORI (the phone's own orientation): 'phone' has "
              f"nothing to show, every row is the identity", file=err)
    rate = n_rows / spent if spent > 0 else 0.0
    print(f"{n_rows} samples in {spent:.3f} s ({rate:.0f} samples/s)", file=err)
    return 0


# ---------------------------------------------------------------- calibrate

def cmd_calibrate(args: argparse.Namespace) -> int:
    from app.toolkit.calibration import calibrate, format_report, to_preset
    from app.sources.readers import read_log_data

    refuse_out_over_input(args.out, args.input)
    rec = read_log_data(args.input)
    stats = calibrate(rec.t, rec.gyr, rec.acc, rec.mag)
    if not stats.sensors:
        raise CliError(f"{args.input}: no accelerometer, gyroscope or magnetometer samples")
    sys.stdout.write(format_report(stats))
    for line in input_summary(rec.counts):
        print(f"{PROG}: {line}", file=sys.stderr)
    if not stats.stationary:
        reasons = "; ".join(stats.warnings)
        if not args.force:
            print(f"{PROG}: not writing {args.out}: the recording does not look stationary "
                  f"({reasons}); its bias and noise would mislead the filters. Record the "
                  "phone lying still, or write it anyway with --force", file=sys.stderr)
            return 1
        print(f"{PROG}: writing {args.out} anyway (--force), though the recording does not "
              f"look stationary ({reasons})", file=sys.stderr)
    _write_preset(args.out, to_preset(stats))
    return 0


def _write_preset(path: str, text: str) -> None:
    """Write a preset and check that --config accepts it."""
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as e:
        raise CliError(f"{path}: cannot write ({e.strerror or e})") from None
    try:
        load_config(path)  # what we write must be what --config accepts
    except ConfigError as e:
        raise CliError(f"the written preset is refused: {e}") from None
    print(f"preset written to {path}")


def cmd_gyro_scale(args: argparse.Namespace) -> int:
    from app.sources.readers import read_log_data
    from app.toolkit.errors import ToolError
    from app.toolkit.gyro_scale import Recording, fit, format_report, to_preset

    refuse_out_over_input(args.out, *args.inputs)
    recs = []
    for path in args.inputs:
        rec = read_log_data(path)
        for line in input_summary(rec.counts):
            print(f"{PROG}: {path}: {line}", file=sys.stderr)
        recs.append(Recording(Path(path).name, rec.t, rec.gyr, rec.acc))
    try:
        result = fit(recs)
    except ToolError as e:
        raise CliError(e.reason) from None
    sys.stdout.write(format_report(result))
    if not result.measured.any():
        print(f"{PROG}: not writing {args.out}: no axis is measured (see the warnings)", file=sys.stderr)
        return 1
    _write_preset(args.out, to_preset(result))
    return 0


# ---------------------------------------------------------------- serve, compile

def cmd_compile(args: argparse.Namespace) -> int:
    from app.warmup import compile_all
    if args.jobs is not None and args.jobs < 1:
        raise CliError("--jobs must be at least 1")
    return compile_all(jobs=args.jobs)


def cmd_serve(args: argparse.Namespace) -> int:
    try:
        from app.server.run import serve
    except ImportError as e:
        raise CliError(f"serve is not available ({e})") from None
    try:
        return int(serve(args) or 0)
    except KeyboardInterrupt:  # Ctrl-C: uvicorn re-raises it after its graceful shutdown
        return 0


def cmd_params(args) -> int:
    from app.config import defaults_toml, params_table
    print(defaults_toml() if args.toml else params_table(), end="")
    return 0


# ---------------------------------------------------------------- entry point

def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (CliError, ReaderError, ConfigError) as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of our output went away (| head): not an error
        try:
            sys.stdout = open(os.devnull, "w")
        except OSError:
            pass
        return 0


if __name__ == "__main__":
    sys.exit(main())
