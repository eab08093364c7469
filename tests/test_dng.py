"""gridnerf.dng: the DNG writer, checked against LibRaw (rawpy) and tifffile directly."""

from __future__ import annotations

import numpy as np
import pytest
import rawpy
import tifffile

from gridnerf import color
from gridnerf.dng import write_dng

BLACK = np.array([[510, 512], [514, 516]])
WHITE = 16383
NEUTRAL = np.array([0.45, 1.0, 0.62])
PATTERNS = {
    "RGGB": [[0, 1], [1, 2]],
    "GRBG": [[1, 0], [2, 1]],
    "BGGR": [[2, 1], [1, 0]],
    "GBRG": [[1, 2], [0, 1]],
}


def _mosaic(seed: int = 0, shape=(64, 96)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, WHITE + 1, shape, dtype=np.uint16)


@pytest.mark.parametrize("name", sorted(PATTERNS))
def test_libraw_reads_back_mosaic_pattern_and_black(tmp_path, name):
    cfa = np.array(PATTERNS[name])
    raw_bayer = _mosaic()
    path = tmp_path / f"{name}.dng"
    write_dng(
        path,
        raw_bayer,
        cfa,
        BLACK,
        WHITE,
        color.CAMERA_XYZ_TO_CAM["Sony ILCE-7SM2"],
        NEUTRAL,
        exposure_time=1 / 30,
        iso=6400,
    )
    with rawpy.imread(str(path)) as raw:
        np.testing.assert_array_equal(raw.raw_image_visible, raw_bayer)
        pattern = np.array(raw.raw_pattern)
        letters = raw.color_desc.decode()
        black_per_channel = np.array(raw.black_level_per_channel)
        assert raw.white_level == WHITE
        wb = np.array(raw.camera_whitebalance[:3])
        shutter = raw.other.shutter_speed
    read_cfa = np.vectorize(lambda i: "RGB".index(letters[i]))(pattern)
    np.testing.assert_array_equal(read_cfa, cfa)
    np.testing.assert_array_equal(black_per_channel[pattern], BLACK)
    # LibRaw's camera multipliers are 1 / AsShotNeutral.
    np.testing.assert_allclose(wb / wb[1], 1.0 / NEUTRAL, rtol=1e-5)
    assert shutter == pytest.approx(1 / 30, rel=1e-6)


def test_tags_are_dng_typed_and_exact(tmp_path):
    path = tmp_path / "tags.dng"
    xyz_to_cam = color.CAMERA_XYZ_TO_CAM["Nikon D850"]
    black = np.array([[510.25, 512.5], [514.75, 516.0]])
    write_dng(
        path,
        _mosaic(1, (32, 48)),
        np.array(PATTERNS["BGGR"]),
        black,
        WHITE,
        xyz_to_cam,
        NEUTRAL,
        iso=3200,
        camera_model="test cam",
    )
    with tifffile.TiffFile(path) as tif:
        assert tif.byteorder == "<"
        page = tif.pages[0]
        tags = page.tags
        assert page.photometric == 32803
        assert page.bitspersample == 16
        assert page.compression == 1
        assert tags[254].value == 0
        assert tuple(tags[33421].value) == (2, 2)
        assert bytes(tags[33422].value) == bytes([2, 1, 1, 0])
        assert bytes(tags[50706].value) == bytes([1, 4, 0, 0])
        assert tags[50708].value == "test cam"
        assert tuple(tags[50713].value) == (2, 2)
        bl = np.array(tags[50714].value, float)
        assert int(tags[50714].dtype) == 5  # RATIONAL
        np.testing.assert_array_equal(bl[0::2] / bl[1::2], black.ravel())
        assert tags[50717].value == WHITE
        cm = np.array(tags[50721].value, float)
        assert int(tags[50721].dtype) == 10  # SRATIONAL
        np.testing.assert_allclose(cm[0::2] / cm[1::2], xyz_to_cam.ravel(), atol=1e-6)
        assert tags[50778].value == 21  # D65
        neutral = np.array(tags[50728].value, float)
        np.testing.assert_allclose(neutral[0::2] / neutral[1::2], NEUTRAL, atol=1e-6)
        assert tags[34855].value == 3200
        assert 33434 not in tags


def test_write_is_atomic_and_overwrites(tmp_path):
    path = tmp_path / "frame.dng"
    cfa = np.array(PATTERNS["RGGB"])
    write_dng(path, _mosaic(2, (24, 24)), cfa, BLACK, WHITE, np.eye(3), NEUTRAL)
    second = _mosaic(3, (24, 24))
    write_dng(path, second, cfa, BLACK, WHITE, np.eye(3), NEUTRAL)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.dng"]
    with rawpy.imread(str(path)) as raw:
        np.testing.assert_array_equal(raw.raw_image_visible, second)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"raw_bayer": np.zeros((32, 32), np.float32)}, "uint16"),
        ({"raw_bayer": np.zeros((16, 32), np.uint16)}, "22"),
        ({"cfa": np.array([[0, 1], [2, 2]])}, "Bayer"),
        ({"black_level": np.array([510, 512])}, "per CFA position"),
        ({"black_level": np.full((2, 2), WHITE)}, "white_level"),
        ({"as_shot_neutral": np.array([0.5, 0.0, 1.0])}, "positive"),
        ({"xyz_to_cam": np.eye(3) * np.nan}, "non-finite"),
    ],
)
def test_bad_inputs_raise_and_write_nothing(tmp_path, change, match):
    args = {
        "raw_bayer": _mosaic(4, (32, 32)),
        "cfa": np.array(PATTERNS["RGGB"]),
        "black_level": BLACK,
        "white_level": WHITE,
        "xyz_to_cam": np.eye(3),
        "as_shot_neutral": NEUTRAL,
    } | change
    path = tmp_path / "bad.dng"
    with pytest.raises(ValueError, match=match):
        write_dng(path, **args)
    assert list(tmp_path.iterdir()) == []


def test_converter_tags_are_off_by_default_and_read_back(tmp_path):
    """DefaultCrop, Orientation, BaselineExposure and an OpcodeList3 holding one
    FixVignetteRadial opcode, as a raw converter writes them; the mosaic reads back as
    before."""
    import struct

    from gridnerf.dng import OPCODE_FIX_VIGNETTE_RADIAL

    cfa = np.array(PATTERNS["RGGB"])
    plain, extra = tmp_path / "plain.dng", tmp_path / "extra.dng"
    raw_bayer = _mosaic(5, (40, 64))
    write_dng(plain, raw_bayer, cfa, BLACK, WHITE, np.eye(3), NEUTRAL)
    k = [0.83, 0.17]
    write_dng(extra, raw_bayer, cfa, BLACK, WHITE, np.eye(3), NEUTRAL,
              default_crop=(2, 4, 60, 32), orientation=6, baseline_exposure=-0.5,
              vignette_k=k, vignette_centre=(0.5, 0.45))
    with tifffile.TiffFile(plain) as tif:
        tags = tif.pages[0].tags
        assert tags[274].value == 1
        assert not {50719, 50720, 50730, 51022} & set(tags.keys())
    with tifffile.TiffFile(extra) as tif:
        tags = tif.pages[0].tags
        assert tags[274].value == 6
        assert tuple(tags[50719].value) == (2, 4) and tuple(tags[50720].value) == (60, 32)
        num, den = tags[50730].value
        assert int(tags[50730].dtype) == 10 and num / den == pytest.approx(-0.5)
        assert int(tags[51022].dtype) == 7  # UNDEFINED
        opcodes = bytes(tags[51022].value)
    count, opcode, *version, flags, size = struct.unpack(">II4BII", opcodes[:20])
    assert (count, opcode, version, flags, size) == (1, OPCODE_FIX_VIGNETTE_RADIAL,
                                                     [1, 3, 0, 0], 0, 56)
    values = struct.unpack(">7d", opcodes[20:])
    np.testing.assert_allclose(values, [0.83, 0.17, 0, 0, 0, 0.5, 0.45])
    assert len(opcodes) == 20 + size
    with rawpy.imread(str(extra)) as raw:
        np.testing.assert_array_equal(raw.raw_image_visible, raw_bayer)
    with pytest.raises(ValueError, match="default_crop"):
        write_dng(tmp_path / "bad.dng", raw_bayer, cfa, BLACK, WHITE, np.eye(3), NEUTRAL,
                  default_crop=(10, 0, 60, 32))
    with pytest.raises(ValueError, match="5 finite"):
        write_dng(tmp_path / "bad.dng", raw_bayer, cfa, BLACK, WHITE, np.eye(3), NEUTRAL,
                  vignette_k=np.ones(6))
    assert not (tmp_path / "bad.dng").exists()
