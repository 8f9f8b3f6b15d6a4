"""Magnetometer calibration: hard and soft iron from the phone turned in all directions.

A magnetometer on a phone reads ``m_raw = A m + b``: ``b`` (µT) is the *hard-iron*
offset (magnetised parts of the phone, moving with it) and ``A`` the *soft-iron*
distortion (iron that bends the field, plus unequal axis gains). Turned in every
direction in a uniform field, the true ``m`` sweeps a sphere of radius |m|, so the raw
readings lie on an ellipsoid. :func:`fit` fits that ellipsoid to the readings
(algebraic least squares, numpy only) and returns the correction

    m = W (m_raw - b)

with ``W`` symmetric positive definite, scaled so the corrected field keeps the
measured strength (the geometric mean of the ellipsoid's radii, µT). Too few directions
covered for a full ellipsoid: a sphere (hard iron only, ``W = I``) is fitted instead and
``model`` says so. A fit that would mislead is refused with its reason
(:class:`MagCalRefused`): degenerate readings (one point: the phone lay still; a line or
a plane: turned about one axis only), too little coverage for the model, a residual
that does not improve, a field outside 10-200 µT. :func:`coverage` measures how much of the sphere of directions the
readings cover (the share of 32 evenly spread directions with at least 3 readings near
them), the number the page shows while the phone is being turned. The residual is the
spread of |m| around the field strength before and after the correction (µT RMS).

Where it is applied: the live server corrects every MAG sample before the estimators see
it (:func:`correct_values`); a preset keeps it as ``[magcal]`` ``offset_uT`` and
``matrix`` (row-major 3x3).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.toolkit.capture import MAX_ROWS, Capture, check_seconds, check_streaming
from app.toolkit.errors import ToolError

log = logging.getLogger("orientlab.magcal")

N_DIRECTIONS = 32
MIN_PER_DIRECTION = 3
MIN_SAMPLES = 30
# The coverage each model needs, from the geometry. (The measure counts a direction once
# 3 readings fall nearest to it, so a cap of a share f of the sphere reads about
# f + 0.15: the cells along its rim count too; a hemisphere reads 0.6-0.7.)
# - a sphere (4 unknowns: the offset and the radius) is pinned by a cap of directions
#   whose sag is a good part of the radius: a cap of half-angle 60° (a quarter of the
#   sphere, reading 0.35-0.45) sags R/2, so the offset along the cap's axis is known to
#   about twice the noise; a smaller cap lets the noise slide the offset freely.
# - an ellipsoid (9 unknowns: also a gain per axis and their cross terms) must tell an
#   axis's gain from the offset along it, which takes readings at both ends of every
#   axis: more than a hemisphere (a hemisphere leaves one end of its axis unseen).
MIN_COVERAGE_SPHERE = 0.35
MIN_COVERAGE_ELLIPSOID = 0.7
# Degenerate readings (no fit says anything about the phone):
MIN_SPREAD_UT = 3.0        # a point: the readings' largest spread (σ, µT) below this:
                           # the phone lay still (turning it 20° in a 25 µT field already
                           # moves the reading ~5 µT)
MIN_FLATNESS = 0.2         # a line or a plane: the smallest spread below 0.2 of the
                           # largest (a cap of a quarter of the sphere gives 0.3; a circle,
                           # turned about one axis, gives the noise)
MIN_IMPROVEMENT = 0.9      # the residual after must be below 90 % of the one before:
                           # a fit that changes nothing has nothing to correct
FIELD_MIN_UT, FIELD_MAX_UT = 10.0, 200.0   # a plausible fitted field: the Earth's is
                           # 25-65 µT; indoors steel bends it, not beyond these


class MagCalError(ValueError):
    pass


class MagCalRefused(MagCalError):
    """A fit refused as misleading (``reason`` in words); ``cal``: the fit computed, if
    one was (shown, never applicable)."""

    def __init__(self, reason: str, cal: "MagCalibration | None" = None):
        super().__init__(reason)
        self.reason = reason
        self.cal = cal


@dataclass(frozen=True)
class MagCalibration:
    offset: np.ndarray          # (3,) µT, hard iron
    matrix: np.ndarray          # (3, 3) soft iron correction W
    field_uT: float             # strength of the corrected field
    model: str                  # "ellipsoid", "sphere" or "identity"
    n: int = 0
    coverage: float = 0.0
    residual_before_uT: float = math.nan
    residual_after_uT: float = math.nan

    def apply(self, m: np.ndarray) -> np.ndarray:
        """Corrected readings (N, 3) or (3,)."""
        m = np.asarray(m, dtype=float)
        return (m - self.offset) @ self.matrix.T

    def as_dict(self) -> dict[str, Any]:
        def num(x):
            return float(x) if math.isfinite(float(x)) else None
        return {"offset_uT": [float(v) for v in self.offset],
                "matrix": [[float(v) for v in r] for r in self.matrix],
                "field_uT": num(self.field_uT), "model": self.model, "n": self.n,
                "coverage": num(self.coverage),
                "residual_before_uT": num(self.residual_before_uT),
                "residual_after_uT": num(self.residual_after_uT)}

    def preset(self) -> dict[str, Any]:
        """The ``[magcal]`` table of a preset."""
        return {"offset_uT": [float(v) for v in self.offset],
                "matrix": [float(v) for v in self.matrix.reshape(-1)]}


IDENTITY = MagCalibration(offset=np.zeros(3), matrix=np.eye(3), field_uT=math.nan,
                          model="identity")


def from_preset(table: dict[str, Any]) -> MagCalibration:
    """A calibration from a preset's ``[magcal]`` table; MagCalError says what is wrong."""
    if not isinstance(table, dict):
        raise MagCalError("[magcal] must be a table")
    unknown = set(table) - {"offset_uT", "matrix"}
    if unknown:
        raise MagCalError(f"[magcal] unknown key {sorted(unknown)[0]!r} (known: offset_uT, matrix)")
    try:
        b = np.asarray(table.get("offset_uT", [0, 0, 0]), dtype=float).reshape(3)
        W = np.asarray(table.get("matrix", np.eye(3).reshape(-1).tolist()), dtype=float).reshape(3, 3)
    except (TypeError, ValueError):
        raise MagCalError("[magcal] offset_uT has 3 numbers and matrix 9 (row-major)") from None
    if not (np.all(np.isfinite(b)) and np.all(np.isfinite(W))):
        raise MagCalError("[magcal] values must be finite")
    if np.max(np.abs(b)) > 5000:
        raise MagCalError("[magcal] offset_uT beyond ±5000 µT")
    Ws = 0.5 * (W + W.T)
    ev = np.linalg.eigvalsh(Ws)
    if np.max(np.abs(W - W.T)) > 1e-6 * max(1.0, np.max(np.abs(W))) or ev.min() <= 0.05 or ev.max() > 20:
        raise MagCalError("[magcal] matrix must be symmetric positive definite with gains in (0.05, 20]")
    return MagCalibration(offset=b, matrix=Ws, field_uT=math.nan, model="preset")


def _directions(n: int = N_DIRECTIONS) -> np.ndarray:
    """``n`` nearly evenly spread unit vectors (Fibonacci sphere)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


_DIRS = _directions()


def _finite_rows(m: np.ndarray) -> np.ndarray:
    m = np.asarray(m, dtype=float).reshape(-1, 3)
    return m[np.all(np.isfinite(m), axis=1)]


def coverage(m: np.ndarray, center: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Share of :data:`N_DIRECTIONS` directions (around ``center``, default the middle
    of the readings' range) with at least :data:`MIN_PER_DIRECTION` readings nearest to
    them, and the count per direction."""
    m = _finite_rows(m)
    if m.shape[0] == 0:
        return 0.0, np.zeros(N_DIRECTIONS, dtype=int)
    c = 0.5 * (m.min(axis=0) + m.max(axis=0)) if center is None else np.asarray(center, float)
    d = m - c
    nrm = np.linalg.norm(d, axis=1)
    ok = nrm > 1e-9
    u = d[ok] / nrm[ok, None]
    idx = np.argmax(u @ _DIRS.T, axis=1)
    counts = np.bincount(idx, minlength=N_DIRECTIONS)
    return float(np.mean(counts >= MIN_PER_DIRECTION)), counts


def _residual(m: np.ndarray, radius: float | None = None) -> float:
    r = np.linalg.norm(m, axis=1)
    ref = float(np.mean(r)) if radius is None else radius
    return float(np.sqrt(np.mean((r - ref) ** 2)))


def _fit_sphere(m: np.ndarray) -> tuple[np.ndarray, float]:
    # |x|² = 2 b·x + (R² - |b|²): linear in (b, c)
    A = np.hstack([2.0 * m, np.ones((m.shape[0], 1))])
    y = np.sum(m * m, axis=1)
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    b = sol[:3]
    r2 = sol[3] + b @ b
    if not r2 > 0:
        raise MagCalError("the readings do not fit a sphere")
    return b, math.sqrt(r2)


def _fit_ellipsoid(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Center b and symmetric W with |W (x - b)| ≈ R for the readings, R the geometric
    mean radius. MagCalError when the quadric is not an ellipsoid."""
    s = np.max(np.abs(m - m.mean(axis=0)))
    mu = m.mean(axis=0)
    x, y, z = ((m - mu) / s).T          # centred and scaled: well-conditioned
    # a x² + b y² + c z² + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z = 1
    D = np.stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z], axis=1)
    sol, *_ = np.linalg.lstsq(D, np.ones(m.shape[0]), rcond=None)
    a, b_, c, f, g, h, p, q, r = sol
    M = np.array([[a, h, g], [h, b_, f], [g, f, c]])
    n = np.array([p, q, r])
    try:
        ctr = -np.linalg.solve(M, n)
    except np.linalg.LinAlgError:
        raise MagCalError("the readings do not determine an ellipsoid") from None
    k = 1.0 + ctr @ M @ ctr
    Mn = M / k
    ev, V = np.linalg.eigh(0.5 * (Mn + Mn.T))
    if not np.all(ev > 0):
        raise MagCalError("the fitted surface is not an ellipsoid (turn the phone in more directions)")
    radii = 1.0 / np.sqrt(ev)                     # in the scaled units
    R = float(np.prod(radii) ** (1.0 / 3.0))
    W = (V * (np.sqrt(ev) * R)) @ V.T             # R * sqrtm(Mn): maps the ellipsoid to radius R
    return mu + ctr * s, W, R * s


def degenerate(m: np.ndarray) -> str | None:
    """Why readings ``m`` (N, 3, finite) cannot be fitted at all, in words: a point (the
    phone lay still), a line or a plane (turned about one axis only); None if they
    spread in three dimensions. From the principal spreads (σ along the principal axes)."""
    sd = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(m, rowvar=False)), 0.0))[::-1]
    if not sd[0] >= MIN_SPREAD_UT:
        return (f"the readings are one point (spread {sd[0]:.2g} µT < {MIN_SPREAD_UT:g}): "
                "the phone lay still; turn it slowly in all directions")
    if sd[1] < MIN_FLATNESS * sd[0]:
        return (f"the readings lie on a line (spreads {sd[0]:.1f}, {sd[1]:.2g}, {sd[2]:.2g} µT): "
                "the field changed in one direction only; turn the phone in all directions")
    if sd[2] < MIN_FLATNESS * sd[0]:
        return (f"the readings lie in a plane (spreads {sd[0]:.1f}, {sd[1]:.1f}, {sd[2]:.2g} µT): "
                "the phone was turned about one axis only; turn it about the others too")
    return None


def refusal(cal: MagCalibration) -> str | None:
    """Why a computed fit would mislead, in words (None: applicable): too little
    coverage for its model, an implausible field, a residual that does not improve
    (every reason that applies, joined by "; ")."""
    why = []
    need = MIN_COVERAGE_ELLIPSOID if cal.model == "ellipsoid" else MIN_COVERAGE_SPHERE
    if not cal.coverage >= need:
        why.append(f"coverage {100 * cal.coverage:.0f} % of directions is too low for the "
                   f"{cal.model} model (at least {100 * need:.0f} %): turn the phone in more "
                   "directions")
    if not math.isfinite(cal.field_uT) or not FIELD_MIN_UT <= cal.field_uT <= FIELD_MAX_UT:
        why.append(f"the fitted field {cal.field_uT:.3g} µT is implausible (the Earth's is "
                   f"25-65 µT; accepted {FIELD_MIN_UT:g}-{FIELD_MAX_UT:g} µT): a magnet or "
                   "steel nearby?")
    if not cal.residual_after_uT < MIN_IMPROVEMENT * cal.residual_before_uT:
        worse = cal.residual_after_uT > cal.residual_before_uT
        why.append(f"the residual does not improve ({cal.residual_before_uT:.2f} -> "
                   f"{cal.residual_after_uT:.2f} µT): the correction would "
                   + ("make the field worse" if worse else "change nothing worth applying"))
    return "; ".join(why) or None


def fit(m: np.ndarray, model: str = "auto", check: bool = True) -> MagCalibration:
    """Fit the correction to readings ``m`` (N, 3) µT (NaN rows ignored). ``model``:
    ``"auto"`` (ellipsoid if the coverage allows, else sphere), ``"ellipsoid"`` or
    ``"sphere"``. MagCalError when there are too few readings or no fit;
    MagCalRefused (``check``) when the readings are degenerate (:func:`degenerate`) or
    the fit would mislead (:func:`refusal`; the fit in ``.cal``)."""
    m = _finite_rows(m)
    if m.shape[0] < MIN_SAMPLES:
        raise MagCalError(f"only {m.shape[0]} magnetometer readings (at least {MIN_SAMPLES} needed)")
    if model not in ("auto", "ellipsoid", "sphere"):
        raise MagCalError(f"model must be auto, ellipsoid or sphere, got {model!r}")
    if check:
        why = degenerate(m)
        if why is not None:
            raise MagCalRefused(why)
    b_s, R_s = _fit_sphere(m)
    cov, _ = coverage(m, b_s)
    if model == "ellipsoid" or (model == "auto" and cov >= MIN_COVERAGE_ELLIPSOID):
        try:
            b, W, R = _fit_ellipsoid(m)
            kind = "ellipsoid"
        except MagCalError:
            if model == "ellipsoid":
                raise
            b, W, R, kind = b_s, np.eye(3), R_s, "sphere"
    else:
        b, W, R, kind = b_s, np.eye(3), R_s, "sphere"
    cal = MagCalibration(offset=b, matrix=W, field_uT=R, model=kind, n=int(m.shape[0]),
                         coverage=coverage(m, b)[0])
    before = _residual(m)
    after = _residual(cal.apply(m), R)
    cal = MagCalibration(offset=b, matrix=W, field_uT=R, model=kind, n=cal.n,
                         coverage=cal.coverage, residual_before_uT=before,
                         residual_after_uT=after)
    if check:
        why = refusal(cal)
        if why is not None:
            raise MagCalRefused(why, cal)
    return cal


def correct_values(cal: MagCalibration, values: tuple) -> tuple:
    """A MAG line's values corrected (3 floats)."""
    v = cal.matrix @ (np.asarray(values[:3], dtype=float) - cal.offset)
    return tuple(float(x) for x in v) + tuple(values[3:])


def correct_samples(cal: MagCalibration | None, samples: list) -> list:
    """MAG samples with the correction applied (others unchanged). Identity or None: the
    samples themselves."""
    if cal is None or cal.model == "identity":
        return samples
    from app.sources.samples import Sample
    return [Sample(s.time_ms, "MAG", correct_values(cal, s.values)) if s.tag == "MAG" else s
            for s in samples]


def uncorrect_samples(cal: MagCalibration | None, samples: list) -> list:
    """:func:`correct_samples` undone: the raw field of corrected MAG samples."""
    if cal is None or cal.model == "identity":
        return samples
    from app.sources.samples import Sample
    inv = np.linalg.inv(cal.matrix)

    def raw(values):
        v = inv @ np.asarray(values[:3], dtype=float) + cal.offset
        return tuple(float(x) for x in v) + tuple(values[3:])
    return [Sample(s.time_ms, "MAG", raw(s.values)) if s.tag == "MAG" else s for s in samples]


def correct_rows(t: np.ndarray, mag: np.ndarray,
                 changes: list[tuple[float | None, dict | None]]) -> np.ndarray:
    """Rows of raw field (N, 3) corrected by the calibration in force at each row's time
    ``t`` (s): ``changes`` is ``[(after t or None: from the start, [magcal] table or
    None)]`` in order (:func:`app.toolkit.recorded.magcal_changes`); a calibration takes
    the rows later than its ``t``. Rows under none stay as they are; NaN rows stay NaN."""
    out = np.array(mag, dtype=float, copy=True)
    t = np.asarray(t, dtype=float)
    for k, (t0, table) in enumerate(changes):
        if not table:
            continue
        t1 = changes[k + 1][0] if k + 1 < len(changes) else None
        sel = np.ones(len(t), dtype=bool) if t0 is None else (t > t0)
        if t1 is not None:
            sel &= t <= t1
        if sel.any():
            out[sel] = from_preset(table).apply(np.asarray(mag, dtype=float)[sel])   # the raw rows
    return out


MAGCAL_MIN_S, MAGCAL_MAX_S = 5.0, 300.0   # a live collection's seconds


class MagCalService:
    """The magnetometer calibration on the live server: collect the raw field while the
    phone is turned (a sample stage of the live core, before the correction), fit it,
    and correct every MAG sample with the calibration in force (the same stage).

    ``core``: the live core; ``preset``: a preset's ``[magcal]`` table (applied at once).
    :meth:`on_change` follows a preset loaded later, :meth:`preset_part` gives the table
    for a saved preset; :attr:`listeners` are called when one is applied or cleared."""

    def __init__(self, core, preset: dict[str, Any] | None = None):
        self.core = core
        self.applied: MagCalibration | None = None
        if preset:
            try:
                self.applied = from_preset(preset)
            except MagCalError as e:
                log.warning("preset: %s", e)
        self.capture: Capture | None = None
        self.result: MagCalibration | None = None
        self.refused: MagCalRefused | None = None   # the last fit refused, and why
        self.listeners: list = []
        self._raw = np.empty((0, 3))                 # MAX_ROWS rows at most
        # where the calibration in force took over: the stage runs as samples arrive,
        # before the reorder buffer, so a change applies from the next MAG sample to
        # arrive, not from the time the filters have reached (record_part)
        self._session = None
        self._last_mag_ms: int | None = None         # the newest MAG sample through here
        self._since_ms: int | None = None            # the calibration's first MAG is after it
        core.sample_stages.append(self.stage)

    def uncorrect(self, samples: list) -> list:
        """Samples this stage has corrected, as they came to it (the raw field)."""
        return uncorrect_samples(self.applied, samples)

    def stage(self, session, samples: list) -> list:
        """The sample stage: the raw field collected, then the correction applied."""
        if session is not self._session:             # a new stream: a new clock
            self._session, self._last_mag_ms, self._since_ms = session, None, None
        if self.capture is not None and self.capture.running:
            self._collect(samples)
        if self.applied is not None:
            samples = correct_samples(self.applied, samples)
        for x in samples:
            if x.tag == "MAG" and (self._last_mag_ms is None or x.time_ms > self._last_mag_ms):
                self._last_mag_ms = x.time_ms
        return samples

    def _changed(self) -> None:
        self._since_ms = self._last_mag_ms

    def _collect(self, samples: list) -> None:
        """The MAG samples' readings kept (at most :data:`MAX_ROWS`); the fit once the
        phone's clock has the seconds, or at a cap (samples or wall time: a frozen
        clock never gets there)."""
        cap = self.capture
        mag = [s for s in samples if s.tag == "MAG"]
        if mag:
            cap.last_wall = time.monotonic()
            if cap.t0 is None:
                cap.t0 = mag[0].time_ms / 1000.0
            end = cap.t0 + cap.seconds
            keep = [s for s in mag if s.time_ms / 1000.0 <= end][:MAX_ROWS - cap.rows]
            if keep:
                cap.t_last = keep[-1].time_ms / 1000.0
                self._raw[cap.rows:cap.rows + len(keep)] = [s.values[:3] for s in keep]
                cap.rows += len(keep)
            if len(keep) < len(mag) and cap.rows < MAX_ROWS:   # past its seconds
                cap.t_last = max(cap.t_last or end, end)
        if cap.elapsed >= cap.seconds or cap.capped() is not None:
            self._finish(cap)

    def _finish(self, cap: Capture) -> None:
        if cap.note is not None:
            why = cap.clock_untrusted()
            if why is not None:
                cap.end(error=why)
                return
        try:
            self.result = fit(self._raw[:cap.rows])
            cap.end(result=self.result.as_dict())
        except MagCalRefused as e:
            self.refused = e
            cap.end(error="fit refused: " + e.reason)
        except MagCalError as e:
            cap.end(error=str(e))

    def on_change(self, ch) -> None:
        """A preset loaded (page or API; the engine's change listener): its magnetometer
        calibration, or none."""
        if not getattr(ch, "magcal_set", False):
            return
        try:
            self.applied = from_preset(ch.magcal) if ch.magcal else None
        except MagCalError as e:    # load_config validated it: not expected
            log.error("preset's [magcal] not applied: %s", e)
        self._changed()

    def preset_part(self) -> dict[str, Any]:
        return {} if self.applied is None else {"magcal": self.applied.preset()}

    def record_part(self) -> dict[str, Any]:
        """What a recording notes beside :meth:`preset_part` at a change: the stream time
        (s) of the last MAG sample corrected the old way, ``magcal_from_t`` (None: no MAG
        yet in this stream, every one is corrected the new way). A re-run corrects the
        log's raw field by the calibration in force after it
        (:func:`app.toolkit.recorded.magcal_changes`)."""
        ms = self._since_ms
        return {"magcal_from_t": None if ms is None else ms / 1000.0}

    def tick(self) -> None:
        """Called a few times a second: end a collection past its wall-time cap (a
        stream that stopped, or a phone clock that does not advance)."""
        cap = self.capture
        if cap is not None and cap.check_stalled() and cap.running:
            self._finish(cap)

    def start(self, seconds: float) -> dict[str, Any]:
        seconds = check_seconds(seconds, MAGCAL_MIN_S, MAGCAL_MAX_S)
        check_streaming(self.core)
        self._raw = np.empty((MAX_ROWS, 3))
        self.result = None
        self.refused = None
        self.capture = Capture("magcal", seconds)
        return self.status()

    def status(self) -> dict[str, Any]:
        cap = self.capture
        out: dict[str, Any] = {"applied": None if self.applied is None else self.applied.as_dict()}
        if cap is None:
            return {**out, "capture": None, "result": None, "refused": None}
        m = self._raw[:cap.rows]
        cov, counts = coverage(m) if len(m) else (0.0, [0] * N_DIRECTIONS)
        out["capture"] = {**cap.status(), "coverage": cov, "per_direction": [int(c) for c in counts],
                          "samples": int(len(m))}
        out["result"] = None if self.result is None else self.result.as_dict()
        r = self.refused
        out["refused"] = None if r is None else {
            "reason": r.reason, "fit": None if r.cal is None else r.cal.as_dict()}
        return out

    def apply(self, clear: bool = False) -> dict[str, Any]:
        """Correct every MAG sample with the fit (``clear``: stop correcting). A refused
        fit is never applied (409, its reason)."""
        if clear:
            self.applied = None
        else:
            if self.result is None:
                if self.refused is not None:
                    raise ToolError("magcal", "the fit was refused, nothing applied: "
                                              + self.refused.reason, 409)
                raise ToolError("magcal", "no fit yet: turn the phone in all directions first", 409)
            self.applied = self.result
        self._changed()
        for cb in self.listeners:
            cb()
        return self.status()
