"""Capture: camera rigs (tripod, arc, slide), pinhole rays and clean Lambertian renders.

Cameras follow docs/design.md: camera-to-world (OpenGL axes, x right, y up, looking
along -z); the ray through pixel (u, v) has camera direction
((u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1), so a hit at ray parameter t lies
at z-depth t. Radiance is Lambertian and view-independent:
  rgb_linear = albedo * (ambient + sum_l I_l * max(0, n . l) * visibility_l),
with visibility the fraction of a fixed set of directions in the light's cone that
reach the sky (soft shadows). Every surface point has one colour from every view, so a
radiance field can represent it (the only exception is the zero-thickness bucket wall,
whose inside and outside differ).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gridnerf import rays
from gridnerf.sim.geometry import cast, dot3, occluded, rotation
from gridnerf.sim.scenes import Light, PointLight, SceneSpec

HFOV_DEG = 55.0
SHADOW_EPS = 1e-3  # shadow rays start this far off the surface


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels of the full frame (w x h)."""

    fx: float
    fy: float
    cx: float
    cy: float
    w: int
    h: int


def intrinsics(width: int, height: int, hfov_deg: float = HFOV_DEG) -> Intrinsics:
    """Square-pixel pinhole with the given horizontal field of view, centred."""
    fx = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2)
    return Intrinsics(float(fx), float(fx), width / 2.0, height / 2.0, int(width), int(height))


def look_at(position: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """(3, 3) camera-to-world rotation looking from `position` at `target` (world up = +y),
    rolled by `roll` radians about the view axis."""
    return rays.look_at(position, target, [0.0, 1.0, 0.0]) @ rotation(roll=roll)


def camera_path(spec: SceneSpec, n_frames: int, rng: np.random.Generator) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses of the scene's rig (`spec.rig`), in capture order.

    "tripod": see `tripod_path`; "arc": `arc_path`; "slide": `slide_path`.
    """
    paths = {"tripod": tripod_path, "arc": arc_path, "slide": slide_path}
    if spec.rig not in paths:
        raise ValueError(f"unknown camera rig {spec.rig!r}; choose one of {', '.join(paths)}")
    return paths[spec.rig](spec, n_frames, rng)


def _pose(position: np.ndarray, rot: np.ndarray) -> np.ndarray:
    c2w = np.eye(4)
    c2w[:3, :3] = rot
    c2w[:3, 3] = position
    return c2w


def tripod_path(spec: SceneSpec, n_frames: int, rng: np.random.Generator) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses of a hand-moved tripod in front of the prop.

    Positions lie on a jittered ellipse (about 12% x 7% of the object distance,
    with some depth wobble) around the rest position; each view aims at the
    prop with a small random aim offset and roll, so yaw/pitch/roll all vary.
    """
    target = np.asarray(spec.target, float)
    rest = target + np.array([0.0, spec.height, spec.distance])
    rx, ry, rz = 0.12 * spec.distance, 0.07 * spec.distance, 0.05 * spec.distance
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    for i in range(n_frames):
        a = 2.0 * np.pi * i / max(n_frames, 1) + rng.uniform(-0.15, 0.15)
        s = rng.uniform(0.75, 1.0)
        pos = rest + np.array([rx * s * np.cos(a), ry * s * np.sin(a), rz * np.sin(2 * a)])
        aim = target + rng.uniform(-0.08, 0.08, 3) * np.array([1.0, 1.0, 0.0])
        poses[i, :3, :3] = look_at(pos, aim, roll=rng.uniform(-0.04, 0.04))
        poses[i, :3, 3] = pos
    return poses


ARC_AIM_JITTER = 0.04  # world units, per axis: where an arc view aims, off the target
ARC_ROLL = 0.035  # radians, largest roll of an arc view


def arc_path(spec: SceneSpec, n_frames: int, rng: np.random.Generator) -> np.ndarray:
    """(N, 4, 4) poses of a handheld sweep along an arc that converges on `spec.target`.

    View i sits at yaw ~ -Y + 2Y i / (N - 1) about the target (Y = spec.yaw_spread_deg,
    a quarter step of jitter, clipped to +-Y), at horizontal radius `spec.distance`
    (+-3%) and `spec.height` above the target (+- a slow 4% wave and 1% jitter of the
    distance). Each view aims at the target plus up to ARC_AIM_JITTER per axis, with up
    to ARC_ROLL of roll: every optical axis passes within ~0.07 units of the target.
    """
    target = np.asarray(spec.target, float)
    half = np.deg2rad(spec.yaw_spread_deg)
    frac = np.linspace(-1.0, 1.0, n_frames) if n_frames > 1 else np.zeros(1)
    step = 2.0 * half / max(n_frames - 1, 1)
    yaw = np.clip(frac * half + rng.uniform(-0.25, 0.25, n_frames) * step, -half, half)
    phase = rng.uniform(0.0, 2.0 * np.pi)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    for i in range(n_frames):
        r = spec.distance * rng.uniform(0.97, 1.03)
        dy = spec.height + spec.distance * (0.04 * np.sin(phase + 1.5 * np.pi * frac[i])
                                            + rng.uniform(-0.01, 0.01))
        pos = target + np.array([r * np.sin(yaw[i]), dy, r * np.cos(yaw[i])])
        aim = target + rng.uniform(-ARC_AIM_JITTER, ARC_AIM_JITTER, 3)
        poses[i] = _pose(pos, look_at(pos, aim, roll=rng.uniform(-ARC_ROLL, ARC_ROLL)))
    return poses


SLIDE_JITTER_RAD = 0.003  # largest yaw/pitch/roll wobble of the slider carriage
SLIDE_JITTER_POS = 0.001  # world units, largest centre offset from the rail


def slide_path(spec: SceneSpec, n_frames: int, rng: np.random.Generator) -> np.ndarray:
    """(N, 4, 4) poses of a slider: camera centres evenly along a horizontal rail.

    The rail passes through the rest position target + (0, height, distance), along
    that view's x axis (horizontal), `spec.baseline * spec.distance` long. Every view
    keeps the rest view's orientation (looking at the target) up to a carriage wobble of
    SLIDE_JITTER_RAD per angle, so the optical axes are parallel; centres are off the
    rail by at most SLIDE_JITTER_POS per axis.
    """
    target = np.asarray(spec.target, float)
    rest = target + np.array([0.0, spec.height, spec.distance])
    rot = look_at(rest, target)
    length = spec.baseline * spec.distance
    along = np.linspace(-0.5, 0.5, n_frames) * length if n_frames > 1 else np.zeros(1)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    for i in range(n_frames):
        pos = rest + along[i] * rot[:, 0] + rng.uniform(-SLIDE_JITTER_POS, SLIDE_JITTER_POS, 3)
        wobble = rotation(*rng.uniform(-SLIDE_JITTER_RAD, SLIDE_JITTER_RAD, 3))
        poses[i] = _pose(pos, rot @ wobble)
    return poses


def pixel_rays(c2w: np.ndarray, intr: Intrinsics, ssaa: int = 1):
    """World rays through pixel sub-samples (an ssaa x ssaa grid per pixel).

    Returns origins, dirs: (H, W, S, 3) float64 with S = ssaa**2; dirs have
    camera-frame z = -1 (unnormalised).
    """
    offs = (np.arange(ssaa) + 0.5) / ssaa
    u = np.arange(intr.w)[None, :, None, None] + offs[None, None, None, :]
    v = np.arange(intr.h)[:, None, None, None] + offs[None, None, :, None]
    u, v = np.broadcast_arrays(u, v)
    shape = (intr.h, intr.w, ssaa * ssaa)
    x = ((u - intr.cx) / intr.fx).reshape(shape)
    y = (-(v - intr.cy) / intr.fy).reshape(shape)
    d_cam = np.stack([x, y, -np.ones(shape)], axis=-1)
    dirs = np.einsum("...j,kj->...k", d_cam, c2w[:3, :3])  # d_cam @ R.T, without BLAS
    origins = np.broadcast_to(c2w[:3, 3], dirs.shape)
    return origins, dirs


def _cone_directions(light: Light, n: int = 4) -> np.ndarray:
    """(n, 3) unit directions spread over the light's penumbra cone (fixed pattern)."""
    d = np.asarray(light.direction, float)
    d /= np.linalg.norm(d)
    if light.soft <= 0.0:
        return d[None]
    a = np.cross(d, [0.0, 1.0, 0.0] if abs(d[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    ang = 2.0 * np.pi * (np.arange(n) + 0.5) / n
    dirs = d + light.soft * (np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b)
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def shade(spec: SceneSpec, points: np.ndarray, normals: np.ndarray,
          albedo: np.ndarray) -> np.ndarray:
    """Lambertian radiance (N, 3) at surface points (N, 3) with unit normals (N, 3)."""
    irradiance = np.full(len(points), spec.ambient)
    for light in spec.lights:
        _add_irradiance(irradiance, spec, light, points, normals)
    return albedo * irradiance[:, None]


def _light_irradiance(spec: SceneSpec, light: Light | PointLight, points: np.ndarray,
                      normals: np.ndarray) -> np.ndarray:
    """(N,) irradiance of one light at surface points (N, 3) with unit normals (N, 3)."""
    return _add_irradiance(np.zeros(len(points)), spec, light, points, normals)


def _add_irradiance(irradiance: np.ndarray, spec: SceneSpec, light: Light | PointLight,
                    points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Add one light's irradiance at surface points (N, 3) with unit normals (N, 3) to
    `irradiance` (N,) in place (sample by sample, so sums keep their order) and return it."""
    occluders = list(spec.props)
    if isinstance(light, PointLight):
        samples = np.asarray(light.position, float) + light.radius * _TETRA
        for q in samples:
            vec = q - points
            dist2 = np.maximum(np.sum(vec * vec, axis=1), 1e-12)
            d = vec / np.sqrt(dist2)[:, None]
            cos = np.maximum(np.sum(normals * d, axis=1), 0.0)
            lit = cos > 0.0
            if light.shadow and lit.any():
                idx = np.nonzero(lit)[0]
                start = points[idx] + SHADOW_EPS * normals[idx]
                dist = np.sqrt(dist2[idx])
                cos[idx[occluded(occluders, start, d[idx], dist)]] = 0.0
            irradiance += light.intensity * cos / dist2 / len(samples)
        return irradiance
    dirs = _cone_directions(light)
    for d in dirs:
        cos = np.maximum(dot3(normals, d), 0.0)
        lit = cos > 0.0
        if light.shadow and lit.any():
            idx = np.nonzero(lit)[0]
            start = points[idx] + SHADOW_EPS * normals[idx]
            blocked = occluded(occluders, start, np.broadcast_to(d, start.shape))
            cos[idx[blocked]] = 0.0
        irradiance += light.intensity * cos / len(dirs)
    return irradiance


# Sample points of a lamp's sphere (unit tetrahedron): soft shadows of point lights.
_TETRA = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0],
                   [-1.0, -1.0, 1.0]]) / np.sqrt(3.0)


def shade_layers(spec: SceneSpec, points: np.ndarray, normals: np.ndarray,
                 albedo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lambertian radiance per illuminant: points, normals, albedo (N, 3) ->
    radiance (N, L, 3) and irradiance (N, L), one layer per spec.kelvins (the ambient
    fill goes to its own illuminant's layer). Their sum is what `shade` would give if
    every light had the same colour."""
    kelvins = spec.kelvins
    irradiance = np.zeros((len(points), len(kelvins)))
    irradiance[:, kelvins.index(spec.kelvin_of(None))] += spec.ambient
    for light in spec.lights:
        irradiance[:, kelvins.index(spec.kelvin_of(light))] += _light_irradiance(
            spec, light, points, normals)
    return albedo[:, None, :] * irradiance[:, :, None], irradiance


def _render(spec: SceneSpec, c2w: np.ndarray, intr: Intrinsics, ssaa: int, tile: int,
            shader, channels: int):
    """Cast every sub-ray tile by tile; shader(points, normals, albedo) -> (n, channels).
    Returns the pixel-area means (H, W, channels) float32 and depth (H, W, S) float32."""
    origins, dirs = pixel_rays(c2w, intr, ssaa)
    shape = dirs.shape[:-1]
    rgb = np.zeros((*shape, channels))
    depth = np.full(shape, np.inf)
    for y0 in range(0, intr.h, tile):
        for x0 in range(0, intr.w, tile):
            block = (slice(y0, y0 + tile), slice(x0, x0 + tile))
            o, d = origins[block].reshape(-1, 3), dirs[block].reshape(-1, 3)
            hits = cast(spec.prims, o, d)
            hit = np.nonzero(hits.prim >= 0)[0]
            out = np.zeros((len(o), channels))
            out[hit] = shader(hits.point[hit], hits.normal[hit], hits.albedo[hit])
            rgb[block] = out.reshape(*depth[block].shape, channels)
            depth[block] = hits.t.reshape(depth[block].shape)
    return rgb.mean(axis=2).astype(np.float32), depth.astype(np.float32)


def render_view(spec: SceneSpec, c2w: np.ndarray, intr: Intrinsics, ssaa: int = 2,
                tile: int = 64):
    """Clean, D65-lit view of the scene.

    Returns rgb_linear: (H, W, 3) float32 (linear sRGB radiance, pixel-area average of
    ssaa x ssaa sub-rays) and depth: (H, W, S) float32 z-depth of every sub-ray
    (inf where a ray misses everything). Rays are cast one `tile` x `tile` pixel block
    at a time: a block's rays form a narrow cone, so primitives outside it are skipped.
    """
    return _render(spec, c2w, intr, ssaa, tile,
                   lambda p, n, a: shade(spec, p, n, a), 3)


def render_normals(spec: SceneSpec, c2w: np.ndarray, intr: Intrinsics, ssaa: int = 1,
                   tile: int = 64) -> np.ndarray:
    """(H, W, 3) float32: the mean of the unit surface normals (facing the camera) of each
    pixel's sub-rays, 0 where they miss: its length is below 1 where a pixel straddles a
    crease or an outline. For scoring only; no trainer sees it."""
    return _render(spec, c2w, intr, ssaa, tile, lambda p, n, a: n, 3)[0]


def render_view_layers(spec: SceneSpec, c2w: np.ndarray, intr: Intrinsics, ssaa: int = 2,
                       tile: int = 64):
    """Clean view rendered light by light (mixed illuminants; see shade_layers).

    Returns layers (L, H, W, 3) float32, each the linear sRGB radiance one illuminant
    (spec.kelvins[l]) contributes as if it were D65 (their sum is the colour-constant
    reference), irradiance (H, W, L) float32 per illuminant (pixel-area means, 0 where
    rays miss) and depth (H, W, S) as render_view.
    """
    n = len(spec.kelvins)

    def shader(p, nrm, a):
        radiance, irradiance = shade_layers(spec, p, nrm, a)
        return np.concatenate([radiance.reshape(len(p), 3 * n), irradiance], axis=1)

    out, depth = _render(spec, c2w, intr, ssaa, tile, shader, 4 * n)
    h, w = out.shape[:2]
    layers = out[..., : 3 * n].reshape(h, w, n, 3).transpose(2, 0, 1, 3)
    return np.ascontiguousarray(layers), out[..., 3 * n:], depth
