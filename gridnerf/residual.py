"""What a trained stage leaves unexplained in its training frames, against their noise.

The reading that sets the last stage's width (grid.detail_width, ABOVE): where
the grid of the last stage but one leaves more of the scene in its frames than the
training views' average leaves of their noise, the data can tell detail from noise and
the last stage may be finer; where it does not, a finer grid would fit noise.

How, without a noise model. The two green photosites of a Bayer cell sit diagonally, one
photosite apart, on different rows, so their shot, read and row noise are independent,
while the scene detail a grid misses is nearly the same at both (it varies over voxels,
2-5 photosites here). With r1, r2 their residuals (frame - render, normalised raw) and
d1, d2 the detail they hold:
    E[r1 r2]              = E[d1 d2]                           (the noise cancels)
    E[(r1 - r2)^2] / 2    = sigma^2 + E[(d1 - d2)^2] / 2        (one photosite's noise)
so their ratio is the missed detail in units of one frame's noise variance, whatever the
noise's distribution (Poisson shot noise, heavy-tailed read noise; a median-based noise
estimate reads these low), and conservative: detail that differs between the two greens
counts as noise. The ratio is taken per level (quantile bins of the rendered green: the
noise variance grows with the signal) and averaged over the cells, then multiplied by the
training views: the unit is the noise an ideal average of the views leaves
(sigma^2 / views), so 1 means the stage misses as much as the views can resolve. Its
standard error comes with it (the spread of r1 r2: about views / sqrt(cells), 0.05 for
24 views and 6 frames of 480x270); a run refines only where the reading exceeds its
threshold by two of them (the conservative side where the evidence is thin).

Units: normalised raw, (DN - black) / (white - black), as dataset.targets gives it.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy.ndimage import map_coordinates

from gridnerf import consistency, dataset, raw, render

LEVEL_BINS = 16  # quantile bins of the rendered green level
EVERY = 4  # every this-many-th training frame is read
MAX_CELLS = 1 << 15  # Bayer cells read per frame at most (a strided subset beyond)
MIN_CELLS = 256  # cells a reading needs; fewer: not measurable (nan)
# a run refines its last stage (grid.detail_width) where the reading less SIGMAS standard
# errors exceeds ABOVE: the grid misses more than the views' average leaves of the noise
ABOVE = 1.0
SIGMAS = 2.0
# ... and no finer than FOOTPRINT = (photosites, vertices): 5 photosites of the frame across
# per 3 vertices across, the footprint at which the rule was measured (480x270 captures, a
# 288-wide last stage). A finer vertex comes near one photosite, below the mosaic's
# sampling of each colour (every second photosite); at 320x180 the default's 192-wide stage
# is already at it (docs/results.md, "The last stage refined where the frames show detail")
FOOTPRINT = (5, 3)


def finest_width(photosites_across: int) -> int:
    """The widest last stage (vertices across) a frame `photosites_across` photosites wide
    holds at FOOTPRINT: 288 at 480, 192 at 320."""
    photosites, vertices = FOOTPRINT
    return int(photosites_across) * vertices // photosites


def exceeds(reading: float, error: float) -> bool:
    """Whether the reading less SIGMAS of its errors exceeds ABOVE (False where it is not
    finite: not measurable)."""
    return bool(np.isfinite(reading) and np.isfinite(error)
                and reading - SIGMAS * error > ABOVE)


def refined_width(reading: float, error: float, detail_width: int, width: int,
                  photosites_across: int) -> int | None:
    """The last stage's width the reading asks for, or None to keep `width` (the config's):
    detail_width (0: the option is off), no wider than finest_width, where the reading less
    SIGMAS errors exceeds ABOVE and that width exceeds `width`. A reading that is not
    finite (not measurable) keeps the width."""
    to = min(int(detail_width), finest_width(photosites_across))
    return to if detail_width > 0 and exceeds(reading, error) and to > width else None


def green_positions(cfa) -> list[tuple[int, int]]:
    """The (row, col) in the 2x2 CFA cell of its two green photosites (colour index 1)."""
    cfa = np.asarray(cfa)
    return [(int(r), int(c)) for r, c in zip(*np.nonzero(cfa == 1), strict=True)]


def cell_pixels(data: dataset.RayData, every: int = EVERY, max_cells: int = MAX_CELLS):
    """frame, v, u of both greens of the read cells: each (2, n) int arrays (green 1 and 2),
    every `every`-th training frame, the cells on an even stride (at most max_cells a
    frame)."""
    h, w = data.image_hw
    hc, wc = h // 2, w // 2
    stride = max(1, int(np.ceil(np.sqrt(hc * wc / max(max_cells, 1)))))
    frames = np.arange(0, data.c2w.shape[0], every)
    f, i, j = np.meshgrid(frames, np.arange(0, hc, stride), np.arange(0, wc, stride),
                          indexing="ij")
    f, i, j = f.ravel(), i.ravel(), j.ravel()
    (r1, c1), (r2, c2) = green_positions(data.cfa)
    fr = np.stack([f, f])
    v = np.stack([2 * i + r1, 2 * i + r2])
    u = np.stack([2 * j + c1, 2 * j + c2])
    return fr, v, u


def detail_over_noise(r1, r2, level, n_bins: int = LEVEL_BINS) -> tuple[float, float]:
    """(the mean over cells of the missed detail over one photosite's noise variance, its
    standard error) (module docstring): per quantile bin of `level`, mean(r1 r2) /
    (mean((r1 - r2)^2) / 2), weighted by the bin's cells; the error from the spread of
    r1 r2 in each bin. r1, r2, level: (n,) arrays. (nan, nan) under MIN_CELLS cells."""
    r1, r2, level = (np.asarray(a, np.float64).ravel() for a in (r1, r2, level))
    n = r1.size
    if n < MIN_CELLS:
        return float("nan"), float("nan")
    order = np.argsort(level, kind="stable")
    total, var, weight = 0.0, 0.0, 0
    for idx in np.array_split(order, min(n_bins, n // (MIN_CELLS // 4) or 1)):
        noise = float(np.mean((r1[idx] - r2[idx]) ** 2)) / 2.0
        if noise > 0:
            shared = r1[idx] * r2[idx]
            total += idx.size * float(np.mean(shared)) / noise
            var += idx.size * float(np.var(shared)) / noise**2
            weight += idx.size
    if not weight:
        return float("nan"), float("nan")
    return total / weight, float(np.sqrt(var)) / weight


def read(structure, params, data: dataset.RayData, near_t, far_t,
         render_cfg) -> tuple[float, float]:
    """(the detail the field leaves in the training frames in units of the noise an ideal
    average of the training views leaves, its standard error): views x
    detail_over_noise of the two greens of every read cell. data: the raw mosaic
    (data.mosaic); (nan, nan) where the frames are not the mosaic or too few unsaturated
    cells are read."""
    if not data.mosaic:
        return float("nan"), float("nan")
    fr, v, u = cell_pixels(data)
    rays = dataset.rays_at_jit(data, jnp.asarray(fr), jnp.asarray(v), jnp.asarray(u))
    out = render.render_image(structure, params, rays["origins"], rays["directions"],
                              near_t, far_t, render_cfg)
    pred = np.asarray(out["rgb_low"], np.float64)[..., 1]
    y = np.asarray(rays["target"], np.float64)[..., 1]
    ok = np.asarray(rays["mask"])[..., 1].min(axis=0) > 0  # both greens unsaturated
    r = (y - pred)[:, ok]
    views = int(data.c2w.shape[0])
    value, error = detail_over_noise(r[0], r[1], pred[:, ok].mean(axis=0))
    return views * value, views * error


# Multi-view reading (read_views): pairs of training frames `gap` apart, every EVERY-th
# pair; a point of frame a counts in frame b where b's own rendered point lies within
# DEPTH_TOL of its depth there (else b sees something else in front of it).
DEPTH_TOL = 0.03


def _frame(structure, params, data: dataset.RayData, f: int, near_t, far_t, render_cfg):
    """(residual (h, w, 3), valid (h, w, 3), world points (h, w, 3), point valid (h, w)) of
    training frame f on the binned lattice: the frame less the render; a mosaic's
    photosites binned 2x2 (raw.bin2x2), their points averaged."""
    h, w = data.image_hw
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    rays = dataset.rays_at_jit(data, jnp.full((h, w), f), jnp.asarray(v), jnp.asarray(u))
    out = render.render_image(structure, params, rays["origins"], rays["directions"],
                              near_t, far_t, render_cfg)
    pts, ok = consistency.world_points(out["depth"], out["acc"], np.asarray(rays["origins"]),
                                       np.asarray(rays["directions"]), data.ndc,
                                       np.asarray(data.ndc_intrinsics))
    m = np.asarray(rays["mask"], np.float64)
    r = (np.asarray(rays["target"], np.float64) - np.asarray(out["rgb_low"], np.float64)) * m
    if not data.mosaic:
        return r, m > 0, pts, ok
    cfa = np.asarray(data.cfa)
    res = raw.bin2x2(r.sum(-1), cfa, np.float64)
    valid = raw.bin2x2_mask(m.sum(-1) > 0, cfa)
    hb, wb = res.shape[:2]
    pts = pts[: 2 * hb, : 2 * wb].reshape(hb, 2, wb, 2, 3).mean(axis=(1, 3))
    ok = ok[: 2 * hb, : 2 * wb].reshape(hb, 2, wb, 2).all(axis=(1, 3))
    return res, valid, pts, ok


def shared_over_rest(ra, rb) -> tuple[float, float]:
    """(mean(ra rb) / (mean(ra^2) - mean(ra rb)), its standard error): the residual two
    views share over what they do not; each (n,) with its mean removed."""
    ra, rb = (np.asarray(a, np.float64) - np.mean(a) for a in (ra, rb))
    shared, total = float(np.mean(ra * rb)), float(np.mean(ra * ra))
    rest = total - shared
    if not ra.size or not rest > 0:
        return float("nan"), float("nan")
    return shared / rest, float(np.std(ra * rb)) / np.sqrt(ra.size) / rest


def read_views(structure, params, data: dataset.RayData, near_t, far_t, render_cfg,
               every: int = EVERY, gap: int = 1) -> tuple[float, float]:
    """(the detail the field leaves in its training frames that two views agree on, in
    units of the noise an ideal average of the training views leaves; its standard error).

    Each pair of training frames (a, b = a + gap), every `every`-th a: a's residual
    (frame - render, binned lattice) is carried to b along the points the field renders
    for a (bilinear in b's residual) where b sees the same point. Detail the field misses
    lies on the surface and moves with it, so a and b share it; their noise is
    independent. shared_over_rest over every channel and pair, times the views: 1 means
    the views agree on as much missed detail as their average leaves of the noise. Detail
    the field's depth cannot carry from one view to the next (finer than its
    reprojection) counts as noise: conservative, and detail a finer grid of the same
    geometry could not fit either. (nan, nan) under MIN_CELLS shared pixels.

    gap > 1 pairs views further apart. What the field cannot fit because it changes with
    the view (a glossy highlight: the path-traced captures have them, the simulator's
    surfaces are matte) is shared by neighbouring views and less by distant ones, while
    detail on a surface stays shared, less what the depth's reprojection error blurs
    (docs/results.md, "The views further apart")."""
    return read_views_at(structure, params, data, near_t, far_t, render_cfg, every,
                         (gap,))[gap]


def read_views_at(structure, params, data: dataset.RayData, near_t, far_t, render_cfg,
                  every: int = EVERY, gaps=(1,)) -> dict[int, tuple[float, float]]:
    """read_views at each of `gaps` (every one >= 1): {gap: (reading, standard error)},
    each frame rendered once whatever the number of gaps."""
    if min(gaps) < 1:
        raise ValueError(f"gap must be at least 1 (a frame paired with a later one), not "
                         f"{min(gaps)}")
    n = int(data.c2w.shape[0])
    c2w, intr = np.asarray(data.c2w, np.float64), np.asarray(data.intrinsics, np.float64)
    scale = 0.5 if data.mosaic else 1.0  # the binned lattice's intrinsics
    rendered = {}

    def frame(f):
        if f not in rendered:
            rendered[f] = _frame(structure, params, data, f, near_t, far_t, render_cfg)
        return rendered[f]

    out = {}
    for gap in gaps:
        ra_all, rb_all = [], []
        for a in range(0, n - gap, every):
            fa, fb = frame(a), frame(a + gap)
            hb, wb = fb[0].shape[:2]
            uv, ui, vi, ok = consistency.landing(fa[2], fa[3], fb[2], fb[3], c2w[a + gap],
                                                 intr[a + gap] * scale, DEPTH_TOL)
            u, v = uv[..., 0] - 0.5, uv[..., 1] - 0.5  # pixel centres at integers: bilinear
            ok &= (u >= 0) & (u <= wb - 1) & (v >= 0) & (v <= hb - 1)
            for c in range(3):
                sel = ok & fa[1][..., c] & fb[1][vi, ui, c]
                if sel.sum() < MIN_CELLS:
                    continue
                rb = map_coordinates(fb[0][..., c], [v[sel], u[sel]], order=1)
                ra = fa[0][..., c][sel]
                ra_all.append(ra - ra.mean())
                rb_all.append(rb - rb.mean())
        if not ra_all:
            out[gap] = (float("nan"), float("nan"))
            continue
        value, error = shared_over_rest(np.concatenate(ra_all), np.concatenate(rb_all))
        out[gap] = (n * value, n * error)
    return out
