"""gridnerf.raw: reading DNGs back, normalisation, saturation, CFA masks and binning."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import tifffile
from test_dng import BLACK, NEUTRAL, PATTERNS, WHITE  # one set of DNG test constants

from gridnerf import color
from gridnerf.dng import write_dng
from gridnerf.errors import RawError
from gridnerf.raw import (
    RawFrame,
    bin2x2,
    bin2x2_mask,
    cfa_from_libraw,
    cfa_masks,
    downscale,
    normalize,
    read_raw,
    saturated_mask,
)


def _write(path, raw_bayer, cfa=PATTERNS["GRBG"], black=BLACK, **kwargs):
    write_dng(
        path, raw_bayer, np.array(cfa), np.asarray(black), WHITE,
        color.CAMERA_XYZ_TO_CAM["Canon EOS 5D Mark IV"], NEUTRAL, **kwargs,
    )  # fmt: skip
    return path


def _mosaic(seed=0, shape=(64, 96)):
    return np.random.default_rng(seed).integers(0, WHITE + 1, shape, dtype=np.uint16)


def _frame(raw_bayer, cfa, black):
    return RawFrame(
        path="mem", raw_bayer=raw_bayer, cfa=np.array(cfa), black_level=np.asarray(black, "f4"),
        white_level=float(WHITE), xyz_to_cam=np.eye(3), as_shot_neutral=np.ones(3),
        exposure_time=None, iso=None,
    )  # fmt: skip


def _write_plain_tiff_cfa(path, dims, pattern, plane, extra=()):
    """A bare DNG written with tifffile, for layouts write_dng refuses to produce."""
    tags = [
        *extra,
        (33421, 3, 2, dims, True),
        (33422, 1, len(pattern), tuple(pattern), True),
        (50706, 1, 4, (1, 4, 0, 0), True),
        (50708, 2, 0, "bare", True),
        (50710, 1, len(plane), tuple(plane), True),
        (50717, 4, 1, WHITE, True),
        (271, 2, 0, "gridnerf", True),
    ]
    raw_bayer = np.full((36, 36), 1000, np.uint16)
    tifffile.imwrite(
        path, raw_bayer, photometric=32803, subfiletype=0, metadata=None, software=False,
        extratags=tags,
    )  # fmt: skip
    return path


@pytest.mark.parametrize("name", sorted(PATTERNS))
def test_read_raw_round_trip(tmp_path, name):
    raw_bayer = _mosaic()
    path = _write(tmp_path / f"{name}.dng", raw_bayer, PATTERNS[name], exposure_time=0.25, iso=800)
    frame = read_raw(path)
    assert frame.path == str(path)
    assert frame.raw_bayer.dtype == np.uint16
    np.testing.assert_array_equal(frame.raw_bayer, raw_bayer)
    np.testing.assert_array_equal(frame.cfa, PATTERNS[name])
    assert frame.black_level.shape == (2, 2)
    np.testing.assert_array_equal(frame.black_level, BLACK)
    assert frame.white_level == WHITE
    np.testing.assert_allclose(
        frame.xyz_to_cam, color.CAMERA_XYZ_TO_CAM["Canon EOS 5D Mark IV"], atol=1e-4
    )
    np.testing.assert_allclose(frame.as_shot_neutral, NEUTRAL, rtol=1e-6)
    assert frame.exposure_time == pytest.approx(0.25)
    assert frame.iso == 800
    with pytest.raises(dataclasses.FrozenInstanceError):
        frame.white_level = 1.0


def test_fractional_black_level_is_exact(tmp_path):
    black = np.array([[510.25, 512.5], [514.75, 516.0]])
    frame = read_raw(_write(tmp_path / "frac.dng", _mosaic(1), PATTERNS["BGGR"], black))
    np.testing.assert_array_equal(frame.black_level, black.astype(np.float32))
    assert frame.exposure_time is None and frame.iso is None


def test_missing_tags_use_documented_fallbacks(tmp_path):
    path = _write_plain_tiff_cfa(tmp_path / "bare.dng", (2, 2), [1, 0, 2, 1], (0, 1, 2))
    frame = read_raw(path)
    np.testing.assert_array_equal(frame.cfa, PATTERNS["GRBG"])
    np.testing.assert_allclose(frame.xyz_to_cam, np.linalg.inv(color.XYZ_FROM_SRGB))
    np.testing.assert_allclose(frame.as_shot_neutral, np.ones(3))


def test_d65_color_matrix_is_chosen(tmp_path):
    def srational(m):
        return tuple(v for x in np.ravel(m) for v in (round(x * 10000), 10000))

    cm_a = color.CAMERA_XYZ_TO_CAM["Nikon D850"]
    cm_d65 = color.CAMERA_XYZ_TO_CAM["Sony ILCE-7SM2"]
    extra = [
        (50721, 10, 9, srational(cm_a), True),
        (50722, 10, 9, srational(cm_d65), True),
        (50778, 3, 1, 17, True),  # Standard light A
        (50779, 3, 1, 21, True),  # D65
        (50728, 5, 3, (1, 2, 1, 1, 3, 4), True),
    ]
    path = _write_plain_tiff_cfa(tmp_path / "two.dng", (2, 2), [0, 1, 1, 2], (0, 1, 2), extra)
    frame = read_raw(path)
    np.testing.assert_allclose(frame.xyz_to_cam, cm_d65, atol=1e-6)
    np.testing.assert_allclose(frame.as_shot_neutral, [0.5, 1.0, 0.75])


def test_normalize_exact_and_keeps_negatives():
    cfa = PATTERNS["GRBG"]
    raw_bayer = np.array([[500, 512, 600, 16383], [514, 400, 0, 1000]], np.uint16)
    raw_bayer = np.tile(raw_bayer, (2, 1))
    black = np.array([[510.5, 512.0], [514.0, 516.25]])
    out = normalize(_frame(raw_bayer, cfa, black))
    assert out.dtype == np.float32 and out.shape == raw_bayer.shape
    black_full = np.tile(black, (2, 2))
    expected = (raw_bayer - black_full) / (WHITE - black_full)
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-7)
    assert out[0, 0] < 0 and out[1, 1] < 0 and out[1, 2] < 0
    assert out[0, 1] == 0.0
    assert out[0, 3] == pytest.approx(1.0)


def test_saturated_mask_marks_white_level():
    raw_bayer = np.full((4, 6), 1000, np.uint16)
    raw_bayer[1, 2] = WHITE
    raw_bayer[3, 5] = WHITE + 1
    raw_bayer[0, 0] = WHITE - 1
    mask = saturated_mask(_frame(raw_bayer, PATTERNS["RGGB"], BLACK))
    assert mask.dtype == bool
    assert sorted(zip(*np.nonzero(mask), strict=True)) == [(1, 2), (3, 5)]


@pytest.mark.parametrize("name", sorted(PATTERNS))
def test_cfa_masks_one_hot_matches_pattern(name):
    cfa = np.array(PATTERNS[name])
    masks = cfa_masks(cfa, 5, 7)
    assert masks.shape == (5, 7, 3) and masks.dtype == np.float32
    np.testing.assert_array_equal(masks.sum(-1), 1.0)
    for y in range(5):
        for x in range(7):
            assert masks[y, x, cfa[y % 2, x % 2]] == 1.0


@pytest.mark.parametrize("name", sorted(PATTERNS))
def test_bin2x2_constant_per_channel(name):
    cfa = np.array(PATTERNS[name])
    values = np.array([0.25, -0.5, 3.0], np.float32)
    raw_bayer = (cfa_masks(cfa, 9, 11) @ values).astype(np.float32)
    rgb_cam = bin2x2(raw_bayer, cfa)
    assert rgb_cam.shape == (4, 5, 3) and rgb_cam.dtype == np.float32
    np.testing.assert_array_equal(rgb_cam, np.broadcast_to(values, (4, 5, 3)))


def test_bin2x2_averages_greens():
    cfa = np.array(PATTERNS["GBRG"])
    raw_bayer = np.array([[10, 20], [30, 40]], np.uint16)  # G B / R G
    np.testing.assert_array_equal(bin2x2(raw_bayer, cfa)[0, 0], [30.0, 25.0, 20.0])


def test_bin2x2_mask_invalidates_saturated_block():
    cfa = np.array(PATTERNS["GRBG"])
    valid = np.ones((6, 8), bool)
    valid[3, 4] = False  # position (1, 0): blue in GRBG, binned pixel (1, 2)
    valid[0, 7] = False  # position (0, 1): red, binned pixel (0, 3)
    valid[4, 4] = False  # position (0, 0): green, binned pixel (2, 2)
    mask = bin2x2_mask(valid, cfa)
    assert mask.shape == (3, 4, 3) and mask.dtype == bool
    expected = np.ones((3, 4, 3), bool)
    expected[1, 2, 2] = False
    expected[0, 3, 0] = False
    expected[2, 2, 1] = False
    np.testing.assert_array_equal(mask, expected)


def test_downscale():
    img = np.full((10, 13, 3), 0.7, np.float32)
    out = downscale(img, 3)
    assert out.shape == (3, 4, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out, 0.7, rtol=1e-6)
    ramp = np.arange(16, dtype=np.uint16).reshape(4, 4)
    np.testing.assert_array_equal(downscale(ramp, 2), [[2.5, 4.5], [10.5, 12.5]])
    np.testing.assert_array_equal(downscale(ramp, 1), ramp)
    with pytest.raises(ValueError):
        downscale(ramp, 0)
    with pytest.raises(ValueError):
        downscale(ramp, 5)


def test_cfa_from_libraw_maps_letters():
    np.testing.assert_array_equal(cfa_from_libraw([[3, 2], [0, 1]], b"RGBG", "f"), [[1, 2], [0, 1]])
    np.testing.assert_array_equal(cfa_from_libraw([[0, 1], [1, 2]], b"RGBG", "f"), [[0, 1], [1, 2]])
    with pytest.raises(RawError, match="unsupported CFA"):
        cfa_from_libraw(None, b"RGB", "f")


def test_missing_file_raises(tmp_path):
    path = tmp_path / "nope.dng"
    with pytest.raises(RawError, match="file not found") as info:
        read_raw(path)
    assert str(path) in str(info.value) and "simulate" in str(info.value)


def test_directory_raises(tmp_path):
    with pytest.raises(RawError, match="not a file"):
        read_raw(tmp_path)


def test_random_bytes_raise(tmp_path):
    path = tmp_path / "noise.dng"
    path.write_bytes(np.random.default_rng(5).bytes(4096))
    with pytest.raises(RawError, match="LibRaw cannot read it") as info:
        read_raw(path)
    assert str(path) in str(info.value) and "re-copy" in str(info.value)


@pytest.mark.parametrize("keep", [0.5, 0.99])
def test_truncated_dng_raises(tmp_path, keep):
    full = _write(tmp_path / "full.dng", _mosaic(6, (32, 32))).read_bytes()
    path = tmp_path / "cut.dng"
    path.write_bytes(full[: int(len(full) * keep)])
    with pytest.raises(RawError, match="LibRaw cannot read it") as info:
        read_raw(path)
    assert str(path) in str(info.value)


def test_xtrans_and_cmyg_rejected(tmp_path):
    xtrans = [1, 1, 0, 1, 1, 2, 1, 1, 2, 1, 1, 0, 2, 0, 1, 0, 2, 1]
    xtrans += [1, 1, 2, 1, 1, 0, 1, 1, 0, 1, 1, 2, 0, 2, 1, 2, 0, 1]
    cases = {
        "xtrans.dng": ((6, 6), xtrans, (0, 1, 2)),
        "cmyg.dng": ((2, 2), [3, 4, 5, 1], (3, 4, 5, 1)),
    }
    for name, (dims, pattern, plane) in cases.items():
        path = _write_plain_tiff_cfa(tmp_path / name, dims, pattern, plane)
        with pytest.raises(RawError, match="unsupported CFA") as info:
            read_raw(path)
        assert str(path) in str(info.value)
