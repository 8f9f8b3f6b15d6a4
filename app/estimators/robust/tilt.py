"""The tilt: the accelerometer update, its inertial low-pass and the tilt loop's damping.

- **Tilt from an inertial low-pass of the accelerometer.** Each specific-force sample
  is rotated into the world frame and low-pass filtered there (``acc_tau``, 3 s), so
  the phone's accelerations, which average to zero, cancel, while gravity stays. The
  filtered direction is the measurement (2 components, ``h = (-δθy, δθx)``); it corrects
  the tilt only, never the heading (``_MASK_TILT``); the
  filter state is rotated with every correction, so it always lives in the current
  estimate's world frame (by how much: below). Every valid sample enters the low-pass
  (leaving out the peaks of a movement would bias its mean); optionally a norm band (off
  by default: it costs accuracy on real data) holds the correction. There is no NIS gate:
  the NIS is computed and flagged, never used to refuse.
- **A damped tilt loop** (``tilt_damping``). The low-pass (time constant τ =
  ``acc_tau``) and the corrections (time constant τc = 1/gain, from P) form a
  second-order loop. Turning the low-pass with every correction makes its poles real,
  -1/τ and -1/τc: overdamped, and a gyroscope drift d leaves d·(τ + τc) of tilt error.
  Turning it with a share ρ of each tilt correction gives s² + (1/τ + ρ/τc) s + 1/(τ τc):
  the same rejection of fast specific force (1/(τ τc ω²)), damping ζ set by ρ =
  2ζ√(τc/τ) - τc/τ, a drift error of d·(τc + ρτ) = d·2ζ/ωn with ωn = 1/√(τ τc).
  The defaults are VQF's: its damping, ζ = 1/√2 (its second-order Butterworth
  low-pass), and its low-pass time constant, τ = ``tauAcc`` = 3 s. At rest τc =
  ``tilt_noise / gyr_noise`` = 3 s as well, so ωn = 1/3 rad/s and ρ = 2ζ - 1 ≈ 0.41.
- **The accelerometer's lag** (``acc_delay_periods``, 0.5). A sample stands for the specific
  force over its period and is stamped at its end, while the attitude at the stamp has been
  propagated with the gyroscope's rate over that same period: the sample is half a period
  behind. In a steady turn about a horizontal axis that lag turns gravity back by rate × lag,
  a constant tilt (3 rad/s × 5 ms is 0.9°). Each sample is turned forward by the gyroscope's
  rate × the lag before it enters the low-pass; the period is measured from the stream (a
  low-pass of the sample intervals), so the lag follows the phone's rate.
- **A tilt more than 90° off is re-aligned.** Over ``acc_tau`` the phone's accelerations
  average out and the low-pass holds gravity, up; no motion makes it point below the
  horizon. When it does, the estimate's up is more than 90° off (it started from a sample
  with the wrong sign, or drifted without an accelerometer), and the tilt update cannot
  bring it back: its innovation, the low-pass's horizontal part, vanishes upside down as it
  does upright, and its Jacobian, taken at the low-pass, makes upside down a second stable
  point. So the filter is re-aligned from the samples, as at the start, keeping the bias it
  has learned (flag RECOVER, value: the angle, rad).
- **Specific force flagged.** An accelerometer sample far from the low-passed gravity
  (``acc_flag_angle``, ``acc_flag_rel``) is flagged ACCEL with the angle (it still
  enters the low-pass): a shake shows.
"""

from __future__ import annotations

import numpy as np

from app import quaternion as qm
from app.estimators.base import (F_ACC, F_ACC_NIS, F_ACC_VAL, R_ACCEL, R_NIS, R_NORM, R_RECOVER,
                                 R_USED)
from app.estimators.kalman import correct
from app.estimators.robust.bias import BIAS_UPD_S, motion_bias_update
from app.estimators.robust.params import PRM
from app.params import GRAVITY
from app.estimators.robust.state import (KF_WORK, S, inject, lp_coef, rotate3, turned_forward,
                                         update_is_due)
from app.jitcache import compiled

# The tilt update corrects the tilt only, never the heading, as the heading update never tilts:
# through the cross-covariances a dipping field's heading updates leave between tilt and heading,
# the accelerometer's errors, the specific force left in the low-pass and correlated for seconds
# (not the white noise the model assumes), would turn the heading (VQF's accelerometer correction
# never turns it either). Without a magnetometer the heading is then the gyroscope's alone.
_MASK_TILT = np.array([1.0, 1.0, 0.0, 0.0, 0.0, 0.0])

# Measurement models in the error state x = [δθ (world), δb]. With q_true = exp(δθ) ⊗ q,
# a world-frame vector v seen through the estimate is v - δθ × v, so dv/dδθ = [v]×.
# The Jacobians here and in :mod:`.heading` follow from that (tested against finite
# differences).


@compiled
def tilt_innovation(a_world):
    """Horizontal components of the (low-passed) specific-force direction in the
    estimate's world frame: zero when the estimate's 'up' is right."""
    n = qm.norm3(a_world)
    out = np.empty(2)
    out[0] = a_world[0] / n
    out[1] = a_world[1] / n
    return out


@compiled
def tilt_jacobian(a_world):
    """d tilt_innovation / dx (2x6): (I - â âᵀ)/|a| [a]× restricted to x, y; for
    a along +z it is [[0, -1, 0], [1, 0, 0]] (the tilt error, rotated)."""
    n = qm.norm3(a_world)
    u0, u1, u2 = a_world[0] / n, a_world[1] / n, a_world[2] / n
    H = np.zeros((2, 6))
    u = (u0, u1, u2)
    for r in range(2):
        for c in range(3):
            # [â]× column c, without making the matrix
            c0, c1, c2 = ((0.0, u2, -u1) if c == 0 else ((-u2, 0.0, u0) if c == 1 else (u1, -u0, 0.0)))
            v = c0 if r == 0 else c1
            v -= u[r] * u0 * c0
            v -= u[r] * u1 * c1
            v -= u[r] * u2 * c2
            H[r, c] = v
    return H


@compiled
def acc_update(s, P, p, t, acc, f):
    """An accelerometer sample: into the inertial low-pass (flagged when it is far from
    gravity), then, at most at ``update_rate_hz``, the tilt correction from the low-pass."""
    n = qm.norm3(acc)
    f[F_ACC_VAL] = n
    dt = t - s[S.acc_t] if np.isfinite(s[S.acc_t]) else 0.0
    s[S.acc_t] = t
    # the sample period, for the sample's lag (acc_delay_periods); not across a gap
    if 0.0 < dt < 0.1:
        s[S.acc_period] = dt if np.isnan(s[S.acc_period]) else s[S.acc_period] + 0.01 * (dt - s[S.acc_period])
    if dt <= 0.0:
        dt = 1e-3
    # inertial low-pass, with a running mean while younger than acc_tau (fast start)
    k = lp_coef(dt, p[PRM.acc_tau])
    age = t - s[S.t0]
    if age > 0.0 and dt / (age + dt) > k:
        k = dt / (age + dt)
    # the sample's lag behind the attitude: acc_delay_periods of its own period (module doc)
    d = p[PRM.acc_delay_periods] * s[S.acc_period]
    if d != 0.0 and not np.isnan(d) and not np.isnan(s[S.w_cur_x]):
        aw = rotate3(s, turned_forward(s, p, acc, d))
    else:
        aw = rotate3(s, acc)
    for i in range(3):
        s[S.acc_lp + i] += k * (aw[i] - s[S.acc_lp + i])
    f[F_ACC] = R_USED  # in the low-pass; the correction below runs at most at update_rate_hz
    # the low-passed specific force points below the horizon: the estimate's up is more than
    # 90° off, which no correction brings back (module doc); robust_step re-aligns
    lz = s[S.acc_lp_z]
    if lz < 0.0:
        ln = qm.norm3((s[S.acc_lp_x], s[S.acc_lp_y], lz))
        if ln > 0.5 * GRAVITY:
            s[S.realign] = 1.0
            f[F_ACC] = R_RECOVER
            f[F_ACC_VAL] = np.arccos(max(-1.0, lz / ln))
            return
    # specific force: the sample is far from the low-passed gravity (angle) or from g
    # (norm): the phone accelerates. It still enters the low-pass (the accelerations
    # average out there) but is flagged, so a shake shows, with the angle as its value.
    if p[PRM.acc_flag_angle] > 0.0 or p[PRM.acc_flag_rel] > 0.0:
        ln = qm.norm3((s[S.acc_lp_x], s[S.acc_lp_y], s[S.acc_lp_z]))   # a tuple: no view per sample
        c = (aw[0] * s[S.acc_lp_x] + aw[1] * s[S.acc_lp_y] + aw[2] * s[S.acc_lp_z]) / max(n * ln, 1e-12)
        c = min(1.0, max(-1.0, c))
        # angle > acc_flag_angle  <=>  cos(angle) < cos(acc_flag_angle): the arccos only for a flag
        if ((p[PRM.acc_flag_angle] > 0.0 and c < p[PRM.acc_flag_cos])
                or (p[PRM.acc_flag_rel] > 0.0 and abs(n - GRAVITY) > p[PRM.acc_flag_rel] * GRAVITY)):
            f[F_ACC] = R_ACCEL
            f[F_ACC_VAL] = np.arccos(c)
    # Every valid sample enters the low-pass: the specific force only averages out if
    # none is left out (refusing the peaks of a movement would bias the mean). The norm
    # band gates the *correction* instead: no tilt update while |a| is far from g.
    if p[PRM.acc_band_rel] > 0.0 and abs(n - GRAVITY) > p[PRM.acc_band_rel] * GRAVITY:
        f[F_ACC] = R_NORM
        return
    due, elapsed = update_is_due(s, S.acc_upd_time, dt, p)
    if not due:
        return
    dt = elapsed
    a = s[S.acc_lp:S.acc_lp + 3]
    an = qm.norm3(a)
    if an < 1e-6:
        return
    # noise density of the low-passed direction (one that grew with the specific force's power,
    # the removed tilt_motion_time, was worse on both shared data sets)
    r = p[PRM.tilt_noise] ** 2 / dt
    Rm = np.zeros((2, 2))
    Rm[0, 0] = r
    Rm[1, 1] = r
    # the tilt update corrects the attitude only: its error is the specific force left in the
    # low-pass, correlated for seconds, which a white-noise model would let the bias absorb
    # (the bias is learned from the corrections' rate below, slowly, as VQF does)
    lp_frac = _tilt_lp_share(P, r, dt, p) if p[PRM.tilt_damping] > 0.0 else 1.0
    ok, nis, dx = correct(P, tilt_jacobian(a), Rm, tilt_innovation(a), 0.0, _MASK_TILT,
                          s[S.kf_work:S.kf_work + KF_WORK])
    f[F_ACC_NIS] = nis
    if ok:
        inject(s, P, dx, lp_frac)
        if p[PRM.bias_motion_noise] > 0.0:
            s[S.mb_sum_x] += dx[0]
            s[S.mb_sum_y] += dx[1]
            s[S.mb_time_tilt] += dt
            if s[S.mb_time_tilt] >= BIAS_UPD_S:
                motion_bias_update(s, P, p, s[S.mb_sum_x], s[S.mb_sum_y], s[S.mb_time_tilt])
                s[S.mb_sum_x] = 0.0
                s[S.mb_sum_y] = 0.0
                s[S.mb_time_tilt] = 0.0
    else:
        f[F_ACC] = R_NIS
        f[F_ACC_VAL] = nis


@compiled
def _tilt_lp_share(P, r, dt, p):
    """The share ρ of a tilt correction the low-pass turns with, for a tilt loop of damping
    ζ = ``tilt_damping``: ρ = 2ζ√x - x with x = τc/τ (module doc). τc is the correction's
    time constant, dt/-ln(1 - k) for this update's gain k = P/(P + R) on the tilt (the
    Jacobian of a vertical low-pass is a rotation: the gain is that of one axis)."""
    ptt = 0.5 * (P[0, 0] + P[1, 1])
    k = ptt / (ptt + r)
    if k >= 1.0:
        return 0.0
    tau = p[PRM.acc_tau]
    if tau <= 0.0 or k <= 0.0:
        return 1.0
    x = dt / (-np.log(1.0 - k) * tau)
    return min(1.0, max(0.0, 2.0 * p[PRM.tilt_damping] * np.sqrt(x) - x))
