"""The heading: the magnetometer update, the field checks, and the recovery when lost.

- **Heading only from the magnetometer.** The field is rotated into the world frame
  with the current tilt and only its horizontal direction is used (scalar ``h = δθz``);
  the gain is masked so this update can never tilt the attitude.
- **Magnetic disturbance detection** (VQF's logic, :func:`_field_check`). The low-passed
  field strength and dip angle are compared with a reference learned while undisturbed
  (``mag_norm_gate_rel``, ``mag_dip_gate``); the first reference is a field stable for
  ``mag_first_field_time`` (never the first samples of a phone that starts moving), and
  tentative until the phone has turned in it as long (a still phone may lie on a laptop); a
  new homogeneous field (stable strength and dip while the phone turns for
  ``mag_new_field_time``, or for ``mag_first_field_time`` against a tentative reference
  when the offset fit sees it as a centred sphere) becomes the reference. Within the gates, a deviation from the
  reference adds heading noise (``mag_dev_weight``).
- **The field's heading noise measured from the data** (:func:`_heading_evidence`,
  ``heading_evidence_tau``): the field's wander against the gyroscope slows the correction.
- **Field turn test** (:func:`_turn_check`). A real field is fixed in the world: seen
  through the estimate (whose turns are the gyroscope's) it stays put while the phone
  turns. A magnet brought in over half a second turns the horizontal field by tens of
  degrees before its strength or dip leave their gates, and the heading would follow; so
  a world-frame field changing faster than ``mag_turn_gate`` beyond ``mag_turn_rel`` ×
  the turn rate is a disturbance too (flag TURN, value: the unexplained rate), ended like
  the others after ``mag_min_undisturbed`` of a field within every gate.
- **A magnet on the phone** (:mod:`.hardiron`): a sensor-fixed offset found by the online
  sphere fit and judged the earth field's is removed from every sample first (flag OFFSET).
- **The field's delay** (``mag_delay``): each sample is turned forward by the gyroscope's
  rate × the delay (0: off).
- **A return after a refusal needs evidence** (``PROBATION_TURN``, ``PROBATION_GATE``): the
  heading σ grown while the field was refused acts only once the field's heading (less the
  gyroscope's, low-passed over ``HV_SMOOTH``) has stayed consistent (within
  ``mag_dip_gate``) over a quarter turn; until then the steady gain, and a field farther from
  the gyroscope's heading than 3σ and ``mag_dip_gate`` is not used (flag NIS): a magnet's
  chance window within the gates.
- **The gyroscope's drift about the vertical from the data** (:func:`_drift_fit`,
  ``heading_drift_window``): a line fitted to the field's heading less the raw gyroscope's;
  its slope is the bias about the vertical (learned by :func:`.bias.heading_drift_update`).
- **Never lost.** An undisturbed field farther than ``mag_lost_angle`` from the heading
  for ``mag_lost_time`` means the estimate is wrong: the heading σ grows to the error,
  the field's heading is taken, the bias learned meanwhile is dropped (flag RECOVER);
  a bias estimate above ``bias_max`` is reset (flag BIAS_RESET, :mod:`.kernel`).
"""

from __future__ import annotations

import numpy as np

from app.estimators.base import (F_MAG, F_MAG_NIS, F_MAG_VAL, R_DIP, R_NEW_FIELD, R_NIS, R_NORM,
                                R_OFFSET, R_RECOVER, R_TURN, R_USED)
from app.estimators.kalman import correct
from app.estimators.robust.bias import BIAS_UPD_S, heading_drift_update
from app.estimators.robust.hardiron import HI_APPLIED, HI_NONE, HI_TRACKING, centred_sphere, hard_iron
from app.estimators.robust.params import PRM
from app.estimators.robust.state import (DT_MAX, KF_WORK, S, attitude_matrix, inject, lp_coef, rotate3,
                                         turned_forward, update_is_due)
from app.jitcache import compiled
from app.quaternion import norm3, wrap_angle

_MASK_HEADING = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])

# A candidate new field stays one while its strength and dip stay within the gates; with a gate
# off, within these (a magnetometer's noise and a room's variation: 5 %, 3°). They were
# parameters (mag_cand_norm_rel, mag_cand_dip) that acted only below the gates: never by default
CAND_OFF_NORM_REL = 0.05
CAND_OFF_DIP = 0.05

# The heading evidence (heading_evidence_tau) first low-passes the field's heading over this (s):
# a magnetometer's white noise and a stride's swing average out; what is left is correlated over
# about this long, so its variance v stands for the noise density 2 v HV_SMOOTH
HV_SMOOTH = 0.5

# The turn (rad) over which a field's heading must stay consistent after a refusal before the
# heading σ grown during the refusal is let act: a quarter turn, over which a magnet's bias on
# the heading (near the phone or on it) changes with the attitude by most of its range
PROBATION_TURN = 0.5 * np.pi

# During that probation a field heading (low-passed over HV_SMOOTH) farther from the gyroscope's
# than this many σ of their difference, and than mag_dip_gate, is not used (3σ: a consistent
# field is refused by chance in 0.3 % of the updates)
PROBATION_GATE = 3.0


@compiled
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


@compiled
def heading_innovation(m_world):
    """Angle (rad) of the horizontal field east of north: zero when the heading is right."""
    out = np.empty(1)
    out[0] = np.arctan2(m_world[0], m_world[1])
    return out


@compiled
def _field_check(s, p, n, dip, dt, rate, turn, f):
    """Judge the field (strength ``n``, dip) against the learned reference, as VQF does:
    a disturbance is a strength or dip off the reference; it ends after the field has been
    within the gates for ``mag_min_undisturbed``; a new homogeneous field (stable strength
    and dip while the phone turns for ``mag_new_field_time``) becomes the reference, unless
    an offset fixed to the phone explains it (below); the
    first reference is the first field stable for ``mag_first_field_time`` (a phone that
    starts moving, or next to a desk, must not fix it from its first samples).
    A field that changes faster than the phone turns (``turn`` > 0, the unexplained change
    rate, see :func:`_turn_check`) is a disturbance too (TURN), judged after strength and dip.
    Returns True when the sample may correct the heading (no reference yet, or undisturbed)."""
    # low-pass of strength and dip: one sample's noise is no disturbance
    if s[S.mag_nd_ok] == 0.0:
        s[S.mag_nd_norm] = n
        s[S.mag_nd_dip] = dip
        s[S.mag_nd_ok] = 1.0
        s[S.cand_norm] = n
        s[S.cand_dip] = dip
        s[S.cand_time] = 0.0
        s[S.cand_turned] = 0.0
    else:
        k = lp_coef(dt, p[PRM.mag_norm_dip_tau])
        s[S.mag_nd_norm] += k * (n - s[S.mag_nd_norm])
        s[S.mag_nd_dip] += k * (dip - s[S.mag_nd_dip])
    nf, df = s[S.mag_nd_norm], s[S.mag_nd_dip]
    # candidate for a new homogeneous field: stable strength and dip (while turning)
    cn_dev = abs(nf - s[S.cand_norm]) / max(s[S.cand_norm], 1e-6)
    cd_dev = abs(df - s[S.cand_dip])
    if (cn_dev <= (p[PRM.mag_norm_gate_rel] if p[PRM.mag_norm_gate_rel] > 0.0 else CAND_OFF_NORM_REL)
            and cd_dev <= (p[PRM.mag_dip_gate] if p[PRM.mag_dip_gate] > 0.0 else CAND_OFF_DIP)):
        if rate >= p[PRM.mag_new_min_rate]:
            s[S.cand_time] += dt
            s[S.cand_turned] += dt
        elif s[S.ref_ok] == 0.0:
            s[S.cand_time] += dt
        kc = lp_coef(dt, p[PRM.mag_cand_tau]) if dt > 0 else 0.0
        s[S.cand_norm] += kc * (nf - s[S.cand_norm])
        s[S.cand_dip] += kc * (df - s[S.cand_dip])
    else:
        s[S.cand_norm] = nf
        s[S.cand_dip] = df
        s[S.cand_time] = 0.0
        s[S.cand_turned] = 0.0
    if s[S.ref_ok] == 0.0:
        if s[S.cand_time] >= p[PRM.mag_first_field_time]:
            s[S.ref_norm] = s[S.cand_norm]
            s[S.ref_dip] = s[S.cand_dip]
            s[S.ref_turned] = s[S.cand_turned]
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
            # a field with a sensor-fixed offset found in it (not yet removed) is not the
            # earth's: it does not teach the reference
            # nor does a field whose strength has been off the reference by more than a
            # room's variation (hard_iron_tol; hardiron.strength_deviations): a bend the phone is
            # carried through, a magnet on it not yet found. The reference is the earth's; a
            # field that stays is taken by the new-field acceptance
            dev = s[S.hi_dev_cor] if s[S.hi_status] == HI_APPLIED else s[S.hi_dev_raw]
            off = dev > (p[PRM.hard_iron_tol] * s[S.ref_norm]) ** 2
            kr = (lp_coef(dt, p[PRM.mag_ref_tau])
                  if dt > 0 and s[S.hi_status] != HI_TRACKING and not off else 0.0)
            if not off and rate >= p[PRM.mag_new_min_rate]:
                s[S.ref_turned] += dt          # turned in the reference's own field
            s[S.ref_norm] += kr * (nf - s[S.ref_norm])
            s[S.ref_dip] += kr * (df - s[S.ref_dip])
    else:
        s[S.undisturbed_time] = 0.0
        s[S.disturbed] = 1.0
        s[S.dist_reason] = reason
        s[S.dist_val] = turn
    # A field that an offset fixed to the phone explains is no new place: the fit has found an
    # offset (3σ or more) whose sphere has the reference's radius, so the field less the offset
    # is the earth's field already known. A magnet of 8-9 µT swings the strength by less than
    # the gate most of the time, so the candidate stays "stable" and, without this, it became
    # the reference before the fit had its evidence; the offset then no longer explained the
    # strength and was dropped (hard_iron_ratio). A new place gives no offset (the sphere of a
    # homogeneous field is centred) or a radius of its own strength.
    explained = (s[S.hi_status] != HI_NONE
                 and abs(s[S.hi_r] - s[S.ref_norm]) <= p[PRM.hard_iron_tol] * s[S.ref_norm])
    # A reference the phone has not yet turned in for mag_first_field_time is tentative: seen
    # from one attitude, a desk's or a laptop's field is as stable as the earth's (a phone
    # that starts lying on one). A new field the phone has turned in for as long takes over
    # from it (VQF's magNewFirstTime, which needs the turn for the first reference too) once
    # the offset fit has seen it from every side as a homogeneous field: a sphere of the
    # candidate's strength centred on zero (half a window of turning, σ at the sensor's
    # noise, no offset beyond 3σ). A magnet put on a phone that lay still shows an offset,
    # and waits for mag_new_field_time (and the offset's verdict) as before.
    new_time = (p[PRM.mag_first_field_time]
                if s[S.ref_turned] < p[PRM.mag_first_field_time] and centred_sphere(s, p, s[S.cand_norm])
                else p[PRM.mag_new_field_time])
    if s[S.disturbed] != 0.0 and s[S.cand_time] >= new_time and not explained:
        # a new homogeneous field: the phone moved to another place (or a magnet stays on it)
        s[S.ref_norm] = s[S.cand_norm]
        s[S.ref_dip] = s[S.cand_dip]
        s[S.ref_turned] = s[S.cand_turned]
        s[S.disturbed] = 0.0
        s[S.undisturbed_time] = p[PRM.mag_min_undisturbed]
        f[F_MAG] = R_NEW_FIELD
        f[F_MAG_VAL] = s[S.ref_norm]
        return True
    if s[S.disturbed] != 0.0:
        f[F_MAG] = s[S.dist_reason]
        r = s[S.dist_reason]
        f[F_MAG_VAL] = nf if r == R_NORM else (s[S.dist_val] if r == R_TURN else d_dev)
        return False
    return True


@compiled
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
            s[S.mt_lp_slow + i] = mw[i]
        s[S.mt_rate] = rate
        s[S.mt_ok] = 1.0
        return 0.0
    tau = p[PRM.mag_turn_tau]
    kf = lp_coef(dt, p[PRM.mag_norm_dip_tau])
    k = lp_coef(dt, tau)
    fx, fy, fz = S.mt_lp_x, S.mt_lp_y, S.mt_lp_z                 # the field, low-passed
    gx, gy, gz = S.mt_lp_slow_x, S.mt_lp_slow_y, S.mt_lp_slow_z  # and low-passed again
    s[fx] += kf * (mw[0] - s[fx])
    s[fy] += kf * (mw[1] - s[fy])
    s[fz] += kf * (mw[2] - s[fz])
    d0, d1, d2 = s[fx] - s[gx], s[fy] - s[gy], s[fz] - s[gz]
    s[gx] += k * d0
    s[gy] += k * d1
    s[gz] += k * d2
    s[S.mt_rate] += k * (rate - s[S.mt_rate])
    # |d| / (|lp| τ) - rel·rate > gate, squared (the square root only for a flag)
    dd = d0 * d0 + d1 * d1 + d2 * d2
    l2 = s[gx] * s[gx] + s[gy] * s[gy] + s[gz] * s[gz]
    allowed = tau * (p[PRM.mag_turn_gate] + p[PRM.mag_turn_rel] * s[S.mt_rate])
    if dd <= allowed * allowed * l2 or l2 <= 0.0:
        return 0.0
    return np.sqrt(dd / l2) / tau - p[PRM.mag_turn_rel] * s[S.mt_rate]


@compiled
def _field_heading_lp(s, z, elapsed):
    """``z``, the innovation plus the corrections applied so far, is the field's heading less
    the gyroscope's alone: the filter's own corrections do not move it, the gyroscope drifts it
    slowly (its bias, at most a few 0.01 rad/s), the field moves it as fast as the phone meets
    its unevenness (indoors, near steel) or turns a residual offset about. Low-passed here over
    ``HV_SMOOTH`` (white noise out) into ``hv_fast``, the one copy the heading evidence and the
    return's probation read. Returns True on its first sample (it started afresh)."""
    if s[S.hv_ok] == 0.0:
        s[S.hv_fast] = z
        s[S.hv_mean] = z
        s[S.hv_var] = 0.0
        s[S.hv_ok] = 1.0
        return True
    s[S.hv_fast] += lp_coef(elapsed, HV_SMOOTH) * wrap_angle(z - s[S.hv_fast])   # headings wrap
    return False


@compiled
def _heading_evidence(s, p, elapsed):
    """The field's heading noise now, from the data (a noise density, rad²·s): the variance
    ``v`` of the low-passed field heading (:func:`_field_heading_lp`) about its mean over
    ``heading_evidence_tau`` is the field's wander; as noise correlated over ``HV_SMOOTH`` its
    density is ``2 v HV_SMOOTH``."""
    k = lp_coef(elapsed, p[PRM.heading_evidence_tau])
    d = s[S.hv_fast] - s[S.hv_mean]
    s[S.hv_mean] += k * d
    s[S.hv_var] += k * (d * d - s[S.hv_var])
    return evidence_density(s[S.hv_var])


@compiled
def evidence_density(v):
    """The heading noise density (rad²·s) a wander of variance ``v`` (rad²), correlated over
    ``HV_SMOOTH``, stands for: ``2 v HV_SMOOTH`` (the filter's term and the diagnostics')."""
    return 2.0 * v * HV_SMOOTH


@compiled
def _deviation_lp(s, elapsed):
    """The field's deviation from its reference now (strength, and |m|·dip, relative to the
    horizontal field), signed and low-passed over ``HV_SMOOTH`` as the field's heading is for
    the evidence: a bend of the field the phone is carried through lasts seconds and stays;
    a magnet on a turning phone swings the deviation to and fro with each turn, and what
    swings faster than the low-pass averages out in the heading too."""
    if s[S.ref_ok] == 0.0:
        s[S.dev_n] = 0.0
        s[S.dev_d] = 0.0
        return
    nh = max(s[S.ref_norm] * np.cos(s[S.ref_dip]), 1e-3)
    dn = (s[S.mag_nd_norm] - s[S.ref_norm]) / nh
    dd = s[S.mag_nd_norm] * (s[S.mag_nd_dip] - s[S.ref_dip]) / nh
    if s[S.hv_ok] == 0.0:           # started afresh (a return, a lost estimate): no history
        s[S.dev_n] = dn
        s[S.dev_d] = dd
        return
    k = lp_coef(elapsed, HV_SMOOTH)
    s[S.dev_n] += k * (dn - s[S.dev_n])
    s[S.dev_d] += k * (dd - s[S.dev_d])


@compiled
def deviation_density(s, p):
    """The heading noise density (rad²·s) of a field off its reference, within the gates
    too. A deviation Δ (strength change, or |m|·Δdip) shows a disturbance δ of any
    direction by about √(2/3)|δ|, which turns the horizontal field by about |δ|/√3: a
    heading error of Δ/(√2 |m_h|) (``mag_dev_weight``). Low-passed over ``HV_SMOOTH``
    (:func:`_deviation_lp`) it is an error correlated over that long, as the measured
    wander, so a density, the same at any update rate (taken per update, as it once was,
    it was 50× too small at 50 Hz and all but inert)."""
    if s[S.ref_ok] == 0.0 or p[PRM.mag_dev_weight] <= 0.0:
        return 0.0
    return evidence_density(p[PRM.mag_dev_weight] ** 2 * (s[S.dev_n] ** 2 + s[S.dev_d] ** 2))


# the heading drift fit's time origin moves on after this long (s): its sums of t² keep their digits
DRIFT_T_SHIFT = 600.0


@compiled
def _drift_fit(s, p, t, z_field, elapsed):
    """The gyroscope's drift about the vertical, from the data. The field's heading less the
    gyroscope's (``z_field``, :func:`_field_heading_lp`) plus the bias removed about the
    vertical (integrated in the time update) is the field's heading less the *raw* gyroscope's: a real field is fixed in
    the world, so its slope is minus the bias along the vertical (whatever the estimate is),
    and what else it does (a stride's swing, a field bent where the phone walks) is noise. A
    line is fitted to it over ``heading_drift_window`` (exponential forgetting, the sums of 1,
    t, t², z, t z, z² low-passed); once it spans two ``heading_drift_corr`` its slope, as a
    measurement of the bias along the vertical the window saw (``dr_H``), and the slope's
    variance (the residual's, one independent sample per ``heading_drift_corr`` of the span,
    up to twice the window) are summed for the next bias update: a short span's slope is
    uncertain by its own arithmetic. Samples the heading update does not use never reach it."""
    T = p[PRM.heading_drift_window]
    h0, h1, h2 = attitude_matrix(s)[6:]        # the world's vertical in the sensor frame
    z = z_field - s[S.dr_bint]
    if s[S.dr_ok] == 0.0:
        s[S.dr_z] = z
        s[S.dr_ok] = 1.0
        s[S.dr_t0] = t
        s[S.dr_start] = t
        s[S.dr_sums:S.dr_sums + 6] = 0.0
        s[S.dr_y] = 0.0
        s[S.dr_var] = 0.0
        s[S.dr_n] = 0.0
        s[S.dr_H_x], s[S.dr_H_y], s[S.dr_H_z] = h0, h1, h2
        return
    s[S.dr_z] += wrap_angle(z - s[S.dr_z])     # headings wrap; the fit needs the unwrapped one
    zu = s[S.dr_z]
    tt = t - s[S.dr_t0]
    if tt > DRIFT_T_SHIFT:                     # move the origin on: t → t - d in every sum
        d = tt
        w, st = s[S.dr_sums_w], s[S.dr_sums_t]
        s[S.dr_sums_tt] += -2.0 * d * st + d * d * w
        s[S.dr_sums_t] = st - d * w
        s[S.dr_sums_tz] -= d * s[S.dr_sums_z]
        s[S.dr_t0] = t
        tt = 0.0
    k = lp_coef(elapsed, T)
    s[S.dr_sums_w] += k * (1.0 - s[S.dr_sums_w])
    s[S.dr_sums_t] += k * (tt - s[S.dr_sums_t])
    s[S.dr_sums_tt] += k * (tt * tt - s[S.dr_sums_tt])
    s[S.dr_sums_z] += k * (zu - s[S.dr_sums_z])
    s[S.dr_sums_tz] += k * (tt * zu - s[S.dr_sums_tz])
    s[S.dr_sums_zz] += k * (zu * zu - s[S.dr_sums_zz])
    s[S.dr_H_x] += k * (h0 - s[S.dr_H_x])
    s[S.dr_H_y] += k * (h1 - s[S.dr_H_y])
    s[S.dr_H_z] += k * (h2 - s[S.dr_H_z])
    span = t - s[S.dr_start]
    if span < 2.0 * p[PRM.heading_drift_corr]:
        return                                  # not yet two independent samples
    w = s[S.dr_sums_w]
    mt, mz = s[S.dr_sums_t] / w, s[S.dr_sums_z] / w
    vt = s[S.dr_sums_tt] / w - mt * mt
    if vt <= 1e-9:
        return
    cov = s[S.dr_sums_tz] / w - mt * mz
    slope = cov / vt
    vr = max(s[S.dr_sums_zz] / w - mz * mz - slope * cov, 1e-12)
    n_ind = max(min(span, 2.0 * T) / p[PRM.heading_drift_corr], 1.0)
    s[S.dr_y] += -slope
    s[S.dr_var] += vr / (vt * n_ind)
    s[S.dr_n] += 1.0


@compiled
def _far(s, elapsed):
    """The heading disagrees with an undisturbed field: count the time; at its start,
    keep the bias estimate (what follows may be learned from a wrong heading)."""
    if s[S.far_time] == 0.0:
        s[S.bias_good:S.bias_good + 3] = s[S.bias:S.bias + 3]
    s[S.far_time] += elapsed


@compiled
def _is_far(p, innov):
    """The field's heading is farther from the estimate than ``mag_lost_angle``."""
    return p[PRM.mag_lost_angle] > 0.0 and abs(innov) > p[PRM.mag_lost_angle]


@compiled
def _not_used(s, p, f, nis, ok, innov, elapsed):
    """A field the checks passed that the heading update does not use (its innovation
    failed a test): flag NIS with its value; a field judged undisturbed (``ok``) that is
    far from the heading still counts towards "never lost"."""
    if f[F_MAG] == R_USED or f[F_MAG] == R_OFFSET:
        f[F_MAG] = R_NIS
        f[F_MAG_VAL] = nis
    f[F_MAG_NIS] = nis
    if ok and _is_far(p, innov):
        _far(s, elapsed)


@compiled
def mag_update(s, P, p, t, mag, rate, has_rate, f):
    """A magnetometer sample: the turn test and the field check; a field judged usable is
    averaged in the world frame and corrects the heading at most at ``update_rate_hz``
    (and, when an undisturbed field has disagreed for long, the estimate is recovered)."""
    dt = t - s[S.mag_t] if np.isfinite(s[S.mag_t]) else 0.0
    dt = min(max(dt, 0.0), DT_MAX)
    s[S.mag_t] = t
    # a sensor-fixed offset (a magnet on the phone), when one is applied, is removed first
    hi, m0, m1, m2 = hard_iron(s, p, mag, dt, rate if has_rate else 0.0)
    mc = (m0, m1, m2)
    # the turn test judges the field as measured: its allowance for what a turn does to a
    # real field (mag_turn_rel) includes the field's lag, and a delay that is not the
    # sensor's own would turn the turn's angular accelerations into field turns
    mw_turn = rotate3(s, mc)
    if has_rate and p[PRM.mag_delay] != 0.0:
        # the field lags the gyroscope by mag_delay
        mw = rotate3(s, turned_forward(s, p, mc, p[PRM.mag_delay]))
    else:
        mw = mw_turn
    n = norm3(mw)
    dip = np.arcsin(min(1.0, max(-1.0, mw[2] / n)))
    f[F_MAG_VAL] = n
    f[F_MAG] = R_USED
    turn = _turn_check(s, p, mw_turn, dt, rate, has_rate)
    was = s[S.disturbed]
    ok = _field_check(s, p, n, dip, dt, rate, turn, f)
    if was == 0.0 and s[S.disturbed] != 0.0:
        s[S.p22_pre] = P[2, 2]          # the heading's σ before the refusal grows it
        s[S.prob] = 0.0
    elif was != 0.0 and s[S.disturbed] == 0.0 and s[S.ref_ok] != 0.0:
        # back to the field after a refusal: evidence first (see PROBATION_TURN)
        s[S.prob] = 1.0
        s[S.prob_turn] = 0.0
        s[S.prob_lo] = np.inf
        s[S.prob_hi] = -np.inf
        s[S.hv_ok] = 0.0        # the gyroscope drifted meanwhile: the evidence starts afresh
    if ok and hi == HI_APPLIED and f[F_MAG] == R_USED:
        f[F_MAG] = R_OFFSET
        f[F_MAG_VAL] = norm3((s[S.hi_applied_x], s[S.hi_applied_y], s[S.hi_applied_z]))
    if not ok:
        # the samples averaged so far are dropped with the refused one: a disturbance starts
        # before the gates see it (they judge a low-passed field), and a world-frame average
        # kept across the refusal would mix in a field seen through a heading since drifted
        s[S.mag_sum:S.mag_sum + 3] = 0.0
        s[S.mag_count] = 0.0
        s[S.mag_upd_time] = 0.0
        return
    # the samples used are averaged in the world frame; the heading correction with
    # their mean runs at most at update_rate_hz
    for i in range(3):
        s[S.mag_sum + i] += mw[i]
    s[S.mag_count] += 1.0
    due, elapsed = update_is_due(s, S.mag_upd_time, dt, p)
    if not due:
        return
    mx = s[S.mag_sum_x] / s[S.mag_count]
    my = s[S.mag_sum_y] / s[S.mag_count]
    mz = s[S.mag_sum_z] / s[S.mag_count]
    s[S.mag_sum:S.mag_sum + 3] = 0.0
    s[S.mag_count] = 0.0
    hn = np.sqrt(mx * mx + my * my)
    if hn < 1e-3 * n:
        return  # field (almost) vertical: no heading information
    m_mean = np.empty(3)
    m_mean[0], m_mean[1], m_mean[2] = mx, my, mz
    innov = heading_innovation(m_mean)
    Rm = np.empty((1, 1))
    Rm[0, 0] = p[PRM.heading_noise] ** 2 / elapsed
    _deviation_lp(s, elapsed)
    Rm[0, 0] += deviation_density(s, p) / elapsed
    H = heading_jacobian(m_mean)
    gate = 0.0      # no NIS gate: the field's own tests judge it (a gate was inert on every trial)
    lost = ok and p[PRM.mag_lost_time] > 0.0 and s[S.far_time] > p[PRM.mag_lost_time]
    z = innov[0] + s[S.hv_corr]     # the field's heading less the gyroscope's alone
    if has_rate and not lost:
        first = _field_heading_lp(s, z, elapsed)
        if p[PRM.heading_evidence_tau] > 0.0 and not first:
            Rm[0, 0] += _heading_evidence(s, p, elapsed) / elapsed
    else:
        # without a gyroscope there is no heading to measure the field against; a lost
        # estimate's jump is no wander of the field nor a drift: both start afresh
        s[S.hv_ok] = 0.0
        s[S.dr_ok] = 0.0
    if s[S.prob] != 0.0 and not has_rate:
        s[S.prob] = 0.0     # no gyroscope heading to test the field against: the field is all
    if s[S.prob] != 0.0 and not lost:
        # a return after a refusal is confirmed by a consistent field over a real turn: its
        # heading less the gyroscope's, low-passed over HV_SMOOTH (one sample's noise is no
        # inconsistency: the range of white noise grows with the number of samples seen),
        # stays within mag_dip_gate while the phone turns by PROBATION_TURN (a magnet near or
        # on a turning phone bends the field's heading by an amount that changes with the
        # attitude; a chance half second "within the gates" is no evidence). Until then the
        # correction runs at the steady gain (R scaled by the growth of the heading variance
        # during the refusal), after it the grown σ lets it catch up at once.
        iv = s[S.hv_fast]
        s[S.prob_lo] = min(s[S.prob_lo], iv)
        s[S.prob_hi] = max(s[S.prob_hi], iv)
        if s[S.prob_hi] - s[S.prob_lo] > p[PRM.mag_dip_gate]:
            s[S.prob_lo] = iv
            s[S.prob_hi] = iv
            s[S.prob_turn] = 0.0
        s[S.prob_turn] += rate * elapsed
        if s[S.prob_turn] >= PROBATION_TURN or p[PRM.mag_dip_gate] <= 0.0:
            s[S.prob] = 0.0
        else:
            # and until then a field whose heading, low-passed over HV_SMOOTH, is farther from
            # the gyroscope's than PROBATION_GATE σ and than mag_dip_gate (the tolerance of a
            # consistent field) is not used: neither the heading's σ (grown during the refusal
            # by what the gyroscope may have drifted) nor the field's noise over HV_SMOOTH
            # explains it (a magnet's chance window within the gates, tens of degrees off). A
            # field that disagrees but stays consistent over the turn ends the probation and is
            # taken (the gyroscope drifted); "never lost" still counts beyond mag_lost_angle
            d = wrap_angle(s[S.hv_fast] - s[S.hv_corr])
            hph = 0.0
            for i in range(3):
                for j in range(3):
                    hph += H[0, i] * P[i, j] * H[0, j]
            v = hph + Rm[0, 0] * elapsed / HV_SMOOTH
            if d * d > max(PROBATION_GATE * PROBATION_GATE * v, p[PRM.mag_dip_gate] ** 2):
                _not_used(s, p, f, d * d / v, ok, innov[0], elapsed)
                return
            if s[S.p22_pre] > 0.0 and P[2, 2] > s[S.p22_pre]:
                Rm[0, 0] *= P[2, 2] / s[S.p22_pre]
    if p[PRM.heading_drift_window] > 0.0 and has_rate and not lost:
        _drift_fit(s, p, t, z, elapsed)
    if lost:
        # an undisturbed field has disagreed with the estimate for long: the estimate is
        # what is wrong. Admit it (heading σ up to the error) and take the field's heading;
        # the bias learned meanwhile (from a heading that was wrong) is dropped.
        P[2, 2] += innov[0] ** 2
        s[S.bias:S.bias + 3] = s[S.bias_good:S.bias_good + 3]
    ok2, nis, dx = correct(P, H, Rm, innov, gate, _MASK_HEADING, s[S.kf_work:S.kf_work + KF_WORK])
    f[F_MAG_NIS] = nis
    if ok2:
        inject(s, P, dx)
        s[S.hv_corr] += dx[2]
        if not lost and s[S.dr_n] > 0.0 and s[S.rest] == 0.0:
            # the bias about the vertical from the drift fit, every BIAS_UPD_S (at rest the
            # gyroscope itself measures it: rest_update)
            s[S.mb_time_heading] += elapsed
            if s[S.mb_time_heading] >= BIAS_UPD_S:
                heading_drift_update(s, P, p, s[S.dr_y] / s[S.dr_n], s[S.dr_var] / s[S.dr_n],
                                     s[S.mb_time_heading])
                s[S.dr_y] = 0.0
                s[S.dr_var] = 0.0
                s[S.dr_n] = 0.0
                s[S.mb_time_heading] = 0.0
        if lost:
            f[F_MAG] = R_RECOVER
            f[F_MAG_VAL] = innov[0]
            s[S.far_time] = 0.0
        elif ok and _is_far(p, innov[0]):
            _far(s, elapsed)  # accepted, but still far: the slow correction may not do
        else:
            s[S.far_time] = 0.0
    else:
        _not_used(s, p, f, nis, ok, innov[0], elapsed)
