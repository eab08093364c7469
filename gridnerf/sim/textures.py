"""Surface materials: photographs shipped with scikit-image and procedural patterns.

A material is a callable `albedo = m(p_local, uv, face)`:
  p_local: (N, 3) hit point in the primitive's frame, uv: (N, 2) surface
  coordinates in [0, 1] (u right, v up), face: (N,) int face/part index,
  albedo: (N, 3) float64 linear sRGB reflectance in [0, 1].
Colours are given as sRGB-encoded triples in [0, 1] and decoded once with
`color.srgb_decode`, so textures are linear-light reflectances. Albedos are
kept below ~0.9 (real surfaces are never perfectly white).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import cache

import numpy as np
import skimage.data
import skimage.transform

from gridnerf.color import srgb_decode

Material = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]

# Photographs in scikit-image's own distribution (they load offline).
PHOTOS = (
    "astronaut",
    "coffee",
    "chelsea",
    "rocket",
    "immunohistochemistry",
    "colorwheel",
    "hubble_deep_field",
    "stereo_motorcycle",
    "brick",
    "grass",
    "gravel",
)
MAX_ALBEDO = 0.9


def _linear(rgb_srgb: Sequence[float]) -> np.ndarray:
    return srgb_decode(np.asarray(rgb_srgb, np.float64)) * MAX_ALBEDO


@cache
def photo(name: str, size: int = 256) -> np.ndarray:
    """A scikit-image photograph as linear sRGB albedo, (size', size'', 3) float64.

    Greyscale images are returned with three equal channels; the longer side
    is resized (anti-aliased) to `size`.
    """
    if name not in PHOTOS:
        raise ValueError(f"unknown photo {name!r}; choose one of {PHOTOS}")
    img = getattr(skimage.data, name)()
    if isinstance(img, tuple):  # stereo_motorcycle returns (left, right, disparity)
        img = img[0]
    img = np.asarray(img, np.float64) / 255.0
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    img = img[..., :3]
    scale = size / max(img.shape[:2])
    shape = (max(2, round(img.shape[0] * scale)), max(2, round(img.shape[1] * scale)))
    img = skimage.transform.resize(img, shape, anti_aliasing=True, order=1)
    return srgb_decode(img) * MAX_ALBEDO


def _bilinear_wrap(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample (H, W, C) at u (columns), v (rows from the top), both in texture periods."""
    h, w = img.shape[:2]
    x = u * w - 0.5
    y = v * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def solid(rgb_srgb: Sequence[float]) -> Material:
    """A uniform colour."""
    albedo = _linear(rgb_srgb)

    def m(p_local, uv, face):
        return np.broadcast_to(albedo, (len(uv), 3)).copy()

    return m


def image(name: str, repeat: tuple[float, float] = (1.0, 1.0),
          tint: Sequence[float] = (1.0, 1.0, 1.0), offset: tuple[float, float] = (0.0, 0.0)
          ) -> Material:
    """A photograph tiled `repeat` times over the uv square, multiplied by a linear `tint`."""
    img = photo(name)
    tint_lin = np.asarray(tint, np.float64)

    def m(p_local, uv, face):
        u = uv[:, 0] * repeat[0] + offset[0]
        v = (1.0 - uv[:, 1]) * repeat[1] + offset[1]
        return np.clip(_bilinear_wrap(img, u, v) * tint_lin, 0.0, MAX_ALBEDO)

    return m


def checker(c1: Sequence[float], c2: Sequence[float], n: tuple[int, int] = (8, 8)) -> Material:
    """An n[0] x n[1] checkerboard of two colours."""
    a, b = _linear(c1), _linear(c2)

    def m(p_local, uv, face):
        k = (np.floor(uv[:, 0] * n[0]) + np.floor(uv[:, 1] * n[1])).astype(np.int64) % 2
        return np.where(k[:, None] == 0, a, b)

    return m


def stripes(colors: Sequence[Sequence[float]], n: float = 8.0, angle_deg: float = 0.0,
            wobble: float = 0.0, grain: float = 0.0, seed: int = 0) -> Material:
    """Bands cycling through `colors`, `n` bands per uv unit, tilted by `angle_deg`.

    wobble > 0 bends the bands with a sine; grain > 0 darkens them by up to that
    fraction with fine random streaks (together: a wood-like look).
    """
    cols = np.stack([_linear(c) for c in colors])
    ang = np.deg2rad(angle_deg)
    streaks = np.random.default_rng(seed).random((256, 64, 1))

    def m(p_local, uv, face):
        s = uv[:, 0] * np.cos(ang) + uv[:, 1] * np.sin(ang)
        s = s + wobble * np.sin(2 * np.pi * (3.0 * uv[:, 1] + 1.7 * uv[:, 0]))
        k = np.floor(s * n).astype(np.int64) % len(cols)
        out = cols[k]
        if grain > 0:
            out = out * (1.0 - grain * _bilinear_wrap(streaks, 4.0 * s, 2.0 * uv[:, 1]))
        return out

    return m


def noise(c1: Sequence[float], c2: Sequence[float], cells: int = 12, seed: int = 0,
          octaves: int = 4) -> Material:
    """Fractal value noise blending two colours (`octaves` octaves from `cells` cells per
    uv unit up, each half the size and weight of the one before), tiled over uv."""
    a, b = _linear(c1), _linear(c2)
    rng = np.random.default_rng(seed)
    grids = [rng.random((cells * 2**i, cells * 2**i, 1)) for i in range(octaves)]
    weights = 0.5 ** np.arange(octaves)
    weights /= weights.sum()

    def m(p_local, uv, face):
        u, v = uv[:, 0], uv[:, 1]
        f = sum(wt * _bilinear_wrap(g, u, v) for wt, g in zip(weights, grids, strict=True))
        f = np.clip((f - 0.5) * 2.2 + 0.5, 0.0, 1.0)
        return a * (1 - f) + b * f

    return m


def dots(bg: Sequence[float], colors: Sequence[Sequence[float]], n: int = 6,
         radius: float = 0.3) -> Material:
    """Polka dots on a grid of n x n cells, dot colours cycling through `colors`."""
    base = _linear(bg)
    cols = np.stack([_linear(c) for c in colors])

    def m(p_local, uv, face):
        cell = np.floor(uv * n)
        f = uv * n - cell - 0.5
        inside = np.hypot(f[:, 0], f[:, 1]) < radius
        k = (cell[:, 0] * 3 + cell[:, 1] * 7).astype(np.int64) % len(cols)
        return np.where(inside[:, None], cols[k], base)

    return m


# Seven-segment layout: segments a..g as (x0, x1, y0, y1) boxes in a unit digit cell.
_SEGMENTS = np.array(
    [
        [0.2, 0.8, 0.84, 0.94],  # a top
        [0.72, 0.82, 0.52, 0.9],  # b upper right
        [0.72, 0.82, 0.1, 0.48],  # c lower right
        [0.2, 0.8, 0.06, 0.16],  # d bottom
        [0.18, 0.28, 0.1, 0.48],  # e lower left
        [0.18, 0.28, 0.52, 0.9],  # f upper left
        [0.2, 0.8, 0.45, 0.55],  # g middle
    ]
)
_DIGIT_SEGMENTS = {
    "0": "abcdef", "1": "bc", "2": "abdeg", "3": "abcdg", "4": "bcfg",
    "5": "acdfg", "6": "acdefg", "7": "abc", "8": "abcdefg", "9": "abcdfg", " ": "",
}


def digits(text: str, colors: Sequence[Sequence[float]], bg: Sequence[float]) -> Material:
    """A seven-segment display showing `text` (digits and spaces) across the uv square.

    Character i is drawn in colors[i % len(colors)] on a `bg` background.
    """
    if any(ch not in _DIGIT_SEGMENTS for ch in text):
        raise ValueError(f"digits() shows only 0-9 and spaces, got {text!r}")
    base = _linear(bg)
    cols = np.stack([_linear(c) for c in colors])
    lit_table = np.array([[s in _DIGIT_SEGMENTS[ch] for s in "abcdefg"] for ch in text])

    def m(p_local, uv, face):
        n = len(text)
        ci = np.clip(np.floor(uv[:, 0] * n).astype(np.int64), 0, n - 1)
        x = uv[:, 0] * n - ci
        y = uv[:, 1]
        seg = (
            (x[:, None] >= _SEGMENTS[:, 0]) & (x[:, None] <= _SEGMENTS[:, 1])
            & (y[:, None] >= _SEGMENTS[:, 2]) & (y[:, None] <= _SEGMENTS[:, 3])
        )
        lit = np.any(seg & lit_table[ci], axis=1)
        return np.where(lit[:, None], cols[ci % len(cols)], base)

    return m


def per_face(materials: dict[int, Material], default: Material) -> Material:
    """Use materials[face] where given, else `default` (e.g. a box's front face)."""

    def m(p_local, uv, face):
        out = default(p_local, uv, face)
        for f, mat in materials.items():
            sel = face == f
            if sel.any():
                out[sel] = mat(p_local[sel], uv[sel], face[sel])
        return out

    return m


def bands_y(materials: Sequence[Material], edges: Sequence[float]) -> Material:
    """Split a surface by v into len(edges)+1 bands, each with its own material."""
    edges_arr = np.asarray(edges, np.float64)

    def m(p_local, uv, face):
        k = np.searchsorted(edges_arr, uv[:, 1])
        out = np.zeros((len(uv), 3))
        for i, mat in enumerate(materials):
            sel = k == i
            if sel.any():
                out[sel] = mat(p_local[sel], uv[sel], face[sel])
        return out

    return m
