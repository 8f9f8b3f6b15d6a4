"""The robust filter's state vector, and the small kernels every mechanism uses on it.

The state ``s`` is one flat float array (numba's fastest form, see :mod:`.params`) whose
slots are named once, in ``STATE``: ``S.q`` is the offset of the attitude, ``S.q_x`` that
of its x component, ``S.mt_lp_slow`` that of a 3-vector. Nothing else numbers them.

The filter's error state is ``x = [δθ (world frame), δb]`` with its 6x6 covariance ``P``
beside ``s``: :func:`inject` applies a correction of it to the nominal state.
"""

from __future__ import annotations

import numpy as np

from app.estimators.kalman import work_size
from app.estimators.robust.params import PRM, layout
from app.jitcache import compiled

# the scratch of a measurement update of the 6 error states by at most 3 measurements (the
# plain Python function: nothing is compiled at import; with NUMBA_DISABLE_JIT=1 it is the
# function itself)
KF_WORK = getattr(work_size, "py_func", work_size)(6, 3)

# A slot is (name, size, doc); a vector read by component gives its components' names
# as its size (see :func:`.params.layout`): ("bias", "xyz") makes S.bias, S.bias_x...
STATE = (
    ("q", "wxyz", "nominal attitude [w, x, y, z], sensor to world"),
    ("bias", "xyz", "gyroscope bias (rad/s, sensor frame)"),
    ("acc_lp", "xyz", "low-passed specific force, world frame of the estimate (m/s²)"),
    ("gyr_lp", 3, "low-passed gyroscope (rest detection)"),
    ("acc_lp_rest", 3, "low-passed accelerometer, sensor frame (rest detection)"),
    ("quiet_time", 1, "s quiet so far (rest detection)"),
    ("t", 1, "time of the last row"),
    ("aligned", 1, "1 once aligned"),
    ("realign", 1, "1 from a lost tilt to its re-alignment, which keeps the bias learned (tilt.acc_update)"),
    ("gyr_held", 3, "held gyroscope sample"),
    ("gyr_held_t", 1, "its time"),
    ("wait_t", 1, "time of the first sample, waiting for alignment (NaN: none yet)"),
    ("wait_acc", 3, "the newest accelerometer sample waiting for alignment (NaN: none)"),
    ("ref_norm", 1, "field reference: strength (µT)"),
    ("ref_dip", 1, "field reference: dip (rad, elevation of the field: negative in the north)"),
    ("ref_ok", 1, "1 once there is a field reference"),
    ("cand_norm", 1, "candidate new field: strength (µT)"),
    ("cand_dip", 1, "candidate new field: dip (rad)"),
    ("cand_time", 1, "s the candidate has been stable while turning"),
    ("cand_turned", 1, "s of that the phone turned at mag_new_min_rate or faster (before the first "
                       "reference cand_time counts a still phone too)"),
    ("ref_turned", 1, "s the phone has turned (mag_new_min_rate) in the reference's own field (within "
                      "hard_iron_tol of its strength, undisturbed): "
                      "below mag_first_field_time the reference is tentative (seen from one attitude, "
                      "a desk's or a laptop's field as well as the earth's)"),
    ("t0", 1, "time of the alignment"),
    ("mag_t", 1, "time of the last magnetometer update attempt"),
    ("acc_t", 1, "time of the last accelerometer sample"),
    ("acc_period", 1, "the accelerometer's sample period, low-passed over 100 samples (s; acc_delay_periods)"),
    ("gyr_lp_t", 1, "time of the last gyroscope sample in the rest low-pass (NaN: none yet)"),
    ("rest", 1, "1 at rest"),
    ("far_time", 1, "s the heading has disagreed with an undisturbed field (far or NIS-refused)"),
    ("acc_upd_time", 1, "s of used accelerometer samples since the last tilt update"),
    ("rest_upd_time", 1, "s at rest since the last bias update"),
    ("mag_sum", "xyz", "sum of world-frame field samples since the last heading update"),
    ("mag_count", 1, "how many"),
    ("mag_upd_time", 1, "s of used magnetometer samples since the last heading update"),
    ("acc_lp_rest_t", 1, "time of the last accelerometer sample in the rest low-pass"),
    ("w_cur", "xyz", "scratch: the rate integrated over the current row"),
    ("pred_T", 18, "scratch of the time update: R [Pbb | Pbt], 3x6 by rows"),
    ("seen", 1, "sensors seen at the time of the last row (bit mask)"),
    ("mag_nd", ("norm", "dip"), "low-passed field strength (µT) and dip (rad)"),
    ("mag_nd_ok", 1, "1 once mag_nd holds a sample"),
    ("undisturbed_time", 1, "s the field has been within the gates"),
    ("disturbed", 1, "1 while the field is judged disturbed"),
    ("dist_reason", 1, "Reason of the current disturbance (NORM, DIP or TURN)"),
    ("dist_val", 1, "TURN: the latest unexplained change rate of the field (rad/s)"),
    ("bias_good", 3, "the bias estimate before the heading began to disagree with the field"),
    ("mb_ok", 1, "1 once the motion-bias low-passes hold a value"),
    ("mb_R", 9, "motion bias: low-passed rotation matrix (rows of R, sensor to world)"),
    ("mb_Rb", "xy", "motion bias: low-passed horizontal rows of R b (rad/s)"),
    ("mb_sum", "xy", "tilt corrections since the last bias update (rad)"),
    ("mb_time", ("tilt", "heading"), "s of tilt corrections / of heading drift fits summed since the "
                                     "last bias update"),
    ("mt_lp", "xyz", "field turn test: the world-frame field (µT, estimate's frame) low-passed over "
                     "mag_norm_dip_tau"),
    ("mt_lp_slow", "xyz", "field turn test: mt_lp low-passed again over mag_turn_tau"),
    ("mt_rate", 1, "field turn test: low-passed turn rate (rad/s)"),
    ("mt_ok", 1, "1 once the field turn test's low-passes hold a value"),
    ("turn_lp", "xy", "net turn rate about the horizontal axes: the world-frame turn rate's x, y "
                      "(rad/s, bias removed) low-passed over acc_tau (gyr_scale_noise: tilt only)"),
    ("hi_A", 16, "hard iron fit: normal matrix Σ w φ φᵀ, φ = (2m, 1) (m in units of HI_SCALE)"),
    ("hi_b", 4, "hard iron fit: Σ w φ |m|²"),
    ("hi_yy", 1, "hard iron fit: Σ w |m|⁴"),
    ("hi_W", 1, "hard iron fit: Σ w (s of turning in the window)"),
    ("hi_o", "xyz", "hard iron fit: the offset found (µT, sensor frame)"),
    ("hi_r", 1, "hard iron fit: the sphere's radius (µT)"),
    ("hi_rms", 1, "hard iron fit: rms residual of the field strength (µT)"),
    ("hi_std", 1, "hard iron fit: σ of the offset, largest axis (µT)"),
    ("hi_status", 1, "hard iron: 0 none, 1 tracking, 2 applied"),
    ("hi_applied", "xyz", "hard iron: the offset removed from the field (µT; 0 unless applied)"),
    ("hi_dev_raw", 1, "hard iron: low-passed (|m| - ref)² of the raw field (µT²)"),
    ("hi_dev_cor", 1, "hard iron: likewise of the field minus the offset found"),
    ("hi_dev_fit", 1, "hard iron: low-passed (|m - o| - r)² of new samples against the current fit (µT²)"),
    ("hi_w_acc", 1, "hard iron: turning time (s) since the last sample fed to the fit"),
    ("hi_feed_t", 1, "hard iron: s since the last sample fed to the fit"),
    ("hi_solve_t", 1, "hard iron: s since the fit was last solved"),
    ("p22_pre", 1, "heading variance when the field was last refused (the steady one)"),
    ("prob", 1, "1 while a return to the field after a refusal awaits evidence"),
    ("prob_lo", 1, "probation: smallest hv_fast seen (rad)"),
    ("prob_hi", 1, "probation: largest hv_fast seen (rad)"),
    ("prob_turn", 1, "probation: turn (rad) over which hv_fast stayed consistent"),
    ("dr_bint", 1, "heading drift: the bias removed from the gyroscope about the vertical, integrated "
                   "(rad): added back, the field's heading less the gyroscope's is the raw gyroscope's"),
    ("dr_z", 1, "heading drift: the field's heading less the raw gyroscope's, unwrapped (rad)"),
    ("dr_ok", 1, "heading drift: 1 once the fit holds a sample"),
    ("dr_t0", 1, "heading drift: the fit's time origin (phone clock, s; moved on as time passes)"),
    ("dr_start", 1, "heading drift: when the fit started (phone clock, s)"),
    ("dr_sums", ("w", "t", "tt", "z", "tz", "zz"), "heading drift: the fit's low-passed sums "
                                                   "(1, t, t², z, t z, z²)"),
    ("dr_H", "xyz", "heading drift: the world's vertical in the sensor frame, low-passed as the sums "
                    "(the slope measures the bias along it)"),
    ("dr_y", 1, "heading drift: slopes (as bias, rad/s) summed since the last bias update"),
    ("dr_var", 1, "heading drift: their variances summed likewise ((rad/s)²)"),
    ("dr_n", 1, "heading drift: how many"),
    ("hv_corr", 1, "heading evidence: the heading corrections applied so far (rad)"),
    ("hv", ("fast", "mean", "var"), "the field's heading less the gyroscope's, low-passed over "
                                    "HV_SMOOTH (rad: the heading evidence and the return's "
                                    "probation read it); that low-passed over "
                                    "heading_evidence_tau (rad); its squared deviation from it, "
                                    "low-passed likewise (rad²)"),
    ("hv_ok", 1, "1 once the hv low-passes hold a value"),
    ("dev", ("n", "d"), "the field's deviation from its reference (strength, |m|·dip) relative to "
                        "the horizontal field, low-passed over HV_SMOOTH as the heading evidence "
                        "(mag_dev_weight); started afresh with the hv low-passes"),
    ("kf_work", KF_WORK, "scratch of the measurement updates (kalman.correct): no array per update"),
)
# slots that start as NaN ("not yet")
STATE_NAN = ("t", "gyr_held_t", "wait_t", "t0", "mag_t", "acc_t", "acc_period", "gyr_lp_t", "acc_lp_rest_t")

S, NSTATE = layout("StateLayout", ((n, k) for n, k, _ in STATE))


def new_state() -> np.ndarray:
    s = np.zeros(NSTATE)
    s[S.q] = 1.0
    for name in STATE_NAN:
        s[getattr(S, name)] = np.nan
    s[S.wait_acc:S.wait_acc + 3] = np.nan     # no accelerometer sample yet
    s[S.hi_std] = np.inf                      # no hard iron fit yet
    s[S.hi_rms] = np.inf
    return s


# The state a stream starts from (read by the compiled code: a slot reset at an alignment
# gets its value from here, the one place initial values are written)
INITIAL = new_state()


# Longest interval (s) a low-pass or an update accumulator takes from one sample: a stall
# in the stream must not look like a long, information-rich average.
DT_MAX = 0.1


@compiled
def attitude_matrix(s):
    """R = Q(q) (formula 2a) of the state's attitude as nine floats, row by row (no array
    made per sample). Its last row is the world's vertical in the sensor frame."""
    q0, q1, q2, q3 = s[S.q_w], s[S.q_x], s[S.q_y], s[S.q_z]
    return (2.0 * (q0 * q0 + q1 * q1) - 1.0, 2.0 * (q1 * q2 - q0 * q3), 2.0 * (q1 * q3 + q0 * q2),
            2.0 * (q1 * q2 + q0 * q3), 2.0 * (q0 * q0 + q2 * q2) - 1.0, 2.0 * (q2 * q3 - q0 * q1),
            2.0 * (q1 * q3 - q0 * q2), 2.0 * (q2 * q3 + q0 * q1), 2.0 * (q0 * q0 + q3 * q3) - 1.0)


@compiled
def rotate3(s, v):
    """Q(q) v for the state's attitude, as three floats (no array made per sample)."""
    w, x, y, z = s[S.q_w], s[S.q_x], s[S.q_y], s[S.q_z]
    tx = 2.0 * (y * v[2] - z * v[1])
    ty = 2.0 * (z * v[0] - x * v[2])
    tz = 2.0 * (x * v[1] - y * v[0])
    return (v[0] + w * tx + (y * tz - z * ty), v[1] + w * ty + (z * tx - x * tz),
            v[2] + w * tz + (x * ty - y * tx))


@compiled
def turned_forward(s, p, v, d):
    """A sensor-frame sample ``v`` that lags the attitude by ``d`` seconds, turned forward to
    now, as three floats (no array per sample): it was measured at t - d, when the sensor
    frame was turned by -ω d from now, so v(t) = v(t - d) - d ω × v(t - d), ω the rate this
    row integrates less the bias, its scale divided out (the field's ``mag_delay``, the accelerometer's
    ``acc_delay_periods``)."""
    wx = (s[S.w_cur_x] - s[S.bias_x]) * p[PRM.gyr_gain_x]
    wy = (s[S.w_cur_y] - s[S.bias_y]) * p[PRM.gyr_gain_y]
    wz = (s[S.w_cur_z] - s[S.bias_z]) * p[PRM.gyr_gain_z]
    return (v[0] - d * (wy * v[2] - wz * v[1]),
            v[1] - d * (wz * v[0] - wx * v[2]),
            v[2] - d * (wx * v[1] - wy * v[0]))


@compiled
def lp_coef(dt, tau):
    """First-order low-pass coefficient (the DNRF form 1 - τ/(τ+Δt))."""
    if tau <= 0.0:
        return 1.0
    return dt / (tau + dt)


@compiled
def update_is_due(s, idx, dt, p):
    """Add the sample interval dt of a used sample to the accumulator ``s[idx]``;
    when it reaches 1/update_rate_hz, reset it and return (True, accumulated s).
    The accumulated time of *used* samples is what scales R = σ²/Δt, so an update
    after a long rejection is not mistaken for a long, information-rich average."""
    dt = min(max(dt, 0.0), DT_MAX)
    s[idx] += dt
    # half a sample of tolerance: 100 Hz data with jittery stamps still updates at 100 Hz
    if s[idx] >= p[PRM.upd_dt] - 0.5 * dt and s[idx] > 0.0:
        acc = s[idx]
        s[idx] = 0.0
        return True, acc
    return False, s[idx]


@compiled
def exp3(vx, vy, vz):
    """exp of the rotation vector (vx, vy, vz) as four scalars (qm.quat_from_rotvec)."""
    a = np.sqrt(vx * vx + vy * vy + vz * vz)
    k = 0.5 if a < 1e-12 else np.sin(0.5 * a) / a
    return np.cos(0.5 * a), vx * k, vy * k, vz * k


@compiled
def _rotate_slot(s, j, d0, d1, d2, d3):
    """The 3-vector slot ``s[j:j+3]`` rotated by the unit quaternion (d0, d1, d2, d3) in
    place (qm.rotate)."""
    ax, ay, az = s[j], s[j + 1], s[j + 2]
    tx = 2.0 * (d2 * az - d3 * ay)
    ty = 2.0 * (d3 * ax - d1 * az)
    tz = 2.0 * (d1 * ay - d2 * ax)
    s[j] = ax + d0 * tx + (d2 * tz - d3 * ty)
    s[j + 1] = ay + d0 * ty + (d3 * tx - d1 * tz)
    s[j + 2] = az + d0 * tz + (d1 * ty - d2 * tx)


@compiled
def inject(s, P, dx, lp_frac=1.0):
    """Apply an error-state correction: q <- exp(δθ) ⊗ q, b <- b + δb, and rotate
    the world-frame low-pass with the attitude so it stays in the estimate's frame
    (with ``lp_frac`` of the tilt part of δθ only: the tilt loop's damping)."""
    # dq = exp(δθ) (qm.quat_from_rotvec), q <- normalize(dq ⊗ q) (qm.quat_mul,
    # qm.normalize) and the low-passes rotated by dq (qm.rotate), written out in scalars
    # with the same arithmetic: an update makes no array here
    vx, vy, vz = dx[0], dx[1], dx[2]
    d0, d1, d2, d3 = exp3(vx, vy, vz)
    q0, q1, q2, q3 = s[S.q_w], s[S.q_x], s[S.q_y], s[S.q_z]
    r0 = d0 * q0 - d1 * q1 - d2 * q2 - d3 * q3
    r1 = d0 * q1 + d1 * q0 + d2 * q3 - d3 * q2
    r2 = d0 * q2 - d1 * q3 + d2 * q0 + d3 * q1
    r3 = d0 * q3 + d1 * q2 - d2 * q1 + d3 * q0
    n = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
    if n == 0.0 or not np.isfinite(n):
        r0, r1, r2, r3, c = 1.0, 0.0, 0.0, 0.0, 1.0
    else:
        c = 1.0 / n
        if r0 < 0.0:
            c = -c
    s[S.q_w], s[S.q_x], s[S.q_y], s[S.q_z] = r0 * c, r1 * c, r2 * c, r3 * c
    for i in range(3):
        s[S.bias + i] += dx[3 + i]
    if lp_frac != 1.0:
        # the tilt's low-pass turns with the heading part and lp_frac of the tilt part
        # (the tilt loop's damping); everything else turns with the whole correction
        e0, e1, e2, e3 = exp3(vx * lp_frac, vy * lp_frac, vz)
        _rotate_slot(s, S.acc_lp, e0, e1, e2, e3)
    else:
        _rotate_slot(s, S.acc_lp, d0, d1, d2, d3)
    _rotate_slot(s, S.mt_lp, d0, d1, d2, d3)        # the field turn test's two low-passes
    _rotate_slot(s, S.mt_lp_slow, d0, d1, d2, d3)
