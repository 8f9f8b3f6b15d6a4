"""The GUI's own logic against the real server with the demo running in real time:
lab given the gyroscope bias from the page follows the demo's truth through the turns;
the demo's shake and magnet light their indicators with the gate and its value."""

from __future__ import annotations

import logging
import time

import httpx
import numpy as np

from harness import running_server, wait_for
from app.sources.simulate import SCENE_DURATION_S, SimConfig


def stream_time(gui, api) -> float | None:
    st = api.get("/api/state").json()
    t0 = gui.stream_t0()
    return None if st["t"] is None or t0 is None else st["t"] - t0


def scene_start(name: str) -> float:
    """Stream time at which a demo scene starts (the first loop)."""
    t = 0.0
    for s in SimConfig().scenes:
        if s == name:
            return t
        t += SCENE_DURATION_S[s]
    raise KeyError(name)


def watch_indicator(gui, scene_, api, sensor: str, start: float, end: float) -> str | None:
    """Refresh the GUI as its task does until ``sensor``'s indicator lights between
    ``start`` and ``end`` (stream time); the pill and the 3D label must agree."""
    while True:
        t = stream_time(gui, api) or 0.0
        gui.refresh_text()
        ind = gui.indicators_now
        text = getattr(ind, sensor)
        if start <= t <= end and text is not None:
            assert scene_.status.text == ind.text()
            assert f"{sensor} disturbed: {text}" in gui.indicators.content
            return text
        if t > end:
            return None
        time.sleep(0.05)


def test_demo_lab_with_bias_follows_the_truth_and_disturbances_light(tmp_path):
    """One loop of the demo, in real time (~32 s):

    - at rest (the demo starts lying still) the page's "calibrate gyro bias" gives lab
      the simulated gyroscope's bias; during a turn it refuses (the phone moves);
    - lab, primary, then stays within a few degrees of the truth through the three turns;
    - the default robust, primary again, lights "acc disturbed" in the shake and "mag
      disturbed" at the magnet, with the gate and its value, pill and 3D label alike.
    """
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        gui, scene_ = srv.app.state.gui, srv.app.state.scene
        default_primary = api.get("/api/params").json()["primary"]
        assert api.patch("/api/params", json={"primary": "lab"}).status_code == 200
        turns = scene_start("turn_x")
        assert turns >= 3.0, "the demo starts with the phone at rest"
        wait_for(lambda: (stream_time(gui, api) or 0.0) >= turns - 1.0, 60.0, 0.02,
                 what="the end of the demo's rest")
        # a variant of lab (exercise 9's approximate time update) gets the phone's bias too
        r = api.post("/api/estimators", json={"name": "lab-approx", "base": "lab",
                                              "params": {"time_update": "approx"}})
        assert r.status_code == 200, r.text
        r = api.post("/api/calibrate/bias", json={"seconds": 2.0})
        assert r.status_code == 200, r.text
        bias = r.json()["applied"]["lab"]["gyr_bias"]
        assert r.json()["applied"]["lab-approx"]["gyr_bias"] == bias
        assert api.delete("/api/estimators/lab-approx").status_code == 200
        assert np.allclose(bias, SimConfig().gyr_bias, atol=0.003)
        assert np.allclose(r.json()["params"]["estimators"]["lab"]["gyr_bias"], bias)
        assert np.allclose(np.radians(r.json()["gyr_bias_deg_s"]), bias, atol=1e-5)
        for body, field in (({"seconds": 0.1}, "seconds"), ({"seconds": "2"}, "seconds"),
                            ({"secs": 2}, "secs")):
            r = api.post("/api/calibrate/bias", json=body)
            assert r.status_code == 422 and field in r.text, (body, r.text)
        assert api.patch("/api/params", json={"estimators": {"lab": {"gyr_bias": [0, 0, 0]}}}).status_code == 200
        gui.bias_seconds.value = 2.0
        gui._on_calibrate_bias(None)          # what the button does (its own, later window)
        wait_for(lambda: np.allclose(api.get("/api/params").json()["estimators"]["lab"]["gyr_bias"],
                                     SimConfig().gyr_bias, atol=0.003), what="lab's gyr_bias set")
        end = scene_start("shake")
        errs, refused = [], None
        while True:
            st = api.get("/api/state").json()
            t = st["t"] - gui.stream_t0()
            if t >= end:
                break
            if t >= turns:
                errs.append(st["estimators"]["lab"]["error_to_truth_deg"])
                if refused is None and t >= turns + 2.0:
                    refused = api.post("/api/calibrate/bias", json={"seconds": 1.5})
            time.sleep(0.1)
        assert refused is not None and refused.status_code == 409 and "moved" in refused.text, refused.text
        assert len(errs) > 20
        print(f"lab with the bias: error to truth through the turns max {max(errs):.2f}°, "
              f"median {np.median(errs):.2f}° ({len(errs)} reads)")
        assert max(errs) < 6.0
        assert api.patch("/api/params", json={"primary": default_primary}).status_code == 200
        shake = watch_indicator(gui, scene_, api, "acc", scene_start("shake"), scene_start("magnet"))
        assert shake is not None, f"acc disturbed never lit in the demo's shake ({default_primary})"
        magnet = watch_indicator(gui, scene_, api, "mag", scene_start("magnet"),
                                 scene_start("magnet") + SCENE_DURATION_S["magnet"])
        assert magnet is not None, f"mag disturbed never lit at the demo's magnet ({default_primary})"
        print(f"shake: 'acc disturbed: {shake}'; magnet: 'mag disturbed: {magnet}'")
        # the gate and the value that tripped it, not only "disturbed"
        assert any(c.isdigit() for c in shake) and any(c.isdigit() for c in magnet)


def test_the_variant_just_added_is_the_one_remove_ends(tmp_path):
    """The README's exercise 10: "Add lab-approx", then "Remove variant ends it". With an
    older variant in the dropdown (exercise 7's), the dropdown kept showing that one, and
    Remove ended it instead of lab-approx."""
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        tab = srv.app.state.toolkit_tab
        for name, base, params in (("lab-no-rejection", "lab", {"mag_band_rel": 0.0}),
                                   ("lab-approx", "lab", {"time_update": "approx"})):
            r = api.post("/api/estimators", json={"name": name, "base": base, "params": params})
            assert r.status_code == 200, r.text
            wait_for(lambda n=name: n in tab.var_remove.options, 30.0, what=f"{name} in the dropdown")
            assert tab.var_remove.value == name


OLD_PRESET = b"[robust]\nmag_nis_gate = 3.0\n[lab]\ngyr_noise = 0.02\n"


def test_the_presets_tab_lists_the_folder_and_an_old_preset_says_what_changed(tmp_path, caplog):
    """A review: the Presets tab listed only what was saved from the page (a preset saved
    through the API or a calibration, or dropped into the folder, never showed), and a
    preset with a removed or renamed key loaded with a green "Preset loaded", the changes
    said only in the server's terminal. Now the list follows the folder, and the API's
    answer and the page's notice say what was read as a new name or left out."""
    caplog.set_level(logging.WARNING, logger="orientlab.gui")
    presets = tmp_path / "presets"
    with running_server(source="demo", preset_dir=presets) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        gui = srv.app.state.gui
        assert api.post("/api/presets/save", json={"name": "by-api"}).status_code == 200
        wait_for(lambda: "`by-api`" in gui.preset_msg.content, 10.0, what="a preset saved by the API listed")
        (presets / "dropped.toml").write_bytes(OLD_PRESET)
        wait_for(lambda: "`dropped`" in gui.preset_msg.content, 10.0, what="a dropped preset listed")
        r = api.post("/api/presets/upload", content=OLD_PRESET,
                     headers={"Content-Type": "application/toml"})
        assert r.status_code == 200, r.text
        warnings = r.json().get("warnings", [])
        assert any("mag_nis_gate was removed from robust" in w and "left out" in w for w in warnings), r.text
        assert any("gyr_noise was renamed gyr_std in lab" in w for w in warnings), r.text
        assert r.json()["estimators"]["lab"]["gyr_std"] == 0.02
        r = api.post("/api/presets/load", json={"name": "by-api"})
        assert r.status_code == 200 and "warnings" not in r.json()
        gui.preset_name.value = "dropped"
        gui._on_load(None)                  # the Load preset button (no viewer: its notice is logged)
        said = [r.getMessage() for r in caplog.records if r.name == "orientlab.gui"]
        assert any(m.startswith("Preset loaded, with changes: dropped:") and "mag_nis_gate" in m
                   and "gyr_std" in m for m in said), said
