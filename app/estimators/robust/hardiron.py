"""A sensor-fixed magnetic offset tracked online: a magnet on the phone (a case, a mount).

A magnet fixed to the phone adds a constant vector ``o`` in the *sensor* frame: the
magnetometer reads ``m = R^T m_earth + o``. The field's strength then swings with the
phone's attitude (``|m|`` between ``|m_earth| - |o|`` and ``|m_earth| + |o|``), its dip and
heading are wrong, and the disturbance gates refuse it for as long as the magnet stays.
Yet once ``o`` is removed, ``|m - o|`` is the earth's strength to the sensor's noise and
its heading is right: the information is there.

**The fit.** While the phone turns, the samples lie on a sphere of radius ``|m_earth|``
centred on ``o``: ``|m|² = 2 m·o + (r² - |o|²)``, linear in ``θ = (o, r² - |o|²)``. A
recursive least-squares fit with exponential forgetting keeps the normal equations
``A = Σ w φ φᵀ``, ``b = Σ w φ y`` (``φ = (2m, 1)``, ``y = |m|²``) over a window of
``hard_iron_window`` seconds *of turning*: a sample's weight is its duration times
``min(1, ω / mag_new_min_rate)``, and the window forgets at the same pace, so at rest the
fit neither learns nor forgets (a still phone shows one point of the sphere). Every
``HI_SOLVE_S`` the 4x4 system is solved; the offset's covariance is ``σ_y² τc A⁻¹``
(``σ_y²`` the fit's mean squared residual, ``τc = HI_CORR_S`` the time over which
magnetometer samples are correlated: their errors are not independent sample to sample).
Little rotation leaves ``A`` ill-conditioned and the σ large: no false offsets at rest.

**Status.** ``none``: no offset distinguishable from zero (``|o| < 3σ``), or not enough
turning seen. ``tracking``: an offset found, not (or no longer) trusted. ``applied``: the
offset is removed from every sample before anything else looks at it, and the field is
*used*. An offset is applied only when

- the fit has seen at least half a window of turning,
- its σ (largest axis) is below ``hard_iron_max_std`` (the sensor's noise level: then
  the heading error it leaves is below σ/|m_h|),
- the fitted sphere's radius matches the learned earth field's strength to
  ``hard_iron_tol`` and the fit's rms residual (in µT) is below ``hard_iron_tol`` × it
  (the corrected field *is* the earth's, not any sphere),
- and the offset explains the field's strength: the raw field's rms deviation from the
  learned strength is ``hard_iron_ratio`` times the corrected field's or more (their
  low-passed squared deviations, over ``mag_cand_tau``). An offset found in a window with
  little turning (a tapped or vibrating phone) or in a room's unevenness moves the strength
  about as much as it fixes, and is left alone: removing one cost 0.3-0.9° on BROAD's
  tapping and vibrating-phone trials. This test is its own: the strength gate
  (``mag_norm_gate_rel``) decides only whether a field is refused, not whether its offset
  is removed (a magnet on the phone that keeps the strength inside the gate would be used
  with its offset in: ``tests/estimators/test_hard_iron.py``, a 10 µT magnet).

A change is detected when new samples leave the fit's sphere by more than 3 × its
residual (and the sensor's noise), low-passed over ``mag_min_undisturbed``, or when the
fit's residual exceeds twice ``hard_iron_tol`` (two fields mixed in the window): the fit
starts over. An applied offset is dropped at once when the raw field fits the learned
strength better than the corrected one (the magnet was taken off: the fit restarts), and
goes back to ``tracking`` when the fit fails the tests above by more than a factor of two
(hysteresis). At most ``HI_FEED_HZ`` samples a second enter the fit, the strength
deviations and the change detection; the others only add their turning time.
"""

from __future__ import annotations

import numpy as np

from app.estimators.robust.params import PRM
from app.estimators.robust.state import DT_MAX, INITIAL, S, lp_coef
from app.jitcache import compiled
from app.quaternion import norm3

# How often the fit is solved (s): the offset changes over seconds
HI_SOLVE_S = 0.1
# Correlation time of the magnetometer's errors (s): a phone's or an IMU's magnetometer is
# low-passed to ~10 Hz, and the field's inhomogeneity changes as fast as the phone moves, so
# samples closer than this are not independent evidence for the fit's σ
HI_CORR_S = 0.1
# Most samples per second fed to the fit
HI_FEED_HZ = 100.0
# The fit works in units of this (µT): the normal equations stay well conditioned
HI_SCALE = 50.0

HI_NONE, HI_TRACKING, HI_APPLIED = 0.0, 1.0, 2.0
HI_STATUS = ("none", "tracking", "applied")


@compiled
def _reset_fit(s):
    s[S.hi_A:S.hi_A + 16] = 0.0
    s[S.hi_b:S.hi_b + 4] = 0.0
    s[S.hi_yy] = 0.0
    s[S.hi_W] = 0.0


@compiled
def hard_iron_reset(s):
    """Start over (alignment): no fit, nothing applied; every hard iron slot (``hi_A`` to
    ``hi_solve_t``, one block of the state) back to its initial value."""
    for i in range(S.hi_A, S.hi_solve_t + 1):
        s[i] = INITIAL[i]


@compiled
def _solve(s, p):
    """Solve the normal equations (Gauss-Jordan on 4x4, no pivoting needed: A is
    positive definite once the sphere is seen); the offset, radius, residual and σ into
    the state. Returns False when the system is (nearly) singular."""
    W = s[S.hi_W]
    if W <= 4.0 * HI_CORR_S:
        return False
    M = np.empty((4, 8))
    for i in range(4):
        for j in range(4):
            M[i, j] = s[S.hi_A + 4 * min(i, j) + max(i, j)]   # only the upper triangle is kept
            M[i, 4 + j] = 1.0 if i == j else 0.0
    for c in range(4):
        piv = c
        for r in range(c + 1, 4):
            if abs(M[r, c]) > abs(M[piv, c]):
                piv = r
        if abs(M[piv, c]) < 1e-12 * W:
            return False
        if piv != c:
            for j in range(8):
                M[c, j], M[piv, j] = M[piv, j], M[c, j]
        d = 1.0 / M[c, c]
        for j in range(8):
            M[c, j] *= d
        for r in range(4):
            if r != c:
                fct = M[r, c]
                if fct != 0.0:
                    for j in range(8):
                        M[r, j] -= fct * M[c, j]
    th = np.zeros(4)
    for i in range(4):
        for j in range(4):
            th[i] += M[i, 4 + j] * s[S.hi_b + j]
    # weighted residual sum of squares: yy - 2 θᵀb + θᵀ A θ
    rss = s[S.hi_yy]
    for i in range(4):
        rss -= 2.0 * th[i] * s[S.hi_b + i]
        for j in range(4):
            rss += th[i] * s[S.hi_A + 4 * min(i, j) + max(i, j)] * th[j]
    rss = max(rss, 0.0)
    r2 = th[3] + th[0] * th[0] + th[1] * th[1] + th[2] * th[2]
    if r2 <= 0.0:
        return False
    r = np.sqrt(r2)
    var_y = rss / (W - 4.0 * HI_CORR_S)
    sd = 0.0
    for i in range(3):
        sd = max(sd, np.sqrt(max(var_y * HI_CORR_S * M[i, 4 + i], 0.0)))
    for i in range(3):
        s[S.hi_o + i] = th[i] * HI_SCALE
    s[S.hi_r] = r * HI_SCALE
    # the residual of |m|² is about 2 r × the residual of |m|
    s[S.hi_rms] = np.sqrt(rss / W) / (2.0 * r) * HI_SCALE
    s[S.hi_std] = sd * HI_SCALE
    return True


@compiled
def strength_deviations(s, p, mag, dt):
    """How far the raw field's strength and the offset-corrected one are from the learned
    reference: their squared deviations low-passed over ``mag_cand_tau`` (``hi_dev_raw``,
    ``hi_dev_cor``). The fit applies an offset when it explains the strength
    (``hard_iron_ratio``, :func:`_judge`), and the reference learns only while the field as
    used stays within ``hard_iron_tol`` of it (``heading._field_check``). Every sample
    :func:`hard_iron` feeds (``dt``: the time since the last one), with the tracking off
    too. Returns the corrected strength |m - o|, which the change detection reads too."""
    n_cor = norm3((mag[0] - s[S.hi_o], mag[1] - s[S.hi_o + 1], mag[2] - s[S.hi_o + 2]))
    if s[S.ref_ok] == 0.0:
        return n_cor
    ref = s[S.ref_norm]
    n_raw = norm3(mag)
    k = lp_coef(dt, p[PRM.mag_cand_tau])
    s[S.hi_dev_raw] += k * ((n_raw - ref) ** 2 - s[S.hi_dev_raw])
    s[S.hi_dev_cor] += k * ((n_cor - ref) ** 2 - s[S.hi_dev_cor])
    return n_cor


@compiled
def hard_iron(s, p, mag, dt, rate):
    """Take one magnetometer sample (sensor frame, µT); return the status (HI_NONE,
    HI_TRACKING, HI_APPLIED) and the field to use as three floats (the sample, minus the
    offset when applied: no array per sample). ``rate`` is the bias-corrected
    turn rate (rad/s), ``dt`` the time since the last magnetometer sample. At most
    ``HI_FEED_HZ`` samples a second are fed (:func:`_feed`): the strength deviations, the
    fit and its judgement; the others only count their turning time (a 285 Hz
    magnetometer adds no geometry over 100 Hz, and the deviations are low-passed over
    seconds)."""
    dt = min(max(dt, 0.0), DT_MAX)
    # turning time: a still phone neither teaches nor makes the fit forget
    mr = p[PRM.mag_new_min_rate]
    s[S.hi_w_acc] += dt * (min(1.0, rate / mr) if mr > 0.0 else 1.0)
    s[S.hi_feed_t] += dt
    if s[S.hi_feed_t] >= 1.0 / HI_FEED_HZ - 0.5 * dt:
        _feed(s, p, mag, s[S.hi_feed_t], s[S.hi_w_acc])
        s[S.hi_w_acc] = 0.0
        s[S.hi_feed_t] = 0.0
    return (s[S.hi_status], mag[0] - s[S.hi_applied_x], mag[1] - s[S.hi_applied_y],
            mag[2] - s[S.hi_applied_z])


@compiled
def _feed(s, p, mag, elapsed, w):
    """A sample fed to the fit, ``elapsed`` after the last one fed, with ``w`` the turning
    time since (the sample's weight): the strength deviations (:func:`strength_deviations`),
    the normal equations, the change detection and, every ``HI_SOLVE_S``, the solution and
    its judgement; the status and the offset applied into the state."""
    n_cor = strength_deviations(s, p, mag, elapsed)
    win = p[PRM.hard_iron_window]
    if win <= 0.0:
        s[S.hi_status] = HI_NONE
        s[S.hi_applied:S.hi_applied + 3] = 0.0
        return
    ref = s[S.ref_norm]
    if w > 0.0:
        lam = 1.0 - w / win if w < 0.1 * win else np.exp(-w / win)   # exp(-w/win), w << win
        u0, u1, u2 = mag[0] / HI_SCALE, mag[1] / HI_SCALE, mag[2] / HI_SCALE
        phi = (2.0 * u0, 2.0 * u1, 2.0 * u2, 1.0)
        y = u0 * u0 + u1 * u1 + u2 * u2
        for i in range(4):
            wi = w * phi[i]
            for j in range(i, 4):       # the upper triangle; mirrored when solved
                s[S.hi_A + 4 * i + j] = lam * s[S.hi_A + 4 * i + j] + wi * phi[j]
            s[S.hi_b + i] = lam * s[S.hi_b + i] + wi * y
        s[S.hi_yy] = lam * s[S.hi_yy] + w * y * y
        s[S.hi_W] = lam * s[S.hi_W] + w
    status = s[S.hi_status]
    # change detection: new samples far off the current fit's sphere (beyond 3 × its own
    # residual and the sensor's noise) mean the offset changed (a magnet put on, taken off,
    # moved): the window's old samples describe another field, start the fit over
    changed = False
    if np.isfinite(s[S.hi_std]) and s[S.hi_r] > 0.0:
        k = lp_coef(elapsed, p[PRM.mag_min_undisturbed])
        s[S.hi_dev_fit] += k * ((n_cor - s[S.hi_r]) ** 2 - s[S.hi_dev_fit])
        lim = 3.0 * max(s[S.hi_rms], p[PRM.hard_iron_max_std])
        changed = s[S.hi_dev_fit] > lim * lim
    if changed or (status == HI_APPLIED and s[S.hi_dev_raw] < s[S.hi_dev_cor]):
        # the offset changed, or the raw field fits the earth's strength better (the magnet
        # is gone): start over
        _reset_fit(s)
        s[S.hi_dev_fit] = 0.0
        s[S.hi_r] = 0.0
        s[S.hi_o:S.hi_o + 3] = 0.0
        s[S.hi_std] = np.inf
        s[S.hi_rms] = np.inf
        s[S.hi_dev_cor] = s[S.hi_dev_raw]
        status = HI_NONE
    else:
        s[S.hi_solve_t] += elapsed
        if s[S.hi_solve_t] >= HI_SOLVE_S:
            s[S.hi_solve_t] = 0.0
            if s[S.hi_W] >= 0.5 * win and _solve(s, p) and s[S.ref_ok] != 0.0:
                status = _judge(s, p, status, ref)
            elif s[S.hi_W] < 0.5 * win and status != HI_APPLIED:
                status = HI_NONE
    s[S.hi_status] = status
    if status == HI_APPLIED:
        for i in range(3):
            s[S.hi_applied + i] = s[S.hi_o + i]
    else:
        s[S.hi_applied:S.hi_applied + 3] = 0.0


@compiled
def centred_sphere(s, p, strength):
    """The fit has seen the field from every side as a homogeneous one of ``strength`` (µT):
    half a window of turning, σ at the sensor's noise, no offset beyond 3σ (the test
    :func:`_judge` calls "none"), and the sphere's radius that strength to
    ``hard_iron_tol``. A new place, not a magnet on the phone (heading._field_check)."""
    sd = s[S.hi_std]
    return (p[PRM.hard_iron_window] > 0.0
            and s[S.hi_W] >= 0.5 * p[PRM.hard_iron_window] and sd <= p[PRM.hard_iron_max_std]
            and norm3((s[S.hi_o], s[S.hi_o + 1], s[S.hi_o + 2])) < 3.0 * sd
            and abs(s[S.hi_r] - strength) <= p[PRM.hard_iron_tol] * strength)


@compiled
def _judge(s, p, status, ref):
    """The status of a fit just solved (see the module's doc): start over when no sphere
    fits, none when the offset is within 3σ of zero, applied when it fits the earth's
    field and explains the strength (``hard_iron_ratio``), else tracking."""
    on = norm3((s[S.hi_o], s[S.hi_o + 1], s[S.hi_o + 2]))
    sd, tol = s[S.hi_std], p[PRM.hard_iron_tol]
    # hysteresis: an applied offset stays while within twice the bounds
    f = 2.0 if status == HI_APPLIED else 1.0
    fits = (sd <= f * p[PRM.hard_iron_max_std]
            and abs(s[S.hi_r] - ref) <= f * tol * ref
            and s[S.hi_rms] <= f * tol * ref)
    if s[S.hi_rms] > 2.0 * tol * min(ref, s[S.cand_norm]):
        # no sphere: the window mixes two fields (a magnet put on while the phone turned, a
        # phone picked up from a laptop turning) or the field is not homogeneous; start over.
        # Judged by the weaker of the reference and the field now (the candidate's): a
        # tentative reference may be a desk's stronger field (heading._field_check)
        _reset_fit(s)
        s[S.hi_o:S.hi_o + 3] = 0.0
        s[S.hi_std] = np.inf
        s[S.hi_r] = 0.0
        return HI_NONE
    if on < 3.0 * sd:
        return HI_NONE
    if fits and (status == HI_APPLIED
                 or s[S.hi_dev_raw] > p[PRM.hard_iron_ratio] ** 2 * s[S.hi_dev_cor]):
        return HI_APPLIED
    return HI_TRACKING
