"""What-if for a first-time user (issue 21, item 4), on the toolkit's service as the page
and the API use it: the change the page is pre-filled with makes a visible difference
on the demo and on a real log, and the re-run's error agrees with what the live filters
showed over the same recording, or the reason is reported beside it."""

from __future__ import annotations

import asyncio
import shutil

import numpy as np
import pytest

from app.live.core import LiveCore
from app.sources.samples import Sample
from app.sources.simulate import Simulation, stream
from app.toolkit.session_recorder import RecordingService
from app.toolkit.whatif import AGREE_DEG, WhatIfService, first_suggestion

WALK = "alekodu_activityrecognition/sensorLog_20221024T182635_walking_hand.txt"
VISIBLE_DEG = 2.0      # a difference anyone sees in a table rounded to 0.1°


def demo_recording(folder, name="demo", warm_s=38.0, seconds=38.0, chunk_ms=50):
    """The dashboard's demo as the server runs it (the live core, the recorder on its
    hooks, the truth beside the estimates), recorded for ``seconds`` after ``warm_s`` of
    stream: the live filters had been running before the recording began, as in class.
    Returns the core and the recording service (not real time: as fast as it computes)."""
    core = LiveCore(None)
    recs = RecordingService(core, folder)
    sim = Simulation()
    boot = sim.config.boot_ms
    session = core.open_session("demo", "simulated phone",
                                truth=lambda ms: sim.truth((np.asarray(ms, float) - boot) / 1000.0))
    core.start(session)
    gen = stream(0)
    pending = next(gen)
    t0 = pending[0]
    due = t0
    started = False
    while pending[0] < t0 + (warm_s + seconds) * 1000:
        due += chunk_ms
        if not started and due >= t0 + warm_s * 1000:
            recs.start(name)
            started = True
        chunk = []
        while pending[0] <= due:
            chunk.append(Sample(*pending))
            pending = next(gen)
        core.process(session, core.feed(session, chunk))
    recs.stop()
    return core, recs


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rec")
    core, recs = demo_recording(folder)
    return core, recs, WhatIfService(core, recs.files)


def _rerun(svc, name, patch):
    return asyncio.run(svc.rerun(name, patch))


def _patch(svc):
    est, param, value = first_suggestion(svc.specs(), svc.core.ensemble.primary)
    return est, {est: {param: value}}


def test_the_first_suggested_change_shows_on_the_demo(demo):
    core, recs, svc = demo
    est, patch = _patch(svc)
    out = _rerun(svc, "demo", patch)
    assert out["reference"] == "truth"
    e = out["estimators"][est]["before"]["error_to_truth_deg"]["rms"]
    a = out["estimators"][est]["after"]["error_to_truth_deg"]["rms"]
    print(f"{est} {patch[est]}: {e:.2f}° -> {a:.2f}°")
    assert abs(a - e) >= VISIBLE_DEG, (patch, e, a)


def test_the_first_suggested_change_shows_on_a_real_log(demo, shared_dir, tmp_path):
    """A real Sensor Fusion log has neither truth nor ORI: no error can be scored, so the
    table reports how far the change moves the estimate; the suggestion must move it."""
    core, recs, _ = demo
    shutil.copy(shared_dir / "data" / "sensorfusion-app" / WALK, tmp_path / "walk.txt")
    svc = WhatIfService(core, RecordingService(LiveCore(None), tmp_path).files)
    est, patch = _patch(svc)
    out = _rerun(svc, "walk", patch)
    assert out["reference"] is None and out["notes"] and "no reference" in out["notes"][0]
    change = out["estimators"][est]["change_deg"]["rms"]
    print(f"{est} {patch[est]}: the estimate moves {change:.2f}° RMS")
    assert change >= VISIBLE_DEG


def test_the_rerun_agrees_with_the_live_readout(demo):
    """The recording begins 38 s into the demo's stream and keeps the live filters' state
    then: every estimator's re-run goes on from it and agrees with what the live filter
    showed, at the rows the recording kept its estimates for (within AGREE_DEG or
    AGREE_REL of the live error, the larger), with no note."""
    core, recs, svc = demo
    out = _rerun(svc, "demo", None)
    key = "error_to_truth_deg"
    assert any("goes on from the live filters' state" in n for n in out["notes"]), out["notes"]
    for name, e in out["estimators"].items():
        if e.get("reference"):
            continue
        live, before = e["live"][key]["rms"], e["before"][key]["rms"]
        print(f"{name}: live {live:.2f}°, re-run {before:.2f}°, note {e['note']!r}")
        assert e["before"]["warm"] and e["note"] is None, name


def test_a_recording_begun_in_motion_reruns_from_the_live_state_or_says_why_not(tmp_path):
    """Begun mid-turn, the re-run goes on from the live filters' state (the gyroscope bias
    they had learned, the demo's is ~3°/s) and agrees with what they showed. Without the
    state file (an older recording) it starts with no learned bias and is far worse than
    the live filter was: the answer says so."""
    core, recs = demo_recording(tmp_path, "moving", warm_s=45.0, seconds=15.0)
    key = "error_to_truth_deg"
    e = _rerun(WhatIfService(core, recs.files), "moving", None)["estimators"][core.ensemble.primary]
    print("warm:", e["live"][key]["rms"], e["before"][key]["rms"], e["note"])
    assert e["before"]["warm"] and e["note"] is None
    assert abs(e["before"][key]["rms"] - e["live"][key]["rms"]) < AGREE_DEG
    (tmp_path / "moving.state.npz").unlink()
    e = _rerun(WhatIfService(core, recs.files), "moving", None)["estimators"][core.ensemble.primary]
    print("cold:", e["live"][key]["rms"], e["before"][key]["rms"], e["note"])
    assert not e["before"]["warm"]
    assert e["before"][key]["rms"] > e["live"][key]["rms"] + 1.0
    assert "cold" in e["note"] and f"live {e['live'][key]['rms']:.1f}°" in e["note"]
