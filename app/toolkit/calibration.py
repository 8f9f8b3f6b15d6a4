"""Statistics of a stationary recording (lab manual, exercise 2) and the preset they give.

Lay the phone still (any pose), record a few seconds, then :func:`calibrate` gives per
sensor the mean, full covariance, standard deviations, a normality test per axis
(D'Agostino-Pearson K², in numpy), the trend (drift per minute from a linear fit) and a
histogram per axis. From them it derives

- ``g0``: the gravity vector in world coordinates, ``(0, 0, |mean acc|)``;
- the gyroscope bias: the mean gyroscope reading;
- ``m0``: the nominal field of formula (7), ``(0, sqrt(mx²+my²), mz)``, computed *after
  levelling* the mean field with the accelerometer (the rotation that takes the mean
  acc to +z), so the phone need not lie flat.

A recording that does not look stationary (gyroscope or accelerometer spread too large,
turning, |acc| far from 9.81, a field that changed) gets warnings. :func:`format_report` renders the result as
text; :func:`to_preset` writes it as a TOML preset for ``--config`` (tables ``[lab]``
and ``[robust]``, the statistics as comments).
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from app import quaternion as qm
from app.params import GRAVITY, dump_toml
from app.toolkit.capture import Capture, check_seconds, check_streaming
from app.toolkit.errors import ToolError
from app.toolkit.jobs import JobQueue

# sensor -> (unit, unit of its covariance)
UNITS = {"acc": ("m/s²", "(m/s²)²"), "gyr": ("rad/s", "(rad/s)²"), "mag": ("µT", "µT²")}
TITLES = {"acc": "accelerometer", "gyr": "gyroscope", "mag": "magnetometer"}
AXES = "xyz"
CAL_MIN_S, CAL_MAX_S = 1.0, 600.0     # a live calibration's seconds


@dataclass(frozen=True)
class StationaryLimits:
    """Above these, a recording is not taken for stationary (a warning, not an error)."""
    gyr_std: float = 0.05       # rad/s, per axis (~2.9 deg/s)
    gyr_mean: float = 0.2       # rad/s, |mean rate| (slow steady turning)
    acc_std: float = 0.5        # m/s², per axis
    acc_norm_tol: float = 1.5   # m/s², | |mean acc| - 9.81 |
    # µT, per axis: a phone magnetometer's noise is 0.2-2 µT; more is a field that changed
    # (a magnet, a laptop, steel moved near the phone), whose mean and spread would mislead
    mag_std: float = 5.0
    min_samples: int = 20       # fewer samples: statistics unreliable


@dataclass
class SensorStats:
    """Statistics of one sensor over the rows where it has a finite sample."""
    name: str
    unit: str
    n: int
    mean: np.ndarray            # (3,)
    cov: np.ndarray             # (3, 3), ddof = 1
    std: np.ndarray             # (3,)
    skew: np.ndarray            # (3,)
    kurtosis: np.ndarray        # (3,) excess kurtosis
    normal_k2: np.ndarray       # (3,) D'Agostino-Pearson K²
    normal_p: np.ndarray        # (3,) its p-value (χ², 2 dof)
    trend_per_min: np.ndarray   # (3,) slope of a linear fit, unit per minute
    hist_counts: list           # per axis, counts (int array)
    hist_edges: list            # per axis, bin edges

    @property
    def normal(self) -> np.ndarray:
        """Per axis, True where normality is not rejected at the 5 % level."""
        return self.normal_p >= 0.05


@dataclass
class CalibrationStats:
    """Everything :func:`calibrate` found (SI units)."""
    n_rows: int
    duration: float                           # s
    sensors: dict[str, SensorStats]
    g0: np.ndarray | None = None              # (3,) world, m/s²
    gyr_bias: np.ndarray | None = None        # (3,) rad/s
    m0: np.ndarray | None = None              # (3,) world, µT
    tilt_deg: float | None = None             # angle of the pose from lying flat
    warnings: list[str] = field(default_factory=list)

    @property
    def stationary(self) -> bool:
        return not self.warnings


# ---------------------------------------------------------------- tests and moments

def normality_test(x: np.ndarray) -> tuple[float, float, float, float]:
    """D'Agostino-Pearson omnibus test of one sample (as ``scipy.stats.normaltest``):
    ``(K², p, skewness, excess kurtosis)``. NaN for fewer than 8 values or no spread."""
    x = np.asarray(x, dtype=float)
    n = x.size
    d = x - x.mean() if n else x
    m2 = float(np.mean(d * d)) if n else 0.0
    if n < 8 or m2 <= 0.0 or not math.isfinite(m2):
        return math.nan, math.nan, math.nan, math.nan
    g1 = float(np.mean(d ** 3)) / m2 ** 1.5
    b2 = float(np.mean(d ** 4)) / m2 ** 2
    # skewness test (D'Agostino 1970)
    y = g1 * math.sqrt((n + 1) * (n + 3) / (6.0 * (n - 2)))
    beta2 = (3.0 * (n * n + 27 * n - 70) * (n + 1) * (n + 3)
             / ((n - 2.0) * (n + 5) * (n + 7) * (n + 9)))
    w2 = -1.0 + math.sqrt(2.0 * (beta2 - 1.0))
    delta = 1.0 / math.sqrt(0.5 * math.log(w2))
    alpha = math.sqrt(2.0 / (w2 - 1.0))
    y = y if y != 0.0 else 1.0
    z_s = delta * math.log(y / alpha + math.sqrt((y / alpha) ** 2 + 1.0))
    # kurtosis test (Anscombe & Glynn 1983)
    e = 3.0 * (n - 1) / (n + 1)
    var_b2 = 24.0 * n * (n - 2) * (n - 3) / ((n + 1) ** 2 * (n + 3) * (n + 5))
    xk = (b2 - e) / math.sqrt(var_b2)
    sqrt_beta1 = (6.0 * (n * n - 5 * n + 2) / ((n + 7) * (n + 9))
                  * math.sqrt(6.0 * (n + 3) * (n + 5) / (n * (n - 2) * (n - 3))))
    a = 6.0 + 8.0 / sqrt_beta1 * (2.0 / sqrt_beta1 + math.sqrt(1.0 + 4.0 / sqrt_beta1 ** 2))
    denom = 1.0 + xk * math.sqrt(2.0 / (a - 4.0))
    if denom == 0.0:
        return math.nan, math.nan, g1, b2 - 3.0
    term2 = math.copysign(abs((1.0 - 2.0 / a) / abs(denom)) ** (1.0 / 3.0), denom)
    z_k = (1.0 - 2.0 / (9.0 * a) - term2) / math.sqrt(2.0 / (9.0 * a))
    k2 = z_s * z_s + z_k * z_k
    return k2, math.exp(-0.5 * k2), g1, b2 - 3.0


def _hist_bins(n: int) -> int:
    return int(min(50, max(10, round(math.sqrt(max(n, 1))))))


def sensor_stats(name: str, t: np.ndarray, x: np.ndarray) -> SensorStats | None:
    """Statistics of sensor ``name`` over the rows of ``x`` (N, 3) that are all finite;
    None when fewer than two such rows."""
    ok = np.all(np.isfinite(x), axis=1) & np.isfinite(t)
    v, tt = x[ok], t[ok]
    n = int(v.shape[0])
    if n < 2:
        return None
    mean = v.mean(axis=0)
    cov = np.cov(v, rowvar=False, ddof=1)
    tests = [normality_test(v[:, i]) for i in range(3)]
    tm = (tt - tt.mean()) / 60.0
    denom = float(np.dot(tm, tm))
    trend = (tm @ (v - mean)) / denom if denom > 0 else np.zeros(3)
    bins = _hist_bins(n)
    hists = [np.histogram(v[:, i], bins=bins) for i in range(3)]
    return SensorStats(name=name, unit=UNITS[name][0], n=n, mean=mean, cov=cov,
                       std=np.sqrt(np.diag(cov)),
                       skew=np.array([r[2] for r in tests]),
                       kurtosis=np.array([r[3] for r in tests]),
                       normal_k2=np.array([r[0] for r in tests]),
                       normal_p=np.array([r[1] for r in tests]),
                       trend_per_min=np.asarray(trend, dtype=float),
                       hist_counts=[h[0] for h in hists], hist_edges=[h[1] for h in hists])


def level_field(acc_mean: np.ndarray, mag_mean: np.ndarray) -> np.ndarray:
    """Formula (7) after levelling: rotate the mean field by the tilt that maps the mean
    specific force to +z, then ``m0 = (0, sqrt(mx²+my²), mz)`` (µT, world)."""
    q = qm.q_from_acc_mag(np.asarray(acc_mean, float), np.zeros(3), False)
    m = qm.Q(q) @ np.asarray(mag_mean, float)   # heading arbitrary, vertical exact
    return qm.field_reference(m)


def calibrate(t, gyr=None, acc=None, mag=None,
              limits: StationaryLimits = StationaryLimits()) -> CalibrationStats:
    """Statistics of a stationary recording: arrays ``t`` (N,) s and (N, 3) per sensor
    (NaN rows: no sample). A :class:`app.sources.readers.LogData` can be passed as
    ``calibrate(rec.t, rec.gyr, rec.acc, rec.mag)``."""
    t = np.asarray(t, dtype=float)
    n = t.shape[0]
    sensors: dict[str, SensorStats] = {}
    for name, x in (("acc", acc), ("gyr", gyr), ("mag", mag)):
        if x is None:
            continue
        s = sensor_stats(name, t, np.asarray(x, dtype=float).reshape(n, 3))
        if s is not None:
            sensors[name] = s
    finite_t = t[np.isfinite(t)]
    duration = float(finite_t.max() - finite_t.min()) if finite_t.size else 0.0
    out = CalibrationStats(n_rows=n, duration=duration, sensors=sensors)
    a, g, m = sensors.get("acc"), sensors.get("gyr"), sensors.get("mag")
    if a is not None:
        norm = float(np.linalg.norm(a.mean))
        out.g0 = np.array([0.0, 0.0, norm])
        out.tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, a.mean[2] / norm))))
        if m is not None:
            out.m0 = level_field(a.mean, m.mean)
    if g is not None:
        out.gyr_bias = g.mean.copy()
    out.warnings = _stationarity_warnings(out, limits)
    # a short movement in a long still recording hides in the whole recording's spread (a
    # phone slid across the table for 2 s of 60), but not in the spread of its own second
    for name, x, lim, unit, what in (("acc", acc, limits.acc_std, "m/s²", "accelerometer"),
                                     ("gyr", gyr, limits.gyr_std, "rad/s", "gyroscope"),
                                     ("mag", mag, limits.mag_std, "µT", "magnetometer")):
        if x is None or name not in sensors or np.max(sensors[name].std) > lim:
            continue        # none, or the whole recording's spread already says it
        worst = _worst_second(t, np.asarray(x, dtype=float).reshape(n, 3))
        if worst is not None and worst[1] > lim:
            why = "the field changed" if name == "mag" else "the phone moved"
            out.warnings.append(f"{what} spread {worst[1]:.3g} {unit} > {lim:g} in the second from "
                                f"{worst[0]:.0f} s of the recording: {why}")
    return out


def _worst_second(t: np.ndarray, x: np.ndarray, window: float = 1.0):
    """``(start, spread)`` of the window of ``window`` s (end to end from the first sample;
    ``start`` in s from it) whose largest per-axis standard deviation is largest; None with
    too few samples."""
    ok = np.all(np.isfinite(x), axis=1) & np.isfinite(t)
    t, x = t[ok], x[ok]
    if t.size < 8:
        return None
    o = np.argsort(t, kind="stable")
    t, x = t[o], x[o]
    k = np.floor((t - t[0]) / window).astype(np.int64)
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])     # each window's first row
    n = np.diff(np.r_[starts, t.size])[:, None]
    s1 = np.add.reduceat(x, starts, axis=0)
    s2 = np.add.reduceat(x * x, starts, axis=0)
    sd = np.sqrt(np.maximum(s2 - s1 * s1 / n, 0.0) / np.maximum(n - 1, 1)).max(axis=1)
    sd[n[:, 0] < 8] = -1.0                                     # too few samples to judge
    i = int(np.argmax(sd))
    if sd[i] < 0.0:
        return None
    return float(k[starts[i]] * window), float(sd[i])


def _stationarity_warnings(st: CalibrationStats, lim: StationaryLimits) -> list[str]:
    w = []
    if not st.sensors:
        w.append("no accelerometer, gyroscope or magnetometer samples")
    for s in st.sensors.values():
        if s.n < lim.min_samples:
            w.append(f"{TITLES[s.name]}: only {s.n} samples, statistics unreliable")
    g, a = st.sensors.get("gyr"), st.sensors.get("acc")
    if g is not None:
        if np.max(g.std) > lim.gyr_std:
            w.append(f"gyroscope spread {np.max(g.std):.3g} rad/s > {lim.gyr_std:g}: "
                     "the phone moved")
        if np.linalg.norm(g.mean) > lim.gyr_mean:
            w.append(f"gyroscope mean |{np.linalg.norm(g.mean):.3g}| rad/s > {lim.gyr_mean:g}: "
                     "the phone was turning")
    if a is not None:
        if np.max(a.std) > lim.acc_std:
            w.append(f"accelerometer spread {np.max(a.std):.3g} m/s² > {lim.acc_std:g}: "
                     "the phone moved")
        norm = float(np.linalg.norm(a.mean))
        if abs(norm - GRAVITY) > lim.acc_norm_tol:
            w.append(f"|mean acc| = {norm:.3g} m/s², far from {GRAVITY}: "
                     "accelerating or miscalibrated")
    m = st.sensors.get("mag")
    if m is not None and np.max(m.std) > lim.mag_std:
        w.append(f"magnetometer spread {np.max(m.std):.3g} µT > {lim.mag_std:g}: the field "
                 "changed (a magnet, a laptop or steel moved near the phone)")
    return w


# ---------------------------------------------------------------- report

_BARS = " ▁▂▃▄▅▆▇█"


def _spark(counts: np.ndarray) -> str:
    top = max(int(np.max(counts)), 1)
    return "".join(_BARS[int(round(c / top * (len(_BARS) - 1)))] for c in counts)


def _row(label: str, values, fmt: str = "{:>12.5g}") -> str:
    return f"  {label:<16}" + "".join(fmt.format(v) for v in values)


def format_report(st: CalibrationStats) -> str:
    """A readable text report: one table per sensor (units given), the derived values
    and any warning."""
    lines = [f"{'Stationary recording' if st.stationary else 'Recording (NOT stationary: see the warnings)'}: "
             f"{st.n_rows} rows over {st.duration:.2f} s"]
    for name in ("acc", "gyr", "mag"):
        s = st.sensors.get(name)
        lines.append("")
        if s is None:
            lines.append(f"{TITLES[name]}: no samples")
            continue
        unit, cunit = UNITS[name]
        rate = (s.n - 1) / st.duration if st.duration > 0 else math.nan
        lines.append(f"{TITLES[name]} ({unit}): {s.n} samples, ~{rate:.0f} Hz")
        lines.append(f"  {'':<16}" + "".join(f"{a:>12}" for a in AXES))
        lines.append(_row(f"mean [{unit}]", s.mean))
        lines.append(_row(f"std [{unit}]", s.std))
        lines.append(_row(f"trend [{unit}/min]", s.trend_per_min))
        lines.append(_row("skewness", s.skew))
        lines.append(_row("excess kurtosis", s.kurtosis))
        lines.append(_row("normality p", s.normal_p))
        lines.append(f"  {'normal (5 %)':<16}" + "".join(
            f"{('n/a' if math.isnan(p) else ('yes' if p >= 0.05 else 'no')):>12}"
            for p in s.normal_p))
        lines.append(f"  covariance [{cunit}]:")
        for r in s.cov:
            lines.append("  " + " " * 16 + "".join(f"{v:>12.4g}" for v in r))
        lines.append(f"  histograms ({len(s.hist_counts[0])} bins, min..max):")
        for i, a in enumerate(AXES):
            e = s.hist_edges[i]
            lines.append(f"    {a}  {e[0]:>10.5g} |{_spark(s.hist_counts[i])}| {e[-1]:<10.5g}")
    lines.append("")
    lines.append("derived:")
    if st.g0 is not None:
        lines.append(f"  g0        = [{', '.join(f'{v:.5g}' for v in st.g0)}] m/s² "
                     f"(|mean acc|; pose tilted {st.tilt_deg:.1f}° from lying flat)")
    if st.gyr_bias is not None:
        lines.append(f"  gyr_bias  = [{', '.join(f'{v:.4g}' for v in st.gyr_bias)}] rad/s "
                     f"({', '.join(f'{math.degrees(v):.3g}' for v in st.gyr_bias)} deg/s)")
    if st.m0 is not None:
        lines.append(f"  m0        = [{', '.join(f'{v:.4g}' for v in st.m0)}] µT "
                     f"(|m0| = {np.linalg.norm(st.m0):.4g} µT, "
                     f"dip {math.degrees(math.atan2(-st.m0[2], st.m0[1])):.1f}°)")
    lines.append("")
    if st.warnings:
        lines.append("WARNING: this recording does not look stationary:")
        lines.extend(f"  - {w}" for w in st.warnings)
    else:
        lines.append("stationary: yes")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- preset

def _clamped(params_cls, key: str, value):
    """``value`` fitted into the range of ``params_cls.key`` (None if no such key)."""
    fmap = {f.name: f for f in dataclasses.fields(params_cls)}
    if key not in fmap:
        return None
    meta = fmap[key].metadata
    lo, hi = meta.get("lo"), meta.get("hi")

    def fit(v: float) -> float:
        v = float(v)
        if lo is not None:
            v = max(lo, v)
        if hi is not None:
            v = min(hi, v)
        return v
    if isinstance(value, (list, tuple, np.ndarray)):
        return [fit(v) for v in np.asarray(value, dtype=float).reshape(-1)]
    return fit(value)


def _positive_definite(c: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(c)) and np.all(np.linalg.eigvalsh(0.5 * (c + c.T)) > 0))


def preset_values(st: CalibrationStats) -> dict[str, dict]:
    """The parameters a preset gets from the statistics: ``{"lab": {...}, "robust": {...}}``
    (only keys the estimators' parameter sets have; values fitted into their ranges)."""
    from app.estimators import estimator_class

    wanted: dict[str, object] = {}
    for name in ("gyr", "acc", "mag"):
        s = st.sensors.get(name)
        if s is None:
            continue
        wanted[f"{name}_std"] = float(np.sqrt(np.mean(np.diag(s.cov))))
        cov = 0.5 * (s.cov + s.cov.T)
        if _positive_definite(cov):
            wanted[f"{name}_cov"] = cov.reshape(-1)
    if st.gyr_bias is not None:
        wanted["gyr_bias"] = st.gyr_bias
    if st.g0 is not None:
        wanted["g0"] = st.g0
    if st.m0 is not None:
        wanted["m0"] = st.m0
    out: dict[str, dict] = {}
    for est, keys in (("lab", list(wanted)), ("robust", ["gyr_bias"])):
        try:
            cls = estimator_class(est).Params
        except ImportError:  # that estimator is not installed
            continue
        sec = {}
        for k in keys:
            if k in wanted:
                v = _clamped(cls, k, wanted[k])
                if v is not None:
                    sec[k] = v
        out[est] = sec
    return out


def to_preset(st: CalibrationStats) -> str:
    """A TOML preset (for ``--config``) with ``[lab]`` and ``[robust]`` tables; the
    report is kept above them as comments."""
    header = ("orientlab preset from a stationary recording (orientlab calibrate)\n\n"
              + format_report(st).rstrip("\n"))
    return dump_toml(preset_values(st), header=header)


# ---------------------------------------------------------------- JSON (the page and the API)

def _jnum(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _jlist(a) -> list:
    return [_jlist(v) if isinstance(v, (list, np.ndarray)) and np.ndim(v) > 0 else _jnum(v)
            for v in (a.tolist() if isinstance(a, np.ndarray) else a)]


def sensor_json(s: SensorStats) -> dict:
    """One sensor's statistics as plain JSON (NaN as null), with per axis the histogram
    and the Gaussian of the same mean and σ scaled to the counts (``fit``: expected
    count per bin, ``n · width · N(centre; mean, σ²)``)."""
    hist = []
    for i, a in enumerate(AXES):
        e = np.asarray(s.hist_edges[i], dtype=float)
        c = np.asarray(s.hist_counts[i], dtype=float)
        centres = 0.5 * (e[:-1] + e[1:])
        width = float(e[1] - e[0]) if e.size > 1 else 0.0
        sd = float(s.std[i])
        if sd > 0 and math.isfinite(sd):
            fit = s.n * width * np.exp(-0.5 * ((centres - s.mean[i]) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))
        else:
            fit = np.full_like(centres, np.nan)
        hist.append({"axis": a, "edges": _jlist(e), "centres": _jlist(centres),
                     "counts": [int(v) for v in c], "fit": _jlist(fit)})
    return {"name": s.name, "title": TITLES[s.name], "unit": s.unit, "n": s.n,
            "mean": _jlist(s.mean), "cov": _jlist(s.cov), "std": _jlist(s.std),
            "skew": _jlist(s.skew), "kurtosis": _jlist(s.kurtosis),
            "normality": {"k2": _jlist(s.normal_k2), "p": _jlist(s.normal_p),
                          "normal_5pct": [bool(p >= 0.05) if math.isfinite(p) else None
                                          for p in s.normal_p.tolist()]},
            "drift_per_min": _jlist(s.trend_per_min), "histograms": hist}


def to_json(st: CalibrationStats, t=None, series: dict | None = None,
            max_points: int = 500) -> dict:
    """Everything :func:`calibrate` found, as JSON for ``POST /api/calibrate`` and the
    page: per sensor :func:`sensor_json`, the derived ``g0``, ``gyr_bias``, ``m0``, the
    warnings, the preset values (``apply``: what one click sets) and, given the samples
    (``t`` and ``series = {"acc": (N, 3), ...}``), decimated time plots."""
    out = {"n_rows": st.n_rows, "duration_s": _jnum(st.duration), "stationary": st.stationary,
           "warnings": list(st.warnings),
           "sensors": {k: sensor_json(v) for k, v in st.sensors.items()},
           "g0": None if st.g0 is None else _jlist(st.g0),
           "gyr_bias": None if st.gyr_bias is None else _jlist(st.gyr_bias),
           "m0": None if st.m0 is None else _jlist(st.m0),
           "tilt_deg": None if st.tilt_deg is None else _jnum(st.tilt_deg),
           "apply": {k: {p: (_jlist(v) if isinstance(v, (list, np.ndarray)) else _jnum(v))
                         for p, v in sec.items()} for k, sec in preset_values(st).items()},
           "report": format_report(st)}
    if t is not None and series:
        t = np.asarray(t, dtype=float)
        plots = {}
        for name, x in series.items():
            x = np.asarray(x, dtype=float).reshape(-1, 3)
            ok = np.all(np.isfinite(x), axis=1) & np.isfinite(t)
            tt, xx = t[ok], x[ok]
            if tt.size == 0:
                continue
            idx = np.linspace(0, tt.size - 1, min(tt.size, max_points)).astype(np.int64)
            plots[name] = {"t": _jlist(tt[idx] - tt[0]), "x": _jlist(xx[idx, 0]),
                           "y": _jlist(xx[idx, 1]), "z": _jlist(xx[idx, 2])}
        out["series"] = plots
    return out


BIAS_ESTIMATORS = ("lab",)        # lab does not estimate the gyroscope's bias: it is given one
BIAS_MIN_S, BIAS_MAX_S = 0.5, 20.0   # "Calibrate gyro bias": the rest window's seconds
BIAS_STILL_DEG_S = 1.0            # an axis's σ above this over the window: the phone moved


def rest_bias(core, seconds: Any) -> np.ndarray:
    """The mean gyroscope rate (rad/s) over the last ``seconds`` of the stream on show, in
    which the phone lay still: the bias "Calibrate gyro bias" gives lab. ToolError naming
    why not: the seconds out of range (422); no stream, too few samples, or the phone moved
    (409)."""
    seconds = check_seconds(seconds, BIAS_MIN_S, BIAS_MAX_S)
    check_streaming(core)
    g = core.history.gyr.window(seconds, 100_000)
    ok = np.all(np.isfinite(g.data), axis=1)
    t, w = g["t"][ok], g["w"][ok]
    if t.shape[0] < 10 or t[-1] - t[0] < 0.5 * seconds:
        raise ToolError("seconds", f"not enough gyroscope samples in the last {seconds:g} s", 409)
    sd = float(np.degrees(w.std(axis=0)).max())
    if sd > BIAS_STILL_DEG_S:
        raise ToolError("seconds", f"the phone moved during the last {seconds:g} s (σ {sd:.2f} "
                        "deg/s on one axis): let it lie still and try again", 409)
    return w.mean(axis=0)


def bias_change(core, bias: np.ndarray) -> dict[str, dict[str, Any]]:
    """The parameters that give ``bias`` to the estimators that take one, variants too (a
    bias is the phone's, not a filter's: lab-approx compares its time update with lab's,
    not another bias), to validate as ``{"estimators": ...}``; ToolError (409) when none
    of them is running."""
    sch = core.ensemble.schema        # one snapshot of the instances (a change may be pending)
    names = [n for n in sch.names if sch.base_of(n) in BIAS_ESTIMATORS]
    if not names:
        raise ToolError("estimators", f"none of {', '.join(BIAS_ESTIMATORS)} is running: no "
                        "estimator takes a gyroscope bias", 409)
    return {n: {"gyr_bias": [float(x) for x in bias]} for n in names}


class CalibrationService:
    """Exercise 2 on the live server: the statistics of the next ``seconds`` of the
    stream (the phone kept still; collected by a record listener of the live core) or
    of a stretch of a recording, and what "apply" sets.

    ``core``: the live core; ``files(name)``: a recording's files (ToolError if none)."""

    def __init__(self, core, files: Callable[..., dict]):
        self.core = core
        self.files = files
        self.capture: Capture | None = None
        self.last: dict[str, Any] | None = None       # the last result (JSON)
        self.last_stats: CalibrationStats | None = None
        self.applied: dict[str, Any] | None = None    # the last result applied
        self.jobs = JobQueue("calibration of a recording")   # heavy: one at a time
        core.record_listeners.append(self.on_records)

    def on_records(self, session, rec) -> None:
        cap = self.capture
        if cap is not None and cap.running and len(rec):
            if cap.add(rec.t, rec.kind, rec.values):
                self._finish(cap)

    async def calibrate(self, seconds: float) -> dict[str, Any]:
        """Statistics of the next ``seconds`` of the live stream (keep the phone still)."""
        seconds = check_seconds(seconds, CAL_MIN_S, CAL_MAX_S)
        if self.capture is not None and self.capture.running:
            raise ToolError("seconds", "a calibration is already running", 409)
        check_streaming(self.core)
        cap = Capture("still", seconds)
        cap.done = asyncio.get_running_loop().create_future()
        self.capture = cap
        await cap.done
        return cap.result

    def _finish(self, cap: Capture) -> None:
        if cap.note is not None:          # stopped at a cap: a clock not to be trusted?
            why = cap.clock_untrusted()
            if why is not None:
                cap.fail(why)
                return
        t, g, a, m = cap.arrays()
        try:
            st = calibrate(t, g, a, m)
            if not st.sensors:
                raise ValueError("no accelerometer, gyroscope or magnetometer samples")
            result = to_json(st, t, {"acc": a, "gyr": g, "mag": m})
        except Exception as e:
            cap.fail(str(e))
            return
        result["note"] = cap.note
        self.last, self.last_stats = result, st
        cap.succeed(result)

    def tick(self) -> None:
        """Called a few times a second: end a capture past its wall-time cap (a stream
        that stopped, or a phone clock that does not advance)."""
        cap = self.capture
        if cap is not None and cap.check_stalled() and cap.running:
            self._finish(cap)

    async def calibrate_recording_job(self, name: str, from_s: float = 0.0,
                                      to_s: float | None = None) -> dict[str, Any]:
        """:meth:`calibrate_recording` as a heavy job (:attr:`jobs`: one at a time, a
        few waiting, more refused with 429), off the event loop."""
        return await self.jobs.run(lambda: self.calibrate_recording(name, from_s, to_s))

    def calibrate_recording(self, name: str, from_s: float = 0.0,
                            to_s: float | None = None) -> dict[str, Any]:
        """The statistics of a stretch of a recording (seconds from its start)."""
        from app.toolkit.recorded import read_recording_log
        rec = read_recording_log(self.files(name, "recording")["log"], "recording")
        if not len(rec):
            raise ToolError("name", "the recording has no samples")
        t = rec.t - rec.t[0]
        hi = t[-1] if to_s is None else float(to_s)
        sel = (t >= float(from_s)) & (t <= hi)
        if sel.sum() < 2:
            raise ToolError("from_s", "the stretch holds fewer than 2 samples")
        st = calibrate(rec.t[sel], rec.gyr[sel], rec.acc[sel], rec.mag[sel])
        out = to_json(st, rec.t[sel], {"acc": rec.acc[sel], "gyr": rec.gyr[sel],
                                       "mag": rec.mag[sel]})
        self.last, self.last_stats = out, st
        return out

    def change(self, force: bool = False) -> dict[str, dict[str, Any]]:
        """What "apply" sets: per estimator on the ensemble, variants too, the values of
        its kind (to validate as ``{"estimators": ...}``). A calibration that does not look
        stationary (the phone moved, too few samples...) is refused (409, the reasons in
        words) unless ``force``: the presenter's explicit "apply anyway"."""
        if self.last is None:
            raise ToolError("calibration", "no calibration yet: POST /api/calibrate first", 409)
        if not force:
            why = refusal(self.last)
            if why is not None:
                raise ToolError("calibration", why, 409)
        # every instance of each kind, variants too: a calibration is the phone's
        apply, sch = self.last["apply"], self.core.ensemble.schema   # one snapshot (any thread)
        return {n: apply[sch.base_of(n)] for n in sch.names if apply.get(sch.base_of(n))}

    def note_applied(self) -> None:
        """The last calibration was applied (its report heads a preset saved next)."""
        self.applied = self.last

    def preset_header(self) -> str:
        """The comment of a preset saved after a calibration was applied (its report)."""
        header = "orientlab preset from a calibration on the page"
        if self.applied is not None:
            header += "\n\n" + self.applied["report"].rstrip("\n")
        return header


def refusal(result: dict[str, Any]) -> str | None:
    """Why a calibration (its JSON) is not applied without "apply anyway": None when it
    looks stationary."""
    if result.get("stationary", True):
        return None
    return ("not applied: not stationary, its bias and noise would mislead the filters "
            "(calibrate again with the phone still, or apply anyway: force): "
            + "; ".join(result["warnings"]))
