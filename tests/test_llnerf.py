"""The LLNeRF-style row (gridnerf.methods.llnerf): enhancement, losses, data, config."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gridnerf import config as cfgmod
from gridnerf.errors import ConfigError
from gridnerf.methods import llnerf


def _colours(seed=0, shape=(4, 8, 8, 3)) -> jnp.ndarray:
    """Dark sRGB colours in [0.01, 0.3], a few of them black."""
    rgb = np.random.default_rng(seed).uniform(0.01, 0.3, shape)
    rgb[0, 0, :3] = 0.0
    return jnp.asarray(rgb, jnp.float32)


def test_decomposition_reconstructs_the_colour():
    rgb_srgb = _colours()
    v, r = llnerf.decompose(rgb_srgb)
    assert v.shape == rgb_srgb.shape[:-1] and r.shape == rgb_srgb.shape
    np.testing.assert_allclose(r * v[..., None], rgb_srgb, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(v, rgb_srgb.max(axis=-1))
    lit = np.asarray(v) > 0
    np.testing.assert_allclose(np.asarray(r).max(axis=-1)[lit], 1.0, rtol=1e-6)
    assert np.all(np.asarray(r)[~lit] == 0)


def test_unit_alpha_and_gamma_is_the_identity_and_others_act_on_the_lighting():
    rgb_srgb = _colours(1)
    np.testing.assert_allclose(llnerf.enhance(rgb_srgb, 1.0, 1.0), rgb_srgb, rtol=1e-6, atol=0)
    # alpha scales, gamma bends the lighting; the reflectance (chromaticity) is kept
    v, r = llnerf.decompose(rgb_srgb)
    out = llnerf.enhance(rgb_srgb, 2.0, 0.5)
    np.testing.assert_allclose(out, np.clip(r * (2.0 * jnp.sqrt(v))[..., None], 0, 1),
                               rtol=1e-5, atol=1e-7)
    assert float(out.mean()) > 2.0 * float(rgb_srgb.mean())
    assert float(llnerf.enhance(jnp.full((3,), 0.9), 4.0, 1.0).max()) == 1.0  # clipped


def test_per_ray_parameters_are_the_composited_gain_over_the_opacity():
    gain = jnp.array([[1.5, 0.4, 0.5], [0.6, 0.5, 0.5]])  # acc 0.5: alpha 3 / 1.2, gamma 0.8 / 1
    acc = jnp.array([0.5, 0.5])
    alpha, gamma = llnerf.enhancement_params(gain, acc)
    np.testing.assert_allclose(alpha, [3.0, 1.2], rtol=1e-6)
    np.testing.assert_allclose(gamma, [0.8, 1.0], rtol=1e-6)


def test_exposure_loss_is_zero_at_the_level_and_positive_otherwise():
    e = 0.55
    assert float(llnerf.exposure_loss(jnp.full((2, 8, 8, 3), e), e)) == pytest.approx(0, abs=1e-6)
    assert float(llnerf.exposure_loss(jnp.full((2, 8, 8, 3), 0.3), e)) == pytest.approx(0.25)
    # a checkerboard averaging E in every 4x4 region is at the level; one bright region is not
    board = np.where((np.indices((8, 8)).sum(0) % 2)[None, ..., None], e - 0.2, e + 0.2)
    board = jnp.asarray(np.broadcast_to(board, (2, 8, 8, 3)), jnp.float32)
    assert float(llnerf.exposure_loss(board, e)) == pytest.approx(0, abs=1e-6)
    assert float(llnerf.exposure_loss(board.at[0, :4, :4].set(0.9), e)) > 0.01
    with pytest.raises(ValueError, match="4x4"):
        llnerf.exposure_loss(jnp.zeros((1, 6, 6, 3)), e)


def test_color_constancy_is_zero_for_grey_and_positive_for_a_tint():
    grey = jnp.repeat(jnp.asarray(np.random.default_rng(2).uniform(0, 1, (4, 8, 8, 1))), 3, -1)
    assert float(llnerf.color_constancy_loss(grey)) == pytest.approx(0, abs=1e-12)
    tinted = jnp.broadcast_to(jnp.array([0.5, 0.3, 0.3]), (4, 8, 8, 3))
    assert float(llnerf.color_constancy_loss(tinted)) == pytest.approx(0.08, rel=1e-5)


def test_gradients_are_finite_for_black_input():
    shape = (2, 8, 8, 3)
    n = 2 * 8 * 8
    black = jnp.zeros((n, 3))
    target, mask = jnp.full((n, 3), 0.05), jnp.ones((n, 3))

    def total(rgb, gain, acc, data):
        terms = llnerf.loss_terms(rgb, gain, acc, target, mask, shape, 0.55, data=data)
        return sum(terms.values())

    for acc, data in ((jnp.ones(n), "rawnerf"), (jnp.zeros(n), "rawnerf"), (jnp.ones(n), "mse")):
        grads = jax.grad(total, argnums=(0, 1))(black, jnp.ones((n, 3)), acc, data)
        for g in grads:
            assert np.all(np.isfinite(np.asarray(g)))
        assert float(jnp.abs(grads[1][:, :2]).sum()) == 0.0  # black stays black: no push
    da, dg, dc = jax.grad(lambda a, g, c: llnerf.enhance(c, a, g).sum(), argnums=(0, 1, 2))(
        0.7, 0.6, jnp.zeros((5, 3)))
    assert all(np.all(np.isfinite(np.asarray(x))) for x in (da, dg, dc))


def test_the_enhancement_losses_train_only_the_enhancement():
    """c is a constant in the exposure and colour terms: only the data term reaches it."""
    shape = (1, 8, 8, 3)
    rgb = _colours(3, shape).reshape(-1, 3)
    terms = lambda c: llnerf.loss_terms(c, jnp.ones((64, 3)), jnp.ones(64), rgb, jnp.ones(  # noqa: E731
        (64, 3)), shape, 0.55)
    g = jax.grad(lambda c: terms(c)["exposure"] + terms(c)["color_constancy"])(rgb)
    assert float(jnp.abs(g).sum()) == 0.0
    ga = jax.grad(lambda gain: llnerf.loss_terms(rgb, gain, jnp.ones(64), rgb, jnp.ones(
        (64, 3)), shape, 0.55)["exposure"])(jnp.ones((64, 3)))
    assert float(ga[:, 0].sum()) < 0  # too dark: raising alpha lowers the exposure loss


def test_the_method_checks_its_config():
    cfg = cfgmod.preset("llnerf")
    assert (cfg.data.target, cfg.loss.method, cfg.loss.gain_model) == ("raw", "llnerf", "field")
    assert (llnerf.W_EXPOSURE, llnerf.EXPOSURE_LEVEL) == (0.1, 0.55)
    llnerf.check(cfg)
    for sets in (["data.target=reference"], ["loss.gain_model=none"], ["train.patch_size=6"],
                 ["data.binning=false"], ["data.mosaic_stages=1"]):
        with pytest.raises(ConfigError):
            llnerf.check(cfgmod.override(cfg, sets))
    # one gain is Bright-NeRF's L_ca target: the method refuses it
    with pytest.raises(ConfigError, match="gain_model"):
        llnerf.check(cfgmod.override(cfg, ["loss.gain_model=global"]))


def test_dark_srgb_target(small_scene):
    from conftest import sim_near_far

    from gridnerf import dataset, raw
    from gridnerf.scene import load_scene

    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    data = dataset.build(scene, scene.train_idx, True, target=llnerf.dark_srgb_frames)
    darker = dataset.build(scene, scene.train_idx, True, target=llnerf.dark_srgb_frames,
                           exposure_ratio=0.5)
    pixels = np.asarray(data.pixels)
    assert pixels.shape[1:] == (45, 80, 3) and pixels.min() >= 0 and pixels.max() <= 1
    assert np.all(np.asarray(data.inv_exposure) == 1)
    i = int(scene.train_idx[0])
    rgb_cam, ok = scene.rgb_cam_binned(i)
    np.testing.assert_array_equal(pixels[0], llnerf.dark_srgb_frame(rgb_cam, scene.xyz_to_cam,
                                                                    ok))
    # a dark photo: sRGB-encoded, never brightened (the 2D baseline's exposure is 0.18 linear)
    assert 0.01 < pixels.mean() < 0.3
    assert np.asarray(darker.pixels).mean() < 0.85 * pixels.mean()
    # grey world: the frame's mean colour is near neutral (the raw's is not)
    from gridnerf import color

    mean_linear = color.srgb_decode(pixels[0].astype(np.float64)).mean((0, 1))
    mean_cam = raw.bin2x2(scene.raw_normalized(i), scene.cfa).mean((0, 1))
    assert np.ptp(mean_linear) / mean_linear.mean() < 0.5 * np.ptp(mean_cam) / mean_cam.mean()
    with pytest.raises(Exception, match="binning"):
        dataset.build(scene, scene.train_idx, False, target=llnerf.dark_srgb_frames)


def test_tiny_llnerf_trains_and_evaluates(small_scene, tmp_path):
    from gridnerf import image_io
    from gridnerf.eval_run import evaluate_run
    from gridnerf.train import load_state, train

    cfg = cfgmod.override(cfgmod.preset("tiny"), ["loss.method=llnerf"])
    run = tmp_path / "llnerf"
    train(small_scene, run, cfg)
    _, params, _, header = load_state(run)
    assert header["stage"] == 2
    assert all(np.all(np.isfinite(np.asarray(v))) for v in params.values())
    recs = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert {"data", "exposure", "color_constancy", "enhance_tv"} <= set(recs[-1])
    assert all(np.isfinite(r["loss"]) for r in recs)
    log_gain = np.asarray(params["log_gain"])  # alpha and gamma trained, channel 2 unused
    assert np.ptp(log_gain[:, 0]) > 1e-3 and np.ptp(log_gain[:, 1]) > 1e-3
    assert np.all(log_gain[:, 2] == 0)
    assert "ca" not in recs[-1] and "smooth" not in recs[-1]

    result = evaluate_run(run)
    summary = json.loads((run / "eval" / "metrics.json").read_text())["summary"]
    assert "llnerf" in summary and "gridnerf" not in summary
    assert np.isfinite(summary["llnerf"]["psnr"]) and summary["llnerf"]["psnr"] > 5
    assert result["alpha"] == {"llnerf": 1.0}
    # the shown image is the enhanced one: near the exposure level, far above the dark data
    name = result["test_views"][0]
    pred_srgb = image_io.read_png(run / "eval" / f"{name}_pred.png")
    assert 0.3 < float(pred_srgb.mean()) < 0.8
