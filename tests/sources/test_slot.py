"""The phone slot's own rules, on its injectable clock (the receivers' tests play real
phones against it: tests/sources/test_receiver.py, tests/server/test_phone_apps.py)."""

from __future__ import annotations

from app.sources.slot import TURNED_AWAY_KEPT, TURNED_AWAY_S, PhoneSlot


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_the_phones_turned_away_are_listed_each_once_the_latest_first_and_forgotten():
    clock = Clock()
    slot = PhoneSlot(idle_s=3.0, clock=clock)
    assert slot.take("sensorfusion", "10.0.0.2:5000", "the phone on show", who="10.0.0.2") is None
    for k in range(3):
        clock.t += 0.5
        slot.touch("10.0.0.2:5000")
        assert slot.take("sensorlogger", "10.0.0.7", "a student") is not None
    clock.t += 0.5
    slot.touch("10.0.0.2:5000")
    assert slot.take("phyphox", "10.0.0.9", "another") is not None
    away = slot.status()["turned_away"]
    assert [(t["app"], t["who"], t["times"]) for t in away] == \
        [("phyphox", "10.0.0.9", 1), ("sensorlogger", "10.0.0.7", 3)]
    assert away[1]["ago_s"] == 0.5 and "another phone (Sensor Fusion app)" in away[1]["why"]
    assert slot.status()["refused"] == 4
    # bounded: only the latest TURNED_AWAY_KEPT phones
    for k in range(TURNED_AWAY_KEPT + 3):
        slot.count_refusal("busy", "sensorlogger", f"10.0.1.{k}")
    whos = [t["who"] for t in slot.turned_away()]
    assert len(whos) == TURNED_AWAY_KEPT and whos[0] == f"10.0.1.{TURNED_AWAY_KEPT + 2}"
    # forgotten a minute later
    clock.t += TURNED_AWAY_S + 0.1
    assert slot.turned_away() == []
    # a refusal a receiver cannot attribute is counted, not listed
    slot.count_refusal("busy")
    assert slot.turned_away() == [] and slot.status()["refused"] == 4 + TURNED_AWAY_KEPT + 3 + 1
