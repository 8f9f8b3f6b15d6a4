"""What-if re-runs (app/toolkit/whatif.py) and the calibration statistics as JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.toolkit.calibration import calibrate, format_report, to_json
from app.cli import main as cli_main
from app.estimators import make_estimator
from app.quaternion import angle_between
from app.sources.readers import read_log_data
from app.sources.simulate import Simulation
from app.toolkit.variants import no_rejection_changes
from app.toolkit.whatif import WhatIfError, hold_ori, rerun

WALK = "alekodu_activityrecognition/sensorLog_20221024T182635_walking_hand.txt"


def demo_log(path, seconds=40.0, seed=3):
    """A log of the simulated phone (it has ORI, and its truth is known)."""
    from app.sources.sensorfusion import format_line
    from app.sources.simulate import Simulation, stream
    lines = []
    boot = Simulation().config.boot_ms
    for ms, tag, vals in stream(seed):
        if ms - boot > seconds * 1000:
            break
        lines.append(format_line(ms, tag, vals))
    path.write_text("\n".join(lines) + "\n")
    sim = Simulation()
    return path, (lambda t_s: sim.truth(t_s - boot / 1000.0))
STILL = "alekodu_activityrecognition/sensorLog_20221024T182616_standstill.txt"


def test_rerun_before_and_after_a_patch(tmp_path):
    path, truth = demo_log(tmp_path / "demo.txt")
    specs = {"robust": ("robust", {}), "lab": ("lab", {}), "phone": ("phone", {}),
             "robust-no-rejection": ("robust", no_rejection_changes("robust"))}
    out = rerun(path, specs, patch={"lab": {"time_update": "approx"},
                                    "robust": no_rejection_changes("robust")})
    json.dumps(out, allow_nan=False)           # plain JSON for the API
    assert out["reference"] == "phone" and out["rows"] > 1000
    rec = read_log_data(path)
    # "before" is exactly what the batch path gives with the current parameters
    res = make_estimator("robust").run(rec.t, rec.gyr, rec.acc, rec.mag, rec.ori)
    ref = hold_ori(rec)
    ok = np.all(np.isfinite(ref), axis=1)
    errs = [angle_between(ref[k], res.q[k]) for k in np.nonzero(ok)[0][::50]]
    r = out["estimators"]["robust"]
    assert r["changed"] and r["after"] is not None
    assert r["before"]["error_to_phone_deg"]["max"] >= np.degrees(max(errs)) - 1e-6
    assert out["estimators"]["phone"]["before"]["error_to_phone_deg"]["max"] < 1e-3
    assert out["estimators"]["robust-no-rejection"]["after"] is None
    # no rejection: nothing refused; the default refuses some magnetometer samples
    assert out["estimators"]["robust-no-rejection"]["before"]["rejected"]["mag"] == 0.0
    assert r["before"]["rejected"]["mag"] > 0.0          # the demo's magnet scene
    assert r["after"]["rejected"]["mag"] == 0.0 < r["before"]["rejected"]["mag"]
    # without rejection the magnet scene costs heading: worse than the default, against
    # the truth during that scene (the phone's own estimate follows the magnet, and the
    # largest error of the whole log is the gyroscope dropout's, where rejection is moot)
    sim = Simulation()
    k = sim.scenes.index("magnet")
    t0, t1 = sim.starts[k], sim.starts[k] + sim.durations[k]
    scored = rerun(path, {"robust": specs["robust"], "nr": specs["robust-no-rejection"]},
                   truth={"t": rec.t, "q": truth(rec.t)})
    tt = np.asarray(scored["t"])
    scene = (tt >= t0) & (tt < t1)
    worst = {name: float(np.nanmax(np.asarray(e["before"]["series"]["error_deg"], float)[scene]))
             for name, e in scored["estimators"].items()}
    assert worst["nr"] > 3.0 * worst["robust"], worst
    n = len(out["t"])
    assert n == len(r["before"]["series"]["error_deg"]) == len(r["after"]["series"]["yaw_deg"])
    # the stream's first row comes before the alignment: no yaw there (not 0°), then yaw
    yaw = r["before"]["series"]["yaw_deg"]
    assert yaw[0] is None and all(v is not None for v in yaw[5:])


def test_a_bad_patch_is_refused_before_anything_runs(shared_dir):
    path = shared_dir / "data" / "sensorfusion-app" / WALK
    with pytest.raises(WhatIfError) as e:
        rerun(path, {"lab": ("lab", {})}, patch={"lab": {"acc_noise": -1}})
    assert e.value.field == "patch.lab.acc_noise"
    with pytest.raises(WhatIfError, match="no estimator named"):
        rerun(path, {"lab": ("lab", {})}, patch={"nope": {}})


def test_rerun_scores_against_the_truth_when_given(tmp_path):
    path, truth = demo_log(tmp_path / "demo.txt", seconds=20)
    rec = read_log_data(path)
    out = rerun(rec, {"robust": ("robust", {}), "phone": ("phone", {})},
                truth={"t": rec.t, "q": truth(rec.t)})
    assert out["reference"] == "truth" and out["has_phone"]
    # the simulated phone's own estimate wanders about 1° off the truth
    ph = out["estimators"]["phone"]["before"]["error_to_truth_deg"]
    assert 0.2 < ph["median"] < 2.0
    assert out["estimators"]["robust"]["before"]["error_to_truth_deg"]["median"] < 3.0


def test_calibration_json_has_the_same_numbers_as_orientlab_calibrate(shared_dir, tmp_path, capsys):
    path = shared_dir / "data" / "sensorfusion-app" / STILL
    # the standstill log is not stationary throughout: its preset is written only --force
    assert cli_main(["calibrate", str(path), "--out", str(tmp_path / "p.toml"), "--force"]) == 0
    printed = capsys.readouterr().out
    rec = read_log_data(path)
    st = calibrate(rec.t, rec.gyr, rec.acc, rec.mag)
    j = to_json(st, rec.t, {"acc": rec.acc, "gyr": rec.gyr, "mag": rec.mag})
    json.dumps(j, allow_nan=False)
    assert j["report"] == format_report(st) and j["report"] in printed
    for name in ("acc", "gyr", "mag"):
        s = j["sensors"][name]
        np.testing.assert_allclose(s["mean"], st.sensors[name].mean)
        np.testing.assert_allclose(s["cov"], st.sensors[name].cov)
        np.testing.assert_allclose(s["drift_per_min"], st.sensors[name].trend_per_min)
        for h in s["histograms"]:
            # the fitted Gaussian holds about as many samples as the histogram
            assert sum(h["counts"]) == s["n"]
            assert abs(sum(h["fit"]) - s["n"]) < 0.2 * s["n"]
    np.testing.assert_allclose(j["m0"], st.m0)
    assert j["apply"]["lab"]["m0"] == pytest.approx(list(st.m0))
    assert j["apply"]["robust"]["gyr_bias"] == pytest.approx(list(st.gyr_bias))
    assert set(j["series"]) == {"acc", "gyr", "mag"}
