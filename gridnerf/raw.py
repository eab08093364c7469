"""RAW frames: reading (rawpy/LibRaw + DNG tags via tifffile), normalisation, CFA helpers.

Conventions (docs/design.md): `cfa` is a (2, 2) int array of colour indices per CFA
position (0=R 1=G 2=B, `cfa[y % 2, x % 2]`); `black_level` is (2, 2) per CFA position;
normalised raw is `(raw - black) / (white - black)` in float32 with negatives kept.

Where the metadata comes from (behaviour of rawpy 0.28 / LibRaw 0.22, checked here):
- mosaic, CFA, per-position black, white level: LibRaw. `black_level_per_channel` is
  ordered by colour index (R, G, B, G2), so it is mapped to CFA positions through
  `raw_pattern`. LibRaw truncates rational DNG black levels to integers; when the DNG's
  own BlackLevel tag agrees with LibRaw to within 1 DN, the exact tag values are used.
- XYZ->camera (D65): the file's ColorMatrix tag calibrated for D65 (ColorMatrix2 when
  neither is D65), else LibRaw's `rgb_xyz_matrix` when non-zero (camera in its table),
  else the documented fallback `inv(color.XYZ_FROM_SRGB)`: a camera whose primaries are
  sRGB's. Whether the tag describes the sensor is checked later, against the frames and
  the camera's reference matrix (gridnerf.colour_target.locus_check).
- as-shot neutral: the DNG AsShotNeutral tag, else `1 / camera_whitebalance` from LibRaw,
  else (1, 1, 1); always normalised so that G = 1.
- exposure time and ISO: the TIFF/EXIF tags (exact rationals), else LibRaw, else None.
- a converter's tags (DNG gain opcodes, DefaultCrop, BaselineExposure: tifffile; the
  orientation: LibRaw's sizes.flip, for every format): the mosaic is returned as displayed,
  its CFA and black levels remapped alike (gridnerf.raw_layout, gridnerf.dng_opcodes).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rawpy
import tifffile

from gridnerf import color, dng_opcodes, raw_layout
from gridnerf.errors import RawError

_FIX_CORRUPT = "re-export or re-copy the file from the camera/card; it may be truncated"
_FIX_UNSUPPORTED_CFA = (
    "use a camera with a 2x2 RGB Bayer sensor (X-Trans, CMYG, Foveon and linear DNGs "
    "are not supported)"
)
_ILLUMINANT_D65 = 21
_PHOTOMETRIC_CFA = 32803


@dataclass(frozen=True, eq=False)
class RawFrame:
    """One RAW exposure with the metadata needed to normalise it and map it to colour.

    raw_bayer: (H, W) uint16 visible mosaic as displayed (the file's gain opcodes,
      DefaultCrop and Orientation applied: gridnerf.raw_layout), black level NOT removed.
    cfa: (2, 2) int, colour index per CFA position (0=R, 1=G, 2=B) of the displayed mosaic.
    black_level: (2, 2) float32 per CFA position of the displayed mosaic.
    xyz_to_cam: (3, 3) float64 XYZ -> camera matrix for D65.
    as_shot_neutral: (3,) float64 camera RGB of a neutral, G normalised to 1.
    has_color_matrix: False when the file gave no colour matrix and sRGB primaries stand in.
    camera_model: the file's UniqueCameraModel (else Model) tag, None where it has none.
    converted: what the file's converter tags did (raw_layout.Converted).
    """

    path: str
    raw_bayer: np.ndarray
    cfa: np.ndarray
    black_level: np.ndarray
    white_level: float
    xyz_to_cam: np.ndarray
    as_shot_neutral: np.ndarray
    exposure_time: float | None
    iso: float | None
    has_color_matrix: bool = True
    camera_model: str | None = None
    converted: raw_layout.Converted = raw_layout.Converted()


def check_cfa(cfa) -> np.ndarray:
    """The (2, 2) int64 Bayer pattern (one R, two G, one B as 0, 1, 2), or RawError: the one
    CFA validation of the package."""
    cfa = np.asarray(cfa)
    ok = (cfa.shape == (2, 2) and np.issubdtype(cfa.dtype, np.integer)
          and sorted(cfa.ravel().tolist()) == [0, 1, 1, 2])
    if not ok:
        raise RawError(None, f"CFA pattern {cfa.tolist()} ({cfa.dtype}{cfa.shape}) is not a "
                       "(2, 2) RGB Bayer pattern", "pass colour indices per CFA position, one R, "
                       "two G, one B, e.g. [[0, 1], [1, 2]] for RGGB")
    return cfa.astype(np.int64)


def _tile(per_position: np.ndarray, height: int, width: int) -> np.ndarray:
    """(2, 2) values per CFA position -> (height, width) array (`v[y % 2, x % 2]`)."""
    reps = ((height + 1) // 2, (width + 1) // 2)
    return np.tile(np.asarray(per_position), reps)[:height, :width]


def cfa_from_libraw(raw_pattern, color_desc: bytes, path) -> np.ndarray:
    """LibRaw `raw_pattern` + `color_desc` -> (2, 2) int cfa (0=R 1=G 2=B).

    `raw_pattern` indexes `color_desc` (e.g. b"RGBG", where index 3 is the second
    green). Anything but a 2x2 R/G/B Bayer pattern raises RawError naming `path`.
    """
    desc = bytes(color_desc or b"").decode("ascii", "replace")
    if raw_pattern is None or np.shape(raw_pattern) != (2, 2):
        shape = None if raw_pattern is None else np.shape(raw_pattern)
        raise RawError(
            path, f"unsupported CFA: pattern shape {shape} (colours {desc!r})", _FIX_UNSUPPORTED_CFA
        )
    letters = []
    for idx in np.asarray(raw_pattern).ravel().tolist():
        letters.append(desc[idx] if 0 <= idx < len(desc) else "?")
    lut = {"R": 0, "G": 1, "B": 2}
    if sorted(letters) != ["B", "G", "G", "R"]:
        raise RawError(
            path,
            f"unsupported CFA: pattern {''.join(letters)!r} is not an RGB Bayer pattern",
            _FIX_UNSUPPORTED_CFA,
        )
    return np.array([lut[c] for c in letters], np.int64).reshape(2, 2)


def _tag_floats(tag) -> np.ndarray:
    """TIFF tag value -> float64 array; (S)RATIONAL (num, den) pairs are divided out."""
    value = tag.value
    values = np.atleast_1d(np.asarray(value if not isinstance(value, bytes) else list(value)))
    values = values.astype(np.float64).ravel()
    if int(tag.dtype) in (5, 10):  # RATIONAL, SRATIONAL
        num, den = values[0::2], values[1::2]
        return num / np.where(den == 0, 1.0, den)
    return values


def _exif_value(page, name: str):
    """A value from the EXIF sub-IFD of `page` (tifffile parses it into a dict), or None."""
    exif = page.tags.get(34665)
    if exif is None or not isinstance(exif.value, dict):
        return None
    value = exif.value.get(name)
    if isinstance(value, tuple) and len(value) == 2 and name == "ExposureTime":
        return value[0] / value[1] if value[1] else None
    return value


def _dng_tags(path: Path) -> dict:
    """Colour/black/exposure tags of a TIFF-based raw (DNG, NEF, ARW...), as floats.

    Returns {} for files tifffile cannot parse (CR3, RAF...): those rely on LibRaw.
    Keys present only when found: black (2, 2), color_matrix (9,), neutral (3,),
    exposure_time, iso, model (UniqueCameraModel, else Model); in a DNG (DNGVersion set)
    also crop (x, y, w, h) floats (DefaultCropOrigin, DefaultCropSize), opcodes {list name:
    bytes} (OpcodeList1/2/3 of the raw IFD) and baseline_exposure (EV, IFD 0).
    """
    out: dict = {}
    try:
        with tifffile.TiffFile(path) as tif:
            ifd0 = tif.pages[0]
            pages = [ifd0, *(ifd0.pages or [])]
            cfa_pages = [p for p in pages if p.tags.get(262) is not None]
            cfa_pages = [p for p in cfa_pages if p.tags[262].value == _PHOTOMETRIC_CFA]
            if cfa_pages and 50714 in cfa_pages[0].tags:
                page = cfa_pages[0]
                black = _tag_floats(page.tags[50714])
                dims = tuple(page.tags[50713].value) if 50713 in page.tags else (1, 1)
                if dims in ((1, 1), (1, 2), (2, 1), (2, 2)) and black.size == dims[0] * dims[1]:
                    out["black"] = np.tile(black.reshape(dims), (2 // dims[0], 2 // dims[1]))
            matrices = {}
            for m_code, i_code in ((50721, 50778), (50722, 50779)):
                if m_code in ifd0.tags:
                    m = _tag_floats(ifd0.tags[m_code])
                    ill = int(ifd0.tags[i_code].value) if i_code in ifd0.tags else 0
                    if m.size == 9 and np.any(m != 0):
                        matrices[m_code] = (m, ill)
            d65 = [m for m, ill in matrices.values() if ill == _ILLUMINANT_D65]
            if d65:
                out["color_matrix"] = d65[0]
            elif matrices:
                out["color_matrix"] = matrices.get(50722, matrices.get(50721))[0]
            for code in (50708, 272):  # UniqueCameraModel, Model
                if code in ifd0.tags and str(ifd0.tags[code].value).strip():
                    out["model"] = str(ifd0.tags[code].value).strip("\x00 ")
                    break
            if 50728 in ifd0.tags:
                neutral = _tag_floats(ifd0.tags[50728])
                if neutral.size == 3 and np.all(neutral > 0):
                    out["neutral"] = neutral
            exposure = _tag_floats(ifd0.tags[33434])[0] if 33434 in ifd0.tags else None
            iso = float(np.ravel(ifd0.tags[34855].value)[0]) if 34855 in ifd0.tags else None
            exposure = exposure if exposure else _exif_value(ifd0, "ExposureTime")
            iso = iso if iso else _exif_value(ifd0, "ISOSpeedRatings")
            if exposure:
                out["exposure_time"] = float(exposure)
            if iso:
                out["iso"] = float(np.ravel(iso)[0])
            if 50706 in ifd0.tags:  # DNGVersion: the converter's tags
                out.update(_converter_tags(ifd0, cfa_pages[0] if cfa_pages else ifd0))
    except (tifffile.TiffFileError, OSError, ValueError, KeyError, IndexError, TypeError):
        # Not a TIFF container or malformed tags: LibRaw's values are used instead.
        return {}
    return out


def _converter_tags(ifd0, raw_ifd) -> dict:
    """DefaultCrop (50719, 50720) and OpcodeList1/2/3 of the raw IFD, BaselineExposure
    (50730) of IFD 0 (DNG 1.4 spec, Chapter 4: where each tag lives)."""
    out: dict = {}
    if 50719 in raw_ifd.tags or 50720 in raw_ifd.tags:
        origin = _tag_floats(raw_ifd.tags[50719]) if 50719 in raw_ifd.tags else np.zeros(2)
        size = _tag_floats(raw_ifd.tags[50720]) if 50720 in raw_ifd.tags else None
        width, length = raw_ifd.imagewidth, raw_ifd.imagelength
        if size is None:
            size = np.array([width - origin[0], length - origin[1]])
        out["crop"] = (*origin[:2].tolist(), *size[:2].tolist())
    lists = {name: bytes(raw_ifd.tags[code].value) for code, name in dng_opcodes.LISTS.items()
             if code in raw_ifd.tags}
    if lists:
        out["opcodes"] = lists
    if 50730 in ifd0.tags:
        out["baseline_exposure"] = float(_tag_floats(ifd0.tags[50730])[0])
    return out


def read_raw(path) -> RawFrame:
    """Read a DNG or any LibRaw-supported raw file into a RawFrame.

    The mosaic comes as displayed (gridnerf.raw_layout: gain opcodes, DefaultCrop,
    Orientation). Raises RawError (naming the file) when it is missing, unreadable/corrupt,
    has a CFA other than a 2x2 RGB Bayer pattern, or carries a converter tag this reader
    must refuse (a required opcode it does not apply, a crop that does not fit).
    """
    p = Path(path)
    if not p.exists():
        raise RawError(
            p, "file not found", "check the path, or re-run `gridnerf simulate` to regenerate it"
        )
    if not p.is_file():
        raise RawError(p, "is not a file", "pass the path of a .dng or camera raw file")
    try:
        with rawpy.imread(str(p)) as raw:
            cfa = cfa_from_libraw(raw.raw_pattern, raw.color_desc, p)
            pattern = np.array(raw.raw_pattern)
            per_channel = np.array(raw.black_level_per_channel, np.float64)
            white_level = float(raw.white_level)
            rgb_xyz = np.array(raw.rgb_xyz_matrix, np.float64)[:3]
            cam_wb = np.array(raw.camera_whitebalance, np.float64)
            shutter = float(raw.other.shutter_speed)
            iso = float(raw.other.iso_speed)
            raw_bayer = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            flip = int(raw.sizes.flip)
    except rawpy.LibRawError as e:
        msg = e.args[0].decode("utf-8", "replace") if e.args and isinstance(e.args[0], bytes) else e
        raise RawError(p, f"LibRaw cannot read it ({type(e).__name__}: {msg})", _FIX_CORRUPT) from e
    if raw_bayer.ndim != 2:
        raise RawError(
            p, f"unsupported CFA: mosaic has shape {raw_bayer.shape}", _FIX_UNSUPPORTED_CFA
        )

    tags = _dng_tags(p)
    black_level = per_channel[pattern]
    if "black" in tags and np.all(np.abs(tags["black"] - black_level) < 1.0):
        black_level = tags["black"]
    if white_level <= black_level.max():
        raise RawError(
            p,
            f"white level {white_level} is not above the black level {black_level.tolist()}",
            _FIX_CORRUPT,
        )

    raw_bayer, cfa, black_level, converted = raw_layout.display(
        p, raw_bayer, cfa, black_level, white_level, tags,
        raw_layout.FLIP_TO_ORIENTATION.get(flip, 1))

    if "color_matrix" in tags:  # the file's own tag wins (DNG)
        xyz_to_cam = tags["color_matrix"].reshape(3, 3)
    elif np.any(rgb_xyz != 0):
        xyz_to_cam = rgb_xyz
    else:
        xyz_to_cam = np.linalg.inv(color.XYZ_FROM_SRGB)

    if "neutral" in tags:
        neutral = tags["neutral"]
    elif np.all(cam_wb[:3] > 0):
        neutral = 1.0 / cam_wb[:3]
    else:
        neutral = np.ones(3)
    neutral = neutral / neutral[1]

    return RawFrame(
        path=str(p),
        raw_bayer=raw_bayer,
        cfa=cfa,
        black_level=black_level.astype(np.float32),
        white_level=white_level,
        xyz_to_cam=np.asarray(xyz_to_cam, np.float64),
        as_shot_neutral=np.asarray(neutral, np.float64),
        exposure_time=tags.get("exposure_time", shutter if shutter > 0 else None),
        iso=tags.get("iso", iso if iso > 0 else None),
        has_color_matrix=bool(np.any(rgb_xyz != 0) or "color_matrix" in tags),
        camera_model=tags.get("model"),
        converted=converted,
    )


def normalize(frame: RawFrame) -> np.ndarray:
    """(raw - black) / (white - black) per CFA position: raw_bayer (H, W) float32."""
    return normalize_mosaic(frame.raw_bayer, frame.black_level, frame.white_level)


def normalize_mosaic(raw_bayer: np.ndarray, black_level, white_level,
                     dtype=np.float32) -> np.ndarray:
    """The one raw normalisation: (raw - black) / (white - black) per CFA position.

    raw_bayer: (H, W) mosaic; black_level: (2, 2) per CFA position; white_level: scalar.
    Returns (H, W) `dtype` (float64 for the simulator's previews). Values below the black
    level stay negative (clipping them biases dark channels).
    """
    height, width = raw_bayer.shape
    black = _tile(np.asarray(black_level, dtype), height, width)
    return (np.asarray(raw_bayer).astype(dtype) - black) / (dtype(white_level) - black)


def saturated_mask(frame: RawFrame) -> np.ndarray:
    """(H, W) bool: pixels at or above the white level (LibRaw's clipping point)."""
    return frame.raw_bayer >= frame.white_level


def cfa_masks(cfa, height: int, width: int) -> np.ndarray:
    """(height, width, 3) float32 one-hot of the colour measured at each pixel."""
    colour = _tile(check_cfa(cfa), height, width)
    return (colour[..., None] == np.arange(3)).astype(np.float32)


def bin2x2(raw_bayer: np.ndarray, cfa, dtype=np.float32) -> np.ndarray:
    """Bin each 2x2 CFA block to one RGB pixel: (H, W) -> rgb_cam (H//2, W//2, 3) float32.

    R and B are copied, the two greens averaged. An odd last row/column is cropped.
    dtype: float32 (training) or float64 (the simulator's previews).
    """
    cfa = check_cfa(cfa)
    raw_bayer = np.asarray(raw_bayer)
    h2, w2 = raw_bayer.shape[0] // 2, raw_bayer.shape[1] // 2
    rgb_cam = np.zeros((h2, w2, 3), dtype)
    for dy in range(2):
        for dx in range(2):
            rgb_cam[..., cfa[dy, dx]] += raw_bayer[dy : 2 * h2 : 2, dx : 2 * w2 : 2]
    rgb_cam[..., 1] *= 0.5
    return rgb_cam


def bin2x2_mask(valid: np.ndarray, cfa) -> np.ndarray:
    """(H, W) bool -> (H//2, W//2, 3) bool; a binned channel is valid iff all its sources are."""
    cfa = check_cfa(cfa)
    valid = np.asarray(valid, bool)
    h2, w2 = valid.shape[0] // 2, valid.shape[1] // 2
    out = np.ones((h2, w2, 3), bool)
    for dy in range(2):
        for dx in range(2):
            out[..., cfa[dy, dx]] &= valid[dy : 2 * h2 : 2, dx : 2 * w2 : 2]
    return out


def downscale(img: np.ndarray, factor: int) -> np.ndarray:
    """Box average over factor x factor blocks: (H, W, ...) -> (H//f, W//f, ...).

    Float inputs keep their dtype; integer and bool inputs give float32. Edge rows and
    columns that do not fill a whole block are cropped.
    """
    img = np.asarray(img)
    f = int(factor)
    if f < 1 or f != factor:
        raise ValueError(f"factor must be a positive integer, got {factor}")
    h, w = img.shape[0] // f, img.shape[1] // f
    if h == 0 or w == 0:
        raise ValueError(f"image of shape {img.shape} is smaller than the factor {f}")
    dtype = img.dtype if np.issubdtype(img.dtype, np.floating) else np.float32
    blocks = img[: h * f, : w * f].reshape(h, f, w, f, *img.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(dtype)
