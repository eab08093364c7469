"""The stored raw mosaic as a raw converter shows it: the file's gain opcodes, DefaultCrop
and Orientation applied in the DNG processing order; BaselineExposure recorded.

transforms.json (and every pose file) describes the image as displayed, so the frames are
read that way. The order (DNG 1.4.0.0 specification): linearization and black subtraction
(Chapter 5), OpcodeList2, demosaicing, OpcodeList3 (Chapter 7), then the crop to the
default crop area (Chapter 4, DefaultCropOrigin 50719 / DefaultCropSize 50720: the final
image area in raw image coordinates, relative to the top-left of the ActiveArea, the
origin given horizontal then vertical), then Orientation (TIFF 6.0 tag 274; the DNG SDK
takes the image's orientation from IFD 0's tag alone, dng_negative.cpp, and applies it to
the rendered, cropped image).

- Gain opcodes (gridnerf.dng_opcodes): applied to the black-subtracted mosaic in DN,
  black + (raw - black) x gain, rounded and capped at the white level (the DNG SDK clips
  its GainMap output at 1.0 too); photosites at or above the white level keep their value
  (they stay saturated, or impossible, for the checks after loading). The rounding adds at
  most 1/12 DN^2 of variance on top of the sensor's own quantisation. The gain is in the
  uint16 mosaic itself, so every consumer (binned and mosaic training, the noise and defect
  checks, the lens-cap frames, which carry the same tags) sees one set of frames; a black
  level error the tag does not record is scaled with the signal, as in any converter. The
  trainer then skips its own falloff estimate (RunPlan.file_falloff, train._vignetting).
- DefaultCrop: the mosaic is cut to the crop area; an odd origin shifts the CFA phase, so
  the CFA pattern and the per-position black levels are read at the crop's first photosite
  (per_position). A fractional crop (RATIONAL tags with a remainder) is refused.
- Orientation 1..8: the mosaic is flipped / rotated to display orientation and the CFA
  pattern and black levels remapped alike. LibRaw's raw_image (rawpy) stays in sensor
  orientation and reports the orientation as sizes.flip, the dcraw code
  "50132467"[orientation & 7] (checked here for all eight values with rawpy 0.28 / LibRaw
  0.22 on DNGs); FLIP_TO_ORIENTATION inverts it, for every raw format LibRaw reads.
  LibRaw's own DefaultCrop (sizes.crop_*) is not used: it moves an odd origin to the next
  even photosite and shrinks the width (origin 3, width 58 read as 4, 57).
- BaselineExposure (Chapter 4, tag 50730, IFD 0): recorded, not applied. It moves the zero
  point of a converter's exposure control per camera model (headroom against shadow
  noise); it does not rescale the stored values, whose relation to the light the trainer
  takes from ExposureTime x ISO per frame (gridnerf.scene: relative exposure). A capture
  whose frames carry different values would be rendered at different brightness by a
  converter, which the scene's printed line says; the training is not changed by it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gridnerf import dng_opcodes
from gridnerf.errors import RawError, SceneError

# LibRaw sizes.flip -> TIFF Orientation (the inverse of dcraw's "50132467"[orientation & 7])
FLIP_TO_ORIENTATION = {0: 1, 1: 2, 3: 3, 2: 4, 4: 5, 6: 6, 7: 7, 5: 8}
ORIENTATION_NAMES = {1: "as stored", 2: "mirrored left-right", 3: "rotated 180 deg",
                     4: "mirrored top-bottom", 5: "transposed",
                     6: "rotated 90 deg clockwise", 7: "transversed",
                     8: "rotated 90 deg counter-clockwise"}
_CFA_NAMES = {(0, 1, 1, 2): "RGGB", (2, 1, 1, 0): "BGGR", (1, 0, 2, 1): "GRBG",
              (1, 2, 0, 1): "GBRG"}


@dataclass(frozen=True)
class Converted:
    """What the file's converter tags did to one frame (all defaults: nothing).

    orientation: TIFF Orientation applied (1: none); crop: (x, y, width, height) DefaultCrop
    in stored photosites, None where the file has none (or it is the whole image);
    stored_hw: (H, W) of the stored mosaic; gains / skipped: labels of the opcodes applied
    / skipped (with the reason); baseline_exposure: the BaselineExposure tag, EV, or None.
    """

    orientation: int = 1
    crop: tuple[int, int, int, int] | None = None
    stored_hw: tuple[int, int] = (0, 0)
    gains: tuple[str, ...] = ()
    skipped: tuple[str, ...] = ()
    baseline_exposure: float | None = None


def cfa_name(cfa) -> str:
    return _CFA_NAMES.get(tuple(int(c) for c in np.ravel(cfa)), str(np.asarray(cfa).tolist()))


def to_display(a: np.ndarray, orientation: int) -> np.ndarray:
    """(H, W, ...) array in stored orientation -> as displayed under TIFF `orientation`
    (row 0 / column 0 of the stored image are: 1 top/left, 2 top/right, 3 bottom/right,
    4 bottom/left, 5 left/top, 6 right/top, 7 right/bottom, 8 left/bottom)."""
    o = int(orientation)
    if o in (5, 6, 7, 8):  # row 0 runs down a side: transpose first
        a = np.swapaxes(a, 0, 1)
        o = {5: 1, 6: 2, 7: 3, 8: 4}[o]
    if o in (2, 3):
        a = a[:, ::-1]
    if o in (3, 4):
        a = a[::-1]
    return a


def from_display(a: np.ndarray, orientation: int) -> np.ndarray:
    """The inverse of to_display: (H, W, ...) as displayed -> as stored."""
    o = int(orientation)
    inverse = {6: 8, 8: 6}.get(o, o)  # flips, 180 deg and the transposes are their own
    return to_display(a, inverse)


def per_position(values, origin: tuple[int, int], crop_hw: tuple[int, int],
                 orientation: int) -> np.ndarray:
    """(2, 2) values per stored CFA position ([y % 2, x % 2]: CFA colours, black levels) ->
    per position of the displayed image: read at the crop's first photosite (origin x, y)
    and turned with it. Only the parities of the origin and of the crop's size matter."""
    values = np.asarray(values)
    x0, y0 = origin[0] % 2, origin[1] % 2
    h, w = 2 + crop_hw[0] % 2, 2 + crop_hw[1] % 2
    tiled = np.tile(values, (3, 3) + (1,) * (values.ndim - 2))[y0:y0 + h, x0:x0 + w]
    return np.ascontiguousarray(to_display(tiled, orientation)[:2, :2])


def _crop_box(path, crop, stored_hw) -> tuple[int, int, int, int] | None:
    """(x, y, w, h) integer DefaultCrop inside the stored image, or None for the whole
    image; RawError naming `path` where it is fractional or outside."""
    if crop is None:
        return None
    values = np.asarray(crop, np.float64)
    if np.any(values != np.round(values)):
        raise RawError(path, f"DefaultCropOrigin/Size {values.tolist()} are fractional",
                       "re-export the frames with whole-photosite crops (or none)")
    x, y, w, h = (int(v) for v in values)
    height, width = stored_hw
    if min(x, y) < 0 or min(w, h) < 2 or x + w > width or y + h > height:
        raise RawError(path, f"DefaultCrop {w}x{h} at ({x}, {y}) does not fit the "
                       f"{width}x{height} mosaic", "re-export the frames with their converter")
    return None if (x, y, w, h) == (0, 0, width, height) else (x, y, w, h)


def display(path, raw_bayer: np.ndarray, cfa: np.ndarray, black_level: np.ndarray,
            white_level: float, tags: dict, orientation: int):
    """The stored mosaic as displayed (module docstring).

    raw_bayer: (H, W) uint16 stored mosaic (LibRaw's raw_image_visible), black included;
    cfa, black_level: (2, 2) per stored CFA position; tags: raw._dng_tags's "opcodes"
    ({list name: bytes}), "crop" ((x, y, w, h) floats) and "baseline_exposure", where found.
    Returns (raw_bayer (H', W') uint16 as displayed, cfa (2, 2), black_level (2, 2),
    Converted). RawError naming `path` for a crop that does not fit, a fractional crop or
    an opcode it must refuse (gridnerf.dng_opcodes.mosaic_gain).
    """
    stored_hw = raw_bayer.shape
    orientation = int(orientation) if int(orientation) in ORIENTATION_NAMES else 1
    gains, skipped = (), ()
    if tags.get("opcodes"):
        height, width = stored_hw
        colour = np.tile(cfa, ((height + 1) // 2, (width + 1) // 2))[:height, :width]
        gain, gains, skipped = dng_opcodes.mosaic_gain(tags["opcodes"], colour, path)
        if gain is not None:
            black = np.tile(black_level, ((height + 1) // 2, (width + 1) // 2))[:height, :width]
            linear_bayer = (raw_bayer.astype(np.float64) - black) * gain
            gained_bayer = np.clip(np.rint(black + linear_bayer), 0, white_level)
            raw_bayer = np.where(raw_bayer >= white_level, raw_bayer,
                                 gained_bayer.astype(np.uint16))
    box = _crop_box(path, tags.get("crop"), stored_hw)
    x, y, w, h = box if box is not None else (0, 0, stored_hw[1], stored_hw[0])
    if box is not None:
        raw_bayer = raw_bayer[y:y + h, x:x + w]
    cfa = per_position(cfa, (x, y), (h, w), orientation)
    black_level = per_position(black_level, (x, y), (h, w), orientation)
    raw_bayer = np.ascontiguousarray(to_display(raw_bayer, orientation))
    return raw_bayer, cfa, black_level, Converted(
        orientation=orientation, crop=box, stored_hw=tuple(stored_hw), gains=tuple(gains),
        skipped=tuple(skipped), baseline_exposure=tags.get("baseline_exposure"))


def describe(converted: list[Converted], cfa, where) -> tuple[list[str], str | None]:
    """The scene's lines on what its files' tags did (each decision once), and the lens
    correction the files carried (the applied gain opcodes, None where none). SceneError
    naming `where` (the raw folder) when only some frames carry a gain opcode: the others
    would keep a falloff the corrected ones do not have."""
    n = len(converted)
    lines = []
    gains = sorted({g for c in converted for g in c.gains})
    with_gain = sum(1 for c in converted if c.gains)
    if with_gain and with_gain < n:
        raise SceneError(where, f"{with_gain} of {n} frames carry {', '.join(gains)} and the "
                         "others none: the frames would differ in lens falloff",
                         "export all frames with one converter and the same settings")
    correction = ", ".join(gains) or None
    if correction:
        lines.append(f"{correction} applied to the linear mosaic (the files' own lens "
                     "falloff / shading correction)")
    for note in sorted({s for c in converted for s in c.skipped}):
        lines.append(f"{note}: skipped")
    for crop, stored in sorted({(c.crop, c.stored_hw) for c in converted if c.crop}):
        odd = " (odd origin: the CFA phase shifts)" if (crop[0] | crop[1]) % 2 else ""
        lines.append(f"DefaultCrop {crop[2]}x{crop[3]} at ({crop[0]}, {crop[1]}) of the "
                     f"{stored[1]}x{stored[0]} mosaic applied{odd}")
    for o in sorted({c.orientation for c in converted if c.orientation != 1}):
        lines.append(f"Orientation {o} ({ORIENTATION_NAMES[o]}) applied")
    turned = [c for c in converted if c.crop or c.orientation != 1]
    if turned:
        c = turned[0]
        h, w = c.crop[:1:-1] if c.crop else c.stored_hw
        h, w = (h, w) if c.orientation < 5 else (w, h)
        lines.append(f"frames are {w}x{h} as displayed, CFA {cfa_name(cfa)}")
    levels = [c.baseline_exposure for c in converted if c.baseline_exposure is not None]
    if levels:
        spread = (f"{levels[0]:+.2f} EV" if np.ptp(levels) == 0 else
                  f"{min(levels):+.2f}..{max(levels):+.2f} EV, differing between frames: a "
                  "converter renders them at different brightness")
        lines.append(f"BaselineExposure {spread}: recorded, not applied (a converter's "
                     "rendering offset; the frames are scaled by ExposureTime x ISO)")
    return [f"raw files: {line}" for line in lines], correction
