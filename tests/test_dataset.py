"""Training targets: the mosaic path normalises per CFA position, keeps negatives and masks
saturated pixels; the binned path matches Scene.rgb_cam_binned; rays match rays.pixel_rays."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import sim_near_far

from gridnerf import dataset, rays
from gridnerf.scene import load_scene


def test_mosaic_targets_are_normalised_raw_on_the_measured_channel(small_scene):
    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    frames = scene.train_idx[:2]
    data = dataset.build(scene, frames, binning=False)
    h, w = scene.raw_bayer.shape[1:]
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    y, m = dataset.targets(data, jnp.zeros_like(v), jnp.asarray(v), jnp.asarray(u))
    expected = scene.raw_normalized(int(frames[0]))[v, u] / scene.exposure[frames[0]]
    channel = scene.cfa[v % 2, u % 2]
    np.testing.assert_allclose(np.asarray(y).sum(-1), expected, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(np.argmax(np.asarray(m), -1), channel)
    assert np.all(np.asarray(m).sum(-1) == 1)
    assert (expected < 0).any()  # dark noise goes below black and is kept


def test_mosaic_masks_saturated_pixels(small_scene):
    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    data = dataset.build(scene, scene.train_idx[:1], binning=False)
    pixels = data.pixels.at[0, 0, 0].set(jnp.uint16(data.white[0]))
    data = dataset.RayData(**{**data.__dict__, "pixels": pixels})
    _, m = dataset.targets(data, jnp.array(0), jnp.array(0), jnp.array(0))
    assert float(jnp.sum(m)) == 0.0


def test_binned_targets_match_scene(small_scene):
    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    i = int(scene.train_idx[1])
    data = dataset.build(scene, np.array([i]), binning=True)
    rgb_cam, valid = scene.rgb_cam_binned(i)
    y, m = dataset.targets(data, jnp.array(0), jnp.array(3), jnp.array(5))
    np.testing.assert_allclose(np.asarray(y), rgb_cam[3, 5] / scene.exposure[i], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(m) > 0, valid[3, 5])


def test_batch_rays_are_pixel_rays_in_ndc(small_scene):
    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    data = dataset.build(scene, scene.train_idx, binning=True)
    b = dataset.batch(data, jax.random.PRNGKey(0), 4, 3)
    assert b["origins"].shape == (4, 3, 3, 3) and b["target"].shape == (4, 3, 3, 3)
    for k in ("origins", "directions", "target", "mask"):
        assert np.all(np.isfinite(np.asarray(b[k])))
    # A whole-image ray through pixel (2, 1) equals rays.pixel_rays at the binned scale.
    cams = scene.cameras.scaled(0.5)
    o, d = dataset.image_rays(cams.c2w[0], np.array([cams.fx[0], cams.fy[0], cams.cx[0],
                                                     cams.cy[0]]), 4, 4)
    o2, d2 = rays.pixel_rays(cams.c2w[0], cams.fx[0], cams.fy[0], cams.cx[0], cams.cy[0],
                             np.array(2.0), np.array(1.0))
    np.testing.assert_allclose(np.asarray(d[1, 2]), d2, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(o[1, 2]), o2, rtol=1e-5, atol=1e-6)


def test_strided_pixels_cover_every_frame_evenly(small_scene):
    """The auto-exposure sample: every frame, a regular grid inside the image, about the
    asked count, the same on every call (no key); rays_at gives the same rays as batch's
    for the same pixels."""
    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    data = dataset.build(scene, scene.train_idx, binning=True)
    n, (h, w) = data.c2w.shape[0], data.image_hw
    fr, v, u = (np.asarray(a) for a in dataset.strided_pixels(data, 500))
    assert fr.shape == v.shape == u.shape and fr.shape[0] == n
    assert 250 <= fr.size <= 1000 and set(fr[:, 0, 0]) == set(range(n))
    assert v.min() >= 0 and v.max() < h and u.min() >= 0 and u.max() < w
    dv, du = np.diff(v[0, :, 0]), np.diff(u[0, 0, :])
    assert len(set(dv)) == 1 and set(dv) == set(du)  # one stride, down and across
    again = dataset.strided_pixels(data, 500)
    assert all(np.array_equal(a, np.asarray(b)) for a, b in zip((fr, v, u), again, strict=True))
    assert dataset.strided_pixels(data, 10**9)[1].size == n * h * w  # stride 1: all pixels
    b = dataset.batch(data, jax.random.PRNGKey(3), 2, 4)
    f, pv, pu = dataset.sample_patches(data, jax.random.PRNGKey(3), 2, 4)
    at = dataset.rays_at(data, jnp.broadcast_to(f[:, None, None], pv.shape), pv, pu)
    for k in ("origins", "directions", "target", "mask"):
        np.testing.assert_array_equal(np.asarray(at[k]), np.asarray(b[k]))


def test_oracle_data_are_the_downscaled_references(small_scene):
    from gridnerf import image_io, raw

    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    frames = scene.train_idx[:2]
    data = dataset.build(scene, frames, binning=True, target="reference")
    want = raw.downscale(image_io.read_exr(scene.gt_linear_paths[scene.names[frames[0]]]), 2)
    np.testing.assert_allclose(np.asarray(data.pixels[0]), want, rtol=1e-6)
    assert bool(jnp.all(data.valid)) and np.allclose(np.asarray(data.inv_exposure), 1.0)
    # the references have no mosaic: the error names binning, not a missing file
    from gridnerf.errors import SceneError

    with pytest.raises(SceneError, match="binning=false") as err:
        dataset.build(scene, frames, binning=False, target="reference")
    assert "missing" not in str(err.value)


def test_a_target_function_gives_the_pixels_and_binned_rays(small_scene):
    """dataset.build takes a target by name (TARGETS) or as a function of its own (the
    LLNeRF row's dark_srgb_frames): the function's pixels, validity and exposures are the
    data's, with binned intrinsics (half the full frame's)."""
    from gridnerf.methods import llnerf

    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    frames = scene.train_idx[:2]
    assert set(dataset.TARGETS) == {"raw", "reference", "processed", "clean"}
    by_name = dataset.build(scene, frames, binning=True, target="raw")
    by_fn = dataset.build(scene, frames, binning=True, target=dataset.raw_frames)
    np.testing.assert_array_equal(np.asarray(by_name.pixels), np.asarray(by_fn.pixels))
    dark = dataset.build(scene, frames, binning=True, target=llnerf.dark_srgb_frames)
    pixels, valid, inv_exposure = llnerf.dark_srgb_frames(scene, frames, True, 1, 1.0)
    np.testing.assert_array_equal(np.asarray(dark.pixels), pixels)
    np.testing.assert_array_equal(np.asarray(dark.valid), valid)
    np.testing.assert_array_equal(np.asarray(dark.inv_exposure), inv_exposure)
    assert not dark.mosaic and 0.0 <= pixels.min() and pixels.max() <= 1.0
    np.testing.assert_allclose(np.asarray(dark.intrinsics), np.asarray(by_name.intrinsics))
    np.testing.assert_allclose(np.asarray(dark.intrinsics[:, 0]),
                               scene.cameras.fx[frames] / 2, rtol=1e-6)
    mosaic = dataset.build(scene, frames, binning=False)
    assert mosaic.mosaic and not by_name.mosaic
    np.testing.assert_allclose(np.asarray(mosaic.intrinsics[:, 0]), scene.cameras.fx[frames],
                               rtol=1e-6)


def test_processed_target_is_the_2d_pipeline_binned(small_scene):
    """data.target = "processed" (2D + NeRF): each training frame through
    baseline.process_denoised_frame, box-downscaled to the binned size, exposure 1."""
    from gridnerf import baseline, config, raw

    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    i = int(scene.train_idx[0])
    data = dataset.build(scene, np.array([i]), binning=True, target="processed")
    expected = raw.downscale(baseline.process_denoised_frame(
        scene.raw_normalized(i), scene.cfa, scene.xyz_to_cam), 2)
    np.testing.assert_allclose(np.asarray(data.pixels[0]), expected, rtol=1e-6)
    assert float(data.inv_exposure[0]) == 1.0 and bool(np.asarray(data.valid).all())
    cfg = config.preset("processed")
    assert cfg.data.target == "processed" and not cfg.loss.use_gains


def test_exposure_ratio_scales_the_targets(small_scene):
    """data.exposure_ratio (the paper's darkness sweep, I_gamma = I_raw gamma after the
    black level): every target scales by gamma, masks do not change; config reads it."""
    from gridnerf import config

    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    v, u = jnp.asarray([[0, 3], [5, 7]]), jnp.asarray([[1, 2], [4, 6]])
    frame = jnp.zeros_like(v)
    for binning in (True, False):
        cfg = config.override(config.preset("tiny"), [f"data.binning={str(binning).lower()}"])
        one = dataset.training_data(scene, cfg.data)
        dark = dataset.training_data(scene, config.override(
            cfg, ["data.exposure_ratio=0.3"]).data)
        y1, m1 = dataset.targets(one, frame, v, u)
        y3, m3 = dataset.targets(dark, frame, v, u)
        np.testing.assert_allclose(np.asarray(y3), 0.3 * np.asarray(y1), rtol=1e-5, atol=1e-9)
        np.testing.assert_array_equal(np.asarray(m1), np.asarray(m3))


def test_clean_target_is_the_noise_free_mean_of_the_raw(small_scene, tmp_path):
    """The error budget's clean raw: per frame and channel its mean is the noisy raw's
    (the same signal, within the noise and the hidden black offset), its pixel-to-pixel
    differences far smaller (no noise)."""
    import shutil

    from experiments.error_budget import write_clean
    from gridnerf.errors import SceneError

    folder = tmp_path / "scene"
    shutil.copytree(small_scene, folder)
    scene = load_scene(folder, near_far=sim_near_far(folder))
    frames = scene.train_idx[:2]
    with pytest.raises(SceneError, match="noise-free raw"):
        dataset.build(scene, frames, binning=True, target="clean")
    write_clean(folder)
    clean = dataset.build(scene, frames, binning=True, target="clean")
    noisy = dataset.build(scene, frames, binning=True, target="raw")
    c, n = np.asarray(clean.pixels, np.float64), np.asarray(noisy.pixels, np.float64)
    assert c.shape == n.shape and np.all(np.isfinite(c)) and np.all(c >= 0)
    level = n.mean(axis=(1, 2))
    assert np.all(np.abs(c.mean(axis=(1, 2)) - level) < 0.25 * level)
    rough = lambda x: np.mean(np.abs(np.diff(x, axis=2)))  # noqa: E731
    assert rough(c) < 0.5 * rough(n)
    np.testing.assert_allclose(np.asarray(clean.inv_exposure), np.asarray(noisy.inv_exposure))
    # as a mosaic: every photosite's target is the clean value itself, on its own channel
    mosaic = dataset.build(scene, frames, binning=False, target="clean")
    assert mosaic.mosaic and mosaic.image_hw == scene.raw_bayer.shape[1:]
    h, w = mosaic.image_hw
    fr, v, u = (jnp.asarray(a) for a in np.meshgrid(np.arange(2), np.arange(h), np.arange(w),
                                                   indexing="ij"))
    y, m = (np.asarray(a, np.float64) for a in dataset.targets(mosaic, fr, v, u))
    truth = np.stack([np.load(folder / dataset.CLEAN_DIR / f"{scene.names[i]}.npy")
                      for i in frames]) * np.asarray(clean.inv_exposure)[:, None, None]
    kept = m.sum(-1) > 0
    assert kept.mean() > 0.99 and np.all(m.sum(-1) <= 1)
    np.testing.assert_allclose(y.sum(-1)[kept], truth[kept], rtol=1e-5, atol=1e-6)
    channel = np.asarray(scene.cfa)[np.arange(h)[:, None] % 2, np.arange(w)[None] % 2]
    assert np.all(m.argmax(-1)[kept] == np.broadcast_to(channel, kept.shape)[kept])
