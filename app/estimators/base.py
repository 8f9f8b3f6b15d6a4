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
from dataclasses import asdict, dataclass
from enum import IntEnum
from typing import Any, ClassVar, Mapping

import numpy as np

from app.jitcache import compiled
from app.params import replace_params, to_dict


class Reason(IntEnum):
    """Why a sensor's sample was or was not used in the update of one row."""
    USED = 0        # the update was made
    ABSENT = 1      # no sample of this sensor in the row
    DISABLED = 2    # switched off by use_gyr / use_acc / use_mag
    INVALID = 3     # NaN, infinite, or an all-zero accelerometer or magnetometer (bad input)
    NORM = 4        # |a| or |m| outside its band (value: the norm, m/s² or µT)
    NIS = 5         # innovation (Mahalanobis) gate (value: NIS)
    DIP = 6         # magnetic dip angle off the learned reference (value: deviation, rad)
    FIELD = 7       # lab: low-pass field strength L_k outside its band (value: L_k, µT)
    INIT = 8        # used to initialise the orientation
    WAIT = 9        # not used yet: waiting for the initial alignment
    GAP = 10        # gyroscope: time gap too long to integrate (value: dt, s)
    REST = 11       # gyroscope: at rest, bias update made
    LATE = 12       # the row's timestamp is before the previous row's: skipped
    ACCEL = 13      # acc: specific force (the phone accelerates); the sample enters robust's
                    # low-pass but is not trusted as gravity (value: angle between the sample
                    # and the low-passed gravity, rad)
    NEW_FIELD = 14  # mag: a new homogeneous field became the reference (value: its strength, µT)
    RECOVER = 15    # the estimate was judged lost and re-aligned (mag: heading far from a
                    # trusted field for long; value: the heading error corrected, rad; acc:
                    # the low-passed gravity below the horizon, the tilt more than 90° off;
                    # value: that angle, rad)
    BIAS_RESET = 16 # gyr: the bias estimate was implausible (above bias_max) and was reset
    TURN = 17       # mag: the field (world frame) changed faster than the phone's turn explains:
                    # a magnet moving in (value: the unexplained change rate, rad/s)
    OFFSET = 18     # mag: used, with a sensor-fixed offset removed (a magnet on the phone, a
                    # case, a mount: tracked online; value: the offset's strength, µT)

    @property
    def label(self) -> str:
        return self.name.lower()


REASON_TEXT = {
    Reason.USED: "used",
    Reason.ABSENT: "no sample",
    Reason.DISABLED: "switched off",
    Reason.INVALID: "invalid value (NaN, inf, or an all-zero acc or mag)",
    Reason.NORM: "norm outside its band",
    Reason.NIS: "innovation gate (NIS) exceeded",
    Reason.DIP: "dip angle off the reference",
    Reason.FIELD: "field strength L_k outside its band",
    Reason.INIT: "used for initial alignment",
    Reason.WAIT: "waiting for initial alignment",
    Reason.GAP: "time gap too long to integrate",
    Reason.REST: "at rest (bias update)",
    Reason.LATE: "timestamp before the previous row (skipped)",
    Reason.ACCEL: "phone accelerating (specific force): not trusted as gravity",
    Reason.NEW_FIELD: "new magnetic field accepted as the reference",
    Reason.RECOVER: "estimate was lost: re-aligned",
    Reason.BIAS_RESET: "implausible gyroscope bias: reset",
    Reason.TURN: "field changed faster than the phone turned",
    Reason.OFFSET: "used with a sensor-fixed offset (a magnet on the phone) removed",
}


# How long an estimator holding its first accelerometer sample waits for a magnetometer
# sample to align the heading too, before it aligns with the accelerometer alone (s).
ALIGN_WAIT_S = 0.5


# What align_step asks of the estimator that calls it
(ALIGN_WAIT,       # nothing yet: keep waiting
 ALIGN_ACC_MAG,    # tilt from the waiting accelerometer sample, heading from this row's field
 ALIGN_ACC,        # tilt from the waiting accelerometer sample, no heading
 ALIGN_NO_ACC,     # no accelerometer (switched off): the estimator's own level start
 ) = range(4)


class TimeIssue(IntEnum):
    OK = 0
    REPEATED = 1    # same timestamp as the previous row: no time update
    BACKWARD = 2    # timestamp before the previous row: row skipped
    GAP = 3         # gap longer than max_gap: no integration across it
    FIRST = 4       # first row


_REASONS = tuple(Reason)          # code -> member, without Enum's slow constructor
_TIME_ISSUES = tuple(TimeIssue)

# Plain int copies of the codes for numba-compiled code (it cannot cast IntEnum to float)
(R_USED, R_ABSENT, R_DISABLED, R_INVALID, R_NORM, R_NIS, R_DIP, R_FIELD, R_INIT, R_WAIT, R_GAP,
 R_REST, R_LATE, R_ACCEL, R_NEW_FIELD, R_RECOVER, R_BIAS_RESET, R_TURN, R_OFFSET) = (int(r) for r in Reason)
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


@compiled
def new_flags():
    f = np.full(NFLAGS, np.nan)
    f[F_GYR] = R_ABSENT
    f[F_ACC] = R_ABSENT
    f[F_MAG] = R_ABSENT
    f[F_REST] = 0.0
    f[F_TIME] = T_OK
    return f


@compiled
def vector_state(v, enabled, zero_ok):
    """Reason for a sensor sample before any gate: ABSENT (all NaN), DISABLED,
    INVALID (some NaN, inf, or all zero unless ``zero_ok``) or USED (fit to try). An
    all-zero accelerometer or magnetometer reading is an app's placeholder (no phone at
    rest reads it); a gyroscope at rest does read 0, 0, 0 once its output is quantised."""
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
    if n_nan > 0 or (n_zero == 3 and not zero_ok):
        return R_INVALID
    return R_USED


@compiled
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


@compiled
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


@compiled
def repeated_time(issue, seen, mask):
    """A row at the same time as the previous one is REPEATED only if it brings a
    sensor already seen at that time (a phone stamps ACC and GYR with the same ms,
    one row each: that is normal). Returns (issue, sensors seen at this time)."""
    if issue != T_REPEATED:
        return issue, mask
    if seen & mask:
        return T_REPEATED, seen | mask
    return T_OK, seen | mask


@compiled
def row_prologue(t_prev, t, max_gap, seen, gyr, acc, mag, use_gyr, use_acc, use_mag):
    """Everything a row needs before any estimator's own work, in one compiled call:
    ``(dt, time issue, sensors seen at this time, gyr/acc/mag state)``."""
    dt, issue = time_step(t_prev, t, max_gap)
    if issue != T_BACKWARD:
        issue, seen = repeated_time(issue, seen, row_mask(gyr, acc, mag))
    return (dt, issue, seen, vector_state(gyr, use_gyr, True), vector_state(acc, use_acc, False),
            vector_state(mag, use_mag, False))


# Slots of the row bookkeeping every estimator's state carries (the first five of a
# compiled estimator's state array): time of the last row, sensors seen at that time, the
# held gyroscope sample and its time.
B_T, B_SEEN, B_W_T, B_W = 0, 1, 2, 3
B_N = 6


@compiled
def begin_row(b, t, gyr, acc, mag, use_gyr, use_acc, use_mag, max_gap, gyr_hold, f):
    """The part of a row every estimator shares, in one compiled call (the one place it
    is decided): the flag record ``f`` reset and filled with the time issue and each
    sensor's state before any gate; the row bookkeeping ``b`` (slots ``B_*``) advanced;
    the gyroscope rate to integrate over ``dt`` (the row's own sample, else the last one
    for up to ``gyr_hold`` s; none across a gap). Returns ``(go, dt, gs, as_, ms, has_w,
    w)``; ``go`` is False for a backward timestamp (row skipped, samples flagged LATE)."""
    f[:] = np.nan
    f[F_REST] = 0.0
    dt, issue, seen, gs, as_, ms = row_prologue(b[B_T], t, max_gap, int(b[B_SEEN]), gyr, acc, mag,
                                                use_gyr, use_acc, use_mag)
    b[B_SEEN] = seen
    f[F_TIME] = issue
    w = np.zeros(3)
    if issue == T_BACKWARD:
        f[F_GYR] = R_LATE if gs == R_USED else gs
        f[F_ACC] = R_LATE if as_ == R_USED else as_
        f[F_MAG] = R_LATE if ms == R_USED else ms
        return False, dt, gs, as_, ms, False, w
    f[F_GYR] = gs
    f[F_ACC] = as_
    f[F_MAG] = ms
    b[B_T] = t
    has_w = False
    if use_gyr:
        if gs == R_USED:
            has_w = True
            w[:] = gyr
            b[B_W:B_W + 3] = gyr
            b[B_W_T] = t
        elif b[B_W_T] == b[B_W_T] and t - b[B_W_T] <= gyr_hold:
            has_w = True
            w[:] = b[B_W:B_W + 3]
    if issue == T_GAP:
        if gs == R_USED:
            f[F_GYR] = R_GAP
        has_w = False
    return True, dt, gs, as_, ms, has_w, w


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

    def rejected(self, sensor: str) -> bool:
        """Was ``sensor``'s sample (gyr, acc or mag) a valid one refused by a gate?"""
        return is_rejected(getattr(self, sensor))

    @property
    def acc_rejected(self) -> bool:
        return is_rejected(self.acc)

    @property
    def mag_rejected(self) -> bool:
        return is_rejected(self.mag)


# Reasons that mean "a valid sample was refused or not trusted by a gate": the ONE place
# deciding what the dashboard shows as "disturbed" (indicators, red samples, rejection counts).
REJECTIONS = frozenset({Reason.NORM, Reason.NIS, Reason.DIP, Reason.FIELD, Reason.ACCEL, Reason.TURN})
# Of those, the ones whose sample still enters the estimate (a specific-force sample is
# averaged into robust's low-pass): a read-out counts them apart from the refused ones.
AVERAGED_IN = frozenset({Reason.ACCEL})
# Reasons that report an event worth telling the user (the filter corrected itself).
ALERTS = frozenset({Reason.NEW_FIELD, Reason.RECOVER, Reason.BIAS_RESET})


def is_rejected(reason) -> bool:
    """True when a flag record's reason (a :class:`Reason` or its code) means that a
    valid sample was refused or not trusted by a gate (see :data:`REJECTIONS`)."""
    try:
        return _REASONS[int(reason)] in REJECTIONS
    except (IndexError, ValueError, TypeError):
        return False


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


@dataclass(frozen=True)
class Diagnostics:
    """What an estimator shows besides its estimate (the plots' gate bands, the 3D view's
    expected arrows, GET /api/state "diagnostics"): one typed read model returned by every
    estimator. SI units (µT for the field), vectors in world coordinates (ENU) as tuples;
    None where the estimator has no such thing or has not learned it yet."""

    # --- references (world frame)
    g0: tuple[float, float, float] | None = None
    """Expected accelerometer reading at rest in world coordinates (m/s², specific force: up)."""
    m0: tuple[float, float, float] | None = None
    """Expected magnetic field in world coordinates (µT): lab's nominal or learned m0,
    robust's learned reference (north and the learned dip)."""
    # --- norm gates
    acc_band: tuple[float, float] | None = None
    """(lo, hi) band |acc| must stay in to be used (m/s²); None: gate off."""
    mag_band: tuple[float, float] | None = None
    """(lo, hi) band the field strength (lab: L_k; robust: |mag|) must stay in (µT); None: off."""
    L_k: float | None = None
    """Lab's low-passed field strength (µT), the value its field gate tests."""
    # --- NIS gates (χ², 3 degrees of freedom; 0: off)
    acc_nis_gate: float | None = None
    """Gate on the accelerometer update's normalised innovation squared."""
    mag_nis_gate: float | None = None
    """Gate on the magnetometer update's normalised innovation squared."""
    nis_gate: float | None = None
    """Lab's single NIS gate, applied to both sensors (= acc_nis_gate = mag_nis_gate)."""
    # --- robust: learned field reference and disturbance state
    mag_ref_norm: float | None = None
    """Strength of the learned field reference (µT)."""
    mag_ref_dip: float | None = None
    """Elevation of the learned field (rad): negative where it points down (north)."""
    acc_lp_world: tuple[float, float, float] | None = None
    """Low-passed specific force in world coordinates (m/s²): the disturbance detector's input."""
    gyr_bias: tuple[float, float, float] | None = None
    """Estimated gyroscope bias (rad/s, sensor frame)."""
    rest: bool | None = None
    """Standstill detected."""
    mag_offset: tuple[float, float, float] | None = None
    """robust: the sensor-fixed field offset (hard iron: a magnet on the phone) its online fit
    finds, sensor frame (µT); zero before the fit has seen enough turning."""
    mag_offset_status: str | None = None
    """robust: "none" (no offset found), "tracking" (an offset found, not yet trusted) or
    "applied" (removed from every field sample)."""
    heading_wander: float | None = None
    """robust: the field's heading wander measured now against the gyroscope's, √v (rad; see
    ``heading_evidence_tau``); 0 before it is measured."""
    heading_noise_now: float | None = None
    """robust: the heading noise density in use now, √(heading_noise² + 2 v · 0.5 s) (rad·√s):
    the larger, the longer the gyroscope alone is trusted."""
    # --- complementary
    alpha: float | None = None
    """Gyro weight α = τ/(τ+dt) of the last blend (NaN: none made yet; 0: compass only)."""
    am_yaw: float | None = None
    """Yaw of the accelerometer/magnetometer (compass) orientation (rad)."""
    am_pitch: float | None = None
    """Pitch of the compass orientation (rad)."""
    am_roll: float | None = None
    """Roll of the compass orientation (rad)."""
    tau: float | None = None
    """Blend time constant τ (s)."""
    ma_window: int | None = None
    """Samples in the moving average of acc and mag."""
    # --- phone
    ori_t: float | None = None
    """Time (s) of the phone's ORI sample shown."""
    ori_age: float | None = None
    """Age (s) of that ORI sample at the last row."""

    def as_dict(self) -> dict[str, Any]:
        """Every field by name (tuples stay tuples); the API passes it through json_safe."""
        return asdict(self)


def vec3(x) -> tuple[float, float, float] | None:
    """A 3-vector as a tuple of floats (None stays None): for Diagnostics' fields."""
    if x is None:
        return None
    a, b, c = (float(v) for v in x)
    return a, b, c


def index_ok(x: Any, n: int, lo: int = 0) -> bool:
    """``x`` a whole number in ``lo .. n - 1`` (a slot the compiled code indexes with)."""
    return bool(np.isfinite(x) and float(x) == int(x) and lo <= int(x) < n)


def _attr(obj: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


class Estimator:
    """Base class: the common interface of every orientation estimator.

    Subclasses set ``name``, ``Params`` (a frozen dataclass of parameters, see
    :mod:`app.params`) and implement ``_reset_state``, ``_step`` (one row, writing the
    flag record) and the accessors. ``step`` and ``run`` are shared.
    """

    name: ClassVar[str] = "base"
    title: ClassVar[str] = ""
    Params: ClassVar[type]
    # the phone's own estimate, shown as it is: the reference the filters are compared
    # with (the error "to phone"), not a filter to tune or to change in a what-if
    reference: ClassVar[bool] = False
    # the attributes that are the mutable state (``a.b``: ``b`` of attribute ``a``), as
    # vqf keeps its state apart from its parameters and the coefficients derived from them
    # (``_on_params``): :meth:`state_arrays` / :meth:`restore_arrays`
    STATE: ClassVar[tuple[str, ...]] = ("_last_t", "_last_f")

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
        self._last_t = float("nan")
        self._last_f = _FLAGS0
        self._reset_state()

    @property
    def last_flags(self) -> StepFlags:
        """The flag record of the last row processed (built when read)."""
        return StepFlags.from_row(self._last_t, self._last_f)

    @property
    def t(self) -> float:
        """Time (s) of the last row processed (NaN before the first)."""
        return float(self._s[B_T])

    def _reset_state(self) -> None:
        raise NotImplementedError

    def save_state(self) -> Any:
        """A copy of the mutable state (:attr:`STATE`): neither the parameters nor what
        derives from them."""
        return {name: copy.deepcopy(_attr(self, name)) for name in self.STATE}

    def load_state(self, state: Any) -> None:
        """Go back to a state :meth:`save_state` gave. The parameters in force stay, and
        what derives from them is derived again: a state saved before a parameter change
        goes on with the new parameters (as :meth:`set_params` would have left it), not
        with the old coefficients."""
        self._set_state(copy.deepcopy(state))
        self._on_params()

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The mutable state (:attr:`STATE`) as named arrays, copied: what a recording
        keeps to re-run warm (``np.savez``, no pickle). The parameters and what derives from
        them are not in it: they come from the parameter set."""
        return {name: np.array(_attr(self, name), dtype=float) for name in self.STATE}

    def restore_arrays(self, arrays: Mapping[str, Any]) -> None:
        """Take up the state :meth:`state_arrays` gave (of an estimator of this kind): the
        next rows go on from it as that estimator's would have. ValueError naming the array
        that is missing or of another shape; nothing is changed then."""
        new = {}
        for name in self.STATE:
            if name not in arrays:
                raise ValueError(f"{self.name}: the saved state has no {name!r}")
            cur = _attr(self, name)
            a = np.asarray(arrays[name], dtype=float)
            if a.shape != np.shape(cur):
                raise ValueError(f"{self.name}: the saved {name!r} has shape {a.shape}, "
                                 f"not {np.shape(cur)}")
            new[name] = a.copy() if isinstance(cur, np.ndarray) else type(cur)(a)
        old = {name: _attr(self, name) for name in self.STATE}
        self._set_state(new)
        why = self._state_error()
        if why is not None:          # a file's state is not trusted: nothing taken
            self._set_state(old)
            raise ValueError(f"{self.name}: the saved state is not one it can have: {why}")

    def _set_state(self, values: Mapping[str, Any]) -> None:
        for name, v in values.items():
            obj, _, last = name.rpartition(".")
            setattr(_attr(self, obj) if obj else self, last, v)

    def _state_error(self) -> str | None:
        """Why the state (just restored) is not one this estimator can have, or None. The
        compiled rows index arrays with some slots: a value out of range must never reach
        them. Subclasses add their own slots (and call this)."""
        f = np.asarray(self._last_f)
        for col, n in ((F_GYR, len(Reason)), (F_ACC, len(Reason)), (F_MAG, len(Reason)),
                       (F_TIME, len(TimeIssue))):
            if not index_ok(f[col], n):
                return f"flag column {col} holds {f[col]!r}"
        return None

    # ----------------------------------------------------------- processing
    def step(self, t: float, gyr=None, acc=None, mag=None, ori=None) -> StepFlags:
        """Process one row (see the module doc) and return its flag record."""
        f = _FLAGS0.copy()
        self._step(float(t), _as_vec(gyr), _as_vec(acc), _as_vec(mag),
                   None if ori is None else np.asarray(ori, dtype=float), f)
        self._last_t, self._last_f = float(t), f
        return self.last_flags

    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        raise NotImplementedError

    def run(self, t, gyr=None, acc=None, mag=None, ori=None) -> BatchResult:
        """Process rows in order; the estimate and flags after each. Arrays are (N,)
        and (N, 3) (ori (N, 4)); None or NaN rows mean absent."""
        t = np.ascontiguousarray(t, dtype=float)
        n = t.shape[0]
        G, A, M = (_rows(x, n) for x in (gyr, acc, mag))
        O = _rows(ori, n, 4)
        qs = np.empty((n, 4))
        flags = np.empty((n, NFLAGS))
        self.run_into(t, G, A, M, O, qs, flags)
        return BatchResult(t=t, q=qs, flags=flags)

    def run_steps(self, t, gyr=None, acc=None, mag=None, ori=None) -> BatchResult:
        """:meth:`run` row by row through ``_step`` (the readable reference the compiled
        batch runs are held to, to 1e-9, by the tests)."""
        t = np.ascontiguousarray(t, dtype=float)
        n = t.shape[0]
        G, A, M = (_rows(x, n) for x in (gyr, acc, mag))
        O = None if ori is None else _rows(ori, n, 4)
        qs = np.empty((n, 4))
        flags = np.empty((n, NFLAGS))
        for k in range(n):
            f = flags[k]
            f[:] = _FLAGS0
            self._step(t[k], G[k], A[k], M[k], None if O is None else O[k], f)
            qs[k] = self.q
        if n:
            self._last_t, self._last_f = t[-1], flags[-1].copy()
        return BatchResult(t=t, q=qs, flags=flags)

    def run_into(self, t, G, A, M, O, qs, flags) -> None:
        """:meth:`run` without checks or allocation (the live ensemble's path): ``t`` (n,),
        ``G``/``A``/``M`` (n, 3), ``O`` (n, 4), contiguous float64 (NaN: absent); the
        estimate and the flag record after each row are written into ``qs`` (n, 4) and
        ``flags`` (n, NFLAGS)."""
        self._run_rows(t, G, A, M, O, qs, flags)
        if t.shape[0]:
            self._last_t, self._last_f = t[-1], flags[-1].copy()

    def _run_rows(self, t, G, A, M, O, qs, flags) -> None:
        """The rows through the estimator (subclasses: one compiled batch run)."""
        for k in range(t.shape[0]):
            f = flags[k]
            f[:] = _FLAGS0
            self._step(t[k], G[k], A[k], M[k], O[k], f)
            qs[k] = self.q

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

    def diagnostics(self) -> Diagnostics:
        """Gate bands, references and learned state worth showing (see Diagnostics)."""
        return Diagnostics()

    def field_strength(self) -> float | None:
        """The low-passed field strength L_k (µT) now (Diagnostics.L_k), None for an
        estimator without one; cheap (the live core reads it before every chunk)."""
        return None

    def field_strength_rows(self, flags: np.ndarray, before: float) -> np.ndarray | None:
        """The low-passed field strength L_k (µT) after each of these rows (``flags``: the
        rows' flag records, in order), given its value ``before`` them; None for an
        estimator without one. Lets the live plots show L_k from a batch run."""
        return None


def _rows(x, n: int, width: int = 3) -> np.ndarray:
    if x is None:
        return np.full((n, width), np.nan)
    a = np.ascontiguousarray(x, dtype=float)
    if a.shape != (n, width):
        raise ValueError(f"expected shape ({n}, {width}), got {a.shape}")
    return a


@compiled
def align_step(s, i_wait_t, i_wait_acc, t, gs, as_, ms, acc, use_acc, use_mag, f):
    """The initial alignment's decision, made here once for every estimator that aligns
    from its first samples (the manual's filter and ``robust``): which samples align it,
    and when. The phone may be moving, so nothing waits for a still start: the first
    accelerometer sample gives the tilt at once when the magnetometer is off; otherwise
    it waits (the newest one kept) for a magnetometer sample to give the heading too,
    for at most :data:`ALIGN_WAIT_S` from the stream's first sample on (a stream without
    a magnetometer aligns without heading). Without an accelerometer (switched off, or
    silent for :data:`ALIGN_WAIT_S`: a phone streaming only its gyroscope and
    magnetometer) the estimator starts level at a gyroscope or magnetometer sample.

    ``s[i_wait_t]`` (the stream's first sample, NaN before) and ``s[i_wait_acc:+3]`` (the
    newest accelerometer sample, NaN before) are the caller's state slots; ``f`` the
    row's flags: WAIT on every sample of the row, INIT on the one that aligned. Returns
    an ``ALIGN_*`` code; for ``ALIGN_ACC``/``ALIGN_ACC_MAG`` the tilt comes from
    ``s[i_wait_acc:+3]``."""
    if s[i_wait_t] != s[i_wait_t] and (gs == R_USED or as_ == R_USED or ms == R_USED):
        s[i_wait_t] = t                      # the wait runs from the first sample on
    if gs == R_USED:
        f[F_GYR] = R_WAIT
    if as_ == R_USED:
        f[F_ACC] = R_WAIT
        s[i_wait_acc:i_wait_acc + 3] = acc
        if not use_mag:
            f[F_ACC] = R_INIT
            return ALIGN_ACC
    has_acc = s[i_wait_acc] == s[i_wait_acc]
    if ms == R_USED:
        f[F_MAG] = R_WAIT
        if has_acc:
            f[F_MAG] = R_INIT
            return ALIGN_ACC_MAG
    waited = s[i_wait_t] == s[i_wait_t] and t - s[i_wait_t] > ALIGN_WAIT_S
    if has_acc and waited:
        f[F_ACC] = R_INIT
        return ALIGN_ACC
    if not has_acc and (not use_acc or waited) and (ms == R_USED or gs == R_USED):
        f[F_MAG if ms == R_USED else F_GYR] = R_INIT
        return ALIGN_NO_ACC
    return ALIGN_WAIT


# ------------------------------------------------------------------ the live ensemble's rows
# A chunk of stream samples becomes estimator rows (one sensor or ORI per row) and every
# instance's flag records are tallied, each in one compiled call (the live path's per-chunk
# bookkeeping; :mod:`app.live.ensemble`).

@compiled
def split_rows(kind, values, G, A, M, O):
    """Rows of a chunk: row ``k`` of kind 0/1/2/3 (gyr/acc/mag/ori) gets ``values[k]`` in
    ``G``/``A``/``M`` (3 values) or ``O`` (4), NaN in the others."""
    for k in range(kind.shape[0]):
        for j in range(3):
            G[k, j] = np.nan
            A[k, j] = np.nan
            M[k, j] = np.nan
        for j in range(4):
            O[k, j] = np.nan
        c = kind[k]
        if c == 0:
            G[k, :] = values[k, :3]
        elif c == 1:
            A[k, :] = values[k, :3]
        elif c == 2:
            M[k, :] = values[k, :3]
        elif c == 3:
            O[k, :] = values[k, :]


@compiled
def tally_rows(kind, t, f, q, counts, last, last_rej, is_rej):
    """One instance's bookkeeping over a chunk's rows: ``counts[sensor, reason] += 1``
    for each sensor row (kind 0/1/2) by the reason in its sensor's flag column; ``last``
    (3, 1 + NFLAGS): per sensor the time and flag record of its last row; ``last_rej``
    the same for the last row whose reason ``is_rej`` (acc and mag only). Returns the
    first row whose estimate ``q`` is not finite, or -1."""
    nreason = counts.shape[1]
    for k in range(kind.shape[0]):
        c = kind[k]
        if c > 2:
            continue
        code = f[k, F_GYR if c == 0 else (F_ACC if c == 1 else F_MAG)]
        last[c, 0] = t[k]
        last[c, 1:] = f[k]
        if not (code >= 0.0 and code < nreason):
            continue
        r = int(code)
        counts[c, r] += 1
        if c > 0 and is_rej[r]:
            last_rej[c, 0] = t[k]
            last_rej[c, 1:] = f[k]
    for k in range(q.shape[0]):
        for j in range(4):
            if not np.isfinite(q[k, j]):
                return k
    return -1
