"""Any phone: Sensor Logger and phyphox pushing to a real server (uvicorn on a free
loopback port) from real HTTP clients, with the phones-tyrex trials converted to each
app's format (Michel et al., PerCom 2017, CeCILL 2.1); the phone slot shared with the
Sensor Fusion app's TCP stream; bad input; the experiment file and ``/api/connect``."""

from __future__ import annotations

import json
import logging
import math
import time
import xml.etree.ElementTree as ET

import httpx
import numpy as np
import pytest

from harness import Phone, running_server, wait_for
from app.quaternion import angle_between

TOKEN = "phone-apps-token"
NEXUS = "Nexus5_Guillaume_NoDist_texting.npz"
IPHONE = "iPhone5_Guillaume_NoDist_texting.npz"


def _trial(shared_dir, name):
    p = shared_dir / "data" / "phones-tyrex" / name
    if not p.is_file():
        pytest.skip(f"{p} not present")
    return p


def _client(srv, local="127.0.0.1", token=None) -> httpx.Client:
    headers = {"X-Orientlab-Token": token} if token else {}
    return httpx.Client(base_url=srv.url, timeout=10.0, headers=headers,
                        transport=httpx.HTTPTransport(local_address=local))


def _state(srv):
    return httpx.get(srv.url + "/api/state", timeout=10.0).json()


# ---------------------------------------------------------------- Sensor Logger

@pytest.mark.shared
@pytest.mark.parametrize("platform", ["android", "ios"])
def test_sensor_logger_pushes_become_the_stream_on_the_phones_clock(shared_dir, platform):
    from tyrex_sensorlogger import duplicated, messages_android, messages_ios, swapped
    path = _trial(shared_dir, NEXUS if platform == "android" else IPHONE)
    bodies = (messages_android(path, 1.0, seconds=12) if platform == "android"
              else messages_ios(path, 1.0, standardise=False, seconds=12))
    bodies = duplicated(swapped(bodies, 3), 6)            # a pair out of order, one twice
    with running_server(open_access=False, token=TOKEN) as srv, _client(srv) as phone:
        for b in bodies:
            r = phone.post("/sensorlogger", content=b, headers={"Content-Type": "application/json"})
            assert r.status_code == 200, r.text
        wait_for(lambda: _state(srv)["counts"]["samples"] > 2500, 20, what="samples processed")
        st = _state(srv)
        assert st["source"] == "phone" and st["initialized"]
        assert 1.7e9 < st["t"] < 2.0e9          # the phone's own epoch clock, in seconds
        v = httpx.get(srv.url + "/api/connect", headers={"X-Orientlab-Token": TOKEN}).json()
        sl = next(s for s in v["http"]["streams"] if s["app"] == "sensorlogger")
        assert sl["platform"] == platform
        assert sl["convention"] == ("android" if platform == "android" else "ios")
        assert sl["duplicates"] >= 1 and sl["out_of_order"] >= 1
        assert v["slot"]["holder"]["app"] == "sensorlogger"
        assert v["stream"]["app"] == "sensorlogger" and v["stream"]["late"] == 0
        # watchers see no address and no connect details
        assert httpx.get(srv.url + "/api/connect").status_code == 403
        assert httpx.get(srv.url + "/api/info").json()["lan_ip"] is None


@pytest.mark.shared
def test_a_longer_batch_period_is_one_stream_not_one_per_push(shared_dir, monkeypatch):
    """Sensor Logger's batch period is the user's setting. Pushes further apart than the
    silence that ends a push stream ended it before every push: a new session each time,
    the filters started over. The stream now waits 2.5 of its batch periods (here the
    silence limit is cut to 1 s and the phone pushes 2 s batches every 2 s)."""
    from tyrex_sensorlogger import messages_android
    from app.server import phones
    monkeypatch.setattr(phones, "PUSH_END_S", 1.0)
    bodies = messages_android(_trial(shared_dir, NEXUS), 2.0, seconds=8)
    assert len(bodies) == 4
    with running_server() as srv, _client(srv) as phone:
        n0 = _state(srv)["counts"]["total_sessions"]
        for i, b in enumerate(bodies):
            if i:
                time.sleep(2.0)
            r = phone.post("/sensorlogger", content=b, headers={"Content-Type": "application/json"})
            assert r.status_code == 200, r.text
        st = wait_for(lambda: (lambda s: s if s["counts"]["samples"] > 2500 else None)(_state(srv)),
                      20, what="samples processed")
        assert st["counts"]["total_sessions"] == n0 + 1 and st["source"] == "phone"
        # and it still ends: 2.5 periods (5 s) after the last push
        wait_for(lambda: _state(srv)["source"] == "phone-disconnected", 15, what="the end")


@pytest.mark.shared
def test_orientation_held_back_for_its_convention_is_not_a_stopped_sensor(shared_dir):
    """The presenter sets Sensor Logger's convention by hand (here a wrong one): the app's
    own orientation is checked again and held back meanwhile, for good once the check
    fails. The phone still sends it: it read "ORI stopped" (switched off in the app?) once
    3 s had passed. Now the rates, the read-outs and the plots say it is held back, and why."""
    from tyrex_sensorlogger import messages_android
    bodies = messages_android(_trial(shared_dir, NEXUS), 1.0, seconds=22)
    with running_server() as srv, _client(srv) as phone:
        def push(bs):
            for b in bs:
                r = phone.post("/sensorlogger", content=b)
                assert r.status_code == 200, r.text

        def sl():
            v = httpx.get(srv.url + "/api/connect", timeout=10.0).json()
            return next(s for s in v["http"]["streams"] if s["app"] == "sensorlogger"), v["stream"]

        push(bodies[:8])
        wait_for(lambda: sl()[0]["orientation"]["state"] == "ok", 20, what="ORI checked")
        st = wait_for(lambda: (lambda s: s if s["rates_hz"].get("ORI") else None)(_state(srv)),
                      20, what="ORI streaming")
        assert st["withheld"] == {}
        t_reset = st["t"]
        r = phone.post("/api/sensorlogger/convention", json={"convention": "ios"})
        assert r.status_code == 200, r.text
        push(bodies[8:15])
        st = wait_for(lambda: (lambda s: s if s["t"] > t_reset + 6.0 else None)(_state(srv)),
                      20, what="the stream 6 s on")
        assert "ORI" not in st["rates_hz"] and st["rates_hz"]["ACC"] > 0
        stream_sl, stream = sl()
        state = stream_sl["orientation"]["state"]
        assert state in ("checking", "left out")
        why = {"checking": "not yet checked", "left out": "left out: its convention"}[state]
        assert "ORI" in st["withheld"] and st["withheld"]["ORI"].startswith(why), st["withheld"]
        assert stream["withheld"] == st["withheld"] and "ORI" not in stream["rates_hz"]
        gui = srv.app.state.gui
        wait_for(lambda: "ORI held back" in gui.readouts.content, 10.0, what="ORI held back")
        assert "ORI stopped" not in gui.readouts.content
        why = srv.app.state.engine.plot_feed.meta()["why"]
        assert "held back" in why["error"], why
        # then Orientation is switched off in the app: no longer held back, it stopped
        no_ori = []
        for b in bodies[15:]:
            m = json.loads(b)
            m["payload"] = [x for x in m["payload"] if x.get("name") != "orientation"]
            no_ori.append(json.dumps(m).encode())
        push(no_ori)
        st = wait_for(lambda: (lambda s: s if s["t"] > t_reset + 12.5 else None)(_state(srv)),
                      20, what="the stream 12.5 s on")
        assert st["withheld"] == {} and st["rates_hz"]["ORI"] == 0.0, st["rates_hz"]
        wait_for(lambda: "ORI stopped" in gui.readouts.content, 10.0, what="ORI stopped")


@pytest.mark.shared
def test_a_sensor_logger_message_seconds_late_leaves_the_clock_alone(shared_dir):
    """Message 8 arrives after 12 (Wi-Fi held it): its place was given up 1.5 s after 9
    came. Its readings were released late, and the orderer took a run of readings 5 s
    behind for the phone's clock stepping back: it moved the stream's time on by 5 s for
    good (every tag's clock offset -5 s, counts.jumps 2, late 0). Now those readings are
    dropped and counted late, and the clock stays the phone's."""
    from tyrex_sensorlogger import messages_android
    bodies = messages_android(_trial(shared_dir, NEXUS), 1.0, seconds=16)
    order = list(range(8)) + list(range(9, 13)) + [8] + list(range(13, len(bodies)))
    with running_server() as srv, _client(srv) as phone:
        for i in order:
            r = phone.post("/sensorlogger", content=bodies[i])
            assert r.status_code == 200, r.text
            time.sleep(0.5)
        wait_for(lambda: _state(srv)["counts"]["late"] > 0, 10, what="late readings counted")
        st = _state(srv)
        assert st["counts"]["jumps"] == 0
        assert all(abs(v) < 0.5 for v in st["clock_offsets_s"].values()), st["clock_offsets_s"]
        v = httpx.get(srv.url + "/api/connect").json()
        sl = next(s for s in v["http"]["streams"] if s["app"] == "sensorlogger")
        assert sl["late"] == 1 and sl["late_readings"] == st["counts"]["late"]


def test_resume_demo_is_refused_while_a_phone_streams():
    """The demo resumes after a phone has left, as the docs say: while one streams,
    POST /api/source/resume took the stream from it (the Sensor Fusion app's connection
    reset, the student had to start again). Now 409, and the phone goes on."""
    with running_server(source="demo") as srv, Phone(srv.phone_port) as ph:
        lines = [f"{t} ACC 0.0 0.0 9.81" for t in range(1000, 3000, 10)]
        ph.send_lines(lines[:100])
        wait_for(lambda: _state(srv)["source"] == "phone", 20, what="the phone streams")
        r = httpx.post(srv.url + "/api/source/resume")
        assert r.status_code == 409 and "phone is streaming" in r.json()["detail"]
        ph.send_lines(lines[100:])
        wait_for(lambda: _state(srv)["counts"]["lines"] == len(lines), 20, what="every line")
        assert _state(srv)["source"] == "phone" and not ph.closed_by_server(0.5)
    with running_server(source="demo") as srv:
        assert httpx.post(srv.url + "/api/source/resume").json() == {"ok": True}


def test_the_slot_takes_true_or_false_only():
    """{"locked": "yes"} locked the slot (FastAPI read the text as true): a typo in a
    presenter's script shut every phone out. JSON booleans only; the rest is refused."""
    with running_server() as srv:
        for body in ({"locked": "yes"}, {"locked": 1}, {"release": "true"}):
            r = httpx.post(srv.url + "/api/phone", json=body)
            assert r.status_code == 422 and list(body)[0] in r.text, (body, r.text)
        assert httpx.get(srv.url + "/api/phone").json()["locked"] is False
        assert httpx.post(srv.url + "/api/phone", json={"locked": True}).json()["locked"] is True


def test_bad_pushes_are_refused_with_the_reason_and_nothing_valid_is_lost():
    reading = {"name": "gyroscope", "time": 1760000000013001000,
               "values": {"x": 0.01, "y": 0.0, "z": 0.0}}
    bad = {"name": "gyroscope", "time": 1760000000014001000,
           "values": {"x": float("nan"), "y": 0.0, "z": 0.0}}
    acc = {"name": "totalacceleration", "time": 1760000000013501000,
           "values": {"x": 0.0, "y": 0.0, "z": 9.81}}
    with running_server(max_push_bytes=200_000) as srv, _client(srv) as phone:
        assert phone.post("/sensorlogger", content=b"{not json").status_code == 400
        r = phone.post("/sensorlogger", content=b'{"payload": 3}')
        assert r.status_code == 400 and "payload" in r.text
        r = phone.post("/sensorlogger", content=b"x" * 300_000)
        assert r.status_code == 413
        body = {"messageId": 1, "sessionId": "s", "deviceId": "d",
                "payload": [reading, bad, acc, {"name": "light", "time": 1, "values": {"lux": 3}}]}
        body = json.dumps(body).replace("NaN", "NaN")
        assert phone.post("/sensorlogger", content=body.encode()).status_code == 200
        v = srv.app.state.connect.view(None)
        assert v["http"]["counts"]["sensorlogger"]["bad"] == {"bad_json": 1, "bad_shape": 1} or \
            sum(v["http"]["counts"]["sensorlogger"]["bad"].values()) == 2
        sl = v["http"]["streams"][0]
        assert sum(sl["invalid"].values()) >= 1          # the NaN reading, counted
        wait_for(lambda: srv.engine.core.session is not None
                 and sum(srv.engine.core.session.orderer.counters.tags.values()) >= 2,
                 10, what="the valid readings of the batch")


# ---------------------------------------------------------------- one phone at a time

def test_one_phone_at_a_time_across_apps_and_the_presenter_releases_it():
    """A Sensor Fusion phone streams over TCP: a Sensor Logger phone is refused with a
    499 whose text the app shows; a stray TCP client trickling a sample every 2 s holds
    the slot until the presenter releases it; then the other phone gets in."""
    msg = {"messageId": 1, "sessionId": "a", "deviceId": "b",
           "payload": [{"name": "gyroscope", "time": 1760000000013001000,
                        "values": {"x": 0.0, "y": 0.0, "z": 0.0}}]}
    with running_server(open_access=False, token=TOKEN) as srv, \
            _client(srv, "127.0.0.2") as other, _client(srv, token=TOKEN) as presenter:
        with Phone(srv.phone_port) as stray:
            t0 = 0
            stray.send_lines([f"{t0}\tACC\t0\t0\t9.81"])
            wait_for(lambda: srv.app.state.slot.holder is not None, 10, what="TCP phone holds the slot")
            for k in range(3):                       # trickles: still the holder
                time.sleep(1.0)
                stray.send_lines([f"{t0 + 1000 * (k + 1)}\tACC\t0\t0\t9.81"])
                r = other.post("/sensorlogger", content=json.dumps(msg).encode())
                assert r.status_code == 499 and "another phone" in r.text
            assert presenter.post("/api/phone", json={"locked": True}).json()["slot"]["locked"]
            r = presenter.post("/api/phone", json={"release": True})
            assert r.status_code == 200 and r.json()["slot"]["holder"] is None
            assert stray.closed_by_server(5.0)
            r = other.post("/sensorlogger", content=json.dumps(msg).encode())
            assert r.status_code == 499 and "locked" in r.text
            presenter.post("/api/phone", json={"locked": False})
            r = other.post("/sensorlogger", content=json.dumps(msg).encode())
            assert r.status_code == 200
            assert srv.app.state.slot.holder.phone_app == "sensorlogger"
        # a watcher can neither release nor lock
        assert httpx.post(srv.url + "/api/phone", json={"release": True}).status_code == 403


def test_a_released_tcp_phone_is_kept_out_when_it_reconnects_from_another_port(caplog):
    """The release keeps the same phone out for 30 s. A Sensor Fusion phone reconnects from
    a new port each time, and the slot keyed the ban by host:port: it was let straight
    back in (a reviewer's find). The ban is now on its address; another phone gets in.
    The server's log gives the release as the reason it left (it said "end of stream")."""
    caplog.set_level(logging.INFO, logger="orientlab.receiver")
    with running_server(open_access=False, token=TOKEN) as srv, \
            _client(srv, token=TOKEN) as presenter, _client(srv, "127.0.0.2") as other:
        with Phone(srv.phone_port) as ph:
            ph.send_lines(["0\tACC\t0\t0\t9.81", "10\tACC\t0\t0\t9.81"])
            wait_for(lambda: srv.app.state.slot.holder is not None, 10, what="the phone holds the slot")
            r = presenter.post("/api/phone", json={"release": True})
            assert r.status_code == 200 and r.json()["slot"]["holder"] is None
            assert ph.closed_by_server(5.0)
        left = wait_for(lambda: [r.getMessage() for r in caplog.records if " left: " in r.getMessage()],
                        10, what="the phone's leaving logged")
        assert left[0].endswith("left: released by the presenter"), left
        refused = presenter.get("/api/phone").json()["slot"]["refused"]
        with Phone(srv.phone_port) as again:             # the same address, a new port
            try:
                again.send_lines(["20\tACC\t0\t0\t9.81", "30\tACC\t0\t0\t9.81"])
            except OSError:
                pass                                      # closed before it could send
            assert again.closed_by_server(5.0)
        slot = presenter.get("/api/phone").json()["slot"]
        assert slot["holder"] is None and slot["refused"] > refused
        assert "released this phone" in slot["last_refusal"]
        msg = {"messageId": 1, "sessionId": "a", "deviceId": "b",
               "payload": [{"name": "gyroscope", "time": 1760000000013001000,
                            "values": {"x": 0.0, "y": 0.0, "z": 0.0}}]}
        assert other.post("/sensorlogger", content=json.dumps(msg).encode()).status_code == 200


# ---------------------------------------------------------------- phyphox

@pytest.mark.shared
def test_phyphox_experiment_points_here_and_its_pushes_stream(shared_dir):
    from tyrex_phyphox import load_trial, push_bodies
    path = _trial(shared_dir, IPHONE)
    with running_server(open_access=False, token=TOKEN) as srv, _client(srv) as phone:
        r = phone.get("/phyphox/orientlab.phyphox")
        assert r.status_code == 200
        root = ET.fromstring(r.text)
        types = {s.get("type") for s in root.iter("sensor")}
        assert {"accelerometer", "gyroscope", "magnetic_field", "attitude"} <= types
        assert all(s.get("rate") == "0" for s in root.iter("sensor"))
        conn = next(root.iter("connection"))
        v = httpx.get(srv.url + "/api/connect", headers={"X-Orientlab-Token": TOKEN}).json()
        assert conn.get("address") == v["phyphox"]["push_url"]
        assert conn.get("service") == "http/post"
        trial = load_trial(path, seconds=15.0)
        for b in push_bodies(trial, 0.1).bodies:
            assert phone.post("/phyphox", content=b).status_code == 200
        wait_for(lambda: _state(srv)["counts"]["samples"] > 3000, 20, what="phyphox samples")
        st = _state(srv)
        assert st["source"] == "phone" and st["initialized"]
        # phyphox's attitude is the phone's own estimate, as fed (within 1°)
        t = st["t"]                 # experiment time (s): the phone's own clock
        i = int(np.argmin(np.abs(trial.t["ORI"] - t)))
        assert abs(trial.t["ORI"][i] - t) < 0.05
        fed = trial.v["ORI"][i].astype(float)
        assert angle_between(np.array(st["phone_q"]), fed) < math.radians(1.0)
        # the phone paused (no more pushes): its last 0.3 s, held by the reorder window,
        # are processed once it has gone quiet (1 s), up to the time every sensor reached,
        # not when the stream ends (5 s)
        reached = min(float(trial.t[tag][-1]) for tag in ("ACC", "GYR", "MAG", "ORI"))
        st = wait_for(lambda: (lambda s: s if s["t"] >= reached - 1e-6 else None)(_state(srv)),
                      20, what="the held samples processed")
        assert st["source"] == "phone" and st["t"] - reached < 0.02, (st["t"], reached)


@pytest.mark.shared
def test_phyphox_remote_access_polled_from_the_page_api(shared_dir):
    """``POST /api/phyphox/poll`` with the address phyphox shows: a custom experiment with
    its own buffer names and iOS's uneven buffers streams through the server."""
    from fake_phyphox import FakePhyphox
    from test_phyphox import _fake_sensors
    from tyrex_phyphox import load_trial
    trial = load_trial(_trial(shared_dir, NEXUS), seconds=20.0)
    with FakePhyphox(_fake_sensors(trial), speed=3.0, ios=True) as fake, \
            running_server(open_access=False, token=TOKEN) as srv, \
            _client(srv, token=TOKEN) as presenter:
        r = presenter.post("/api/phyphox/poll", json={"url": "ftp://nope"})
        assert r.status_code == 422
        r = presenter.post("/api/phyphox/poll", json={"url": fake.url})
        assert r.status_code == 200, r.text
        wait_for(lambda: _state(srv)["counts"]["samples"] > 1500, 30, what="polled samples")
        v = presenter.get("/api/connect").json()
        assert v["http"]["poll"]["state"] == "measuring" and fake.starts >= 1
        assert v["slot"]["holder"]["app"] == "phyphox-poll"
        assert fake.max_in_flight == 1
        assert presenter.post("/api/phyphox/poll", json={"url": None}).status_code == 200
        assert srv.app.state.slot.holder is None


@pytest.mark.shared
def test_phyphox_remote_access_says_what_it_lacks_recovers_and_pauses(shared_dir):
    """phyphox's own experiments record one sensor each. With one that has no magnetometer
    the Connect tab said "measuring", nothing more (a reviewer's find): it now names what
    the experiment lacks. An error while the phone was away stayed on show after it came
    back; now it goes when data flows again. The phone paused in phyphox was reported as
    "is the app still sending?", and the last 0.1 s it sent waited for more: now the
    status says it is paused, and those samples are processed."""
    from fake_phyphox import FakePhyphox
    from test_phyphox import _fake_sensors
    from tyrex_phyphox import load_trial
    trial = load_trial(_trial(shared_dir, NEXUS), seconds=30.0)
    sensors = [s for s in _fake_sensors(trial) if s.source != "magnetic_field"]
    with FakePhyphox(sensors, speed=1.0) as fake, \
            running_server(open_access=False, token=TOKEN) as srv, \
            _client(srv, token=TOKEN) as presenter:
        def poll():
            return presenter.get("/api/connect").json()["http"]["poll"]

        assert presenter.post("/api/phyphox/poll", json={"url": fake.url}).status_code == 200
        wait_for(lambda: _state(srv)["counts"]["samples"] > 300, 30, what="polled samples")
        p = poll()
        assert p["state"] == "measuring" and "no magnetometer" in p["status"], p
        fake.go_away()
        wait_for(lambda: poll()["state"] == "unreachable", 20, what="the phone away")
        assert poll()["last_error"]
        fake.come_back()
        n = _state(srv)["counts"]["samples"]
        wait_for(lambda: _state(srv)["counts"]["samples"] > n + 100, 30, what="data again")
        p = poll()
        assert p["state"] == "measuring" and p["last_error"] is None, p
        fake._stop()                                   # paused on the phone
        st = wait_for(lambda: (lambda s: s if "no samples for" in s["status"] else None)(_state(srv)),
                      20, what="the silent status")
        assert "paused on the phone" in st["status"], st["status"]
        # what the reorder window held is processed: at most each sensor's lead is left
        assert st["counts"]["buffered"] <= 4, st["counts"]
        fake.go_away()                                 # then gone: no longer "paused"
        wait_for(lambda: poll()["state"] == "unreachable", 20, what="the phone away")
        assert "paused" not in _state(srv)["status"]


@pytest.mark.browser
def test_connect_tab_qr_codes_decode_to_the_connect_addresses(tmp_path):
    """The presenter's Connect tab in a real Chromium: each app's QR code, decoded by
    zbar from a screenshot, is the address ``/api/connect`` gives; a watcher's page
    shows no address, port or code."""
    import shutil
    import subprocess
    from harness import CHROMIUM, chromium_page
    if CHROMIUM is None or shutil.which("zbarimg") is None:
        pytest.skip("needs Debian's chromium and zbar-tools (zbarimg)")
    pytest.importorskip("playwright.sync_api")
    with running_server(open_access=False, token=TOKEN) as srv:
        want = httpx.get(srv.url + "/api/connect", headers={"X-Orientlab-Token": TOKEN}).json()
        expect = {"sensorlogger": want["sensor_logger"]["url"],
                  "phyphox": want["phyphox"]["experiment_url"],
                  "sensorfusion": f'{want["sensorfusion"]["host"]}:{want["sensorfusion"]["port"]}'}
        # (the presenter's page, its cookie cleared below, then meets 403s on its polls)
        with chromium_page(f"{srv.url}/?token={TOKEN}", tmp_path / "profile", viewer=False,
                           console_errors_ok=("status of 403 (Forbidden) (http://127.0.0.1:",)) as (page, _):
            page.locator("#sl-url").filter(has_text="http").wait_for(timeout=30_000)
            for app, text in expect.items():
                page.locator(f'.apps [data-app="{app}"]').click()
                img = page.locator(f'#app-{app} img.qr')
                img.wait_for(state="visible", timeout=10_000)
                page.wait_for_function(f'document.querySelector("#app-{app} img.qr").naturalWidth > 0')
                shot = tmp_path / f"{app}.png"
                img.screenshot(path=str(shot))
                out = subprocess.run(["zbarimg", "--raw", "-q", str(shot)], capture_output=True,
                                     text=True, timeout=30)
                assert out.stdout.strip() == text, (app, out.stdout, out.stderr)
            page.locator('.apps [data-app="sensorlogger"]').click()
            assert want["sensor_logger"]["url"] in page.locator("#app-sensorlogger").inner_text()
            # this server listens on loopback only (--host 127.0.0.1): the tab says a phone
            # cannot push here, and what to do
            assert want["unreachable"] and "--host" in want["unreachable"]
            note = page.locator("#unreachable")
            note.wait_for(state="visible", timeout=10_000)
            assert "no phone can reach" in note.inner_text()
            # a student's page (no token, no cookie): no addresses, no codes
            page.context.clear_cookies()
            page2 = page.context.new_page()
            # a slow network: /api/info (whose page is this?) is held back. Until it answers
            # the page shows neither the presenter's part nor the watcher's note
            held = []
            page2.route("**/api/info", lambda route: route.continue_() if held else held.append(route))
            page2.goto(srv.url + "/")
            wait_for(lambda: (page2.wait_for_timeout(100), held)[1], 30.0, what="the page's /api/info")
            assert page2.locator("#presenter-connect").is_hidden(), "shown before /api/info answered"
            assert page2.locator("#watch-note").is_hidden()
            # and the request is dropped: the page asks again and gets its answer
            held[0].abort()
            page2.locator("#watch-note").wait_for(state="visible", timeout=30_000)
            assert page2.locator("#presenter-connect").is_hidden()
            assert want["sensorfusion"]["host"] not in page2.locator("aside").inner_text()
            assert page2.locator("img.qr[src]").count() == 0
            # a presenter's page opened while a Sensor Fusion phone streams shows that app's
            # steps (it showed Sensor Logger's whatever streamed), until the presenter picks
            with Phone(srv.phone_port) as ph:
                ph.send_lines([f"{1000 + 10 * k}\tACC\t0\t0\t9.81" for k in range(50)])
                wait_for(lambda: srv.app.state.slot.holder is not None, 10.0, what="the phone")
                page3 = page.context.new_page()
                page3.goto(f"{srv.url}/?token={TOKEN}")
                page3.locator('.apps [data-app="sensorfusion"][aria-selected="true"]').wait_for(
                    state="attached", timeout=30_000)
                assert page3.locator("#app-sensorlogger").is_hidden()
                page3.close()


def test_connect_tab_says_silent_by_the_slots_own_rule(tmp_path):
    """The Connect tab calls a phone "silent" when the slot does: once another phone may
    take over (``phone_idle_s``). It had a threshold of its own, 1.5 s, and called a phone
    silent that the slot still held as busy."""
    from harness import CHROMIUM, chromium_page
    if CHROMIUM is None:
        pytest.skip("needs Debian's chromium")
    pytest.importorskip("playwright.sync_api")
    with running_server(open_access=False, token=TOKEN, phone_idle_s=4.0) as srv:
        with chromium_page(f"{srv.url}/?token={TOKEN}", tmp_path / "profile", viewer=False) as (page, _):
            status = page.locator("#phone-status")
            with Phone(srv.phone_port) as ph:
                ph.send_lines([f"{10 * k}\tACC\t0\t0\t9.81" for k in range(20)])
                wait_for(lambda: "last data" in status.inner_text(), 30.0, what="the phone on the tab")
                seen = []

                def silent_shown():
                    page.wait_for_timeout(100)
                    if "silent for" not in status.inner_text():
                        return False
                    seen.append(httpx.get(srv.url + "/api/connect",
                                          headers={"X-Orientlab-Token": TOKEN}).json()["slot"])
                    return True
                wait_for(silent_shown, 30.0, what="the tab saying silent")
                # the slot agrees (asked after the page said so: busy can only have ended)
                assert seen[0]["holder"] is not None and not seen[0]["busy"], seen
                assert "another phone may take over" in status.inner_text()


def test_connect_tab_names_each_phone_turned_away(tmp_path):
    """While a phone streams, a student's Sensor Logger phone pushing from another address
    is refused; the presenter's Connect tab says which phone was turned away, from where,
    how often and why (it said only "refused N×" with the last reason, however many phones
    were waiting). A watcher's API answer does not carry the phone's address."""
    from harness import CHROMIUM, chromium_page
    if CHROMIUM is None:
        pytest.skip("needs Debian's chromium")
    pytest.importorskip("playwright.sync_api")
    msg = {"messageId": 1, "sessionId": "a", "deviceId": "b",
           "payload": [{"name": "gyroscope", "time": 1760000000013001000,
                        "values": {"x": 0.0, "y": 0.0, "z": 0.0}}]}
    with running_server(open_access=False, token=TOKEN) as srv, \
            _client(srv, "127.0.0.3") as student, Phone(srv.phone_port) as ph:
        ph.send_lines([f"{10 * k}\tACC\t0\t0\t9.81" for k in range(20)])
        wait_for(lambda: srv.app.state.slot.holder is not None, 10, what="the phone holds the slot")
        with chromium_page(f"{srv.url}/?token={TOKEN}", tmp_path / "profile", viewer=False) as (page, _):
            status = page.locator("#phone-status")
            for k in range(2):
                ph.send_lines([f"{200 + 10 * k}\tACC\t0\t0\t9.81"])     # still streaming
                r = student.post("/sensorlogger", content=json.dumps(msg).encode())
                assert r.status_code == 499, r.text
            # (the tab polls: it may show the first refusal before the second)
            wait_for(lambda: "turned away: Sensor Logger from 127.0.0.3 · 2×"
                     in status.inner_text(), 30.0, what="the tab naming it, twice refused")
            text = status.inner_text()
            assert "another phone (Sensor Fusion app) is streaming" in text, text
            assert "takes over once that one has been silent for" in text, text   # not "try again"
        watcher = httpx.get(srv.url + "/api/phone").json()["slot"]["turned_away"]
        assert [t["who"] for t in watcher] == ["a phone"], watcher
        assert watcher[0]["app"] == "sensorlogger" and watcher[0]["times"] == 2


def test_connect_tab_says_what_to_change_for_a_right_pose(tmp_path):
    """An iPhone with Standardise on and no Magnetometer ticked showed upside down, and the
    page said only "assumed" in small print. The Connect tab now says the convention is a
    guess and where to set it; a Gravity without Accelerometer says to tick it."""
    from harness import CHROMIUM, chromium_page
    from sources.test_sensorlogger import T0, body, face_up_ios
    if CHROMIUM is None:
        pytest.skip("needs Debian's chromium")
    pytest.importorskip("playwright.sync_api")
    with running_server(open_access=False, token=TOKEN) as srv, _client(srv) as phone:
        with chromium_page(f"{srv.url}/?token={TOKEN}", tmp_path / "profile", viewer=False) as (page, _):
            status = page.locator("#phone-status")
            for m in range(30):       # 3 s, face up, no magnetometer, no accelerometer
                rows = [r for r in face_up_ios(10, t_start=T0 + m * 100_000_000, standardised=True)
                        if r["name"] not in ("magnetometer", "accelerometer")]
                assert phone.post("/sensorlogger", content=body(rows, mid=m + 1)).status_code == 200
            wait_for(lambda: "a guess" in status.inner_text(), 30.0, what="the guess said")
            text = status.inner_text()
            assert "Connect tab" in text and "tick Accelerometer" in text, text
            # the convention in force in words, as the status line says it (not "ios, ios")
            detected = page.locator("#sl-detected").inner_text()
            assert detected.startswith("in force: iPhone, Standardise"), detected


def test_phone_addresses_follow_the_address_given_with_host():
    """``--host`` names the one address the page listens on (a PC on Wi-Fi and a VPN: the
    Wi-Fi's). The banner, ``/api/connect`` and the QR codes gave phones the first LAN
    address found instead, where nothing listens (a reviewer's find). Only loopback
    addresses are bound in tests: this one is given to the pure parts (no server)."""
    from app.server.app import banner
    from app.server.connect import Connect
    from app.server.settings import Settings
    picked = "192.0.2.7"                       # TEST-NET-1: never a real host here
    connect = Connect(Settings(host=picked), None)
    assert connect.host() == picked and connect.base_url() == f"http://{picked}:8000"
    assert connect.unreachable() is None
    out = banner(Settings(host=picked), connect.host(), 8080, 3400, 8000)
    assert f"http://{picked}:8000/sensorlogger" in out and f"address {picked}" in out
    loop = Connect(Settings(host="127.0.0.1"), None)
    assert loop.host() != "127.0.0.1" and "no phone can reach" in loop.unreachable()
    assert "the Sensor Fusion app" in loop.unreachable()      # its port is on loopback too
    for name in ("localhost", "::1", "127.0.0.2"):
        assert "no phone can reach" in Connect(Settings(host=name), None).unreachable(), name
    # the page on the network, the phone's TCP port on this PC only
    tcp = Connect(Settings(host=picked, phone_host="127.0.0.1"), None).unreachable()
    assert "(the Sensor Fusion app)" in tcp and "Sensor Logger" not in tcp, tcp
    out = banner(Settings(host="127.0.0.1"), loop.host(), 8080, 3400, 8000,
                 unreachable=loop.unreachable())
    assert "note:" in out and "--host" in out


@pytest.mark.shared
def test_serve_with_a_phyphox_source_polls_it_from_the_start(shared_dir):
    """``orientlab serve --source phyphox:http://PHONE:PORT``: no demo, the phone is polled
    at once; a phone that is not there yet is a status with retries, then streams."""
    from fake_phyphox import FakePhyphox
    from test_phyphox import _fake_sensors
    from tyrex_phyphox import load_trial
    from harness import free_port
    trial = load_trial(_trial(shared_dir, IPHONE), seconds=10.0)
    fake = FakePhyphox(_fake_sensors(trial), speed=2.0)
    fake.port = free_port()
    with running_server(source=f"phyphox:http://127.0.0.1:{fake.port}") as srv:
        hp = srv.app.state.http_phones
        wait_for(lambda: hp.status()["poll"]["state"] == "unreachable", 20, what="unreachable")
        assert _state(srv)["source"] == "none"          # no demo meanwhile
        with fake:
            wait_for(lambda: _state(srv)["counts"]["samples"] > 500, 30, what="polled samples")
        assert srv.app.state.slot.status()["holder"]["app"] == "phyphox-poll"


@pytest.mark.shared
def test_a_recording_of_a_sensor_logger_iphone_is_the_same_replayable_log(shared_dir, tmp_path):
    """Recorded from Sensor Logger (an iPhone, Standardise off): the log is the app log
    format with the phone's own orientation, its events name the app and the platform,
    and ``orientlab estimate`` and the re-run read it unchanged."""
    import subprocess
    import sys
    from tyrex_sensorlogger import messages_ios
    from app.sources.readers import read_log_data
    from app.toolkit.recorded import read_events
    path = _trial(shared_dir, IPHONE)
    bodies = messages_ios(path, 1.0, standardise=False, seconds=20)
    rec_dir = tmp_path / "rec"
    with running_server(recordings=rec_dir) as srv, _client(srv) as phone:
        assert phone.post("/sensorlogger", content=bodies[0]).status_code == 200
        wait_for(lambda: srv.engine.core.session is not None, 10, what="the stream")
        assert phone.post("/api/recordings/start", json={"name": "iphone"}).status_code == 200
        for b in bodies[1:]:
            assert phone.post("/sensorlogger", content=b).status_code == 200
        wait_for(lambda: _state(srv)["counts"]["samples"] > 1500, 20, what="samples")
        assert phone.post("/api/recordings/stop").status_code == 200
        r = phone.post("/api/recordings/iphone/rerun", json={"changes": {}})
        assert r.status_code in (200, 422), r.text     # no truth: the change alone is reported
    log = rec_dir / "iphone.txt"
    data = read_log_data(log)
    assert len(data) > 1500 and data.ori is not None and np.isfinite(data.ori).any()
    start = read_events(rec_dir / "iphone.events.jsonl")[0]
    assert start["phone"]["app"] == "sensorlogger" and start["phone"]["platform"] == "ios"
    out = subprocess.run([sys.executable, "-m", "app.cli", "estimate", str(log), "-o",
                          str(tmp_path / "est.csv")], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert len((tmp_path / "est.csv").read_text().splitlines()) > 1500


def test_every_push_app_is_routed_capped_and_refuses_a_bad_body_with_its_reason():
    """The push apps are declared once (``PUSH_APPS``): each has its route, its label, the
    push's body cap (not the API's 1 MB) and a 400 with the reason for a body that is no
    message, counted under its own name (an app missing from one of the places the server
    used to list them by hand was decoded as another's, or answered 500)."""
    from app.server.phones import PUSH_APPS
    from app.sources.slot import PHONE_APPS
    assert set(PUSH_APPS) <= set(PHONE_APPS)
    with running_server(max_body_bytes=100_000, max_push_bytes=400_000) as srv, _client(srv) as phone:
        for key, app in PUSH_APPS.items():
            r = phone.post(app.path, content=b"{not json")
            assert r.status_code == 400 and r.text, (key, r.status_code, r.text)
            r = phone.post(app.path, content=b"[" + b" " * 200_000 + b"]")    # over the API's cap
            assert r.status_code == 400, (key, r.status_code)                # read, not 413
            assert phone.post(app.path, content=b"x" * 500_000).status_code == 413, key
            counts = srv.app.state.connect.view(None)["http"]["counts"][key]
            assert counts["requests"] >= 2 and counts["bad_total"] == 2, (key, counts)


def test_a_phones_model_is_shown_as_text_never_run_as_markup(tmp_path):
    """A phone names itself (phyphox's ``model``, Sensor Logger's device): the Connect tab
    wrote it into the presenter's page as HTML, so a student's phone could run a script there
    with the presenter's rights (a reviewer's find: it locked the slot). It is text now."""
    from harness import CHROMIUM, chromium_page
    from tyrex_phyphox import Trial, push_bodies
    if CHROMIUM is None:
        pytest.skip("needs Debian's chromium")
    pytest.importorskip("playwright.sync_api")
    evil = '<img id="evil" src="x" onerror="document.title=\'pwned\'"><b>bold</b>'
    n = 300
    t = np.arange(n) * 0.01 + 0.01
    still = {"ACC": np.tile([0.0, 0.0, 9.81], (n, 1)), "GYR": np.zeros((n, 3)),
             "MAG": np.tile([0.0, 20.0, -40.0], (n, 1)), "ORI": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))}
    trial = Trial("still", evil[:100], {k: t.copy() for k in still},
                  {k: v.astype(np.float32) for k, v in still.items()})
    with running_server(open_access=False, token=TOKEN) as srv, _client(srv) as phone:
        with chromium_page(f"{srv.url}/?token={TOKEN}", tmp_path / "profile", viewer=False) as (page, _):
            for b in push_bodies(trial, 0.1).bodies:
                assert phone.post("/phyphox", content=b).status_code == 200
            status = page.locator("#phone-status")
            wait_for(lambda: "<img" in status.inner_text(), 30.0, what="the model on the tab")
            assert page.locator("#phone-status img, #phone-status #evil").count() == 0
            page.wait_for_timeout(500)
            assert page.title() != "pwned"
            assert evil[:100] in status.inner_text()


def test_a_phone_sending_a_batch_every_few_seconds_keeps_the_slot_between_them(caplog):
    """Sensor Logger's batch period is the user's setting: a phone set to 2 s sends nothing
    for 2 s at a time. The slot let another phone take over after ``phone_idle_s`` whatever
    the period, so two phones took turns (a reviewer's find, 5 s batches against 1 s). The
    holder's allowance is 1.5 of its batch period once its batches show it; the status line
    does not call it silent meanwhile either."""
    from sources.test_sensorlogger import T0, body, face_up_ios
    caplog.set_level(logging.INFO, logger="orientlab.phones")
    with running_server(open_access=False, token=TOKEN, phone_idle_s=1.0) as srv, \
            _client(srv) as a, _client(srv, local="127.0.0.2") as b:
        for m in range(3):          # three 2 s batches (phone time), the last one now
            rows = face_up_ios(200, t_start=T0 + m * 2_000_000_000, standardised=True)
            assert a.post("/sensorlogger", content=body(rows, mid=m + 1)).status_code == 200
        wait_for(lambda: srv.app.state.slot.holder is not None, 10.0, what="phone A in the slot")
        time.sleep(1.6)             # past phone_idle_s, within 1.5 batch periods (3 s)
        r = b.post("/sensorlogger", content=body(face_up_ios(20), mid=1, device="d-2"))
        assert r.status_code == 499 and "another phone" in r.text, (r.status_code, r.text)
        assert "no samples for" not in _state(srv)["status"]
        slot = srv.app.state.slot
        assert slot.holder.key == "127.0.0.1" and slot.busy()
        time.sleep(1.8)             # past 1.5 batch periods: silent, B may take over
        assert not slot.busy()
        r = b.post("/sensorlogger", content=body(face_up_ios(20), mid=2, device="d-2"))
        assert r.status_code == 200
    # the terminal tells the teacher, as it does for the Sensor Fusion app's phones
    said = [x.getMessage() for x in caplog.records if x.name == "orientlab.phones"]
    assert any("127.0.0.1 (Sensor Logger) connected" in m for m in said), said
    assert any(m.startswith("refused phone 127.0.0.2 (Sensor Logger)") for m in said), said
    assert any("127.0.0.1 (Sensor Logger) left" in m for m in said), said


def test_a_refused_push_is_answered_before_its_body_is_read():
    """While a phone streams, another's push is refused: it was read whole first (16 MB a
    push; a flood of them took 0.3 GB and a core, a reviewer's find). The refusal comes on
    the request head, before a byte of the body is sent."""
    import socket
    from sources.test_sensorlogger import T0, body, face_up_ios
    with running_server(open_access=False, token=TOKEN) as srv, _client(srv) as a:
        rows = face_up_ios(100, t_start=T0, standardised=True)
        assert a.post("/sensorlogger", content=body(rows, mid=1)).status_code == 200
        wait_for(lambda: srv.app.state.slot.busy(), 10.0, what="phone A streaming")
        with socket.create_connection(("127.0.0.1", srv.settings.port), timeout=10,
                                      source_address=("127.0.0.2", 0)) as s:
            s.sendall(b"POST /sensorlogger HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                      b"Content-Type: application/json\r\nContent-Length: 10000000\r\n\r\n")
            s.settimeout(5.0)
            out = b""
            while b"another phone" not in out:      # the head and the text may come apart
                chunk = s.recv(65536)
                if not chunk:
                    break
                out += chunk
        assert out.startswith(b"HTTP/1.1 499"), out[:200]
        assert b"another phone" in out


def test_a_push_address_opened_in_a_phones_browser_says_it_works(tmp_path):
    """A student scans the Connect tab's code with the camera, or checks the address in the
    browser: GET on a push address answered 405 "Method Not Allowed", read as a broken
    server. Now it says the phone reaches the PC and what to do with the address."""
    with running_server(source="none", preset_dir=tmp_path) as srv:
        for path, app_words in (("/sensorlogger", "Sensor Logger"), ("/phyphox", "phyphox")):
            r = httpx.get(srv.url + path, timeout=10.0)
            assert r.status_code == 200 and "this phone reaches the PC" in r.text, r.text
            assert app_words in r.text
        assert httpx.post(srv.url + "/sensorlogger", content=b"{", timeout=10.0).status_code == 400


def test_the_connect_tab_names_the_sensors_not_ticked_in_the_sensor_fusion_app(tmp_path):
    """A real accelerometer-only stream from the Sensor Fusion app: the tab showed only
    "rates: ACC 120 Hz", with no word that Gyroscope and Magnetometer are not ticked."""
    from harness import CHROMIUM, chromium_page
    if CHROMIUM is None:
        pytest.skip("needs Debian's chromium")
    pytest.importorskip("playwright.sync_api")
    with running_server(open_access=False, token=TOKEN) as srv, Phone(srv.phone_port) as ph:
        with chromium_page(f"{srv.url}/?token={TOKEN}", tmp_path / "profile", viewer=False) as (page, _):
            page.locator("#tab-connect").click()
            status = page.locator("#phone-status")
            for k in range(60):                          # 6 s of a phone sending ACC only
                ph.send_lines([f"{100 * k + 10 * j}\tACC\t0\t0\t9.81" for j in range(10)])
                time.sleep(0.1)
            text = wait_for(lambda: (lambda t: t if "tick them in the app" in t else None)(
                status.inner_text()), 30.0, what="the missing sensors named")
            assert "no Gyroscope, no Magnetometer" in text and "Accelerometer" not in text, text


def test_a_push_to_a_wrong_address_says_where_pushes_go(tmp_path, caplog):
    """Sensor Logger given the page's address, or its own example path /data: the reply
    was a bare 404 or 405 and the terminal said nothing, so neither the student (the app
    shows nothing of it) nor the teacher knew. The reply and one terminal line say where
    pushes go."""
    import logging
    caplog.set_level(logging.WARNING, logger="orientlab.push")
    with running_server(source="none", preset_dir=tmp_path) as srv:
        for path in ("/data", "/", "/SensorLogger"):
            r = httpx.post(srv.url + path, content=b'{"messageId": 1}', timeout=10.0)
            assert r.status_code in (404, 405) and "/sensorlogger" in r.text, (path, r.text)
        said = [m for m in caplog.messages if "found nothing here" in m]
        assert len(said) == 1 and "'/data'" in said[0], said          # once, not per push
        r = httpx.get(srv.url + "/api/no-such-route", timeout=10.0)   # the API's 404 as before
        assert r.status_code == 404 and r.json() == {"detail": "Not Found"}
