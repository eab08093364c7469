"""Ray marching through the sparse grid with empty-space skipping, and compositing.

Rays are given in the grid's coordinate space (NDC rays with t in [0, 1] for
forward-facing scenes, or world rays with near/far). Marching happens in index space
(see grid.py), where one unit is one voxel on every axis:

1. clip the ray to the box and to [near_t, far_t];
2. place N candidate samples at the midpoints of equal steps of
   max(1 / samples_per_voxel, segment / N) voxels (N is static);
3. test each candidate against the occupancy bitmask (one cheap gather) and keep the
   first K = max_samples occupied ones per ray (fixed shapes for jit);
4. trilinear lookup (one flat gather) and activations for the K kept samples only;
5. composite with alpha_i = 1 - exp(-sigma_i * step_i), step in voxels: every kept sample
   carries its own step, so dropping empty candidates changes nothing (exact skipping).

Rays with more than K occupied candidates are truncated after the K-th (`n_occupied` in
the output says how many there were). Options are gridnerf.config.RenderConfig (static
under jit): samples_per_voxel, max_samples (K), chunk, skip_empty. The candidate count N is
a separate static argument `n_cand` (0: the box diagonal's count); render_image fits it to
its own rays and training to each stage's training rays (the run plan keeps it).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from gridnerf import devices
from gridnerf import grid as gridlib
from gridnerf.config import RenderConfig
from gridnerf.grid import GridStructure

_TINY = 1e-12


def n_candidates(structure: GridStructure, cfg: RenderConfig, n_cand: int = 0) -> int:
    """Static candidate count N: n_cand, or (0) the box diagonal in voxels x spv."""
    if n_cand:
        return int(n_cand)
    diag = math.sqrt(sum((r - 1) ** 2 for r in structure.resolution))
    return int(math.ceil(diag * float(cfg.samples_per_voxel)))


def fit_n_candidates(structure: GridStructure, origins, directions, near_t, far_t,
                     samples_per_voxel: float, chunk: int = 1 << 16) -> int:
    """Smallest static N that gives every one of these rays its full 1/spv spacing.

    origins, directions: (n, 3) (e.g. all training rays, host arrays); near_t, far_t: scalars
    or (n,). Forward-facing NDC rays cross ~Rz voxels, far fewer than the box diagonal that
    n_candidates() assumes, so this saves candidate work; pass it as n_cand.
    """
    o, d = np.asarray(origins, np.float32), np.asarray(directions, np.float32)
    near = np.broadcast_to(np.asarray(near_t, np.float32), o.shape[:1])
    far = np.broadcast_to(np.asarray(far_t, np.float32), o.shape[:1])
    longest = 0.0
    for s in range(0, o.shape[0], chunk):
        sl = slice(s, s + chunk)
        if o[sl].shape[0]:
            longest = max(longest, float(_longest_segment(structure, o[sl], d[sl], near[sl],
                                                          far[sl])))
    return max(1, int(math.ceil(longest * samples_per_voxel)))


@jax.jit
def _longest_segment(structure: GridStructure, origins, directions, near_t, far_t):
    """The longest of these rays' segments inside the box, in voxels (0 if all miss)."""
    return jnp.max(_ray_segments(structure, origins, directions, near_t, far_t, 1, 1.0)[5])


def _ray_segments(structure: GridStructure, origins, directions, near_t, far_t, n_cand, spv):
    """Index-space rays and their candidate spacing.

    Returns o_u (n,3), d_u (n,3), t_enter (n,), dt (n,) in t units, step_vox (n,) in voxels,
    seg_vox (n,) in voxels (0 for a miss).
    """
    hi = jnp.asarray(structure.resolution, jnp.float32) - 1.0
    scale = hi / (structure.bbox_max - structure.bbox_min)
    o_u = (origins - structure.bbox_min) * scale
    d_u = directions * scale
    d_safe = jnp.where(jnp.abs(d_u) < _TINY, _TINY, d_u)
    t0, t1 = (0.0 - o_u) / d_safe, (hi - o_u) / d_safe
    t_enter = jnp.maximum(jnp.max(jnp.minimum(t0, t1), axis=-1), near_t)
    t_exit = jnp.minimum(jnp.min(jnp.maximum(t0, t1), axis=-1), far_t)
    speed = jnp.maximum(jnp.linalg.norm(d_u, axis=-1), _TINY)  # voxels per unit t
    seg_vox = jnp.where(t_exit > t_enter, (t_exit - t_enter) * speed, 0.0)
    step_vox = jnp.maximum(1.0 / spv, seg_vox / n_cand)
    t_enter = jnp.where(seg_vox > 0.0, t_enter, 0.0)
    return o_u, d_u, t_enter, step_vox / speed, step_vox, seg_vox


def _first_k(occupied: jax.Array, k: int) -> jax.Array:
    """(n, N) bool -> (n, k) int32 candidate ids of the first k True entries, N = none.

    Binary search of the running count (measured 2-3x faster than a scatter, 15x faster
    than top_k on 2 CPU cores for 4096 x 381 -> 64). As a loop ("scan"), not unrolled: XLA
    fuses an unrolled search into each of its consumers, so the 8 corner lookups of every
    sample ran it 8 times (13 of bucket's 77 ms per training step, in a profile); the
    loop's result is computed once (the same ids; docs/speed.md).
    """
    count = jnp.cumsum(occupied, axis=1, dtype=jnp.int32)
    want = jnp.arange(1, k + 1, dtype=jnp.int32)
    find = jax.vmap(lambda c: jnp.searchsorted(c, want, side="left", method="scan"))
    return find(count).astype(jnp.int32)


def _occupied(structure: GridStructure, u: jax.Array) -> jax.Array:
    """(..., 3) index-space points -> (...,) bool from the occupancy bitmask."""
    rx, ry, rz = structure.resolution
    cell = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, jnp.asarray([rx - 2, ry - 2, rz - 2]))
    b = cell // structure.occ_factor
    bx, by, bz = structure.occupancy.shape
    return structure.occupancy.reshape(-1)[(b[..., 0] * by + b[..., 1]) * bz + b[..., 2]]


def composite(sigma, step_vox, values: dict) -> tuple[jax.Array, dict]:
    """Weights w_i = T_i alpha_i and weighted sums.

    sigma: (n, K) per voxel; step_vox: (n, K) voxels (0 for invalid samples);
    values: name -> (n, K, ...) -> (w (n, K), name -> (n, ...)).
    """
    tau = sigma * step_vox
    alpha = 1.0 - jnp.exp(-tau)
    trans = jnp.exp(-(jnp.cumsum(tau, axis=-1) - tau))
    w = trans * alpha
    return w, {k: jnp.einsum("nk,nk...->n...", w, v) for k, v in values.items()}


def march(structure: GridStructure, origins, directions, near_t, far_t, cfg, key=None,
          n_cand: int = 0):
    """Sample placement with empty-space skipping (steps 1-3 of the module docstring).

    origins, directions: (n, 3) grid coordinates; near_t, far_t: scalars or (n,).
    Returns u (n, K, 3) index-space points (unused slots parked at 0), t (n, K) ray
    parameters, step (n, K) voxels (0 for unused slots), n_occupied (n,) int32.
    """
    n = origins.shape[0]
    n_cand = n_candidates(structure, cfg, n_cand)
    spv = float(cfg.samples_per_voxel)
    near_t = jnp.broadcast_to(jnp.asarray(near_t, jnp.float32), (n,))
    far_t = jnp.broadcast_to(jnp.asarray(far_t, jnp.float32), (n,))
    o_u, d_u, t_enter, dt, step_vox, seg_vox = _ray_segments(
        structure, origins, directions, near_t, far_t, n_cand, spv)
    offset = (jnp.full((n,), 0.5) if key is None
              else jax.random.uniform(key, (n,), jnp.float32))
    pos = jnp.arange(n_cand, dtype=jnp.float32)[None, :] + offset[:, None]  # (n, N) in steps
    inside = pos * step_vox[:, None] < seg_vox[:, None]
    if cfg.skip_empty:
        t_cand = t_enter[:, None] + pos * dt[:, None]
        u_cand = o_u[:, None, :] + t_cand[..., None] * d_u[:, None, :]
        occupied = inside & _occupied(structure, u_cand)
        k = min(int(cfg.max_samples), n_cand)
        cand = _first_k(occupied, k)
        valid = cand < n_cand
        n_occupied = jnp.sum(occupied, axis=1, dtype=jnp.int32)
        pos = cand.astype(jnp.float32) + offset[:, None]
    else:
        valid = inside
        n_occupied = jnp.sum(inside, axis=1, dtype=jnp.int32)
    t = t_enter[:, None] + pos * dt[:, None]  # (n, K)
    u = o_u[:, None, :] + t[..., None] * d_u[:, None, :]
    u = jnp.where(valid[..., None], u, 0.0)  # park unused slots on one cell: ~25% faster
    return u, t, jnp.where(valid, step_vox[:, None], 0.0), n_occupied


def render_rays(structure: GridStructure, params, origins, directions, near_t, far_t, cfg,
                key=None, n_cand: int = 0) -> dict:
    """Render rays through the grid.

    origins, directions: (n, 3) grid coordinates (directions need not be unit);
    near_t, far_t: scalars or (n,); cfg: RenderConfig (static under jit);
    key: optional PRNG key -> one random offset per ray for the candidate grid (training);
    n_cand: static candidate count (0: the box diagonal's, n_candidates).
    Returns rgb_low (n,3) low-light camera RGB, gain (n,3) = sum w s, rgb_restored (n,3) =
    sum w c_l s, depth (n,) expected t (not divided by acc), acc (n,), n_occupied (n,) int32,
    and per sample (n, K): `weights` w_i, `s_vox` position along the ray in voxels from the
    first sample, `step_vox` interval length in voxels (0 for unused slots),
    `gain_samples` (n, K, 3) the gains s_i (frozen_density_gain), `rgb_samples` (n, K, 3)
    the low-light colours c_i and `points` (n, K, 3) the samples in index space
    (gridnerf.colour_solve). Outputs a jitted caller does not use cost nothing.
    """
    u, t, step, n_occupied = march(structure, origins, directions, near_t, far_t, cfg, key,
                                   n_cand)
    table = gridlib.feature_table(structure, params, pad_to=8)
    feats = gridlib.trilinear_index_space(structure, table, u)[..., : structure.n_channels]
    unit_dirs = directions / jnp.maximum(jnp.linalg.norm(directions, axis=-1, keepdims=True),
                                         _TINY)
    sigma, rgb_low, gain = gridlib.decode(structure, feats, unit_dirs[:, None, :])
    w, sums = composite(sigma, step, {"rgb_low": rgb_low, "gain": gain,
                                      "rgb_restored": rgb_low * gain, "depth": t})
    acc = jnp.sum(w, axis=-1)
    sums = composite_background(structure, sums, acc)
    scale = (jnp.asarray(structure.resolution, jnp.float32) - 1.0) / (
        structure.bbox_max - structure.bbox_min)
    speed = jnp.linalg.norm(directions * scale, axis=-1, keepdims=True)  # voxels per unit t
    return {**sums, "acc": acc, "n_occupied": n_occupied, "weights": w,
            "s_vox": (t - t[:, :1]) * speed, "step_vox": step, "gain_samples": gain,
            "rgb_samples": rgb_low, "points": u}


def frozen_density_gain(out: dict) -> tuple[jax.Array, jax.Array]:
    """(gain (n, 3), acc (n,)) of a render_rays output composited with stop-gradient
    weights: sum sg(w_i) s_i and sg(acc). What a prior on the gain field (L_ca, the
    smoothness, LLNeRF's enhancement losses) computes from these can never move the
    geometry. Equal to rendering the rays again with stop-gradient density (same samples),
    without a second march, gather and backward pass."""
    w = jax.lax.stop_gradient(out["weights"])
    return jnp.einsum("nk,nkc->nc", w, out["gain_samples"]), jax.lax.stop_gradient(out["acc"])


def composite_background(structure: GridStructure, sums: dict, acc) -> dict:
    """Add the backdrop behind the grid: rgb_low += (1 - acc) b, rgb_restored += (1 - acc)
    b g with (b, g) = structure.background; `gain` and `depth` are the grid's alone.

    sums: rgb_low, rgb_restored (n, 3) (composite's sums); acc: (n,). With a grey backdrop
    a ray that ends on nothing shows the capture's mean colour, so dark texture cannot be
    rendered as transparency for free (grid.background)."""
    rest = (1.0 - acc)[:, None]
    low, gain = structure.background[0], structure.background[1]
    return {**sums, "rgb_low": sums["rgb_low"] + rest * low,
            "rgb_restored": sums["rgb_restored"] + rest * (low * gain)}


def cell_visibility(structure: GridStructure, params, origins, directions, near_t, far_t,
                    cfg, n_cand: int = 0) -> tuple[jax.Array, jax.Array]:
    """Per cell ((Rx-1)(Ry-1)(Rz-1),): the largest rendering weight w_i = T_i alpha_i any of
    these rays gives a sample in it, and the sum of those weights. n_cand: static candidate
    count as in march (fit_n_candidates of these rays: the same samples as the box
    diagonal's count, fewer candidates tested). One scatter per sample, where scattering
    to the 8 corner rows took 8 (grid.cells_to_rows spreads the cells to the vertices)."""
    u, _, step, _ = march(structure, origins, directions, near_t, far_t, cfg, n_cand=n_cand)
    table = gridlib.feature_table(structure, params, pad_to=8)
    feats = gridlib.trilinear_index_space(structure, table, u)[..., : structure.n_channels]
    w, _ = composite(jax.nn.softplus(feats[..., 0]), step, {})
    w = jnp.where(step > 0, w, 0.0).reshape(-1)
    cells = gridlib.cell_ids(structure, u).reshape(-1)
    zeros = jnp.zeros((math.prod(r - 1 for r in structure.resolution),), jnp.float32)
    return zeros.at[cells].max(w), zeros.at[cells].add(w)


def vertex_visibility(structure: GridStructure, params, origins, directions, near_t, far_t,
                      cfg, n_cand: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex (M,): the largest rendering weight w_i = T_i alpha_i any of these rays
    gives a sample in a cell touching it (svox2's weight-threshold pruning criterion: free
    space and everything hidden behind surfaces score ~0), and the sum of those weights over
    8 (where the rendered mass is; a floater that serves one view holds little of it).
    cell_visibility, spread to the rows (grid.cells_to_rows)."""
    return cells_to_vertices(structure, *cell_visibility(
        structure, params, origins, directions, near_t, far_t, cfg, n_cand))


def cells_to_vertices(structure: GridStructure, c_max, c_sum) -> tuple[np.ndarray, np.ndarray]:
    """cell_visibility's (max, sum) per cell -> vertex_visibility's (max, sum / 8) per row."""
    return (gridlib.cells_to_rows(structure, np.asarray(c_max), "max"),
            gridlib.cells_to_rows(structure, np.asarray(c_sum, np.float64), "sum") / 8.0)


# per-sample outputs of render_rays, (n, K) each: needed by losses, not by images (at
# 1920x1080 and K = 64 they are 1.6 GB per view; docs/speed.md)
PER_SAMPLE = ("weights", "s_vox", "step_vox", "gain_samples", "rgb_samples", "points")


def _render_pixels(structure, params, origins, directions, near_t, far_t, cfg, n_cand):
    out = render_rays(structure, params, origins, directions, near_t, far_t, cfg, n_cand=n_cand)
    return {k: v for k, v in out.items() if k not in PER_SAMPLE}


_render_jit = jax.jit(_render_pixels, static_argnames=("cfg", "n_cand"))

# an image render's fitted candidate count is rounded up to a multiple of this, so a path of
# views compiles a handful of shapes rather than one per view
CANDIDATE_QUANTUM = 32


def image_candidates(structure: GridStructure, cfg: RenderConfig, origins, directions, near_t,
                     far_t) -> int:
    """The candidate count n_cand of an image render, fitted to its rays.

    origins, directions: (n, 3); near_t, far_t: scalars or (n,). The box diagonal's count
    (bucket's 192x113x64 grid: 346 candidates) is far more than a forward-facing view's
    longest ray crosses (bucket's test view: 114). Every ray keeps its full
    1 / samples_per_voxel spacing with either count, so the samples, and the image, are the
    same; only the candidate test shrinks (bucket, 480x270: march 0.95 -> 0.36 s of a
    1.7 s render on a loaded machine). Rounded up to CANDIDATE_QUANTUM, never above the
    box diagonal's count.
    """
    auto = n_candidates(structure, cfg)
    n = fit_n_candidates(structure, origins, directions, near_t, far_t, cfg.samples_per_voxel)
    n = -(-n // CANDIDATE_QUANTUM) * CANDIDATE_QUANTUM
    return min(n, auto)


def render_image(structure: GridStructure, params, origins, directions, near_t, far_t, cfg,
                 chunk: int | None = None) -> dict:
    """Chunked render of (H, W, 3) rays -> dict of (H, W, ...) numpy arrays: the per-ray
    outputs of render_rays (rgb_low, gain, rgb_restored, acc, depth, n_occupied), not the
    per-sample ones (PER_SAMPLE), which never leave the device.

    near_t, far_t: scalars or (H, W). One jit per chunk shape: the last chunk is padded.
    The candidate count is fitted to the image's rays (image_candidates).
    Each chunk is split over all local devices (gridnerf.devices).
    """
    shape = origins.shape[:-1]
    chunk = int(chunk or cfg.chunk)
    o = np.asarray(origins, np.float32).reshape(-1, 3)
    d = np.asarray(directions, np.float32).reshape(-1, 3)
    near = np.broadcast_to(np.asarray(near_t, np.float32), shape).reshape(-1)
    far = np.broadcast_to(np.asarray(far_t, np.float32), shape).reshape(-1)
    n = o.shape[0]
    n_cand = image_candidates(structure, cfg, o, d, near, far)
    n_dev = devices.device_count()
    chunk = -(-max(1, min(chunk, n)) // n_dev) * n_dev  # chunks split evenly over devices
    outs: dict[str, list] = {}
    for start in range(0, n, chunk):
        sl = slice(start, min(start + chunk, n))
        pad = chunk - (sl.stop - sl.start)
        args = devices.put_rays(*[np.pad(a[sl], [(0, pad)] + [(0, 0)] * (a.ndim - 1),
                                          mode="edge") for a in (o, d, near, far)])
        res = _render_jit(structure, params, *args, cfg=cfg, n_cand=n_cand)
        for name, v in res.items():
            outs.setdefault(name, []).append(np.asarray(v)[: chunk - pad])
    return {k: np.concatenate(v, 0).reshape(*shape, *v[0].shape[1:]) for k, v in outs.items()}


def render_rays_reference(structure: GridStructure, params, origins, directions, near_t, far_t,
                          cfg, n_cand: int = 0) -> dict:
    """Slow float64 reference: every candidate shaded (no skipping), own trilinear, loops.

    Same candidate placement as render_rays with key=None and the same n_cand. For tests
    on small inputs.
    """
    res = np.asarray(structure.resolution)
    index = np.asarray(structure.index)
    m = structure.n_rows
    dens = np.asarray(params["density"], np.float64)
    rgb = np.asarray(params["rgb"], np.float64).reshape(m, 3, -1)
    lg = np.asarray(params["log_gain"], np.float64)
    lo, hi = np.asarray(structure.bbox_min, np.float64), np.asarray(structure.bbox_max, np.float64)
    n_cand = n_candidates(structure, cfg, n_cand)
    spv = float(cfg.samples_per_voxel)
    origins, directions = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
    n = origins.shape[0]
    near = np.broadcast_to(np.asarray(near_t, np.float64), (n,))
    far = np.broadcast_to(np.asarray(far_t, np.float64), (n,))
    out = {k: np.zeros((n, 3)) for k in ("rgb_low", "gain", "rgb_restored")}
    out.update(depth=np.zeros(n), acc=np.zeros(n))

    def vertex_features(ijk):
        row = index[tuple(ijk)]
        if row == m:
            return gridlib.EMPTY_DENSITY_RAW, np.zeros(rgb.shape[1:]), np.zeros(3)
        return dens[row], rgb[row], lg[row]

    for r in range(n):
        o_u = (origins[r] - lo) / (hi - lo) * (res - 1)
        d_u = directions[r] / (hi - lo) * (res - 1)
        t_in, t_out = near[r], far[r]
        for a in range(3):
            if abs(d_u[a]) < _TINY:
                if not 0.0 <= o_u[a] <= res[a] - 1:
                    t_out = -np.inf
                continue
            ta, tb = -o_u[a] / d_u[a], (res[a] - 1 - o_u[a]) / d_u[a]
            t_in, t_out = max(t_in, min(ta, tb)), min(t_out, max(ta, tb))
        speed = np.linalg.norm(d_u)
        if not t_out > t_in or speed < _TINY:
            continue
        seg = (t_out - t_in) * speed
        step = max(1.0 / spv, seg / n_cand)
        unit = directions[r] / np.linalg.norm(directions[r])
        basis = np.asarray(gridlib.sh_basis(jnp.asarray(unit, jnp.float32),
                                            structure.sh_degree), np.float64)
        trans = 1.0
        for i in range(n_cand):
            if (i + 0.5) * step >= seg:
                break
            t = t_in + (i + 0.5) * step / speed
            u = np.clip(o_u + t * d_u, 0.0, res - 1)
            base = np.minimum(np.floor(u).astype(int), res - 2)
            f = u - base
            d_raw, c_raw, g_raw = 0.0, np.zeros(rgb.shape[1:]), np.zeros(3)
            for corner in np.ndindex(2, 2, 2):
                wgt = np.prod([f[a] if corner[a] else 1.0 - f[a] for a in range(3)])
                vd, vc, vg = vertex_features(base + np.asarray(corner))
                d_raw, c_raw, g_raw = d_raw + wgt * vd, c_raw + wgt * vc, g_raw + wgt * vg
            sigma = np.logaddexp(0.0, d_raw)
            c_low = structure.color_scale * np.logaddexp(0.0, c_raw @ basis)
            gain = np.exp(np.clip(g_raw, -30.0, 30.0))
            alpha = 1.0 - np.exp(-sigma * step)
            w = trans * alpha
            trans *= 1.0 - alpha
            out["rgb_low"][r] += w * c_low
            out["gain"][r] += w * gain
            out["rgb_restored"][r] += w * c_low * gain
            out["depth"][r] += w * t
            out["acc"][r] += w
    back = np.asarray(structure.background, np.float64)  # every ray, those missing the box too
    rest = (1.0 - out["acc"])[:, None]
    out["rgb_low"] += rest * back[0]
    out["rgb_restored"] += rest * back[0] * back[1]
    return out
