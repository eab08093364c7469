"""Scene depth bounds (near, far) when the capture does not give them.

nerfstudio `transforms.json` files never carry bounds, and a user should not have to guess
them: a guess that is 2x too loose used to cost 2-5 dB. gridnerf only needs bounds to place
the NDC near plane and the first (coarse) grid; after the coarse stage the grid box is
refitted to the content the model found (train.py), so bounds need to be safe, not tight.

Order of sources (first that works):
1. the scene's own bounds (`near_far` in transforms.json, poses_bounds.npy, COLMAP points
   of sparse/0) -- scene.load_scene reads those;
2. sparse structure at the *given* poses: SIFT + matching + incremental mapping with pycolmap
   on the previews (images/, else previews made from the RAW frames), then the depths of the
   triangulated points in the COLMAP cameras, rescaled to the given world. Depth in a camera
   is invariant to a rigid motion of the whole reconstruction, so only the scale matters:
   s = median over camera pairs of |c_i - c_j| (given) / |c_i - c_j| (COLMAP);
3. the camera layout alone (no image content): the point nearest to all optical axes for
   converging captures, else a multiple of the camera spread; deliberately loose, with a
   warning, since the coarse-stage refit tightens it.
Nothing is written into the scene folder; train.py stores the result in the run folder.
"""

from __future__ import annotations

import itertools
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gridnerf import cameras as cam_mod
from gridnerf import pose_files, poses
from gridnerf.cameras import Cameras
from gridnerf.errors import GridNerfError
from gridnerf.scene import raw_files

# Safety factors around the sparse points' depth percentiles (1st / 99th per view): sparse
# points miss textureless and oblique near surfaces (a table top), and content nearer than
# the NDC near plane is lost, while a near plane too close only costs the coarse stage some
# depth resolution (the box refit after it removes the rest).
NEAR_FACTOR, FAR_FACTOR = 0.5, 2.0
# SIFT sees the previews at most this many pixels on their long side (COLMAP scales the
# keypoints back to preview pixels). Depth percentiles need no fine detail: on seven
# 1280x720 and 1920x1080 captures the bounds at 480 px lay within 5 % (near) and 9 % (far)
# of those at full size, and bouquet's took 23 s instead of 82 (docs/speed.md, "Outside
# the training loop at 1920x1080").
# A capture that does not reconstruct at this size is tried again at full size.
SFM_IMAGE_SIZE = 480


@dataclass(frozen=True)
class Bounds:
    near: float  # world units, along the cameras' viewing axes (z-depth)
    far: float
    source: str  # "sfm" | "cameras"
    detail: dict

    def to_dict(self) -> dict:
        return {"near": self.near, "far": self.far, "source": self.source, **self.detail}


def pair_scale(given: np.ndarray, other: np.ndarray) -> float | None:
    """Scale s with |g_i - g_j| ~ s |o_i - o_j|: median over pairs. given, other: (N, 3)."""
    ratios = []
    for i, j in itertools.combinations(range(len(given)), 2):
        dg, do = np.linalg.norm(given[i] - given[j]), np.linalg.norm(other[i] - other[j])
        if do > 1e-9 and dg > 1e-9:
            ratios.append(dg / do)
    return float(np.median(ratios)) if ratios else None


def _registered(rec, names: list[str]) -> list[str]:
    """The frames (stems, in `names` order) that rec gives a pose."""
    posed = {Path(im.name).stem for im in rec.images.values() if im.has_pose}
    return [n for n in names if n in posed]


def _sparse(image_dir: Path, images: list[str], work: Path, known, names: list[str]):
    """COLMAP's largest model on the previews at SFM_IMAGE_SIZE, or at full size where that
    registers fewer than 3 frames (None where neither does)."""
    larger = max(poses.preview_size(image_dir, images[0])) > SFM_IMAGE_SIZE
    rec = None
    for size in (SFM_IMAGE_SIZE, None) if larger else (SFM_IMAGE_SIZE,):
        attempt = work / f"sfm-{size or 'full'}"
        attempt.mkdir()
        rec = poses.run_colmap(image_dir, images, attempt, "PINHOLE", known,
                               max_image_size=size)
        if rec is not None and len(_registered(rec, names)) >= 3:
            break
    return rec


def from_sfm(scene_dir: Path, cams: Cameras) -> Bounds | None:
    """Bounds from COLMAP points triangulated on the previews (module docstring, 2)."""
    files = raw_files(scene_dir)
    names = [n for n in cams.names if n in files]
    source = "images" if (scene_dir / "images").is_dir() else "raw"
    import pycolmap

    pycolmap.logging.minloglevel = 2  # errors only: the bounds step should not flood the log
    with tempfile.TemporaryDirectory(prefix="gridnerf-bounds-") as tmp:
        work = Path(tmp)
        try:
            image_dir, previews, _ = poses.sfm_images(scene_dir, files, names, source, work)
            usable = [n for n in names if n in previews]
            if len(usable) < max(3, len(names) // 2) and source == "images":
                image_dir, previews, _ = poses.sfm_images(scene_dir, files, names, "raw", work)
                usable = [n for n in names if n in previews]
            known = poses.known_intrinsics(cams, image_dir, previews[usable[0]])
            rec = _sparse(image_dir, [previews[n] for n in usable], work, known, names)
        except (GridNerfError, RuntimeError, ValueError, OSError, IndexError):
            return None
        if rec is None:
            return None
        sparse = work / "sparse"
        sparse.mkdir()
        rec.write(sparse)
        registered = _registered(rec, names)
        if len(registered) < 3:
            return None
        colmap_cams, points = pose_files.load_colmap(sparse, registered)
    given = cams.take([cams.names.index(n) for n in registered]).c2w[:, :, 3]
    scale = pair_scale(given, colmap_cams.c2w[:, :, 3])
    found = cam_mod.bounds_from_points(colmap_cams, points, margin=0.0)
    if scale is None or found is None or len(points) < 20:
        return None
    near, far = found[0] * scale * NEAR_FACTOR, found[1] * scale * FAR_FACTOR
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        return None
    return Bounds(near, far, "sfm", {"registered": len(registered), "frames": len(names),
                                     "points": int(len(points)), "preview_source": source})


def from_cameras(cams: Cameras) -> Bounds:
    """Loose bounds from the camera layout alone (module docstring, 3)."""
    centres = cams.c2w[:, :, 3]
    axes = -cams.c2w[:, :, 2]
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).mean())
    # Least-squares point nearest to every optical axis: sum (I - a a^T) (p - c) = 0.
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    a, b = proj.sum(0), np.einsum("nij,nj->i", proj, centres)
    depth = None
    if np.linalg.cond(a) < 1e4:
        point = np.linalg.solve(a, b)
        depths = np.einsum("ni,ni->n", point - centres, axes)
        if np.all(depths > 0) and np.median(depths) < 100.0 * max(spread, 1e-9):
            depth = float(np.median(depths))
    if depth is not None:
        near, far, how = depth / 4.0, depth * 4.0, "optical axes converge"
    else:
        base = max(spread, 1e-3)
        near, far, how = 2.0 * base, 200.0 * base, "parallel axes: camera spread"
    return Bounds(near, far, "cameras", {"how": how, "camera_spread": spread})


def estimate(scene_dir, cams: Cameras) -> Bounds:
    """Bounds for a scene whose files give none: SfM points at the given poses, else the
    camera layout (with a warning)."""
    scene_dir = Path(scene_dir)
    found = from_sfm(scene_dir, cams)
    if found is not None:
        return found
    guess = from_cameras(cams)
    warnings.warn(f"{scene_dir}: no sparse points could be triangulated; near/far guessed from "
                  f"the camera layout ({guess.near:.3g}, {guess.far:.3g}); the grid box is "
                  "refitted after the coarse stage. Run `gridnerf poses` for better bounds.",
                  stacklevel=2)
    return guess
