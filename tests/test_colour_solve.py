"""The colour solve (gridnerf.colour_solve): exact at its start, converging, resumable."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gridnerf import colour_solve, dataset, eval_run, render
from gridnerf import config as cfgmod


@pytest.fixture(scope="module")
def solved_run(small_scene, tmp_path_factory):
    from gridnerf.train import train

    run = tmp_path_factory.mktemp("runs") / "solved"
    cfg = cfgmod.override(cfgmod.preset("tiny"), ["train.colour_solve_iters=4"])
    return run, train(small_scene, run, cfg)


def _loaded(run):
    cfg, plan, scene, structure, params, _ = eval_run.load_run(run)
    data = dataset.training_data(scene, cfg.data)
    near_t, far_t = dataset.grid_box(scene)[2:]
    return cfg, plan, structure, params, data, near_t, far_t


def test_kept_samples_render_exactly_what_the_renderer_renders(solved_run):
    """With every slot kept, or with a few and the rest frozen into the base, C_r(x0) is the
    renderer's rgb_low of the same rays (fixed mid offsets)."""
    cfg, plan, structure, params, data, near_t, far_t = _loaded(solved_run[0])
    n_cand = plan.n_candidates[-1]
    samples = {keep: colour_solve.ray_samples(structure, params, data, near_t, far_t,
                                              cfg.render, n_cand, keep)
               for keep in (2, cfg.render.max_samples)}
    n, h, w = data.pixels.shape[0], *data.image_hw
    pick = np.arange(0, n * h * w, 97)
    fr, rest = np.divmod(pick, h * w)
    v, u = np.divmod(rest, w)
    rays = dataset.rays_at(data, jnp.asarray(fr), jnp.asarray(v), jnp.asarray(u))
    want = np.asarray(render.render_rays(structure, params, rays["origins"],
                                         rays["directions"], near_t, far_t, cfg.render,
                                         n_cand=n_cand)["rgb_low"])
    for s in samples.values():
        chunks = jax.lax.map(lambda ch: colour_solve._render_kept(
            structure, params["rgb"], params["density"], params["log_gain"], *ch),
            (s["u"], s["w"], s["base"]))
        got = np.asarray(chunks).reshape(-1, 3)[pick]
        np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-7)


def test_the_solve_recovers_a_colour_field_from_its_renders(solved_run):
    """Targets rendered from known vertex colours, the solve started far from them (no
    priors): the data term falls by over 100x, and the colours approach the truth."""
    cfg, plan, structure, params, data, near_t, far_t = _loaded(solved_run[0])
    samples = colour_solve.ray_samples(structure, params, data, near_t, far_t, cfg.render,
                                       plan.n_candidates[-1], cfg.render.max_samples)
    truth = params["rgb"]
    rendered = jax.lax.map(lambda ch: colour_solve._render_kept(
        structure, truth, params["density"], params["log_gain"], *ch),
        (samples["u"], samples["w"], samples["base"]))
    samples = {**samples, "target": rendered, "mask": jnp.ones_like(rendered)}
    start = {**params, "rgb": truth + 0.5 * jax.random.normal(jax.random.PRNGKey(0),
                                                              truth.shape)}
    objective, data_part, aux = colour_solve.make_objective(structure, start, samples,
                                                            plan.data_eps, 0.0, 0.0)
    import optax

    opt = optax.lbfgs()
    vg = jax.jit(optax.value_and_grad_from_state(objective))
    x, state = start["rgb"], opt.init(start["rgb"])
    before = float(data_part(x, aux))
    for _ in range(40):
        value, grad = vg(x, aux, state=state)
        updates, state = opt.update(grad, state, x, value=value, grad=grad,
                                    value_fn=objective, aux=aux)
        x = optax.apply_updates(x, updates)
    after = float(data_part(x, aux))
    assert np.isfinite(after) and after < before / 100, (before, after)


def test_the_run_records_the_solve_and_does_not_solve_twice(solved_run, small_scene, capsys):
    from gridnerf.train import train

    run, summary = solved_run
    record = summary["colour_solve"]
    assert record["iterations"] == 4 and record["kept"] in ("solved", "adam")
    assert record["objective_after"] <= record["objective_before"]
    assert np.isfinite(record["data_after"]) and record["rays"] > 0
    # stopped after the solve, before the summary: the rerun reads the solve's record from
    # the checkpoint and does not solve again
    (run / "summary.json").unlink()
    again = train(small_scene, run, cfgmod.load(run / "config.json"))
    assert again["colour_solve"] == record
    assert "colour solve:" not in capsys.readouterr().out


def test_the_solve_is_off_by_default_and_validated():
    cfg = cfgmod.preset("default")
    assert cfg.train.colour_solve_iters == 0
    from gridnerf.errors import ConfigError

    with pytest.raises(ConfigError, match="colour_solve_iters"):
        cfgmod.override(cfg, ["train.colour_solve_iters=-1"])
    from gridnerf import methods

    # refused before training starts, not after it: the solve fits view-independent colour
    with pytest.raises(ConfigError, match="sh_degree"):
        methods.get("brightnerf").check(cfgmod.override(
            cfg, ["train.colour_solve_iters=5", "grid.sh_degree=1"]))


def test_a_capture_with_more_rays_than_the_cap_solves_an_even_subset(solved_run, monkeypatch):
    """ray_samples keeps MAX_RAYS of the frames' pixels where there are more (memory), and
    the padding of the last chunk counts nothing."""
    cfg, plan, structure, params, data, near_t, far_t = _loaded(solved_run[0])
    monkeypatch.setattr(colour_solve, "MAX_RAYS", 1000)
    s = colour_solve.ray_samples(structure, params, data, near_t, far_t, cfg.render,
                                 plan.n_candidates[-1], 4)
    assert s["u"].shape[:3] == (1, colour_solve.CHUNK, 4)
    used = np.asarray(jnp.max(s["mask"], axis=-1)).reshape(-1) > 0
    assert 990 <= used.sum() <= 1000  # a few may be saturated
    assert not used[1000:].any()
