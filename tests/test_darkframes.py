"""Black level from lens-cap frames: recovery of the simulator's hidden offsets, the
frames it refuses, and that a run's measured black level reaches every load of its scene."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import sim_near_far

from gridnerf import darkframes, dng, raw, runfolder
from gridnerf.errors import SceneError
from gridnerf.scene import load_scene


@pytest.fixture()
def scene_copy(small_scene, tmp_path):
    """A writable copy of the small simulated scene (its dark/ frames included)."""
    return shutil.copytree(small_scene, tmp_path / "scene")


def _loaded(folder):
    return load_scene(folder, near_far=sim_near_far(folder))


def _write_dark(folder, name, raw_bayer, like):
    frame = raw.read_raw(like)
    dng.write_dng(folder / "dark" / name, raw_bayer, frame.cfa, frame.black_level,
                  int(frame.white_level), frame.xyz_to_cam, np.ones(3),
                  exposure_time=frame.exposure_time, iso=frame.iso)


def test_measures_the_hidden_offsets(small_scene):
    truth = np.array(json.loads((small_scene / "sim.json").read_text())
                     ["noise"]["black_bias_dn_per_cfa_position"])
    got = darkframes.measure(small_scene)
    # 2 frames of 160x90: 7200 photosites per CFA position, ~7.3 DN of read noise each
    np.testing.assert_allclose(got["offset_dn"], truth, atol=0.4)
    assert 6.0 < got["read_sigma_dn"] < 9.0
    assert got["files"] == ["dark_000.dng", "dark_001.dng"]


def test_hot_and_dead_photosites_do_not_move_the_offsets(scene_copy):
    clean = darkframes.measure(scene_copy)
    like = next((scene_copy / "raw").iterdir())
    path = scene_copy / "dark" / "dark_000.dng"
    dark = raw.read_raw(path).raw_bayer.copy()
    rng = np.random.default_rng(0)
    v, u = rng.integers(0, dark.shape[0], 40), rng.integers(0, dark.shape[1], 40)
    dark[v[:30], u[:30]] = 16383  # hot
    dark[v[30:], u[30:]] = 0  # dead
    _write_dark(scene_copy, "dark_000.dng", dark, like)
    got = darkframes.measure(scene_copy)
    np.testing.assert_allclose(got["offset_dn"], clean["offset_dn"], atol=0.05)
    assert abs(got["read_sigma_dn"] - clean["read_sigma_dn"]) < 0.1


def test_apply_shifts_the_normalised_frames_by_the_offsets(small_scene):
    scene = _loaded(small_scene)
    offset = np.array([[1.0, -2.0], [3.0, 0.5]])
    moved = darkframes.apply(scene, offset)
    raw_dn = scene.raw_bayer[0].astype(np.float64)
    black = np.tile(scene.black_level[0] + offset, (raw_dn.shape[0] // 2, raw_dn.shape[1] // 2))
    expected = (raw_dn - black) / (scene.white_level[0] - black)
    np.testing.assert_allclose(moved.raw_normalized(0), expected, rtol=1e-5, atol=1e-7)
    assert moved.raw_bayer is scene.raw_bayer  # the frames are not copied


def test_refuses_missing_lit_and_odd_dark_frames(scene_copy):
    like = next((scene_copy / "raw").iterdir())
    assert darkframes.has_dark_frames(scene_copy)  # the simulator writes two
    shutil.rmtree(scene_copy / "dark")
    assert not darkframes.has_dark_frames(scene_copy)
    with pytest.raises(SceneError, match="no dark frames|there are none"):
        darkframes.measure(scene_copy)
    (scene_copy / "dark").mkdir()
    lit = raw.read_raw(like).raw_bayer.copy()  # a frame of the scene: light reached it
    lit += np.uint16(400)
    _write_dark(scene_copy, "dark_000.dng", lit, like)
    with pytest.raises(SceneError, match="dark_000.dng.*is not dark"):
        darkframes.measure(scene_copy)
    small = np.full((40, 60), 512, np.uint16)
    _write_dark(scene_copy, "dark_000.dng", small, like)
    with pytest.raises(SceneError, match="dark_000.dng.*60x40"):
        darkframes.measure(scene_copy)


def test_a_runs_measured_black_level_reaches_its_scene(small_scene, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    near, far = sim_near_far(small_scene)
    (run / runfolder.BOUNDS).write_text(json.dumps({"near": near, "far": far}))
    plain = runfolder.open_scene(small_scene, run)
    darkframes.save(run, {"offset_dn": [[2.0, 2.0], [2.0, 2.0]], "files": []})
    shifted = runfolder.open_scene(small_scene, run, dark=True)
    np.testing.assert_allclose(shifted.black_level, plain.black_level + 2.0)
    # a run whose config says data.black_offset=file ignores a left-over measurement
    np.testing.assert_array_equal(runfolder.open_scene(small_scene, run).black_level,
                                  plain.black_level)
    (run / darkframes.BLACK_LEVEL).write_text("{}")
    with pytest.raises(SceneError, match="black_level.json"):
        runfolder.open_scene(small_scene, run, dark=True)


def test_training_without_dark_frames_stops_with_one_line(scene_copy, tmp_path, capsys):
    from gridnerf import cli

    shutil.rmtree(scene_copy / "dark")
    run = tmp_path / "run"
    code = cli.main(["train", str(scene_copy), "--out", str(run), "--preset", "fast",
                     "--set", "data.black_offset=dark"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
    assert "dark" in err and "lens cap" in err
    assert not run.exists()  # nothing half-written
