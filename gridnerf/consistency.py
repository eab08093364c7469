"""Multi-view consistency: how much two views of the same surface disagree in colour.

The paper claims that processing each frame on its own (2D enhancement) gives views that
disagree where a 3D model cannot. This module makes that a number: the pixels of view A
are moved to view B along the 3D points the grid renders for A, and the colours of the
two images are compared where B sees the same point (its own rendered point lies at the
same depth, so occluded pixels are left out). The geometry is the grid's for every method
compared, so only the images differ.

Points come from a render (render.render_image outputs): the expected ray parameter
depth / acc along the grid-space ray, mapped back to the normalised world through the
inverse of the scene's NDC warp for forward-facing scenes (rays.ndc_points with near 1).
"""

from __future__ import annotations

import numpy as np

from gridnerf import rays
from gridnerf.cameras import project_points


def world_points(depth, acc, origins, directions, ndc: bool, ndc_intrinsics=None,
                 min_acc: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) world points and (H, W) bool validity of a render.

    depth, acc: (H, W) render outputs (depth = sum w t, not divided by acc); origins,
    directions: (H, W, 3) the grid-space rays it was rendered from; ndc: the scene's grid
    is NDC, ndc_intrinsics (4,) fx, fy, width, height of its warp. Rays with opacity below
    min_acc have no surface to speak of and are invalid.
    """
    acc = np.asarray(acc, np.float64)
    t = np.asarray(depth, np.float64) / np.maximum(acc, 1e-6)
    p = np.asarray(origins, np.float64) + t[..., None] * np.asarray(directions, np.float64)
    valid = acc >= min_acc
    if ndc:
        fx, fy, w, h = (float(v) for v in np.asarray(ndc_intrinsics))
        p = rays.world_from_ndc(p, fx, fy, w, h, near=1.0, xp=np)
    return p, valid & np.all(np.isfinite(p), axis=-1)


def camera_depth(c2w, points) -> np.ndarray:
    """(..., 3) world points -> (...) depth along the camera's viewing axis (-z)."""
    c2w = np.asarray(c2w, np.float64)
    return -((np.asarray(points, np.float64) - c2w[:, 3]) @ c2w[:, :3])[..., 2]


def landing(points_a, valid_a, points_b, valid_b, c2w_b, intrinsics_b,
            rel_tol: float = 0.03) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where view A's surface points land in view B: (uv (H, W, 2) continuous pixel
    coordinates in B (project_points), u, v (H, W) the pixel of B each lands in (0 where
    it does not count), ok (H, W) bool). A pixel of A counts when it is valid, lands inside
    B, on a valid pixel of B whose own point lies within rel_tol of the depth of A's point
    in B (else B sees something in front of it: occluded). points_*, valid_*: world_points
    of each view; c2w_b (3, 4), intrinsics_b (fx, fy, cx, cy) of view B."""
    h, w = np.shape(valid_b)[:2]
    uv = project_points(c2w_b, intrinsics_b, points_a)
    ok = np.asarray(valid_a, bool) & np.all(np.isfinite(uv), axis=-1)
    u = np.floor(np.where(ok, uv[..., 0], -1)).astype(np.int64)
    v = np.floor(np.where(ok, uv[..., 1], -1)).astype(np.int64)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v = np.where(ok, u, 0), np.where(ok, v, 0)
    ok &= np.asarray(valid_b, bool)[v, u]
    d_a = camera_depth(c2w_b, points_a)
    d_b = camera_depth(c2w_b, np.asarray(points_b)[v, u])
    ok &= np.abs(d_a - d_b) <= rel_tol * np.abs(d_b)
    return uv, u, v, ok


def warp_disagreement(image_a, points_a, valid_a, image_b, points_b, valid_b, c2w_b,
                      intrinsics_b, rel_tol: float = 0.03) -> dict:
    """Mean absolute colour difference between view A and view B at the same surface points.

    image_a, image_b: (H, W, C) images of the two views in one colour space (e.g. rgb_srgb);
    points_a, points_b: (H, W, 3) world points and valid_a, valid_b (H, W) of each view
    (world_points); c2w_b (3, 4), intrinsics_b (fx, fy, cx, cy) of view B. The pixels of A
    that count (landing, within rel_tol of B's depth) are compared with B's pixel they land
    in (nearest pixel). Returns {"mae": mean |A - B| over counted pixels and channels,
    "coverage": counted share of A's pixels}; mae is NaN when no pixel counts.
    """
    _, u, v, ok = landing(points_a, valid_a, points_b, valid_b, c2w_b, intrinsics_b, rel_tol)
    if not ok.any():
        return {"mae": float("nan"), "coverage": 0.0}
    a = np.asarray(image_a, np.float64)[ok]
    diff = np.abs(a - np.asarray(image_b, np.float64)[v[ok], u[ok]])
    return {"mae": float(diff.mean()), "coverage": float(ok.mean())}
