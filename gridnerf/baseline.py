"""The plain 2D baseline gridnerf must beat: brighten one dark RAW frame on its own.

demosaic (bilinear) -> grey-world white balance -> camera -> linear sRGB ->
auto exposure -> clip negatives. No multi-view averaging, so the output keeps
all of the frame's noise; that is exactly what a NeRF should improve on.

Conventions (docs/design.md): `cfa` is a (2, 2) int array of colour indices
(0=R, 1=G, 2=B) with `cfa[y % 2, x % 2]`; `raw_bayer` is normalised raw with
negatives kept.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import convolve
from skimage.restoration import denoise_nl_means
from skimage.transform import resize

from gridnerf.color import luminance, srgb_decode, srgb_encode
from gridnerf.errors import RawError
from gridnerf.exposure import alpha_for_luminance, display_matrix
from gridnerf.illuminant import gains_from_illuminant, grey_world
from gridnerf.raw import bin2x2, cfa_masks, check_cfa

# Bilinear interpolation kernel for normalised convolution: cross neighbours
# weigh twice the diagonal ones, the centre four times.
_BILINEAR = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]])


def demosaic_bilinear(raw_bayer, cfa) -> np.ndarray:
    """Bilinear demosaic for any 2x2 RGB pattern, by normalised convolution.

    Each channel is `conv(raw * mask_c, K) / conv(mask_c, K)` with the 3x3
    bilinear kernel K and zero padding (so borders average only real samples),
    and measured samples are kept exactly. Negative values are kept.

    Args:
      raw_bayer: (H, W) float, normalised mosaic, H, W >= 2.
      cfa: (2, 2) int colour index per CFA position.

    Returns:
      rgb_cam: (H, W, 3) float32, camera-native linear RGB.
    """
    raw_bayer = np.asarray(raw_bayer)
    if raw_bayer.ndim != 2 or min(raw_bayer.shape) < 2:
        raise RawError(
            None,
            f"expected a 2D Bayer mosaic of at least 2x2, got shape {raw_bayer.shape}",
            "pass the single-channel raw frame (H, W), not a demosaicked image",
        )
    masks = cfa_masks(check_cfa(cfa), *raw_bayer.shape)
    raw = raw_bayer.astype(np.float64)
    channels = []
    for c in range(3):
        mask = masks[..., c] > 0
        weight = mask.astype(np.float64)
        num = convolve(raw * weight, _BILINEAR, mode="constant", cval=0.0)
        den = convolve(weight, _BILINEAR, mode="constant", cval=0.0)
        # Every 3x3 window clipped to the image holds a full 2x2 CFA period: den > 0.
        channels.append(np.where(mask, raw, num / den))
    return np.stack(channels, axis=-1).astype(np.float32)


def grey_world_gains(rgb_cam, mask=None) -> np.ndarray:
    """Grey-world von Kries gains: (3,) with `gains_k * mean_k == mean(mean_R, mean_G, mean_B)`.

    The same target as L_ca (`K_avg / Cbar_k`): illuminant.grey_world followed by
    illuminant.gains_from_illuminant. A channel whose mean is at or below 1e-3 of the
    brightest channel mean (e.g. an all-zero blue channel, or pure noise with a negative
    mean) is floored there, capping its gain near 1000; an image with no positive channel
    mean gets unit gains.

    Args:
      rgb_cam: (H, W, 3) float, camera-native linear RGB.
      mask: optional (H, W) bool, pixels to average over (all when None).

    Returns:
      (3,) float32 gains.
    """
    rgb = np.asarray(rgb_cam, np.float64)
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.size != rgb.size // 3:
            raise ValueError(f"mask has {mask.size} pixels, image has {rgb.size // 3}")
        mask = mask.reshape(rgb.shape[:-1])
    return gains_from_illuminant(grey_world(rgb, mask)).astype(np.float32)


def process_dark_frame(raw_bayer, cfa, xyz_to_cam, use_matrix: bool = True) -> np.ndarray:
    """Brighten one dark RAW frame: the 2D baseline.

    demosaic_bilinear -> grey_world_gains -> (exposure.display_matrix when use_matrix:
    row-normalised D65) ->
    exposure.alpha_for_luminance (mean luminance 0.18) -> clip negatives to 0.

    Args:
      raw_bayer: (H, W) float, normalised mosaic (negatives kept).
      cfa: (2, 2) int colour index per CFA position.
      xyz_to_cam: (3, 3) XYZ->camera matrix (DNG ColorMatrix); ignored when
        use_matrix is False (may then be None).
      use_matrix: convert camera RGB to linear sRGB with the colour matrix.

    Returns:
      rgb_linear: (H, W, 3) float32, >= 0, finite.
    """
    raw_bayer = np.asarray(raw_bayer)
    if not np.all(np.isfinite(raw_bayer)):
        raise RawError(None, "raw frame contains NaN/Inf", "re-read the RAW file; it is corrupt")
    rgb = demosaic_bilinear(raw_bayer, cfa).astype(np.float64)
    rgb = rgb * grey_world_gains(rgb).astype(np.float64)
    if use_matrix:
        matrix = np.asarray(xyz_to_cam, np.float64) if xyz_to_cam is not None else None
        if matrix is None or matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
            raise RawError(
                None,
                "a finite (3, 3) XYZ->camera colour matrix is needed",
                "pass the DNG ColorMatrix, or use_matrix=False",
            )
        rgb = rgb @ display_matrix(matrix, True).T
    rgb = rgb * alpha_for_luminance(rgb)
    return np.maximum(rgb, 0.0).astype(np.float32)


def process_binned_frame(raw_bayer, cfa, xyz_to_cam, gt_linear) -> np.ndarray:
    """The per-frame pipeline the 3D model must beat, made generous: 2x2 binning (4 raw
    samples per output pixel, a denoiser for free), grey world, the colour matrix
    (exposure.display_matrix, row-normalised D65), an exposure
    matched to the reference (mean luminance equal to gt's, which a real pipeline cannot
    know), bilinear upsampling back to the frame size, negatives clipped.

    raw_bayer: (H, W) normalised mosaic; gt_linear: (H, W, 3) the reference, linear sRGB.
    Returns rgb_linear (H, W, 3) float32.
    """
    rgb = bin2x2(np.asarray(raw_bayer, np.float32), check_cfa(cfa)).astype(np.float64)
    rgb = rgb * grey_world_gains(rgb).astype(np.float64)
    rgb = rgb @ display_matrix(np.asarray(xyz_to_cam, np.float64), True).T
    rgb = resize(rgb, np.asarray(gt_linear).shape[:2], order=1, anti_aliasing=False)
    target = float(np.mean(luminance(np.asarray(gt_linear, np.float64))))
    rgb = rgb * alpha_for_luminance(rgb, target)
    return np.maximum(rgb, 0.0).astype(np.float32)


_IMMERKAER = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def _immerkaer(x) -> float:
    h, w = x.shape
    if h < 3 or w < 3:
        return 0.0
    total = np.abs(convolve(x, _IMMERKAER, mode="nearest")[1:-1, 1:-1]).sum()
    return float(total * np.sqrt(np.pi / 2.0) / (6.0 * (w - 2) * (h - 2)))


def noise_sigma(rgb, demosaicked: bool = False) -> float:
    """Gaussian noise sigma of an (H, W, 3) image, averaged over channels: Immerkaer's
    estimator (1996, "Fast noise variance estimation"): sqrt(pi / 2) / (6 (W-2)(H-2)) times
    the sum of |image * M|, M the 3x3 difference of two Laplacians (zero on planes).
    demosaicked: interpolation smooths the noise of a demosaicked image, so each channel is
    measured on its four 2x2-phase sub-images and the largest (its measured samples) kept.
    """
    x = np.asarray(rgb, np.float64)
    if not demosaicked:
        return float(np.mean([_immerkaer(x[..., c]) for c in range(x.shape[-1])]))
    return float(np.mean([max(_immerkaer(x[dy::2, dx::2, c]) for dy in (0, 1) for dx in (0, 1))
                          for c in range(x.shape[-1])]))


def process_denoised_frame(raw_bayer, cfa, xyz_to_cam) -> np.ndarray:
    """The paper's 2D per-image row: process_dark_frame (demosaic, grey world, colour
    matrix, auto exposure), then the sRGB gamma and a classical denoiser, non-local means
    (Buades et al. 2005; scikit-image, 5x5 patches searched within 6 pixels, fast mode, h =
    0.8 x the noise sigma of the gamma-encoded image, noise_sigma), decoded
    back to linear for scoring. Returns rgb_linear (H, W, 3) float32, >= 0."""
    rgb_linear = process_dark_frame(raw_bayer, cfa, xyz_to_cam)
    rgb_srgb = srgb_encode(np.clip(rgb_linear, 0.0, 1.0).astype(np.float64))
    sigma = noise_sigma(rgb_srgb, demosaicked=True)
    if sigma > 0:
        rgb_srgb = denoise_nl_means(rgb_srgb, patch_size=5, patch_distance=6, h=0.8 * sigma,
                                    sigma=sigma, fast_mode=True, channel_axis=-1)
    return np.maximum(srgb_decode(np.clip(rgb_srgb, 0.0, 1.0)), 0.0).astype(np.float32)
