"""The scale-factor noise of ``robust`` follows the net turn, not the turn rate.

A gyroscope whose scale factor is off by 1 % turns the estimate by 1 % of the rotation.
A steady turn builds that up over the tilt loop's time scale, so the tilt must correct
faster then; a back-and-forth of the same rate (running, swinging) cancels, so it must
not: there the accelerometer carries the specific force the loop averages out. The
stream is synthesised here from an exact rotation about the world's east axis (a tilt),
with the scale error as the only fault.
"""

from __future__ import annotations

import numpy as np

from app import quaternion as qm
from app.estimators import make_estimator

RATE_HZ = 100.0
FIELD_WORLD = np.array([0.0, 21.0, -45.0])   # µT, ENU, a dip of 65°
SCALE_ERROR = 0.01


def _stream(angle):
    """Rows of a phone turned about the world's east axis by ``angle(t)`` (rad), its
    gyroscope reading the rate 1 % too high."""
    t = np.arange(0.0, 60.0, 1.0 / RATE_HZ)
    theta = angle(t)
    q = qm.quat_from_rotvec_many(np.outer(theta, [1.0, 0.0, 0.0]))
    rate = np.gradient(theta, t)
    gyr = np.zeros((t.size, 3))
    gyr[:, 0] = rate * (1.0 + SCALE_ERROR)    # about a fixed axis, body rate = world rate
    acc = qm.rotate_inv_many(q, np.array([0.0, 0.0, 9.81]))
    mag = qm.rotate_inv_many(q, FIELD_WORLD)
    return t, gyr, acc, mag, q


def _tilt_rms_deg(params, angle):
    t, gyr, acc, mag, q = _stream(angle)
    est = make_estimator("robust", params)
    res = est.run(t, gyr, acc, mag)
    late = t > 20.0                           # after the loop has settled
    _, _, inc = qm.error_angles(res.q[late], q[late])
    return float(np.degrees(np.sqrt(np.mean(inc ** 2)))), est


def _tilt_var_added(angle):
    """How much the scale noise adds to the tilt variance (rad²) by the end of the run."""
    tilt_var = lambda e: float(np.trace(e.attitude_cov()[:2, :2]))  # noqa: E731
    return tilt_var(_tilt_rms_deg({}, angle)[1]) - tilt_var(_tilt_rms_deg({"gyr_scale_noise": 0.0}, angle)[1])


def steady(t):
    return 1.0 * t                                       # 1 rad/s, one way


def swing(t):
    return 1.0 * np.sin(2.0 * np.pi * 1.0 * t)           # ±1 rad at 1 Hz: up to 6.3 rad/s


def test_a_steady_turn_makes_the_tilt_correct_faster():
    off, _ = _tilt_rms_deg({"gyr_scale_noise": 0.0}, steady)
    on, _ = _tilt_rms_deg({}, steady)
    # the drift is 0.01 rad/s; the faster correction leaves clearly less of it
    assert on < 0.75 * off, (on, off)


def test_a_back_and_forth_does_not_speed_the_tilt_up():
    # the swing's rate averages 4x the steady turn's, yet its net turn is ~0: the scale
    # noise adds a small fraction of what the steady turn makes it add
    added_steady, added_swing = _tilt_var_added(steady), _tilt_var_added(swing)
    assert added_steady > 0.0
    assert added_swing < 0.2 * added_steady, (added_swing, added_steady)
