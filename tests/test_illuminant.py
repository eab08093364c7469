"""Illuminant estimators: invariants, recovery of a known cast, masks, degenerate input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gridnerf import illuminant as il

NAMES = il.ESTIMATORS


def _texture(h=48, w=64, seed=0) -> np.ndarray:
    """(h, w) smooth random reflectance in [0.05, 0.95]."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(size=(h // 8 + 1, w // 8 + 1))
    t = np.kron(t, np.ones((8, 8)))[:h, :w]
    return 0.05 + 0.9 * t


def _grey_world_scene(h=48, w=64) -> np.ndarray:
    """(h, w, 3) reflectance whose channels are circular shifts of one texture: every
    channel has the same mean, p-norm and gradient statistics (all estimators' premise)."""
    t = _texture(h, w)
    return np.stack([t, np.roll(t, (16, 24), (0, 1)), np.roll(t, (32, 8), (0, 1))], -1)


def _est(name, rgb, mask=None):
    return il.estimate(name, rgb, mask=mask)


@pytest.mark.parametrize("name", NAMES)
def test_grey_scene_gives_unit_gains(name):
    rgb = np.repeat(_texture()[..., None], 3, axis=-1) * 0.003
    e = _est(name, rgb)
    np.testing.assert_allclose(np.linalg.norm(e), 1.0, rtol=1e-12)
    np.testing.assert_allclose(il.gains_from_illuminant(e), np.ones(3), rtol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_scaling_the_input_does_not_change_the_estimate(name):
    rgb = _grey_world_scene() * np.array([0.9, 0.6, 0.25])
    ref = _est(name, rgb)
    for scale in (1e-5, 0.01, 300.0):
        np.testing.assert_allclose(_est(name, scale * rgb), ref, rtol=1e-9, atol=1e-12)
    g = il.gains_from_illuminant(ref)
    np.testing.assert_allclose(il.gains_from_illuminant(42.0 * ref), g, rtol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_known_coloured_illuminant_is_recovered(name):
    light = np.array([1.0, 0.62, 0.27])  # a warm ~2800 K cast in camera RGB
    rgb = 0.004 * _grey_world_scene() * light
    e = _est(name, rgb)
    # grey edge: the circular shifts move a few edges across the image border
    tol = 2.0 if name == "grey_edge" else 0.5
    assert float(il.angular_error_deg(e, light)) < tol
    # the gains undo the cast: the balanced scene's channel means are equal
    balanced = rgb * il.gains_from_illuminant(e)
    means = balanced.reshape(-1, 3).mean(0)
    assert np.ptp(means) / means.mean() < tol / 20


@pytest.mark.parametrize("name", NAMES)
def test_masked_pixels_are_ignored(name):
    rgb = 0.004 * _grey_world_scene() * np.array([0.8, 1.0, 0.4])
    mask = np.ones(rgb.shape[:2], bool)
    mask[:, 40:] = False
    ref = _est(name, rgb, mask)
    bad = rgb.copy()
    bad[:, 40:] = [5.0, 0.0, 0.0]
    bad[3:6, 50:] = np.nan
    bad[7, 60] = np.inf
    np.testing.assert_allclose(_est(name, bad, mask), ref, rtol=1e-12)
    assert float(il.angular_error_deg(_est(name, bad), ref)) > 5.0  # unmasked: it matters
    # a per-channel mask (Bayer-style) is accepted too
    np.testing.assert_allclose(_est(name, bad, np.repeat(mask[..., None], 3, -1)), ref,
                               rtol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_no_nan_on_black_constant_or_negative_input(name):
    neutral = np.ones(3) / np.sqrt(3.0)
    for rgb in (np.zeros((8, 8, 3)), np.full((8, 8, 3), 0.25), np.full((8, 8, 3), -0.01),
                np.zeros((8, 8, 3)) + [0.01, 0.0, 0.0]):
        e = _est(name, rgb)
        g = il.gains_from_illuminant(e)
        assert np.all(np.isfinite(e)) and np.all(np.isfinite(g)) and np.all(g > 0)
        np.testing.assert_allclose(np.linalg.norm(e), 1.0, rtol=1e-9)
    np.testing.assert_allclose(_est(name, np.zeros((8, 8, 3))), neutral)
    # everything masked out: the neutral estimate, unit gains
    e = _est(name, np.ones((8, 8, 3)), np.zeros((8, 8), bool))
    np.testing.assert_allclose(il.gains_from_illuminant(e), np.ones(3))
    # a black channel gets a large finite gain
    g = il.gains_from_illuminant(np.array([0.7, 0.7, 0.0]))
    assert np.all(np.isfinite(g)) and 300.0 < g[2] < 1000.0


@pytest.mark.parametrize("name", NAMES)
def test_jax_matches_numpy_and_jits(name):
    rgb = 0.004 * _grey_world_scene() * np.array([0.9, 0.7, 0.35])
    mask = np.ones(rgb.shape[:2], np.float32)
    mask[::7] = 0.0
    ref = _est(name, rgb, mask)
    fn = jax.jit(lambda x, m: il.estimate(name, x, mask=m))
    out = fn(jnp.asarray(rgb, jnp.float32), jnp.asarray(mask))
    assert isinstance(out, jax.Array)
    np.testing.assert_allclose(np.asarray(out), ref, atol=2e-5)
    g = jax.grad(lambda x: il.gains_from_illuminant(il.estimate(name, x)).sum())(
        jnp.asarray(rgb, jnp.float32))
    assert np.all(np.isfinite(np.asarray(g)))


def test_shades_of_grey_spans_grey_world_to_max_rgb():
    rgb = 0.01 * _grey_world_scene() * np.array([1.0, 0.5, 0.3])
    rgb[0, 0] = [0.5, 0.5, 0.5]  # one bright white point
    gw = il.grey_world(rgb)
    np.testing.assert_allclose(il.shades_of_grey(rgb, p=1.0), gw, rtol=1e-12)
    np.testing.assert_allclose(il.shades_of_grey(rgb, p=np.inf), np.ones(3) / np.sqrt(3))
    with pytest.raises(ValueError, match="p must be"):
        il.shades_of_grey(rgb, p=0.5)


def test_weighted_grey_leaves_out_near_black_and_clipped_points():
    light = np.array([0.9, 0.7, 0.35])
    surface = (0.004 * _grey_world_scene() * light).reshape(-1, 3)
    junk = np.tile([[2e-5, 0.0, 3e-5]], (surface.shape[0], 1))  # near-black noise, blue cast
    clipped = np.tile([[1.0, 1.0, 0.2]], (50, 1))
    rgb = np.concatenate([surface, junk, clipped])
    assert float(il.angular_error_deg(il.weighted_grey(rgb), light)) < 1.5
    assert float(il.angular_error_deg(il.grey_world(rgb), light)) > 5.0
    # weights act like a soft mask; zero weights == masked out
    w = np.r_[np.ones(surface.shape[0]), np.zeros(junk.shape[0] + 50)]
    np.testing.assert_allclose(il.weighted_grey(rgb, weights=w),
                               il.weighted_grey(surface), rtol=1e-12)
    # nothing survives the exclusions: falls back to the weighted grey world
    np.testing.assert_allclose(il.weighted_grey(clipped), il.grey_world(clipped))


def test_footprint_weights_scale_with_depth_squared():
    w = il.footprint_weights(np.array([1.0, 2.0, np.inf]), np.array([1.0, 0.5, 1.0]))
    np.testing.assert_allclose(w, [1.0, 8.0, 0.0])


def test_grey_edge_needs_images_and_works_on_ray_patches():
    rgb = 0.004 * _grey_world_scene() * np.array([1.0, 0.6, 0.3])
    # 8x8 patches straddling the texture's 8x8 blocks, so each patch holds edges
    patches = rgb[4:44, 4:60].reshape(5, 8, 7, 8, 3).transpose(0, 2, 1, 3, 4).reshape(-1, 8, 8, 3)
    e = il.grey_edge(patches, sigma=0.0)
    assert float(il.angular_error_deg(e, [1.0, 0.6, 0.3])) < 2.0
    with pytest.raises(ValueError, match="H, W >= 2"):
        il.grey_edge(rgb.reshape(-1, 3))


def test_angular_error():
    assert float(il.angular_error_deg([1.0, 0.0, 0.0], [1.0, 1.0, 0.0])) == pytest.approx(45.0)
    assert float(il.angular_error_deg([0.2, 0.4, 0.1], [2.0, 4.0, 1.0])) == pytest.approx(
        0.0, abs=1e-6)
    errs = il.angular_error_deg(np.array([[1.0, 0, 0], [0, 1.0, 0]]), np.array([0, 1.0, 0]))
    np.testing.assert_allclose(errs, [90.0, 0.0], atol=1e-9)
    with pytest.raises(ValueError, match="unknown illuminant estimator"):
        il.estimate("white_patch", np.ones((4, 4, 3)))


def test_planckian_locus_projection_keeps_temperature_and_drops_green_magenta():
    from gridnerf.color import CAMERA_XYZ_TO_CAM, blackbody_xyz_white

    m = CAMERA_XYZ_TO_CAM["Canon EOS 5D Mark IV"]
    locus = il.planckian_locus(m)
    assert locus.shape == (1024, 3)
    np.testing.assert_allclose(np.linalg.norm(locus, axis=1), 1.0, rtol=1e-12)
    # adjacent entries are close, so the nearest entry is within a fraction of a degree
    steps = il.angular_error_deg(locus[1:], locus[:-1])
    assert float(np.max(steps)) < 0.1
    truth = m @ blackbody_xyz_white(2900.0)
    # a blackbody lands on itself; a magenta cast (green too low) is removed ...
    assert float(il.angular_error_deg(il.to_locus(truth, locus), truth)) < 0.1
    cast = truth * np.array([1.0, 0.9, 1.0])
    before = float(il.angular_error_deg(cast, truth))
    assert before > 2.0
    # what is left is the part of the cast that runs along the locus (a temperature error)
    assert float(il.angular_error_deg(il.to_locus(cast, locus), truth)) < 0.4 * before
    # ... scale-free, and the same under jit
    np.testing.assert_allclose(il.to_locus(1e-4 * cast, locus), il.to_locus(cast, locus))
    j = jax.jit(il.to_locus)(jnp.asarray(cast, jnp.float32), jnp.asarray(locus, jnp.float32))
    np.testing.assert_allclose(np.asarray(j), il.to_locus(cast, locus), rtol=1e-5)
    # the entry it takes is the one nearest in what the gains do (gain_distance), for any cast
    rng = np.random.default_rng(0)
    for e in truth * rng.uniform(0.5, 2.0, size=(20, 3)):
        nearest = min(il.gain_distance(row, e) for row in locus)
        assert il.gain_distance(il.to_locus(e, locus), e) == pytest.approx(nearest, abs=1e-9)


def test_frames_estimate_recovers_a_light_on_several_frames():
    """A capture of grey-mean, edge-balanced frames under one light: every estimator finds
    the light from the frames pooled (pixels with a mask left out, frames of any size)."""
    rng = np.random.default_rng(7)
    light = np.array([0.7, 1.0, 0.45])
    images, masks = [], []
    for h, w in ((24, 32), (20, 28)):
        reflect = rng.uniform(0.05, 1.0, (h, w, 1)) * np.ones(3)  # grey surfaces
        img = reflect * light
        m = np.ones((h, w), bool)
        img[:3, :3] = [50.0, 0.0, 0.0]  # clipped red patch, masked out
        m[:3, :3] = False
        images.append(img)
        masks.append(m)
    for name in il.ESTIMATORS:
        est = il.frames_estimate(name, images, masks)
        assert est.shape == (3,)
        assert float(il.angular_error_deg(est, light)) < 0.5, name
        scaled = il.frames_estimate(name, [9.0 * x for x in images], masks)
        np.testing.assert_allclose(scaled, est, rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(il.capture_estimate(name, images, masks), est)
    three = [il.frames_estimate(n, images, masks) for n in il.CONSENSUS]
    np.testing.assert_array_equal(il.capture_estimate("consensus", images, masks),
                                  il.consensus(three))


def test_consensus_outvotes_one_estimator():
    """The per-channel median of three estimates: two that agree decide, one far off is
    outvoted; with a locus the result lies on it."""
    truth = il.unit(np.array([0.7, 1.0, 0.45]))
    off = il.unit(np.array([0.4, 1.0, 0.9]))
    near = [il.unit(truth + d) for d in (np.array([0.01, 0, 0]), np.array([0, 0, 0.01]))]
    assert float(il.angular_error_deg(il.consensus([near[0], off, near[1]]), truth)) < 1.0
    locus = il.planckian_locus(np.array([[0.6446, -0.0366, -0.0864], [-0.4436, 1.2204, 0.2513],
                                         [-0.0952, 0.2496, 0.6348]]))
    on = il.consensus([near[0], off, near[1]], locus)
    assert np.min(il.angular_error_deg(on, locus)) < 1e-9
