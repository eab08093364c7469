"""Pose estimation with pycolmap on a simulated scene, and the pose-agreement maths."""

from __future__ import annotations

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gridnerf import cameras as cam_mod
from gridnerf import pose_files
from gridnerf.dng import write_dng
from gridnerf.errors import PoseError
from gridnerf.poses import estimate_poses, pose_agreement, umeyama
from gridnerf.scene import load_scene


def test_estimate_poses_on_simulated_box(tmp_path):
    from gridnerf.sim import simulate_scene

    scene = simulate_scene("box", tmp_path / "box", width=320, height=180, n_frames=12, seed=0)
    from_jpeg = shutil.copytree(scene, tmp_path / "box_jpeg")
    truth, truth_split, _ = pose_files.load_transforms(scene / "transforms.json")

    # Previews made from the RAW frames: registration and accuracy against the true poses
    # (the simulator's transforms.json, moved to transforms.prev.json and compared).
    report = estimate_poses(scene, source="raw")
    print("estimate_poses(source='raw'):", json.dumps(report))
    assert report["total"] == 12 and report["registered"] >= 9
    assert report["registered"] + len(report["dropped"]) == 12
    assert (scene / "sparse" / "0" / "images.bin").is_file()
    assert (scene / "transforms.prev.json").is_file()
    assert report["compared_frames"] == report["registered"] and report["intrinsics"] == "known"
    assert report["rotation_error_deg"] < 1.0 and report["rotation_error_deg_max"] < 2.0
    assert report["position_error_relative"] < 0.15

    cams, split, near_far = pose_files.load_transforms(scene / "transforms.json")
    assert set(cams.names) == set(truth.names) - set(report["dropped"])
    assert split["test"] == [n for n in truth_split["test"] if n in cams.names]
    assert (cams.width, cams.height) == (320, 180)
    np.testing.assert_allclose(cams.fx, truth.fx[0], rtol=1e-5)  # raw-frame pixels
    assert near_far is not None and 0 < near_far[0] < near_far[1]
    loaded = load_scene(scene)
    assert loaded.names == cams.names and loaded.forward_facing

    # The camera-style JPEG previews in images/: registration (accuracy is reported only:
    # on strongly denoised previews it ranged from 0.6 to 8.6 degrees between runs).
    # One preview is corrupt: it is named, with the reason, and left out.
    bad = sorted((from_jpeg / "images").glob("*.jpg"))[5]
    bad.write_bytes(b"\xff\xd8 not a jpeg")
    with pytest.warns(UserWarning, match=f"{bad.name}: its preview image cannot be decoded"):
        jpeg = estimate_poses(from_jpeg)
    print("estimate_poses(source='images'):", json.dumps(jpeg))
    assert "cannot be decoded" in jpeg["dropped"][bad.stem]
    assert jpeg["registered"] >= 8 and (from_jpeg / "sparse" / "0" / "points3D.bin").is_file()


def test_too_few_registered_frames_raise(tmp_path):
    scene = tmp_path / "noise"
    (scene / "raw").mkdir(parents=True)
    (scene / "images").mkdir()
    rng = np.random.default_rng(0)
    for k in range(4):
        write_dng(scene / "raw" / f"f{k}.dng", np.full((32, 48), 600, np.uint16),
                  np.array([[0, 1], [1, 2]]), np.full((2, 2), 512.0), 16383, np.eye(3),
                  np.ones(3))
        iio.imwrite(scene / "images" / f"f{k}.jpg", rng.integers(0, 255, (64, 96, 3), np.uint8))
    with pytest.raises(PoseError, match="registered only") as info:
        estimate_poses(scene)
    assert str(scene / "images") in str(info.value) and "overlap" in str(info.value)
    assert not (scene / "transforms.json").exists()
    for k in range(1, 4):
        (scene / "images" / f"f{k}.jpg").unlink()
    with pytest.raises(PoseError, match="1 of 4 raw frames have a readable preview"):
        estimate_poses(scene)


def test_umeyama_and_pose_agreement():
    rng = np.random.default_rng(1)
    rots = Rotation.random(6, random_state=2).as_matrix()
    centres = rng.normal(size=(6, 3))
    prev = cam_mod.make_cameras("abcdef", np.concatenate([rots, centres[:, :, None]], 2),
                                100, 100, 50, 40, 100, 80)
    # The same rig in another world frame: x' = s R x + t, camera rotations R @ R_i.
    s, r, t = 0.3, Rotation.from_euler("xyz", [0.3, -1.0, 2.0]).as_matrix(), np.array([1, 2, 3])
    new_c2w = np.concatenate([r @ rots, (s * centres @ r.T + t)[:, :, None]], 2)
    new_c2w[2, :, :3] = new_c2w[2, :, :3] @ Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    new = prev.with_c2w(new_c2w)
    scale, rot, trans = umeyama(centres, new_c2w[:, :, 3])
    assert scale == pytest.approx(s) and np.allclose(rot, r) and np.allclose(trans, t)
    agree = pose_agreement(prev, new)
    assert agree["compared_frames"] == 6 and agree["position_error"] < 1e-9
    assert agree["rotation_error_deg_max"] == pytest.approx(2.0, abs=0.4)
    assert agree["rotation_error_deg"] < agree["rotation_error_deg_max"] / 2


def test_raw_previews_conceal_the_sensors_defects(tmp_path, capsys):
    """A hot pixel at one sensor position in every frame is found across the frames and
    concealed in the SfM previews: its blurred dot would be a feature that matches in every
    view with no motion."""
    from gridnerf.poses import raw_defects, raw_preview

    rng = np.random.default_rng(0)
    files = []
    for k in range(6):
        mosaic = rng.normal(2000.0, 20.0, (48, 64)).clip(0, 16383).astype(np.uint16)
        mosaic[20, 30] = 16000  # hot: the same photosite in every frame
        files.append(tmp_path / f"f{k}.dng")
        write_dng(files[-1], mosaic, np.array([[0, 1], [1, 2]]), np.full((2, 2), 512.0),
                  16383, np.eye(3), np.ones(3))
    defects = raw_defects(files)
    assert defects is not None and defects[20, 30] and defects.sum() == 1
    assert "1 defective pixels" in capsys.readouterr().out
    plain = raw_preview(files[0]).astype(float)
    concealed = raw_preview(files[0], defects).astype(float)
    background = np.median(concealed)
    assert plain[19:22, 29:32].max() > background + 30  # the blurred dot
    assert np.abs(concealed[17:24, 27:34] - background).max() < 25
