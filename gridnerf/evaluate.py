"""Image-quality metrics for rendered views against ground truth (numpy, offline).

Protocol (RawNeRF, Mildenhall et al. CVPR 2022, as in google-research/multinerf's raw
evaluation): compare in sRGB after clipping the
linear images to [0, 1] and cropping a border; report each metric unaligned
and after a per-channel affine alignment fitted in linear space, which
forgives a global exposure/white-balance offset and isolates structure.

LPIPS and LIQE need network weights that cannot be downloaded here:
`lpips_status()` says "n/a" and no substitute is ever reported.
"""

from __future__ import annotations

import math

import numpy as np
from skimage.color import deltaE_ciede2000, rgb2lab
from skimage.metrics import structural_similarity

from gridnerf.color import srgb_encode
from gridnerf.errors import NumericsError, SceneError

METRIC_KEYS = ("psnr", "ssim", "delta_e", "psnr_aligned", "ssim_aligned", "delta_e_aligned")


def _pair(a, b) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    return a, b


def psnr(a_srgb, b_srgb) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]; inf when identical.

    Args:
      a_srgb, b_srgb: (H, W, 3) float, same shape.
    """
    a, b = _pair(a_srgb, b_srgb)
    mse = float(np.mean((a - b) ** 2))
    return math.inf if mse == 0.0 else float(-10.0 * np.log10(mse))


def ssim(a_srgb, b_srgb) -> float:
    """Mean SSIM (scikit-image, 7x7 uniform window, data_range 1) over channels.

    Images smaller than 7 pixels on a side use the largest odd window that
    fits (at least 3x3).

    Args:
      a_srgb, b_srgb: (H, W, 3) float in [0, 1], same shape, at least 3x3.
    """
    a, b = _pair(a_srgb, b_srgb)
    side = min(a.shape[0], a.shape[1])
    if side < 3:
        raise ValueError(f"SSIM needs images of at least 3x3 pixels, got {a.shape}")
    win = min(7, side if side % 2 else side - 1)
    return float(structural_similarity(a, b, win_size=win, channel_axis=-1, data_range=1.0))


def delta_e(a_srgb, b_srgb) -> float:
    """Mean CIEDE2000 colour difference (CIELAB via scikit-image, D65).

    Args:
      a_srgb, b_srgb: (H, W, 3) float sRGB, clipped to [0, 1] before conversion.
    """
    a, b = _pair(a_srgb, b_srgb)
    lab_a = rgb2lab(np.clip(a, 0.0, 1.0), channel_axis=-1)
    lab_b = rgb2lab(np.clip(b, 0.0, 1.0), channel_axis=-1)
    return float(np.mean(deltaE_ciede2000(lab_a, lab_b, channel_axis=-1)))


def align_affine(est_linear, gt_linear) -> np.ndarray:
    """RawNeRF-style per-channel affine alignment of an estimate onto ground truth.

    Fits `a_k * gt_k + b_k ~= est_k` by least squares for each channel k and
    returns `(est_k - b_k) / a_k`. A constant gt channel gets `a_k = 1` (offset
    only); `|a_k|` is floored at 1e-6 so the inversion stays finite.

    Args:
      est_linear: (H, W, 3) float, the estimate (linear).
      gt_linear: (H, W, 3) float, the reference (linear).

    Returns:
      (H, W, 3) float32, the aligned estimate.
    """
    est, gt = _pair(est_linear, gt_linear)
    e = est.reshape(-1, est.shape[-1])
    g = gt.reshape(-1, gt.shape[-1])
    g_mean, e_mean = g.mean(axis=0), e.mean(axis=0)
    var = np.mean((g - g_mean) ** 2, axis=0)
    cov = np.mean((g - g_mean) * (e - e_mean), axis=0)
    degenerate = var <= 1e-12 * np.maximum(np.mean(g**2, axis=0), 1e-30)
    a = np.where(degenerate, 1.0, cov / np.where(degenerate, 1.0, var))
    a = np.where(np.abs(a) < 1e-6, np.where(a < 0, -1e-6, 1e-6), a)
    b = e_mean - a * g_mean
    return ((est - b) / a).astype(np.float32)


def _crop(image: np.ndarray, crop: int) -> np.ndarray:
    return image[crop : image.shape[0] - crop, crop : image.shape[1] - crop]


def effective_crop(height: int, width: int, crop: int) -> int:
    """Border crop actually used: at most a quarter of the shorter side, so half remains."""
    return max(0, min(int(crop), min(height, width) // 4))


def _srgb(rgb_linear: np.ndarray) -> np.ndarray:
    return srgb_encode(np.clip(rgb_linear, 0.0, 1.0))


def image_metrics(pred_linear, gt_linear, crop: int = 16, *, name: str | None = None) -> dict:
    """All metrics of one rendered view against its reference.

    Both images are cropped by `effective_crop(H, W, crop)` pixels on every
    border, then compared in sRGB (`srgb_encode(clip(x, 0, 1))`); the
    `*_aligned` metrics first apply `align_affine(pred, gt)` (fitted on the
    crop) in linear space.

    Args:
      pred_linear: (H, W, 3) float, rendered linear sRGB.
      gt_linear: (H, W, 3) float, reference linear sRGB.
      crop: border in pixels (RawNeRF uses 16).
      name: frame name used in error messages.

    Returns:
      dict with float values for METRIC_KEYS:
      psnr, ssim, delta_e, psnr_aligned, ssim_aligned, delta_e_aligned.
    """
    pred = np.asarray(pred_linear, np.float64)
    gt = np.asarray(gt_linear, np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise SceneError(
            name,
            f"prediction {pred.shape} and ground truth {gt.shape} are not equal (H, W, 3) shapes",
            "render the view at the resolution of its ground-truth image",
        )
    if min(pred.shape[:2]) < 3:
        raise SceneError(name, f"image {pred.shape} is too small to evaluate", "use at least 3x3")
    if not np.all(np.isfinite(pred)):
        raise NumericsError(name, "prediction contains NaN/Inf", "check the model checkpoint")
    if not np.all(np.isfinite(gt)):
        raise SceneError(name, "ground truth contains NaN/Inf", "regenerate the reference image")
    c = effective_crop(pred.shape[0], pred.shape[1], crop)
    pred, gt = _crop(pred, c), _crop(gt, c)
    gt_srgb = _srgb(gt)
    out = {}
    for suffix, est in (("", pred), ("_aligned", align_affine(pred, gt))):
        est_srgb = _srgb(est)
        out["psnr" + suffix] = psnr(est_srgb, gt_srgb)
        out["ssim" + suffix] = ssim(est_srgb, gt_srgb)
        out["delta_e" + suffix] = delta_e(est_srgb, gt_srgb)
    return out


def summarize(per_view: dict[str, dict]) -> dict:
    """Mean of every metric over views: {view: {metric: value}} -> {metric: mean}.

    Metrics missing from some views are averaged over the views that have them.
    An empty input gives an empty dict.
    """
    keys: list[str] = []
    for metrics in per_view.values():
        keys += [k for k in metrics if k not in keys]
    return {k: float(np.mean([float(m[k]) for m in per_view.values() if k in m])) for k in keys}


def error_image(pred_srgb, gt_srgb, gain: float = 4.0) -> np.ndarray:
    """Visualise |pred - gt| as a 'hot' colour map (black -> red -> yellow -> white).

    The per-pixel error is the mean absolute difference over channels times
    `gain`, clipped to [0, 1]: black is exact, white is an error >= 1/gain.

    Args:
      pred_srgb, gt_srgb: (H, W, 3) float in [0, 1].

    Returns:
      (H, W, 3) float32 sRGB in [0, 1], ready for `write_png`.
    """
    a, b = _pair(pred_srgb, gt_srgb)
    err = np.clip(np.mean(np.abs(a - b), axis=-1) * gain, 0.0, 1.0)
    hot = np.stack([3.0 * err, 3.0 * err - 1.0, 3.0 * err - 2.0], axis=-1)
    return np.clip(hot, 0.0, 1.0).astype(np.float32)


def lpips_status() -> str:
    """LPIPS/LIQE need pretrained network weights that are not available offline: "n/a"."""
    return "n/a"


def white_balance_angular_error(pred_linear, gt_linear) -> float:
    """Angle in degrees between the mean colours of two linear images (a WB accuracy figure).

    0 means the same chromaticity of the mean colour, whatever the exposure.
    An all-black image has no colour and scores 90 degrees (the worst case for
    non-negative colours).

    Args:
      pred_linear, gt_linear: (H, W, 3) float, linear RGB.
    """
    a, b = _pair(pred_linear, gt_linear)
    ma = a.reshape(-1, a.shape[-1]).mean(axis=0)
    mb = b.reshape(-1, b.shape[-1]).mean(axis=0)
    if not np.any(ma) or not np.any(mb):
        return 90.0
    # atan2 of |cross| and dot stays accurate for tiny angles, unlike arccos.
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(ma, mb)), np.dot(ma, mb))))
