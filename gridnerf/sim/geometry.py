"""Analytic primitives and vectorised ray casting (numpy, float64).

Three primitive kinds cover every prop: `ellipsoid` (spheres too), `box` and
`frustum` (a truncated cone along local y: cylinders, cones, an open bucket).
Each primitive has a pose (`center`, `rot`: local-to-world rotation whose
columns are the local axes) and is intersected in its local frame, where
`p_local = rot.T @ (p_world - center)`. A bounding sphere culls rays before
the exact test, so a small primitive costs only the rays that come near it.

Rays are `(origins (N, 3), dirs (N, 3))` with any non-zero direction length;
hit distances `t` are in units of the direction vector, so with camera rays
whose camera-frame z component is -1 (docs/design.md), `t` is the z-depth.

Surfaces are one-sided in appearance: `Hits.normal` always faces the ray
(the inside of an open bucket is lit as an inside).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

T_EPS = 1e-6  # smallest accepted hit distance (shadow rays start offset from the surface)


@dataclass(frozen=True, eq=False)
class Primitive:
    """One analytic solid.

    kind: "ellipsoid" (size = radii), "box" (size = half extents) or "frustum"
      (size = (r_bottom, half_height, r_top), axis along local y; `caps` says
      which of the bottom/top discs exist: a bucket is (True, False)).
    center: (3,) world position; rot: (3, 3) local-to-world rotation.
    material: callable(p_local (N, 3), uv (N, 2), face (N,) int) -> albedo (N, 3)
      linear sRGB reflectance in [0, 1].
    """

    kind: str
    center: np.ndarray
    size: np.ndarray
    material: object
    rot: np.ndarray = field(default_factory=lambda: np.eye(3))
    caps: tuple[bool, bool] = (True, True)

    def bound_radius(self) -> float:
        """Radius of a sphere around `center` that contains the primitive."""
        s = np.asarray(self.size, np.float64)
        if self.kind == "ellipsoid":
            return float(s.max())
        if self.kind == "box":
            return float(np.linalg.norm(s))
        return float(np.hypot(max(s[0], s[2]), s[1]))


@dataclass(frozen=True)
class Hits:
    """Closest hits of N rays. Rays that miss have `prim == -1` and `t == inf`.

    t: (N,) hit distance; prim: (N,) int primitive index; point: (N, 3) world
    position; normal: (N, 3) unit world normal facing the ray; albedo: (N, 3)
    linear sRGB reflectance (0 for misses).
    """

    t: np.ndarray
    prim: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray


def rotation(yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """(3, 3) rotation R = Ry(yaw) @ Rx(pitch) @ Rz(roll), angles in radians."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    rz = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return ry @ rx @ rz


def rotation_to(axis_y) -> np.ndarray:
    """(3, 3) rotation whose local y axis points along `axis_y` (any length > 0)."""
    y = np.asarray(axis_y, np.float64)
    y = y / np.linalg.norm(y)
    helper = np.array([0.0, 0.0, 1.0]) if abs(y[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(y, helper)
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=1)


def tube(points, radius: float, material) -> list[Primitive]:
    """A round tube along a polyline: one cylinder per segment plus a sphere per joint.

    points: (M, 3) world positions, M >= 2. Returns 2M - 1 primitives.
    """
    pts = np.asarray(points, np.float64)
    prims = []
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        half = 0.5 * np.linalg.norm(b - a)
        prims.append(Primitive("frustum", 0.5 * (a + b), np.array([radius, half, radius]),
                               material, rot=rotation_to(b - a)))
    for p in pts:
        prims.append(Primitive("ellipsoid", p, np.full(3, radius), material))
    return prims


def _to_local(prim: Primitive, origins: np.ndarray, dirs: np.ndarray):
    o = (origins - prim.center) @ prim.rot
    d = dirs @ prim.rot
    return o, d


def _ellipsoid(prim: Primitive, o: np.ndarray, d: np.ndarray):
    """Nearest hit with the ellipsoid; returns t (inf = miss), local normal, uv, face."""
    r = np.asarray(prim.size, np.float64)
    os_, ds = o / r, d / r
    a = np.einsum("ij,ij->i", ds, ds)
    b = np.einsum("ij,ij->i", os_, ds)
    c = np.einsum("ij,ij->i", os_, os_) - 1.0
    disc = b * b - a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t0, t1 = (-b - sq) / a, (-b + sq) / a
    t = np.where(t0 > T_EPS, t0, np.where(t1 > T_EPS, t1, np.inf))
    t = np.where(disc >= 0.0, t, np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    n = p / (r * r)
    q = p / r
    u = np.arctan2(q[:, 2], q[:, 0]) / (2.0 * np.pi) + 0.5
    v = 1.0 - np.arccos(np.clip(q[:, 1], -1.0, 1.0)) / np.pi
    return t, n, np.stack([u, v], -1), np.zeros(len(t), np.int64)


def _box(prim: Primitive, o: np.ndarray, d: np.ndarray):
    """Slab test; face index 0..5 = -x, +x, -y, +y, -z, +z."""
    h = np.asarray(prim.size, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        ta, tb = (-h - o) * inv, (h - o) * inv
    tmin, tmax = np.minimum(ta, tb), np.maximum(ta, tb)
    tmin = np.nan_to_num(tmin, nan=-np.inf)
    tmax = np.nan_to_num(tmax, nan=np.inf)
    t_near, t_far = tmin.max(axis=1), tmax.min(axis=1)
    ok = t_far >= np.maximum(t_near, T_EPS)
    t = np.where(ok, np.where(t_near > T_EPS, t_near, t_far), np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    q = np.clip(p / h, -1.0, 1.0)
    axis = np.argmax(np.abs(q), axis=1)
    sign = np.sign(q[np.arange(len(q)), axis])
    n = np.zeros_like(p)
    n[np.arange(len(q)), axis] = sign
    face = 2 * axis + (sign > 0)
    # uv on each face: x-faces use (z, y), y-faces (x, z), z-faces (x, y); u right, v up.
    uv_axes = np.array([[2, 1], [0, 2], [0, 1]])[axis]
    uv = (np.take_along_axis(q, uv_axes, axis=1) + 1.0) * 0.5
    return t, n, uv, face


def _frustum(prim: Primitive, o: np.ndarray, d: np.ndarray):
    """Truncated cone x^2 + z^2 = (a + b y)^2, |y| <= hh, with optional caps.

    face 0 = side, 1 = bottom cap, 2 = top cap.
    """
    r0, hh, r1 = (float(x) for x in prim.size)
    b = (r1 - r0) / (2.0 * hh)
    a = 0.5 * (r0 + r1)
    ra = a + b * o[:, 1]
    qa = d[:, 0] ** 2 + d[:, 2] ** 2 - (b * d[:, 1]) ** 2
    qb = o[:, 0] * d[:, 0] + o[:, 2] * d[:, 2] - b * ra * d[:, 1]
    qc = o[:, 0] ** 2 + o[:, 2] ** 2 - ra * ra
    disc = qb * qb - qa * qc
    sq = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        roots = np.stack([(-qb - sq) / qa, (-qb + sq) / qa], axis=1)
    roots = np.where((disc >= 0.0)[:, None] & np.isfinite(roots), roots, np.inf)
    y = o[:, 1:2] + roots * d[:, 1:2]
    valid = (roots > T_EPS) & (np.abs(y) <= hh) & (a + b * y >= 0.0)
    t_side = np.where(valid, roots, np.inf).min(axis=1)
    cands = [t_side]
    for k, (yc, rc) in enumerate(((-hh, r0), (hh, r1))):
        if not prim.caps[k]:
            cands.append(np.full(len(o), np.inf))
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            tc = (yc - o[:, 1]) / d[:, 1]
        pc = o + np.nan_to_num(tc, nan=0.0, posinf=0.0, neginf=0.0)[:, None] * d
        inside = pc[:, 0] ** 2 + pc[:, 2] ** 2 <= rc * rc
        cands.append(np.where((tc > T_EPS) & inside, tc, np.inf))
    cands = np.stack(cands, axis=1)
    face = np.argmin(cands, axis=1)
    t = cands[np.arange(len(o)), face]
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    n_side = np.stack([p[:, 0], -b * (a + b * p[:, 1]), p[:, 2]], axis=1)
    n_cap = np.zeros_like(p)
    n_cap[:, 1] = np.where(face == 1, -1.0, 1.0)
    n = np.where((face == 0)[:, None], n_side, n_cap)
    u_side = np.arctan2(p[:, 2], p[:, 0]) / (2.0 * np.pi) + 0.5
    v_side = (p[:, 1] + hh) / (2.0 * hh)
    rmax = max(r0, r1, 1e-9)
    uv_cap = np.stack([p[:, 0], p[:, 2]], axis=1) / (2.0 * rmax) + 0.5
    uv = np.where((face == 0)[:, None], np.stack([u_side, v_side], 1), uv_cap)
    return t, n, uv, face


_INTERSECT = {"ellipsoid": _ellipsoid, "box": _box, "frustum": _frustum}


def _candidates(prim: Primitive, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Indices of rays that pass within the primitive's bounding sphere (ahead of origin)."""
    r = prim.bound_radius()
    oc = origins - prim.center
    a = np.einsum("ij,ij->i", dirs, dirs)
    b = np.einsum("ij,ij->i", oc, dirs)
    c = np.einsum("ij,ij->i", oc, oc) - r * r
    disc = b * b - a * c
    far = (-b + np.sqrt(np.maximum(disc, 0.0))) / a
    return np.nonzero((disc >= 0.0) & (far > T_EPS))[0]


def cast(prims: list[Primitive], origins: np.ndarray, dirs: np.ndarray) -> Hits:
    """Closest hit of each ray against all primitives.

    origins, dirs: (N, 3) float. Returns `Hits` with albedo evaluated by the
    winning primitive's material and a unit normal turned to face the ray.
    """
    origins = np.asarray(origins, np.float64)
    dirs = np.asarray(dirs, np.float64)
    n = len(origins)
    t_best = np.full(n, np.inf)
    prim_best = np.full(n, -1, np.int64)
    normal = np.zeros((n, 3))
    p_local = np.zeros((n, 3))
    uv_best = np.zeros((n, 2))
    face_best = np.zeros(n, np.int64)
    for k, prim in enumerate(prims):
        idx = _candidates(prim, origins, dirs)
        if idx.size == 0:
            continue
        o, d = _to_local(prim, origins[idx], dirs[idx])
        t, n_local, uv, face = _INTERSECT[prim.kind](prim, o, d)
        closer = t < t_best[idx]
        sel = idx[closer]
        t_best[sel] = t[closer]
        prim_best[sel] = k
        normal[sel] = n_local[closer] @ prim.rot.T
        p_local[sel] = o[closer] + t[closer][:, None] * d[closer]
        uv_best[sel] = uv[closer]
        face_best[sel] = face[closer]
    albedo = np.zeros((n, 3))
    for k, prim in enumerate(prims):
        sel = np.nonzero(prim_best == k)[0]
        if sel.size:
            albedo[sel] = prim.material(p_local[sel], uv_best[sel], face_best[sel])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    facing = np.einsum("ij,ij->i", normal, dirs) > 0.0
    normal[facing] *= -1.0
    hit = np.isfinite(t_best)
    point = origins + np.where(hit, t_best, 0.0)[:, None] * dirs
    return Hits(t=t_best, prim=prim_best, point=point, normal=normal, albedo=albedo)


def occluded(prims: list[Primitive], origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N,) bool: does a ray (origin + t dir, t > 0) hit any primitive at all."""
    origins = np.asarray(origins, np.float64)
    dirs = np.asarray(dirs, np.float64)
    blocked = np.zeros(len(origins), bool)
    for prim in prims:
        idx = _candidates(prim, origins, dirs)
        idx = idx[~blocked[idx]]
        if idx.size == 0:
            continue
        o, d = _to_local(prim, origins[idx], dirs[idx])
        t = _INTERSECT[prim.kind](prim, o, d)[0]
        blocked[idx[np.isfinite(t)]] = True
    return blocked
