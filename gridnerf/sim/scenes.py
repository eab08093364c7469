"""The simulated scenes: the nine LMRAW-named ones and the held-out set.

The nine (`SCENES`), named after LMRAW's, are each a prop on a table before a wall.
World units are metres: the table top is the plane y = 0, the wall's front face is
z = -3, the prop stands near the origin (about 1-1.5 units tall) and a tripod camera
(`rig="tripod"`) looks at it along -z from z ~ 3.4.

The held-out scenes (`HELDOUT`) change what the nine share: handheld converging arcs
(`rig="arc"`) and slider captures (`rig="slide"`), a hall whose depth spans far/near
~8, and high-frequency textures (brick joints, printed text, finely tiled photos, wood
grain). They are held out: no default of the method is tuned on them; use them only to
check that results carry over.

The mixed-light scenes (`MIXED`) are lit by two illuminants of different colour
temperature, a lamp (`PointLight`, falling off with distance) and daylight (a directional
`Light` plus the ambient fill), each dominating its own part of the scene; they are
rendered light by light (capture.render_view_layers) and the writer records both lights
and a per-frame map of which one dominates where.

The quirky-camera scenes (`HELDOUT_QUIRK`) re-shoot held-out scenes with a camera that
has a real camera's quirks (another CFA layout, a 12- or 10-bit ADC, lens falloff,
per-frame auto-exposure jitter, hot and stuck pixels; sensor.SensorParams): the same
geometry, light, photon budget and cameras as their clean-camera twin (`twin_of`), so the
references are the twin's.

Geometry and sensor settings are fixed per scene name; the seed only moves the
cameras and draws the noise.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, replace

import numpy as np

from gridnerf.sim import textures as tx
from gridnerf.sim.geometry import Primitive, rotation, rotation_to, tube
from gridnerf.sim.sensor import SensorParams

SCENES: tuple[str, ...] = (
    "bouquet", "deer", "head", "rabbit", "bucket", "doll", "dora", "scoreboard", "box",
)
# Held out: no default is tuned on these (see the module docstring).
HELDOUT: tuple[str, ...] = (
    "held_arc_brick", "held_slide_shelf", "held_deep_hall", "held_arc_table",
)
# Tuning scenes with the held-out set's kinds of rig, depth and texture (an arc, a slide),
# but other geometry, textures and sensors: defaults may be chosen on these and the nine,
# never on HELDOUT.
DEV: tuple[str, ...] = ("dev_arc_shop", "dev_slide_bench")
# Lit by two illuminants of different colour temperature (a lamp and daylight), each
# dominating its own part of the scene: a global white balance cannot be right everywhere.
MIXED: tuple[str, ...] = ("mixed_lamp_window", "mixed_desk_daylight")
# Mixed light, held out: other rigs (a converging arc, a slider), lights, sensors and
# content (warm, cool) than MIXED; no default of the mixed-light path is chosen on them.
# held_mixed_hall and held_mixed_toys add two lamps whose light changes with
# depth, and two lights only 1500 K apart on saturated content.
HELDOUT_MIXED: tuple[str, ...] = ("held_mixed_arc", "held_mixed_slide", "held_mixed_hall",
                                   "held_mixed_toys")
# Colour held out: captures that break the colour path's assumptions, no default chosen on
# them: a file whose ColorMatrix does not describe the sensor (generic, another camera's,
# rows scaled) and lights off the Planckian locus (a green-tinted sodium-like lamp, a
# magenta-tinted LED), on the held-out scenes' geometry and rigs.
HELDOUT_COLOUR: tuple[str, ...] = ("held_colour_generic", "held_colour_other",
                                   "held_colour_diagonal", "held_colour_sodium",
                                   "held_colour_led")
# A camera's quirks held out: held-out scenes re-shot (same geometry, light, photon budget,
# cameras and noise streams) by a camera with another CFA layout, a 12- or 10-bit ADC, lens
# falloff with no correction, per-frame auto-exposure jitter and hot and stuck pixels; no
# default is chosen on them.
HELDOUT_QUIRK: tuple[str, ...] = ("held_quirk_brick", "held_quirk_shelf", "held_quirk_table")
# A sensor that is not its camera model's reference, held out: held_colour_other's capture
# by a unit whose channels leak 10 % into their neighbours (4.4 deg from the Sony
# ILCE-7SM2's reference matrix), its own matrix in the file (the reference is then the
# wrong one) or a generic one (the reference is then the nearer); no default is chosen on
# them.
HELDOUT_UNIT: tuple[str, ...] = ("held_unit_own", "held_unit_generic")
# every scene name the simulator knows
ALL_SCENES: tuple[str, ...] = (SCENES + HELDOUT + DEV + MIXED + HELDOUT_MIXED
                               + HELDOUT_COLOUR + HELDOUT_QUIRK + HELDOUT_UNIT)
RIGS: tuple[str, ...] = ("tripod", "arc", "slide")


@dataclass(frozen=True)
class Light:
    """A directional light: `direction` points TOWARD the light; `soft` is the shadow
    penumbra half-angle in radians (0 = hard); `shadow=False` lights through everything;
    `kelvin`: its colour temperature (None: the scene's illuminant, sensor.kelvin)."""

    direction: tuple[float, float, float]
    intensity: float
    shadow: bool = True
    soft: float = 0.04
    kelvin: float | None = None


@dataclass(frozen=True)
class PointLight:
    """A lamp: a point light at `position` whose irradiance falls off as 1 / distance^2
    (`intensity` is the irradiance at 1 unit, facing it); `radius` softens its shadows
    (4 fixed sample points); `kelvin` as for Light."""

    position: tuple[float, float, float]
    intensity: float
    shadow: bool = True
    radius: float = 0.05
    kelvin: float | None = None


@dataclass(frozen=True)
class SceneSpec:
    """A scene: primitives (room first), lights, camera rig and aim, and the sensor.

    Only `props` cast shadows. The camera rig (capture.camera_path) aims at `target`:
    rig "tripod": a jittered ellipse around the rest position target + (0, height,
      distance) (the nine scenes);
    rig "arc": a handheld converging arc at about `distance` from the target, camera
      yaw about the target spread over +-`yaw_spread_deg`, `height` above it;
    rig "slide": a slider: centres on a horizontal line through the rest position,
      `baseline * distance` long, all with the orientation that looks at the target
      from the rest position.
    """

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
    rig: str = "tripod"
    yaw_spread_deg: float = 18.0
    baseline: float = 0.4
    ambient_kelvin: float | None = None  # colour of the ambient fill (None: sensor.kelvin)
    # the scene this one re-shoots with another camera: its cameras and random streams are
    # that scene's (writer.capture_salt); None: its own
    twin_of: str | None = None

    @property
    def prims(self) -> list[Primitive]:
        return [*self.room, *self.props]

    def kelvin_of(self, light: Light | PointLight | None) -> float:
        """Colour temperature of a light (None: the ambient fill)."""
        k = self.ambient_kelvin if light is None else light.kelvin
        return float(self.sensor.kelvin if k is None else k)

    @property
    def kelvins(self) -> tuple[float, ...]:
        """The distinct illuminant colour temperatures, lights first, in order of appearance
        (one layer each when rendered by capture.render_view_layers)."""
        out: list[float] = []
        for light in (*self.lights, None):
            if self.kelvin_of(light) not in out:
                out.append(self.kelvin_of(light))
        return tuple(out)

    @property
    def layered(self) -> bool:
        """Rendered light by light (mixed illuminants or lamps), not by capture.shade."""
        return (self.ambient_kelvin is not None
                or any(isinstance(li, PointLight) or li.kelvin is not None for li in self.lights))


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
    "held_arc_brick": (2600, "Nikon D850", "GRBG", 9.0, 0.018, 5.5),
    "held_slide_shelf": (3000, "Canon EOS 5D Mark IV", "RGGB", 18.0, 0.035, 4.5),
    "held_deep_hall": (2400, "Sony ILCE-7SM2", "RGGB", 7.0, 0.014, 6.0),
    "held_arc_table": (3150, "Sony ILCE-7SM2", "GRBG", 28.0, 0.05, 4.0),
    "dev_arc_shop": (2750, "Canon EOS 5D Mark IV", "RGGB", 11.0, 0.022, 5.0),
    "dev_slide_bench": (2500, "Nikon D850", "GRBG", 14.0, 0.028, 5.0),
    # mixed light: kelvin is the lamp's; each scene names its lights' own temperatures
    "mixed_lamp_window": (2700, "Sony ILCE-7SM2", "RGGB", 12.0, 0.024, 5.0),
    "mixed_desk_daylight": (2400, "Canon EOS 5D Mark IV", "RGGB", 16.0, 0.03, 4.5),
    "held_mixed_arc": (3000, "Nikon D850", "GRBG", 10.0, 0.02, 5.5),
    "held_mixed_slide": (2200, "Sony ILCE-7SM2", "GRBG", 12.0, 0.024, 5.0),
    "held_mixed_hall": (2850, "Canon EOS 5D Mark IV", "GBRG", 8.0, 0.016, 5.5),
    "held_mixed_toys": (3400, "Nikon D850", "BGGR", 20.0, 0.04, 4.5),
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


# ---------------------------------------------------------------- held-out scenes
# Held out: no default is tuned on these. Real scale (1 unit = 1 m) matters here: brick
# courses, glyphs and wood pores are sized like the real things, so at the capture
# distances they land at or below the pixel pitch.

_BRICK_RED = [(0.62, 0.25, 0.16), (0.55, 0.22, 0.15), (0.7, 0.33, 0.2), (0.48, 0.2, 0.14)]
_MORTAR = (0.78, 0.75, 0.7)
_INK = (0.08, 0.08, 0.1)
_PAPER = (0.93, 0.9, 0.82)


def _real_bricks(width: float, height: float, colors=_BRICK_RED, mortar=_MORTAR,
                 seed: int = 0) -> tx.Material:
    """Bricks at real scale (75 mm courses, 225 mm bricks, 10 mm joints) on a face
    `width` x `height` metres."""
    return tx.bricks(colors, mortar, rows=height / 0.075, cols=width / 0.225, joint=0.13,
                     aspect=0.33, seed=seed)


def _floor(material, center=(0.0, -0.5, 1.5), half=(12.0, 0.5, 5.0)) -> Primitive:
    """A floor (or table) slab whose top face is y = center[1] + half[1]."""
    return _b(center, half, material)


def _board(center, half, front, back, yaw=0.0, pitch=0.0) -> Primitive:
    """A thin panel (local z thinnest) with `front` on its +z face and `back` elsewhere."""
    return _b(center, half, tx.per_face({5: front}, back), yaw=yaw, pitch=pitch)


def _held_arc_brick() -> SceneSpec:
    """Held out (nothing is tuned on it). A converging handheld arc around a plinth
    before a real-scale brick wall, with a printed notice on an easel, a lantern and
    crates. Subject ~2.3 m away, depth 1.6-5.4 m."""
    wall = _b([0, 3.0, -2.5], [12.0, 7.0, 0.5], _real_bricks(24.0, 14.0, seed=5))
    floor = _floor(tx.noise((0.42, 0.4, 0.38), (0.62, 0.6, 0.56), cells=96, seed=6))
    marble = tx.noise((0.9, 0.88, 0.84), (0.55, 0.55, 0.6), cells=10, seed=7)
    notice = tx.text(_INK, _PAPER, rows=22, cols=34, seed=8)
    easel = tx.solid((0.35, 0.22, 0.12))
    ribs = tx.stripes([(0.15, 0.15, 0.17), (0.75, 0.62, 0.3)], 24, angle_deg=90)
    crate = tx.wood((0.72, 0.55, 0.35), (0.45, 0.3, 0.18), rings=6, planks=3, seed=9)
    label = tx.text((0.6, 0.05, 0.05), (0.95, 0.9, 0.75), rows=4, cols=10, seed=10)
    props = [
        _b([0, 0.4, 0], [0.22, 0.4, 0.22], marble),
        _e([0, 0.98, 0], [0.18] * 3, tx.image("moon", (2, 1), tint=(0.8, 0.9, 1.1),
                                                size=512)),
        _board([-0.68, 0.62, 0.22], [0.28, 0.36, 0.012], notice, easel, yaw=0.35, pitch=-0.12),
        *tube([[-0.88, 0.0, 0.18], [-0.86, 0.3, 0.21]], 0.015, easel),
        *tube([[-0.44, 0.0, 0.35], [-0.45, 0.3, 0.3]], 0.015, easel),
        _f([0.62, 0.25, 0.18], 0.12, 0.25, 0.1, ribs),
        _f([0.62, 0.56, 0.18], 0.14, 0.06, 0.0, tx.solid((0.15, 0.15, 0.17))),
        _b([0.5, 0.15, -0.5], [0.25, 0.15, 0.2], tx.per_face({5: label}, crate), yaw=-0.25),
        _b([0.48, 0.38, -0.52], [0.17, 0.08, 0.14], crate, yaw=0.15),
        _b([0.15, 0.035, 0.6], [0.11, 0.035, 0.055], _real_bricks(0.22, 0.07, seed=11),
           yaw=0.4),
    ]
    return SceneSpec(name="held_arc_brick", room=(wall, floor), props=tuple(props),
                     sensor=_sensor("held_arc_brick"), target=(0.0, 0.6, 0.0),
                     distance=2.25, height=0.45, rig="arc", yaw_spread_deg=18.0)


def _book(x, y, z, w, h, d, color, seed, yaw=0.0) -> Primitive:
    """A standing book: spine (+z face) printed with a short title."""
    title = tx.text((0.95, 0.9, 0.7), color, rows=1, cols=6, seed=seed)
    return _b([x, y + h, z], [w, h, d], tx.per_face({5: title}, tx.solid(color)), yaw=yaw)


def _held_slide_shelf() -> SceneSpec:
    """Held out (nothing is tuned on it). A slider capture of a bookshelf (books with
    printed spines, a framed photo, photo-printed boxes) before finely tiled photo
    wallpaper, with a potted plant on a stool and a mug on a side table in front:
    objects at 1.1-1.6 m, the shelf at 2.5-2.8 m, the wall at ~3 m."""
    wallpaper = tx.image("camera", (48, 28), tint=(0.95, 0.85, 0.7))
    wall = _b([0, 3.0, -2.5], [12.0, 7.0, 0.5], wallpaper)
    floor = _floor(tx.wood((0.6, 0.42, 0.26), (0.4, 0.26, 0.15), rings=5, planks=66,
                           repeat=(12.0, 1.0), seed=12))
    shelf = tx.wood((0.5, 0.32, 0.2), (0.3, 0.18, 0.1), rings=8, planks=1, seed=13)
    z = -1.75
    props = [_b([sx, 0.9, z], [0.02, 0.9, 0.22], shelf) for sx in (-0.82, 0.82)]
    props += [_b([0, y, z], [0.8, 0.015, 0.22], shelf) for y in (0.03, 0.46, 0.9, 1.34)]
    colours = [(0.55, 0.1, 0.1), (0.1, 0.25, 0.55), (0.15, 0.4, 0.2), (0.6, 0.45, 0.1),
               (0.3, 0.15, 0.4), (0.1, 0.1, 0.12), (0.65, 0.3, 0.15)]
    x = -0.76
    for i, (w, h) in enumerate([(0.025, 0.15), (0.035, 0.17), (0.02, 0.13), (0.04, 0.18),
                                (0.03, 0.16), (0.025, 0.14), (0.045, 0.18)]):
        props.append(_book(x + w, 0.475, z + 0.05, w, h, 0.12, colours[i], seed=20 + i))
        x += 2 * w + 0.004
    x = 0.2
    for i, (w, h) in enumerate([(0.03, 0.16), (0.04, 0.17), (0.025, 0.15), (0.035, 0.14)]):
        props.append(_book(x + w, 0.915, z + 0.05, w, h, 0.12, colours[(i + 3) % 7],
                           seed=30 + i))
        x += 2 * w + 0.004
    props += [
        _b([0.45, 0.6, z + 0.02], [0.16, 0.12, 0.1], tx.image("coffee", (3, 3), size=512),
           yaw=-0.15),
        _board([-0.35, 1.08, z + 0.08], [0.2, 0.15, 0.012],
               tx.image("astronaut", size=512), tx.solid((0.75, 0.6, 0.25)), pitch=-0.15),
        _e([-0.1, 1.47, z + 0.05], [0.11] * 3, tx.image("coins", (3, 2), size=512)),
        _b([0.4, 1.45, z], [0.2, 0.1, 0.14], tx.image("chelsea", (4, 2), size=512), yaw=0.1),
        _b([-0.55, 0.13, z + 0.02], [0.18, 0.1, 0.15], tx.image("rocket", (2, 2)), yaw=0.2),
        # Foreground: a stool with a potted plant, and a side table with a mug.
        _f([-0.35, 0.275, -0.3], 0.16, 0.275, 0.14, tx.solid((0.2, 0.2, 0.22))),
        _f([-0.35, 0.67, -0.3], 0.08, 0.12, 0.11,
           tx.stripes([(0.75, 0.35, 0.2), (0.6, 0.28, 0.15)], 16, angle_deg=90)),
    ]
    leaf = tx.stripes([(0.2, 0.55, 0.15), (0.3, 0.7, 0.2)], 5, angle_deg=90)
    for k in range(6):  # leaves fanning out of the pot
        a = 2.0 * np.pi * k / 6 + 0.3
        props.append(_e([-0.35 + 0.09 * np.cos(a), 0.86 + 0.03 * (k % 3),
                         -0.3 + 0.09 * np.sin(a)], [0.1, 0.012, 0.035], leaf,
                        yaw=-a, roll=0.5))
    props += [
        _b([0.55, 0.35, -0.55], [0.2, 0.35, 0.2], shelf),
        _f([0.5, 0.76, -0.5], 0.045, 0.055, 0.05, tx.text(_INK, (0.9, 0.88, 0.85), rows=3,
                                                         cols=12, repeat=(-1, 1), seed=40)),
    ]
    return SceneSpec(name="held_slide_shelf", room=(wall, floor), props=tuple(props),
                     sensor=_sensor("held_slide_shelf"), target=(0.0, 0.9, -1.5),
                     distance=2.5, height=0.15, rig="slide", baseline=0.4)


def _held_deep_hall() -> SceneSpec:
    """Held out (nothing is tuned on it). A slider capture down a 7.5 m hall: a table
    with a book, a mug and a figurine ~1 m from the cameras, pillars, a bench and a tree
    midway, a brick back wall with a printed poster at ~7.6 m (true far/near ~7.8)."""
    tiles = tx.bricks([(0.7, 0.68, 0.62), (0.6, 0.58, 0.55)], (0.3, 0.3, 0.3),
                      rows=12.0 / 0.3, cols=5.0 / 0.3, joint=0.04, aspect=1.0, seed=14)
    room = (
        _b([0, -0.5, -3.0], [2.5, 0.5, 6.0], tiles),  # floor y = 0, z in [-9, 3]
        _b([0, 3.3, -3.0], [2.5, 0.3, 6.0],
           tx.noise((0.8, 0.78, 0.74), (0.65, 0.63, 0.6), cells=64, seed=15)),  # ceiling 3 m
        _b([-2.3, 1.5, -3.0], [0.3, 1.5, 6.0], _real_bricks(12.0, 3.0, seed=16)),
        _b([2.3, 1.5, -3.0], [0.3, 1.5, 6.0], tx.image("page", (40, 8), size=384,
                                                       tint=(0.95, 0.9, 0.8))),
        _b([0, 1.5, -7.8], [2.5, 1.5, 0.3],
           _real_bricks(5.0, 3.0, [(0.55, 0.5, 0.45), (0.45, 0.42, 0.4)], seed=17)),
        _board([0.6, 1.5, -7.49], [0.6, 0.8, 0.01], tx.text(_INK, _PAPER, rows=16, cols=28,
                                                             seed=18), tx.solid(_PAPER)),
        _board([-0.9, 1.4, -7.49], [0.4, 0.3, 0.01], tx.image("chelsea", size=512),
               tx.solid((0.2, 0.15, 0.1))),
        *[_f([sx, 1.5, sz], 0.14, 1.5, 0.14,
             tx.stripes([(0.85, 0.82, 0.76), (0.7, 0.68, 0.64)], 32, angle_deg=90))
          for sx in (-1.5, 1.5) for sz in (-3.2, -5.6)],
    )
    table = tx.wood((0.62, 0.44, 0.28), (0.4, 0.27, 0.16), rings=9, planks=3, seed=19)
    legs = tx.solid((0.15, 0.12, 0.1))
    props = [
        _b([0, 0.82, -1.2], [0.75, 0.03, 0.4], table),  # top y = 0.85, z in [-1.6, -0.8]
        *_legs([(-0.7, -0.85), (0.7, -0.85), (-0.7, -1.55), (0.7, -1.55)], 0.79, 0.025, legs),
        _b([-0.28, 0.87, -1.12], [0.15, 0.02, 0.1], tx.per_face(
            {3: tx.text(_INK, _PAPER, rows=14, cols=20, repeat=(1, -1), seed=21)},
            tx.solid((0.5, 0.1, 0.1))),
           yaw=0.2),
        _f([0.28, 0.91, -1.05], 0.04, 0.06, 0.045, tx.text(_INK, (0.9, 0.9, 0.85), rows=3,
                                                           cols=10, repeat=(-1, 1), seed=22)),
        _e([0.05, 0.96, -1.35], [0.06, 0.11, 0.06], tx.image("coins", (2, 1), size=512)),
        # Midway: a bench and a potted tree.
        _b([0.9, 0.225, -3.9], [0.6, 0.025, 0.2], tx.wood((0.55, 0.38, 0.22),
                                                          (0.35, 0.22, 0.12), seed=23)),
        *_legs([(0.4, -3.9), (1.4, -3.9)], 0.2, 0.04, legs),
        _f([-0.9, 0.2, -4.6], 0.16, 0.2, 0.2, tx.solid((0.5, 0.3, 0.2))),
        _e([-0.9, 0.95, -4.6], [0.35, 0.55, 0.35],
           tx.noise((0.15, 0.4, 0.12), (0.35, 0.6, 0.2), cells=24, seed=24)),
    ]
    return SceneSpec(name="held_deep_hall", room=room, props=tuple(props),
                     sensor=_sensor("held_deep_hall"), target=(0.0, 0.95, -2.5),
                     distance=2.5, height=0.3, rig="slide", baseline=0.3,
                     lights=(Light((-0.4, 0.8, 0.45), 0.95), Light((0.6, 0.4, 0.7), 0.35,
                                                                   shadow=False)))


def _held_arc_table() -> SceneSpec:
    """Held out (nothing is tuned on it). A converging handheld arc over a wood-grain
    table: a teapot, a cup and saucer, a framed photo and three photo prints lying on
    the table. Subject ~1.6 m away, depth 1.0-5.5 m."""
    table = tx.wood((0.66, 0.47, 0.3), (0.42, 0.28, 0.16), rings=7, planks=50,
                    repeat=(12.0, 1.0), seed=25)
    wall = tx.image("coins", (40, 20), tint=(0.8, 0.9, 0.75))
    glaze = tx.dots((0.2, 0.35, 0.6), [(0.95, 0.92, 0.85), (0.9, 0.75, 0.2)], n=14,
                    radius=0.22)
    white = tx.solid((0.9, 0.88, 0.85))
    spout = [[-0.1, 0.14, -0.05], [-0.02, 0.2, -0.05], [0.03, 0.26, -0.05]]
    handle = [[-0.4, 0.22, -0.05], [-0.47, 0.2, -0.05], [-0.47, 0.1, -0.05],
              [-0.39, 0.07, -0.05]]
    props = [
        _e([-0.25, 0.13, -0.05], [0.16, 0.13, 0.16], glaze),
        _e([-0.25, 0.25, -0.05], [0.07, 0.03, 0.07], glaze),
        _e([-0.25, 0.29, -0.05], [0.02] * 3, white),
        *tube(spout, 0.018, glaze),
        *tube(handle, 0.014, glaze),
        # cup and saucer
        _f([0.12, 0.006, 0.22], 0.08, 0.006, 0.075, white),
        _f([0.12, 0.05, 0.22], 0.035, 0.04, 0.045, tx.text((0.2, 0.3, 0.6), (0.92, 0.9, 0.86),
                                                           rows=2, cols=10, repeat=(-1, 1),
                                                           seed=26),
           caps=(True, False)),
        # framed photo leaning back on a strut
        _board([0.32, 0.2, -0.3], [0.15, 0.19, 0.01], tx.image("astronaut", size=512),
               tx.solid((0.2, 0.12, 0.08)), yaw=-0.3, pitch=-0.2),
        *tube([[0.36, 0.0, -0.42], [0.34, 0.25, -0.33]], 0.008, tx.solid((0.2, 0.12, 0.08))),
    ]
    for (x, z, yaw, name) in [(0.08, 0.45, 0.3, "chelsea"), (-0.32, 0.33, -0.2, "coffee"),
                              (0.5, 0.12, 0.9, "rocket")]:  # prints read from the cameras
        props.append(_b([x, 0.002, z], [0.1, 0.002, 0.07],
                        tx.per_face({3: tx.image(name, (1, -1), size=512)}, white), yaw=yaw))
    room = (_b([0.0, 3.0, -3.5], [12.0, 7.0, 0.5], wall), _floor(table))
    return SceneSpec(name="held_arc_table", room=room, props=tuple(props),
                     sensor=_sensor("held_arc_table"), target=(0.0, 0.15, 0.0),
                     distance=1.5, height=0.55, rig="arc", yaw_spread_deg=17.0)


_HELD = {"held_arc_brick": _held_arc_brick, "held_slide_shelf": _held_slide_shelf,
         "held_deep_hall": _held_deep_hall, "held_arc_table": _held_arc_table}


# ---------------------------------------------------------------- tuning scenes (DEV)

def _dev_arc_shop() -> SceneSpec:
    """Tuning (not held out). A converging handheld arc around a shop counter before a
    wall of glazed tiles and printed price lists: jars with text labels, a tiled photo
    box, a globe, a checkered cloth. Subject ~2 m away, depth 1.4-4.6 m."""
    tiles = tx.bricks([(0.78, 0.8, 0.74), (0.7, 0.74, 0.7)], (0.35, 0.33, 0.3),
                      rows=7.0 / 0.15, cols=12.0 / 0.15, joint=0.06, aspect=1.0, seed=41)
    wall = _b([0, 3.0, -2.2], [12.0, 7.0, 0.5], tiles)
    floor = _floor(tx.noise((0.5, 0.45, 0.4), (0.3, 0.27, 0.24), cells=128, seed=42))
    counter = tx.wood((0.55, 0.36, 0.2), (0.35, 0.22, 0.12), rings=12, planks=8, seed=43)
    props = [
        _b([0, 0.45, 0], [0.7, 0.45, 0.3], counter),  # top y = 0.9
        _b([0, 0.905, 0.05], [0.45, 0.005, 0.2],
           tx.checker((0.7, 0.12, 0.1), (0.93, 0.9, 0.85), (16, 8))),
        _board([-0.45, 1.55, -1.65], [0.35, 0.45, 0.01],
               tx.text(_INK, _PAPER, rows=26, cols=30, seed=44), tx.solid((0.25, 0.2, 0.15))),
        _board([0.5, 1.6, -1.65], [0.3, 0.3, 0.01], tx.image("coffee", size=512),
               tx.solid((0.2, 0.2, 0.2))),
        _e([0.45, 1.065, -0.1], [0.16] * 3, tx.image("hubble_deep_field", (2, 1), size=512)),
        _b([0.1, 1.0, -0.05], [0.12, 0.1, 0.1], tx.image("chelsea", (2, 2), size=512),
           yaw=0.3),
    ]
    for i, x in enumerate((-0.55, -0.38, -0.21)):
        props.append(_f([x, 1.0, 0.1], 0.07, 0.1, 0.065, tx.text(
            _INK, [(0.95, 0.9, 0.8), (0.85, 0.92, 0.95), (0.95, 0.85, 0.85)][i], rows=4,
            cols=10, repeat=(-1, 1), seed=45 + i)))
        props.append(_f([x, 1.115, 0.1], 0.07, 0.015, 0.07, tx.solid((0.6, 0.55, 0.2))))
    return SceneSpec(name="dev_arc_shop", room=(wall, floor), props=tuple(props),
                     sensor=_sensor("dev_arc_shop"), target=(0.0, 1.05, 0.0),
                     distance=2.0, height=0.4, rig="arc", yaw_spread_deg=16.0)


def _dev_slide_bench() -> SceneSpec:
    """Tuning (not held out). A slider capture of a workbench: a toolbox, cans with
    printed labels and a radio on the bench ~1.3 m away, a pegboard with hanging tools
    and a calendar of photos on the wall at ~2.6 m, a plank floor."""
    wall = _b([0, 3.0, -2.3], [12.0, 7.0, 0.5],
              tx.noise((0.75, 0.76, 0.72), (0.62, 0.64, 0.6), cells=160, seed=50))
    peg = tx.dots((0.7, 0.6, 0.45), [(0.2, 0.17, 0.14)], n=48, radius=0.2)
    floor = _floor(tx.wood((0.5, 0.4, 0.3), (0.3, 0.22, 0.15), rings=4, planks=50,
                           repeat=(12.0, 1.0), seed=51))
    bench = tx.wood((0.7, 0.55, 0.38), (0.5, 0.36, 0.22), rings=10, planks=5, seed=52)
    metal = tx.solid((0.3, 0.32, 0.35))
    props = [
        _board([0.0, 1.55, -1.79], [1.0, 0.6, 0.005], peg, peg),  # pegboard
        _b([0, 0.78, -0.6], [0.9, 0.03, 0.35], bench),  # top y = 0.81
        *_legs([(-0.85, -0.3), (0.85, -0.3), (-0.85, -0.9), (0.85, -0.9)], 0.75, 0.03,
               metal),
        _b([-0.45, 0.93, -0.65], [0.22, 0.12, 0.12], tx.stripes(
            [(0.75, 0.12, 0.1), (0.6, 0.1, 0.08)], 12, angle_deg=90), yaw=0.2),
        _b([0.45, 0.92, -0.7], [0.16, 0.11, 0.08], tx.per_face(
            {5: tx.image("camera", size=384)}, tx.solid((0.2, 0.18, 0.15))), yaw=-0.25),
        _board([0.0, 1.75, -1.77], [0.25, 0.35, 0.01], tx.image("astronaut", size=512),
               tx.solid((0.9, 0.9, 0.88))),
        _board([0.75, 1.7, -1.77], [0.2, 0.28, 0.01],
               tx.text(_INK, _PAPER, rows=18, cols=22, seed=53), tx.solid(_PAPER)),
    ]
    for i, x in enumerate((-0.1, 0.08, 0.22)):
        props.append(_f([x, 0.89, -0.45 + 0.05 * i], 0.05, 0.08, 0.05, tx.text(
            (0.1, 0.2, 0.5), (0.95, 0.93, 0.9), rows=3, cols=8, repeat=(-1, 1), seed=54 + i)))
    for x in (-0.8, -0.6, -0.4):  # tools hanging on the pegboard
        props += tube([[x, 1.95, -1.76], [x + 0.03, 1.55, -1.75]], 0.012, metal)
    return SceneSpec(name="dev_slide_bench", room=(wall, floor), props=tuple(props),
                     sensor=_sensor("dev_slide_bench"), target=(0.0, 1.0, -1.0),
                     distance=2.3, height=0.2, rig="slide", baseline=0.35)


_DEV = {"dev_arc_shop": _dev_arc_shop, "dev_slide_bench": _dev_slide_bench}


# ---------------------------------------------------------------- mixed-light scenes

def _mixed_lamp_window() -> SceneSpec:
    """Mixed light. A table before a pale plaster wall, lit by a warm 2700 K lamp at the
    left (a point light 2 m before the wall, ~1 m from the nearest props, falling off with
    distance) and by cool 6500 K daylight from a window at the right (directional, with
    the sky's ambient fill): the lamp gives about half the light, most of it on the left
    of the scene, the window dominates the right, and each fills the other's shadows."""
    plaster = tx.noise((0.86, 0.85, 0.82), (0.74, 0.73, 0.7), cells=24, seed=31)
    room = _room(plaster, _wood([(0.62, 0.45, 0.3), (0.52, 0.37, 0.24)], 34))
    props = [
        _f([-0.55, 0.3, 0.05], 0.16, 0.3, 0.12, tx.solid((0.9, 0.9, 0.88))),  # white vase
        _e([-0.55, 0.72, 0.05], [0.14] * 3, tx.image("colorwheel")),
        _b([0.0, 0.25, -0.15], [0.25, 0.25, 0.25], tx.checker((0.2, 0.45, 0.8),
                                                                 (0.92, 0.9, 0.86), (6, 3)),
           yaw=0.3),
        _e([0.05, 0.68, -0.15], [0.16, 0.18, 0.16], tx.image("coffee", (2, 1))),
        _b([0.6, 0.2, 0.2], [0.2, 0.2, 0.2], tx.image("rocket"), yaw=-0.4),
        _e([0.62, 0.55, 0.2], [0.13] * 3, tx.stripes([(0.9, 0.15, 0.1), (0.95, 0.9, 0.8)], 8,
                                                     angle_deg=90)),
    ]
    lights = (PointLight((-1.5, 1.3, -1.0), 3.0, radius=0.06, kelvin=2700.0),
              Light((0.85, 0.45, 0.25), 0.7, kelvin=6500.0))
    return SceneSpec(name="mixed_lamp_window", room=room, props=tuple(props),
                     sensor=_sensor("mixed_lamp_window"), lights=lights, ambient=0.1,
                     ambient_kelvin=6500.0)


def _mixed_desk_daylight() -> SceneSpec:
    """Mixed light. A desk scene: books, a mug and a globe before a grey-blue wall, under
    5600 K daylight from high at the left (directional, with its ambient fill) and a
    2400 K desk lamp low at the front right (a point light close to the props): the
    lamp's warm pool covers the right foreground, daylight dominates the rest."""
    wall = tx.stripes([(0.62, 0.66, 0.7), (0.58, 0.62, 0.66)], 36)
    room = _room(wall, tx.noise((0.55, 0.5, 0.45), (0.7, 0.66, 0.6), 20, seed=32))
    props = [
        _b([-0.5, 0.15, 0.0], [0.3, 0.15, 0.2], tx.per_face(
            {5: tx.text(_INK, _PAPER, rows=6, cols=14, seed=33)}, tx.solid((0.5, 0.1, 0.12))),
           yaw=0.15),
        _b([-0.48, 0.42, -0.02], [0.24, 0.12, 0.17], tx.solid((0.12, 0.3, 0.55)), yaw=0.05),
        _e([-0.45, 0.75, 0.0], [0.2] * 3, tx.image("hubble_deep_field", (2, 1))),
        _f([0.35, 0.14, 0.25], 0.1, 0.14, 0.1, tx.text(_INK, (0.93, 0.92, 0.9), rows=3,
                                                       cols=12, repeat=(-1, 1), seed=34)),
        _b([0.5, 0.3, -0.35], [0.2, 0.3, 0.12], tx.image("astronaut"), yaw=-0.3),
        _e([0.05, 0.1, 0.45], [0.1, 0.1, 0.1], tx.checker((0.95, 0.8, 0.1), (0.3, 0.6, 0.3),
                                                           (8, 4))),
    ]
    lights = (Light((-0.55, 0.75, 0.4), 0.6, kelvin=5600.0),
              PointLight((1.0, 0.8, 0.9), 2.5, radius=0.05, kelvin=2400.0))
    return SceneSpec(name="mixed_desk_daylight", room=room, props=tuple(props),
                     sensor=_sensor("mixed_desk_daylight"), lights=lights, ambient=0.12,
                     ambient_kelvin=5600.0)


def _held_mixed_arc() -> SceneSpec:
    """Held out, mixed light (nothing is tuned on it). A converging handheld arc around a
    reading corner: an armchair with a striped cushion, a side table with books and a
    globe, a potted plant, a rug on a plank floor, a poster on a brick wall. A 3000 K
    floor lamp stands high at the back left (a point light over the chair), 5000 K light
    falls from a skylight above the right (directional, with its ambient fill). Subject
    ~2.2 m away."""
    wall = _b([0, 3.0, -2.4], [12.0, 7.0, 0.5],
              _real_bricks(24.0, 14.0, colors=[(0.78, 0.74, 0.68), (0.7, 0.66, 0.6)],
                           seed=61))
    floor = _floor(tx.wood((0.6, 0.45, 0.3), (0.42, 0.3, 0.2), rings=5, planks=40,
                           repeat=(12.0, 1.0), seed=62))
    fabric = tx.noise((0.3, 0.45, 0.35), (0.2, 0.32, 0.25), cells=40, seed=63)
    cushion = tx.stripes([(0.85, 0.8, 0.2), (0.9, 0.88, 0.82), (0.2, 0.3, 0.6)], 9,
                         angle_deg=30)
    top = tx.wood((0.5, 0.32, 0.2), (0.35, 0.2, 0.12), rings=8, planks=2, seed=64)
    leaf = tx.dots((0.2, 0.5, 0.18), [(0.35, 0.65, 0.2), (0.1, 0.3, 0.1)], n=9, radius=0.3)
    props = [
        _b([-0.55, 0.22, -0.3], [0.4, 0.22, 0.35], fabric, yaw=0.25),  # seat
        _b([-0.62, 0.62, -0.62], [0.4, 0.3, 0.08], fabric, yaw=0.25),  # back
        _e([-0.5, 0.56, -0.3], [0.2, 0.12, 0.06], cushion, yaw=0.25, pitch=-0.4),
        _b([0.45, 0.28, -0.2], [0.22, 0.28, 0.22], top, yaw=-0.2),  # side table
        _book(0.35, 0.56, -0.25, 0.03, 0.11, 0.08, (0.6, 0.1, 0.1), 65, yaw=-0.2),
        _book(0.42, 0.56, -0.25, 0.03, 0.1, 0.08, (0.1, 0.25, 0.5), 66, yaw=-0.2),
        _e([0.55, 0.68, -0.15], [0.1] * 3, tx.image("hubble_deep_field", (2, 1), size=512)),
        _f([1.0, 0.18, -0.7], 0.14, 0.18, 0.18, tx.solid((0.7, 0.35, 0.2))),  # pot
        _e([1.0, 0.6, -0.7], [0.28, 0.3, 0.28], leaf),
        _b([0.0, 0.004, 0.35], [0.8, 0.004, 0.5], tx.checker((0.6, 0.15, 0.15),
                                                               (0.85, 0.75, 0.55), (10, 6))),
        _board([0.2, 1.5, -1.88], [0.35, 0.45, 0.01], tx.image("coffee", size=512),
               tx.solid((0.15, 0.15, 0.15))),
    ]
    lights = (PointLight((-1.1, 1.7, -0.4), 2.2, radius=0.08, kelvin=3000.0),
              Light((0.45, 0.85, 0.25), 0.55, kelvin=5000.0))
    return SceneSpec(name="held_mixed_arc", room=(wall, floor), props=tuple(props),
                     sensor=_sensor("held_mixed_arc"), lights=lights, ambient=0.1,
                     ambient_kelvin=5000.0, target=(0.0, 0.45, -0.3), distance=2.2,
                     height=0.5, rig="arc", yaw_spread_deg=20.0)


def _held_mixed_slide() -> SceneSpec:
    """Held out, mixed light (nothing is tuned on it; added so that the
    held-out mixed-light result is not one scene). Cool content where held_mixed_arc is
    warm: a workbench of blue-grey metal before a teal wall, on slate tiles, with a blue
    toolbox, a green bottle, a white jug, a greyscale print and a blue-and-white rug,
    seen from a slider (forward-facing). A 2200 K work lamp close at the right (a point
    light) and 7500 K north-sky light from high at the left (directional, with its
    ambient fill). Subject ~2 m away."""
    wall = _b([0, 3.0, -2.0], [12.0, 7.0, 0.5],
              tx.noise((0.35, 0.52, 0.58), (0.29, 0.45, 0.5), cells=30, seed=71))
    floor = _floor(tx.checker((0.42, 0.45, 0.5), (0.34, 0.37, 0.42), (24, 10)))
    metal = tx.noise((0.3, 0.34, 0.4), (0.36, 0.4, 0.46), cells=16, seed=72)
    props = [
        _b([0.0, 0.35, -0.9], [0.8, 0.35, 0.3], metal),  # workbench
        _b([-0.45, 0.82, -0.9], [0.18, 0.12, 0.12], tx.solid((0.1, 0.25, 0.6)), yaw=0.2),
        _f([0.05, 0.85, -0.85], 0.07, 0.15, 0.03, tx.solid((0.15, 0.45, 0.3))),  # bottle
        _f([0.38, 0.8, -0.95], 0.08, 0.1, 0.06, tx.solid((0.9, 0.9, 0.92))),  # jug
        _b([0.12, 0.705, -0.72], [0.15, 0.005, 0.1], tx.text(_INK, (0.9, 0.92, 0.95), rows=6,
                                                             cols=14, seed=73)),
        _board([-0.2, 1.35, -1.48], [0.3, 0.22, 0.01], tx.image("coins", size=512),
               tx.solid((0.15, 0.15, 0.15))),
        _b([0.0, 0.004, -0.1], [0.7, 0.004, 0.45],
           tx.stripes([(0.2, 0.3, 0.55), (0.85, 0.87, 0.9)], 10)),  # rug
        _f([0.65, 0.25, -0.25], 0.15, 0.25, 0.13, tx.solid((0.2, 0.5, 0.5))),  # stool
    ]
    lights = (PointLight((0.9, 0.95, -0.35), 1.2, radius=0.05, kelvin=2200.0),
              Light((-0.6, 0.7, 0.4), 0.6, kelvin=7500.0))
    return SceneSpec(name="held_mixed_slide", room=(wall, floor), props=tuple(props),
                     sensor=_sensor("held_mixed_slide"), lights=lights, ambient=0.12,
                     ambient_kelvin=7500.0, target=(0.0, 0.8, -0.9), distance=2.0,
                     height=0.25, rig="slide", baseline=0.4)


def _held_mixed_hall() -> SceneSpec:
    """Held out, mixed light (added before anything ran on it): two lamps
    and no daylight, the light changing with depth. A slider capture down a 7 m room: a
    2850 K pendant low over a small table near the cameras (a white mug, a green book),
    white chairs and a potted plant midway, a blue cabinet and a poster at the back under
    a 4400 K ceiling lamp; a red door in the left wall, a printed right wall, grey stone
    tiles. Each lamp falls off with distance, so the near part is warm and the far part
    cool, with both mixed between; the ambient fill is the far lamp's. Subject ~3 m away,
    depth 1-7.5 m."""
    tiles = tx.checker((0.45, 0.45, 0.44), (0.36, 0.36, 0.35), (30, 14))
    plaster = tx.noise((0.82, 0.8, 0.74), (0.72, 0.7, 0.64), cells=40, seed=81)
    room = (
        _b([0, -0.5, -2.5], [2.6, 0.5, 5.5], tiles),  # floor y = 0, z in [-8, 3]
        _b([-2.4, 1.5, -2.5], [0.2, 1.5, 5.5], plaster),
        _b([2.4, 1.5, -2.5], [0.2, 1.5, 5.5], tx.image("immunohistochemistry", (24, 4),
                                                       tint=(0.9, 0.85, 0.8))),
        _b([0, 1.5, -7.2], [2.6, 1.5, 0.2], plaster),
        _board([-2.19, 1.0, -3.0], [0.01, 1.0, 0.45], tx.solid((0.6, 0.12, 0.1)),
               tx.solid((0.6, 0.12, 0.1)), yaw=np.pi / 2),  # red door
        _board([0.7, 1.6, -6.99], [0.45, 0.6, 0.01], tx.image("rocket", size=512),
               tx.solid((0.1, 0.1, 0.1))),
    )
    white = tx.solid((0.88, 0.87, 0.84))
    legs = tx.solid((0.2, 0.2, 0.22))
    props = [
        _b([0.2, 0.7, -0.9], [0.35, 0.02, 0.3], tx.wood((0.6, 0.45, 0.3), (0.45, 0.32, 0.2),
                                                        rings=6, planks=2, seed=82)),
        *_legs([(-0.1, -1.15), (0.5, -1.15), (-0.1, -0.65), (0.5, -0.65)], 0.68, 0.02, legs),
        _f([0.05, 0.77, -0.85], 0.04, 0.05, 0.045, white),  # mug
        _b([0.35, 0.735, -0.95], [0.12, 0.015, 0.09], tx.per_face(
            {3: tx.text((0.9, 0.9, 0.8), (0.1, 0.4, 0.2), rows=2, cols=8, seed=83)},
            tx.solid((0.1, 0.4, 0.2))), yaw=0.3),  # green book
        _b([-0.9, 0.45, -2.8], [0.22, 0.45, 0.22], white),  # chairs
        _b([0.6, 0.45, -3.1], [0.22, 0.45, 0.22], white, yaw=0.4),
        _f([1.5, 0.2, -2.3], 0.15, 0.2, 0.18, tx.solid((0.6, 0.35, 0.25))),  # pot
        _e([1.5, 0.75, -2.3], [0.3, 0.4, 0.3], tx.dots((0.18, 0.42, 0.16),
                                                       [(0.3, 0.6, 0.2), (0.1, 0.28, 0.1)],
                                                       n=10, radius=0.3)),
        _b([-0.8, 0.7, -6.6], [0.5, 0.7, 0.3], tx.solid((0.15, 0.3, 0.6))),  # cabinet
    ]
    lights = (PointLight((0.2, 1.4, -0.8), 1.5, radius=0.05, kelvin=2850.0),
              PointLight((-0.3, 2.7, -5.2), 2.5, radius=0.08, kelvin=4400.0))
    return SceneSpec(name="held_mixed_hall", room=room, props=tuple(props),
                     sensor=_sensor("held_mixed_hall"), lights=lights, ambient=0.08,
                     ambient_kelvin=4400.0, target=(0.0, 0.7, -3.0), distance=3.2,
                     height=0.4, rig="slide", baseline=0.3)


def _held_mixed_toys() -> SceneSpec:
    """Held out, mixed light (added before anything ran on it): two lights
    only 1500 K apart (the closest pair: a field has the least to add) on saturated
    content. A converging handheld arc ~1.2 m around toys on a pale table: a red cube,
    a yellow cylinder, a blue ball, a green box, an orange cone, a magenta-and-cyan
    striped ball and a colour-wheel print, before a grey-green wall. 4900 K window light
    from the left (directional, with its ambient fill) and a 3400 K lamp close at the
    right."""
    wall = tx.noise((0.62, 0.66, 0.6), (0.55, 0.6, 0.54), cells=30, seed=91)
    table = tx.noise((0.8, 0.79, 0.76), (0.74, 0.73, 0.7), cells=50, seed=92)
    props = [
        _b([-0.3, 0.08, 0.0], [0.08, 0.08, 0.08], tx.solid((0.75, 0.1, 0.08)), yaw=0.4),
        _f([-0.05, 0.1, -0.15], 0.05, 0.1, 0.05, tx.solid((0.9, 0.75, 0.1))),
        _e([0.18, 0.07, 0.05], [0.07] * 3, tx.solid((0.1, 0.2, 0.7))),
        _b([0.4, 0.05, -0.12], [0.1, 0.05, 0.07], tx.solid((0.15, 0.55, 0.2)), yaw=-0.3),
        _f([-0.15, 0.08, 0.2], 0.06, 0.08, 0.005, tx.solid((0.95, 0.45, 0.08))),
        _e([0.05, 0.06, 0.25], [0.06] * 3, tx.stripes([(0.8, 0.15, 0.6), (0.1, 0.7, 0.75)],
                                                       6, angle_deg=45)),
        _board([0.05, 0.25, -0.45], [0.2, 0.2, 0.01], tx.image("colorwheel", size=512),
               tx.solid((0.9, 0.9, 0.9)), pitch=-0.15),
    ]
    room = (_b([0.0, 3.0, -1.2], [12.0, 7.0, 0.5], wall), _floor(table))
    lights = (Light((-0.7, 0.6, 0.35), 0.55, kelvin=4900.0),
              PointLight((0.7, 0.6, 0.25), 0.5, radius=0.04, kelvin=3400.0))
    return SceneSpec(name="held_mixed_toys", room=room, props=tuple(props),
                     sensor=_sensor("held_mixed_toys"), lights=lights, ambient=0.1,
                     ambient_kelvin=4900.0, target=(0.0, 0.12, 0.0), distance=1.2,
                     height=0.45, rig="arc", yaw_spread_deg=20.0)


_MIX = {"mixed_lamp_window": _mixed_lamp_window, "mixed_desk_daylight": _mixed_desk_daylight,
        "held_mixed_arc": _held_mixed_arc, "held_mixed_slide": _held_mixed_slide,
        "held_mixed_hall": _held_mixed_hall, "held_mixed_toys": _held_mixed_toys}


# name: (geometry of, kelvin, camera, file_matrix, tint_duv, crosstalk); the sensor's noise
# and light level are those of the geometry's own scene
_COLOUR = {
    "held_colour_generic": ("held_slide_shelf", 2600.0, "Canon EOS 5D Mark IV", "generic", 0.0,
                            0.0),
    "held_colour_other": ("held_arc_table", 2900.0, "Sony ILCE-7SM2", "other", 0.0, 0.0),
    "held_colour_diagonal": ("held_arc_brick", 3200.0, "Nikon D850", "diagonal", 0.0, 0.0),
    "held_colour_sodium": ("held_arc_brick", 2100.0, "Sony ILCE-7SM2", "sensor", 0.02, 0.0),
    "held_colour_led": ("held_deep_hall", 3500.0, "Canon EOS 5D Mark IV", "sensor", -0.010,
                        0.0),
    "held_unit_own": ("held_arc_table", 2900.0, "Sony ILCE-7SM2", "sensor", 0.0, 0.1),
    "held_unit_generic": ("held_arc_table", 2900.0, "Sony ILCE-7SM2", "generic", 0.0, 0.1),
}


def _held_colour(name: str) -> SceneSpec:
    geometry, kelvin, camera, file_matrix, duv, crosstalk = _COLOUR[name]
    spec = _HELD[geometry]()
    sensor = replace(spec.sensor, kelvin=kelvin, camera_model=camera, file_matrix=file_matrix,
                     tint_duv=duv, crosstalk=crosstalk, bias=_bias(name))
    return replace(spec, name=name, sensor=sensor)


# name: (twin, cfa, bits, vignette stops, exposure jitter stops, hot pixels); everything
# else (geometry, light, camera model, photon budget, noise, bias) is the twin's
_QUIRK = {
    "held_quirk_brick": ("held_arc_brick", "BGGR", 12, 1.2, 1.0 / 3.0, 20),
    "held_quirk_shelf": ("held_slide_shelf", "GRBG", 10, 1.5, 1.0 / 3.0, 12),
    "held_quirk_table": ("held_arc_table", "GBRG", 12, 1.0, 1.0 / 3.0, 30),
}


def _held_quirk(name: str) -> SceneSpec:
    twin, cfa, bits, vignette, jitter, hot = _QUIRK[name]
    spec = _HELD[twin]()
    sensor = replace(spec.sensor, cfa_pattern=cfa, bits=bits, vignette_stops=vignette,
                     exposure_jitter_stops=jitter, hot_pixels=hot)
    return replace(spec, name=name, sensor=sensor, twin_of=twin)


def build_scene(name: str) -> SceneSpec:
    """The SceneSpec for one of SCENES, HELDOUT, DEV, MIXED, HELDOUT_MIXED,
    HELDOUT_COLOUR, HELDOUT_QUIRK or HELDOUT_UNIT (ValueError for other names)."""
    if name in _COLOUR:
        return _held_colour(name)
    if name in _QUIRK:
        return _held_quirk(name)
    if name in _HELD:
        return _HELD[name]()
    if name in _MIX:
        return _MIX[name]()
    if name in _DEV:
        return _DEV[name]()
    if name not in _PROPS:
        raise ValueError(f"unknown scene {name!r}; choose one of "
                         f"{', '.join(ALL_SCENES)}")
    wall, table = _ROOMS[name]()
    return SceneSpec(name=name, room=_room(wall, table), props=tuple(_PROPS[name]()),
                     sensor=_sensor(name))
