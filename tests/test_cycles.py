"""The path-traced captures: camera poses that look at the room, and (where Blender is
installed) a tiny capture written in the scene-folder format the loaders read, its light
applied in the renderer's RGB."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gridnerf.sim import cycles


def test_arc_poses_are_rigid_and_look_at_the_target():
    target = np.array([0.0, -0.8, 0.6])
    poses = cycles.arc_poses(7, target=target)
    assert poses.shape == (7, 4, 4)
    for pose in poses:
        rot = pose[:3, :3]
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0)
        view = -rot[:, 2]  # OpenGL: the camera looks down -z
        to_target = (target - pose[:3, 3]) / np.linalg.norm(target - pose[:3, 3])
        assert view @ to_target == pytest.approx(1.0)
        assert rot[2, 1] > 0  # image up is world up (z)


def test_a_tiny_cycles_capture_loads_with_its_true_light(tmp_path):
    if cycles.blender_available() is None:
        print("Blender is not installed: the Cycles capture test is skipped")
        pytest.skip("blender not installed (Debian: apt-get install blender)")
    from conftest import sim_near_far

    from gridnerf import illuminant
    from gridnerf.color import XYZ_FROM_SRGB
    from gridnerf.scene import load_scene

    out = cycles.simulate_cycles("cycles_sodium_room", tmp_path / "c", width=64, height=48,
                                 n_frames=3, samples=4)
    sim = json.loads((out / "sim.json").read_text())
    scene = load_scene(out, near_far=sim_near_far(out))
    assert len(scene.names) == 3 and scene.raw_bayer.shape[1:] == (48, 64)
    assert sim["renderer"].startswith("Blender") and sim["held_out"]
    light = np.asarray(sim["light_rgb"])
    cam = np.asarray(sim["xyz_to_cam"]) @ XYZ_FROM_SRGB @ light
    np.testing.assert_allclose(sim["illuminant_neutral_cam"], cam / cam[1], rtol=1e-9)
    # the raw's grey world leans the way the light does: the sodium-like lamp's blue is weak
    grey = np.mean([scene.rgb_cam_binned(i)[0].reshape(-1, 3).mean(0)
                    for i in range(len(scene.names))], axis=0)
    assert grey[2] < 0.5 * grey[1]
    assert float(illuminant.angular_error_deg(grey, cam)) < 20.0
    # the reference is the white-lit render: reused, not rendered again
    assert cycles.simulate_cycles("cycles_sodium_room", out, width=64, height=48,
                                  n_frames=3, samples=4) == out


def test_the_truth_rebuilds_a_path_traced_captures_clean_raw(tmp_path, monkeypatch):
    """truth.clean_mean of a path-traced capture (its light applied in sRGB, no kelvin) is
    the mean its raw frames scatter around: the noise fitted on it finds the sensor's K.
    Blender stands in for a smooth synthetic white render (no Blender needed)."""
    from gridnerf import noisefit
    from gridnerf.sim.truth import clean_mean, noise_truth

    def render_views(spec, poses, intr, samples, seed, workdir):
        y, x = np.mgrid[0:intr.h, 0:intr.w] / max(intr.h, intr.w)
        base = np.stack([0.2 + 0.6 * x, 0.3 + 0.5 * y, 0.5 + 0.3 * x * y], -1)
        return np.stack([base * (0.8 + 0.1 * i) for i in range(len(poses))]).astype(np.float32)

    monkeypatch.setattr(cycles, "render_views", render_views)
    out = cycles.simulate_cycles("cycles_sodium_room", tmp_path / "c", width=96, height=64,
                                 n_frames=4, samples=1)
    fit, scale = noisefit.fit_scene(out, clean_mean(out))
    truth = noise_truth(out)
    got = fit.in_dn(scale)
    assert fit.converged
    assert got["K_dn_per_electron"] == pytest.approx(truth["K_dn_per_electron"], rel=0.1)
