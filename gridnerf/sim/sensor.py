"""A dark-scene camera: warm illuminant, camera colour response, Bayer mosaic, ELD noise.

Pipeline for one view (an ELD-style low-light noise model: Wei et al., "A Physics-based
Noise Formation Model for Extreme Low-light Raw Denoising", CVPR 2020):
  rgb_linear (reflectance x shading, linear sRGB, as if lit by D65)
  -> XYZ under a dim blackbody at `kelvin`:  CA(D65 -> T) @ XYZ_FROM_SRGB @ rgb_linear
  -> rgb_cam = xyz_to_cam @ XYZ             (real DNG ColorMatrix, D65)
  -> expected electrons = scale * mosaic(rgb_cam), negatives clipped at 0
  -> DN = K * Poisson(e) + TukeyLambda(sigma, lambda) + row noise + bias, rounded,
     + black level 512, clipped to [0, 16383] -> uint16.
The per-CFA-position black-level `bias` is an unknown sensor offset: it is NOT in the
DNG BlackLevel tag (which says 512), exactly like a real sensor's drift.

A camera's quirks, all off by default (SensorParams): a 12- or 10-bit ADC (the same
photon statistics quantised coarser: K and the read noise scale by 2**(bits - 14), black
and white levels BLACK_BY_BITS and 2**bits - 1), lens falloff (vignette_gain, on the
electrons of the raw frames only), per-frame auto-exposure jitter (exposure_factors) and
defective photosites fixed over a capture (draw_defects, apply_defects).

`preview_srgb` is the camera's in-body JPEG pipeline for the `images/` previews (made
from the raw frame with its mapped defects concealed, conceal_defects):
subtract the black level it knows (the tag, not the unknown bias), demosaic by 2x2
binning, grey-world auto white balance, camera -> sRGB matrix, noise reduction (Gaussian:
mild on luma, strong on chroma; it is what lets feature matching work on dark frames),
digital gain to a normal brightness, upsample to full size, sRGB curve. It stays
visibly noisy and is used for pose estimation only, never as a reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.ndimage
import skimage.transform

from gridnerf import raw
from gridnerf.color import (
    CAMERA_XYZ_TO_CAM,
    D65_XYZ,
    SRGB_FROM_XYZ,
    XYZ_FROM_SRGB,
    chromatic_adaptation,
    luminance,
    srgb_encode,
    srgb_from_cam,
    tinted_xyz_white,
)
from gridnerf.sim.converter import ConverterTags

BLACK_LEVEL = 512
WHITE_LEVEL = 16383
# sensor bit depth -> black level (DN) the file records; the white level is 2**bits - 1
BLACK_BY_BITS = {14: BLACK_LEVEL, 12: 256, 10: 64}
K_PER_ISO = 9.56e-4  # system gain K (DN/e-) per ISO step, Sony A7S2 (ELD)

# CFA pattern name -> colour index per position (0=R 1=G 2=B), indexed [y % 2, x % 2].
CFA_PATTERNS = {
    "RGGB": ((0, 1), (1, 2)),
    "GRBG": ((1, 0), (2, 1)),
    "GBRG": ((1, 2), (0, 1)),
    "BGGR": ((2, 1), (1, 0)),
}


@dataclass(frozen=True)
class SensorParams:
    """Illuminant, camera and noise settings of one simulated capture.

    electrons: target MEAN expected green signal in electrons per pixel over all
      pixels of all frames (sets the photon budget; before lens falloff and exposure
      jitter, which then change the photons a frame gets); lux: the nominal light level
      class it stands for; k_gain: system gain K in DN per electron;
      read_sigma, tl_lambda: Tukey-lambda read noise scale (DN) and shape;
      row_sigma: std of the per-row offset (DN); bias: (2, 2) per-CFA-position
      black-level offset in DN (not recorded in the DNG).
    k_gain, read_sigma, row_sigma and bias are 14-bit figures: a capture at `bits` < 14
    uses them times dn_scale = 2**(bits - 14) (the same photons, a coarser ADC), while
    `iso` stays that of the 14-bit gain (the same camera setting).
    The quirk fields (bits, vignette_stops, exposure_jitter_stops, hot_pixels) default to
    the clean camera; at their defaults nothing is drawn from any random stream.
    """

    camera_model: str = "Sony ILCE-7SM2"
    cfa_pattern: str = "RGGB"
    kelvin: float = 2800.0
    electrons: float = 10.0
    lux: float = 0.02
    k_gain: float = 5.0
    read_sigma: float = 3.5
    tl_lambda: float = -0.075
    row_sigma: float = 0.7
    bias: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 0.0), (0.0, 0.0))
    exposure_time: float = 1.0 / 30.0
    # the light's distance from the Planckian locus (CIE 1960 Duv; + green, - magenta)
    tint_duv: float = 0.0
    # the ColorMatrix the file records: "sensor" (the camera's own), "generic" (XYZ -> linear
    # sRGB, what a converter writes for a camera it does not know), "other" (another
    # camera's), "diagonal" (the camera's with its rows scaled, as a converter that
    # calibrated under another light)
    file_matrix: str = "sensor"
    # share of each of this unit's colour channels taken from its spectral neighbours
    # (crosstalk_matrix; 0: the camera model's reference matrix is the sensor's)
    crosstalk: float = 0.0
    # ADC bit depth: 14, 12 or 10 (white level 2**bits - 1, black level BLACK_BY_BITS)
    bits: int = 14
    # lens falloff at the image corners, stops (vignette_gain; 0: none), raw frames only
    vignette_stops: float = 0.0
    # largest per-frame auto-exposure change, stops (frame time = exposure_time * 2**u)
    exposure_jitter_stops: float = 0.0
    # defective photosites, the same in every frame of a capture (half hot, half stuck)
    hot_pixels: int = 0
    # what a raw converter writes into the DNGs (crop margin, orientation, falloff opcode,
    # BaselineExposure): gridnerf.sim.converter; the default writes none of them
    converter: ConverterTags = ConverterTags()

    def __post_init__(self):
        if not 0.0 <= self.crosstalk < 0.5:
            raise ValueError(f"crosstalk must be in [0, 0.5), got {self.crosstalk}")
        if self.bits not in BLACK_BY_BITS:
            raise ValueError(f"bits must be one of {sorted(BLACK_BY_BITS)}, got {self.bits}")
        for field in ("vignette_stops", "exposure_jitter_stops", "hot_pixels"):
            value = getattr(self, field)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{field} must be finite and >= 0, got {value}")
        if self.hot_pixels != int(self.hot_pixels):
            raise ValueError(f"hot_pixels must be a whole number, got {self.hot_pixels}")
        if self.converter.vignette_opcode and not self.vignette_stops:
            raise ValueError("converter.vignette_opcode undoes vignette_stops: set it > 0")

    @property
    def dn_scale(self) -> float:
        """DN of this bit depth per 14-bit DN: 2**(bits - 14) (1 at 14 bits)."""
        return 2.0 ** (self.bits - 14)

    @property
    def black_level(self) -> int:
        """Black level in DN that the file records (BLACK_BY_BITS)."""
        return BLACK_BY_BITS[self.bits]

    @property
    def white_level(self) -> int:
        """White (clipping) level in DN: 2**bits - 1."""
        return 2**self.bits - 1

    @property
    def iso(self) -> float:
        """ISO that gives this system gain (K = 9.56e-4 * ISO)."""
        return self.k_gain / K_PER_ISO

    @property
    def cfa(self) -> np.ndarray:
        """(2, 2) int colour index per CFA position."""
        return np.array(CFA_PATTERNS[self.cfa_pattern], np.int64)

    @property
    def xyz_to_cam(self) -> np.ndarray:
        """(3, 3) XYZ -> camera matrix of the sensor: its camera model's DNG ColorMatrix1
        (D65), mixed by this unit's crosstalk (crosstalk_matrix)."""
        return crosstalk_matrix(self.crosstalk) @ CAMERA_XYZ_TO_CAM[self.camera_model]

    @property
    def file_xyz_to_cam(self) -> np.ndarray:
        """(3, 3) the ColorMatrix the file records (file_matrix), which need not describe
        the sensor."""
        if self.file_matrix == "sensor":
            return self.xyz_to_cam
        if self.file_matrix == "generic":
            return SRGB_FROM_XYZ.copy()
        if self.file_matrix == "other":
            others = [m for m in CAMERA_XYZ_TO_CAM if m != self.camera_model]
            return CAMERA_XYZ_TO_CAM[others[-1]]
        if self.file_matrix == "diagonal":
            return np.diag(FILE_MATRIX_DIAGONAL) @ self.xyz_to_cam
        raise ValueError(f"unknown file_matrix {self.file_matrix!r}")


def crosstalk_matrix(share: float) -> np.ndarray:
    """(3, 3) camera RGB of the model's reference -> this unit's: the unit's R and B each
    take `share` of their signal from G, its G share / 2 from each of R and B (rows sum to
    1, so a grey stays grey).
    0.1 puts the unit 4.4 deg from the Sony ILCE-7SM2's reference in the colour of a
    blackbody (illuminant.matrix_disagreement_deg), over the 2 deg at which the colour path
    calls a file's matrix not its camera's."""
    s = float(share)
    return np.array([[1.0 - s, s, 0.0], [s / 2, 1.0 - s, s / 2], [0.0, s, 1.0 - s]])


# the row scales of file_matrix = "diagonal"
FILE_MATRIX_DIAGONAL = (1.25, 1.0, 0.7)


def light_xyz(params: SensorParams) -> np.ndarray:
    """XYZ (Y = 1) of the scene's light: the blackbody at `kelvin`, tint_duv off the locus."""
    return tinted_xyz_white(params.kelvin, params.tint_duv)


def cam_from_scene(params: SensorParams) -> np.ndarray:
    """(3, 3) matrix: D65-lit linear sRGB reflectance x shading -> camera RGB under the
    scene's light (light_xyz)."""
    adapt = chromatic_adaptation(D65_XYZ, light_xyz(params))
    return params.xyz_to_cam @ adapt @ XYZ_FROM_SRGB


def illuminant_neutral(params: SensorParams) -> np.ndarray:
    """(3,) camera RGB of a white surface under the scene illuminant, green = 1."""
    white = cam_from_scene(params) @ np.ones(3)
    return white / white[1]


def scene_to_cam(rgb_linear: np.ndarray, params: SensorParams) -> np.ndarray:
    """rgb_linear: (..., 3) -> rgb_cam: (..., 3) float32, relative (unscaled) camera signal."""
    m = cam_from_scene(params).astype(np.float32)
    return np.einsum("...j,kj->...k", np.asarray(rgb_linear, np.float32), m)


def cfa_index(height: int, width: int, cfa: np.ndarray) -> np.ndarray:
    """(H, W) int colour index (0=R 1=G 2=B) of each photosite."""
    rows = np.arange(height)[:, None] % 2
    cols = np.arange(width)[None, :] % 2
    return np.asarray(cfa)[rows, cols]


def mosaic(rgb_cam: np.ndarray, cfa: np.ndarray) -> np.ndarray:
    """rgb_cam: (H, W, 3) -> raw_bayer: (H, W), keeping the CFA colour at each photosite."""
    idx = cfa_index(rgb_cam.shape[0], rgb_cam.shape[1], cfa)
    return np.take_along_axis(rgb_cam, idx[..., None], axis=-1)[..., 0]


def tukey_lambda(rng: np.random.Generator, shape, lam: float, sigma: float) -> np.ndarray:
    """Tukey-lambda samples sigma * (U^lam - (1 - U)^lam) / lam (logistic at lam = 0)."""
    u = np.clip(rng.random(shape), 1e-12, 1.0 - 1e-12)
    if abs(lam) < 1e-8:
        return sigma * np.log(u / (1.0 - u))
    return sigma * (u**lam - (1.0 - u) ** lam) / lam


def expose(electrons_bayer: np.ndarray, params: SensorParams,
           rng: np.random.Generator, defects: Defects | None = None) -> np.ndarray:
    """Expected electrons (H, W) -> noisy raw_bayer (H, W) uint16, black level included.

    Shot noise K * Poisson(e) (e clipped at 0), Tukey-lambda read noise, one
    Gaussian offset per row, the fixed per-CFA-position bias (all four in DN of the
    sensor's bit depth: the 14-bit figures times params.dn_scale), rounding to DN, the
    black level (512 at 14 bits) and clipping to [0, params.white_level]; then the
    sensor's `defects` (draw_defects), if any.
    """
    e = np.maximum(np.asarray(electrons_bayer, np.float64), 0.0)
    h, w = e.shape
    scale = params.dn_scale
    dn = (params.k_gain * scale) * rng.poisson(e).astype(np.float64)
    dn += tukey_lambda(rng, (h, w), params.tl_lambda, params.read_sigma * scale)
    dn += rng.normal(0.0, params.row_sigma * scale, (h, 1))
    bias = np.asarray(params.bias, np.float64) * scale
    dn += bias[np.arange(h)[:, None] % 2, np.arange(w)[None, :] % 2]
    dn = np.round(dn) + params.black_level
    raw_bayer = np.clip(dn, 0, params.white_level).astype(np.uint16)
    return raw_bayer if defects is None else apply_defects(raw_bayer, defects, params)


# ---------------------------------------------------------------- a camera's quirks


def vignette_coefficient(stops: float) -> float:
    """c of vignette_falloff: 2**(stops / 2) - 1, so that the corners get 2**-stops."""
    return float(2.0 ** (0.5 * stops) - 1.0)


def vignette_falloff(r: np.ndarray, stops: float) -> np.ndarray:
    """Relative illumination of a lens at normalised radius r (..., 0 at the optical
    centre, 1 at the image corners): 1 / (1 + c r^2)^2 with c = vignette_coefficient(stops).

    The cos^4 law of a lens whose corner ray leaves at tan(angle) = sqrt(c): natural
    falloff at this camera's 55 deg field of view is ~0.9 stop, a fast lens wide open
    adds its mechanical vignetting, both taken up in c. Smooth, radial, monotone, 1 at
    the centre and exactly 2**-stops at r = 1. Its inverse 1 + 2c r^2 + c^2 r^4 is the
    DNG FixVignetteRadial polynomial (k0 = 2c, k1 = c^2). Returns (...) float64.
    """
    c = vignette_coefficient(stops)
    return 1.0 / (1.0 + c * np.square(np.asarray(r, np.float64))) ** 2


def vignette_radius(height: int, width: int) -> np.ndarray:
    """(H, W) float64 distance of each pixel centre from the image centre (the optical
    centre, cx, cy of the pinhole) over the distance from the centre to a corner."""
    y = np.arange(height) + 0.5 - 0.5 * height
    x = np.arange(width) + 0.5 - 0.5 * width
    return np.hypot(y[:, None], x[None, :]) / np.hypot(0.5 * height, 0.5 * width)


def vignette_gain(height: int, width: int, stops: float) -> np.ndarray:
    """(H, W) float64 gain on the electrons of each photosite: vignette_falloff of its
    vignette_radius (all ones at stops = 0)."""
    return vignette_falloff(vignette_radius(height, width), stops)


def exposure_factors(params: SensorParams, n_frames: int,
                     rng: np.random.Generator) -> np.ndarray:
    """(N,) float64 each frame's exposure time over params.exposure_time: 2**u with u
    uniform in [-j, +j], j = params.exposure_jitter_stops (handheld auto exposure, frame by
    frame). All ones, and nothing drawn from rng, when j = 0."""
    j = float(params.exposure_jitter_stops)
    if j == 0.0:
        return np.ones(n_frames)
    return 2.0 ** rng.uniform(-j, j, n_frames)


@dataclass(frozen=True)
class Defects:
    """Defective photosites of one sensor, the same in every frame of a capture (the
    lens-cap frames too).

    hot_yx: (Nh, 2) int row, column; hot_dn: (Nh,) float DN added whatever the light (a
    leaky photosite), the sum clipped at the white level; stuck_yx: (Ns, 2) int;
    stuck_dn: (Ns,) float the value read whatever the light, in [black, white] (a dead
    one reads near black).
    """

    hot_yx: np.ndarray
    hot_dn: np.ndarray
    stuck_yx: np.ndarray
    stuck_dn: np.ndarray


HOT_RANGE = (0.5, 1.0)  # a hot pixel adds this fraction of white - black, drawn uniformly


def draw_defects(params: SensorParams, height: int, width: int,
                 rng: np.random.Generator) -> Defects | None:
    """params.hot_pixels distinct photosites of an (H, W) sensor, drawn from rng: the first
    ceil(n / 2) hot (adding HOT_RANGE of white - black), the rest stuck (a value uniform in
    [black, white]). None, and nothing drawn, when hot_pixels = 0."""
    n = int(params.hot_pixels)
    if n == 0:
        return None
    flat = rng.choice(height * width, size=n, replace=False)
    yx = np.stack(np.unravel_index(flat, (height, width)), axis=1).astype(np.int64)
    n_hot = (n + 1) // 2
    span = params.white_level - params.black_level
    hot_dn = np.round(rng.uniform(*HOT_RANGE, n_hot) * span)
    stuck_dn = np.round(rng.uniform(params.black_level, params.white_level, n - n_hot))
    return Defects(yx[:n_hot], hot_dn, yx[n_hot:], stuck_dn)


def apply_defects(raw_bayer: np.ndarray, defects: Defects, params: SensorParams) -> np.ndarray:
    """raw_bayer (H, W) uint16 -> a copy with the hot photosites raised (clipped at the
    white level) and the stuck ones set."""
    out = np.asarray(raw_bayer).astype(np.int64)
    out[defects.hot_yx[:, 0], defects.hot_yx[:, 1]] += defects.hot_dn.astype(np.int64)
    out[defects.stuck_yx[:, 0], defects.stuck_yx[:, 1]] = defects.stuck_dn.astype(np.int64)
    return np.clip(out, 0, params.white_level).astype(np.uint16)


def grey_world_neutral(rgb_cam: np.ndarray) -> np.ndarray:
    """AsShotNeutral a camera's grey-world AWB would record: (3,) channel means / green mean.

    rgb_cam: (..., 3) clean camera signal. Clipped to [0.02, 50] so the tag stays valid.
    """
    means = np.asarray(rgb_cam, np.float64).reshape(-1, 3).mean(axis=0)
    return np.clip(means / max(means[1], 1e-12), 0.02, 50.0)


def conceal_defects(raw_bayer: np.ndarray, defects: Defects | None) -> np.ndarray:
    """What a camera's JPEG engine does with the defects in its factory map: raw_bayer (H, W)
    uint16 -> a copy with each defective photosite replaced by the median of its same-colour
    neighbours two photosites away (up, down, left, right; defects left out). The raw
    frames keep their defects; the previews (preview_srgb) are made from this."""
    if defects is None:
        return raw_bayer
    h, w = raw_bayer.shape
    bad = {tuple(p) for p in np.concatenate([defects.hot_yx, defects.stuck_yx]).tolist()}
    out = raw_bayer.copy()
    for y, x in bad:
        near = [int(raw_bayer[y + dy, x + dx]) for dy, dx in ((-2, 0), (2, 0), (0, -2), (0, 2))
                if 0 <= y + dy < h and 0 <= x + dx < w and (y + dy, x + dx) not in bad]
        if near:
            out[y, x] = int(np.median(near))
    return out


# ---------------------------------------------------------------- in-camera JPEG preview

PREVIEW_MEAN_LUMINANCE = 0.18


def preview_srgb(raw_bayer: np.ndarray, cfa: np.ndarray, black_level: np.ndarray,
                 white_level: int, xyz_to_cam: np.ndarray, luma_sigma: float = 1.5,
                 chroma_sigma: float = 4.0) -> np.ndarray:
    """Camera-style preview of one dark frame.

    raw_bayer: (H, W) uint16 mosaic; cfa: (2, 2) colour index per CFA position;
    black_level: (2, 2) per CFA position (as in the DNG); xyz_to_cam: (3, 3);
    luma_sigma / chroma_sigma: Gaussian noise-reduction widths in half-resolution
    pixels for luminance and for colour differences.
    Returns rgb_srgb: (H, W, 3) float32 in [0, 1].
    """
    h, w = raw_bayer.shape
    raw_norm = raw.normalize_mosaic(raw_bayer, black_level, white_level, np.float64)
    rgb_cam = raw.bin2x2(raw_norm, cfa, dtype=np.float64)
    means = np.maximum(rgb_cam.reshape(-1, 3).mean(axis=0), 1e-6)
    rgb_cam_wb = rgb_cam * (means[1] / means)
    rgb_linear = np.einsum("...j,kj->...k", rgb_cam_wb, srgb_from_cam(xyz_to_cam))
    # Noise reduction like a camera's: mild on luma, strong on chroma.
    luma = luminance(rgb_linear)[..., None]
    luma_nr = scipy.ndimage.gaussian_filter(luma, (luma_sigma, luma_sigma, 0))
    chroma_nr = scipy.ndimage.gaussian_filter(rgb_linear - luma, (chroma_sigma, chroma_sigma, 0))
    rgb_linear = luma_nr + chroma_nr
    gain = PREVIEW_MEAN_LUMINANCE / max(float(luminance(np.maximum(rgb_linear, 0)).mean()), 1e-6)
    rgb_linear = np.clip(rgb_linear * gain, 0.0, 1.0)
    rgb_linear = skimage.transform.resize(rgb_linear, (h, w, 3), order=1, mode="edge")
    return srgb_encode(rgb_linear).astype(np.float32)


def to_uint8(rgb_srgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> uint8, rounded."""
    return np.round(np.clip(rgb_srgb, 0.0, 1.0) * 255.0).astype(np.uint8)
