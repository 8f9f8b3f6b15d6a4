"""``robust`` never stays lost: each failure mode seen on real phones, replayed from a real trial
(the smartphone attitude benchmark of Michel et al., ``../shared/data/phones-tyrex``; BROAD by
Laidig et al.; the shared app logs), and the flags that name what happened.

Skipped when ``../shared`` is absent. Each test runs a slice of a real recording (a few seconds of
compiled filter time)."""

from __future__ import annotations

import numpy as np
import pytest

from app.estimators import Reason, is_rejected, make_estimator
from app.estimators.base import F_ACC, F_ACC_VAL, F_GYR, F_MAG, F_MAG_VAL
from app.estimators.robust import S
from app.quaternion import error_angles, quat_mul
from app.sources.readers import read_log_data

DEG = 180.0 / np.pi


def _npz(shared_dir, folder, name, t, ref):
    """A trial of ``../shared/data/<folder>`` as float arrays; its times by ``t(d)``, its truth
    under the key ``ref``. Skipped when absent."""
    path = shared_dir / "data" / folder / f"{name}.npz"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    d = np.load(path)
    f = lambda k: np.ascontiguousarray(d[k], dtype=float)  # noqa: E731
    return dict(t=t(d), gyr=f("gyr"), acc=f("acc"), mag=f("mag"), ref=f(ref))


def _trial(shared_dir, name):
    return _npz(shared_dir, "phones-tyrex", name, lambda d: d["t"] - d["t"][0], "gt_quat")


def _broad(shared_dir, name):
    return _npz(shared_dir, "broad", name, lambda d: np.arange(d["gyr"].shape[0]) / float(d["fs"]),
                "opt_quat")


def _heading_err_deg(q, ref):
    ok = np.all(np.isfinite(ref), axis=1)
    out = np.full(len(q), np.nan)
    out[ok] = error_angles(q[ok], ref[ok])[1] * DEG
    return out


def _window(t, err, t0, t1):
    m = (t >= t0) & (t < t1) & np.isfinite(err)
    return err[m]


def _mag_refused(flags):
    codes = flags[:, F_MAG].astype(int)
    valid = codes != Reason.ABSENT
    rej = np.array([is_rejected(c) for c in codes])
    return float(np.mean(rej[valid]))


def test_field_reference_not_fixed_while_moving_at_the_start(shared_dir):
    """iPhone 4S, back pocket, undisturbed: the phone moves at the start, the field there reads
    35 µT and 42 µT for the rest of the trial. A reference taken from the first 2 s refused 97 % of
    the magnetometer and the heading drifted 78°. Now the first reference is a field stable for
    mag_first_field_time: the heading stays right and the field is not called disturbed."""
    tr = _trial(shared_dir, "iPhone4S_Guillaume_NoDist_backpocket")
    n = int(np.searchsorted(tr["t"], 60.0))
    res = make_estimator("robust").run(tr["t"][:n], tr["gyr"][:n], tr["acc"][:n], tr["mag"][:n])
    err = _heading_err_deg(res.q, tr["ref"][:n])
    assert np.sqrt(np.mean(_window(tr["t"][:n], err, 10.0, 60.0) ** 2)) < 10.0
    assert _mag_refused(res.flags) < 0.5


def test_running_with_the_phone_in_hand_keeps_heading(shared_dir):
    """Nexus 5, running, phone in hand: the field's norm swings ±8 % per stride while the gyroscope
    reaches 8-11 rad/s; a 6 % gate refused ~90 % of the field and the heading error climbed to 175°.
    Now the gates judge the low-passed strength and dip against a learned reference, and a long
    refusal resumes: the heading error stays bounded over the whole trial."""
    tr = _trial(shared_dir, "Nexus5_Guillaume_NoDist_runninghand")
    res = make_estimator("robust").run(tr["t"], tr["gyr"], tr["acc"], tr["mag"])
    err = _heading_err_deg(res.q, tr["ref"])
    late = _window(tr["t"], err, 10.0, 120.0)
    assert np.sqrt(np.mean(late ** 2)) < 15.0
    assert np.nanmax(late) < 45.0
    # the runner's strides are specific force: flagged, with the angle as the value
    acc = res.flags[:, F_ACC].astype(int)
    assert np.mean(acc[acc != Reason.ABSENT] == Reason.ACCEL) > 0.3
    vals = res.flags[acc == Reason.ACCEL, F_ACC_VAL]
    assert np.all(np.isfinite(vals)) and np.nanmax(vals) > np.radians(30.0)


@pytest.mark.parametrize("name", ["iPhone5_Guillaume_NoDist_texting", "Nexus5_Guillaume_NoDist_swinging"])
def test_heading_lost_mid_trial_is_noticed_and_recovered(shared_dir, name):
    """Whatever made the heading wrong (a saturated gyroscope, a bad start), an undisturbed field
    that disagrees with the estimate for long must win: replay a real trial, turn the estimate 120°
    about the vertical at 40 s, and check that the filter flags RECOVER (with the error as value)
    and is back under 10° within 15 s."""
    tr = _trial(shared_dir, name)
    t, k = tr["t"], int(np.searchsorted(tr["t"], 40.0))
    est = make_estimator("robust")
    first = est.run(t[:k], tr["gyr"][:k], tr["acc"][:k], tr["mag"][:k])
    a = np.radians(120.0)
    turn = np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])
    est._s[S.q:S.q + 4] = quat_mul(turn, est._s[S.q:S.q + 4])
    end = int(np.searchsorted(t, 70.0))
    rest = est.run(t[k:end], tr["gyr"][k:end], tr["acc"][k:end], tr["mag"][k:end])
    err = _heading_err_deg(rest.q, tr["ref"][k:end])
    tt = t[k:end]
    assert np.nanmax(_heading_err_deg(first.q, tr["ref"][:k])[t[:k] > 10]) < 20.0
    assert np.nanmean(_window(tt, err, 40.0, 40.5)) > 90.0          # lost indeed
    assert np.nanmax(_window(tt, err, 55.0, 70.0)) < 10.0            # back within 15 s
    mag = rest.flags[:, F_MAG].astype(int)
    rec = np.flatnonzero(mag == Reason.RECOVER)
    assert rec.size >= 1 and tt[rec[0]] < 50.0
    assert abs(rest.flags[rec[0], F_MAG_VAL]) > np.radians(30.0)  # the value is the error corrected


def test_heading_after_a_long_refusal_in_motion_corrects_at_once(shared_dir):
    """BROAD, a magnet attached 3 cm from the IMU while it turns at 4-5 rad/s: the field is
    refused for about 50 s and the gyroscope alone keeps the heading, which drifts by
    6-7° (its scale error times the turn). With the heading σ grown along the turn
    (refused_turn_noise), the first good field corrects it within seconds; with the
    covariance grown by the white gyroscope noise alone it took half a minute."""
    tr = _broad(shared_dir, "34_disturbed_attached_magnet_3cm")
    t = tr["t"]
    start, rms = {}, {}
    # (issue 19: by default the magnet's offset is now tracked and the field used, not refused;
    # the refusal this test replays is the filter without the offset tracking, and without the
    # field's delay compensation. The field's chance windows within the gates during the
    # magnet's 50 s, 33-82° off the gyroscope's heading, are refused by the return's innovation
    # test (flag NIS): the heading the refusal ends with is the gyroscope's drift alone)
    off = {"hard_iron_window": 0.0, "mag_delay": 0.0}
    for p in (off, {**off, "refused_turn_noise": 0.0}):
        res = make_estimator("robust", p).run(t, tr["gyr"], tr["acc"], tr["mag"])
        win = (t >= 85.0) & (t < 98.0)
        assert np.mean([is_rejected(c) for c in res.flags[win, F_MAG].astype(int)]) > 0.8
        during = res.flags[(t > 50.0) & (t < 100.0), F_MAG].astype(int)
        assert np.sum(during == Reason.NIS) > 20          # the chance windows, refused
        err = _heading_err_deg(res.q, tr["ref"])
        key = "refused_turn_noise" in p
        start[key] = float(np.sqrt(np.mean(_window(t, err, 95.0, 100.0) ** 2)))
        rms[key] = float(np.sqrt(np.mean(_window(t, err, 102.0, 112.0) ** 2)))
    assert start[False] > 4.0, start                   # the gyroscope's drift over the refusal
    # the defaults: most of it corrected within 2-12 s of the field's return ...
    assert rms[False] < 0.25 * start[False], (start, rms)
    # ... without: half of it still there
    assert rms[True] > 0.4 * start[True], (start, rms)


def test_implausible_bias_is_reset_and_flagged(shared_dir):
    """A bias estimate no phone has (here forced to 0.6 rad/s) means the filter is lost: the next
    row resets it and says so (gyr flag BIAS_RESET)."""
    tr = _trial(shared_dir, "iPhone5_Guillaume_NoDist_ar")
    est = make_estimator("robust")
    est.run(tr["t"][:1000], tr["gyr"][:1000], tr["acc"][:1000], tr["mag"][:1000])
    est._s[S.bias:S.bias + 3] = [0.0, 0.0, 0.6]
    res = est.run(tr["t"][1000:1010], tr["gyr"][1000:1010], tr["acc"][1000:1010], tr["mag"][1000:1010])
    assert res.flags[0, F_GYR] == Reason.BIAS_RESET
    assert np.linalg.norm(est.gyr_bias) < 0.1
    assert np.all(res.flags[1:, F_GYR] != Reason.BIAS_RESET)


def test_magnet_attached_is_flagged_and_a_standstill_log_is_not(shared_dir):
    """A magnet 1 cm from the IMU (BROAD, Laidig et al.) lights "mag disturbed" (NORM or DIP, with
    the value tested); an undisturbed real phone log lying still lights neither flag."""
    tr = _broad(shared_dir, "32_disturbed_attached_magnet_1cm")
    res = make_estimator("robust").run(tr["t"], tr["gyr"], tr["acc"], tr["mag"])
    mag = res.flags[:, F_MAG].astype(int)
    dist = np.isin(mag, [Reason.NORM, Reason.DIP])
    assert dist.mean() > 0.05
    assert np.all(np.isfinite(res.flags[dist, F_MAG_VAL]))
    log = shared_dir / "data" / "sensorfusion-app" / "alekodu_activityrecognition" / \
        "sensorLog_20221024T182616_standstill.txt"
    if not log.is_file():
        pytest.skip(f"{log} not present")
    r = read_log_data(log)
    res = make_estimator("robust").run(r.t, r.gyr, r.acc, r.mag)
    assert _mag_refused(res.flags) < 0.01
    acc = res.flags[:, F_ACC].astype(int)
    assert np.mean(acc[acc != Reason.ABSENT] == Reason.ACCEL) < 0.05


def test_a_shake_flags_acc_with_reason_and_value():
    """With the default robust, shaking a still phone (specific force of ±1 g at 5 Hz) lights
    "acc disturbed": Reason.ACCEL, counted as rejected, with the angle to gravity as the value."""
    fs, n = 100.0, 1000
    t = np.arange(n) / fs
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    shake = (t > 5.0) & (t < 7.0)
    acc[shake, 0] += 9.81 * np.sin(2 * np.pi * 5.0 * t[shake])
    gyr = np.zeros((n, 3))
    mag = np.tile([0.0, 20.0, -40.0], (n, 1))
    res = make_estimator("robust").run(t, gyr, acc, mag)
    a = res.flags[:, F_ACC].astype(int)
    assert np.mean(a[shake] == Reason.ACCEL) > 0.5
    assert np.all(a[(t > 2.0) & (t < 5.0)] != Reason.ACCEL)
    assert is_rejected(Reason.ACCEL) and is_rejected(int(Reason.ACCEL))
    assert np.nanmax(res.flags[shake & (a == Reason.ACCEL), F_ACC_VAL]) > np.radians(20.0)


def _tilted_still_phone(n=6000, fs=100.0, seed=0):
    """A phone lying still, tilted 20° about x and turned 30° about the vertical, with sensor
    noise: (t, gyr, acc, mag, the truth)."""
    from app.quaternion import quat_from_rotvec, rotate_inv_many
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    q = quat_mul(quat_from_rotvec(np.array([0.0, 0.0, np.radians(30.0)])),
                 quat_from_rotvec(np.array([np.radians(20.0), 0.0, 0.0])))
    Q = np.tile(q, (n, 1))
    acc = rotate_inv_many(Q, np.tile([0.0, 0.0, 9.81], (n, 1))) + rng.normal(0.0, 0.05, (n, 3))
    mag = rotate_inv_many(Q, np.tile([0.0, 20.0, -40.0], (n, 1))) + rng.normal(0.0, 0.5, (n, 3))
    gyr = rng.normal(0.0, 0.005, (n, 3))
    return t, gyr, acc, mag, Q


def _first_rows_negated(acc, t, seconds):
    a = acc.copy()
    a[t < seconds] *= -1.0
    return a


def test_a_start_upside_down_is_realigned():
    """The first 0.4 s of the accelerometer with the wrong sign (a Sensor Logger iPhone before its
    sign convention is detected) aligned robust upside down, and it stayed there for good: the
    tilt update's innovation, the low-passed gravity's horizontal part, vanishes upside down as
    upright, and the accelerometer said "used" all along. Now gravity below the horizon re-aligns
    the filter (acc flag RECOVER, with the angle), and a normal start never does."""
    t, gyr, acc, mag, truth = _tilted_still_phone()
    res = make_estimator("robust").run(t, gyr, _first_rows_negated(acc, t, 0.4), mag)
    total = error_angles(res.q, truth)[0] * DEG
    assert np.max(total[t > 5.0]) < 2.0
    a = res.flags[:, F_ACC].astype(int)
    rec = np.flatnonzero(a == Reason.RECOVER)
    assert len(rec) == 1 and t[rec[0]] < 2.0
    assert res.flags[rec[0], F_ACC_VAL] > np.radians(90.0)
    clean = make_estimator("robust").run(t, gyr, acc, mag)
    assert np.max(error_angles(clean.q, truth)[0][t > 5.0] * DEG) < 2.0
    assert not np.any(clean.flags[:, F_ACC].astype(int) == Reason.RECOVER)


def test_a_real_trial_started_upside_down_is_realigned(shared_dir):
    """The same on a real phone in a back pocket (phones-tyrex): the first 0.4 s negated left
    robust 177-180° off for the whole minute; now it is back to the clean start's error within
    2 s, and the bias learned meanwhile is kept."""
    tr = _trial(shared_dir, "iPhone4S_Guillaume_NoDist_backpocket")
    n = int(np.searchsorted(tr["t"], 60.0))
    t, gyr, acc, mag, ref = (tr[k][:n] for k in ("t", "gyr", "acc", "mag", "ref"))
    ok = np.all(np.isfinite(ref), axis=1)
    clean = make_estimator("robust").run(t, gyr, acc, mag)
    flipped = make_estimator("robust").run(t, gyr, _first_rows_negated(acc, t, 0.4), mag)
    e_clean = error_angles(clean.q[ok], ref[ok])[2] * DEG
    e_flip = error_angles(flipped.q[ok], ref[ok])[2] * DEG
    late = t[ok] > 3.0
    assert np.sqrt(np.mean(e_flip[late] ** 2)) < np.sqrt(np.mean(e_clean[late] ** 2)) + 2.0
    assert np.sum(flipped.flags[:, F_ACC].astype(int) == Reason.RECOVER) == 1
