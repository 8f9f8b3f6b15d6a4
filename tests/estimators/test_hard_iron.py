"""A magnet stuck on the phone (a sensor-fixed offset, hard iron) is tracked and removed, not
refused: the simulator's phone turns about every axis; mid-stream a 30 µT magnet is stuck on it
(a constant vector in the *sensor* frame, as ``app.toolkit.inject`` adds with ``frame="sensor"``),
later it is taken off. With the offset tracked the heading stays close; without it (the fit off,
``hard_iron_window=0``, the filter before issue 19) the field is refused for the whole time and the
gyroscope's bias drifts the heading. A still phone finds no offset."""

from __future__ import annotations

import numpy as np
import pytest

from app.estimators import Reason, make_estimator
from app.estimators.base import F_MAG, F_MAG_VAL
from app.quaternion import error_angles
from harness import MAGNET_OFF_S as OFF
from harness import MAGNET_OFFSET_UT, MAGNET_TURNS as TURNS, magnet_rows
from harness import MAGNET_ON_S as ON

DEG = 180.0 / np.pi
OFFSET = np.array(MAGNET_OFFSET_UT)                   # µT, sensor frame (|o| = 29.5 µT)


def _rows(magnet=True, scenes=TURNS, seed=3):
    return magnet_rows(None if magnet else 0.0, scenes=scenes, seed=seed)


def _heading(res, truth, mask):
    _, h, _ = error_angles(res.q[mask], truth[mask])
    return h * DEG


def test_magnet_on_the_phone_is_tracked_applied_and_dropped():
    rows, truth = _rows()
    est = make_estimator("robust")
    res = est.run(rows.t, rows.gyr, rows.acc, rows.mag, rows.ori)
    without = make_estimator("robust", {"hard_iron_window": 0.0}).run(rows.t, rows.gyr, rows.acc,
                                                                        rows.mag, rows.ori)
    mag = res.flags[:, F_MAG]
    late = (rows.t > ON + 30.0) & (rows.t < OFF)        # the offset found by then
    # the field is used with the offset removed, and flagged so
    has_mag = np.isfinite(rows.mag[:, 0])
    assert np.mean(mag[late & has_mag] == Reason.OFFSET) > 0.8
    # ... and the heading follows the corrected field: far better than refusing it
    h, h0 = _heading(res, truth, late), _heading(without, truth, late)
    rms, rms0 = np.sqrt(np.mean(h ** 2)), np.sqrt(np.mean(h0 ** 2))
    assert rms < 2.0, f"heading with the offset tracked: {rms:.2f}°"
    assert rms < 0.5 * rms0, f"tracked {rms:.2f}° against refused {rms0:.2f}°"
    # the offset found is the magnet's, to a µT
    off, status = est.mag_offset
    # (the estimator's state is at the end of the run: taken off by then, see below)
    assert status in ("none", "tracking")
    assert np.allclose(off, 0.0)
    # after the magnet is taken off the offset is dropped: no OFFSET flags 10 s later
    after = rows.t > OFF + 10.0
    assert not np.any(mag[after] == Reason.OFFSET)
    assert np.sqrt(np.mean(_heading(res, truth, after) ** 2)) < 2.0


@pytest.mark.parametrize("size", [6.0, 8.0, 9.0, 10.0])
def test_a_magnet_too_weak_for_the_strength_gate_is_removed_too(size):
    """A magnet of 6-10 µT (a case's, a mount's) swings the strength of the 50 µT field by
    ±12-20 % as the phone turns: inside the strength gate (15 %) most of the time, so the
    field is used with the offset in and its heading is 10-16° off (RMS). The offset is removed
    all the same, because it explains the strength's swing (``hard_iron_ratio``): the heading
    stays within a degree. Before, an offset was removed only when the raw field's deviation
    exceeded the strength gate (10 µT: 16°, as without the tracking); until the reference
    stopped learning from a field off it by more than hard_iron_tol, the 6 µT magnet's field
    taught the reference before the fit had seen enough turning, and the corrected field was
    then no closer to it than the raw one (9.6°); and until a field the offset explains stopped
    counting as a new place, the 8 and 9 µT magnets' field became the reference by the
    new-field acceptance, and the offset was dropped (11.9° and 15.0°)."""
    rows, truth = magnet_rows(size)
    res = make_estimator("robust").run(rows.t, rows.gyr, rows.acc, rows.mag, rows.ori)
    kept = make_estimator("robust", {"hard_iron_window": 0.0}).run(rows.t, rows.gyr, rows.acc,
                                                                     rows.mag, rows.ori)
    late = (rows.t > ON + 30.0) & (rows.t < OFF)
    has_mag = np.isfinite(rows.mag[:, 0])
    assert np.mean(res.flags[late & has_mag, F_MAG] == Reason.OFFSET) > 0.8
    h, h0 = _heading(res, truth, late), _heading(kept, truth, late)
    rms, rms0 = np.sqrt(np.mean(h ** 2)), np.sqrt(np.mean(h0 ** 2))
    assert rms < 2.0, f"heading with the weak offset removed: {rms:.2f}°"
    assert rms < 0.7 * rms0, f"removed {rms:.2f}° against kept {rms0:.2f}°"


def test_chance_windows_of_a_magnet_on_the_phone_do_not_pull_the_heading():
    """Issue 19 item 3, without the offset tracking (the filter before it, or a magnet too
    strong or too brief to fit): a 30 µT magnet on the turning phone leaves the field within
    the strength and dip gates for a few seconds at some attitudes, its heading 45-95° off.
    Such a return after a refusal must not be taken at face value: the field's heading is
    tested against the gyroscope's (flag NIS) and the heading stays as good as the gyroscope
    alone keeps it (the same stream without field samples while the magnet is on). Taken at
    once, the windows pulled it 35-39° off (RMS over the magnet's 70 s)."""
    rows, truth = _rows()
    on = (rows.t > ON) & (rows.t < OFF)
    res = make_estimator("robust", {"hard_iron_window": 0.0}).run(rows.t, rows.gyr, rows.acc,
                                                                   rows.mag, rows.ori)
    no_field = rows.mag.copy()
    no_field[(rows.t >= ON) & (rows.t < OFF)] = np.nan
    alone = make_estimator("robust", {"hard_iron_window": 0.0}).run(rows.t, rows.gyr, rows.acc,
                                                                     no_field, rows.ori)
    mag = res.flags[:, F_MAG].astype(int)
    refused = on & (mag == Reason.NIS)
    assert refused.sum() > 50                              # the chance windows: tested, refused
    assert res.flags[refused, F_MAG_VAL].min() > 9.0       # each beyond 3σ
    h, h0 = _heading(res, truth, on), _heading(alone, truth, on)
    rms, rms0 = np.sqrt(np.mean(h ** 2)), np.sqrt(np.mean(h0 ** 2))
    assert rms < rms0 + 1.0, f"heading {rms:.2f}° against the gyroscope alone {rms0:.2f}°"
    assert np.abs(h).max() < np.abs(h0).max() + 1.5


def test_offset_found_is_the_magnets_and_shown_in_diagnostics():
    rows, truth = _rows()
    est = make_estimator("robust")
    stop = rows.t < OFF - 5.0
    est.run(rows.t[stop], rows.gyr[stop], rows.acc[stop], rows.mag[stop], rows.ori[stop])
    d = est.diagnostics()
    assert d.mag_offset_status == "applied"
    assert np.linalg.norm(np.asarray(d.mag_offset) - OFFSET) < 1.5
    off, status = est.mag_offset
    assert status == "applied" and np.linalg.norm(off - OFFSET) < 1.5


def test_no_offset_without_a_magnet():
    for scenes in (TURNS, ("still",) * 30):
        rows, truth = _rows(magnet=False, scenes=scenes)
        est = make_estimator("robust")
        res = est.run(rows.t, rows.gyr, rows.acc, rows.mag, rows.ori)
        assert not np.any(res.flags[:, F_MAG] == Reason.OFFSET)
        assert est.diagnostics().mag_offset_status != "applied"


def test_hard_iron_slots_are_one_block_reset_to_their_initial_values():
    """hard_iron_reset restores the block hi_A..hi_solve_t from the initial state: every
    hard iron slot lies in it, and after a reset they equal a new state's."""
    from app.estimators.robust.hardiron import hard_iron_reset
    from app.estimators.robust.state import INITIAL, S, STATE, new_state

    names = [n for n, _, _ in STATE]
    block = names[names.index("hi_A"):names.index("hi_solve_t") + 1]
    assert block == [n for n in names if n.startswith("hi_")]
    s = new_state()
    s[S.hi_A:S.hi_solve_t + 1] = 7.0
    hard_iron_reset(s)
    np.testing.assert_array_equal(s, INITIAL)
    assert np.isinf(s[S.hi_std]) and np.isinf(s[S.hi_rms])
