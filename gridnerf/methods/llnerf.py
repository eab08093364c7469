"""The LLNeRF-style comparison row on the grid: pure functions.

LLNeRF (Wang et al., "Lighting up NeRF via Unsupervised Decomposition and Enhancement",
ICCV 2023) trains on the camera-finished (sRGB) dark photos, splits the colour into a
lighting and a reflectance part and enhances the lighting under unsupervised losses. Here
on the same sparse grid as the method (loss.method = "llnerf", the `llnerf` preset):

- data (dark_srgb_frame, training_data): each training frame as a camera saves
  a dark photo: 2x2 binning of the normalised raw, grey world, the colour matrix, NO
  brightening, the sRGB curve, clipped to [0, 1]. The grid's low-light colour stores it.
- decomposition (decompose): a rendered dark colour c (sRGB) is lighting v = max_k c_k
  (scalar) times reflectance r = c / v.
- enhancement (enhance): v_e = alpha v^gamma, c_e = clip(r v_e, 0, 1). alpha, gamma > 0 per
  vertex in the grid's gain field (log_gain channel ALPHA = log alpha, GAMMA = log gamma;
  channel 2 unused), composited along the ray (the renderer's gain = sum_i w_i exp(log_gain_i))
  and divided by the opacity as losses.normalized_gain does (enhancement_params).
- losses (loss_terms, enhancement_tv), per batch of (P, p, p) ray patches: data = c
  against the dark sRGB, "rawnerf" (losses.data_loss: LLNeRF's released script trains its
  sRGB input with data_loss_type 'rawnerf', and the grid's regularisers were weighed against
  that term; the plain MSE of dark sRGB is ~1000x smaller: 6e-4 on the 160x90 test bucket
  against 0.6 weighted, so the TV, opacity and sparsity priors would dominate the fit) or
  "mse" (plain masked MSE), DATA_TERM; LLNeRF's enhancement losses in Zero-DCE's form (Guo
  et al., CVPR 2020) on c_e: exposure control, mean over pool x pool regions of |mean
  intensity - E|; colour constancy, sum over channel pairs of (mean_p - mean_q)^2 over the
  batch; total variation of log alpha and log gamma on the grid (losses.tv). The
  enhancement losses see c as a constant, so they train the enhancement field alone and the
  dark colour follows the data.

Weights and E (W_EXPOSURE 0.1, EXPOSURE_LEVEL 0.55, W_COLOR_CONSTANCY 0.1, W_ENHANCE_TV 0.1)
are those of LLNeRF's released training script (github.com/onpix/LLNeRF scripts/trian.sh:
exposure_loss_mult, fixed_exposure, gray_loss_mult, alpha_/gamma_ltv_loss_mult; Zero-DCE's
own E is 0.6). Differences from LLNeRF: its
release learns gamma per channel (3) and alpha as a scalar, which the 3-channel gain field
cannot hold with both; its losses are per-pixel squared ones; it enhances per sample, not
per ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from gridnerf import baseline, color, dataset, exposure, losses, render
from gridnerf.config import Config
from gridnerf.errors import ConfigError, SceneError
from gridnerf.plan import ColourPlan

NAME = "llnerf"
MAIN_OUTPUT = "llnerf"
W_EXPOSURE = 0.1  # exposure control: mean |pooled mean intensity - E|
EXPOSURE_LEVEL = 0.55  # E, the sRGB intensity the enhanced render is pushed to
EXPOSURE_POOL = 4  # side of the pooled regions of a ray patch (divides train.patch_size)
W_COLOR_CONSTANCY = 0.1  # sum over channel pairs of (mean_p - mean_q)^2
W_ENHANCE_TV = 0.1  # grid TV of log alpha and log gamma
DATA_TERM = "rawnerf"  # the data term on the dark sRGB: "rawnerf" or "mse"
EPS = 1e-6  # floor of the lighting v: r = c / max(v, EPS) and v^gamma stay finite at v = 0
ALPHA, GAMMA = 0, 1  # log_gain channels of log alpha and log gamma
_TINY = 1e-30


def dark_srgb_frame(rgb_cam, xyz_to_cam, valid=None) -> np.ndarray:
    """One frame as a camera saves a dark photo: grey-world white balance
    (baseline.grey_world_gains over the valid pixels), the colour matrix
    (exposure.display_matrix: the ColorMatrix for D65, row-normalised), no exposure, the
    sRGB curve (color.srgb_encode, which clips to [0, 1]).

    rgb_cam: (h, w, 3) binned camera RGB (raw.bin2x2 of the normalised raw, negatives
    kept); xyz_to_cam: (3, 3) DNG ColorMatrix; valid: optional (h, w) or (h, w, 3) bool,
    the unsaturated pixels (all channels) the grey world averages over.
    Returns rgb_srgb (h, w, 3) float32 in [0, 1].
    """
    rgb_cam = np.asarray(rgb_cam, np.float64)
    mask = None
    if valid is not None:
        valid = np.asarray(valid, bool)
        mask = valid.all(axis=-1) if valid.ndim == rgb_cam.ndim else valid
    rgb_cam = rgb_cam * baseline.grey_world_gains(rgb_cam, mask).astype(np.float64)
    rgb_linear = rgb_cam @ exposure.display_matrix(xyz_to_cam, True).T
    return color.srgb_encode(rgb_linear).astype(np.float32)


def decompose(rgb_srgb):
    """LLNeRF's decomposition: rgb_srgb (..., 3) >= 0 -> (v (...,), r (..., 3)), the
    lighting v = max over channels and the reflectance r = c / max(v, EPS) (max_k r_k = 1).
    r * v == c wherever v >= EPS or c = 0."""
    v = jnp.max(rgb_srgb, axis=-1)
    return v, rgb_srgb / jnp.maximum(v, EPS)[..., None]


def enhance(rgb_srgb, alpha, gamma):
    """The enhanced colour c_e = clip(r * alpha * v^gamma, 0, 1) of (v, r) = decompose(c).

    rgb_srgb: (..., 3) dark sRGB >= 0; alpha, gamma: (...) > 0 (or scalars). v is floored
    at EPS inside the power, so alpha = gamma = 1 gives back c exactly (up to rounding) and
    black stays black with finite gradients. Returns rgb_srgb (..., 3) in [0, 1].
    """
    v, r = decompose(rgb_srgb)
    v_e = alpha * jnp.maximum(v, EPS) ** gamma
    return jnp.clip(r * v_e[..., None], 0.0, 1.0)


def enhancement_params(gain, acc):
    """Per-ray (alpha, gamma), (...) each, from a render's composited gain (..., 3) =
    sum_i w_i exp(log_gain_i) and opacity acc (...): losses.normalized_gain (acc a constant,
    floored at 1e-3), channels ALPHA and GAMMA."""
    g = losses.normalized_gain(gain, acc)
    return g[..., ALPHA], g[..., GAMMA]


def enhanced_render(rgb_srgb, gain, acc):
    """The shown output of a render: enhance(rgb_srgb, *enhancement_params(gain, acc)).
    rgb_srgb, gain: (..., 3); acc: (...). Returns rgb_srgb (..., 3) in [0, 1]."""
    return enhance(rgb_srgb, *enhancement_params(gain, acc))


def init_log_gain_at(mean_level: float, level: float) -> np.ndarray:
    """(3,) log_gain a run starts from: gamma = 1 and alpha = level / mean_level, so the
    data's mean intensity (mean_level, e.g. data_term.data_statistics) starts at the exposure
    level E (as the method's gains start at the L_ca target)."""
    return np.array([np.log(level / max(mean_level, 1e-6)), 0.0, 0.0])


def data_loss(rgb_srgb, target, mask):
    """Plain masked MSE: sum m (c - y)^2 / sum m. rgb_srgb, target, mask: (n, 3)."""
    diff = jnp.where(mask > 0, rgb_srgb - target, 0.0)
    return jnp.sum(mask * diff**2) / jnp.maximum(jnp.sum(mask), _TINY)


def exposure_loss(rgb_srgb, level: float, pool: int = 4):
    """Zero-DCE's exposure control: mean over pool x pool regions of each patch of
    |mean intensity - level|, the intensity the channel mean (Zero-DCE's average intensity).

    rgb_srgb: (P, h, w, 3) ray patches, h and w multiples of pool. Returns a scalar >= 0,
    0 iff every region's mean intensity is `level`.
    """
    p, h, w, _ = rgb_srgb.shape
    if h % pool or w % pool:
        raise ValueError(f"patches of {h}x{w} do not split into {pool}x{pool} regions")
    y = jnp.mean(rgb_srgb, axis=-1).reshape(p, h // pool, pool, w // pool, pool)
    return jnp.mean(jnp.abs(jnp.mean(y, axis=(2, 4)) - level))


def color_constancy_loss(rgb_srgb):
    """Zero-DCE's colour constancy: sum over the channel pairs (R, G), (R, B), (G, B) of
    (mean_p - mean_q)^2, the means over the whole batch. rgb_srgb: (..., 3). 0 for grey."""
    m = jnp.mean(rgb_srgb.reshape(-1, 3), axis=0)
    return (m[0] - m[1]) ** 2 + (m[0] - m[2]) ** 2 + (m[1] - m[2]) ** 2


def enhancement_tv(log_gain) -> jax.Array:
    """TV of the enhancement field on the grid: losses.tv of log_gain's channels ALPHA and
    GAMMA ((r, 4, 3), a grid_sample's "log_gain"; TV(log alpha) + TV(log gamma), LLNeRF's
    alpha and gamma smoothness)."""
    return losses.tv(log_gain[..., :2])


def loss_terms(rgb_srgb, gain, acc, target, mask, patch_shape, level: float,
               pool: int = 4, data: str = "rawnerf") -> dict:
    """The per-batch terms: {"data", "exposure", "color_constancy"} (scalars, unweighted).

    rgb_srgb: (n, 3) the rendered dark colour c; gain: (n, 3) composited gains and acc (n,)
    opacity (render with stop-gradient density so that the enhancement losses cannot move
    the geometry); target, mask: (n, 3) dark sRGB and its weights; patch_shape: (P, p, p,
    3) of the batch; data: "rawnerf" (losses.data_loss) or "mse" (data_loss). The enhanced
    render c_e = enhanced_render(sg(c), gain, acc).
    """
    if data not in ("rawnerf", "mse"):
        raise ValueError(f"unknown data term {data!r}: use 'rawnerf' or 'mse'")
    fit = losses.data_loss if data == "rawnerf" else data_loss
    rgb_e = enhanced_render(jax.lax.stop_gradient(rgb_srgb), gain, acc).reshape(patch_shape)
    return {"data": fit(rgb_srgb, target, mask),
            "exposure": exposure_loss(rgb_e, level, pool),
            "color_constancy": color_constancy_loss(rgb_e)}


def check(cfg: Config) -> None:
    """ConfigError unless the config trains this row: the dark frames come from the raw
    capture, binned in every stage, with the gains (its enhancement field) on, and
    EXPOSURE_POOL divides the ray patches."""
    n_stages = len(cfg.grid.resolutions)
    if (cfg.data.target != "raw" or cfg.data.mosaic_from(n_stages) < n_stages
            or cfg.loss.gain_model != "field"):
        raise ConfigError(
            None, f"loss.method = 'llnerf' with data.target = {cfg.data.target!r}, "
            f"data.binning = {str(cfg.data.binning).lower()}, data.mosaic_stages = "
            f"{cfg.data.mosaic_stages} and loss.gain_model = {cfg.loss.gain_model!r}",
            "use the llnerf preset (data.target=raw, data.binning=true, "
            "data.mosaic_stages=0, loss.gain_model=field: the field holds its enhancement)")
    if cfg.train.patch_size % EXPOSURE_POOL:
        raise ConfigError(None, f"train.patch_size = {cfg.train.patch_size} is not a multiple "
                          f"of the LLNeRF row's exposure pool ({EXPOSURE_POOL})",
                          f"set train.patch_size to a multiple of {EXPOSURE_POOL}, e.g. 8")


def dark_srgb_frames(scene, frames, binning: bool, downscale: int, exposure_ratio: float):
    """The row's targets (a dataset.TARGETS-style function): each frame as a camera saves a
    dark photo (dark_srgb_frame of the binned raw times exposure_ratio; rgb_srgb in
    [0, 1]), exposure 1, pixels with a saturated channel invalid."""
    if not binning:
        raise SceneError(scene.path, "the LLNeRF row trains on binned frames: it needs "
                         "data.binning=true", "set data.binning=true")
    pairs = [scene.rgb_cam_binned(int(i), downscale) for i in frames]
    pixels = np.stack([dark_srgb_frame(rgb_cam * float(exposure_ratio), scene.xyz_to_cam, ok)
                       for rgb_cam, ok in pairs]).astype(np.float32)
    valid = np.stack([np.broadcast_to(ok.all(axis=-1, keepdims=True), ok.shape)
                      for _, ok in pairs])
    return pixels, valid, np.ones(len(frames), np.float32)


def fits_raw(cfg: Config) -> bool:
    """The data term weighs dark sRGB, not raw frames."""
    return False


def training_data(scene, cfg: Config) -> dataset.RayData:
    d = cfg.data
    return dataset.build(scene, scene.train_idx, d.binning, d.downscale, dark_srgb_frames,
                         d.exposure_ratio)


def plan_colour(data, scene, cfg: Config, saved=None):
    """Nothing is estimated from the frames: the enhancement losses set the colour."""
    return data, ColourPlan(model="none")


def init_log_gain(cfg: Config, colour, color_scale: float, grey_log_gain) -> np.ndarray:
    """alpha brings the data's mean level to EXPOSURE_LEVEL, gamma 1 (init_log_gain)."""
    return init_log_gain_at(color_scale, EXPOSURE_LEVEL)


def batch_terms(structure, params, flat: dict, out: dict, shape, sample: dict, cfg: Config,
                step):
    """(terms, weights) of one batch: "data" (the dark render against the dark sRGB,
    DATA_TERM), "exposure" and "color_constancy" (of the enhanced render), "enhance_tv"
    (grid TV of log alpha and log gamma on the step's grid_sample `sample`).

    flat: the batch's (n, 3) arrays; out: its render; shape: (P, p, p, 3). The
    enhancement parameters are composited with stop-gradient weights
    (render.frozen_density_gain, as for L_ca), so the enhancement losses train the
    enhancement field alone.
    """
    gain, acc = render.frozen_density_gain(out)
    terms = loss_terms(out["rgb_low"], gain, acc, flat["target"], flat["mask"], shape,
                       EXPOSURE_LEVEL, EXPOSURE_POOL, DATA_TERM)
    terms["enhance_tv"] = enhancement_tv(sample["log_gain"])
    return terms, {"data": cfg.loss.w_data, "exposure": W_EXPOSURE,
                   "color_constancy": W_COLOR_CONSTANCY, "enhance_tv": W_ENHANCE_TV}


@dataclass(frozen=True)
class EnhancedOutput:
    """The row's output: the dark sRGB render enhanced per ray (enhanced_render), decoded
    to linear sRGB; no exposure (alpha stays 1)."""

    alpha: float = 1.0

    def show(self, out: dict) -> tuple[np.ndarray, np.ndarray]:
        """(rgb_linear, rgb_srgb) of a render."""
        rgb_srgb = np.asarray(enhanced_render(out["rgb_low"], out["gain"], out["acc"]),
                              np.float32)
        return color.srgb_decode(rgb_srgb).astype(np.float32), rgb_srgb


def outputs(structure, params, scene, cfg: Config, plan, out: dict | None = None
            ) -> dict[str, EnhancedOutput]:
    """One output, "llnerf": the enhanced render, nothing exposed."""
    return {"llnerf": EnhancedOutput()}
