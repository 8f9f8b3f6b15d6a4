"""The simulated phone: its sensors agree with its own truth, as a real phone's would."""

from __future__ import annotations


import numpy as np
import pytest

from app.sources.sensorfusion import format_line, parse_line
from app.quaternion import Q, S_bar, angle_between
from app.sources.simulate import SCENES, SimConfig, Simulation, simulate, stream


@pytest.fixture(scope="module")
def run():
    return simulate(seed=1)


def by_tag(run, tag):
    ms = np.array([s[0] for s in run.samples if s[1] == tag])
    v = np.array([s[2] for s in run.samples if s[1] == tag])
    return ms, v


def test_rates_and_order(run):
    ms = [s[0] for s in run.samples]
    assert ms == sorted(ms)
    for tag, period in (("ACC", 10), ("MAG", 20), ("ORI", 10)):
        t, _ = by_tag(run, tag)
        assert np.all(np.diff(t) == period), tag
    t, _ = by_tag(run, "GYR")
    # the gyroscope drops out during its scene, and only then
    sim = run.sim
    names = np.array(sim.scenes)[sim.scene_at((t - run.boot_ms) / 1000)]
    assert "gyro_dropout" not in names
    assert len(t) == int(round((sim.period - sim.durations[sim.scenes.index("gyro_dropout")]) * 100))


def test_accelerometer_is_specific_force_of_the_truth(run):
    ms, acc = by_tag(run, "ACC")
    q = run.truth_at_ms(ms)
    f_world = np.einsum("nij,nj->ni", np.array([Q(x) for x in q]), acc)
    names = np.array(run.sim.scenes)[run.sim.scene_at((ms - run.boot_ms) / 1000)]
    still = names != "shake"
    assert np.allclose(f_world[still], [0, 0, 9.81], atol=0.3)
    assert np.max(np.abs(f_world[~still, 0])) > 4.0     # the shake is along east


def test_magnetometer_is_the_earth_field_plus_the_magnet(run):
    ms, mag = by_tag(run, "MAG")
    q = run.truth_at_ms(ms)
    m_world = np.einsum("nij,nj->ni", np.array([Q(x) for x in q]), mag)
    names = np.array(run.sim.scenes)[run.sim.scene_at((ms - run.boot_ms) / 1000)]
    calm = names != "magnet"
    norm = np.linalg.norm(m_world[calm], axis=1)
    assert np.mean(norm) == pytest.approx(50.0, abs=0.5)
    dip = np.degrees(np.arctan2(-m_world[calm, 2], m_world[calm, 1]))
    assert np.mean(dip) == pytest.approx(65.0, abs=1.0)
    assert np.max(np.linalg.norm(m_world[~calm], axis=1)) > 80.0


def test_gyroscope_is_the_truths_rate_plus_bias():
    sim = Simulation()
    t = np.linspace(0.1, sim.period - 0.1, 400)
    h = 1e-5
    q0, q1 = sim.truth(t - h), sim.truth(t + h)
    qm = sim.truth(t)
    w_num = np.array([2 * S_bar(qq).T @ ((b - a) / (2 * h)) for qq, a, b in zip(qm, q0, q1)])
    w = sim.motion(t)[1]
    assert np.allclose(w, w_num, atol=1e-4)
    assert np.max(np.abs(w)) > 0.5          # the turns are real turns
    r = simulate(("still",), seed=2)
    _, gyr = by_tag(r, "GYR")
    assert np.allclose(gyr.mean(axis=0), SimConfig().gyr_bias, atol=0.002)


def test_a_sample_stands_for_its_period_and_lags_its_stamp_by_half_of_it():
    """As a real sensor's: the mean over the period before the stamp, so half a period
    behind the truth at the stamp (what mag_delay and acc_delay_periods turn forward)."""
    sim = Simulation()
    turn = sim.starts[sim.scenes.index("turn_x")]
    t = turn + np.linspace(0.5, 5.5, 200)
    for period in (0.01, 0.02):
        w, f, m = sim.sensed(t, period)
        for got, at in ((w, lambda tt: sim.motion(tt)[1]),
                        (f, lambda tt: sim.sensed(tt, 1e-9)[1]),
                        (m, lambda tt: sim.sensed(tt, 1e-9)[2])):
            at_stamp = np.max(np.abs(got - at(t)))
            half_back = np.max(np.abs(got - at(t - period / 2)))
            assert at_stamp > 2e-3 * period / 0.01           # a real lag: slope × half a period
            assert half_back < 0.02 * at_stamp               # half a period: second order only
    # and the stream's samples are those means (noise aside)
    r = simulate(("turn_x",), seed=3, config=SimConfig(gyr_noise=0.0, acc_noise=0.0, mag_noise=0.0,
                                                      gyr_bias=(0.0, 0.0, 0.0)))
    for tag, col, period in (("GYR", 0, 0.01), ("ACC", 1, 0.01), ("MAG", 2, 0.02)):
        ms, v = by_tag(r, tag)
        tt = (ms - r.boot_ms) / 1000.0
        assert np.allclose(v, r.sim.sensed(tt, period)[col], atol=1e-9), tag


def test_phone_estimate_is_near_the_truth(run):
    ms, ori = by_tag(run, "ORI")
    q = run.truth_at_ms(ms)
    err = np.degrees([angle_between(a, b) for a, b in zip(ori, q)])
    assert 0.1 < np.mean(err) < 3.0


def test_lines_round_trip_through_the_parser(run):
    for s in run.samples[:500]:
        p = parse_line(format_line(*s))
        assert p.time_ms == s[0] and p.tag == s[1]
        assert np.allclose(p.values, s[2], rtol=1e-6, atol=1e-9)


def test_seed_and_loop():
    a, b = simulate(("still",), seed=4), simulate(("still",), seed=4)
    assert a.samples == b.samples
    assert simulate(("still",), seed=5).samples != a.samples
    sim = Simulation()
    # scenes return to the base orientation: the loop is seamless
    assert angle_between(sim.truth([0.0])[0], sim.truth([sim.period - 1e-6])[0]) < 1e-4
    gen = stream(seed=0)
    first = [next(gen) for _ in range(int(sim.period * 1000 / 10 * 4))]
    ms = [s[0] for s in first]
    assert ms == sorted(ms) and ms[-1] - ms[0] > sim.period * 1000


def test_unknown_scene_is_refused():
    with pytest.raises(ValueError, match="unknown scene"):
        simulate(("still", "jump"))
    assert set(SCENES) == {"still", "turn_x", "turn_y", "turn_z", "shake", "magnet", "gyro_dropout"}
