"""Forward+backward throughput of grid rendering + losses on this CPU.

A synthetic forward-facing scene in NDC-like coordinates: a 128 x 128 x 64 vertex grid on
[-1, 1]^3 holding a back wall and a few spheres, pruned and with a density occupancy
bitmask. 4096 rays per step as 64 patches of 8 x 8 adjacent pixels (coherent batches),
loss = data + 0.1 L_ca + 0.1 L_smooth(patch) + TV(density, 10% of rows).
Prints one table row per (sh_degree, skipping, candidate count) setting: N candidates per
ray (fitted to the rays with render.fit_n_candidates, or the box diagonal), K shaded.

Run: LD_PRELOAD=/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4 \
     .venv/bin/python experiments/bench_render.py
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from gridnerf import grid, losses, render
from gridnerf.config import RenderConfig


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


def patch_rays(n_patches: int, patch: int, image: int, seed: int):
    """NDC-like forward-facing rays: origins on z = -1, directions mostly +z. (n, 3) each."""
    rng = np.random.default_rng(seed)
    corner = rng.integers(0, image - patch + 1, (n_patches, 2))
    ij = corner[:, None, None, :] + np.stack(np.meshgrid(np.arange(patch), np.arange(patch),
                                                         indexing="ij"), -1)[None]
    xy = (ij.reshape(-1, 2) + 0.5) / image * 2.0 - 1.0
    origins = np.concatenate([xy, -np.ones((xy.shape[0], 1))], 1)
    directions = np.concatenate([-0.15 * xy, 2.0 * np.ones((xy.shape[0], 1))], 1)
    return origins.astype(np.float32), directions.astype(np.float32)


def make_step(structure, cfg, n_patches, patch):
    def loss_fn(params, origins, directions, target, key):
        out = render.render_rays(structure, params, origins, directions, 0.0, 1.0, cfg, key=key)
        shape = (n_patches, patch, patch, 3)
        return (losses.data_loss(out["rgb_low"], target, jnp.ones_like(target))
                + 0.1 * losses.ca_loss(out["rgb_low"], out["gain"])
                + 0.1 * losses.smooth_loss_patch(out["gain"].reshape(shape),
                                                 out["rgb_low"].reshape(shape))
                + 1e-4 * losses.tv_loss(structure, params["density"], sample_key=key,
                                        fraction=0.1)), out["n_occupied"]

    opt = optax.adam(1e-2)

    @jax.jit
    def step(params, opt_state, origins, directions, target, key):
        (loss, n_occ), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, origins, directions, target, key)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, n_occ

    return step, opt


def bench(sh_degree: int, skip: bool, fitted: bool, k: int, args) -> dict:
    structure, params = synthetic_scene(tuple(args.resolution), sh_degree)
    origins, directions = patch_rays(args.patches, args.patch, 512, 0)
    # fitted: N from the longest ray of a full 512 x 512 view; else the box diagonal
    o_all, d_all = patch_rays(1, 512, 512, 0)
    n_fit = (render.fit_n_candidates(structure, o_all, d_all, 0.0, 1.0, args.spv)
             if fitted else 0)
    cfg = RenderConfig(samples_per_voxel=args.spv, max_samples=k, skip_empty=skip,
                       n_candidates=n_fit)
    n_cand = render.n_candidates(structure, cfg)
    target = np.full((origins.shape[0], 3), 5e-3, np.float32)
    step, opt = make_step(structure, cfg, args.patches, args.patch)
    opt_state = opt.init(params)
    key = jax.random.PRNGKey(0)
    params, opt_state, loss, n_occ = step(params, opt_state, origins, directions, target, key)
    jax.block_until_ready(loss)
    times = []
    for i in range(args.iters):
        o, d = patch_rays(args.patches, args.patch, 512, i + 1)
        t0 = time.perf_counter()
        params, opt_state, loss, n_occ = step(params, opt_state, o, d, target,
                                              jax.random.PRNGKey(i + 1))
        jax.block_until_ready(loss)
        times.append(time.perf_counter() - t0)
    sec = float(np.median(times))
    n_rays = origins.shape[0]
    shaded = min(k, n_cand) if skip else n_cand
    n_occ = np.asarray(n_occ)
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
                                                        (False, True, 0)]
        for skip, fitted, k in settings:
            r = bench(sh, skip, fitted, k, args)
            print(f"{r['sh']:>2} {str(r['skip']):>5} {r['rows']:>8} {r['N']:>4} {r['K']:>4} "
                  f"{r['ms']:>8.1f} {r['rays_s']:>8.0f} {r['shaded_s'] / 1e6:>8.2f}M "
                  f"{r['occ_mean']:>16.1f} {r['occ_p99']:>4.0f} {r['occ_max']:>4d} "
                  f"{r['overflow']:>8.3f}", flush=True)
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
