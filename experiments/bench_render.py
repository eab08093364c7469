"""Throughput of the package's training step (train.make_step) on this CPU.

A synthetic forward-facing scene in NDC: a 128 x 128 x 64 vertex grid on [-1, 1]^3 holding
a back wall and a few spheres, pruned and with a density occupancy bitmask, seen by three
512 x 512 pinhole cameras (dataset.RayData built from synthetic arrays: constant targets).
Each step is the training step itself: dataset.batch (64 patches of 8 x 8 adjacent pixels,
4096 rays) -> train.loss_fn (the default preset's loss terms and weights) -> the default
optimiser. Prints one table row per (sh_degree, skipping, candidate count) setting: N
candidates per ray (fitted to the rays with render.fit_n_candidates, or the box diagonal),
K shaded; the occupied-candidate statistics come from a forward render of one batch.

Run: LD_PRELOAD=/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4 \
     .venv/bin/python experiments/bench_render.py
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from gridnerf import config as cfgmod
from gridnerf import dataset, grid, render, train

IMAGE = 512  # side of the synthetic views (pixels)


def synthetic_scene(resolution, sh_degree: int, seed: int = 0):
    """(structure, params): wall at z ~ 0.7 and spheres, pruned, occupancy updated."""
    structure, params = grid.init_grid(resolution, -np.ones(3), np.ones(3), sh_degree=sh_degree,
                                       color_scale=5e-3)
    res = np.asarray(resolution)
    pos = np.asarray(structure.coords) / (res - 1) * 2.0 - 1.0
    solid = np.abs(pos[:, 2] - 0.7) < 0.06
    rng = np.random.default_rng(seed)
    for _ in range(6):
        c = rng.uniform([-0.7, -0.7, -0.4], [0.7, 0.7, 0.4])
        solid |= np.linalg.norm(pos - c, axis=1) < rng.uniform(0.1, 0.25)
    params["density"] = jnp.asarray(np.where(solid, 3.0, -12.0), jnp.float32)
    params["rgb"] = params["rgb"] + 0.3 * jnp.asarray(
        rng.standard_normal(params["rgb"].shape), jnp.float32)
    keep = grid.density_keep_mask(structure, params, threshold=1e-3, dilate=1)
    structure, params = grid.prune(structure, params, keep)
    structure = grid.update_occupancy(structure, params, threshold=1e-4)
    return structure, params


def synthetic_views(n_frames: int = 3, level: float = 5e-3) -> dataset.RayData:
    """Binned RayData of n_frames IMAGE x IMAGE views from cameras at the origin shifted
    along x (looking down -z, NDC on), with constant targets `level`, all valid."""
    c2w = np.tile(np.eye(3, 4, dtype=np.float32), (n_frames, 1, 1))
    c2w[:, 0, 3] = np.linspace(-0.1, 0.1, n_frames)
    f = float(IMAGE)
    pixels = np.full((n_frames, IMAGE, IMAGE, 3), level, np.float32)
    return dataset.RayData(
        c2w=jnp.asarray(c2w),
        intrinsics=jnp.asarray(np.tile([f, f, IMAGE / 2, IMAGE / 2], (n_frames, 1)), jnp.float32),
        ndc_intrinsics=jnp.asarray([f, f, IMAGE, IMAGE], jnp.float32),
        pixels=jnp.asarray(pixels), valid=jnp.ones(pixels.shape, bool),
        black=jnp.zeros((n_frames, 2, 2), jnp.float32), white=jnp.ones(n_frames, jnp.float32),
        inv_exposure=jnp.ones(n_frames, jnp.float32), cfa=jnp.asarray([[0, 1], [1, 2]]),
        mosaic=False, ndc=True)


def bench(sh_degree: int, skip: bool, fitted: bool, k: int, args) -> dict:
    structure, params = synthetic_scene(tuple(args.resolution), sh_degree)
    data = synthetic_views()
    near_t, far_t = 0.0, 1.0
    # fitted: N from the longest ray of the first full view; else the box diagonal
    o_all, d_all = dataset.image_rays(data.c2w[0], data.intrinsics[0], IMAGE, IMAGE)
    o_all, d_all = dataset.to_grid_space(True, data.ndc_intrinsics, o_all, d_all)
    base = cfgmod.preset("default")
    render_cfg = dataclasses.replace(base.render, samples_per_voxel=args.spv, max_samples=k,
                                     skip_empty=skip, n_candidates=0)
    if fitted:
        render_cfg = dataclasses.replace(render_cfg, n_candidates=render.fit_n_candidates(
            structure, o_all.reshape(-1, 3), d_all.reshape(-1, 3), near_t, far_t, args.spv))
    cfg = dataclasses.replace(
        base, grid=dataclasses.replace(base.grid, sh_degree=sh_degree), render=render_cfg,
        train=dataclasses.replace(base.train, batch_patches=args.patches,
                                  patch_size=args.patch))
    n_cand = render.n_candidates(structure, render_cfg)
    tx = train.make_optimizer(cfg, args.iters + 1)
    step = train.make_step(cfg, tx, near_t, far_t)
    opt_state = tx.init(params)
    params, opt_state, loss, _ = step(params, opt_state, structure, data, jax.random.PRNGKey(0))
    jax.block_until_ready(loss)
    times = []
    for i in range(args.iters):
        t0 = time.perf_counter()
        params, opt_state, loss, _ = step(params, opt_state, structure, data,
                                          jax.random.PRNGKey(i + 1))
        jax.block_until_ready((params, loss))
        times.append(time.perf_counter() - t0)
    sec = float(np.median(times))
    rays = dataset.batch(data, jax.random.PRNGKey(args.iters + 1), args.patches, args.patch)
    flat = {name: rays[name].reshape(-1, 3) for name in ("origins", "directions")}
    n_occ = np.asarray(jax.jit(render.render_rays, static_argnames="cfg")(
        structure, params, flat["origins"], flat["directions"], near_t, far_t, cfg=render_cfg,
        key=jax.random.PRNGKey(0))["n_occupied"])
    n_rays = args.patches * args.patch**2
    shaded = min(k, n_cand) if skip else n_cand
    return {"sh": sh_degree, "skip": skip, "rows": structure.n_rows, "N": n_cand,
            "K": shaded, "ms": sec * 1e3, "rays_s": n_rays / sec,
            "shaded_s": n_rays * shaded / sec, "occ_mean": float(n_occ.mean()),
            "occ_p99": float(np.percentile(n_occ, 99)), "occ_max": int(n_occ.max()),
            "overflow": float(np.mean(n_occ > shaded)) if skip else 0.0,
            "loss": float(loss)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, nargs=3, default=[128, 128, 64])
    p.add_argument("--patches", type=int, default=64)
    p.add_argument("--patch", type=int, default=8)
    p.add_argument("--spv", type=float, default=2.0, help="candidate samples per voxel")
    p.add_argument("--k", type=int, nargs="+", default=[64, 32],
                   help="kept samples per ray when skipping (one row each)")
    p.add_argument("--iters", type=int, default=5)
    p.add_argument("--sh", type=int, nargs="+", default=[0, 2])
    args = p.parse_args()
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, grid {args.resolution}, "
          f"{args.patches * args.patch**2} rays/step, median of {args.iters} steps, "
          f"load average {os.getloadavg()[0]:.1f} (other processes share the CPU)")
    head = (f"{'sh':>2} {'skip':>5} {'rows':>8} {'N':>4} {'K':>4} {'ms/step':>8} {'rays/s':>8} "
            f"{'shaded/s':>9} {'occupied/ray mean p99 max':>26} {'overflow':>8}")
    print(head)
    for sh in args.sh:
        settings = [(True, True, k) for k in args.k] + [(True, False, args.k[0]),
                                                        (False, True, args.k[0])]
        for skip, fitted, k in settings:
            r = bench(sh, skip, fitted, k, args)
            print(f"{r['sh']:>2} {str(r['skip']):>5} {r['rows']:>8} {r['N']:>4} {r['K']:>4} "
                  f"{r['ms']:>8.1f} {r['rays_s']:>8.0f} {r['shaded_s'] / 1e6:>8.2f}M "
                  f"{r['occ_mean']:>16.1f} {r['occ_p99']:>4.0f} {r['occ_max']:>4d} "
                  f"{r['overflow']:>8.3f}", flush=True)
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
