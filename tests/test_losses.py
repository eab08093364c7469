"""Loss hard cases: negative targets, black channels, tiny exposures, masks, TV."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from gridnerf import grid, losses, optim

# jitted once per shape: far cheaper than op-by-op dispatch for these tiny arrays
data_loss = jax.jit(losses.data_loss)
ca_loss = jax.jit(losses.ca_loss, static_argnames=("stop_grad_mean",))
smooth_loss_patch = jax.jit(losses.smooth_loss_patch, static_argnames=("stop_grad_color",))
@jax.jit
def _tv_at(values, rows, eps):
    return losses.tv(values[rows], eps)


def tv_loss(structure, values, eps=1e-8, sample_key=None, fraction=1.0):
    """losses.tv of compact rows (M,) or (M, C) at neighbour_rows; 0 for M = 0."""
    if values.shape[0] == 0:
        return jnp.zeros((), values.dtype)
    return _tv_at(values, losses.neighbour_rows(structure, sample_key, fraction), eps)
grid_sample = jax.jit(losses.grid_sample, static_argnames=("fraction",))


def edge_aware_gain_tv(structure, params, **sampling):
    return losses.edge_aware_gain_tv(grid_sample(structure, params, **sampling))


def finite(*xs) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree_util.tree_leaves(xs))


def test_data_loss_matches_formula_and_ignores_masked_entries():
    c = np.array([[0.01, 0.2, 3.0]], np.float32)
    y = np.array([[-0.005, 0.25, 0.5]], np.float32)
    m = np.array([[1.0, 1.0, 0.0]], np.float32)
    expect = ((0.01 + 0.005) / 0.011) ** 2 + ((0.2 - 0.25) / 0.201) ** 2
    np.testing.assert_allclose(data_loss(c, y, m), expect / 2, rtol=1e-5)
    # saturated / unmeasured entries, even NaN, change nothing under a zero mask
    y_bad = y.copy()
    y_bad[0, 2] = np.nan
    assert float(data_loss(c, y_bad, m)) == float(data_loss(c, y, m))
    g = jax.grad(data_loss)(jnp.asarray(c), jnp.asarray(y_bad), jnp.asarray(m))
    assert finite(g) and g[0, 2] == 0.0 and g[0, 0] > 0.0 and g[0, 1] < 0.0
    assert float(data_loss(c, y, np.zeros_like(m))) == 0.0


@settings(max_examples=25, deadline=None)
@given(rgb=arrays(np.float32, (16, 3), elements=st.floats(0, 2, width=32)),
       target=arrays(np.float32, (16, 3), elements=st.floats(-0.0625, 1.5, width=32)),
       mask=arrays(np.float32, (16, 3), elements=st.sampled_from([0.0, 1.0])),
       ratio=st.sampled_from([1.0, 0.05]))
def test_data_loss_finite_with_negative_targets_and_exposure_ratio(rgb, target, mask, ratio):
    args = (jnp.asarray(rgb * ratio), jnp.asarray(target * ratio), jnp.asarray(mask))
    value, g = jax.value_and_grad(data_loss)(*args)
    assert finite(value, g) and float(value) >= 0.0


def test_data_loss_is_relative_error_at_any_exposure():
    # linearised log-L2: the same 10% error costs about the same at 1x and 0.05x exposure
    y = np.full((8, 3), 0.4, np.float32)
    m = np.ones_like(y)
    full = float(data_loss(1.1 * y, y, m))
    dark = float(data_loss(1.1 * 0.05 * y, 0.05 * y, m))
    assert 0.005 < full < 0.01 and 0.7 < dark / full < 1.0
    assert float(data_loss(0.05 * y, 0.05 * y, m)) == 0.0


def test_ca_loss_grey_world_target():
    rgb = np.array([[0.02, 0.01, 0.005], [0.04, 0.01, 0.015]], np.float32)
    cbar = rgb.mean(0)
    target = cbar.mean() / cbar
    gain = np.broadcast_to(target, rgb.shape)
    assert abs(float(ca_loss(rgb, gain))) < 1e-10
    np.testing.assert_allclose(ca_loss(rgb, np.ones_like(rgb)),
                               np.sum((target - 1) ** 2) / 3, rtol=1e-5)
    # averaged over rays: duplicating the batch leaves it unchanged
    np.testing.assert_allclose(ca_loss(np.tile(rgb, (3, 1)), np.ones((6, 3))),
                               ca_loss(rgb, np.ones_like(rgb)), rtol=1e-6)


def test_ca_loss_black_channel_is_finite():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.001, 0.01, (32, 3)).astype(np.float32)
    rgb[:, 2] = 0.0  # a blue channel that renders black
    gain = rng.uniform(0.5, 2.0, (32, 3)).astype(np.float32)
    for flag in (True, False):
        value, (g_rgb, g_gain) = jax.value_and_grad(ca_loss, argnums=(0, 1))(
            jnp.asarray(rgb), jnp.asarray(gain), 1e-6, flag)
        assert finite(value, g_rgb, g_gain) and float(value) > 1e6  # large finite target
    all_black = jax.value_and_grad(ca_loss, argnums=(0, 1))(
        jnp.zeros((4, 3)), jnp.ones((4, 3)))
    assert finite(all_black)


def test_ca_loss_stop_gradient_flag():
    rgb = jnp.asarray(np.random.default_rng(1).uniform(0.001, 0.01, (8, 3)), jnp.float32)
    gain = jnp.ones((8, 3))
    g_stop = jax.grad(ca_loss)(rgb, gain, stop_grad_mean=True)
    g_flow = jax.grad(ca_loss)(rgb, gain, stop_grad_mean=False)
    assert np.all(np.asarray(g_stop) == 0.0) and np.abs(np.asarray(g_flow)).max() > 0.0


def patches(seed=0):
    rng = np.random.default_rng(seed)
    rgb = np.full((2, 4, 6, 3), 0.004, np.float32)
    rgb[:, :, 3:, :] = 0.012  # a vertical colour edge between columns 2 and 3
    gain = 1.0 + 0.01 * rng.normal(size=rgb.shape).astype(np.float32)
    return gain, rgb


def test_smooth_loss_is_edge_aware_and_scale_free():
    gain, rgb = patches()
    flat = np.ones_like(gain)
    assert float(smooth_loss_patch(flat, rgb, 1e-2)) == 0.0
    step_at_edge, step_in_flat = flat.copy(), flat.copy()
    step_at_edge[:, :, 3:, :] = 1.5
    step_in_flat[:, :, 1:, :] = 1.5  # the same step where colour is flat
    at_edge = float(smooth_loss_patch(step_at_edge, rgb, 1e-2))
    in_flat = float(smooth_loss_patch(step_in_flat, rgb, 1e-2))
    assert 0.0 < at_edge < 0.05 * in_flat
    # normalised by the mean intensity: 20x darker colour, same loss
    np.testing.assert_allclose(smooth_loss_patch(step_in_flat, 0.05 * rgb, 1e-2), in_flat,
                               rtol=1e-4)
    value, (g_gain, g_rgb) = jax.value_and_grad(smooth_loss_patch, argnums=(0, 1))(
        jnp.asarray(gain), jnp.zeros_like(jnp.asarray(rgb)), 1e-2)
    assert finite(value, g_gain, g_rgb) and np.all(np.asarray(g_rgb) == 0.0)


def test_smooth_loss_gammas_weight_directions():
    gain, rgb = patches()
    rgb = np.full_like(rgb, 0.01)
    v_only = gain.copy()
    v_only[:, 2:, :, :] += 0.5  # a horizontal line: vertical differences only
    base = float(smooth_loss_patch(v_only, rgb, 1e-2, gamma1=1.0, gamma2=0.0))
    doubled = float(smooth_loss_patch(v_only, rgb, 1e-2, gamma1=2.0, gamma2=0.0))
    np.testing.assert_allclose(doubled, 2 * base, rtol=1e-6)
    assert base > 10 * float(smooth_loss_patch(v_only, rgb, 1e-2, gamma1=0.0))


def small_grid(res=(5, 4, 3)):
    return grid.init_grid(res, -np.ones(3), np.ones(3))


def test_tv_loss_on_constant_and_linear_values():
    structure, params = small_grid()
    m = structure.n_rows
    np.testing.assert_allclose(tv_loss(structure, jnp.zeros(m), eps=1e-8), 1e-4, rtol=1e-3)
    slope = 0.3
    values = jnp.asarray(np.asarray(structure.coords)[:, 0] * slope, jnp.float32)
    has_x = np.asarray(structure.coords)[:, 0] < structure.resolution[0] - 1
    expect = (has_x.sum() * slope + (~has_x).sum() * 1e-4) / m
    np.testing.assert_allclose(tv_loss(structure, values[:, None], eps=1e-8), expect,
                               rtol=1e-4)
    sub = tv_loss(structure, values, sample_key=jax.random.PRNGKey(0), fraction=0.5)
    assert 0.0 < float(sub) <= slope + 1e-4
    g = jax.grad(tv_loss, argnums=1)(structure, jnp.zeros((m, 3)))
    assert finite(g)


def test_tv_loss_skips_absent_neighbours_and_empty_grids():
    structure, params = small_grid()
    values = jnp.asarray(np.random.default_rng(2).normal(size=structure.n_rows), jnp.float32)
    pruned, pp = grid.prune(structure, {"v": values}, np.asarray(structure.coords)[:, 0] != 2)
    # columns x <= 1 and x >= 3 are now disconnected: no difference across the gap
    left = np.asarray(pruned.coords)[:, 0] == 1
    assert np.all(np.asarray(pruned.neighbors)[left, 0] == pruned.n_rows)
    assert np.isfinite(float(tv_loss(pruned, pp["v"])))
    empty, pe = grid.prune(structure, params, np.zeros(structure.n_rows, bool))
    assert float(tv_loss(empty, pe["density"])) == 0.0
    assert float(edge_aware_gain_tv(empty, pe)) == 0.0


def test_edge_aware_gain_tv_prefers_gain_steps_at_colour_edges():
    structure, params = small_grid((8, 4, 3))
    x = np.asarray(structure.coords)[:, 0]
    rgb = np.where(x[:, None] >= 4, 2.0, -1.0).astype(np.float32)  # colour edge between 3 and 4
    params["rgb"] = jnp.asarray(np.repeat(rgb, 3, axis=1))
    at_edge = dict(params, log_gain=jnp.asarray(np.where(x[:, None] >= 4, 0.5, 0.0) *
                                                np.ones((1, 3)), jnp.float32))
    in_flat = dict(params, log_gain=jnp.asarray(np.where(x[:, None] >= 2, 0.5, 0.0) *
                                                np.ones((1, 3)), jnp.float32))
    e = float(edge_aware_gain_tv(structure, at_edge))
    f = float(edge_aware_gain_tv(structure, in_flat))
    assert 0.0 < e < 0.5 * f
    assert float(edge_aware_gain_tv(structure, params)) < 1e-3  # constant gains
    g = jax.grad(lambda p: losses.edge_aware_gain_tv(losses.grid_sample(
        structure, p, sample_key=jax.random.PRNGKey(1), fraction=0.5)))(at_edge)
    assert finite(g) and np.all(np.asarray(g["rgb"]) == 0.0)


def test_chroma_tv_sees_colour_edges_not_brightness_edges():
    """A step in brightness (every channel alike) costs the chroma TV nothing; the same
    step in one channel costs it, as the colour TV does; its gradient is finite and leaves
    the grey direction alone."""
    structure, params = small_grid((8, 4, 3))
    x = np.asarray(structure.coords)[:, 0]
    step = np.where(x[:, None] >= 4, 1.0, 0.0).astype(np.float32)
    grey = jnp.asarray(np.repeat(step, 3, axis=1) + 0.3)
    red = jnp.asarray(np.concatenate([step, 0 * step, 0 * step], axis=1) + 0.3)
    eps = 1e-8
    floor = 2 * np.sqrt(eps)  # two chroma channels of a constant field
    rows = losses.neighbour_rows(structure)

    def chroma_tv(rgb, eps=1e-8):
        return losses.chroma_tv(rgb[rows], eps)
    assert float(chroma_tv(grey, eps)) == pytest.approx(floor, rel=1e-3)
    assert float(chroma_tv(red, eps)) > 10 * floor
    assert float(tv_loss(structure, grey, eps)) > float(tv_loss(structure, red, eps)) > 0.0
    g = np.asarray(jax.grad(chroma_tv)(red))
    assert finite(g) and np.abs(g.sum(axis=1)).max() < 1e-6


def test_sparsity_loss_prefers_empty_space():
    raw = jnp.asarray(np.linspace(-8.0, 6.0, 40), jnp.float32)
    sigma = np.logaddexp(0.0, np.asarray(raw, np.float64))
    np.testing.assert_allclose(losses.sparsity_loss(raw), np.mean(np.log1p(2 * sigma**2)),
                               rtol=1e-5)
    assert float(losses.sparsity_loss(raw - 5.0)) < float(losses.sparsity_loss(raw))
    g = jax.grad(losses.sparsity_loss)(raw)
    assert finite(g) and np.all(np.asarray(g) > 0.0)  # always pushes density down
    assert float(losses.sparsity_loss(jnp.zeros((0,)))) == 0.0


def _foggy_scene():
    """A small grid with semi-transparent density and gains that vary along the rays."""
    structure, params = grid.init_grid((8, 8, 8), -np.ones(3), np.ones(3), color_scale=5e-3)
    rng = np.random.default_rng(3)
    m = structure.n_rows
    params["density"] = jnp.asarray(rng.uniform(-3.0, 0.5, m), jnp.float32)
    params["rgb"] = jnp.asarray(rng.normal(0.0, 0.5, params["rgb"].shape), jnp.float32)
    params["log_gain"] = jnp.asarray(rng.normal(0.3, 0.4, (m, 3)), jnp.float32)
    structure = grid.update_occupancy(structure, params, threshold=1e-6)
    xy = np.stack(np.meshgrid(np.linspace(-0.6, 0.6, 4), np.linspace(-0.6, 0.6, 4),
                              indexing="ij"), -1).reshape(1, 4, 4, 2)
    xy = np.concatenate([xy, xy + 0.05], axis=0)  # (2, 4, 4, 2): two patches
    origins = np.concatenate([xy, -np.ones((2, 4, 4, 1))], -1).astype(np.float32)
    directions = np.concatenate([0.1 * xy, 2.0 * np.ones((2, 4, 4, 1))], -1).astype(np.float32)
    rays = {"origins": jnp.asarray(origins), "directions": jnp.asarray(directions),
            "target": jnp.full((2, 4, 4, 3), 4e-3), "mask": jnp.ones((2, 4, 4, 3))}
    return structure, params, rays


def _step(**kw):
    """The StepPlan of a test step: RawNeRF's eps, no opacity prior, the box diagonal's
    candidate count, the gain terms on; kw overrides (anchor, locus, data_eps, ...)."""
    from gridnerf.plan import StepPlan

    return StepPlan(**{"data_eps": 1e-3, "opacity": 0.0, "n_candidates": 0,
                       "train_gains": True, **kw})


def _colour_prior_grads(smooth_mode: str, illuminant: str = "grey_world", w_data=0.0):
    from gridnerf import config as cfgmod

    c = cfgmod.override(cfgmod.preset("tiny"), [
        "render.max_samples=16", f"loss.w_data={w_data}", "loss.tv_density=0",
        "loss.tv_rgb=0", "loss.sparsity=0", "loss.opacity=0", "loss.w_ca=1",
        "loss.w_smooth=1", f"loss.smooth_mode={smooth_mode}",
        f"loss.ca_illuminant={illuminant}",
        "loss.ca_target=batch"])  # each batch's own estimate: no frames
    structure, params, rays = _foggy_scene()
    loss = jax.jit(lambda p: optim.loss_fn(p, structure, rays, jax.random.PRNGKey(0), c,
                                           _step(), -1.0, 1.0)[0])
    return jax.grad(loss)(params)


@pytest.mark.parametrize("smooth_mode", ["tv", "patch"])
@pytest.mark.parametrize("illuminant", ["grey_world", "weighted_grey", "grey_edge"])
def test_normalized_gain_map_sends_no_gradient_to_density(illuminant, smooth_mode):
    g = _colour_prior_grads(smooth_mode, illuminant)
    assert finite(g)
    assert np.all(np.asarray(g["density"]) == 0.0)  # exactly: the prior never moves density
    assert np.all(np.asarray(g["rgb"]) == 0.0)
    assert np.abs(np.asarray(g["log_gain"])).max() > 0.0
    # the data term on the same scene does reach density and colour (the zeros above are
    # the colour prior's, not a dead render)
    g_data = _colour_prior_grads(smooth_mode, illuminant, w_data=1.0)
    assert np.abs(np.asarray(g_data["density"])).max() > 0.0
    assert np.abs(np.asarray(g_data["rgb"])).max() > 0.0


def test_normalized_gain_is_the_surface_gain_of_a_thin_ray():
    gain_surface = jnp.asarray([[1.5, 1.0, 2.5], [0.8, 1.0, 1.2]])
    acc = jnp.asarray([0.4, 1e-6])  # a half-transparent ray and an empty one
    s = gain_surface * acc[:, None]  # what compositing renders for a constant gain
    out = losses.normalized_gain(s, acc)
    np.testing.assert_allclose(out[0], gain_surface[0], rtol=1e-6)
    assert finite(out) and float(jnp.abs(out[1]).max()) < 1e-2  # divided by eps, ~0
    g = jax.grad(lambda a: jnp.sum(losses.normalized_gain(s, a)))(acc)
    assert np.all(np.asarray(g) == 0.0)


def test_ca_loss_takes_any_illuminant_estimate():
    rgb = jnp.asarray(np.random.default_rng(4).uniform(0.001, 0.01, (16, 3)), jnp.float32)
    c = jnp.asarray([0.6, 1.0, 0.3])
    target = c.mean() / c
    gain = jnp.broadcast_to(target, rgb.shape)
    assert float(ca_loss(rgb, gain, illuminant=c)) < 1e-10
    assert float(ca_loss(rgb, gain, illuminant=7.0 * c)) < 1e-10  # scale-free
    for name in ("grey_world", "shades_of_grey", "grey_edge", "weighted_grey"):
        est = losses.batch_illuminant(name, rgb, jnp.ones(16), (1, 4, 4, 3))
        assert est.shape == (3,) and finite(est)
        np.testing.assert_allclose(float(jnp.linalg.norm(est)), 1.0, rtol=1e-5)


def test_ca_locus_puts_the_target_on_the_locus():
    """With loss.ca_locus, L_ca's target is the locus entry nearest the batch estimate: a
    one-entry locus makes that entry the target whatever the batch looks like."""
    from gridnerf import config as cfgmod
    from gridnerf.illuminant import gains_from_illuminant

    c = cfgmod.override(cfgmod.preset("tiny"), [
        "render.max_samples=16", "loss.ca_locus=true", "loss.ca_illuminant=grey_edge",
        "loss.ca_target=batch"])
    structure, params, rays = _foggy_scene()
    light = jnp.asarray([[0.6, 1.0, 0.3]]) / jnp.linalg.norm(jnp.asarray([0.6, 1.0, 0.3]))
    target = gains_from_illuminant(light[0])
    params = {**params, "log_gain": jnp.broadcast_to(jnp.log(target), params["log_gain"].shape)}

    def ca(locus):
        return float(optim.loss_fn(params, structure, rays, jax.random.PRNGKey(0), c,
                                   _step(locus=locus), -1.0, 1.0)[1]["ca"])

    assert ca(light) < 1e-6  # the gains already equal the locus target
    assert ca(None) > 1e-3  # the batch's own estimate is another colour


def test_scene_target_replaces_the_batch_estimate():
    """loss.ca_target = "scene": the L_ca target is the capture's illuminant (the step
    plan's anchor) for every batch (no per-batch estimate, no locus projection at step
    time)."""
    from gridnerf import config as cfgmod
    from gridnerf.illuminant import gains_from_illuminant

    c = cfgmod.override(cfgmod.preset("tiny"), [
        "render.max_samples=16", "loss.ca_target=scene", "loss.ca_locus=true"])
    structure, params, rays = _foggy_scene()
    light = jnp.asarray([0.6, 1.0, 0.3])
    params = {**params, "log_gain": jnp.broadcast_to(jnp.log(gains_from_illuminant(light)),
                                                     params["log_gain"].shape)}

    def ca(anchor):
        return float(optim.loss_fn(params, structure, rays, jax.random.PRNGKey(0), c,
                                   _step(anchor=anchor), -1.0, 1.0)[1]["ca"])

    assert ca(light) < 1e-6 and ca(3.0 * light) < 1e-6  # the gains equal its target
    assert ca(jnp.asarray([1.0, 1.0, 1.0])) > 1e-3  # another light: another target


def test_one_gain_step_has_no_gain_terms():
    """A step whose colour is not the gain field (one gain, no gains: train_gains off)
    has the data term but neither L_ca nor the smoothness."""
    from gridnerf import config as cfgmod

    c = cfgmod.override(cfgmod.preset("tiny"), ["render.max_samples=16",
                                                "loss.ca_target=scene"])
    structure, params, rays = _foggy_scene()
    on = optim.loss_fn(params, structure, rays, jax.random.PRNGKey(0), c,
                       _step(anchor=jnp.asarray([0.6, 1.0, 0.3])), -1.0, 1.0)[1]
    off = optim.loss_fn(params, structure, rays, jax.random.PRNGKey(0), c,
                        _step(train_gains=False), -1.0, 1.0)[1]
    assert {"data", "ca", "smooth"} <= set(on) and "data" in off
    assert "ca" not in off and "smooth" not in off
    assert float(off["data"]) == pytest.approx(float(on["data"]), rel=1e-6)


@pytest.mark.parametrize("follow", [True, False])
def test_eps_scaled_with_the_raw_makes_the_data_term_free_of_its_scale(follow):
    """The darkness sweep scales the raw by gamma (signal and noise alike). With the eps
    scaled alike (the noise-sigma cap, data_term.capped_eps, scales it with the noise) the
    data term is the same at every gamma; with a fixed absolute eps it is not."""
    from dataclasses import replace

    from gridnerf import config as cfgmod

    c = cfgmod.override(cfgmod.preset("tiny"), ["render.max_samples=16",
                                                "loss.gain_model=none"])
    structure, params, rays = _foggy_scene()
    rays["target"] = rays["target"] * jnp.linspace(0.5, 1.5, 32).reshape(2, 4, 4, 1)
    eps = 0.4 * structure.color_scale

    def data_term(gamma):
        s = replace(structure, color_scale=structure.color_scale * gamma)
        r = {**rays, "target": rays["target"] * gamma}
        step = _step(data_eps=eps * gamma if follow else eps, train_gains=False)
        return float(optim.loss_fn(params, s, r, jax.random.PRNGKey(0), c, step, -1.0,
                                   1.0)[1]["data"])

    ratio = data_term(0.1) / data_term(1.0)
    if follow:
        assert ratio == pytest.approx(1.0, rel=1e-4)
    else:
        assert not 0.9 < ratio < 1.1


def test_stage_warmup_ramps_the_rates_of_later_stages_only():
    """train.warmup_steps: a later stage's first update is zero and its rate reaches lr after
    the ramp, then decays to lr * lr_decay by the stage's end; the first stage starts at lr."""
    from gridnerf import config as cfgmod

    cfg = cfgmod.override(cfgmod.preset("default"), ["train.warmup_steps=10"])
    params = {"density": jnp.zeros(4), "rgb": jnp.zeros((4, 3)), "log_gain": jnp.zeros((4, 3))}
    grads = jax.tree_util.tree_map(jnp.ones_like, params)

    def steps_taken(stage, n=100):
        tx = optim.make_optimizer(cfg, n, stage)
        state, sizes = tx.init(params), []
        for _ in range(n):
            upd, state = tx.update(grads, state, params)
            sizes.append(-float(upd["rgb"][0, 0]))  # Adam on a constant gradient: the rate
        return np.asarray(sizes)

    lr, decay = cfg.train.lr_rgb, cfg.train.lr_decay
    first, later = steps_taken(0), steps_taken(1)
    np.testing.assert_allclose(first[0], lr, rtol=1e-5)
    assert later[0] == 0.0 and np.all(np.diff(later[:11]) > 0)
    np.testing.assert_allclose(later[10], lr, rtol=1e-5)
    np.testing.assert_allclose(later[-1], lr * decay ** (89 / 90), rtol=1e-4)
    assert np.all(np.diff(later[10:]) < 0)
    # without the field (old runs) every stage starts at lr
    plain = cfgmod.preset("default")
    assert plain.train.warmup_steps == 0
    tx = optim.make_optimizer(plain, 100, 2)
    upd, _ = tx.update(grads, tx.init(params), params)
    np.testing.assert_allclose(-float(upd["rgb"][0, 0]), lr, rtol=1e-5)


def test_grid_sample_feeds_every_prior_as_its_own_gather_would():
    """One grid_sample serves all grid priors: each equals the prior computed from its own
    rows (tv_loss on the same neighbour_rows), the sample's entries are the params at
    those rows, sampling draws int(M * fraction) rows, and an empty grid gives zeros."""
    structure, params = small_grid((6, 5, 4))
    rng = np.random.default_rng(3)
    params = {k: jnp.asarray(rng.normal(size=v.shape), jnp.float32) for k, v in params.items()}
    key = jax.random.PRNGKey(4)
    sample = grid_sample(structure, params, sample_key=key, fraction=0.5)
    rows = losses.neighbour_rows(structure, key, 0.5)
    assert rows.shape == (int(structure.n_rows * 0.5), 4)
    for name in ("density", "rgb", "log_gain"):
        np.testing.assert_array_equal(np.asarray(sample[name]), np.asarray(params[name][rows]))
    priors = losses.grid_priors(sample)
    for name, values in (("tv_density", params["density"]), ("tv_rgb", params["rgb"])):
        np.testing.assert_allclose(priors[name], tv_loss(structure, values, sample_key=key,
                                                         fraction=0.5), rtol=1e-6)
    np.testing.assert_allclose(priors["sparsity"],
                               losses.sparsity_loss(params["density"][rows[:, 0]]), rtol=1e-6)
    empty, pe = grid.prune(structure, params, np.zeros(structure.n_rows, bool))
    zeros = losses.grid_priors(losses.grid_sample(empty, pe, sample_key=key, fraction=0.5))
    assert all(float(v) == 0.0 for v in zeros.values())
    assert float(losses.edge_aware_gain_tv(losses.grid_sample(empty, pe))) == 0.0


def test_tv_scale_strengthens_the_tvs_of_stages_finer_than_the_reference_only():
    """loss.tv_ref_width: a stage wider than it has its density, colour and chroma TVs
    weighted by width / ref (the prior's strength per unit of the scene kept); narrower
    stages and the default (0) are unscaled, and nothing else in the loss changes."""
    from gridnerf import config as cfgmod

    c = cfgmod.override(cfgmod.preset("tiny"), [
        "render.max_samples=16", "loss.ca_target=scene", "loss.tv_ref_width=8",
        "loss.tv_chroma=0.01",
        "grid.resolutions=[[6,6,6],[8,8,8],[12,12,12]]", "train.steps_per_stage=[1,1,1]"])
    assert [optim.tv_scale(c, s) for s in range(3)] == [1.0, 1.0, 1.5]
    plain = cfgmod.override(c, ["loss.tv_ref_width=0"])
    assert [optim.tv_scale(plain, s) for s in range(3)] == [1.0, 1.0, 1.0]
    structure, params, rays = _foggy_scene()
    args = (params, structure, rays, jax.random.PRNGKey(0), c)
    total1, terms = optim.loss_fn(*args, _step(train_gains=False), -1.0, 1.0)
    total2, terms2 = optim.loss_fn(*args, _step(train_gains=False, tv_scale=1.5),
                                   -1.0, 1.0)
    extra = 0.5 * sum(w * float(terms[k]) for k, w in
                      (("tv_density", c.loss.tv_density), ("tv_rgb", c.loss.tv_rgb),
                       ("tv_chroma", c.loss.tv_chroma)))
    assert extra > 0
    assert float(total2) - float(total1) == pytest.approx(extra, rel=1e-4, abs=1e-9)
    assert all(float(terms2[k]) == pytest.approx(float(terms[k]), rel=1e-6) for k in terms)
