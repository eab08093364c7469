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

`preview_srgb` is the camera's in-body JPEG pipeline for the `images/` previews:
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

BLACK_LEVEL = 512
WHITE_LEVEL = 16383
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
      pixels of all frames (sets the photon budget); lux: the nominal light level
      class it stands for; k_gain: system gain K in DN per electron;
      read_sigma, tl_lambda: Tukey-lambda read noise scale (DN) and shape;
      row_sigma: std of the per-row offset (DN); bias: (2, 2) per-CFA-position
      black-level offset in DN (not recorded in the DNG).
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
        """(3, 3) XYZ -> camera matrix of the sensor (its DNG ColorMatrix1, D65)."""
        return CAMERA_XYZ_TO_CAM[self.camera_model]

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
           rng: np.random.Generator) -> np.ndarray:
    """Expected electrons (H, W) -> noisy raw_bayer (H, W) uint16, black level included.

    Shot noise K * Poisson(e) (e clipped at 0), Tukey-lambda read noise, one
    Gaussian offset per row, the fixed per-CFA-position bias, rounding to DN,
    black level 512 and clipping to [0, WHITE_LEVEL].
    """
    e = np.maximum(np.asarray(electrons_bayer, np.float64), 0.0)
    h, w = e.shape
    dn = params.k_gain * rng.poisson(e).astype(np.float64)
    dn += tukey_lambda(rng, (h, w), params.tl_lambda, params.read_sigma)
    dn += rng.normal(0.0, params.row_sigma, (h, 1))
    bias = np.asarray(params.bias, np.float64)
    dn += bias[np.arange(h)[:, None] % 2, np.arange(w)[None, :] % 2]
    dn = np.round(dn) + BLACK_LEVEL
    return np.clip(dn, 0, WHITE_LEVEL).astype(np.uint16)


def grey_world_neutral(rgb_cam: np.ndarray) -> np.ndarray:
    """AsShotNeutral a camera's grey-world AWB would record: (3,) channel means / green mean.

    rgb_cam: (..., 3) clean camera signal. Clipped to [0.02, 50] so the tag stays valid.
    """
    means = np.asarray(rgb_cam, np.float64).reshape(-1, 3).mean(axis=0)
    return np.clip(means / max(means[1], 1e-12), 0.02, 50.0)


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
