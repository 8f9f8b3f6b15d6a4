"""``complementary``: the DNRF (Drift & Noise Removal Filter) of Ayub, Bahraminisaab and
Honary, "A Sensor Fusion Method for Smart phone Orientation Estimation", in orientlab's
conventions. Hold this file beside the paper (``shared/seeds/paper_dnrf-...txt``).

How the paper's matrices map onto ours
--------------------------------------
The paper's rotation matrix R (its eq. 5 and 9, elements ``r1..r9`` row by row) has as
rows "the projections of the ERF axes on the DRF axes": row 1 is east, row 2 north,
row 3 up, each written in sensor (Android device) coordinates. That is exactly our
sensor->world matrix ``Q(q)`` (formula 2a of the lab manual): ``v_world = R v_sensor``.
Its eq. 5, ``R = Rz Rx Ry`` with the paper's (passive) eqs. 1-3, equals our ``Q(q)``
element by element, and its Euler angles (eqs. 19-21)

    yaw = atan2(r2, r5)      pitch = -asin(r8)      roll = atan2(r7, r9)

are the very angles of the manual's ``q2euler`` (yaw about z, positive clockwise seen
from above like a compass; pitch about x; roll about y; each negative for a right-handed
turn); the tests check both
agreements. We compute pitch as ``atan2(-r8, hypot(r7, r9))``, the same angle for an
orthonormal R but accurate near ±90°. In gimbal lock (``cos(pitch) = 0``, eq. 22) roll is
set to 0 and ``yaw = atan2(-r4, r1)`` (eq. 23).

The gyroscope update (eqs. 6-8) is ``R <- R (I + [ω]× dt)``: for a sensor->world R,
``dR/dt = R [ω]×`` with ω in sensor coordinates (as in the paper's reference [7],
Premerlani & Bizard). The paper prints ``Ω(t)`` as the transpose ``-[ω]×``; with its own
R that would turn the wrong way, so we use ``+[ω]×`` (the tests check the sign against the
quaternion update 2j). ``gyro_update = "exact"`` (the default) uses Rodrigues'
``exp([ω]× dt)`` instead: the paper's first-order step followed by its row-wise
re-orthonormalisation is off by about ``0.17 (|ω| dt)²`` rad per step (measured; the
row-wise repair is not the nearest rotation), a drift of ~0.1°/s at 1 rad/s and 100 Hz,
which costs accuracy on BROAD's fast trials (8.5° against 10.4° total RMSE at τ = 8 s).
After every update the rows are re-orthonormalised as in Section III-B: the error
``e = R1·R2`` is split half and half between rows 1 and 2, row 3 is their cross
product, and each row is normalised by the Taylor step ``(3 - r·r)/2`` (eqs. 12-18; eq. 12
misprints R2 as ``[r3 r4 r5]``, we use ``[r4 r5 r6]``). A row far from unit length (a
long step) is divided by its norm instead, where the Taylor step would not converge.

The accelerometer/magnetometer orientation (the "compass", Section III-A) is Android's
``getRotationMatrix`` (TRIAD): ``up = a/|a|``, ``east = m × up / |m × up|``,
``north = up × east``; R's rows are east, north, up.

The complementary blend (eqs. 24-25) is made per Euler angle:
``θ = α θ_gyro + (1 - α) θ_am`` with ``α = τ / (τ + Ts)``, ``Ts`` the time step of the row,
so the correction rate is 1/τ whatever the row structure. Angles wrap at ±π: the blend
goes from θ_am by α times the difference. Yaw and roll differences are taken modulo 2π,
and among their representatives (d, d ± 2π) the pair that is shortest as a rotation is
chosen (the metric of these Euler angles is ``dy² + dp² + dr² - 2 sin(p) dy dr``). Away
from ±90° pitch that is the usual wrap to (-π, π]; near gimbal lock, where only one
combination of yaw and roll is observable, it keeps that combination continuous, so the
blended angles stay consistent and no jump of (1 - α)·360° appears. The fused angles
rebuild R (eq. 5), which the next gyroscope update starts from.

Rows, sensors and switches
--------------------------
Rows come one sample at a time in a live stream, so the filter holds the latest
(moving-average filtered, window ``ma_window`` samples) accelerometer and magnetometer
vectors for up to ``am_hold`` s, and blends on every row after the gyroscope update:

- all sensors: as above;
- no magnetometer: the compass uses the current estimate's north axis instead of the
  field, so the heading stays the gyroscope's while the accelerometer corrects the tilt;
- no accelerometer: the compass uses the current estimate's up axis, so the tilt is the
  gyroscope's alone and the magnetometer still corrects the heading;
- no gyroscope (switched off, or nothing within ``gyr_hold``, or a time gap): the compass
  orientation is taken directly (α = 0).

The orientation starts from the first accelerometer sample together with a magnetometer
sample (waiting up to :data:`ALIGN_WAIT_S` for one, else heading 0: the phone's top
pointing north); without any accelerometer it starts level. The filter keeps no
covariance (``attitude_cov`` is None).
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np

from app import quaternion as qm
from app.jitcache import compiled
from app.quaternion import wrap_angle
from app.params import CommonParams, ParamError, param
from app.estimators.base import (ALIGN_WAIT_S, B_N, B_SEEN, B_T, B_W, B_W_T, F_ACC, F_ACC_VAL, F_GYR, F_MAG,
                   F_MAG_VAL, R_INIT, R_USED, R_WAIT, Diagnostics, Estimator,
                   index_ok, begin_row)

TWO_PI = 2.0 * np.pi
GIMBAL_EPS = 1e-12   # cos(pitch) below this is gimbal lock (eq. 22)
POLE_BAND = 1e-5     # below this cos(pitch), yaw from R's well-conditioned elements (euler_from_matrix)


@dataclass(frozen=True)
class ComplementaryParams(CommonParams):
    # τ = 1 s keeps a phone-sized gyroscope bias (0.05 rad/s, not estimated here) to ~3°;
    # BROAD's well calibrated IMU prefers longer: total RMSE 20.2° (τ = 1 s), 11.0° (4 s),
    # 8.5° (8 s), 7.4° (16 s), 10.3° (32 s), all with the exact gyroscope step.
    tau: float = param(1.0, unit="s", lo=0.0, hi=100.0,
                       doc="time constant τ of the complementary filter: α = τ/(τ+Ts); "
                           "larger trusts the gyroscope longer (error ≈ gyro bias × τ), "
                           "0 takes the compass only")
    ma_window: int = param(1, unit="samples", lo=1, hi=200,
                           doc="moving-average window of the accelerometer and magnetometer "
                               "pre-filter (1: off)")
    am_hold: float = param(0.25, unit="s", lo=0.0, hi=5.0,
                           doc="how long the last accelerometer/magnetometer sample stands in "
                               "for rows without one")
    gyro_update: str = param("exact", choices=("exact", "paper"),
                             doc="gyroscope step: paper's first order R(I+[ω]×dt) "
                                 "or exact exp([ω]×dt); both re-orthonormalised")

    def check(self) -> None:
        if self.ma_window != int(self.ma_window):
            raise ParamError("ma_window", f"must be a whole number, got {self.ma_window!r}")


# ------------------------------------------------------------------ the paper's math

@compiled
def _unit_row(r):
    """Row scaled to unit length: the paper's Taylor step (eq. 16-18) when it is close to
    unit length, an exact division otherwise."""
    n2 = r @ r
    if abs(n2 - 1.0) < 0.01:
        return 0.5 * (3.0 - n2) * r
    return r / np.sqrt(n2)


@compiled
def orthonormalize(R):
    """Section III-B: re-orthonormalise the rows of R (eqs. 12-18)."""
    r1 = R[0].copy()
    r2 = R[1].copy()
    err = r1 @ r2                       # eq. 12
    r1o = r1 - 0.5 * err * r2           # eq. 13
    r2o = r2 - 0.5 * err * r1           # eq. 14
    r3o = np.cross(r1o, r2o)            # eq. 15
    out = np.empty((3, 3))
    out[0] = _unit_row(r1o)
    out[1] = _unit_row(r2o)
    out[2] = _unit_row(r3o)
    return out


@compiled
def gyro_step(R, w, dt, exact):
    """Eqs. 6-8 in our convention: R (I + [ω]× dt), or R exp([ω]× dt); then III-B."""
    if exact:
        v = w * dt
        a = np.sqrt(v @ v)
        K = qm.skew(v)
        if a < 1e-8:
            inc = np.eye(3) + K + 0.5 * (K @ K)
        else:
            inc = np.eye(3) + (np.sin(a) / a) * K + ((1.0 - np.cos(a)) / (a * a)) * (K @ K)
    else:
        inc = np.eye(3) + qm.skew(w) * dt
    return orthonormalize(R @ inc)


@compiled
def euler_from_matrix(R):
    """Eqs. 19-21 with the gimbal-lock case (22-23): ``[yaw, pitch, roll]`` in rad."""
    cp = np.sqrt(R[2, 0] * R[2, 0] + R[2, 2] * R[2, 2])
    out = np.empty(3)
    out[1] = np.arctan2(-R[2, 1], cp)                 # = -asin(r8)
    if cp < GIMBAL_EPS:
        out[0] = np.arctan2(-R[1, 0], R[0, 0])        # eq. 23, roll := 0
        out[2] = 0.0
    elif cp < POLE_BAND:
        # near a pole yaw and roll turn about almost the same axis: roll alone (eq. 21) is
        # known to rounding / cos(pitch), but yaw - sin(pitch)·roll is R's own (r1, r4, as
        # eq. 23): yaw follows from both, so R is rebuilt to rounding
        out[2] = np.arctan2(R[2, 0], R[2, 2])
        out[0] = wrap_angle(np.arctan2(-R[1, 0], R[0, 0]) + (1.0 if R[2, 1] < 0.0 else -1.0) * out[2])
    else:
        out[0] = np.arctan2(R[0, 1], R[1, 1])         # eq. 19
        out[2] = np.arctan2(R[2, 0], R[2, 2])         # eq. 21
    return out


@compiled
def matrix_from_euler(e):
    """Eq. 5: R = Rz Rx Ry of ``[yaw, pitch, roll]``."""
    cy, sy = np.cos(e[0]), np.sin(e[0])
    cp, sp = np.cos(e[1]), np.sin(e[1])
    cr, sr = np.cos(e[2]), np.sin(e[2])
    R = np.empty((3, 3))
    R[0, 0] = cr * cy + sr * sp * sy
    R[0, 1] = cp * sy
    R[0, 2] = -sr * cy + cr * sp * sy
    R[1, 0] = -cr * sy + sr * sp * cy
    R[1, 1] = cp * cy
    R[1, 2] = sr * sy + cr * sp * cy
    R[2, 0] = sr * cp
    R[2, 1] = -sp
    R[2, 2] = cr * cp
    return R


@compiled
def blend_angles(theta_g, theta_am, alpha):
    """Eq. 24 per angle, θ = θ_am + α (θ_gyro - θ_am), across the ±π wrap (see the module
    doc: the yaw/roll representatives that are shortest as a rotation)."""
    dy = wrap_angle(theta_g[0] - theta_am[0])
    dp = theta_g[1] - theta_am[1]
    dr = wrap_angle(theta_g[2] - theta_am[2])
    s = np.sin(0.5 * (theta_g[1] + theta_am[1]))
    best_y, best_r = dy, dr
    best = dy * dy + dr * dr - 2.0 * s * dy * dr
    for a in (-1.0, 0.0, 1.0):
        for b in (-1.0, 0.0, 1.0):
            y = dy + a * TWO_PI
            r = dr + b * TWO_PI
            c = y * y + r * r - 2.0 * s * y * r
            if c < best - 1e-12:
                best, best_y, best_r = c, y, r
    out = np.empty(3)
    out[0] = wrap_angle(theta_am[0] + alpha * best_y)
    out[1] = theta_am[1] + alpha * dp
    out[2] = wrap_angle(theta_am[2] + alpha * best_r)
    return out


@compiled
def dnrf_row(R, w, dt, has_w, exact, up, has_up, ref, has_ref, tau):
    """One row of the DNRF after the alignment. ``R`` is the fused matrix of the last row;
    ``w`` the rate over ``dt`` (``has_w``); ``up``/``ref`` the filtered accelerometer and
    magnetometer (``has_up``/``has_ref``). Returns ``(R, alpha, theta_am)``; alpha is NaN
    and theta_am NaN when no compass was available."""
    if has_w and dt > 0.0:
        R = gyro_step(R, w, dt, exact)
    theta_am = np.full(3, np.nan)
    if not (has_up or has_ref):
        return R, np.nan, theta_am
    u = up if has_up else R[2].copy()          # no accelerometer: keep the current tilt
    m = ref if has_ref else R[1].copy()        # no magnetometer: keep the current heading
    Ram = qm.compass_matrix(u, m, R)
    theta_am = euler_from_matrix(Ram)
    if not has_w:
        return Ram, 0.0, theta_am              # no gyroscope: the compass directly
    alpha = tau / (tau + dt) if tau + dt > 0.0 else 0.0
    if alpha >= 1.0:
        return R, 1.0, theta_am
    theta = blend_angles(euler_from_matrix(R), theta_am, alpha)
    return matrix_from_euler(theta), alpha, theta_am



# ------------------------------------------------------------------ the compiled batch run
# ``ComplementaryDNRF.run`` (the live dashboard's path and the CLI's) takes the very steps of
# ``_step`` in one compiled loop; ``_step`` stays the readable reference (tests hold them
# to 1e-9). Scalars travel in one array (slots below), R and the two pre-filters apart.
# slots 0-5: the row bookkeeping every estimator shares (base.B_*)
C_T, C_SEEN, C_W_T, C_W = B_T, B_SEEN, B_W_T, B_W
(C_INIT, C_ACC_T, C_MAG_T, C_FIRST_T, C_FIRST_ACC_T, C_ALPHA, C_ACC_N, C_ACC_I, C_MAG_N,
 C_MAG_I) = range(B_N, B_N + 10)
C_THETA = 16     # 3: the compass angles of the last blend
C_NSTATE = 19
(CP_USE_GYR, CP_USE_ACC, CP_USE_MAG, CP_MAX_GAP, CP_GYR_HOLD, CP_AM_HOLD, CP_TAU, CP_EXACT) = range(8)
CP_N = 8


@compiled
def _ma_push(buf, s, n_slot, i_slot, v):
    k = buf.shape[0]
    i = int(s[i_slot])
    buf[i] = v
    s[i_slot] = (i + 1) % k
    s[n_slot] = min(s[n_slot] + 1.0, k)


@compiled
def _ma_mean(buf, n):
    """MovingAverage.mean: the last sample for a window of 1, else the mean of the n held."""
    if buf.shape[0] == 1:
        return buf[0].copy()
    out = np.zeros(3)
    for j in range(n):
        out += buf[j]
    return out / n


@compiled
def _fresh(t_sample, t, enabled, hold):
    return enabled and t - t_sample <= hold


@compiled
def _dnrf_align(s, R, p, abuf, mbuf, t, as_, ms, f):
    has_acc = _fresh(s[C_ACC_T], t, p[CP_USE_ACC] > 0.5, p[CP_AM_HOLD])
    has_mag = _fresh(s[C_MAG_T], t, p[CP_USE_MAG] > 0.5, p[CP_AM_HOLD])
    if has_acc:
        up = _ma_mean(abuf, int(s[C_ACC_N]))
        if has_mag:
            R[:, :] = qm.compass_matrix(up, _ma_mean(mbuf, int(s[C_MAG_N])), np.eye(3))
        else:
            e = euler_from_matrix(qm.compass_matrix(up, np.array([0.0, 1.0, 0.0]), np.eye(3)))
            e[0] = 0.0
            R[:, :] = matrix_from_euler(e)
    elif has_mag:
        R[:, :] = qm.compass_matrix(np.array([0.0, 0.0, 1.0]), _ma_mean(mbuf, int(s[C_MAG_N])),
                                    np.eye(3))
    else:
        R[:, :] = np.eye(3)
    s[C_THETA:C_THETA + 3] = euler_from_matrix(R)
    s[C_INIT] = 1.0
    if as_ == R_USED:
        f[F_ACC] = R_INIT
    if ms == R_USED:
        f[F_MAG] = R_INIT
    if as_ != R_USED and ms != R_USED:   # aligned on a gyroscope row (from the pre-filters)
        f[F_GYR] = R_INIT


@compiled
def _dnrf_row(s, R, p, abuf, mbuf, t, gyr, acc, mag, f):
    """One row of the DNRF (see the module doc): the valid accelerometer/magnetometer
    samples into the pre-filters, then the alignment or the gyroscope step and the blend.
    ``s`` the state slots above, ``R`` and the pre-filter buffers in place, ``f`` the
    row's flag record. Uncompiled: ``_dnrf_row.py_func``."""
    use_gyr, use_acc, use_mag = p[CP_USE_GYR] > 0.5, p[CP_USE_ACC] > 0.5, p[CP_USE_MAG] > 0.5
    go, dt, gs, as_, ms, has_w, w = begin_row(s, t, gyr, acc, mag, use_gyr, use_acc, use_mag,
                                              p[CP_MAX_GAP], p[CP_GYR_HOLD], f)
    if not go:
        return
    if not has_w:
        w = np.zeros(3)
    if as_ == R_USED:   # the pre-filters take the valid samples
        _ma_push(abuf, s, C_ACC_N, C_ACC_I, acc)
        s[C_ACC_T] = t
        f[F_ACC_VAL] = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
    if ms == R_USED:
        _ma_push(mbuf, s, C_MAG_N, C_MAG_I, mag)
        s[C_MAG_T] = t
        f[F_MAG_VAL] = math.sqrt(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2])
    if s[C_INIT] < 0.5:   # the alignment: accelerometer + magnetometer, or what there is
        if gs == R_USED:
            f[F_GYR] = R_WAIT
        if as_ == R_USED:
            f[F_ACC] = R_WAIT
        if ms == R_USED:
            f[F_MAG] = R_WAIT
        if s[C_FIRST_T] != s[C_FIRST_T]:
            s[C_FIRST_T] = t
        if as_ == R_USED and s[C_FIRST_ACC_T] != s[C_FIRST_ACC_T]:
            s[C_FIRST_ACC_T] = t
        has_acc = _fresh(s[C_ACC_T], t, use_acc, p[CP_AM_HOLD])
        has_mag = _fresh(s[C_MAG_T], t, use_mag, p[CP_AM_HOLD])
        if has_acc and (has_mag or not use_mag or t - s[C_FIRST_ACC_T] >= ALIGN_WAIT_S):
            _dnrf_align(s, R, p, abuf, mbuf, t, as_, ms, f)
        elif s[C_FIRST_ACC_T] != s[C_FIRST_ACC_T] and (not use_acc or t - s[C_FIRST_T] >= ALIGN_WAIT_S) \
                and (has_mag or gs == R_USED):
            _dnrf_align(s, R, p, abuf, mbuf, t, as_, ms, f)
        return
    has_up = _fresh(s[C_ACC_T], t, use_acc, p[CP_AM_HOLD])
    has_ref = _fresh(s[C_MAG_T], t, use_mag, p[CP_AM_HOLD])
    up = _ma_mean(abuf, int(s[C_ACC_N])) if has_up else np.zeros(3)
    ref = _ma_mean(mbuf, int(s[C_MAG_N])) if has_ref else np.zeros(3)
    Rn, alpha, theta_am = dnrf_row(R, w, dt, has_w, p[CP_EXACT] > 0.5, up, has_up, ref, has_ref,
                                   p[CP_TAU])
    R[:, :] = Rn
    s[C_ALPHA] = alpha
    if has_up or has_ref:
        s[C_THETA:C_THETA + 3] = theta_am


@compiled
def dnrf_run(s, R, p, abuf, mbuf, T, G, A, M, Qout, Fout):
    """Batch: ``_dnrf_row`` for every row; the estimate and flags after each."""
    for k in range(T.shape[0]):
        _dnrf_row(s, R, p, abuf, mbuf, T[k], G[k], A[k], M[k], Fout[k])
        Qout[k, :] = qm.quat_from_matrix(R)


# ------------------------------------------------------------------ pre-filter

class MovingAverage:
    """Mean of the last ``window`` vectors pushed (the paper's pre-filter, Section II-B)."""

    def __init__(self, window: int):
        self.buf = np.zeros((max(1, int(window)), 3))
        self.n = 0        # samples held (<= window)
        self.i = 0        # next slot

    def resize(self, window: int) -> None:
        """Keep the newest samples that fit the new window."""
        window = max(1, int(window))
        if window == self.buf.shape[0]:
            return
        old = self.values()
        self.buf = np.zeros((window, 3))
        self.n = self.i = 0
        for v in old[-window:]:
            self.push(v)

    def values(self) -> np.ndarray:
        """The held samples, oldest first."""
        k = self.buf.shape[0]
        idx = [(self.i - self.n + j) % k for j in range(self.n)]
        return self.buf[idx]

    def push(self, v: np.ndarray) -> None:
        self.buf[self.i] = v
        self.i = (self.i + 1) % self.buf.shape[0]
        self.n = min(self.n + 1, self.buf.shape[0])

    def mean(self) -> np.ndarray:
        """The filtered vector (the slots 0..n-1 are the filled ones)."""
        if self.buf.shape[0] == 1:
            return self.buf[0].copy()
        return self.buf[: self.n].mean(axis=0)


# ------------------------------------------------------------------ the estimator

class ComplementaryDNRF(Estimator):
    name = "complementary"
    title = "Complementary filter (DNRF)"
    Params = ComplementaryParams

    def _on_params(self) -> None:
        p = self._params
        self._pv = np.array([p.use_gyr, p.use_acc, p.use_mag, p.max_gap, p.gyr_hold, p.am_hold,
                             float(p.tau), p.gyro_update == "exact"], dtype=float)
        st = getattr(self, "_s", None)
        if st is None:
            return
        w = int(p.ma_window)
        for ma, n_slot, i_slot in ((self._acc_ma, C_ACC_N, C_ACC_I),
                                   (self._mag_ma, C_MAG_N, C_MAG_I)):
            ma.n, ma.i = int(st[n_slot]), int(st[i_slot])
            ma.resize(w)
            st[n_slot], st[i_slot] = ma.n, ma.i

    # the moving averages' fill and next slot are in _s (C_*_N, C_*_I): the compiled row
    # keeps them there; MovingAverage.n/.i are read from them on a parameter change
    STATE = Estimator.STATE + ("R", "_s", "_acc_ma.buf", "_mag_ma.buf")   # derived: _pv

    def _state_error(self) -> str | None:
        w = int(self._params.ma_window)
        for ma, n_slot, i_slot in ((self._acc_ma, C_ACC_N, C_ACC_I),
                                   (self._mag_ma, C_MAG_N, C_MAG_I)):
            n, i = self._s[n_slot], self._s[i_slot]
            if not (index_ok(n, w + 1) and index_ok(i, w)) or ma.buf.shape != (w, 3):
                return f"moving-average slots n={n!r}, i={i!r} for a window of {w}"
        return super()._state_error()

    def _reset_state(self) -> None:
        # the whole mutable state in arrays the compiled rows update in place: the scalars
        # (slots C_*), R and the two pre-filters' buffers (their fill and next slot in C_*)
        w = int(self._params.ma_window)
        self.R = np.eye(3)
        self._acc_ma = MovingAverage(w)
        self._mag_ma = MovingAverage(w)
        s = np.full(C_NSTATE, np.nan)
        s[C_SEEN], s[C_INIT] = 0.0, 0.0
        s[C_ACC_N] = s[C_ACC_I] = s[C_MAG_N] = s[C_MAG_I] = 0.0
        self._s = s

    # ------------------------------------------------------------------ one row
    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        """One row through the compiled ``_dnrf_row`` (the one implementation)."""
        dnrf_run(self._s, self.R, self._pv, self._acc_ma.buf, self._mag_ma.buf,
                 np.array([t], dtype=float), gyr.reshape(1, 3), acc.reshape(1, 3),
                 mag.reshape(1, 3), np.empty((1, 4)), flags.reshape(1, -1))

    # ------------------------------------------------------------------ batch (compiled)
    def _run_rows(self, t, G, A, M, O, qs, flags) -> None:
        """Rows in order through the compiled ``dnrf_run`` (the same steps as ``_step``)."""
        dnrf_run(self._s, self.R, self._pv, self._acc_ma.buf, self._mag_ma.buf, t, G, A, M, qs,
                 flags)

    @property
    def _init(self) -> bool:
        return bool(self._s[C_INIT] > 0.5)

    @property
    def _alpha(self) -> float:
        return float(self._s[C_ALPHA])

    @property
    def _theta_am(self) -> np.ndarray:
        return self._s[C_THETA:C_THETA + 3].copy()

    # ------------------------------------------------------------------ read-outs
    @property
    def initialized(self) -> bool:
        return self._init

    @property
    def q(self) -> np.ndarray:
        return qm.quat_from_matrix(self.R)

    def attitude_cov(self) -> None:
        return None

    def diagnostics(self) -> Diagnostics:
        """α of the last blend (NaN: none made) and the compass angles (rad)."""
        y, p, r = (float(v) for v in self._theta_am)
        return Diagnostics(alpha=float(self._alpha), am_yaw=y, am_pitch=p, am_roll=r,
                           tau=float(self._params.tau), ma_window=int(self._params.ma_window))
