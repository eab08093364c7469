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

from gridnerf import baseline, image_io, raw, rays
from gridnerf.errors import SceneError
from gridnerf.scene import Scene


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class RayData:
    """Device-side training data. Array fields are pytree leaves; mode/ndc are static."""

    c2w: jax.Array  # (N, 3, 4) camera-to-world of the training frames
    intrinsics: jax.Array  # (N, 4) fx, fy, cx, cy at the target resolution
    ndc_intrinsics: jax.Array  # (4,) fx, fy, width, height of camera 0 at full resolution
    # binned: rgb_cam (N, h, w, 3) float32; mosaic: raw_bayer (N, H, W) uint16 (float32 DN
    # for the clean raw)
    pixels: jax.Array
    valid: jax.Array  # binned: (N, h, w, 3) bool, False where saturated; mosaic: unused (N,)
    black: jax.Array  # (N, 2, 2) black level per CFA position (mosaic)
    white: jax.Array  # (N,) white level (mosaic)
    inv_exposure: jax.Array  # (N,) 1 / relative exposure of each frame
    cfa: jax.Array  # (2, 2) int32 colour index per CFA position
    # (N, hb, wb, 3) per-frame L_ca illuminant map (loss.ca_target = "map", with_map) or None
    illuminant_map: jax.Array | None = None
    # (2,) k1, k2 of a lens falloff exp(k1 r^2 + k2 r^4) the mosaic targets are divided by
    # (gridnerf.vignetting; binned pixels are divided once, in place), or None
    falloff: jax.Array | None = None
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


def _binned_only(scene: Scene, binning: bool, target: str) -> None:
    if not binning:
        raise SceneError(scene.path, f"data.target={target} trains on binned frames: it needs "
                         "data.binning=true", "set data.binning=true")


def raw_frames(scene: Scene, frames, binning: bool, downscale: int, exposure_ratio: float):
    """The capture itself: binned camera RGB (rgb_cam) with its validity, or the Bayer
    mosaic (raw_bayer, uint16), divided by each frame's exposure times exposure_ratio
    (gamma: I_gamma = I_raw gamma after black-level removal, the paper's darkness sweep:
    noise and signal alike, so only the magnitude changes)."""
    inv_exposure = (float(exposure_ratio) / scene.exposure[frames]).astype(np.float32)
    if binning:
        pairs = [scene.rgb_cam_binned(int(i), downscale) for i in frames]
        return (np.stack([p[0] for p in pairs]).astype(np.float32),
                np.stack([p[1] for p in pairs]), inv_exposure)
    if downscale != 1:
        raise ValueError("mosaic training needs data.downscale=1 (use binning to downscale)")
    return scene.raw_bayer[frames], np.ones(len(frames), bool), inv_exposure


def reference_frames(scene: Scene, frames, binning: bool, downscale: int, exposure_ratio: float):
    """The oracle's data: the clean normal-light references gt/<name>.exr (rgb_linear)
    box-downscaled to the binned size, exposure 1, all valid."""
    missing = [scene.names[i] for i in frames if scene.names[i] not in scene.gt_linear_paths]
    if missing:
        raise SceneError(scene.path / "gt", f"the oracle needs gt/<name>.exr for every "
                         f"training frame (missing: {missing[:3]})",
                         "train the oracle only on scenes with references")
    if not binning:
        raise SceneError(scene.path / "gt", "the references are fitted at the binned size: "
                         "data.binning=false has no reference to fit",
                         "train the oracle with data.binning=true (its default)")
    pixels = np.stack([raw.downscale(image_io.read_exr(scene.gt_linear_paths[scene.names[i]]),
                                     2 * downscale) for i in frames]).astype(np.float32)
    return pixels, np.ones(pixels.shape, bool), np.ones(len(frames), np.float32)


def processed_frames(scene: Scene, frames, binning: bool, downscale: int, exposure_ratio: float):
    """The "2D + NeRF" data: each training frame processed on its own by the 2D pipeline
    (baseline.process_denoised_frame: demosaic, grey world, colour matrix, auto exposure,
    non-local means; rgb_linear), box-downscaled to the binned size, exposure 1."""
    _binned_only(scene, binning, "processed")
    pixels = np.stack([raw.downscale(baseline.process_denoised_frame(
        scene.raw_normalized(int(i)), scene.cfa, scene.xyz_to_cam), 2 * downscale)
        for i in frames]).astype(np.float32)
    return pixels, np.ones(pixels.shape, bool), np.ones(len(frames), np.float32)


CLEAN_DIR = "clean"  # <scene>/clean/<frame>.npy: a simulated capture's noise-free raw


def clean_frames(scene: Scene, frames, binning: bool, downscale: int, exposure_ratio: float):
    """The error budget's noise-free row: a simulated capture's exact clean raw,
    <scene>/clean/<frame>.npy ((H, W) float32 normalised mosaic, black level removed, no
    shot or read noise, no hidden black offset; written from the simulator's truth by
    `python -m experiments.error_budget`), binned like the raw, or as a mosaic (float32
    raw_bayer in DN: clean x (white - black) + black, the frame's own levels, so the
    batch gather's normalisation gives the clean values back), exposure as the raw's."""
    folder = scene.path / CLEAN_DIR
    missing = [scene.names[i] for i in frames
               if not (folder / f"{scene.names[i]}.npy").is_file()]
    if missing:
        raise SceneError(folder, f"data.target=clean needs the noise-free raw of every "
                         f"training frame (missing: {missing[:3]})", "write them for a "
                         "simulated scene with python -m experiments.error_budget")
    if not binning and downscale != 1:
        raise ValueError("mosaic training needs data.downscale=1 (use binning to downscale)")
    pixels = []
    for i in frames:
        clean = np.load(folder / f"{scene.names[int(i)]}.npy")
        if not binning:
            h, w = clean.shape
            black = np.tile(scene.black_level[int(i)], (h // 2, w // 2))
            pixels.append(clean * (scene.white_level[int(i)] - black) + black)
            continue
        rgb_cam = raw.bin2x2(clean, scene.cfa)
        pixels.append(raw.downscale(rgb_cam, downscale) if downscale > 1 else rgb_cam)
    pixels = np.stack(pixels).astype(np.float32)
    valid = np.ones(pixels.shape if binning else len(frames), bool)
    inv_exposure = (float(exposure_ratio) / scene.exposure[frames]).astype(np.float32)
    return pixels, valid, inv_exposure


# data.target -> (scene, frames, binning, downscale, exposure_ratio) -> (pixels, valid,
# inv_exposure); a method with targets of its own passes its function to build
TARGETS = {"raw": raw_frames, "reference": reference_frames, "processed": processed_frames,
           "clean": clean_frames}


def build(scene: Scene, frames: np.ndarray, binning: bool, downscale: int = 1,
          target="raw", exposure_ratio: float = 1.0) -> RayData:
    """Device arrays for `frames` (indices into scene.names).

    target: a name of TARGETS (data.target) or such a function itself. Every target but
    the raw mosaic (binning off, "raw") is binned: rays through the centres of the binned
    pixels.
    """
    frames_fn = TARGETS[target] if isinstance(target, str) else target
    pixels, valid, inv_exposure = frames_fn(scene, frames, binning, downscale, exposure_ratio)
    mosaic = pixels.ndim == 3
    cams = scene.cameras
    factor = 1.0 if mosaic else 1.0 / (2 * downscale)
    intr = (
        np.stack([cams.fx[frames], cams.fy[frames], cams.cx[frames], cams.cy[frames]], axis=1)
        * factor
    )
    return RayData(
        c2w=jnp.asarray(cams.c2w[frames].astype(np.float32)),
        intrinsics=jnp.asarray(intr.astype(np.float32)),
        ndc_intrinsics=jnp.asarray(ndc_intrinsics(scene)),
        pixels=jnp.asarray(pixels),
        valid=jnp.asarray(valid),
        black=jnp.asarray(scene.black_level[frames].astype(np.float32)),
        white=jnp.asarray(scene.white_level[frames].astype(np.float32)),
        inv_exposure=jnp.asarray(inv_exposure),
        cfa=jnp.asarray(scene.cfa.astype(np.int32)),
        mosaic=mosaic,
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
    divided by the exposure."""
    if not data.mosaic:
        y = data.pixels[frame, v, u]
        y = y * data.inv_exposure[frame][..., None]
        return y, data.valid[frame, v, u].astype(jnp.float32)
    raw = data.pixels[frame, v, u].astype(jnp.float32)
    black = data.black[frame, v % 2, u % 2]
    y = (raw - black) / (data.white[frame] - black)
    y = y * data.inv_exposure[frame]
    if data.falloff is not None:
        r2 = radius2(data.image_hw, data.intrinsics[frame], v, u, xp=jnp)
        y = y * jnp.exp(-(data.falloff[0] * r2 + data.falloff[1] * r2 * r2))
    ok = (raw < data.white[frame]).astype(jnp.float32)
    mask = jax.nn.one_hot(data.cfa[v % 2, u % 2], 3) * ok[..., None]
    return y[..., None] * mask, mask


def radius2(image_hw: tuple[int, int], intrinsics, v, u, xp=np):
    """(...) squared distance of pixels (v, u) from their frame's principal point, over that
    of the frame's farthest corner: 0 at the centre, 1 there. intrinsics (..., 4) fx, fy, cx,
    cy of each pixel's frame at the pixels' resolution; the lens falloff's radius
    (gridnerf.vignetting)."""
    h, w = image_hw
    cx, cy = intrinsics[..., 2], intrinsics[..., 3]
    real = np.float64 if xp is np else jnp.float32
    du = xp.asarray(u, real) + 0.5 - cx
    dv = xp.asarray(v, real) + 0.5 - cy
    far = xp.maximum(xp.maximum(cx, w - cx) ** 2 + xp.maximum(cy, h - cy) ** 2, 1e-12)
    return (du * du + dv * dv) / far


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


# rays_at as one compiled call, for callers outside a jitted function (one compile per
# shape instead of one per eager operation: the lens-falloff estimate's first call took
# 5.4 s, 3 s of it compiling its eager ray operations)
rays_at_jit = jax.jit(rays_at)


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
