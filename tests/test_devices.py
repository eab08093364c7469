"""Data parallelism over forced host devices matches the single-device run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

_SCRIPT = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    from gridnerf import colour_target, data_term, dataset, devices, grid, optim, render
    from gridnerf import config as cfgmod
    from gridnerf import plan as planmod
    from gridnerf.scene import load_scene
    scene_dir, near, far = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
    cfg = cfgmod.preset("tiny")
    scene = load_scene(scene_dir, near_far=(near, far))
    data = dataset.build(scene, scene.train_idx, True, 1, "raw")
    lo, hi, near_t, far_t = dataset.grid_box(scene)
    color_scale, log_gain, _ = data_term.data_statistics(data, jax.random.PRNGKey(1))
    structure, params = grid.init_grid((16, 16, 8), lo, hi, init_log_gain=log_gain,
                                       color_scale=color_scale)
    tx = optim.make_optimizer(cfg, 5)
    opt_state = tx.init(params)
    data, colour = colour_target.plan_colour(data, scene, cfg)
    n_stages = len(cfg.grid.resolutions)
    plan = planmod.RunPlan(
        method="brightnerf", black_level="file", data_noise=None,
        data_eps=cfg.loss.data_eps, colour=colour,
        opacity=planmod.opacity_schedule(cfg.loss.opacity, n_stages, cfg.loss.opacity_stages),
        n_candidates=(0,) * n_stages)
    step = optim.make_step(cfg, optim.step_plan(cfg, plan, 0, scene), tx, near_t, far_t)
    losses = []
    for k in range(3):
        params, opt_state, total, _ = step(params, opt_state, structure, data,
                                           jax.random.PRNGKey(k))
        losses.append(float(total))
    o, d = dataset.image_rays(scene.cameras.c2w[0], np.array([20.0, 20.0, 8.0, 6.0]), 12, 16)
    o, d = dataset.to_grid_space(data.ndc, data.ndc_intrinsics, o, d)
    img = render.render_image(structure, params, o, d, near_t, far_t, cfg.render, chunk=64)
    print(json.dumps({"devices": devices.device_count(), "losses": losses,
                      "density": np.asarray(params["density"])[:50].tolist(),
                      "rgb": img["rgb_low"].ravel().tolist()}))
""")


def _run(small_scene, n_devices: int) -> dict:
    from conftest import sim_near_far

    near, far = sim_near_far(small_scene)
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={n_devices}")
    out = subprocess.run([sys.executable, "-c", _SCRIPT, str(small_scene), str(near), str(far)],
                         env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_two_devices_match_one(small_scene):
    one, two = _run(small_scene, 1), _run(small_scene, 2)
    assert (one["devices"], two["devices"]) == (1, 2)
    assert one["losses"] == pytest.approx(two["losses"], rel=1e-4)
    assert one["density"] == pytest.approx(two["density"], rel=1e-4, abs=1e-5)
    assert one["rgb"] == pytest.approx(two["rgb"], rel=1e-4, abs=1e-7)


def test_batch_that_does_not_split_is_refused(monkeypatch):
    from gridnerf import devices
    from gridnerf.errors import ConfigError

    monkeypatch.setattr(devices, "device_count", lambda: 3)
    with pytest.raises(ConfigError, match="train.batch_patches = 64 does not split over 3"):
        devices.check_divisible(64, "train.batch_patches")
