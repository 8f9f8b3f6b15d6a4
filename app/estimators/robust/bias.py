"""The gyroscope bias: learned at rest, and in motion from the tilt corrections and the heading's drift.

- **Rest detection** (gyroscope and accelerometer both quiet for ``rest_time``, and the
  gyroscope reading no more than a plausible bias, ``bias_max``: a steady turn about the
  vertical is as quiet as rest): the low-passed gyroscope is then a direct measurement of
  the bias.
- **Bias in motion from the tilt corrections' rate** (VQF's motion bias estimation, through
  the same ``correct``). The tilt update corrects the attitude only: its errors (specific
  force left in the low-pass) last for seconds, and a white-noise model would let the bias
  absorb them (it wandered by 1.5 °/s on a phone held still in the hand). Instead, the rate
  of the tilt corrections (x, y) measures the bias error, with its own noise density
  (``bias_motion_noise``) and a clip (``bias_motion_clip``): the bias follows the corrections
  over a minute, not seconds. The tilt update (:mod:`.tilt`) sums its corrections and calls
  :func:`motion_bias_update` every ``BIAS_UPD_S``.
- **The bias about the vertical from the heading's drift** (``heading_drift_window``,
  ``heading_drift_corr``): the heading update (:mod:`.heading`) fits a line to the field's
  heading less the raw gyroscope's; its slope is the bias along the vertical, its residual
  (a field bent indoors, a stride's swing) its uncertainty; :func:`heading_drift_update` learns
  it. A rest-learned bias is not the bias in motion (a MEMS gyroscope's bias changes with the
  gravity it feels, 0.1 °/s/g); this learns the one in motion where the field allows.
"""

from __future__ import annotations

import numpy as np

from app.estimators.base import F_GYR, F_REST, R_REST
from app.estimators.kalman import correct
from app.estimators.robust.params import PRM
from app.estimators.robust.state import DT_MAX, KF_WORK, S, attitude_matrix, inject, lp_coef
from app.jitcache import compiled

# The bias learned in motion follows the correction rates over a minute: it is updated
# with the corrections summed over this long (s), not after every correction.
BIAS_UPD_S = 0.1

_MASK_BIAS = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0])

# Measurement model in the error state x = [δθ (world), δb] (see :mod:`.tilt`):
H_BIAS = np.hstack((np.zeros((3, 3)), np.eye(3)))  # at rest the low-passed gyroscope measures b


@compiled
def _lp_sensor(s, idx, idx_t, v, t, tau):
    """Low-pass ``s[idx:idx+3]`` towards v with the time since that sensor's last
    sample (a phone sends one sensor per row); returns |v - low-pass|² (squared: the
    caller compares it with a squared threshold, no root per row)."""
    if np.isnan(s[idx_t]):
        s[idx:idx + 3] = v
        s[idx_t] = t
        return 0.0
    k = lp_coef(min(t - s[idx_t], DT_MAX), tau)
    s[idx_t] = t
    d2 = 0.0
    for i in range(3):
        s[idx + i] += k * (v[i] - s[idx + i])
        d2 += (v[i] - s[idx + i]) ** 2
    return d2


@compiled
def rest_update(s, P, p, t, gyr, acc, dt, has_gyr, has_acc, f):
    """Rest detection on the deviation of gyroscope and accelerometer from their
    low-passes; at rest the low-passed gyroscope measures the bias directly."""
    if p[PRM.rest_time] <= 0.0:
        s[S.rest] = 0.0
        return
    quiet = True
    if has_gyr and _lp_sensor(s, S.gyr_lp, S.gyr_lp_t, gyr, t, p[PRM.rest_lp_tau]) > p[PRM.rest_gyr_th] ** 2:
        quiet = False
    if has_gyr and p[PRM.bias_max] > 0.0 and quiet:
        # a steady turn about the vertical (a turntable, a swivel chair) leaves gyroscope and
        # accelerometer as constant as rest does: a rate above any plausible bias is a turn
        g2 = s[S.gyr_lp] ** 2 + s[S.gyr_lp + 1] ** 2 + s[S.gyr_lp + 2] ** 2
        if g2 > p[PRM.bias_max] ** 2:
            quiet = False
    if has_acc and _lp_sensor(s, S.acc_lp_rest, S.acc_lp_rest_t, acc, t,
                              p[PRM.rest_lp_tau]) > p[PRM.rest_acc_th] ** 2:
        quiet = False
    s[S.quiet_time] = s[S.quiet_time] + dt if quiet else 0.0
    s[S.rest] = 1.0 if s[S.quiet_time] >= p[PRM.rest_time] else 0.0
    f[F_REST] = s[S.rest]
    if s[S.rest] == 0.0:
        s[S.rest_upd_time] = 0.0
        return
    # time at rest since the last bias update; the update runs on a gyroscope row
    s[S.rest_upd_time] += min(dt, DT_MAX)
    if not has_gyr or s[S.rest_upd_time] < p[PRM.upd_dt] - 0.5 * dt or s[S.rest_upd_time] <= 0.0:
        return
    elapsed = s[S.rest_upd_time]
    s[S.rest_upd_time] = 0.0
    Rm = np.zeros((3, 3))
    for i in range(3):
        Rm[i, i] = p[PRM.rest_noise] ** 2 / elapsed
    innov = s[S.gyr_lp:S.gyr_lp + 3] - s[S.bias:S.bias + 3]
    ok, nis, dx = correct(P, H_BIAS, Rm, innov, 0.0, None, s[S.kf_work:S.kf_work + KF_WORK])
    if ok:
        inject(s, P, dx)
        f[F_GYR] = R_REST


@compiled
def motion_bias_update(s, P, p, dx0, dx1, dt):
    """Gyroscope bias during motion from the rate of the tilt corrections (VQF's motion bias
    estimation, through the one ``correct``). A bias error δb turns the estimate at -R δb in
    the world frame; the tilt corrections, which keep the inclination, then run at that rate
    in x and y. Through the low-pass (``acc_tau``) they show it averaged over the last
    seconds, so the measurement is ``LP(R b) - dx/Δt`` of ``LP(R) b``: LP(R) b̂ plus the
    rate the corrections needed. Its noise (``bias_motion_noise``) is what the specific
    force left in the low-pass makes the corrections wander: the bias follows the
    corrections over minutes, not seconds; a rate off the model by more than
    ``bias_motion_clip`` counts as that much (a first correction, a shake is no bias).
    Only x and y: the vertical is the heading's (the magnetometer's) to learn."""
    R = s[S.mb_R:S.mb_R + 9]
    r = attitude_matrix(s)
    b0, b1, b2 = s[S.bias_x], s[S.bias_y], s[S.bias_z]
    rb0 = r[0] * b0 + r[1] * b1 + r[2] * b2
    rb1 = r[3] * b0 + r[4] * b1 + r[5] * b2
    if s[S.mb_ok] == 0.0:
        for i in range(9):
            R[i] = r[i]
        s[S.mb_Rb_x] = rb0
        s[S.mb_Rb_y] = rb1
        s[S.mb_ok] = 1.0
    else:
        k = lp_coef(dt, p[PRM.acc_tau])
        for i in range(9):
            R[i] += k * (r[i] - R[i])
        s[S.mb_Rb_x] += k * (rb0 - s[S.mb_Rb_x])
        s[S.mb_Rb_y] += k * (rb1 - s[S.mb_Rb_y])
    if s[S.rest] != 0.0:
        return  # at rest the gyroscope itself measures the bias (rest_update)
    innov = np.empty(2)
    innov[0] = s[S.mb_Rb_x] - dx0 / dt - (R[0] * b0 + R[1] * b1 + R[2] * b2)
    innov[1] = s[S.mb_Rb_y] - dx1 / dt - (R[3] * b0 + R[4] * b1 + R[5] * b2)
    clip = p[PRM.bias_motion_clip]
    if clip > 0.0:
        for i in range(2):
            innov[i] = min(clip, max(-clip, innov[i]))
    H = np.zeros((2, 6))
    for j in range(3):
        H[0, 3 + j] = R[j]
        H[1, 3 + j] = R[3 + j]
    Rm = np.zeros((2, 2))
    Rm[0, 0] = p[PRM.bias_motion_noise] ** 2 / dt
    Rm[1, 1] = Rm[0, 0]
    ok, nis, db = correct(P, H, Rm, innov, 0.0, _MASK_BIAS, s[S.kf_work:S.kf_work + KF_WORK])
    if ok:
        for i in range(3):
            s[S.bias + i] += db[3 + i]


@compiled
def heading_drift_update(s, P, p, y, var, dt):
    """The bias about the vertical from the heading drift fit (:func:`.heading._drift_fit`): ``y``
    (rad/s) is the slope of the field's heading less the raw gyroscope's over
    ``heading_drift_window``, which measures the bias along the world's vertical as the window
    saw it (``dr_H``), with variance ``var`` from the fit's residual. Fed every ``dt`` (about
    ``BIAS_UPD_S``), its noise is that of one window's fit spread over the window's length
    (``var`` × 2 window / ``dt``): a window's slope is learned once, not once per update. A slope off the estimate by more than ``bias_motion_clip`` counts as that much."""
    H = np.zeros((1, 6))
    H[0, 3] = s[S.dr_H_x]
    H[0, 4] = s[S.dr_H_y]
    H[0, 5] = s[S.dr_H_z]
    innov = np.empty(1)
    innov[0] = y - (s[S.dr_H_x] * s[S.bias_x] + s[S.dr_H_y] * s[S.bias_y] + s[S.dr_H_z] * s[S.bias_z])
    clip = p[PRM.bias_motion_clip]
    if clip > 0.0:
        innov[0] = min(clip, max(-clip, innov[0]))
    Rm = np.empty((1, 1))
    Rm[0, 0] = var * 2.0 * p[PRM.heading_drift_window] / dt
    ok, nis, db = correct(P, H, Rm, innov, 0.0, _MASK_BIAS, s[S.kf_work:S.kf_work + KF_WORK])
    if ok:
        for i in range(3):
            s[S.bias + i] += db[3 + i]
