"""phyphox: the experiment file, push decoding and the remote-access poller (against a
fake phone that is a real HTTP server on loopback; see fake_phyphox.py)."""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
import xml.etree.ElementTree as ET

import httpx
import numpy as np
import pytest

from app.sources.phyphox import (PUSH_BUFFERS, Batch, PhyphoxError, PhyphoxPushStream,
                                 buffers_to_samples, experiment_xml)
from app.sources.phyphox_poll import PhyphoxPoller, parse_base_url, parse_config
from sources.fake_phyphox import FakePhyphox, FakeSensor, java_float
from sources.tyrex_phyphox import delivery, expected, load_trial, push_bodies

TYREX = "data/phones-tyrex"
NOTE_BODY = b"""{"acc_t":[12.3499,12.3549],"accX":[0.0431,0.0419],"accY":[-0.1185,-0.1173],"accZ":[9.8124,9.8100],
 "gyr_t":[12.3491,12.3516,12.3541],"gyrX":[0.0011,0.0009,0.0012],"gyrY":[-0.0007,-0.0006,-0.0008],"gyrZ":[0.0003,0.0002,0.0003],
 "mag_t":[12.3502],"magX":[15.2],"magY":[0.8],"magZ":[-47.9],
 "timeinfo":{"now":1760000123.456,"events":[{"event":"START","experimentTime":0,"systemTime":1760000111.101}]},
 "model":"Pixel 7"}"""


def _trial(shared_dir, name, seconds=None):
    path = shared_dir / TYREX / f"{name}.npz"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    return load_trial(path, seconds)


def _by_tag(samples):
    out = {}
    for s in samples:
        out.setdefault(s.tag, []).append(s)
    return out


def _body(**arrays) -> bytes:
    return json.dumps(arrays).encode()


# ------------------------------------------------------------------ experiment file

def test_experiment_xml_declares_everything_it_uses():
    url = 'http://192.168.1.23:8000/phyphox?a=1&b="2"<x>'
    root = ET.fromstring(experiment_xml(url, interval_s=0.2))
    assert root.tag == "phyphox"
    assert tuple(map(int, root.get("version").split("."))) >= (1, 14)
    declared = {c.text for c in root.iter("container")}
    assert all(c.get("size") == "0" for c in root.iter("container"))
    sensors = {s.get("type"): s for s in root.find("input").iter("sensor")}
    assert set(sensors) == {"accelerometer", "gyroscope", "magnetic_field", "attitude"}
    assert all(s.get("rate") == "0" for s in sensors.values())
    assert sensors["attitude"].get("ignoreUnavailable") == "true"
    assert {o.get("component") for o in sensors["attitude"]} == {"x", "y", "z", "abs", "t"}
    used = [o.text for s in sensors.values() for o in s.iter("output")]
    used += [i.text for i in root.find("views").iter("input")]
    used += [d.text for d in root.find("export").iter("data")]
    conn = root.find("network/connection")
    assert conn.get("service") == "http/post" and conn.get("address") == url
    assert conn.get("interval") == "0.2" and conn.get("autoConnect") == "true"
    assert conn.get("conversion") == "none"
    assert conn.get("privacy") == "http://192.168.1.23:8000/privacy"
    sends = list(conn.iter("send"))
    bufs = [s for s in sends if s.get("type") == "buffer"]
    assert all(s.get("keep") == "false" and s.get("id") == s.text for s in bufs)
    used += [s.text for s in bufs]
    assert set(used) <= declared and {s.text for s in bufs} == declared
    assert [s.get("id") for s in sends if s.get("type") == "time"] == ["timeinfo"]
    meta = [s for s in sends if s.get("type") == "meta"]
    assert [(s.get("id"), s.text) for s in meta] == [("model", "deviceModel")]
    # the buffers the push decoder looks for are the ones the file sends
    assert {n for t, c in PUSH_BUFFERS.values() for n in (t, *c)} == declared


def test_experiment_xml_without_push_and_bad_arguments():
    root = ET.fromstring(experiment_xml(None, title="a & b"))
    assert root.find("network") is None and root.find("title").text == "a & b"
    for bad in ("ftp://x/y", "192.168.1.2:8000", "http://", "http://h:99999/"):
        with pytest.raises(ValueError):
            experiment_xml(bad)
    with pytest.raises(ValueError):
        experiment_xml("http://h/p", interval_s=0)


# ------------------------------------------------------------------ buffers -> samples

def test_buffers_to_samples_skips_and_counts():
    from collections import Counter
    c = Counter()
    conv = buffers_to_samples("ACC", [1.0, 2.0, None, 4.0, 5.0, 6.0, 7.0],
                              [[0, 1e6, 0, None, "nan", 1, 0.5, 9],
                               [0, 0, 0, 0, 0, "x", 0],
                               [9.8, 0, 0, 0, 0, 0, 9.8]], c)
    assert [s.time_ms for s in conv.samples] == [1000.0, 7000.0]
    assert conv.kept == 7 and conv.last_t == 7.0
    assert c == Counter(impossible=1, bad_time=1, null=2, not_numeric=1, truncated=1)
    # attitude: abs is w; w >= 0 out; x, y, z only -> w from the norm
    q = buffers_to_samples("ORI", [1.0, 2.0], [[-0.5, 0.5], [0.5, 0.5], [-0.5, 0.5],
                                               [0.5, 0.5]]).samples
    assert q[0].values == (0.5, -0.5, 0.5, -0.5) and q[1].values == (0.5,) * 4
    q3 = buffers_to_samples("ORI", [1.0], [[0.0], [0.0], [0.6]]).samples
    assert q3[0].values == pytest.approx((0.8, 0.0, 0.0, 0.6))
    c2 = Counter()
    assert buffers_to_samples("MAG", [1.0], [[0.0], [0.0], [0.0]], c2).samples == []
    assert c2["mag_zero"] == 1


# ------------------------------------------------------------------ push

def test_push_decodes_the_notes_example():
    stream = PhyphoxPushStream()
    batch = stream.decode(NOTE_BODY, now=1760000123.5)
    assert isinstance(batch, Batch) and batch.new_session
    times = [s.time_ms for s in batch.samples]
    assert times == sorted(times)
    by = _by_tag(batch.samples)
    assert [s.time_ms for s in by["ACC"]] == pytest.approx([12349.9, 12354.9])
    assert by["ACC"][1].values == (0.0419, -0.1173, 9.81)
    assert len(by["GYR"]) == 3 and by["MAG"][0].values == (15.2, 0.8, -47.9)
    assert "ORI" not in by
    assert stream.model == "Pixel 7"
    assert stream.unix_base_s == pytest.approx(1760000111.101)
    # newest sample 12.3549 s after START, arriving at PC time ...123.5
    assert stream.clock_offset_s == pytest.approx(1760000111.101 + 12.3549 - 1760000123.5)
    assert stream.phone_now_offset_s == pytest.approx(-0.044, abs=1e-6)
    json.dumps(stream.status())
    # the same body again: all duplicates, nothing new
    again = stream.decode(NOTE_BODY, now=1760000123.6)
    assert again.samples == [] and not again.new_session
    assert stream.counts["duplicate"] == 6


def test_push_keys_missing_empty_unequal_and_nulls():
    s = PhyphoxPushStream()
    b = s.decode(_body(acc_t=[1.0, 1.01, 1.02], accX=[0, 0.1, None], accY=[0, 0, 0],
                       accZ=[9.8, 9.8, 9.8], gyr_t=[], gyrX=[], gyrY=[], gyrZ=[],
                       mag_t=[1.0, 1.02], magX=[20, 21, 22], magY=[1, 1], magZ=[-40, -40],
                       att_t=1.005, attW=1.0, attX=0.0, attY=0.0, attZ=0.0), now=0.0)
    by = _by_tag(b.samples)
    assert len(by["ACC"]) == 2 and "GYR" not in by and len(by["MAG"]) == 2
    assert by["ORI"][0].values == (1.0, 0.0, 0.0, 0.0)
    assert s.counts["null"] == 1 and s.counts["truncated"] == 1
    # a sensor's time without its values (or values without time): counted, skipped
    b2 = s.decode(_body(acc_t=[1.03], gyr_t=[1.03], gyrX=[0.1], gyrY=[0], gyrZ=[0]), now=0.1)
    assert [x.tag for x in b2.samples] == ["GYR"] and s.counts["missing_component"] == 1
    # an empty object is a valid (empty) push; the model alone too
    assert s.decode(b"{}", now=0.2).samples == []
    assert s.decode(b'{"model": null, "timeinfo": {"now": 5}}', now=0.3).samples == []


@pytest.mark.parametrize("body,reason", [
    (b"not json", "bad_json"), (b"\xff\xfe{", "bad_json"), (b"", "bad_json"),
    (b"[1, 2]", "not_object"), (b'"x"', "not_object"),
    (b'{"acc_t": "1.0"}', "bad_buffer"), (b'{"accX": {"a": 1}}', "bad_buffer"),
    (b'{"acc_t": true}', "bad_buffer"),
    (b'{"timeinfo": [1]}', "bad_timeinfo"), (b'{"model": 7}', "bad_model"),
])
def test_push_malformed_bodies_raise(body, reason):
    stream = PhyphoxPushStream()
    with pytest.raises(PhyphoxError) as ei:
        stream.decode(body, now=0.0)
    assert ei.value.reason == reason
    assert isinstance(ei.value, ValueError)
    assert stream.counts[f"rejected_{reason}"] == 1 and stream.counts["posts"] == 0


def test_push_read_apart_from_the_stream_then_taken_as_decode_would():
    """read() (run on a worker thread by the server) touches no state; take() of what it
    read gives what decode() gives."""
    whole, apart = PhyphoxPushStream(), PhyphoxPushStream()
    obj = PhyphoxPushStream.read(NOTE_BODY)
    assert apart.counts == {} and apart.model is None
    a, b = whole.decode(NOTE_BODY, now=1760000123.5), apart.take(obj, now=1760000123.5)
    assert [(s.tag, s.time_ms, s.values) for s in a.samples] == \
           [(s.tag, s.time_ms, s.values) for s in b.samples]
    assert a.new_session and b.new_session
    assert whole.status() == apart.status()


def test_push_error_message_does_not_echo_input():
    big = b'{"acc_t": "' + b"A" * 100_000 + b'"}'
    for body in (big, b"x" * 100_000):
        with pytest.raises(PhyphoxError) as ei:
            PhyphoxPushStream().decode(body, now=0.0)
        assert len(str(ei.value)) < 120 and "AAAA" not in str(ei.value)


def test_push_impossible_values_counted():
    s = PhyphoxPushStream()
    b = s.decode(b'{"acc_t":[1,2,3],"accX":[Infinity,1e6,0],"accY":[0,0,0],"accZ":[9.8,0,9.8],'
                 b'"att_t":[1],"attW":[3],"attX":[0],"attY":[0],"attZ":[0]}', now=0.0)
    assert [x.time_ms for x in b.samples] == [3000.0]
    assert s.counts["impossible"] == 3


def test_an_integer_beyond_any_float_is_one_impossible_reading_not_a_lost_post():
    """JSON integers have no size limit: one of 401 digits raised OverflowError out of the
    decoder, the POST was answered 500 and its good readings lost."""
    huge, s = "1" + "0" * 400, PhyphoxPushStream()
    b = s.decode(('{"acc_t":[1,2],"accX":[%s,0.1],"accY":[0,0],"accZ":[9.8,9.8],'
                  '"gyr_t":[1,2,%s],"gyrX":[0,0,0],"gyrY":[0,0,0],"gyrZ":[0.1,0.1,0.1]}'
                  % (huge, huge)).encode(), now=0.0)
    assert sorted((x.tag, x.time_ms) for x in b.samples) == [
        ("ACC", 2000.0), ("GYR", 1000.0), ("GYR", 2000.0)]
    assert s.counts["impossible"] == 1 and s.counts["bad_time"] == 1


def _all(stream, bodies, now0=0.0):
    out, flags = [], []
    for i, body in enumerate(bodies):
        b = stream.decode(body, now=now0 + 0.1 * i)
        out += b.samples
        flags.append(b.new_session)
    return out, flags


@pytest.mark.parametrize("name", ["Nexus5_Guillaume_NoDist_ar", "iPhone4S_Guillaume_NoDist_ar"])
def test_push_tyrex_trial_decodes_to_the_npz(shared_dir, name):
    trial = _trial(shared_dir, name)
    ios = name.startswith("iPhone")
    pushed = push_bodies(trial, uneven_every=7 if ios else 0)
    stream = PhyphoxPushStream()
    out, flags = _all(stream, pushed.bodies, now0=1_760_000_111.2)
    assert flags[0] and not any(flags[1:])
    by = _by_tag(out)
    for tag in ("ACC", "GYR", "MAG", "ORI"):
        t_ms, v = expected(trial, tag, pushed.lost)
        got_t = np.array([s.time_ms for s in by[tag]])
        got_v = np.array([s.values for s in by[tag]])
        np.testing.assert_allclose(got_t, t_ms, rtol=0, atol=1e-9)
        if tag == "ORI":
            np.testing.assert_allclose(got_v, v, rtol=0, atol=1e-6)
        else:
            np.testing.assert_array_equal(got_v.astype(np.float32), v.astype(np.float32))
    assert stream.model == trial.model
    if ios:
        assert stream.counts["truncated"] == len(pushed.lost["ACC"]) > 0
        # the iPhone 4S trial's one NaN attitude row is counted, not passed on
        assert stream.counts["null"] == 1
    assert stream.counts["duplicate"] == stream.counts["reordered"] == 0
    assert stream.counts["gap"] == 0 and stream.counts["sessions"] == 1


def test_push_overlapping_reordered_and_lost_posts(shared_dir):
    trial = _trial(shared_dir, "Nexus5_Guillaume_NoDist_texting", seconds=6)
    pushed = push_bodies(trial)
    bodies = list(pushed.bodies)
    n_in = [len(json.loads(b)["acc_t"]) + len(json.loads(b)["gyr_t"])
            + len(json.loads(b)["mag_t"]) + len(json.loads(b)["att_t"]) for b in bodies]
    stream = PhyphoxPushStream(interval_s=0.1)
    # body 10 twice (overlap), 20 and 21 swapped (reordered), 40 lost
    out, flags = _all(stream, delivery(bodies, duplicate=10, swap=20, lose=40))
    assert stream.counts["duplicate"] == n_in[10]
    assert stream.counts["reordered"] == n_in[20]
    assert stream.counts["gap"] == 1 and stream.counts["gap_filled"] == 1
    assert not any(flags[1:])
    # every sample once, except those of the lost POST; merged by time they are the trial
    lost = {tag: list(range(*pushed.ranges[40][tag])) for tag in PUSH_BUFFERS}
    by = _by_tag(sorted(out, key=lambda s: s.time_ms))
    for tag in PUSH_BUFFERS:
        t_ms, _ = expected(trial, tag, lost)
        np.testing.assert_allclose([s.time_ms for s in by[tag]], t_ms, atol=1e-9)


def test_push_first_post_overtaken_by_the_second_is_kept(shared_dir):
    """phyphox's POSTs overlap: the second may arrive first. The first then held times
    older than any remembered, and was dropped as ``stale`` (a reviewer's find: 0.1 s lost
    at the start). Only a time older than the memory's span is stale; it is reordered."""
    trial = _trial(shared_dir, "Nexus5_Guillaume_NoDist_texting", seconds=3)
    pushed = push_bodies(trial)
    bodies = list(pushed.bodies)
    n0 = sum(len(json.loads(bodies[0])[k]) for k in ("acc_t", "gyr_t", "mag_t", "att_t"))
    stream = PhyphoxPushStream(interval_s=0.1)
    out, flags = _all(stream, delivery(bodies, swap=0))
    assert stream.counts["stale"] == 0 and stream.counts["reordered"] == n0 > 0
    assert flags[0] and not any(flags[1:]) and stream.counts["sessions"] == 1
    by = _by_tag(sorted(out, key=lambda s: s.time_ms))
    for tag in PUSH_BUFFERS:
        t_ms, _ = expected(trial, tag, {})
        np.testing.assert_allclose([s.time_ms for s in by[tag]], t_ms, atol=1e-9)


def test_push_new_session_flag_waits_for_samples():
    s = PhyphoxPushStream()
    empty = _body(acc_t=[], accX=[], accY=[], accZ=[], model="Pixel 7")
    assert s.decode(empty, now=0) == Batch([], False)
    b = s.decode(_body(acc_t=[0.01], accX=[0], accY=[0], accZ=[9.8]), now=0.1)
    assert b.new_session and len(b.samples) == 1
    assert not s.decode(_body(acc_t=[0.02], accX=[0], accY=[0], accZ=[9.8]), now=0.2).new_session


def test_push_keep_true_style_resend_only_new_released():
    s = PhyphoxPushStream()
    acc = dict(accX=[0, 0, 0], accY=[0, 0, 0], accZ=[9.8, 9.8, 9.8])
    s.decode(_body(acc_t=[1.0, 1.01], **{k: v[:2] for k, v in acc.items()}), now=0)
    b = s.decode(_body(acc_t=[1.0, 1.01, 1.02], **acc), now=0.1)
    assert [x.time_ms for x in b.samples] == [1020.0] and s.counts["duplicate"] == 2


def test_push_new_session_by_time_start_or_model():
    def body(t0, n=5, start=100.0, model="Pixel 7"):
        t = [t0 + 0.01 * i for i in range(n)]
        return _body(acc_t=t, accX=[0] * n, accY=[0] * n, accZ=[9.8] * n, model=model,
                     timeinfo={"now": start + t0, "events": [
                         {"event": "START", "experimentTime": 0, "systemTime": start}]})
    s = PhyphoxPushStream()
    assert s.decode(body(0.01), now=0).new_session
    for k in range(1, 40):
        assert not s.decode(body(0.1 * k), now=0).new_session
    # a pause and resume adds a START at a later experiment time: same session
    resumed = json.loads(body(4.0))
    resumed["timeinfo"]["events"] += [{"event": "PAUSE", "experimentTime": 3.95,
                                       "systemTime": 104.0},
                                      {"event": "START", "experimentTime": 3.95,
                                       "systemTime": 110.0}]
    assert not s.decode(json.dumps(resumed).encode(), now=0).new_session
    assert s.unix_base_s == pytest.approx(110.0 - 3.95)
    # a new START systemTime (cleared / new experiment): new session, nothing dropped
    b = s.decode(body(4.1, start=200.0), now=0)
    assert b.new_session and len(b.samples) == 5
    # experiment time back near 0 (no timeinfo): new session, old times not duplicates
    raw = json.loads(body(0.0))
    del raw["timeinfo"]
    for k in range(1, 40):
        s.decode(body(4.1 + 0.1 * k, start=200.0), now=0)
    b = s.decode(json.dumps(raw).encode(), now=0)
    assert b.new_session and len(b.samples) == 5 and s.counts["duplicate"] == 0
    # another phone model: new session
    assert s.decode(body(0.1, start=200.0, model="iPhone14,2"), now=0).new_session
    assert s.counts["sessions"] == 4


# ------------------------------------------------------------------ poll: pieces

def test_parse_base_url():
    assert parse_base_url("http://192.168.1.5:8080") == ("192.168.1.5", 8080)
    assert parse_base_url("http://10.0.0.2/") == ("10.0.0.2", 80)
    assert parse_base_url("192.168.1.5:8080") == ("192.168.1.5", 8080)
    for bad in ("https://1.2.3.4:8080", "http://1.2.3.4:8080/get", "http://1.2.3.4/?a=1",
                "http://u:p@1.2.3.4", "http://:8080", "", "http://1.2.3.4:70000",
                "ftp://1.2.3.4"):
        with pytest.raises(ValueError) as ei:
            parse_base_url(bad)
        assert "http" in str(ei.value)


def test_parse_config_and_the_notes_get_reply():
    cfg = {"title": "Acceleration with g", "buffers": [{"name": "acc_time", "size": 0}],
           "inputs": [{"source": "accelerometer", "outputs": [
               {"x": "accX"}, {"y": "accY"}, {"z": "accZ"}, {"t": "acc_time"}]},
               {"source": "location", "outputs": [{"lat": "lat"}]}]}
    found, sizes, missing = parse_config(cfg)
    assert found == {"ACC": {"t": "acc_time", "x": "accX", "y": "accY", "z": "accZ"}}
    assert missing == ["gyroscope", "magnetic_field", "attitude"]
    reply = json.loads("""{"buffer":{
"acc_time":{"size":0,"updateMode":"partial", "buffer":[1.2349871E1,1.2354863E1,1.2359855E1]},
"accX":{"size":0,"updateMode":"partial", "buffer":[4.3102264E-2,4.1906738E-2,4.5497131E-2]},
"accY":{"size":0,"updateMode":"partial", "buffer":[-1.1849213E-1,-1.1729431E-1,-1.1968994E-1]},
"accZ":{"size":0,"updateMode":"partial", "buffer":[9.8124084E0,9.8100128E0,9.8136062E0]}},
"status":{"session":"3fa91c", "measuring":true, "timedRun":false, "countDown":0}}""")
    got = []
    p = PhyphoxPoller("http://127.0.0.1:9", lambda s, n: got.append((s, n)))
    p.sensors = found
    p._threshold = {"ACC": 12.345}
    p._take(reply["buffer"], {"ACC": 12.345})
    (samples, new), = got
    assert new and [s.time_ms for s in samples] == pytest.approx([12349.871, 12354.863,
                                                                  12359.855])
    assert samples[0].values == (4.3102264e-2, -1.1849213e-1, 9.8124084)
    assert p._threshold["ACC"] == 12.359855
    assert java_float(9.8066502) == "9.8066502E0" and java_float(-0.0431) == "-4.3100000E-2"


# ------------------------------------------------------------------ poll: fake phone

ACC_NAMES = {"t": "myAccTime", "x": "ax", "y": "ay", "z": "az"}
NAMES = {"accelerometer": ACC_NAMES,
         "gyroscope": {"t": "gT", "x": "gx", "y": "gy", "z": "gz"},
         "magnetic_field": {"t": "magnetT", "x": "mx", "y": "my", "z": "mz"},
         "attitude": {"t": "q_t", "x": "qx", "y": "qy", "z": "qz", "abs": "qw"}}
TAG_OF = {"accelerometer": "ACC", "gyroscope": "GYR", "magnetic_field": "MAG",
          "attitude": "ORI"}


def _fake_sensors(trial, names=NAMES):
    out = []
    for source, nm in names.items():
        tag = TAG_OF[source]
        comps = ("abs", "x", "y", "z") if tag == "ORI" else ("x", "y", "z")
        out.append(FakeSensor(source, nm, trial.t[tag],
                              {c: trial.v[tag][:, j] for j, c in enumerate(comps)}))
    return out


class Collector:
    def __init__(self):
        self.batches: list[tuple[list, bool]] = []
        self.statuses: list[dict] = []

    def on_samples(self, samples, new_session):
        self.batches.append((list(samples), new_session))

    def on_status(self, st):
        json.dumps(st)
        self.statuses.append(st)

    def samples(self, since=0):
        return [s for b, _ in self.batches[since:] for s in b]

    def count(self):
        return sum(len(b) for b, _ in self.batches)


async def _until(cond, timeout=5.0, what="condition"):
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


def _check_stream(trial, samples, tags=("ACC", "GYR", "MAG", "ORI"), rtol=2e-7):
    by = _by_tag(samples)
    for tag in tags:
        t_ms, v = expected(trial, tag)
        got_t = np.array([s.time_ms for s in by[tag]])
        assert len(got_t) == len(t_ms), tag
        assert np.all(np.diff(got_t) > 0), f"{tag} not in order / repeated"
        np.testing.assert_allclose(got_t, t_ms, rtol=1e-7, atol=1e-6)
        got_v = np.array([s.values for s in by[tag]])
        np.testing.assert_allclose(got_v, v, rtol=rtol, atol=1e-6)


def _run(scenario):
    return asyncio.run(asyncio.wait_for(scenario(), 20))


@pytest.mark.parametrize("ios", [False, True], ids=["android", "ios"])
def test_poller_streams_a_trial_once_in_order(shared_dir, ios):
    trial = _trial(shared_dir, "iPhone5_Guillaume_NoDist_texting" if ios
                   else "Nexus5_Guillaume_NoDist_ar", seconds=12)
    col = Collector()

    async def scenario():
        with FakePhyphox(_fake_sensors(trial), speed=25.0, ios=ios, delay_s=0.003,
                         model="Nexus 5") as fake:
            p = PhyphoxPoller(fake.url, col.on_samples, col.on_status)
            task = asyncio.create_task(p.run())
            total = sum(len(expected(trial, t)[0]) for t in TAG_OF.values())
            await _until(lambda: col.count() >= total, 8, "all samples")
            await asyncio.sleep(0.1)
            p.stop()
            await asyncio.wait_for(task, 1.0)
            return fake, p

    fake, p = _run(scenario)
    # custom buffer names found via /config; start sent once as it was not measuring
    st = p.status()
    assert st["sensors"]["accelerometer"] == ACC_NAMES and st["missing"] == []
    assert fake.starts == 1 and sum(r.startswith("/control?cmd=start") for r in fake.requests) == 1
    assert fake.requests[0] == "/config"
    gets = [r for r in fake.requests if r.startswith("/get")]
    assert "myAccTime=full" in gets[0] and "ax=full" in gets[0]
    assert any("ax=" in g and "%7CmyAccTime" in g for g in gets[1:])
    # one request in flight, ever
    assert fake.max_in_flight == 1 and p.max_in_flight == 1
    _check_stream(trial, col.samples())
    assert col.batches[0][1] and not any(n for _, n in col.batches[1:])
    for b, _ in col.batches:
        assert [s.time_ms for s in b] == sorted(s.time_ms for s in b)
    assert st["device_model"] == "Nexus 5" and st["session"] == "3fa91c"
    assert 90 < st["rate_hz"]["ACC"] < 110 and st["gaps"] == 0
    if ios:
        assert st["truncated"] > 0       # uneven buffers were cut, and nothing was lost
    assert st["state"] in ("measuring", "stopped")


def test_poller_accelerometer_only_session_change_and_stop(shared_dir):
    trial = _trial(shared_dir, "Nexus5_Guillaume_NoDist_phoning", seconds=3)
    trial2 = _trial(shared_dir, "Nexus5_Guillaume_NoDist_runninghand", seconds=2)
    only_acc = {"accelerometer": {"t": "acc_time", "x": "accX", "y": "accY", "z": "accZ"}}
    col = Collector()

    async def scenario():
        with FakePhyphox(_fake_sensors(trial, only_acc), measuring=True,
                         speed=10.0) as fake:
            p = PhyphoxPoller(fake.url, col.on_samples, col.on_status)
            task = asyncio.create_task(p.run())
            n1 = len(trial.t["ACC"])
            await _until(lambda: col.count() >= n1, 5, "first session")
            assert fake.starts == 1            # already measuring: no start sent
            assert not any("cmd=start" in r for r in fake.requests)
            assert p.status()["missing"] == ["gyroscope", "magnetic_field", "attitude"]
            # the student pauses the phone that was measuring when polled: the pause is
            # theirs (a start was sent at once, and the phone measured on)
            fake._stop()
            await _until(lambda: p.status()["state"] == "not measuring", 5, "the pause seen")
            await asyncio.sleep(0.3)
            assert fake.starts == 1 and not any("cmd=start" in r for r in fake.requests)
            fake._start()                       # and starts it again on the phone
            starts = fake.starts
            first_batches = len(col.batches)
            configs = fake.requests.count("/config")
            # the phone restarts its server with another experiment
            fake.new_session("8812ab", _fake_sensors(trial2, NAMES))
            total2 = sum(len(expected(trial2, t)[0]) for t in TAG_OF.values())
            await _until(lambda: sum(len(b) for b, _ in col.batches[first_batches:])
                         >= total2, 5, "second session")
            assert fake.requests.count("/config") > configs
            assert fake.starts == starts + 1   # started by the poller in the new session
            t0 = time.monotonic()
            p.stop()
            await asyncio.wait_for(task, 1.0)
            assert time.monotonic() - t0 < 1.0
            return p, first_batches

    p, first_batches = _run(scenario)
    _check_stream(trial, col.samples()[:len(trial.t["ACC"])], tags=("ACC",))
    assert col.batches[first_batches][1]       # new_session on the first batch after
    assert sum(n for _, n in col.batches) == 2
    _check_stream(trial2, col.samples(first_batches))
    st = p.status()
    assert st["session"] == "8812ab" and st["state"] == "stopped"
    assert st["counts"]["session_changes"] == 1


def test_poller_unreachable_then_back(shared_dir, caplog):
    trial = _trial(shared_dir, "iPhone4S_Guillaume_NoDist_texting", seconds=6)
    col = Collector()
    caplog.set_level(logging.INFO, logger="app.sources.phyphox_poll")

    async def scenario():
        fake = FakePhyphox(_fake_sensors(trial), measuring=True, speed=0.0)
        fake.serve()
        try:
            p = PhyphoxPoller(fake.url, col.on_samples, col.on_status,
                              retry_min_s=0.05, retry_max_s=0.2)
            task = asyncio.create_task(p.run())
            fake.advance(2.0)
            await _until(lambda: col.count() >= 4 * 190, 5, "first part")
            fake.go_away()                         # phone locked: server gone
            await _until(lambda: p.status()["state"] == "unreachable", 3, "unreachable")
            st = p.status()
            assert "refused" in st["status"] and st["last_error"].startswith("unreachable")
            assert "locked screen" in st["status"]      # the likely cause on a phone, named
            r0 = p.requests
            await asyncio.sleep(0.6)
            assert p.requests >= r0 + 2            # retries, with backoff
            assert p.requests <= r0 + 12
            fake.advance(4.5)                      # the rest of the trial
            fake.come_back()                       # same port, same session, stopped
            await _until(lambda: p.status()["state"] == "measuring", 5, "back")
            assert fake.starts == 2                # measurement started again
            total = sum(len(expected(trial, t)[0]) for t in TAG_OF.values())
            await _until(lambda: col.count() >= total, 5, "the rest")
            p.stop()
            await asyncio.wait_for(task, 1.0)
            return p
        finally:
            fake.go_away()

    p = _run(scenario)
    _check_stream(trial, col.samples(), rtol=1e-6)   # nothing lost, nothing twice
    assert sum(n for _, n in col.batches) == 1       # same session: no reset
    assert p.status()["session"] == "3fa91c" and p.max_in_flight == 1
    assert not any(r.exc_info for r in caplog.records)
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "unreachable" in warnings[0].getMessage()
    states = [s["state"] for s in col.statuses]
    assert states.count("unreachable") == 1


def test_poller_timeout_slow_phone_and_prompt_stop(shared_dir):
    trial = _trial(shared_dir, "Nexus5_Guillaume_NoDist_ar", seconds=1)
    col = Collector()

    async def scenario():
        with FakePhyphox(_fake_sensors(trial), measuring=True, delay_s=0.6) as fake:
            p = PhyphoxPoller(fake.url, col.on_samples, col.on_status, timeout_s=0.3,
                              retry_min_s=0.05, retry_max_s=0.1)
            task = asyncio.create_task(p.run())
            await _until(lambda: p.status()["state"] == "unreachable", 3, "timeout")
            assert "no reply within 0.3 s" in p.status()["status"]
            fake.delay_s = 0.0
            await _until(lambda: p.status()["state"] == "measuring", 5, "recovery")
            # stop while a slow request is in flight
            fake.delay_s = 5.0
            await asyncio.sleep(0.2)
            t0 = time.monotonic()
            threading.Thread(target=p.stop).start()       # from another thread too
            await asyncio.wait_for(task, 1.0)
            assert time.monotonic() - t0 < 1.0
            fake.delay_s = 0.0

    _run(scenario)


def test_poller_no_accelerometer_and_not_phyphox():
    col = Collector()

    async def scenario():
        gyro_only = [FakeSensor("gyroscope", {"t": "t", "x": "x", "y": "y", "z": "z"},
                                [0.1], {"x": [0], "y": [0], "z": [0]})]
        with FakePhyphox(gyro_only) as fake:
            p = PhyphoxPoller(fake.url, col.on_samples, col.on_status)
            task = asyncio.create_task(p.run())
            await _until(lambda: p.status()["state"] == "no accelerometer", 3, "refusal")
            assert "gyroscope" in p.status()["detail"]
            p.stop()
            await asyncio.wait_for(task, 1.0)

    _run(scenario)
    assert col.count() == 0


@pytest.mark.parametrize("ios", [False, True], ids=["android", "ios"])
def test_poller_follows_a_clear_and_refuses_what_is_not_phyphox(shared_dir, tmp_path, ios):
    trial = _trial(shared_dir, "iPhone5_Guillaume_NoDist_ar", seconds=2)
    only_acc = {"accelerometer": ACC_NAMES}
    col = Collector()
    n = len(trial.t["ACC"])

    async def scenario():
        with FakePhyphox(_fake_sensors(trial, only_acc), measuring=True,
                         speed=10.0, ios=ios) as fake:
            p = PhyphoxPoller(fake.url, col.on_samples, col.on_status)
            p.time_check_s = 0.1       # iOS: the clear is seen in /time
            task = asyncio.create_task(p.run())
            await _until(lambda: col.count() >= n, 5, "first run")
            fake.clear()                           # the user pressed clear on the phone
            await _until(lambda: col.count() >= 2 * n, 5, "after the clear")
            p.stop()
            await asyncio.wait_for(task, 1.0)
            return p
    p = _run(scenario)
    flags = [nw for _, nw in col.batches]
    assert flags[0] and sum(flags) == 2
    k = next(i for i, f in enumerate(flags) if f and i > 0)
    _check_stream(trial, col.samples()[:n], tags=("ACC",))
    _check_stream(trial, col.samples(k), tags=("ACC",))
    assert p.status()["counts"]["cleared"] == 1

    # an ordinary web server is no phyphox: a clear error state, retried, no exception
    import functools
    from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
    (tmp_path / "index.html").write_text("<html></html>")

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *a):
            pass
    srv = ThreadingHTTPServer(("127.0.0.1", 0),
                              functools.partial(Quiet, directory=str(tmp_path)))
    th = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05},
                          daemon=True)
    th.start()

    async def other():
        p = PhyphoxPoller(f"http://127.0.0.1:{srv.server_address[1]}", col.on_samples)
        task = asyncio.create_task(p.run())
        await _until(lambda: p.status()["state"] == "error", 3, "error state")
        assert "404" in p.status()["detail"]
        p.stop()
        await asyncio.wait_for(task, 1.0)
    try:
        _run(other)
    finally:
        srv.shutdown()
        srv.server_close()


def test_http_get_keep_alive_chunked_and_garbage():
    from app.sources.phyphox_poll import Unreachable, http_get
    replies = {
        b"/ka": b"HTTP/1.1 200 OK\r\nContent-Length: 11\r\n\r\n{\"a\": true}",
        b"/chunked": (b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n"
                      b"4\r\n{\"a\"\r\n7\r\n: true}\r\n0\r\n\r\n"),
        b"/garbage": b"SSH-2.0-OpenSSH\r\n",
    }

    async def handle(reader, writer):
        line = await reader.readline()
        while (await reader.readline()) not in (b"\r\n", b""):
            pass
        path = line.split()[1]
        writer.write(replies[path])
        await writer.drain()
        if path != b"/ka":                     # /ka keeps the connection open
            writer.close()
        else:
            await asyncio.sleep(5)
            writer.close()

    async def scenario():
        srv = await asyncio.start_server(handle, "127.0.0.1", 0)
        port = srv.sockets[0].getsockname()[1]
        t0 = time.monotonic()
        assert await http_get("127.0.0.1", port, "/ka", 3) == (200, b'{"a": true}')
        assert time.monotonic() - t0 < 1.0
        assert await http_get("127.0.0.1", port, "/chunked", 3) == (200, b'{"a": true}')
        with pytest.raises(Unreachable):
            await http_get("127.0.0.1", port, "/garbage", 3)
        srv.close()
        await srv.wait_closed()
    _run(scenario)


# ------------------------------------------------------------------ the fake itself

def test_fake_phone_get_semantics():
    t = np.array([0.5, 1.0, 1.5, 2.0])
    s = FakeSensor("accelerometer", {"t": "acc_time", "x": "accX", "y": "accY", "z": "accZ"},
                   t, {"x": t * 10, "y": t * 0, "z": t * 0 + 9.8})
    with FakePhyphox([s], measuring=True) as fake:
        fake.advance(1.6)
        with httpx.Client(base_url=fake.url, timeout=3) as c:
            r = c.get("/get?acc_time=1.0&accX=1.0|acc_time&nope=1").json()
            assert r["buffer"]["acc_time"]["buffer"] == [1.5]
            assert r["buffer"]["accX"] == {"size": 0, "updateMode": "partial",
                                           "buffer": [15.0]}
            assert "nope" not in r["buffer"] and r["status"]["measuring"] is True
            assert c.get("/get?accX").json()["buffer"]["accX"]["updateMode"] == "single"
            assert c.get("/get?accX=1|nope").status_code == 400
            assert c.get("/get?accX=abc").status_code == 500
            c.get("/control?cmd=clear")
            r = c.get("/get?acc_time=1.5").json()["buffer"]["acc_time"]
            assert r["updateMode"] == "full" and r["buffer"] == []
            fake.advance(1.0)                       # time restarted at 0 by the clear
            assert c.get("/get?acc_time=0.5").json()["buffer"]["acc_time"] == {
                "size": 0, "updateMode": "partial", "buffer": [1.0]}
            assert c.get("/meta").json()["deviceModel"] == "Pixel 7"
            assert c.get("/time").json()[0]["event"] == "START"
            assert c.get("/config").json()["inputs"][0]["source"] == "accelerometer"
        # the in-flight count does see a client that does not wait for its replies
        assert fake.max_in_flight == 1
        fake.delay_s = 0.3
        th = [threading.Thread(target=httpx.get, args=(fake.url + "/meta",)) for _ in "ab"]
        for x in th:
            x.start()
        for x in th:
            x.join()
        assert fake.max_in_flight == 2


@pytest.mark.parametrize("extra,reason", [
    ({"model": 5}, "bad_model"), ({"timeinfo": [1]}, "bad_timeinfo"),
    ({"gyr_t": [1.0], "gyrX": "oops", "gyrY": [0], "gyrZ": [0]}, "bad_buffer"),
])
def test_push_a_bad_part_loses_nothing_that_was_good(extra, reason):
    """One part of the wrong type (the model, the timeinfo, one sensor's buffer) is counted
    by its reason and left out; the POST's good buffers are used. Before, the whole POST was
    refused with 400, and the phone (keep="false") had already cleared what it sent."""
    stream = PhyphoxPushStream()
    body = json.loads(_body(acc_t=[1.0, 1.01], accX=[0, 0], accY=[0, 0], accZ=[9.8, 9.8]))
    batch = stream.decode(json.dumps({**body, **extra}).encode(), now=0.0)
    assert [(x.tag, x.values) for x in batch.samples] == [("ACC", (0.0, 0.0, 9.8))] * 2
    assert stream.counts[reason] == 1 and stream.counts["posts"] == 1
    assert not any(k.startswith("rejected_") for k in stream.counts)
