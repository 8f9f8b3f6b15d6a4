"""Presets: configs/default.toml mirrors the parameter definitions, the shipped presets
load and run, and a bad preset is refused with the section and key named."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.config import ConfigError, defaults_toml, estimator_params, load_config, params_table
from app.estimators import NAMES, estimator_class, make_estimator
from app.params import CONFIG_DIR, DEFAULT_CONFIG, load_toml, param, to_dict
from app.toolkit.variants import no_rejection_changes
from harness import sim_rows


def test_default_toml_is_the_parameter_definitions():
    """The file users read is generated from the dataclasses; regenerate it with
    `orientlab params --toml > configs/default.toml` when a default changes."""
    assert DEFAULT_CONFIG.read_text() == defaults_toml()
    raw = load_toml(DEFAULT_CONFIG)
    for name in NAMES:
        defaults = to_dict(estimator_class(name).Params())
        given = {k: v for k, v in defaults.items() if v is not None}
        assert raw[name] == given, name


@pytest.mark.parametrize("preset", sorted(p.stem for p in CONFIG_DIR.glob("*.toml")))
def test_every_shipped_preset_loads_and_runs(preset):
    cfg = load_config(preset)
    rows, _ = sim_rows(("still", "turn_x", "shake"), seed=1)
    for name in NAMES:
        est = make_estimator(name, estimator_params(cfg, name))
        out = est.run(rows.t, rows.gyr, rows.acc, rows.mag, rows.ori)
        assert np.all(np.isfinite(out.q))


def test_galaxy_s7_preset_is_report_a():
    cfg = load_config("galaxy_s7")
    assert cfg["primary"] == "lab"
    lab = make_estimator("lab", cfg["lab"])
    assert lab.diagnostics().mag_band == (35.0, 55.0)
    np.testing.assert_allclose(np.diag(lab._Rw), [2.285e-06, 1.231e-06, 1.729e-06])
    assert lab.params.time_update == "approx"


@pytest.mark.parametrize("text,words", [
    ('[robust]\nno_such_key = 1\n', ["[robust]", "no_such_key"]),
    ('[robust]\ngyr_noise = -1.0\n', ["[robust]", "gyr_noise", "minimum"]),
    ('[kalman]\nx = 1\n', ["[kalman]", "not an estimator"]),
    ('primary = "best"\n', ["primary", "best"]),
    ('[lab]\ntime_update = "euler"\n', ["time_update", "exact"]),
    ('[lab\n', ["not valid TOML"]),
])
def test_a_bad_preset_is_refused_naming_what_is_wrong(tmp_path, text, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(path)
    for w in words:
        assert w in str(e.value)


def test_params_table_lists_every_parameter_with_its_unit():
    table = params_table()
    for name in NAMES:
        for f in dataclasses.fields(estimator_class(name).Params):
            assert f"`{f.name}`" in table
    assert "deg/s" in table  # user units shown beside SI ones


def test_every_default_of_the_default_filter_says_where_it_comes_from():
    """Issue 19: a default from physics, a datasheet or a published value, or, said so, from
    the shared trials. A parameter added without its source, or one dropped while its source
    stays, fails here; the table users read (`orientlab params`) shows the column."""
    from app.estimators.robust.params import RobustParams
    names = [f.name for f in dataclasses.fields(RobustParams)]
    sources = RobustParams.default_from
    assert sorted(sources) == sorted(names)
    kinds = ("VQF:", "physics:", "datasheet:", "design:", "shared trials")
    for name, src in sources.items():
        assert src.startswith(kinds), f"{name}: {src!r} names no kind of source"
    rows = [line for line in params_table().splitlines() if line.startswith("| `mag_new_field_time` |")]
    assert rows and rows[0].rstrip(" |").endswith("VQF: magNewTime 20 s")
    # the other estimators, which claim none, get no empty column
    lab = params_table().split("### `lab`")[1].splitlines()[2]
    assert "default from" not in lab


@pytest.mark.parametrize("ts", [0.01, 1 / 285.7])
def test_the_bias_measurement_noises_are_vqfs_published_sigmas_as_densities(ts):
    """bias_motion_noise and rest_noise say they are VQF's biasSigmaMotion (0.1 °/s) and
    biasSigmaRest (0.03 °/s) as noise densities. VQF turns each σ into a per-sample
    measurement variance W = p²/V + p (p = σ², V the bias's growth per sample from
    biasForgettingTime); W · Ts is the density², the same at any rate. Read from vqf's own
    coefficients, so a default that drifts from the published value fails here."""
    vqf = pytest.importorskip("vqf")
    from app.estimators.robust.params import RobustParams
    c = vqf.PyVQF(ts).coeffs            # VQF keeps its biases in 0.01 °/s
    p = RobustParams()
    deg = 180.0 / np.pi
    motion = np.sqrt(c.biasMotionW * c.accTs) / 100.0
    rest = np.sqrt(c.biasRestW * c.accTs) / 100.0
    assert p.bias_motion_noise * deg == pytest.approx(motion, rel=0.01)
    assert p.rest_noise * deg == pytest.approx(rest, rel=0.03)
    assert RobustParams.default_from["bias_motion_noise"].startswith("VQF: biasSigmaMotion")
    assert RobustParams.default_from["rest_noise"].startswith("VQF: biasSigmaRest")
    # where each settles (docs/accuracy.md, the labels): a random walk of density q measured
    # with density r settles at sqrt(q r) with the time constant r / q; VQF's own q is its V
    q_vqf = np.sqrt(c.biasV / c.accTs) / 100.0 / deg      # (0.01 °/s)² per sample -> rad/s/√s
    assert q_vqf / p.bias_noise == pytest.approx(5.8, abs=0.05)
    for r, sigma, tau, sigma_vqf, tau_vqf in ((p.bias_motion_noise, 0.041, 582.0, 0.1, 100.0),
                                              (p.rest_noise, 0.0126, 53.3, 0.030, 9.2)):
        assert np.sqrt(p.bias_noise * r) * deg == pytest.approx(sigma, rel=0.02)
        assert r / p.bias_noise == pytest.approx(tau, rel=0.02)
        assert np.sqrt(q_vqf * r) * deg == pytest.approx(sigma_vqf, rel=0.02)
        assert r / q_vqf == pytest.approx(tau_vqf, rel=0.02)


def test_an_old_preset_with_a_renamed_key_loads_translated(tmp_path, caplog):
    """lab's gyr_noise is now gyr_std (the same per-sample σ): read as the new name with a
    warning saying so; both names at once is refused."""
    path = tmp_path / "old.toml"
    path.write_text("[lab]\ngyr_noise = 0.02\nrw_noise = 0.4\n")
    with caplog.at_level("WARNING", logger="orientlab.config"):
        cfg = load_config(path)
    assert cfg["lab"]["gyr_std"] == 0.02 and cfg["lab"]["q_rw_noise"] == 0.4
    assert "gyr_noise was renamed gyr_std in lab (per-sample σ, rad/s)" in caplog.text
    path.write_text("[lab]\ngyr_noise = 0.02\ngyr_std = 0.03\n")
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert "both gyr_noise and gyr_std" in str(e.value)


def test_a_preset_saved_before_a_parameter_was_removed_still_loads(tmp_path, caplog):
    """A saved preset holds every parameter of its day: one robust no longer has is left out
    with a warning saying why (the rest of the preset applies); a key no version had is still
    refused."""
    path = tmp_path / "saved_last_term.toml"
    path.write_text("[robust]\nbias_heading_noise = 0.0349\nmag_max_reject = 60.0\nheading_noise = 0.12\n")
    with caplog.at_level("WARNING", logger="orientlab.config"):
        cfg = load_config(path)
    assert cfg["robust"]["heading_noise"] == 0.12
    assert "bias_heading_noise" not in cfg["robust"] and "mag_max_reject" not in cfg["robust"]
    assert "bias_heading_noise was removed from robust (the bias about the vertical is learned " \
           "from the heading's drift now" in caplog.text
    assert "mag_max_reject was removed from robust" in caplog.text
    path.write_text("[robust]\nbias_heading_nosie = 0.03\n")
    with pytest.raises(ConfigError, match="bias_heading_nosie: unknown parameter"):
        load_config(path)


def test_every_rejecting_parameter_is_declared_and_the_no_rejection_variant_turns_it_off():
    """A gate, a band or a de-weighting declares itself (``param(rejects=True)``): the
    no-rejection variant switches off exactly those, each to its off value, and nothing
    else; a rejecting parameter without an off value is refused where it is defined."""
    robust = no_rejection_changes("robust")
    assert {"mag_norm_gate_rel", "mag_dip_gate", "mag_turn_gate", "mag_dev_weight",
            "heading_evidence_tau", "acc_band_rel"} <= set(robust)
    assert no_rejection_changes("lab") == {"acc_band_rel": 0.0, "mag_band_rel": 0.0,
                                           "mag_band_uT": None, "nis_gate": 0.0}
    for name in NAMES:
        changes = no_rejection_changes(name)
        flagged = {f.name for f in dataclasses.fields(estimator_class(name).Params)
                   if f.metadata.get("rejects")}
        assert set(changes) == flagged
        make_estimator(name, changes)      # every off value is a valid value
    with pytest.raises(ValueError, match="off value"):
        param(0.1, doc="a gate without a way to switch it off", rejects=True)
