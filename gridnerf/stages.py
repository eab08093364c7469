"""Coarse to fine: the grid a run starts from, the grid between training stages, and the
rays that decide it.

Training starts from a dense first-stage grid on the scene's box (initial_grid) and runs
one stage per resolution in grid.resolutions. Between stages the grid is
carved to what the training rays see, its box optionally refitted to the content, and
resampled to the next resolution (next_stage_grid; docs/method.md). Each stage's
step then tests only as many candidate voxels per ray as its training rays cross
(fitted_candidates), and shades only as many occupied samples per ray as nearly all of them
hold (fitted_samples). All of this walks the training rays in chunks (training_rays).
"""

from __future__ import annotations

from functools import partial

import jax
import numpy as np

from gridnerf import data_term, dataset, grid, render
from gridnerf.config import Config
from gridnerf.errors import NumericsError


def resolve_resolution(res, bbox_min, bbox_max, image_hw: tuple[int, int],
                       forward_facing: bool) -> tuple[int, int, int]:
    """Vertex counts of a stage: `res` (x, y, z), where y = 0 means "from the aspect".

    A y of 0 becomes the count that gives y voxels the footprint of x voxels: in NDC the
    box's x and y extents map to image pixels at W/2 and H/2 pixels per unit, so a 16:9
    frame gets y = 0.56 x on the full NDC box (a square grid would spend 1.8x the vertices
    on y for nothing); a world box uses the ratio of its extents.
    """
    rx, ry, rz = (int(r) for r in res)
    if ry > 0:
        return rx, ry, rz
    ext = np.asarray(bbox_max, np.float64) - np.asarray(bbox_min, np.float64)
    h, w = image_hw
    ratio = ext[1] * h / (ext[0] * w) if forward_facing else ext[1] / ext[0]
    return rx, max(2, int(round((rx - 1) * ratio)) + 1), rz


# margin on the longest training ray when fitting the candidate count (a batch ray's pixel
# may sit a fraction of a pixel off the fitted ones)
CANDIDATE_MARGIN = 1.05
# carving keeps this many vertices around the survivors of the weight threshold
PRUNE_DILATE = 1
# the box fitted after the first stage leaves this share of the rendered mass outside it at
# each end of each axis, with a margin of FIT_MARGIN first-stage voxels around the content
FIT_QUANTILE = 0.005
FIT_MARGIN = 2.0
# carving marches every CARVE_STRIDE-th pixel per axis of a capture CARVE_WIDTH pixels wide
# (480x270, where the carving was set) and as many rays per frame on a wider one
# (carving_stride; docs/speed.md, "Outside the training loop at 1920x1080")
CARVE_STRIDE, CARVE_WIDTH = 2, 480
INIT_DENSITY = -4.0  # raw density a grid starts from (softplus: sigma 0.018 per voxel)


def fitted_candidates(structure, data: dataset.RayData, near_t: float, far_t: float,
                      render_cfg) -> int:
    """The candidate count of a stage's step: render.fit_n_candidates over every training
    pixel, times CANDIDATE_MARGIN, at most the box diagonal's count (render.n_candidates).

    The box diagonal (192x118x64: 351 candidates per ray) is far more than a
    forward-facing NDC ray crosses (little more than the z voxels): every training ray
    keeps its full 1 / samples_per_voxel spacing either way, so the samples are the same
    and only the candidate test (occupancy lookups, running count, search) shrinks.
    Image renders fit the count to their own rays (render.image_candidates).
    """
    longest = max(render.fit_n_candidates(structure, oc, dc, near_t, far_t,
                                          render_cfg.samples_per_voxel)
                  for oc, dc, _ in training_rays(data, 1 << 16, stride=1))
    return min(int(np.ceil(longest * CANDIDATE_MARGIN)) + 1,
               render.n_candidates(structure, render_cfg))


# the occupied-sample slots per ray are fitted in steps of this many (a handful of shapes)
SAMPLE_QUANTUM = 8
# fitted_samples marches every this-many-th training pixel per axis (a 480x270 capture's
# last stage: 2.7M photosites, 42k rays marched)
SAMPLE_STRIDE = 8


def fitted_samples(structure, data: dataset.RayData, near_t: float, far_t: float,
                   render_cfg, n_cand: int) -> int:
    """The occupied-sample slots K per ray of a stage's step: the (1 - truncated_share)
    quantile of the occupied samples its training rays hold on the stage's grid (every
    SAMPLE_STRIDE-th pixel per axis, render.march's n_occupied on the current occupancy),
    rounded up to a multiple of SAMPLE_QUANTUM, at most render.max_samples;
    render.max_samples where render.truncated_share is 0. (render.march shades at most
    n_cand slots whatever K is.)

    Why: the step gathers and scatters K slots per ray whether occupied or not (fixed
    shapes). On a carved final grid of a shallow scene nearly every ray holds fewer than 48
    (bucket: 0.18 % more) and 48 slots take 15 % off the step; a deep scene's rays hold
    more (dev_arc_shop: 10 % above 48, 4 % above 64), and cutting them off cost it 0.10 dB.
    The quantile keeps K where the rays need it (docs/speed.md, "Slots fitted to the
    rays")."""
    cap = int(render_cfg.max_samples)
    share = float(render_cfg.truncated_share)
    if share <= 0.0:
        return cap
    march = jax.jit(render.march, static_argnames=("cfg", "n_cand"))
    counts = []
    for oc, dc, n in training_rays(data, int(render_cfg.chunk), stride=SAMPLE_STRIDE):
        counts.append(np.asarray(march(structure, oc, dc, near_t, far_t, render_cfg,
                                       n_cand=n_cand)[3])[:n])
    occupied = np.concatenate(counts)
    if occupied.size == 0:
        return cap
    need = float(np.quantile(occupied, 1.0 - share, method="higher"))
    k = SAMPLE_QUANTUM * max(1, int(np.ceil(need / SAMPLE_QUANTUM)))
    return min(k, cap)


@partial(jax.jit, static_argnames=("hw", "stride", "ndc"))
def _frame_rays(c2w, intrinsics, ndc_intrinsics, hw: tuple[int, int], stride: int, ndc: bool):
    """Grid-space rays (h', w', 3) each of every `stride`-th pixel per axis of one frame."""
    o, d = dataset.image_rays(c2w, intrinsics, *hw)
    return dataset.to_grid_space(ndc, ndc_intrinsics, o[::stride, ::stride],
                                 d[::stride, ::stride])


def training_rays(data: dataset.RayData, chunk: int, stride: int = 2):
    """Every `stride`-th pixel per axis of each training frame as grid-space rays, in padded
    chunks (origins, directions, n_real): (chunk, 3) each, the first n_real real; padding
    rays start far outside the box, so they miss it and weigh nothing."""
    for f in range(int(data.c2w.shape[0])):
        o, d = _frame_rays(data.c2w[f], data.intrinsics[f], data.ndc_intrinsics,
                           tuple(data.image_hw), stride, bool(data.ndc))
        o, d = np.asarray(o).reshape(-1, 3), np.asarray(d).reshape(-1, 3)
        for s in range(0, o.shape[0], chunk):
            sl = slice(s, s + chunk)
            pad = chunk - o[sl].shape[0]
            yield (np.pad(o[sl], ((0, pad), (0, 0)), constant_values=1e6),
                   np.pad(d[sl], ((0, pad), (0, 0)), mode="edge"), chunk - pad)


def vertex_visibility(structure, params, data: dataset.RayData, cfg: Config, near_t: float,
                      far_t: float, stride: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex (M,) over the training rays (every `stride`-th pixel per axis): max and
    sum of the rendering weights (render.vertex_visibility): the carving criterion and
    where the mass is. Accumulated per cell over the chunks, spread to the rows once."""
    fn = jax.jit(render.cell_visibility, static_argnames=("cfg", "n_cand"))
    chunk = int(cfg.render.chunk)
    # the rays' own candidate count (render.fit_n_candidates): the same samples as the box
    # diagonal's count, a fraction of the candidates tested. The rays are generated again
    # below rather than kept (a full-size mosaic's would be hundreds of MB).
    n_cand = max(render.fit_n_candidates(structure, oc, dc, near_t, far_t,
                                         cfg.render.samples_per_voxel)
                 for oc, dc, _ in training_rays(data, chunk, stride))
    c_max = c_sum = None
    for oc, dc, _ in training_rays(data, chunk, stride):
        v_max, v_sum = fn(structure, params, oc, dc, near_t, far_t, cfg.render, n_cand=n_cand)
        v_max, v_sum = np.asarray(v_max), np.asarray(v_sum, np.float64)
        c_max = v_max if c_max is None else np.maximum(c_max, v_max)
        c_sum = v_sum if c_sum is None else c_sum + v_sum
    return render.cells_to_vertices(structure, c_max, c_sum)


def carving_stride(width: int, mosaic: bool) -> int:
    """The pixel stride of the carving's rays on training frames `width` pixels wide (the
    raw mosaic's photosites where `mosaic`, else binned or downscaled pixels): CARVE_STRIDE
    times the frames' width over the width a CARVE_WIDTH capture's frames have in the same
    form (CARVE_WIDTH photosites, CARVE_WIDTH / 2 binned pixels), rounded, at least 1. So
    every capture is carved by about the rays per frame, and a stage's voxels by the rays
    each, of the 480x270 captures the carving was set on."""
    reference = CARVE_WIDTH if mosaic else CARVE_WIDTH / 2
    return CARVE_STRIDE * max(1, int(round(int(width) / reference)))


def next_stage_grid(structure, params, res, data, cfg: Config, near_t, far_t, fit: bool,
                    forward_facing: bool = True):
    """Carve, optionally refit the box to the content, and resample to resolution `res`
    (a y of 0 is resolved on the new box, see resolve_resolution), judged on every
    carving_stride-th training pixel per axis.

    Carving keeps the vertices some training ray weighs by more than grid.prune_threshold,
    dilated by PRUNE_DILATE; the fitted box leaves FIT_QUANTILE of the rendered mass out at
    each end (grid.content_box). Returns (structure, params, info) with info = box and
    occupancy figures.
    """
    gc = cfg.grid
    stride = carving_stride(data.image_hw[1], bool(data.mosaic))
    vis, mass = vertex_visibility(structure, params, data, cfg, near_t, far_t, stride)
    keep = grid.dilate_rows(structure, vis > gc.prune_threshold, PRUNE_DILATE)
    if not keep.any() or not mass.sum() > 0:
        raise NumericsError(None, "the coarse grid is empty: no vertex is visible from the "
                            "training views", "check the poses and the frames' exposure")
    lo, hi = np.asarray(structure.bbox_min), np.asarray(structure.bbox_max)
    if fit:  # in the box's own dtype
        fit_lo, fit_hi = grid.content_box(structure, mass, FIT_QUANTILE, margin=FIT_MARGIN)
        lo, hi = lo.copy(), hi.copy()
        lo[:], hi[:] = fit_lo, fit_hi
    old_box = np.prod(np.asarray(structure.bbox_max) - np.asarray(structure.bbox_min))
    structure, params = grid.prune(structure, params, keep)
    res = resolve_resolution(res, lo, hi, data.image_hw, forward_facing)
    structure, params = grid.resample(structure, params, res, lo, hi)
    info = {"bbox_min": np.asarray(lo).tolist(), "bbox_max": np.asarray(hi).tolist(),
            "box_fraction_of_previous": float(np.prod(hi - lo) / old_box),
            "occupied_fraction": structure.n_rows / float(np.prod(res)),
            "resolution": res}
    return structure, params, info


def initial_grid(data: dataset.RayData, scene, cfg: Config, key, init_log_gain):
    """(structure, params) a run starts from: the dense first-stage grid on the scene's box,
    colour at the data's mean level, the backdrop of grid.background. init_log_gain:
    (color_scale, grey-world log gains (3,)) -> the log gains (3,) the field starts at
    (the method's: gridnerf.methods)."""
    bbox_min, bbox_max, near_t, _ = dataset.grid_box(scene)
    color_scale, log_gain, mean_colour = data_term.data_statistics(data, jax.random.fold_in(key, 1))
    log_gain = init_log_gain(color_scale, log_gain)
    background = grid.BLACK
    if cfg.grid.background == "mean":  # the capture's mean colour, at the gains' start
        background = np.stack([mean_colour, np.exp(log_gain)])
    return grid.init_grid(
        resolve_resolution(cfg.grid.resolutions[0], bbox_min, bbox_max, data.image_hw,
                           scene.forward_facing),
        bbox_min, bbox_max, sh_degree=cfg.grid.sh_degree, init_density=INIT_DENSITY,
        init_log_gain=log_gain, color_scale=color_scale, background=background,
        key=jax.random.fold_in(key, 2))
