"""Pinhole cameras: the `Cameras` container, resizing, validation, projection.

Conventions (docs/design.md): camera-to-world `(N, 3, 4)` in OpenGL axes (x right, y up,
the camera looks along -z). Pixel (col u, row v) has its centre at `(u + 0.5, v + 0.5)`;
the ray through it has camera-frame direction `((u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1)`.
Intrinsics are in pixels of the full-resolution frame. COLMAP uses the same pixel-centre
convention, so its `cx, cy` carry over unchanged.

The pose files that hold them are read and written by gridnerf.pose_files.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from gridnerf.errors import PoseError, SceneError


@dataclass(frozen=True, eq=False)
class Cameras:
    """N pinhole cameras sharing one frame size.

    names: frame stems (raw/<name>.dng); c2w: (N, 3, 4) float64 OpenGL camera-to-world;
    fx, fy, cx, cy: (N,) float64 pixels of the full-res frame; width, height: frame size.
    """

    names: tuple[str, ...]
    c2w: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    width: int
    height: int

    def __len__(self) -> int:
        return len(self.names)

    def intrinsics(self, i: int) -> np.ndarray:
        """(4,) fx, fy, cx, cy of frame i in pixels."""
        return np.array([self.fx[i], self.fy[i], self.cx[i], self.cy[i]], np.float64)

    def scaled(self, factor: float) -> Cameras:
        """Cameras for the image scaled by `factor` (0.5 for 2x2 binning); sizes are floored."""
        return dataclasses.replace(
            self,
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=self.cx * factor,
            cy=self.cy * factor,
            width=int(np.floor(self.width * factor + 1e-9)),
            height=int(np.floor(self.height * factor + 1e-9)),
        )

    def take(self, indices) -> Cameras:
        """The subset (in the given order) of cameras `indices` (int sequence)."""
        idx = np.asarray(indices, dtype=int)
        return dataclasses.replace(
            self,
            names=tuple(self.names[i] for i in idx),
            c2w=self.c2w[idx],
            fx=self.fx[idx],
            fy=self.fy[idx],
            cx=self.cx[idx],
            cy=self.cy[idx],
        )

    def with_c2w(self, c2w: np.ndarray) -> Cameras:
        """The same cameras with new poses c2w: (N, 3, 4)."""
        return dataclasses.replace(self, c2w=np.asarray(c2w, dtype=np.float64))


def make_cameras(names, c2w, fx, fy, cx, cy, width: int, height: int) -> Cameras:
    """Build `Cameras`, broadcasting scalar intrinsics to (N,) float64 arrays."""
    n = len(names)
    c2w = np.asarray(c2w, dtype=np.float64).reshape(n, -1, 4)[:, :3, :]

    def vec(x):
        return np.broadcast_to(np.asarray(x, dtype=np.float64), (n,)).copy()

    return Cameras(tuple(names), c2w, vec(fx), vec(fy), vec(cx), vec(cy), int(width), int(height))


def resize_to(cams: Cameras, width: int, height: int, source_path) -> Cameras:
    """Rescale intrinsics given for another image size (e.g. JPEG previews) to width x height.

    Raises SceneError naming source_path if the aspect ratios differ by more than 2%.
    """
    if (cams.width, cams.height) == (width, height):
        return cams
    return rescale(cams, width / cams.width, height / cams.height, width, height, source_path)


def rescale(cams: Cameras, sx: float, sy: float, width: int, height: int, path) -> Cameras:
    if abs(sx / sy - 1.0) > 0.02:
        raise SceneError(
            path,
            f"camera size {cams.width}x{cams.height} does not match the raw frames' "
            f"{width}x{height} (different aspect ratio)",
            "give intrinsics for the full raw frame size (w, h in transforms.json) or "
            "re-run `gridnerf poses` on previews with the raw frames' aspect ratio",
        )
    return dataclasses.replace(
        cams, fx=cams.fx * sx, fy=cams.fy * sy, cx=cams.cx * sx, cy=cams.cy * sy,
        width=int(width), height=int(height),
    )


def validate(cams: Cameras, source_path) -> None:
    """PoseError naming source_path and the frame for non-finite or non-rigid poses."""
    for i, name in enumerate(cams.names):
        m = cams.c2w[i]
        intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]])
        if not (np.all(np.isfinite(m)) and np.all(np.isfinite(intr))):
            raise PoseError(source_path, f"frame {name!r} has a NaN/Inf pose or intrinsics",
                            "re-run `gridnerf poses` or remove the frame")
        r = m[:, :3]
        err = np.abs(r.T @ r - np.eye(3)).max()
        if err > 1e-3 or np.linalg.det(r) <= 0:
            raise PoseError(source_path, f"frame {name!r}: rotation is not rigid "
                            f"(|R^T R - I| = {err:.2g}, det = {np.linalg.det(r):.3g})",
                            "give orthonormal right-handed rotations (no scale or mirror)")
        if cams.fx[i] <= 0 or cams.fy[i] <= 0:
            raise PoseError(source_path, f"frame {name!r}: focal length must be positive",
                            "fix fl_x/fl_y")


def project_points(c2w, intrinsics, points_world) -> np.ndarray:
    """points_world: (..., 3) -> (..., 2) continuous pixel coords (u right, v down) in the
    camera c2w (3, 4), intrinsics (fx, fy, cx, cy).

    Pixel (u, v) has its centre at (u + 0.5, v + 0.5). Points behind the camera give NaN.
    """
    c2w = np.asarray(c2w, np.float64)
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    p_cam = (np.asarray(points_world, dtype=np.float64) - c2w[:, 3]) @ c2w[:, :3]
    depth = -p_cam[..., 2]
    safe = np.where(depth > 0, depth, np.nan)
    return np.stack([cx + fx * p_cam[..., 0] / safe, cy - fy * p_cam[..., 1] / safe], axis=-1)


def project(cams: Cameras, i: int, points_world: np.ndarray) -> np.ndarray:
    """points_world: (P, 3) -> (P, 2) pixel coords in camera i (project_points)."""
    return project_points(cams.c2w[i], (cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]),
                          points_world)


def bounds_from_points(cams: Cameras, points_world: np.ndarray, margin: float = 0.1
                       ) -> tuple[float, float] | None:
    """Scene (near, far) from sparse points: per view, the 1st/99th percentile of the depths
    of the points it sees; near = min over views / (1 + margin), far = max * (1 + margin).
    Returns None when no view sees a point."""
    nears, fars = [], []
    for i in range(len(cams)):
        uv = project(cams, i, points_world)
        p_cam = (points_world - cams.c2w[i][:, 3]) @ cams.c2w[i][:, :3]
        seen = ((uv[:, 0] >= 0) & (uv[:, 0] <= cams.width)
                & (uv[:, 1] >= 0) & (uv[:, 1] <= cams.height))
        depth = -p_cam[seen, 2]
        if depth.size:
            nears.append(np.percentile(depth, 1))
            fars.append(np.percentile(depth, 99))
    if not nears:
        return None
    return float(min(nears) / (1 + margin)), float(max(fars) * (1 + margin))
