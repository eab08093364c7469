"""Colour spaces and camera colour matrices (numpy; jnp-compatible where noted).

Naming: `rgb_linear` is linear sRGB primaries (D65), `rgb_srgb` is sRGB-encoded
in [0, 1], `rgb_cam` is camera-native linear RGB (where the raw lives).
"""

from __future__ import annotations

import numpy as np

# Linear sRGB (D65) -> CIE XYZ. Rows: X, Y, Z.
XYZ_FROM_SRGB = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
SRGB_FROM_XYZ = np.linalg.inv(XYZ_FROM_SRGB)

# XYZ -> camera (D65), as stored in DNG ColorMatrix tags (x 1e-4); the values of Adobe DNG
# Converter / LibRaw's camera table for these bodies.
CAMERA_XYZ_TO_CAM = {
    "Sony ILCE-7SM2": np.array([5838, -1430, -246, -3497, 11477, 2297, -748, 1885, 5778]) / 1e4,
    "Canon EOS 5D Mark IV": np.array([6446, -366, -864, -4436, 12204, 2513, -952, 2496, 6348])
    / 1e4,
    "Nikon D850": np.array([10405, -3755, -1270, -5461, 13787, 1793, -1040, 2015, 6785]) / 1e4,
}
CAMERA_XYZ_TO_CAM = {k: v.reshape(3, 3) for k, v in CAMERA_XYZ_TO_CAM.items()}

# Rec. 709 luma weights (the Y row of XYZ_FROM_SRGB).
LUMA = XYZ_FROM_SRGB[1]


def srgb_encode(rgb_linear, xp=np):
    """Linear sRGB -> sRGB curve. Input is clipped to [0, 1]. Works with np or jnp (xp)."""
    x = xp.clip(rgb_linear, 0.0, 1.0)
    lo = 12.92 * x
    hi = 1.055 * xp.power(xp.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055
    return xp.where(x <= 0.0031308, lo, hi)


def srgb_decode(rgb_srgb, xp=np):
    """sRGB curve -> linear sRGB. Works with np or jnp (xp)."""
    x = xp.clip(rgb_srgb, 0.0, 1.0)
    lo = x / 12.92
    hi = xp.power((xp.maximum(x, 0.04045) + 0.055) / 1.055, 2.4)
    return xp.where(x <= 0.04045, lo, hi)


def cam_from_srgb(xyz_to_cam: np.ndarray) -> np.ndarray:
    """Row-normalised camera-from-linear-sRGB matrix (3, 3).

    Rows sum to one, so sRGB white (1, 1, 1) maps to camera (1, 1, 1): a
    neutral that the von Kries gains have balanced stays neutral (RawNeRF's
    convention).
    """
    m = np.asarray(xyz_to_cam, np.float64) @ XYZ_FROM_SRGB
    return m / m.sum(axis=1, keepdims=True)


def srgb_from_cam(xyz_to_cam: np.ndarray) -> np.ndarray:
    """Linear-sRGB-from-white-balanced-camera-RGB matrix (3, 3); inverse of cam_from_srgb."""
    return np.linalg.inv(cam_from_srgb(xyz_to_cam))


def luminance(rgb_linear, xp=np):
    """Relative luminance Y of linear sRGB, shape (..., 3) -> (...)."""
    return rgb_linear @ xp.asarray(LUMA, dtype=rgb_linear.dtype)


def _uv(xyz: np.ndarray) -> np.ndarray:
    """CIE 1960 (u, v) of an XYZ colour."""
    x, y, z = np.asarray(xyz, np.float64)
    d = x + 15.0 * y + 3.0 * z
    return np.array([4.0 * x / d, 6.0 * y / d])


def tinted_xyz_white(kelvin: float, duv: float) -> np.ndarray:
    """XYZ (Y = 1) of a light `duv` off the Planckian locus at `kelvin`: the blackbody's
    CIE 1960 (u, v) moved by duv along the locus's normal (ANSI C78.377's Duv: positive
    above the locus, towards green, as many fluorescent and LED lights and high-pressure
    sodium are; negative below, towards magenta). duv = 0 gives blackbody_xyz_white."""
    if duv == 0:
        return blackbody_xyz_white(kelvin)
    uv = _uv(blackbody_xyz_white(kelvin))
    tangent = _uv(blackbody_xyz_white(kelvin * 1.01)) - _uv(blackbody_xyz_white(kelvin / 1.01))
    tangent /= np.linalg.norm(tangent)
    normal = np.array([-tangent[1], tangent[0]])  # the locus runs towards lower v as T rises
    normal = normal if normal[1] > 0 else -normal  # +v: above the locus
    u, v = uv + duv * normal
    x, y = 3.0 * u / (2.0 * u - 8.0 * v + 4.0), 2.0 * v / (2.0 * u - 8.0 * v + 4.0)
    return np.array([x / y, 1.0, (1.0 - x - y) / y])


def blackbody_xyz_white(kelvin: float) -> np.ndarray:
    """XYZ of a Planckian illuminant at `kelvin`, normalised to Y = 1 (shape (3,)).

    Integrates Planck's law against the CIE 1931 2-degree observer, using
    the analytic multi-lobe Gaussian fit of Wyman, Sloan and Shirley (2013).
    """
    lam = np.arange(380.0, 781.0, 1.0)  # nm

    def g(x, mu, s1, s2):
        s = np.where(x < mu, s1, s2)
        return np.exp(-0.5 * ((x - mu) / s) ** 2)

    xbar = 1.056 * g(lam, 599.8, 37.9, 31.0) + 0.362 * g(lam, 442.0, 16.0, 26.7) - 0.065 * g(
        lam, 501.1, 20.4, 26.2
    )
    ybar = 0.821 * g(lam, 568.8, 46.9, 40.5) + 0.286 * g(lam, 530.9, 16.3, 31.1)
    zbar = 1.217 * g(lam, 437.0, 11.8, 36.0) + 0.681 * g(lam, 459.0, 26.0, 13.8)
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lm = lam * 1e-9
    spd = 1.0 / (lm**5 * (np.exp(h * c / (lm * k * kelvin)) - 1.0))
    xyz = np.array([np.sum(spd * xbar), np.sum(spd * ybar), np.sum(spd * zbar)])
    return xyz / xyz[1]


# CIE D65 white point, Y = 1.
D65_XYZ = np.array([0.95047, 1.0, 1.08883])

# Bradford cone-response matrix (XYZ -> LMS-like sharpened space).
BRADFORD = np.array(
    [[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]]
)


def chromatic_adaptation(src_white_xyz: np.ndarray, dst_white_xyz: np.ndarray) -> np.ndarray:
    """Bradford (von Kries in sharpened cone space) XYZ->XYZ matrix (3, 3), src -> dst white."""
    s = BRADFORD @ src_white_xyz
    d = BRADFORD @ dst_white_xyz
    return np.linalg.inv(BRADFORD) @ np.diag(d / s) @ BRADFORD


def srgb_from_cam_under(xyz_to_cam: np.ndarray, white_xyz: np.ndarray) -> np.ndarray:
    """Linear-sRGB-from-camera-RGB matrix (3, 3) for a scene lit by `white_xyz` (unbalanced
    camera RGB in, D65 linear sRGB out): the inverse of the camera matrix, then Bradford
    adaptation of the scene's white to D65, the DNG pipeline's order (Adobe DNG
    specification 1.6, "Mapping Camera Color Space to CIE XYZ Space": camera -> XYZ with
    the ColorMatrix, then chromatic adaptation of the camera neutral's white to the output
    white). The camera's own neutral under that light maps to sRGB white."""
    return (SRGB_FROM_XYZ @ chromatic_adaptation(np.asarray(white_xyz, np.float64), D65_XYZ)
            @ np.linalg.inv(np.asarray(xyz_to_cam, np.float64)))
