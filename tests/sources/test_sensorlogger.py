"""Sensor Logger's push messages -> samples (app.sources.sensorlogger).

The format: shared/protocols/sensor-logger.md. Real phones: the phones-tyrex trials
(shared/data/phones-tyrex, T. Michel et al., CeCILL 2.1) turned into the bodies the app
would push (tests/sources/tyrex_sensorlogger.py)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from app.sources.samples import Sample
from app.sources.sensorlogger import NO_ORI_AFTER, Batch, SensorLoggerError, SensorLoggerStream

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tyrex_sensorlogger as tx  # noqa: E402

# ---------------------------------------------------------------- the note's examples

ANDROID_EXAMPLE = b"""{"messageId": 12,
 "sessionId": "3f1c2a9e-5b7d-4c11-9a0e-2d6f8b1c4e77",
 "deviceId": "a8d4e0c2-61f3-4b9a-b7d5-0c9e2f4a6b13",
 "payload": [
  {"name": "gyroscope", "time": 1760000000013001000, "accuracy": 3, "values": {"z": 0.0003, "y": -0.0007, "x": 0.0011}},
  {"name": "totalacceleration", "time": 1760000000012345600, "accuracy": 3, "values": {"z": 9.8124, "y": -0.1187, "x": 0.0431}},
  {"name": "accelerometer", "time": 1760000000014912000, "accuracy": 3, "values": {"z": 0.0207, "y": -0.0094, "x": 0.0112}},
  {"name": "gravity", "time": 1760000000014912000, "accuracy": 3, "values": {"z": 9.8059, "y": -0.1093, "x": 0.0319}},
  {"name": "magnetometer", "time": 1760000000020480000, "accuracy": 3, "values": {"z": -47.9, "y": 0.8, "x": 15.2}},
  {"name": "orientation", "time": 1760000000014912000, "accuracy": 3, "values": {"qw": 0.9999, "qx": 0.0056, "qy": -0.0016, "qz": 0.0004, "yaw": 0.0008, "pitch": 0.0112, "roll": -0.0033}}
 ]}"""

IOS_EXAMPLE = b"""{"messageId": 40, "sessionId": "0ba5f3e8-0000-4c40-b9ea-95d7ed4d1132", "deviceId": "8b5937fb-0000-4825-ba40-4bc646f93839",
 "payload": [
  {"name": "gravity", "time": 1760000000010000000, "values": {"z": -9.8061, "y": 0.1093, "x": -0.0319}},
  {"name": "accelerometer", "time": 1760000000010000000, "values": {"z": -0.0110, "y": 0.0081, "x": -0.0042}},
  {"name": "gyroscope", "time": 1760000000010000000, "values": {"z": 0.0002, "y": -0.0009, "x": 0.0013}},
  {"name": "magnetometer", "time": 1760000000010000000, "accuracy": 2, "values": {"z": -47.7, "y": 0.6, "x": 15.4}},
  {"name": "orientation", "time": 1760000000010000000, "values": {"qw": 0.9999, "qx": -0.0056, "qy": 0.0016, "qz": 0.0004, "yaw": 0.0011, "pitch": -0.0112, "roll": 0.0033}}
 ]}"""

T0 = 1_760_000_000_000_000_000


def body(payload, mid=1, session="s-1", device="d-1", **extra) -> bytes:
    return json.dumps({"messageId": mid, "sessionId": session, "deviceId": device,
                       "payload": payload, **extra}).encode()


def rd(name, t_ns, accuracy=None, **values):
    r = {"name": name, "time": t_ns, "values": values}
    if accuracy is not None:
        r["accuracy"] = accuracy
    return r


def stream(**kw) -> SensorLoggerStream:
    """A stream that releases at once: what these tests check does not depend on the wait
    for the accelerometer's sign at a session's start (its own tests say start_hold)."""
    return SensorLoggerStream(start_hold_s=kw.pop("start_hold_s", 0.0), **kw)


def by_tag(samples, tag):
    return [s for s in samples if s.tag == tag]


def face_up_ios(n, t_start=T0, standardised=False, dt_ns=10_000_000, raw_g=None):
    """n iOS readings of a phone lying face up, y to magnetic north (northern dip)."""
    s = 1.0 if standardised else -1.0
    out = []
    for i in range(n):
        t = t_start + i * dt_ns
        out += [rd("gravity", t, x=0.0, y=0.0, z=s * 9.80665),
                rd("accelerometer", t, x=0.0, y=0.0, z=s * 0.01),
                rd("gyroscope", t, x=0.001, y=0.0, z=0.0),
                rd("magnetometer", t, accuracy=2, x=0.5, y=20.0, z=-40.0)]
        if raw_g is not None:
            out.append(rd("accelerometeruncalibrated", t, x=0.0, y=0.0, z=raw_g))
    return out


# ---------------------------------------------------------------- parsing

def test_android_example_from_the_note():
    st = stream()
    b = st.decode(ANDROID_EXAMPLE, now=100.0)
    assert isinstance(b, Batch) and b.new_session
    tags = [s.tag for s in b.samples]
    assert sorted(tags) == ["ACC", "GYR", "MAG"]          # ORI: not yet checked
    assert [s.time_ms for s in b.samples] == sorted(s.time_ms for s in b.samples)
    acc = by_tag(b.samples, "ACC")[0]
    assert acc.values == (0.0431, -0.1187, 9.8124)         # totalacceleration as is
    assert acc.time_ms == pytest.approx(1760000000012.3456, abs=1e-3)
    assert by_tag(b.samples, "GYR")[0].values == (0.0011, -0.0007, 0.0003)
    assert by_tag(b.samples, "MAG")[0].values == (15.2, 0.8, -47.9)
    s = st.status()
    assert s["platform"] == "android" and s["convention"] == "android"
    assert s["convention_source"] == "detected"
    assert s["sources"]["ACC"] == "totalacceleration"
    assert s["unused"]["accelerometer"] == 1 and s["unused"]["gravity"] == 1
    assert s["orientation"]["state"] in ("unchecked", "checking")
    assert "not yet checked" in s["orientation"]["message"]
    assert s["messages"] == 1 and s["gaps"] == 0
    assert s["device_id"].startswith("a8d4e0c2") and len(s["device_id"]) <= 9
    json.dumps(s, allow_nan=False)


def test_ios_example_from_the_note_is_negated_by_default():
    st = stream()
    b = st.decode(IOS_EXAMPLE, now=5.0)
    acc = by_tag(b.samples, "ACC")[0]
    # Standardise off (the app's default): f = -(accelerometer + gravity), +9.81 face up
    assert acc.values == pytest.approx((0.0319 + 0.0042, -0.1093 - 0.0081, 9.8061 + 0.0110))
    s = st.status()
    assert s["platform"] == "ios"
    assert any("share timestamps" in r for r in s["reasons"])
    assert s["convention"] == "ios" and s["convention_source"] == "assumed"
    assert s["sources"]["ACC"] == "accelerometer+gravity"
    assert {x.tag for x in b.samples} == {"ACC", "GYR", "MAG"}
    assert len({x.time_ms for x in b.samples}) == 1


def test_empty_payload_is_a_message():
    st = stream()
    b = st.decode(body([]), now=0.0)
    assert b.samples == [] and b.new_session
    assert st.status()["messages"] == 1


def test_userid_accuracy_absent_or_present_give_the_same_values():
    with_acc = [rd("gyroscope", T0, accuracy=3, x=0.1, y=0.2, z=0.3)]
    without = [rd("gyroscope", T0, x=0.1, y=0.2, z=0.3)]
    a = stream().decode(body(with_acc, userId="study-7"), 0.0).samples
    b = stream().decode(body(without), 0.0).samples
    assert a == b == [Sample(T0 / 1e6, "GYR", (0.1, 0.2, 0.3))]


def test_bad_readings_are_counted_and_the_rest_kept():
    st = stream()
    payload = [
        {"name": "test", "time": T0, "values": {"x": 1}},           # the app's test push
        rd("barometer", T0, pressure=1013.2, relativeAltitude=0.1),  # unknown here
        rd("Wrist Motion", T0, x=1.0),
        {"name": "gyroscope", "time": T0 + 1},                       # no values
        {"name": "gyroscope", "values": {"x": 0.0, "y": 0.0, "z": 0.0}},  # no time
        rd("gyroscope", "soon", x=0.0, y=0.0, z=0.0),
        rd("gyroscope", T0 + 2, x="0.1", y=0.0, z=0.0),             # text, not a number
        rd("gyroscope", T0 + 3, x=True, y=0.0, z=0.0),
        rd("gyroscope", T0 + 4, x=0.0, y=0.0),                       # z missing
        "not a reading",
        {"time": T0, "values": {}},                                  # no name
        rd("GYROSCOPE", T0 + 5, x=0.5, y=0.0, z=0.0),                # case: accepted
        rd("gyroscope", T0 + 6, x=0.6, y=0.0, z=0.0),
    ]
    b = st.decode(body(payload), 0.0)
    assert [s.values[0] for s in b.samples] == [0.5, 0.6]
    s = st.status()
    assert s["ignored"] == {"test": 1, "barometer": 1, "wrist motion": 1}
    assert s["invalid"] == {"no_values": 1, "no_time": 1, "bad_time": 1, "not_numeric": 2,
                            "missing_axis": 1, "bad_reading": 1, "no_name": 1}


def test_a_message_is_read_apart_from_the_stream_then_taken_as_decode_would():
    """read() (the part the server runs on a worker thread) touches no state of the
    stream; take() of what it read gives what decode() gives, counters included; a
    duplicate's bad readings are not counted twice."""
    payload = [rd("gyroscope", T0 + k * 10_000_000, x=0.1 * k, y=0.0, z=0.0) for k in range(5)]
    payload += [rd("barometer", T0, pressure=1013.2), rd("gyroscope", "soon", x=0.0, y=0.0, z=0.0),
                rd("gyroscope", T0 + 99, x=float("nan"), y=0.0, z=0.0)]
    raw = body(payload, mid=7)
    whole, apart = stream(), stream()
    before = json.dumps(apart.status(), sort_keys=True)
    read = SensorLoggerStream.read(raw)
    read_again = apart.read(raw)
    assert json.dumps(apart.status(), sort_keys=True) == before    # nothing seen yet
    assert read.key == ("d-1", "s-1") and read.mid == 7
    a = whole.decode(raw, 5.0)
    b = apart.take(read, 5.0)
    assert [(s.tag, s.time_ms, s.values) for s in a.samples] == \
           [(s.tag, s.time_ms, s.values) for s in b.samples]
    assert len(b.samples) == 5
    assert whole.status() == apart.status()
    assert apart.status()["invalid"] == {"bad_time": 1, "not_finite": 1}
    assert apart.status()["ignored"] == {"barometer": 1}
    # the same message again is a duplicate: dropped whole, its bad readings not counted
    assert apart.take(read_again, 5.1).samples == []
    assert apart.status()["duplicates"] == 1
    assert apart.status()["invalid"] == {"bad_time": 1, "not_finite": 1}
    # what read refuses is counted by the stream only when told
    with pytest.raises(SensorLoggerError) as e:
        SensorLoggerStream.read(b"[1, 2]")
    assert apart.status()["rejected"] == {}
    apart.count_rejected(e.value)
    assert apart.status()["rejected"] == {"bad_shape": 1}


def test_nan_inf_and_absurd_values_are_counted_and_skipped():
    st = stream()
    text = ('{"messageId": 1, "sessionId": "s", "deviceId": "d", "payload": ['
            f'{{"name": "gyroscope", "time": {T0}, "values": {{"x": NaN, "y": 0, "z": 0}}}},'
            f'{{"name": "gyroscope", "time": {T0 + 1000}, "values": {{"x": Infinity, "y": 0, "z": 0}}}},'
            f'{{"name": "gyroscope", "time": {T0 + 2000}, "values": {{"x": 1e9, "y": 0, "z": 0}}}},'
            f'{{"name": "gyroscope", "time": {T0 + 3000}, "values": {{"x": 0.25, "y": 0, "z": 0}}}},'
            f'{{"name": "magnetometeruncalibrated", "time": {T0}, "values": {{"x": -2455.0, "y": 10, "z": 3}}}},'
            f'{{"name": "magnetometeruncalibrated", "time": {T0 + 5000}, "values": {{"x": -45.0, "y": 10, "z": 3}}}},'
            f'{{"name": "orientation", "time": {T0}, "values": {{"qw": 3.0, "qx": 0, "qy": 0, "qz": 0}}}},'
            f'{{"name": "totalacceleration", "time": {T0}, "values": {{"x": 0, "y": 0, "z": 1e5}}}},'
            f'{{"name": "gyroscope", "time": {T0 + 4000}, "values": {{"x": 1{"0" * 400}, "y": 0, "z": 0}}}}'
            ']}').encode()
    b = st.decode(text, 0.0)
    assert [(s.tag, s.values) for s in b.samples] == [("GYR", (0.25, 0.0, 0.0)),
                                                      ("MAG", (-45.0, 10.0, 3.0))]
    inv = st.status()["invalid"]
    assert inv == {"not_finite": 2, "impossible": 5}
    assert st.status()["sources"]["MAG"] == "magnetometeruncalibrated"


@pytest.mark.parametrize("raw, reason", [
    (b"{not json", "bad_json"),
    (b"\xff\xfe\x00garbage", "bad_json"),
    (b"", "bad_json"),
    (b"[1, 2, 3]", "bad_shape"),
    (b'"payload"', "bad_shape"),
    (b'{"messageId": 1, "sessionId": "s"}', "bad_shape"),
    (b'{"messageId": 1, "payload": {"name": "gyroscope"}}', "bad_shape"),
    (b'{"messageId": 1, "payload": "' + b"x" * 100_000 + b'"}', "bad_shape"),
    (b'{"payload": [' + b"x" * 100_000 + b"]}", "bad_json"),
])
def test_malformed_messages_raise_with_a_reason(raw, reason):
    st = stream()
    with pytest.raises(SensorLoggerError) as e:
        st.decode(raw, 0.0)
    assert e.value.reason == reason
    assert isinstance(e.value, ValueError)
    assert len(str(e.value)) <= 100          # never echoes a large body
    assert st.status()["rejected"] == {reason: 1}
    # the stream still works afterwards
    assert st.decode(body([rd("gyroscope", T0, x=0.0, y=0.0, z=0.0)]), 0.0).samples


def test_nineteen_digit_times_keep_sub_ms_precision():
    st = stream()
    payload = [rd("gyroscope", T0 + 12_345_600 + k * 1000, x=float(k), y=0.0, z=0.0)
               for k in (2, 0, 1, 1)]      # unsorted, with an exact duplicate time
    b = st.decode(body(payload), 0.0)
    times = [s.time_ms for s in b.samples]
    assert [s.values[0] for s in b.samples] == [0.0, 1.0, 2.0]
    for k, t in enumerate(times):
        assert t == pytest.approx(1760000000012.3456 + k * 0.001, abs=5e-4)
    assert times[0] < times[1] < times[2]
    assert st.status()["invalid"] == {"duplicate_time": 1}


def test_a_reading_sent_again_in_a_later_message_is_dropped():
    """The note: drop exact duplicate times per sensor. Within one release they were; a
    reading sent again in the next message (a push repeated under a new messageId) went
    through twice, two samples at one time."""
    st = stream()
    first = [rd("gyroscope", T0 + k * 10_000_000, x=float(k), y=0.0, z=0.0) for k in range(5)]
    again = first[3:] + [rd("gyroscope", T0 + k * 10_000_000, x=float(k), y=0.0, z=0.0)
                         for k in range(5, 8)]
    out = st.decode(body(first, mid=1), 0.0).samples + st.decode(body(again, mid=2), 0.1).samples
    out += st.flush()
    gyr = [x for x in out if x.tag == "GYR"]
    assert [x.values[0] for x in gyr] == [float(k) for k in range(8)]
    assert st.status()["invalid"] == {"duplicate_time": 2}


# ---------------------------------------------------------------- message order

def gyro_msg(mid, k, session="s-1", device="d-1"):
    """Message ``mid`` holds the gyro readings of second k (two of them)."""
    return body([rd("gyroscope", T0 + k * 10**9 + 500_000_000, x=k + 0.5, y=0.0, z=0.0),
                 rd("gyroscope", T0 + k * 10**9, x=float(k), y=0.0, z=0.0)],
                mid=mid, session=session, device=device)


def test_in_order_messages_are_released_at_once():
    st = stream()
    for mid in (4, 5, 6):
        out = st.decode(gyro_msg(mid, mid), now=float(mid)).samples
        assert [s.values[0] for s in out] == [mid, mid + 0.5]
    assert st.status()["gaps"] == st.status()["out_of_order"] == 0


def test_message_ahead_of_a_missing_one_is_held_then_merged_in_time_order():
    st = stream()
    st.decode(gyro_msg(4, 4), now=0.0)
    assert st.decode(gyro_msg(6, 6), now=0.1).samples == []          # 5 missing: held
    assert st.status()["held"] == 1
    out = st.decode(gyro_msg(5, 5), now=0.2).samples                 # 5 after 6
    assert [s.values[0] for s in out] == [5, 5.5, 6, 6.5]
    s = st.status()
    assert s["out_of_order"] == 1 and s["gaps"] == 0 and s["held"] == 0


def test_first_message_then_an_older_one_is_late_not_lost():
    st = stream()
    assert len(st.decode(gyro_msg(6, 6), now=0.0).samples) == 2
    out = st.decode(gyro_msg(5, 5), now=0.1).samples
    assert [s.values[0] for s in out] == [5, 5.5]
    assert st.status()["out_of_order"] == 1 and st.status()["late"] == 1


def test_a_message_seconds_late_keeps_only_what_is_not_seconds_behind():
    """A message whose place was given up, arriving after seconds of newer ones: its
    readings more than 2 s behind the newest released would make the orderer take the
    phone's clock for stepped back (and move the stream's time on by seconds for good).
    They are dropped and counted late; a reading less late still goes on."""
    st = stream(hold_s=1.5)
    for mid in range(1, 8):
        st.decode(gyro_msg(mid, mid), now=float(mid))
    for mid in range(9, 13):                         # 8 is missing: given up after 1.5 s
        st.decode(gyro_msg(mid, mid), now=float(mid))
    b = st.decode(gyro_msg(8, 8), now=13.0)          # newest released: second 12.5
    assert b.samples == [] and b.late == 2
    assert st.status()["late"] == 1 and st.status()["late_readings"] == 2
    b = st.decode(gyro_msg(13, 13), now=14.0)
    assert [s.values[0] for s in b.samples] == [13, 13.5] and b.late == 0
    st.decode(gyro_msg(15, 15), now=15.0)            # 14 missing, given up at 16.5
    st.decode(gyro_msg(16, 15.3), now=16.6)
    b = st.decode(gyro_msg(14, 14), now=16.7)         # 1.8 s and 1.3 s behind 15.8: kept
    assert [s.values[0] for s in b.samples] == [14, 14.5] and b.late == 0


def test_duplicate_message_is_dropped_whole():
    st = stream()
    st.decode(gyro_msg(1, 1), now=0.0)
    assert st.decode(gyro_msg(1, 1), now=0.1).samples == []
    assert len(st.decode(gyro_msg(2, 2), now=0.2).samples) == 2
    s = st.status()
    assert s["duplicates"] == 1 and s["messages"] == 2


def test_gap_is_counted_and_released_after_hold_s():
    st = stream(hold_s=1.5)
    st.decode(gyro_msg(4, 4), now=10.0)
    assert st.decode(gyro_msg(7, 7), now=10.5).samples == []
    assert st.decode(gyro_msg(8, 8), now=11.0).samples == []
    assert st.due(11.9) == []
    out = st.due(12.0)                                              # 1.5 s after 7 came
    assert [s.values[0] for s in out] == [7, 7.5, 8, 8.5]
    s = st.status()
    assert s["gaps"] == 2 and s["held"] == 0
    # 5 comes after all: late, released at once, no longer missing (its readings less than
    # 2 s behind the newest released; further behind, test_a_message_seconds_late_...)
    assert len(st.decode(gyro_msg(5, 6.6), now=12.5).samples) == 2
    assert st.status()["gaps"] == 1 and st.status()["late"] == 1
    # decode also releases what timed out meanwhile
    st.decode(gyro_msg(10, 10), now=13.0)
    b = st.decode(body([], mid=11), now=20.0)
    assert [s.values[0] for s in b.samples] == [10, 10.5]


def test_flush_releases_everything_held():
    st = stream()
    st.decode(gyro_msg(1, 1), now=0.0)
    st.decode(gyro_msg(3, 3), now=0.0)
    assert [s.values[0] for s in st.flush()] == [3, 3.5]
    assert st.status()["gaps"] == 1


def test_new_session_resets_state():
    st = stream()
    st.decode(gyro_msg(1, 1), now=0.0)
    st.decode(gyro_msg(3, 3), now=0.1)                               # held
    st.decode(gyro_msg(3, 3), now=0.2)                               # duplicate
    b = st.decode(gyro_msg(1, 9, session="s-2"), now=0.3)
    assert b.new_session
    assert [s.values[0] for s in b.ended] == [3, 3.5]               # the old session's
    assert [s.values[0] for s in b.samples] == [9, 9.5]
    s = st.status()
    assert s["messages"] == 1 and s["duplicates"] == 0 and s["gaps"] == 0
    assert s["session_id"] == "s-2" and s["sessions"] == 2
    assert not st.decode(gyro_msg(2, 10, session="s-2"), now=0.4).new_session
    # a straggler of the finished recording does not start it again
    assert st.decode(gyro_msg(4, 4), now=0.5) == Batch([], False)
    assert st.decode(gyro_msg(3, 11, session="s-2"), now=0.6).samples
    # a new device is a new session too
    assert st.decode(gyro_msg(1, 1, device="d-2", session="s-2"), now=0.7).new_session


# ---------------------------------------------------------------- signs

def test_ios_standardise_off_detected_from_raw_accelerometer_in_g():
    st = stream()
    out = st.decode(body(face_up_ios(3, raw_g=-1.0)), 0.0).samples
    s = st.status()
    assert s["convention"] == "ios" and s["convention_source"] == "detected"
    for a in by_tag(out, "ACC"):
        assert a.values[2] == pytest.approx(9.81, abs=0.02)


def test_ios_standardised_detected_from_raw_accelerometer_in_ms2():
    st = stream()
    out = st.decode(body(face_up_ios(3, standardised=True, raw_g=9.81)), 0.0).samples
    s = st.status()
    assert s["convention"] == "ios-standardised" and s["convention_source"] == "detected"
    for a in by_tag(out, "ACC"):
        assert a.values[2] == pytest.approx(9.81, abs=0.02)


@pytest.mark.parametrize("standardised", [False, True])
def test_ios_sign_detected_from_the_field_dip(standardised):
    st = stream()
    out = st.decode(body(face_up_ios(60, standardised=standardised)), 0.0).samples
    s = st.status()
    assert s["convention"] == ("ios-standardised" if standardised else "ios")
    assert s["convention_source"] == "detected"
    assert any("dips" in r for r in s["reasons"])
    acc = by_tag(out, "ACC")
    assert len(acc) == 60
    for a in acc:                        # decided before the first sample went out
        assert a.values[2] == pytest.approx(9.82, abs=0.02)


def test_ios_first_samples_wait_for_the_sign_then_all_go_out_right():
    """An iPhone with Standardise on, pushing every 0.1 s: its first samples used to go out
    with the default's sign (negated) until the dip had 50 samples of evidence, and the
    filters aligned on them upside down. Now they wait for the evidence and go out together,
    every one with the right sign; the status says they wait."""
    st = SensorLoggerStream()
    first = st.decode(body(face_up_ios(10, standardised=True), mid=1), 0.0).samples
    assert first == []
    assert any("wait" in r for r in st.status()["reasons"])
    released = [first] + [st.decode(body(face_up_ios(10, t_start=T0 + m * 100_000_000,
                                                      standardised=True), mid=m + 1), float(m)).samples
                          for m in range(1, 10)]
    assert st.status()["convention"] == "ios-standardised"
    acc = [a for out in released for a in by_tag(out, "ACC")]
    assert len(acc) == 100                                # nothing lost
    assert all(a.values[2] > 9.0 for a in acc)           # none with the wrong sign
    k = next(i for i, out in enumerate(released) if out)
    assert 1 <= k <= 6                                    # released once decided (50 samples)
    times = [x.time_ms for out in released for x in out]
    assert times == sorted(times)


def test_ios_without_sign_evidence_waits_at_most_start_hold_s():
    """No magnetometer, so no dip: the first samples wait start_hold_s (2 s of the phone's
    time), then go out with the app's default (Standardise off: negated), none lost; flush
    releases what still waits at the end."""
    st = SensorLoggerStream()
    released = []
    for m in range(30):
        rows = [r for r in face_up_ios(10, t_start=T0 + m * 100_000_000) if r["name"] != "magnetometer"]
        released.append(st.decode(body(rows, mid=m + 1), float(m)).samples)
    k = next(i for i, out in enumerate(released) if out)
    assert k == 20                                        # 2.0 s of phone time spanned
    acc = [a for out in released for a in by_tag(out, "ACC")]
    assert len(acc) == 300 and all(a.values[2] > 9.0 for a in acc)
    st2 = SensorLoggerStream()
    assert st2.decode(body(face_up_ios(5), mid=1), 0.0).samples == []
    assert len(by_tag(st2.flush(), "ACC")) == 5


def test_the_hints_say_which_convention_is_a_guess_and_which_rests_on_the_dip():
    """An iPhone reviewer's finds: without a magnetometer (Standardise on) the convention is
    the app's default, a guess, and a phone standardised showed upside down with nothing
    said; from the field's dip it holds north of the magnetic equator only. The status's
    hints say both, for the page to show."""
    st = stream()
    st.decode(body([r for r in face_up_ios(60, standardised=True) if r["name"] != "magnetometer"]), 0.0)
    s = st.status()
    assert s["convention_source"] == "assumed"
    assert any("a guess" in h and "Connect tab" in h for h in s["hints"]), s["hints"]
    st = stream()
    st.decode(body(face_up_ios(60)), 0.0)
    s = st.status()
    assert s["convention_source"] == "detected"
    assert any("northern hemisphere" in h for h in s["hints"]), s["hints"]
    st = stream()                                       # decisive evidence: no hint
    st.decode(body(face_up_ios(60, raw_g=-1.0)), 0.0)
    assert st.status()["hints"] == []


def test_the_raw_field_does_not_decide_the_sign():
    """Only the uncalibrated magnetometer ticked: its hard-iron offset (here +120 µT on z)
    turned the dip over, and an iPhone with Standardise off was taken as standardised:
    upside down. Its dip is no evidence now: the app's default holds, said to be a guess."""
    rows = []
    for r in face_up_ios(60):
        if r["name"] == "magnetometer":
            v = r["values"]
            r = rd("magnetometeruncalibrated", r["time"], x=v["x"], y=v["y"], z=v["z"] + 120.0)
        rows.append(r)
    st = stream()
    out = st.decode(body(rows), 0.0).samples
    s = st.status()
    assert s["sources"]["MAG"] == "magnetometeruncalibrated"
    assert s["convention"] == "ios" and s["convention_source"] == "assumed"
    assert all(a.values[2] > 9.0 for a in by_tag(out, "ACC"))
    assert any("a guess" in h for h in s["hints"])


def test_gravity_alone_gives_the_tilt_and_accelerometer_alone_says_what_to_tick():
    """Gravity ticked without Accelerometer: the filters had no tilt at all (90° off); the
    phone's gravity is the tilt now, and the hint asks for Accelerometer (the shakes).
    Accelerometer without Gravity (linear acceleration: gravity removed) cannot give a tilt:
    the hint asks for Gravity."""
    st = stream()
    out = st.decode(body([r for r in face_up_ios(60) if r["name"] != "accelerometer"]), 0.0).samples
    acc = by_tag(out, "ACC")
    assert len(acc) == 60 and all(a.values[2] == pytest.approx(9.80665) for a in acc)
    s = st.status()
    assert s["sources"]["ACC"] == "gravity" and "gravity" not in s["unused"]
    assert any("tick Accelerometer" in h for h in s["hints"]), s["hints"]
    st = stream()
    out = st.decode(body([r for r in face_up_ios(60) if r["name"] != "gravity"]), 0.0).samples
    assert by_tag(out, "ACC") == []
    assert any("tick Gravity" in h for h in st.status()["hints"])
    # and Accelerometer ticked later: the pair takes over
    st = stream()
    st.decode(body([r for r in face_up_ios(60) if r["name"] != "accelerometer"], mid=1), 0.0)
    st.decode(body(face_up_ios(60, t_start=T0 + 1_000_000_000), mid=2), 1.0)
    assert st.status()["sources"]["ACC"] == "accelerometer+gravity"


def test_android_is_never_negated():
    st = stream()
    payload = [rd("totalacceleration", T0 + i * 5_000_000, accuracy=3, x=0.0, y=0.0, z=9.81)
               for i in range(10)]
    payload += [rd("magnetometer", T0 + i * 10_000_000, accuracy=3, x=0.0, y=-20.0, z=40.0)
                for i in range(5)]      # southern-looking dip: must not matter on Android
    out = st.decode(body(payload), 0.0).samples
    assert all(a.values[2] == 9.81 for a in by_tag(out, "ACC"))
    assert st.status()["convention"] == "android"


def test_android_without_totalacceleration_pairs_nearest_gravity():
    st = stream()
    payload = [rd("accelerometer", T0 + 2_000_000 * i + 700_000, accuracy=3, x=0.1 * i, y=0.0, z=0.0)
               for i in range(5)]
    payload += [rd("gravity", T0 + 4_000_000 * i, accuracy=3, x=0.0, y=0.0, z=9.0 + i)
                for i in range(3)]
    out = st.decode(body(payload), 0.0).samples
    acc = by_tag(out, "ACC")
    # accelerometer at 0.7, 2.7, 4.7, 6.7, 8.7 ms; gravity at 0, 4, 8 ms
    assert [round(a.values[2], 6) for a in acc] == [9.0, 10.0, 10.0, 11.0, 11.0]
    assert [round(a.values[0], 6) for a in acc] == [0.0, 0.1, 0.2, 0.3, 0.4]
    assert st.status()["convention"] == "android"


def test_android_evidence_wins_over_shared_time_stamps():
    st = stream()
    shared = [rd("gyroscope", T0, x=0.0, y=0.0, z=0.0),
              rd("gravity", T0, x=0.0, y=0.0, z=9.81),
              rd("accelerometer", T0, x=0.0, y=0.0, z=0.0)]
    out = st.decode(body(shared), 0.0).samples
    assert st.status()["platform"] == "ios"
    assert by_tag(out, "ACC")[0].values[2] == pytest.approx(-9.81)   # assumed: negated
    later = [rd("totalacceleration", T0 + 10**7, accuracy=3, x=0.0, y=0.0, z=9.81)]
    out = st.decode(body(later, mid=2), 1.0).samples
    s = st.status()
    assert s["platform"] == "android" and s["convention"] == "android"
    assert s["sources"]["ACC"] == "totalacceleration"
    assert by_tag(out, "ACC")[0].values == (0.0, 0.0, 9.81)


def test_status_of_a_fresh_stream_is_json_safe():
    s = stream().status()
    json.dumps(s, allow_nan=False)
    assert s["platform"] == "unknown" and s["messages"] == 0 and s["clock_offset_s"] is None


def test_clock_offset_is_phone_time_minus_now():
    st = stream()
    for i in range(5):
        st.decode(gyro_msg(i + 1, i), now=T0 / 1e9 + i + 1.7)   # 1.2 s after the newest
    assert st.status()["clock_offset_s"] == pytest.approx(-1.2, abs=1e-3)
    assert st.status()["last_sample_s"] == pytest.approx(T0 / 1e9 + 4.5)
    assert st.status()["rates_hz"]["GYR"] == pytest.approx(2.0)


def test_presenter_override_wins_and_survives_sessions():
    st = stream()
    with pytest.raises(ValueError) as e:
        st.set_convention("iphone")
    for allowed in ("auto", "android", "ios", "ios-standardised"):
        assert allowed in str(e.value)
    st.set_convention("ios-standardised")
    out = st.decode(IOS_EXAMPLE, 0.0).samples
    assert by_tag(out, "ACC")[0].values[2] == pytest.approx(-9.8171)   # as sent
    s = st.status()
    assert s["convention"] == "ios-standardised" and s["convention_source"] == "presenter"
    other = IOS_EXAMPLE.replace(b"0ba5f3e8-0000", b"0ba5f3e8-1111")
    b = st.decode(other, 1.0)
    assert b.new_session and st.status()["convention_source"] == "presenter"
    st.set_convention("auto")
    s = st.status()
    assert s["convention"] == "ios" and s["convention_source"] == "assumed"


# ---------------------------------------------------------------- real phones (tyrex)

def trial(shared_dir, name) -> Path:
    p = shared_dir / "data" / "phones-tyrex" / f"{name}.npz"
    if not p.is_file():
        pytest.skip(f"{p} not present")
    return p


def decode_all(bodies, hold_s=1.5):
    st = stream(hold_s=hold_s)
    out = tx.deliver(st, bodies)
    return st, out


def check_against_npz(path, out, kind, tail=None):
    """ACC/GYR/MAG values equal the trial's rows (float precision), in time order."""
    d = np.load(path)
    fs = float(d["fs"])
    t_all = [s.time_ms for s in out]
    assert t_all == sorted(t_all)
    for tag, key, name in (("ACC", "acc", "totalacceleration" if kind == "android-total"
                            else "accelerometer"),
                           ("GYR", "gyr", "gyroscope"), ("MAG", "mag", "magnetometer")):
        ss = by_tag(out, tag)
        tm = np.array([s.time_ms for s in ss])
        assert (np.diff(tm) > 0).all()
        off = tx.ANDROID_OFFSETS[name] if kind.startswith("android") else 0.0
        idx = tx.row_index(tm, d["t"], fs, off)
        ref = d[key]
        ok = np.isfinite(ref).all(axis=1)
        if tag == "ACC" and kind != "android-total":     # no gravity reading, no pair
            ok &= np.isfinite(tx.gravity_of(tx.load(path))).all(axis=1)
        finite = np.flatnonzero(ok)
        vals = np.array([s.values for s in ss])
        if tail is None:
            assert np.array_equal(idx, finite)                      # nothing lost, no extra
        else:
            k = int(len(idx) * tail)
            idx, vals = idx[-k:], vals[-k:]
        np.testing.assert_allclose(vals, ref[idx], rtol=1e-12, atol=1e-12)


CASES = [
    ("Nexus5_Guillaume_NoDist_texting", "android-total", {}),
    ("Nexus5_Guillaume_NoDist_ar", "android-pairs", {"total": False}),
    ("iPhone5_Guillaume_NoDist_ar", "ios", {}),
    ("iPhone4S_Guillaume_NoDist_texting", "ios", {}),
    ("iPhone5_Guillaume_NoDist_texting", "ios", {"standardise": True, "uncalibrated": True}),
    ("iPhone4S_Guillaume_NoDist_ar", "ios", {"uncalibrated": True, "batch_s": 0.25}),
]


@pytest.mark.parametrize("name, kind, kw", CASES, ids=[f"{c[0]}-{c[1]}-{len(c[2])}" for c in CASES])
def test_tyrex_trials_decode_to_their_values(shared_dir, name, kind, kw):
    path = trial(shared_dir, name)
    make = tx.messages_android if kind.startswith("android") else tx.messages_ios
    st, out = decode_all(make(path, **kw))
    check_against_npz(path, out, kind)
    s = st.status()
    assert s["platform"] == ("android" if kind.startswith("android") else "ios")
    want = "android" if kind.startswith("android") else (
        "ios-standardised" if kw.get("standardise") else "ios")
    assert s["convention"] == want and s["convention_source"] == "detected"
    assert s["gaps"] == s["duplicates"] == s["out_of_order"] == 0
    assert s["invalid"] == {}
    for tag in ("ACC", "GYR", "MAG"):
        assert s["rates_hz"][tag] == pytest.approx(100.0, rel=0.02)
    json.dumps(s, allow_nan=False)


def test_tyrex_standardised_ios_found_from_the_dip(shared_dir):
    path = trial(shared_dir, "iPhone5_Guillaume_NoDist_ar")
    st, out = decode_all(tx.messages_ios(path, standardise=True))
    s = st.status()
    assert s["convention"] == "ios-standardised" and s["convention_source"] == "detected"
    check_against_npz(path, out, "ios", tail=0.8)


@pytest.mark.parametrize("name,skip", [("iPhone5_Guillaume_NoDist_swinging", 5),
                                       ("iPhone5_Guillaume_NoDist_runninghand", 8)])
def test_standardised_ios_found_when_the_recording_starts_in_motion(shared_dir, name, skip):
    """An iPhone with Standardise on whose recording starts while it swings or runs: the
    dip was read only from samples at rest (|f| = g, gyroscope still), none came within the
    session's first 2 s, the app's default (Standardise off) went, and the whole stream was
    upside down (178 deg off the truth, a reviewer's find). The pushed gravity has no motion
    in it: its dip against the field decides while the phone moves."""
    bodies = tx.messages_ios(trial(shared_dir, name), standardise=True, seconds=30)[skip:]
    st = SensorLoggerStream()          # the real start: samples wait for the sign (2 s)
    out = tx.deliver(st, bodies)
    s = st.status()
    assert s["convention"] == "ios-standardised" and s["convention_source"] == "detected", s
    check_against_npz(trial(shared_dir, name), out, "ios", tail=1.0)   # every sample's sign


def angle_deg(q1, q2):
    dot = np.abs(np.einsum("ij,ij->i", q1, q2))
    return np.degrees(2 * np.arccos(np.clip(dot, 0.0, 1.0)))


@pytest.mark.parametrize("name, kind, ori, want", [
    ("Nexus5_Guillaume_NoDist_texting", "android", "enu", "as sent, world turned 0°"),
    ("iPhone5_Guillaume_NoDist_ar", "ios", "nwu", "as sent, world turned 90°"),
    ("iPhone4S_Guillaume_NoDist_texting", "ios", "enu-conj", "conjugated, world turned 0°"),
    ("Nexus5_Guillaume_NoDist_texting", "android", "nwu-conj", "conjugated, world turned 90°"),
])
def test_orientation_convention_found_on_real_phones(shared_dir, name, kind, ori, want):
    path = trial(shared_dir, name)
    make = tx.messages_android if kind == "android" else tx.messages_ios
    st, out = decode_all(make(path, ori=ori))
    s = st.status()
    assert s["orientation"]["state"] == "ok", s["orientation"]
    assert s["orientation"]["convention"] == want
    assert s["sources"]["ORI"] == "orientation"
    ori_s = by_tag(out, "ORI")
    assert len(ori_s) > 0.8 * len(by_tag(out, "GYR"))
    d = np.load(path)
    off = tx.ANDROID_OFFSETS["orientation"] if kind == "android" else 0.0
    idx = tx.row_index([x.time_ms for x in ori_s], d["t"], float(d["fs"]), off)
    got = np.array([x.values for x in ori_s])
    assert (got[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-9)
    assert angle_deg(got, d["os_quat"][idx]).max() < 1.0


def test_orientation_in_a_wrong_convention_is_left_out(shared_dir):
    path = trial(shared_dir, "iPhone5_Guillaume_NoDist_ar")
    st, out = decode_all(tx.messages_ios(path, ori="wrong"))
    s = st.status()
    assert s["orientation"]["state"] == "left out"
    assert "did not match gravity and the field" in s["orientation"]["message"]
    assert by_tag(out, "ORI") == []
    assert s["sources"]["ORI"] is None
    assert len(by_tag(out, "ACC")) > 10000        # the rest goes on


def test_tyrex_messages_out_of_order_duplicated_and_missing(shared_dir):
    path = trial(shared_dir, "Nexus5_Guillaume_NoDist_texting")
    bodies = tx.messages_android(path, seconds=20)
    _, clean = decode_all(bodies)
    st, out = decode_all(tx.duplicated(tx.swapped(bodies, 5), 9))
    assert out == clean
    s = st.status()
    assert s["out_of_order"] == 1 and s["duplicates"] == 1 and s["gaps"] == 0
    st, out = decode_all(tx.missing(bodies, 7))
    s = st.status()
    assert s["gaps"] == 1
    lost = json.loads(bodies[7])["payload"]
    gone = {r["time"] / 1e6 for r in lost}
    assert [x for x in clean if x.time_ms not in gone] == out


def test_presenter_override_on_a_real_iphone(shared_dir):
    path = trial(shared_dir, "iPhone5_Guillaume_NoDist_ar")
    st = stream()
    st.set_convention("ios-standardised")       # wrong on purpose: no negation
    out = tx.deliver(st, tx.messages_ios(path, seconds=10))
    acc = np.array([a.values for a in by_tag(out, "ACC")])
    d = np.load(path)
    np.testing.assert_allclose(acc, -d["acc"][: len(acc)], rtol=1e-12, atol=1e-12)
    assert st.status()["convention_source"] == "presenter"


# ---------------------------------------------------------------- robustness

_KEYS = ["name", "time", "values", "x", "y", "z", "qw", "qx", "qy", "qz", "accuracy",
         "payload", "messageId"]
_ATOMS = [None, True, False, 0, -1, 2**70, -2**70, T0, T0 + 7, 0.5, -0.0, 1e308, "",
          "gyroscope", "totalacceleration", "orientation", "gravity", "accelerometer",
          "magnetometeruncalibrated", "accelerometeruncalibrated", "x", "qw", "1.5"]


def _random_json(rng, depth=0):
    k = rng.random()
    if depth > 3 or k < 0.5:
        return rng.choice(_ATOMS + [rng.uniform(-50, 50), rng.randint(-5, 5)])
    if k < 0.65:
        return [_random_json(rng, depth + 1) for _ in range(rng.randint(0, 4))]
    return {rng.choice(_KEYS): _random_json(rng, depth + 1) for _ in range(rng.randint(0, 5))}


def _random_reading(rng):
    r = {"name": rng.choice(_ATOMS[13:20]), "time": rng.choice([T0 + rng.randint(0, 10**9), T0, -5, "t", None]),
         "values": {key: rng.choice([rng.uniform(-30, 30), 1e9, None, "a", True])
                    for key in rng.sample(_KEYS[3:10], rng.randint(0, 7))}}
    return r if rng.random() < 0.8 else _random_json(rng)


def test_any_json_either_decodes_or_raises_a_sensorlogger_error():
    import random
    rng = random.Random(7)
    st = stream()
    for i in range(400):
        msg = {"messageId": rng.choice([i, i, i - 3, None, "7", 2.0, -1]),
               "sessionId": rng.choice(["s", "s", "s", "t"]), "deviceId": "d",
               "payload": [_random_reading(rng) for _ in range(rng.randint(0, 8))]}
        if rng.random() < 0.1:
            msg = _random_json(rng)
        try:
            b = st.decode(json.dumps(msg).encode(), float(i) / 4)
        except SensorLoggerError as e:
            assert e.reason in ("bad_json", "bad_shape")
            continue
        for x in b.samples + b.ended + st.due(float(i) / 4):
            assert x.tag in ("ACC", "GYR", "MAG", "ORI")
            assert all(math.isfinite(v) for v in x.values)
        json.dumps(st.status(), allow_nan=False)
    st.flush()


def test_a_phone_without_the_orientation_sensor_is_told_to_tick_it(shared_dir):
    """Holding the phone still cannot help when the app sends no orientation at all: the
    status says which sensor to tick instead (a reviewer's find)."""
    path = trial(shared_dir, "Nexus5_Guillaume_NoDist_ar")
    st = stream()
    bodies = [json.loads(b) for b in tx.messages_android(path, 1.0, seconds=8)]
    for i, m in enumerate(bodies):
        m["payload"] = [r for r in m["payload"] if r["name"] != "orientation"]
        st.decode(json.dumps(m).encode(), float(i))
        o = st.status()["orientation"]
        if i + 1 < NO_ORI_AFTER:
            assert o["state"] != "absent"
    assert o["state"] == "absent" and "tick Orientation" in o["message"]
    with_ori = stream()
    for i, b in enumerate(tx.messages_android(path, 1.0, seconds=8)):
        with_ori.decode(b, float(i))
    assert with_ori.status()["orientation"]["state"] != "absent"


def test_made_up_reading_names_cannot_grow_the_ignored_counter():
    """A phone (or a stray client) sending new unknown names in every message: at most
    MAX_IGNORED_NAMES distinct names are kept, each cut to 40 characters, the rest counted
    as "(other)"; no reading goes uncounted."""
    from app.sources.sensorlogger_wire import MAX_IGNORED_NAMES
    st = stream()
    n = 0
    for m in range(1, 6):
        payload = [rd(f"n{m}-{k}-" + "x" * 50, T0 + k, x=0.0, y=0.0, z=0.0) for k in range(30)]
        payload.append(rd("gyroscope", T0 + 100 * m, x=0.0, y=0.0, z=0.0))
        st.decode(body(payload, mid=m), float(m))
        n += 30
    ig = st.status()["ignored"]
    assert len(ig) == MAX_IGNORED_NAMES + 1 and sum(ig.values()) == n
    assert all(len(k) <= 40 for k in ig) and ig["(other)"] == n - MAX_IGNORED_NAMES


def test_a_message_id_no_app_reaches_is_counted_and_the_session_goes_on():
    """A script's messageId of 10**400 was taken: the session's gap count became a 400-digit
    number and its later messages were dropped as duplicates (a reviewer's find). One beyond
    2**53 is counted as a bad message id and the message used without it."""
    st = stream()
    rows = [rd("accelerometer", T0 + k * 10_000_000, x=0.0, y=0.0, z=9.81) for k in range(5)]
    st.decode(body(rows[:2], mid=1), 0.0)
    st.decode(body(rows[2:3], mid=10 ** 400), 0.0)
    st.decode(body(rows[3:], mid=2), 0.0)
    s = st.status()
    assert s["invalid"].get("bad_message_id") == 1
    assert s["gaps"] == 0 and s["duplicates"] == 0, s
    assert st.messages == 3          # the message without its id is used, the next one too


@pytest.mark.parametrize("yaw0", [2.0, 45.0, 92.0])
def test_orientation_check_decides_once_the_phone_rests_at_another_heading(yaw0):
    """A phone lying flat with its top to the north fits 'as sent' and 'conjugated' alike
    (conjugated, its heading changes sign). Before, the check needed one candidate to fit
    twice as much of all the rest seen: after 10 s at north, 2 s at another heading never
    sufficed, and the page said "not yet checked (10.0 s of 2 s near rest seen)". Now it
    says why, and those 2 s decide."""
    import math

    import numpy as np

    from app.quaternion import Q_many
    from app.sources.sensorlogger import OrientationCheck

    def rest(t0_s, seconds, yaw_deg):
        t = (np.arange(int(seconds * 100)) * 0.01 + t0_s) * 1e9
        t = t.astype(np.int64)
        half = math.radians(yaw_deg) / 2.0
        q = np.tile([math.cos(half), 0.0, 0.0, math.sin(half)], (len(t), 1))
        m_world = np.array([0.0, 20.0, -45.0])                          # ENU, µT: north, dipping
        m = np.einsum("nji,j->ni", Q_many(q), m_world)                 # in the sensor's axes
        f = np.tile([0.0, 0.0, 9.81], (len(t), 1))
        return t, q, t, f, t, m, t, np.zeros((len(t), 3))

    chk = OrientationCheck()
    for k in range(10):
        chk.feed(*rest(k, 1.0, yaw0))
    assert chk.state == "checking"
    assert "fits two conventions alike" in chk.message() and "20-30°" in chk.message()
    chk.feed(*rest(10.0, 1.0, yaw0 + 25.0))       # turned as the message says
    chk.feed(*rest(11.0, 1.0, yaw0 + 25.0))
    assert chk.state == "ok", chk.status()
    assert chk.status()["convention"] == "as sent, world turned 0°"


def test_a_sensor_not_ticked_in_the_app_is_named():
    """An iPhone with Magnetometer not ticked: the orientation check said "hold the phone
    still" for good, though it cannot run without the field. (That a sensor is not ticked
    at all the Connect tab says for every app: Session.missing.)"""
    st = stream()
    for m in range(8):                          # 8 messages of 0.1 s, Orientation ticked
        rows = [r for r in face_up_ios(10, t_start=T0 + m * 100_000_000, standardised=True)
                if r["name"] not in ("magnetometer", "gyroscope")]
        rows += [rd("orientation", T0 + m * 100_000_000 + k * 10_000_000,
                    qw=1.0, qx=0.0, qy=0.0, qz=0.0) for k in range(10)]
        st.decode(body(rows, mid=m + 1), m * 0.1)
    assert "needs the magnetometer" in st.status()["orientation"]["message"]
    assert "needs the magnetometer" in st.withheld()["ORI"]
    full = stream()                             # with the magnetometer: checked
    for m in range(8):
        rows = face_up_ios(10, t_start=T0 + m * 100_000_000, standardised=True)
        rows += [rd("orientation", T0 + m * 100_000_000 + k * 10_000_000,
                    qw=1.0, qx=0.0, qy=0.0, qz=0.0) for k in range(10)]
        full.decode(body(rows, mid=m + 1), m * 0.1)
    assert "needs the magnetometer" not in full.status()["orientation"]["message"]
