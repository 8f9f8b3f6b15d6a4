"""What-if: re-run a whole recording through every estimator, before and after a
parameter change, and compare.

:func:`rerun` reads the recording once (:func:`app.sources.readers.read_log_data`, as
``orientlab estimate`` does), then runs each estimator over all its rows with the batch
path (``Estimator.run``) twice: with the parameters it has now ("before") and with the
patch applied ("after"; skipped when the patch leaves it unchanged). Per estimator and
run it returns

- the error to the phone's own estimate (the log's ORI, held between samples), and to
  the truth when the recording has one (the ``truth`` rows of its estimates file,
  written by the recorder for the demo): RMS, median, 95th percentile and maximum, in
  degrees, counted from the estimator's initial alignment on;
- the share of accelerometer and magnetometer samples refused by a gate (of those
  present and valid);
- decimated time series for the page to overlay: error to the phone (or truth), yaw,
  pitch and roll (degrees, the manual's ``q2euler``);
- ``change_deg``: how far the patch moves the estimate (the angle between before and
  after; the only figure when the log has neither truth nor ORI);
- ``live``: the error of what the live filter showed, at the rows the recording's estimates
  file has an estimate for (``live.rerun``: the re-run's "before" at those rows), and ``note``: why the re-run differs from it there, when it
  does by more than :data:`AGREE_DEG` / :data:`AGREE_REL`. A recording begun into its
  stream keeps the live filters' state as it began (``NAME.state.npz``): each run goes on
  from it, so with the parameters it was recorded with the re-run is what the live filter
  showed. One without (an older recording, a log dropped in) starts cold at its first
  sample (gyroscope bias and field learned again): on the demo (gyroscope bias ~3°/s) one
  begun mid-motion re-ran at ~9° RMS where the live filter showed ~1°. ``notes`` (top
  level): what the error is measured against, in words (the page shows them under the
  table).

An estimator is described by a *spec* ``(base, params)``: ``base`` the estimator class
name (``robust``, ``lab``, ...) and ``params`` its parameter dict, so variants
(``robust-no-rejection``) re-run like the others. A patch is ``{name: {key: value}}``.
The ``phone`` estimator is the reference itself (the held ORI): it is scored, not run.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from app.estimators import REJECTIONS, Reason, estimator_class, make_estimator
from app.estimators.base import F_ACC, F_MAG
from app.params import ParamError, to_dict
from app.quaternion import IDENTITY, error_angles, not_estimated, q2euler_many
from app.sources.readers import LogData, read_log_data
from app.toolkit.errors import ToolError
from app.toolkit.jobs import JobQueue, run_in_chunks

MAX_POINTS = 1500
_REJ = np.array(sorted(int(r) for r in REJECTIONS))
_NOT_OFFERED = np.array([int(Reason.ABSENT), int(Reason.DISABLED), int(Reason.INVALID),
                         int(Reason.WAIT), int(Reason.LATE)])


class WhatIfError(ValueError):
    """A refused re-run (bad patch, unknown estimator); ``field`` names what."""

    def __init__(self, field_name: str, reason: str):
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason


def hold_ori(rec: LogData) -> np.ndarray | None:
    """The phone's estimate at every row: the last ORI sample held (NaN before the
    first), or None when the recording has none."""
    if rec.ori is None:
        return None
    o = np.asarray(rec.ori, dtype=float)
    ok = np.all(np.isfinite(o), axis=1)
    if not ok.any():
        return None
    idx = np.where(ok, np.arange(len(o)), -1)
    idx = np.maximum.accumulate(idx)
    out = np.full_like(o, np.nan)
    have = idx >= 0
    q = o[idx[have]]
    out[have] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return out


def truth_at(t: np.ndarray, truth: dict[str, np.ndarray] | None) -> np.ndarray | None:
    """The truth (``{"t", "q"}``) at times ``t`` (the latest truth row at or before)."""
    if truth is None or len(truth["t"]) == 0:
        return None
    tt, qq = np.asarray(truth["t"]), np.asarray(truth["q"])
    order = np.argsort(tt, kind="stable")
    tt, qq = tt[order], qq[order]
    i = np.searchsorted(tt, t, side="right") - 1
    out = np.full((len(t), 4), np.nan)
    ok = i >= 0
    out[ok] = qq[i[ok]]
    return out


LIVE_MATCH_S = 0.0005    # a live estimate is at a row's time when this close (ms clocks)


def live_at(t: np.ndarray, live: dict[str, np.ndarray] | None) -> np.ndarray | None:
    """The live filter's recorded estimates (``{"t", "q"}``) at the rows of times ``t``
    that have one (NaN elsewhere): a recording keeps them at a lower rate than its samples
    (``recording_estimates_hz``), and one held over the rows between would be charged with
    the motion since it (a degree at a brisk turn)."""
    q = truth_at(t, live)
    if q is None:
        return None
    tt = np.sort(np.asarray(live["t"], dtype=float))
    i = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 1)
    q[np.abs(t - tt[i]) > LIVE_MATCH_S] = np.nan
    return q


def _stats_deg(x: np.ndarray) -> dict[str, float | None]:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"rms": None, "median": None, "p95": None, "max": None, "n": 0}
    d = np.degrees(x)
    return {"rms": float(np.sqrt(np.mean(d * d))), "median": float(np.median(d)),
            "p95": float(np.percentile(d, 95)), "max": float(d.max()), "n": int(d.size)}


def rejected_share(flags: np.ndarray, col: int) -> float | None:
    """Share of the valid samples offered to a sensor's update that a gate refused."""
    f = flags[:, col].astype(np.int64)
    offered = ~np.isin(f, _NOT_OFFERED)
    n = int(offered.sum())
    if n == 0:
        return None
    return float(np.isin(f[offered], _REJ).sum()) / n


def _aligned_from(flags: np.ndarray) -> int:
    """The first row at which the estimator has aligned (its first INIT or USED update)."""
    f = flags[:, [F_ACC, F_MAG]].astype(np.int64)
    hit = np.nonzero(np.any((f == int(Reason.INIT)) | (f == int(Reason.USED)), axis=1))[0]
    return int(hit[0]) if hit.size else 0


def _decimate(n: int, max_points: int) -> np.ndarray:
    if n <= max_points:
        return np.arange(n)
    return np.linspace(0, n - 1, max_points).astype(np.int64)


def _one_run(base: str, params: dict[str, Any], rec: LogData, ref: np.ndarray | None,
             ref_kind: str | None, truth: np.ndarray | None, idx: np.ndarray,
             phone_ref: np.ndarray | None,
             saved=None) -> tuple[dict[str, Any], float]:
    """One estimator over the recording; ``saved``: the live filter's state as the
    recording began (:func:`app.toolkit.recorded.recorded_state`'s entry): it goes on
    from it, ``params`` set as a live change (one that does not fit: a cold start)."""
    from app.toolkit.recorded import warm_estimator
    est, warm = warm_estimator(base, params, saved)
    t0 = time.perf_counter()
    res = run_in_chunks(est, rec.t, rec.gyr, rec.acc, rec.mag, rec.ori)   # the loop keeps its turns
    spent = time.perf_counter() - t0
    start = _aligned_from(res.flags)
    out: dict[str, Any] = {
        "rejected": {"acc": rejected_share(res.flags, F_ACC),
                     "mag": rejected_share(res.flags, F_MAG)},
        "seconds_cpu": spent,
        "warm": warm,
    }
    err_series = None
    for key, r in (("error_to_phone_deg", phone_ref), ("error_to_truth_deg", truth)):
        if r is None:
            out[key] = None
            continue
        ok = np.all(np.isfinite(r), axis=1)
        ok[:start] = False
        tot = np.full(len(rec.t), np.nan)
        head = np.full(len(rec.t), np.nan)
        if ok.any():
            a, h, _ = error_angles(res.q[ok], r[ok])
            tot[ok], head[ok] = a, h
        out[key] = {**_stats_deg(tot[ok]), "heading": _stats_deg(head[ok])}
        if (ref_kind == "truth" and key == "error_to_truth_deg") or \
                (ref_kind == "phone" and key == "error_to_phone_deg"):
            err_series = tot
    eul = np.degrees(q2euler_many(res.q[idx]))
    eul[not_estimated(res.q[idx])] = np.nan     # before the alignment: a gap
    out["series"] = {"yaw_deg": _clean(eul[:, 0]), "pitch_deg": _clean(eul[:, 1]),
                     "roll_deg": _clean(eul[:, 2]),
                     "error_deg": None if err_series is None else _clean(np.degrees(err_series[idx]))}
    out["_q"], out["_start"] = res.q, start    # for rerun's comparisons; popped before JSON
    return out, spent


def _phone_entry(phone: np.ndarray | None, truth: np.ndarray | None,
                 idx: np.ndarray) -> dict[str, Any] | None:
    """The phone's own estimate (held ORI) scored like the others, without a run."""
    if phone is None:
        return None
    ok = np.all(np.isfinite(phone), axis=1)
    out: dict[str, Any] = {"rejected": {"acc": None, "mag": None}, "seconds_cpu": 0.0,
                           "error_to_phone_deg": {**_stats_deg(np.zeros(int(ok.sum()))),
                                                  "heading": _stats_deg(np.zeros(int(ok.sum())))},
                           "error_to_truth_deg": None}
    err = None
    if truth is not None:
        both = ok & np.all(np.isfinite(truth), axis=1)
        err = np.full(len(phone), np.nan)
        head = np.full(len(phone), np.nan)
        if both.any():
            a, h, _ = error_angles(phone[both], truth[both])
            err[both], head[both] = a, h
        out["error_to_truth_deg"] = {**_stats_deg(err[both]), "heading": _stats_deg(head[both])}
    q = np.where(ok[:, None], phone, IDENTITY)
    eul = np.degrees(q2euler_many(q[idx]))
    eul[~ok[idx]] = np.nan
    out["series"] = {"yaw_deg": _clean(eul[:, 0]), "pitch_deg": _clean(eul[:, 1]),
                     "roll_deg": _clean(eul[:, 2]),
                     "error_deg": None if err is None else _clean(np.degrees(err[idx]))}
    return out


def _clean(x: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in np.round(x, 4).tolist()]


AGREE_DEG = 0.3     # the re-run "agrees" with the live filter within this (degrees RMS)...
AGREE_REL = 0.15    # ... or this share of the live filter's RMS error, the larger


def _score(q: np.ndarray, start: int, phone: np.ndarray | None,
           truth: np.ndarray | None) -> dict[str, Any]:
    """The errors of estimates ``q`` (one per row) to the phone and to the truth, from row
    ``start`` on, like a re-run's."""
    out: dict[str, Any] = {}
    for key, r in (("error_to_phone_deg", phone), ("error_to_truth_deg", truth)):
        if r is None:
            out[key] = None
            continue
        ok = np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(q), axis=1)
        ok[:start] = False
        out[key] = _stats_deg(error_angles(q[ok], r[ok])[0]) if ok.any() else _stats_deg(np.zeros(0))
    return out


def _key(ref_kind: str | None) -> str | None:
    return {"truth": "error_to_truth_deg", "phone": "error_to_phone_deg"}.get(ref_kind or "")


def _why_differs(before: dict[str, Any], live: dict[str, Any], ref_kind: str | None,
                 q_rerun: np.ndarray, q_live: np.ndarray, start: int,
                 t: np.ndarray) -> str | None:
    """Why the re-run's error (parameters in force now, from a cold start at the
    recording's first row or from the live filter's state then: ``before["warm"]``)
    differs from the live filter's over the same rows, or None when they agree (within
    :data:`AGREE_DEG` or :data:`AGREE_REL`)."""
    key = _key(ref_kind)
    if key is None or before.get(key) is None or live.get(key) is None:
        return None
    b, lv = before[key]["rms"], live[key]["rms"]
    if b is None or lv is None or abs(b - lv) <= max(AGREE_DEG, AGREE_REL * lv):
        return None
    ok = np.all(np.isfinite(q_live), axis=1)
    ok[:start] = False
    d = np.full(len(t), np.nan)
    if ok.any():
        d[ok] = np.degrees(error_angles(q_rerun[ok], q_live[ok])[0])
    t_rel = t - t[0]
    first = ok & (t_rel < t_rel[-1] / 3.0)
    rest = ok & ~first
    rms = (lambda m: float(np.sqrt(np.mean(d[m] ** 2))) if m.any() else float("nan"))
    what = "better" if b < lv else "worse"
    why = ("the re-run goes on from the live filter's state at the recording's first sample, "
           "with the parameters in force now: they were changed since, or during the "
           "recording") if before.get("warm") else \
        ("the re-run starts cold at the recording's first sample (gyroscope bias and field "
         "learned again), the live filter had been running before it")
    return (f"re-run {b:.1f}°, live {lv:.1f}°: {why}; {what} by {abs(b - lv):.1f}°. The two "
            f"estimates differ by {rms(first):.1f}° RMS in the first {t_rel[-1] / 3.0:.0f} s, "
            f"{rms(rest):.1f}° after")


def _notes(ref_kind: str | None, have_live: bool) -> list[str]:
    """What the reported error is, in words (the page shows them beside the numbers)."""
    ref = {"truth": "to the truth (the demo's simulated orientation), as the live read-out's "
                    "\"error to truth\"",
           "phone": "against the phone's own estimate (its ORI), not the truth: a difference, "
                    "not an error. The phone's own is itself often several degrees off "
                    "(docs/accuracy.md), so a change that makes a filter more accurate can show a "
                    "larger difference"}.get(ref_kind or "")
    out = [f"RMS error {ref}, over the whole recording from each filter's alignment on; the "
           "live read-out shows the error at one instant" if ref else
           "no reference in this log (no truth, no ORI): no error can be scored; \"change\" is "
           "how far the change moves each estimate (RMS)"]
    if have_live:
        out.append("live: the error of what the live filters showed during the recording, "
                   "at the rows it kept their estimates for")
    return out


def first_suggestion(specs: dict[str, tuple[str, dict[str, Any]]],
                     primary: str) -> tuple[str, str, Any]:
    """The change a first what-if is pre-filled with: one that shows on any recording
    with a magnetometer (the heading then follows the gyroscope alone and drifts with its
    bias): ``(estimator, parameter, value)``."""
    name = primary if primary in specs else next(
        (n for n, (b, _) in specs.items() if not estimator_class(b).reference), primary)
    params = specs.get(name, ("", {}))[1]
    if params.get("use_mag", True):
        return name, "use_mag", False
    return name, "use_acc", not params.get("use_acc", True)


def rerun(source: str | Path | LogData, specs: dict[str, tuple[str, dict[str, Any]]],
          patch: dict[str, dict[str, Any]] | None = None,
          truth: dict[str, np.ndarray] | None = None,
          max_points: int = MAX_POINTS,
          recorded: dict[str, dict[str, np.ndarray]] | None = None,
          state: dict[str, tuple] | None = None) -> dict[str, Any]:
    """Re-run a recording (a path or a read :class:`LogData`) through every estimator
    of ``specs`` (``{name: (base, params)}``), before and after ``patch``
    (``{name: {key: value}}``); see the module doc for what comes back. ``recorded``:
    the recording's estimates file (:func:`app.toolkit.recorded.read_estimates`), what the
    live filters showed: each estimator's ``live`` error over the same rows beside the re-run's.
    ``state``: the live filters' state as the recording began, per instance
    (:func:`app.toolkit.recorded.recorded_state`): each run, before and after, goes on
    from it.
    WhatIfError for a patch naming an unknown estimator or a refused value (nothing run)."""
    patch = patch or {}
    for name, changes in patch.items():
        if name not in specs:
            raise WhatIfError(f"patch.{name}", f"no estimator named {name!r} "
                                               f"(known: {', '.join(specs)})")
        if not isinstance(changes, dict):
            raise WhatIfError(f"patch.{name}", "expected an object of parameter changes")
    after_params: dict[str, dict[str, Any]] = {}
    for name, (base, params) in specs.items():
        ch = patch.get(name)
        if ch:
            merged = {**params, **ch}
            try:
                make_estimator(base, merged)
            except ParamError as e:
                raise WhatIfError(f"patch.{name}.{e.field}", e.reason) from None
            after_params[name] = merged
    t_read = time.perf_counter()
    rec = source if isinstance(source, LogData) else read_log_data(source)
    read_s = time.perf_counter() - t_read
    n = len(rec)
    phone = hold_ori(rec)
    tq = truth_at(rec.t, truth) if n else None
    ref_kind = "truth" if tq is not None else ("phone" if phone is not None else None)
    idx = _decimate(n, max_points)
    duration = float(rec.t[-1] - rec.t[0]) if n > 1 else 0.0
    results: dict[str, Any] = {}
    cpu = 0.0
    for name, (base, params) in specs.items():
        if estimator_class(base).reference:   # the reference itself: its estimate is the held ORI
            results[name] = {"base": base, "reference": True, "changed": False,
                             "before": _phone_entry(phone, tq, idx), "after": None}
            continue
        if n == 0:
            results[name] = {"base": base, "before": None, "after": None, "changed": False}
            continue
        saved = (state or {}).get(name)
        before, s1 = _one_run(base, params, rec, None, ref_kind, tq, idx, phone, saved)
        cpu += s1
        q_before, start = before.pop("_q"), before.pop("_start")
        entry = {"base": base, "before": before, "changed": name in after_params,
                 "patch": patch.get(name) or {}, "after": None, "change_deg": None,
                 "live": None, "note": None}
        if name in after_params:
            after, s2 = _one_run(base, after_params[name], rec, None, ref_kind, tq, idx, phone,
                                 saved)
            cpu += s2
            q_after, start_a = after.pop("_q"), after.pop("_start")
            entry["after"] = after
            s0 = max(start, start_a)
            entry["change_deg"] = _stats_deg(error_angles(q_before[s0:], q_after[s0:])[0]) \
                if s0 < n else None
        live = live_at(rec.t, (recorded or {}).get(name))
        has = None if live is None else np.isfinite(live).all(axis=1)
        if has is not None and has.any():
            entry["live"] = _score(live, start, phone, tq)
            # the re-run scored on the same rows as the live filter, for the comparison
            same = _score(np.where(has[:, None], q_before, np.nan), start, phone, tq)
            entry["live"]["rerun"] = same      # "before" at those rows: like for like
            entry["note"] = _why_differs({**same, "warm": before["warm"]}, entry["live"],
                                         ref_kind, q_before, live, start, rec.t)
        results[name] = entry
    return {"rows": n, "duration_s": duration, "read_s": read_s, "estimate_s": cpu,
            "realtime_ratio": (duration / cpu) if cpu > 0 else None,
            "reference": ref_kind, "has_phone": phone is not None, "has_truth": tq is not None,
            "notes": _notes(ref_kind, recorded is not None and any(
                e.get("live") for e in results.values())),
            "t": _clean(rec.t[idx] - (rec.t[0] if n else 0.0)) if n else [],
            "estimators": results, "counts": _json_counts(rec.counts)}


def with_recorded_magcal(rec: LogData, events: list[dict[str, Any]]) -> LogData:
    """``rec`` with its field corrected by the magnetometer calibration in force while it
    was recorded (its events; the log holds the raw field, the live filters got it
    corrected), or ``rec`` itself when none was. The copy's ``counts["magcal"]`` says how
    many calibrations were applied."""
    from dataclasses import replace
    from app.toolkit.magcal import correct_rows
    from app.toolkit.recorded import magcal_changes
    changes = magcal_changes(events)
    used = sum(1 for _, table in changes if table)
    if not used or not len(rec):
        return rec
    return replace(rec, mag=correct_rows(rec.t, rec.mag, changes),
                   counts={**rec.counts, "magcal": used})


def _json_counts(c: dict) -> dict:
    out = {}
    for k, v in c.items():
        if isinstance(v, dict):
            out[k] = _json_counts(v)
        elif isinstance(v, (int, str, bool)) or v is None:
            out[k] = v
        elif isinstance(v, float):
            out[k] = v if math.isfinite(v) else None
        elif isinstance(v, (list, tuple)):
            out[k] = [x for x in v if isinstance(x, (int, float, str))]
    return out


class WhatIfService:
    """What-if on the live server: re-run a recording of the folder through every
    estimator on the ensemble, with the parameters in force before and ``patch`` after, in
    a worker thread (the live stream goes on meanwhile): one re-run at a time, two more
    waiting, more refused with 429 (:attr:`jobs`, :class:`app.toolkit.jobs.JobQueue`).

    ``core``: the live core (its ensemble's instances); ``files(name)``: a recording's
    files (ToolError if none)."""

    def __init__(self, core, files: Callable[[str], dict]):
        self.core = core
        self.files = files
        self.last: dict[str, Any] | None = None
        self._cache: dict = {}                  # touched by the one running job only
        self.jobs = JobQueue("what-if re-run")

    def specs(self) -> dict[str, tuple[str, dict[str, Any]]]:
        b = self.core.ensemble
        return {n: (b.base_of(n), to_dict(b.params_of(n))) for n in b.names}

    async def rerun(self, name: str, patch: dict[str, Any] | None) -> dict[str, Any]:
        from app.toolkit.recorded import (cut_short, event, file_size, read_estimates, read_events,
                                          recorded_state, warm_note, warm_start_s)
        files = self.files(name)
        if patch is not None and not isinstance(patch, dict):
            raise ToolError("patch", "must be an object {estimator: {param: value}}")
        specs = self.specs()

        def run():   # in the job's thread: reading the files too (never on the loop)
            recorded = None    # what the live filters showed (and the demo's truth)
            said = []
            if files["estimates"] is not None:
                cut_est: list[str] = []                    # (may be in progress)
                recorded = read_estimates(files["estimates"], warn=False, said=cut_est)
                said += [f"the live column covers what the estimates file holds: {w}" for w in cut_est]
            events = read_events(files.get("events"))
            cut = cut_short(file_size(files["log"]), event(events, "end", last=True))
            if cut:
                said.append(cut)
            rec = with_recorded_magcal(self._read_cached(files["log"]), events)
            state, why = recorded_state(files, events)
            out = rerun(rec, specs, patch, (recorded or {}).get("truth"), recorded=recorded,
                        state=state)
            if rec.counts.get("magcal"):
                out["notes"].append("the magnetometer calibration in force while recording "
                                    "is applied to the log's raw field, as it was live")
            warm = warm_note(warm_start_s(events), any(
                (e.get("before") or {}).get("warm") for e in out["estimators"].values()), why)
            if warm:
                out["notes"].append(warm)
            out["notes"] += said
            return out
        try:
            out = await self.jobs.run(run)
        except ToolError:        # busy (429), a file that is no log: as it is
            raise
        except WhatIfError as e:
            raise ToolError(e.field, e.reason) from None
        except ValueError as e:  # a file's other refusal (its events, its estimates)
            raise ToolError("name", str(e)) from None
        out["name"] = name
        self.last = out
        return out

    def _read_cached(self, path: Path) -> LogData:
        """The recording at ``path``, parsed once: a what-if is re-run again and again
        with new parameters (reading a 10-minute log costs more than re-running it).
        Keyed on the file's size and time, so a rewritten file is read again; two kept."""
        st = path.stat()
        key = (str(path), st.st_size, st.st_mtime_ns)
        cache = self._cache
        if key in cache:
            cache[key] = cache.pop(key)
            return cache[key]
        from app.toolkit.recorded import read_recording_log
        rec = read_recording_log(path)       # ToolError for a file that is no log
        cache[key] = rec
        while len(cache) > 2:
            cache.pop(next(iter(cache)))
        return rec
