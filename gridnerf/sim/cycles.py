"""Captures path-traced by Blender Cycles: a renderer the method was not written against.

`simulate_cycles(name, out_dir)` scripts Debian's `blender` (gridnerf.sim.blender_scene) to
path-trace a small room with coloured walls from a converging arc of cameras, under a
white area light, and writes the same scene folder as the procedural scenes
(gridnerf.sim.writer). What these captures break that the procedural ones keep:

- the light's colour is applied in the renderer's RGB (linear sRGB, the light's RGB times
  the white render, exact for an RGB path tracer), not as a chromatic adaptation or a
  diagonal in camera space: a von Kries gain in camera space cannot undo it exactly;
- interreflection: light bounced off a red or green wall tints its neighbours, so the
  light's colour varies over the scene although there is one lamp. The references are
  the white-lit render, which keeps that tint (a photograph under white light shows it):
  a gain field that white-balances it away is wrong;
- the lights are not blackbodies where the scene says so (sodium-like, LED-like RGB).

The camera signal is xyz_to_cam @ XYZ_FROM_SRGB @ (light_rgb * render); the noise, the
DNG and the previews are the procedural scenes' (gridnerf.sim.sensor). The true light for
sim.json is the camera RGB of white under light_rgb. Debian's Blender has no denoiser, so
the references carry the path tracer's own noise at SAMPLES samples a pixel; 24 views of
320x180 take 5-10 minutes on 2 cores (`make cycles` writes every scene of CYCLES under
data/cycles/). Nothing of it is committed: the folders are data.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import tempfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gridnerf.color import XYZ_FROM_SRGB, luminance
from gridnerf.errors import SceneError
from gridnerf.image_io import read_exr
from gridnerf.sim import sensor, writer
from gridnerf.sim.capture import HFOV_DEG, Intrinsics, intrinsics

SCRIPT = Path(__file__).with_name("blender_scene.py")
CYCLES_VERSION = 1  # part of the folder's cache key: bump when the written files change
WIDTH, HEIGHT, SAMPLES = 320, 180, 48  # the captures' size and path-tracing samples a pixel


@dataclass(frozen=True)
class CyclesScene:
    """A room for blender_scene.py. walls: {"left", "right", "back", "floor": (3,) sRGB
    albedo, "floor_checker"/"back_checker": second checker colour}; objects: blender_scene's
    object dicts; light: {"location", "size", "power"}; light_rgb: the lamp's colour
    (linear sRGB, any scale); sensor: the camera (gridnerf.sim.sensor.SensorParams
    fields); note: what the scene breaks."""

    walls: dict
    objects: list
    light: dict
    light_rgb: tuple[float, float, float]
    sensor: dict = field(default_factory=dict)
    note: str = ""


_OBJECTS = [
    {"kind": "sphere", "location": [-0.9, -0.6, 0.55], "size": 0.55, "color": [0.8, 0.8, 0.78]},
    {"kind": "cube", "location": [0.8, -0.9, 0.45], "size": 0.45, "color": [0.15, 0.25, 0.65],
     "checker": [0.7, 0.7, 0.2], "rotation": 25},
    {"kind": "cylinder", "location": [0.1, -1.6, 0.7], "size": 0.3, "height": 1.4,
     "color": [0.75, 0.45, 0.15], "checker": [0.3, 0.15, 0.05], "scale": 8.0},
    {"kind": "sphere", "location": [0.35, 0.1, 0.25], "size": 0.25, "color": [0.2, 0.6, 0.3]},
]

CYCLES = {
    # a Cornell-like box under a warm incandescent-like lamp: red and green walls tint
    # the grey sphere and the floor next to them
    "cycles_cornell": CyclesScene(
        walls={"left": (0.65, 0.06, 0.05), "right": (0.08, 0.5, 0.1), "back": (0.7, 0.7, 0.68),
               "floor": (0.5, 0.42, 0.32), "floor_checker": (0.3, 0.25, 0.2),
               "back_checker": (0.55, 0.55, 0.6)},
        objects=_OBJECTS, light={"location": [0.0, 0.5, 3.2], "size": 1.2, "power": 400.0},
        light_rgb=(1.0, 0.62, 0.32),
        sensor={"camera_model": "Sony ILCE-7SM2", "cfa_pattern": "RGGB", "electrons": 12.0,
                "lux": 0.024, "k_gain": 5.0},
        note="warm lamp (RGB, not a blackbody), red and green walls"),
    # a sodium-like lamp (little blue) in a room with a blue wall and a yellow one
    "cycles_sodium_room": CyclesScene(
        walls={"left": (0.1, 0.2, 0.6), "right": (0.7, 0.6, 0.1), "back": (0.6, 0.6, 0.6),
               "floor": (0.45, 0.45, 0.45), "floor_checker": (0.2, 0.2, 0.22),
               "back_checker": (0.4, 0.35, 0.3)},
        objects=_OBJECTS, light={"location": [0.5, 0.8, 3.0], "size": 0.8, "power": 450.0},
        light_rgb=(1.0, 0.55, 0.08),
        sensor={"camera_model": "Nikon D850", "cfa_pattern": "GRBG", "electrons": 14.0,
                "lux": 0.028, "k_gain": 5.0},
        note="sodium-like lamp (blue 8 % of red), blue and yellow walls"),
    # a cool LED with a magenta tint, an orange wall
    "cycles_led_studio": CyclesScene(
        walls={"left": (0.75, 0.35, 0.08), "right": (0.6, 0.6, 0.62), "back": (0.5, 0.55, 0.6),
               "floor": (0.35, 0.3, 0.28), "floor_checker": (0.6, 0.55, 0.5),
               "back_checker": (0.3, 0.3, 0.35)},
        objects=_OBJECTS, light={"location": [-0.6, 0.6, 3.1], "size": 1.0, "power": 380.0},
        light_rgb=(0.85, 0.78, 1.0),
        sensor={"camera_model": "Canon EOS 5D Mark IV", "cfa_pattern": "RGGB",
                "electrons": 10.0, "lux": 0.02, "k_gain": 5.5},
        note="cool LED with a magenta tint (RGB), an orange wall"),
}


def arc_poses(n_frames: int, radius: float = 4.6, height: float = 1.5,
              target=(0.0, -0.8, 0.6), span_deg: float = 50.0) -> np.ndarray:
    """(n, 4, 4) OpenGL camera-to-world poses (z up world) on a converging arc in front of
    the room, each looking at `target`."""
    target = np.asarray(target, np.float64)
    poses = []
    for a in np.radians(np.linspace(-span_deg / 2, span_deg / 2, n_frames)):
        pos = np.array([radius * math.sin(a), radius * math.cos(a) - 0.8, height])
        fwd = target - pos
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up, -fwd, pos
        poses.append(pose)
    return np.stack(poses)


def blender_available() -> str | None:
    """The blender executable on PATH, or None."""
    return shutil.which("blender")


def render_views(spec: CyclesScene, poses: np.ndarray, intr: Intrinsics, samples: int,
                 seed: int, workdir: Path) -> np.ndarray:
    """(N, H, W, 3) float32 linear sRGB renders under a white lamp (blender_scene.py)."""
    exe = blender_available()
    if exe is None:
        raise SceneError(None, "Blender is not installed: the Cycles captures need it",
                         "install it (Debian: apt-get install blender) or use the "
                         "procedural scenes")
    settings = {"out": str(workdir), "width": intr.w, "height": intr.h, "samples": samples,
                "seed": seed, "walls": spec.walls, "objects": spec.objects,
                "light": spec.light, "poses": [p.tolist() for p in poses],
                "fov_deg": HFOV_DEG}
    path = workdir / "settings.json"
    path.write_text(json.dumps(settings))
    proc = subprocess.run([exe, "-b", "--factory-startup", "--python-exit-code", "1",
                           "-P", str(SCRIPT), "--", str(path)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SceneError(SCRIPT, "Blender failed: " + proc.stderr.strip()[-400:],
                         "run the command by hand to see Blender's output")
    return np.stack([read_exr(workdir / f"view_{i:03d}.exr")[..., :3]
                     for i in range(len(poses))]).astype(np.float32)


def simulate_cycles(name: str, out_dir, width: int = WIDTH, height: int = HEIGHT,
                    n_frames: int = 24, seed: int = 0, samples: int = SAMPLES,
                    overwrite: bool = False) -> Path:
    """Write the Cycles capture `name` (one of CYCLES) into out_dir (module docstring);
    reused where out_dir already holds it with the same parameters."""
    out = Path(out_dir)
    if name not in CYCLES:
        raise SceneError(out, f"unknown Cycles scene {name!r}", f"choose one of "
                         f"{', '.join(CYCLES)}")
    key = {"version": CYCLES_VERSION, "scene": name, "seed": int(seed), "width": int(width),
           "height": int(height), "n_frames": int(n_frames), "samples": int(samples)}
    manifest = out / "sim.json"
    if manifest.is_file() and not overwrite:
        old = json.loads(manifest.read_text())
        if all(old.get(k) == v for k, v in key.items()):
            return out
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise SceneError(out, "already holds files that are not this Cycles capture",
                         "choose another output folder or pass overwrite=True")
    spec = CYCLES[name]
    params = sensor.SensorParams(**spec.sensor)
    intr = intrinsics(width, height)
    poses = arc_poses(n_frames)
    with tempfile.TemporaryDirectory() as work:
        white = render_views(spec, poses, intr, samples, seed, Path(work))
    light = np.asarray(spec.light_rgb, np.float64)
    light = light / luminance(light)  # the lamp's colour at the white render's luminance
    cam = params.xyz_to_cam @ XYZ_FROM_SRGB  # linear sRGB -> camera RGB
    lit_cam = np.einsum("...j,kj->...k", white * light.astype(np.float32), cam.astype(np.float32))
    gt_scale = writer.GT_MEAN_LUMINANCE / float(luminance(white.reshape(-1, 3).mean(0)))
    e_scale = params.electrons / float(lit_cam[..., 1].mean())
    neutral = cam @ light
    # planar depth of the room's corners from each camera: generous bounds for reference
    corners = np.array([[x, y, z] for x in (-3, 3) for y in (-3, 3) for z in (0, 3.5)], float)
    depth = np.concatenate([-(corners - p[:3, 3]) @ p[:3, 2] for p in poses])
    near_far = [max(float(depth.min()), 0.1), float(depth.max())]

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f"{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir()
        salt = zlib.crc32(name.encode())
        quirks = writer.draw_quirks(params, n_frames, intr.h, intr.w, seed, salt)
        test = writer.write_capture(tmp, params, poses, intr, white, lambda i: lit_cam[i],
                                    e_scale, gt_scale, seed, salt, quirks=quirks)
        names = writer.frame_names(n_frames)
        writer._write_json(tmp / "sim.json", {
            **key, "renderer": "Blender Cycles (blender_scene.py)", "held_out": True,
            "rig": "arc", "note": spec.note, "frames": names,
            "test_frames": [names[i] for i in test],
            "dark_frames": [f"dark/{n}.dng" for n in writer.dark_names()],
            "light_rgb": light.tolist(), "illuminant_kelvin": None,
            "illuminant_neutral_cam": (neutral / neutral[1]).tolist(),
            **writer.sensor_manifest(params, e_scale, gt_scale, near_far, quirks),
            "exposure_convention": (
                "references are the white-lit render (linear sRGB, interreflections kept), "
                "one scale so that the mean luminance over all views is 0.18"),
        })
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out
