"""Automatic exposure and output colour: camera RGB after gains -> display sRGB.

The raw is linear, so brightness is one scale factor alpha (paper eq. 13).
Convention (shared with the simulator's references): alpha makes the mean
luminance of the bright *training* renders equal `target_luminance` (0.18,
middle grey). One alpha per scene, so every view is rendered consistently.

Gains act in camera RGB. For display, the gain-corrected camera RGB goes to
linear sRGB through the colour matrix of the raw file for the balanced illuminant
(`display_matrix`: the DNG pipeline, Bradford adaptation to D65; neutral stays
neutral). With
`use_color_matrix=False` the camera RGB is shown as if it were sRGB: the
paper's matrix-free output, which cannot undo the sensor's channel mixing.
"""

from __future__ import annotations

import warnings

import numpy as np

from gridnerf import color, illuminant


def display_matrix(xyz_to_cam: np.ndarray, use_color_matrix: bool,
                   neutral: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) linear-sRGB-from-balanced-camera-RGB matrix, or identity (paper's output).

    neutral: (3,) the camera RGB of the scene's white that the von Kries gains balanced
    (the illuminant estimate). Given, the matrix is the DNG pipeline's for the blackbody
    nearest to it on the camera's Planckian locus (color.srgb_from_cam_under: camera ->
    XYZ, Bradford adaptation to D65), applied after undoing the gains of that locus white,
    so a balanced neutral stays neutral and saturated colours are adapted in cone space
    rather than by diagonal gains in camera space. None: the row-normalised D65 matrix
    (color.srgb_from_cam, RawNeRF's convention; used where nothing was balanced).
    """
    if not use_color_matrix:
        return np.eye(3)
    if neutral is None:
        return color.srgb_from_cam(xyz_to_cam)
    kelvin = illuminant.locus_kelvin(neutral, xyz_to_cam)
    white = color.blackbody_xyz_white(kelvin)
    cam_white = np.asarray(xyz_to_cam, np.float64) @ white  # the camera's neutral, unbalanced
    unbalance = np.diag(cam_white / cam_white.mean())  # inverse of its von Kries gains
    return color.srgb_from_cam_under(xyz_to_cam, white) @ unbalance


def alpha_for_luminance(rgb_linear: np.ndarray, target: float = 0.18) -> float:
    """Scalar alpha with mean(luminance(alpha * rgb_linear)) == target.

    rgb_linear: (..., 3). A black or non-finite input gives alpha = 1 rather than Inf/NaN,
    with a warning (the output will be black or unexposed).
    """
    y = float(np.mean(color.luminance(np.asarray(rgb_linear, np.float64))))
    if not np.isfinite(y) or y <= 1e-12:
        warnings.warn(f"the image to expose is {'black' if np.isfinite(y) else 'not finite'} "
                      f"(mean luminance {y:.3g}); exposure alpha = 1", stacklevel=2)
        return 1.0
    return target / y


def to_display(rgb_cam: np.ndarray, alpha: float, matrix: np.ndarray):
    """Gain-corrected camera RGB (..., 3) -> (rgb_linear, rgb_srgb), both (..., 3) float32."""
    rgb_linear = (alpha * np.asarray(rgb_cam, np.float64)) @ matrix.T
    rgb_linear = rgb_linear.astype(np.float32)
    return rgb_linear, color.srgb_encode(rgb_linear).astype(np.float32)
