"""Minimal DNG writer (tifffile) for simulated RAW frames and tests.

Writes one uncompressed 16-bit CFA image in IFD0 with the DNG tags LibRaw needs to
decode it: CFA layout, per-CFA-position black level, white level, a D65 colour
matrix and the as-shot neutral. The container is always 16 bits per sample; the
sensor bit depth is carried by `WhiteLevel` (pidng's 14-bit packing was found broken
when checked for this project; a 16-bit container with WhiteLevel 16383 reads back exactly).

Tag numbers and types follow the DNG 1.4 specification and TIFF/EP:

| tag   | name                 | type      |
|-------|----------------------|-----------|
| 33421 | CFARepeatPatternDim  | SHORT 2   |
| 33422 | CFAPattern           | BYTE 4    |
| 33434 | ExposureTime         | RATIONAL  |
| 34855 | ISOSpeedRatings      | SHORT     |
| 50706 | DNGVersion           | BYTE 4    |
| 50707 | DNGBackwardVersion   | BYTE 4    |
| 50708 | UniqueCameraModel    | ASCII     |
| 50710 | CFAPlaneColor        | BYTE 3    |
| 50711 | CFALayout            | SHORT     |
| 50713 | BlackLevelRepeatDim  | SHORT 2   |
| 50714 | BlackLevel           | RATIONAL 4|
| 50717 | WhiteLevel           | LONG      |
| 50721 | ColorMatrix1         | SRATIONAL 9 |
| 50728 | AsShotNeutral        | RATIONAL 3 |
| 50778 | CalibrationIlluminant1 | SHORT   |

Optional, off by default (what a raw converter writes; gridnerf.raw applies them on
reading, gridnerf.raw_layout):

| tag   | name                 | type      |
|-------|----------------------|-----------|
| 274   | Orientation          | SHORT (always written; 1 unless given) |
| 50719 | DefaultCropOrigin    | LONG 2 (x, y) |
| 50720 | DefaultCropSize      | LONG 2 (width, height) |
| 50730 | BaselineExposure     | SRATIONAL (EV) |
| 51022 | OpcodeList3          | UNDEFINED (big-endian opcode list) |
| 51008, 51009 | OpcodeList1, OpcodeList2 | UNDEFINED, given verbatim (opcode_lists) |

The vignetting opcode list holds one FixVignetteRadial opcode (ID 3, DNG 1.3): the gain
g(r) = 1 + k0 r^2 + k1 r^4 + k2 r^6 + k3 r^8 + k4 r^10 that undoes a lens's falloff, r the
distance from the optical centre (cx, cy, fractions of the image width and height) over
its distance to the farthest image corner.
"""

from __future__ import annotations

import struct
from fractions import Fraction
from pathlib import Path

import numpy as np
import tifffile

from gridnerf import atomic

# TIFF field types.
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _UNDEFINED, _SRATIONAL = 1, 2, 3, 4, 5, 7, 10

# Tag codes (see module docstring).
TAG_MAKE = 271
TAG_MODEL = 272
TAG_ORIENTATION = 274
TAG_CFA_REPEAT_PATTERN_DIM = 33421
TAG_CFA_PATTERN = 33422
TAG_EXPOSURE_TIME = 33434
TAG_ISO = 34855
TAG_DNG_VERSION = 50706
TAG_DNG_BACKWARD_VERSION = 50707
TAG_UNIQUE_CAMERA_MODEL = 50708
TAG_CFA_PLANE_COLOR = 50710
TAG_CFA_LAYOUT = 50711
TAG_BLACK_LEVEL_REPEAT_DIM = 50713
TAG_BLACK_LEVEL = 50714
TAG_WHITE_LEVEL = 50717
TAG_DEFAULT_CROP_ORIGIN = 50719
TAG_DEFAULT_CROP_SIZE = 50720
TAG_COLOR_MATRIX_1 = 50721
TAG_COLOR_MATRIX_2 = 50722
TAG_AS_SHOT_NEUTRAL = 50728
TAG_BASELINE_EXPOSURE = 50730
TAG_CALIBRATION_ILLUMINANT_1 = 50778
TAG_CALIBRATION_ILLUMINANT_2 = 50779
TAG_OPCODE_LIST_3 = 51022

OPCODE_FIX_VIGNETTE_RADIAL = 3
OPCODE_VERSION_1_3 = (1, 3, 0, 0)  # the DNG version that introduced FixVignetteRadial

PHOTOMETRIC_CFA = 32803
ILLUMINANT_D65 = 21

# LibRaw refuses images narrower or shorter than this ("Unsupported file format").
MIN_SIZE = 22

# Largest denominator used when storing floats as (S)RATIONAL.
_MAX_DENOMINATOR = 1_000_000


def _rationals(values, signed: bool) -> tuple[int, ...]:
    """Flat (num0, den0, num1, den1, ...) tuple of the closest fractions to `values`."""
    out: list[int] = []
    for v in np.asarray(values, np.float64).ravel():
        if not np.isfinite(v):
            raise ValueError(f"cannot store non-finite value {v} as a DNG rational")
        if not signed and v < 0:
            raise ValueError(f"cannot store negative value {v} as an unsigned DNG rational")
        f = Fraction(float(v)).limit_denominator(_MAX_DENOMINATOR)
        limit = 2**31 - 1 if signed else 2**32 - 1
        if abs(f.numerator) > limit:
            raise ValueError(f"value {v} is too large for a DNG rational")
        out += [f.numerator, f.denominator]
    return tuple(out)


def fix_vignette_radial(k, centre=(0.5, 0.5)) -> bytes:
    """One FixVignetteRadial opcode, big-endian: ID, DNG version, flags (0), parameter size,
    then k0..k4 and cx, cy as doubles. k: up to 5 coefficients of g(r) (missing ones 0);
    centre: the optical centre as fractions of the image width and height."""
    k = np.asarray(k, np.float64).ravel()
    if k.size > 5 or not np.all(np.isfinite(k)):
        raise ValueError(f"FixVignetteRadial takes up to 5 finite coefficients, got {k}")
    cx, cy = (float(v) for v in centre)
    if not (0.0 <= cx <= 1.0 and 0.0 <= cy <= 1.0):
        raise ValueError(f"the optical centre must lie in [0, 1]^2, got {centre}")
    params = struct.pack(">7d", *np.pad(k, (0, 5 - k.size)), cx, cy)
    return (struct.pack(">I4BII", OPCODE_FIX_VIGNETTE_RADIAL, *OPCODE_VERSION_1_3, 0,
                        len(params)) + params)


def opcode_list(opcodes: list[bytes]) -> bytes:
    """A DNG opcode list (big-endian whatever the file's byte order): count, then opcodes."""
    return struct.pack(">I", len(opcodes)) + b"".join(opcodes)


def _check_inputs(raw_bayer, cfa, black_level, white_level, xyz_to_cam, as_shot_neutral):
    """Validate shapes, dtypes and ranges; returns the arrays in canonical form."""
    raw_bayer = np.asarray(raw_bayer)
    if raw_bayer.ndim != 2 or min(raw_bayer.shape) < MIN_SIZE:
        raise ValueError(
            f"raw_bayer must be (H, W) with H, W >= {MIN_SIZE} (LibRaw's minimum), "
            f"got {raw_bayer.shape}"
        )
    if raw_bayer.dtype != np.uint16:
        raise ValueError(f"raw_bayer must be uint16, got {raw_bayer.dtype}")
    cfa = np.asarray(cfa)
    if cfa.shape != (2, 2) or sorted(cfa.ravel().tolist()) != [0, 1, 1, 2]:
        raise ValueError(f"cfa must be a (2, 2) Bayer pattern of 0=R 1=G 2=B, got {cfa.tolist()}")
    black_level = np.asarray(black_level, np.float64)
    if black_level.shape != (2, 2):
        raise ValueError(f"black_level must be (2, 2) per CFA position, got {black_level.shape}")
    if not 0 < int(white_level) <= 65535:
        raise ValueError(f"white_level must be in 1..65535, got {white_level}")
    if np.any(black_level < 0) or np.any(black_level >= int(white_level)):
        raise ValueError(f"black_level {black_level.tolist()} must lie in [0, white_level)")
    xyz_to_cam = np.asarray(xyz_to_cam, np.float64)
    if xyz_to_cam.shape != (3, 3):
        raise ValueError(f"xyz_to_cam must be (3, 3), got {xyz_to_cam.shape}")
    as_shot_neutral = np.asarray(as_shot_neutral, np.float64)
    if as_shot_neutral.shape != (3,) or np.any(as_shot_neutral <= 0):
        raise ValueError(f"as_shot_neutral must be 3 positive values, got {as_shot_neutral}")
    return raw_bayer, cfa, black_level, xyz_to_cam, as_shot_neutral


def _converter_tags(shape, default_crop, orientation, baseline_exposure, vignette_k,
                    vignette_centre, opcode_lists=None) -> list[tuple]:
    """The optional tags (module docstring) as tifffile extratags; Orientation always."""
    if int(orientation) != orientation or not 1 <= orientation <= 8:
        raise ValueError(f"orientation must be a TIFF Orientation 1..8, got {orientation}")
    tags = [(TAG_ORIENTATION, _SHORT, 1, int(orientation), True)]
    if default_crop is not None:
        x, y, w, h = (int(v) for v in default_crop)
        if min(x, y) < 0 or min(w, h) < 1 or x + w > shape[1] or y + h > shape[0]:
            raise ValueError(f"default_crop {default_crop} must lie inside the "
                             f"{shape[1]}x{shape[0]} image")
        tags += [(TAG_DEFAULT_CROP_ORIGIN, _LONG, 2, (x, y), True),
                 (TAG_DEFAULT_CROP_SIZE, _LONG, 2, (w, h), True)]
    if baseline_exposure is not None:
        tags.append((TAG_BASELINE_EXPOSURE, _SRATIONAL, 1,
                     _rationals([baseline_exposure], signed=True), True))
    lists = dict(opcode_lists or {})
    if not set(lists) <= {51008, 51009, TAG_OPCODE_LIST_3}:
        raise ValueError(f"opcode_lists takes tags 51008, 51009, 51022, got {sorted(lists)}")
    if vignette_k is not None:
        if TAG_OPCODE_LIST_3 in lists:
            raise ValueError("give OpcodeList3 either as vignette_k or in opcode_lists")
        lists[TAG_OPCODE_LIST_3] = opcode_list([fix_vignette_radial(vignette_k,
                                                                    vignette_centre)])
    for code, opcodes in sorted(lists.items()):
        tags.append((code, _UNDEFINED, len(opcodes), bytes(opcodes), True))
    return tags


def write_dng(
    path,
    raw_bayer: np.ndarray,
    cfa: np.ndarray,
    black_level: np.ndarray,
    white_level: int,
    xyz_to_cam: np.ndarray,
    as_shot_neutral: np.ndarray,
    exposure_time: float | None = None,
    iso: float | None = None,
    camera_model: str = "gridnerf simulated camera",
    default_crop: tuple[int, int, int, int] | None = None,
    orientation: int = 1,
    baseline_exposure: float | None = None,
    vignette_k=None,
    vignette_centre: tuple[float, float] = (0.5, 0.5),
    opcode_lists: dict[int, bytes] | None = None,
) -> None:
    """Write a Bayer mosaic as an uncompressed 16-bit DNG, atomically.

    Args:
      path: destination file (`.dng`); written to written atomically (gridnerf.atomic).
      raw_bayer: (H, W) uint16 visible mosaic, black level included; H, W >= 22.
      cfa: (2, 2) int colour index per CFA position, 0=R 1=G 2=B (`cfa[y % 2, x % 2]`).
      black_level: (2, 2) float per CFA position; non-integers are kept (RATIONAL tag).
      white_level: int, the sensor clipping level in DN (e.g. 16383 for 14 bits).
      xyz_to_cam: (3, 3) XYZ -> camera matrix for D65, stored as ColorMatrix1.
      as_shot_neutral: (3,) camera RGB of a neutral surface (AsShotNeutral).
      exposure_time: seconds, optional (ExposureTime).
      iso: optional ISO speed (ISOSpeedRatings, rounded to an integer).
      camera_model: UniqueCameraModel and Model string.
      default_crop: optional (x, y, width, height) in photosites, the part a converter
        shows (DefaultCropOrigin, DefaultCropSize); inside the image.
      orientation: TIFF Orientation, 1 (default, as stored) to 8.
      baseline_exposure: optional EV a converter adds (BaselineExposure).
      vignette_k: optional (<= 5,) FixVignetteRadial coefficients k0..k4, written as
        OpcodeList3 with the optical centre vignette_centre (fractions of width, height).
      opcode_lists: optional {tag: opcode list bytes} for OpcodeList1 (51008), OpcodeList2
        (51009) or OpcodeList3 (51022, not with vignette_k), written as given
        (opcode_list, gridnerf.dng_opcodes.encode).
    """
    raw_bayer, cfa, black_level, xyz_to_cam, as_shot_neutral = _check_inputs(
        raw_bayer, cfa, black_level, white_level, xyz_to_cam, as_shot_neutral
    )
    height = raw_bayer.shape[0]
    model = str(camera_model)
    extratags = [
        (TAG_CFA_REPEAT_PATTERN_DIM, _SHORT, 2, (2, 2), True),
        (TAG_CFA_PATTERN, _BYTE, 4, tuple(int(c) for c in cfa.ravel()), True),
        (TAG_DNG_VERSION, _BYTE, 4, (1, 4, 0, 0), True),
        (TAG_DNG_BACKWARD_VERSION, _BYTE, 4, (1, 1, 0, 0), True),
        (TAG_UNIQUE_CAMERA_MODEL, _ASCII, 0, model, True),
        (TAG_CFA_PLANE_COLOR, _BYTE, 3, (0, 1, 2), True),
        (TAG_CFA_LAYOUT, _SHORT, 1, 1, True),
        (TAG_BLACK_LEVEL_REPEAT_DIM, _SHORT, 2, (2, 2), True),
        (TAG_BLACK_LEVEL, _RATIONAL, 4, _rationals(black_level, signed=False), True),
        (TAG_WHITE_LEVEL, _LONG, 1, int(white_level), True),
        (TAG_COLOR_MATRIX_1, _SRATIONAL, 9, _rationals(xyz_to_cam, signed=True), True),
        (TAG_AS_SHOT_NEUTRAL, _RATIONAL, 3, _rationals(as_shot_neutral, signed=False), True),
        (TAG_CALIBRATION_ILLUMINANT_1, _SHORT, 1, ILLUMINANT_D65, True),
        (TAG_MAKE, _ASCII, 0, "gridnerf", True),
        (TAG_MODEL, _ASCII, 0, model, True),
    ]
    if exposure_time is not None:
        extratags.append(
            (TAG_EXPOSURE_TIME, _RATIONAL, 1, _rationals([exposure_time], signed=False), True)
        )
    if iso is not None:
        extratags.append((TAG_ISO, _SHORT, 1, int(round(float(iso))), True))
    extratags += _converter_tags(raw_bayer.shape, default_crop, orientation, baseline_exposure,
                                 vignette_k, vignette_centre, opcode_lists)

    def fill(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            tifffile.imwrite(
                fh,
                np.ascontiguousarray(raw_bayer),
                byteorder="<",
                photometric=PHOTOMETRIC_CFA,
                planarconfig="contig",
                compression=None,
                subfiletype=0,
                rowsperstrip=height,
                metadata=None,
                software=False,
                extratags=extratags,
            )

    atomic.write(path, fill)
