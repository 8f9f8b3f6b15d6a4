"""A phone spinning steadily about the vertical (a turntable, a swivel chair).

- The magnetometer's lag behind the gyroscope (``mag_delay``, issue 19 item 4): with a field that
  lags by 10 ms, a 5 rad/s spin puts the field's heading behind by rate × lag (2.9°), and the
  estimate follows the field. Turned forward by the gyroscope's rate × the delay, the field gives
  the heading back.
- The accelerometer's lag (``acc_delay_periods``, issue 19 item 4): a phone tumbling about a
  horizontal axis (a wheel, a rotisserie) with an accelerometer that lags by one sample period
  sees gravity turned back by rate × lag, a constant tilt. An accelerometer that stands for the
  specific force over its period and is stamped at its end lags by half a period: the default.
- A steady spin is no rest (found while writing the first test)."""

from __future__ import annotations

import numpy as np

from app import quaternion as qm
from app.estimators import make_estimator

DEG = 180.0 / np.pi
G = np.array([0.0, 0.0, 9.81])
M_WORLD = np.array([0.0, 20.0, -45.0])       # µT, ENU: north and down (a northern field)
RATE, LAG, FS = 5.0, 0.010, 100.0            # rad/s about the vertical, s, Hz


def _spin(seconds=40.0, seed=4, rate=RATE):
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * FS)) / FS
    tilt = qm.quat_from_rotvec(np.array([0.3, -0.2, 0.0]))          # held tilted, spinning about up
    yaw = lambda tt: qm.quat_from_rotvec_many(np.outer(rate * tt, [0.0, 0.0, 1.0]))  # noqa: E731
    q = qm.quat_mul_many(yaw(t), np.tile(tilt, (len(t), 1)))
    q_lag = qm.quat_mul_many(yaw(t - LAG), np.tile(tilt, (len(t), 1)))
    w_sensor = qm.rotate_inv_many(np.tile(tilt, (len(t), 1)), np.tile([0.0, 0.0, rate], (len(t), 1)))
    gyr = w_sensor + 0.003 * rng.standard_normal((len(t), 3))
    acc = qm.rotate_inv_many(q, np.tile(G, (len(t), 1))) + 0.05 * rng.standard_normal((len(t), 3))
    mag = qm.rotate_inv_many(q_lag, np.tile(M_WORLD, (len(t), 1))) + 0.3 * rng.standard_normal((len(t), 3))
    return t, gyr, acc, mag, q


def _heading_rms(delay: float) -> float:
    t, gyr, acc, mag, q = _spin()
    res = make_estimator("robust", {"mag_delay": delay}).run(t, gyr, acc, mag)
    late = t > 20.0
    _, h, _ = qm.error_angles(res.q[late], q[late])
    return float(np.sqrt(np.mean(h ** 2)) * DEG)


def test_a_lagging_field_is_turned_forward_by_the_delay():
    lagged = _heading_rms(0.0)
    compensated = _heading_rms(LAG)
    assert lagged > 2.0, f"uncompensated heading {lagged:.2f}°: the lag should show (2.9°)"
    assert compensated < 0.5, f"compensated heading {compensated:.2f}°"
    # the default compensates (a delay, half a magnetometer's period): part of the 10 ms lag goes
    default = make_estimator("robust").params.mag_delay
    assert 0.0 < default < LAG
    assert _heading_rms(default) < 0.7 * lagged


def test_a_steady_spin_is_no_rest():
    """A phone spinning steadily about the vertical (a turntable, a swivel chair) reads a constant
    gyroscope and a constant accelerometer, as at rest; taken for rest, the spin was learned as
    bias and the heading turned away by 90-160° within seconds. A reading above any plausible
    bias (``bias_max``) is a turn."""
    for rate in (0.5, 5.0):
        t, gyr, acc, mag, q = _spin(seconds=20.0, rate=rate)
        est = make_estimator("robust", {"mag_delay": LAG})
        res = est.run(t, gyr, acc, mag)
        _, h, _ = qm.error_angles(res.q, q)
        assert np.max(np.abs(h[t > 2.0])) * DEG < 3.0, f"{rate} rad/s: heading {np.max(np.abs(h)) * DEG:.1f}°"
        assert np.linalg.norm(est.gyr_bias) < 0.01


def _tumble(acc_at, seconds=40.0, rate=3.0, seed=5):
    """A phone tumbling about the world's x axis at ``rate``; ``acc_at(t)``: the times whose
    gravity each accelerometer sample shows (rows: samples, columns: averaged together)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * FS)) / FS
    axis = np.array([1.0, 0.0, 0.0])
    turn = lambda tt: qm.quat_from_rotvec_many(np.outer(rate * tt, axis))  # noqa: E731
    q = turn(t)
    ta = acc_at(t)
    acc = np.mean([qm.rotate_inv_many(turn(ta[:, j]), np.tile(G, (len(t), 1))) for j in range(ta.shape[1])],
                  axis=0) + 0.05 * rng.standard_normal((len(t), 3))
    gyr = qm.rotate_inv_many(q, np.tile(rate * axis, (len(t), 1))) + 0.003 * rng.standard_normal((len(t), 3))
    mag = qm.rotate_inv_many(q, np.tile(M_WORLD, (len(t), 1))) + 0.3 * rng.standard_normal((len(t), 3))
    return t, gyr, acc, mag, q


def _inclination_rms(data, periods: float) -> float:
    t, gyr, acc, mag, q = data
    res = make_estimator("robust", {"acc_delay_periods": periods}).run(t, gyr, acc, mag)
    late = t > 20.0
    _, _, incl = qm.error_angles(res.q[late], q[late])
    return float(np.sqrt(np.mean(incl ** 2)) * DEG)


def test_a_lagging_accelerometer_is_turned_forward():
    """3 rad/s × a 10 ms lag is 1.7° of tilt, gone when the sample is turned forward by the
    gyroscope's rate × the lag (one period of the 100 Hz stream, measured from it)."""
    lagged = _tumble(lambda t: (t - 1.0 / FS)[:, None])
    off = _inclination_rms(lagged, 0.0)
    assert off > 1.2, f"uncompensated inclination {off:.2f}°: the lag should show (1.7°)"
    assert _inclination_rms(lagged, 1.0) < 0.2


def test_the_default_lag_is_half_a_period_of_an_averaging_accelerometer():
    """An accelerometer whose sample is the mean over its period, stamped at its end, stands for
    the middle of the period: the default (half a period) takes the tilt it leaves away."""
    averaging = _tumble(lambda t: t[:, None] - (np.arange(10)[None, :] + 0.5) / (10 * FS))
    default = make_estimator("robust").params.acc_delay_periods
    assert default == 0.5
    off = _inclination_rms(averaging, 0.0)
    assert off > 0.6, f"uncompensated inclination {off:.2f}° (half of 1.7°)"
    assert _inclination_rms(averaging, default) < 0.2 * off
