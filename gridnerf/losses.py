"""Losses of Bright-NeRF on the grid (Bright-NeRF, AAAI 2025, eqs. 14-17; the data term as
RawNeRF's code implements it: linearised log-L2 with a stop-gradient weight).

All losses are means (not the paper's sums over rays), so their weights do not depend on
the batch size. Low-light colours are tiny (~1e-3); every ratio that would otherwise
depend on that scale is normalised by a stop-gradient batch mean.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from gridnerf import grid as gridlib
from gridnerf import illuminant as illuminant_lib
from gridnerf.grid import GridStructure

_TINY = 1e-30


def data_loss(rgb_low: jax.Array, target: jax.Array, mask: jax.Array,
              eps: float = 1e-3) -> jax.Array:
    """RawNeRF linearised log-L2 (eq. 16 as RawNeRF implements it, eps 1e-3).

    rgb_low: (n, 3) rendered low-light camera RGB; target: (n, 3) normalised raw, may be
    negative (never logged, never clipped); mask: (n, 3) weights, 0 for unmeasured Bayer
    channels and saturated pixels; eps > 0 (loss.data_eps: scaling C, y and eps alike
    scales nothing else).
    Returns sum m (min(C,1) - y)^2 / (sg(min(C,1)) + eps)^2 / sum m, a scalar.
    """
    c = jnp.minimum(rgb_low, 1.0)
    diff = jnp.where(mask > 0, c - target, 0.0)  # masked targets may hold anything, even NaN
    scaled = diff / (jax.lax.stop_gradient(c) + eps)
    return jnp.sum(mask * scaled**2) / jnp.maximum(jnp.sum(mask), _TINY)


def ca_loss(rgb_low: jax.Array, gain: jax.Array, eps: float = 1e-6,
            stop_grad_mean: bool = True, illuminant: jax.Array | None = None) -> jax.Array:
    """Chromatic adaptation loss (eq. 14), averaged over the rays of the batch.

    rgb_low: (n, 3) rendered low-light camera RGB; gain: (n, 3) rendered gains S (use
    normalized_gain so that the loss cannot reach density through the opacity).
    Target gain K_avg / C_k (illuminant.gains_from_illuminant) with C the illuminant
    estimate: `illuminant` (3,) or (n, 3) when given (any scale, e.g.
    illuminant.shades_of_grey of the batch), else grey world, C_k = Cbar_k the batch mean
    of channel k. Channels at or below eps x the largest are floored there: a black channel
    gives a large finite target, never Inf/NaN. stop_grad_mean: the estimate is a constant
    (default).

    Each ray's composited gain is compared with the target, not each sample's: a per-sample
    form (sum_i w_i |t - s_i|^2 / acc, the per-ray loss plus the gains' variance along the
    ray) was tried and changed nothing measurable (dev_arc_shop,
    dev_slide_bench, mixed_lamp_window, mixed_desk_daylight: +0.00 to +0.01 dB,
    CIEDE2000 -0.01 to -0.08).
    """
    c = illuminant_lib.grey_world(rgb_low) if illuminant is None else illuminant
    if stop_grad_mean:
        c = jax.lax.stop_gradient(c)
    target = illuminant_lib.gains_from_illuminant(c, floor=eps)
    return jnp.mean(jnp.sum((target - gain) ** 2, axis=-1)) / 3.0


def normalized_gain(gain: jax.Array, acc: jax.Array, eps: float = 1e-3) -> jax.Array:
    """Gain map independent of opacity: S / max(sg(acc), eps).

    gain: (n, 3) rendered S = sum_i w_i s_i; acc: (n,) sum_i w_i. A ray that is half
    transparent renders S ~ 0.5 s; dividing by its opacity gives back the gain of the
    surface, so L_ca no longer pushes the gains of dark, thin rays to target / acc. acc is
    a constant here, and S should come from weights that are constants too (render with
    stop-gradient density, as optim.loss_fn does): then the colour prior sends no gradient
    to density at all. Rays with acc < eps are divided by eps (they render ~0 anyway).
    """
    acc = jax.lax.stop_gradient(acc)
    return gain / jnp.maximum(acc, eps)[..., None]


def batch_illuminant(name: str, rgb_low: jax.Array, acc: jax.Array | None = None,
                     patch_shape: tuple[int, ...] | None = None, p: float = 6.0) -> jax.Array:
    """The L_ca illuminant estimate (3,) of one batch of rendered rays, a constant.

    name: one of illuminant.ESTIMATORS; rgb_low: (n, 3) rendered low-light camera RGB;
    acc: (n,) rendered opacity (weighted_grey: surface colour rgb_low / acc weighted by acc,
    near-black rays left out); patch_shape: (P, h, w, 3) the batch's ray patches (grey_edge
    differentiates inside each patch); p: Minkowski p of shades_of_grey.
    """
    rgb = jax.lax.stop_gradient(rgb_low)
    if name == "grey_edge":
        if patch_shape is None:
            raise ValueError("grey_edge needs the batch's patch shape (P, h, w, 3)")
        return illuminant_lib.grey_edge(rgb.reshape(patch_shape), p=1.0, sigma=1.0)
    if name == "weighted_grey":
        a = jnp.ones(rgb.shape[:-1], rgb.dtype) if acc is None else jax.lax.stop_gradient(acc)
        surface = rgb / jnp.maximum(a, 1e-3)[..., None]
        return illuminant_lib.weighted_grey(surface, weights=a)
    return illuminant_lib.estimate(name, rgb, p=p)


def smooth_loss_patch(gain: jax.Array, rgb: jax.Array, eps: float = 1e-2, gamma1: float = 1.0,
                      gamma2: float = 1.0, stop_grad_color: bool = True) -> jax.Array:
    """Local smoothness (eq. 15) on patches of adjacent rays.

    gain: (p, h, w, 3) rendered gains; rgb: (p, h, w, 3) rendered low-light colour.
    Per neighbour pair: gamma * sum_k dS_k^2 / (|dC|^2 / mu^2 + eps), with dS and dC taken
    between the *same* neighbours (vertical pairs weighted by gamma1, horizontal by gamma2)
    in the edge-aware reading of the paper's eq. 15 (as printed it divides the vertical
    gain step by the horizontal colour step). mu is the stop-gradient batch mean intensity,
    so eps is relative to the image level. Colour is a constant here (stop_grad_color):
    otherwise the loss would reward sharper colour edges. Mean over pairs.
    """
    if stop_grad_color:
        rgb = jax.lax.stop_gradient(rgb)
    mu2 = jnp.maximum(jax.lax.stop_gradient(jnp.mean(rgb)), 1e-12) ** 2  # float32-safe

    def term(axis: int, gamma: float) -> jax.Array:
        ds2 = jnp.sum(jnp.diff(gain, axis=axis) ** 2, axis=-1)
        dc2 = jnp.sum(jnp.diff(rgb, axis=axis) ** 2, axis=-1) / mu2
        return gamma * jnp.mean(ds2 / (dc2 + eps))

    total = jnp.zeros((), gain.dtype)
    if gain.shape[1] > 1:
        total = total + term(1, gamma1)
    if gain.shape[2] > 1:
        total = total + term(2, gamma2)
    return total


def neighbour_rows(structure: GridStructure, sample_key=None, fraction: float = 1.0
                   ) -> jax.Array:
    """(r, 4) int32: the rows of r vertices and of their +x, +y, +z neighbours (the
    vertex's own row where that neighbour is absent, so its difference is 0). All M rows in
    order, or with sample_key and fraction < 1 a uniform random subset (with replacement)
    of int(M * fraction) rows."""
    m = structure.n_rows
    if sample_key is None or fraction >= 1.0:
        own = jnp.arange(m, dtype=jnp.int32)
        nb = structure.neighbors
    else:
        own = jax.random.randint(sample_key, (max(1, int(m * fraction)),), 0, m)
        nb = structure.neighbors[own]
    return jnp.concatenate([own[:, None], jnp.where(nb == m, own[:, None], nb)], axis=1)


def grid_sample(structure: GridStructure, params, sample_key=None, fraction: float = 1.0
                ) -> dict[str, jax.Array]:
    """The trainable rows at neighbour_rows, by one gather of the feature table
    (grid.feature_table): {"density": (r, 4), "rgb": (r, 4, 3 n_sh), "log_gain": (r, 4, 3)},
    index 0 of the second axis the vertex, 1-3 its +x, +y, +z neighbours. Every grid
    prior of a step reads the one sample: on bucket (480x270) the last stage's training
    step took 65 ms against 85 with a sample and a gather per prior (docs/speed.md).
    M = 0 gives r = 0."""
    n_sh = structure.n_sh
    if structure.n_rows == 0:
        g = jnp.zeros((0, 4, structure.n_channels), jnp.float32)
    else:
        table = gridlib.feature_table(structure, params, pad_to=8)
        g = table[neighbour_rows(structure, sample_key, fraction)]  # (r, 4, C')
    return {"density": g[..., 0], "rgb": g[..., 1:1 + 3 * n_sh],
            "log_gain": g[..., 1 + 3 * n_sh:4 + 3 * n_sh]}


def _mean(x: jax.Array) -> jax.Array:
    """Mean over the first axis's rows, 0 for none."""
    return jnp.zeros((), x.dtype) if x.shape[0] == 0 else jnp.mean(x)


def tv(values: jax.Array, eps: float = 1e-8) -> jax.Array:
    """Plenoxels TV of sampled rows: mean over rows of sum_c sqrt(eps + dx_c^2 + dy_c^2 +
    dz_c^2). values: (r, 4) or (r, 4, C), a grid_sample entry (the vertex, then its +x, +y,
    +z neighbours; absent ones repeat the vertex and count 0). r = 0 gives 0."""
    v = values.reshape(*values.shape[:2], math.prod(values.shape[2:]))
    d = v[:, 1:] - v[:, :1]  # (r, 3, C)
    return _mean(jnp.sum(jnp.sqrt(eps + jnp.sum(d**2, axis=1)), axis=-1))


def _dc(rgb: jax.Array) -> jax.Array:
    """(r, 4, 3 n_sh) grid_sample "rgb" -> (r, 4, 3) its DC coefficients."""
    return rgb.reshape(*rgb.shape[:2], 3, rgb.shape[-1] // 3)[..., 0]


def chroma_tv(rgb: jax.Array, eps: float = 1e-8) -> jax.Array:
    """TV of the low-light colour's chroma: tv of (v_R - v_G, v_B - v_G), v the DC
    coefficients of rgb (r, 4, 3 n_sh), grid_sample's "rgb" (c = color_scale softplus(v)).
    Raw noise is independent per channel, so a colour difference carries twice a channel's
    variance and the mean of the channels a third of it: chroma noise is what a prior can
    smooth most cheaply."""
    dc = _dc(rgb)
    return tv(jnp.stack([dc[..., 0] - dc[..., 1], dc[..., 2] - dc[..., 1]], axis=-1), eps)


def edge_aware_gain_tv(sample: dict, scale: float = 0.5, eps: float = 1e-8) -> jax.Array:
    """Grid form of the local smoothness loss on a grid_sample: TV of log_gain, weighted
    per vertex by exp(-|grad c| / scale), |grad c| the forward-difference norm of the vertex
    low-light colour (DC term) divided by its mean over the sampled vertices, so `scale` is
    relative. Weights are constants (stop-gradient). r = 0 gives 0."""
    color = jax.nn.softplus(_dc(jax.lax.stop_gradient(sample["rgb"])))  # (r, 4, 3)
    color = color / jnp.maximum(_mean(color[:, 0]), _TINY)
    grad_c = jnp.sqrt(jnp.sum((color[:, 1:] - color[:, :1]) ** 2, axis=(1, 2)))
    d = sample["log_gain"][:, 1:] - sample["log_gain"][:, :1]
    return _mean(jnp.exp(-grad_c / scale) * jnp.sum(jnp.sqrt(eps + jnp.sum(d**2, axis=1)),
                                                      axis=-1))


def sparsity_loss(density_raw: jax.Array) -> jax.Array:
    """Cauchy sparsity prior on density (Plenoxels' forward-facing regulariser).

    density_raw: (r,) raw density rows (grid_sample's "density"[:, 0], or all rows); mean
    of log(1 + 2 sigma^2), sigma = softplus(raw). Pushes free space to zero density so
    pruning and empty-space skipping have work to do; the log keeps surfaces (large sigma)
    cheap. r = 0 gives 0.
    """
    return _mean(jnp.log1p(2.0 * jax.nn.softplus(density_raw) ** 2))


def grid_priors(sample: dict, eps: float = 1e-8) -> dict[str, jax.Array]:
    """The grid priors every method shares, on one grid_sample: "tv_density", "tv_rgb",
    "tv_chroma" and "sparsity"."""
    return {"tv_density": tv(sample["density"], eps), "tv_rgb": tv(sample["rgb"], eps),
            "tv_chroma": chroma_tv(sample["rgb"], eps),
            "sparsity": sparsity_loss(sample["density"][:, 0])}


def opacity_loss(acc: jax.Array) -> jax.Array:
    """Mean (1 - acc)^2 over rays; acc: (n,) accumulated opacity.

    The renderer composites over black, so without this prior a ray can be made darker by
    making it transparent: dark texture (mortar lines, printed ink) turns into holes that
    show what lies behind, and thin fog stands in for surfaces. In a forward-facing capture
    every ray ends on a surface inside the box, so acc should be 1.
    """
    return jnp.mean((1.0 - acc) ** 2)
