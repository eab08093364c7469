"""What a raw converter or a phone writes into a simulated capture's DNGs (ConverterTags):
a crop margin (DefaultCrop), the orientation the camera was held in (Orientation), the lens
falloff correction (a FixVignetteRadial opcode in OpcodeList3) and BaselineExposure.

The stored files are made so that a reader that honours the tags (gridnerf.raw_layout)
recovers the clean camera's view that transforms.json describes: the simulated mosaic is
the image as displayed; stored() turns it by the inverse of the orientation and pads it
by the crop margin (photosites outside the displayed area: black-level sensor noise, which
a reader that ignores the crop shows as dark borders). The CFA pattern written is the
stored mosaic's, so that reading it at the crop origin and turning it gives the sensor's
displayed pattern back. The falloff (SensorParams.vignette_stops) stays on the light as
simulated; the opcode written undoes it exactly: the displayed image's polynomial
1 + 2c r^2 + c^2 r^4 re-expressed for the stored image, whose radius is normalised to its
own farthest corner (DNG 1.4 spec, Chapter 7, FixVignetteRadial) and whose optical centre
is the displayed area's centre. At the defaults nothing changes and nothing is drawn.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gridnerf import raw_layout


@dataclass(frozen=True)
class ConverterTags:
    """The converter tags a simulated capture's DNGs carry (all off by default).

    crop_margin: (left, top, right, bottom) photosites of the stored mosaic around the
      displayed area (in stored orientation), written as DefaultCropOrigin/Size; an odd
      left or top margin shifts the stored CFA phase.
    orientation: TIFF Orientation 1..8 written; the stored mosaic is the displayed one
      turned back (raw_layout.from_display).
    vignette_opcode: write the FixVignetteRadial opcode that undoes vignette_stops.
    baseline_exposure: BaselineExposure (EV) written, one value or one per frame (cycled).
    """

    crop_margin: tuple[int, int, int, int] = (0, 0, 0, 0)
    orientation: int = 1
    vignette_opcode: bool = False
    baseline_exposure: float | tuple[float, ...] | None = None

    def __post_init__(self):
        margin = tuple(self.crop_margin)
        if len(margin) != 4 or any(int(m) != m or m < 0 for m in margin):
            raise ValueError(f"crop_margin must be 4 whole numbers >= 0, got {margin}")
        if self.orientation not in raw_layout.ORIENTATION_NAMES:
            raise ValueError(f"orientation must be a TIFF Orientation 1..8, "
                             f"got {self.orientation}")
        levels = np.atleast_1d(np.asarray(self.baseline_exposure
                                          if self.baseline_exposure is not None else 0.0))
        if levels.size == 0 or not np.all(np.isfinite(levels.astype(np.float64))):
            raise ValueError(f"baseline_exposure must be finite EV values, "
                             f"got {self.baseline_exposure}")

    @property
    def is_default(self) -> bool:
        return self == ConverterTags()


def stored_shape(display_hw: tuple[int, int], tags: ConverterTags) -> tuple[int, int]:
    """(H, W) of the stored mosaic of a displayed (H, W) image."""
    h, w = display_hw if tags.orientation < 5 else display_hw[::-1]
    left, top, right, bottom = tags.crop_margin
    return h + top + bottom, w + left + right


def stored(raw_bayer: np.ndarray, cfa, tags: ConverterTags,
           margin_fill: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(stored raw_bayer (Hs, Ws), stored cfa (2, 2)) of a displayed raw_bayer (H, W)
    with displayed cfa (2, 2); margin_fill: (Hs, Ws) the photosites around the displayed
    area (needed where crop_margin is not all zero)."""
    inner_bayer = raw_layout.from_display(np.asarray(raw_bayer), tags.orientation)
    left, top, _, _ = tags.crop_margin
    h, w = inner_bayer.shape
    stored_bayer = inner_bayer
    if any(tags.crop_margin):
        stored_bayer = np.array(margin_fill, dtype=inner_bayer.dtype, copy=True)
        stored_bayer[top:top + h, left:left + w] = inner_bayer
    # the stored pattern: the displayed one turned back (only the size's parity matters),
    # phase-shifted by the margin
    hd, wd = np.shape(raw_bayer)
    proxy = np.tile(np.asarray(cfa), (2, 2))[:2 + hd % 2, :2 + wd % 2]
    colour = raw_layout.from_display(proxy, tags.orientation)[:2, :2]
    stored_cfa = np.roll(colour, (top, left), axis=(0, 1))
    return stored_bayer, stored_cfa


def vignette_opcode(display_hw: tuple[int, int], tags: ConverterTags,
                    c: float) -> tuple[list[float], tuple[float, float]]:
    """(k0..k1, (cx, cy)) of the FixVignetteRadial that undoes the falloff 1 / (1 + c r^2)^2
    of a displayed (H, W) image (sensor.vignette_falloff, r normalised to its corner) on
    the stored image: centre at the displayed area's centre, r_displayed = s r_stored with
    s the stored image's corner distance over the displayed one's."""
    hs, ws = stored_shape(display_hw, tags)
    h, w = display_hw if tags.orientation < 5 else display_hw[::-1]
    left, top, _, _ = tags.crop_margin
    cx, cy = left + 0.5 * w, top + 0.5 * h
    s2 = (max(cx, ws - cx) ** 2 + max(cy, hs - cy) ** 2) / (0.25 * (w * w + h * h))
    return [2.0 * c * s2, c * c * s2 * s2], (cx / ws, cy / hs)


def dng_kwargs(tags: ConverterTags, display_hw: tuple[int, int], c: float | None,
               frame: int) -> dict:
    """write_dng's converter arguments for frame `frame` of a capture ({} at the
    defaults); c: the falloff coefficient (sensor.vignette_coefficient) or None."""
    if tags.is_default:
        return {}
    out: dict = {"orientation": tags.orientation}
    if any(tags.crop_margin):
        h, w = display_hw if tags.orientation < 5 else display_hw[::-1]
        out["default_crop"] = (tags.crop_margin[0], tags.crop_margin[1], w, h)
    if tags.vignette_opcode and c:
        out["vignette_k"], out["vignette_centre"] = vignette_opcode(display_hw, tags, c)
    if tags.baseline_exposure is not None:
        levels = np.atleast_1d(np.asarray(tags.baseline_exposure, np.float64))
        out["baseline_exposure"] = float(levels[frame % levels.size])
    return out


def manifest(tags: ConverterTags, display_hw: tuple[int, int], c: float | None) -> dict:
    """sim.json's "converter_tags" entry ({} at the defaults)."""
    if tags.is_default:
        return {}
    entry = {"crop_margin_ltrb": list(tags.crop_margin), "orientation": tags.orientation,
             "stored_hw": list(stored_shape(display_hw, tags)),
             "note": "raw/ and dark/ store the displayed mosaic turned back by the "
                     "orientation and padded by the margin (black-level noise); a reader "
                     "that honours DefaultCrop, Orientation and OpcodeList3 recovers the "
                     "view transforms.json describes"}
    if tags.vignette_opcode and c:
        k, centre = vignette_opcode(display_hw, tags, c)
        entry["fix_vignette_radial"] = {"k": k, "centre": list(centre)}
    if tags.baseline_exposure is not None:
        entry["baseline_exposure_ev"] = np.atleast_1d(tags.baseline_exposure).tolist()
    return {"converter_tags": entry}
