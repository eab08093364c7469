"""Black level from lens-cap frames: recovery of the simulator's hidden offsets, the
frames it refuses, and that a run's measured black level reaches every load of its scene."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import sim_near_far

from gridnerf import darkframes, data_term, dng, raw, runfolder
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
    # a run whose plan says black_level = file ignores a left-over measurement
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


# ---------------------------------------------------------------- which black level


def test_signal_per_colour_and_the_offsets_share_of_it():
    cfa = np.array([[0, 1], [1, 2]])  # RGGB
    black = np.full((2, 2), 512.0)
    frame = np.tile(np.array([[512 + 40, 512 + 20], [512 + 22, 512 + 8]], np.uint16), (4, 6))
    scene = type("S", (), {"cfa": cfa, "train_idx": np.array([0, 1]),
                           "raw_bayer": np.stack([frame, frame]),
                           "black_level": np.stack([black, black])})()
    np.testing.assert_allclose(darkframes.signal_dn(scene), [40.0, 21.0, 8.0])
    share = darkframes.offset_share(darkframes.signal_dn(scene))
    assert share == pytest.approx(darkframes.OFFSET_DN / 8.0)
    scene.black_level = scene.black_level + np.array([[0.0, 0.0], [0.0, 8.0]])
    share = darkframes.offset_share(darkframes.signal_dn(scene))
    assert share == float("inf")  # blue at the black level


def _gate(folder, run, capsys, *overrides):
    """data_term.black_level on a fresh run: (its decision, the scene with the black level
    the decision gives, what it printed)."""
    from gridnerf import config as cfgmod

    cfg = cfgmod.override(cfgmod.preset("default"), list(overrides))
    plain = _loaded(folder)
    what = data_term.black_level(folder, run, cfg, plain)
    assert what in ("file", "lens_cap")
    scene = darkframes.apply(plain, darkframes.load(run)) if what == "lens_cap" else plain
    return what, scene, capsys.readouterr().out


def test_lens_cap_frames_that_show_the_files_level_off_replace_it(tmp_path, capsys,
                                                                 monkeypatch):
    from gridnerf.sim import simulate_scene

    folder = simulate_scene("bucket", tmp_path / "dim", width=128, height=72, n_frames=3,
                            light=0.05)
    truth = np.array(json.loads((folder / "sim.json").read_text())
                     ["noise"]["black_bias_dn_per_cfa_position"])
    share = darkframes.offset_share(darkframes.signal_dn(_loaded(folder)))
    assert share > data_term.LENS_CAP_SHARE
    for name in ("run", "dark", "within", "odd", "bare"):
        (tmp_path / name).mkdir()
    run = tmp_path / "run"
    what, scene, out = _gate(folder, run, capsys)  # the default: the file's, checked
    assert what == "lens_cap"
    assert "black level from the lens-cap frames" in out and len(out.splitlines()) == 1
    offset = darkframes.load(run)  # kept for training, resume and eval
    np.testing.assert_allclose(scene.black_level - _loaded(folder).black_level,
                               np.broadcast_to(offset, scene.black_level.shape), atol=1e-3)
    np.testing.assert_allclose(offset, truth, atol=1.0)
    # data.black_offset = dark: the same frames, the same offsets
    dark = tmp_path / "dark"
    what, _, out = _gate(folder, dark, capsys, "data.black_offset=dark")
    assert what == "lens_cap" and out.startswith("black level from the lens-cap frames")
    np.testing.assert_allclose(darkframes.load(dark), offset, atol=1e-9)
    # offsets that move no colour's mean by more than OFFSET_MATTERS: the file's, said once
    monkeypatch.setattr(data_term, "OFFSET_MATTERS", 1e9)
    what, scene, out = _gate(folder, tmp_path / "within", capsys)
    assert what == "file" and out.startswith("black level: the file's")
    assert len(out.splitlines()) == 1 and darkframes.load(tmp_path / "within") is None
    assert np.array_equal(scene.black_level, _loaded(folder).black_level)
    monkeypatch.undo()
    # lens-cap frames that cannot serve: one warning naming the frame, the file's level
    like = next((folder / "raw").iterdir())
    _write_dark(folder, "dark_000.dng", np.full((36, 64), 512, np.uint16), like)
    odd = tmp_path / "odd"
    what, scene, out = _gate(folder, odd, capsys)
    assert what == "file"
    assert out.startswith("warning:") and "dark_000.dng" in out and "cannot serve" in out
    assert len(out.splitlines()) == 1 and darkframes.load(odd) is None
    # with data.black_offset = dark such frames stop the run
    with pytest.raises(SceneError, match="dark_000.dng"):
        _gate(folder, tmp_path / "odd", capsys, "data.black_offset=dark")
    # no lens-cap frames under a weak signal: one warning naming the folder to shoot them into
    shutil.rmtree(folder / "dark")
    bare = tmp_path / "bare"
    what, scene, out = _gate(folder, bare, capsys)
    assert what == "file"
    assert out.startswith("warning:") and str(folder / "dark") in out
    assert darkframes.load(bare) is None


def test_a_colours_shift_is_its_mean_offset_over_its_mean_signal():
    cfa = np.array([[0, 1], [1, 2]])  # RGGB
    offset = np.array([[1.0, 2.0], [-1.0, 3.0]])  # green's two positions average to 0.5
    assert darkframes.offset_shift(offset, cfa, [100.0, 10.0, 60.0]) == pytest.approx(0.05)
    assert darkframes.offset_shift(offset, cfa, [100.0, 10.0, 0.0]) == float("inf")


def test_at_a_scenes_own_light_its_lens_cap_frames_are_checked_and_used(
        small_scene, tmp_path, capsys):
    assert darkframes.offset_share(darkframes.signal_dn(_loaded(small_scene))) < 0.5
    what, scene, out = _gate(small_scene, tmp_path, capsys)
    assert what == "lens_cap" and out.startswith("black level from the lens-cap frames")
    assert "of a colour's mean signal off the file's" in out


def test_a_dim_capture_trains_and_evaluates_with_its_lens_cap_black_level(tmp_path, capsys):
    """End to end at a twentieth of bucket's light (under 1 electron per pixel): the gate
    and the downscaled estimates both act, training keeps the offsets, evaluation reads
    them back, and every number that comes out is finite."""
    from gridnerf import config as cfgmod
    from gridnerf.eval_run import evaluate_run, load_run
    from gridnerf.sim import simulate_scene
    from gridnerf.train import train

    folder = simulate_scene("bucket", tmp_path / "dim", width=128, height=72, n_frames=6,
                            light=0.05)
    run = tmp_path / "run"
    summary = train(folder, run, cfgmod.preset("tiny"))
    out = capsys.readouterr().out
    assert "black level from the lens-cap frames" in out and "downscaled" in out
    truth = np.array(json.loads((folder / "sim.json").read_text())
                     ["noise"]["black_bias_dn_per_cfa_position"])
    np.testing.assert_allclose(summary["black_offset_dn"], truth, atol=1.0)
    _, plan, scene, *_ = load_run(run)
    assert plan.black_level == "lens_cap"  # kept in the run plan: resume and eval read it
    np.testing.assert_allclose(scene.black_level - _loaded(folder).black_level,
                               np.broadcast_to(darkframes.load(run), scene.black_level.shape),
                               atol=1e-3)
    metrics = evaluate_run(run)["summary"]
    assert all(np.isfinite(v) for out in metrics.values() if isinstance(out, dict)
               for v in out.values() if isinstance(v, float))
