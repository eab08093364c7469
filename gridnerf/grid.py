"""Sparse voxel grid: a dense int32 index into compact trainable rows, trilinear lookup.

Layout
  Values sit at grid *vertices*. Vertex (i, j, k) lies at
  `bbox_min + (i, j, k) * (bbox_max - bbox_min) / (resolution - 1)`; a point is
  interpolated trilinearly from the 8 vertices of its cell. "Index space" is the
  continuous vertex coordinate `u = (p - bbox_min) / (bbox_max - bbox_min) * (R - 1)`.
  `structure.index[i, j, k]` is the row of that vertex in the compact arrays, or M
  (the number of rows) when the vertex is empty. Trainable params (a dict pytree):
    density  (M,)          raw density, sigma = softplus(raw) in 1/voxel (optical depth per
                           voxel length measured in index space, so raw params are O(1) at any
                           resolution and bbox; NDC or world units do not matter)
    rgb      (M, 3 * n_sh) low-light camera-RGB colour coefficients, channel-major
                           (`rgb.reshape(M, 3, n_sh)`), c_l = color_scale * softplus(v)
    log_gain (M, 3)        von Kries gains s = exp(log_gain) > 0
  The gather table is the concatenation [density | rgb | log_gain] of shape (M + 1, C),
  C = 4 + 3 n_sh, whose extra last row is the empty vertex: zero colour and log gain,
  and raw density EMPTY_DENSITY_RAW (-30, sigma 9e-14), so empty space has no density
  while softplus keeps gradients alive everywhere else (a zero row would mean sigma =
  softplus(0) = 0.69 with softplus; ReLU would kill gradients under Adam).

Memory grows with the M occupied vertices, except the int32 index and the bool
occupancy bitmask. Structure edits (prune, upsample) run on the host; the occupancy
refresh (update_occupancy) runs on the device.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage

from gridnerf.errors import GridNerfError

EMPTY_DENSITY_RAW = -30.0
RGB_UNIT_RAW = math.log(math.e - 1.0)  # softplus(RGB_UNIT_RAW) == 1: c_l == color_scale
MAX_SH_DEGREE = 3
_CHUNK = 1 << 18  # points per host-side interpolation chunk (upsample)


@dataclasses.dataclass(frozen=True)
class GridStructure:
    """Non-trainable sparse layout; a pytree whose static fields are python values.

    index:     (Rx, Ry, Rz) int32, vertex -> row in [0, M], M = empty
    coords:    (M, 3) int32, vertex of each row (rows sorted in C order of the vertex)
    neighbors: (M, 3) int32, row of the +x/+y/+z neighbour vertex, M when absent
    occupancy: (Bx, By, Bz) bool, block of occ_factor^3 cells may hold density
    bbox_min, bbox_max: (3,) float32
    background: (2, 3) float32, the backdrop a ray's leftover transmittance renders: row 0
      its low-light camera RGB, row 1 its gains (zeros / ones: black, the old compositing)
    """

    index: jax.Array
    coords: jax.Array
    neighbors: jax.Array
    occupancy: jax.Array
    bbox_min: jax.Array
    bbox_max: jax.Array
    background: jax.Array
    resolution: tuple[int, int, int] = (2, 2, 2)
    sh_degree: int = 0
    occ_factor: int = 1
    color_scale: float = 1.0

    @property
    def n_rows(self) -> int:
        return int(self.coords.shape[0])

    @property
    def n_sh(self) -> int:
        return n_sh_coeffs(self.sh_degree)

    @property
    def n_channels(self) -> int:
        return 4 + 3 * self.n_sh


jax.tree_util.register_dataclass(
    GridStructure,
    data_fields=["index", "coords", "neighbors", "occupancy", "bbox_min", "bbox_max",
                 "background"],
    meta_fields=["resolution", "sh_degree", "occ_factor", "color_scale"],
)


def n_sh_coeffs(sh_degree: int) -> int:
    return (sh_degree + 1) ** 2


def _check_layout(resolution, bbox_min, bbox_max, sh_degree, occ_factor) -> None:
    if len(resolution) != 3 or min(resolution) < 2:
        raise GridNerfError(None, f"grid resolution {tuple(resolution)} is invalid",
                            "give three vertex counts, each >= 2 (grid.resolutions)")
    lo, hi = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    ok = lo.shape == hi.shape == (3,) and np.all(np.isfinite(lo + hi)) and np.all(hi > lo)
    if not ok:
        raise GridNerfError(None, f"grid box {lo} .. {hi} is empty or not finite",
                            "pass finite bbox_min < bbox_max on every axis")
    if not 0 <= sh_degree <= MAX_SH_DEGREE:
        raise GridNerfError(None, f"sh_degree {sh_degree} is unsupported",
                            f"use a spherical-harmonic degree in 0..{MAX_SH_DEGREE}")
    if occ_factor < 1:
        raise GridNerfError(None, f"occ_factor {occ_factor} is invalid", "use an integer >= 1")


BLACK = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], np.float32)  # backdrop: none


def _build_structure(kept: np.ndarray, bbox_min, bbox_max, sh_degree: int, occ_factor: int,
                     color_scale: float, background=BLACK) -> GridStructure:
    """Structure from a dense (Rx, Ry, Rz) bool mask of kept vertices (host side);
    background: (2, 3) as GridStructure.background."""
    res = tuple(int(r) for r in kept.shape)
    coords = np.argwhere(kept).astype(np.int32)  # C order, matches index assignment below
    m = coords.shape[0]
    index = np.full(res, m, np.int32)
    index[kept] = np.arange(m, dtype=np.int32)
    neighbors = np.full((m, 3), m, np.int32)
    for axis in range(3):
        nb = coords.copy()
        nb[:, axis] += 1
        ok = nb[:, axis] < res[axis]
        neighbors[ok, axis] = index[nb[ok, 0], nb[ok, 1], nb[ok, 2]]
    return GridStructure(
        index=jnp.asarray(index), coords=jnp.asarray(coords), neighbors=jnp.asarray(neighbors),
        occupancy=jnp.asarray(_cells_to_blocks(_cells_with_kept_corner(kept), occ_factor)),
        bbox_min=jnp.asarray(bbox_min, jnp.float32), bbox_max=jnp.asarray(bbox_max, jnp.float32),
        background=jnp.asarray(background, jnp.float32).reshape(2, 3), resolution=res,
        sh_degree=int(sh_degree), occ_factor=int(occ_factor), color_scale=float(color_scale))


def _cells_with_kept_corner(kept, xp=np):
    """(Rx-1, Ry-1, Rz-1) bool: cells with at least one kept corner vertex.

    kept: (Rx, Ry, Rz) bool; xp: np (host) or jnp (jittable).
    """
    cx, cy, cz = (r - 1 for r in kept.shape)
    cells = xp.zeros((cx, cy, cz), bool)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                cells = cells | kept[dx:dx + cx, dy:dy + cy, dz:dz + cz]
    return cells


def _cells_to_blocks(cells, f: int, xp=np):
    """OR-reduce (Cx, Cy, Cz) bool cells into (ceil(Cx / f), ceil(Cy / f), ceil(Cz / f))
    blocks; xp: np (host) or jnp (jittable)."""
    shape = tuple(-(-c // f) for c in cells.shape)
    padded = xp.pad(cells, [(0, s * f - c) for s, c in zip(shape, cells.shape, strict=True)])
    return padded.reshape(shape[0], f, shape[1], f, shape[2], f).any(axis=(1, 3, 5))


def init_grid(resolution, bbox_min, bbox_max, sh_degree: int = 0, init_density: float = -4.0,
              init_log_gain=(0.0, 0.0, 0.0), key=None, color_scale: float = 1.0,
              occ_factor: int = 1, init_rgb_noise: float = 0.0, background=BLACK):
    """Dense grid, every vertex occupied -> (structure, params); background: (2, 3) as
    GridStructure.background (the default: black, nothing behind the grid).

    init_density is raw: -4 gives sigma = 0.018 per voxel, so a ray crossing 64 voxels keeps
    31% transmittance and every depth receives gradient. Colour starts at c_l = color_scale
    (grey, DC coefficient RGB_UNIT_RAW); `key` with init_rgb_noise > 0 adds Gaussian noise to
    the colour coefficients. color_scale should be the data's mean level (~1e-3..1e-2).
    """
    resolution = tuple(int(r) for r in resolution)
    _check_layout(resolution, bbox_min, bbox_max, sh_degree, occ_factor)
    structure = _build_structure(np.ones(resolution, bool), bbox_min, bbox_max, sh_degree,
                                 occ_factor, color_scale, background)
    m, n_sh = structure.n_rows, n_sh_coeffs(sh_degree)
    rgb = np.zeros((m, 3, n_sh), np.float32)
    rgb[:, :, 0] = RGB_UNIT_RAW
    rgb = jnp.asarray(rgb.reshape(m, 3 * n_sh))
    if key is not None and init_rgb_noise > 0:
        rgb = rgb + init_rgb_noise * jax.random.normal(key, rgb.shape, jnp.float32)
    log_gain = np.broadcast_to(np.asarray(init_log_gain, np.float32), (m, 3))
    params = {
        "density": jnp.full((m,), init_density, jnp.float32),
        "rgb": rgb,
        "log_gain": jnp.asarray(log_gain),
    }
    return structure, params


def feature_table(structure: GridStructure, params, pad_to: int = 1) -> jax.Array:
    """(M + 1, C') float32 [density | rgb | log_gain | zeros] with the empty row appended.

    C' is C rounded up to a multiple of pad_to: on this CPU, gathering 32 floats per row ran
    ~2x faster than 31 (8 vs 7: up to 2x, noisy); render pads to 8, then drops the padding.
    """
    body = jnp.concatenate(
        [params["density"][:, None], params["rgb"], params["log_gain"]], axis=1)
    width = -(-body.shape[1] // pad_to) * pad_to
    body = jnp.pad(body, ((0, 1), (0, width - body.shape[1])))
    return body.at[-1, 0].set(EMPTY_DENSITY_RAW)


def to_index_space(structure: GridStructure, points: jax.Array) -> jax.Array:
    """(..., 3) grid coordinates -> (..., 3) continuous vertex coordinates."""
    res1 = jnp.asarray(structure.resolution, jnp.float32) - 1.0
    return (points - structure.bbox_min) * (res1 / (structure.bbox_max - structure.bbox_min))


def corner_rows(structure: GridStructure, u: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Rows of the 8 corners of the cell holding each index-space point (clamped to the box).

    u: (..., 3) -> rows (..., 8) int32 in [0, M] (M = empty), corner order (dx, dy, dz) in
    C order; frac (..., 3) the position inside the cell.
    """
    rx, ry, rz = structure.resolution
    uc, base = _cell_of(structure, u)
    corner = np.array([(dx * ry + dy) * rz + dz for dx in (0, 1) for dy in (0, 1)
                       for dz in (0, 1)], np.int32)
    index = structure.index.reshape(-1)

    def cells(b):
        return (b[..., 0] * ry + b[..., 1]) * rz + b[..., 2]
    # An always-true conditional (rows are >= 0) keeps the cells computed once per point.
    # Without it XLA fuses the point's whole placement (the ray march) into the 8-corner
    # gather and runs it again for every corner; XLA on CPU drops optimization barriers,
    # a conditional's operands it keeps. bucket's training step: that gather 13 -> 1.7 ms;
    # the whole `gridnerf train` 200.0 -> 183.2 s (docs/speed.md).
    flat = jax.lax.cond(index[0] >= -1, cells, lambda b: jnp.zeros(b.shape[:-1], b.dtype), base)
    return jnp.take(index, flat[..., None] + corner, mode="clip"), uc - base


def _cell_of(structure: GridStructure, u: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(u clamped to the box, (..., 3) int32 lower corner of the cell holding it)."""
    rx, ry, rz = structure.resolution
    uc = jnp.clip(u, 0.0, jnp.asarray([rx - 1, ry - 1, rz - 1], jnp.float32))
    return uc, jnp.minimum(jnp.floor(uc).astype(jnp.int32), jnp.asarray([rx - 2, ry - 2, rz - 2]))


def cell_ids(structure: GridStructure, u: jax.Array) -> jax.Array:
    """(..., 3) index-space points -> (...,) int32 flat C-order id of the cell holding each
    (the cell whose corners corner_rows reads) among the (Rx-1)(Ry-1)(Rz-1) cells."""
    _, ry, rz = structure.resolution
    base = _cell_of(structure, u)[1]
    return (base[..., 0] * (ry - 1) + base[..., 1]) * (rz - 1) + base[..., 2]


def cells_to_rows(structure: GridStructure, cells, reduce: str) -> np.ndarray:
    """(Cx Cy Cz,) per-cell values (host) -> (M,) per row: the max ("max") or the sum
    ("sum") over the up to 8 cells the row's vertex is a corner of."""
    cx, cy, cz = (r - 1 for r in structure.resolution)
    fill = -np.inf if reduce == "max" else 0.0
    padded = np.pad(np.asarray(cells).reshape(cx, cy, cz), 1, constant_values=fill)
    out = None
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                part = padded[dx:dx + cx + 1, dy:dy + cy + 1, dz:dz + cz + 1]
                out = part if out is None else (np.maximum(out, part) if reduce == "max"
                                                else out + part)
    coords = np.asarray(structure.coords)
    return out[coords[:, 0], coords[:, 1], coords[:, 2]]


def trilinear_index_space(structure: GridStructure, table: jax.Array, u: jax.Array,
                          outside_empty: bool = False) -> jax.Array:
    """Trilinear lookup by one flat gather.

    table: (M + 1, C) from feature_table; u: (..., 3) index-space points -> (..., C).
    Points are clamped to the box, or read as the empty row when outside_empty.
    """
    rows, frac = corner_rows(structure, u)
    if outside_empty:
        hi = jnp.asarray(structure.resolution, jnp.float32) - 1.0
        outside = jnp.any((u < 0.0) | (u > hi), axis=-1, keepdims=True)
        rows = jnp.where(outside, table.shape[0] - 1, rows)
    fx, fy, fz = frac[..., 0], frac[..., 1], frac[..., 2]
    gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz
    # explicit products (corner order of corner_rows): faster on CPU than broadcasting
    weights = jnp.stack([gx * gy * gz, gx * gy * fz, gx * fy * gz, gx * fy * fz,
                         fx * gy * gz, fx * gy * fz, fx * fy * gz, fx * fy * fz], axis=-1)
    return jnp.einsum("...k,...kc->...c", weights, jnp.take(table, rows, axis=0, mode="clip"))


def interpolate(structure: GridStructure, params, points: jax.Array) -> jax.Array:
    """Raw features at points: (..., 3) grid coordinates -> (..., C); outside: the empty row."""
    table = feature_table(structure, params)
    return trilinear_index_space(structure, table, to_index_space(structure, points),
                                 outside_empty=True)


def sh_basis(dirs: jax.Array, sh_degree: int) -> jax.Array:
    """(..., 3) unit directions -> (..., (deg+1)^2) real SH basis.

    The DC basis is 1 (not 0.282) so degree 0 is plain RGB; bands 1..3 are the standard
    orthonormal real spherical harmonics (svox2/Plenoxels constants and ordering).
    """
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    out = [jnp.ones_like(x)]
    if sh_degree >= 1:
        c1 = 0.4886025119029199
        out += [-c1 * y, c1 * z, -c1 * x]
    if sh_degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [1.0925484305920792 * xy, -1.0925484305920792 * yz,
                0.31539156525252005 * (2.0 * zz - xx - yy), -1.0925484305920792 * xz,
                0.5462742152960396 * (xx - yy)]
    if sh_degree >= 3:
        out += [-0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * xy * z,
                -0.4570457994644658 * y * (4 * zz - xx - yy),
                0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
                -0.4570457994644658 * x * (4 * zz - xx - yy),
                1.445305721320277 * z * (xx - yy), -0.5900435899266435 * x * (xx - 3 * yy)]
    return jnp.stack(out, axis=-1)


def decode(structure: GridStructure, features: jax.Array, dirs: jax.Array | None = None):
    """Activations of raw features.

    features: (..., C); dirs: (..., 3) unit view directions broadcastable to features[..., 0]
    (needed only when sh_degree > 0).
    Returns sigma (...,) >= 0 per voxel, rgb_cam_low (..., 3) >= 0, gain (..., 3) > 0
    (log gains clipped to +-30 so gains stay finite).
    """
    n_sh = structure.n_sh
    sigma = jax.nn.softplus(features[..., 0])
    coeffs = features[..., 1:1 + 3 * n_sh].reshape(*features.shape[:-1], 3, n_sh)
    if structure.sh_degree == 0:
        value = coeffs[..., 0]
    else:
        if dirs is None:
            raise ValueError("decode needs view directions when sh_degree > 0")
        value = jnp.einsum("...cs,...s->...c", coeffs, sh_basis(dirs, structure.sh_degree))
    rgb_cam_low = structure.color_scale * jax.nn.softplus(value)
    gain = jnp.exp(jnp.clip(features[..., -3:], -30.0, 30.0))
    return sigma, rgb_cam_low, gain


def _kept_dense(structure: GridStructure) -> np.ndarray:
    return np.asarray(structure.index) < structure.n_rows


def _alpha(density_raw, step_size: float) -> np.ndarray:
    sigma = np.logaddexp(0.0, np.asarray(density_raw, np.float64))
    return 1.0 - np.exp(-sigma * step_size)


def prune(structure: GridStructure, params, keep_vertex_mask):
    """Drop rows: keep_vertex_mask is (M,) bool per row or (Rx, Ry, Rz) bool per vertex.

    Returns (structure, params) with structural occupancy (cells with a kept corner); call
    update_occupancy afterwards for a density-based bitmask.
    """
    keep = np.asarray(keep_vertex_mask, bool)
    coords = np.asarray(structure.coords)
    if keep.shape == tuple(structure.resolution):
        keep = keep[coords[:, 0], coords[:, 1], coords[:, 2]]
    if keep.shape != (structure.n_rows,):
        raise ValueError(f"keep mask shape {keep.shape} is neither ({structure.n_rows},) "
                         f"nor {structure.resolution}")
    kept = np.zeros(structure.resolution, bool)
    kept[tuple(coords[keep].T)] = True
    new = _build_structure(kept, structure.bbox_min, structure.bbox_max, structure.sh_degree,
                           structure.occ_factor, structure.color_scale, structure.background)
    rows = jnp.asarray(np.flatnonzero(keep))
    return new, jax.tree_util.tree_map(lambda a: a[rows], params)


# empty-space skipping: cells whose largest corner alpha (over half a voxel) is below this
# are skipped, and the bitmask is refreshed every OCCUPANCY_EVERY training steps
OCCUPANCY_THRESHOLD = 0.005
OCCUPANCY_EVERY = 100


def update_occupancy(structure: GridStructure, params, threshold: float = OCCUPANCY_THRESHOLD,
                     step_size: float = 0.5) -> GridStructure:
    """Bitmask of blocks holding a cell with a corner whose alpha over step_size > threshold.

    Inside a cell the raw density is a convex combination of its corners' and softplus is
    monotone, so every skipped sample has alpha <= threshold: with threshold 0 skipping is
    exact (only cells whose corners are all empty are skipped). Runs on the device (no host
    sync); the alpha test is _alpha's (float64) exactly, as a floor on the raw density.
    """
    floor = _density_floor(threshold, step_size)
    return dataclasses.replace(
        structure, occupancy=_occupancy_blocks(structure, params["density"], floor))


@jax.jit
def _occupancy_blocks(structure: GridStructure, density: jax.Array, floor) -> jax.Array:
    """(Bx, By, Bz) bool occupancy from density (M,) raw: a row is hot when density >= floor,
    a cell when one of its 8 corner vertices is hot, a block when one of its cells is."""
    hot = jnp.append(density >= floor, False)[structure.index]  # (Rx, Ry, Rz), empty: M
    return _cells_to_blocks(_cells_with_kept_corner(hot, jnp), structure.occ_factor, jnp)


def _density_floor(threshold: float, step_size: float) -> np.float32:
    """Smallest float32 raw density d with _alpha(d, step_size) > threshold (NaN if none).

    _alpha is monotone in d, so `d >= floor` on float32 densities is `_alpha(d) > threshold`
    bit for bit; found by bisection over the ordered float32 bit patterns.
    """
    def hot(bits: int) -> bool:
        return bool(_alpha(_ordered_f32(bits), step_size) > threshold)

    lo, hi = -0x7F800000, 0x7F800000  # -inf, +inf; invariant: not hot(lo), hot(hi)
    if hot(lo):
        return np.float32(-np.inf)
    if not hot(hi):
        return np.float32(np.nan)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if hot(mid) else (mid, hi)
    return _ordered_f32(hi)


def _ordered_f32(k: int) -> np.float32:
    """The float32 at position k of the ordered non-NaN floats (0: +0.0, -1: the largest
    negative subnormal, +-0x7F800000: +-inf)."""
    bits = k if k >= 0 else 0x80000000 | -k
    return np.array(bits, np.uint32).view(np.float32)[()]


def upsample(structure: GridStructure, params, new_resolution):
    """Coarse-to-fine: a finer grid on the same box -> (structure, params) (see resample)."""
    return resample(structure, params, new_resolution)


def resample(structure: GridStructure, params, new_resolution, bbox_min=None, bbox_max=None):
    """A new grid of `new_resolution` vertices on a new box (default: the same box).

    A new vertex is kept when the old cell containing it has a kept corner (vertices outside
    the old box are dropped); its values are the trilinear resampling of the old raw field
    (empty old corners read as the empty row), so linear fields are reproduced exactly where
    all old corners exist. bbox_min, bbox_max: (3,) grid coordinates.
    """
    new_resolution = tuple(int(r) for r in new_resolution)
    old_lo = np.asarray(structure.bbox_min, np.float64)
    old_hi = np.asarray(structure.bbox_max, np.float64)
    lo = old_lo if bbox_min is None else np.asarray(bbox_min, np.float64)
    hi = old_hi if bbox_max is None else np.asarray(bbox_max, np.float64)
    _check_layout(new_resolution, lo, hi, structure.sh_degree, structure.occ_factor)
    cells = _cells_with_kept_corner(_kept_dense(structure))
    axes_u, axes_c, axes_in = [], [], []
    for a, (rc, rf) in enumerate(zip(structure.resolution, new_resolution, strict=True)):
        p = lo[a] + np.arange(rf, dtype=np.float64) * ((hi[a] - lo[a]) / (rf - 1))
        u = (p - old_lo[a]) * ((rc - 1) / (old_hi[a] - old_lo[a]))
        inside = (u >= -1e-6) & (u <= rc - 1 + 1e-6)
        u = np.clip(u, 0.0, rc - 1)
        axes_u.append(u)
        axes_c.append(np.clip(np.floor(u).astype(np.int64), 0, rc - 2))
        axes_in.append(inside)
    ix, iy, iz = axes_in
    kept = cells[np.ix_(*axes_c)] & ix[:, None, None] & iy[None, :, None] & iz[None, None, :]
    new = _build_structure(kept, lo, hi, structure.sh_degree, structure.occ_factor,
                           structure.color_scale, structure.background)
    coords = np.asarray(new.coords)
    table = feature_table(structure, params)
    lookup = jax.jit(trilinear_index_space, static_argnames=("outside_empty",))
    feats = []
    for start in range(0, coords.shape[0], _CHUNK):
        c = coords[start:start + _CHUNK]
        u = np.stack([axes_u[a][c[:, a]] for a in range(3)], axis=1).astype(np.float32)
        feats.append(lookup(structure, table, jnp.asarray(u)))
    feats = (jnp.concatenate(feats, 0) if feats
             else jnp.zeros((0, structure.n_channels), jnp.float32))
    n_rgb = 3 * structure.n_sh
    new_params = {"density": feats[:, 0], "rgb": feats[:, 1:1 + n_rgb],
                  "log_gain": feats[:, 1 + n_rgb:]}
    return new, new_params


def content_box(structure: GridStructure, mass, quantile: float = 0.005, margin: float = 2.0):
    """Box (bbox_min (3,), bbox_max (3,)) holding all but `quantile` of the rendered mass at
    each end of each axis, grown by `margin` voxels of this grid and clipped to the box.

    mass: (M,) non-negative weight per row (e.g. summed rendering weights): floaters that
    serve a single view hold little mass, so they do not stretch the box.
    """
    coords = np.asarray(structure.coords)
    mass = np.maximum(np.asarray(mass, np.float64), 0.0)
    lo, hi = np.asarray(structure.bbox_min, np.float64), np.asarray(structure.bbox_max, np.float64)
    if coords.size == 0 or not mass.sum() > 0:
        return lo, hi
    voxel = (hi - lo) / (np.asarray(structure.resolution) - 1)
    first, last = np.zeros(3), np.zeros(3)
    for a in range(3):
        per_plane = np.bincount(coords[:, a], mass, minlength=structure.resolution[a])
        cdf = np.cumsum(per_plane) / per_plane.sum()
        first[a] = np.searchsorted(cdf, quantile)
        last[a] = np.searchsorted(cdf, 1.0 - quantile)
    new_lo = lo + (first - margin) * voxel
    new_hi = lo + (last + margin) * voxel
    return np.maximum(new_lo, lo), np.minimum(new_hi, hi)


def dilate_rows(structure: GridStructure, keep_rows, iterations: int = 1) -> np.ndarray:
    """(M,) bool: kept rows grown by `iterations` vertices (3x3x3 neighbourhood each)."""
    coords = np.asarray(structure.coords)
    keep = np.asarray(keep_rows, bool)
    dense = np.zeros(structure.resolution, bool)
    dense[tuple(coords[keep].T)] = True
    if iterations > 0 and keep.any():
        dense = scipy.ndimage.binary_dilation(dense, np.ones((3, 3, 3), bool),
                                              iterations=iterations)
    return dense[coords[:, 0], coords[:, 1], coords[:, 2]]


def to_state(structure: GridStructure, params) -> dict[str, np.ndarray]:
    """Host arrays that rebuild (structure, params) with from_state (for checkpoints)."""
    meta = np.array([structure.sh_degree, structure.occ_factor], np.int64)
    return {
        "coords": np.asarray(structure.coords), "occupancy": np.asarray(structure.occupancy),
        "resolution": np.asarray(structure.resolution, np.int64), "meta": meta,
        "bbox": np.stack([np.asarray(structure.bbox_min), np.asarray(structure.bbox_max)]),
        "color_scale": np.asarray(structure.color_scale, np.float64),
        "background": np.asarray(structure.background),
        **{f"param_{k}": np.asarray(v) for k, v in params.items()},
    }


def from_state(state: dict[str, np.ndarray]):
    """Inverse of to_state -> (structure, params)."""
    res = tuple(int(r) for r in state["resolution"])
    kept = np.zeros(res, bool)
    kept[tuple(np.asarray(state["coords"]).T)] = True
    sh_degree, occ_factor = (int(v) for v in state["meta"])
    structure = _build_structure(kept, state["bbox"][0], state["bbox"][1], sh_degree,
                                 occ_factor, float(state["color_scale"]),
                                 state.get("background", BLACK))  # runs before the backdrop
    structure = dataclasses.replace(structure, occupancy=jnp.asarray(state["occupancy"]))
    params = {k[len("param_"):]: jnp.asarray(v) for k, v in state.items()
              if k.startswith("param_")}
    return structure, params
