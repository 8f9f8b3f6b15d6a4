"""A magnetometer fit that would mislead is refused, with the reason in words (issue 21,
item 1): a still phone (one point), a phone turned about one axis (a plane), too little
coverage for the model, a residual that does not improve (a real log), an implausible
field, a 1e-9 µT noise ball."""

from __future__ import annotations

import numpy as np
import pytest

from app.sources.readers import read_log_data
from app.toolkit import magcal as mc
from app.toolkit.magcal import MagCalError, fit

FIELD = np.array([0.0, 20.0, -44.0])          # µT, |m| ≈ 48
LOGS = "data/sensorfusion-app/alekodu_activityrecognition/"


def _sphere(n=800, radius=48.0, seed=1, zmin=None, noise=0.3, offset=(12.0, -7.0, 20.0)):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n * 8, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    if zmin is not None:                      # only a cap of directions around +z
        u = u[u[:, 2] > zmin]
    u = u[:n]
    return radius * u + np.asarray(offset) + rng.normal(scale=noise, size=u.shape)


def _about_one_axis(n=800, seed=2):
    """The field as a phone turned about its z axis only reads it: a circle."""
    rng = np.random.default_rng(seed)
    a = np.linspace(0, 4 * np.pi, n)
    R = np.stack([np.cos(a), np.sin(a)], axis=1)
    xy = np.stack([R[:, 0] * FIELD[1], -R[:, 1] * FIELD[1]], axis=1)
    m = np.column_stack([xy, np.full(n, FIELD[2])]) + np.array([12.0, -7.0, 20.0])
    return m + rng.normal(scale=0.3, size=m.shape)


def _refused(m, model="auto"):
    with pytest.raises(mc.MagCalRefused) as e:
        fit(m, model)
    return e.value


def test_a_still_phone_is_one_point(shared_dir):
    rec = read_log_data(shared_dir / LOGS / "sensorLog_20221024T182616_standstill.txt")
    e = _refused(rec.mag)
    assert "one point" in e.reason and "lay still" in e.reason and e.cal is None


def test_a_tiny_noise_ball_is_refused():
    rng = np.random.default_rng(0)
    ball = np.array([20.0, 5.0, -40.0]) + rng.normal(scale=1e-9, size=(500, 3))
    e = _refused(ball)
    assert "one point" in e.reason
    # and were it fitted: its field (~1e-9 µT) is implausible
    cal = fit(ball, check=False)
    assert "implausible" in mc.refusal(cal)


def test_turned_about_one_axis_is_a_plane():
    e = _refused(_about_one_axis())
    assert "plane" in e.reason and "one axis" in e.reason


def test_a_line_is_refused():
    rng = np.random.default_rng(3)
    s = np.linspace(-30, 30, 500)[:, None]
    e = _refused(np.array([10.0, 20.0, -30.0]) + s * np.array([[0.6, 0.8, 0.0]])
                 + rng.normal(scale=0.2, size=(500, 3)))
    assert "line" in e.reason


def test_coverage_too_low_for_the_model():
    cap = _sphere(zmin=0.7)                   # ~15 % of the sphere: not even a sphere
    e = _refused(cap)
    assert "coverage" in e.reason and "sphere" in e.reason and e.cal is not None
    half = _sphere(zmin=0.1)                  # ~45 %: a sphere, not an ellipsoid
    e = _refused(half, "ellipsoid")
    assert "coverage" in e.reason and "ellipsoid" in e.reason
    cal = fit(half)                           # auto: the sphere it can tell
    assert cal.model == "sphere" and np.allclose(cal.offset, [12.0, -7.0, 20.0], atol=1.0)


def test_a_residual_that_does_not_improve_is_refused(shared_dir):
    """A real log (the phone run with in the hand): the fitted sphere makes the spread
    of |m| worse (6.68 -> 6.73 µT), as the issue's 6.61 -> 7.85 µT was applied."""
    rec = read_log_data(shared_dir / LOGS / "sensorLog_20221024T182741_running_hand.txt")
    e = _refused(rec.mag)
    assert "residual does not improve" in e.reason and "worse" in e.reason
    assert e.cal.residual_after_uT > e.cal.residual_before_uT


def test_an_implausible_field_is_refused():
    e = _refused(_sphere(radius=260.0, noise=1.0))
    assert "implausible" in e.reason and "260" in e.reason
    e = _refused(_sphere(radius=7.0, noise=0.05))
    assert "implausible" in e.reason


def test_a_good_turn_is_accepted():
    cal = fit(_sphere(n=1500))
    assert cal.model == "ellipsoid" and mc.refusal(cal) is None
    with pytest.raises(MagCalError, match="at least"):
        fit(np.ones((5, 3)))
