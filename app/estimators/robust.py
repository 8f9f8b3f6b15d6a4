"""``robust``: orientlab's default estimator, an error-state EKF built for real phones.

Structure (4c) of the lab manual (gyroscope as input, its bias in the state) in the
error-state (multiplicative) form: the nominal attitude ``q`` is a unit quaternion; the
filter's state is the small rotation ``δθ`` (world frame, ``q_true = exp(δθ) ⊗ q``) and
the gyroscope bias ``b`` (sensor frame), 6 states with a well-conditioned 6x6 ``P``
(no covariance along the unit-norm constraint, no renormalisation hack).

What makes it accurate on real data (see ``shared/notes/robust-orientation.md``):

- **Tilt from an inertial low-pass of the accelerometer.** Each specific-force sample
  is rotated into the world frame and low-pass filtered there (``acc_tau``, ~3 s), so
  the phone's accelerations, which average to zero, cancel, while gravity stays. The
  filtered direction is the measurement (2 components, ``h = (-δθy, δθx)``); the
  filter state is rotated with every correction, so it always lives in the current
  estimate's world frame. Every valid sample enters the low-pass (leaving out the
  peaks of a movement would bias its mean); an innovation (NIS) gate, and optionally
  a norm band (off by default: it costs accuracy on real data), hold the correction.
- **Heading only from the magnetometer.** The field is rotated into the world frame
  with the current tilt and only its horizontal direction is used (scalar ``h = δθz``);
  the gain is masked so this update can never tilt the attitude.
- **Magnetic disturbance detection.** Field strength and dip angle are compared with
  a reference learned slowly while undisturbed (``mag_norm_gate_rel``,
  ``mag_dip_gate``); a persistent new homogeneous field (stable strength and dip
  while the phone turns for ``mag_new_field_time``) becomes the new reference; after
  ``mag_max_reject`` seconds of rejection the reference is re-learned.
- **Rest detection** (gyroscope and accelerometer both quiet for ``rest_time``):
  the low-passed gyroscope is then a direct measurement of the bias.
- **Measurement noise as densities** (``tilt_noise``, ``heading_noise`` in rad·√s):
  ``R = σ²/Δt`` per update, so the correction time constants, ``tilt_noise /
  gyr_noise`` and ``heading_noise / gyr_noise``, do not depend on the sample rates.

Every update goes through :func:`app.estimators.kalman.correct`. The per-row code is
numba-compiled (``robust_step``); ``robust_run`` loops it over arrays for batch
use. The same functions run uncompiled (``.py_func``) as the readable numpy reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .. import quaternion as qm
from ..params import CommonParams, DEG, param
from .base import (F_ACC, F_ACC_NIS, F_ACC_VAL, F_GYR, F_MAG, F_MAG_NIS, F_MAG_VAL, F_REST,
                   F_TIME, NFLAGS, R_DIP, R_INIT, R_LATE, R_NIS, R_NORM, R_REST,
                   R_USED, R_WAIT, R_GAP, T_BACKWARD, T_GAP, ALIGN_WAIT_S, BatchResult,
                   Estimator, row_prologue)
from .kalman import correct

GRAVITY = 9.81


@dataclass(frozen=True)
class RobustParams(CommonParams):
    gyr_noise: float = param(0.005, unit="rad/√s", lo=1e-6, hi=1.0, log=True, user_unit="deg/√s",
                             user_scale=DEG, doc="gyroscope noise density (attitude random walk)")
    bias_noise: float = param(3e-5, unit="rad/s/√s", lo=0.0, hi=0.1, log=True, user_unit="deg/s/√s",
                              user_scale=DEG, doc="gyroscope bias random walk")
    bias_init: float = param(0.05, unit="rad/s", lo=0.0, hi=1.0, log=True, user_unit="deg/s",
                             user_scale=DEG, doc="σ of the gyroscope bias at the start")
    gyr_bias: tuple = param((0.0, 0.0, 0.0), unit="rad/s", lo=-1.0, hi=1.0, tunable=False,
                            doc="initial gyroscope bias (calibration)")
    tilt_noise: float = param(0.02, unit="rad·√s", lo=1e-5, hi=10.0, log=True, user_unit="deg·√s",
                              user_scale=DEG, doc="noise density of the low-passed gravity direction")
    acc_tau: float = param(1.0, unit="s", lo=0.0, hi=60.0,
                           doc="time constant of the inertial low-pass of the accelerometer")
    acc_band_rel: float = param(0.0, lo=0.0, hi=2.0,
                                doc="tilt corrections pause while | |a| - g | > this × g (every sample "
                                    "still enters the low-pass); 0: off")
    acc_nis_gate: float = param(30.0, lo=0.0, hi=1000.0,
                                doc="NIS gate of the tilt update (χ², 2 dof); 0: off")
    heading_noise: float = param(0.1, unit="rad·√s", lo=1e-5, hi=10.0, log=True, user_unit="deg·√s",
                                 user_scale=DEG, doc="noise density of the magnetometer heading")
    mag_nis_gate: float = param(30.0, lo=0.0, hi=1000.0,
                                doc="NIS gate of the heading update (χ², 1 dof); 0: off")
    mag_norm_gate_rel: float = param(0.06, lo=0.0, hi=2.0,
                                     doc="field strength may differ from the reference by this fraction; 0: off")
    mag_dip_gate: float = param(15.0 / DEG, unit="rad", lo=0.0, hi=1.6, user_unit="deg", user_scale=DEG,
                                doc="dip angle may differ from the reference by this much; 0: off")
    mag_ref_tau: float = param(30.0, unit="s", lo=0.1, hi=3600.0,
                               doc="time constant of learning the field reference while undisturbed")
    mag_new_field_time: float = param(20.0, unit="s", lo=0.0, hi=600.0,
                                      doc="a new homogeneous field is accepted after this long while turning")
    mag_new_min_rate: float = param(20.0 / DEG, unit="rad/s", lo=0.0, hi=10.0, user_unit="deg/s",
                                    user_scale=DEG, doc="turn rate that counts towards accepting a new field")
    mag_max_reject: float = param(60.0, unit="s", lo=0.0, hi=3600.0,
                                  doc="after this long rejected, the field reference is re-learned; 0: never")
    rest_gyr_th: float = param(2.0 / DEG, unit="rad/s", lo=0.0, hi=1.0, user_unit="deg/s", user_scale=DEG,
                               doc="rest: gyroscope deviation from its low-pass below this")
    rest_acc_th: float = param(0.5, unit="m/s²", lo=0.0, hi=10.0,
                               doc="rest: accelerometer deviation from its low-pass below this")
    rest_time: float = param(1.5, unit="s", lo=0.0, hi=60.0, doc="quiet this long = at rest; 0: no rest detection")
    rest_noise: float = param(0.005, unit="rad/s·√s", lo=1e-6, hi=1.0, log=True, user_unit="deg/s·√s",
                              user_scale=DEG, doc="noise density of the bias measurement at rest")
    rw_noise: float = param(0.5, unit="rad/√s", lo=1e-4, hi=10.0, log=True,
                            doc="attitude random walk without gyroscope")
    update_rate_hz: float = param(50.0, unit="Hz", lo=0.0, hi=10000.0,
                                  doc="most measurement updates per second and sensor (the low-passes "
                                      "and averages see every sample); 0: every sample")


# ----------------------------------------------------------------- layouts
# parameter vector (derived coefficients included), built by RobustEKF._on_params
(P_USE_GYR, P_USE_ACC, P_USE_MAG, P_MAX_GAP, P_GYR_HOLD, P_GYR_NOISE, P_BIAS_NOISE, P_BIAS_INIT,
 P_TILT_NOISE, P_ACC_TAU, P_ACC_BAND, P_ACC_NIS, P_HEAD_NOISE, P_MAG_NIS, P_MAG_NORM, P_MAG_DIP,
 P_MAG_REF_TAU, P_MAG_NEW_T, P_MAG_NEW_RATE, P_MAG_MAX_REJ, P_REST_GYR, P_REST_ACC, P_REST_T,
 P_REST_NOISE, P_RW_NOISE, P_B0X, P_B0Y, P_B0Z, P_UPD_DT, NPARAM) = range(30)

# state vector (everything but P)
S_Q = 0          # 4: nominal attitude
S_B = 4          # 3: gyroscope bias
S_ALP = 7        # 3: low-passed specific force, world frame of the estimate
S_GLP = 10       # 3: low-passed gyroscope (rest detection)
S_AL2 = 13       # 3: low-passed accelerometer, sensor frame (rest detection)
S_REST_T = 16    # s quiet so far
S_T = 17         # time of the last row
S_INIT = 18      # 1 once aligned
S_W = 19         # 3: held gyroscope sample
S_W_T = 22       # its time
S_WAIT_T = 23    # time of an accelerometer sample waiting for alignment (NaN: none)
S_WAIT = 24      # 3: that sample
S_REF_N = 27     # field reference: strength (µT)
S_REF_D = 28     # field reference: dip (rad, elevation of the field: negative in the north)
S_REF_OK = 29    # 1 once there is a reference
S_CAND_N = 30    # candidate new field: strength
S_CAND_D = 31    # candidate new field: dip
S_CAND_T = 32    # s the candidate has been stable while turning
S_REJ_T = 33     # s of continuous magnetic rejection
S_T0 = 34        # time of the alignment
S_MAG_T = 35     # time of the last magnetometer update attempt
S_ACC_T = 36     # time of the last accelerometer sample
S_GLP_T = 37     # time of the last gyroscope sample in the rest low-pass (NaN: none yet)
S_REST = 38      # 1 at rest
S_NIS_REJ_T = 39 # s of continuous heading-NIS rejection
S_ACC_UPD_T = 40 # s of used accelerometer samples since the last tilt update
S_REST_UPD_T = 41  # s at rest since the last bias update
S_MAG_SUM = 42   # 3: sum of world-frame field samples since the last heading update
S_MAG_CNT = 45   # how many
S_MAG_UPD_T = 46 # s of used magnetometer samples since the last heading update
S_AL2_T = 47     # likewise for the accelerometer
S_WCUR = 48      # 3: scratch: the rate integrated over the current row
S_SEEN = 51      # sensors seen at the time of the last row (bit mask)
NSTATE = 52

_MASK_HEADING = np.array([0.0, 0.0, 1.0, 1.0, 1.0, 1.0])

# Measurement models in the error state x = [δθ (world), δb]. With q_true = exp(δθ) ⊗ q,
# a world-frame vector v seen through the estimate is v - δθ × v, so dv/dδθ = [v]×.
# The Jacobians below follow from that (tested against finite differences).
H_BIAS = np.hstack((np.zeros((3, 3)), np.eye(3)))  # at rest the low-passed gyroscope measures b


@njit(cache=True)
def tilt_innovation(a_world):
    """Horizontal components of the (low-passed) specific-force direction in the
    estimate's world frame: zero when the estimate's 'up' is right."""
    n = qm.norm3(a_world)
    out = np.empty(2)
    out[0] = a_world[0] / n
    out[1] = a_world[1] / n
    return out


@njit(cache=True)
def tilt_jacobian(a_world):
    """d tilt_innovation / dx (2x6): (I - â âᵀ)/|a| [a]× restricted to x, y; for
    a along +z it is [[0, -1, 0], [1, 0, 0]] (the tilt error, rotated)."""
    n = qm.norm3(a_world)
    u0, u1, u2 = a_world[0] / n, a_world[1] / n, a_world[2] / n
    C = qm.skew(np.array([u0, u1, u2]))  # [â]×
    H = np.zeros((2, 6))
    u = (u0, u1, u2)
    for r in range(2):
        for c in range(3):
            v = C[r, c]
            for k in range(3):
                v -= u[r] * u[k] * C[k, c]
            H[r, c] = v
    return H


@njit(cache=True)
def heading_jacobian(m_world):
    """d heading_innovation / dx (1x6): (-mx mz, -my mz, mx² + my²) / (mx² + my²).
    The tilt columns are not zero (a tilt error changes the apparent heading of a
    dipping field); the update masks them, so heading never tilts the estimate,
    but S accounts for the tilt uncertainty."""
    h2 = m_world[0] ** 2 + m_world[1] ** 2
    H = np.zeros((1, 6))
    H[0, 0] = -m_world[0] * m_world[2] / h2
    H[0, 1] = -m_world[1] * m_world[2] / h2
    H[0, 2] = 1.0
    return H


@njit(cache=True)
def heading_innovation(m_world):
    """Angle (rad) of the horizontal field east of north: zero when the heading is right."""
    out = np.empty(1)
    out[0] = np.arctan2(m_world[0], m_world[1])
    return out


@njit(cache=True)
def _lp_coef(dt, tau):
    """First-order low-pass coefficient (the DNRF form 1 - τ/(τ+Δt))."""
    if tau <= 0.0:
        return 1.0
    return dt / (tau + dt)


@njit(cache=True)
def _inject(s, P, dx):
    """Apply an error-state correction: q <- exp(δθ) ⊗ q, b <- b + δb, and rotate
    the world-frame low-pass with the attitude so it stays in the estimate's frame."""
    dq = qm.quat_from_rotvec(dx[0:3])
    s[S_Q:S_Q + 4] = qm.normalize(qm.quat_mul(dq, s[S_Q:S_Q + 4]))
    for i in range(3):
        s[S_B + i] += dx[3 + i]
    s[S_ALP:S_ALP + 3] = qm.rotate(dq, s[S_ALP:S_ALP + 3])


@njit(cache=True)
def _align(s, P, p, t, acc, mag, use_mag):
    s[S_Q:S_Q + 4] = qm.q_from_acc_mag(acc, mag, use_mag)
    for i in range(3):
        s[S_B + i] = p[P_B0X + i]
    s[S_ALP:S_ALP + 3] = qm.rotate(s[S_Q:S_Q + 4], acc)
    P[:, :] = 0.0
    tilt0 = 10.0 * np.pi / 180.0
    head0 = (20.0 if use_mag else 180.0) * np.pi / 180.0
    P[0, 0] = tilt0 ** 2
    P[1, 1] = tilt0 ** 2
    P[2, 2] = head0 ** 2
    for i in range(3, 6):
        P[i, i] = max(p[P_BIAS_INIT], 1e-6) ** 2
    s[S_INIT] = 1.0
    s[S_T0] = t
    s[S_WAIT_T] = np.nan
    s[S_MAG_T] = t
    s[S_ACC_T] = t
    s[S_ACC_UPD_T] = 0.0
    s[S_REST_UPD_T] = 0.0
    s[S_MAG_CNT] = 0.0
    s[S_MAG_SUM:S_MAG_SUM + 3] = 0.0
    s[S_MAG_UPD_T] = 0.0
    s[S_REF_OK] = 0.0
    s[S_REJ_T] = 0.0
    s[S_CAND_T] = 0.0
    s[S_NIS_REJ_T] = 0.0


@njit(cache=True)
def _integrate(s, vx, vy, vz):
    """q <- q ⊗ exp(v) for the body-frame rotation vector v (exact, formula 2j), w >= 0."""
    a = np.sqrt(vx * vx + vy * vy + vz * vz)
    c = np.cos(0.5 * a)
    k = 0.5 if a < 1e-12 else np.sin(0.5 * a) / a
    x, y, z = vx * k, vy * k, vz * k
    q0, q1, q2, q3 = s[S_Q], s[S_Q + 1], s[S_Q + 2], s[S_Q + 3]
    r0 = q0 * c - q1 * x - q2 * y - q3 * z
    r1 = q0 * x + q1 * c + q2 * z - q3 * y
    r2 = q0 * y - q1 * z + q2 * c + q3 * x
    r3 = q0 * z + q1 * y - q2 * x + q3 * c
    n = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
    if r0 < 0.0:
        n = -n
    s[S_Q], s[S_Q + 1], s[S_Q + 2], s[S_Q + 3] = r0 / n, r1 / n, r2 / n, r3 / n


@njit(cache=True)
def _due(s, idx, dt, p):
    """Add the sample interval dt of a used sample to the accumulator ``s[idx]``;
    when it reaches 1/update_rate_hz, reset it and return (True, accumulated s).
    The accumulated time of *used* samples is what scales R = σ²/Δt, so an update
    after a long rejection is not mistaken for a long, information-rich average."""
    dt = min(max(dt, 0.0), 0.1)
    s[idx] += dt
    # half a sample of tolerance: 100 Hz data with jittery stamps still updates at 100 Hz
    if s[idx] >= p[P_UPD_DT] - 0.5 * dt and s[idx] > 0.0:
        acc = s[idx]
        s[idx] = 0.0
        return True, acc
    return False, s[idx]


@njit(cache=True)
def _predict(s, P, p, w, dt):
    """Time update over dt with the rate w (NaN: random walk without gyroscope)."""
    if np.isnan(w[0]):
        var = p[P_RW_NOISE] ** 2 * dt
        for i in range(3):
            P[i, i] += var
        bv = p[P_BIAS_NOISE] ** 2 * dt
        for i in range(3, 6):
            P[i, i] += bv
        return
    R = qm.Q(s[S_Q:S_Q + 4])
    _integrate(s, (w[0] - s[S_B]) * dt, (w[1] - s[S_B + 1]) * dt, (w[2] - s[S_B + 2]) * dt)
    # F = [[I, -R dt], [0, I]];  P <- F P F' + Qd, by blocks with T = R [Pbb | Pbt]:
    # Ptt += dt² T[:, :3] R' - dt (T[:, 3:] + T[:, 3:]');  Ptb -= dt T[:, :3]
    T = np.zeros((3, 6))
    for i in range(3):
        for k in range(3):
            r = R[i, k]
            for j in range(3):
                T[i, j] += r * P[3 + k, 3 + j]      # R Pbb
                T[i, 3 + j] += r * P[3 + k, j]      # R Pbt
    dt2 = dt * dt
    for i in range(3):
        for j in range(i, 3):
            v = -dt * (T[i, 3 + j] + T[j, 3 + i])
            for l in range(3):
                v += dt2 * T[i, l] * R[j, l]
            P[i, j] += v
            if j != i:
                P[j, i] = P[i, j]
    for i in range(3):
        for j in range(3):
            P[i, 3 + j] -= dt * T[i, j]
            P[3 + j, i] = P[i, 3 + j]
    gv = p[P_GYR_NOISE] ** 2 * dt
    bv = p[P_BIAS_NOISE] ** 2 * dt
    for i in range(3):
        P[i, i] += gv
        P[3 + i, 3 + i] += bv


@njit(cache=True)
def _lp_sensor(s, idx, idx_t, v, t, tau):
    """Low-pass ``s[idx:idx+3]`` towards v with the time since that sensor's last
    sample (a phone sends one sensor per row); returns |v - low-pass|."""
    if np.isnan(s[idx_t]):
        s[idx:idx + 3] = v
        s[idx_t] = t
        return 0.0
    k = _lp_coef(min(t - s[idx_t], 0.1), tau)
    s[idx_t] = t
    d2 = 0.0
    for i in range(3):
        s[idx + i] += k * (v[i] - s[idx + i])
        d2 += (v[i] - s[idx + i]) ** 2
    return np.sqrt(d2)


@njit(cache=True)
def _rest_update(s, P, p, t, gyr, acc, dt, has_gyr, has_acc, f):
    """Rest detection on the deviation of gyroscope and accelerometer from their
    low-passes; at rest the low-passed gyroscope measures the bias directly."""
    if p[P_REST_T] <= 0.0:
        s[S_REST] = 0.0
        return
    quiet = True
    if has_gyr and _lp_sensor(s, S_GLP, S_GLP_T, gyr, t, 0.5) > p[P_REST_GYR]:
        quiet = False
    if has_acc and _lp_sensor(s, S_AL2, S_AL2_T, acc, t, 0.5) > p[P_REST_ACC]:
        quiet = False
    s[S_REST_T] = s[S_REST_T] + dt if quiet else 0.0
    s[S_REST] = 1.0 if s[S_REST_T] >= p[P_REST_T] else 0.0
    f[F_REST] = s[S_REST]
    if s[S_REST] == 0.0:
        s[S_REST_UPD_T] = 0.0
        return
    # time at rest since the last bias update; the update runs on a gyroscope row
    s[S_REST_UPD_T] += min(dt, 0.1)
    if not has_gyr or s[S_REST_UPD_T] < p[P_UPD_DT] - 0.5 * dt or s[S_REST_UPD_T] <= 0.0:
        return
    elapsed = s[S_REST_UPD_T]
    s[S_REST_UPD_T] = 0.0
    Rm = (p[P_REST_NOISE] ** 2 / elapsed) * np.eye(3)
    innov = s[S_GLP:S_GLP + 3] - s[S_B:S_B + 3]
    ok, nis, dx = correct(P, H_BIAS, Rm, innov, 0.0)
    if ok:
        _inject(s, P, dx)
        f[F_GYR] = R_REST


@njit(cache=True)
def _acc_update(s, P, p, t, acc, f):
    n = qm.norm3(acc)
    f[F_ACC_VAL] = n
    dt = t - s[S_ACC_T] if np.isfinite(s[S_ACC_T]) else 0.0
    s[S_ACC_T] = t
    if dt <= 0.0:
        dt = 1e-3
    # inertial low-pass, with a running mean while younger than acc_tau (fast start)
    k = _lp_coef(dt, p[P_ACC_TAU])
    age = t - s[S_T0]
    if age > 0.0 and dt / (age + dt) > k:
        k = dt / (age + dt)
    aw = qm.rotate(s[S_Q:S_Q + 4], acc)
    for i in range(3):
        s[S_ALP + i] += k * (aw[i] - s[S_ALP + i])
    f[F_ACC] = R_USED  # in the low-pass; the correction below runs at most at update_rate_hz
    # Every valid sample enters the low-pass: the specific force only averages out if
    # none is left out (refusing the peaks of a movement would bias the mean). The norm
    # band gates the *correction* instead: no tilt update while |a| is far from g.
    if p[P_ACC_BAND] > 0.0 and abs(n - GRAVITY) > p[P_ACC_BAND] * GRAVITY:
        f[F_ACC] = R_NORM
        return
    due, elapsed = _due(s, S_ACC_UPD_T, dt, p)
    if not due:
        return
    dt = elapsed
    a = s[S_ALP:S_ALP + 3]
    an = qm.norm3(a)
    if an < 1e-6:
        return
    Rm = (p[P_TILT_NOISE] ** 2 / dt) * np.eye(2)
    ok, nis, dx = correct(P, tilt_jacobian(a), Rm, tilt_innovation(a), p[P_ACC_NIS])
    f[F_ACC_NIS] = nis
    if ok:
        _inject(s, P, dx)
        f[F_ACC] = R_USED
    else:
        f[F_ACC] = R_NIS
        f[F_ACC_VAL] = nis


@njit(cache=True)
def _mag_update(s, P, p, t, mag, w, f):
    mw = qm.rotate(s[S_Q:S_Q + 4], mag)
    n = qm.norm3(mw)
    dip = np.arcsin(min(1.0, max(-1.0, mw[2] / n)))
    dt = t - s[S_MAG_T] if np.isfinite(s[S_MAG_T]) else 0.0
    s[S_MAG_T] = t
    if s[S_REF_OK] == 0.0:
        s[S_REF_N] = n
        s[S_REF_D] = dip
        s[S_CAND_N] = n
        s[S_CAND_D] = dip
        s[S_REF_OK] = 1.0
    # candidate for a new homogeneous field: stable strength and dip while turning
    kc = _lp_coef(dt, 2.0) if dt > 0 else 0.0
    cn_dev = abs(n - s[S_CAND_N]) / max(s[S_CAND_N], 1e-6)
    cd_dev = abs(dip - s[S_CAND_D])
    if cn_dev <= max(p[P_MAG_NORM], 0.05) and cd_dev <= max(p[P_MAG_DIP], 0.05):
        rate = 0.0 if np.isnan(w[0]) else qm.norm3(w)
        if rate >= p[P_MAG_NEW_RATE]:
            s[S_CAND_T] += dt
        s[S_CAND_N] += kc * (n - s[S_CAND_N])
        s[S_CAND_D] += kc * (dip - s[S_CAND_D])
    else:
        s[S_CAND_N] = n
        s[S_CAND_D] = dip
        s[S_CAND_T] = 0.0
    n_dev = abs(n - s[S_REF_N]) / s[S_REF_N]
    d_dev = abs(dip - s[S_REF_D])
    reason = R_USED
    if p[P_MAG_NORM] > 0.0 and n_dev > p[P_MAG_NORM]:
        reason = R_NORM
        f[F_MAG_VAL] = n
    elif p[P_MAG_DIP] > 0.0 and d_dev > p[P_MAG_DIP]:
        reason = R_DIP
        f[F_MAG_VAL] = d_dev
    if reason != R_USED:
        s[S_REJ_T] += dt
        relearn = p[P_MAG_MAX_REJ] > 0.0 and s[S_REJ_T] >= p[P_MAG_MAX_REJ]
        new_field = s[S_CAND_T] >= p[P_MAG_NEW_T]
        if relearn or new_field:
            s[S_REF_N] = s[S_CAND_N]
            s[S_REF_D] = s[S_CAND_D]
            s[S_REJ_T] = 0.0
            s[S_CAND_T] = 0.0
            # the heading may have drifted meanwhile: let the next updates pull harder
            P[2, 2] += (10.0 * np.pi / 180.0) ** 2
        f[F_MAG] = reason
        return
    s[S_REJ_T] = 0.0
    kr = _lp_coef(dt, p[P_MAG_REF_TAU]) if dt > 0 else 0.0
    s[S_REF_N] += kr * (n - s[S_REF_N])
    s[S_REF_D] += kr * (dip - s[S_REF_D])
    f[F_MAG_VAL] = n
    f[F_MAG] = R_USED
    # accepted samples are averaged in the world frame; the heading correction with
    # their mean runs at most at update_rate_hz
    for i in range(3):
        s[S_MAG_SUM + i] += mw[i]
    s[S_MAG_CNT] += 1.0
    due, elapsed = _due(s, S_MAG_UPD_T, dt, p)
    if not due:
        return
    mx = s[S_MAG_SUM] / s[S_MAG_CNT]
    my = s[S_MAG_SUM + 1] / s[S_MAG_CNT]
    mz = s[S_MAG_SUM + 2] / s[S_MAG_CNT]
    s[S_MAG_SUM:S_MAG_SUM + 3] = 0.0
    s[S_MAG_CNT] = 0.0
    hn = np.sqrt(mx * mx + my * my)
    if hn < 1e-3 * n:
        return  # field (almost) vertical: no heading information
    m_mean = np.empty(3)
    m_mean[0], m_mean[1], m_mean[2] = mx, my, mz
    innov = heading_innovation(m_mean)
    Rm = np.empty((1, 1))
    Rm[0, 0] = p[P_HEAD_NOISE] ** 2 / elapsed
    gate = p[P_MAG_NIS]
    if s[S_NIS_REJ_T] > 10.0:
        gate = 0.0  # rejected for long with a plausible field: the estimate is what is wrong
    ok, nis, dx = correct(P, heading_jacobian(m_mean), Rm, innov, gate, _MASK_HEADING)
    f[F_MAG_NIS] = nis
    if ok:
        _inject(s, P, dx)
        s[S_NIS_REJ_T] = 0.0
    else:
        f[F_MAG] = R_NIS
        f[F_MAG_VAL] = nis
        s[S_NIS_REJ_T] += elapsed


@njit(cache=True)
def robust_step(s, P, p, t, gyr, acc, mag, f):
    """Process one row: time update, rest detection, tilt update, heading update."""
    dt, issue, seen, gs, as_, ms = row_prologue(s[S_T], t, p[P_MAX_GAP], int(s[S_SEEN]), gyr, acc,
                                                mag, p[P_USE_GYR] > 0.5, p[P_USE_ACC] > 0.5,
                                                p[P_USE_MAG] > 0.5)
    s[S_SEEN] = seen
    f[F_TIME] = issue
    if issue == T_BACKWARD:
        f[F_GYR] = R_LATE if gs == R_USED else gs
        f[F_ACC] = R_LATE if as_ == R_USED else as_
        f[F_MAG] = R_LATE if ms == R_USED else ms
        return
    f[F_GYR] = gs
    f[F_ACC] = as_
    f[F_MAG] = ms
    s[S_T] = t
    w = s[S_WCUR:S_WCUR + 3]  # the rate integrated over this row (a slot of the state)
    w[:] = np.nan
    if p[P_USE_GYR] > 0.5:
        if gs == R_USED:
            w[:] = gyr
            s[S_W:S_W + 3] = gyr
            s[S_W_T] = t
        elif np.isfinite(s[S_W_T]) and t - s[S_W_T] <= p[P_GYR_HOLD]:
            w[:] = s[S_W:S_W + 3]
    if issue == T_GAP:
        if gs == R_USED:
            f[F_GYR] = R_GAP
        w[:] = np.nan

    if s[S_INIT] == 0.0:
        _try_align(s, P, p, t, acc, mag, gs, as_, ms, f)
        return
    if dt > 0.0:
        _predict(s, P, p, w, dt)
    _rest_update(s, P, p, t, gyr, acc, dt, gs == R_USED, as_ == R_USED, f)
    if as_ == R_USED:
        _acc_update(s, P, p, t, acc, f)
    if ms == R_USED:
        wb = w - s[S_B:S_B + 3]
        _mag_update(s, P, p, t, mag, wb, f)


@njit(cache=True)
def _try_align(s, P, p, t, acc, mag, gs, as_, ms, f):
    if gs == R_USED:
        f[F_GYR] = R_WAIT
    if as_ == R_USED:
        f[F_ACC] = R_WAIT
        if p[P_USE_MAG] < 0.5:
            _align(s, P, p, t, acc, mag, False)
            f[F_ACC] = R_INIT
            return
        s[S_WAIT_T] = t
        s[S_WAIT:S_WAIT + 3] = acc
    if ms == R_USED:
        f[F_MAG] = R_WAIT
        if np.isfinite(s[S_WAIT_T]):
            _align(s, P, p, t, s[S_WAIT:S_WAIT + 3].copy(), mag, True)
            f[F_MAG] = R_INIT
            return
    if np.isfinite(s[S_WAIT_T]) and t - s[S_WAIT_T] > ALIGN_WAIT_S:
        _align(s, P, p, t, s[S_WAIT:S_WAIT + 3].copy(), mag, False)
        f[F_ACC] = R_INIT
        return
    if p[P_USE_ACC] < 0.5 and (ms == R_USED or gs == R_USED):
        # no accelerometer: start level, heading from the field if there is one
        up = np.array([0.0, 0.0, GRAVITY])
        _align(s, P, p, t, up, mag, ms == R_USED)
        P[0, 0] = (30.0 * np.pi / 180.0) ** 2
        P[1, 1] = P[0, 0]
        f[F_MAG if ms == R_USED else F_GYR] = R_INIT


@njit(cache=True)
def robust_run(s, P, p, T, G, A, M, Qout, Fout):
    """Batch: ``robust_step`` for every row; the estimate and flags after each."""
    for k in range(T.shape[0]):
        f = Fout[k]
        f[:] = np.nan
        f[F_GYR] = 1.0
        f[F_ACC] = 1.0
        f[F_MAG] = 1.0
        f[F_REST] = 0.0
        f[F_TIME] = 0.0
        robust_step(s, P, p, T[k], G[k], A[k], M[k], f)
        Qout[k, :] = s[S_Q:S_Q + 4]


def new_state() -> np.ndarray:
    s = np.zeros(NSTATE)
    s[S_Q] = 1.0
    for i in (S_T, S_W_T, S_WAIT_T, S_T0, S_MAG_T, S_ACC_T, S_GLP_T, S_AL2_T):
        s[i] = np.nan
    return s


class RobustEKF(Estimator):
    name = "robust"
    title = "Robust error-state EKF (default)"
    Params = RobustParams

    def _on_params(self) -> None:
        p = self._params
        v = np.zeros(NPARAM)
        v[P_USE_GYR], v[P_USE_ACC], v[P_USE_MAG] = float(p.use_gyr), float(p.use_acc), float(p.use_mag)
        v[P_MAX_GAP], v[P_GYR_HOLD] = p.max_gap, p.gyr_hold
        v[P_GYR_NOISE], v[P_BIAS_NOISE], v[P_BIAS_INIT] = p.gyr_noise, p.bias_noise, p.bias_init
        v[P_TILT_NOISE], v[P_ACC_TAU], v[P_ACC_BAND], v[P_ACC_NIS] = (p.tilt_noise, p.acc_tau,
                                                                       p.acc_band_rel, p.acc_nis_gate)
        v[P_HEAD_NOISE], v[P_MAG_NIS] = p.heading_noise, p.mag_nis_gate
        v[P_MAG_NORM], v[P_MAG_DIP], v[P_MAG_REF_TAU] = p.mag_norm_gate_rel, p.mag_dip_gate, p.mag_ref_tau
        v[P_MAG_NEW_T], v[P_MAG_NEW_RATE], v[P_MAG_MAX_REJ] = (p.mag_new_field_time, p.mag_new_min_rate,
                                                               p.mag_max_reject)
        v[P_REST_GYR], v[P_REST_ACC], v[P_REST_T], v[P_REST_NOISE] = (p.rest_gyr_th, p.rest_acc_th,
                                                                     p.rest_time, p.rest_noise)
        v[P_RW_NOISE] = p.rw_noise
        v[P_B0X:P_B0X + 3] = p.gyr_bias
        v[P_UPD_DT] = 1.0 / p.update_rate_hz if p.update_rate_hz > 0 else 0.0
        self._p = v

    def _reset_state(self) -> None:
        self._s = new_state()
        self._P = np.eye(6) * 1e-4

    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        robust_step(self._s, self._P, self._p, t, gyr, acc, mag, flags)
        self.t = self._s[S_T]

    def run(self, t, gyr=None, acc=None, mag=None, ori=None) -> BatchResult:
        t = np.ascontiguousarray(t, dtype=float)
        n = t.shape[0]
        arrs = [np.full((n, 3), np.nan) if x is None else np.ascontiguousarray(x, dtype=float)
                for x in (gyr, acc, mag)]
        for a in arrs:
            if a.shape != (n, 3):
                raise ValueError(f"expected shape ({n}, 3), got {a.shape}")
        qs = np.empty((n, 4))
        flags = np.empty((n, NFLAGS))
        robust_run(self._s, self._P, self._p, t, arrs[0], arrs[1], arrs[2], qs, flags)
        self.t = self._s[S_T]
        return BatchResult(t=t, q=qs, flags=flags)

    @property
    def initialized(self) -> bool:
        return bool(self._s[S_INIT])

    @property
    def q(self) -> np.ndarray:
        return self._s[S_Q:S_Q + 4].copy()

    def attitude_cov(self) -> np.ndarray:
        return self._P[0:3, 0:3].copy()

    @property
    def gyr_bias(self) -> np.ndarray:
        return self._s[S_B:S_B + 3].copy()

    @property
    def covariance(self) -> np.ndarray:
        return self._P.copy()

    def diagnostics(self) -> dict:
        p, s = self._params, self._s
        ref_n = s[S_REF_N] if s[S_REF_OK] else float("nan")
        return {
            "acc_band": (GRAVITY * (1 - p.acc_band_rel), GRAVITY * (1 + p.acc_band_rel))
            if p.acc_band_rel > 0 else None,
            "mag_band": (ref_n * (1 - p.mag_norm_gate_rel), ref_n * (1 + p.mag_norm_gate_rel))
            if p.mag_norm_gate_rel > 0 and s[S_REF_OK] else None,
            "mag_ref_norm": ref_n,
            # elevation of the field (rad): negative where it points down (north)
            "mag_ref_dip": s[S_REF_D] if s[S_REF_OK] else float("nan"),
            # the expected field in world coordinates (µT): north and the learned dip
            "m0": [0.0, ref_n * np.cos(s[S_REF_D]), ref_n * np.sin(s[S_REF_D])]
            if s[S_REF_OK] else None,
            "acc_lp_world": s[S_ALP:S_ALP + 3].tolist(),
            "gyr_bias": s[S_B:S_B + 3].tolist(),
            "rest": bool(s[S_REST]),
            "acc_nis_gate": p.acc_nis_gate,
            "mag_nis_gate": p.mag_nis_gate,
        }
