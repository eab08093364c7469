"""Renderer invariants: agreement with the slow reference, compositing, hard rays."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gridnerf import grid, render
from gridnerf.config import RenderConfig

LO, HI = -np.ones(3), np.ones(3)
KEYS = ("rgb_low", "gain", "rgb_restored", "depth", "acc")
CFG = RenderConfig(samples_per_voxel=2.0, max_samples=40)  # shared: jit cache hits


def random_scene(sh_degree=0, res=(8, 7, 6), seed=0, prune_half=True):
    """Random grid on [-1, 1]^3; the x > 0.2 half pruned (empty) when prune_half."""
    rng = np.random.default_rng(seed)
    structure, params = grid.init_grid(res, LO, HI, sh_degree=sh_degree)
    params = {k: v + jnp.asarray(rng.normal(0, 0.7, v.shape), jnp.float32)
              for k, v in params.items()}
    params["density"] = params["density"] + 4.0
    if prune_half:
        x = np.asarray(structure.coords)[:, 0] / (res[0] - 1) * 2 - 1
        structure, params = grid.prune(structure, params, x < 0.2)
    return structure, params


def random_rays(n=24, seed=1):
    """Rays from z = -1.5 towards +z, spread in x/y; some miss the box."""
    rng = np.random.default_rng(seed)
    origins = np.concatenate([rng.uniform(-1.6, 1.6, (n, 2)), np.full((n, 1), -1.5)], 1)
    directions = np.concatenate([rng.normal(0, 0.4, (n, 2)), np.ones((n, 1))], 1)
    return origins.astype(np.float32), directions.astype(np.float32)


_render = jax.jit(render.render_rays, static_argnames=("cfg", "n_cand"))


def render_np(structure, params, o, d, near, far, cfg, **kw):
    out = _render(structure, params, jnp.asarray(o), jnp.asarray(d), near, far, cfg=cfg, **kw)
    return {k: np.asarray(v) for k, v in out.items()}


def reference(structure, params, o, d, near, far, cfg, n_cand=0):
    """render.render_rays_reference with the candidate count n_cand (0: the box diagonal's)."""
    return render.render_rays_reference(structure, params, o, d, near, far, cfg, n_cand)


@pytest.mark.parametrize(("sh_degree", "skip", "spv", "n_cand"), [
    (0, True, 2.0, 0), (2, True, 1.5, 12), (0, False, 1.5, 12), (2, False, 2.0, 0)])
def test_fast_renderer_matches_reference(sh_degree, skip, spv, n_cand):
    """n_cand = 12 is fewer than most segments need: steps stretch beyond 1 / spv."""
    structure, params = random_scene(sh_degree)
    o, d = random_rays()
    cfg = RenderConfig(samples_per_voxel=spv, max_samples=40, skip_empty=skip)
    fast = render_np(structure, params, o, d, 0.2, 3.0, cfg, n_cand=n_cand)
    ref = reference(structure, params, o, d, 0.2, 3.0, cfg, n_cand)
    # the set count is the one used (the box diagonal's is more): no more sample slots
    n = n_cand or render.n_candidates(structure, cfg)
    assert n_cand < render.n_candidates(structure, cfg)
    assert fast["weights"].shape == (o.shape[0], min(n, 40))
    assert fast["n_occupied"].max() <= 40  # no truncation: skipping must be exact
    assert ref["acc"].max() > 0.5 and ref["acc"].min() == 0.0  # hits and misses
    for k in KEYS:
        np.testing.assert_allclose(fast[k], ref[k], atol=2e-5 * max(1.0, np.abs(ref[k]).max()),
                                   err_msg=k)


def test_skipping_with_density_occupancy_is_exact_at_threshold_zero():
    structure, params = random_scene(0, seed=3)
    coords = np.asarray(structure.coords)
    centres = np.array([[2, 2, 3], [1, 5, 2], [3, 1, 1]])  # three 3x3x3 blobs of density
    hot = (np.abs(coords[:, None, :] - centres[None]).max(-1) <= 1).any(1)
    params["density"] = jnp.where(hot, 6.0, -40.0)
    structure = grid.update_occupancy(structure, params, threshold=1e-6)
    assert 0.1 < np.asarray(structure.occupancy).mean() < 0.75
    o, d = random_rays(seed=4)
    fast = render_np(structure, params, o, d, 0.0, 4.0, CFG)
    ref = render.render_rays_reference(structure, params, o, d, 0.0, 4.0, CFG)
    dense = render_np(structure, params, o, d, 0.0, 4.0,
                      RenderConfig(samples_per_voxel=2.0, skip_empty=False))
    assert fast["n_occupied"].sum() < 0.6 * dense["n_occupied"].sum()  # most were skipped
    assert ref["acc"].max() > 0.5
    for k in KEYS:
        np.testing.assert_allclose(fast[k], ref[k], atol=1e-5, err_msg=k)


def test_constant_colour_and_unit_gains_composite_exactly():
    structure, params = grid.init_grid((6, 6, 6), LO, HI, init_density=1.0, color_scale=0.02)
    c = np.array([0.3, 1.0, 2.0], np.float32)  # c_l = 0.02 * c
    params["rgb"] = jnp.broadcast_to(jnp.asarray(np.log(np.expm1(c))), params["rgb"].shape)
    o, d = random_rays(32, seed=5)
    cfg = RenderConfig(samples_per_voxel=2.0, max_samples=64)
    out = render_np(structure, params, o, d, 0.0, 5.0, cfg)
    acc = out["acc"][:, None]
    assert 0.05 < out["acc"].max() < 1.0
    np.testing.assert_allclose(out["rgb_low"], 0.02 * c * acc, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(out["gain"], np.broadcast_to(acc, (32, 3)), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(out["rgb_restored"], out["rgb_low"], rtol=1e-5, atol=1e-9)
    # opaque: acc == 1 where the ray hits, rgb_low == c there
    params["density"] = jnp.full_like(params["density"], 50.0)
    opaque = render_np(structure, params, o, d, 0.0, 5.0, cfg)
    hit = opaque["acc"] > 0
    np.testing.assert_allclose(opaque["acc"][hit], 1.0, atol=1e-6)
    np.testing.assert_allclose(opaque["rgb_low"][hit], np.broadcast_to(0.02 * c, (hit.sum(), 3)),
                               rtol=1e-5)
    # gains of 2 double the restored colour
    params["log_gain"] = jnp.full_like(params["log_gain"], np.log(2.0))
    doubled = render_np(structure, params, o, d, 0.0, 5.0, cfg)
    np.testing.assert_allclose(doubled["rgb_restored"], 2 * opaque["rgb_low"], rtol=1e-5)


def _sum_outputs(params, structure, o, d, near, far, cfg):
    out = render.render_rays(structure, params, o, d, near, far, cfg)
    return sum(jnp.sum(out[k]) for k in KEYS)


_value_and_grad = jax.jit(jax.value_and_grad(_sum_outputs), static_argnames=("cfg",))


def loss_and_grads(structure, params, o, d, near, far, cfg):
    return _value_and_grad(params, structure, jnp.asarray(o), jnp.asarray(d), near, far, cfg=cfg)


def all_finite(tree) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree_util.tree_leaves(tree))


def test_missing_rays_are_zero_with_finite_gradients():
    structure, params = random_scene(0)
    o, d = random_rays()
    o[:4] = [[5.0, 5.0, -2.0], [0.0, 0.0, -2.0], [0.0, 0.0, 0.0], [0.0, 0.0, -2.0]]
    d[:4] = [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    # beside the box, pointing away, zero direction, parallel to a face outside
    out = render_np(structure, params, o, d, 0.0, 10.0, CFG)
    for k in KEYS:
        assert np.all(out[k][:4] == 0.0), k
    assert out["acc"][4:].max() > 0.5
    _, grads = loss_and_grads(structure, params, o[:4], d[:4], 0.0, 10.0, CFG)
    assert all_finite(grads) and all(np.all(np.asarray(g) == 0.0) for g in grads.values())


def test_empty_grid_renders_zeros():
    structure, params = random_scene(0)
    structure, params = grid.prune(structure, params, np.zeros(structure.n_rows, bool))
    o, d = random_rays()
    for cfg in (CFG, RenderConfig(samples_per_voxel=2.0, skip_empty=False)):
        out = render_np(structure, params, o, d, 0.0, 10.0, cfg)
        assert all_finite(out)
        for k in KEYS:
            assert np.abs(out[k]).max() < 1e-9, k
    value, grads = loss_and_grads(structure, params, o, d, 0.0, 10.0, CFG)
    assert np.isfinite(float(value)) and grads["density"].shape == (0,)


def test_long_rays_and_huge_densities_stay_finite():
    structure, params = random_scene(0)
    params["density"] = jnp.full_like(params["density"], 1e6)
    params["rgb"] = params["rgb"] * 50.0
    params["log_gain"] = params["log_gain"] * 100.0
    o, d = random_rays()
    o = o * 1e3  # far away origins, very long segment limits
    d = np.concatenate([-o[:, :2] / 1.5e3, np.ones((24, 1))], 1).astype(np.float32)  # aim at 0
    out = render_np(structure, params, o, d, -1e7, 1e7, CFG)
    assert all_finite(out) and np.all(out["acc"] <= 1.0 + 1e-6) and out["acc"].max() > 0.99
    _, grads = loss_and_grads(structure, params, o, d, -1e7, 1e7, CFG)
    assert all_finite(grads)


def test_gradients_are_compact_and_local():
    structure, params = random_scene(0, res=(8, 8, 6), prune_half=False)
    res = np.asarray(structure.resolution)
    # rays parallel to z through two (x, y) spots: only their cell columns can be touched
    xy = np.array([[-0.55, 0.1], [0.4, -0.7]], np.float32)
    o = np.concatenate([xy, np.full((2, 1), -3.0, np.float32)], 1)
    d = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (2, 1))
    _, grads = loss_and_grads(structure, params, o, d, 0.0, 10.0, CFG)
    assert grads["density"].shape == (structure.n_rows,)  # compact rows
    cell = np.floor((xy - LO[:2]) / (HI[:2] - LO[:2]) * (res[:2] - 1)).astype(int)
    coords = np.asarray(structure.coords)
    touched = np.zeros(structure.n_rows, bool)
    for cx, cy in cell:
        touched |= np.isin(coords[:, 0], [cx, cx + 1]) & np.isin(coords[:, 1], [cy, cy + 1])
    for name in ("density", "rgb", "log_gain"):
        g = np.abs(np.asarray(grads[name])).reshape(structure.n_rows, -1).sum(1)
        assert np.all(g[~touched] == 0.0), name
        assert np.count_nonzero(g[touched]) > touched.sum() // 2, name
        assert np.all(np.isfinite(g))


def test_overflowing_rays_are_counted_and_truncated():
    structure, params = random_scene(0)
    o, d = random_rays()
    small = render_np(structure, params, o, d, 0.0, 5.0,
                      RenderConfig(samples_per_voxel=2.0, max_samples=4))
    full = render_np(structure, params, o, d, 0.0, 5.0, CFG)
    assert full["n_occupied"].max() <= 40
    assert np.array_equal(small["n_occupied"], full["n_occupied"])
    over = small["n_occupied"] > 4
    assert over.any()
    assert np.all(small["acc"][over] < full["acc"][over] + 1e-7) and all_finite(small)
    np.testing.assert_allclose(small["acc"][~over], full["acc"][~over], atol=1e-6)


def test_jitter_key_and_config_dataclass():
    structure, params = random_scene(0)
    o, d = random_rays()
    cfg = RenderConfig()  # gridnerf.config's options work too (fields read by name)
    plain = render_np(structure, params, o, d, 0.0, 5.0, cfg)
    a = render_np(structure, params, o, d, 0.0, 5.0, cfg, key=jax.random.PRNGKey(7))
    b = render_np(structure, params, o, d, 0.0, 5.0, cfg, key=jax.random.PRNGKey(7))
    np.testing.assert_array_equal(a["rgb_low"], b["rgb_low"])
    assert all_finite(a) and not np.allclose(a["rgb_low"], plain["rgb_low"], rtol=1e-6, atol=0)
    assert np.mean(np.abs(a["acc"] - plain["acc"])) < 0.1  # same field, another quadrature


def test_fitted_candidate_count_renders_the_same():
    structure, params = random_scene(0)
    o, d = random_rays(seed=11)
    n_fit = render.fit_n_candidates(structure, o, d, 0.2, 3.0, 2.0)
    assert 0 < n_fit < render.n_candidates(structure, CFG)
    a = render_np(structure, params, o, d, 0.2, 3.0, CFG)
    b = render_np(structure, params, o, d, 0.2, 3.0, CFG, n_cand=n_fit)
    for k in KEYS:
        np.testing.assert_allclose(a[k], b[k], atol=1e-6, err_msg=k)


def test_render_image_matches_render_rays_with_padding():
    structure, params = random_scene(0)
    o, d = random_rays(seed=9)
    whole = render_np(structure, params, o, d, 0.1, 4.0, CFG)
    img = render.render_image(structure, params, o.reshape(4, 6, 3), d.reshape(4, 6, 3), 0.1,
                              np.full((4, 6), 4.0), CFG, chunk=10)
    assert img["rgb_low"].shape == (4, 6, 3) and img["acc"].shape == (4, 6)
    for k in KEYS:
        np.testing.assert_allclose(img[k].reshape(whole[k].shape), whole[k], atol=1e-6)


def test_render_image_fits_the_candidate_count_and_renders_the_same():
    """render_image fits N to its rays (image_candidates): fewer candidates than the box
    diagonal for rays along z, a multiple of CANDIDATE_QUANTUM, and the image of the auto
    count exactly."""
    structure, params = random_scene(0, res=(40, 36, 12), seed=3)
    o, d = random_rays(n=60, seed=5)
    cfg = RenderConfig(samples_per_voxel=2.0, max_samples=40)
    fitted = render.image_candidates(structure, cfg, o, d, 0.2, 3.0)
    assert isinstance(fitted, int)
    assert 0 < fitted < render.n_candidates(structure, cfg)
    assert fitted % render.CANDIDATE_QUANTUM == 0
    assert fitted >= render.fit_n_candidates(structure, o, d, 0.2, 3.0, 2.0)
    whole = render_np(structure, params, o, d, 0.2, 3.0, cfg)
    assert whole["acc"].max() > 0.5
    img = render.render_image(structure, params, o.reshape(6, 10, 3), d.reshape(6, 10, 3),
                              0.2, 3.0, cfg)
    for k in KEYS + ("n_occupied",):
        np.testing.assert_array_equal(img[k].reshape(whole[k].shape), whole[k], err_msg=k)


def test_vertex_visibility_sees_the_first_surface_only():
    """An opaque slab at z ~ 0: vertices in front (empty) and behind (hidden) get ~0."""
    res = (6, 6, 11)
    structure, params = grid.init_grid(res, LO, HI)
    z = np.asarray(structure.coords)[:, 2]
    params["density"] = jnp.asarray(np.where(z >= 5, 8.0, -30.0), jnp.float32)
    g = np.linspace(-0.5, 0.5, 8)
    o = np.stack([*np.meshgrid(g, g, indexing="ij"), np.full((8, 8), -1.5)], -1).reshape(-1, 3)
    d = np.tile([0.0, 0.0, 1.0], (64, 1))
    cfg = RenderConfig(samples_per_voxel=2.0, max_samples=64)
    vis = render.vertex_visibility(
        structure, params, jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32), 0.0, 5.0,
        cfg)
    assert len(vis) == 2
    vis_max, vis_sum = (np.asarray(v) for v in vis)
    surface = (z == 5) | (z == 6)
    assert vis_max.shape == vis_sum.shape == (structure.n_rows,)
    # surface: corners of the first opaque cells
    assert vis_max[z == 5].max() > 0.5 and vis_sum[surface].sum() > 0.8 * vis_sum.sum()
    assert vis_max[z >= 8].max() < 1e-3  # hidden behind the slab
    assert vis_max[z <= 3].max() < 1e-3  # free space in front of it


def test_vertex_visibility_is_the_corner_scatter_of_the_sample_weights():
    """Per cell, spread to the rows (grid.cells_to_rows), equals scattering every sample's
    weight to its cell's 8 corner rows: max, and sum / 8; on a pruned grid, where some
    corners are empty rows, and with the fitted candidate count as with the box's."""
    structure, params = random_scene(0, seed=3)
    structure = grid.update_occupancy(structure, params)
    o, d = random_rays(n=48, seed=4)
    o, d = jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)
    u, _, step, _ = render.march(structure, o, d, 0.2, 3.0, CFG)
    table = grid.feature_table(structure, params, pad_to=8)
    feats = grid.trilinear_index_space(structure, table, u)
    w, _ = render.composite(jax.nn.softplus(feats[..., 0]), step, {})
    w = np.asarray(jnp.where(step > 0, w, 0.0), np.float64).reshape(-1)
    rows = np.asarray(grid.corner_rows(structure, u)[0]).reshape(-1, 8)
    want_max = np.zeros(structure.n_rows + 1)
    want_sum = np.zeros(structure.n_rows + 1)
    for k in range(8):
        np.maximum.at(want_max, rows[:, k], w)
        np.add.at(want_sum, rows[:, k], w / 8.0)
    assert want_max[:-1].max() > 0.1 and (want_max[:-1] == 0).any()
    n_fit = render.fit_n_candidates(structure, o, d, 0.2, 3.0, CFG.samples_per_voxel)
    for n_cand in (0, n_fit):
        got_max, got_sum = render.vertex_visibility(structure, params, o, d, 0.2, 3.0, CFG,
                                                    n_cand=n_cand)
        np.testing.assert_allclose(got_max, want_max[:-1], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(got_sum, want_sum[:-1], rtol=1e-5, atol=1e-7)


def test_backdrop_fills_what_the_grid_leaves_and_matches_the_reference():
    """rgb_low(backdrop) = rgb_low(black) + (1 - acc) b, restored with the backdrop's gains
    g; rays that miss the box show b itself; gain, depth and acc are the grid's alone."""
    structure, params = random_scene(0, seed=6)
    o, d = random_rays(seed=7)
    o[0], d[0] = [5.0, 5.0, -2.0], [0.0, 0.0, 1.0]  # misses the box
    black = render_np(structure, params, o, d, 0.2, 3.0, CFG)
    b, g = np.array([0.02, 0.05, 0.01], np.float32), np.array([2.0, 1.0, 3.0], np.float32)
    grey = dataclasses.replace(structure, background=jnp.asarray(np.stack([b, g])))
    out = render_np(grey, params, o, d, 0.2, 3.0, CFG)
    rest = 1.0 - black["acc"][:, None]
    assert rest.min() < 0.5 and rest[0] == 1.0
    np.testing.assert_allclose(out["rgb_low"], black["rgb_low"] + rest * b, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(out["rgb_restored"], black["rgb_restored"] + rest * b * g,
                               rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(out["rgb_low"][0], b, rtol=1e-6)
    for k in ("gain", "depth", "acc"):
        np.testing.assert_array_equal(out[k], black[k])
    ref = render.render_rays_reference(grey, params, o, d, 0.2, 3.0, CFG)
    for k in KEYS:
        np.testing.assert_allclose(out[k], ref[k], atol=2e-5 * max(1.0, np.abs(ref[k]).max()),
                                   err_msg=k)


def test_frozen_density_gain_is_a_second_render_with_frozen_density():
    """render.frozen_density_gain equals rendering the rays again with stop-gradient density
    (the same samples: same key), in value and in gradient: a loss on it moves the gains as
    that render would and never the density."""
    structure, params = random_scene(seed=3)
    o, d = (jnp.asarray(a) for a in random_rays(seed=4))
    key = jax.random.PRNGKey(7)

    def new(p):
        out = render.render_rays(structure, p, o, d, 0.2, 3.0, CFG, key=key)
        gain, acc = render.frozen_density_gain(out)
        return jnp.sum(jnp.sin(gain)) + jnp.sum(acc**2), (gain, acc)

    def old(p):
        frozen = {**p, "density": jax.lax.stop_gradient(p["density"])}
        out = render.render_rays(structure, frozen, o, d, 0.2, 3.0, CFG, key=key)
        return jnp.sum(jnp.sin(out["gain"])) + jnp.sum(out["acc"] ** 2), (out["gain"],
                                                                         out["acc"])

    (_, (g_new, a_new)), grads_new = jax.value_and_grad(new, has_aux=True)(params)
    (_, (g_old, a_old)), grads_old = jax.value_and_grad(old, has_aux=True)(params)
    assert float(a_new.max()) > 0.5  # rays that hit something
    np.testing.assert_allclose(g_new, g_old, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(a_new, a_old, rtol=1e-6, atol=1e-7)
    assert not np.any(np.asarray(grads_new["density"]))
    for k in params:
        np.testing.assert_allclose(grads_new[k], grads_old[k], rtol=1e-5, atol=1e-6)
    assert np.abs(np.asarray(grads_new["log_gain"])).max() > 0  # the gains do move
