"""Lens falloff (vignetting) estimated from the views themselves, and taken off the data.

A fast lens wide open darkens the corners of every frame by the same radial law, 1-1.5
stops on many lenses, and a RAW file carries no correction unless a converter wrote one.
A single frame cannot tell that falloff from a scene that is darker at its edges; many
views can: a surface seen near the centre of one frame and near the corner of another is
one radiance (a diffuse surface), so the ratio of the two observations is the ratio of the
falloff at the two radii.

After the first, coarse stage of the fit, whose depth is good enough to match pixels
between views, estimate takes an even sample of the training pixels, puts each at its
rendered depth, projects it into every other training frame whose ray meets it at under
MAX_PARALLAX_DEG and pairs the two observations (correspondences). fit_pairs then solves
log(I_i / I_j) = g(r_i) - g(r_j), g(r) = k1 r^2 + k2 r^4, with r the distance from the
principal point over the farthest corner's, by least squares over 2-D bins of (r_i^2,
r_j^2) each holding the ratio of its sums (the noise of 5-35 photo-electrons a pixel
averages out; occlusions and glossy surfaces add scatter, not a radial trend). Comparing
the frames with the fit's render instead does not work: the grid absorbs most of a falloff
shared by all views as darker paint (on a 1.2-stop lens it saw 0.26 stop).

Where the fitted corner falloff exceeds MIN_STOPS, the run takes it off the training pixels
(apply: divided by exp(k1 r^2 + k2 r^4)) for the later stages and keeps (k1, k2) in the run
plan (RunPlan.vignetting); after the second stage, whose finer depth matches fewer pixels
wrongly (wrong matches pull the ratio towards 1), what is left is measured and added.
Under MIN_STOPS nothing changes: a capture without falloff trains as before.
"""

from __future__ import annotations

from dataclasses import replace

import jax.numpy as jnp
import numpy as np

from gridnerf import consistency, dataset, illuminant, render
from gridnerf.cameras import project_points

# the corner falloff (stops) above which it is taken off the data (29 % at the corners).
# Captures without falloff read -0.35 to 0.42 (held_mixed_arc, cycles_sodium_room; the
# coarse depth still pairs some pixels with the wrong surface), the three captures 1-1.5
# stops down 0.96-1.01 after the first stage (docs/results.md, "Camera quirks")
MIN_STOPS = 0.5
# bins of each observation's radius (equal count) the pairs' ratios are summed over
PAIR_BINS = 8
# a bin is used where it holds this many pairs
MIN_PAIRS = 50
# a sample point is placed at its rendered depth where the fit is this opaque
MIN_ACC = 0.9
# a point seen in another frame is paired where that frame's rendered depth at its pixel
# is within this share of the point's own depth there (else an occluder, or a wrong match)
DEPTH_TOL = 0.05
# rays of the training frames the estimate renders (an even grid, dataset.strided_pixels)
RAYS = 16384
# a point is paired between two frames whose rays meet there at under this angle (deg):
# a depth or pose error moves the match by an amount that grows with the angle, and a
# glossy surface changes with it. With all pairs, estimated poses (0.18 deg rotation
# error) read 0.98 stop of falloff left after the second stage where the simulator's
# poses read 0.03; with pairs under 5 deg, 0.35 and -0.05 (docs/results.md, "Camera quirks")
MAX_PARALLAX_DEG = 5.0


def radius2(data: dataset.RayData, frame, v, u) -> np.ndarray:
    """(...) squared distance of pixels (v, u) of training frames `frame` from their frame's
    principal point, over that of the frame's farthest corner (dataset.radius2)."""
    intr = np.asarray(data.intrinsics)[np.asarray(frame)]
    return dataset.radius2(data.image_hw, intr, v, u)


def parallax_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P,) angle in degrees between the vectors a (P, 3) and b (P, 3) (or (3,)): at a
    surface point, between its rays to two cameras (illuminant.angular_error_deg, the one
    scale-free angle between 3-vectors)."""
    return np.asarray(illuminant.angular_error_deg(np.asarray(a, np.float64),
                                                   np.asarray(b, np.float64)))


def corner_stops(k: tuple[float, float]) -> float:
    """How many stops darker the corners (r = 1) are than the centre under exp(k1 r^2 +
    k2 r^4): positive for a falloff."""
    return -float(k[0] + k[1]) / float(np.log(2.0))


def fit_pairs(r2_i: np.ndarray, r2_j: np.ndarray, obs_i: np.ndarray,
              obs_j: np.ndarray) -> tuple[float, float]:
    """(k1, k2) of log(obs_i / obs_j) = g(r_i) - g(r_j), g = k1 r^2 + k2 r^4, weighted least
    squares over PAIR_BINS x PAIR_BINS bins of (r2_i, r2_j) (equal-count edges), each the
    log of the ratio of its sums against its pairs' mean r^2 and r^4 differences.

    r2_i, r2_j: (P,) radius2 of the two observations of P pairs; obs_i, obs_j: (P,) their
    exposure-normalised signals. (0, 0) where fewer than 3 bins hold pairs."""
    r2_i, r2_j = np.asarray(r2_i, np.float64), np.asarray(r2_j, np.float64)
    obs_i, obs_j = np.asarray(obs_i, np.float64), np.asarray(obs_j, np.float64)
    if r2_i.size == 0:
        return 0.0, 0.0
    edges = np.quantile(np.concatenate([r2_i, r2_j]), np.linspace(0, 1, PAIR_BINS + 1))
    bi = np.clip(np.searchsorted(edges, r2_i, side="right") - 1, 0, PAIR_BINS - 1)
    bj = np.clip(np.searchsorted(edges, r2_j, side="right") - 1, 0, PAIR_BINS - 1)
    cell = bi * PAIR_BINS + bj
    n_cells = PAIR_BINS * PAIR_BINS

    def sums(x):
        return np.bincount(cell, weights=x, minlength=n_cells)

    count = np.bincount(cell, minlength=n_cells).astype(np.float64)
    si, sj = sums(obs_i), sums(obs_j)
    use = (count >= MIN_PAIRS) & (si > 0) & (sj > 0)
    use &= np.arange(n_cells) // PAIR_BINS != np.arange(n_cells) % PAIR_BINS  # r_i != r_j
    if use.sum() < 3:
        return 0.0, 0.0
    c = np.maximum(count, 1.0)
    x1 = (sums(r2_i) - sums(r2_j)) / c
    x2 = (sums(r2_i**2) - sums(r2_j**2)) / c
    y = np.log(np.where(use, si, 1.0) / np.where(use, sj, 1.0))
    w = np.sqrt(count[use])
    design = np.stack([x1[use], x2[use]], axis=1) * w[:, None]
    k = np.linalg.lstsq(design, y[use] * w, rcond=None)[0]
    return float(k[0]), float(k[1])


def correspondences(structure, params, data: dataset.RayData, near_t: float, far_t: float,
                    render_cfg) -> tuple[np.ndarray, ...]:
    """(r2_i, r2_j, obs_i, obs_j) each (P,): pairs of observations of one surface point in
    two training frames. The points: an even sample of the training pixels (RAYS rays) at
    the depth the fit (structure, params) renders for them, where it is opaque (acc over
    MIN_ACC); each projected into every other training frame it lies in front of and inside,
    and kept where that frame sees it (_seen: the fit's depth there agrees; pixels that
    see an occluder, or a surface the coarse depth matched wrongly, would set a corner beside
    other content, on average the brighter middle of the frames). obs: the pixels'
    exposure-normalised signal summed over the channels (valid in all)."""
    frame, v, u = (np.asarray(a) for a in dataset.strided_pixels(data, RAYS))
    sample = dataset.rays_at_jit(data, frame, v, u)
    out = render.render_image(structure, params, sample["origins"], sample["directions"],
                              near_t, far_t, render_cfg)
    points, opaque = consistency.world_points(
        out["depth"], out["acc"], sample["origins"], sample["directions"], data.ndc,
        data.ndc_intrinsics, MIN_ACC)
    mask = np.asarray(sample["mask"], np.float64).reshape(-1, 3).min(-1) > 0
    keep = opaque.reshape(-1) & mask
    points = points.reshape(-1, 3)[keep]
    fi = frame.reshape(-1)[keep]
    r2_i = radius2(data, fi, v.reshape(-1)[keep], u.reshape(-1)[keep])
    obs_i = np.asarray(sample["target"], np.float64).reshape(-1, 3)[keep].sum(-1)
    pixels = np.asarray(data.pixels)
    valid = np.asarray(data.valid).all(-1)
    inv = np.asarray(data.inv_exposure, np.float64)
    c2w = np.asarray(data.c2w, np.float64)
    intr = np.asarray(data.intrinsics, np.float64)
    h, w = data.image_hw
    cand = []  # (index into the points, frame j, row, column) of every projection
    to_i = c2w[fi, :, 3] - points
    for j in range(c2w.shape[0]):
        uv = project_points(c2w[j], intr[j], points)  # NaN behind the camera
        ok = np.all(np.isfinite(uv), axis=-1)
        ok &= parallax_deg(to_i, c2w[j, :, 3] - points) <= MAX_PARALLAX_DEG
        uj = np.floor(np.where(ok, uv[:, 0], -1.0)).astype(np.int64)
        vj = np.floor(np.where(ok, uv[:, 1], -1.0)).astype(np.int64)
        inside = ok & (fi != j) & (uj >= 0) & (uj < w) & (vj >= 0) & (vj < h)
        idx = np.flatnonzero(inside)
        idx = idx[valid[j, vj[idx], uj[idx]]]
        cand.append(np.stack([idx, np.full(idx.size, j), vj[idx], uj[idx]], axis=1))
    cand = np.concatenate(cand)
    cand = cand[_seen(structure, params, data, near_t, far_t, render_cfg, cand[:, 1],
                      cand[:, 2], cand[:, 3], points[cand[:, 0]])]
    idx, fj, vj, uj = cand.T
    out_lists = (r2_i[idx], radius2(data, fj, vj, uj), obs_i[idx],
                 pixels[fj, vj, uj].astype(np.float64).sum(-1) * inv[fj])
    return out_lists


def _seen(structure, params, data: dataset.RayData, near_t: float, far_t: float,
          render_cfg, fj: np.ndarray, vj: np.ndarray, uj: np.ndarray, points: np.ndarray
          ) -> np.ndarray:
    """(P,) bool: pixels (vj, uj) of frames fj see the points (P, 3) themselves, not a
    surface in front of or behind them: the depth the fit renders there is within DEPTH_TOL
    of the point's own depth in that camera (consistency.camera_depth)."""
    if points.shape[0] == 0:
        return np.zeros(0, bool)
    sample = dataset.rays_at_jit(data, jnp.asarray(fj), jnp.asarray(vj), jnp.asarray(uj))
    out = render.render_image(structure, params, sample["origins"], sample["directions"],
                              near_t, far_t, render_cfg)
    seen, opaque = consistency.world_points(
        out["depth"], out["acc"], sample["origins"], sample["directions"], data.ndc,
        data.ndc_intrinsics, MIN_ACC)
    c2w = np.asarray(data.c2w, np.float64)
    own, there = np.empty(len(fj)), np.empty(len(fj))
    for j in np.unique(fj):
        at = fj == j
        own[at] = consistency.camera_depth(c2w[j], points[at])
        there[at] = consistency.camera_depth(c2w[j], seen[at])
    return opaque & (np.abs(there - own) <= DEPTH_TOL * np.abs(own))


def estimate(structure, params, data: dataset.RayData, near_t: float, far_t: float,
             render_cfg) -> tuple[float, float]:
    """(k1, k2): the lens falloff of the training frames, from the pairs of observations
    the fit's depth gives (correspondences, fit_pairs)."""
    return fit_pairs(*correspondences(structure, params, data, near_t, far_t, render_cfg))


def apply(data: dataset.RayData, k: tuple[float, float] | None) -> dataset.RayData:
    """data with its pixels divided by the falloff exp(k1 r^2 + k2 r^4) (k None or zero:
    data itself): binned pixels in place; the mosaic's raw integers are kept, and k is added
    to the falloff its targets are divided by as they are read (dataset.targets)."""
    if k is None or (k[0] == 0 and k[1] == 0):
        return data
    if data.mosaic:
        total = np.asarray(k, np.float32)
        if data.falloff is not None:
            total = total + np.asarray(data.falloff, np.float32)
        return replace(data, falloff=jnp.asarray(total))
    n = data.c2w.shape[0]
    h, w = data.image_hw
    frame, v, u = np.meshgrid(np.arange(n), np.arange(h), np.arange(w), indexing="ij")
    r2 = radius2(data, frame, v, u)
    gain = np.exp(-(k[0] * r2 + k[1] * r2 * r2)).astype(np.float32)[..., None]
    return replace(data, pixels=data.pixels * jnp.asarray(gain))
