"""The robust filter's compiled loop: the time update, the alignment, one row, a batch.

:func:`robust_step` processes one row: the time update (:func:`_predict`), rest
detection (:mod:`.bias`), the tilt update (:mod:`.tilt`), the heading update
(:mod:`.heading`); :func:`robust_run` loops it over arrays for batch use. The time update
adds, beside the gyroscope's white noise, what grows with the turn:

- **Scale-factor noise along the net turn** (``gyr_scale_noise``). A gyroscope's scale
  factor is off by some 0.2-3 % (``benchmarks/gyro_scale.py`` against the optical truth:
  BROAD's research IMU 0.2 % median, the phones 2.3 %), so it turns the estimate by that
  share of the rotation. A steady turn builds that up over the tilt loop's time scale; a
  back-and-forth (running, swinging) cancels. So tilt noise is added along the *net* turn
  rate, the world-frame rate low-passed over ``acc_tau``: a steady turn makes the tilt
  correct faster, a shaking phone, whose specific force the loop must average out, does
  not (along the raw turn rate it did, and running lost). Tilt only: about the vertical
  the magnetometer's errors grow with a turn too, and a faster heading correction follows
  them.
- **The heading's σ grows with the turn while the field is refused**
  (``refused_turn_noise``). Then the gyroscope alone keeps the heading, off by its scale
  error times the turn about the vertical; with only the white gyroscope noise in P, the
  first good field after a long refusal in motion (a magnet attached for 50 s) corrected
  at the steady rate, half a minute for 2-3°. Growing σ along the vertical turn rate
  while refused makes it correct at once; while the field is used the term stays out
  (the magnetometer's turn-bound errors grow as well).

After the updates, a bias estimate above ``bias_max`` means the filter is lost, not the
sensor: the bias is reset (flag BIAS_RESET).
"""

from __future__ import annotations

import numpy as np

from app import quaternion as qm
from app.estimators.base import (ALIGN_ACC, ALIGN_ACC_MAG, ALIGN_NO_ACC, F_ACC, F_ACC_VAL, F_GYR, F_MAG,
                                 F_REST, F_TIME, R_ABSENT, R_BIAS_RESET, R_GAP, R_LATE, R_RECOVER, R_USED,
                                 T_BACKWARD, T_GAP, T_OK, align_step, row_prologue)
from app.estimators.robust.bias import rest_update
from app.estimators.robust.hardiron import hard_iron_reset
from app.estimators.robust.heading import mag_update
from app.estimators.robust.params import PRM
from app.params import GRAVITY
from app.estimators.robust.state import DT_MAX, S, attitude_matrix, exp3, lp_coef
from app.estimators.robust.tilt import acc_update
from app.jitcache import compiled


@compiled
def _align(s, P, p, t, acc, mag, use_mag):
    """The alignment from the samples: at the start, or again when the tilt was lost
    (``s[S.realign]``: then the bias learned so far, and its covariance, are kept)."""
    keep = s[S.realign] != 0.0
    Pbb = P[3:, 3:].copy()
    s[S.realign] = 0.0
    s[S.q:S.q + 4] = qm.q_from_acc_mag(acc, mag, use_mag)
    if not keep:
        for i in range(3):
            s[S.bias + i] = p[PRM.gyr_bias + i]
    s[S.acc_lp:S.acc_lp + 3] = qm.rotate(s[S.q:S.q + 4], acc)
    s[S.turn_lp:S.turn_lp + 2] = 0.0
    s[S.mb_ok] = 0.0
    s[S.mb_sum:S.mb_sum + 2] = 0.0
    s[S.mb_time:S.mb_time + 2] = 0.0
    P[:, :] = 0.0
    tilt0 = p[PRM.init_tilt_std]
    head0 = p[PRM.init_heading_std] if use_mag else np.pi
    P[0, 0] = tilt0 ** 2
    P[1, 1] = tilt0 ** 2
    P[2, 2] = head0 ** 2
    if keep:
        P[3:, 3:] = Pbb
    else:
        for i in range(3, 6):
            P[i, i] = max(p[PRM.bias_init], 1e-6) ** 2
    s[S.aligned] = 1.0
    s[S.t0] = t
    s[S.wait_t] = np.nan
    s[S.mag_t] = t
    s[S.acc_t] = t
    s[S.acc_upd_time] = 0.0
    s[S.rest_upd_time] = 0.0
    s[S.mag_count] = 0.0
    s[S.mag_sum:S.mag_sum + 3] = 0.0
    s[S.mag_upd_time] = 0.0
    s[S.ref_ok] = 0.0
    s[S.cand_time] = 0.0
    s[S.cand_turned] = 0.0
    s[S.ref_turned] = 0.0
    s[S.far_time] = 0.0
    s[S.mag_nd_ok] = 0.0
    s[S.undisturbed_time] = 0.0
    s[S.disturbed] = 0.0
    s[S.mt_ok] = 0.0
    hard_iron_reset(s)
    s[S.hv_ok] = 0.0
    s[S.prob] = 0.0
    s[S.p22_pre] = 0.0
    s[S.dr_ok] = 0.0


@compiled
def _integrate(s, vx, vy, vz):
    """q <- q ⊗ exp(v) for the body-frame rotation vector v (exact, formula 2j), w >= 0."""
    c, x, y, z = exp3(vx, vy, vz)
    q0, q1, q2, q3 = s[S.q_w], s[S.q_x], s[S.q_y], s[S.q_z]
    r0 = q0 * c - q1 * x - q2 * y - q3 * z
    r1 = q0 * x + q1 * c + q2 * z - q3 * y
    r2 = q0 * y - q1 * z + q2 * c + q3 * x
    r3 = q0 * z + q1 * y - q2 * x + q3 * c
    n = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
    if r0 < 0.0:
        n = -n
    s[S.q_w], s[S.q_x], s[S.q_y], s[S.q_z] = r0 / n, r1 / n, r2 / n, r3 / n


@compiled
def _predict(s, P, p, w, dt):
    """Time update over dt with the rate w (NaN: random walk without gyroscope)."""
    if np.isnan(w[0]):
        var = p[PRM.rw_noise] ** 2 * dt
        for i in range(3):
            P[i, i] += var
        bv = p[PRM.bias_noise] ** 2 * dt
        for i in range(3, 6):
            P[i, i] += bv
        return
    # R = Q(q) of the attitude before this step, as nine scalars
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = attitude_matrix(s)
    # the rate: bias removed, scale-factor error divided out (gyr_gain = 1 / (1 + gyr_scale))
    gx, gy, gz = p[PRM.gyr_gain_x], p[PRM.gyr_gain_y], p[PRM.gyr_gain_z]
    wx, wy, wz = (w[0] - s[S.bias_x]) * gx, (w[1] - s[S.bias_y]) * gy, (w[2] - s[S.bias_z]) * gz
    # the bias removed about the vertical, integrated: the heading drift fit adds it back
    s[S.dr_bint] += (r20 * s[S.bias_x] * gx + r21 * s[S.bias_y] * gy + r22 * s[S.bias_z] * gz) * dt
    _integrate(s, wx * dt, wy * dt, wz * dt)
    # the rate's derivative by the bias is -G (the scale's gain per axis): below, R stands
    # for R G (f here), the attitude's derivative by the bias over dt (-R G dt)
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = (r00 * gx, r01 * gy, r02 * gz, r10 * gx, r11 * gy,
                                                   r12 * gz, r20 * gx, r21 * gy, r22 * gz)
    # F = [[I, -R dt], [0, I]];  P <- F P F' + Qd, by blocks with T = R [Pbb | Pbt]:
    # Ptt += dt² T[:, :3] R' - dt (T[:, 3:] + T[:, 3:]');  Ptb -= dt T[:, :3]
    # (T lives in a scratch slot of the state, s[T + 6 i + j], indexed there: neither an
    # array nor a view of one is made per sample; a view costs its reference counting)
    T = S.pred_T
    for i in range(3):
        ri0, ri1, ri2 = (f00, f01, f02) if i == 0 else ((f10, f11, f12) if i == 1 else (f20, f21, f22))
        for j in range(3):
            s[T + 6 * i + j] = ri0 * P[3, 3 + j] + ri1 * P[4, 3 + j] + ri2 * P[5, 3 + j]      # R Pbb
            s[T + 6 * i + 3 + j] = ri0 * P[3, j] + ri1 * P[4, j] + ri2 * P[5, j]              # R Pbt
    dt2 = dt * dt
    for i in range(3):
        for j in range(i, 3):
            rj0, rj1, rj2 = (f00, f01, f02) if j == 0 else ((f10, f11, f12) if j == 1 else (f20, f21, f22))
            v = -dt * (s[T + 6 * i + 3 + j] + s[T + 6 * j + 3 + i])
            v += dt2 * s[T + 6 * i] * rj0
            v += dt2 * s[T + 6 * i + 1] * rj1
            v += dt2 * s[T + 6 * i + 2] * rj2
            P[i, j] += v
            if j != i:
                P[j, i] = P[i, j]
    for i in range(3):
        for j in range(3):
            P[i, 3 + j] -= dt * s[T + 6 * i + j]
            P[3 + j, i] = P[i, 3 + j]
    # gyroscope noise, plus what grows with the turn rate (scale factor, misalignment, timing)
    gv = p[PRM.gyr_noise] ** 2 * dt
    bv = p[PRM.bias_noise] ** 2 * dt
    for i in range(3):
        P[i, i] += gv
        P[3 + i, 3 + i] += bv
    if p[PRM.refused_turn_noise] > 0.0 and s[S.disturbed] != 0.0:
        # The same scale error turns the heading by its share of the turn about the vertical.
        # While the field is used this is left out: the magnetometer's own errors grow with
        # a turn as well (lag, residual hard iron), so a faster correction in a turn follows
        # them (BROAD's heading gets worse, see the README). While the field is refused the
        # gyroscope is alone: the heading σ grows with the turn, and the first good field
        # after the refusal corrects what the turn did at once instead of at the steady rate.
        wv = r20 * wx + r21 * wy + r22 * wz
        P[2, 2] += p[PRM.refused_turn_noise] ** 2 * wv * wv * dt
    if p[PRM.gyr_scale_noise] > 0.0:
        # A scale-factor error s turns the estimate by s × the net rotation, about the turn's
        # axis: over the tilt loop's time scale (acc_tau) a steady turn builds it up, a
        # back-and-forth (running, swinging) cancels. So the noise runs along the net turn
        # rate, the world-frame rate low-passed over acc_tau. Tilt only: about the vertical
        # the magnetometer's own errors grow with a turn too (a residual hard iron sweeps the
        # heading as the phone turns, the field lags), and a faster heading correction there
        # follows them (BROAD's heading 1.53° -> 1.77° with it, see the README).
        k = lp_coef(min(dt, DT_MAX), p[PRM.acc_tau])
        s[S.turn_lp_x] += k * ((r00 * wx + r01 * wy + r02 * wz) - s[S.turn_lp_x])
        s[S.turn_lp_y] += k * ((r10 * wx + r11 * wy + r12 * wz) - s[S.turn_lp_y])
        ux, uy = s[S.turn_lp_x], s[S.turn_lp_y]
        g2 = p[PRM.gyr_scale_noise] ** 2 * dt
        P[0, 0] += g2 * ux * ux
        P[0, 1] += g2 * ux * uy
        P[1, 1] += g2 * uy * uy
        P[1, 0] = P[0, 1]


@compiled
def robust_step(s, P, p, t, gyr, acc, mag, f):
    """Process one row: time update, rest detection, tilt update, heading update."""
    dt, issue, seen, gs, as_, ms = row_prologue(s[S.t], t, p[PRM.max_gap], int(s[S.seen]), gyr, acc,
                                                mag, p[PRM.use_gyr] > 0.5, p[PRM.use_acc] > 0.5,
                                                p[PRM.use_mag] > 0.5)
    s[S.seen] = seen
    f[F_TIME] = issue
    if issue == T_BACKWARD:
        f[F_GYR] = R_LATE if gs == R_USED else gs
        f[F_ACC] = R_LATE if as_ == R_USED else as_
        f[F_MAG] = R_LATE if ms == R_USED else ms
        return
    f[F_GYR] = gs
    f[F_ACC] = as_
    f[F_MAG] = ms
    s[S.t] = t
    w0, w1, w2 = np.nan, np.nan, np.nan
    if p[PRM.use_gyr] > 0.5:
        if gs == R_USED:
            w0, w1, w2 = gyr[0], gyr[1], gyr[2]
            s[S.gyr_held], s[S.gyr_held + 1], s[S.gyr_held + 2] = w0, w1, w2
            s[S.gyr_held_t] = t
        elif np.isfinite(s[S.gyr_held_t]) and t - s[S.gyr_held_t] <= p[PRM.gyr_hold]:
            w0, w1, w2 = s[S.gyr_held], s[S.gyr_held + 1], s[S.gyr_held + 2]
    if issue == T_GAP:
        if gs == R_USED:
            f[F_GYR] = R_GAP
        w0, w1, w2 = np.nan, np.nan, np.nan
    # the rate integrated over this row, in the state too (turned_forward reads it there)
    s[S.w_cur_x], s[S.w_cur_y], s[S.w_cur_z] = w0, w1, w2
    w = (w0, w1, w2)

    if s[S.aligned] == 0.0:
        _try_align(s, P, p, t, acc, mag, gs, as_, ms, f)
        return
    if dt > 0.0:
        _predict(s, P, p, w, dt)
    rest_update(s, P, p, t, gyr, acc, dt, gs == R_USED, as_ == R_USED, f)
    if as_ == R_USED:
        acc_update(s, P, p, t, acc, f)
        if s[S.realign] != 0.0:
            # the tilt was lost (tilt.acc_update): align again from the samples, as at the
            # start, this one first (the flag keeps saying why)
            angle = f[F_ACC_VAL]
            s[S.aligned] = 0.0
            s[S.wait_t] = np.nan
            s[S.wait_acc:S.wait_acc + 3] = np.nan
            _try_align(s, P, p, t, acc, mag, gs, as_, ms, f)
            f[F_ACC] = R_RECOVER
            f[F_ACC_VAL] = angle
            return
    if ms == R_USED:
        # the turn rate (bias removed) that counts towards accepting a new field
        rate = 0.0
        if not np.isnan(w[0]):
            bx, by, bz = w[0] - s[S.bias_x], w[1] - s[S.bias_y], w[2] - s[S.bias_z]
            rate = np.sqrt(bx * bx + by * by + bz * bz)
        mag_update(s, P, p, t, mag, rate, not np.isnan(w[0]), f)
    if p[PRM.bias_max] > 0.0:
        b2 = s[S.bias_x] ** 2 + s[S.bias_y] ** 2 + s[S.bias_z] ** 2
        if b2 > p[PRM.bias_max] ** 2:
            # no phone's gyroscope is that far off: the estimate is lost, not the sensor
            for i in range(3):
                s[S.bias + i] = p[PRM.gyr_bias + i]
                for j in range(6):
                    P[3 + i, j] = 0.0
                    P[j, 3 + i] = 0.0
                P[3 + i, 3 + i] = max(p[PRM.bias_init], 1e-6) ** 2
            f[F_GYR] = R_BIAS_RESET


@compiled
def _try_align(s, P, p, t, acc, mag, gs, as_, ms, f):
    """The initial alignment when :func:`~.base.align_step` says so."""
    act = align_step(s, S.wait_t, S.wait_acc, t, gs, as_, ms, acc, p[PRM.use_acc] > 0.5,
                     p[PRM.use_mag] > 0.5, f)
    if act == ALIGN_ACC or act == ALIGN_ACC_MAG:
        _align(s, P, p, t, s[S.wait_acc:S.wait_acc + 3].copy(), mag, act == ALIGN_ACC_MAG)
    elif act == ALIGN_NO_ACC:
        # no accelerometer: start level, heading from the field if there is one
        up = np.array([0.0, 0.0, GRAVITY])
        _align(s, P, p, t, up, mag, ms == R_USED)
        P[0, 0] = p[PRM.noacc_tilt_std] ** 2
        P[1, 1] = P[0, 0]


@compiled
def robust_run(s, P, p, T, G, A, M, Qout, Fout):
    """Batch: ``robust_step`` for every row; the estimate and flags after each."""
    for k in range(T.shape[0]):
        f = Fout[k]
        f[:] = np.nan
        f[F_GYR] = R_ABSENT
        f[F_ACC] = R_ABSENT
        f[F_MAG] = R_ABSENT
        f[F_REST] = 0.0
        f[F_TIME] = T_OK
        robust_step(s, P, p, T[k], G[k], A[k], M[k], f)
        for i in range(4):
            Qout[k, i] = s[S.q + i]
