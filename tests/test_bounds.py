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
