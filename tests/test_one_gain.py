"""loss.gain_model: one gain for the capture where one light, the field where lights mix."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from gridnerf import config as cfgmod
from gridnerf import data_term, optim
from gridnerf.errors import ConfigError


def _cfg(model: str, **loss):
    cfg = cfgmod.preset("tiny")
    return replace(cfg, loss=replace(cfg.loss, gain_model=model, **loss))


def test_the_decision_is_the_data_s_under_auto():
    """colour_target.one_gain: "global" always, "field" never, "auto" exactly where the
    maps' spread is under loss.ca_one_light_deg (and not without a spread)."""
    from gridnerf.colour_target import one_gain

    limit = cfgmod.preset("tiny").loss.ca_one_light_deg
    assert one_gain(_cfg("global"), None) and one_gain(_cfg("global"), 10 * limit)
    assert not one_gain(_cfg("field"), 0.0)
    assert one_gain(_cfg("auto"), 0.5 * limit)
    assert not one_gain(_cfg("auto"), limit) and not one_gain(_cfg("auto"), 2 * limit)
    assert not one_gain(_cfg("auto"), None)


def test_config_refuses_one_gain_without_a_capture_target():
    with pytest.raises(ConfigError, match="loss.gain_model"):
        _cfg("auto", ca_target="batch", ca_illuminant="grey_world")
    with pytest.raises(ConfigError, match="loss.gain_model"):
        _cfg("global", method="llnerf")
    # a saved config without the field was trained with the field; no gains: inert
    saved = cfgmod.to_dict(cfgmod.preset("tiny"))
    del saved["loss"]["gain_model"]
    assert cfgmod.from_dict(saved).loss.gain_model == "field"
    nogain = replace(_cfg("auto"), loss=replace(_cfg("auto").loss, use_gains=False))
    assert cfgmod.effective(nogain) == cfgmod.effective(
        replace(nogain, loss=replace(nogain.loss, gain_model="field")))


def test_one_gain_file_round_trip_and_bad_files(tmp_path):
    from gridnerf import colour_target, illuminant

    ill = np.array([0.5, 1.0, 0.4])
    colour_target.save_one_gain(tmp_path, ill)
    got = colour_target.load_one_gain(tmp_path, _cfg("auto"))
    assert got == pytest.approx(illuminant.gains_from_illuminant(ill / np.linalg.norm(ill)))
    assert colour_target.load_one_gain(tmp_path, _cfg("field")) is None  # the field's run
    for bad in ('{"gains": [1.0, -2.0, 1.0]}', '{"gains": [1.0, NaN, 1.0]}', "[]", "{",
                '{"gains": [1, 2]}'):
        (tmp_path / colour_target.ONE_GAIN).write_text(bad)
        assert colour_target.load_one_gain(tmp_path, _cfg("auto")) is None


@pytest.fixture(scope="module")
def step_setup(small_scene):
    import jax
    from conftest import sim_near_far

    from gridnerf import colour_target, dataset, grid
    from gridnerf.scene import load_scene

    cfg = _cfg("global")
    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    data = dataset.build(scene, scene.train_idx, True, 1, "raw")
    lo, hi, near_t, far_t = dataset.grid_box(scene)
    color_scale, log_gain, _ = data_term.data_statistics(data, jax.random.PRNGKey(1))
    structure, params = grid.init_grid((16, 16, 8), lo, hi, init_log_gain=log_gain,
                                       color_scale=color_scale, key=jax.random.PRNGKey(3))
    data, colour = colour_target.colour_inputs(data, scene, cfg)
    return cfg, structure, params, data, colour, near_t, far_t


def test_one_gain_steps_leave_the_gains_and_train_the_same_field(step_setup):
    """With one gain the steps have no gain terms: the gains do not move, and density and
    colour take the steps the field's training gives them (the data term gives the gains
    no gradient, and L_ca on the normalised map none to density or colour)."""
    import jax


    cfg, structure, params, data, colour, near_t, far_t = step_setup
    assert colour.get("one_gain") is True  # "global"
    field = {k: v for k, v in colour.items() if k != "one_gain"}
    results = {}
    for name, kwargs in (("one", colour), ("field", field)):
        tx = optim.make_optimizer(cfg, 5)
        p, s = params, tx.init(params)
        step = optim.make_step(cfg, tx, near_t, far_t, **kwargs)
        for k in range(3):
            p, s, total, terms = step(p, s, structure, data, jax.random.PRNGKey(k))
        assert np.isfinite(float(total))
        results[name] = (p, terms)
    one, one_terms = results["one"]
    fld, fld_terms = results["field"]
    assert "ca" not in one_terms and "smooth" not in one_terms and "ca" in fld_terms
    np.testing.assert_array_equal(np.asarray(one["log_gain"]), np.asarray(params["log_gain"]))
    assert not np.array_equal(np.asarray(fld["log_gain"]), np.asarray(params["log_gain"]))
    for k in ("density", "rgb"):
        moved = np.abs(np.asarray(fld[k]) - np.asarray(params[k])).max()
        assert moved > 1e-3
        np.testing.assert_allclose(np.asarray(one[k]), np.asarray(fld[k]), rtol=0,
                                   atol=1e-4 * moved)


def test_auto_trains_one_gain_on_one_light_and_eval_shows_it(small_scene, tmp_path):
    """The tiny bucket (one light) under "auto": one_gain.json holds the anchor's gains,
    the summary and eval/metrics.json name them, and the shown output is the low-light
    colour times them (not the field's gains)."""
    from gridnerf import colour_target, eval_run
    from gridnerf.train import train

    run = tmp_path / "auto"
    cfg = _cfg("auto")
    summary = train(small_scene, run, cfg)
    gains = colour_target.load_one_gain(run, cfg)
    assert gains is not None and summary["one_gain"] == pytest.approx(gains.tolist())
    record = json.loads((run / colour_target.ONE_GAIN).read_text())
    ill = np.asarray(record["illuminant"])
    assert gains == pytest.approx(colour_target.illuminant.gains_from_illuminant(ill))
    _, scene, structure, params, _ = eval_run.load_run(run)
    shown = eval_run.run_outputs(run, structure, params, scene, cfg)["gridnerf"]
    assert shown.source == "rgb_low" and np.allclose(shown.gains, gains)
    field = eval_run.outputs(structure, params, scene, cfg)["gridnerf"]  # without the gain
    assert field.source == "rgb_restored"
    metrics = eval_run.evaluate_run(run)
    assert metrics["colour"] == {"one_gain": pytest.approx(gains.tolist())}
    assert np.isfinite(metrics["summary"]["gridnerf"]["psnr"])
