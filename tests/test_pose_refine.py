"""Test-view pose refinement: the rotation is a rotation; a test camera turned and moved off
its pose comes back towards it when aligned to its own raw frame through a trained field;
eval records what it did and refuses runs that do not fit the raw."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from gridnerf import pose_refine


def test_rotation_is_orthonormal_and_turns_by_the_vector_s_length():
    assert np.allclose(pose_refine.rotation(jnp.zeros(3)), np.eye(3), atol=1e-7)
    omega = np.array([0.3, -0.2, 0.1])
    r = np.asarray(pose_refine.rotation(jnp.asarray(omega)), np.float64)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-5)
    assert np.allclose(r @ omega, omega, atol=1e-5)  # the axis stays put
    angle = np.arccos((np.trace(r) - 1) / 2)
    assert angle == pytest.approx(np.linalg.norm(omega), abs=1e-5)


def test_a_test_camera_off_its_pose_is_brought_back(small_scene, tmp_path, monkeypatch):
    """A small training; its first test camera turned by 0.8 deg and moved by 2 % of the
    near bound, aligned to the field's own noise-free render at the simulator's pose (so
    that the pose which explains the frame is known exactly): it ends within a tenth of
    that rotation and translation. Then eval with refine_poses records each view's move,
    also for a run that fits the mosaic, and refuses a run that does not fit the raw."""
    from gridnerf import config as cfgmod
    from gridnerf import dataset, eval_run, render
    from gridnerf.errors import SceneError
    from gridnerf.train import train

    cfg = cfgmod.override(cfgmod.preset("tiny"), ["train.steps_per_stage=[120,40]"])
    run = tmp_path / "run"
    train(small_scene, run, cfg)
    cfg, plan, scene, structure, params, _ = eval_run.load_run(run)
    i = int(scene.test_idx[0])
    true = np.asarray(scene.cameras.c2w[i], np.float64)
    near_t, far_t = dataset.grid_box(scene)[2:]

    def rendered_frame(data, fr, v, u):  # the frame as the field shows it at the true pose
        c2w = jnp.broadcast_to(jnp.asarray(true, jnp.float32), v.shape + (3, 4))
        intr = jnp.broadcast_to(data.intrinsics[0], v.shape + (4,))
        o, d = dataset.pixel_rays(c2w, intr, u.astype(jnp.float32), v.astype(jnp.float32))
        o, d = dataset.to_grid_space(data.ndc, data.ndc_intrinsics, o, d)
        out = render.render_image(structure, params, o, d, near_t, far_t, cfg.render)
        return jnp.asarray(out["rgb_low"]), jnp.ones(v.shape + (3,))

    off = np.array([0.0, np.radians(0.8), 0.0, 0.02, 0.0, -0.01])
    start = np.asarray(pose_refine.moved(jnp.asarray(true, jnp.float32),
                                         jnp.asarray(off, jnp.float32), float(scene.near)))
    with monkeypatch.context() as mp:
        mp.setattr(dataset, "targets", rendered_frame)
        r = pose_refine.refine(structure, params, scene, cfg, plan, i, start=start)

    def distance(c2w):
        rel = c2w[:, :3] @ true[:, :3].T
        angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
        return angle, np.linalg.norm(c2w[:, 3] - true[:, 3]) / scene.near

    a0, t0 = distance(start)
    a1, t1 = distance(r.c2w)
    assert r.loss_after < 0.01 * r.loss_before
    assert a1 < 0.1 * a0 and t1 < 0.1 * t0, (a0, a1, t0, t1)

    metrics = eval_run.evaluate_run(run, refine_poses=True)
    assert metrics["test_poses"] == "refined"
    moved = metrics["pose_refined"]
    assert set(moved) == set(metrics["test_views"])
    assert all(np.isfinite(v["rotation_deg"]) and v["data_loss"][1] <= v["data_loss"][0]
               for v in moved.values())
    assert json.loads((run / "eval" / "metrics.json").read_text())["test_poses"] == "refined"

    def copy_as(name, change):  # the run's files under a config with `change`
        other = run.parent / name
        other.mkdir()
        for f in run.iterdir():
            if f.is_file():
                (other / f.name).write_bytes(f.read_bytes())
        cfgmod.save(cfgmod.override(cfg, [change]), other / "config.json")
        return other

    # a field fitted to the mosaic is the same camera RGB: aligned to the binned frame
    mosaic = eval_run.evaluate_run(copy_as("mosaic", "data.binning=false"), refine_poses=True)
    assert mosaic["test_poses"] == "refined"
    with pytest.raises(SceneError, match="refine-poses"):
        eval_run.evaluate_run(copy_as("processed", "data.target=processed"), refine_poses=True)
