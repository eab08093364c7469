"""Pixel rays, LLFF-style world normalisation and NDC (normalised device coordinates).

Ray directions are NOT unit length: their camera-frame z component is -1, so a ray
parameter t is the depth along the camera's viewing axis. Ray functions work on numpy
and jax arrays alike (the array namespace follows the inputs, or pass `xp`).
"""

from __future__ import annotations

import numpy as np

from gridnerf.cameras import Cameras


def _namespace(*arrays):
    """numpy unless one of the inputs is a jax array (or tracer)."""
    for a in arrays:
        if not isinstance(a, np.ndarray | np.generic | float | int):
            import jax.numpy as jnp

            return jnp
    return np


def pixel_rays(c2w, fx, fy, cx, cy, u, v, xp=None):
    """World rays through the centres of pixels (u, v).

    c2w: (3, 4) or broadcastable (..., 3, 4); fx, fy, cx, cy: scalars or (...,);
    u, v: (...,) pixel indices (column, row; floats allowed). Returns origins (..., 3)
    and directions (..., 3), camera-frame direction ((u+0.5-cx)/fx, -(v+0.5-cy)/fy, -1).
    """
    xp = xp or _namespace(c2w, u, v)
    d_cam = xp.stack(
        [(u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -xp.ones_like((u + 0.5) / fx)], axis=-1
    )
    directions = xp.einsum("...ij,...j->...i", c2w[..., :3, :3], d_cam)
    origins = xp.broadcast_to(c2w[..., :3, 3], directions.shape)
    return origins, directions


def camera_rays(cams: Cameras, i: int, xp=np):
    """All rays of camera i: origins (H, W, 3), directions (H, W, 3) in world coordinates."""
    v, u = np.meshgrid(np.arange(cams.height, dtype=np.float64),
                       np.arange(cams.width, dtype=np.float64), indexing="ij")
    origins, directions = pixel_rays(cams.c2w[i], cams.fx[i], cams.fy[i], cams.cx[i],
                                     cams.cy[i], u, v, xp=np)
    if xp is not np:
        return xp.asarray(origins, dtype=xp.float32), xp.asarray(directions, dtype=xp.float32)
    return np.ascontiguousarray(origins), directions


def look_at(position, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(3, 3) camera-to-world rotation (OpenGL axes: the camera looks along -z) from
    `position` towards `target`, its y axis in the plane of `up` and the view direction."""
    f = np.asarray(target, float) - np.asarray(position, float)
    f /= np.linalg.norm(f)
    x = np.cross(f, up)
    x /= np.linalg.norm(x)
    y = np.cross(x, f)
    return np.stack([x, y, -f], axis=1)


def average_pose(c2w: np.ndarray) -> np.ndarray:
    """(N, 3, 4) -> (3, 4): mean position; axes from the mean backward and up vectors,
    re-orthonormalised (LLFF's poses_avg, OpenGL axes)."""
    back = c2w[:, :, 2].mean(axis=0)
    back = back / np.linalg.norm(back)
    up = c2w[:, :, 1].mean(axis=0)
    right = np.cross(up, back)
    right = right / np.linalg.norm(right)
    up = np.cross(back, right)
    return np.stack([right, up, back, c2w[:, :, 3].mean(axis=0)], axis=1)


def normalize_world(c2w: np.ndarray, near: float, far: float):
    """Recentre poses on their average pose and scale by s = 1 / (0.75 * near) (LLFF).

    c2w: (N, 3, 4). Returns (c2w' (N, 3, 4), near' = 1/0.75, far' = far * s, T (4, 4))
    where T maps normalised points to world points: p_world = T @ [p_norm, 1].
    In the new frame the average camera sits at the origin looking along -z.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    avg = average_pose(c2w)
    r_avg, t_avg = avg[:, :3], avg[:, 3]
    s = 1.0 / (0.75 * near)
    rot = np.einsum("ji,njk->nik", r_avg, c2w[:, :, :3])
    pos = s * (c2w[:, :, 3] - t_avg) @ r_avg
    world_from_norm = np.eye(4)
    world_from_norm[:3, :3] = r_avg / s
    world_from_norm[:3, 3] = t_avg
    return np.concatenate([rot, pos[:, :, None]], axis=2), near * s, far * s, world_from_norm


def forward_facing(c2w: np.ndarray, max_angle_deg: float = 45.0) -> bool:
    """True when every viewing direction (-z axis) is within max_angle_deg of the mean one."""
    view = -np.asarray(c2w)[:, :, 2]
    view = view / np.linalg.norm(view, axis=1, keepdims=True)
    mean = view.mean(axis=0)
    norm = np.linalg.norm(mean)
    if norm < 1e-8:
        return False
    return bool(np.all(view @ (mean / norm) >= np.cos(np.deg2rad(max_angle_deg))))


def ndc_rays(origins, directions, fx, fy, width, height, near=1.0, xp=None):
    """LLFF NDC rays: move origins to the plane z = -near, then warp.

    origins, directions: (..., 3) in the normalised world (cameras look along -z).
    Returns (origins_ndc, directions_ndc), each (..., 3): the NDC ray o + t d, t in [0, 1],
    covers depth near..infinity (ndc z from -1 to +1). Use one scene-level fx, fy, width,
    height (the first camera's) for all views: NDC is a fixed warp of space.
    """
    xp = xp or _namespace(origins, directions)
    t = -(near + origins[..., 2]) / directions[..., 2]
    o = origins + t[..., None] * directions
    ax, ay = -2.0 * fx / width, -2.0 * fy / height
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = directions[..., 0], directions[..., 1], directions[..., 2]
    o_ndc = xp.stack([ax * ox / oz, ay * oy / oz, 1.0 + 2.0 * near / oz], axis=-1)
    d_ndc = xp.stack(
        [ax * (dx / dz - ox / oz), ay * (dy / dz - oy / oz), -2.0 * near / oz], axis=-1
    )
    return o_ndc, d_ndc


def ndc_points(points, fx, fy, width, height, near=1.0, xp=None):
    """The NDC image of world points (..., 3) with z < 0 (the warp ndc_rays applies)."""
    xp = xp or _namespace(points)
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return xp.stack(
        [-2.0 * fx / width * x / z, -2.0 * fy / height * y / z, 1.0 + 2.0 * near / z], axis=-1
    )


def world_from_ndc(points_ndc, fx, fy, width, height, near=1.0, xp=None):
    """World points (..., 3) of NDC points (..., 3) with z_ndc < 1: the inverse of
    ndc_points (z = -ndc_depth_to_world(z_ndc))."""
    xp = xp or _namespace(points_ndc)
    z = -ndc_depth_to_world(xp.minimum(points_ndc[..., 2], 1.0 - 1e-6), near)
    return xp.stack([-points_ndc[..., 0] * z * width / (2.0 * fx),
                     -points_ndc[..., 1] * z * height / (2.0 * fy), z], axis=-1)


def ndc_depth_to_world(z_ndc, near=1.0):
    """NDC z in [-1, 1) -> world depth along -z (near .. infinity)."""
    return 2.0 * near / (1.0 - z_ndc)
