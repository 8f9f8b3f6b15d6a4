"""Calibration statistics: synthetic tilted pose, normality test against scipy, the
preset through load_config, the real standstill log."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps

from app import quaternion as qm
from app.toolkit.calibration import (StationaryLimits, calibrate, format_report, normality_test,
    preset_values, to_preset)
from app.config import load_config
from app.sources.readers import read_log_data

G = 9.81
M0_TRUE = np.array([0.0, 15.0, -45.0])    # µT, ENU (north, down-pointing dip)


def stationary(q, n=3000, fs=100.0, seed=0, bias=(0.01, -0.02, 0.005), drift_per_min=0.0,
               gyr_sigma=0.003):
    """A still phone in pose ``q``: acc/mag from the true references plus noise."""
    rng = np.random.default_rng(seed)
    R = qm.Q(np.asarray(q, float))
    t = np.arange(n) / fs
    acc_cov = np.array([[0.02, 0.005, 0.0], [0.005, 0.03, -0.004], [0.0, -0.004, 0.05]])
    acc = R.T @ [0.0, 0.0, G] + rng.multivariate_normal(np.zeros(3), acc_cov, n)
    gyr = np.asarray(bias) + rng.normal(0.0, gyr_sigma, (n, 3))
    gyr[:, 2] += drift_per_min * (t / 60.0)
    mag = R.T @ M0_TRUE + rng.normal(0.0, 0.4, (n, 3))
    return t, gyr, acc, mag


TILTED = qm.normalize(np.array([0.8, 0.35, -0.4, 0.28]))


def test_normality_test_matches_scipy():
    rng = np.random.default_rng(3)
    for x in (rng.normal(size=500), rng.exponential(size=300), rng.uniform(size=40),
              rng.standard_t(3, size=2000)):
        k2, p, skew, kurt = normality_test(x)
        ref = sps.normaltest(x)
        assert k2 == pytest.approx(ref.statistic, rel=1e-9)
        assert p == pytest.approx(ref.pvalue, rel=1e-6, abs=1e-300)
        assert skew == pytest.approx(sps.skew(x), rel=1e-9)
        assert kurt == pytest.approx(sps.kurtosis(x), rel=1e-9)
    assert all(math.isnan(v) for v in normality_test(np.ones(100)))
    assert all(math.isnan(v) for v in normality_test(np.arange(5.0)))


def test_tilted_stationary_recording():
    t, gyr, acc, mag = stationary(TILTED)
    st = calibrate(t, gyr, acc, mag)
    assert st.stationary and st.warnings == []
    # g0, bias, m0 recovered in a pose far from lying flat
    assert st.tilt_deg > 30
    np.testing.assert_allclose(st.g0, [0.0, 0.0, G], atol=0.02)
    np.testing.assert_allclose(st.gyr_bias, [0.01, -0.02, 0.005], atol=3e-4)
    np.testing.assert_allclose(st.m0, M0_TRUE, atol=0.3)
    # moments against numpy
    for name, x in (("acc", acc), ("gyr", gyr), ("mag", mag)):
        s = st.sensors[name]
        assert s.n == len(t)
        np.testing.assert_allclose(s.mean, x.mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(s.cov, np.cov(x.T), rtol=1e-10, atol=1e-15)
        np.testing.assert_allclose(s.std, x.std(axis=0, ddof=1), rtol=1e-10)
        assert all(int(c.sum()) == len(t) for c in s.hist_counts)
        for i in range(3):
            e = s.hist_edges[i]
            assert e[0] == x[:, i].min() and e[-1] == x[:, i].max()
    # Gaussian noise: normality is not rejected on (nearly) every axis
    assert np.sum(st.sensors["gyr"].normal) >= 2
    np.testing.assert_allclose(st.sensors["acc"].cov, [[0.02, 0.005, 0.0],
                                                       [0.005, 0.03, -0.004],
                                                       [0.0, -0.004, 0.05]], atol=3e-3)


@pytest.mark.parametrize("q", [
    [1.0, 0.0, 0.0, 0.0],                        # lying flat, face up
    [0.0, 1.0, 0.0, 0.0],                        # face down
    [math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0],   # standing on its bottom edge
    [math.cos(0.6), 0.0, 0.0, math.sin(0.6)],    # flat, turned: heading must not matter
])
def test_m0_recovered_in_any_pose(q):
    t, gyr, acc, mag = stationary(q, n=500, seed=5)
    st = calibrate(t, gyr, acc, mag)
    np.testing.assert_allclose(st.m0, M0_TRUE, atol=0.3)
    assert st.m0[0] == 0.0


def test_trend_per_minute():
    t, gyr, acc, mag = stationary(TILTED, n=6000, drift_per_min=0.03)
    st = calibrate(t, gyr, acc, mag)
    assert st.sensors["gyr"].trend_per_min[2] == pytest.approx(0.03, abs=0.002)
    assert abs(st.sensors["gyr"].trend_per_min[0]) < 0.002


def test_nan_rows_are_ignored_per_sensor():
    t, gyr, acc, mag = stationary(TILTED, n=400)
    mag[::2] = np.nan          # magnetometer at half the rate
    acc[5, 1] = np.inf
    st = calibrate(t, gyr, acc, mag)
    assert st.sensors["mag"].n == 200 and st.sensors["acc"].n == 399
    np.testing.assert_allclose(st.sensors["mag"].mean, np.nanmean(mag, axis=0))


def test_moving_recording_is_flagged():
    t, gyr, acc, mag = stationary(TILTED, gyr_sigma=0.3)
    st = calibrate(t, gyr, acc, mag)
    assert not st.stationary
    assert any("gyroscope spread" in w for w in st.warnings)
    assert "WARNING" in format_report(st)
    fast = calibrate(t, gyr, acc * 1.5, mag)
    assert any("|mean acc|" in w for w in fast.warnings)
    short = calibrate(t[:10], gyr[:10], acc[:10], mag[:10], StationaryLimits(min_samples=20))
    assert any("only 10 samples" in w for w in short.warnings)


def test_a_short_movement_in_a_long_still_recording_is_flagged():
    """A phone slid across the table for one second of thirty: the whole recording's spread
    stayed under the limit (0.2 m/s² against 0.5), so it passed as stationary and its mean
    went into the preset. Each second's own spread says it; a still recording stays clean."""
    t, gyr, acc, mag = stationary(TILTED)
    assert calibrate(t, gyr, acc, mag).stationary
    moved = acc.copy()
    second = (t >= 12.0) & (t < 13.0)
    moved[second, 0] += 1.0 * np.sin(2 * np.pi * 2.0 * t[second])     # a slide, ±1 m/s²
    st = calibrate(t, gyr, moved, mag)
    assert np.max(st.sensors["acc"].std) < StationaryLimits().acc_std
    assert not st.stationary
    assert any("in the second from 12 s" in w for w in st.warnings), st.warnings


def test_a_field_that_changed_during_the_recording_is_not_stationary():
    """A magnet brought near a still phone (the demo's magnet scene): gyroscope and
    accelerometer said 'still', so a reviewer's calibration passed and set the lab
    filter's magnetometer noise to 15.6 µT and m0 from the disturbed field. A field whose
    spread is past any magnetometer's noise is now a warning, and so is one second of it."""
    t, gyr, acc, mag = stationary(TILTED)
    near = mag.copy()
    on = (t >= 10.0) & (t < 20.0)
    near[on] += [40.0, -10.0, 20.0]                     # 10 s of a magnet, then gone
    st = calibrate(t, gyr, acc, near)
    assert not st.stationary
    assert any("magnetometer spread" in w and "the field changed" in w for w in st.warnings)
    brief = mag.copy()
    s1 = (t >= 5.0) & (t < 6.0)
    brief[s1, 1] += 30.0 * np.sin(2 * np.pi * t[s1])     # one second of it
    st = calibrate(t, gyr, acc, brief)
    assert np.max(st.sensors["mag"].std) < StationaryLimits().mag_std
    assert any("in the second from 5 s" in w and "field changed" in w for w in st.warnings)
    # a phone magnetometer's own noise (up to 2 µT) stays clean
    noisy = mag + np.random.default_rng(3).normal(0.0, 2.0, mag.shape)
    assert calibrate(t, gyr, acc, noisy).stationary


def test_report_and_preset_load_with_load_config(tmp_path):
    t, gyr, acc, mag = stationary(TILTED)
    st = calibrate(t, gyr, acc, mag)
    report = format_report(st)
    for text in ("accelerometer (m/s²)", "gyroscope (rad/s)", "magnetometer (µT)",
                 "covariance", "normality p", "trend", "g0", "m0", "stationary: yes"):
        assert text in report
    path = tmp_path / "preset.toml"
    path.write_text(to_preset(st), encoding="utf-8")
    cfg = load_config(path)
    lab = cfg["lab"]
    np.testing.assert_allclose(lab["gyr_bias"], st.gyr_bias)
    np.testing.assert_allclose(lab["g0"], st.g0)
    np.testing.assert_allclose(lab["m0"], st.m0)
    np.testing.assert_allclose(lab["acc_cov"], st.sensors["acc"].cov.reshape(-1))
    np.testing.assert_allclose(lab["gyr_std"], math.sqrt(np.trace(st.sensors["gyr"].cov) / 3))
    np.testing.assert_allclose(cfg["robust"]["gyr_bias"], st.gyr_bias)
    # the statistics travel as comments
    assert "# gyroscope (rad/s)" in path.read_text(encoding="utf-8")


def test_preset_values_fit_parameter_ranges_and_skip_singular_covariance():
    t, gyr, acc, mag = stationary(TILTED, n=200)
    gyr[:] = 0.0                       # a quantised, perfectly still gyroscope
    st = calibrate(t, gyr, acc, mag)
    vals = preset_values(st)
    assert "gyr_cov" not in vals["lab"]
    assert vals["lab"]["gyr_std"] > 0.0        # raised to the parameter's minimum


def test_real_standstill_log(shared_dir, tmp_path):
    path = (shared_dir / "data" / "sensorfusion-app" / "alekodu_activityrecognition"
            / "sensorLog_20221024T182616_standstill.txt")
    if not path.is_file():
        pytest.skip("standstill log absent")
    rec = read_log_data(path)
    st = calibrate(rec.t, rec.gyr, rec.acc, rec.mag)
    assert set(st.sensors) == {"acc", "gyr", "mag"}
    assert st.sensors["acc"].n == 2635 and st.sensors["mag"].n == 712
    assert 9.5 < st.g0[2] < 10.3
    assert st.m0[0] == 0.0 and 20.0 < np.linalg.norm(st.m0) < 70.0 and st.m0[2] < 0
    assert np.all(np.abs(st.gyr_bias) < 0.05)
    # held in a hand: the report says it moved
    assert not st.stationary
    out = tmp_path / "real.toml"
    out.write_text(to_preset(st), encoding="utf-8")
    assert load_config(out)["lab"]["m0"][0] == 0.0
