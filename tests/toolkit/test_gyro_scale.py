"""The gyroscope's scale factor (``orientlab gyro-scale``, :mod:`app.toolkit.gyro_scale`) and the
``gyr_scale`` parameter that applies it.

A phone's gyroscope is off by 0.2-3 %: with the field refused, the heading drifts by that share of
every turn. A simulated phone with a known scale error per axis is turned whole turns about each
of its axes between rests; the fit must find the scale from the tilt at the rests, say which axes
it could not see, refuse a recording it cannot use, and the estimators must turn right with it."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app import quaternion as qm
from app.config import load_config
from app.estimators import make_estimator
from app.toolkit.errors import ToolError
from app.toolkit.gyro_scale import MEASURED_STD, Recording, find_rests, fit, to_preset
from harness import ALL_AXES, BIAS, FLAT, TURN, turns_log_lines, turns_session as session
from harness import SCALE as _SCALE

REPO = Path(__file__).resolve().parents[2]
SCALE = np.asarray(_SCALE)


def rec(moves, name="phone", **kw) -> Recording:
    t, gyr, acc, _, _ = session(moves, **kw)
    return Recording(name, t, gyr, acc)


def test_the_fit_finds_each_axis_scale_from_the_rests():
    r = rec(ALL_AXES)
    assert len(find_rests(r)) == len(ALL_AXES) + 1
    f = fit([r])
    assert f.measured.all(), f.std
    assert np.all(f.std < MEASURED_STD)
    assert np.allclose(f.scale, SCALE, atol=2e-4), f.scale
    assert np.all(np.abs(f.scale - SCALE) < 4.0 * f.std + 5e-5), (f.scale, f.std)
    assert f.rms_after_deg < 0.1 * f.rms_before_deg
    # no scale error: none found
    f0 = fit([rec(ALL_AXES, scale=np.zeros(3), seed=2)])
    assert np.all(np.abs(f0.scale) < 5e-4), f0.scale


def test_an_axis_never_level_while_turning_is_not_measured():
    """Turned about z only while flat, the tilt never sees z's scale: reported, left at 0."""
    f = fit([rec(FLAT)])
    assert f.measured.tolist() == [True, True, False], f.std
    assert np.allclose(f.scale[:2], SCALE[:2], atol=5e-4)
    assert f.preset_scale()[2] == 0.0
    assert any("axis z" in w and "level" in w for w in f.warnings)


def test_recordings_without_enough_rests_are_refused_with_a_reason():
    one_span = rec([(0, 2 * TURN, 4.0)], name="short")
    with pytest.raises(ToolError, match="three rests"):
        fit([one_span])
    # a short recording beside a good one: counted, not used, said so
    f = fit([rec(ALL_AXES), one_span])
    assert f.rests == {"phone": len(ALL_AXES) + 1, "short": 2}
    assert any(w.startswith("short: 2 rests, not used") for w in f.warnings)
    # two recordings of the same phone: one scale, a bias error each
    f2 = fit([rec(ALL_AXES[:4], name="a"), rec(ALL_AXES[4:], name="b", seed=3)])
    assert np.allclose(f2.scale, SCALE, atol=1e-3), f2.scale
    # the same recording twice (listed twice, or a copy) is not new evidence: it had
    # shrunk each σ by √2 and made a weak axis "measured"
    a = rec(FLAT, name="a")
    with pytest.raises(ToolError, match="a and a copy hold the same samples"):
        fit([a, Recording("a copy", a.t.copy(), a.gyr.copy(), a.acc.copy())])


@pytest.mark.parametrize("name", ["robust", "lab"])
def test_the_estimators_turn_right_with_gyr_scale(name):
    """Five whole turns on the table with the magnetometer off: a 2 % scale error about z turns
    the heading 36° too far; with gyr_scale set, it does not."""
    moves = [(2, 5 * TURN, 10.0)]
    t, gyr, acc, mag, q = session(moves, scale=np.array([0.0, 0.0, 0.02]))
    gyr = gyr - BIAS                 # the bias is another calibration's

    def heading_after(params):
        est = make_estimator(name, {"use_mag": False, **params})
        res = est.run(t, gyr, acc, mag)
        _, h, _ = qm.error_angles(res.q[-50:], q[-50:])
        return float(np.degrees(np.mean(np.abs(h))))

    off = heading_after({})
    on = heading_after({"gyr_scale": [0.0, 0.0, 0.02]})
    assert off > 30.0, off
    assert on < 1.0, on


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)


def test_the_command_writes_a_preset_the_estimators_load(tmp_path):
    t, gyr, acc, mag, _ = session(ALL_AXES)
    path = tmp_path / "turns.npz"
    np.savez(path, t=t, gyr=gyr, acc=acc, mag=mag)
    out = tmp_path / "scale.toml"
    p = _cli("gyro-scale", path, "--out", out)
    assert p.returncode == 0, p.stderr
    printed = dict(re.findall(r"([xyz]): s = ([+-][0-9.]+) %", p.stdout))
    assert np.allclose([float(printed[a]) for a in "xyz"], SCALE * 100.0, atol=0.05), p.stdout
    cfg = load_config(out)
    for est in ("robust", "lab"):
        assert np.allclose(cfg[est]["gyr_scale"], SCALE, atol=5e-4), cfg[est]
    assert to_preset(fit([Recording("turns.npz", t, gyr, acc)])) == out.read_text(encoding="utf-8")
    p = _cli("estimate", path, "--config", out, "--out", tmp_path / "est.csv", "--quiet")
    assert p.returncode == 0, p.stderr

    # the same session as the app's log (what the page's recorder writes): one sensor per line
    log = tmp_path / "turns.txt"
    log.write_text("\n".join(turns_log_lines(t, gyr, acc, mag)) + "\n", encoding="utf-8")
    p = _cli("gyro-scale", log, "--out", tmp_path / "log.toml")
    assert p.returncode == 0, p.stderr
    assert np.allclose(load_config(tmp_path / "log.toml")["robust"]["gyr_scale"], SCALE, atol=5e-4)

    still = tmp_path / "still.npz"
    np.savez(still, t=t[:300], gyr=gyr[:300], acc=acc[:300], mag=mag[:300])
    p = _cli("gyro-scale", still, "--out", tmp_path / "none.toml")
    assert p.returncode == 2 and "three rests" in p.stderr, (p.returncode, p.stderr)
    assert not (tmp_path / "none.toml").exists()
