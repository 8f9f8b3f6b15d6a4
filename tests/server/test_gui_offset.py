"""The page shows the field offset robust tracks (a magnet stuck on the phone): the read-outs
of the dashboard's panel, fed by a real live core on the simulator's turning phone (no server)."""

from __future__ import annotations

import re

import numpy as np

from app.live import LiveCore
from app.live.views import state
from app.server.gui.main import _readouts_html
from app.sources.samples import Sample
from app.sources.simulate import SimConfig, simulate

DEG = 180.0 / np.pi
OFFSET = np.array([18.0, -12.0, 20.0])        # µT, sensor frame (|o| = 29.5 µT)


def _offset_text(core) -> str:
    html = _readouts_html(state(core))
    m = re.search(r"magnet on the phone</td><td>(.*?)</td></tr>", html)
    assert m, html
    return m[1]


def test_the_panel_shows_a_magnet_on_the_phone_found_and_removed():
    cfg = SimConfig(gyr_bias=(0.0, 0.0, 0.5 / DEG))
    sim = simulate(("turn_x", "turn_y", "turn_z") * 4, seed=3, config=cfg)   # 72 s of turning
    t0 = sim.samples[0][0]
    core = LiveCore()
    s = core.open_session("demo", "test")
    core.start(s)
    seen = []
    chunk = []
    for ms, tag, v in sim.samples:
        v = np.asarray(v, dtype=float)
        if tag == "MAG" and ms - t0 >= 10_000:          # stuck on the phone from 10 s
            v = v + OFFSET
        chunk.append(Sample(ms, tag, tuple(v)))
        if len(chunk) == 200:
            core.process(s, core.feed(s, chunk))
            chunk = []
            seen.append(_offset_text(core))
    core.process(s, core.feed(s, chunk) + core.close_session(s))
    assert seen[0] == "none found"              # no magnet yet
    last = _offset_text(core)
    assert last.startswith("<b>removed</b>"), last
    size = float(re.search(r"removed</b>: ([\d.]+) µT", last)[1])
    assert abs(size - np.linalg.norm(OFFSET)) < 2.0, last
    vec = [float(x) for x in re.search(r"<code>([^<]*)</code>", last)[1].split()]
    assert np.linalg.norm(np.asarray(vec) - OFFSET) < 2.0, last
    # on the way it was found before it was trusted
    assert any(x.startswith("fitting") for x in seen), seen
    # the heading noise the data sets now, beside it
    html = _readouts_html(state(core))
    m = re.search(r"field's heading noise</td><td>([\d.]+) deg·√s \(the field wanders ([\d.]+)°\)", html)
    assert m, html
    d = core.ensemble.estimator("robust").diagnostics()
    assert float(m[1]) == round(np.degrees(d.heading_noise_now), 1) >= round(np.degrees(
        core.ensemble.params_of("robust").heading_noise), 1)
    assert float(m[2]) == round(np.degrees(d.heading_wander), 1)


def test_estimators_without_the_fit_show_no_offset_row():
    html = _readouts_html({**_min_state(), "diagnostics": {}})
    assert "magnet on the phone" not in html and "heading noise" not in html


def _min_state() -> dict:
    core = LiveCore()
    return state(core)
