"""The dashboard end to end: a real uvicorn + viser server on free loopback ports, a real
TCP client playing a phone, the HTTP and WebSocket API, the GUI's controls."""

from __future__ import annotations

import asyncio
import json
import math
import time
from dataclasses import fields
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets

from app.sources.samples import MOTION_TAGS
from app.quaternion import angle_between_many
from harness import Phone, free_port, log_lines, running_server, wait_for
from app.sources.simulate import simulate
from app.sources.ordering import SampleOrderer
from app.estimators.phone import ORI_HOLD_S

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
REAL_LOGS = SHARED / "data" / "sensorfusion-app"


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with running_server(preset_dir=tmp_path_factory.mktemp("presets")) as s:
        yield s


@pytest.fixture()
def api(srv):
    with httpx.Client(base_url=srv.url, timeout=30.0) as c:
        yield c
    # switch the sensors back on for the next test
    with httpx.Client(base_url=srv.url, timeout=30.0) as c:
        c.patch("/api/params", json={"use_gyr": True, "use_acc": True, "use_mag": True})


def play(srv, api, lines: list[str], *, end: str = "\n") -> dict:
    """Stream ``lines`` as a phone, hang up, wait until the server has processed all."""
    n_before = api.get("/api/state").json()["counts"].get("total_sessions", 0)
    with Phone(srv.phone_port) as ph:
        ph.send_lines(lines, end=end)   # a connection is a phone once it sends a valid sample
        wait_for(lambda: api.get("/api/state").json()["counts"]["total_sessions"] > n_before,
                 what="the phone session")
    return wait_for(lambda: (lambda st: st if st["source"] == "phone-disconnected"
                             and st["counts"]["buffered"] == 0 and st["counts"]["queued"] == 0
                             else None)(api.get("/api/state").json()),
                    what="the end of the stream")


def expected_release(lines: list[str]):
    """What the stream's orderer releases for these lines (the reference for counts)."""
    o = SampleOrderer(window=0.05)
    out = o.push_lines(lines) + o.flush()
    return out, o


def test_health_info_and_docs(srv, api):
    h = api.get("/api/health").json()
    assert h["status"] == "ok"
    assert set(h["estimators"]) >= {"lab", "robust"}
    info = api.get("/api/info").json()
    assert info["phone_port"] == srv.phone_port and info["viewer_port"] == srv.viewer_port
    spec = api.get("/openapi.json").json()
    assert "patch" in spec["paths"]["/api/params"]
    page = api.get("/")
    assert page.status_code == 200 and "iframe" in page.text and "/docs" in page.text


def test_generated_log_is_followed(srv, api):
    sim = simulate(("still", "turn_z"), seed=3)
    lines = sim.lines()
    # bad input mixed in: wrong count, unknown tag, not numeric, empty
    bad = ["123\tACC\t1.0\t2.0", "123\tFOO\t1", "123\tGYR\ta\tb\tc", ""]
    mixed = lines[:100] + bad + lines[100:]
    released, _ = expected_release(mixed)
    st = play(srv, api, mixed)
    assert st["counts"]["samples"] == len(released) == len(lines)
    assert st["counts"]["malformed"] == len(bad)
    assert st["counts"]["lines"] == len(mixed)
    assert st["t"] == pytest.approx(max(s[0] for s in sim.samples) / 1000.0)
    assert st["phone_q"] is not None and st["error_to_phone_deg"] is not None
    # the filter follows the truth (the phone's own estimate is within ~2° of it)
    q_true = sim.truth_at_ms([sim.samples[-1][0]])[0]
    err = math.degrees(2 * math.acos(min(1.0, abs(float(np.dot(q_true, st["q"]))))))
    assert err < 10.0
    assert st["rates_hz"]["ACC"] == pytest.approx(100.0, rel=0.05)
    assert st["rates_hz"]["MAG"] == pytest.approx(50.0, rel=0.05)
    assert len(st["euler_deg"]) == 3
    for name, e in st["estimators"].items():
        assert len(e["q"]) == 4, name

    # the Lab tab's table says each estimator's last field decision in words, not codes: lab
    # given a field band no field fits refuses every sample ("field", in words "field
    # strength L_k outside its band")
    from app.estimators import REASON_TEXT, Reason
    r = api.patch("/api/params", json={"estimators": {"lab": {"mag_band_uT": [1.0, 2.0]}}})
    assert r.status_code == 200, r.text
    try:
        play(srv, api, lines)
        rows = {row.split("|")[1].strip(" `"): row.split("|")[4].strip()
                for row in srv.app.state.toolkit_tab._readouts().splitlines()[2:]}
        assert rows["lab"] == REASON_TEXT[Reason.FIELD], rows
        assert all(v in set(REASON_TEXT.values()) for v in rows.values()), rows
    finally:
        api.patch("/api/params", json={"estimators": {"lab": {"mag_band_uT": None}}})


@pytest.mark.skipif(not REAL_LOGS.is_dir(), reason="../shared/data/sensorfusion-app not present")
@pytest.mark.parametrize("name", ["alekodu_activityrecognition/sensorLog_20221024T182616_standstill.txt",
                                  "BaiLiping_WASP_IMU/sensorLog.txt"])
def test_real_log_is_followed(srv, api, name):
    lines = log_lines(REAL_LOGS / name)
    released, orderer = expected_release(lines)
    st = play(srv, api, lines)
    assert st["counts"]["samples"] == len(released)
    assert st["counts"]["malformed"] == sum(orderer.counters.malformed.values())
    assert st["t"] == pytest.approx(released[-1].time_ms / 1000.0)
    if "standstill" in name:  # holds two corrupted RAWGYR lines
        assert st["counts"]["malformed"] == 2
        assert st["counts"]["malformed_by_reason"] == {"wrong_count": 2}
        assert st["standstill"] or st["estimators"]


def test_an_unusable_ori_line_is_not_the_phones_estimate(srv, api):
    """ORI with NaN or all zeros is refused by the phone estimator's own check, in the
    engine's read-outs too: the last good ORI stays the phone's estimate."""
    good = [0.9238795, 0.0, 0.0, 0.3826834]  # 45 deg about z
    lines = ["1000\tACC\t0\t0\t9.81", "1000\tORI\t" + "\t".join(map(str, good)),
             "1010\tORI\tNaN\tNaN\tNaN\tNaN", "1020\tORI\t0\t0\t0\t0",
             "1030\tACC\t0\t0\t9.81"]
    st = play(srv, api, lines)
    np.testing.assert_allclose(st["phone_q"], good, atol=1e-6)


def watch(srv, api, lines: list[str]) -> tuple[dict, np.ndarray, np.ndarray]:
    """Play ``lines`` while reading WS /ws/state: the final state, and the primary's
    estimate after every motion sample (t in s, q (N, 4))."""
    n_motion = sum(1 for ln in lines if ln.split("\t")[1] in MOTION_TAGS)

    async def collect():
        got = []
        async with websockets.connect(f"{srv.ws_url}/ws/state", max_size=None) as ws:
            json.loads(await ws.recv())
            st = await asyncio.to_thread(play, srv, api, lines)
            while len(got) < n_motion:
                got.extend(json.loads(await asyncio.wait_for(ws.recv(), 30.0))["estimates"])
        return st, got

    st, got = asyncio.run(collect())
    return st, np.array([g["t"] for g in got]), np.array([g["q"] for g in got])


def test_use_mag_off_changes_behaviour(srv, api):
    """A magnet next to the phone pulls lab's heading while it uses the magnetometer;
    with the magnetometer off the magnet changes nothing: lab's error to the truth grows
    only as its uncorrected gyroscope bias lets it (lab does not estimate the bias)."""
    sim = simulate(("still", "magnet"), seed=5)
    magnet_from = sim.boot_ms / 1000.0 + sim.sim.starts[1]

    def pull_deg(t, q):
        """How much the error to the truth grew during the magnet scene (deg)."""
        err = np.degrees(angle_between_many(q, sim.truth_at_ms(t * 1000.0)))
        return float(np.max(err[t >= magnet_from]) - err[t < magnet_from][-1])

    api.patch("/api/params", json={"primary": "lab"})
    st_on, t, q = watch(srv, api, sim.lines())
    upd_on = st_on["counts"]["updates"]["lab"]["mag"]
    assert upd_on.get("used", 0) > 100
    pull_on = pull_deg(t, q)
    r = api.patch("/api/params", json={"use_mag": False})
    assert r.status_code == 200 and r.json()["use_mag"] is False
    assert all(p["use_mag"] is False for p in r.json()["estimators"].values())
    st_off, t, q = watch(srv, api, sim.lines())
    api.patch("/api/params", json={"primary": "robust"})
    for name, e in st_off["estimators"].items():
        assert e["mag"]["reason"] == "disabled", name
    upd_off = st_off["counts"]["updates"]["lab"]["mag"]
    assert upd_off.get("used", 0) == 0 and upd_off.get("disabled", 0) > 100
    # the magnet no longer pulls the heading: the estimate stays nearer the truth
    pull_off = pull_deg(t, q)
    gyro_drift = math.degrees(np.linalg.norm(sim.sim.config.gyr_bias)) * sim.sim.durations[1]
    assert pull_off < gyro_drift < pull_on
    assert st_off["mag_rejected"] is False


def test_patch_refuses_bad_input_and_applies_nothing(srv, api):
    before = api.get("/api/params").json()
    for body, loc in (({"bogus": 1}, ["body", "bogus"]),
                      ({"use_mag": False, "estimators": {"lab": {"acc_std": -1.0}}},
                       ["body", "estimators", "lab", "acc_std"]),
                      ({"use_acc": False, "gyr_noise": 1e9}, ["body", "gyr_noise"]),
                      ({"primary": "nope"}, ["body", "primary"]),
                      ({"estimators": {"nope": {}}}, ["body", "estimators", "nope"]),
                      ({"use_mag": "yes"}, ["body", "use_mag"])):
        r = api.patch("/api/params", json=body)
        assert r.status_code == 422, body
        assert r.json()["detail"][0]["loc"] == loc
        assert api.get("/api/params").json() == before

    # one meaning per name: a renamed key says its new name; a name some estimators give a
    # meaning of their own is not taken at the top level
    r = api.patch("/api/params", json={"estimators": {"lab": {"gyr_noise": 0.02}}})
    assert r.status_code == 422
    assert r.json()["detail"][0]["msg"] == "gyr_noise was renamed gyr_std in lab (per-sample σ, rad/s)"
    # a removed one says why, and what replaced it
    r = api.patch("/api/params", json={"estimators": {"robust": {"bias_heading_noise": 0.02}}})
    assert r.status_code == 422
    assert r.json()["detail"][0]["msg"].startswith("bias_heading_noise was removed from robust (the bias "
                                                   "about the vertical is learned from the heading's drift")
    r = api.patch("/api/params", json={"gyr_noise": 0.01})
    assert r.status_code == 422 and "robust's own" in r.json()["detail"][0]["msg"]
    assert api.get("/api/params").json() == before


def test_patch_primary_specific_and_gui_follows(srv, api):
    gui = srv.app.state.gui
    r = api.patch("/api/params", json={"primary": "lab",
                                       "estimators": {"lab": {"time_update": "approx", "acc_std": 0.3}}})
    assert r.status_code == 200
    p = r.json()
    assert p["primary"] == "lab"
    assert p["estimators"]["lab"]["time_update"] == "approx"
    assert p["estimators"]["lab"]["acc_std"] == pytest.approx(0.3)
    assert api.get("/api/state").json()["primary"] == "lab"
    # the GUI shows what the API set (one source of truth)
    ctl = {(c.estimator, c.name): c for c in gui.controls}
    wait_for(lambda: gui.primary.value == "lab", what="GUI primary")

    def first_in_tuning():   # the folder the Tuning tab shows first, and lab's bias tool's place
        folders = {**gui.folders, "bias tool": gui.bias_folder}
        return min(folders, key=lambda k: folders[k].order)

    # the primary's controls come first; lab's bias tool sits just before lab's own folder
    wait_for(lambda: first_in_tuning() == "bias tool", what="lab's folders first")
    assert gui.bias_folder.order < gui.folders["lab"].order < min(
        f.order for n, f in gui.folders.items() if n != "lab")
    assert ctl[("lab", "time_update")].handle.value == "approx"
    assert ctl[("lab", "acc_std")].from_gui(ctl[("lab", "acc_std")].handle.value) == pytest.approx(0.3)
    api.patch("/api/params", json={"use_mag": False})
    assert wait_for(lambda: gui.switches["use_mag"].value is False, what="GUI switch")
    # and a GUI change reaches the API (the callback validates and posts)
    gui.switches["use_gyr"].value = False
    wait_for(lambda: api.get("/api/params").json()["use_gyr"] is False, what="GUI -> params")
    # a sync back does not post a change again (no loop): the value stays
    assert api.get("/api/params").json()["estimators"]["lab"]["acc_std"] == pytest.approx(0.3)
    api.patch("/api/params", json={"primary": "robust", "use_gyr": True,
                                   "estimators": {"lab": {"time_update": "exact", "acc_std": 0.5}}})
    wait_for(lambda: first_in_tuning() == "robust", what="robust's folder first again")
    assert gui.folders["robust"].order < gui.bias_folder.order < gui.folders["lab"].order


def test_a_number_typed_through_a_refused_value_is_not_set_back_between_keystrokes(srv, api):
    """A number box sends every keystroke. Typing 0.5 into lab's mag_std (2 µT) sends 0
    first, below its minimum: it was refused and the box set back to 2 at once, so the
    next keys made 2.5 and 2.5 was applied (a reviewer's find). The set-back now waits for
    the typing to pause; a refused value left alone is still set back, and said."""
    from app.server.gui.main import REFUSAL_SETTLE_S
    gui = srv.app.state.gui
    c = {(x.estimator, x.name): x for x in gui.controls}[("lab", "mag_std")]
    lab = lambda: api.get("/api/params").json()["estimators"]["lab"]["mag_std"]  # noqa: E731
    before = lab()
    try:
        c.handle.value = c.to_gui(0.0)              # "0", on the way to "0.5"
        time.sleep(0.6)                              # between two keys
        assert c.from_gui(c.handle.value) == 0.0     # not set back under the fingers
        c.handle.value = c.to_gui(0.5)
        wait_for(lambda: lab() == pytest.approx(0.5), what="0.5 applied")
        time.sleep(REFUSAL_SETTLE_S + 0.5)
        assert c.from_gui(c.handle.value) == pytest.approx(0.5) and lab() == pytest.approx(0.5)
        c.handle.value = c.to_gui(0.0)              # refused, and left so
        wait_for(lambda: c.from_gui(c.handle.value) == pytest.approx(0.5),
                 REFUSAL_SETTLE_S + 10.0, what="the box set back to the value in force")
        assert lab() == pytest.approx(0.5)
    finally:
        api.patch("/api/params", json={"estimators": {"lab": {"mag_std": before}}})


def test_every_parameter_of_every_estimator_has_a_control(srv):
    """The page sets every parameter (issue 6): each field of each estimator's parameter
    set has its control in that estimator's folder; the sensor switches are common."""
    from app.params import describe
    from app.server.gui.main import SENSOR_SWITCHES
    gui, ensemble = srv.app.state.gui, srv.engine.core.ensemble
    have = {(c.estimator, c.name) for c in gui.controls}
    for name in ensemble.names:
        fields = {row["name"] for row in describe(type(ensemble.params_of(name)))}
        missing = fields - dict(SENSOR_SWITCHES).keys() - {n for e, n in have if e == name}
        assert not missing, (name, sorted(missing))
    assert set(gui.switches) == set(dict(SENSOR_SWITCHES))     # the common switches


def test_every_gui_control_is_patchable(srv, api):
    gui = srv.app.state.gui
    assert gui.controls
    for c in gui.controls:
        value = getattr(srv.engine.core.ensemble.params_of(c.estimator), c.name)
        r = api.patch("/api/params", json={"estimators": {c.estimator: {c.name: value}}})
        assert r.status_code == 200, (c.estimator, c.name, r.text)


def test_websocket_streams_every_estimate(srv, api):
    sim = simulate(("still",), seed=7)
    lines = sim.lines()
    n_motion = sum(1 for s in sim.samples if s[1] in MOTION_TAGS)

    async def collect():
        got = []
        async with websockets.connect(f"{srv.ws_url}/ws/state", max_size=None) as ws:
            first = json.loads(await ws.recv())
            assert "state" in first
            await asyncio.to_thread(play, srv, api, lines)
            while len(got) < n_motion:
                msg = json.loads(await asyncio.wait_for(ws.recv(), 30.0))
                got.extend(msg["estimates"])
        return got

    got = asyncio.run(collect())
    assert len(got) == n_motion
    ts = [g["t"] for g in got]
    assert ts == sorted(ts)
    assert got[-1]["t"] == pytest.approx(sim.samples[-1][0] / 1000.0)
    assert all(len(g["q"]) == 4 for g in got)


def test_presets_save_and_load(srv, api):
    api.patch("/api/params", json={"estimators": {"lab": {"acc_std": 0.77}}})
    r = api.post("/api/presets/save", json={"name": "test-preset"})
    assert r.status_code == 200 and Path(r.json()["saved"]).is_file()
    api.patch("/api/params", json={"estimators": {"lab": {"acc_std": 0.5}}})
    r = api.post("/api/presets/load", json={"name": "test-preset"})
    assert r.status_code == 200
    assert r.json()["estimators"]["lab"]["acc_std"] == pytest.approx(0.77)
    assert api.post("/api/presets/save", json={"name": "../evil"}).status_code == 422
    assert api.post("/api/presets/load", json={"name": "missing"}).status_code == 422
    api.patch("/api/params", json={"estimators": {"lab": {"acc_std": 0.5}}})


def test_reset_forgets_orientation(srv, api):
    play(srv, api, simulate(("still",), seed=1).lines())
    assert api.get("/api/state").json()["initialized"] is True
    r = api.post("/api/reset")
    assert r.status_code == 200
    st = api.get("/api/state").json()
    assert st["initialized"] is False and st["counts"]["updates"]["lab"]["acc"] == {}


def test_demo_source_and_phone_takeover(tmp_path):
    with running_server(source="demo", preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        st = wait_for(lambda: (lambda x: x if x["t"] and x["counts"]["samples"] > 200 else None)(
            api.get("/api/state").json()), what="demo samples")
        assert st["source"] == "demo" and st["truth_q"] is not None and st["phone_q"] is not None
        assert st["error_to_truth_deg"] is not None
        gui = s.app.state.gui
        gui.refresh_text()
        assert gui.resume.disabled is True       # the demo runs: nothing to resume
        lines = simulate(("still",), seed=2).lines()
        with Phone(s.phone_port) as ph:
            ph.send_lines(lines[:200])
            wait_for(lambda: api.get("/api/state").json()["source"] == "phone", what="the phone")
            gui.refresh_text()
            assert gui.resume.disabled is True   # a phone streams: the demo is not to be resumed
            ph.send_lines(lines[200:])
        st = wait_for(lambda: (lambda x: x if x["source"] == "phone-disconnected"
                               and x["counts"]["buffered"] == 0 and x["counts"]["queued"] == 0
                               else None)(api.get("/api/state").json()), what="the end of the stream")
        assert st["source"] == "phone-disconnected" and "disconnected" in st["status"]
        assert st["counts"]["samples"] == len(lines)
        # the demo does not resume by itself: the last state stays
        t_last = st["t"]
        assert api.get("/api/state").json()["t"] == t_last
        assert srv_gui_text(s).find("disconnected") >= 0
        assert gui.resume.disabled is False      # paused by the phone: the button offers it
        assert gui.resume.visible is True         # always there: nothing moves when it is offered
        api.post("/api/source/resume")
        wait_for(lambda: api.get("/api/state").json()["source"] == "demo", what="demo resumed")
        wait_for(lambda: (gui.refresh_text(), gui.resume.disabled)[1], what="the button greyed again")


def srv_gui_text(s) -> str:
    gui = s.app.state.gui
    gui.refresh_text()
    return gui.status.content


def test_replay_source(tmp_path):
    log = tmp_path / "sensorLog_test.txt"
    log.write_text("\n".join(simulate(("still",), seed=4).lines()) + "\n")
    with running_server(source=str(log), preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        st = wait_for(lambda: (lambda x: x if x["counts"]["samples"] > 100 else None)(
            api.get("/api/state").json()), what="replayed samples")
        assert st["source"] == "replay" and "sensorLog_test.txt" in st["status"]


def test_resume_offers_a_replay_started_from_the_page_and_nothing_without_one(tmp_path):
    """With ``--source none`` there is nothing to resume after a phone; a log replayed from
    the page (POST /api/replay) is a background source like the demo: once a phone has
    taken over and left, "Resume demo" offers it again."""
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "lesson.txt").write_text("\n".join(simulate(("still",), seed=4).lines()) + "\n")
    lines = simulate(("still",), seed=5).lines()
    with running_server(source="none", preset_dir=tmp_path, recordings=rec) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        gui = s.app.state.gui
        play(s, api, lines)
        gui.refresh_text()
        assert gui.resume.disabled is True       # no demo, no replay: nothing to resume
        api.post("/api/replay", json={"name": "lesson"}).raise_for_status()
        wait_for(lambda: api.get("/api/state").json()["source"] == "replay", what="the replay")
        play(s, api, lines)
        gui.refresh_text()
        assert gui.resume.disabled is False      # the replay waits behind the phone that left
        api.post("/api/source/resume")
        wait_for(lambda: api.get("/api/state").json()["source"] == "replay", what="the replay again")


def test_busy_port_is_reported():
    from app.server.run import serve
    import socket
    import types
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        port = blocker.getsockname()[1]
        args = types.SimpleNamespace(host="127.0.0.1", port=port, viewer_port=free_port(),
                                     phone_port=free_port(), config=None, source="none")
        assert serve(args) != 0


def test_scene_draws_a_rejected_sensor(srv):
    """A refused magnetometer sample turns its arrow red (viser takes the colour as an
    array); the indicators name the gate, the same text in the pill and the 3D label."""
    from app.estimators.base import F_MAG, F_MAG_VAL, R_NORM, StepFlags, new_flags
    from app.server.gui.main import _indicators_html
    from app.server.gui.scene import Indicators, describe_rejection
    f = new_flags()
    f[F_MAG], f[F_MAG_VAL] = R_NORM, 80.0
    flags = StepFlags.from_row(1.0, f)
    eng, scene = srv.engine, srv.app.state.scene
    snap = eng.core.snapshot()
    snap.mag, snap.mag_flags, snap.initialized = np.array([0.0, 20.0, -75.0]), flags, True
    scene.draw(snap)
    assert scene.mag.colors.tolist() == [230, 30, 30]
    ind = Indicators(mag=describe_rejection("mag", flags))
    scene.set_indicators(ind)
    assert scene.status.text == "mag disturbed: |m| = 80.0 µT"
    assert "mag disturbed: |m| = 80.0 µT" in _indicators_html(ind)
    snap.mag_flags = StepFlags.from_row(1.0, new_flags())
    scene.draw(snap)
    assert scene.mag.colors.tolist() != [230, 30, 30]


def test_the_whatif_goes_to_a_new_primary(srv, api):
    """The Lab tab's what-if was pre-set to the primary at start-up: after a switch to lab its
    re-run changed robust. It follows the primary now, unless a viewer picked another."""
    tab = srv.app.state.toolkit_tab
    assert tab.whatif.est.value == "robust"
    try:
        api.patch("/api/params", json={"primary": "lab"})
        wait_for(lambda: tab.whatif.est.value == "lab", 10.0, what="the what-if on lab")
        lab_params = {f.name for f in fields(srv.app.state.engine.core.ensemble.params_of("lab"))}
        assert tab.whatif.rows and all(r["name"] in lab_params for r in tab.whatif.rows.values())
        tab.whatif.est.value = "complementary"                 # a viewer's own pick stays
        api.patch("/api/params", json={"primary": "robust"})
        time.sleep(1.5)
        assert tab.whatif.est.value == "complementary"
    finally:
        api.patch("/api/params", json={"primary": "robust"})


def test_the_whatif_is_ready_to_show_a_change_on_the_newest_recording(tmp_path):
    """A reviewer's find: the what-if stayed on the oldest recording when a new one was
    made, and after a new primary it offered the magnetometer "on", as it was: a click
    re-ran nothing. It goes to a recording just made, and offers a switch turned over."""
    with running_server(source="demo", preset_dir=tmp_path, recordings=tmp_path / "rec") as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        tab = s.app.state.toolkit_tab
        for name in ("first", "second"):
            assert api.post("/api/recordings/start", json={"name": name}).status_code == 200
            time.sleep(1.0)
            assert api.post("/api/recordings/stop").status_code == 200
            wait_for(lambda: tab.whatif.recording.value == name, 10.0, what=f"the what-if on {name}")
        api.patch("/api/params", json={"primary": "lab"})
        wait_for(lambda: tab.whatif.est.value == "lab", 10.0, what="the what-if on lab")
        assert tab.whatif.rows[tab.whatif.param.value]["name"] == "use_mag"
        assert tab.whatif.choice.value == "off"


def test_a_sensor_switched_off_and_a_silent_phone_are_said_so(srv, api):
    """The phone app stops its magnetometer and its orientation while the stream goes on:
    their rates read 0 (stopped) and the field's last judgement is gone ("absent", not a
    stale "disturbed"), the phone's own orientation too; then the app sends nothing, the
    connection open: the status says so instead of "streaming"."""
    sim = simulate(("still", "turn_z", "still"), seed=5)
    lines = sim.lines()
    t_end = max(s[0] for s in sim.samples)
    cut = t_end - 6000                         # the last 6 s without MAG and ORI
    kept = [ln for ln in lines
            if not (ln.split("\t")[1] in ("MAG", "ORI") and int(ln.split("\t")[0]) > cut)]
    n_before = api.get("/api/state").json()["counts"].get("total_sessions", 0)
    with Phone(srv.phone_port) as ph:
        ph.send_lines(kept)
        st = wait_for(lambda: (lambda s: s if s["counts"].get("total_sessions", 0) > n_before
                               and s["t"] is not None and s["t"] * 1000 >= t_end - 100
                               and s["source"] == "phone" else None)(api.get("/api/state").json()),
                      what="the stream processed")
        assert st["rates_hz"]["MAG"] == 0.0 and st["rates_hz"]["ORI"] == 0.0
        assert st["rates_hz"]["ACC"] == pytest.approx(100.0, rel=0.05)
        assert st["mag"]["reason"] == "absent" and not st["mag_rejected"]
        assert st["acc"]["reason"] != "absent"
        assert st["phone_q"] is None and st["error_to_phone_deg"] is None
        assert "streaming" in st["status"] and st["silent_s"] is None
        stream = api.get("/api/connect").json()["stream"]
        assert stream["rates_hz"]["MAG"] == 0.0
        # the page's read-outs say it, the field's indicator is off, no field arrow is drawn
        why = srv.app.state.engine.plot_feed.meta()["why"]
        assert "magnetometer stopped sending" in why["mag"] and "no accelerometer" in why["acc"]
        gui = srv.app.state.gui
        wait_for(lambda: "MAG stopped" in gui.readouts.content, 10.0, what="MAG stopped")
        assert gui.indicators_now.mag is None
        # the scene refreshes on its own tick (scene_hz), after the read-outs: wait for it
        wait_for(lambda: not np.asarray(gui.scene.mag.points).any(), 10.0,
                 what="the field's arrow gone")
        # the plots' history: the phone's own orientation until ORI_HOLD_S after its last
        # sample, none after (no frozen pose drawn as live, nor errors against it)
        core = srv.app.state.engine.core
        w = core.history.pose.window(10.0, 100_000)
        t_ori = max(x[0] for x in sim.samples if x[1] == "ORI" and x[0] <= cut) / 1000.0
        has = np.isfinite(w["phone_q"]).all(axis=1)
        assert has[w["t"] < t_ori].all() and not has[w["t"] > t_ori + ORI_HOLD_S + 0.05].any()
        # the Lab tab's read-outs: no error to a frozen phone pose, no stale field decision
        lab = srv.app.state.toolkit_tab._readouts()
        for row in lab.splitlines()[2:]:
            assert row.split("|")[3:5] == [" - ", " - "], row
        # the app goes quiet, the connection stays open; lines it cannot parse are no
        # sign of life either
        st = wait_for(lambda: (lambda s: s if "no samples for" in s["status"] else None)(
            api.get("/api/state").json()), 15.0, what="the silent status")
        assert st["source"] == "phone" and "is the app still sending" in st["status"]
        assert st["silent_s"] >= 3.0
        # what the reorder window held when the app went quiet is processed, up to the
        # time both sensors still sending reached (it waited for the next chunk or the
        # end: the page showed a state 0.1-0.2 s old)
        reached = min(max(int(ln.split("\t")[0]) for ln in kept if ln.split("\t")[1] == tag)
                      for tag in ("ACC", "GYR"))
        assert st["t"] * 1000 == pytest.approx(reached, abs=1.0), st["counts"]
        for _ in range(4):
            ph.send_lines(["not a line", "123\tACC\t1.0"])
            time.sleep(0.5)
        st = api.get("/api/state").json()
        assert "no samples for" in st["status"] and st["counts"]["malformed"] >= 8
