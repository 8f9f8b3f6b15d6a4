"""Virtual magnet and shake (app/toolkit/inject.py): what they add to the lines, their marks,
and what the estimators make of them on a real still phone."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

from app.estimators import REJECTIONS, make_estimator
from app.estimators.base import F_MAG, F_MAG_VAL, Reason
from app.toolkit.inject import InjectError, Injector, inject_at, marks_in_log, parse_request
from app.sources.sensorfusion import decode_lines, format_line, parse_line
from app.quaternion import Q, error_angles, quat_from_rotvec
from app.sources.readers import rows_of_lines
from app.toolkit.variants import no_rejection_changes


def _dec(lines):
    return decode_lines(lines, Counter())


def _feed(inj, lines):
    """The injector on the samples of these lines; the result as lines again."""
    out, marks = inj.feed(decode_lines(lines, Counter()))
    return [format_line(s.time_ms, s.tag, s.values).encode() for s in out], marks


def _lines(seconds=4.0, mag=(10.0, 20.0, -40.0), acc=(0.0, 0.0, 9.81)):
    out = []
    for k in range(int(seconds * 100)):
        ms = 1000 + 10 * k
        out.append(f"{ms}\tACC\t{acc[0]}\t{acc[1]}\t{acc[2]}".encode())
        if k % 2 == 0:
            out.append(f"{ms + 3}\tMAG\t{mag[0]}\t{mag[1]}\t{mag[2]}".encode())
        out.append(f"{ms + 5}\tGYR\t0.01\t0.0\t0.0".encode())
    return out


def test_requests_are_validated_with_the_field_named():
    d = parse_request({"kind": "magnet", "strength_uT": 50, "direction": "east", "seconds": 3})
    assert d.kind == "magnet" and d.frame == "world" and d.direction == (1.0, 0.0, 0.0)
    assert parse_request({"kind": "shake", "amplitude_ms2": 5, "seconds": 2}).frame == "sensor"
    for body, field in [({"kind": "laser"}, "kind"),
                        ({"kind": "magnet", "seconds": 3}, "strength_uT"),
                        ({"kind": "magnet", "strength_uT": "x", "seconds": 3}, "strength_uT"),
                        ({"kind": "magnet", "strength_uT": 50, "seconds": -1}, "seconds"),
                        ({"kind": "magnet", "strength_uT": 50, "seconds": 1, "direction": [0, 0, 0]}, "direction"),
                        ({"kind": "magnet", "strength_uT": 50, "seconds": 1, "frame": "moon"}, "frame"),
                        ({"kind": "shake", "amplitude_ms2": 5, "seconds": 1, "strength_uT": 3}, "strength_uT"),
                        ({"kind": "magnet", "strength_uT": math.nan, "seconds": 1}, "strength_uT")]:
        with pytest.raises(InjectError) as e:
            parse_request(body)
        assert e.value.field == field


def test_magnet_in_the_sensor_frame_adds_its_field_for_its_seconds_only():
    lines = _lines()
    inj = Injector()
    before, _ = _feed(inj, lines[:90])                 # nothing requested: unchanged
    assert _dec(before) == _dec(lines[:90])
    inj.start(parse_request({"kind": "magnet", "strength_uT": 50, "direction": [0, 0, 1],
                             "frame": "sensor", "seconds": 1.0}))
    out, marks = _feed(inj, lines[90:])
    assert [m["event"] for m in marks] == ["start", "end"]
    assert not inj.busy
    mags = [parse_line(ln) for ln in out if b"\tMAG\t" in ln]
    changed = [s for s in mags if abs(s.values[2] + 40.0) > 1e-6]
    assert changed and all(abs(s.values[2] - 10.0) < 1e-4 for s in changed)    # -40 + 50
    span = (changed[-1].time_ms - changed[0].time_ms) / 1000.0
    assert 0.95 <= span <= 1.0
    assert all(s.values[:2] == (10.0, 20.0) for s in changed)
    # ACC/GYR untouched, marks are TXT lines of the app's format at their place
    assert _dec([ln for ln in out if b"\tACC\t" in ln]) == _dec([ln for ln in lines[90:] if b"\tACC\t" in ln])
    txt = marks_in_log(out)
    assert len(txt) == 2 and txt[0]["text"].startswith("magnet 50 uT")
    assert txt[0]["time_ms"] == changed[0].time_ms


def test_world_frame_magnet_turns_with_the_phone():
    q = quat_from_rotvec(np.array([0.0, 0.0, math.pi / 2]))     # turned 90° about up
    inj = Injector(orientation=lambda: q)
    inj.start(parse_request({"kind": "magnet", "strength_uT": 30, "direction": "east",
                             "seconds": 0.5}))
    out, _ = _feed(inj, _lines(1.0))
    s = next(parse_line(ln) for ln in out if b"\tMAG\t" in ln)
    added = np.array(s.values) - np.array([10.0, 20.0, -40.0])
    np.testing.assert_allclose(added, Q(q).T @ np.array([30.0, 0, 0]), atol=1e-4)
    assert inj.history[-1].frame_used == "world"


def test_shake_adds_a_sinusoid_to_the_accelerometer():
    inj = Injector()
    inj.start(parse_request({"kind": "shake", "amplitude_ms2": 8, "seconds": 2,
                             "frequency_hz": 2, "ramp_s": 0}))
    out, _ = _feed(inj, _lines(3.0))
    acc = np.array([parse_line(ln).values for ln in out if b"\tACC\t" in ln])
    dx = acc[:, 0]
    assert 7.9 < dx.max() <= 8.0 and -8.0 <= dx.min() < -7.9
    np.testing.assert_allclose(acc[:, 1:], [[0.0, 9.81]] * len(acc), atol=1e-6)


def test_primary_rides_out_a_50uT_magnet_and_the_no_rejection_variant_does_not(shared_dir):
    """A real still phone (standstill log) with a 50 µT magnet for 5 s: with the
    defaults the primary refuses it and its heading moves < 3°; the same filter with
    every gate off turns by tens of degrees."""
    path = (shared_dir / "data" / "sensorfusion-app" / "alekodu_activityrecognition"
            / "sensorLog_20221024T182616_standstill.txt")
    lines = path.read_bytes().splitlines()
    out, on, off = inject_at(lines, {"kind": "magnet", "strength_uT": 50, "direction": "x",
                                     "frame": "sensor", "seconds": 5}, 6.0)
    assert [m["text"].split()[-3] for m in marks_in_log(out)] == ["start", "end"]
    assert off - on == pytest.approx(5.0, abs=0.05)
    clean, dist = rows_of_lines(lines), rows_of_lines(out)
    w = (dist.t >= dist.t[0] + 6.0) & (dist.t <= dist.t[0] + 13.0)
    moved = {}
    for name, params in (("robust", {}), ("robust-no-rejection", no_rejection_changes("robust"))):
        a = make_estimator("robust", params).run(clean.t, clean.gyr, clean.acc, clean.mag, clean.ori)
        b = make_estimator("robust", params).run(dist.t, dist.gyr, dist.acc, dist.mag, dist.ori)
        _, heading, _ = error_angles(b.q[w], a.q[w])
        moved[name] = math.degrees(heading.max())
        if name == "robust":
            mag_rows = b.flags[w][~np.isnan(dist.mag[w, 0]), F_MAG].astype(int)
            in_magnet = mag_rows[5:200]     # MAG at ~50 Hz: the first 4 s of the magnet
            assert np.mean(np.isin(in_magnet, [int(r) for r in REJECTIONS])) > 0.9
    assert moved["robust"] < 3.0, moved
    assert moved["robust-no-rejection"] > 20.0, moved


STILL = ("alekodu_activityrecognition", "sensorLog_20221024T182616_standstill.txt")
# a 50 µT magnet along each of the phone's axes (stuck on it) and each compass direction
# (lying on the desk; the still phone's orientation turns it into the sensor frame)
DIRECTIONS = [("x", "sensor"), ("-x", "sensor"), ("y", "sensor"), ("-y", "sensor"),
              ("z", "sensor"), ("-z", "sensor"), ("east", "world"), ("north", "world"),
              ("west", "world"), ("south", "world")]


@pytest.fixture(scope="module")
def still(request):
    from conftest import SHARED
    path = SHARED / "data" / "sensorfusion-app" / STILL[0] / STILL[1]
    if not path.is_file():
        pytest.skip(f"{path} not present")
    lines = path.read_bytes().splitlines()
    clean = rows_of_lines(lines)
    ref = make_estimator("robust").run(clean.t, clean.gyr, clean.acc, clean.mag, clean.ori)
    return lines, clean, ref


def _with_magnet(still, direction, frame, ramp_s):
    """The real still phone's rows with a 50 µT magnet from 6 s to 11 s (the Injector
    given the phone's true orientation then, for a magnet fixed in the world), and the
    magnet's start and end (stream s)."""
    lines, clean, ref = still
    q_then = ref.q[np.searchsorted(clean.t, clean.t[0] + 6.0)]
    out, on, off = inject_at(lines, {"kind": "magnet", "strength_uT": 50, "direction": direction,
                                     "frame": frame, "seconds": 5, "ramp_s": ramp_s},
                             6.0, orientation=lambda: q_then)
    return rows_of_lines(out), on, off


def _magnet_effect(still, direction, frame, ramp_s):
    """A 50 µT magnet from 6 s to 11 s of the real still phone: how far the primary's
    heading moves from where it goes without the magnet, during the magnet and the
    second after (deg), and the share of MAG samples it refuses once the magnet is in."""
    _, clean, ref = still
    dist, on, off = _with_magnet(still, direction, frame, ramp_s)
    b = make_estimator("robust").run(dist.t, dist.gyr, dist.acc, dist.mag, dist.ori)
    np.testing.assert_array_equal(dist.t, clean.t)        # the same rows, MAG disturbed
    w = (dist.t >= on) & (dist.t <= off + 1.0)
    _, heading, _ = error_angles(b.q[w], ref.q[w])
    full = (dist.t >= on + ramp_s + 0.1) & (dist.t <= off - ramp_s) & ~np.isnan(dist.mag[:, 0])
    refused = np.isin(b.flags[full, F_MAG].astype(int), [int(r) for r in REJECTIONS]).mean()
    return math.degrees(np.abs(heading).max()), float(refused)


@pytest.mark.parametrize("direction, frame", DIRECTIONS, ids=[f"{f}-{d}" for d, f in DIRECTIONS])
def test_primary_flags_and_rides_out_a_50uT_magnet_from_any_direction(still, direction, frame):
    """Issue 9's claim with the defaults: a 50 µT magnet put down at once is flagged and
    the heading moves < 3° (most of what it moves is the gyroscope's drift while the
    heading waits for an undisturbed field)."""
    moved, refused = _magnet_effect(still, direction, frame, ramp_s=0.0)
    assert refused > 0.9, refused
    assert moved < 3.0, moved


def test_primary_rides_out_a_50uT_magnet_brought_in_over_half_a_second(still):
    """Brought in over 0.5 s, the magnet turns the horizontal field by tens of degrees before
    its strength or dip leave their gates (~0.3 s); the field turn test (the world-frame
    field changes while the gyroscope says the phone is still) refuses it from the start."""
    moved = {f"{f} {d}": _magnet_effect(still, d, f, ramp_s=0.5)[0] for d, f in DIRECTIONS}
    assert max(moved.values()) < 3.0, moved


def test_a_ramped_magnet_is_first_refused_as_a_field_turning_without_the_phone(still):
    """The flag says why: the first refusal of the ramped magnet is TURN, with the
    unexplained change rate (rad/s) above the gate, before strength or dip leave theirs;
    without the turn test (mag_turn_gate 0) the same ramp is refused later, by NORM or DIP,
    and the heading moves more."""
    dist, on, _ = _with_magnet(still, "-x", "sensor", ramp_s=0.5)
    first = {}
    for name, params in (("turn", {}), ("off", {"mag_turn_gate": 0.0})):
        est = make_estimator("robust", params)
        b = est.run(dist.t, dist.gyr, dist.acc, dist.mag, dist.ori)
        rows = np.nonzero((dist.t >= on) & ~np.isnan(dist.mag[:, 0])
                          & np.isin(b.flags[:, F_MAG].astype(int), [int(r) for r in REJECTIONS]))[0]
        first[name] = (dist.t[rows[0]] - on, int(b.flags[rows[0], F_MAG]), b.flags[rows[0], F_MAG_VAL])
    t_turn, code, value = first["turn"]
    assert code == int(Reason.TURN) and value > make_estimator("robust").params.mag_turn_gate, first
    t_off, code_off, _ = first["off"]
    assert code_off in (int(Reason.NORM), int(Reason.DIP)) and t_off > t_turn + 0.05, first


def test_a_real_field_is_not_called_turned_while_the_phone_walks_or_runs(real_log_9dof):
    """The turn test's other side: on the real app logs (standstill to running, turn rates
    up to ~18 rad/s, beyond a phone gyroscope's range) the field is never flagged TURN."""
    from app.sources.readers import read_log_data
    r = read_log_data(real_log_9dof)
    assert (~np.isnan(r.mag[:, 0])).sum() > 100 and (~np.isnan(r.gyr[:, 0])).sum() > 100
    res = make_estimator("robust").run(r.t, r.gyr, r.acc, r.mag)
    judged = np.isin(res.flags[:, F_MAG].astype(int), [int(Reason.USED)] + [int(x) for x in REJECTIONS])
    assert judged.sum() > 100                     # the field was judged, not waited out
    assert not np.any(res.flags[:, F_MAG] == int(Reason.TURN))


def test_the_turn_test_is_off_without_a_gyroscope(still):
    """Without a gyroscope the estimate's world frame does not turn with the phone: every
    turn would look like a field turning, so the test stays off (and with the gate at 0)."""
    d, _, _ = _with_magnet(still, "-x", "sensor", ramp_s=0.5)
    for params in ({}, {"use_gyr": False}, {"mag_turn_gate": 0.0}):
        codes = make_estimator("robust", params).run(d.t, d.gyr, d.acc, d.mag, d.ori).flags[:, F_MAG]
        assert np.any(codes == int(Reason.TURN)) == (params == {}), params
