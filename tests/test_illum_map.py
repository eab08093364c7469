"""Illuminant maps (gridnerf.illum_map): one light gives a flat map, two lights a gradient."""

from __future__ import annotations

import numpy as np
import pytest

from gridnerf import illum_map, illuminant

H, W = 128, 384
PATCH = 64  # paint patches span several blocks, as objects do in a frame


def _paint(seed: int = 0) -> np.ndarray:
    """(H, W, 3) reflectance: PATCH x PATCH squares of random paint (sharp edges only)."""
    rng = np.random.default_rng(seed)
    patches = rng.uniform(0.15, 0.9, size=(H // PATCH, W // PATCH, 3))
    return np.repeat(np.repeat(patches, PATCH, 0), PATCH, 1)


def _light(warm, cool) -> np.ndarray:
    """(H, W, 3) illuminant blending smoothly from `warm` (left) to `cool` (right)."""
    t = np.linspace(0.0, 1.0, W)[None, :, None]
    return np.broadcast_to((1 - t) * np.asarray(warm) + t * np.asarray(cool), (H, W, 3))


WARM, COOL = np.array([0.60, 1.0, 0.35]), np.array([0.37, 1.0, 0.72])


def _noisy(rgb, electrons: float, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.poisson(rgb * electrons) / electrons


@pytest.mark.parametrize(("electrons", "p90_deg"), [(np.inf, 0.5), (20.0, 2.5)])
def test_one_light_gives_a_flat_map(electrons, p90_deg):
    """Paint under one light: the map stays at the anchor, up to the noise that slips under
    tau (two lights of 2700 K and 6500 K lie ~20 deg apart)."""
    rgb_cam = _paint() * WARM
    if np.isfinite(electrons):
        rgb_cam = _noisy(rgb_cam, electrons)
    maps = illum_map.frame_maps([rgb_cam], [None], WARM, block=8, tau=0.1)
    assert maps.shape == (1, H // 8, W // 8, 3)
    err = illuminant.angular_error_deg(maps, WARM)
    assert float(np.percentile(err, 90)) < p90_deg, np.percentile(err, [50, 90, 100])


def test_two_lights_give_the_gradient_between_them():
    rgb_cam = _noisy(_paint() * _light(WARM, COOL), 20.0)
    anchor = illuminant.grey_world(_light(WARM, COOL))  # the mean light, as a capture sees it
    maps = illum_map.frame_maps([rgb_cam], [None], anchor, block=8, tau=0.1)[0]
    truth = illuminant.unit(raw_blocks(_light(WARM, COOL), 8))
    err_map = illuminant.angular_error_deg(maps, truth)
    err_flat = illuminant.angular_error_deg(np.broadcast_to(anchor, truth.shape), truth)
    assert err_map.mean() < 0.7 * err_flat.mean(), (err_map.mean(), err_flat.mean())
    # warm on the left, cool on the right
    assert maps[:, :4, 0].mean() > maps[:, -4:, 0].mean()
    assert maps[:, :4, 2].mean() < maps[:, -4:, 2].mean()


def raw_blocks(x, b):
    from gridnerf import raw

    return raw.downscale(x, b)


def test_map_is_scale_free_and_finite_on_black_and_masked_input():
    rgb_cam = _noisy(_paint() * _light(WARM, COOL), 20.0)
    a = illum_map.log_chroma_map(rgb_cam, block=8)
    np.testing.assert_allclose(illum_map.log_chroma_map(1e-4 * rgb_cam, block=8), a,
                               atol=1e-6)
    mask = np.ones((H, W), bool)
    mask[:, : W // 2] = False  # half the frame saturated
    for img, m in ((np.zeros((H, W, 3)), None), (rgb_cam, mask), (-rgb_cam, None)):
        out = illum_map.frame_maps([img], [m], WARM, block=8)
        assert np.isfinite(out).all()
        np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-9)


def test_integrated_steps_recover_a_field_up_to_its_weighted_mean():
    """integrate_steps: the exact neighbour differences of a field over every edge give the
    field back less its weighted mean; dropping every edge (ties only) gives a flat map."""
    rng = np.random.default_rng(3)
    hb, wb = 9, 13
    field = np.cumsum(rng.normal(0, 0.05, (hb, wb, 2)), axis=1)
    weight = rng.uniform(0.2, 1.0, (hb, wb))
    a, b = illum_map.neighbour_pairs(hb, wb)
    assert len(a) == hb * (wb - 1) + (hb - 1) * wb
    steps = field.reshape(-1, 2)[b] - field.reshape(-1, 2)[a]
    got = illum_map.integrate_steps(steps, np.ones(len(a), bool), weight)
    mean = (field * weight[..., None]).sum((0, 1)) / weight.sum()
    np.testing.assert_allclose(got, field - mean, atol=2e-3)
    flat = illum_map.integrate_steps(steps, np.zeros(len(a), bool), weight)
    np.testing.assert_allclose(flat, 0.0, atol=1e-9)


def test_to_locus_projects_every_entry_of_a_map():
    locus = illuminant.planckian_locus(np.eye(3))
    e = np.random.default_rng(0).uniform(0.2, 1.0, size=(4, 5, 3))
    out = illuminant.to_locus(e, locus)
    assert out.shape == (4, 5, 3)
    for i in range(4):
        for j in range(5):
            np.testing.assert_array_equal(out[i, j], illuminant.to_locus(e[i, j], locus))


ONES = np.ones((H, W), bool)


def _estimate(name):
    return lambda images, masks: illuminant.frames_estimate(name, images, masks)


def test_regional_anchor_keeps_one_light():
    """One light: both halves see it, so the anchor is the capture's estimate (to noise)."""
    rgb_cam = _noisy(_paint(3) * WARM, 20.0)
    rel, weight = illum_map.relative_maps([rgb_cam], [None], block=8)
    capture = illuminant.frames_estimate("grey_world", [rgb_cam], [ONES])
    anchor = illum_map.regional_anchor([rgb_cam], [None], rel, weight, _estimate("grey_world"),
                                       block=8)
    assert np.linalg.norm(anchor) == pytest.approx(1.0)
    assert float(illuminant.angular_error_deg(anchor, capture)) < 1.0


def test_regional_anchor_is_not_pulled_to_the_brighter_light():
    """Warm light on the left, four times brighter than the cool light on the right: an
    estimator that weighs bright pixels (shades of grey) sees mostly the warm one; the
    anchor made from each half apart brings the maps closer to the per-block truth."""
    t = np.linspace(0.0, 1.0, W)[None, :, None]
    light = (1 - t) * 4.0 * WARM + t * COOL
    light = np.broadcast_to(light, (H, W, 3))
    rgb_cam = _noisy(_paint(5) * light / 4.0, 80.0)
    rel, weight = illum_map.relative_maps([rgb_cam], [None], block=8)
    sog = _estimate("shades_of_grey")
    capture = sog([rgb_cam], [ONES])
    regional = illum_map.regional_anchor([rgb_cam], [None], rel, weight, sog, block=8)
    truth = illuminant.unit(raw_blocks(light, 8))
    err = {name: float(illuminant.angular_error_deg(
        illum_map.frame_maps([rgb_cam], [None], a, block=8, rel=rel)[0], truth).mean())
        for name, a in (("capture", capture), ("regional", regional))}
    assert err["regional"] < 0.9 * err["capture"], err
    # the same maps with or without precomputed relative maps
    np.testing.assert_array_equal(illum_map.frame_maps([rgb_cam], [None], capture, block=8),
                                  illum_map.frame_maps([rgb_cam], [None], capture, block=8,
                                                       rel=rel))


def test_map_spread_tells_one_light_from_two():
    """illum_map.map_spread_deg: the maps of paint under one light stay within a fraction of
    a degree of their anchor; a lamp-to-window blend strays by degrees."""
    one = [_paint(s) * WARM for s in range(2)]
    two = [_paint(s) * _light(WARM, COOL) for s in range(2)]
    spreads = []
    for frames in (one, two):
        masks = [None] * len(frames)
        anchor = illuminant.capture_estimate("consensus", frames, [np.ones((H, W))] * 2)
        maps = illum_map.frame_maps(frames, masks, anchor)
        spreads.append(illum_map.map_spread_deg(maps, anchor))
    assert spreads[0] < 0.5 < 3.0 < spreads[1]


def test_consistent_estimator_picks_per_light_count():
    """colour_target.consistent_estimator: under one light the estimator whose quadrants agree
    (quadrant_spreads' least), under two grey world; the quadrant spreads do not change
    with the frames' scale."""
    from gridnerf import colour_target

    masks = [np.ones((H, W))] * 2
    one = [_paint(s) * WARM for s in range(2)]
    spreads = illuminant.quadrant_spreads(one, masks)
    assert set(spreads) == set(illuminant.CONSENSUS)
    name = colour_target.consistent_estimator((one, masks))
    assert name == illuminant.least_spread(spreads)
    assert spreads[name][1] == min(s for _, s in spreads.values())
    scaled = illuminant.quadrant_spreads([7.0 * x for x in one], masks)
    for n, (est, s) in spreads.items():
        np.testing.assert_allclose(scaled[n][0], est, atol=1e-9)
        assert scaled[n][1] == pytest.approx(s, abs=1e-6)
    two = [_paint(s) * _light(WARM, COOL) for s in range(2)]
    assert colour_target.consistent_estimator((two, masks)) == "grey_world"


def test_estimates_run_downscaled_where_the_noise_rivals_the_signal():
    """colour_target.estimate_downscale: the smallest power of 2 that brings the frames'
    noise under ratio x their level, whatever their scale; downscaled averages d x d blocks
    and keeps a block valid only where all its pixels are; on frames whose noise is twice
    their level, the consistent pick on the downscaled frames lands nearer the light than
    on the full frames, where shades of grey and grey edge measure the noise."""
    from gridnerf import colour_target

    rng = np.random.default_rng(0)
    clean = [_paint(s) * WARM for s in range(3)]
    masks = [np.ones((H, W), bool)] * 3
    level = float(np.mean(clean))

    def noisy(share, scale=1.0):
        return [scale * (c + rng.normal(0.0, share * level, c.shape)) for c in clean]

    assert colour_target.estimate_downscale((clean, masks), 0.6) == 1
    assert colour_target.estimate_downscale((noisy(0.3), masks), 0.6) == 1
    assert colour_target.estimate_downscale((noisy(1.0), masks), 0.6) == 2
    assert colour_target.estimate_downscale((noisy(2.0, scale=1e-3), masks), 0.6) == 4
    assert colour_target.estimate_downscale((noisy(2.0), masks), 0.0) == 1
    assert colour_target.estimate_downscale(([0 * c for c in clean], masks), 0.6) == 1
    assert colour_target.downscaled((clean, masks), 1) == (clean, masks)
    holed = masks[0].copy()
    holed[0, 0] = False
    small, small_masks = colour_target.downscaled(([clean[0]], [holed]), 2)
    assert small[0].shape == (H // 2, W // 2, 3) and not small_masks[0][0, 0]
    assert small_masks[0][0, 1] and small_masks[0].sum() == H * W // 4 - 1
    np.testing.assert_allclose(small[0][0, 1], clean[0][:2, 2:4].mean(axis=(0, 1)))

    frames = (noisy(2.0), masks)
    d = colour_target.estimate_downscale(frames, 0.6)
    errors = {}
    for k in (1, d):
        name = colour_target.consistent_estimator(frames, k)
        small, small_masks = colour_target.downscaled(frames, k)
        est = illuminant.capture_estimate(name, small, small_masks)
        errors[k] = illuminant.angular_error_deg(est, WARM)
    assert errors[d] < errors[1] / 2


def test_map_blocks_keep_their_share_of_the_view():
    """16 binned pixels up to 479 wide (a 480x270 capture: the size the one-light test was
    read off), powers of 2 more on wider frames; a frame twice as wide keeps the same block
    grid and the same spread."""
    from gridnerf import colour_target

    widths = (80, 160, 240, 384, 479, 480, 960, 1920)
    assert [colour_target.map_block(w) for w in widths] == [16, 16, 16, 16, 16, 32, 64, 128]
    rng = np.random.default_rng(0)
    small = rng.uniform(0.2, 0.4, (135, 240, 3))
    wide = np.repeat(np.repeat(small, 2, 0), 2, 1)  # the same view at twice the pixels
    grids = []
    for img in (small, wide):
        mask = np.ones(img.shape[:2], bool)
        frames = ([img, img], [mask, mask])
        spread, _ = colour_target.light_spread(frames)
        grids.append(spread)
        block = colour_target.map_block(img.shape[1])
        assert img.shape[1] // block == 15 and img.shape[0] // block == 8
    np.testing.assert_allclose(grids[0], grids[1], rtol=1e-3)
