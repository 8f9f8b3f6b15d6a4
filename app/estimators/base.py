"""The interface every estimator shares, and the per-update flag record.

An estimator consumes *rows*: a time ``t`` (s) and any of a gyroscope (rad/s),
accelerometer (m/s², specific force) and magnetometer (µT) sample taken at that
time (missing ones are ``None`` or NaN). One row is processed as

1. a time update from the previous row's time to ``t`` with the gyroscope
   (the row's own sample if it has one, else the last one held: piece-wise
   constant rate), or a random walk when the gyroscope is off or absent;
2. the accelerometer measurement update;
3. the magnetometer measurement update.

After every row the estimator writes one flag record (:data:`FLAG_COLUMNS`) that says
for each sensor whether its sample was used or why not (:class:`Reason`), with the value
that was tested. Rows are what a CSV/npz line is; the live receiver and the app-log
reader make one row per sample, in time order.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar

import numpy as np
from numba import njit

from ..params import replace_params, to_dict


class Reason(IntEnum):
    """Why a sensor's sample was or was not used in the update of one row."""
    USED = 0        # the update was made
    ABSENT = 1      # no sample of this sensor in the row
    DISABLED = 2    # switched off by use_gyr / use_acc / use_mag
    INVALID = 3     # NaN, infinite or all-zero vector (bad input)
    NORM = 4        # |a| or |m| outside its band (value: the norm, m/s² or µT)
    NIS = 5         # innovation (Mahalanobis) gate (value: NIS)
    DIP = 6         # magnetic dip angle off the learned reference (value: deviation, rad)
    FIELD = 7       # lab: low-pass field strength L_k outside its band (value: L_k, µT)
    INIT = 8        # used to initialise the orientation
    WAIT = 9        # not used yet: waiting for the initial alignment
    GAP = 10        # gyroscope: time gap too long to integrate (value: dt, s)
    REST = 11       # gyroscope: at rest, bias update made
    LATE = 12       # the row's timestamp is before the previous row's: skipped

    @property
    def label(self) -> str:
        return self.name.lower()


REASON_TEXT = {
    Reason.USED: "used",
    Reason.ABSENT: "no sample",
    Reason.DISABLED: "switched off",
    Reason.INVALID: "invalid value (NaN, inf or zero)",
    Reason.NORM: "norm outside its band",
    Reason.NIS: "innovation gate (NIS) exceeded",
    Reason.DIP: "dip angle off the reference",
    Reason.FIELD: "field strength L_k outside its band",
    Reason.INIT: "used for initial alignment",
    Reason.WAIT: "waiting for initial alignment",
    Reason.GAP: "time gap too long to integrate",
    Reason.REST: "at rest (bias update)",
    Reason.LATE: "timestamp before the previous row (skipped)",
}


# How long an estimator holding its first accelerometer sample waits for a magnetometer
# sample to align the heading too, before it aligns with the accelerometer alone (s).
ALIGN_WAIT_S = 0.5


class TimeIssue(IntEnum):
    OK = 0
    REPEATED = 1    # same timestamp as the previous row: no time update
    BACKWARD = 2    # timestamp before the previous row: row skipped
    GAP = 3         # gap longer than max_gap: no integration across it
    FIRST = 4       # first row


_REASONS = tuple(Reason)          # code -> member, without Enum's slow constructor
_TIME_ISSUES = tuple(TimeIssue)

# Plain int copies of the codes for numba-compiled code (it cannot cast IntEnum to float)
R_USED, R_ABSENT, R_DISABLED, R_INVALID, R_NORM, R_NIS, R_DIP, R_FIELD, R_INIT, R_WAIT, R_GAP, \
    R_REST, R_LATE = (int(r) for r in Reason)
T_OK, T_REPEATED, T_BACKWARD, T_GAP, T_FIRST = (int(x) for x in TimeIssue)

# The flag record written after every row (floats so one array holds them all).
FLAG_COLUMNS = (
    "gyr",          # Reason
    "acc",          # Reason
    "acc_value",    # value tested by the gate that decided (norm m/s², NIS, ...) or NaN
    "acc_nis",      # NIS of the accelerometer update or NaN
    "mag",          # Reason
    "mag_value",    # value tested (norm µT, dip rad, L_k µT, NIS) or NaN
    "mag_nis",      # NIS of the magnetometer update or NaN
    "rest",         # 1.0 at rest (standstill detected) else 0.0
    "time",         # TimeIssue
)
NFLAGS = len(FLAG_COLUMNS)
F_GYR, F_ACC, F_ACC_VAL, F_ACC_NIS, F_MAG, F_MAG_VAL, F_MAG_NIS, F_REST, F_TIME = range(NFLAGS)


@njit(cache=True)
def new_flags():
    f = np.full(NFLAGS, np.nan)
    f[F_GYR] = R_ABSENT
    f[F_ACC] = R_ABSENT
    f[F_MAG] = R_ABSENT
    f[F_REST] = 0.0
    f[F_TIME] = T_OK
    return f


@njit(cache=True)
def vector_state(v, enabled):
    """Reason for a sensor sample before any gate: ABSENT (all NaN), DISABLED,
    INVALID (some NaN, inf, or all zero) or USED (fit to try)."""
    n_nan = 0
    n_zero = 0
    for i in range(3):
        if np.isnan(v[i]):
            n_nan += 1
        elif not np.isfinite(v[i]):
            return R_INVALID if enabled else R_DISABLED
        elif v[i] == 0.0:
            n_zero += 1
    if n_nan == 3:
        return R_ABSENT
    if not enabled:
        return R_DISABLED
    if n_nan > 0 or n_zero == 3:
        return R_INVALID
    return R_USED


@njit(cache=True)
def time_step(t_prev, t, max_gap):
    """(dt, TimeIssue) of a row at ``t`` after one at ``t_prev`` (NaN: first row)."""
    if np.isnan(t_prev):
        return 0.0, T_FIRST
    dt = t - t_prev
    if not np.isfinite(dt) or dt < 0.0:
        return 0.0, T_BACKWARD
    if dt == 0.0:
        return 0.0, T_REPEATED
    if max_gap > 0.0 and dt > max_gap:
        return dt, T_GAP
    return dt, T_OK


@njit(cache=True)
def row_mask(gyr, acc, mag):
    """Bit mask of the sensors present in a row (1 gyr, 2 acc, 4 mag)."""
    m = 0
    if not np.isnan(gyr[0]) or not np.isnan(gyr[1]) or not np.isnan(gyr[2]):
        m |= 1
    if not np.isnan(acc[0]) or not np.isnan(acc[1]) or not np.isnan(acc[2]):
        m |= 2
    if not np.isnan(mag[0]) or not np.isnan(mag[1]) or not np.isnan(mag[2]):
        m |= 4
    return m


@njit(cache=True)
def repeated_time(issue, seen, mask):
    """A row at the same time as the previous one is REPEATED only if it brings a
    sensor already seen at that time (a phone stamps ACC and GYR with the same ms,
    one row each: that is normal). Returns (issue, sensors seen at this time)."""
    if issue != T_REPEATED:
        return issue, mask
    if seen & mask:
        return T_REPEATED, seen | mask
    return T_OK, seen | mask


@njit(cache=True)
def row_prologue(t_prev, t, max_gap, seen, gyr, acc, mag, use_gyr, use_acc, use_mag):
    """Everything a row needs before any estimator's own work, in one compiled call:
    ``(dt, time issue, sensors seen at this time, gyr/acc/mag state)``."""
    dt, issue = time_step(t_prev, t, max_gap)
    if issue != T_BACKWARD:
        issue, seen = repeated_time(issue, seen, row_mask(gyr, acc, mag))
    return (dt, issue, seen, vector_state(gyr, use_gyr), vector_state(acc, use_acc),
            vector_state(mag, use_mag))


_NAN3 = np.full(3, np.nan)
_FLAGS0 = new_flags()  # the record of a row before anything happened (copied per row)


def _as_vec(v) -> np.ndarray:
    if v is None:
        return _NAN3.copy()
    if type(v) is np.ndarray and v.shape == (3,) and v.dtype == np.float64:
        return v
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.size != 3:
        raise ValueError(f"a sensor sample has 3 values, got {a.size}")
    return a


@dataclass
class StepFlags:
    """The flag record of one row in readable form."""
    t: float
    gyr: Reason
    acc: Reason
    acc_value: float
    acc_nis: float
    mag: Reason
    mag_value: float
    mag_nis: float
    rest: bool
    time: TimeIssue

    @classmethod
    def from_row(cls, t: float, f: np.ndarray) -> "StepFlags":
        v = f.tolist()
        return cls(t=float(t), gyr=_REASONS[int(v[F_GYR])], acc=_REASONS[int(v[F_ACC])],
                   acc_value=v[F_ACC_VAL], acc_nis=v[F_ACC_NIS],
                   mag=_REASONS[int(v[F_MAG])], mag_value=v[F_MAG_VAL],
                   mag_nis=v[F_MAG_NIS], rest=v[F_REST] > 0.5,
                   time=_TIME_ISSUES[int(v[F_TIME])])

    @property
    def acc_rejected(self) -> bool:
        return self.acc in REJECTIONS

    @property
    def mag_rejected(self) -> bool:
        return self.mag in REJECTIONS


# Reasons that mean "a valid sample was refused by a gate"
REJECTIONS = frozenset({Reason.NORM, Reason.NIS, Reason.DIP, Reason.FIELD})


@dataclass
class BatchResult:
    t: np.ndarray       # (N,) s
    q: np.ndarray       # (N, 4) estimate after each row, [w, x, y, z]
    flags: np.ndarray   # (N, NFLAGS), see FLAG_COLUMNS

    def counts(self) -> dict[str, dict[str, int]]:
        return count_flags(self.flags)


def count_flags(flags: np.ndarray) -> dict[str, dict[str, int]]:
    """Per sensor, how many rows ended with each reason; plus time issues."""
    flags = np.atleast_2d(flags)
    out: dict[str, dict[str, int]] = {}
    for key, col in (("gyr", F_GYR), ("acc", F_ACC), ("mag", F_MAG)):
        vals, n = np.unique(flags[:, col].astype(int), return_counts=True)
        out[key] = {Reason(v).label: int(c) for v, c in zip(vals, n) if v != Reason.ABSENT}
    vals, n = np.unique(flags[:, F_TIME].astype(int), return_counts=True)
    out["time"] = {TimeIssue(v).name.lower(): int(c) for v, c in zip(vals, n)
                   if v not in (TimeIssue.OK, TimeIssue.FIRST)}
    out["rest"] = {"rows": int(np.sum(flags[:, F_REST] > 0.5))}
    return out


@dataclass
class Row:
    """What ``Estimator._begin_row`` found out about a row."""
    dt: float               # s since the previous row (0 on the first, repeated or gap row)
    issue: TimeIssue
    gyr: Reason             # state of each sensor's sample before any gate
    acc: Reason
    mag: Reason
    w: np.ndarray | None    # angular rate to integrate over dt (rad/s), None: random walk


class Estimator:
    """Base class: the common interface of every orientation estimator.

    Subclasses set ``name``, ``Params`` (a frozen dataclass of parameters, see
    :mod:`app.params`) and implement ``_reset_state``, ``_step`` (one row, writing the
    flag record) and the accessors. ``step`` and ``run`` are shared.
    """

    name: ClassVar[str] = "base"
    title: ClassVar[str] = ""
    Params: ClassVar[type]

    def __init__(self, params=None, **changes: Any):
        p = params if params is not None else self.Params()
        if changes:
            p = replace_params(p, changes)
        self._params = p
        self._on_params()
        self.reset()

    # ----------------------------------------------------------- parameters
    @property
    def params(self):
        return self._params

    def set_params(self, **changes: Any) -> None:
        """Validate and apply parameter changes; they take effect from the next row.
        Raises :class:`app.params.ParamError` (nothing applied) on a bad change."""
        self._params = replace_params(self._params, changes)
        self._on_params()

    def params_dict(self) -> dict[str, Any]:
        return to_dict(self._params)

    def _on_params(self) -> None:
        """Recompute what derives from the parameters (called after every change)."""

    # ----------------------------------------------------------- state
    def reset(self) -> None:
        """Forget the orientation; the next rows align it again."""
        self.t = float("nan")
        self._w = None
        self._w_t = float("nan")
        self._seen = 0  # sensors seen at the time of the last row
        self.last_flags = StepFlags.from_row(np.nan, new_flags())
        self._reset_state()

    def _reset_state(self) -> None:
        raise NotImplementedError

    def snapshot(self) -> Any:
        """A deep copy of the whole mutable state (not the parameters)."""
        return copy.deepcopy({k: v for k, v in self.__dict__.items() if k != "_params"})

    def restore(self, snap: Any) -> None:
        self.__dict__.update(copy.deepcopy(snap))

    # ----------------------------------------------------------- processing
    def step(self, t: float, gyr=None, acc=None, mag=None, ori=None) -> StepFlags:
        """Process one row (see the module doc) and return its flag record."""
        f = _FLAGS0.copy()
        self._step(float(t), _as_vec(gyr), _as_vec(acc), _as_vec(mag),
                   None if ori is None else np.asarray(ori, dtype=float), f)
        self.last_flags = StepFlags.from_row(t, f)
        return self.last_flags

    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        raise NotImplementedError

    def _begin_row(self, t, gyr, acc, mag, flags) -> "Row | None":
        """The part of a row every estimator shares: the time step and its issues,
        each sensor's state before any gate (``vector_state``), and the held gyroscope
        rate (the row's own sample, else the last one for up to ``gyr_hold`` s).
        Returns None (row skipped, samples flagged LATE) for a backward timestamp.
        Uses ``self.t`` (time of the last row) and ``self._w``/``self._w_t`` (held rate)."""
        p = self._params
        dt, issue, self._seen, gs, as_, ms = row_prologue(
            self.t, t, p.max_gap, self._seen, gyr, acc, mag, p.use_gyr, p.use_acc, p.use_mag)
        flags[F_TIME] = issue
        if issue == T_BACKWARD:
            for col, st in ((F_GYR, gs), (F_ACC, as_), (F_MAG, ms)):
                flags[col] = Reason.LATE if st == Reason.USED else st
            return None
        flags[F_GYR], flags[F_ACC], flags[F_MAG] = gs, as_, ms
        self.t = t
        w = None
        if p.use_gyr:
            if gs == Reason.USED:
                w = gyr
                self._w, self._w_t = gyr.copy(), t
            elif self._w is not None and t - self._w_t <= p.gyr_hold:
                w = self._w
        if issue == TimeIssue.GAP:
            if gs == Reason.USED:
                flags[F_GYR] = Reason.GAP
            w = None
        return Row(dt=dt, issue=_TIME_ISSUES[issue], gyr=_REASONS[gs], acc=_REASONS[as_],
                   mag=_REASONS[ms], w=w)

    def run(self, t, gyr=None, acc=None, mag=None, ori=None) -> BatchResult:
        """Process rows in order; the estimate and flags after each. Arrays are (N,)
        and (N, 3) (ori (N, 4)); None or NaN rows mean absent."""
        t = np.asarray(t, dtype=float)
        n = t.shape[0]
        G, A, M = (_rows(x, n) for x in (gyr, acc, mag))
        O = None if ori is None else np.asarray(ori, dtype=float)
        qs = np.empty((n, 4))
        flags = np.empty((n, NFLAGS))
        for k in range(n):
            f = new_flags()
            self._step(t[k], G[k], A[k], M[k], None if O is None else O[k], f)
            qs[k] = self.q
            flags[k] = f
        if n:
            self.last_flags = StepFlags.from_row(t[-1], flags[-1])
        return BatchResult(t=t, q=qs, flags=flags)

    # ----------------------------------------------------------- read-outs
    @property
    def initialized(self) -> bool:
        raise NotImplementedError

    @property
    def q(self) -> np.ndarray:
        """Current estimate [w, x, y, z], sensor to world (identity before alignment)."""
        raise NotImplementedError

    def attitude_cov(self) -> np.ndarray | None:
        """3x3 covariance (rad²) of the attitude error as a rotation vector in the
        world frame, or None where the estimator has no covariance."""
        return None

    @property
    def gyr_bias(self) -> np.ndarray | None:
        return None

    def diagnostics(self) -> dict[str, Any]:
        """Values worth plotting (gate bands, references); SI units."""
        return {}


def _rows(x, n: int) -> np.ndarray:
    if x is None:
        return np.full((n, 3), np.nan)
    a = np.asarray(x, dtype=float)
    if a.shape != (n, 3):
        raise ValueError(f"expected shape ({n}, 3), got {a.shape}")
    return a

