"""The ``phone`` estimator: the stream's ORI quaternion passed through and held."""

from __future__ import annotations

import numpy as np
import pytest

from app import quaternion as qm
from app.estimators import Reason, TimeIssue, make_estimator
from app.estimators.phone import PhoneOrientation, ori_quaternion
from app.params import CommonParams


def test_passes_ori_through_normalised_with_w_nonnegative():
    est = make_estimator("phone")
    assert isinstance(est, PhoneOrientation) and est.params == CommonParams()
    assert not est.initialized
    assert est.q.tolist() == [1.0, 0.0, 0.0, 0.0]
    f = est.step(0.0, gyr=[0.1, 0.2, 0.3], acc=[0.0, 0.0, 9.8], mag=[0.0, 20.0, -45.0])
    assert not est.initialized                        # sensors alone do not start it
    assert (f.gyr, f.acc, f.mag) == (Reason.DISABLED, Reason.DISABLED, Reason.DISABLED)
    est.step(0.01, ori=[-0.5, 0.5, -1.0, 1.5])        # not unit, w < 0
    q = est.q
    assert est.initialized
    assert q[0] > 0 and np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(q, -np.array([-0.5, 0.5, -1.0, 1.5]) / np.linalg.norm([0.5, 0.5, 1, 1.5]))


def test_holds_the_last_ori_between_samples():
    rng = np.random.default_rng(0)
    truth = np.array([qm.normalize(rng.normal(size=4)) for _ in range(50)])
    n = 200
    t = np.arange(n) * 0.01
    ori = np.full((n, 4), np.nan)
    ori[10::4] = truth[: len(ori[10::4])]             # ORI in every 4th row from row 10
    gyr = rng.normal(size=(n, 3))
    res = make_estimator("phone").run(t, gyr=gyr, ori=ori)
    np.testing.assert_array_equal(res.q[:10], np.tile([1.0, 0.0, 0.0, 0.0], (10, 1)))
    for k in range(10, n):
        last = 10 + 4 * ((k - 10) // 4)
        np.testing.assert_allclose(res.q[k], qm.normalize(ori[last]), atol=1e-15)
    assert np.all(res.flags[:, 0] == Reason.DISABLED)  # gyroscope present, not used
    assert np.all(res.flags[:, 1] == Reason.ABSENT)
    assert np.all(res.flags[:, 4] == Reason.ABSENT)


def test_three_value_ori_and_bad_samples():
    v = np.array([0.1, -0.2, 0.3])
    q = ori_quaternion(v)
    np.testing.assert_allclose(q, [np.sqrt(1 - v @ v), *v])
    assert ori_quaternion(None) is None
    assert ori_quaternion([np.nan] * 4) is None
    assert ori_quaternion([0.0] * 4) is None
    assert ori_quaternion([1.0, np.inf, 0.0, 0.0]) is None
    assert ori_quaternion([0.9, 0.9, 0.0]) is None    # vector part longer than 1
    est = make_estimator("phone")
    est.step(0.0, ori=[0.0, 0.0, 1.0, 0.0])
    est.step(0.01, ori=[np.nan, 1.0, 0.0, 0.0])       # bad sample: the last one is kept
    np.testing.assert_array_equal(est.q, [0.0, 0.0, 1.0, 0.0])


def test_switches_time_and_save_state():
    est = make_estimator("phone", {"use_acc": False})
    f = est.step(1.0, acc=[0.0, 0.0, 9.8], ori=[1.0, 0.0, 0.0, 0.0])
    assert f.acc == Reason.DISABLED and f.time == TimeIssue.FIRST
    saved = est.save_state()
    est.step(1.1, ori=[0.0, 1.0, 0.0, 0.0])
    f = est.step(1.05, ori=[0.0, 0.0, 1.0, 0.0])      # backward timestamp: row skipped
    assert f.time == TimeIssue.BACKWARD
    np.testing.assert_array_equal(est.q, [0.0, 1.0, 0.0, 0.0])
    assert est.diagnostics().ori_t == 1.1
    est.load_state(saved)
    np.testing.assert_array_equal(est.q, [1.0, 0.0, 0.0, 0.0])
    est.reset()
    assert not est.initialized and est.attitude_cov() is None


def test_on_the_lab_simulator():
    """The simulated phone's ORI (truth turned by a wandering error of about 1°) comes out."""
    from app.sources.simulate import simulate
    sim = simulate(("still", "turn_x", "shake"), seed=2)
    est = make_estimator("phone")
    times, qs = [], []
    for ms, tag, v in sim.samples:
        if tag in ("ACC", "GYR", "MAG", "ORI"):
            est.step((ms - sim.boot_ms) / 1000.0, **{tag.lower(): v})
            if est.initialized:
                times.append(ms)
                qs.append(est.q)
    tot, _, _ = qm.error_angles(np.array(qs), sim.truth_at_ms(times))
    assert np.degrees(tot).max() < 2.5                 # the phone's error, plus <= 10 ms hold
    assert np.degrees(np.sqrt(np.mean(tot ** 2))) > 0.3  # it is the phone's, not the truth


def test_compiled_run_equals_the_reference_step():
    """The compiled batch run takes the steps of ``_step``: valid, NaN, zero and backward
    ORI rows, sensors switched off, a gap."""
    from app.estimators.base import Estimator
    rng = np.random.default_rng(1)
    n = 400
    t = np.cumsum(rng.uniform(0.0, 0.02, n))
    t[150] = t[149] - 0.05                      # backward
    t[300:] += 2.0                              # a gap
    ori = rng.normal(size=(n, 4))
    ori[::7] = np.nan
    ori[::11] = 0.0
    gyr = np.where(rng.random((n, 1)) < 0.5, rng.normal(size=(n, 3)), np.nan)
    acc = np.where(rng.random((n, 1)) < 0.5, rng.normal(size=(n, 3)), np.nan)
    for params in ({}, {"use_gyr": False, "use_mag": False}):
        ref = Estimator.run_steps(make_estimator("phone", params), t, gyr, acc, None, ori)
        est = make_estimator("phone", params)
        parts = [est.run(t[i:i + 50], gyr[i:i + 50], acc[i:i + 50], None, ori[i:i + 50])
                 for i in range(0, n, 50)]
        np.testing.assert_allclose(np.concatenate([p.q for p in parts]), ref.q, atol=1e-12)
        f = np.concatenate([p.flags for p in parts])
        np.testing.assert_array_equal(np.nan_to_num(f, nan=-7), np.nan_to_num(ref.flags, nan=-7))


def test_a_held_ori_expires_when_the_app_stops_sending_it():
    """An app that stops ORI while its other sensors go on: the last ORI is held for
    ORI_HOLD_S of stream time, then there is no phone estimate (not initialised, the
    identity) until ORI comes back; step by step as in a batch."""
    from app.estimators.phone import ORI_HOLD_S
    n = 1000
    t = np.arange(n) * 0.01                           # 10 s
    gyr = np.zeros((n, 3))
    ori = np.full((n, 4), np.nan)
    q0 = qm.normalize(np.array([0.9, 0.1, -0.2, 0.3]))
    ori[:200] = q0                                    # ORI for 2 s
    ori[800:] = q0                                    # back after 8 s
    res = make_estimator("phone").run(t, gyr=gyr, ori=ori)
    held = (t >= 2.0) & (t - 1.99 <= ORI_HOLD_S)
    gone = (t - 1.99 > ORI_HOLD_S + 1e-9) & (t < 8.0)
    np.testing.assert_allclose(res.q[held], np.tile(q0, (held.sum(), 1)), atol=1e-15)
    assert qm.not_estimated(res.q[gone]).all() and gone.sum() > 250
    np.testing.assert_allclose(res.q[800:], np.tile(q0, (200, 1)), atol=1e-15)
    est = make_estimator("phone")
    for k in range(600):
        est.step(float(t[k]), gyr=gyr[k], ori=None if np.isnan(ori[k, 0]) else ori[k])
    assert not est.initialized and est.q.tolist() == [1.0, 0.0, 0.0, 0.0]
