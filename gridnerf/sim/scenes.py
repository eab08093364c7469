"""The nine procedural scenes, named after LMRAW's, each a prop on a table before a wall.

World units: the table top is the plane y = 0, the wall's front face is z = -3, the
prop stands near the origin (about 1-1.5 units tall) and the camera looks at it
along -z from z ~ 3.4. Geometry and sensor settings are fixed per scene name; the
seed only moves the cameras and draws the noise.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from gridnerf.sim import textures as tx
from gridnerf.sim.geometry import Primitive, rotation, rotation_to, tube
from gridnerf.sim.sensor import SensorParams

SCENES: tuple[str, ...] = (
    "bouquet", "deer", "head", "rabbit", "bucket", "doll", "dora", "scoreboard", "box",
)


@dataclass(frozen=True)
class Light:
    """A directional light: `direction` points TOWARD the light; `soft` is the shadow
    penumbra half-angle in radians (0 = hard); `shadow=False` lights through everything."""

    direction: tuple[float, float, float]
    intensity: float
    shadow: bool = True
    soft: float = 0.04


@dataclass(frozen=True)
class SceneSpec:
    """A scene: primitives (room first), lights, camera aim and the sensor settings."""

    name: str
    room: tuple[Primitive, ...]
    props: tuple[Primitive, ...]
    sensor: SensorParams
    lights: tuple[Light, ...] = (
        Light((-0.55, 0.75, 0.65), 0.95),
        Light((0.7, 0.35, 0.6), 0.35, shadow=False),
    )
    ambient: float = 0.22
    target: tuple[float, float, float] = (0.0, 0.6, 0.0)
    distance: float = 3.4
    height: float = 0.4

    @property
    def prims(self) -> list[Primitive]:
        return [*self.room, *self.props]


def _bias(name: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """Fixed per-scene black-level offsets in [-2, 4] DN per CFA position."""
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    b = np.round(rng.uniform(-2.0, 4.0, (2, 2)), 2)
    return ((float(b[0, 0]), float(b[0, 1])), (float(b[1, 0]), float(b[1, 1])))


# name: (kelvin, camera, cfa, mean green electrons, lux class, K in DN/e-)
_SENSORS = {
    "bouquet": (2500, "Sony ILCE-7SM2", "RGGB", 8.0, 0.016, 6.0),
    "deer": (2700, "Canon EOS 5D Mark IV", "RGGB", 12.0, 0.024, 5.0),
    "head": (3000, "Nikon D850", "RGGB", 20.0, 0.04, 4.5),
    "rabbit": (2900, "Sony ILCE-7SM2", "RGGB", 12.0, 0.024, 5.5),
    "bucket": (2800, "Sony ILCE-7SM2", "RGGB", 10.0, 0.02, 5.0),
    "doll": (3200, "Canon EOS 5D Mark IV", "RGGB", 25.0, 0.05, 4.0),
    "dora": (3100, "Nikon D850", "GRBG", 15.0, 0.03, 5.0),
    "scoreboard": (2300, "Sony ILCE-7SM2", "RGGB", 6.0, 0.012, 6.0),
    "box": (2900, "Canon EOS 5D Mark IV", "RGGB", 30.0, 0.05, 4.0),
}


def _sensor(name: str) -> SensorParams:
    kelvin, camera, cfa, electrons, lux, k = _SENSORS[name]
    return SensorParams(camera_model=camera, cfa_pattern=cfa, kelvin=float(kelvin),
                        electrons=electrons, lux=lux, k_gain=k, bias=_bias(name))


def _room(wall, table) -> tuple[Primitive, ...]:
    """A wide table top (y = 0) meeting a wall (front face z = -3)."""
    return (
        Primitive("box", np.array([0.0, 3.0, -3.5]), np.array([12.0, 7.0, 0.5]), wall),
        Primitive("box", np.array([0.0, -0.5, 1.5]), np.array([12.0, 0.5, 5.0]), table),
    )


def _e(center, radii, material, yaw=0.0, pitch=0.0, roll=0.0) -> Primitive:
    return Primitive("ellipsoid", np.asarray(center, float), np.asarray(radii, float),
                     material, rot=rotation(yaw, pitch, roll))


def _b(center, half, material, yaw=0.0, pitch=0.0, roll=0.0) -> Primitive:
    return Primitive("box", np.asarray(center, float), np.asarray(half, float), material,
                     rot=rotation(yaw, pitch, roll))


def _f(center, r_bottom, half_h, r_top, material, axis=(0.0, 1.0, 0.0), caps=(True, True)):
    return Primitive("frustum", np.asarray(center, float), np.array([r_bottom, half_h, r_top]),
                     material, rot=rotation_to(axis), caps=caps)


def _eyes(center, spread, radius=0.035, color=(0.05, 0.05, 0.08)) -> list[Primitive]:
    c = np.asarray(center, float)
    m = tx.solid(color)
    return [_e(c + [-spread, 0, 0], [radius] * 3, m), _e(c + [spread, 0, 0], [radius] * 3, m)]


def _legs(xz, top, radius, material) -> list[Primitive]:
    return [_f([x, top / 2, z], radius, top / 2, radius * 1.2, material) for x, z in xz]


def _bouquet() -> list[Primitive]:
    vase = _f([0, 0.32, 0], 0.2, 0.32, 0.14, tx.image("immunohistochemistry", (2, 1)))
    stem = tx.solid((0.25, 0.55, 0.2))
    heads = [([-0.35, 1.15, 0.05], (0.9, 0.1, 0.2)), ([0.0, 1.35, -0.05], (1.0, 0.8, 0.1)),
             ([0.33, 1.1, 0.1], (0.85, 0.2, 0.75)), ([-0.12, 1.0, 0.3], (1.0, 0.5, 0.1)),
             ([0.2, 1.3, 0.25], (0.3, 0.35, 0.95))]
    prims = [vase]
    for i, (p, col) in enumerate(heads):
        p = np.asarray(p)
        base = np.array([0.0, 0.62, 0.0])
        prims += tube([base, 0.5 * (base + p) + [0, 0.05, 0], p], 0.022, stem)
        petal = tx.dots(col, [(1.0, 1.0, 0.9), (0.2, 0.1, 0.05)], n=5 + i, radius=0.25)
        prims.append(_e(p, [0.14, 0.11, 0.14], petal, yaw=0.5 * i, pitch=0.3))
    leaf = tx.stripes([(0.2, 0.6, 0.15), (0.35, 0.75, 0.2)], n=10, angle_deg=70)
    prims += [_e([-0.25, 0.8, 0.1], [0.2, 0.04, 0.08], leaf, roll=0.5),
              _e([0.27, 0.78, 0.05], [0.2, 0.04, 0.08], leaf, roll=-0.6)]
    return prims


def _deer() -> list[Primitive]:
    fur = tx.image("chelsea", (2, 1), tint=(1.15, 0.85, 0.55))
    cream = tx.solid((0.93, 0.86, 0.7))
    prims = [_e([0, 0.78, 0], [0.5, 0.22, 0.2], fur),
             _e([0.45, 1.02, 0.02], [0.09, 0.25, 0.09], fur, roll=-0.55),
             _e([0.62, 1.22, 0.03], [0.16, 0.1, 0.1], fur, roll=0.2),
             _e([0.78, 1.19, 0.03], [0.05, 0.045, 0.05], tx.solid((0.15, 0.08, 0.06))),
             _e([-0.5, 0.9, 0], [0.06, 0.09, 0.05], cream)]
    prims += _legs([(-0.35, 0.1), (-0.3, -0.1), (0.32, 0.1), (0.36, -0.1)], 0.62, 0.045,
                   tx.solid((0.45, 0.28, 0.15)))
    prims += [_e([0.68, 1.26, 0.1], [0.025] * 3, tx.solid((0.05, 0.05, 0.05)))]
    for side in (-1, 1):
        prims += tube([[0.58, 1.3, 0.05 * side], [0.55, 1.5, 0.15 * side],
                       [0.45, 1.65, 0.22 * side]], 0.022, cream)
        prims += tube([[0.55, 1.5, 0.15 * side], [0.68, 1.62, 0.2 * side]], 0.018, cream)
    return prims


def _head() -> list[Primitive]:
    marble = tx.noise((0.92, 0.9, 0.85), (0.45, 0.55, 0.7), cells=8, seed=3)
    face = tx.image("astronaut", (2, 1), offset=(0.0, -0.2))
    return [
        _b([0, 0.2, 0], [0.35, 0.2, 0.3], marble),
        _e([0, 0.55, 0], [0.42, 0.17, 0.26], tx.stripes([(0.2, 0.3, 0.75), (0.9, 0.9, 0.9)], 14)),
        _f([0, 0.75, 0], 0.12, 0.1, 0.1, tx.solid((0.9, 0.68, 0.55))),
        _e([0, 1.05, 0], [0.25, 0.3, 0.26], face),
        _e([0, 1.2, -0.04], [0.27, 0.2, 0.27], tx.noise((0.35, 0.2, 0.05), (0.7, 0.45, 0.1), 10)),
        _e([0, 1.03, 0.26], [0.04, 0.06, 0.05], tx.solid((0.95, 0.65, 0.55))),
        _e([-0.25, 1.03, 0], [0.04, 0.08, 0.05], tx.solid((0.95, 0.65, 0.55))),
        _e([0.25, 1.03, 0], [0.04, 0.08, 0.05], tx.solid((0.95, 0.65, 0.55))),
        _f([0, 1.5, -0.02], 0.2, 0.15, 0.0, tx.stripes([(0.9, 0.1, 0.1), (1.0, 0.85, 0.1)], 6,
                                                        angle_deg=90)),
        *_eyes([0, 1.1, 0.22], 0.09, 0.035, (0.1, 0.35, 0.15)),
    ]


def _rabbit() -> list[Primitive]:
    plush = tx.dots((0.95, 0.6, 0.75), [(0.55, 0.2, 0.6), (1.0, 1.0, 1.0)], n=9, radius=0.28)
    inner = tx.solid((1.0, 0.45, 0.55))
    prims = [_e([0, 0.38, 0], [0.36, 0.38, 0.3], plush),
             _e([0, 0.9, 0.05], [0.22, 0.2, 0.2], plush),
             _e([-0.11, 1.3, 0.0], [0.06, 0.25, 0.035], inner, roll=0.18),
             _e([0.11, 1.3, 0.0], [0.06, 0.25, 0.035], inner, roll=-0.18),
             _e([0, 0.4, -0.32], [0.09] * 3, tx.solid((0.95, 0.95, 0.95))),
             _e([-0.18, 0.06, 0.2], [0.1, 0.06, 0.15], inner),
             _e([0.18, 0.06, 0.2], [0.1, 0.06, 0.15], inner),
             _e([0, 0.86, 0.25], [0.03] * 3, tx.solid((0.9, 0.2, 0.3))),
             *_eyes([0, 0.95, 0.22], 0.08)]
    carrot = tx.stripes([(1.0, 0.5, 0.05), (0.85, 0.35, 0.02)], 12, angle_deg=90)
    prims.append(_f([0.6, 0.08, 0.3], 0.08, 0.3, 0.0, carrot, axis=(-0.3, 0.0, 1.0)))
    prims += [_e([0.68, 0.1, 0.02], [0.1, 0.03, 0.04], tx.solid((0.2, 0.7, 0.2)), yaw=0.5)]
    return prims


def _bucket() -> list[Primitive]:
    metal = tx.stripes([(0.85, 0.1, 0.1), (0.95, 0.9, 0.85), (0.1, 0.3, 0.8)], 9, angle_deg=90)
    handle = tx.solid((0.95, 0.75, 0.1))
    arc = [[0.44 * np.cos(a), 0.82 + 0.4 * np.sin(a), 0.0] for a in np.linspace(0, np.pi, 7)]
    prims = [_f([0, 0.4, 0], 0.32, 0.4, 0.44, metal, caps=(True, False)), *tube(arc, 0.02, handle)]
    prims += [_e([-0.1, 0.72, 0.1], [0.16] * 3, tx.image("colorwheel")),
              _e([0.14, 0.7, -0.12], [0.14] * 3, tx.checker((0.1, 0.7, 0.3), (1, 1, 0.9), (8, 4))),
              _e([0.75, 0.2, 0.25], [0.2] * 3, tx.image("coffee", (2, 1)))]
    prims.append(_b([-0.75, 0.15, 0.2], [0.15, 0.15, 0.15], tx.image("rocket"), yaw=0.5))
    return prims


def _doll() -> list[Primitive]:
    dress = tx.dots((0.8, 0.05, 0.15), [(1.0, 0.85, 0.2), (1.0, 1.0, 1.0)], n=10, radius=0.3)
    skin = tx.solid((0.98, 0.78, 0.65))
    hair = tx.stripes([(0.95, 0.8, 0.2), (0.85, 0.65, 0.1)], 20, angle_deg=90)
    prims = [_f([0, 0.32, 0], 0.4, 0.32, 0.16, dress),
             _e([0, 0.78, 0], [0.2, 0.2, 0.16], tx.solid((0.2, 0.45, 0.9))),
             _e([0, 1.13, 0], [0.19, 0.2, 0.19], skin),
             _e([0, 1.2, -0.04], [0.22, 0.2, 0.2], hair),
             _e([-0.26, 0.75, 0.02], [0.06, 0.2, 0.06], skin, roll=-0.4),
             _e([0.26, 0.75, 0.02], [0.06, 0.2, 0.06], skin, roll=0.4),
             _e([0, 1.06, 0.17], [0.05, 0.025, 0.02], tx.solid((0.9, 0.2, 0.3))),
             *_eyes([0, 1.14, 0.17], 0.07, 0.03, (0.1, 0.2, 0.7))]
    prims.append(_b([0.7, 0.25, 0.1], [0.25, 0.25, 0.25], tx.image("astronaut"), yaw=-0.4))
    return prims


def _dora() -> list[Primitive]:
    skin = tx.solid((0.75, 0.5, 0.32))
    prims = [_e([0, 0.8, 0], [0.22, 0.26, 0.16], tx.solid((1.0, 0.35, 0.65))),
             _f([0, 0.5, 0], 0.2, 0.1, 0.2, tx.solid((1.0, 0.55, 0.1))),
             *_legs([(-0.1, 0.0), (0.1, 0.0)], 0.42, 0.06, skin),
             _e([0, 1.22, 0.02], [0.2, 0.21, 0.19], skin),
             _e([0, 1.28, -0.03], [0.22, 0.2, 0.2], tx.solid((0.25, 0.12, 0.05))),
             _b([0, 0.85, -0.25], [0.18, 0.2, 0.1], tx.solid((0.5, 0.25, 0.8))),
             _e([-0.27, 0.82, 0.02], [0.06, 0.2, 0.06], skin, roll=-0.3),
             _e([0.27, 0.82, 0.02], [0.06, 0.2, 0.06], skin, roll=0.3),
             *_eyes([0, 1.25, 0.18], 0.07, 0.035)]
    sign = tx.stripes([(1.0, 0.9, 0.2), (0.3, 0.7, 0.95), (0.95, 0.3, 0.2)], 3, angle_deg=45)
    prims.append(_b([-0.7, 0.3, 0.2], [0.2, 0.3, 0.03], sign, yaw=0.3))
    return prims


def _scoreboard() -> list[Primitive]:
    front = tx.digits("12 34", [(1.0, 0.15, 0.1), (1.0, 0.8, 0.1), (0.2, 1.0, 0.3)],
                      (0.06, 0.08, 0.1))
    frame = tx.checker((0.1, 0.3, 0.8), (0.9, 0.9, 0.95), (4, 2))
    legs = tx.solid((0.6, 0.6, 0.62))
    prims = [_b([0, 0.85, 0], [0.75, 0.38, 0.08], tx.per_face({5: front}, frame)),
             *_legs([(-0.5, 0.0), (0.5, 0.0)], 0.47, 0.04, legs)]
    prims.append(_e([0.6, 0.12, 0.45], [0.12] * 3, tx.stripes([(1.0, 0.5, 0.0), (0.1, 0.1, 0.1)],
                                                             6, angle_deg=90)))
    return prims


def _boxes() -> list[Primitive]:
    return [
        _b([-0.45, 0.3, 0], [0.3, 0.3, 0.3], tx.image("rocket"), yaw=0.35),
        _b([0.35, 0.25, 0.1], [0.25, 0.25, 0.25], tx.image("coffee"), yaw=-0.5),
        _b([-0.4, 0.8, 0.0], [0.2, 0.2, 0.2], tx.checker((0.95, 0.8, 0.1), (0.6, 0.1, 0.6)),
           yaw=0.8),
        _b([0.35, 0.65, 0.05], [0.14, 0.15, 0.14], tx.image("hubble_deep_field"), yaw=0.2),
        _b([0.05, 0.12, 0.55], [0.18, 0.12, 0.12], tx.stripes([(0.1, 0.7, 0.6), (0.95, 0.4, 0.3)],
                                                               8, angle_deg=30), yaw=-0.2),
    ]


_PROPS = {"bouquet": _bouquet, "deer": _deer, "head": _head, "rabbit": _rabbit,
          "bucket": _bucket, "doll": _doll, "dora": _dora, "scoreboard": _scoreboard,
          "box": _boxes}

_WOOD = [(0.55, 0.35, 0.2), (0.45, 0.28, 0.15)]


def _wood(colors=_WOOD, n: float = 30.0) -> tx.Material:
    """Wood-grain table top: wobbly bands with fine dark streaks."""
    return tx.stripes(colors, n, wobble=0.004, grain=0.35)


# Wall and table materials per scene (built lazily: photos load on first use).
_ROOMS = {
    "bouquet": lambda: (tx.image("brick", (6, 4), tint=(0.9, 0.55, 0.4)), _wood()),
    "deer": lambda: (tx.image("grass", (5, 4), tint=(0.5, 0.9, 0.45)),
                     tx.noise((0.45, 0.3, 0.15), (0.7, 0.55, 0.3), 16, seed=1)),
    "head": lambda: (tx.stripes([(0.3, 0.5, 0.55), (0.35, 0.58, 0.62)], 40),
                     tx.checker((0.85, 0.82, 0.75), (0.2, 0.2, 0.25), (40, 20))),
    "rabbit": lambda: (tx.image("immunohistochemistry", (6, 3), tint=(0.7, 1.1, 0.8)),
                       tx.image("gravel", (8, 4), tint=(0.8, 0.75, 0.65))),
    "bucket": lambda: (tx.noise((0.2, 0.45, 0.8), (0.7, 0.85, 0.95), 24, seed=2),
                       _wood([(0.6, 0.4, 0.22), (0.5, 0.32, 0.18)], 40)),
    "doll": lambda: (tx.image("stereo_motorcycle", (2, 2)),
                     tx.checker((0.9, 0.3, 0.3), (0.95, 0.9, 0.85), (30, 15))),
    "dora": lambda: (tx.stripes([(0.45, 0.65, 0.95), (0.95, 0.8, 0.4)], 30, angle_deg=90),
                     tx.image("grass", (8, 4), tint=(0.6, 0.8, 0.4))),
    "scoreboard": lambda: (tx.image("brick", (6, 4), tint=(0.55, 0.6, 0.95)),
                           tx.noise((0.2, 0.5, 0.25), (0.3, 0.65, 0.3), 20, seed=4)),
    "box": lambda: (tx.image("colorwheel", (10, 6)),
                    _wood([(0.5, 0.34, 0.2), (0.4, 0.27, 0.16)], 36)),
}


def build_scene(name: str) -> SceneSpec:
    """The SceneSpec for one of SCENES (raises ValueError for other names)."""
    if name not in _PROPS:
        raise ValueError(f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    wall, table = _ROOMS[name]()
    return SceneSpec(name=name, room=_room(wall, table), props=tuple(_PROPS[name]()),
                     sensor=_sensor(name))
