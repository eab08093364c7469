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
    "camera",
    "coins",
    "moon",
    "page",
    "text",
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
          tint: Sequence[float] = (1.0, 1.0, 1.0), offset: tuple[float, float] = (0.0, 0.0),
          size: int = 256) -> Material:
    """A photograph tiled `repeat` times over the uv square, multiplied by a linear `tint`.

    `size` is the photo's longer side in texels (see `photo`): a larger size keeps
    fine detail (printed text, hair) when a photo is seen up close or tiled finely.
    """
    img = photo(name, size)
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


# ---------------------------------------------------------------- high-frequency patterns


def _nearest_wrap(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample (H, W, ...) at u (columns), v (rows from the top) in texture periods, with
    nearest-texel lookup (crisp edges: pixel-area averaging is left to the renderer)."""
    h, w = img.shape[:2]
    x = np.floor(u * w).astype(np.int64) % w
    y = np.floor(v * h).astype(np.int64) % h
    return img[y, x]


def _hash01(a: np.ndarray, b: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random numbers in [0, 1) for integer cell coordinates (a, b)."""
    x = (a.astype(np.int64) * 73856093) ^ (b.astype(np.int64) * 19349663) ^ (seed * 83492791)
    x = (x ^ (x >> 13)) * 1274126177
    return ((x ^ (x >> 16)) & 0xFFFF) / 65536.0


def bricks(colors: Sequence[Sequence[float]], mortar: Sequence[float], rows: float = 12.0,
           cols: float = 4.0, joint: float = 0.13, aspect: float = 0.33, seed: int = 0
           ) -> Material:
    """Running-bond brickwork: `rows` courses per uv unit of v, `cols` bricks per course
    per uv unit of u, alternate courses shifted by half a brick.

    joint: mortar line thickness as a fraction of a course's height; vertical joints are
    `joint * aspect` of a brick's length (aspect = brick height / brick length on the
    surface), so both joints are equally thin in the world. Each brick takes one of
    `colors` with +-15% brightness and a fine speckle (one value per ~1/24 brick height).
    At real scale (about 13 courses per metre) the joints are fine lines one pixel or
    less wide at a few metres: a high-frequency test for any reconstruction.
    """
    cols_lin = np.stack([_linear(c) for c in colors])
    mortar_lin = _linear(mortar)
    speckle = np.random.default_rng(seed).random((96, 384))

    def m(p_local, uv, face):
        y = uv[:, 1] * rows
        row = np.floor(y)
        x = uv[:, 0] * cols + 0.5 * (row % 2)
        col = np.floor(x)
        fy, fx = y - row, x - col
        in_joint = (fy < joint) | (fx < joint * aspect)
        k = np.floor(_hash01(row, col, seed) * len(cols_lin)).astype(np.int64)
        shade = 0.85 + 0.3 * _hash01(col, row, seed + 1)
        grit = 0.8 + 0.4 * _nearest_wrap(speckle, x / 16.0, y / 4.0)
        brick = cols_lin[k] * (shade * grit)[:, None]
        return np.clip(np.where(in_joint[:, None], mortar_lin, brick), 0.0, MAX_ALBEDO)

    return m


def wood(light: Sequence[float], dark: Sequence[float], rings: float = 10.0,
         planks: int = 4, repeat: tuple[float, float] = (1.0, 1.0), seed: int = 0
         ) -> Material:
    """Wood grain running along u: `planks` planks across v with dark seams, each with
    growth-ring bands (`rings` per plank width) bent by low-frequency noise, and fine
    dark pore streaks stretched along the grain (one texel is 1/512 of a u period).
    The pattern is tiled `repeat` times over the uv square."""
    a, b = _linear(light), _linear(dark)
    rng = np.random.default_rng(seed)
    warp = rng.random((8, 16, 1))
    pores = rng.random((64, 512, 1))
    shift = rng.random(planks)

    def m(p_local, uv, face):
        u, v = uv[:, 0] * repeat[0], uv[:, 1] * repeat[1]
        pv = v * planks
        plank = np.floor(pv).astype(np.int64)
        across = pv - plank
        bend = 1.2 * _bilinear_wrap(warp, u + shift[plank % planks], across * 0.5)[:, 0]
        s = across * rings + bend + 3.0 * shift[plank % planks]
        band = (0.5 + 0.5 * np.cos(2.0 * np.pi * s)) ** 3
        streak = _bilinear_wrap(pores, u + 0.37 * plank, across * 0.25 + 0.5 * s / rings)[:, 0]
        f = np.clip(0.65 * band + 0.45 * streak ** 4, 0.0, 1.0)
        out = a * (1.0 - f[:, None]) + b * f[:, None]
        seam = (across < 0.012) | (across > 0.988)
        return np.where(seam[:, None], b * 0.35, out)

    return m


# A 5 x 7 bitmap font: five column bytes per glyph, bit 0 = top row.
_FONT5X7 = {
    " ": (0x00, 0x00, 0x00, 0x00, 0x00), ".": (0x00, 0x60, 0x60, 0x00, 0x00),
    ",": (0x00, 0x50, 0x30, 0x00, 0x00), "-": (0x08, 0x08, 0x08, 0x08, 0x08),
    "0": (0x3E, 0x51, 0x49, 0x45, 0x3E), "1": (0x00, 0x42, 0x7F, 0x40, 0x00),
    "2": (0x42, 0x61, 0x51, 0x49, 0x46), "3": (0x21, 0x41, 0x45, 0x4B, 0x31),
    "4": (0x18, 0x14, 0x12, 0x7F, 0x10), "5": (0x27, 0x45, 0x45, 0x45, 0x39),
    "6": (0x3C, 0x4A, 0x49, 0x49, 0x30), "7": (0x01, 0x71, 0x09, 0x05, 0x03),
    "8": (0x36, 0x49, 0x49, 0x49, 0x36), "9": (0x06, 0x49, 0x49, 0x29, 0x1E),
    "A": (0x7E, 0x11, 0x11, 0x11, 0x7E), "B": (0x7F, 0x49, 0x49, 0x49, 0x36),
    "C": (0x3E, 0x41, 0x41, 0x41, 0x22), "D": (0x7F, 0x41, 0x41, 0x22, 0x1C),
    "E": (0x7F, 0x49, 0x49, 0x49, 0x41), "F": (0x7F, 0x09, 0x09, 0x09, 0x01),
    "G": (0x3E, 0x41, 0x49, 0x49, 0x7A), "H": (0x7F, 0x08, 0x08, 0x08, 0x7F),
    "I": (0x00, 0x41, 0x7F, 0x41, 0x00), "J": (0x20, 0x40, 0x41, 0x3F, 0x01),
    "K": (0x7F, 0x08, 0x14, 0x22, 0x41), "L": (0x7F, 0x40, 0x40, 0x40, 0x40),
    "M": (0x7F, 0x02, 0x0C, 0x02, 0x7F), "N": (0x7F, 0x04, 0x08, 0x10, 0x7F),
    "O": (0x3E, 0x41, 0x41, 0x41, 0x3E), "P": (0x7F, 0x09, 0x09, 0x09, 0x06),
    "Q": (0x3E, 0x41, 0x51, 0x21, 0x5E), "R": (0x7F, 0x09, 0x19, 0x29, 0x46),
    "S": (0x46, 0x49, 0x49, 0x49, 0x31), "T": (0x01, 0x01, 0x7F, 0x01, 0x01),
    "U": (0x3F, 0x40, 0x40, 0x40, 0x3F), "V": (0x1F, 0x20, 0x40, 0x20, 0x1F),
    "W": (0x3F, 0x40, 0x38, 0x40, 0x3F), "X": (0x63, 0x14, 0x08, 0x14, 0x63),
    "Y": (0x07, 0x08, 0x70, 0x08, 0x07), "Z": (0x61, 0x51, 0x49, 0x45, 0x43),
}
GLYPHS = "".join(_FONT5X7)


def glyph(ch: str) -> np.ndarray:
    """(7, 5) bool bitmap of one character of the 5 x 7 font (rows top to bottom)."""
    cols = _FONT5X7[ch]
    return np.array([[(c >> r) & 1 for c in cols] for r in range(7)], bool)


def text_bitmap(lines: Sequence[str]) -> np.ndarray:
    """(9 * rows, 6 * cols) bool ink mask of lines of text in the 5 x 7 font.

    Each character cell is 6 x 9 texels (one column of letter spacing, two rows of
    leading); lines are padded with spaces to the longest one.
    """
    width = max(len(line) for line in lines)
    out = np.zeros((9 * len(lines), 6 * width), bool)
    for r, line in enumerate(lines):
        for c, ch in enumerate(line.upper()):
            if ch not in _FONT5X7:
                raise ValueError(f"text() has no glyph for {ch!r}; use {GLYPHS!r}")
            out[9 * r + 1: 9 * r + 8, 6 * c: 6 * c + 5] = glyph(ch)
    return out


def random_lines(rows: int, cols: int, seed: int = 0) -> list[str]:
    """`rows` lines of `cols` characters of pseudo-words (2-8 letters, some digits)."""
    rng = np.random.default_rng(seed)
    letters = "ETAOINSRHDLUCMFYWGPBVKXQJZ"
    weights = np.linspace(2.0, 0.2, len(letters))
    weights /= weights.sum()
    lines = []
    for _ in range(rows):
        line = ""
        while len(line) < cols:
            n = int(rng.integers(2, 9))
            if rng.random() < 0.12:
                word = "".join(rng.choice(list("0123456789"), n))
            else:
                word = "".join(rng.choice(list(letters), n, p=weights))
            line += word + (". " if rng.random() < 0.15 else " ")
        lines.append(line[:cols])
    return lines


def text(ink: Sequence[float], paper: Sequence[float], rows: int = 12, cols: int = 32,
         lines: Sequence[str] | None = None, repeat: tuple[float, float] = (1.0, 1.0),
         seed: int = 0) -> Material:
    """Printed text: rows of small 5 x 7 glyphs in `ink` on `paper`, filling the uv square.

    lines: the text (A-Z, 0-9, space, '.', ',' and '-'), else `rows` lines of `cols`
    pseudo-words drawn from `seed`. The block is tiled `repeat` times. Glyph strokes are
    1/9 of a line's height: at a dozen lines per 10 cm they are sub-pixel at 1-2 m.
    """
    mask = text_bitmap(list(lines) if lines is not None else random_lines(rows, cols, seed))
    a, b = _linear(paper), _linear(ink)

    def m(p_local, uv, face):
        u = uv[:, 0] * repeat[0]
        v = (1.0 - uv[:, 1]) * repeat[1]
        inked = _nearest_wrap(mask, u, v)
        return np.where(inked[:, None], b, a)

    return m
