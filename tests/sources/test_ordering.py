"""SampleOrderer: time order, per-tag clocks, late samples, counters; samples_to_rows."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.sources.samples import Sample
from app.sources.ordering import SampleOrderer, samples_to_rows


def run_all(orderer: SampleOrderer, samples) -> list[Sample]:
    out = []
    for s in samples:
        out.extend(orderer.push(s))
    return out + orderer.flush()


def imu_stream(n: int, start_ms: int = 1_000_000, step_ms: int = 10, acc_offset_ms: int = 0):
    """ACC, GYR every step, MAG every other step, lines in arrival order."""
    out = []
    for k in range(n):
        t = start_ms + k * step_ms
        out.append(Sample(t + acc_offset_ms, "ACC", (0.0, 0.0, 9.81 + k)))
        out.append(Sample(t + 1, "GYR", (0.01 * k, 0.0, 0.0)))
        if k % 2 == 0:
            out.append(Sample(t + 2, "MAG", (0.0, 20.0, -40.0)))
    return out


def leading_mag_stream() -> list[Sample]:
    """ACC and GYR at 200 Hz, MAG at 50 Hz stamped 0.2 s ahead of them when it arrives (as
    in a real log), in arrival order."""
    src = []
    for k in range(300):
        t = 5000 + 5 * k
        src.append(Sample(t, "ACC", (0.0, 0.0, 9.81)))
        src.append(Sample(t, "GYR", (0.0, 0.0, 0.0)))
        if k % 4 == 0:
            src.append(Sample(t + 200, "MAG", (0.0, 20.0, -40.0)))
    return src


def times(samples) -> list[int]:
    return [s.time_ms for s in samples]


def test_in_order_stream_passes_through_unchanged():
    src = imu_stream(50)
    o = SampleOrderer()
    out = run_all(o, src)
    assert out == src
    assert o.counters.late == o.counters.clamped == 0
    assert o.reference_tag == "ACC"
    assert o.offsets == {"ACC": 0.0, "GYR": 0.0, "MAG": 0.0}


def test_push_holds_samples_until_the_window_has_passed():
    o = SampleOrderer(window=0.05)
    assert o.push(Sample(1000, "ACC", (0, 0, 9.8))) == []
    assert o.push(Sample(1030, "ACC", (0, 0, 9.8))) == []
    released = o.push(Sample(1060, "ACC", (0, 0, 9.8)))
    assert times(released) == [1000]          # 1060 - 50 ms reached 1000 only
    assert o.buffered == 2
    assert times(o.flush()) == [1030, 1060]
    assert o.buffered == 0


def test_unsorted_lines_come_out_in_time_order_without_loss():
    src = imu_stream(200)
    rng = random.Random(1)
    # arrival jitter of a few ms between tags: swap neighbours at random
    arrived = list(src)
    for i in range(0, len(arrived) - 1, 2):
        if rng.random() < 0.5:
            arrived[i], arrived[i + 1] = arrived[i + 1], arrived[i]
    o = SampleOrderer()
    out = run_all(o, arrived)
    assert times(out) == sorted(times(src))
    assert sorted(map(repr, out)) == sorted(map(repr, src))
    assert o.counters.late == o.counters.clamped == 0


def test_leading_tag_does_not_make_the_others_late():
    """A real log had MAG stamped ~0.2 s ahead of ACC/GYR when it arrived: the buffer
    waits for the lagging motion tags instead of releasing past them."""
    src = leading_mag_stream()
    o = SampleOrderer(window=0.05)
    out = run_all(o, src)
    assert o.counters.late == o.counters.clamped == 0
    assert times(out) == sorted(times(src))


def test_a_stall_releases_up_to_every_tag_and_nothing_comes_late():
    """The stream stalls (Wi-Fi, a paused app): ``release_held`` lets out what waits for
    the window, not a leading tag's lead. When the queued samples then come on, none is
    late or clamped (releasing the whole buffer made the lagging tags late: 0.2 s here)."""
    src = leading_mag_stream()
    o = SampleOrderer(window=0.05)
    out = []
    for s in src[:400]:
        out.extend(o.push(s))
    held = o.buffered
    reached = min(max(s.time_ms for s in src[:400] if s.tag == tag) for tag in ("ACC", "GYR"))
    released = o.release_held()
    assert released and max(times(released)) == reached and o.buffered < held
    assert o.buffered == sum(1 for s in src[:400] if s.time_ms > reached) > 0   # MAG's lead
    out.extend(released)
    for s in src[400:]:
        out.extend(o.push(s))
    out.extend(o.flush())
    assert o.counters.late == o.counters.clamped == 0
    assert times(out) == sorted(times(src))
    assert SampleOrderer().release_held() == []          # nothing seen yet


def test_silent_motion_tag_is_not_waited_for_longer_than_max_delay():
    o = SampleOrderer(window=0.05, max_delay=0.5)
    o.push(Sample(0, "MAG", (0.0, 20.0, -40.0)))      # MAG then goes silent
    released = []
    for k in range(1, 200):
        released += o.push(Sample(10 * k, "ACC", (0.0, 0.0, 9.81)))
    newest = 10 * 199
    # everything older than newest - (max_delay + window) has been released
    assert released and released[-1].time_ms >= newest - 550
    assert o.buffered <= 56


def test_per_tag_clock_offset_is_detected_and_removed():
    """On one phone ACC ran 131 072 s ahead of GYR/MAG; GPS in Unix-epoch ms."""
    off = 131_072_000
    src = imu_stream(100, acc_offset_ms=0)
    src = [Sample(s.time_ms + off, s.tag, s.values) if s.tag == "ACC" else s for s in src]
    # GYR first so that GYR's clock is the reference
    src[0], src[1] = src[1], src[0]
    src.insert(10, Sample(1_666_000_000_000, "GPS", (58.4, 15.6, 80.0)))
    o = SampleOrderer()
    out = run_all(o, src)
    assert o.reference_tag == "GYR"
    assert o.offsets["GYR"] == 0.0 and o.offsets["MAG"] == 0.0
    assert o.offsets["ACC"] == pytest.approx(131_072.0, abs=0.01)
    assert abs(o.offsets["GPS"]) > 1e9 / 1000
    ts = times(out)
    assert ts == sorted(ts)
    assert max(ts) - min(ts) < 2000          # all on one clock now
    assert o.counters.late == 0
    # the ACC values come out intact, mapped to GYR's clock within a few ms
    accs = [s for s in out if s.tag == "ACC"]
    assert len(accs) == 100 and accs[5].values == (0.0, 0.0, 9.81 + 5)


def test_small_differences_are_not_taken_for_a_clock_offset():
    src = imu_stream(20)
    src.insert(15, Sample(src[14].time_ms + 1500, "PRX", (5.0,)))   # 1.5 s < 2 s threshold
    o = SampleOrderer()
    run_all(o, src)
    assert o.offsets["PRX"] == 0.0


def test_reference_is_the_first_motion_tag_even_after_other_tags():
    o = SampleOrderer()
    out = o.push(Sample(1_666_000_000_000, "GPS", (58.4, 15.6, 80.0)))
    assert out == [] and o.reference_tag is None and o.buffered == 1
    out += run_all(o, imu_stream(10))
    assert o.reference_tag == "ACC"
    assert o.offsets["GPS"] != 0.0
    assert len(out) == 1 + len(imu_stream(10))


def test_stream_without_motion_tags_still_comes_out_at_flush():
    o = SampleOrderer(max_pending=3)
    out = []
    for k in range(5):
        out += o.push(Sample(1000 + 1000 * k, "PRS", (1013.0 + k,)))
    out += o.flush()
    assert [s.values[0] for s in out] == [1013.0 + k for k in range(5)]
    assert o.reference_tag == "PRS"


def test_slightly_late_sample_is_clamped_and_very_late_sample_dropped():
    o = SampleOrderer(window=0.0, late_tolerance=0.1)
    out = []
    for t in (1000, 1010, 1020, 1030):
        out += o.push(Sample(t, "ACC", (0.0, 0.0, 9.81)))
    assert o.last_released == pytest.approx(1.030)
    # 25 ms late: released at once, time clamped to the last released time
    late = o.push(Sample(1005, "GYR", (1.0, 2.0, 3.0)))
    assert [(s.time_ms, s.tag, s.values) for s in late] == [(1030, "GYR", (1.0, 2.0, 3.0))]
    assert o.counters.clamped == 1 and o.counters.late == 0
    # 530 ms late: dropped, counted
    assert o.push(Sample(500, "GYR", (1.0, 2.0, 3.0))) == []
    assert o.counters.late == 1
    assert o.counters.tags["GYR"] == 2


def test_push_line_counts_malformed_lines_by_reason():
    o = SampleOrderer()
    lines = ["1000\tACC\t0\t0\t9.81\n", "1000\tRAWGYR\t1\t2\n", "\n", "1001\tFOO\t1\n",
             "1002\tGYR\t0.1\tx\t0.3\r\n", "abc\tACC\t1\t2\t3\n", "1003\tGYR\t0.1\t0.2\t0.3\r"]
    out = o.push_lines(lines) + o.flush()
    assert [s.tag for s in out] == ["ACC", "GYR"]
    assert dict(o.counters.malformed) == {"wrong_count": 1, "empty": 1, "unknown_tag": 1,
                                          "not_numeric": 1, "bad_time": 1}
    assert o.summary()["malformed"]["wrong_count"] == 1


def test_rates_per_tag():
    o = SampleOrderer()
    run_all(o, imu_stream(100, step_ms=10))
    r = o.rates()
    assert r["ACC"] == pytest.approx(100.0, rel=1e-6)
    assert r["MAG"] == pytest.approx(50.0, rel=1e-6)
    o2 = SampleOrderer()
    o2.push(Sample(0, "ACC", (0.0, 0.0, 9.81)))
    assert math.isnan(o2.rates()["ACC"])


def test_samples_to_rows():
    samples = [Sample(1000, "ACC", (1.0, 2.0, 3.0)), Sample(1001, "GPS", (1.0, 2.0, 3.0)),
               Sample(1002, "GYR", (0.1, 0.2, 0.3)), Sample(1003, "MAG", (10.0, 20.0, 30.0)),
               Sample(1004, "ORI", (1.0, 0.0, 0.0, 0.0))]
    r = samples_to_rows(samples)
    assert len(r) == 4
    np.testing.assert_allclose(r.t, [1.000, 1.002, 1.003, 1.004])
    np.testing.assert_array_equal(r.acc[0], [1.0, 2.0, 3.0])
    assert np.isnan(r.acc[1:]).all() and np.isnan(r.gyr[[0, 2, 3]]).all()
    np.testing.assert_array_equal(r.gyr[1], [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(r.mag[2], [10.0, 20.0, 30.0])
    np.testing.assert_array_equal(r.ori[3], [1.0, 0.0, 0.0, 0.0])
    assert r.ori.shape == (4, 4) and np.isnan(r.ori[:3]).all()
    empty = samples_to_rows([])
    assert len(empty) == 0 and empty.acc.shape == (0, 3)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 40), min_size=1, max_size=300), st.integers(0, 2**32 - 1))
def test_property_bounded_jitter_is_always_sorted_without_loss(jitters, seed):
    """Any arrival order in which each sample is at most 40 ms behind the newest
    comes out sorted, complete and with nothing late (window 50 ms)."""
    rng = random.Random(seed)
    tags = ("ACC", "GYR", "MAG")
    src, newest = [], 0
    for k, j in enumerate(jitters):
        newest += rng.randint(0, 10)
        src.append(Sample(max(0, newest - j), tags[k % 3], (float(k), 0.0, 0.0)))
    o = SampleOrderer(window=0.05, max_delay=10.0)
    out = run_all(o, src)
    assert o.counters.late == o.counters.clamped == 0
    assert times(out) == sorted(times(src))
    assert sorted(s.values[0] for s in out) == [float(k) for k in range(len(src))]


# ---------------------------------------------------------------- clock jumps (issue 10)

def test_one_time_stamp_ten_seconds_ahead_costs_only_that_sample():
    """A digit flip (+10 s on one line) used to make the buffer drop the following
    samples as late; now only the wrong one is dropped, counted as time_jump."""
    stream = imu_stream(1000)
    k = 400
    bad = stream[k]
    stream[k] = Sample(bad.time_ms + 10_000, bad.tag, bad.values)
    o = SampleOrderer(window=0.05)
    out = run_all(o, stream)
    assert len(out) == len(stream) - 1
    assert times(out) == sorted(times(out))
    assert o.counters.late == 0 and o.counters.malformed["time_jump"] == 1
    assert o.counters.jumps == 0


def test_time_stamp_far_in_the_future_or_past_is_a_glitch():
    stream = imu_stream(600)
    stream[100] = Sample(10 ** 13, "GYR", (0.0, 0.0, 0.0))       # absurd, but finite
    stream[300] = Sample(5, "ACC", (0.0, 0.0, 9.81))             # far back
    o = SampleOrderer(window=0.05)
    out = run_all(o, stream)
    assert len(out) == len(stream) - 2
    assert o.counters.late == 0 and o.counters.malformed["time_jump"] == 2


@pytest.mark.parametrize("tag, shift_ms", [("ACC", 10_000), ("GYR", 10_000), ("MAG", -10_000),
                                             ("GYR", -10_000)])
def test_a_wrong_first_stamp_leaves_the_sensors_in_step(tag, shift_ms):
    """The first sample of a sensor stamped 10 s off. Its offset was read from that one
    stamp, so the sensor looked like one on another clock; each sample after it was a
    jump, and when the stream's very first sample was the wrong one, every other sensor's
    offset was read against it: ACC and GYR ended 10 s apart for the rest of the session
    (120 re-anchorings in 3 s of a live TCP stream, a review found). Now the sensors stay
    in step: one offset for all, at most one re-anchoring, nothing dropped as late."""
    stream = imu_stream(600)
    k = next(i for i, x in enumerate(stream) if x.tag == tag)
    stream[k] = Sample(stream[k].time_ms + shift_ms, tag, stream[k].values)
    o = SampleOrderer(window=0.05)
    out = run_all(o, stream)
    assert times(out) == sorted(times(out))
    assert o.counters.jumps <= 1 and o.counters.late == 0
    assert len(set(o.offsets.values())) == 1, o.offsets          # one clock for all three
    assert len(out) >= len(stream) - 1
    # after the first second every sensor's samples come on their own intervals, in step
    late = [x for x in out[len(out) // 3:]]
    for t in ("ACC", "GYR", "MAG"):
        d = np.diff(times([x for x in late if x.tag == t]))
        assert d.min() >= 0 and np.median(d) == (10 if t != "MAG" else 20)
    acc = times([x for x in late if x.tag == "ACC"])
    gyr = times([x for x in late if x.tag == "GYR"])
    assert abs(np.median(np.array(gyr[:50]) - np.array(acc[:50]))) <= 2     # GYR 1 ms after ACC


def test_a_real_clock_jump_is_reanchored_without_loss():
    """The whole stream moves by +60 s (or back by 30 s): nothing is dropped, the jump is
    counted. Forward, the times are the phone's. Back, the stream's time goes on 1 ms after
    the last sample released, with the phone's intervals: before, the time went back and
    every filter skipped each row as late until the new clock passed the old one (a 10 s
    step back froze the estimate for 10 s, and ``orientlab estimate`` lost the rest)."""
    for shift in (60_000, -30_000):
        before = imu_stream(300)
        after = [Sample(s.time_ms + 3000 + shift, s.tag, s.values) for s in imu_stream(300)]
        o = SampleOrderer(window=0.05)
        out = run_all(o, before + after)
        assert len(out) == len(before) + len(after)
        assert o.counters.late == 0 and o.counters.jumps == 1
        assert sum(o.counters.malformed.values()) == 0
        n = len(before)
        assert times(out[:n]) == sorted(times(before))
        t_after = sorted(times(after))
        if shift > 0:
            assert times(out[n:]) == t_after and o.counters.back_ms == 0
        else:
            assert times(out) == sorted(times(out))                      # never back
            assert times(out)[n] == times(out)[n - 1] + 1
            assert np.allclose(np.diff(times(out[n:])), np.diff(t_after))
            assert o.counters.back_ms == times(out)[n] - t_after[0]


def test_a_frozen_clock_cannot_grow_the_buffer_without_bound():
    """A phone whose clock stands still stamps every sample with one time: the release
    limit never moves, so before, every sample stayed in the buffer (390 MB in 20 s of a
    fast stream). The buffer is bounded; the samples go on in order, counted."""
    o = SampleOrderer(window=0.05, max_buffered=1000)
    out = []
    for k in range(10_000):
        out += o.push(Sample(5000, ("ACC", "GYR", "MAG")[k % 3], (0.0, 0.0, 9.81)))
    assert o.buffered <= 1000
    assert len(out) >= 9000 and o.counters.forced == len(out)
    assert [s.time_ms for s in out] == sorted(s.time_ms for s in out)


def _tagged(tags_hz: dict[str, float], t0_s: float, t1_s: float) -> list[Sample]:
    out = []
    for tag, hz in tags_hz.items():
        n = int(round((t1_s - t0_s) * hz))
        out += [Sample(int(round((t0_s + i / hz) * 1000)), tag, (0.0, 0.0, 1.0)) for i in range(n)]
    return sorted(out, key=lambda s: s.time_ms)


def test_a_sensor_that_stops_while_the_others_go_on_is_stopped_and_its_rate_zero():
    o = SampleOrderer()
    for s in _tagged({"ACC": 100, "GYR": 100, "MAG": 50}, 0.0, 5.0):
        o.push(s)
    assert o.stopped() == frozenset()
    for s in _tagged({"ACC": 100, "GYR": 100}, 5.0, 7.5):      # the field switched off
        o.push(s)
    assert o.stopped() == frozenset()                        # 2.5 s: could be a batch
    for s in _tagged({"ACC": 100, "GYR": 100}, 7.5, 9.0):
        o.push(s)
    assert o.stopped() == {"MAG"}
    r = o.rates()
    assert r["MAG"] == 0.0 and r["ACC"] == pytest.approx(100.0, rel=0.02)
    assert o.summary()["rates_hz"]["MAG"] == pytest.approx(50.0, rel=0.02)   # a log's own rate
    for s in _tagged({"ACC": 100, "GYR": 100, "MAG": 50}, 9.0, 9.5):        # back on
        o.push(s)
    assert o.stopped() == frozenset() and o.rates()["MAG"] > 0


def test_a_slow_sensor_is_stopped_only_after_five_of_its_periods():
    o = SampleOrderer()
    for s in _tagged({"ACC": 100, "ORI": 0.25}, 0.0, 12.0):      # ORI every 4 s
        o.push(s)
    assert o.stopped() == frozenset()        # ORI 4 s behind ACC: within 5 periods (20 s)
    for s in _tagged({"ACC": 100}, 12.0, 30.0):
        o.push(s)
    assert o.stopped() == {"ORI"}


def test_a_slow_sensors_first_sample_is_no_stop():
    """A sensor set to 0.2 Hz (Sensor Logger allows it): with one sample it has no period
    yet, so the others going on for 4.9 s do not make it 'stopped'."""
    o = SampleOrderer()
    for s in _tagged({"ACC": 100, "MAG": 0.2}, 0.0, 4.9):
        o.push(s)
    assert o.stopped() == frozenset()
    for s in _tagged({"ACC": 100, "MAG": 0.2}, 5.0, 9.9):
        o.push(s)
    assert o.stopped() == frozenset() and o.rates()["MAG"] == pytest.approx(0.2)


def test_held_and_released_samples_go_back_on_their_own_clocks():
    """A recording begun into its stream writes what the buffer holds (and what it has
    released but is not filtered yet) into its log: each on its own sensor's clock, as it
    came in, as every later line is (on the reference clock they were 180° off in a
    reviewer's re-run of a phone whose ACC runs 131072 s ahead)."""
    o = SampleOrderer(window=0.05)
    ahead = 131_072_000
    came: list[Sample] = []
    released: list[Sample] = []
    for k in range(40):
        for s in (Sample(1000 + 5 * k, "GYR", (0.0, 0.0, 0.0)),
                  Sample(1000 + 5 * k + ahead, "ACC", (0.0, 0.0, 9.81))):
            came.append(s)
            released.extend(o.push(s))
    held = o.held()
    assert held and released and o.offsets["ACC"] == pytest.approx(ahead / 1000.0)
    assert any(s.tag == "ACC" for s in held)
    back = o.unmapped(released) + held
    assert sorted((s.time_ms, s.tag) for s in back) == sorted((s.time_ms, s.tag) for s in came)
    assert len(o.held()) == len(held)          # a copy: nothing released
