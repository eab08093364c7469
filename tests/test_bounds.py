"""Bounds without the user: SfM depth scale, camera-layout fallback, the run's bounds.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gridnerf import bounds, runfolder
from gridnerf.cameras import make_cameras
from gridnerf.scene import BoundsMissing, load_scene


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_pair_scale_recovers_a_similarity():
    rng = np.random.default_rng(0)
    given = rng.normal(size=(6, 3))
    other = (given @ _rotation(1).T) / 3.7 + np.array([5.0, -2.0, 1.0])
    assert bounds.pair_scale(given, other) == pytest.approx(3.7)
    assert bounds.pair_scale(given[:1], other[:1]) is None  # no pair


def _look_at(pos, target):
    f = target - pos
    f /= np.linalg.norm(f)
    x = np.cross(f, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(x, f)
    return np.concatenate([np.stack([x, y, -f], 1), pos[:, None]], 1)


def _cams(c2w):
    n = len(c2w)
    return make_cameras([f"f{i}" for i in range(n)], np.stack(c2w), 100.0, 100.0, 50.0, 40.0,
                        100, 80)


def test_converging_cameras_bracket_the_subject():
    target = np.array([0.0, 0.5, -3.0])
    c2w = [_look_at(np.array([3.0 * np.sin(a), 0.6, 3.0 * np.cos(a) - 3.0]), target)
           for a in np.deg2rad(np.linspace(-18, 18, 9))]
    b = bounds.from_cameras(_cams(c2w))
    assert b.source == "cameras" and b.near < 3.0 < b.far and "converge" in b.detail["how"]


def test_parallel_cameras_fall_back_to_the_spread():
    c2w = [np.concatenate([np.eye(3), np.array([[x], [0.0], [0.0]])], 1)
           for x in np.linspace(-0.5, 0.5, 6)]
    b = bounds.from_cameras(_cams(c2w))
    assert 0 < b.near < b.far and np.isfinite(b.far) and "parallel" in b.detail["how"]


def test_run_folder_estimates_bounds_once_and_reuses_them(small_scene, tmp_path, monkeypatch):
    with pytest.raises(BoundsMissing) as info:
        load_scene(small_scene)
    assert len(info.value.cameras) == 12
    calls = []

    def fake_estimate(scene_dir, cams):
        calls.append(scene_dir)
        return bounds.Bounds(1.5, 9.0, "cameras", {"how": "test"})

    monkeypatch.setattr(bounds, "estimate", fake_estimate)
    run = tmp_path / "run"
    first = runfolder.open_scene(small_scene, run)
    saved = json.loads((run / runfolder.BOUNDS).read_text())
    assert (saved["near"], saved["far"], saved["source"]) == (1.5, 9.0, "cameras")
    second = runfolder.open_scene(small_scene, run)
    assert len(calls) == 1 and second.far == pytest.approx(first.far)
    with pytest.raises(BoundsMissing):
        runfolder.open_scene(small_scene, tmp_path / "other", estimate=False)


class _Image:
    def __init__(self, name):
        self.name, self.has_pose = name, True


class _Rec:
    def __init__(self, names):
        self.images = {i: _Image(f"{n}.png") for i, n in enumerate(names)}


@pytest.mark.parametrize("width, fails, sizes", [
    (1920, False, [bounds.SFM_IMAGE_SIZE]),  # a large capture: SIFT on small previews
    (1920, True, [bounds.SFM_IMAGE_SIZE, None]),  # ... and at full size where that fails
    (bounds.SFM_IMAGE_SIZE, True, [bounds.SFM_IMAGE_SIZE]),  # nothing larger to try
])
def test_sfm_bounds_look_at_small_previews_first(tmp_path, monkeypatch, width, fails, sizes):
    import imageio.v3 as iio

    from gridnerf import poses

    names = ["a", "b", "c"]
    for n in names:
        iio.imwrite(tmp_path / f"{n}.png", np.zeros((width * 9 // 16, width, 3), np.uint8))
    seen = []

    def fake_colmap(image_dir, images, work, model, known, max_image_size=None):
        assert work.is_dir() and not any(work.iterdir())  # each attempt its own folder
        seen.append(max_image_size)
        return None if fails and max_image_size else _Rec(names)

    monkeypatch.setattr(poses, "run_colmap", fake_colmap)
    work = tmp_path / "work"
    work.mkdir()
    rec = bounds._sparse(tmp_path, [f"{n}.png" for n in names], work, None, names)
    assert seen == sizes
    assert (rec is None) == (fails and width <= bounds.SFM_IMAGE_SIZE)


def test_inlier_threshold_is_set_in_the_pixels_sift_sees():
    from gridnerf.poses import inlier_threshold

    assert inlier_threshold(320) == 2.0 and inlier_threshold(480) == 3.0
    assert inlier_threshold(1920) == 4.0  # COLMAP's own from 640 px up
    # SIFT on a 1920-pixel preview scaled to 480: 3 of its pixels, 12 preview pixels
    assert inlier_threshold(1920, 480) == pytest.approx(12.0)
    assert inlier_threshold(480, 960) == 3.0  # a limit above the size changes nothing
