"""app.live.ensemble: every instance steps a chunk in one batch run; the same estimates as
stepping sample by sample; variants; a step that raises or a state that goes non-finite
is contained."""

from __future__ import annotations

import numpy as np
import pytest

from app.estimators import NAMES, make_estimator
from app.estimators.base import Estimator
from app.estimators.phone import PhoneOrientation
from app.estimators.robust import RobustEKF
from app.estimators.robust.state import S
from app.params import GRAVITY
from app.live.ensemble import Ensemble, EnsembleError
from app.sources.simulate import simulate
from app.sources.ordering import SampleOrderer

SENSOR_OF_TAG = {"GYR": "gyr", "ACC": "acc", "MAG": "mag"}


def chunks(lines, size=37):
    o = SampleOrderer(window=0.05)
    out = [sum((o.push_line(ln) for ln in lines[i:i + size]), []) for i in range(0, len(lines), size)]
    out.append(o.flush())
    return [c for c in out if c]


@pytest.fixture(scope="module")
def sim_chunks():
    return chunks(simulate(("turn_z", "magnet"), seed=2).lines()[:3000])


def stepped(name, chs):
    """The reference: one Estimator.step per sample, as the engine did before."""
    est = make_estimator(name)
    qs = []
    for ch in chs:
        for s in ch:
            sensor = SENSOR_OF_TAG.get(s.tag)
            if sensor is None and s.tag != "ORI":
                continue
            kw = {sensor: np.array(s.values)} if sensor else {"ori": np.array(s.values)}
            est.step(s.time_ms / 1000.0, **kw)
            qs.append(est.q)
    return np.array(qs)


def test_batch_per_chunk_equals_stepping_per_sample(sim_chunks):
    ensemble = Ensemble()
    out = {n: [] for n in ensemble.names}
    for ch in sim_chunks:
        rec = ensemble.step(ch)
        for n in ensemble.names:
            out[n].append(rec.q[n])
    for n in ensemble.names:
        np.testing.assert_allclose(np.concatenate(out[n]), stepped(n, sim_chunks), rtol=0, atol=1e-9)


def test_counts_and_last_decisions(sim_chunks):
    ensemble = Ensemble()
    recs = [ensemble.step(ch) for ch in sim_chunks]
    n_acc = sum(int((r.kind == 1).sum()) for r in recs)
    lab = ensemble.instances["lab"]
    assert lab.counts[1].sum() == n_acc
    assert lab.updates()["acc"]["used"] > 0
    f = lab.flags("acc")
    assert f is not None and f.t == recs[-1].t[recs[-1].kind == 1][-1]
    assert ensemble.phone_q is not None
    assert np.isnan(recs[0].phone_q[0]).all() or ensemble.instances["phone"].estimator.initialized


def test_variants_run_beside_the_builtins(sim_chunks):
    ensemble = Ensemble()
    v = ensemble.add("lab-approx", "lab", {"time_update": "approx"})
    assert not v.builtin and ensemble.params_of("lab-approx").time_update == "approx"
    assert ensemble.params_of("lab").time_update == "exact"
    for ch in sim_chunks:
        rec = ensemble.step(ch)
    assert set(rec.q) == {*NAMES, "lab-approx"}
    assert ensemble.estimator("lab-approx").initialized
    with pytest.raises(EnsembleError):
        ensemble.add("lab-approx", "lab")
    with pytest.raises(EnsembleError):
        ensemble.add("Bad Name", "lab")
    with pytest.raises(EnsembleError):
        ensemble.add("x", "nope")
    with pytest.raises(EnsembleError):
        ensemble.remove("lab")
    ensemble.set_primary("lab-approx")
    ensemble.remove("lab-approx")
    assert "lab-approx" not in ensemble.names and ensemble.primary == "lab"


class Raising(PhoneOrientation):
    """The phone estimator, raising on an ORI sample whose x is 0.5 (a planted bug)."""

    _run_rows = Estimator._run_rows   # the generic loop over _step (the compiled run does not call it)

    def _step(self, t, gyr, acc, mag, ori, flags):
        if ori is not None and ori[1] == 0.5:
            raise RuntimeError("planted")
        super()._step(t, gyr, acc, mag, ori, flags)


def ori_chunk(t0, xs):
    from app.sources.samples import Sample
    return [Sample(t0 + 10 * i, "ORI", (float(np.sqrt(1 - x * x)), x, 0.0, 0.0)) for i, x in enumerate(xs)]


def test_a_step_that_raises_skips_that_sample_only():
    ensemble = Ensemble()
    inst = ensemble.add("raiser", "phone", estimator=Raising())
    rec = ensemble.step(ori_chunk(1000, [0.1, 0.5, 0.2]))
    assert inst.step_errors == 1 and "planted" in inst.last_error
    q = rec.q["raiser"]
    np.testing.assert_allclose(q[1], q[0])            # the bad sample left the state as it was
    np.testing.assert_allclose(q[2], rec.q["phone"][2])
    rec = ensemble.step(ori_chunk(2000, [0.3]))          # and the next chunk runs in batch again
    np.testing.assert_allclose(rec.q["raiser"], rec.q["phone"])
    assert ensemble.step_errors() == 1


class NaNMaker(PhoneOrientation):
    _run_rows = Estimator._run_rows

    def _step(self, t, gyr, acc, mag, ori, flags):
        super()._step(t, gyr, acc, mag, ori, flags)
        if ori is not None and ori[1] == 0.5:
            self._q = np.full(4, np.nan)


def test_a_non_finite_state_is_restored():
    ensemble = Ensemble()
    inst = ensemble.add("nan", "phone", estimator=NaNMaker())
    ensemble.step(ori_chunk(1000, [0.1]))
    rec = ensemble.step(ori_chunk(2000, [0.2, 0.5, 0.3]))
    assert inst.restored == 1
    assert np.isfinite(rec.q["nan"]).all() and np.isfinite(inst.estimator.q).all()


class NaNRobust(RobustEKF):
    """robust, its estimate made NaN by a gyroscope sample whose x is 0.5 (a planted bug)."""

    _run_rows = Estimator._run_rows

    def _step(self, t, gyr, acc, mag, ori, flags):
        super()._step(t, gyr, acc, mag, ori, flags)
        if gyr[0] == 0.5:
            self._s[S.q_w] = np.nan


def test_a_restore_after_a_parameter_change_keeps_the_new_parameters():
    """The last good state was saved before a parameter change; the restore brings back
    that state, and the estimator goes on with the parameters in force (a deep copy of
    the whole object had brought back the old coefficients: a switched-off magnetometer
    used again)."""
    from app.estimators.base import F_MAG, Reason
    from app.sources.samples import Sample

    def chunk(t0, gx):
        return [Sample(t0, "GYR", (gx, 0.0, 0.0)), Sample(t0 + 2, "ACC", (0.0, 0.0, GRAVITY)),
                Sample(t0 + 4, "MAG", (0.0, 20.0, -40.0))]

    ensemble = Ensemble()
    inst = ensemble.add("nan", "robust", estimator=NaNRobust())
    ensemble.step(chunk(1000, 0.0) + chunk(1010, 0.0))    # the good state is saved as it begins
    ensemble.set_params("nan", {"use_mag": False})
    rec = ensemble.step(chunk(1020, 0.5))                  # ... and restored here
    assert inst.restored == 1 and np.isfinite(rec.q["nan"]).all()
    rec = ensemble.step(chunk(1030, 0.0))
    assert rec.flags["nan"][2, F_MAG] == Reason.DISABLED
    assert not inst.estimator.params.use_mag


def test_the_phones_own_estimate_is_nan_until_its_first_valid_ori_then_shown_every_row():
    from app.sources.samples import Sample
    ensemble = Ensemble()
    gyr = lambda t: Sample(t, "GYR", (0.01, 0.0, 0.0))      # noqa: E731
    x = 0.3
    ori = Sample(1020, "ORI", (float(np.sqrt(1 - x * x)), x, 0.0, 0.0))
    r1 = ensemble.step([gyr(1000), gyr(1010)])                # no ORI yet
    assert np.isnan(r1.phone_q).all()
    r2 = ensemble.step([ori, gyr(1030), Sample(1040, "ORI", (0.0, 0.0, 0.0, 0.0))])
    expected = np.array([np.sqrt(1 - x * x), x, 0.0, 0.0])
    np.testing.assert_allclose(r2.phone_q, np.tile(expected, (3, 1)))   # a zero ORI is refused
    r3 = ensemble.step([gyr(1050)])                           # initialised before the chunk
    np.testing.assert_allclose(r3.phone_q, [expected])
