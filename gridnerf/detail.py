"""The fine detail a grid stage leaves in its training frames, told apart from their noise.

A grid either holds a scene's fine structure or it does not; where it does not, the
residual of every training frame (the raw minus the grid's render of that view) holds the
missing detail under the frame's noise. With r1, r2 the residuals of the two green
photosites of each 2x2 CFA cell after a high-pass (each green plane minus its Gaussian blur
of SIGMA plane pixels: detail finer than about two binned pixels),

    total  = (mean(r1^2) + mean(r2^2)) / 2        the band's power: detail + noise
    noise  = G * mean(var(level))                  the band's share of the frames' noise
    detail = total - noise

and the reading's `ratio` = detail / (noise / n_views): the missing detail in units of the
band's noise after an ideal average of the n training views. G is the high-pass's gain on
white noise (its kernel's sum of squares). var(level) is one photosite's noise variance at
the render's level, read from the frames themselves: the two greens of a cell see nearly
the same point (one photosite apart on the diagonal) and their shot, read and row noise
are independent (they lie on different rows), so (r1 - r2) / sqrt(2), before the
high-pass, is that noise wherever the scene has no structure at the photosite's own scale;
the median absolute deviation (x 1.4826, squared) in each of N_LEVELS quantile bins of the
level outvotes the cells where it has some. A per-position black offset is constant and
leaves the band.

Why not the greens' shared part alone (mean(r1 r2), free of any noise estimate): the greens
sit half a plane pixel apart in each axis, so their shared part misses the finest band,
which is what a finer grid adds; on the four tuning scenes it did not tell the scenes a
288-wide last stage helps from those it hurts (docs/results.md, "Refining where the frames
show detail"). Heavy-tailed read noise makes the median read a little under the variance,
most in the darkest frames, which raises the reading there.

Measured on tiles of TILE x TILE photosites spread evenly over every EVERY-th training
frame, at most MAX_RAYS photosites in all, rendered by the grid in low-light camera RGB (the
data term's own prediction: exposure-normalised raw, lens falloff taken off as the
training targets are, gridnerf.dataset.targets); saturated photosites are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from gridnerf import dataset, render, vignetting

TILE = 64  # photosites a side of one measured tile (even: whole CFA cells)
SIGMA = 1.0  # the high-pass's Gaussian, in pixels of one CFA plane (two photosites)
EVERY = 4  # every this many training frames are measured
MAX_RAYS = 1 << 19  # photosites rendered at most (tiles thinned evenly above it)
_TRIM = 3  # plane pixels at each tile edge left out of the band (the blur's reach)
N_LEVELS = 16  # quantile bins of the render's level the noise is read in


@dataclass(frozen=True)
class DetailReading:
    """ratio: detail / (noise / views), the module docstring's reading; detail, noise: the
    band powers (normalised raw squared); views: the training views the unit averages;
    pairs: green cells measured."""

    ratio: float
    detail: float
    noise: float
    views: int
    pairs: int


def green_positions(cfa: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    """The two (row, col) positions of a 2x2 CFA's repeated colour (green in every
    RGB Bayer layout); ValueError for a CFA with none repeated."""
    cfa = np.asarray(cfa)
    values, counts = np.unique(cfa, return_counts=True)
    if counts.max() != 2:
        raise ValueError(f"a 2x2 CFA with one colour twice, not {cfa.tolist()}")
    rows, cols = np.nonzero(cfa == values[np.argmax(counts)])
    return (int(rows[0]), int(cols[0])), (int(rows[1]), int(cols[1]))


def highpass(planes: np.ndarray) -> np.ndarray:
    """(T, h, w) -> (T, h - 2 _TRIM, w - 2 _TRIM): each plane minus its Gaussian blur
    (SIGMA), the edges the blur reaches past left out."""
    planes = np.asarray(planes, np.float64)
    low = ndimage.gaussian_filter(planes, sigma=(0, SIGMA, SIGMA), mode="nearest")
    return (planes - low)[:, _TRIM:-_TRIM, _TRIM:-_TRIM]


def white_gain() -> float:
    """G: the band power highpass leaves of unit white noise (its kernel's sum of squares,
    from its response to a delta)."""
    n = 2 * _TRIM + 1 + 16
    delta = np.zeros((1, n, n))
    delta[0, n // 2, n // 2] = 1.0
    low = ndimage.gaussian_filter(delta, sigma=(0, SIGMA, SIGMA), mode="constant")
    return float(((delta - low) ** 2).sum())


def level_noise(diff: np.ndarray, level: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(edges (N_LEVELS + 1,), var (N_LEVELS,)): one photosite's noise variance in quantile
    bins of `level`, from `diff` = (r1 - r2) / sqrt(2) of the same cells (1-D each): the
    squared median absolute deviation x 1.4826 of each bin."""
    edges = np.quantile(level, np.linspace(0.0, 1.0, N_LEVELS + 1))
    idx = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, N_LEVELS - 1)
    var = np.array([(1.4826 * np.median(np.abs(diff[idx == b]))) ** 2 if (idx == b).any()
                    else np.nan for b in range(N_LEVELS)])
    return edges, np.where(np.isfinite(var), var, np.nanmean(var))


def band_powers(resid: np.ndarray, level: np.ndarray, valid: np.ndarray, cfa: np.ndarray
                ) -> tuple[float, float, int]:
    """(detail, noise, cells) of residual tiles resid, level, valid (T, TILE, TILE) (each
    photosite's residual, the render's level there and its validity): the module
    docstring's band powers of the two green planes, over the cells whose band both greens
    see unsaturated."""
    (a0, a1), (b0, b1) = green_positions(cfa)
    r1, r2 = resid[:, a0::2, a1::2], resid[:, b0::2, b1::2]
    lv = 0.5 * (level[:, a0::2, a1::2] + level[:, b0::2, b1::2])
    ok = valid[:, a0::2, a1::2] & valid[:, b0::2, b1::2]
    # a cell counts where no invalid photosite lies within the blur's reach of it
    band = ~ndimage.binary_dilation(~ok, structure=np.ones((1, 2 * _TRIM + 1, 2 * _TRIM + 1)))
    h1, h2 = highpass(np.where(ok, r1, 0.0)), highpass(np.where(ok, r2, 0.0))
    band = band[:, _TRIM:-_TRIM, _TRIM:-_TRIM]
    n = int(band.sum())
    if n == 0:
        return float("nan"), float("nan"), 0
    edges, var = level_noise(((r1 - r2) / math.sqrt(2.0))[ok], lv[ok])
    at = lv[:, _TRIM:-_TRIM, _TRIM:-_TRIM][band]
    idx = np.clip(np.searchsorted(edges, at, side="right") - 1, 0, N_LEVELS - 1)
    noise = white_gain() * float(var[idx].mean())
    total = float(0.5 * ((h1**2)[band].mean() + (h2**2)[band].mean()))
    return total - noise, noise, n


def tiles(image_hw: tuple[int, int], n_frames: int, max_rays: int = MAX_RAYS
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """frame, v, u (T, TILE, TILE) integer photosites of tiles laid evenly over each of
    n_frames frames (whole tiles, centred; every k-th tile where more than max_rays
    photosites would be rendered)."""
    h, w = image_hw
    ny, nx = h // TILE, w // TILE
    if ny == 0 or nx == 0:
        raise ValueError(f"frames of {w}x{h} photosites are smaller than a {TILE} tile")
    y0, x0 = (h - ny * TILE) // 2 // 2 * 2, (w - nx * TILE) // 2 // 2 * 2
    ty, tx = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    corners = np.stack([y0 + ty.ravel() * TILE, x0 + tx.ravel() * TILE], 1)
    keep = max(1, int(math.ceil(n_frames * len(corners) * TILE * TILE / max_rays)))
    frames = np.repeat(np.arange(n_frames), len(corners))
    corners = np.tile(corners, (n_frames, 1))
    frames, corners = frames[::keep], corners[::keep]
    dv, du = np.meshgrid(np.arange(TILE), np.arange(TILE), indexing="ij")
    v = corners[:, 0, None, None] + dv
    u = corners[:, 1, None, None] + du
    return np.broadcast_to(frames[:, None, None], v.shape), v, u


def measure(structure, params, scene, data_cfg, render_cfg, near_t: float, far_t: float,
            falloff: tuple[float, float] | None = None, every: int = EVERY,
            max_rays: int = MAX_RAYS) -> DetailReading:
    """The reading of a trained grid on its scene's training frames (module docstring).

    data_cfg: the run's data section (its target and exposure_ratio; the raw mosaic is
    read whatever the stage trained on); render_cfg: the run's render section;
    falloff: the run plan's lens falloff (k1, k2), taken off the targets as in training.
    """
    frames = np.asarray(scene.train_idx)[::every]
    data = vignetting.apply(
        dataset.build(scene, frames, binning=False, target=data_cfg.target,
                      exposure_ratio=data_cfg.exposure_ratio), falloff)
    views = len(scene.train_idx)
    if min(data.image_hw) < TILE:  # frames smaller than a tile: nothing to read
        return DetailReading(float("nan"), float("nan"), float("nan"), views, 0)
    fr, v, u = tiles(data.image_hw, len(frames), max_rays)
    rays = dataset.rays_at_jit(data, *(np.ascontiguousarray(a) for a in (fr, v, u)))
    out = render.render_image(structure, params, rays["origins"], rays["directions"],
                              near_t, far_t, render_cfg)
    mask = np.asarray(rays["mask"], np.float64)
    level = (mask * np.asarray(out["rgb_low"], np.float64)).sum(-1)
    resid = (mask * np.asarray(rays["target"], np.float64)).sum(-1) - level
    detail, noise, pairs = band_powers(resid, level, mask.sum(-1) > 0, scene.cfa)
    ratio = detail * views / noise if pairs and noise > 0 else float("nan")
    return DetailReading(ratio=float(ratio), detail=detail, noise=noise, views=views,
                         pairs=pairs)



def refinement(plan, structure, params, scene, cfg, near_t: float, far_t: float,
               fits_raw: bool):
    """The run plan at the start of the last stage: the reading of the grid the stage before
    it trained and whether the last trains at grid.refine_resolution (plan.with_refinement:
    the ratio over grid.refine_detail), with one printed line; the plan as it is where it
    was decided already, where the config never refines (grid.refine_detail 0, or a
    single stage), or where the data term does not fit raw frames (the oracle's
    references hold no noise to tell detail from)."""
    threshold = cfg.grid.refine_detail
    if (plan.refined is not None or threshold <= 0 or not fits_raw
            or len(cfg.grid.resolutions) < 2):
        return plan
    shaded = replace(cfg.render, max_samples=plan.samples(len(cfg.grid.resolutions) - 2, cfg))
    reading = measure(structure, params, scene, cfg.data, shaded, near_t, far_t,
                      plan.vignetting)
    ok = math.isfinite(reading.ratio)
    refined = ok and reading.ratio > threshold
    last, finer = list(cfg.grid.resolutions[-1]), list(cfg.grid.refine_resolution)
    told = (f"{reading.ratio:.2f} times their noise after averaging the {reading.views} "
            "views" if ok else "not measurable on these frames")
    print(f"detail: the frames hold fine detail of {told} (grid.refine_detail "
          f"{threshold:g}): the last stage trains at {finer if refined else last}"
          + (f" in place of {last}" if refined else ""))
    return plan.with_refinement(reading.ratio if ok else None, refined)
