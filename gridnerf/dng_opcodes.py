"""DNG opcode lists: parsing, and the gain opcodes applied to a raw mosaic.

Format (DNG 1.4.0.0 specification, Chapter 7 "Opcode List Processing"): an opcode list is
big-endian whatever the file's byte order; a LONG count, then per opcode a LONG opcode ID,
4 bytes of the DNG version it needs, a LONG of flags (bit 0 "optional": a reader that does
not know the opcode may skip it, else it must not process the file; bit 1 "preview only"),
a LONG byte count of its parameters, and the parameters.

Where each list applies (DNG 1.4 spec, Chapter 4, tags OpcodeList1 51008, OpcodeList2
51009, OpcodeList3 51022): OpcodeList1 to the raw values as read from the file;
OpcodeList2 just after they are mapped to linear reference values (Chapter 5: black level
subtracted, scaled by the white level), i.e. the one-plane CFA mosaic; OpcodeList3 just
after demosaicing, the linear camera RGB (one plane per colour). All of them act in the
stored image's coordinates (its ActiveArea; LibRaw's raw_image_visible) before DefaultCrop
and Orientation.

What this reader does (mosaic_gain):
- FixVignetteRadial (ID 3) and GainMap (ID 9), both DNG 1.3, in OpcodeList2 or 3: one gain
  per photosite on the black-subtracted mosaic. For OpcodeList3 the spec applies them after
  demosaicing; here the gain a colour plane gets at a pixel goes to the photosites of that
  colour there, before the 2x2 binning, which differs from applying it after by the gain's
  change over one 2x2 block (smooth by construction: a radial polynomial, a bilinear grid).
- FixBadPixelsConstant (4) and FixBadPixelsList (5): skipped with a note: the loader maps
  defective photosites itself from their recurrence across frames (gridnerf.defects) and
  leaves them out of the fit instead of interpolating them.
- any other opcode, and every opcode of OpcodeList1 (it acts before the black level, where
  a gain would scale the black too): skipped with a note where its flags say optional, else
  the file is refused (RawError naming the file and the opcode): a warp, a trim or a value
  map left out would leave frames that differ from what the converter shows.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from gridnerf.errors import RawError

# DNG 1.4 spec, Chapter 7 (DNG 1.6 adds WarpRectilinear2)
NAMES = {1: "WarpRectilinear", 2: "WarpFisheye", 3: "FixVignetteRadial",
         4: "FixBadPixelsConstant", 5: "FixBadPixelsList", 6: "TrimBounds", 7: "MapTable",
         8: "MapPolynomial", 9: "GainMap", 10: "DeltaPerRow", 11: "DeltaPerColumn",
         12: "ScalePerRow", 13: "ScalePerColumn", 14: "WarpRectilinear2"}
FIX_VIGNETTE_RADIAL, GAIN_MAP = 3, 9
BAD_PIXELS = (4, 5)
FLAG_OPTIONAL = 1
LISTS = {51008: "OpcodeList1", 51009: "OpcodeList2", 51022: "OpcodeList3"}
GAIN_LISTS = ("OpcodeList2", "OpcodeList3")
_FIX = "re-export the file with its raw converter (or a DNG converter that keeps the data)"


@dataclass(frozen=True)
class Opcode:
    """One opcode of a list: its ID, the list it came from, flags and parameter bytes."""

    opcode_id: int
    where: str
    flags: int
    params: bytes

    @property
    def name(self) -> str:
        return NAMES.get(self.opcode_id, f"opcode {self.opcode_id}")

    @property
    def label(self) -> str:
        return f"{self.name} ({self.where})"

    @property
    def optional(self) -> bool:
        return bool(self.flags & FLAG_OPTIONAL)


def parse_list(data: bytes, where: str, path) -> list[Opcode]:
    """The opcodes of one opcode list (big-endian bytes); RawError naming `path` when the
    list is truncated or its byte counts do not add up."""
    data = bytes(data)
    try:
        (count,) = struct.unpack_from(">I", data, 0)
        pos, out = 4, []
        for _ in range(count):
            opcode_id, _version, flags, size = struct.unpack_from(">I4sII", data, pos)
            pos += 16
            if pos + size > len(data):
                raise struct.error("parameters run past the end of the list")
            out.append(Opcode(opcode_id, where, flags, data[pos:pos + size]))
            pos += size
    except struct.error as exc:
        raise RawError(path, f"malformed {where} ({exc})", _FIX) from None
    return out


def encode(opcode_id: int, params: bytes, flags: int = 0, version=(1, 3, 0, 0)) -> bytes:
    """One opcode, big-endian: ID, the DNG version it needs, flags, byte count, params."""
    return struct.pack(">I4BII", opcode_id, *version, flags, len(params)) + params


def encode_gain_map(gains, area=(0, 0, 0, 0), plane: int = 0, planes: int = 1,
                    pitch=(1, 1), spacing=None, origin=(0.0, 0.0), flags: int = 0) -> bytes:
    """A GainMap opcode (DNG 1.4 spec, Chapter 7): gains (V, H, P) float32 map points ×
    map planes; area (top, left, bottom, right) photosites ((0, 0, 0, 0): the whole image);
    plane, planes: the image planes it applies to; pitch (rows, columns) between the
    photosites it applies to; spacing, origin (v, h) of the map points in fractions of the
    image height and width (spacing default: points spread over [0, 1])."""
    gains = np.asarray(gains, np.float32)
    if gains.ndim == 2:
        gains = gains[..., None]
    v, h, p = gains.shape
    if spacing is None:
        spacing = (1.0 / max(v - 1, 1), 1.0 / max(h - 1, 1))
    params = struct.pack(">4i4I", *(int(a) for a in area), plane, planes, *pitch)
    params += struct.pack(">II4dI", v, h, *spacing, *origin, p)
    params += gains.astype(">f4").tobytes()
    return encode(GAIN_MAP, params, flags)


def vignette_radial_gain(params: bytes, height: int, width: int, path=None) -> np.ndarray:
    """(H, W) float64 FixVignetteRadial gain (DNG 1.4 spec, Chapter 7): parameters k0..k4,
    cx, cy (7 DOUBLEs); g = 1 + k0 r^2 + k1 r^4 + k2 r^6 + k3 r^8 + k4 r^10, r the distance
    of a pixel from the optical centre (cx, cy in fractions of the image width and height,
    from its top-left edge) over the centre's distance to the farthest image corner. Pixels
    sit at their centres (x + 0.5), as in the DNG SDK (dng_lens_correction.cpp)."""
    if len(params) != 56:
        raise RawError(path, f"FixVignetteRadial has {len(params)} parameter bytes, not 56",
                       _FIX)
    *k, cx_rel, cy_rel = struct.unpack(">7d", params)
    if not (np.all(np.isfinite(k)) and 0 <= cx_rel <= 1 and 0 <= cy_rel <= 1):
        raise RawError(path, f"FixVignetteRadial parameters {k}, centre ({cx_rel}, {cy_rel}) "
                       "are not finite coefficients and a centre inside the image", _FIX)
    cx, cy = cx_rel * width, cy_rel * height
    far2 = max(cx, width - cx) ** 2 + max(cy, height - cy) ** 2
    dy2 = (np.arange(height) + 0.5 - cy) ** 2
    dx2 = (np.arange(width) + 0.5 - cx) ** 2
    r2 = (dy2[:, None] + dx2[None, :]) / far2
    gain = np.ones((height, width))
    term = np.ones((height, width))
    for ki in k:
        term = term * r2
        gain += ki * term
    return gain


def _map_axis(n: int, points: int, spacing: float, origin: float):
    """Rows (or columns) 0..n-1 -> (index0, index1, fraction) into `points` map points:
    the pixel centre's position in fractions of the image, clamped to the first and last
    point (DNG SDK dng_gain_map_interpolator)."""
    if points == 1:
        zeros = np.zeros(n, np.int64)
        return zeros, zeros, np.zeros(n)
    pos = np.clip(((np.arange(n) + 0.5) / n - origin) / spacing, 0.0, points - 1)
    i0 = np.minimum(np.floor(pos).astype(np.int64), points - 2)
    return i0, i0 + 1, pos - i0


def gain_map_gain(params: bytes, colour: np.ndarray, n_planes: int, path=None) -> np.ndarray:
    """(H, W) float64 gain of one GainMap opcode (DNG 1.4 spec, Chapter 7): an area
    (Top, Left, Bottom, Right LONGs; all zero: the whole image), the planes it acts on
    (Plane, Planes), RowPitch, ColPitch (the photosites it acts on: every RowPitch-th row
    from Top), then the map: MapPointsV, MapPointsH (LONG), MapSpacingV/H, MapOriginV/H
    (DOUBLE, fractions of the image height / width), MapPlanes (LONG) and the FLOAT gains
    [V][H][MapPlanes], bilinearly interpolated and clamped at the map's edges.

    colour: (H, W) int the image plane of each photosite: 0 for the CFA mosaic
    (OpcodeList2, n_planes 1), its CFA colour for OpcodeList3 (n_planes 3); plane p of the
    image takes map plane min(p, MapPlanes - 1) (as the DNG SDK does). 1 where it does not
    act."""
    height, width = colour.shape
    try:
        top, left, bottom, right, plane, planes, row_pitch, col_pitch = struct.unpack_from(
            ">4i4I", params, 0)
        v, h, sv, sh, ov, oh, map_planes = struct.unpack_from(">II4dI", params, 32)
    except struct.error:
        raise RawError(path, f"GainMap has {len(params)} parameter bytes, too few for its "
                       "header", _FIX) from None
    size = 76 + 4 * v * h * map_planes
    bad = (len(params) != size or min(v, h, map_planes, planes, row_pitch, col_pitch) < 1
           or (v > 1 and not sv > 0) or (h > 1 and not sh > 0))
    if bad:
        raise RawError(path, f"GainMap of {v}x{h}x{map_planes} points, spacing ({sv}, {sh}), "
                       f"pitch ({row_pitch}, {col_pitch}) in {len(params)} bytes is "
                       "malformed", _FIX)
    grid = np.frombuffer(params, ">f4", offset=76).astype(np.float64).reshape(v, h, map_planes)
    if bottom <= top or right <= left:  # an empty area: the whole image
        top, left, bottom, right = 0, 0, height, width
    r0, r1, fr = _map_axis(height, v, sv, ov)
    c0, c1, fc = _map_axis(width, h, sh, oh)
    rows = np.zeros(height, bool)
    rows[max(top, 0):min(bottom, height)] = True
    rows &= (np.arange(height) - top) % row_pitch == 0
    cols = np.zeros(width, bool)
    cols[max(left, 0):min(right, width)] = True
    cols &= (np.arange(width) - left) % col_pitch == 0
    gain = np.ones((height, width))
    for p in range(plane, min(plane + planes, n_planes)):
        m = grid[..., min(p, map_planes - 1)]
        at_rows = (1 - fr)[:, None] * m[r0] + fr[:, None] * m[r1]  # (H, h)
        g = (1 - fc)[None, :] * at_rows[:, c0] + fc[None, :] * at_rows[:, c1]
        sel = rows[:, None] & cols[None, :] & (colour == p)
        gain[sel] *= g[sel]
    return gain


def mosaic_gain(lists: dict[str, bytes], colour: np.ndarray, path
                ) -> tuple[np.ndarray | None, tuple[str, ...], tuple[str, ...]]:
    """The gain of a file's opcode lists on its black-subtracted mosaic (module docstring).

    lists: {"OpcodeList1"/"OpcodeList2"/"OpcodeList3": bytes} as found in the file;
    colour: (H, W) int CFA colour (0=R 1=G 2=B) of each photosite of the stored mosaic.
    Returns (gain (H, W) float64 or None where no gain opcode applies, the applied opcodes'
    labels, the skipped ones' labels with the reason). RawError naming `path` and the
    opcode for a required opcode this reader does not apply."""
    gain, applied, skipped = None, [], []
    for where in ("OpcodeList1", "OpcodeList2", "OpcodeList3"):
        if where not in lists:
            continue
        for op in parse_list(lists[where], where, path):
            if where in GAIN_LISTS and op.opcode_id in (FIX_VIGNETTE_RADIAL, GAIN_MAP):
                if op.opcode_id == FIX_VIGNETTE_RADIAL:
                    g = vignette_radial_gain(op.params, *colour.shape, path)
                else:
                    planes = 1 if where == "OpcodeList2" else 3
                    g = gain_map_gain(op.params, colour * (planes > 1), planes, path)
                gain = g if gain is None else gain * g
                applied.append(op.label)
            elif op.opcode_id in BAD_PIXELS:
                skipped.append(f"{op.label}: defective photosites are found from the frames "
                               "(gridnerf.defects)")
            elif op.optional:
                skipped.append(f"{op.label}: optional, not applied")
            else:
                raise RawError(path, f"{op.label} is required by the file (not flagged "
                               "optional) and this reader does not apply it", "re-export "
                               "the frames without it (e.g. a DNG converter with lens "
                               "corrections off) or as another raw format")
    return gain, tuple(applied), tuple(skipped)
