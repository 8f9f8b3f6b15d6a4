"""app/server/gui/toolkit_tab.py's heading monitor, fed by a real live core (no server)."""

from __future__ import annotations


import numpy as np

from app.live import LiveCore
from harness import feed_lines
from app.quaternion import not_estimated, q2euler_many
from app.server.gui.toolkit_tab import MONITOR_HZ, Monitor
from app.sources.sensorfusion import format_line
from app.sources.simulate import simulate


def test_the_monitor_keeps_each_estimators_heading_at_its_rate():
    core = LiveCore()
    mon = Monitor(core)    # it reads only the core's record hook
    seen = []
    core.record_listeners.append(lambda s, rec: seen.append(rec))
    sim = simulate(duration_s=6.0, seed=3)
    s = core.open_session("demo", "test")
    core.start(s)
    lines = [format_line(*x).encode() for x in sim.samples]
    for i in range(0, len(lines), 200):
        core.process(s, feed_lines(core, s, lines[i:i + 200]))
    core.process(s, core.close_session(s))
    assert set(mon.yaw) == set(core.ensemble.names) and len(mon.t) > 100
    t = np.asarray(mon.t)
    assert np.all(np.diff(t) >= 1.0 / MONITOR_HZ - 1e-9)
    all_t = np.concatenate([r.t for r in seen])
    rows = np.searchsorted(all_t, t)                      # the rows the monitor kept
    np.testing.assert_array_equal(all_t[rows], t)
    for name in core.ensemble.names:
        q = np.concatenate([r.q[name] for r in seen])[rows]
        want = np.degrees(q2euler_many(q)[:, 0])
        before = not_estimated(q)                             # no estimate yet: a gap
        assert 0 < before.sum() < 5 and not before[-1]
        want[before] = np.nan
        np.testing.assert_allclose(mon.yaw[name], want, equal_nan=True, atol=1e-9)


def test_readouts_count_a_running_phones_specific_force_apart_from_refusals(real_log_9dof):
    """A sample flagged as specific force still enters robust's low-pass: the read-out
    counts it as "accelerating (averaged in)", not as rejected; the three counts add up to
    every accelerometer sample the primary judged."""
    import re

    from app.estimators import AVERAGED_IN, Reason, is_rejected
    from app.live.views import state
    from app.server.gui.main import _readouts_html

    core = LiveCore()
    s = core.open_session("phone", "test")
    core.start(s)
    lines = real_log_9dof.read_bytes().splitlines()
    for i in range(0, len(lines), 200):
        core.process(s, feed_lines(core, s, lines[i:i + 200]))
    core.process(s, core.close_session(s))
    st = state(core)
    html = _readouts_html(st)
    acc = st["counts"]["updates"][st["primary"]]["acc"]
    m = re.search(r"acc updates</td><td>(\d+) used, (?:(\d+) accelerating \(averaged in\), )?(\d+) rejected", html)
    assert m, html
    used, accel, rej = int(m[1]), int(m[2] or 0), int(m[3])
    assert used == acc.get("used", 0) and accel == acc.get(Reason.ACCEL.label, 0)
    assert AVERAGED_IN == {Reason.ACCEL}
    assert rej == sum(v for k, v in acc.items() if k != "accel" and is_rejected(Reason[k.upper()]))
    if "running" in real_log_9dof.name:
        assert accel > rej and accel > 0.5 * (used + accel + rej)   # a running phone accelerates
