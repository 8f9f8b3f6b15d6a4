"""Hard- and soft-iron calibration (app/toolkit/magcal.py)."""

from __future__ import annotations

import numpy as np
import pytest

from app.toolkit.magcal import (IDENTITY, MIN_COVERAGE_ELLIPSOID, MIN_COVERAGE_SPHERE, MagCalError,
    correct_samples, coverage, fit, from_preset)
from app.sources.sensorfusion import parse_line


def _turned(n=600, field=48.0, seed=1, cap=None):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    if cap is not None:                 # only directions near +z: a phone barely turned
        u = u[u[:, 2] > cap]
    return field * u


def test_recovers_a_synthetic_offset_and_scale():
    true_field = _turned()
    A = np.array([[1.25, 0.08, 0.0], [0.08, 0.85, 0.05], [0.0, 0.05, 1.05]])   # soft iron
    b = np.array([22.0, -13.0, 31.0])                                           # hard iron
    rng = np.random.default_rng(2)
    raw = true_field @ A.T + b + rng.normal(scale=0.3, size=true_field.shape)
    cal = fit(raw)
    assert cal.model == "ellipsoid"
    np.testing.assert_allclose(cal.offset, b, atol=0.3)
    # the correction undoes A up to a rotation and the field strength: W A is a
    # scaled rotation, so the corrected field is a sphere
    WA = cal.matrix @ A
    s = np.cbrt(abs(np.linalg.det(WA)))
    np.testing.assert_allclose(WA.T @ WA / s**2, np.eye(3), atol=0.02)
    assert abs(cal.field_uT - 48.0 * np.cbrt(np.linalg.det(A)) * 1.0) < 1.0
    assert cal.residual_before_uT > 5.0 and cal.residual_after_uT < 0.5
    assert cal.coverage == 1.0
    corrected = cal.apply(raw)
    assert np.std(np.linalg.norm(corrected, axis=1)) < 0.5


def test_poor_coverage_gives_hard_iron_only_and_says_so():
    # a cap of 35 % of the directions: enough for a sphere, too little for an ellipsoid
    # (a smaller one is refused: test_magcal_refusals.py)
    raw = _turned(n=1500, cap=0.3) + np.array([5.0, 5.0, 5.0])
    frac, counts = coverage(raw, np.array([5.0, 5.0, 5.0]))
    assert MIN_COVERAGE_SPHERE <= frac < MIN_COVERAGE_ELLIPSOID and counts.sum() == len(raw)
    cal = fit(raw)
    assert cal.model == "sphere"
    np.testing.assert_allclose(cal.matrix, np.eye(3))
    np.testing.assert_allclose(cal.offset, [5, 5, 5], atol=1e-6)


def test_too_few_samples_and_bad_presets_are_refused():
    with pytest.raises(MagCalError, match="at least"):
        fit(np.ones((5, 3)))
    with pytest.raises(MagCalError, match="matrix"):
        from_preset({"offset_uT": [0, 0, 0], "matrix": [1, 2, 3, 4, 5, 6, 7, 8, 9]})
    with pytest.raises(MagCalError, match="unknown key"):
        from_preset({"offsets": [0, 0, 0]})
    cal = from_preset({"offset_uT": [1, 2, 3], "matrix": [1, 0, 0, 0, 2, 0, 0, 0, 1]})
    np.testing.assert_allclose(cal.apply(np.array([2.0, 3.0, 4.0])), [1.0, 2.0, 1.0])


def test_correct_samples_changes_mag_samples_only():
    cal = from_preset({"offset_uT": [10, 0, 0], "matrix": [1, 0, 0, 0, 1, 0, 0, 0, 1]})
    samples = [parse_line(b"100\tMAG\t15\t2\t-40"), parse_line(b"101\tACC\t0\t0\t9.81")]
    out = correct_samples(cal, samples)
    assert out[0].values == (5.0, 2.0, -40.0) and out[0].time_ms == 100
    assert out[1:] == samples[1:]
    assert correct_samples(IDENTITY, samples) is samples
