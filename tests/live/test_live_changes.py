"""app.live.changes: a PATCH body or a preset -> a validated change; one meaning per name."""

from __future__ import annotations

import dataclasses

import pytest

from app.estimators import NAMES, estimator_class
from app.live.ensemble import Ensemble
from app.live.changes import (Change, PatchError, Variant, apply_change, change_from_config,
                              shared_names, validate_patch)
from app.params import SHARED_MEANINGS


def test_every_name_two_estimators_share_has_one_declared_meaning_and_unit():
    """A parameter name in more than one estimator is one quantity: declared in
    SHARED_MEANINGS, with the same unit and user unit everywhere."""
    where: dict[str, list] = {}
    for n in NAMES:
        for f in dataclasses.fields(estimator_class(n).Params):
            where.setdefault(f.name, []).append((n, f.metadata))
    shared = {k: v for k, v in where.items() if len(v) > 1}
    assert set(shared) <= set(SHARED_MEANINGS), set(shared) - set(SHARED_MEANINGS)
    for k, defs in shared.items():
        units = {(m.get("unit"), m.get("user_unit"), m.get("user_scale")) for _, m in defs}
        assert len(units) == 1, (k, defs)
    # the naming rule: *_noise is a density (per √s), *_std a per-sample σ
    for k, defs in where.items():
        for n, m in defs:
            if k.endswith("_noise"):
                assert "√s" in m["unit"], (n, k, m["unit"])
            if k.endswith("_std"):
                assert "√s" not in m["unit"], (n, k)


def test_top_level_takes_shared_names_only():
    ensemble = Ensemble()
    assert "use_mag" in shared_names(ensemble) and "gyr_noise" not in shared_names(ensemble)
    ch = validate_patch(ensemble, {"use_mag": False})
    assert set(ch.params) == set(ensemble.names) and all(c == {"use_mag": False} for c in ch.params.values())
    with pytest.raises(PatchError) as e:
        validate_patch(ensemble, {"gyr_noise": 0.01})
    assert e.value.loc == ("gyr_noise",)
    assert "gyr_noise was renamed gyr_std in lab" in e.value.reason
    assert "robust" in e.value.reason and "estimators" in e.value.reason
    with pytest.raises(PatchError) as e:
        validate_patch(ensemble, {"tau": 2.0})
    assert "complementary" in e.value.reason
    with pytest.raises(PatchError) as e:
        validate_patch(ensemble, {"bogus": 1})
    assert "unknown parameter" in e.value.reason


def test_a_refusal_names_the_key_where_the_client_sent_it():
    """A shared key sent at the top is refused there, not under an estimator the client
    never named; one wrong element of a vector is named with its index."""
    ensemble = Ensemble()
    for body, loc in (({"gyr_bias": [0.1, 0.2, "x"]}, ("gyr_bias[2]",)),
                      ({"gyr_bias": [0.1, 0.2]}, ("gyr_bias",)),
                      ({"max_gap": -1.0}, ("max_gap",)),
                      ({"estimators": {"lab": {"gyr_bias": [0.1, "x", 0.0]}}},
                       ("estimators", "lab", "gyr_bias[1]")),
                      ({"estimators": {"lab": {"acc_std": -1.0}}}, ("estimators", "lab", "acc_std"))):
        with pytest.raises(PatchError) as e:
            validate_patch(ensemble, body)
        assert e.value.loc == loc, (body, e.value.loc)


def test_a_renamed_key_is_refused_with_its_new_name():
    ensemble = Ensemble()
    with pytest.raises(PatchError) as e:
        validate_patch(ensemble, {"estimators": {"lab": {"gyr_noise": 0.02}}})
    assert e.value.loc == ("estimators", "lab", "gyr_noise")
    assert e.value.reason == "gyr_noise was renamed gyr_std in lab (per-sample σ, rad/s)"
    ch = validate_patch(ensemble, {"estimators": {"lab": {"gyr_std": 0.02}, "robust": {"gyr_noise": 0.01}}})
    apply_change(ensemble, ch)
    assert ensemble.params_of("lab").gyr_std == 0.02 and ensemble.params_of("robust").gyr_noise == 0.01


def test_nothing_applies_unless_everything_passes():
    ensemble = Ensemble()
    before = {n: ensemble.params_of(n) for n in ensemble.names}
    for body in ({"use_mag": False, "estimators": {"lab": {"acc_std": -1.0}}},
                 {"primary": "nope"}, {"primary": {"a": 1}}, {"primary": ["robust"]},
                 {"estimators": {"nope": {}}}, {"use_mag": "yes"}, {"reset": 1}, [1, 2]):
        with pytest.raises(PatchError):
            apply_change(ensemble, validate_patch(ensemble, body))
    assert {n: ensemble.params_of(n) for n in ensemble.names} == before


def test_estimator_keys_win_and_primary_and_reset():
    ensemble = Ensemble()
    ch = validate_patch(ensemble, {"use_acc": False, "estimators": {"lab": {"use_acc": True}},
                                "primary": "lab", "reset": True})
    apply_change(ensemble, ch)
    assert ensemble.primary == "lab" and ensemble.params_of("lab").use_acc is True
    assert ensemble.params_of("robust").use_acc is False


def test_variants_through_a_change_and_presets_leave_them_alone():
    ensemble = Ensemble()
    apply_change(ensemble, Change(add=[Variant("robust-no-rejection", "robust", {"mag_dip_gate": 0.0})]))
    assert ensemble.base_of("robust-no-rejection") == "robust"
    ch = validate_patch(ensemble, {"estimators": {"robust-no-rejection": {"mag_norm_gate_rel": 0.0}}})
    apply_change(ensemble, ch)
    apply_change(ensemble, change_from_config(ensemble, {"primary": "lab", "lab": {"acc_std": 0.3}}))
    assert ensemble.params_of("lab").acc_std == 0.3 and ensemble.primary == "lab"
    assert ensemble.params_of("robust-no-rejection").mag_norm_gate_rel == 0.0
    with pytest.raises(PatchError):
        apply_change(ensemble, Change(remove=["robust"]))
    apply_change(ensemble, Change(remove=["robust-no-rejection"]))
    assert "robust-no-rejection" not in ensemble.names
