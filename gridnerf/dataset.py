"""Training rays and targets: Scene -> device arrays -> random ray patches (jittable).

Two target modes (config.data.binning):
- binned: 2x2-binned camera RGB (`rgb_cam`, (N, h, w, 3) float32) with a
  validity mask; rays go through the centres of the binned pixels.
- mosaic: the Bayer mosaic kept as uint16 (`raw_bayer`, (N, H, W)), normalised
  inside the batch gather; the target's mask is one-hot on the measured
  channel (and zero on saturated pixels), so the loss sees the raw mosaic.
Targets are divided by each frame's relative exposure (RawNeRF's shutter
ratio), and negative values are kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from gridnerf import baseline, image_io, llnerf, raw, rays
from gridnerf.errors import SceneError
from gridnerf.scene import Scene


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class RayData:
    """Device-side training data. Array fields are pytree leaves; mode/ndc are static."""

    c2w: jax.Array  # (N, 3, 4) camera-to-world of the training frames
    intrinsics: jax.Array  # (N, 4) fx, fy, cx, cy at the target resolution
    ndc_intrinsics: jax.Array  # (4,) fx, fy, width, height of camera 0 at full resolution
    pixels: jax.Array  # binned: rgb_cam (N, h, w, 3) float32; mosaic: raw_bayer (N, H, W) uint16
    valid: jax.Array  # binned: (N, h, w, 3) bool, False where saturated; mosaic: unused (N,)
    black: jax.Array  # (N, 2, 2) black level per CFA position (mosaic)
    white: jax.Array  # (N,) white level (mosaic)
    inv_exposure: jax.Array  # (N,) 1 / relative exposure of each frame
    cfa: jax.Array  # (2, 2) int32 colour index per CFA position
    # (N, hb, wb, 3) per-frame L_ca illuminant map (loss.ca_target = "map", with_map) or None
    illuminant_map: jax.Array | None = None
    # (2, 2) black offset per CFA position in normalised raw, taken off the targets
    # (data.black_offset = "fit", gridnerf.sensorfit), or None
    black_offset: jax.Array | None = None
    mosaic: bool = field(default=False, metadata={"static": True})
    ndc: bool = field(default=True, metadata={"static": True})

    @property
    def image_hw(self) -> tuple[int, int]:
        return int(self.pixels.shape[1]), int(self.pixels.shape[2])


def training_data(scene: Scene, data_cfg) -> RayData:
    """The training frames as a config's `data` section (config.DataConfig) asks for them:
    binning, downscale, target and exposure_ratio (the one place that reads them)."""
    return build(scene, scene.train_idx, data_cfg.binning, data_cfg.downscale,
                 data_cfg.target, data_cfg.exposure_ratio)


def build(scene: Scene, frames: np.ndarray, binning: bool, downscale: int = 1,
          target: str = "raw", exposure_ratio: float = 1.0) -> RayData:
    """Device arrays for `frames` (indices into scene.names).

    target "reference": the oracle's data, the clean normal-light references gt/<name>.exr
    (rgb_linear) box-downscaled to the binned size, exposure 1, all valid; "processed":
    the "2D + NeRF" data, each training frame processed on its own by the 2D pipeline
    (baseline.process_denoised_frame: demosaic, grey world, colour matrix, auto exposure,
    non-local means; rgb_linear), box-downscaled the same way; "dark_srgb": the LLNeRF-style
    row's data, each training frame as a camera saves a dark photo (the binned frame through
    llnerf.dark_srgb_frame: grey world, colour matrix, no brightening, sRGB curve;
    rgb_srgb in [0, 1]), exposure 1, pixels with a saturated channel invalid. exposure_ratio
    gamma scales the raw targets (I_gamma = I_raw gamma after black-level removal, the
    paper's darkness sweep: noise and signal alike, so only the magnitude changes); for
    "dark_srgb" the binned raw before it is processed.
    """
    cams = scene.cameras
    full = ndc_intrinsics(scene)
    c2w = cams.c2w[frames].astype(np.float32)
    black = scene.black_level[frames].astype(np.float32)
    white = scene.white_level[frames].astype(np.float32)
    # exposure_ratio: Bright-NeRF's darkness sweep, the raw scaled after black-level removal
    inv_exposure = (float(exposure_ratio) / scene.exposure[frames]).astype(np.float32)
    if target == "processed":  # the "2D + NeRF" row: each dark frame processed on its own
        if not binning:
            raise SceneError(scene.path, "data.target=processed trains on processed frames: "
                             "it needs data.binning=true", "set data.binning=true")
        factor = 1.0 / (2 * downscale)
        pixels = np.stack([raw.downscale(baseline.process_denoised_frame(
            scene.raw_normalized(int(i)), scene.cfa, scene.xyz_to_cam), 2 * downscale)
            for i in frames]).astype(np.float32)
        valid = np.ones(pixels.shape, bool)
        inv_exposure = np.ones(len(frames), np.float32)
    elif target == "dark_srgb":  # the LLNeRF-style row: the dark photos a camera saves
        if not binning:
            raise SceneError(scene.path, "data.target=dark_srgb trains on binned frames: it "
                             "needs data.binning=true", "set data.binning=true")
        factor = 1.0 / (2 * downscale)
        pairs = [scene.rgb_cam_binned(int(i), downscale) for i in frames]
        pixels = np.stack([llnerf.dark_srgb_frame(rgb_cam * float(exposure_ratio),
                                                  scene.xyz_to_cam, ok)
                           for rgb_cam, ok in pairs]).astype(np.float32)
        valid = np.stack([np.broadcast_to(ok.all(axis=-1, keepdims=True), ok.shape)
                          for _, ok in pairs])
        inv_exposure = np.ones(len(frames), np.float32)
    elif target == "reference":
        missing = [scene.names[i] for i in frames if scene.names[i] not in scene.gt_linear_paths]
        if missing or not binning:
            raise SceneError(scene.path / "gt", f"the oracle needs gt/<name>.exr for every "
                             f"training frame (missing: {missing[:3]}) and data.binning=true",
                             "train the oracle only on scenes with references")
        factor = 1.0 / (2 * downscale)
        pixels = np.stack([raw.downscale(image_io.read_exr(scene.gt_linear_paths[scene.names[i]]),
                                         2 * downscale) for i in frames]).astype(np.float32)
        valid = np.ones(pixels.shape, bool)
        inv_exposure = np.ones(len(frames), np.float32)
    elif binning:
        factor = 1.0 / (2 * downscale)
        pairs = [scene.rgb_cam_binned(int(i), downscale) for i in frames]
        pixels = np.stack([p[0] for p in pairs]).astype(np.float32)
        valid = np.stack([p[1] for p in pairs])
    else:
        if downscale != 1:
            raise ValueError("mosaic training needs data.downscale=1 (use binning to downscale)")
        factor = 1.0
        pixels = scene.raw_bayer[frames]
        valid = np.ones(len(frames), bool)
    intr = (
        np.stack([cams.fx[frames], cams.fy[frames], cams.cx[frames], cams.cy[frames]], axis=1)
        * factor
    )
    return RayData(
        c2w=jnp.asarray(c2w),
        intrinsics=jnp.asarray(intr.astype(np.float32)),
        ndc_intrinsics=jnp.asarray(full),
        pixels=jnp.asarray(pixels),
        valid=jnp.asarray(valid),
        black=jnp.asarray(black),
        white=jnp.asarray(white),
        inv_exposure=jnp.asarray(inv_exposure),
        cfa=jnp.asarray(scene.cfa.astype(np.int32)),
        mosaic=not binning,
        ndc=scene.forward_facing,
    )


def pixel_rays(c2w, intrinsics, u, v):
    """World rays through pixel centres: c2w (..., 3, 4), intrinsics (..., 4) fx, fy, cx, cy,
    u, v (...) pixel column/row. Returns origins, directions (..., 3), camera-frame z = -1."""
    fx, fy, cx, cy = (intrinsics[..., k] for k in range(4))
    return rays.pixel_rays(c2w, fx, fy, cx, cy, u, v, xp=jnp)


def ndc_intrinsics(scene: Scene) -> np.ndarray:
    """(4,) float32 fx, fy, width, height of camera 0 at full resolution: the one NDC warp of
    a scene (every view, training or rendered, goes through the same warp)."""
    c = scene.cameras
    return np.array([c.fx[0], c.fy[0], c.width, c.height], np.float32)


def to_grid_space(ndc: bool, ndc_intrinsics, origins, directions):
    """Rays in the grid's coordinates: NDC (forward-facing scenes) or world.

    ndc_intrinsics: (4,) fx, fy, width, height of camera 0 at full resolution.
    """
    if not ndc:
        return origins, directions
    fx, fy, w, h = (ndc_intrinsics[k] for k in range(4))
    return rays.ndc_rays(origins, directions, fx, fy, w, h, near=1.0, xp=jnp)


def targets(data: RayData, frame, v, u):
    """Targets and masks at integer pixels: (..., 3) float32 each (mask 0/1); normalised raw
    less the fitted black offsets when the data carry them, divided by the exposure."""
    if not data.mosaic:
        y = data.pixels[frame, v, u]
        if data.black_offset is not None:  # binned: R, mean of the greens, B
            onehot = jax.nn.one_hot(data.cfa, 3)  # (2, 2, 3)
            y = y - (onehot * data.black_offset[..., None]).sum((0, 1)) / onehot.sum((0, 1))
        y = y * data.inv_exposure[frame][..., None]
        return y, data.valid[frame, v, u].astype(jnp.float32)
    raw = data.pixels[frame, v, u].astype(jnp.float32)
    black = data.black[frame, v % 2, u % 2]
    y = (raw - black) / (data.white[frame] - black)
    if data.black_offset is not None:
        y = y - data.black_offset[v % 2, u % 2]
    y = y * data.inv_exposure[frame]
    ok = (raw < data.white[frame]).astype(jnp.float32)
    mask = jax.nn.one_hot(data.cfa[v % 2, u % 2], 3) * ok[..., None]
    return y[..., None] * mask, mask


def sample_patches(data: RayData, key, n_patches: int, patch: int):
    """Random square ray patches: frame (P,), v, u (P, patch, patch) integer pixels."""
    h, w = data.image_hw
    n = data.c2w.shape[0]
    kf, kv, ku = jax.random.split(key, 3)
    frame = jax.random.randint(kf, (n_patches,), 0, n)
    v0 = jax.random.randint(kv, (n_patches,), 0, h - patch + 1)
    u0 = jax.random.randint(ku, (n_patches,), 0, w - patch + 1)
    dv, du = jnp.meshgrid(jnp.arange(patch), jnp.arange(patch), indexing="ij")
    return frame, v0[:, None, None] + dv, u0[:, None, None] + du


def strided_pixels(data: RayData, n_rays: int):
    """A deterministic, even sample of every training frame: frame, v, u (N, hs, ws) integer
    pixels on a regular grid (the same stride across and down, centred in its cells), about
    n_rays in all (at least one pixel a frame)."""
    h, w = data.image_hw
    n = data.c2w.shape[0]
    stride = max(1, int(np.ceil(np.sqrt(n * h * w / max(n_rays, 1)))))
    v = np.arange(min(stride // 2, h - 1), h, stride)
    u = np.arange(min(stride // 2, w - 1), w, stride)
    frame, vv, uu = np.meshgrid(np.arange(n), v, u, indexing="ij")
    return jnp.asarray(frame), jnp.asarray(vv), jnp.asarray(uu)


def batch(data: RayData, key, n_patches: int, patch: int) -> dict:
    """One training batch of (P, patch, patch) rays: origins, directions, target, mask (each
    (P, patch, patch, 3)), and "illuminant" when the data carry an illuminant map."""
    frame, v, u = sample_patches(data, key, n_patches, patch)
    return rays_at(data, jnp.broadcast_to(frame[:, None, None], v.shape), v, u)


def rays_at(data: RayData, fr, v, u) -> dict:
    """The rays of training pixels: fr, v, u integer arrays of one shape S (frame, row,
    column) -> origins, directions, target, mask (each S + (3,)), and "illuminant" when the
    data carry an illuminant map."""
    uf, vf = u.astype(jnp.float32), v.astype(jnp.float32)
    o, d = pixel_rays(data.c2w[fr], data.intrinsics[fr], uf, vf)
    o, d = to_grid_space(data.ndc, data.ndc_intrinsics, o, d)
    y, m = targets(data, fr, v, u)
    out = {"origins": o, "directions": d, "target": y, "mask": m}
    if data.illuminant_map is not None:  # the block of the map each pixel falls in
        hb, wb = data.illuminant_map.shape[1:3]
        h, w = data.image_hw
        out["illuminant"] = data.illuminant_map[fr, v * hb // h, u * wb // w]
    return out


def image_rays(data_c2w: np.ndarray, intrinsics: np.ndarray, height: int, width: int):
    """Rays of a whole image (H, W, 3) each, for rendering (world space)."""
    v, u = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    c2w = jnp.broadcast_to(jnp.asarray(data_c2w, jnp.float32), (height, width, 3, 4))
    intr = jnp.broadcast_to(jnp.asarray(intrinsics, jnp.float32), (height, width, 4))
    return pixel_rays(c2w, intr, u.astype(jnp.float32), v.astype(jnp.float32))


def grid_box(scene: Scene) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Grid bounding box and ray t-range in grid space.

    Forward-facing: NDC box (ndc z = 1 - 2 / depth for depth in the normalised world,
    where the near bound is 1 / 0.75); z runs from the near bound to just past the far
    bound, so no voxel lies in front of the near bound (NDC's own near plane, depth 1,
    is z = -1: a quarter of z would otherwise sit before the near bound, where
    low-texture content collapses into a billboard). Rays start at the near bound
    (NDC t = (z + 1) / 2). Otherwise a world AABB around the cameras' far bound.
    Returns bbox_min (3,), bbox_max (3,), near_t, far_t.
    """
    if scene.forward_facing:
        z_near = float(np.clip(1.0 - 2.0 / max(scene.near, 1.0), -1.0, 0.9))
        z_far = min(1.0 - 2.0 / (1.25 * scene.far), 0.999) if scene.far > 1.0 else 0.999
        z_far = max(z_far, z_near + 0.05)
        return (np.array([-1.25, -1.25, z_near]), np.array([1.25, 1.25, z_far]),
                0.5 * (z_near + 1.0), 1.0)
    centre = scene.cameras.c2w[:, :, 3].mean(axis=0)
    r = float(scene.far)
    return centre - r, centre + r, float(scene.near), float(scene.far)


def frustum_xy(scene: Scene, frames, bbox_min, bbox_max, near_t: float,
               margin: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """NDC x/y extent that every ray of the given cameras crosses inside the z range of the
    box: (lo (2,), hi (2,)). NDC rays are straight, so the extremes over depth lie at the
    box's near and far z, and over the image on its border (sampled every 4 pixels).
    A converging arc of +-17 degrees with a 55-degree lens sees NDC x up to +-1.9, where
    the reference camera's frustum is +-1.
    """
    cams = scene.cameras
    ndc = ndc_intrinsics(scene)
    t_far = 0.5 * (float(bbox_max[2]) + 1.0)
    h, w = cams.height, cams.width
    cols, rows = np.arange(0, w, 4, dtype=np.float32), np.arange(0, h, 4, dtype=np.float32)
    u = np.concatenate([cols, cols, np.zeros_like(rows), np.full_like(rows, w - 1)])
    v = np.concatenate([np.zeros_like(cols), np.full_like(cols, h - 1), rows, rows])
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for i in frames:
        intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]], np.float32)
        o, d = pixel_rays(jnp.asarray(cams.c2w[i], jnp.float32), jnp.asarray(intr), u, v)
        o, d = (np.asarray(a) for a in to_grid_space(True, ndc, o, d))
        for t in (near_t, t_far):
            p = o[:, :2] + t * d[:, :2]
            lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
    pad = margin * (hi - lo)
    return lo - pad, hi + pad
