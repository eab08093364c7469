"""The colour solve: with the geometry fixed, the vertex colours fitted to every training ray.

Why. Adam on 4096-ray batches with a decaying rate approaches the colour; it does not
average the frames. The last stage's 2100 steps x 4096 rays see each of the 2.7 M
photosites of a 480x270, 21-frame capture about three times, and a vertex's colour ends
as a running average of the few noisy gradients its rays gave it last. With the density
fixed, the rendered low-light colour of ray r is

    C_r(x) = sum_i w_ri c(u_ri; x) + b_r,    c(u; x) = s softplus(sum_k t_k(u) x_row(k))

(w_ri = T_i alpha_i the frozen compositing weights, t_k the 8 trilinear weights of the
sample's cell, s the grid's colour scale, b_r the backdrop behind the grid): a smooth
function of the vertex colours x alone, nearly linear (softplus of an interpolation). The
solve minimises, over every training ray of the last stage at once,

    J(x) = sum_r m_r v_r (min(C_r(x), 1) - y_r)^2 / sum_r m_r
           + tv_rgb TV(x) + tv_chroma TV_chroma(x)

with v_r = 1 / (min(C_r(x0), 1) + eps)^2 fixed at the start: RawNeRF's weighted data term
(gridnerf.losses.data_loss, whose weight is a stop-gradient of the render) as one
iteratively reweighted least-squares step, so that J is one function that a line search can
trust. The TVs are the step's grid priors (gridnerf.losses.grid_priors) on all rows rather
than a sample of them, with the stage's weights. x0 is Adam's colour; the solver is
L-BFGS (optax.lbfgs with its zoom line search) for train.colour_solve_iters iterations.

Samples. Each ray's samples are placed once, as rendering places them (the fixed mid
offsets of gridnerf.render.march), and its `keep` heaviest are kept; what the rest
contribute (and the backdrop) is frozen at x0 into b_r, so C_r(x0) is exactly the render.
Memory: 16 bytes a kept sample, 2.7 M rays x 8 samples = 350 MB (KEEP).
"""

from __future__ import annotations

import time
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import optax

from gridnerf import dataset, losses, render
from gridnerf import grid as gridlib
from gridnerf.config import Config
from gridnerf.grid import GridStructure

CHUNK = 1 << 15  # rays per chunk of the objective's scan (and of the sample placement)
# the heaviest samples a ray the solve refits: on bucket's default run 8 carry a median 60 %
# of a ray's rendering weight, 24 carry 93 % at 4x the time of an iteration (docs/results.md)
KEEP = 8
# at most this many training rays take part (an even subset of the frames' pixels where
# there are more): 16 bytes a kept sample and 36 a ray, so 4.2 M rays hold 0.7 GB; a
# 480x270 capture's 21 frames have 2.7 M photosites, a 1920x1080 one's mosaic 44 M
MAX_RAYS = 1 << 22


def _samples_chunk(structure: GridStructure, params, data: dataset.RayData, fr, v, u,
                   near_t, far_t, render_cfg, n_cand: int, keep: int):
    """The kept samples of one chunk of training pixels (fr, v, u: (n,) int32).

    Returns u (n, keep, 3) index-space points, w (n, keep) compositing weights, base (n, 3)
    the render minus the kept samples' colour at x0, target (n, 3), mask (n, 3)."""
    rays = dataset.rays_at(data, fr, v, u)
    out = render.render_rays(structure, params, rays["origins"], rays["directions"], near_t,
                             far_t, render_cfg, n_cand=n_cand)
    w_top, idx = jax.lax.top_k(out["weights"], keep)
    pts_top = jnp.take_along_axis(out["points"], idx[..., None], axis=1)
    rgb_top = jnp.take_along_axis(out["rgb_samples"], idx[..., None], axis=1)
    base = out["rgb_low"] - jnp.einsum("nk,nkc->nc", w_top, rgb_top)
    return pts_top, w_top, base, rays["target"], rays["mask"]


_samples_jit = jax.jit(_samples_chunk, static_argnames=("render_cfg", "n_cand", "keep"))


def ray_samples(structure: GridStructure, params, data: dataset.RayData, near_t, far_t,
                render_cfg, n_cand: int, keep: int) -> dict:
    """Every training pixel of `data` (an even subset of MAX_RAYS where there are more) as a
    row of chunks: {"u": (c, CHUNK, keep, 3), "w": (c, CHUNK, keep), "base": (c, CHUNK, 3),
    "target", "mask": (c, CHUNK, 3)}, the last chunk padded with rays of mask 0. Only for
    sh_degree 0 (no view directions kept)."""
    n, h, w = data.pixels.shape[0], *data.image_hw
    ids = np.arange(n * h * w)
    if ids.size > MAX_RAYS:
        ids = ids[np.linspace(0, ids.size - 1, MAX_RAYS).astype(np.int64)]
    total = ids.size
    n_chunks = -(-total // CHUNK)
    flat = ids[np.arange(n_chunks * CHUNK) % total]
    fr, rest = np.divmod(flat, h * w)
    vv, uu = np.divmod(rest, w)
    parts = []
    for c in range(n_chunks):
        sl = slice(c * CHUNK, (c + 1) * CHUNK)
        parts.append(_samples_jit(structure, params, data, jnp.asarray(fr[sl], jnp.int32),
                                  jnp.asarray(vv[sl], jnp.int32),
                                  jnp.asarray(uu[sl], jnp.int32), near_t, far_t,
                                  render_cfg=render_cfg, n_cand=n_cand, keep=keep))
    names = ("u", "w", "base", "target", "mask")
    out = {k: jnp.stack([p[i] for p in parts]) for i, k in enumerate(names)}
    pad = n_chunks * CHUNK - total  # the wrapped-around rays count once
    if pad:
        out["mask"] = out["mask"].at[-1, CHUNK - pad:].set(0.0)
    return out


def _render_kept(structure: GridStructure, rgb, density, log_gain, u, w, base):
    """C_r(x) of a chunk: (n, keep, 3) points and (n, keep) weights -> (n, 3)."""
    table = gridlib.feature_table(structure, {"density": density, "rgb": rgb,
                                              "log_gain": log_gain}, pad_to=8)
    feats = gridlib.trilinear_index_space(structure, table, u)[..., : structure.n_channels]
    _, rgb_low, _ = gridlib.decode(structure, feats)
    return base + jnp.einsum("nk,nkc->nc", w, rgb_low)


@jax.jit
def _initial_render(aux: dict, rgb) -> jax.Array:
    """(c, CHUNK, 3) C_r(x0), min 1: each chunk's render at the colour rows rgb."""
    smp = aux["samples"]
    return jnp.minimum(jax.lax.map(
        lambda ch: _render_kept(aux["structure"], rgb, aux["density"], aux["log_gain"], *ch),
        (smp["u"], smp["w"], smp["base"])), 1.0)


def make_objective(structure: GridStructure, params, samples: dict, data_eps: float,
                   tv_rgb: float, tv_chroma: float):
    """(objective, data_part, aux): J of the module docstring and its data part alone, as
    functions f(rgb, aux) of the colour rows (M, 3 n_sh), and aux, what they read: the grid,
    the density and the gains fixed at `params`, the samples and their weights v_r, taken
    at the samples' own render (x0). The samples travel as an argument, never closed over:
    jit copies the arrays a function closes over into every executable it compiles (a
    peak of 12 GB on bucket, where the samples hold 0.5 GB)."""
    aux = {"structure": structure, "density": params["density"],
           "log_gain": params["log_gain"], "samples": samples}
    c0 = _initial_render(aux, params["rgb"])
    aux["weight"] = samples["mask"] / (c0 + data_eps) ** 2
    aux["target"] = jnp.where(samples["mask"] > 0, samples["target"], 0.0)
    aux["norm"] = jnp.maximum(jnp.sum(samples["mask"]), 1.0)

    def data_part(rgb, aux):
        smp = aux["samples"]

        @jax.checkpoint
        def body(acc, chunk):
            u, w, base, y, v = chunk
            c = jnp.minimum(_render_kept(aux["structure"], rgb, aux["density"],
                                         aux["log_gain"], u, w, base), 1.0)
            return acc + jnp.sum(v * (c - y) ** 2), None

        total, _ = jax.lax.scan(body, jnp.zeros((), jnp.float32),
                                (smp["u"], smp["w"], smp["base"], aux["target"],
                                 aux["weight"]))
        return total / aux["norm"]

    def objective(rgb, aux):
        fields = {"density": aux["density"], "rgb": rgb, "log_gain": aux["log_gain"]}
        priors = losses.grid_priors(losses.grid_sample(aux["structure"], fields))
        return (data_part(rgb, aux) + tv_rgb * priors["tv_rgb"]
                + tv_chroma * priors["tv_chroma"])

    return objective, data_part, aux


def solve(structure: GridStructure, params, data: dataset.RayData, near_t, far_t,
          cfg: Config, data_eps: float, n_cand: int, tv_scale: float = 1.0,
          keep: int = KEEP) -> tuple[dict, dict]:
    """(params with the colour solved, a record) for the last stage's grid and data.

    cfg: the run's config with the render config the last stage trained with (its slots);
    data_eps: the plan's eps; n_cand: the stage's candidate count; tv_scale: the stage's
    factor on the TVs (optim.tv_scale); keep: samples a ray refitted. The record:
    iterations, seconds, the objective and its data part before and after, rays, kept
    samples a ray. If an iteration leaves a non-finite colour or a larger objective, Adam's
    colour is kept and the record says so.
    """
    if structure.sh_degree != 0:
        raise ValueError("train.colour_solve_iters needs grid.sh_degree = 0")
    t0 = time.perf_counter()
    samples = ray_samples(structure, params, data, near_t, far_t,
                          replace(cfg.render, skip_empty=True), n_cand, keep)
    lc = cfg.loss
    objective, data_part, aux = make_objective(
        structure, params, samples, data_eps, lc.tv_rgb * tv_scale,
        lc.tv_chroma * tv_scale if lc.tv_chroma > 0 else 0.0)
    f, data_f = jax.jit(objective), jax.jit(data_part)
    value_and_grad = jax.jit(optax.value_and_grad_from_state(objective))
    opt = optax.lbfgs()
    rgb = params["rgb"]
    state = opt.init(rgb)
    start, start_data = float(f(rgb, aux)), float(data_f(rgb, aux))
    update = jax.jit(lambda g, s, x, val, aux: opt.update(g, s, x, value=val, grad=g,
                                                          value_fn=objective, aux=aux))
    for _ in range(int(cfg.train.colour_solve_iters)):
        value, grad = value_and_grad(rgb, aux, state=state)
        updates, state = update(grad, state, rgb, value, aux)
        rgb = optax.apply_updates(rgb, updates)
    end = float(f(rgb, aux))
    record = {"iterations": int(cfg.train.colour_solve_iters), "rays": int(
        np.asarray(jnp.sum(jnp.max(samples["mask"], axis=-1)))), "kept_samples": keep,
        "objective_before": start, "data_before": start_data}
    if not (np.isfinite(end) and bool(jnp.all(jnp.isfinite(rgb)))) or end > start:
        record.update(kept="adam", objective_after=start, data_after=start_data)
        rgb = params["rgb"]
    else:
        record.update(kept="solved", objective_after=end, data_after=float(data_f(rgb, aux)))
    record["seconds"] = time.perf_counter() - t0
    return {**params, "rgb": rgb}, record
