"""app.estimators.lab: the compiled batch run (live dashboard, CLI) takes the very steps of
the readable ``_step``: same estimates, same flags, chunk by chunk, whatever the settings."""

from __future__ import annotations

import numpy as np
import pytest

from app.estimators import make_estimator
from app.estimators.base import Estimator
from app.sources.simulate import simulate
from app.sources.ordering import SampleOrderer, samples_to_rows


@pytest.fixture(scope="module")
def rows():
    sim = simulate(("still", "turn_z", "magnet", "shake", "gyro_dropout"), seed=4)
    o = SampleOrderer(0.05)
    return samples_to_rows(o.push_lines(sim.lines()) + o.flush())


@pytest.mark.parametrize("params", [{}, {"time_update": "approx"}, {"use_mag": False},
                                    {"use_acc": False}, {"use_gyr": False},
                                    {"mag_band_uT": [35.0, 55.0]}, {"nis_gate": 5.0},
                                    {"m0": [0.0, 20.0, -40.0]}, {"max_gap": 0.01}],
                         ids=lambda p: ",".join(p) or "defaults")
def test_compiled_run_equals_the_reference_step(rows, params):
    ref = Estimator.run_steps(make_estimator("lab", params), rows.t, rows.gyr, rows.acc, rows.mag)
    est = make_estimator("lab", params)
    qs, fs = [], []
    for i in range(0, len(rows.t), 37):       # chunk by chunk, as the live path runs it
        r = est.run(rows.t[i:i + 37], rows.gyr[i:i + 37], rows.acc[i:i + 37], rows.mag[i:i + 37])
        qs.append(r.q)
        fs.append(r.flags)
    q, f = np.concatenate(qs), np.concatenate(fs)
    np.testing.assert_allclose(q, ref.q, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.isnan(f), np.isnan(ref.flags))
    np.testing.assert_allclose(np.nan_to_num(f), np.nan_to_num(ref.flags), rtol=0, atol=1e-9)
    # and the state it leaves is the one stepping leaves: the next row agrees too
    ref_est = make_estimator("lab", params)
    Estimator.run_steps(ref_est, rows.t, rows.gyr, rows.acc, rows.mag)
    t1 = rows.t[-1] + 0.01
    a = est.step(t1, gyr=np.array([0.1, 0.0, 0.0]), acc=np.array([0.0, 0.5, 9.8]))
    b = ref_est.step(t1, gyr=np.array([0.1, 0.0, 0.0]), acc=np.array([0.0, 0.5, 9.8]))
    np.testing.assert_allclose(est.q, ref_est.q, atol=1e-9)
    assert a.acc == b.acc and a.gyr == b.gyr


@pytest.mark.parametrize("key, value", [("g0", [0.0, 0.0, 0.0]), ("m0", [0.0, 0.0, 0.0]),
                                        ("m0", [0.0, 1.0, -2.0])])
def test_a_reference_vector_that_is_no_field_is_refused_naming_it(key, value):
    """A zero (or near zero) g0 or m0 is no gravity and no earth field: lab would refuse
    every sample against it without a word. Refused, naming it; null m0 still learns it."""
    from app.params import ParamError
    est = make_estimator("lab")
    with pytest.raises(ParamError, match=key):
        est.set_params(**{key: value})
    est.set_params(m0=[0.0, 20.0, -40.0])
    est.set_params(m0=None)
    assert est.params.m0 is None


def test_a_given_m0_taken_away_mid_stream_is_learned_again_at_once(rows):
    """A teacher loads the preset ``default`` (or sets m0 to 0 0 0) after a calibration
    set m0 elsewhere: the page says m0 is learned, so lab must stop holding the old one and
    learn it by (7) from the field now, not keep it in force until a reset (a review saw
    the old band refuse the field after the load)."""
    wrong = np.array([0.0, 10.0, -60.0])
    est = make_estimator("lab", {"m0": wrong.tolist()})
    half = len(rows.t) // 4
    est.run(rows.t[:half], rows.gyr[:half], rows.acc[:half], rows.mag[:half])
    np.testing.assert_allclose(est.diagnostics().m0, wrong)
    learned = make_estimator("lab")
    learned.run(rows.t[:half], rows.gyr[:half], rows.acc[:half], rows.mag[:half])
    est.set_params(m0=None)
    assert est.diagnostics().m0 is None            # learning, not the old one
    later = np.searchsorted(rows.t, rows.t[half] + est.params.m0_learn_time + 0.5)
    est.run(rows.t[half:later], rows.gyr[half:later], rows.acc[half:later], rows.mag[half:later])
    m0 = np.asarray(est.diagnostics().m0)
    assert np.linalg.norm(m0 - wrong) > 10.0
    np.testing.assert_allclose(np.linalg.norm(m0), np.linalg.norm(learned.diagnostics().m0), rtol=0.05)
