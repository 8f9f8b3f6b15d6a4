"""Initial alignment without a magnetometer: a stream that brings only the accelerometer
(an ACC-only log, or a phone whose magnetometer is off in the app) must still align
after the wait for a magnetometer sample, not wait for ever."""

from __future__ import annotations

import numpy as np
import pytest

from app.estimators import Reason, make_estimator
from app.estimators.base import ALIGN_WAIT_S


@pytest.mark.parametrize("name", ["robust", "lab", "complementary"])
def test_an_accelerometer_only_stream_aligns_after_the_wait(name):
    est = make_estimator(name)
    tilt = np.array([0.0, 3.0, 9.33])            # the phone lies tilted, 18° about x
    flags = []
    fs = 100.0
    for k in range(int(2 * fs)):                 # 2 s of accelerometer samples only
        flags.append(est.step(k / fs, acc=tilt).acc)
    inits = [k for k, r in enumerate(flags) if r == Reason.INIT]
    assert est.initialized, f"{name} never aligned on an accelerometer-only stream"
    assert len(inits) == 1
    # aligned once the wait for a magnetometer sample ran out, counted from the first sample
    assert inits[0] / fs == pytest.approx(ALIGN_WAIT_S, abs=2.5 / fs)
    up = est.q  # the estimate's gravity direction agrees with the samples'
    from app import quaternion as qm
    g_world = qm.Q(up) @ (tilt / np.linalg.norm(tilt))
    assert g_world[2] > np.cos(np.radians(1.0))


def test_the_alignment_decision_is_one_function_for_every_case():
    """base.align_step: what aligns, and when (lab and robust both ask it)."""
    from app.estimators.base import (ALIGN_ACC, ALIGN_ACC_MAG, ALIGN_NO_ACC, ALIGN_WAIT, F_ACC,
                                     F_GYR, F_MAG, R_ABSENT, R_USED, align_step, new_flags)
    acc = np.array([0.0, 3.0, 9.33])
    absent = R_ABSENT

    def run(rows, use_acc=True, use_mag=True):
        s = np.full(4, np.nan)
        out = []
        for t, gs, as_, ms in rows:
            f = new_flags()
            act = align_step(s, 0, 1, t, gs, as_, ms, acc, use_acc, use_mag, f)
            out.append((act, int(f[F_GYR]), int(f[F_ACC]), int(f[F_MAG])))
            if act != ALIGN_WAIT:
                break
        return out, s

    W, I = int(Reason.WAIT), int(Reason.INIT)
    # accelerometer then magnetometer: tilt and heading, the waiting sample kept
    out, s = run([(0.00, R_USED, R_USED, absent), (0.01, R_USED, absent, R_USED)])
    assert out == [(ALIGN_WAIT, W, W, absent), (ALIGN_ACC_MAG, W, absent, I)]
    assert np.array_equal(s[1:], acc)
    # magnetometer off: the first accelerometer sample aligns at once
    out, _ = run([(0.0, R_USED, R_USED, absent)], use_mag=False)
    assert out == [(ALIGN_ACC, W, I, absent)]
    # no magnetometer sample: tilt only, once the wait has run out
    rows = [(k * 0.01, R_USED, R_USED, absent) for k in range(100)]
    out, _ = run(rows)
    assert out[-1][0] == ALIGN_ACC and out[-1][2] == I
    assert (len(out) - 1) * 0.01 > ALIGN_WAIT_S >= (len(out) - 2) * 0.01
    # a magnetometer sample before any accelerometer sample aligns nothing
    out, _ = run([(0.0, R_USED, absent, R_USED), (0.01, R_USED, absent, absent)])
    assert [o[0] for o in out] == [ALIGN_WAIT, ALIGN_WAIT]
    # accelerometer off: a level start at the first gyroscope or magnetometer sample
    out, _ = run([(0.0, absent, absent, R_USED)], use_acc=False)
    assert out == [(ALIGN_NO_ACC, absent, absent, I)]
    out, _ = run([(0.0, R_USED, absent, absent)], use_acc=False)
    assert out == [(ALIGN_NO_ACC, I, absent, absent)]


@pytest.mark.parametrize("name", ["robust", "lab", "complementary"])
def test_a_stream_without_accelerometer_aligns_level_after_the_wait(name):
    """A phone streaming its gyroscope and magnetometer only (accelerometer on in the
    filter): it starts level after the wait, heading from the field, and goes on."""
    est = make_estimator(name)
    fs = 100.0
    mag = np.array([0.0, 20.0, -40.0])          # the phone lies flat, top to the north
    inits = []
    for k in range(int(2 * fs)):
        f = est.step(k / fs, gyr=np.array([1e-4, 0.0, 0.0]), mag=mag if k % 2 else None)
        if Reason.INIT in (f.gyr, f.mag):
            inits.append(k)
    assert est.initialized, f"{name} never aligned without an accelerometer"
    assert inits and inits[0] / fs == pytest.approx(ALIGN_WAIT_S, abs=2.5 / fs)
    from app import quaternion as qm
    yaw_north = qm.Q(est.q) @ np.array([0.0, 1.0, 0.0])   # the phone's top in the world
    assert yaw_north[1] > np.cos(np.radians(5.0))
