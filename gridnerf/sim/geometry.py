"""Analytic primitives and vectorised ray casting (numpy, float64).

Three primitive kinds cover every prop: `ellipsoid` (spheres too), `box` and
`frustum` (a truncated cone along local y: cylinders, cones, an open bucket).
Each primitive has a pose (`center`, `rot`: local-to-world rotation whose
columns are the local axes) and is intersected in its local frame, where
`p_local = rot.T @ (p_world - center)`. A bounding sphere culls rays before
the exact test, so a small primitive costs only the rays that come near it, and a
coherent bundle (one camera tile, or parallel shadow rays) skips every primitive outside
its bounding cone or cylinder at once.

Rays are `(origins (N, 3), dirs (N, 3))` with any non-zero direction length;
hit distances `t` are in units of the direction vector, so with camera rays
whose camera-frame z component is -1 (docs/design.md), `t` is the z-depth.

`Hits.normal` is turned to face the ray, so both sides of a zero-thickness wall are
shaded as seen (the inside of an open bucket is lit as an inside).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

T_EPS = 1e-6  # smallest accepted hit distance (shadow rays start offset from the surface)
GROUP_RADIUS = 3.0  # primitives with smaller bounding spheres are culled as one group


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


def mat3(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """x @ m.T for x (N, 3) and m (3, 3), via einsum: threaded BLAS is slow (and stalls
    on a busy machine) for such 3-wide products."""
    return np.einsum("ij,kj->ik", x, m)


def dot3(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """x @ v for x (N, 3) and v (3,), without BLAS."""
    return x[:, 0] * v[0] + x[:, 1] * v[1] + x[:, 2] * v[2]


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
    if np.array_equal(prim.rot, np.eye(3)):
        return origins - prim.center, dirs
    return mat3(origins - prim.center, prim.rot.T), mat3(dirs, prim.rot.T)


# Each kind has a hit test `(prim, o, d) -> (t (N,), face (N,) int)` in the local frame
# (t = inf for a miss) and a surface function `(prim, p, face) -> (normal, uv, face)` at
# local hit points p, evaluated only for the rays a primitive finally wins.


def _ellipsoid_hit(prim: Primitive, o: np.ndarray, d: np.ndarray):
    r = np.asarray(prim.size, np.float64)
    os_, ds = o / r, d / r
    a = np.einsum("ij,ij->i", ds, ds)
    b = np.einsum("ij,ij->i", os_, ds)
    c = np.einsum("ij,ij->i", os_, os_) - 1.0
    disc = b * b - a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t0, t1 = (-b - sq) / a, (-b + sq) / a
    t = np.where(t0 > T_EPS, t0, np.where(t1 > T_EPS, t1, np.inf))
    return np.where(disc >= 0.0, t, np.inf), np.zeros(len(t), np.int64)


def _ellipsoid_surface(prim: Primitive, p: np.ndarray, face: np.ndarray):
    r = np.asarray(prim.size, np.float64)
    q = p / r
    u = np.arctan2(q[:, 2], q[:, 0]) / (2.0 * np.pi) + 0.5
    v = 1.0 - np.arccos(np.clip(q[:, 1], -1.0, 1.0)) / np.pi
    return p / (r * r), np.stack([u, v], -1), face


def _box_hit(prim: Primitive, o: np.ndarray, d: np.ndarray):
    """Slab test, one axis at a time. A slab whose entry or exit is NaN (a ray parallel
    to it, starting exactly on its plane) constrains nothing (fmax/fmin skip NaN)."""
    h = np.asarray(prim.size, np.float64)
    t_near = t_far = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(3):
            inv = 1.0 / d[:, i]
            ta, tb = (-h[i] - o[:, i]) * inv, (h[i] - o[:, i]) * inv
            lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
            t_near = lo if t_near is None else np.fmax(t_near, lo)
            t_far = hi if t_far is None else np.fmin(t_far, hi)
    ok = t_far >= np.maximum(t_near, T_EPS)
    t = np.where(ok, np.where(t_near > T_EPS, t_near, t_far), np.inf)
    return t, np.zeros(len(t), np.int64)


def _box_surface(prim: Primitive, p: np.ndarray, face: np.ndarray):
    """Face index 0..5 = -x, +x, -y, +y, -z, +z (from the hit point)."""
    q = np.clip(p / np.asarray(prim.size, np.float64), -1.0, 1.0)
    rows = np.arange(len(q))
    axis = np.argmax(np.abs(q), axis=1)
    sign = np.sign(q[rows, axis])
    n = np.zeros_like(p)
    n[rows, axis] = sign
    # uv on each face: x-faces use (z, y), y-faces (x, z), z-faces (x, y); u right, v up.
    uv_axes = np.array([[2, 1], [0, 2], [0, 1]])[axis]
    uv = (np.take_along_axis(q, uv_axes, axis=1) + 1.0) * 0.5
    return n, uv, 2 * axis + (sign > 0)


def _frustum_coeffs(prim: Primitive):
    r0, hh, r1 = (float(x) for x in prim.size)
    return r0, hh, r1, (r1 - r0) / (2.0 * hh), 0.5 * (r0 + r1)


def _frustum_hit(prim: Primitive, o: np.ndarray, d: np.ndarray):
    """Truncated cone x^2 + z^2 = (a + b y)^2, |y| <= hh, with optional caps.

    face 0 = side, 1 = bottom cap, 2 = top cap.
    """
    r0, hh, r1, b, a = _frustum_coeffs(prim)
    ra = a + b * o[:, 1]
    qa = d[:, 0] ** 2 + d[:, 2] ** 2 - (b * d[:, 1]) ** 2
    qb = o[:, 0] * d[:, 0] + o[:, 2] * d[:, 2] - b * ra * d[:, 1]
    qc = o[:, 0] ** 2 + o[:, 2] ** 2 - ra * ra
    disc = qb * qb - qa * qc
    sq = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        roots = np.stack([(-qb - sq) / qa, (-qb + sq) / qa], axis=1)
    roots = np.where((disc >= 0.0)[:, None] & np.isfinite(roots), roots, np.inf)
    with np.errstate(invalid="ignore"):  # inf * 0 for missed roots of axis-parallel rays
        y = o[:, 1:2] + roots * d[:, 1:2]
        valid = (roots > T_EPS) & (np.abs(y) <= hh) & (a + b * y >= 0.0)
    cands = [np.where(valid, roots, np.inf).min(axis=1)]
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
    return cands[np.arange(len(o)), face], face


def _frustum_surface(prim: Primitive, p: np.ndarray, face: np.ndarray):
    r0, hh, r1, b, a = _frustum_coeffs(prim)
    side = (face == 0)[:, None]
    n_side = np.stack([p[:, 0], -b * (a + b * p[:, 1]), p[:, 2]], axis=1)
    n_cap = np.zeros_like(p)
    n_cap[:, 1] = np.where(face == 1, -1.0, 1.0)
    u_side = np.arctan2(p[:, 2], p[:, 0]) / (2.0 * np.pi) + 0.5
    v_side = (p[:, 1] + hh) / (2.0 * hh)
    uv_cap = np.stack([p[:, 0], p[:, 2]], axis=1) / (2.0 * max(r0, r1, 1e-9)) + 0.5
    uv = np.where(side, np.stack([u_side, v_side], 1), uv_cap)
    return np.where(side, n_side, n_cap), uv, face


_HIT = {"ellipsoid": _ellipsoid_hit, "box": _box_hit, "frustum": _frustum_hit}
_SURFACE = {"ellipsoid": _ellipsoid_surface, "box": _box_surface, "frustum": _frustum_surface}


class _Rays:
    """Rays plus the per-ray dot products that bounding-sphere tests reuse."""

    def __init__(self, origins: np.ndarray, dirs: np.ndarray):
        self.o, self.d = origins, dirs
        self.dd = np.einsum("ij,ij->i", dirs, dirs)
        self.od = np.einsum("ij,ij->i", origins, dirs)
        self.oo = np.einsum("ij,ij->i", origins, origins)

    def subset(self, idx: np.ndarray) -> _Rays:
        sub = object.__new__(_Rays)
        sub.o, sub.d, sub.dd, sub.od, sub.oo = (
            self.o[idx], self.d[idx], self.dd[idx], self.od[idx], self.oo[idx])
        return sub

    def near_sphere(self, center: np.ndarray, radius: float) -> np.ndarray:
        """Indices of rays that pass within the sphere, ahead of their origin."""
        b = self.od - dot3(self.d, center)
        c = self.oo - 2.0 * dot3(self.o, center) + (center @ center - radius * radius)
        disc = b * b - self.dd * c
        return np.nonzero((disc >= 0.0) & ((disc > b * np.abs(b)) | (b < 0.0)))[0]


def _bundle_test(origins: np.ndarray, dirs: np.ndarray):
    """A conservative whole-bundle test keep(center (3,), radius) -> bool: False only
    when no ray of the bundle can meet the sphere.

    Rays from one origin (a camera tile) are bounded by a cone around their mean
    direction; parallel rays (shadow rays toward a directional light) by a cylinder
    around their projected origins, cut off behind the rearmost origin. Other bundles
    keep every sphere. Coherent bundles (image tiles) let whole primitives be skipped
    without a per-ray test.
    """
    if len(origins) == 0:
        return lambda center, radius: False
    o0, d0 = origins[0], dirs[0]
    if (origins == o0).all():
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        axis = unit.mean(axis=0)
        if np.linalg.norm(axis) < 0.5:
            return lambda center, radius: True
        axis /= np.linalg.norm(axis)
        half = float(np.arccos(np.clip(dot3(unit, axis).min(), -1.0, 1.0)))

        def keep_cone(center, radius):
            v = center - o0
            dist = float(np.linalg.norm(v))
            if dist <= radius * (1.0 + 1e-9) + 1e-9:
                return True
            angle = np.arccos(np.clip(v @ axis / dist, -1.0, 1.0))
            return bool(angle <= half + np.arcsin(radius / dist) + 1e-6)

        return keep_cone
    if (dirs == d0).all():
        d = d0 / np.linalg.norm(d0)
        along = dot3(origins, d)
        flat = origins - along[:, None] * d
        mid = flat.mean(axis=0)
        spread = float(np.sqrt(np.max(np.einsum("ij,ij->i", flat - mid, flat - mid))))
        rear = float(along.min())

        def keep_cylinder(center, radius):
            ahead = center @ d
            if ahead + radius < rear - 1e-9:
                return False
            off = center - ahead * d - mid
            return bool(np.sqrt(off @ off) <= spread + radius + 1e-9)

        return keep_cylinder
    return lambda center, radius: True


def _culled(prims: list[Primitive], origins: np.ndarray, dirs: np.ndarray):
    """Yield (k, prim, ray indices near prim) for the primitives the bundle may reach
    (`_bundle_test`). Small primitives share one bounding sphere, tested once, so their
    own tests only see the rays that come near the group."""
    keep = _bundle_test(origins, dirs)
    radii = np.array([p.bound_radius() for p in prims])
    centers = np.array([p.center for p in prims], np.float64).reshape(-1, 3)
    reach = np.array([keep(c, r) for c, r in zip(centers, radii, strict=True)], bool)
    if not reach.any():
        return
    rays = _Rays(origins, dirs)
    small = radii < GROUP_RADIUS
    for k in np.nonzero(~small & reach)[0]:
        yield k, prims[k], rays.near_sphere(centers[k], radii[k])
    small &= reach
    if small.any():
        g_center = centers[small].mean(axis=0)
        g_radius = float(np.max(np.linalg.norm(centers[small] - g_center, axis=1) + radii[small]))
        near = rays.near_sphere(g_center, g_radius)
        near_rays = rays.subset(near)
        for k in np.nonzero(small)[0]:
            yield k, prims[k], near[near_rays.near_sphere(centers[k], radii[k])]


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
    face_best = np.zeros(n, np.int64)
    for k, prim, idx in _culled(prims, origins, dirs):
        if idx.size == 0:
            continue
        t, face = _HIT[prim.kind](prim, *_to_local(prim, origins[idx], dirs[idx]))
        closer = t < t_best[idx]
        sel = idx[closer]
        t_best[sel] = t[closer]
        prim_best[sel] = k
        face_best[sel] = face[closer]
    normal = np.zeros((n, 3))
    albedo = np.zeros((n, 3))
    for k, prim in enumerate(prims):
        sel = np.nonzero(prim_best == k)[0]
        if sel.size == 0:
            continue
        o, d = _to_local(prim, origins[sel], dirs[sel])
        p_local = o + t_best[sel, None] * d
        n_local, uv, face = _SURFACE[prim.kind](prim, p_local, face_best[sel])
        normal[sel] = mat3(n_local, prim.rot)
        albedo[sel] = prim.material(p_local, uv, face)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    facing = np.einsum("ij,ij->i", normal, dirs) > 0.0
    normal[facing] *= -1.0
    hit = np.isfinite(t_best)
    point = origins + np.where(hit, t_best, 0.0)[:, None] * dirs
    return Hits(t=t_best, prim=prim_best, point=point, normal=normal, albedo=albedo)


def occluded(prims: list[Primitive], origins: np.ndarray, dirs: np.ndarray,
             t_max: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: does a ray (origin + t dir, t > 0) hit any primitive at all (before
    t_max (N,), when given: a point light's distance)."""
    origins = np.asarray(origins, np.float64)
    dirs = np.asarray(dirs, np.float64)
    blocked = np.zeros(len(origins), bool)
    for _, prim, idx in _culled(prims, origins, dirs):
        idx = idx[~blocked[idx]]
        if idx.size == 0:
            continue
        o, d = _to_local(prim, origins[idx], dirs[idx])
        t = _HIT[prim.kind](prim, o, d)[0]
        hit = np.isfinite(t) if t_max is None else np.isfinite(t) & (t < t_max[idx])
        blocked[idx[hit]] = True
    return blocked
