"""A camera's quirks in the simulator (sensor.SensorParams: bits, vignette_stops,
exposure_jitter_stops, hot_pixels) and the held-out quirky-camera scenes (HELDOUT_QUIRK):
each quirk checked against a twin capture that differs from it in that quirk alone."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import OpenEXR
import pytest
import rawpy
import tifffile

from gridnerf import cli
from gridnerf.scene import load_scene
from gridnerf.sim import HELDOUT, HELDOUT_QUIRK, simulate_scene, writer
from gridnerf.sim import scenes as sc
from gridnerf.sim import sensor as sn
from gridnerf.sim.capture import camera_path

SIZE = {"width": 160, "height": 90, "n_frames": 6, "seed": 0}
BASE = "bucket"  # the scene the variants re-shoot
NO_BIAS = ((0.0, 0.0), (0.0, 0.0))  # no hidden black offset: levels compare exactly
# variant -> SensorParams changes of BASE (every variant without the hidden bias)
VARIANTS = {
    "clean": {},
    "coarse": {"cfa_pattern": "BGGR", "bits": 12},
    "jitter": {"exposure_jitter_stops": 1.0 / 3.0},
    "vignette": {"vignette_stops": 1.5},
}
QUIRK = "held_quirk_table"


@pytest.fixture(scope="module")
def variants(tmp_path_factory):
    """{variant: scene folder} of BASE shot by the VARIANTS cameras (same cameras, light
    and photon budget: only the sensor differs)."""
    root = tmp_path_factory.mktemp("quirk_variants")
    base = sc.build_scene(BASE)
    out = {}
    for key, change in VARIANTS.items():
        spec = replace(base, sensor=replace(base.sensor, bias=NO_BIAS, **change))
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(writer, "build_scene", lambda name, spec=spec: spec)
            out[key] = simulate_scene(BASE, root / key, **SIZE)
    return out


@pytest.fixture(scope="module")
def quirk_pair(tmp_path_factory):
    """(QUIRK folder, its clean-camera twin's folder), both at SIZE."""
    root = tmp_path_factory.mktemp("quirk_pair")
    twin = sc.build_scene(QUIRK).twin_of
    return (simulate_scene(QUIRK, root / QUIRK, **SIZE),
            simulate_scene(twin, root / twin, **SIZE))


def _manifest(folder):
    return json.loads((folder / "sim.json").read_text())


def _load(folder):
    from conftest import sim_near_far

    return load_scene(folder, near_far=sim_near_far(folder))


def _levels(path):
    """(rawpy black per CFA position, rawpy white, tifffile BlackLevel (4,), WhiteLevel,
    ExposureTime s) of one DNG."""
    with rawpy.imread(str(path)) as r:
        black = np.array(r.black_level_per_channel)[np.array(r.raw_pattern)].ravel()
        white = r.white_level
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        bl = np.array(tags[50714].value, float)
        time = tags[33434].value
        return black, white, bl[0::2] / bl[1::2], tags[50717].value, time[0] / time[1]


def _binned_means(scene):
    """(N, 3) mean normalised binned camera RGB of every frame of a loaded scene."""
    return np.stack([scene.rgb_cam_binned(i)[0].reshape(-1, 3).mean(axis=0)
                     for i in range(len(scene.names))]).astype(np.float64)


def _raw(path):
    with rawpy.imread(str(path)) as r:
        return r.raw_image_visible.copy()


# ---------------------------------------------------------------- defaults


def test_defaults_are_the_clean_camera_and_draw_nothing():
    params = sn.SensorParams()
    assert (params.bits, params.black_level, params.white_level, params.dn_scale) == (
        14, sn.BLACK_LEVEL, sn.WHITE_LEVEL, 1.0)
    rng = np.random.default_rng(7)
    assert np.array_equal(sn.exposure_factors(params, 5, rng), np.ones(5))
    assert sn.draw_defects(params, 90, 160, rng) is None
    assert rng.random() == np.random.default_rng(7).random()  # no draw was made
    assert writer.quirks_manifest(params, writer.draw_quirks(params, 5, 90, 160, 0, 1)) == {}
    np.testing.assert_array_equal(sn.vignette_gain(9, 16, 0.0), np.ones((9, 16)))
    with pytest.raises(ValueError, match="bits"):
        sn.SensorParams(bits=13)
    with pytest.raises(ValueError, match="hot_pixels"):
        sn.SensorParams(hot_pixels=-1)


# ---------------------------------------------------------------- bit depth


@pytest.mark.parametrize("bits", [12, 10])
def test_coarser_adc_keeps_the_photon_statistics(bits):
    """The same flat field at 14 and at `bits` bits: in electrons, the same mean and the
    same variance (shot + read noise, both scaled with the ADC; rounding's 1/12 DN^2 out)."""
    electrons = np.full((200, 200), 20.0)
    stats = {}
    for b in (14, bits):
        params = sn.SensorParams(bits=b, bias=NO_BIAS)
        dn = sn.expose(electrons, params, np.random.default_rng(3)).astype(np.float64)
        k = params.k_gain * params.dn_scale
        signal = dn - params.black_level
        stats[b] = (signal.mean() / k, (signal.var() - 1.0 / 12.0) / k**2, dn.max())
    assert sn.SensorParams(bits=bits).black_level == {12: 256, 10: 64}[bits]
    assert sn.SensorParams(bits=bits).white_level == 2**bits - 1
    assert stats[bits][0] == pytest.approx(stats[14][0], rel=0.01)
    assert stats[bits][0] == pytest.approx(20.0, rel=0.01)
    assert stats[bits][1] == pytest.approx(stats[14][1], rel=0.04)
    assert stats[bits][2] <= 2**bits - 1


def test_twelve_bit_bggr_capture_matches_its_fourteen_bit_rggb_twin(variants):
    """The DNG records the 12-bit levels, the loader reads BGGR, and the normalised binned
    camera RGB is the 14-bit RGGB twin's to within the black pedestal: 256 of 4095 takes a
    larger share of the range than 512 of 16383, so the 12-bit level is
    (16383 - 512) / 4 / (4095 - 256) = 1.034 times the 14-bit one. Green sits on the same
    photosites in both layouts (within noise, 0.5 %); red and blue swap sites, which sample
    the scene's texture half a binned pixel apart (up to 2 % on these small frames)."""
    clean, coarse = _load(variants["clean"]), _load(variants["coarse"])
    assert clean.cfa.tolist() == [[0, 1], [1, 2]] and coarse.cfa.tolist() == [[2, 1], [1, 0]]
    black, white, tag_black, tag_white, _ = _levels(variants["coarse"] / "raw" / "frame_002.dng")
    np.testing.assert_array_equal(black, [256] * 4)
    np.testing.assert_array_equal(tag_black, [256] * 4)
    assert white == tag_white == 4095
    np.testing.assert_array_equal(coarse.black_level, 256.0)
    np.testing.assert_array_equal(coarse.white_level, 4095.0)
    assert int(coarse.raw_bayer.max()) <= 4095
    manifest = _manifest(variants["coarse"])
    assert (manifest["bits"], manifest["black_level"], manifest["white_level"]) == (12, 256, 4095)
    assert manifest["K_dn_per_electron"] == pytest.approx(_manifest(variants["clean"])[
        "K_dn_per_electron"] / 4)
    ratio = _binned_means(coarse).mean(axis=0) / _binned_means(clean).mean(axis=0)
    pedestal = (16383 - 512) / 4 / (4095 - 256)
    assert ratio[1] == pytest.approx(pedestal, rel=0.005)
    np.testing.assert_allclose(ratio, pedestal, rtol=0.03)
    assert ratio.mean() == pytest.approx(1.0, rel=0.05)


# ---------------------------------------------------------------- exposure jitter


def test_exposure_jitter_is_in_the_files_and_the_loader_undoes_it(variants):
    folder = variants["jitter"]
    manifest = _manifest(folder)
    nominal = manifest["exposure_time_s"]
    times = np.array([_levels(folder / "raw" / f"{n}.dng")[4] for n in manifest["frames"]])
    stops = np.log2(times / nominal)
    assert np.all(np.abs(stops) <= 1.0 / 3.0 + 1e-6) and np.ptp(stops) > 0.1
    np.testing.assert_allclose(times, manifest["exposure_jitter"]["exposure_time_s_per_frame"],
                               rtol=1e-6)
    dark_time = _levels(folder / "dark" / "dark_000.dng")[4]
    assert dark_time == pytest.approx(times[0], rel=1e-6)  # darkframes' settings check
    clean_times = [_levels(variants["clean"] / "raw" / f"{n}.dng")[4] for n in manifest["frames"]]
    np.testing.assert_allclose(clean_times, nominal, rtol=1e-6)

    jitter, clean = _load(folder), _load(variants["clean"])
    np.testing.assert_allclose(jitter.exposure, times / np.median(times), rtol=1e-6)
    np.testing.assert_array_equal(clean.exposure, 1.0)
    # frame by frame, the jittered level over the clean twin's follows the exposure ...
    level = np.log2(_binned_means(jitter).mean(axis=1) / _binned_means(clean).mean(axis=1))
    assert np.ptp(level) > 0.1
    np.testing.assert_allclose(level - level.mean(), stops - stops.mean(), atol=0.03)
    # ... and the trainer's normalisation (divide by scene.exposure) makes the frames agree
    agreed = level - np.log2(jitter.exposure)
    assert np.ptp(agreed) < 0.04


# ---------------------------------------------------------------- vignetting


@pytest.mark.parametrize("stops", [0.5, 1.0, 1.5])
def test_vignette_gain_darkens_the_corners_by_the_set_stops(stops):
    r = np.linspace(0.0, 1.0, 101)
    falloff = sn.vignette_falloff(r, stops)
    assert falloff[0] == 1.0 and falloff[-1] == pytest.approx(2.0**-stops, rel=1e-12)
    assert np.all(np.diff(falloff) < 0)
    c = sn.vignette_coefficient(stops)  # its inverse is FixVignetteRadial's polynomial
    np.testing.assert_allclose(1.0 / falloff, 1 + 2 * c * r**2 + c * c * r**4, rtol=1e-12)
    gain = sn.vignette_gain(90, 160, stops)
    assert gain.shape == (90, 160)
    np.testing.assert_allclose(gain, gain[::-1, ::-1], rtol=1e-12)  # radial about the centre
    assert gain.max() == pytest.approx(1.0, abs=1e-3)
    corners = gain[[0, 0, -1, -1], [0, -1, 0, -1]]
    np.testing.assert_allclose(np.log2(gain.max() / corners), stops, atol=0.05)


def test_vignetting_darkens_the_raw_and_not_the_references(variants):
    """Raw of the vignetted capture over its twin's: ~1 at the centre, 2**-1.5 towards the
    corners as vignette_gain predicts; the references are the twin's, bit for bit."""
    vig, clean = _load(variants["vignette"]), _load(variants["clean"])
    stack = [np.sum([s.rgb_cam_binned(i)[0].sum(-1) for i in range(len(s.names))], axis=0)
             for s in (vig, clean)]
    gain = sn.vignette_gain(90, 160, 1.5).reshape(45, 2, 80, 2).mean(axis=(1, 3))
    boxes = {"centre": np.s_[15:30, 30:50], "top left": np.s_[:12, :16],
             "bottom right": np.s_[-12:, -16:], "top right": np.s_[:12, -16:]}
    for where, box in boxes.items():
        measured = stack[0][box].sum() / stack[1][box].sum()
        assert np.log2(measured) == pytest.approx(np.log2(gain[box].mean()), abs=0.12), where
    assert np.log2(gain[boxes["centre"]].mean() / gain[boxes["top left"]].mean()) > 0.8
    for name in ("frame_000", "frame_005"):
        a = OpenEXR.File(str(variants["vignette"] / "gt" / f"{name}.exr")).channels()["RGB"]
        b = OpenEXR.File(str(variants["clean"] / "gt" / f"{name}.exr")).channels()["RGB"]
        np.testing.assert_array_equal(a.pixels, b.pixels)
    vignetting = _manifest(variants["vignette"])["vignetting"]
    assert vignetting["stops_at_corners"] == 1.5
    assert vignetting["c"] == pytest.approx(sn.vignette_coefficient(1.5))


# ---------------------------------------------------------------- hot and stuck pixels


def test_hot_pixels_sit_still_in_every_frame_and_the_dark_frames(quirk_pair):
    folder = quirk_pair[0]
    manifest = _manifest(folder)
    defects = manifest["defects"]
    hot = {(y, x) for x, y, _ in defects["hot_xy_dn"]}
    stuck = {(y, x): v for x, y, v in defects["stuck_xy_dn"]}
    assert len(hot) + len(stuck) == defects["count"] == 30 and len(hot) == 15
    assert not hot & set(stuck)
    black, white = manifest["black_level"], manifest["white_level"]
    threshold = black + 0.4 * (white - black)  # hot ones add at least half the range
    bright_stuck = {p for p, v in stuck.items() if v > threshold}
    files = ([folder / "raw" / f"{n}.dng" for n in manifest["frames"]]
             + [folder / p for p in manifest["dark_frames"]])
    for path in files:
        raw_bayer = _raw(path)
        assert raw_bayer.shape == (90, 160)
        bright = {tuple(p) for p in np.argwhere(raw_bayer > threshold).tolist()}
        assert bright == hot | bright_stuck, path.name
        for (y, x), v in stuck.items():
            assert raw_bayer[y, x] == v, path.name
    # the rest of the frame is the twin's sensor: the same signal level away from them
    twin = _raw(quirk_pair[1] / "dark" / "dark_000.dng")
    assert twin.max() < sn.BLACK_LEVEL + 100


def test_defects_are_drawn_once_and_concealed_in_the_previews_only():
    params = sn.SensorParams(bits=12, hot_pixels=9, bias=NO_BIAS)
    defects = sn.draw_defects(params, 36, 64, np.random.default_rng([0, 1, 4]))
    again = sn.draw_defects(params, 36, 64, np.random.default_rng([0, 1, 4]))
    np.testing.assert_array_equal(defects.hot_yx, again.hot_yx)  # the seed fixes them
    assert len(defects.hot_yx) == 5 and len(defects.stuck_yx) == 4
    flat = np.full((36, 64), 20.0)
    raw_bayer = sn.expose(flat, params, np.random.default_rng(0), defects)
    np.testing.assert_array_equal(raw_bayer, sn.apply_defects(
        sn.expose(flat, params, np.random.default_rng(0)), defects, params))
    level = 256 + 20 * params.k_gain * params.dn_scale  # the flat field's DN: 281
    hot = raw_bayer[defects.hot_yx[:, 0], defects.hot_yx[:, 1]]
    assert np.all(hot >= np.minimum(level + defects.hot_dn - 20, 4095))
    np.testing.assert_array_equal(raw_bayer[defects.stuck_yx[:, 0], defects.stuck_yx[:, 1]],
                                  defects.stuck_dn)
    bad = np.concatenate([defects.hot_yx, defects.stuck_yx])
    concealed = sn.conceal_defects(raw_bayer, defects)
    assert np.abs(concealed[bad[:, 0], bad[:, 1]] - level).max() < 20
    good = np.ones(raw_bayer.shape, bool)
    good[bad[:, 0], bad[:, 1]] = False
    np.testing.assert_array_equal(concealed[good], raw_bayer[good])
    assert sn.conceal_defects(raw_bayer, None) is raw_bayer


# ---------------------------------------------------------------- held-out quirky scenes


def test_quirk_scenes_reshoot_a_heldout_twin_with_a_quirky_camera():
    assert set(HELDOUT_QUIRK) == {"held_quirk_brick", "held_quirk_shelf", "held_quirk_table"}
    assert set(HELDOUT_QUIRK) <= set(sc.ALL_SCENES)
    assert len(set(sc.ALL_SCENES)) == len(sc.ALL_SCENES)  # no name taken twice
    cfas = set()
    for name in HELDOUT_QUIRK:
        spec = sc.build_scene(name)
        twin = sc.build_scene(spec.twin_of)
        assert spec.name == name and spec.twin_of in HELDOUT
        assert writer.capture_salt(spec) == writer.capture_salt(twin)
        for field in ("rig", "target", "distance", "height", "yaw_spread_deg", "baseline",
                      "lights", "ambient", "ambient_kelvin"):
            assert getattr(spec, field) == getattr(twin, field), field
        s = spec.sensor
        assert s.bits in (10, 12) and s.vignette_stops >= 1.0
        assert s.exposure_jitter_stops == pytest.approx(1.0 / 3.0) and s.hot_pixels > 0
        assert s.cfa_pattern != twin.sensor.cfa_pattern
        cfas.add(s.cfa_pattern)
        clean = replace(s, cfa_pattern=twin.sensor.cfa_pattern, bits=14, vignette_stops=0.0,
                        exposure_jitter_stops=0.0, hot_pixels=0)
        assert clean == twin.sensor  # light, camera, photon budget, noise, bias: the twin's
    assert len(cfas) == 3


def test_quirk_scene_has_its_twins_cameras_and_references(quirk_pair):
    quirk, twin = quirk_pair
    manifest = _manifest(quirk)
    assert manifest["held_out"] is True and manifest["twin_of"] == "held_arc_table"
    assert "twin_of" not in _manifest(twin)
    poses = [np.array([f["transform_matrix"] for f in json.loads(
        (folder / "transforms.json").read_text())["frames"]]) for folder in (quirk, twin)]
    np.testing.assert_array_equal(poses[0], poses[1])
    spec = sc.build_scene("held_arc_table")
    expected = camera_path(spec, SIZE["n_frames"], np.random.default_rng(
        [SIZE["seed"], writer.capture_salt(spec), 0]))
    np.testing.assert_allclose(poses[0], expected)
    for name in ("frame_001", "frame_004"):
        a = OpenEXR.File(str(quirk / "gt" / f"{name}.exr")).channels()["RGB"].pixels
        b = OpenEXR.File(str(twin / "gt" / f"{name}.exr")).channels()["RGB"].pixels
        np.testing.assert_array_equal(a, b)
    assert manifest["gt_scale"] == _manifest(twin)["gt_scale"]
    scene = _load(quirk)  # loads without leaving frames out
    assert scene.cfa.tolist() == [[1, 2], [0, 1]] and len(scene.train_idx) == 5


def test_cli_simulates_heldquirk_group(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["simulate", "heldquirk", "--width", "64", "--height", "36",
                     "--frames", "2"]) == 0
    for name in HELDOUT_QUIRK:
        folder = tmp_path / "data" / "sim" / name
        manifest = _manifest(folder)
        assert manifest["held_out"] is True and manifest["twin_of"] in HELDOUT
        bits = manifest["bits"]
        black, white, tag_black, tag_white, _ = _levels(folder / "raw" / "frame_001.dng")
        assert white == tag_white == 2**bits - 1
        np.testing.assert_array_equal(black, [sn.BLACK_BY_BITS[bits]] * 4)
        np.testing.assert_array_equal(tag_black, [sn.BLACK_BY_BITS[bits]] * 4)
    assert _manifest(tmp_path / "data" / "sim" / "held_quirk_shelf")["white_level"] == 1023
    assert cli.main(["simulate", "teapot"]) == 2
    assert "heldquirk" in capsys.readouterr().err


def test_the_loader_finds_the_sensor_defects_and_leaves_them_out(quirk_pair, capsys):
    """gridnerf.defects on the quirky capture: the hot pixels and the stuck ones that stand
    out from their neighbours are found at their sensor positions and nothing else; the
    bins that hold them are invalid; the clean twin has none."""
    folder, twin = quirk_pair
    defects = _manifest(folder)["defects"]
    scene = _load(folder)
    assert "defective pixels" in capsys.readouterr().out
    found = {tuple(p) for p in np.argwhere(scene.defects).tolist()}
    hot = {(y, x) for x, y, _ in defects["hot_xy_dn"]}
    stuck = {(y, x) for x, y, _ in defects["stuck_xy_dn"]}
    assert hot <= found <= hot | stuck
    _, valid = scene.rgb_cam_binned(int(scene.train_idx[0]))
    for y, x in found:
        assert not valid[y // 2, x // 2].all()
    assert _load(twin).defects is None
