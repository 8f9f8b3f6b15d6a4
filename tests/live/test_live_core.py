"""app.live.core: a stream's lines in, the read models out; no server."""

from __future__ import annotations

import numpy as np

from app.estimators import NAMES
from app.live import LiveCore
from harness import feed_lines
from app.sources.sensorfusion import format_line
from app.sources.simulate import simulate


def run(core: LiveCore, lines, size=50):
    s = core.open_session("phone", "test")
    core.start(s)
    for i in range(0, len(lines), size):
        core.process(s, feed_lines(core, s, lines[i:i + size]))
    core.process(s, core.close_session(s))
    return s


def test_a_stream_through_the_core():
    core = LiveCore(None, history_s=5.0)
    raw, recs = [], []
    core.sample_stages.append(lambda s, smp: raw.extend(smp) or smp)
    core.record_listeners.append(lambda s, rec: recs.append(rec))
    lines = simulate(("still",), seed=1).lines()
    bad = ["123\tACC\t1.0", "nonsense"]
    s = run(core, bad + lines)
    st = core.state()
    assert [format_line(x.time_ms, x.tag, x.values) for x in raw] == lines
    assert st["counts"]["lines"] == len(lines) + 2 and st["counts"]["malformed"] == 2
    assert st["counts"]["samples"] == len(lines) == sum(r.n_samples for r in recs)
    assert st["source"] == "phone-disconnected" and st["initialized"]
    assert st["phone_q"] is not None and st["error_to_phone_deg"] < 5.0
    assert set(st["estimators"]) == set(NAMES)
    assert st["acc"]["reason"] in ("used", "norm", "nis")
    w = core.history.pose.window(5.0, 100)
    ok = np.isfinite(w["q"]).all(axis=1)
    assert 2 < len(w) <= 100 and ok[-1]
    assert ok[np.argmax(ok):].all()           # a gap before the alignment, none after
    np.testing.assert_allclose(w["q"][-1], st["q"])
    m = core.history.mag.window(5.0, 100)
    assert len(m) and np.isfinite(m["norm"]).all()
    snap = core.snapshot()
    assert snap.primary == "robust" and snap.acc is not None and snap.mag is not None
    assert s.samples == len(lines)


def test_samples_of_a_replaced_stream_are_not_processed():
    core = LiveCore(None)
    old = core.open_session("demo", "demo")
    released = feed_lines(core, old, simulate(("still",), seed=1).lines()[:300])
    core.open_session("phone", "new")
    assert core.process(old, released) is None
    assert core.state()["counts"]["samples"] == 0


def test_params_view_and_presets_of_the_builtins():
    core = LiveCore(None)
    core.apply(core.validate({"use_mag": False, "primary": "lab"}))
    v = core.params_view()
    assert v["primary"] == "lab" and v["use_mag"] is False and v["bases"]["lab"] == "lab"
    core.ensemble.add("lab-approx", "lab", {"time_update": "approx"})
    assert "lab-approx" in core.params_view()["estimators"]
    sec = core.preset_sections()
    assert "lab-approx" not in sec and sec["primary"] == "lab" and sec["lab"]["use_mag"] is False


def test_a_replaced_streams_reason_names_the_new_phone_by_its_app():
    """The reason a stream ended goes into recordings the class downloads: the phone that
    replaced it is named by its app, not by its address (a reviewer found
    "replaced by phone 192.168.1.23 (Sensor Logger)" in a recording's end event)."""
    core = LiveCore(None)
    old = core.open_session("demo", "simulated phone")
    core.open_session("phone", "192.168.1.23 (Sensor Logger)", phone_app="sensorlogger")
    assert old.close_reason == "replaced by a phone (Sensor Logger)", old.close_reason
    replay = core.open_session("replay", "walk.txt")
    core.open_session("phone", "127.0.0.1:40000")
    assert "127.0.0.1" not in replay.close_reason and "replaced by a phone" in replay.close_reason


def test_the_phones_own_estimate_says_it_uses_no_sample_not_switched_off():
    """A review: with every sensor switch on, the ``phone`` estimator's accelerometer and
    magnetometer decisions read "switched off". It uses none of the samples (it shows the
    phone's own orientation): its decisions say that; another estimator's switched-off
    sensor still reads "switched off"."""
    from app.live.views import state
    core = LiveCore(None)
    run(core, simulate(("still",), seed=1).lines())
    st = state(core)["estimators"]
    for sensor in ("acc", "mag"):
        assert st["phone"][sensor]["reason"] == "disabled"
        assert "phone's own estimate" in st["phone"][sensor]["text"], st["phone"][sensor]
        assert st["robust"][sensor]["text"] != st["phone"][sensor]["text"]
    core.apply(core.validate({"use_mag": False}))
    run(core, simulate(("still",), seed=2).lines())
    assert state(core)["estimators"]["robust"]["mag"]["text"] == "switched off"
