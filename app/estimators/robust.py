"""``robust``: orientlab's default estimator, an error-state EKF built for real phones.

Structure (4c) of the lab manual (gyroscope as input, its bias in the state) in the
error-state (multiplicative) form: the nominal attitude ``q`` is a unit quaternion; the
filter's state is the small rotation ``δθ`` (world frame, ``q_true = exp(δθ) ⊗ q``) and
the gyroscope bias ``b`` (sensor frame), 6 states with a well-conditioned 6x6 ``P``
(no covariance along the unit-norm constraint, no renormalisation hack).

What makes it accurate on real data (see ``shared/notes/robust-orientation.md``):

- **Tilt from an inertial low-pass of the accelerometer.** Each specific-force sample
  is rotated into the world frame and low-pass filtered there (``acc_tau``, 4.5 s), so
  the phone's accelerations, which average to zero, cancel, while gravity stays. The
  filtered direction is the measurement (2 components, ``h = (-δθy, δθx)``); the
  filter state is rotated with every correction, so it always lives in the current
  estimate's world frame (by how much: below). Every valid sample enters the low-pass
  (leaving out the peaks of a movement would bias its mean); an innovation (NIS) gate, and optionally
  a norm band (off by default: it costs accuracy on real data), hold the correction.
- **A damped tilt loop** (``tilt_damping``). The low-pass (time constant τ =
  ``acc_tau``) and the corrections (time constant τc = 1/gain, from P) form a
  second-order loop. Turning the low-pass with every correction makes its poles real,
  -1/τ and -1/τc: overdamped, and a gyroscope drift d leaves d·(τ + τc) of tilt error.
  Turning it with a share ρ of each tilt correction gives s² + (1/τ + ρ/τc) s + 1/(τ τc):
  the same rejection of fast specific force (1/(τ τc ω²)), damping ζ set by ρ =
  2ζ√(τc/τ) - τc/τ, a drift error of d·(τc + ρτ) = d·2ζ/ωn with ωn = 1/√(τ τc).
  The default is VQF's damping, ζ = 1/√2 (its second-order Butterworth low-pass), at
  the bandwidth the overdamped loop had (ωn ≈ 0.28 rad/s at rest: τ = 4.5 s, τc =
  ``tilt_noise / gyr_noise`` = 3 s, before τ = 3 s, τc = 4 s): the same rejection of
  the specific force, ~30 % less lag where the gyroscope drifts (fast turns).
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
- **Heading only from the magnetometer.** The field is rotated into the world frame
  with the current tilt and only its horizontal direction is used (scalar ``h = δθz``);
  the gain is masked so this update can never tilt the attitude.
- **Magnetic disturbance detection** (VQF's logic, :func:`_field_check`). The low-passed
  field strength and dip angle are compared with a reference learned while undisturbed
  (``mag_norm_gate_rel``, ``mag_dip_gate``); the first reference is a field stable for
  ``mag_first_field_time`` (never the first samples of a phone that starts moving); a
  new homogeneous field (stable strength and dip while the phone turns for
  ``mag_new_field_time``) becomes the reference; after ``mag_max_reject`` seconds of
  refusal the heading update resumes ``mag_reject_factor`` times slower. Within the
  gates, a deviation from the reference adds heading noise (``mag_dev_weight``).
- **Field turn test** (:func:`_turn_check`). A real field is fixed in the world: seen
  through the estimate (whose turns are the gyroscope's) it stays put while the phone
  turns. A magnet brought in over half a second turns the horizontal field by tens of
  degrees before its strength or dip leave their gates, and the heading would follow; so
  a world-frame field changing faster than ``mag_turn_gate`` beyond ``mag_turn_rel`` ×
  the turn rate is a disturbance too (flag TURN, value: the unexplained rate), ended like
  the others after ``mag_min_undisturbed`` of a field within every gate.
- **Never lost.** An undisturbed field farther than ``mag_lost_angle`` from the heading
  for ``mag_lost_time`` means the estimate is wrong: the heading σ grows to the error,
  the field's heading is taken, the bias learned meanwhile is dropped (flag RECOVER);
  a bias estimate above ``bias_max`` is reset (flag BIAS_RESET).
- **Specific force flagged.** An accelerometer sample far from the low-passed gravity
  (``acc_flag_angle``, ``acc_flag_rel``) is flagged ACCEL with the angle (it still
  enters the low-pass): a shake shows.
- **Rest detection** (gyroscope and accelerometer both quiet for ``rest_time``):
  the low-passed gyroscope is then a direct measurement of the bias.
- **Bias in motion from the correction rates** (VQF's motion bias estimation, through
  the same ``correct``). The tilt and heading updates correct the attitude only: their
  errors (specific force left in the low-pass, a field bent indoors) last for seconds,
  and a white-noise model would let the bias absorb them (it wandered by 1.5 °/s on a
  phone held still in the hand). Instead, the rate of the tilt corrections (x, y) and
  of the heading corrections (about the vertical) measures the bias error, with their
  own noise densities (``bias_motion_noise``, ``bias_heading_noise``) and a clip
  (``bias_motion_clip``): the bias follows the corrections over a minute, not seconds.
- **Measurement noise as densities** (``tilt_noise``, ``heading_noise`` in rad·√s):
  ``R = σ²/Δt`` per update, so the correction time constants, ``tilt_noise /
  gyr_noise`` and ``heading_noise / gyr_noise``, do not depend on the sample rates.

Every update goes through :func:`app.estimators.kalman.correct`. The per-row code is
numba-compiled (``robust_step``); ``robust_run`` loops it over arrays for batch
use. The same functions run uncompiled (``.py_func``) as the readable numpy reference.
The kernels read the parameters, the coefficients derived from them and the state from
two flat arrays whose slots are named once (``PRM`` and ``S``, see "layouts" below).
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import MISSING, dataclass, fields as dataclass_fields

import numpy as np
from numba import njit

from .. import quaternion as qm
from ..params import CommonParams, DEG, param
from .base import (F_ACC, F_ACC_NIS, F_ACC_VAL, F_GYR, F_MAG, F_MAG_NIS, F_MAG_VAL, F_REST,
                   F_TIME, R_DIP, R_LATE, R_NIS, R_NORM, R_REST,
                   R_USED, R_GAP, R_ABSENT, R_ACCEL, R_NEW_FIELD, R_RECOVER, R_BIAS_RESET, R_TURN,
                   T_BACKWARD, T_GAP, T_OK, ALIGN_ACC, ALIGN_ACC_MAG, ALIGN_NO_ACC,
                   align_step,
                   Estimator, row_prologue)
from .kalman import correct

GRAVITY = 9.81


@dataclass(frozen=True)
class RobustParams(CommonParams):
    gyr_noise: float = param(0.005, unit="rad/√s", lo=1e-6, hi=1.0, log=True, user_unit="deg/√s",
                             user_scale=DEG, doc="gyroscope noise density (attitude random walk)")
    bias_noise: float = param(3e-5, unit="rad/s/√s", lo=0.0, hi=0.1, log=True, user_unit="deg/s/√s",
                              user_scale=DEG, doc="gyroscope bias random walk")
    bias_max: float = param(0.3, unit="rad/s", lo=0.0, hi=10.0, user_unit="deg/s", user_scale=DEG,
                            doc="a bias estimate above this is implausible (the filter is lost): it "
                                "is reset and flagged; 0: off")
    gyr_scale_noise: float = param(0.02, unit="√s", lo=0.0, hi=1.0,
                                   doc="tilt noise density per rad/s of net turn rate (the world-frame "
                                       "turn rate low-passed over acc_tau): a gyroscope's scale factor, off "
                                       "by 0.2-3 %, turns the estimate by that share of the net rotation "
                                       "(0.02 √s: about 1 % over acc_tau), so a steady turn makes the tilt "
                                       "correct faster; a back-and-forth (running, swinging) cancels and "
                                       "does not; 0: off")
    refused_turn_noise: float = param(0.01, unit="√s", lo=0.0, hi=1.0,
                                      doc="heading noise density per rad/s of vertical turn rate while the "
                                          "field is refused as disturbed: the gyroscope alone then keeps the "
                                          "heading, off by its scale error (0.2-3 %) × the turn, so the heading "
                                          "σ grows with the turn and the first good field after a long refusal "
                                          "corrects at once, not at the steady rate (0.01 √s: 1 % of a turn "
                                          "over a second); 0: off")
    bias_init: float = param(0.01, unit="rad/s", lo=0.0, hi=1.0, log=True, user_unit="deg/s",
                             user_scale=DEG, doc="σ of the gyroscope bias at the start")
    bias_motion_noise: float = param(1.0 / DEG, unit="rad/s·√s", lo=0.0, hi=1.0, user_unit="deg/s·√s",
                                     user_scale=DEG,
                                     doc="noise density of the bias seen in the rate of the tilt corrections "
                                         "(during motion the specific force left after the low-pass makes "
                                         "the corrections wander for seconds); 0: no bias learning in motion")
    bias_motion_clip: float = param(2.0 / DEG, unit="rad/s", lo=0.0, hi=1.0, user_unit="deg/s",
                                    user_scale=DEG,
                                    doc="a correction rate is taken to show at most this much bias error "
                                        "(a first correction after a moving start, a shake, is no bias); "
                                        "the estimate itself is not clipped: a phone's 3-6 °/s is learned "
                                        "at rest at once, in motion in steps of this; 0: no clip")
    bias_heading_noise: float = param(2.0 / DEG, unit="rad/s·√s", lo=0.0, hi=1.0, user_unit="deg/s·√s",
                                      user_scale=DEG,
                                      doc="likewise for the bias about the vertical, seen in the rate of the "
                                          "heading corrections (indoor fields bend the heading by degrees "
                                          "for many seconds: larger than the tilt's); 0: off")
    gyr_bias: tuple = param((0.0, 0.0, 0.0), unit="rad/s", lo=-1.0, hi=1.0, tunable=False,
                            doc="initial gyroscope bias (calibration)")
    tilt_noise: float = param(0.015, unit="rad·√s", lo=1e-5, hi=10.0, log=True, user_unit="deg·√s",
                              user_scale=DEG, doc="noise density of the low-passed gravity direction")
    acc_tau: float = param(4.5, unit="s", lo=0.0, hi=60.0,
                           doc="time constant of the inertial low-pass of the accelerometer")
    tilt_damping: float = param(math.sqrt(0.5), lo=0.0, hi=2.0,
                                doc="damping ratio ζ of the tilt loop (the low-pass and the corrections "
                                    "together, a second-order system): 1/√2 as VQF's Butterworth "
                                    "low-pass, a drift error of 2ζ/ωn; 1 critically damped; 0: off (the "
                                    "low-pass turns with every correction: overdamped, ζ >= 1, it lags "
                                    "more)")
    acc_band_rel: float = param(0.0, lo=0.0, hi=2.0,
                                doc="tilt corrections pause while | |a| - g | > this × g (every sample "
                                    "still enters the low-pass); 0: off")
    tilt_motion_time: float = param(0.0, unit="s", lo=0.0, hi=10.0,
                                    doc="correlation time of the specific force: its power (low-passed, "
                                        "over g²) times this is added to tilt_noise² (0: off)")
    acc_flag_angle: float = param(10.0 * math.pi / 180.0, unit="rad", lo=0.0, hi=3.2, user_unit="deg",
                                  user_scale=DEG, doc="a sample this far from the low-passed gravity is "
                                                      "flagged as specific force (ACCEL; it still enters "
                                                      "the low-pass); 0: off")
    acc_flag_rel: float = param(0.1, lo=0.0, hi=5.0,
                                doc="likewise when | |a| - g | > this × g; 0: off")
    acc_nis_gate: float = param(30.0, lo=0.0, hi=1000.0,
                                doc="NIS gate of the tilt update (χ², 2 dof); 0: off")
    heading_noise: float = param(0.15, unit="rad·√s", lo=1e-5, hi=10.0, log=True, user_unit="deg·√s",
                                 user_scale=DEG, doc="noise density of the magnetometer heading")
    mag_nis_gate: float = param(30.0, lo=0.0, hi=1000.0,
                                doc="NIS gate of the heading update (χ², 1 dof); 0: off")
    mag_norm_gate_rel: float = param(0.15, lo=0.0, hi=2.0,
                                     doc="field strength may differ from the reference by this fraction; 0: off")
    mag_dip_gate: float = param(10.0 * math.pi / 180.0, unit="rad", lo=0.0, hi=1.6, user_unit="deg", user_scale=DEG,
                                doc="dip angle may differ from the reference by this much; 0: off")
    mag_ref_tau: float = param(20.0, unit="s", lo=0.1, hi=3600.0,
                               doc="time constant of learning the field reference while undisturbed")
    mag_new_field_time: float = param(20.0, unit="s", lo=0.0, hi=600.0,
                                      doc="a new homogeneous field is accepted after this long while turning")
    mag_new_min_rate: float = param(20.0 / DEG, unit="rad/s", lo=0.0, hi=10.0, user_unit="deg/s",
                                    user_scale=DEG, doc="turn rate that counts towards accepting a new field")
    mag_max_reject: float = param(60.0, unit="s", lo=0.0, hi=3600.0,
                                  doc="after this long refused as disturbed, the heading update resumes "
                                      "mag_reject_factor times slower (a field that stays is the field); "
                                      "0: never")
    mag_reject_factor: float = param(2.0, lo=1.0, hi=100.0,
                                     doc="heading noise multiplier of the resumed updates in a field "
                                         "judged disturbed; the rejection budget refills this much faster")
    mag_dev_weight: float = param(1.0, lo=0.0, hi=100.0,
                                  doc="heading σ added per relative deviation of the field from its "
                                      "reference (Δ/|m_h|), within the gates too; 0: off")
    mag_first_field_time: float = param(5.0, unit="s", lo=0.0, hi=600.0,
                                        doc="the first field reference is a field stable this long (until "
                                            "then every sample corrects the heading: nothing to judge it by)")
    mag_min_undisturbed: float = param(0.5, unit="s", lo=0.0, hi=60.0,
                                       doc="a field within the gates this long ends a disturbance")
    mag_norm_dip_tau: float = param(0.05, unit="s", lo=0.0, hi=10.0,
                                    doc="time constant of the low-pass of strength and dip (and of the "
                                        "world-frame field of the turn test) before the gates")
    mag_turn_gate: float = param(15.0 / DEG, unit="rad/s", lo=0.0, hi=100.0, user_unit="deg/s",
                                 user_scale=DEG,
                                 doc="a real field is fixed in the world: seen through the estimate, whose "
                                     "turns are the gyroscope's, it stays put while the phone turns. A field "
                                     "that changes faster than this (relative change, as an angle per second) "
                                     "beyond what the turn explains is a disturbance (flag TURN): a magnet "
                                     "brought in, before its strength or dip leave their gates. 2.5× a "
                                     "phone's largest gyroscope bias (0.1 rad/s, which turns the field this "
                                     "way until it is learned); 0: off")
    mag_turn_rel: float = param(0.5, lo=0.0, hi=10.0,
                                doc="change rate of the world-frame field (rad/s) allowed per rad/s of turn "
                                    "rate: a saturated gyroscope (running) reads at least 2/3 of the turn; "
                                    "scale error, magnetometer lag and residual hard iron are smaller")
    mag_turn_tau: float = param(0.2, unit="s", lo=0.01, hi=10.0,
                                doc="the turn test's time scale: the world-frame field low-passed over "
                                    "mag_norm_dip_tau is low-passed again over this, a change at rate r "
                                    "leaves it behind by r × this; the turn rate is low-passed over it too")
    rest_gyr_th: float = param(2.0 / DEG, unit="rad/s", lo=0.0, hi=1.0, user_unit="deg/s", user_scale=DEG,
                               doc="rest: gyroscope deviation from its low-pass below this")
    rest_acc_th: float = param(0.5, unit="m/s²", lo=0.0, hi=10.0,
                               doc="rest: accelerometer deviation from its low-pass below this")
    rest_time: float = param(1.5, unit="s", lo=0.0, hi=60.0, doc="quiet this long = at rest; 0: no rest detection")
    rest_noise: float = param(0.0016, unit="rad/s·√s", lo=1e-6, hi=1.0, log=True, user_unit="deg/s·√s",
                              user_scale=DEG, doc="noise density of the bias measurement at rest (VQF's "
                                                  "0.09 °/s·√s: ten times a phone gyroscope's white noise, "
                                                  "for a table that trembles; a short rest must teach "
                                                  "the bias, motion teaches it slowly)")
    rw_noise: float = param(0.5, unit="rad/√s", lo=1e-4, hi=10.0, log=True,
                            doc="attitude random walk without gyroscope")
    update_rate_hz: float = param(50.0, unit="Hz", lo=0.0, hi=10000.0,
                                  doc="most measurement updates per second and sensor (the low-passes "
                                      "and averages see every sample); 0: every sample")
    rest_lp_tau: float = param(0.5, unit="s", lo=0.0, hi=10.0,
                               doc="rest detection: time constant of the gyroscope and accelerometer "
                                   "low-passes the samples are compared with")
    mag_cand_tau: float = param(2.0, unit="s", lo=0.0, hi=60.0,
                                doc="time constant of the candidate new field's strength and dip")
    mag_cand_norm_rel: float = param(0.05, lo=0.0, hi=2.0,
                                     doc="a candidate new field stays one while its strength stays within "
                                         "this fraction (at least mag_norm_gate_rel)")
    mag_cand_dip: float = param(0.05, unit="rad", lo=0.0, hi=1.6, user_unit="deg", user_scale=DEG,
                                doc="likewise for its dip angle (at least mag_dip_gate)")
    mag_lost_angle: float = param(30.0 * math.pi / 180.0, unit="rad", lo=0.0, hi=3.2, user_unit="deg",
                                  user_scale=DEG, doc="an undisturbed field this far from the estimated "
                                                      "heading for mag_lost_time means the estimate is lost")
    mag_lost_time: float = param(5.0, unit="s", lo=0.0, hi=600.0,
                                 doc="after this long with an undisturbed field far from the heading (or "
                                     "refused by the NIS gate), the estimate is judged lost: its heading σ "
                                     "grows to the error and the field's heading is taken (flag RECOVER); "
                                     "0: never")
    init_tilt_std: float = param(10.0 * math.pi / 180.0, unit="rad", lo=1e-4, hi=3.2, user_unit="deg",
                                 user_scale=DEG, doc="σ of the tilt after the initial alignment")
    init_heading_std: float = param(20.0 * math.pi / 180.0, unit="rad", lo=1e-4, hi=3.2, user_unit="deg",
                                    user_scale=DEG, doc="σ of the heading after an alignment with the field")
    noacc_tilt_std: float = param(30.0 * math.pi / 180.0, unit="rad", lo=1e-4, hi=3.2, user_unit="deg",
                                  user_scale=DEG, doc="σ of the tilt of a start without accelerometer (level)")


# ----------------------------------------------------------------- layouts
# The compiled kernels keep the filter in two flat float arrays, the state ``s`` and the
# parameter vector ``p`` (numba's fastest form). Their slots are NAMED here, once: ``S.q``
# is the offset of the attitude in ``s``, ``PRM.gyr_noise`` the offset of that parameter in
# ``p``. As in vqf's pyvqf.py, three kinds of numbers are kept apart: parameters (the
# user's, :class:`RobustParams`), coefficients derived from them (``DERIVED`` below,
# recomputed by ``RobustEKF._on_params`` on every change) and the state (``STATE``).

def _layout(name: str, fields) -> tuple:
    """A namedtuple of offsets for ``fields`` ((name, size), ...) and the total size.
    numba folds a global namedtuple's fields into constants: no cost per access."""
    offsets, n = {}, 0
    for fname, size in fields:
        offsets[fname] = n
        n += size
    return namedtuple(name, offsets)(**offsets), n


# coefficients derived from the parameters (appended to the parameter vector)
DERIVED = (
    ("upd_dt", 1, "s between two measurement updates of a sensor (1/update_rate_hz; 0: every sample)"),
    ("acc_flag_cos", 1, "cos(acc_flag_angle): the flag test compares cosines"),
)

STATE = (
    ("q", 4, "nominal attitude [w, x, y, z], sensor to world"),
    ("bias", 3, "gyroscope bias (rad/s, sensor frame)"),
    ("acc_lp", 3, "low-passed specific force, world frame of the estimate (m/s²)"),
    ("gyr_lp", 3, "low-passed gyroscope (rest detection)"),
    ("acc_lp_rest", 3, "low-passed accelerometer, sensor frame (rest detection)"),
    ("quiet_time", 1, "s quiet so far (rest detection)"),
    ("t", 1, "time of the last row"),
    ("aligned", 1, "1 once aligned"),
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
    ("reject_time", 1, "s of continuous magnetic rejection"),
    ("t0", 1, "time of the alignment"),
    ("mag_t", 1, "time of the last magnetometer update attempt"),
    ("acc_t", 1, "time of the last accelerometer sample"),
    ("gyr_lp_t", 1, "time of the last gyroscope sample in the rest low-pass (NaN: none yet)"),
    ("rest", 1, "1 at rest"),
    ("far_time", 1, "s the heading has disagreed with an undisturbed field (far or NIS-refused)"),
    ("acc_upd_time", 1, "s of used accelerometer samples since the last tilt update"),
    ("rest_upd_time", 1, "s at rest since the last bias update"),
    ("mag_sum", 3, "sum of world-frame field samples since the last heading update"),
    ("mag_count", 1, "how many"),
    ("mag_upd_time", 1, "s of used magnetometer samples since the last heading update"),
    ("acc_lp_rest_t", 1, "time of the last accelerometer sample in the rest low-pass"),
    ("w_cur", 3, "scratch: the rate integrated over the current row"),
    ("pred_T", 18, "scratch of the time update: R [Pbb | Pbt], 3x6 by rows"),
    ("seen", 1, "sensors seen at the time of the last row (bit mask)"),
    ("mag_nd", 2, "low-passed field strength (µT) and dip (rad)"),
    ("mag_nd_ok", 1, "1 once mag_nd holds a sample"),
    ("undisturbed_time", 1, "s the field has been within the gates"),
    ("disturbed", 1, "1 while the field is judged disturbed"),
    ("dist_reason", 1, "Reason of the current disturbance (NORM, DIP or TURN)"),
    ("dist_val", 1, "TURN: the latest unexplained change rate of the field (rad/s)"),
    ("bias_good", 3, "the bias estimate before the heading began to disagree with the field"),
    ("acc_var", 1, "low-passed power of the specific force, |a - low-pass|² (m²/s⁴)"),
    ("mb_ok", 1, "1 once the motion-bias low-passes hold a value"),
    ("mb_R", 9, "motion bias: low-passed rotation matrix (rows of R, sensor to world)"),
    ("mb_Rb", 2, "motion bias: low-passed horizontal rows of R b (rad/s)"),
    ("mb_sum", 3, "tilt (x, y) and heading (z) corrections since the last bias update (rad)"),
    ("mb_time", 2, "s of tilt / heading corrections summed there"),
    ("mt_lp", 6, "field turn test: the world-frame field (µT, estimate's frame) low-passed over "
                 "mag_norm_dip_tau, then that over mag_turn_tau"),
    ("mt_rate", 1, "field turn test: low-passed turn rate (rad/s)"),
    ("mt_ok", 1, "1 once the field turn test's low-passes hold a value"),
    ("turn_lp", 2, "net turn rate about the horizontal axes: the world-frame turn rate's x, y "
                   "(rad/s, bias removed) low-passed over acc_tau (gyr_scale_noise: tilt only)"),
)
# slots that start as NaN ("not yet")
_STATE_NAN = ("t", "gyr_held_t", "wait_t", "t0", "mag_t", "acc_t", "gyr_lp_t", "acc_lp_rest_t")


def _param_fields():
    """(name, size) of every RobustParams field, in order, then the derived coefficients."""
    out = []
    for f in dataclass_fields(RobustParams):
        default = f.default_factory() if f.default is MISSING else f.default
        out.append((f.name, len(default) if isinstance(default, tuple) else 1))
    return tuple(out) + tuple((n, k) for n, k, _ in DERIVED)


S, NSTATE = _layout("StateLayout", ((n, k) for n, k, _ in STATE))
PRM, NPARAM = _layout("ParamLayout", _param_fields())

# Longest interval (s) a low-pass or an update accumulator takes from one sample: a stall
# in the stream must not look like a long, information-rich average.
DT_MAX = 0.1

# The bias learned in motion follows the correction rates over a minute: it is updated
# with the corrections summed over this long (s), not after every correction.
BIAS_UPD_S = 0.1

_MASK_HEADING = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
_MASK_ATTITUDE = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
_MASK_BIAS = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0])

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
def _rotate3(s, v):
    """Q(q) v for the state's attitude, as three floats (no array made per sample)."""
    w, x, y, z = s[S.q], s[S.q + 1], s[S.q + 2], s[S.q + 3]
    tx = 2.0 * (y * v[2] - z * v[1])
    ty = 2.0 * (z * v[0] - x * v[2])
    tz = 2.0 * (x * v[1] - y * v[0])
    return (v[0] + w * tx + (y * tz - z * ty), v[1] + w * ty + (z * tx - x * tz),
            v[2] + w * tz + (x * ty - y * tx))


@njit(cache=True)
def _lp_coef(dt, tau):
    """First-order low-pass coefficient (the DNRF form 1 - τ/(τ+Δt))."""
    if tau <= 0.0:
        return 1.0
    return dt / (tau + dt)


@njit(cache=True)
def _exp3(vx, vy, vz):
    """exp of the rotation vector (vx, vy, vz) as four scalars (qm.quat_from_rotvec)."""
    a = np.sqrt(vx * vx + vy * vy + vz * vz)
    k = 0.5 if a < 1e-12 else np.sin(0.5 * a) / a
    return np.cos(0.5 * a), vx * k, vy * k, vz * k


@njit(cache=True)
def _rotate_slot(s, j, d0, d1, d2, d3):
    """s[j:j+3] rotated by the unit quaternion (d0, d1, d2, d3) in place (qm.rotate)."""
    ax, ay, az = s[j], s[j + 1], s[j + 2]
    tx = 2.0 * (d2 * az - d3 * ay)
    ty = 2.0 * (d3 * ax - d1 * az)
    tz = 2.0 * (d1 * ay - d2 * ax)
    s[j] = ax + d0 * tx + (d2 * tz - d3 * ty)
    s[j + 1] = ay + d0 * ty + (d3 * tx - d1 * tz)
    s[j + 2] = az + d0 * tz + (d1 * ty - d2 * tx)


@njit(cache=True)
def _inject(s, P, dx, lp_frac=1.0):
    """Apply an error-state correction: q <- exp(δθ) ⊗ q, b <- b + δb, and rotate
    the world-frame low-pass with the attitude so it stays in the estimate's frame
    (with ``lp_frac`` of the tilt part of δθ only: the tilt loop's damping)."""
    # dq = exp(δθ) (qm.quat_from_rotvec), q <- normalize(dq ⊗ q) (qm.quat_mul,
    # qm.normalize) and the low-passes rotated by dq (qm.rotate), written out in scalars
    # with the same arithmetic: an update makes no array here
    vx, vy, vz = dx[0], dx[1], dx[2]
    d0, d1, d2, d3 = _exp3(vx, vy, vz)
    q0, q1, q2, q3 = s[S.q], s[S.q + 1], s[S.q + 2], s[S.q + 3]
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
    s[S.q], s[S.q + 1], s[S.q + 2], s[S.q + 3] = r0 * c, r1 * c, r2 * c, r3 * c
    for i in range(3):
        s[S.bias + i] += dx[3 + i]
    if lp_frac != 1.0:
        # the tilt's low-pass turns with the heading part and lp_frac of the tilt part
        # (the tilt loop's damping); everything else turns with the whole correction
        e0, e1, e2, e3 = _exp3(vx * lp_frac, vy * lp_frac, vz)
        _rotate_slot(s, S.acc_lp, e0, e1, e2, e3)
    else:
        _rotate_slot(s, S.acc_lp, d0, d1, d2, d3)
    _rotate_slot(s, S.mt_lp, d0, d1, d2, d3)        # the field turn test's two low-passes
    _rotate_slot(s, S.mt_lp + 3, d0, d1, d2, d3)


@njit(cache=True)
def _align(s, P, p, t, acc, mag, use_mag):
    s[S.q:S.q + 4] = qm.q_from_acc_mag(acc, mag, use_mag)
    for i in range(3):
        s[S.bias + i] = p[PRM.gyr_bias + i]
    s[S.acc_lp:S.acc_lp + 3] = qm.rotate(s[S.q:S.q + 4], acc)
    s[S.acc_var] = 0.0
    s[S.turn_lp:S.turn_lp + 2] = 0.0
    s[S.mb_ok] = 0.0
    s[S.mb_sum:S.mb_sum + 3] = 0.0
    s[S.mb_time:S.mb_time + 2] = 0.0
    P[:, :] = 0.0
    tilt0 = p[PRM.init_tilt_std]
    head0 = p[PRM.init_heading_std] if use_mag else np.pi
    P[0, 0] = tilt0 ** 2
    P[1, 1] = tilt0 ** 2
    P[2, 2] = head0 ** 2
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
    s[S.reject_time] = 0.0
    s[S.cand_time] = 0.0
    s[S.far_time] = 0.0
    s[S.mag_nd_ok] = 0.0
    s[S.undisturbed_time] = 0.0
    s[S.disturbed] = 0.0
    s[S.mt_ok] = 0.0


@njit(cache=True)
def _integrate(s, vx, vy, vz):
    """q <- q ⊗ exp(v) for the body-frame rotation vector v (exact, formula 2j), w >= 0."""
    a = np.sqrt(vx * vx + vy * vy + vz * vz)
    c = np.cos(0.5 * a)
    k = 0.5 if a < 1e-12 else np.sin(0.5 * a) / a
    x, y, z = vx * k, vy * k, vz * k
    q0, q1, q2, q3 = s[S.q], s[S.q + 1], s[S.q + 2], s[S.q + 3]
    r0 = q0 * c - q1 * x - q2 * y - q3 * z
    r1 = q0 * x + q1 * c + q2 * z - q3 * y
    r2 = q0 * y - q1 * z + q2 * c + q3 * x
    r3 = q0 * z + q1 * y - q2 * x + q3 * c
    n = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
    if r0 < 0.0:
        n = -n
    s[S.q], s[S.q + 1], s[S.q + 2], s[S.q + 3] = r0 / n, r1 / n, r2 / n, r3 / n


@njit(cache=True)
def _due(s, idx, dt, p):
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


@njit(cache=True)
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
    # R = Q(q) (formula 2a) of the attitude before this step, as nine scalars
    q0, q1, q2, q3 = s[S.q], s[S.q + 1], s[S.q + 2], s[S.q + 3]
    r00 = 2.0 * (q0 * q0 + q1 * q1) - 1.0
    r01 = 2.0 * (q1 * q2 - q0 * q3)
    r02 = 2.0 * (q1 * q3 + q0 * q2)
    r10 = 2.0 * (q1 * q2 + q0 * q3)
    r11 = 2.0 * (q0 * q0 + q2 * q2) - 1.0
    r12 = 2.0 * (q2 * q3 - q0 * q1)
    r20 = 2.0 * (q1 * q3 - q0 * q2)
    r21 = 2.0 * (q2 * q3 + q0 * q1)
    r22 = 2.0 * (q0 * q0 + q3 * q3) - 1.0
    wx, wy, wz = w[0] - s[S.bias], w[1] - s[S.bias + 1], w[2] - s[S.bias + 2]
    _integrate(s, wx * dt, wy * dt, wz * dt)
    # F = [[I, -R dt], [0, I]];  P <- F P F' + Qd, by blocks with T = R [Pbb | Pbt]:
    # Ptt += dt² T[:, :3] R' - dt (T[:, 3:] + T[:, 3:]');  Ptb -= dt T[:, :3]
    # (T lives in a scratch slot of the state: no array is made per sample)
    T = s[S.pred_T:S.pred_T + 18]
    for i in range(3):
        ri0, ri1, ri2 = (r00, r01, r02) if i == 0 else ((r10, r11, r12) if i == 1 else (r20, r21, r22))
        for j in range(3):
            T[6 * i + j] = ri0 * P[3, 3 + j] + ri1 * P[4, 3 + j] + ri2 * P[5, 3 + j]      # R Pbb
            T[6 * i + 3 + j] = ri0 * P[3, j] + ri1 * P[4, j] + ri2 * P[5, j]              # R Pbt
    dt2 = dt * dt
    for i in range(3):
        for j in range(i, 3):
            rj0, rj1, rj2 = (r00, r01, r02) if j == 0 else ((r10, r11, r12) if j == 1 else (r20, r21, r22))
            v = -dt * (T[6 * i + 3 + j] + T[6 * j + 3 + i])
            v += dt2 * T[6 * i] * rj0
            v += dt2 * T[6 * i + 1] * rj1
            v += dt2 * T[6 * i + 2] * rj2
            P[i, j] += v
            if j != i:
                P[j, i] = P[i, j]
    for i in range(3):
        for j in range(3):
            P[i, 3 + j] -= dt * T[6 * i + j]
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
        k = _lp_coef(min(dt, DT_MAX), p[PRM.acc_tau])
        j = S.turn_lp
        s[j] += k * ((r00 * wx + r01 * wy + r02 * wz) - s[j])
        s[j + 1] += k * ((r10 * wx + r11 * wy + r12 * wz) - s[j + 1])
        ux, uy = s[j], s[j + 1]
        g2 = p[PRM.gyr_scale_noise] ** 2 * dt
        P[0, 0] += g2 * ux * ux
        P[0, 1] += g2 * ux * uy
        P[1, 1] += g2 * uy * uy
        P[1, 0] = P[0, 1]


@njit(cache=True)
def _lp_sensor(s, idx, idx_t, v, t, tau):
    """Low-pass ``s[idx:idx+3]`` towards v with the time since that sensor's last
    sample (a phone sends one sensor per row); returns |v - low-pass|."""
    if np.isnan(s[idx_t]):
        s[idx:idx + 3] = v
        s[idx_t] = t
        return 0.0
    k = _lp_coef(min(t - s[idx_t], DT_MAX), tau)
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
    if p[PRM.rest_time] <= 0.0:
        s[S.rest] = 0.0
        return
    quiet = True
    if has_gyr and _lp_sensor(s, S.gyr_lp, S.gyr_lp_t, gyr, t, p[PRM.rest_lp_tau]) > p[PRM.rest_gyr_th]:
        quiet = False
    if has_acc and _lp_sensor(s, S.acc_lp_rest, S.acc_lp_rest_t, acc, t, p[PRM.rest_lp_tau]) > p[PRM.rest_acc_th]:
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
    ok, nis, dx = correct(P, H_BIAS, Rm, innov, 0.0)
    if ok:
        _inject(s, P, dx)
        f[F_GYR] = R_REST


@njit(cache=True)
def _acc_update(s, P, p, t, acc, f):
    n = qm.norm3(acc)
    f[F_ACC_VAL] = n
    dt = t - s[S.acc_t] if np.isfinite(s[S.acc_t]) else 0.0
    s[S.acc_t] = t
    if dt <= 0.0:
        dt = 1e-3
    # inertial low-pass, with a running mean while younger than acc_tau (fast start)
    k = _lp_coef(dt, p[PRM.acc_tau])
    age = t - s[S.t0]
    if age > 0.0 and dt / (age + dt) > k:
        k = dt / (age + dt)
    aw = _rotate3(s, acc)
    d2 = 0.0
    for i in range(3):
        s[S.acc_lp + i] += k * (aw[i] - s[S.acc_lp + i])
        d2 += (aw[i] - s[S.acc_lp + i]) ** 2
    # the power of the specific force over the same window (what the low-pass averages out)
    s[S.acc_var] += k * (d2 - s[S.acc_var])
    f[F_ACC] = R_USED  # in the low-pass; the correction below runs at most at update_rate_hz
    # specific force: the sample is far from the low-passed gravity (angle) or from g
    # (norm): the phone accelerates. It still enters the low-pass (the accelerations
    # average out there) but is flagged, so a shake shows, with the angle as its value.
    if p[PRM.acc_flag_angle] > 0.0 or p[PRM.acc_flag_rel] > 0.0:
        ln = qm.norm3(s[S.acc_lp:S.acc_lp + 3])
        c = (aw[0] * s[S.acc_lp] + aw[1] * s[S.acc_lp + 1] + aw[2] * s[S.acc_lp + 2]) / max(n * ln, 1e-12)
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
    due, elapsed = _due(s, S.acc_upd_time, dt, p)
    if not due:
        return
    dt = elapsed
    a = s[S.acc_lp:S.acc_lp + 3]
    an = qm.norm3(a)
    if an < 1e-6:
        return
    # noise density of the low-passed direction: the sensor's, plus what the specific force
    # leaves in it (its power over g², times its correlation time): a walking or running
    # phone's gravity estimate is trusted less than a still one's
    r = (p[PRM.tilt_noise] ** 2 + p[PRM.tilt_motion_time] * s[S.acc_var] / (GRAVITY * GRAVITY)) / dt
    Rm = np.zeros((2, 2))
    Rm[0, 0] = r
    Rm[1, 1] = r
    # the tilt update corrects the attitude only: its error is the specific force left in the
    # low-pass, correlated for seconds, which a white-noise model would let the bias absorb
    # (the bias is learned from the corrections' rate below, slowly, as VQF does)
    lp_frac = _tilt_lp_share(P, r, dt, p) if p[PRM.tilt_damping] > 0.0 else 1.0
    ok, nis, dx = correct(P, tilt_jacobian(a), Rm, tilt_innovation(a), p[PRM.acc_nis_gate], _MASK_ATTITUDE)
    f[F_ACC_NIS] = nis
    if ok:
        _inject(s, P, dx, lp_frac)
        if p[PRM.bias_motion_noise] > 0.0:
            s[S.mb_sum] += dx[0]
            s[S.mb_sum + 1] += dx[1]
            s[S.mb_time] += dt
            if s[S.mb_time] >= BIAS_UPD_S:
                _motion_bias_update(s, P, p, s[S.mb_sum], s[S.mb_sum + 1], s[S.mb_time])
                s[S.mb_sum] = 0.0
                s[S.mb_sum + 1] = 0.0
                s[S.mb_time] = 0.0
    else:
        f[F_ACC] = R_NIS
        f[F_ACC_VAL] = nis


@njit(cache=True)
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


@njit(cache=True)
def _motion_bias_update(s, P, p, dx0, dx1, dt):
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
    q0, q1, q2, q3 = s[S.q], s[S.q + 1], s[S.q + 2], s[S.q + 3]
    R = s[S.mb_R:S.mb_R + 9]
    r = (2.0 * (q0 * q0 + q1 * q1) - 1.0, 2.0 * (q1 * q2 - q0 * q3), 2.0 * (q1 * q3 + q0 * q2),
         2.0 * (q1 * q2 + q0 * q3), 2.0 * (q0 * q0 + q2 * q2) - 1.0, 2.0 * (q2 * q3 - q0 * q1),
         2.0 * (q1 * q3 - q0 * q2), 2.0 * (q2 * q3 + q0 * q1), 2.0 * (q0 * q0 + q3 * q3) - 1.0)
    b0, b1, b2 = s[S.bias], s[S.bias + 1], s[S.bias + 2]
    rb0 = r[0] * b0 + r[1] * b1 + r[2] * b2
    rb1 = r[3] * b0 + r[4] * b1 + r[5] * b2
    if s[S.mb_ok] == 0.0:
        for i in range(9):
            R[i] = r[i]
        s[S.mb_Rb] = rb0
        s[S.mb_Rb + 1] = rb1
        s[S.mb_ok] = 1.0
    else:
        k = _lp_coef(dt, p[PRM.acc_tau])
        for i in range(9):
            R[i] += k * (r[i] - R[i])
        s[S.mb_Rb] += k * (rb0 - s[S.mb_Rb])
        s[S.mb_Rb + 1] += k * (rb1 - s[S.mb_Rb + 1])
    if s[S.rest] != 0.0:
        return  # at rest the gyroscope itself measures the bias (_rest_update)
    innov = np.empty(2)
    innov[0] = s[S.mb_Rb] - dx0 / dt - (R[0] * b0 + R[1] * b1 + R[2] * b2)
    innov[1] = s[S.mb_Rb + 1] - dx1 / dt - (R[3] * b0 + R[4] * b1 + R[5] * b2)
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
    ok, nis, db = correct(P, H, Rm, innov, 0.0, _MASK_BIAS)
    if ok:
        for i in range(3):
            s[S.bias + i] += db[3 + i]


@njit(cache=True)
def _heading_bias_update(s, P, p, dz, dt):
    """The bias about the vertical from the rate of the heading corrections, as
    :func:`_motion_bias_update` does for x and y: a bias error δb turns the heading at
    -(R δb)_z, the corrections follow at that rate. The heading update itself corrects the
    heading only: through the cross-covariances a field bent for seconds (and, with a dipping
    field, the tilt columns of its Jacobian) would pull every axis of the bias."""
    q0, q1, q2, q3 = s[S.q], s[S.q + 1], s[S.q + 2], s[S.q + 3]
    H = np.zeros((1, 6))
    H[0, 3] = 2.0 * (q1 * q3 - q0 * q2)
    H[0, 4] = 2.0 * (q2 * q3 + q0 * q1)
    H[0, 5] = 2.0 * (q0 * q0 + q3 * q3) - 1.0
    innov = np.empty(1)
    innov[0] = -dz / dt
    clip = p[PRM.bias_motion_clip]
    if clip > 0.0:
        innov[0] = min(clip, max(-clip, innov[0]))
    Rm = np.empty((1, 1))
    Rm[0, 0] = p[PRM.bias_heading_noise] ** 2 / dt
    ok, nis, db = correct(P, H, Rm, innov, 0.0, _MASK_BIAS)
    if ok:
        for i in range(3):
            s[S.bias + i] += db[3 + i]


@njit(cache=True)
def _field_check(s, p, n, dip, dt, rate, turn, f):
    """Judge the field (strength ``n``, dip) against the learned reference, as VQF does:
    a disturbance is a strength or dip off the reference; it ends after the field has been
    within the gates for ``mag_min_undisturbed``; a new homogeneous field (stable strength
    and dip while the phone turns for ``mag_new_field_time``) becomes the reference; the
    first reference is the first field stable for ``mag_first_field_time`` (a phone that
    starts moving, or next to a desk, must not fix it from its first samples).
    A field that changes faster than the phone turns (``turn`` > 0, the unexplained change
    rate, see :func:`_turn_check`) is a disturbance too (TURN), judged after strength and dip.
    Returns True when the sample may correct the heading (no reference yet, or undisturbed)."""
    # low-pass of strength and dip: one sample's noise is no disturbance
    if s[S.mag_nd_ok] == 0.0:
        s[S.mag_nd] = n
        s[S.mag_nd + 1] = dip
        s[S.mag_nd_ok] = 1.0
        s[S.cand_norm] = n
        s[S.cand_dip] = dip
        s[S.cand_time] = 0.0
    else:
        k = _lp_coef(dt, p[PRM.mag_norm_dip_tau])
        s[S.mag_nd] += k * (n - s[S.mag_nd])
        s[S.mag_nd + 1] += k * (dip - s[S.mag_nd + 1])
    nf, df = s[S.mag_nd], s[S.mag_nd + 1]
    # candidate for a new homogeneous field: stable strength and dip (while turning)
    cn_dev = abs(nf - s[S.cand_norm]) / max(s[S.cand_norm], 1e-6)
    cd_dev = abs(df - s[S.cand_dip])
    if (cn_dev <= max(p[PRM.mag_norm_gate_rel], p[PRM.mag_cand_norm_rel])
            and cd_dev <= max(p[PRM.mag_dip_gate], p[PRM.mag_cand_dip])):
        if rate >= p[PRM.mag_new_min_rate] or s[S.ref_ok] == 0.0:
            s[S.cand_time] += dt
        kc = _lp_coef(dt, p[PRM.mag_cand_tau]) if dt > 0 else 0.0
        s[S.cand_norm] += kc * (nf - s[S.cand_norm])
        s[S.cand_dip] += kc * (df - s[S.cand_dip])
    else:
        s[S.cand_norm] = nf
        s[S.cand_dip] = df
        s[S.cand_time] = 0.0
    if s[S.ref_ok] == 0.0:
        if s[S.cand_time] >= p[PRM.mag_first_field_time]:
            s[S.ref_norm] = s[S.cand_norm]
            s[S.ref_dip] = s[S.cand_dip]
            s[S.ref_ok] = 1.0
            s[S.disturbed] = 0.0
            s[S.undisturbed_time] = p[PRM.mag_min_undisturbed]
        return True
    # disturbance: strength or dip off the reference
    n_dev = abs(nf - s[S.ref_norm]) / s[S.ref_norm]
    d_dev = abs(df - s[S.ref_dip])
    reason = R_USED
    if p[PRM.mag_norm_gate_rel] > 0.0 and n_dev > p[PRM.mag_norm_gate_rel]:
        reason = R_NORM
    elif p[PRM.mag_dip_gate] > 0.0 and d_dev > p[PRM.mag_dip_gate]:
        reason = R_DIP
    elif turn > 0.0:
        reason = R_TURN
    if reason == R_USED:
        s[S.undisturbed_time] += dt
        if s[S.undisturbed_time] >= p[PRM.mag_min_undisturbed]:
            s[S.disturbed] = 0.0
            kr = _lp_coef(dt, p[PRM.mag_ref_tau]) if dt > 0 else 0.0
            s[S.ref_norm] += kr * (nf - s[S.ref_norm])
            s[S.ref_dip] += kr * (df - s[S.ref_dip])
    else:
        s[S.undisturbed_time] = 0.0
        s[S.disturbed] = 1.0
        s[S.dist_reason] = reason
        s[S.dist_val] = turn
    if s[S.disturbed] != 0.0 and s[S.cand_time] >= p[PRM.mag_new_field_time]:
        # a new homogeneous field: the phone moved to another place (or a magnet stays on it)
        s[S.ref_norm] = s[S.cand_norm]
        s[S.ref_dip] = s[S.cand_dip]
        s[S.disturbed] = 0.0
        s[S.undisturbed_time] = p[PRM.mag_min_undisturbed]
        s[S.reject_time] = 0.0
        f[F_MAG] = R_NEW_FIELD
        f[F_MAG_VAL] = s[S.ref_norm]
        return True
    if s[S.disturbed] != 0.0:
        f[F_MAG] = s[S.dist_reason]
        r = s[S.dist_reason]
        f[F_MAG_VAL] = nf if r == R_NORM else (s[S.dist_val] if r == R_TURN else d_dev)
        return False
    return True


@njit(cache=True)
def _turn_check(s, p, mw, dt, rate, has_rate):
    """The field turn test: a real field is fixed in the world; seen through the estimate
    (whose turn is the gyroscope's) it stays put while the phone turns. Its change rate is
    measured as the distance between the world-frame field low-passed over
    ``mag_norm_dip_tau`` (one sample's noise is no change) and that low-passed again over
    ``mag_turn_tau``, over ``mag_turn_tau`` and the field's strength (an angle, or a
    relative change of strength, per second: a steady change of rate r leaves the second
    low-pass behind by r·τ). Beyond ``mag_turn_rel`` × the low-passed turn rate (scale
    errors, saturation, lag and hard iron make a real field seem to move while the phone
    turns) it is what the turn does not explain: returned (rad/s) when above
    ``mag_turn_gate``, else 0. Off without a gyroscope."""
    if p[PRM.mag_turn_gate] <= 0.0 or not has_rate:
        s[S.mt_ok] = 0.0
        return 0.0
    if s[S.mt_ok] == 0.0:
        for i in range(3):
            s[S.mt_lp + i] = mw[i]
            s[S.mt_lp + 3 + i] = mw[i]
        s[S.mt_rate] = rate
        s[S.mt_ok] = 1.0
        return 0.0
    tau = p[PRM.mag_turn_tau]
    kf = _lp_coef(dt, p[PRM.mag_norm_dip_tau])
    k = _lp_coef(dt, tau)
    f, g = S.mt_lp, S.mt_lp + 3
    s[f] += kf * (mw[0] - s[f])
    s[f + 1] += kf * (mw[1] - s[f + 1])
    s[f + 2] += kf * (mw[2] - s[f + 2])
    d0, d1, d2 = s[f] - s[g], s[f + 1] - s[g + 1], s[f + 2] - s[g + 2]
    s[g] += k * d0
    s[g + 1] += k * d1
    s[g + 2] += k * d2
    s[S.mt_rate] += k * (rate - s[S.mt_rate])
    # |d| / (|lp| τ) - rel·rate > gate, squared (the square root only for a flag)
    dd = d0 * d0 + d1 * d1 + d2 * d2
    l2 = s[g] * s[g] + s[g + 1] * s[g + 1] + s[g + 2] * s[g + 2]
    allowed = tau * (p[PRM.mag_turn_gate] + p[PRM.mag_turn_rel] * s[S.mt_rate])
    if dd <= allowed * allowed * l2 or l2 <= 0.0:
        return 0.0
    return np.sqrt(dd / l2) / tau - p[PRM.mag_turn_rel] * s[S.mt_rate]


@njit(cache=True)
def _far(s, elapsed):
    """The heading disagrees with an undisturbed field: count the time; at its start,
    keep the bias estimate (what follows may be learned from a wrong heading)."""
    if s[S.far_time] == 0.0:
        s[S.bias_good:S.bias_good + 3] = s[S.bias:S.bias + 3]
    s[S.far_time] += elapsed


@njit(cache=True)
def _mag_update(s, P, p, t, mag, rate, has_rate, f):
    mw = _rotate3(s, mag)
    n = np.sqrt(mw[0] * mw[0] + mw[1] * mw[1] + mw[2] * mw[2])
    dip = np.arcsin(min(1.0, max(-1.0, mw[2] / n)))
    dt = t - s[S.mag_t] if np.isfinite(s[S.mag_t]) else 0.0
    dt = min(max(dt, 0.0), DT_MAX)
    s[S.mag_t] = t
    f[F_MAG_VAL] = n
    f[F_MAG] = R_USED
    turn = _turn_check(s, p, mw, dt, rate, has_rate)
    ok = _field_check(s, p, n, dip, dt, rate, turn, f)
    scale = 1.0
    if ok:
        s[S.reject_time] = max(s[S.reject_time] - p[PRM.mag_reject_factor] * dt, 0.0)
    elif p[PRM.mag_max_reject] > 0.0 and s[S.reject_time] > p[PRM.mag_max_reject]:
        # refused for long: a field that stays is the field; resume, slower (still flagged)
        scale = p[PRM.mag_reject_factor]
    else:
        s[S.reject_time] += dt
        return
    # the samples used are averaged in the world frame; the heading correction with
    # their mean runs at most at update_rate_hz
    for i in range(3):
        s[S.mag_sum + i] += mw[i]
    s[S.mag_count] += 1.0
    due, elapsed = _due(s, S.mag_upd_time, dt, p)
    if not due:
        return
    mx = s[S.mag_sum] / s[S.mag_count]
    my = s[S.mag_sum + 1] / s[S.mag_count]
    mz = s[S.mag_sum + 2] / s[S.mag_count]
    s[S.mag_sum:S.mag_sum + 3] = 0.0
    s[S.mag_count] = 0.0
    hn = np.sqrt(mx * mx + my * my)
    if hn < 1e-3 * n:
        return  # field (almost) vertical: no heading information
    m_mean = np.empty(3)
    m_mean[0], m_mean[1], m_mean[2] = mx, my, mz
    innov = heading_innovation(m_mean)
    Rm = np.empty((1, 1))
    Rm[0, 0] = (scale * p[PRM.heading_noise]) ** 2 / elapsed
    if s[S.ref_ok] != 0.0 and p[PRM.mag_dev_weight] > 0.0:
        # a field off its reference by Δ (strength change, or |m|·Δdip) can turn the
        # horizontal field by up to Δ/|m_h|: that much heading noise, within the gates too
        nh = s[S.ref_norm] * np.cos(s[S.ref_dip])
        dn = s[S.mag_nd] - s[S.ref_norm]
        dd = s[S.mag_nd] * (s[S.mag_nd + 1] - s[S.ref_dip])
        Rm[0, 0] += p[PRM.mag_dev_weight] ** 2 * (dn * dn + dd * dd) / max(nh * nh, 1e-6)
    H = heading_jacobian(m_mean)
    gate = p[PRM.mag_nis_gate]
    lost = ok and p[PRM.mag_lost_time] > 0.0 and s[S.far_time] > p[PRM.mag_lost_time]
    if lost:
        # an undisturbed field has disagreed with the estimate for long: the estimate is
        # what is wrong. Admit it (heading σ up to the error) and take the field's heading;
        # the bias learned meanwhile (from a heading that was wrong) is dropped.
        P[2, 2] += innov[0] ** 2
        gate = 0.0
        s[S.bias:S.bias + 3] = s[S.bias_good:S.bias_good + 3]
    ok2, nis, dx = correct(P, H, Rm, innov, gate, _MASK_HEADING)
    f[F_MAG_NIS] = nis
    if ok2:
        _inject(s, P, dx)
        if not lost and p[PRM.bias_heading_noise] > 0.0 and s[S.rest] == 0.0:
            s[S.mb_sum + 2] += dx[2]
            s[S.mb_time + 1] += elapsed
            if s[S.mb_time + 1] >= BIAS_UPD_S:
                _heading_bias_update(s, P, p, s[S.mb_sum + 2], s[S.mb_time + 1])
                s[S.mb_sum + 2] = 0.0
                s[S.mb_time + 1] = 0.0
        if lost:
            f[F_MAG] = R_RECOVER
            f[F_MAG_VAL] = innov[0]
            s[S.far_time] = 0.0
        elif ok and p[PRM.mag_lost_angle] > 0.0 and abs(innov[0]) > p[PRM.mag_lost_angle]:
            _far(s, elapsed)  # accepted, but still far: the slow correction may not do
        else:
            s[S.far_time] = 0.0
    else:
        if f[F_MAG] == R_USED:
            f[F_MAG] = R_NIS
            f[F_MAG_VAL] = nis
        if ok:
            _far(s, elapsed)


@njit(cache=True)
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
    w = s[S.w_cur:S.w_cur + 3]  # the rate integrated over this row (a slot of the state)
    w[:] = np.nan
    if p[PRM.use_gyr] > 0.5:
        if gs == R_USED:
            w[:] = gyr
            s[S.gyr_held:S.gyr_held + 3] = gyr
            s[S.gyr_held_t] = t
        elif np.isfinite(s[S.gyr_held_t]) and t - s[S.gyr_held_t] <= p[PRM.gyr_hold]:
            w[:] = s[S.gyr_held:S.gyr_held + 3]
    if issue == T_GAP:
        if gs == R_USED:
            f[F_GYR] = R_GAP
        w[:] = np.nan

    if s[S.aligned] == 0.0:
        _try_align(s, P, p, t, acc, mag, gs, as_, ms, f)
        return
    if dt > 0.0:
        _predict(s, P, p, w, dt)
    _rest_update(s, P, p, t, gyr, acc, dt, gs == R_USED, as_ == R_USED, f)
    if as_ == R_USED:
        _acc_update(s, P, p, t, acc, f)
    if ms == R_USED:
        # the turn rate (bias removed) that counts towards accepting a new field
        rate = 0.0
        if not np.isnan(w[0]):
            bx, by, bz = w[0] - s[S.bias], w[1] - s[S.bias + 1], w[2] - s[S.bias + 2]
            rate = np.sqrt(bx * bx + by * by + bz * bz)
        _mag_update(s, P, p, t, mag, rate, not np.isnan(w[0]), f)
    if p[PRM.bias_max] > 0.0:
        bn = qm.norm3(s[S.bias:S.bias + 3])
        if bn > p[PRM.bias_max]:
            # no phone's gyroscope is that far off: the estimate is lost, not the sensor
            for i in range(3):
                s[S.bias + i] = p[PRM.gyr_bias + i]
                for j in range(6):
                    P[3 + i, j] = 0.0
                    P[j, 3 + i] = 0.0
                P[3 + i, 3 + i] = max(p[PRM.bias_init], 1e-6) ** 2
            f[F_GYR] = R_BIAS_RESET


@njit(cache=True)
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


@njit(cache=True)
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
        Qout[k, :] = s[S.q:S.q + 4]


def new_state() -> np.ndarray:
    s = np.zeros(NSTATE)
    s[S.q] = 1.0
    for name in _STATE_NAN:
        s[getattr(S, name)] = np.nan
    s[S.wait_acc:S.wait_acc + 3] = np.nan     # no accelerometer sample yet
    return s


def derived(p: RobustParams) -> dict[str, float]:
    """The coefficients derived from the parameters (see ``DERIVED``)."""
    return {"upd_dt": 1.0 / p.update_rate_hz if p.update_rate_hz > 0 else 0.0,
            "acc_flag_cos": math.cos(p.acc_flag_angle)}


def param_vector(p: RobustParams) -> np.ndarray:
    """The compiled kernels' parameter vector: every field of ``p`` at its ``PRM`` offset
    (booleans as 0/1, vectors over consecutive slots), then the derived coefficients."""
    v = np.zeros(NPARAM)
    for f in dataclass_fields(RobustParams):
        val = getattr(p, f.name)
        off = getattr(PRM, f.name)
        if isinstance(val, tuple):
            v[off:off + len(val)] = val
        else:
            v[off] = float(val)
    for name, val in derived(p).items():
        v[getattr(PRM, name)] = val
    return v


class RobustEKF(Estimator):
    name = "robust"
    title = "Robust error-state EKF (default)"
    Params = RobustParams

    def _on_params(self) -> None:
        self._p = param_vector(self._params)

    def _reset_state(self) -> None:
        self._s = new_state()
        self._P = np.eye(6) * 1e-4

    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        robust_step(self._s, self._P, self._p, t, gyr, acc, mag, flags)

    def _run_rows(self, t, G, A, M, O, qs, flags) -> None:
        robust_run(self._s, self._P, self._p, t, G, A, M, qs, flags)

    @property
    def t(self) -> float:
        return float(self._s[S.t])

    @property
    def initialized(self) -> bool:
        return bool(self._s[S.aligned])

    @property
    def q(self) -> np.ndarray:
        return self._s[S.q:S.q + 4].copy()

    def attitude_cov(self) -> np.ndarray:
        return self._P[0:3, 0:3].copy()

    @property
    def gyr_bias(self) -> np.ndarray:
        return self._s[S.bias:S.bias + 3].copy()

    @property
    def covariance(self) -> np.ndarray:
        return self._P.copy()

    def diagnostics(self):
        """Diagnostics: gravity as the reference, the learned field (None until learned)."""
        from .base import Diagnostics, vec3    # here: this method is the whole of the change
        p, s = self._params, self._s
        ok = bool(s[S.ref_ok])
        ref_n, dip = float(s[S.ref_norm]), float(s[S.ref_dip])
        return Diagnostics(
            g0=(0.0, 0.0, GRAVITY),
            # the expected field in world coordinates (µT): north and the learned dip
            m0=vec3((0.0, ref_n * np.cos(dip), ref_n * np.sin(dip))) if ok else None,
            acc_band=(GRAVITY * (1 - p.acc_band_rel), GRAVITY * (1 + p.acc_band_rel))
            if p.acc_band_rel > 0 else None,
            mag_band=(ref_n * (1 - p.mag_norm_gate_rel), ref_n * (1 + p.mag_norm_gate_rel))
            if p.mag_norm_gate_rel > 0 and ok else None,
            acc_nis_gate=float(p.acc_nis_gate), mag_nis_gate=float(p.mag_nis_gate),
            mag_ref_norm=ref_n if ok else None,
            mag_ref_dip=dip if ok else None,
            acc_lp_world=vec3(s[S.acc_lp:S.acc_lp + 3]),
            gyr_bias=vec3(s[S.bias:S.bias + 3]),
            rest=bool(s[S.rest]),
        )
