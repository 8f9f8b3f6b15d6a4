"""Replay control (app/sources/pacing.py ReplayControl): pause, speed, seek, loop."""

from __future__ import annotations

import pytest

from app.sources.pacing import ReplayControl, ReplayError


def _ctl():
    lines = [f"{1000 + 10 * k}\tACC\t0\t0\t9.81".encode() for k in range(1001)]   # 10 s
    return ReplayControl(lines, "x.txt")


def test_speed_pause_and_seek_move_the_playhead():
    c = _ctl()
    assert c.duration_s == pytest.approx(10.0)
    assert c.due(100.0) == (0, 0)                   # the first call anchors the clock
    i, j = c.due(101.0)                             # 1 s of wall at 1x
    assert (i, j) == (0, 101) and c.position_s == pytest.approx(1.0)
    c.set(speed=10.0)
    c.due(200.0)
    i, j = c.due(200.5)                             # 0.5 s wall at 10x = 5 s of log
    assert c.position_s == pytest.approx(6.0) and j == 601
    c.set(paused=True)
    assert c.due(300.0) == (601, 601) and c.due(400.0) == (601, 601)
    c.set(paused=False, speed=0.1, seek_s=2.0)
    assert c.restart and c.index == 200 and c.position_s == 2.0
    c.due(500.0)
    c.due(510.0)                                    # 10 s wall at 0.1x = 1 s
    assert c.position_s == pytest.approx(3.0)
    c.set(seek_s=10.0)
    c.due(600.0)
    c.due(601.0)
    assert c.at_end and c.status()["at_end"]


def test_bad_requests_name_the_field():
    c = _ctl()
    for kw, field in [({"speed": 20}, "speed"), ({"speed": 0.01}, "speed"), ({"speed": "fast"}, "speed"),
                      ({"seek_s": -1}, "seek_s"), ({"seek_s": 11.0}, "seek_s"),
                      ({"paused": "yes"}, "paused"), ({"loop": 1}, "loop")]:
        with pytest.raises(ReplayError) as e:
            c.set(**kw)
        assert e.value.field == field
    assert c.speed == 1.0 and c.index == 0 and not c.paused
