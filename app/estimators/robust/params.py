"""The robust filter's parameters and the compiled kernels' parameter vector.

The compiled kernels keep the filter in two flat float arrays, the state ``s`` and the
parameter vector ``p`` (numba's fastest form). Their slots are NAMED, once: ``PRM.gyr_noise``
is the offset of that parameter in ``p`` (here), ``S.q`` the offset of the attitude in ``s``
(:mod:`.state`). As in vqf's pyvqf.py, three kinds of numbers are kept apart: parameters
(the user's, :class:`RobustParams`), coefficients derived from them (``DERIVED`` below,
recomputed by ``RobustEKF._on_params`` on every change) and the state (``STATE``).
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import MISSING, dataclass, fields as dataclass_fields

import numpy as np

from app.params import CommonParams, DEG, gyr_scale_param, param



@dataclass(frozen=True)
class RobustParams(CommonParams):
    gyr_noise: float = param(0.005, unit="rad/√s", lo=1e-6, hi=1.0, log=True, user_unit="deg/√s",
                             user_scale=DEG, doc="gyroscope noise density (attitude random walk)")
    bias_noise: float = param(3e-5, unit="rad/s/√s", lo=0.0, hi=0.1, log=True, user_unit="deg/s/√s",
                              user_scale=DEG, doc="gyroscope bias random walk")
    bias_max: float = param(0.3, unit="rad/s", lo=0.0, hi=10.0, user_unit="deg/s", user_scale=DEG,
                            doc="the largest plausible gyroscope bias (a phone's reach 0.05-0.1 rad/s): "
                                "a bias estimate above it is reset and flagged (the filter is lost), a "
                                "reading above it is no rest (a steady turn on a turntable or a swivel "
                                "chair reads as constant as rest); 0: off")
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
    bias_init: float = param(0.5 / DEG, unit="rad/s", lo=0.0, hi=1.0, log=True, user_unit="deg/s",
                             user_scale=DEG, doc="σ of the gyroscope bias at the start")
    bias_motion_noise: float = param(1.0 / DEG, unit="rad/s·√s", lo=0.0, hi=1.0, user_unit="deg/s·√s",
                                     user_scale=DEG,
                                     doc="noise density of the bias seen in the rate of the tilt corrections "
                                         "(VQF's biasSigmaMotion 0.1 °/s as a density, 1 °/s·√s: during "
                                         "motion the specific force left after the low-pass makes the "
                                         "corrections wander for seconds); 0: no bias learning in motion")
    bias_motion_clip: float = param(2.0 / DEG, unit="rad/s", lo=0.0, hi=1.0, user_unit="deg/s",
                                    user_scale=DEG,
                                    doc="a correction rate is taken to show at most this much bias error "
                                        "(a first correction after a moving start, a shake, is no bias); "
                                        "the estimate itself is not clipped: a phone's 3-6 °/s is learned "
                                        "at rest at once, in motion in steps of this; 0: no clip")
    heading_drift_window: float = param(20.0, unit="s", lo=0.0, hi=600.0,
                                        doc="the gyroscope's drift about the vertical measured from the data: "
                                            "the field's heading less the raw gyroscope's (its bias not removed) "
                                            "is fitted with a line over this window (exponential forgetting); the "
                                            "line's slope is the bias about the vertical, the fit's residual its "
                                            "uncertainty. The heading's time constant (heading_noise / gyr_noise): "
                                            "a field bent for less than that is told from a drift; 0: no bias "
                                            "learning from the heading")
    heading_drift_corr: float = param(4.0, unit="s", lo=0.01, hi=600.0,
                                      doc="correlation time of what the field's heading does besides the drift "
                                          "(a stride's swing, a bend walked through, an arm's turn): the fit's "
                                          "residual counts one independent sample per this long, so the slope's σ "
                                          "grows with it")
    gyr_bias: tuple = param((0.0, 0.0, 0.0), unit="rad/s", lo=-1.0, hi=1.0, tunable=False,
                            doc="initial gyroscope bias (calibration)")
    gyr_scale: tuple = gyr_scale_param()
    tilt_noise: float = param(0.015, unit="rad·√s", lo=1e-5, hi=10.0, log=True, user_unit="deg·√s",
                              user_scale=DEG, doc="noise density of the low-passed gravity direction")
    acc_tau: float = param(3.0, unit="s", lo=0.0, hi=60.0,
                           doc="time constant of the inertial low-pass of the accelerometer")
    tilt_damping: float = param(math.sqrt(0.5), lo=0.0, hi=2.0,
                                doc="damping ratio ζ of the tilt loop (the low-pass and the corrections "
                                    "together, a second-order system): 1/√2 as VQF's Butterworth "
                                    "low-pass, a drift error of 2ζ/ωn; 1 critically damped; 0: off (the "
                                    "low-pass turns with every correction: overdamped, ζ >= 1, it lags "
                                    "more)")
    acc_band_rel: float = param(0.0, lo=0.0, hi=2.0,
                                doc="tilt corrections pause while | |a| - g | > this × g (every sample "
                                    "still enters the low-pass); 0: off", rejects=True)
    acc_flag_angle: float = param(10.0 * math.pi / 180.0, unit="rad", lo=0.0, hi=3.2, user_unit="deg",
                                  user_scale=DEG, doc="a sample this far from the low-passed gravity is "
                                                      "flagged as specific force (ACCEL; it still enters "
                                                      "the low-pass); 0: off")
    acc_flag_rel: float = param(0.1, lo=0.0, hi=5.0,
                                doc="likewise when | |a| - g | > this × g; 0: off")
    acc_delay_periods: float = param(0.5, lo=-5.0, hi=5.0,
                                     doc="the accelerometer's samples lag the attitude by this many of its "
                                         "sample periods (measured from the stream): each sample is turned "
                                         "forward by the gyroscope's rate × the lag before it enters the "
                                         "low-pass. A sample stands for the specific force over its period, "
                                         "stamped at its end, while the attitude at the stamp is propagated "
                                         "with the gyroscope's rate over that same period: half a period "
                                         "behind (a steady turn about a horizontal axis leaves rate × lag of "
                                         "tilt); 0: off")
    heading_noise: float = param(0.1, unit="rad·√s", lo=1e-5, hi=10.0, log=True, user_unit="deg·√s",
                                 user_scale=DEG,
                                 doc="noise density of the magnetometer heading in a steady field (the "
                                     "field's wander measured now adds to it: heading_evidence_tau)")
    heading_evidence_tau: float = param(2.0, unit="s", lo=0.0, hi=600.0,
                                        doc="the field's heading noise measured from the data: the field's "
                                            "heading less the gyroscope's (which the corrections do not move) "
                                            "wanders while the phone moves through an uneven field or turns "
                                            "with a residual offset; its variance v about its mean over this "
                                            "window (a few strides, a turn of the hand: short against the "
                                            "heading's time constant of tens of seconds) adds 2 v × 0.5 s to "
                                            "heading_noise² (a noise correlated over 0.5 s); 0: off",
                                            rejects=True)
    mag_norm_gate_rel: float = param(0.15, lo=0.0, hi=2.0,
                                     doc="field strength may differ from the reference by this fraction; 0: off. "
                                         "It also bounds a new field's candidate while it is watched",
                                     rejects=True)
    mag_dip_gate: float = param(10.0 * math.pi / 180.0, unit="rad", lo=0.0, hi=1.6, user_unit="deg", user_scale=DEG,
                                doc="dip angle may differ from the reference by this much; 0: off. It "
                                    "also bounds a new field's candidate while it is watched, and the "
                                    "return after a refusal (the probation's floor; 0: no probation)",
                                rejects=True)
    mag_ref_tau: float = param(20.0, unit="s", lo=0.1, hi=3600.0,
                               doc="time constant of learning the field reference while undisturbed")
    mag_new_field_time: float = param(20.0, unit="s", lo=0.0, hi=600.0,
                                      doc="a new homogeneous field is accepted after this long while turning (not "
                                          "one an offset found on the phone explains)")
    mag_new_min_rate: float = param(20.0 / DEG, unit="rad/s", lo=0.0, hi=10.0, user_unit="deg/s",
                                    user_scale=DEG, doc="turn rate that counts towards accepting a new field "
                                                        "(and weighs the hard-iron fit's samples, and makes "
                                                        "a field reference firm once turned through)")
    mag_dev_weight: float = param(math.sqrt(0.5), lo=0.0, hi=2.0,
                                  doc="heading σ per relative deviation of the field from its reference "
                                      "(Δ/|m_h|), within the gates too: a disturbance δ of any direction "
                                      "shows a deviation Δ of about √(2/3) |δ| (strength and dip) and turns "
                                      "the horizontal field by about |δ|/√3, so 1/√2 × Δ/|m_h|. The "
                                      "deviation is low-passed over 0.5 s as the field's wander is (a magnet "
                                      "on a turning phone swings it to and fro: that averages out; a bend "
                                      "the phone is carried through stays) and counts as a noise correlated "
                                      "over that long (its density adds to heading_noise²: an update rate "
                                      "does not change it); 0: off", rejects=True)
    mag_first_field_time: float = param(5.0, unit="s", lo=0.0, hi=600.0,
                                        doc="the first field reference is a field stable this long (until "
                                            "then every sample corrects the heading: nothing to judge it by); "
                                            "until the phone has turned this long in it, it is tentative: a "
                                            "new field the phone has turned in this long, homogeneous by the "
                                            "offset fit, replaces it (a phone picked up from a laptop)")
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
                                     "way until it is learned); 0: off", rejects=True)
    mag_turn_rel: float = param(0.5, lo=0.0, hi=10.0,
                                doc="change rate of the world-frame field (rad/s) allowed per rad/s of turn "
                                    "rate: a saturated gyroscope (running) reads at least 2/3 of the turn; "
                                    "scale error, magnetometer lag and residual hard iron are smaller")
    mag_turn_tau: float = param(0.2, unit="s", lo=0.01, hi=10.0,
                                doc="the turn test's time scale: the world-frame field low-passed over "
                                    "mag_norm_dip_tau is low-passed again over this, a change at rate r "
                                    "leaves it behind by r × this; the turn rate is low-passed over it too")
    mag_delay: float = param(0.005, unit="s", lo=-0.1, hi=0.1,
                             doc="the magnetometer's samples lag the gyroscope's by this: each field "
                                 "sample is turned forward by the gyroscope's rate × this before use "
                                 "(above 300 °/s a 5 ms lag is 1.5° of heading). A sample stands for "
                                 "the field over its conversion, stamped at its end: half the period "
                                 "of a 100 Hz magnetometer (a phone's usual rate) is 5 ms; a research "
                                 "IMU's was measured at 1-2 samples of 286 Hz (3.5-7 ms); 0: off")
    hard_iron_window: float = param(10.0, unit="s", lo=0.0, hi=600.0,
                                    doc="a magnet fixed to the phone (a case, a mount) is a constant offset "
                                        "in the sensor frame: it is fitted online, the field's samples on a "
                                        "sphere about it, over this much turning (a sample counts by its "
                                        "duration × min(1, turn rate / mag_new_min_rate): a still phone "
                                        "neither teaches nor forgets); 10 s of turning sees the sphere from "
                                        "every side; 0: off")
    hard_iron_max_std: float = param(1.0, unit="µT", lo=0.0, hi=100.0,
                                     doc="the fitted offset is applied only when its σ (largest axis) is "
                                         "below this: a magnetometer's noise (0.3-1 µT), so the heading "
                                         "error it leaves is below σ/|m_h| (2-3° on a 20-25 µT horizontal "
                                         "field)")
    hard_iron_tol: float = param(0.05, lo=0.0, hi=1.0,
                                 doc="the offset is applied only when the fitted sphere's radius matches "
                                     "the learned earth field's strength to this fraction and the fit's "
                                     "rms residual is below this fraction of it (the corrected field is "
                                     "the earth's, to a sensor's scale error and a room's variation of "
                                     "a few %); and the field's reference learns only from a field "
                                     "whose strength is within this fraction of it (rms over "
                                     "mag_cand_tau): a bend the phone is carried through, or a magnet "
                                     "on it not yet found, does not teach it")
    hard_iron_ratio: float = param(3.0, lo=1.0, hi=100.0,
                                   doc="the offset is applied only when the raw field's rms deviation from "
                                       "the learned strength is this many times the corrected field's (over "
                                       "mag_cand_tau): an offset that explains the strength's swing, not one "
                                       "a window with little turning or a room's unevenness leaves (it moves "
                                       "the strength about as much as it fixes); 1: whenever the corrected "
                                       "field is closer")
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
    mag_lost_angle: float = param(30.0 * math.pi / 180.0, unit="rad", lo=0.0, hi=3.2, user_unit="deg",
                                  user_scale=DEG, doc="an undisturbed field this far from the estimated "
                                                      "heading for mag_lost_time means the estimate is lost")
    mag_lost_time: float = param(5.0, unit="s", lo=0.0, hi=600.0,
                                 doc="after this long with an undisturbed field far from the heading, the "
                                     "estimate is judged lost: its heading σ grows to the error and the "
                                     "field's heading is taken (flag RECOVER); 0: never")
    init_tilt_std: float = param(10.0 * math.pi / 180.0, unit="rad", lo=1e-4, hi=3.2, user_unit="deg",
                                 user_scale=DEG, doc="σ of the tilt after the initial alignment")
    init_heading_std: float = param(20.0 * math.pi / 180.0, unit="rad", lo=1e-4, hi=3.2, user_unit="deg",
                                    user_scale=DEG, doc="σ of the heading after an alignment with the field")
    noacc_tilt_std: float = param(30.0 * math.pi / 180.0, unit="rad", lo=1e-4, hi=3.2, user_unit="deg",
                                  user_scale=DEG, doc="σ of the tilt of a start without accelerometer (level)")


# Where each default comes from (issue 19: a default from physics, a datasheet or a published value,
# not from the shared trials' optimum). The first word is the kind: "VQF" (its published default,
# Laidig & Seel 2023, vqf's pyvqf.py), "physics" or "datasheet" (the reason follows), "design" (a
# choice the reason gives, no figure behind it), "shared trials" (set with the shared BROAD and
# phone trials in view: docs/accuracy.md cross-validates it and names its sensitivity). Shown as
# a column of `orientlab params` and docs/parameters.md.
# Parameters removed from robust, and why: a preset that still sets one loads without it (a
# warning says so); the API refuses it with this reason (app.config.renamed_message)
RobustParams.removed = {
    "bias_heading_noise": "the bias about the vertical is learned from the heading's drift now: "
                          "heading_drift_window, heading_drift_corr",
    "acc_nis_gate": "it never acted: the tilt update has no NIS gate",
    "mag_nis_gate": "it never acted: the field's own tests judge it",
    "mag_max_reject": "a field that stays is taken by the new-field acceptance (mag_new_field_time)",
    "mag_reject_factor": "a field that stays is taken by the new-field acceptance (mag_new_field_time)",
    "mag_cand_norm_rel": "it acted only below the strength gate (mag_norm_gate_rel)",
    "mag_cand_dip": "it acted only below the dip gate (mag_dip_gate)",
}

RobustParams.default_from = {
    "use_gyr": "design: every sensor on", "use_acc": "design: every sensor on",
    "use_mag": "design: every sensor on",
    "max_gap": "design: 1 s of a 0.1 rad/s bias is 6°, more than a gap should bridge",
    "gyr_hold": "design: a few samples of a phone sending one sensor per row",
    "gyr_noise": "shared trials (set with them in view; its source measured on them since): the "
                 "gyroscope's attitude random walk against BROAD's optical truth, "
                 "0.0036-0.0056 rad/√s over 2-20 s in a steady field (benchmarks/noise_densities.py): "
                 "a model error (scale, misalignment, timing), 40× a phone gyroscope's white noise",
    "bias_noise": "physics: a MEMS bias drifting by 0.02 °/s over VQF's biasForgettingTime (100 s)",
    "bias_max": "physics: 3× the largest phone bias (0.1 rad/s)",
    "gyr_scale_noise": "physics: a 1 % scale error over acc_tau (benchmarks/gyro_scale.py: 0.2-2.3 %)",
    "refused_turn_noise": "shared trials (set with them in view): a 1 % scale error per second of turn",
    "bias_init": "VQF: biasSigmaInit 0.5 °/s, the size of an OS-calibrated phone gyroscope's bias "
                 "(0.006-0.009 rad/s against the truth); a raw gyroscope's 0.05-0.1 rad/s starts "
                 "5.7-11.5 σ off and is learned at rest and in motion",
    "bias_motion_noise": "VQF: biasSigmaMotion 0.1 °/s as a noise density (VQF's per-sample "
                         "W = σ⁴/V + σ², with biasForgettingTime 100 s: 1 °/s·√s); with robust's own "
                         "bias_noise, 5.8× below VQF's V, the bias settles at 0.04 °/s in 10 min, not "
                         "VQF's 0.1 °/s in 100 s",
    "bias_motion_clip": "VQF: biasClip 2 °/s",
    "heading_drift_window": "physics: the heading's time constant, heading_noise / gyr_noise",
    "heading_drift_corr": "physics: a few strides or turns of the arm (0.5-1 s each)",
    "gyr_bias": "design: none known",
    "gyr_scale": "design: none known (a phone's is off by 0.2-3 %, benchmarks/gyro_scale.py; orientlab "
                 "gyro-scale measures it from a recording)",
    "tilt_noise": "shared trials: the accelerometer's direction against BROAD's optical truth is "
                  "0.01 (median) to 0.05 (RMS) rad·√s (benchmarks/noise_densities.py), not one value; "
                  "0.015 makes the correction's time constant at rest (tilt_noise / gyr_noise) the "
                  "low-pass's, acc_tau (VQF's tauAcc 3 s)",
    "acc_tau": "VQF: tauAcc 3 s, the time constant of its inertial low-pass of the accelerometer",
    "tilt_damping": "VQF: its second-order Butterworth low-pass, ζ = 1/√2",
    "acc_band_rel": "design: off (VQF has no band)",
    "acc_flag_angle": "design: a flag only, no estimate changes",
    "acc_flag_rel": "design: a flag only, no estimate changes",
    "acc_delay_periods": "physics: a sample stands for its period and is stamped at its end: half a "
                         "period behind the attitude at its stamp",
    "heading_noise": "shared trials (set with them in view; its source measured on them since): the "
                     "field's heading against BROAD's optical truth in a steady field, "
                     "0.09-0.10 rad·√s at the heading's time scale, 10-20 s "
                     "(benchmarks/noise_densities.py); a noisier field's wander adds to it",
    "heading_evidence_tau": "physics: a few strides, short against the heading's tens of seconds",
    "mag_norm_gate_rel": "shared trials (set with them in view; its source measured on them since): an "
                         "undisturbed phone's field strength, low-passed as the gate sees it, "
                         "stays within 14 % of its median 99 % of the time (median of the 24 undisturbed "
                         "phone trials: an uncalibrated magnetometer's residual hard and soft iron; a "
                         "calibrated IMU's, 6 %, is under VQF's magNormTh 10 %; benchmarks/noise_densities.py)",
    "mag_dip_gate": "VQF: magDipTh 10°",
    "mag_ref_tau": "VQF: magRefTau 20 s",
    "mag_new_field_time": "VQF: magNewTime 20 s",
    "mag_new_min_rate": "VQF: magNewMinGyr 20 °/s",
    "mag_dev_weight": "physics: a disturbance of any direction turns the horizontal field by "
                      "about 1/√2 of the deviation it shows in strength and dip, Δ/|m_h|",
    "mag_first_field_time": "VQF: magNewFirstTime 5 s",
    "mag_min_undisturbed": "VQF: magMinUndisturbedTime 0.5 s",
    "mag_norm_dip_tau": "VQF: magCurrentTau 0.05 s",
    "mag_turn_gate": "physics: 2.5× a phone's largest gyroscope bias (0.1 rad/s)",
    "mag_turn_rel": "physics: a saturated gyroscope reads at least 2/3 of a turn",
    "mag_turn_tau": "design: shorter than a magnet brought in (0.5 s)",
    "mag_delay": "physics: half the period of a 100 Hz magnetometer (stamped at the end of its "
                 "conversion)",
    "hard_iron_window": "physics: 10 s of turning sees the sphere from every side (the window "
                        "issue 19 measured)",
    "hard_iron_max_std": "datasheet: a magnetometer's noise, 0.3-1 µT",
    "hard_iron_tol": "physics: a magnetometer's scale error and a room's variation, a few %",
    "hard_iron_ratio": "design: the offset explains most of the strength's deviation (the corrected "
                       "field at most a third as far off, the 3 of a 3σ test)",
    "rest_gyr_th": "VQF: restThGyr 2 °/s",
    "rest_acc_th": "VQF: restThAcc 0.5 m/s²",
    "rest_time": "VQF: restMinT 1.5 s",
    "rest_noise": "VQF: biasSigmaRest 0.03 °/s, as a noise density; with robust's own bias_noise the "
                  "bias at rest settles at 0.013 °/s in about 50 s, not VQF's 0.03 °/s in 9 s",
    "rw_noise": "design: a hand turns a phone by about 0.5 rad in a second",
    "update_rate_hz": "design: the cost of an update; every sample still enters the low-passes",
    "rest_lp_tau": "VQF: restFilterTau 0.5 s",
    "mag_cand_tau": "design: a few seconds, longer than the field's low-pass (0.05 s)",
    "mag_lost_angle": "design: three times mag_dip_gate",
    "mag_lost_time": "design: longer than a magnet passing by",
    "init_tilt_std": "physics: the tilt of a phone aligned while it moves",
    "init_heading_std": "physics: a field bent indoors by tens of degrees",
    "noacc_tilt_std": "design: a level start, tilted up to 30°",
}


# ----------------------------------------------------------------- layouts

def layout(name: str, fields) -> tuple:
    """A namedtuple of offsets for ``fields`` ((name, size), ...) and the total size.
    A size may be given as the names of the slot's components instead (a string of
    one-letter names or a tuple of names): ``("q", "wxyz")`` names the slot ``q`` (its
    first offset) and each component, ``q_w``, ``q_x``, ``q_y``, ``q_z``, so code reads
    ``s[S.q_x]``, never ``s[S.q + 1]``. numba folds a global namedtuple's fields into
    constants: no cost per access."""
    offsets, n = {}, 0

    def name_slot(slot: str, offset: int) -> None:
        if slot in offsets:
            raise ValueError(f"{name}: {slot!r} named twice")
        offsets[slot] = offset

    for fname, size in fields:
        name_slot(fname, n)
        if not isinstance(size, int):
            for i, c in enumerate(size):
                name_slot(f"{fname}_{c}", n + i)
            size = len(size)
        n += size
    return namedtuple(name, offsets)(**offsets), n


# coefficients derived from the parameters (appended to the parameter vector)
DERIVED = (
    ("gyr_gain", "xyz", "1 / (1 + gyr_scale) per axis: the rate, its bias removed, is multiplied by it"),
    ("upd_dt", 1, "s between two measurement updates of a sensor (1/update_rate_hz; 0: every sample)"),
    ("acc_flag_cos", 1, "cos(acc_flag_angle): the flag test compares cosines"),
)


def _param_fields():
    """(name, size) of every RobustParams field, in order, then the derived coefficients."""
    out = []
    for f in dataclass_fields(RobustParams):
        default = f.default_factory() if f.default is MISSING else f.default
        out.append((f.name, len(default) if isinstance(default, tuple) else 1))
    return tuple(out) + tuple((n, k) for n, k, _ in DERIVED)


PRM, NPARAM = layout("ParamLayout", _param_fields())


def derived(p: RobustParams) -> dict[str, float | tuple[float, ...]]:
    """The coefficients derived from the parameters (see ``DERIVED``)."""
    return {"gyr_gain": tuple(1.0 / (1.0 + s) for s in p.gyr_scale),
            "upd_dt": 1.0 / p.update_rate_hz if p.update_rate_hz > 0 else 0.0,
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
        off = getattr(PRM, name)
        if isinstance(val, tuple):
            v[off:off + len(val)] = val
        else:
            v[off] = val
    return v
