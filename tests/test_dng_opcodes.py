"""A converter's DNG tags on reading: the opcode lists (gridnerf.dng_opcodes), DefaultCrop
and Orientation (gridnerf.raw_layout), through gridnerf.raw.read_raw on files written by
gridnerf.dng."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from gridnerf import dng_opcodes, raw_layout
from gridnerf.dng import fix_vignette_radial, opcode_list, write_dng
from gridnerf.errors import RawError
from gridnerf.raw import read_raw
from gridnerf.sim import sensor

RGGB = np.array([[0, 1], [1, 2]])
BLACK = np.array([[500.0, 510.0], [520.0, 530.0]])  # distinct: their remapping is seen
WHITE = 16383


def _write(path, raw_bayer, cfa=RGGB, **kw):
    write_dng(path, raw_bayer, cfa, BLACK, WHITE, np.eye(3), np.ones(3), **kw)
    return path


def test_fix_vignette_radial_undoes_the_simulated_falloff_exactly():
    """The simulator's falloff 1 / (1 + c r^2)^2 times the opcode's gain 1 + 2c r^2 + c^2 r^4
    is 1 at every photosite: both put pixels at their centres and normalise r to the
    farthest corner (DNG 1.4 spec, Chapter 7; DNG SDK dng_lens_correction.cpp)."""
    c = sensor.vignette_coefficient(1.5)
    params = fix_vignette_radial([2 * c, c * c])[16:]
    gain = dng_opcodes.vignette_radial_gain(params, 36, 64)
    np.testing.assert_allclose(gain * sensor.vignette_gain(36, 64, 1.5), 1.0, rtol=1e-12)
    off = dng_opcodes.vignette_radial_gain(fix_vignette_radial([1.0], (0.0, 0.0))[16:], 4, 4)
    assert off[0, 0] == pytest.approx(1 + 0.5**2 * 2 / 32) and off[3, 3] == pytest.approx(
        1 + 3.5**2 * 2 / 32)  # centre at the top-left corner: r = 1 at the far corner


def test_gain_map_interpolates_bilinearly_and_clamps_at_its_edges():
    """A 2x2 map whose points sit at the image's quarter positions: pixel centres between
    them are interpolated, pixels outside take the nearest edge value."""
    gains = np.array([[1.0, 2.0], [3.0, 5.0]])
    op = dng_opcodes.encode_gain_map(gains, spacing=(0.5, 0.5), origin=(0.25, 0.25))
    (parsed,) = dng_opcodes.parse_list(opcode_list([op]), "OpcodeList2", "x.dng")
    assert (parsed.name, parsed.optional) == ("GainMap", False)
    gain = dng_opcodes.gain_map_gain(parsed.params, np.zeros((8, 8), int), 1)
    assert gain[0, 0] == 1.0 and gain[7, 7] == 5.0 and gain[0, 7] == 2.0  # clamped
    # row 3 centre 3.5 / 8 = 0.4375: (0.4375 - 0.25) / 0.5 = 0.375 of the way down
    v, h = 0.375, (5.5 / 8 - 0.25) / 0.5
    top, bottom = 1 + h * (2 - 1), 3 + h * (5 - 3)
    assert gain[3, 5] == pytest.approx(top + v * (bottom - top))


def test_per_cfa_gain_maps_and_colour_planes():
    """Four one-point GainMaps in OpcodeList2, one per CFA position (Top/Left 0 or 1, pitch
    2), as phones write them; one three-plane map in OpcodeList3 acts on each photosite by
    its colour; a map limited to an area leaves the rest alone."""
    colour = raw_layout.per_position(RGGB, (0, 0), (6, 8), 1)
    colour = np.tile(colour, (3, 4))
    ops = [dng_opcodes.encode_gain_map([[g]], area=(t, left, 6, 8), pitch=(2, 2))
           for (t, left), g in zip(((0, 0), (0, 1), (1, 0), (1, 1)), (2.0, 3.0, 4.0, 5.0),
                                   strict=True)]
    gain, applied, skipped = dng_opcodes.mosaic_gain({"OpcodeList2": opcode_list(ops)},
                                                     colour, "x.dng")
    np.testing.assert_array_equal(gain, np.tile([[2.0, 3.0], [4.0, 5.0]], (3, 4)))
    assert applied == ("GainMap (OpcodeList2)",) * 4 and skipped == ()
    planes = dng_opcodes.encode_gain_map(np.array([[[2.0, 1.5, 3.0]]]), plane=0, planes=3)
    gain, _, _ = dng_opcodes.mosaic_gain({"OpcodeList3": opcode_list([planes])}, colour, "x")
    np.testing.assert_array_equal(gain, np.choose(colour, [2.0, 1.5, 3.0]))
    part = dng_opcodes.encode_gain_map([[2.0]], area=(2, 2, 4, 8))
    gain, _, _ = dng_opcodes.mosaic_gain({"OpcodeList2": opcode_list([part])}, colour, "x")
    assert gain[2:4, 2:].min() == 2.0 and gain.sum() == 48 + 12


@pytest.mark.parametrize(("where", "opcode", "flags", "outcome"), [
    ("OpcodeList3", 1, 0, "WarpRectilinear (OpcodeList3) is required"),
    ("OpcodeList2", 77, 0, "opcode 77 (OpcodeList2) is required"),
    ("OpcodeList1", 3, 0, "FixVignetteRadial (OpcodeList1) is required"),
    ("OpcodeList3", 1, 1, "WarpRectilinear (OpcodeList3): optional, not applied"),
    ("OpcodeList1", 5, 0, "FixBadPixelsList (OpcodeList1): defective photosites"),
])
def test_opcodes_it_does_not_apply_are_skipped_or_refused(where, opcode, flags, outcome):
    data = opcode_list([dng_opcodes.encode(opcode, b"\0" * 8, flags)])
    colour = np.zeros((4, 4), int)
    if "required" in outcome:
        with pytest.raises(RawError, match="re-export") as info:
            dng_opcodes.mosaic_gain({where: data}, colour, "frame.dng")
        assert str(info.value).startswith("frame.dng: ") and outcome in str(info.value)
        assert "\n" not in str(info.value)
    else:
        gain, applied, skipped = dng_opcodes.mosaic_gain({where: data}, colour, "frame.dng")
        assert gain is None and applied == () and skipped[0].startswith(outcome)


def test_malformed_opcode_lists_are_refused():
    good = opcode_list([dng_opcodes.encode_gain_map([[2.0]])])
    with pytest.raises(RawError, match="malformed OpcodeList2"):
        dng_opcodes.mosaic_gain({"OpcodeList2": good[:-3]}, np.zeros((4, 4), int), "f.dng")
    short = opcode_list([dng_opcodes.encode(dng_opcodes.GAIN_MAP, b"\0" * 80)])
    with pytest.raises(RawError, match="GainMap of"):
        dng_opcodes.mosaic_gain({"OpcodeList2": short}, np.zeros((4, 4), int), "f.dng")
    vignette = opcode_list([dng_opcodes.encode(3, struct.pack(">6d", *[0.0] * 6))])
    with pytest.raises(RawError, match="48 parameter bytes"):
        dng_opcodes.mosaic_gain({"OpcodeList3": vignette}, np.zeros((4, 4), int), "f.dng")


@pytest.mark.parametrize("orientation", range(1, 9))
def test_read_raw_crops_and_turns_the_mosaic_with_its_cfa_and_black(tmp_path, orientation):
    """LibRaw's sizes.flip gives each TIFF Orientation back; the mosaic read is the crop of
    the stored one turned to display orientation, its CFA and per-position black levels
    the stored ones read at the (odd) crop origin and turned alike."""
    stored = np.random.default_rng(orientation).integers(600, 9000, (40, 64), dtype=np.uint16)
    path = _write(tmp_path / "f.dng", stored, default_crop=(3, 1, 57, 34),
                  orientation=orientation, baseline_exposure=-0.5)
    frame = read_raw(path)
    expected = raw_layout.to_display(stored[1:35, 3:60], orientation)
    np.testing.assert_array_equal(frame.raw_bayer, expected)
    colour = raw_layout.to_display(np.tile(RGGB, (20, 32))[1:35, 3:60], orientation)
    black = raw_layout.to_display(np.tile(BLACK, (20, 32))[1:35, 3:60], orientation)
    np.testing.assert_array_equal(frame.cfa, colour[:2, :2])
    np.testing.assert_array_equal(frame.black_level, black[:2, :2])
    c = frame.converted
    assert (c.orientation, c.crop, c.stored_hw, c.baseline_exposure) == (
        orientation, (3, 1, 57, 34), (40, 64), -0.5)


def test_read_raw_applies_the_vignetting_opcode_to_the_linear_mosaic(tmp_path):
    """black + (raw - black) x gain per photosite, rounded; saturated photosites stay at the
    white level, values over it (corrupt) as they were."""
    c = sensor.vignette_coefficient(1.0)
    stored = np.full((36, 64), 1500, np.uint16)
    stored[0, 0], stored[0, 1], stored[35, 63] = WHITE, 16000, 65535
    frame = read_raw(_write(tmp_path / "v.dng", stored, vignette_k=[2 * c, c * c]))
    gain = 1.0 / sensor.vignette_gain(36, 64, 1.0)
    black = np.tile(BLACK, (18, 32))
    expected = np.rint(black + (1500 - black) * gain)
    np.testing.assert_array_equal(frame.raw_bayer[1:35], expected[1:35])
    assert frame.raw_bayer[0, 0] == WHITE and frame.raw_bayer[35, 63] == 65535
    assert frame.raw_bayer[0, 1] == WHITE  # 16000 x 2 capped at the white level
    assert frame.converted.gains == ("FixVignetteRadial (OpcodeList3)",)
