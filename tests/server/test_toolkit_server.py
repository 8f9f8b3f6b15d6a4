"""The lab session toolkit against the real server: uvicorn on a free loopback port, a
TCP client playing the phone with a real Sensor Fusion log, HTTP calls as a script or
the page makes them (issue 9)."""

from __future__ import annotations

import math
import shutil
import threading
import time

import httpx
import numpy as np
import pytest

from app.toolkit.calibration import calibrate
from app.sources.readers import read_log_data
from app.toolkit.recorded import read_estimates, read_events
from harness import ALL_AXES, SCALE, Phone, running_server, turns_log_lines, turns_session, wait_for

STILL = "alekodu_activityrecognition/sensorLog_20221024T182616_standstill.txt"


def _state(api):
    return api.get("/api/state").json()


def _split_at(lines: list[bytes], seconds: float) -> int:
    t0 = int(lines[0].split(b"\t")[0])
    return next(i for i, ln in enumerate(lines) if int(ln.split(b"\t")[0]) - t0 >= seconds * 1000)


def _dec(lines):
    """The samples these lines hold (the log holds the stream's samples, bit for bit)."""
    from collections import Counter
    from app.sources.sensorfusion import decode_lines
    return decode_lines(lines, Counter())


def _send(phone: Phone, lines: list[bytes]) -> None:
    phone.send_bytes(b"".join(ln + b"\n" for ln in lines))


def _processed(api, n: int, what: str):
    return wait_for(lambda: (lambda s: s if s["counts"]["samples"] >= n else None)(_state(api)),
                    timeout=60, what=what)


@pytest.fixture
def still_log(shared_dir):
    return shared_dir / "data" / "sensorfusion-app" / STILL


def test_record_calibrate_rerun_over_a_real_phone_stream(tmp_path, still_log):
    lines = still_log.read_bytes().splitlines()
    rec_dir = tmp_path / "recordings"
    with running_server(recordings=rec_dir, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=60.0) as api:
        r = api.post("/api/calibrate", json={"seconds": 4})
        assert r.status_code == 409 and "no stream" in r.text           # nothing streams yet
        r = api.post("/api/recordings/start", json={"name": "lesson"})
        assert r.status_code == 200, r.text
        assert api.post("/api/recordings/start", json={}).status_code == 409
        with Phone(s.phone_port) as phone:
            k = 200
            _send(phone, lines[:k])
            wait_for(lambda: _state(api)["source"] == "phone", what="phone session")
            out = {}
            th = threading.Thread(target=lambda: out.update(
                r=api.post("/api/calibrate", json={"seconds": 4.0})))
            th.start()
            wait_for(lambda: api.get("/api/calibrate").json()["capture"] is not None, what="capture")
            _send(phone, lines[k:])
            th.join(60)
            cal = out["r"]
            assert cal.status_code == 200, cal.text
            cal = cal.json()
            _processed(api, 8000, "the log processed")
            # apply (the phone still connected: the change lands in the recording):
            # noise levels, bias, g0, m0 into the estimators, and a preset
            # (a variant of lab is given the phone's calibration too)
            assert api.post("/api/estimators", json={"name": "lab-approx", "base": "lab", "params": {
                "time_update": "approx"}}).status_code == 200
            r = api.post("/api/calibrate/apply", json={"save_as": "mycal"})
            assert r.status_code == 200, r.text
            p = api.get("/api/params").json()["estimators"]
            np.testing.assert_allclose(p["lab"]["m0"], cal["m0"], atol=1e-9)
            np.testing.assert_allclose(p["robust"]["gyr_bias"], cal["gyr_bias"], atol=1e-9)
            for k in ("m0", "gyr_bias", "gyr_std", "g0"):
                np.testing.assert_allclose(p["lab-approx"][k], p["lab"][k], atol=1e-12)
            assert p["lab-approx"]["time_update"] == "approx"
            assert api.delete("/api/estimators/lab-approx").status_code == 200
            assert (tmp_path / "mycal.toml").is_file()
        wait_for(lambda: _state(api)["source"] == "phone-disconnected", what="disconnect")
        # the statistics: the same numbers as orientlab calibrate on those 4 s of samples
        rec = read_log_data(still_log)
        for name in ("acc", "gyr", "mag"):
            assert cal["sensors"][name]["n"] > 50
        for name in ("acc", "gyr", "mag"):       # a histogram per axis, its fitted Gaussian
            s = cal["sensors"][name]
            assert [h["axis"] for h in s["histograms"]] == ["x", "y", "z"]
            for i, h in enumerate(s["histograms"]):
                assert sum(h["counts"]) == s["n"]
                width = h["edges"][1] - h["edges"][0]
                # the Gaussian in counts per bin: its sum over the bins about n
                assert sum(h["fit"]) == pytest.approx(s["n"], rel=0.1)
                assert h["centres"][int(np.argmax(h["fit"]))] == pytest.approx(
                    s["mean"][i], abs=width)
        assert 3.9 <= cal["duration_s"] <= 4.0
        st = None
        # the capture began with a sample after the first 200 lines: find its 4 s window
        best = math.inf
        for start in np.unique(rec.t[(rec.t - rec.t[0]) < 3.0])[::5]:
            sel = (rec.t >= start) & (rec.t <= start + 4.0)
            cand = calibrate(rec.t[sel], rec.gyr[sel], rec.acc[sel], rec.mag[sel])
            d = abs(cand.sensors["acc"].n - cal["sensors"]["acc"]["n"]) + \
                float(np.abs(cand.sensors["gyr"].mean - cal["sensors"]["gyr"]["mean"]).sum()) * 1e3
            if d < best:
                best, st = d, cand
        for name in ("acc", "gyr", "mag"):
            np.testing.assert_allclose(cal["sensors"][name]["mean"], st.sensors[name].mean, atol=2e-3)
            np.testing.assert_allclose(cal["sensors"][name]["std"], st.sensors[name].std, rtol=0.05)
        assert cal["m0"][0] == 0.0 and cal["m0"][2] < 0      # formula (7): north and down
        # the recording: the log is exactly the stream; its segment ended with the phone
        r = api.post("/api/recordings/stop")
        assert r.status_code == 200, r.text
        summary = r.json()
        assert summary["name"] == "lesson" and summary["samples"] > 5000   # ACC, GYR, MAG
        assert summary["seconds"] == pytest.approx(rec.t[-1] - rec.t[0], abs=0.5)
        log = rec_dir / "lesson.txt"
        body = log.read_bytes()
        txt = [ln for ln in body.splitlines() if b"\tTXT\t" in ln]
        assert _dec([ln for ln in body.splitlines() if b"\tTXT\t" not in ln]) == _dec(lines)
        assert txt and b"parameters changed" in txt[0]               # the apply, marked
        ev = read_events(rec_dir / "lesson.events.jsonl")
        kinds = [e["kind"] for e in ev]
        assert kinds[0] == "start" and "params" in kinds and kinds[-1] == "end"
        assert "disconnect" in ev[-1]["reason"] or "closed" in ev[-1]["reason"] or ev[-1]["reason"]
        est = read_estimates(rec_dir / "lesson.estimates.csv.gz")
        assert {"robust", "lab", "complementary", "phone"} <= set(est)
        listed = api.get("/api/recordings").json()
        assert "lesson" in [x["name"] for x in listed["recordings"]]
        assert api.get("/api/recordings/lesson/log").content == body
        # a recording is shared with the class: the phone by its app, never its address
        phone = next(e["phone"] for e in ev if e.get("phone"))     # recorded before it came
        assert phone["label"] == "a phone (Sensor Fusion app)", phone
        assert "127.0.0.1" not in (rec_dir / "lesson.events.jsonl").read_text()
        assert "127.0.0.1" not in str(listed), listed["status"]
        # a file dropped in the folder that is no log: the tools that read it say so
        (rec_dir / "notes.txt").write_text("bring a magnet at 12:05\n")
        r = api.post("/api/calibrate", json={"recording": "notes"})
        assert r.status_code == 422 and "notes.txt: unknown format" in r.text, r.text
        r = api.post("/api/gyro-scale", json={"recordings": ["notes"]})
        assert r.status_code == 422 and "notes.txt: unknown format" in r.text, r.text
        assert str(rec_dir) not in r.text
        assert api.get("/api/recordings/nope/log").status_code == 404
        assert api.get("/api/recordings/..%2Fetc/log").status_code in (404, 422)
        # a CSV or npz dropped in is downloaded as what it is, not as text
        assert api.get("/api/recordings/lesson/log").headers["content-type"].startswith("text/plain")
        (rec_dir / "table.csv").write_text("t,acc_x,acc_y,acc_z\n0,0,0,9.81\n0.01,0,0,9.81\n")
        np.savez(rec_dir / "trial.npz", t=np.arange(3) * 0.01, acc=np.tile([0.0, 0.0, 9.81], (3, 1)))
        for name, kind in (("table", "text/csv"), ("trial", "application/octet-stream")):
            r = api.get(f"/api/recordings/{name}/log")
            assert r.status_code == 200 and r.headers["content-type"].startswith(kind), (name, r.headers)
        # what-if: the whole recording re-run, before and after a change
        r = api.post("/api/recordings/lesson/rerun",
                     json={"patch": {"lab": {"time_update": "approx"}}})
        assert r.status_code == 200, r.text
        w = r.json()
        assert w["estimators"]["lab"]["changed"] and w["estimators"]["lab"]["after"] is not None
        assert w["estimators"]["robust"]["after"] is None
        r = api.post("/api/recordings/lesson/rerun", json={"patch": {"lab": {"acc_std": -1}}})
        assert r.status_code == 422 and "acc_std" in r.text


def test_magnet_injected_into_a_real_stream_primary_rides_it_out(tmp_path, still_log):
    """The acceptance demonstration: a 50 µT magnet on a real still phone. The primary
    flags it and its heading moves < 3°; the one-click variant without rejection turns."""
    lines = still_log.read_bytes().splitlines()
    rec_dir = tmp_path / "rec"
    with running_server(recordings=rec_dir, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=60.0) as api:
        r = api.post("/api/estimators", json={"preset": "no-rejection"})
        assert r.status_code == 200, r.text
        variant = r.json()["name"]
        assert variant == "robust-no-rejection"
        assert api.post("/api/estimators", json={"preset": "no-rejection"}).status_code == 422
        bad = api.post("/api/inject", json={"kind": "magnet", "strength_uT": -5, "seconds": 5})
        assert bad.status_code in (409, 422)
        assert api.post("/api/recordings/start", json={"name": "magnet"}).status_code == 200
        k = _split_at(lines, 6.0)
        with Phone(s.phone_port) as phone:
            _send(phone, lines[:k])
            _processed(api, k - 200, "first 6 s")
            st = _state(api)
            assert variant in st["estimators"]
            r = api.post("/api/inject", json={"kind": "magnet", "strength_uT": 50, "direction": "east",
                                              "seconds": 5})
            assert r.status_code == 200, r.text
            assert r.json()["text"].startswith("magnet 50 µT along [1,0,0]")   # the page's words
            _send(phone, lines[k:])
            _processed(api, len(lines) - 300, "the rest")
        summary = api.post("/api/recordings/stop").json()
        marks = api.get("/api/inject").json()["marks"]
        assert [m["event"] for m in marks] == ["start", "end"]
        t_on, t_off = marks[0]["t"], marks[1]["t"]
        assert t_off - t_on == pytest.approx(5.0, abs=0.05)
        est = read_estimates(rec_dir / "magnet.estimates.csv.gz")
        body = (rec_dir / "magnet.txt").read_bytes()
        assert body.count(b"\tTXT\torientlab: magnet 50 uT") == 2        # marked in the recording
        assert summary["samples"] > 5000

        # the same log without the magnet, through the batch path: what each estimator
        # would have shown; the magnet's effect is the heading difference to it
        from app.estimators import make_estimator
        from app.quaternion import error_angles
        from app.toolkit.variants import no_rejection_changes
        clean = read_log_data(still_log)
        ref = {"robust": make_estimator("robust").run(clean.t, clean.gyr, clean.acc, clean.mag),
               variant: make_estimator("robust", no_rejection_changes("robust")).run(
                   clean.t, clean.gyr, clean.acc, clean.mag)}

        def heading_move(name):
            t, q = est[name]["t"], est[name]["q"]
            i = np.clip(np.searchsorted(ref[name].t, t), 0, len(ref[name].t) - 1)
            _, head, _ = error_angles(q, ref[name].q[i])
            head = np.degrees(head)
            before = np.median(head[(t > t_on - 1.0) & (t < t_on)])
            during = head[(t >= t_on) & (t <= t_off + 1.0)]
            return float(np.abs(during - before).max())
        moved, moved_nr = heading_move("robust"), heading_move(variant)
        assert moved < 3.0, (moved, moved_nr)
        assert moved_nr > 20.0, (moved, moved_nr)
        counts = _state(api)["counts"]["updates"] if "updates" in _state(api)["counts"] else None
        if counts is not None:
            refused = sum(v for k2, v in counts["robust"]["mag"].items() if k2 not in ("used", "absent"))
            assert refused > 100
        assert api.delete(f"/api/estimators/{variant}").status_code == 200
        assert api.delete("/api/estimators/robust").status_code == 409
        assert variant not in _state(api)["estimators"]


def test_a_disturbance_ends_with_its_stream_and_never_reaches_the_next(tmp_path, still_log):
    """A reviewer's find: a magnet still on when its stream ended stayed armed and was
    added to the next phone's live stream once that phone's clock passed its start time
    (a real phone's data faked, and recorded so). It now ends with its stream."""
    lines = still_log.read_bytes().splitlines()
    k = _split_at(lines, 3.0)
    with running_server(recordings=tmp_path / "rec", preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=60.0) as api:
        assert api.post("/api/recordings/start", json={"name": "two"}).status_code == 200
        with Phone(s.phone_port) as phone:
            _send(phone, lines[:k])
            _processed(api, k - 200, "the first 3 s")
            r = api.post("/api/inject", json={"kind": "magnet", "strength_uT": 80,
                                              "direction": "east", "seconds": 60})
            assert r.status_code == 200, r.text
            _send(phone, lines[k:2 * k])                 # the magnet on this stream
            _processed(api, 2 * k - 400, "3 s more")
        wait_for(lambda: _state(api)["source"] == "phone-disconnected", 30, what="the end")
        on = api.get("/api/inject").json()["recent"][-1]
        assert on["lines"] > 0
        # the same phone again, from its first line: its clock passes the magnet's start
        with Phone(s.phone_port) as phone:
            _send(phone, lines)
            _processed(api, len(lines) - 300, "the second stream")
        st = api.get("/api/inject").json()
        assert st["active"] == [] and st["recent"][-1]["lines"] == on["lines"]
        mag = s.app.state.engine.core.history.mag.window(1e9, 100_000)
        clean = np.linalg.norm([x.values for x in _dec(lines) if x.tag == "MAG"], axis=1)
        assert np.nanmax(mag["norm"]) < clean.max() + 1.0     # no 80 µT added anywhere
        # the recording spans both streams: one file each, and the Lab tab names both
        # (the first name alone plays the first stream only)
        last = api.post("/api/recordings/stop").json()
        assert [g["name"] for g in last["segments"]] == ["two", "two_2"]
        # each file says which recording it belongs to, and whose stream it holds
        starts = [read_events(s.settings.recordings / f"{n}.events.jsonl")[0] for n in ("two", "two_2")]
        assert [(e["recording"], e["segment"]) for e in starts] == [("two", 1), ("two", 2)]
        assert starts[0]["source"] == "" and starts[1]["source"] == "a phone (Sensor Fusion app)", starts
        # (recorded before the phone streamed: its stream is named when it came)
        came = [e for e in read_events(s.settings.recordings / "two.events.jsonl") if e["kind"] == "stream"]
        assert len(came) == 1 and came[0]["source"] == "a phone (Sensor Fusion app)", came
        tab = s.app.state.toolkit_tab
        wait_for(lambda: "`two_2`" in tab.rec_md.content and "2 streams" in tab.rec_md.content,
                 10.0, what="both files named")


def test_replay_a_recording_with_pause_speed_and_seek(tmp_path, still_log):
    rec_dir = tmp_path / "recordings"
    rec_dir.mkdir()
    shutil.copy(still_log, rec_dir / "dropped.txt")                  # an app log dropped in
    with running_server(recordings=rec_dir, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=60.0) as api:
        assert api.post("/api/replay", json={"speed": 2}).status_code == 409   # nothing replayed
        assert "dropped" in [x["name"] for x in api.get("/api/recordings").json()["recordings"]]
        r = api.post("/api/replay", json={"name": "dropped", "speed": 4.0, "loop": False})
        assert r.status_code == 200, r.text
        wait_for(lambda: api.get("/api/replay").json()["position_s"] > 2.0, what="replay moving")
        # while it plays, Seek is left to the viewer: the refresh wrote the playhead into
        # it several times a second and overwrote what a student typed into its box
        tab = s.app.state.toolkit_tab
        seek0 = tab.rp_seek.value
        import time
        time.sleep(1.5)
        assert api.get("/api/replay").json()["position_s"] > seek0 + 3.0
        assert tab.rp_seek.value == seek0
        st = api.post("/api/replay", json={"paused": True}).json()
        pos = st["position_s"]
        n = _state(api)["counts"]["samples"]
        import time
        time.sleep(0.5)
        assert api.get("/api/replay").json()["position_s"] == pos
        assert _state(api)["counts"]["samples"] <= n + 50          # the reorder tail at most
        # the Lab tab's controls show the replay as it is (they kept a previous replay's
        # values, and typing the value shown again changed nothing): speed, loop, playhead
        tab = s.app.state.toolkit_tab
        wait_for(lambda: tab.rp_speed.value == 4.0 and tab.rp_loop.value is False
                 and abs(tab.rp_seek.value - pos) < 0.5, 10, what="the replay's controls")
        r = api.post("/api/replay", json={"seek_s": 10.0, "paused": False})
        assert r.status_code == 200
        wait_for(lambda: "from 10.0 s" in _state(api)["status"] or
                 api.get("/api/replay").json()["position_s"] > 10.0, what="seek")
        # a pause and a seek are no loop: loops counts the log's restarts at its end (it
        # counted every new stream, 2 here)
        assert api.get("/api/replay").json()["loops"] == 0
        for body, field in [({"speed": 50}, "speed"), ({"seek_s": 1e6}, "seek_s"), ({"paused": "no"}, "paused"),
                            ({"warp": 1}, "warp")]:
            r = api.post("/api/replay", json=body)
            assert r.status_code == 422 and field in r.text, (body, r.text)
        assert api.post("/api/replay", json={"stop": True}).json()["replaying"] is False


def test_changing_routes_need_the_presenter(tmp_path):
    with running_server(recordings=tmp_path, preset_dir=tmp_path, open_access=False,
                        token="secret-token") as s, httpx.Client(base_url=s.url, timeout=30.0) as api:
        for method, path, body in [("post", "/api/recordings/start", {}), ("post", "/api/recordings/stop", None),
                                   ("post", "/api/calibrate", {"seconds": 5}),
                                   ("post", "/api/inject", {"kind": "shake", "amplitude_ms2": 5, "seconds": 1}),
                                   ("post", "/api/estimators", {"preset": "lab-approx"}),
                                   ("delete", "/api/estimators/lab-approx", None),
                                   ("post", "/api/replay", {"paused": True}),
                                   ("post", "/api/magcal", {"seconds": 10}),
                                   ("post", "/api/gyro-scale", {"recordings": ["x"]}),
                                   ("post", "/api/gyro-scale/apply", None)]:
            kw = {"json": body} if body is not None else {}
            r = getattr(api, method)(path, **kw)
            assert r.status_code == 403, (path, r.status_code)
        assert api.get("/api/recordings").status_code == 200
        r = api.post("/api/estimators", json={"preset": "lab-approx"},
                     headers={"X-Orientlab-Token": "secret-token"})
        assert r.status_code == 200, r.text


def _turning_phone(seconds: float, offset, A, field=(0.0, 20.0, -44.0)):
    """Lines of a phone turned through every direction, its magnetometer with hard and
    soft iron: raw = A R(t)ᵀ m + b."""
    from app.quaternion import Q, quat_from_rotvec
    out = []
    m = np.array(field)
    for k in range(int(seconds * 50)):
        t = k / 50.0
        ax = np.array([math.sin(0.37 * t), math.cos(0.23 * t), math.sin(0.11 * t + 1.0)])
        q = quat_from_rotvec(ax / np.linalg.norm(ax) * (1.3 * t))
        raw = A @ (Q(q).T @ m) + offset
        ms = 5000 + 20 * k
        out.append(f"{ms}\tMAG\t{raw[0]:.4f}\t{raw[1]:.4f}\t{raw[2]:.4f}".encode())
        out.append(f"{ms + 1}\tACC\t0\t0\t9.81".encode())
    return out


def test_magnetometer_calibration_from_the_stream(tmp_path):
    b = np.array([15.0, -8.0, 25.0])
    A = np.diag([1.15, 0.9, 1.0])
    lines = _turning_phone(40.0, b, A)
    with running_server(recordings=tmp_path, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=60.0) as api:
        with Phone(s.phone_port) as phone:
            _send(phone, lines[:20])
            wait_for(lambda: _state(api)["source"] == "phone", what="phone")
            r = api.post("/api/magcal", json={"seconds": 30})
            assert r.status_code == 200, r.text
            _send(phone, lines[20:])
            res = wait_for(lambda: api.get("/api/magcal").json().get("result"), what="fit")
        cap = api.get("/api/magcal").json()["capture"]
        assert cap["coverage"] > 0.8
        # the samples it kept are its rows; its wall time stops when it is done
        assert cap["done"] and cap["rows"] == cap["samples"] > 100, cap
        time.sleep(0.3)
        assert api.get("/api/magcal").json()["capture"]["wall_s"] == cap["wall_s"]
        np.testing.assert_allclose(res["offset_uT"], b, atol=0.5)
        assert res["residual_before_uT"] > 3.0 and res["residual_after_uT"] < 0.5
        r = api.post("/api/magcal/apply", json={"save_as": "withmag"})
        assert r.status_code == 200 and r.json()["applied"]["offset_uT"] == res["offset_uT"]
        for bad in ("false", 1, None):              # "false" had cleared the calibration
            r = api.post("/api/magcal/apply", json={"clear": bad})
            assert r.status_code == 422 and "clear" in r.text, (bad, r.text)
        assert api.get("/api/magcal").json()["applied"]["offset_uT"] == res["offset_uT"]
        text = (tmp_path / "withmag.toml").read_text()
        assert "[magcal]" in text
        # from now on every MAG sample is corrected: a raw reading of the offset alone
        # (zero field) reads ~0 µT (once the first phone's stream, sent faster than it
        # is processed, has ended: else the second phone is refused as a second one)
        wait_for(lambda: (lambda st: st["source"] == "phone-disconnected"
                          and st["counts"]["queued"] == 0)(_state(api)), 60.0,
                 what="the end of the first phone's stream")
        with Phone(s.phone_port) as phone:
            second = []
            for k in range(0, 3000, 10):
                second.append(f"{100 + k}\tACC\t0\t0\t9.81".encode())
                if k % 20 == 0:
                    second.append(f"{103 + k}\tMAG\t{b[0]}\t{b[1]}\t{b[2]}".encode())
            _send(phone, second)
            wait_for(lambda: _state(api)["source"] == "phone" and _state(api)["counts"]["samples"] > 300,
                     what="second phone")
        snap = s.engine.core.snapshot()
        assert np.linalg.norm(snap.mag) < 0.5


def test_a_presets_magnetometer_calibration_is_applied_when_it_is_loaded(tmp_path):
    """A preset holding [magcal] (hard and soft iron) sets it again when loaded by name,
    by path or uploaded; a preset without one clears it (a preset is the whole tuning);
    saving keeps the one in force."""
    b = [15.0, -8.0, 25.0]
    (tmp_path / "withmag.toml").write_text(
        "[magcal]\noffset_uT = [15.0, -8.0, 25.0]\nmatrix = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]\n")
    with running_server(recordings=tmp_path, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=60.0) as api:
        def applied():
            a = api.get("/api/magcal").json()["applied"]
            return None if a is None else a["offset_uT"]
        assert applied() is None
        r = api.post("/api/presets/load", json={"name": "withmag"})
        assert r.status_code == 200, r.text
        assert applied() == b
        # every MAG sample is corrected from now on: a raw reading of the offset alone
        # (zero field) reads ~0 µT
        with Phone(s.phone_port) as phone:
            lines = []
            for k in range(0, 3000, 10):
                lines.append(f"{100 + k}\tACC\t0\t0\t9.81".encode())
                if k % 20 == 0:
                    lines.append(f"{103 + k}\tMAG\t{b[0]}\t{b[1]}\t{b[2]}".encode())
            _send(phone, lines)
            wait_for(lambda: _state(api)["source"] == "phone" and _state(api)["counts"]["samples"] > 300,
                     what="the phone's samples")
        assert np.linalg.norm(s.engine.core.snapshot().mag) < 0.5
        r = api.post("/api/presets/save", json={"name": "roundtrip"})
        assert r.status_code == 200 and "[magcal]" in (tmp_path / "roundtrip.toml").read_text()
        assert api.post("/api/presets/load", json={"name": "default"}).status_code == 200
        assert applied() is None
        assert api.post("/api/presets/load", json={"path": str(tmp_path / "roundtrip.toml")}).status_code == 200
        assert applied() == b
        assert api.post("/api/presets/load", json={"name": "default"}).status_code == 200
        r = api.post("/api/presets/upload", content=(tmp_path / "withmag.toml").read_bytes())
        assert r.status_code == 200, r.text
        assert applied() == b


def test_gyroscope_scale_from_a_recorded_stream(tmp_path):
    """The lab's flow: record a phone turned whole turns between rests (TCP, the app's lines),
    measure its gyroscope's scale from the recording, apply it; refusals with their reasons."""
    t, gyr, acc, mag, _ = turns_session(ALL_AXES)
    lines = [ln.encode() for ln in turns_log_lines(t + 100.0, gyr, acc, mag)]
    rec_dir = tmp_path / "recordings"
    with running_server(recordings=rec_dir, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=120.0) as api:
        r = api.post("/api/gyro-scale/apply")
        assert r.status_code == 409 and "no fit yet" in r.text
        assert api.post("/api/recordings/start", json={"name": "turns"}).status_code == 200
        with Phone(s.phone_port) as phone:
            _send(phone, lines)
            _processed(api, len(lines) - 50, "the turns processed")
        wait_for(lambda: _state(api)["source"] == "phone-disconnected", what="disconnect")
        api.post("/api/recordings/stop")
        r = api.post("/api/gyro-scale", json={"recordings": ["turns"]})
        assert r.status_code == 200, r.text
        fit = r.json()
        assert fit["rests"] == {"turns": len(ALL_AXES) + 1} and all(fit["measured"])
        np.testing.assert_allclose(fit["scale"], SCALE, atol=5e-4)
        assert "x: s = " in fit["report"]
        assert api.get("/api/gyro-scale").json()["result"]["scale"] == fit["scale"]
        tab = s.app.state.toolkit_tab      # the Lab tab shows a fit made through the API too
        wait_for(lambda: tab.gs_apply.disabled is False, 30.0, what="the Lab tab's apply enabled")
        assert "spans between rests" in tab.gs_md.content
        r = api.post("/api/gyro-scale/apply", json={"save_as": "myphone"})
        assert r.status_code == 200, r.text
        p = api.get("/api/params").json()["estimators"]
        for est in ("robust", "lab"):
            np.testing.assert_allclose(p[est]["gyr_scale"], fit["preset_scale"], atol=1e-12)
        assert "gyr_scale" in (tmp_path / "myphone.toml").read_text(encoding="utf-8")
        # refused, each with its reason, nothing applied
        for body, status, words in [({"recordings": "turns"}, 422, "list of"),
                                    ({"recordings": []}, 422, "list of"),
                                    ({"recordings": ["nope"]}, 404, "nope"),
                                    ({"names": ["turns"]}, 422, "unknown key")]:
            r = api.post("/api/gyro-scale", json=body)
            assert r.status_code == status and words in r.text, (body, r.status_code, r.text)
