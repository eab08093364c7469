"""Metrics (evaluate.py) and the plain 2D baseline (baseline.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gridnerf.baseline import (
    demosaic_bilinear,
    grey_world_gains,
    process_dark_frame,
)
from gridnerf.color import CAMERA_XYZ_TO_CAM, luminance, srgb_encode
from gridnerf.errors import NumericsError, RawError, SceneError
from gridnerf.evaluate import (
    METRIC_KEYS,
    align_affine,
    delta_e,
    effective_crop,
    error_image,
    image_metrics,
    lpips_status,
    psnr,
    ssim,
    summarize,
    white_balance_angular_error,
)
from gridnerf.exposure import alpha_for_luminance
from gridnerf.raw import cfa_masks as raw_cfa_masks

SONY = CAMERA_XYZ_TO_CAM["Sony ILCE-7SM2"]
PATTERNS = {
    "RGGB": [[0, 1], [1, 2]],
    "GRBG": [[1, 0], [2, 1]],
    "BGGR": [[2, 1], [1, 0]],
    "GBRG": [[1, 2], [0, 1]],
}


def _textured(h=40, w=48, seed=0):
    """(H, W, 3) smooth-plus-detail linear image in (0.02, 0.8)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([0.3 + 0.2 * np.sin(6 * xx), 0.3 + 0.2 * np.cos(5 * yy), 0.2 + 0.2 * xx * yy])
    return np.clip(base.transpose(1, 2, 0) + 0.1 * rng.uniform(size=(h, w, 3)), 0.02, 0.8)


# ---------------------------------------------------------------- metrics


def test_psnr_identical_and_known_offset():
    a = np.random.default_rng(0).uniform(0.2, 0.8, (8, 8, 3))
    assert psnr(a, a) == math.inf
    assert psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-9)
    assert psnr(a, a + 0.01) == pytest.approx(40.0, abs=1e-9)


def test_ssim_and_delta_e():
    a = _textured()
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    noisy = np.clip(a + np.random.default_rng(1).normal(0, 0.1, a.shape), 0, 1)
    assert ssim(a, noisy) < 0.9
    assert delta_e(a, a) == pytest.approx(0.0, abs=1e-9)
    shifted = a.copy()
    shifted[..., 2] += 0.1  # bluer
    assert delta_e(a, shifted) > 3.0
    # Tiny images use a smaller SSIM window instead of failing.
    assert ssim(a[:5, :4], a[:5, :4]) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="3x3"):
        ssim(a[:2, :2], a[:2, :2])


def test_align_affine_recovers_exact_affine():
    gt = _textured()
    gain, offset = np.array([0.5, 2.0, 1.3]), np.array([0.05, -0.1, 0.2])
    est = gt * gain + offset
    np.testing.assert_allclose(align_affine(est, gt), gt, atol=1e-5)
    metrics = image_metrics(est, gt, crop=4)
    assert metrics["psnr_aligned"] > 80.0 and metrics["psnr"] < 20.0
    assert metrics["ssim_aligned"] > 0.999 and metrics["ssim"] < metrics["ssim_aligned"]
    assert metrics["delta_e_aligned"] < 0.05 and metrics["delta_e"] > 5.0


def test_align_affine_degenerate_channels_stay_finite():
    gt = _textured()
    gt[..., 1] = 0.3  # constant gt channel: offset-only alignment
    est = gt.copy()
    est[..., 1] += 0.2
    est[..., 2] = 0.4  # estimate ignores gt: slope 0 is floored, result finite
    out = align_affine(est, gt)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out[..., 1], 0.3, atol=1e-6)
    np.testing.assert_allclose(out[..., 0], gt[..., 0], atol=1e-6)


def test_image_metrics_keys_and_crop():
    gt = _textured(80, 96)
    pred = gt.copy()
    pred[:16] = 0.0  # damage only the top border rows
    pred[:, -16:] = 1.0  # and the right border columns
    full = image_metrics(pred, gt, crop=0)
    cropped = image_metrics(pred, gt, crop=16)
    assert tuple(cropped) == METRIC_KEYS
    assert all(isinstance(v, float) for v in cropped.values())
    assert full["psnr"] < 20.0 and cropped["psnr"] == math.inf  # damage cropped away
    assert effective_crop(40, 48, 16) == 10
    # Small images: the crop shrinks so something remains.
    assert effective_crop(8, 30, 16) == 2 and effective_crop(3, 3, 16) == 0
    small = image_metrics(gt[:8, :8] * 0.9, gt[:8, :8], crop=16)
    assert set(small) == set(METRIC_KEYS) and np.isfinite(small["psnr"])
    assert small["psnr_aligned"] > small["psnr"]


def test_image_metrics_rejects_bad_input():
    gt = _textured(10, 10)
    with pytest.raises(SceneError, match="view_003.*resolution"):
        image_metrics(gt[:9], gt, name="view_003")
    bad = gt.copy()
    bad[2, 2, 0] = np.nan
    with pytest.raises(NumericsError, match="NaN"):
        image_metrics(bad, gt)


def test_image_metrics_clips_before_srgb():
    gt = _textured(20, 20)
    over = gt.copy()
    over[gt > 0.5] = 5.0  # bright overshoot clips to 1 like any value above 1
    ref = gt.copy()
    ref[gt > 0.5] = 1.0
    a, b = image_metrics(over, gt, crop=0), image_metrics(ref, gt, crop=0)
    assert a["psnr"] == pytest.approx(b["psnr"])


def test_summarize_means():
    per_view = {
        "a": {"psnr": 20.0, "ssim": 0.5},
        "b": {"psnr": 30.0, "ssim": 0.7},
        "c": {"psnr": 25.0, "ssim": 0.9, "delta_e": 4.0},
    }
    out = summarize(per_view)
    assert out["psnr"] == pytest.approx(25.0)
    assert out["ssim"] == pytest.approx(0.7)
    assert out["delta_e"] == pytest.approx(4.0)
    assert summarize({}) == {}


def test_error_image_and_lpips_status():
    a = np.zeros((4, 5, 3))
    b = a.copy()
    b[0, 0] = 1.0
    b[1, 1] = 0.05
    vis = error_image(b, a)
    assert vis.shape == (4, 5, 3) and vis.dtype == np.float32
    assert vis.min() >= 0.0 and vis.max() <= 1.0
    np.testing.assert_allclose(vis[0, 0], [1.0, 1.0, 1.0])  # saturated: white
    np.testing.assert_allclose(vis[1, 1], [0.6, 0.0, 0.0], atol=1e-6)  # 0.05*4*3 red
    np.testing.assert_array_equal(vis[2, 2], [0.0, 0.0, 0.0])
    assert lpips_status() == "n/a"


def test_white_balance_angular_error():
    gt = _textured()
    assert white_balance_angular_error(gt * 3.0, gt) == pytest.approx(0.0, abs=1e-6)
    grey = np.full((4, 4, 3), 0.2)
    red = np.zeros((4, 4, 3))
    red[..., 0] = 0.2
    assert white_balance_angular_error(red, grey) == pytest.approx(
        math.degrees(math.acos(1 / math.sqrt(3)))
    )
    assert white_balance_angular_error(np.zeros((4, 4, 3)), grey) == 90.0
    tiny = grey.copy()
    tiny[..., 0] *= 1.0001
    assert 0.0 < white_balance_angular_error(tiny, grey) < 0.01


# ---------------------------------------------------------------- baseline


def cfa_masks(shape, cfa):
    """(3, H, W) bool per-colour sample masks, from gridnerf.raw.cfa_masks."""
    return raw_cfa_masks(np.asarray(cfa), *shape).transpose(2, 0, 1) > 0


def _mosaic(rgb_cam, cfa):
    """(H, W, 3) -> (H, W) mosaic sampling the CFA colour at each pixel."""
    masks = cfa_masks(rgb_cam.shape[:2], cfa)
    return np.sum(rgb_cam * masks.transpose(1, 2, 0), axis=-1).astype(np.float32)


@pytest.mark.parametrize("name", sorted(PATTERNS))
def test_demosaic_constant_channels(name):
    cfa = np.array(PATTERNS[name])
    consts = np.array([0.7, 0.3, -0.05], np.float32)  # negative noise floor kept
    raw_bayer = _mosaic(np.broadcast_to(consts, (10, 13, 3)), cfa)
    rgb_cam = demosaic_bilinear(raw_bayer, cfa)
    assert rgb_cam.shape == (10, 13, 3) and rgb_cam.dtype == np.float32
    np.testing.assert_allclose(rgb_cam, np.broadcast_to(consts, rgb_cam.shape), atol=1e-6)


@pytest.mark.parametrize("name", ["RGGB", "GRBG"])
def test_demosaic_keeps_samples_and_interpolates_ramps(name):
    cfa = np.array(PATTERNS[name])
    xx = np.arange(12, dtype=np.float32)
    ramp = np.broadcast_to(xx[None, :, None] * np.array([1.0, 2.0, 3.0]), (8, 12, 3))
    raw_bayer = _mosaic(ramp, cfa)
    rgb_cam = demosaic_bilinear(raw_bayer, cfa)
    masks = cfa_masks(raw_bayer.shape, cfa)
    for c in range(3):
        np.testing.assert_array_equal(rgb_cam[..., c][masks[c]], raw_bayer[masks[c]])
    # Linear ramps are reproduced exactly away from the left/right borders.
    np.testing.assert_allclose(rgb_cam[:, 1:-1], ramp[:, 1:-1], atol=1e-5)


def test_demosaic_rejects_bad_input():
    with pytest.raises(RawError, match="RGB Bayer"):
        demosaic_bilinear(np.zeros((4, 4)), [[0, 1], [1, 1]])
    with pytest.raises(RawError, match=r"\(2, 2\)"):
        demosaic_bilinear(np.zeros((4, 4)), np.zeros((3, 3), int))
    with pytest.raises(RawError, match="2D Bayer"):
        demosaic_bilinear(np.zeros((4, 4, 3)), [[0, 1], [1, 2]])


def test_grey_world_gains_equalise_means():
    rgb_cam = _textured() * np.array([1.5, 1.0, 0.3])
    gains = grey_world_gains(rgb_cam)
    means = (rgb_cam * gains).reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(means, means.mean(), rtol=1e-5)
    np.testing.assert_allclose(means.mean(), rgb_cam.reshape(-1, 3).mean(axis=0).mean(), rtol=1e-5)
    # Masked: only the masked pixels count.
    mask = np.zeros(rgb_cam.shape[:2], bool)
    mask[:10] = True
    rgb_cam[~mask] = [5.0, 0.0, 0.0]
    gm = grey_world_gains(rgb_cam, mask)
    mm = (rgb_cam[mask] * gm).mean(axis=0)
    np.testing.assert_allclose(mm, mm.mean(), rtol=1e-5)
    # Degenerate channels stay finite and bounded.
    zero_blue = rgb_cam.copy()
    zero_blue[..., 2] = 0.0
    g0 = grey_world_gains(zero_blue)
    assert np.all(np.isfinite(g0)) and g0[2] <= 1000.0
    np.testing.assert_array_equal(grey_world_gains(np.zeros((4, 4, 3))), np.ones(3))


def test_auto_exposure_hits_target():
    rgb_linear = _textured() * 0.01
    alpha = alpha_for_luminance(rgb_linear)
    assert np.mean(luminance(alpha * rgb_linear)) == pytest.approx(0.18, rel=1e-9)
    alpha = alpha_for_luminance(rgb_linear, target=0.4)
    assert np.mean(luminance(alpha * rgb_linear)) == pytest.approx(0.4, rel=1e-9)
    with pytest.warns(UserWarning, match="black"):
        assert alpha_for_luminance(np.zeros((3, 3, 3))) == 1.0


def _cam_from_linear_under(kelvin: float) -> np.ndarray:
    from gridnerf.color import D65_XYZ, XYZ_FROM_SRGB, blackbody_xyz_white, chromatic_adaptation

    return SONY @ chromatic_adaptation(D65_XYZ, blackbody_xyz_white(kelvin)) @ XYZ_FROM_SRGB


def test_process_dark_frame_restores_colour_and_exposure():
    cfa = np.array(PATTERNS["RGGB"])
    rgb_linear = _textured(32, 40)
    # The scene under a 2900 K blackbody, very dark (the DNG colour model: Bradford
    # adaptation from D65, then the ColorMatrix): grey world restores it.
    rgb_cam = rgb_linear @ _cam_from_linear_under(2900.0).T
    raw_bayer = _mosaic(rgb_cam / rgb_cam.max() * 0.01, cfa)
    out = process_dark_frame(raw_bayer, cfa, SONY)
    assert out.shape == (32, 40, 3) and out.dtype == np.float32
    assert np.all(out >= 0) and np.all(np.isfinite(out))
    assert np.mean(luminance(out.astype(np.float64))) == pytest.approx(0.18, rel=0.02)
    # Grey-world on a scene whose own means are unequal still leaves it near the truth.
    gt = rgb_linear * alpha_for_luminance(rgb_linear)
    assert white_balance_angular_error(out, gt) < 8.0
    without = process_dark_frame(raw_bayer, cfa, None, use_matrix=False)
    assert np.all(np.isfinite(without)) and not np.allclose(without, out)


def test_denoised_baseline_lowers_the_noise():
    """The paper's 2D row (non-local means after the gamma) leaves far less noise than the
    plain processed frame on a noisy dark mosaic of a smooth scene, at the same colour and
    exposure, and stays finite and >= 0."""
    from gridnerf.baseline import noise_sigma, process_denoised_frame

    cfa = np.array(PATTERNS["RGGB"])
    ramp = np.add.outer(np.linspace(0.2, 0.6, 48), np.linspace(0.0, 0.3, 64))
    rgb_cam = ramp[..., None] * np.array([1.0, 0.8, 0.35]) * 0.01
    rng = np.random.default_rng(0)
    noisy = _mosaic(rng.poisson(rgb_cam * 3000.0) / 3000.0, cfa)
    plain = process_dark_frame(noisy, cfa, SONY)
    denoised = process_denoised_frame(noisy, cfa, SONY)
    assert denoised.shape == plain.shape and np.isfinite(denoised).all() and denoised.min() >= 0
    assert (noise_sigma(srgb_encode(denoised), demosaicked=True)
            < 0.5 * noise_sigma(srgb_encode(plain), demosaicked=True))
    # no noise, nothing to remove: the plain processed frame comes back
    clean = _mosaic(rgb_cam, cfa)
    np.testing.assert_allclose(process_denoised_frame(clean, cfa, SONY),
                               process_dark_frame(clean, cfa, SONY), atol=2e-3)


def test_process_dark_frame_guards_negative_and_zero_blue():
    rng = np.random.default_rng(3)
    cfa = np.array(PATTERNS["BGGR"])
    raw_bayer = rng.normal(0.0, 0.01, (24, 30)).astype(np.float32)  # pure noise, negatives
    raw_bayer[cfa_masks(raw_bayer.shape, cfa)[2]] = 0.0  # all-zero blue channel
    raw_bayer[cfa_masks(raw_bayer.shape, cfa)[0]] += 0.02
    out = process_dark_frame(raw_bayer, cfa, SONY)
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    all_neg = -np.abs(raw_bayer) - 0.01
    out_neg = process_dark_frame(all_neg, cfa, SONY)
    assert np.all(np.isfinite(out_neg)) and np.all(out_neg >= 0)
    with pytest.raises(RawError, match="NaN"):
        process_dark_frame(np.full((4, 4), np.nan), cfa, SONY)
    with pytest.raises(RawError, match="colour matrix"):
        process_dark_frame(raw_bayer, cfa, None)


def test_binned_baseline_matches_the_reference_exposure(small_scene):
    from conftest import sim_near_far

    from gridnerf import baseline, color, image_io
    from gridnerf.scene import load_scene

    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    name = scene.names[0]
    gt_linear = image_io.read_exr(scene.gt_linear_paths[name])
    out = baseline.process_binned_frame(scene.raw_normalized(0), scene.cfa, scene.xyz_to_cam,
                                        gt_linear)
    assert out.shape == gt_linear.shape and np.all(np.isfinite(out)) and out.min() >= 0.0
    # exposure matched before clipping negatives: the means agree closely
    assert np.mean(color.luminance(out)) == pytest.approx(
        np.mean(color.luminance(gt_linear)), rel=0.1)


def test_noise_sigma_of_white_noise_and_of_a_plane():
    from gridnerf.baseline import noise_sigma

    rng = np.random.default_rng(0)
    plane = np.add.outer(np.linspace(0, 1, 64), np.linspace(0, 0.5, 80))[..., None] * [1, 1, 1]
    assert noise_sigma(plane) < 1e-9
    assert noise_sigma(plane + rng.normal(0, 0.05, plane.shape)) == pytest.approx(0.05, rel=0.1)


def test_display_matrix_for_the_balanced_white_inverts_the_camera():
    """Camera RGB of linear-sRGB colours under a 2900 K blackbody (the simulator's model:
    ColorMatrix after Bradford adaptation from D65), balanced by the camera neutral's von
    Kries gains: the matrix for that neutral returns the colours (up to one scale), the D65
    row-normalised matrix does not for saturated ones; a neutral stays neutral."""
    from gridnerf import exposure, illuminant
    from gridnerf.color import D65_XYZ, XYZ_FROM_SRGB, blackbody_xyz_white, chromatic_adaptation

    xyz_to_cam = SONY
    kelvin = float(illuminant.LOCUS_KELVIN[400])
    cam_from_linear = (xyz_to_cam @ chromatic_adaptation(D65_XYZ, blackbody_xyz_white(kelvin))
                       @ XYZ_FROM_SRGB)
    rgb_linear = np.array([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.1, 0.2, 0.9], [0.5, 0.5, 0.5]])
    rgb_cam = rgb_linear @ cam_from_linear.T
    neutral = cam_from_linear @ np.ones(3)
    balanced = rgb_cam * illuminant.gains_from_illuminant(neutral)
    new = balanced @ exposure.display_matrix(xyz_to_cam, True, neutral).T
    scale = new[3, 1] / 0.5
    np.testing.assert_allclose(new / scale, rgb_linear, atol=1e-6)
    old = balanced @ exposure.display_matrix(xyz_to_cam, True).T
    assert np.abs(old / (old[3, 1] / 0.5) - rgb_linear).max() > 0.02
    np.testing.assert_array_equal(exposure.display_matrix(xyz_to_cam, False, neutral), np.eye(3))
