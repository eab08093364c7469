"""loss.gain_model: one gain for the capture where one light, the field where lights mix."""

from __future__ import annotations

import numpy as np
import pytest

from gridnerf import config as cfgmod
from gridnerf import data_term, optim
from gridnerf.errors import ConfigError


def _cfg(model: str):
    return cfgmod.override(cfgmod.preset("tiny"), [f"loss.gain_model={model}"])


def test_the_decision_is_the_data_s_under_auto():
    """colour_target.one_gain: "global" always, "field" never, "auto" exactly where the
    maps stray less than the one-light limit."""
    from gridnerf.colour_target import ONE_LIGHT_DEG as limit
    from gridnerf.colour_target import one_gain

    assert one_gain("global", None) and one_gain("global", 10 * limit)
    assert not one_gain("field", 0.0) and not one_gain("none", 0.0)
    assert one_gain("auto", 0.5 * limit)
    assert not one_gain("auto", limit) and not one_gain("auto", 2 * limit)
    assert not one_gain("auto", None)


def test_config_refuses_one_gain_without_a_capture_target():
    with pytest.raises(ConfigError, match="loss.gain_model"):
        cfgmod.override(_cfg("auto"), ["loss.ca_illuminant=grey_world", "loss.ca_target=batch"])
    from gridnerf.methods import llnerf

    with pytest.raises(ConfigError, match="loss.gain_model"):
        llnerf.check(cfgmod.override(_cfg("global"), ["loss.method=llnerf"]))
    saved = cfgmod.to_dict(cfgmod.preset("tiny"))
    del saved["loss"]["gain_model"]
    assert cfgmod.from_dict(saved).loss.gain_model == "field"


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
    data, colour = colour_target.plan_colour(data, scene, cfg)
    return cfg, structure, params, data, colour, near_t, far_t, scene


def test_one_gain_steps_leave_the_gains_and_train_the_same_field(step_setup):
    """With one gain the steps have no gain terms: the gains do not move, and density and
    colour take the steps the field's training gives them (the data term gives the gains
    no gradient, and L_ca on the normalised map none to density or colour)."""
    from dataclasses import replace

    import jax

    from gridnerf.plan import StepPlan

    cfg, structure, params, data, colour, near_t, far_t, scene = step_setup
    assert colour.model == "one_gain"  # "global"
    one = StepPlan(data_eps=1e-3, opacity=0.1, n_candidates=0, train_gains=False,
                   anchor=np.asarray(colour.anchor, np.float32))
    results = {}
    for name, plan in (("one", one), ("field", replace(one, train_gains=True))):
        tx = optim.make_optimizer(cfg, 5)
        p, s = params, tx.init(params)
        step = optim.make_step(cfg, plan, tx, near_t, far_t)
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
    """The tiny bucket (one light) under "auto": the run plan holds the anchor's gains,
    the summary and eval/metrics.json name them, and the shown output is the low-light
    colour times them (not the field's gains)."""
    from dataclasses import replace

    from gridnerf import eval_run, illuminant, plan
    from gridnerf.train import train

    run = tmp_path / "auto"
    cfg = _cfg("auto")
    summary = train(small_scene, run, cfg)
    saved = plan.load(run)
    assert saved.colour.model == "one_gain" and saved.colour.light_spread_deg < 3.0
    gains = np.asarray(saved.one_gain)
    assert summary["one_gain"] == pytest.approx(gains.tolist())
    ill = np.asarray(saved.colour.anchor, np.float32).astype(np.float64)
    assert gains == pytest.approx(illuminant.gains_from_illuminant(illuminant.unit(ill)))
    _, run_plan, scene, structure, params, _ = eval_run.load_run(run)
    shown = eval_run.run_outputs(cfg, run_plan, scene, structure, params)["gridnerf"]
    assert shown.source == "rgb_low" and np.allclose(shown.gains, gains)
    as_field = replace(run_plan, colour=replace(run_plan.colour, model="field"))
    field = eval_run.run_outputs(cfg, as_field, scene, structure, params)["gridnerf"]
    assert field.source == "rgb_restored"
    # the display goes through the matrix the run takes as the sensor's: the file's, or
    # the reference the frames chose over it (colour.locus_matrix)
    from gridnerf import exposure
    from gridnerf.color import CAMERA_XYZ_TO_CAM

    np.testing.assert_allclose(shown.matrix, exposure.display_matrix(scene.xyz_to_cam, True))
    other = next(m for m in CAMERA_XYZ_TO_CAM.values()
                 if not np.allclose(m, scene.xyz_to_cam))
    chosen = replace(run_plan, colour=replace(run_plan.colour,
                                              locus_matrix=tuple(np.ravel(other))))
    for name, o in eval_run.run_outputs(cfg, chosen, scene, structure, params).items():
        expected = np.eye(3) if name == "gridnerf_matrix_free" else exposure.display_matrix(
            other, True)
        np.testing.assert_allclose(o.matrix, expected, err_msg=name)
    metrics = eval_run.evaluate_run(run)
    assert metrics["colour"] == {"one_gain": pytest.approx(gains.tolist())}
    assert np.isfinite(metrics["summary"]["gridnerf"]["psnr"])
