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
