"""Each camera quirk and converter tag on a tiny simulated capture, loaded against the
clean camera's twin (the same scene, cameras, light and noise streams; only the quirk
differs): load_scene gives the twin's frames, or refuses the capture in one line naming
the file and the reason. One capture with every quirk at once also trains a few steps.

Comparisons are of the binned camera RGB in 14-bit DN of signal (_rgb_cam_dn: normalised
raw x (white - black) / 2**(bits - 14), divided by the frame's relative exposure), which
is K x electrons whatever the bit depth. Where the stored files are the twin's mosaic
turned or padded (crop, orientation, BaselineExposure) the frames must be identical. Where
the quirk changes what the sensor records (another CFA layout, bit depth, falloff,
exposure, defects) the shot and read noise are other draws, so means over the frames or
over 4 x 4 blocks of them are compared: at BRIGHT electrons a block's mean has ~1 % noise
(green; ~2 % for blue, the weakest channel under the scene's 2800 K light); the tolerances
(stated per test) add the differences each quirk makes by construction.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from gridnerf import dng_opcodes
from gridnerf.dng import opcode_list, write_dng
from gridnerf.errors import RawError, SceneError
from gridnerf.scene import load_scene
from gridnerf.sim import converter, simulate_scene, writer
from gridnerf.sim import scenes as sc
from gridnerf.sim import sensor as sn

W, H, N = 64, 36, 6
BASE = "bucket"
# mean green electrons: 4x the scene's budget, so that means are tight (at much more, the
# texture of these tiny frames starts to read as recurring defects in a clean capture)
BRIGHT = 40.0
CLEAN = {"bias": ((0.0, 0.0), (0.0, 0.0)), "electrons": BRIGHT}


def _simulate(root, key, **change):
    """BASE shot at W x H by the clean camera changed by `change` (SensorParams fields)."""
    base = sc.build_scene(BASE)
    spec = replace(base, sensor=replace(base.sensor, **CLEAN, **change))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(writer, "build_scene", lambda name, spec=spec: spec)
        return simulate_scene(BASE, root / key, width=W, height=H, n_frames=N, seed=0)


def _load(folder):
    return load_scene(folder, near_far=tuple(json.loads((folder / "sim.json").read_text())[
        "near_far"]))


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("quirk_matrix")


@pytest.fixture(scope="module")
def twin(root):
    """The clean camera's capture, loaded (and its folder)."""
    folder = _simulate(root, "twin")
    return folder, _load(folder)


def _rgb_cam_dn(scene) -> np.ndarray:
    """(N, H/2, W/2, 3) binned signal in 14-bit DN per unit exposure (module docstring)."""
    dn_scale = 2.0 ** (np.log2(scene.white_level + 1) - 14)
    scale = (scene.white_level - scene.black_level[:, 0, 0]) / dn_scale / scene.exposure
    return np.stack([scene.rgb_cam_binned(i)[0] * scale[i] for i in range(len(scene.names))])


def _blocks(rgb_cam: np.ndarray) -> np.ndarray:
    """(N, h, w, 3) -> (4, 4, 3) mean over all frames in a 4 x 4 grid of blocks (edges
    cropped)."""
    n, h, w, _ = rgb_cam.shape
    bh, bw = h // 4, w // 4
    return rgb_cam[:, :4 * bh, :4 * bw].reshape(n, 4, bh, 4, bw, 3).mean(axis=(0, 2, 4))


def _assert_same_frames(scene, twin_scene):
    np.testing.assert_array_equal(scene.raw_bayer, twin_scene.raw_bayer)
    np.testing.assert_array_equal(scene.cfa, twin_scene.cfa)
    np.testing.assert_array_equal(scene.black_level, twin_scene.black_level)
    np.testing.assert_array_equal(scene.exposure, twin_scene.exposure)
    np.testing.assert_allclose(scene.cameras.c2w, twin_scene.cameras.c2w)
    assert (scene.cameras.width, scene.cameras.height) == (W, H)


# ---------------------------------------------------------------- the sensor's quirks


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_cfa_layouts_read_as_the_twin(root, twin, cfa):
    """The layout is read from the file; the frames' mean red, green and blue match the
    twin's to 3 %, 1 % and 7 % (red and blue, or the greens, sit on other photosites and
    sample the texture half a binned pixel apart: on these 32 x 18 binned frames that moves
    red 2.7 %, blue 5.7 %). A misread layout is far outside: swapping red and blue moves
    them by the capture's red / blue ratio (over 20 %), a green read as red by 80 %."""
    scene = _load(_simulate(root, f"cfa_{cfa}", cfa_pattern=cfa))
    assert scene.cfa.tolist() == [list(r) for r in sn.CFA_PATTERNS[cfa]]
    means, twin_means = _rgb_cam_dn(scene).mean((0, 1, 2)), _rgb_cam_dn(twin[1]).mean((0, 1, 2))
    assert np.all(np.abs(means / twin_means - 1.0) <= [0.03, 0.01, 0.07])
    assert twin_means[0] / twin_means[2] > 1.2 and twin_means[1] / twin_means[0] > 1.5
    if cfa == "RGGB":
        np.testing.assert_array_equal(scene.raw_bayer, twin[1].raw_bayer)


@pytest.mark.parametrize("bits", [10, 12, 14])
def test_bit_depths_read_as_the_twin(root, twin, bits):
    """Black and white levels are the file's; in 14-bit DN the blocks match the twin's to
    1 % (4 % for blue): the same electrons, rounded to fewer levels (at 10 bits one DN is
    16 of the 14-bit ones, a sixth of the blue signal's mean; 2.8 % seen)."""
    scene = _load(_simulate(root, f"bits_{bits}", bits=bits))
    np.testing.assert_array_equal(scene.white_level, 2**bits - 1)
    np.testing.assert_array_equal(scene.black_level, sn.BLACK_BY_BITS[bits])
    ratio = _blocks(_rgb_cam_dn(scene)) / _blocks(_rgb_cam_dn(twin[1]))
    assert np.all(np.abs(ratio - 1.0) <= [0.01, 0.01, 0.04])


def test_exposure_jitter_is_undone_by_the_exposure_times(root, twin):
    """Each frame's own ExposureTime scales it: per unit exposure the frames match the
    twin's up to one factor for the capture (the median frame's), to 1.5 % (other shot
    noise draws; 0.6 % seen)."""
    scene = _load(_simulate(root, "jitter", exposure_jitter_stops=0.5))
    assert np.ptp(np.log2(scene.exposure)) > 0.2
    per_frame = _rgb_cam_dn(scene).mean(axis=(1, 2, 3)) / _rgb_cam_dn(twin[1]).mean(axis=(1, 2, 3))
    np.testing.assert_allclose(per_frame / per_frame.mean(), 1.0, atol=0.015)


def test_hot_pixels_are_mapped_and_left_out(root, twin):
    """The defects are found at their photosites; the frames elsewhere are the twin's
    (valid bins' means to 0.1 %: the defects change no other photosite's draws)."""
    folder = _simulate(root, "hot", hot_pixels=12)
    scene = _load(folder)
    defects = json.loads((folder / "sim.json").read_text())["defects"]
    hot = {(y, x) for x, y, _ in defects["hot_xy_dn"]}
    assert scene.defects is not None
    assert hot <= {tuple(p) for p in np.argwhere(scene.defects).tolist()}
    valid = np.stack([scene.rgb_cam_binned(i)[1] for i in range(N)])
    ratio = _rgb_cam_dn(scene)[valid].mean() / _rgb_cam_dn(twin[1])[valid].mean()
    assert ratio == pytest.approx(1.0, abs=0.001)


# ---------------------------------------------------------------- lens falloff


def _radial(rgb_cam: np.ndarray) -> np.ndarray:
    """(N, h, w, 3) -> (2,) summed signal of the four corner blocks and of the four centre
    blocks."""
    b = _blocks(rgb_cam).sum(-1)
    return np.array([b[[0, 0, 3, 3], [0, 3, 0, 3]].sum(), b[1:3, 1:3].sum()])


@pytest.mark.parametrize("opcode", [False, True])
def test_vignetting_with_and_without_the_files_opcode(root, twin, opcode):
    """Without an opcode the loader keeps the falloff (the trainer estimates it): corners
    over centre are the simulated gain's (3 %); with the FixVignetteRadial the converter
    wrote, the frames are the twin's (corner and centre blocks to 3 %: the corners' shot
    noise, other draws, is amplified by the gain, 2.8x at 1.5 stops; 1.5 % seen)."""
    tags = converter.ConverterTags(vignette_opcode=opcode)
    scene = _load(_simulate(root, f"vignette_{opcode}", vignette_stops=1.5, converter=tags))
    measured = _radial(_rgb_cam_dn(scene)) / _radial(_rgb_cam_dn(twin[1]))
    if opcode:
        assert scene.lens_correction == "FixVignetteRadial (OpcodeList3)"
        np.testing.assert_allclose(measured, 1.0, atol=0.03)
    else:
        assert scene.lens_correction is None
        gain = sn.vignette_gain(H, W, 1.5).reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3))
        rgb_cam = _rgb_cam_dn(twin[1])
        expected = _radial(rgb_cam * gain[None, ..., None]) / _radial(rgb_cam)
        np.testing.assert_allclose(measured, expected, rtol=0.03)


def test_per_cfa_gain_maps_in_opcodelist2_undo_the_falloff(root, twin):
    """A phone's lens-shading correction: four GainMaps (one per CFA position, pitch 2) of
    9 x 16 points sampling 1 / falloff, rewritten into a vignetted capture's frames; the
    frames come back as the twin's (3 %, as with FixVignetteRadial; the bilinear map
    between its points included)."""
    folder = _simulate(root, "gainmap", vignette_stops=1.0)
    points = sn.vignette_gain(H, W, 1.0)[2::4, 2::4]  # 9 x 16 samples at pixel centres
    spacing, origin = (4.0 / H, 4.0 / W), (2.5 / H, 2.5 / W)
    ops = [dng_opcodes.encode_gain_map(1.0 / points, area=(t, left, H, W), pitch=(2, 2),
                                       spacing=spacing, origin=origin)
           for t in (0, 1) for left in (0, 1)]
    for path in sorted((folder / "raw").glob("*.dng")):
        _rewrite(path, opcode_lists={51009: opcode_list(ops)})
    scene = _load(folder)
    assert scene.lens_correction == "GainMap (OpcodeList2)"
    measured = _radial(_rgb_cam_dn(scene)) / _radial(_rgb_cam_dn(twin[1]))
    np.testing.assert_allclose(measured, 1.0, atol=0.03)


# ---------------------------------------------------------------- stored as a converter does


@pytest.mark.parametrize(("margin", "orientation"), [
    ((2, 2, 2, 2), 1), ((1, 3, 2, 0), 1), ((0, 0, 0, 0), 3), ((0, 0, 0, 0), 6),
    ((0, 0, 0, 0), 8), ((3, 1, 0, 2), 6), ((1, 2, 1, 1), 2), ((0, 1, 1, 0), 7),
])
def test_crop_and_orientation_give_the_twins_frames_exactly(root, twin, margin, orientation,
                                                            capsys):
    """The stored mosaic is the twin's turned back and padded (odd margins shift the CFA
    phase): the loader crops, turns and remaps the CFA to the twin's frames, bit for bit,
    and says what it did once."""
    tags = converter.ConverterTags(crop_margin=margin, orientation=orientation)
    folder = _simulate(root, f"geometry_{margin}_{orientation}", converter=tags)
    stored_hw = converter.stored_shape((H, W), tags)
    probe = _rewrite(folder / "raw" / "frame_000.dng", probe=True)
    assert probe.shape == stored_hw
    capsys.readouterr()
    _assert_same_frames(_load(folder), twin[1])
    out = capsys.readouterr().out
    assert out.count("raw files: ") == (any(margin) + (orientation != 1) + 1)
    assert f"frames are {W}x{H} as displayed, CFA RGGB" in out


@pytest.mark.parametrize("baseline", [0.5, (-0.5, 0.0, 0.5, 1.0)])
def test_baseline_exposure_is_recorded_not_applied(root, twin, baseline, capsys):
    folder = _simulate(root, f"baseline_{baseline}",
                       converter=converter.ConverterTags(baseline_exposure=baseline))
    capsys.readouterr()
    scene = _load(folder)
    _assert_same_frames(scene, twin[1])
    np.testing.assert_allclose(scene.baseline_exposure, np.resize(baseline, N))
    out = capsys.readouterr().out
    assert out.count("BaselineExposure") == 1 and ("differing" in out) == (
        not np.isscalar(baseline))


# ---------------------------------------------------------------- refused in one line


def _rewrite(path, probe=False, **kw):
    """Re-write one simulated DNG with extra write_dng arguments (its mosaic, levels and
    tags as stored); probe: return the stored mosaic only."""
    import rawpy
    import tifffile

    with rawpy.imread(str(path)) as r:
        stored = r.raw_image_visible.copy()
    if probe:
        return stored
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        cfa = np.frombuffer(bytes(tags[33422].value), np.uint8).reshape(2, 2)
        black = np.array(tags[50714].value, float)
        black = (black[0::2] / black[1::2]).reshape(2, 2)
        time = tags[33434].value
        white = tags[50717].value
    write_dng(path, stored, cfa, black, white, np.eye(3), np.ones(3),
              exposure_time=time[0] / time[1], **kw)
    return path


def test_refusals_name_the_file_and_the_reason(root, twin, tmp_path):
    import shutil

    def copy(name):
        out = tmp_path / name
        shutil.copytree(twin[0], out)
        return out

    folder = copy("required_opcode")
    _rewrite(folder / "raw" / "frame_002.dng", opcode_lists={
        51022: opcode_list([dng_opcodes.encode(1, b"\0" * 16)])})
    with pytest.raises(RawError) as info:
        _load(folder)
    message = str(info.value)
    assert "frame_002.dng" in message and "WarpRectilinear (OpcodeList3) is required" in message
    assert "\n" not in message

    folder = copy("one_frame_corrected")
    _rewrite(folder / "raw" / "frame_001.dng", vignette_k=[0.3])
    with pytest.raises(SceneError, match=f"1 of {N} frames carry FixVignetteRadial") as info:
        _load(folder)
    assert str(folder / "raw") in str(info.value)

    folder = copy("turned_transforms")  # transforms.json of the stored, not the displayed image
    for path in sorted((folder / "raw").glob("*.dng")):
        _rewrite(path, orientation=6)
    with pytest.raises(SceneError, match=f"{W}x{H} images but the raw frames are {H}x{W}") as info:
        _load(folder)
    assert str(info.value).startswith(str(folder / "transforms.json"))

    folder = copy("optional_opcode")
    for path in sorted((folder / "raw").glob("*.dng")):
        _rewrite(path, opcode_lists={51022: opcode_list([dng_opcodes.encode(14, b"", 1)])})
    _assert_same_frames(_load(folder), twin[1])  # optional: skipped (printed once)


# ---------------------------------------------------------------- a few training steps


def test_a_files_falloff_correction_skips_the_frame_estimate(monkeypatch):
    """Where the plan records the files' correction, the stage-1 estimate is not run (it
    would take a falloff off twice) and the data and plan pass through unchanged."""
    from gridnerf import plan as planmod
    from gridnerf import train, vignetting

    def no_estimate(*args, **kw):
        raise AssertionError("the frame-based falloff estimate ran")

    monkeypatch.setattr(vignetting, "estimate", no_estimate)
    plan = planmod.RunPlan(method="gridnerf", black_level="file", data_noise=None,
                           data_eps=1e-3, colour=planmod.ColourPlan(), opacity=(0.0, 0.0),
                           n_candidates=(0, 0), file_falloff="FixVignetteRadial (OpcodeList3)")
    data = object()
    for stage in (1, 2):
        assert train._vignetting(None, plan, stage, None, None, data, None, 0.0, 1.0, None,
                                 True) == (data, plan)
    assert planmod.from_dict(planmod.to_dict(plan)) == plan


def test_a_quirky_capture_trains_a_few_finite_steps(root, tmp_path, capsys):
    """Every quirk at once (GRBG, 10 bits, exposure jitter, hot pixels, vignetting with its
    opcode, an odd crop, Orientation 6, BaselineExposure): three steps of one stage, without
    gains (the colour path is not what this checks); the losses are finite and the plan
    records the files' falloff correction."""
    from gridnerf import config as cfgmod
    from gridnerf import plan as planmod
    from gridnerf.train import train

    tags = converter.ConverterTags(crop_margin=(1, 3, 2, 0), orientation=6,
                                   vignette_opcode=True, baseline_exposure=0.3)
    folder = _simulate(root, "train", cfa_pattern="GRBG", bits=10, exposure_jitter_stops=0.3,
                       hot_pixels=8, vignette_stops=1.5, converter=tags)
    transforms = json.loads((folder / "transforms.json").read_text())
    transforms["near_far"] = json.loads((folder / "sim.json").read_text())["near_far"]
    (folder / "transforms.json").write_text(json.dumps(transforms))
    cfg = cfgmod.override(cfgmod.preset("tiny"), [
        "grid.resolutions=[[12,12,8]]", "train.steps_per_stage=[3]", "train.log_every=1",
        "loss.gain_model=none"])
    summary = train(folder, tmp_path / "run", cfg)
    losses = [json.loads(line)["loss"]
              for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert len(losses) == 3 and np.all(np.isfinite(losses))
    assert np.isfinite(summary["data_level"]) and summary["data_level"] > 0
    plan = planmod.load(tmp_path / "run")
    assert plan.file_falloff == "FixVignetteRadial (OpcodeList3)" and plan.vignetting is None
    out = capsys.readouterr().out
    assert "frame-based estimate is skipped" in out and "Orientation 6" in out
