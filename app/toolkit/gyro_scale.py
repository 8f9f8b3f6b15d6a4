"""The gyroscope's scale factor from recordings with rests (``orientlab gyro-scale``).

A gyroscope whose scale factor is off by ``s`` reads (1 + s) × the turn: a phone's is off by
0.2-3 % (``benchmarks/gyro_scale.py``), so a whole turn integrates to 1-11° too far or too
short. The magnetometer hides it while the field is good; with the field refused (a magnet, a
steel desk, the magnetometer switched off) the heading drifts by that share of every turn.

**How it is measured.** While the phone lies still its specific force is gravity, so its tilt
is known to a few hundredths of a degree. Between two rests the gyroscope, its bias (the mean
over the recording's rests) removed, is integrated from the first rest's tilt; the tilt it
arrives with at the next rest, against that rest's gravity, is the span's error. In the world
frame it is

    δ = Σ_i s_i ∫ R[:, i] ω_i dt  +  Σ_i e_i ∫ R[:, i] dt

(``R`` the attitude, ``ω_i`` the rate about sensor axis i, ``e`` the bias error). Its two
horizontal components are fitted by least squares over every span of every recording: a bias
error per recording (three) and one scale error per sensor axis (the phone). No magnetometer is
needed: the heading the integration starts from turns the error and its regressors alike.

**What the recording needs.** Only a *net* rotation shows a scale error: a turn and back
cancels. And the tilt sees an axis's scale only while that axis is horizontal. So: lay the
phone still (2 s), turn it whole turns in one direction about one of its axes while that axis
is level (flip it end over end for x, roll it over its long edge for y, stand it on its long
edge and turn it like a wheel for z), lay it still again; repeat for each axis, in both
directions. A recording needs at least three rests: with two, its bias error takes up the one
span. An axis whose σ stays above ``MEASURED_STD`` is reported as not measured and left out of
the preset.

Rests are found with the thresholds of robust's rest detection, VQF's (``restThGyr`` 2 °/s,
``restThAcc`` 0.5 m/s², ``restMinT`` 1.5 s): blocks of ``REST_BLOCK_S`` whose gyroscope and
accelerometer stay that close to their block means (RMS: a phone's noise is not a movement)
and whose gravity direction stays within ``REST_TILT`` of the run's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from app import quaternion as qm
from app.estimators.robust.params import RobustParams
from app.params import GRAVITY
from app.params import dump_toml, fields_of
from app.toolkit.errors import ToolError
from app.toolkit.jobs import JobQueue

# a rest as robust's rest detection takes it (VQF's thresholds): one definition, its defaults
_REST = RobustParams()
REST_GYR = _REST.rest_gyr_th      # rad/s: VQF restThGyr 2 °/s
REST_ACC = _REST.rest_acc_th      # m/s²: VQF restThAcc
REST_MIN_S = _REST.rest_time      # s: VQF restMinT
REST_BLOCK_S = 0.25               # s: the blocks a rest is made of
REST_TILT = math.radians(0.5)     # rad: gravity's direction within a rest
REST_NORM = 1.5                   # m/s²: | |a| - g | at rest (an accelerometer's own scale error)
MEASURED_STD = 0.002              # an axis's scale is measured when its σ is below 0.2 %
MAX_SCALE = 0.1                   # |s| above 10 %: not a scale factor (no rest, a bad recording)
AXES = "xyz"


@dataclass
class Recording:
    """One recording's rows (as :class:`app.sources.readers.LogData`: NaN where a sensor has no
    sample in a row), and its name for the report."""
    name: str
    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray


@dataclass
class GyroScaleFit:
    """The fit: per sensor axis the scale error (the gyroscope reads (1 + s) × the turn), its σ
    and whether it is measured (σ below ``MEASURED_STD``); the spans and rests it used, the
    spans' RMS tilt error (degrees) before and after, and what a user should know."""
    scale: np.ndarray
    std: np.ndarray
    measured: np.ndarray
    spans: int
    rests: dict[str, int]
    rms_before_deg: float
    rms_after_deg: float
    warnings: list[str] = field(default_factory=list)

    def preset_scale(self) -> tuple[float, float, float]:
        """The measured axes' scale errors, 0 for the others."""
        return tuple(float(s) if m else 0.0 for s, m in zip(self.scale, self.measured))


def _gyro_rows(rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    ok = np.all(np.isfinite(rec.gyr), axis=1)
    return rec.t[ok], rec.gyr[ok]


def _block_stats(block: np.ndarray, v: np.ndarray, nb: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per block: the mean (nb, 3), the RMS of |v - mean| and the count of ``v``'s rows."""
    n = np.bincount(block, minlength=nb).astype(float)
    d = np.maximum(n, 1.0)
    mean = np.stack([np.bincount(block, v[:, i], minlength=nb) for i in range(3)], axis=1) / d[:, None]
    sq = np.bincount(block, np.sum(v * v, axis=1), minlength=nb) / d
    return mean, np.sqrt(np.maximum(sq - np.sum(mean * mean, axis=1), 0.0)), n


def find_rests(rec: Recording) -> list[tuple[float, float]]:
    """The recording's rests as (start, end) times (s): runs of still blocks at least
    ``REST_MIN_S`` long (see the module doc)."""
    tg, g = _gyro_rows(rec)
    ok_a = np.all(np.isfinite(rec.acc), axis=1)
    ta, a = rec.t[ok_a], rec.acc[ok_a]
    if len(tg) < 2 or len(ta) < 2:
        return []
    t0, t1 = min(tg[0], ta[0]), max(tg[-1], ta[-1])
    nb = int((t1 - t0) // REST_BLOCK_S)
    if nb < 1:
        return []
    bg = np.minimum(((tg - t0) // REST_BLOCK_S).astype(int), nb - 1)
    ba = np.minimum(((ta - t0) // REST_BLOCK_S).astype(int), nb - 1)
    mg, dev_g, ng = _block_stats(bg, g, nb)
    ma, dev_a, na = _block_stats(ba, a, nb)
    norm = np.linalg.norm(ma, axis=1)
    with np.errstate(invalid="ignore"):
        still = ((ng >= 2) & (na >= 2) & (dev_g < REST_GYR) & (dev_a < REST_ACC)
                 & (np.abs(norm - GRAVITY) < REST_NORM))
    up = ma / np.maximum(norm, 1e-9)[:, None]
    rests, b = [], 0
    while b < nb:
        if not still[b]:
            b += 1
            continue
        e, ref = b + 1, up[b]
        while e < nb and still[e] and float(np.dot(up[e], ref)) > math.cos(REST_TILT):
            e += 1
        if (e - b) * REST_BLOCK_S >= REST_MIN_S:
            rests.append((t0 + b * REST_BLOCK_S, t0 + e * REST_BLOCK_S))
        b = e
    return rests


def _mean_in(t: np.ndarray, v: np.ndarray, span: tuple[float, float]) -> np.ndarray:
    ok = (t >= span[0]) & (t < span[1]) & np.all(np.isfinite(v), axis=1)
    return v[ok].mean(axis=0)


def span_evidence(rec: Recording, rests: list[tuple[float, float]],
                  scale=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Per span between two consecutive rests: the horizontal tilt error (2,) in rad (the
    integration over-turned by δ gives +δ) and its regressors (2, 6): the world-frame integrals
    of a unit bias error about each sensor axis, then of a unit scale error of each. The rate
    integrated is the gyroscope's, its bias removed, divided by 1 + ``scale``."""
    tg, g = _gyro_rows(rec)
    bias = np.mean([_mean_in(tg, g, r) for r in rests], axis=0)
    gain = 1.0 / (1.0 + np.asarray(scale, dtype=float))
    errs, regs = [], []
    for (_, end0), (start1, end1) in zip(rests[:-1], rests[1:]):
        up0 = _mean_in(rec.t, rec.acc, (end0 - REST_MIN_S, end0))
        up1 = _mean_in(rec.t, rec.acc, (start1, end1))
        q0 = qm.normalize(np.asarray(qm.q_from_acc_mag(up0, up0, False), dtype=float))
        sel = np.flatnonzero((tg > end0) & (tg <= start1))
        if len(sel) < 2:
            continue
        t_prev = np.concatenate([[tg[max(sel[0] - 1, 0)]], tg[sel[:-1]]])
        dt = tg[sel] - t_prev
        w = (g[sel] - bias) * gain
        qs = qm.integrate_many(q0, w * dt[:, None])
        R = qm.Q_many(np.vstack([q0, qs[:-1]]))         # the attitude each sample's turn starts from
        x = np.concatenate([R * dt[:, None, None], R * (w * dt[:, None])[:, None, :]], axis=2).sum(axis=0)
        u = qm.Q(qs[-1]) @ (up1 / np.linalg.norm(up1))  # gravity through the integrated attitude
        errs.append([-u[1], u[0]])                     # δ × z = (δy, -δx, 0)
        regs.append(x[:2])
    return np.array(errs).reshape(-1, 2), np.array(regs).reshape(-1, 2, 6)


@dataclass
class Evidence:
    """One recording's part of the fit: its rests, and per span its tilt error and regressors
    (:func:`span_evidence`; empty with fewer than three rests, and a warning why)."""
    name: str
    rests: int
    errors: np.ndarray
    regressors: np.ndarray
    warning: str | None = None


def evidence(rec: Recording, scale=(0.0, 0.0, 0.0)) -> Evidence:
    """What ``rec`` gives the fit, its gyroscope divided by 1 + ``scale``."""
    r = find_rests(rec)
    if len(r) < 3:
        return Evidence(rec.name, len(r), np.zeros((0, 2)), np.zeros((0, 2, 6)),
                        f"{rec.name}: {len(r)} rest{'s' if len(r) != 1 else ''}, not used (it needs three: "
                        "with two, the recording's bias error takes up their one span)")
    e, x = span_evidence(rec, r, scale)
    return Evidence(rec.name, len(r), e, x)


def fit(recordings: list[Recording], max_iter: int = 5) -> GyroScaleFit:
    """The scale errors from ``recordings`` of one phone (see the module doc). Raises
    :class:`ToolError` when the recordings cannot give them.

    The error is linear in the scale only while it is small: two turns 2 % off leave the
    integration 14° out, and the regressors are integrated along that wrong attitude. So the
    fit is repeated with the gyroscope divided by 1 + the scale found, until what is left
    changes it by less than 10⁻⁵ (Gauss-Newton)."""
    for i, a in enumerate(recordings):     # the same samples twice would halve the σ
        for b in recordings[:i]:
            if a.t.shape == b.t.shape and np.array_equal(a.t, b.t) \
                    and np.array_equal(a.gyr, b.gyr, equal_nan=True):
                raise ToolError("recordings", f"{b.name} and {a.name} hold the same samples: "
                                "give each recording once")
    scale = np.zeros(3)
    first = None
    for _ in range(max_iter):
        f = solve([evidence(rec, scale) for rec in recordings])
        if first is None:
            first = f
        step = (1.0 + scale) * (1.0 + f.scale) - 1.0 - scale
        scale = scale + step
        if np.max(np.abs(step)) < 1e-5:
            break
    f.scale = scale
    f.rms_before_deg = first.rms_before_deg
    measured = f.measured
    if np.any(np.abs(scale[measured]) > MAX_SCALE):
        raise ToolError("recordings", f"a scale error of {np.max(np.abs(scale[measured])) * 100:.0f} % is no "
                        "gyroscope's: check that the phone lay still between the turns")
    return f


def solve(parts: list[Evidence]) -> GyroScaleFit:
    """One least-squares pass over ``parts`` (one per recording): a bias error per recording, a
    scale error per axis (of the gyroscope as the parts integrated it). Raises
    :class:`ToolError` when they cannot give it."""
    warnings = [p.warning for p in parts if p.warning]
    used = [p for p in parts if len(p.errors)]
    if not used:
        raise ToolError("recordings", "no recording has three rests: lay the phone still for 2 s between "
                        "the turns (" + "; ".join(warnings) + ")")
    nrec = len(used)
    ncol = 3 * nrec + 3
    rows, ys = [], []
    for k, p in enumerate(used):
        a = np.zeros((len(p.errors), 2, ncol))
        a[:, :, 3 * k:3 * k + 3] = p.regressors[:, :, :3]
        a[:, :, 3 * nrec:] = p.regressors[:, :, 3:]
        rows.append(a.reshape(-1, ncol))
        ys.append(p.errors.reshape(-1))
    A, y = np.concatenate(rows), np.concatenate(ys)
    spans = len(y) // 2
    dof = len(y) - ncol
    if dof < 1:
        raise ToolError("recordings", f"{spans} spans between rests give {len(y)} equations for {ncol} "
                        "unknowns: record more turns, each between two rests")
    c, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ c
    cov = float(r @ r) / dof * np.linalg.pinv(A.T @ A)
    # the integrated rate is (1 + s) × the turn, so it over-turns by s / (1 + s) of itself: the
    # fitted coefficient c is that share, s = c / (1 - c)
    c_s = c[3 * nrec:]
    scale = c_s / (1.0 - c_s)
    std = np.sqrt(np.maximum(np.diag(cov)[3 * nrec:], 0.0)) / (1.0 - c_s) ** 2
    measured = std < MEASURED_STD
    for i in np.flatnonzero(~measured):
        warnings.append(f"axis {AXES[i]}: σ {std[i] * 100:.2f} % (not measured, left at 0): turn the phone "
                        f"whole turns about its {AXES[i]} axis while that axis is level")
    rms = lambda v: float(np.sqrt(np.mean(v ** 2)) * 180.0 / math.pi)  # noqa: E731
    return GyroScaleFit(scale=scale, std=std, measured=measured, spans=spans,
                        rests={p.name: p.rests for p in parts}, rms_before_deg=rms(y), rms_after_deg=rms(r),
                        warnings=warnings)


def format_report(f: GyroScaleFit) -> str:
    """The fit as text, one line per axis."""
    lines = ["gyroscope scale factor (it reads (1 + s) × the turn)",
             f"  {f.spans} spans between rests, in {len(f.rests)} recording(s):"]
    lines += [f"    {n}: {k} rests" for n, k in f.rests.items()]
    lines += [f"  tilt error at the rests: {f.rms_before_deg:.3f}° RMS, {f.rms_after_deg:.3f}° with the "
             "scale and bias errors fitted"]
    for i, a in enumerate(AXES):
        tag = "" if f.measured[i] else "   (not measured)"
        lines.append(f"  {a}: s = {f.scale[i] * 100:+.3f} % ± {f.std[i] * 100:.3f} %{tag}")
    lines += [f"  warning: {w}" for w in f.warnings]
    return "\n".join(lines) + "\n"


def to_preset(f: GyroScaleFit) -> str:
    """A TOML preset (for ``--config``) setting ``gyr_scale`` of the estimators that have it; the
    report is kept above as comments."""
    from app.estimators import NAMES, estimator_class

    out = {est: {"gyr_scale": list(f.preset_scale())} for est in NAMES
           if "gyr_scale" in fields_of(estimator_class(est).Params)}
    header = "orientlab preset from recordings with rests (orientlab gyro-scale)\n\n" + format_report(f).rstrip("\n")
    return dump_toml(out, header=header)


def to_json(f: GyroScaleFit) -> dict[str, Any]:
    """The fit as plain JSON (the page and the API), with the report's text."""
    return {"scale": [float(v) for v in f.scale], "std": [float(v) for v in f.std],
            "measured": [bool(v) for v in f.measured], "preset_scale": list(f.preset_scale()),
            "spans": f.spans, "rests": dict(f.rests), "rms_before_deg": f.rms_before_deg,
            "rms_after_deg": f.rms_after_deg, "warnings": list(f.warnings), "report": format_report(f)}


class GyroScaleService:
    """``orientlab gyro-scale`` on the live server: the fit over recordings of the lab's folder
    (a heavy job: one at a time, a few waiting, more refused), and what "apply" sets.

    ``core``: the live core; ``files(name)``: a recording's files (ToolError if none)."""

    def __init__(self, core, files: Callable[..., dict]):
        self.core = core
        self.files = files
        self.last: dict[str, Any] | None = None
        self.jobs = JobQueue("gyroscope scale fit")

    async def fit_job(self, names: list[str]) -> dict[str, Any]:
        """:meth:`fit_recordings` off the event loop."""
        return await self.jobs.run(lambda: self.fit_recordings(names))

    def fit_recordings(self, names: list[str]) -> dict[str, Any]:
        from app.toolkit.recorded import read_recording_log
        recs = []
        for name in names:
            rec = read_recording_log(self.files(name, "recordings")["log"], "recordings")
            recs.append(Recording(name, rec.t, rec.gyr, rec.acc))
        out = to_json(fit(recs))
        out["recordings"] = list(names)
        self.last = out
        return out

    def change(self) -> dict[str, dict[str, Any]]:
        """What "apply" sets: ``gyr_scale`` of every estimator on the ensemble that has it."""
        if self.last is None:
            raise ToolError("gyro_scale", "no fit yet: POST /api/gyro-scale first", 409)
        if not any(self.last["measured"]):
            raise ToolError("gyro_scale", "no axis was measured: " + "; ".join(self.last["warnings"]), 409)
        ens = self.core.ensemble
        out = {name: {"gyr_scale": self.last["preset_scale"]} for name in ens.names
               if hasattr(ens.params_of(name), "gyr_scale")}
        if not out:
            raise ToolError("gyro_scale", "no estimator on the page has gyr_scale (robust, lab)", 409)
        return out
