"""simulate_scene: render a procedural scene and write an LMRAW-like scene folder.

Folder layout (the contract every loader follows):
  raw/<name>.dng       noisy dark RAW frames frame_000 ... (16-bit DNG container; black 512,
                       white 16383 for the default 14-bit sensor, 256 / 4095 at 12 bits,
                       64 / 1023 at 10; ExposureTime per frame)
  images/<name>.jpg    camera-style previews of the dark frames (for pose estimation)
  transforms.json      nerfstudio cameras (OpenGL camera-to-world) and the train/test
                       split (every 8th frame is test). No scene bounds: a trainer must
                       find near/far itself, as with a real capture
  gt/<name>.exr|.png   clean normal-light references (linear float32 / sRGB 8-bit)
  dark/dark_000.dng ...  lens-cap frames (no light) at the frames' ISO and exposure time:
                       a dark-frame calibration a photographer can shoot with the capture.
                       Only `data.black_offset=dark` reads them (gridnerf.darkframes);
                       by default the trainer sees raw/ alone
  illuminant/<name>.png  mixed-light scenes only: 8-bit map of the first illuminant's share
                       of the camera green signal per pixel (255 = all of it)
  sim.json             manifest, written LAST (its presence marks a complete scene);
                       it keeps the true "near_far" (min/max z-depth over all rendered
                       sub-rays) and the camera "rig" for reference only

Exposure convention of the references: they are linear sRGB (the scene's
reflectance x shading as if lit by D65, no noise), multiplied by ONE scale factor per
scene chosen so that the mean luminance (color.luminance) over all views is 0.18.
The EXR stores that linear image unclipped; the PNG is srgb_encode(clip(., 0, 1)).

A camera's quirks (sensor.SensorParams: bits, vignette_stops, exposure_jitter_stops,
hot_pixels; all off by default, and then nothing about them is drawn or written) are
recorded in sim.json: "bits", "vignetting" (model and parameters), "exposure_jitter" (each
frame's exposure time) and "defects" (the positions and values of the hot and stuck
photosites). Vignetting darkens raw/ only; the references in gt/ stay the scene's
radiance, and the lens-cap frames see no light. The converter's tags
(sensor.SensorParams.converter: crop margin, orientation, falloff opcode, BaselineExposure;
gridnerf.sim.converter) change how raw/ and dark/ store the same view ("converter_tags").

The folder is built in `<out_dir>.tmp-<pid>` and renamed into place at the end, so a
half-written scene never looks valid.
"""

from __future__ import annotations

import json
import os
import shutil
import zlib
from dataclasses import replace
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from gridnerf import atomic
from gridnerf.color import luminance, srgb_encode
from gridnerf.dng import MIN_SIZE, write_dng
from gridnerf.errors import SceneError
from gridnerf.image_io import write_exr, write_png
from gridnerf.sim import converter, sensor
from gridnerf.sim.capture import (
    HFOV_DEG,
    camera_path,
    intrinsics,
    render_view,
    render_view_layers,
)
from gridnerf.sim.scenes import ALL_SCENES, HELDOUT, HELDOUT_MIXED, HELDOUT_QUIRK, build_scene

# Scene-folder format version, part of the cache key: bump it whenever the written
# files change so that folders written before are rebuilt. 2: camera rigs, held-out
# scenes, no near_far in transforms.json. 3: dark/ lens-cap frames (raw/ unchanged).
SIM_VERSION = 3
N_DARK = 2  # lens-cap frames per scene
GT_MEAN_LUMINANCE = 0.18
SSAA = 2  # sub-rays per pixel side (pixel-area integration)
TEST_EVERY = 8
JPEG_QUALITY = 90
EXPOSURE_CONVENTION = (
    "references are linear sRGB (reflectance x shading under D65, no noise); one scale "
    "factor per scene so that the mean luminance (color.luminance) over all views is 0.18; "
    "EXR unclipped, PNG = srgb_encode(clip(x, 0, 1))"
)


def folder_name(name: str, light: float = 1.0) -> str:
    """The default folder name of scene `name` simulated at `light` (simulate_scene):
    the name itself at the scene's own photon budget, `<name>_light<f>` below or above it."""
    return name if light == 1.0 else f"{name}_light{light:g}"


def frame_names(n_frames: int) -> list[str]:
    """Frame stems: frame_000, frame_001, ..."""
    return [f"frame_{i:03d}" for i in range(n_frames)]


def dark_names() -> list[str]:
    """Lens-cap frame stems: dark_000, dark_001, ..."""
    return [f"dark_{j:03d}" for j in range(N_DARK)]


def _key(name: str, width: int, height: int, n_frames: int, seed: int,
         light: float = 1.0) -> dict:
    return {"version": SIM_VERSION, "scene": name, "seed": int(seed), "width": int(width),
            "height": int(height), "n_frames": int(n_frames), "light": float(light)}


def _manifest_key(manifest: dict, key: dict) -> dict:
    """The manifest's values of `key`'s fields; a manifest written before `light` existed
    was written at light 1."""
    return {k: manifest.get(k, 1.0 if k == "light" else None) for k in key}


def _read_manifest(out: Path) -> dict | None:
    try:
        manifest = json.loads((out / "sim.json").read_text())
    except (OSError, ValueError):
        return None
    return manifest if isinstance(manifest, dict) else None


def _is_stale(out: Path, key: dict) -> bool:
    """True when out/sim.json is this simulator's manifest for the same scene and
    parameters written by another SIM_VERSION (so the folder is ours to rebuild)."""
    manifest = _read_manifest(out)
    if manifest is None or manifest.get("version") == key["version"]:
        return False
    found = _manifest_key(manifest, key)
    return all(found[k] == v for k, v in key.items() if k != "version")


def _is_complete(out: Path, key: dict) -> bool:
    """True when out/sim.json matches `key` and every listed file exists."""
    manifest = _read_manifest(out)
    if manifest is None or _manifest_key(manifest, key) != key:
        return False
    names = frame_names(key["n_frames"])
    files = ["transforms.json"] + [f"{d}/{n}.{e}" for n in names
                                   for d, e in (("raw", "dng"), ("images", "jpg"),
                                                ("gt", "exr"), ("gt", "png"))]
    files += [f"dark/{n}.dng" for n in dark_names()]
    return all((out / f).is_file() for f in files)


def _write_json(path: Path, data: dict) -> None:
    atomic.write_text(path, json.dumps(data, indent=2) + "\n")


def _render_all(spec, poses, intr):
    """Clean renders of every view: rgb_linear (N, H, W, 3) float32 and [near, far]."""
    frames = np.zeros((len(poses), intr.h, intr.w, 3), np.float32)
    near, far = np.inf, 0.0
    for i, c2w in enumerate(poses):
        frames[i], depth = render_view(spec, c2w, intr, ssaa=SSAA)
        finite = depth[np.isfinite(depth)]
        if finite.size:
            near, far = min(near, float(finite.min())), max(far, float(finite.max()))
    return frames, [near, far]


def _render_layers(spec, poses, intr):
    """Light-by-light renders of every view: layers (N, L, H, W, 3), irradiance
    (N, H, W, L) float32 and [near, far]."""
    n = len(spec.kelvins)
    layers = np.zeros((len(poses), n, intr.h, intr.w, 3), np.float32)
    irradiance = np.zeros((len(poses), intr.h, intr.w, n), np.float32)
    near, far = np.inf, 0.0
    for i, c2w in enumerate(poses):
        layers[i], irradiance[i], depth = render_view_layers(spec, c2w, intr, ssaa=SSAA)
        finite = depth[np.isfinite(depth)]
        if finite.size:
            near, far = min(near, float(finite.min())), max(far, float(finite.max()))
    return layers, irradiance, [near, far]


def _mixed_light(spec, layers, irradiance):
    """Camera signal per view (N, H, W, 3) of a layered scene, its mean green, the
    per-pixel share of the first illuminant in camera green (N, H, W) and the manifest's
    illuminant entries (each light's kelvin, neutral, share of the green signal) and the
    signal-weighted global neutral."""
    lights = [replace(spec.sensor, kelvin=k) for k in spec.kelvins]
    to_cam = [sensor.cam_from_scene(p) for p in lights]
    white = np.stack([m @ np.ones(3) for m in to_cam])  # (L, 3) cam RGB of white per light
    rgb_cam = sum(np.einsum("n...j,kj->n...k", layers[:, i], m.astype(np.float32))
                  for i, m in enumerate(to_cam))
    green = irradiance.astype(np.float64) * white[:, 1]  # (N, H, W, L) green per light
    total = green.sum(-1)
    share = np.where(total > 0, green[..., 0] / np.maximum(total, 1e-30), 0.0)
    signal = green.reshape(-1, len(lights)).sum(0)
    frac = signal / max(signal.sum(), 1e-30)
    mixed = (frac[:, None] * white / white[:, 1:2]).sum(0)
    entries = [{"kelvin": p.kelvin, "neutral_cam": (w / w[1]).tolist(),
                "share_of_green_signal": float(f)}
               for p, w, f in zip(lights, white, frac, strict=True)]
    mean_layers = layers.reshape(len(layers), len(lights), -1, 3).mean(axis=(0, 2),
                                                                      dtype=np.float64)
    mean_green = float(sum(m[1] @ ml for m, ml in zip(to_cam, mean_layers, strict=True)))
    return rgb_cam, mean_green, share, entries, (mixed / mixed[1]).tolist()


def _build(folder: Path, name: str, width: int, height: int, n_frames: int, seed: int,
           light: float = 1.0) -> None:
    spec = build_scene(name)
    if light != 1.0:  # fewer photons: the same camera settings, a darker scene
        dimmer = replace(spec.sensor, electrons=spec.sensor.electrons * light,
                         lux=spec.sensor.lux * light)
        spec = replace(spec, sensor=dimmer)
    params = spec.sensor
    salt = capture_salt(spec)
    intr = intrinsics(width, height)
    poses = camera_path(spec, n_frames, np.random.default_rng([seed, salt, 0]))
    if spec.layered:
        layers, irradiance, near_far = _render_layers(spec, poses, intr)
        frames = layers.sum(axis=1)  # every light white balanced: the colour-constant view
        rgb_cams, mean_green, share, lights, neutral = _mixed_light(spec, layers, irradiance)
        del layers, irradiance
    else:
        frames, near_far = _render_all(spec, poses, intr)

    mean_rgb_linear = frames.reshape(-1, 3).mean(axis=0, dtype=np.float64)
    gt_scale = GT_MEAN_LUMINANCE / float(luminance(mean_rgb_linear))
    if not spec.layered:
        mean_green = float(sensor.cam_from_scene(params)[1] @ mean_rgb_linear)
    e_scale = params.electrons / mean_green  # electrons per unit of relative camera signal

    names = frame_names(n_frames)
    quirks = draw_quirks(params, n_frames, height, width, seed, salt)
    test = write_capture(folder, params, poses, intr, frames,
                         (lambda i: rgb_cams[i]) if spec.layered
                         else (lambda i: sensor.scene_to_cam(frames[i], params)),
                         e_scale, gt_scale, seed, salt, share if spec.layered else None,
                         quirks=quirks)
    mixed = {}
    if spec.layered:
        mixed = {
            "illuminants": lights,
            "illuminant_note": (
                "several illuminants: illuminant_neutral_cam is their mix weighted by each "
                "one's share of the camera green signal (what one global gain should undo), "
                "illuminant_kelvin the strongest one's; illuminant/<frame>.png holds per "
                "pixel round(255 * share of the first illuminant in camera green); the "
                "references white balance every light (as if each were D65)"),
        }
        main = max(lights, key=lambda e: e["share_of_green_signal"])
    _write_json(folder / "sim.json", {
        **_key(name, width, height, n_frames, seed, light),
        "held_out": name in HELDOUT + HELDOUT_MIXED + HELDOUT_QUIRK, "rig": spec.rig,
        **({"twin_of": spec.twin_of} if spec.twin_of else {}),
        **({"mixed_light": True} if spec.layered else {}),
        "frames": names, "test_frames": [names[i] for i in test],
        "dark_frames": [f"dark/{n}.dng" for n in dark_names()],
        "illuminant_kelvin": main["kelvin"] if spec.layered else params.kelvin,
        "illuminant_neutral_cam": (neutral if spec.layered
                                   else sensor.illuminant_neutral(params).tolist()),
        **mixed,
        **sensor_manifest(params, e_scale, gt_scale, near_far, quirks),
        **converter.manifest(params.converter, (height, width), sensor.vignette_coefficient(
            params.vignette_stops) if params.vignette_stops else None),
    })


def capture_salt(spec) -> int:
    """The salt of a scene's random streams (camera path, noise, quirks): crc32 of its
    name, or of the scene it re-shoots (spec.twin_of), whose cameras it then shares."""
    return zlib.crc32((spec.twin_of or spec.name).encode())


def draw_quirks(params, n_frames: int, height: int, width: int, seed: int,
                salt: int) -> tuple[np.ndarray, sensor.Defects | None]:
    """A capture's per-frame exposure factors (N,) (sensor.exposure_factors) and its
    sensor's defects (sensor.draw_defects, or None), each from a stream of its own
    ([seed, salt, 3] and [seed, salt, 4]): at the defaults nothing is drawn, and the
    frames' noise streams are the same whatever the quirks."""
    factors = sensor.exposure_factors(params, n_frames, np.random.default_rng([seed, salt, 3]))
    defects = sensor.draw_defects(params, height, width, np.random.default_rng([seed, salt, 4]))
    return factors, defects


def write_capture(folder: Path, params, poses, intr, frames, rgb_cam_of, e_scale: float,
                  gt_scale: float, seed: int, salt: int, share=None,
                  quirks=None) -> list[int]:
    """Write a capture's files (all but sim.json) into `folder`: raw/ (noisy DNGs),
    images/ (previews), gt/ (references: frames (N, H, W, 3) linear sRGB times gt_scale),
    dark/ (lens-cap frames), transforms.json (poses (N, 4, 4), intr), and illuminant/
    where `share` (N, H, W) is given. rgb_cam_of(i): the clean camera signal (H, W, 3) of
    view i, times e_scale electrons. quirks: draw_quirks's (factors (N,), defects), drawn
    here when None; frame i's electrons are times sensor.vignette_gain and factors[i], its
    ExposureTime params.exposure_time * factors[i]; the defects are in every raw/ and dark/
    frame (dark/ ExposureTime: the first frame's), concealed in the previews as a camera's
    JPEG engine would (sensor.conceal_defects). raw/ and dark/ store the frames as
    params.converter asks (gridnerf.sim.converter: turned, padded, tagged; nothing at the
    defaults); images/ and transforms.json stay the view as displayed. Returns the test
    views' indices."""
    n_frames = len(poses)
    height, width = intr.h, intr.w
    names = frame_names(n_frames)
    factors, defects = (quirks if quirks is not None
                        else draw_quirks(params, n_frames, height, width, seed, salt))
    falloff = (sensor.vignette_gain(height, width, params.vignette_stops)
               if params.vignette_stops else None)  # (H, W) on the electrons
    tags = params.converter  # the converter's tags: the files store the view turned, padded
    c = sensor.vignette_coefficient(params.vignette_stops) if params.vignette_stops else None

    def write_raw(path, raw_bayer, neutral, time, rng_key, frame):
        """One DNG of the displayed raw_bayer (H, W), stored as params.converter asks; the
        crop margin's photosites from the stream [seed, salt, *rng_key]."""
        cfa, margin = params.cfa, None
        if any(tags.crop_margin):
            margin = sensor.expose(np.zeros(converter.stored_shape((height, width), tags)),
                                   params, np.random.default_rng([seed, salt, *rng_key]))
        if not tags.is_default:
            raw_bayer, cfa = converter.stored(raw_bayer, params.cfa, tags, margin)
        write_dng(path, raw_bayer, cfa, black, params.white_level, params.file_xyz_to_cam,
                  neutral, exposure_time=time, iso=params.iso,
                  camera_model=params.camera_model,
                  **converter.dng_kwargs(tags, (height, width), c, frame))

    for sub in ("raw", "images", "gt", "dark", *(("illuminant",) if share is not None else ())):
        (folder / sub).mkdir(parents=True)
    black = np.full((2, 2), float(params.black_level))
    for i, stem in enumerate(names):
        if share is not None:
            iio.imwrite(folder / "illuminant" / f"{stem}.png",
                        np.round(255.0 * share[i]).astype(np.uint8), extension=".png")
        rgb_cam = rgb_cam_of(i)
        electrons = sensor.mosaic(rgb_cam, params.cfa) * e_scale
        if falloff is not None:
            electrons = electrons * falloff
        if factors[i] != 1.0:
            electrons = electrons * factors[i]
        raw_bayer = sensor.expose(electrons, params, np.random.default_rng([seed, salt, 1, i]),
                                  defects)
        write_raw(folder / "raw" / f"{stem}.dng", raw_bayer, sensor.grey_world_neutral(rgb_cam),
                  float(params.exposure_time * factors[i]), (5, i), i)
        preview = sensor.preview_srgb(sensor.conceal_defects(raw_bayer, defects), params.cfa,
                                      black, params.white_level, params.xyz_to_cam)
        iio.imwrite(folder / "images" / f"{stem}.jpg", sensor.to_uint8(preview),
                    extension=".jpg", quality=JPEG_QUALITY)
        rgb_linear = frames[i] * np.float32(gt_scale)
        write_exr(folder / "gt" / f"{stem}.exr", rgb_linear)
        write_png(folder / "gt" / f"{stem}.png", srgb_encode(np.clip(rgb_linear, 0.0, 1.0)))

    # lens cap on: no electrons, same sensor, the first frame's exposure time (with
    # auto-exposure jitter: as if locked after it; the dark signal does not depend on it)
    for j, stem in enumerate(dark_names()):
        raw_bayer = sensor.expose(np.zeros((height, width)), params,
                                  np.random.default_rng([seed, salt, 2, j]), defects)
        write_raw(folder / "dark" / f"{stem}.dng", raw_bayer, np.ones(3),
                  float(params.exposure_time * factors[0]), (6, j), 0)

    test = [i for i in range(n_frames) if i % TEST_EVERY == 0]
    paths = [f"raw/{stem}.dng" for stem in names]
    _write_json(folder / "transforms.json", {
        "camera_model": "OPENCV", "fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx,
        "cy": intr.cy, "w": intr.w, "h": intr.h, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": [{"file_path": p, "transform_matrix": pose.tolist()}
                   for p, pose in zip(paths, poses, strict=True)],
        "train_filenames": [p for i, p in enumerate(paths) if i not in test],
        "test_filenames": [paths[i] for i in test],
    })
    return test


def sensor_manifest(params, e_scale: float, gt_scale: float, near_far,
                    quirks=None) -> dict:
    """sim.json's entries on the sensor, the noise, the references and the bounds; noise
    figures in DN of the file's bit depth. quirks: draw_quirks's (factors, defects), whose
    values are recorded where the sensor has those quirks."""
    scale = params.dn_scale
    return {
        "lux": params.lux, "exposure_time_s": params.exposure_time, "iso": params.iso,
        "electrons_mean_green": params.electrons, "electrons_per_unit_signal": e_scale,
        "K_dn_per_electron": params.k_gain * scale,
        "noise": {"model": "K*Poisson(e) + TukeyLambda + row + bias, rounded",
                  "read_tukey_sigma_dn": params.read_sigma * scale,
                  "read_tukey_lambda": params.tl_lambda,
                  "row_sigma_dn": params.row_sigma * scale,
                  "black_bias_dn_per_cfa_position": [[b * scale for b in r]
                                                     for r in params.bias]},
        "black_level": params.black_level, "white_level": params.white_level,
        **quirks_manifest(params, quirks),
        "camera_model": params.camera_model, "cfa_pattern": params.cfa_pattern,
        "cfa": params.cfa.tolist(), "xyz_to_cam": params.xyz_to_cam.tolist(),
        # where the file's ColorMatrix or the light breaks the colour path's assumptions
        **({"file_matrix": params.file_matrix,
            "file_xyz_to_cam": params.file_xyz_to_cam.tolist(),
            "light_tint_duv": params.tint_duv}
           if params.file_matrix != "sensor" or params.tint_duv else {}),
        **({"sensor_crosstalk": params.crosstalk} if params.crosstalk else {}),
        "hfov_deg": HFOV_DEG, "ssaa": SSAA, "near_far": near_far,
        "near_far_note": "true bounds for reference only; not in transforms.json",
        "depth_convention": "z-depth along the camera's -z axis, world units",
        "exposure_convention": EXPOSURE_CONVENTION, "gt_scale": gt_scale,
        "gt_mean_luminance": GT_MEAN_LUMINANCE,
    }


def quirks_manifest(params, quirks=None) -> dict:
    """sim.json's entries on the camera's quirks ({} for a clean camera): "bits",
    "vignetting", "exposure_jitter" (each frame's exposure time, from quirks' factors) and
    "defects" (hot and stuck photosites as [x, y, DN], from quirks' defects)."""
    factors, defects = quirks if quirks is not None else (None, None)
    out: dict = {}
    if params.bits != 14:
        out["bits"] = params.bits
        out["bits_note"] = (
            "the 14-bit capture's photon statistics quantised coarser: K, read and row "
            f"noise and bias are the 14-bit figures times 2**(bits - 14) = {params.dn_scale:g}; "
            "black level 512 / 256 / 64 at 14 / 12 / 10 bits, white level 2**bits - 1")
    if params.vignette_stops:
        c = sensor.vignette_coefficient(params.vignette_stops)
        out["vignetting"] = {
            "model": "gain(r) = 1 / (1 + c r^2)^2 (cos^4 law), r = distance from the image "
                     "centre / distance from the centre to a corner; on the electrons of "
                     "raw/ only (not gt/, not dark/), " + (
                         "undone by the files' FixVignetteRadial (converter_tags)"
                         if params.converter.vignette_opcode else "no correction in the files"),
            "stops_at_corners": params.vignette_stops, "c": c,
            "fix_vignette_radial_k": [2.0 * c, c * c, 0.0, 0.0, 0.0],
        }
    if params.exposure_jitter_stops:
        out["exposure_jitter"] = {
            "model": "frame exposure time = exposure_time_s * 2**u, u uniform in "
                     "[-stops, +stops] per frame, the frame's electrons scaled alike (DNG "
                     "ExposureTime); dark/ frames at the first frame's exposure time",
            "stops": params.exposure_jitter_stops,
            **({"factor_per_frame": [float(f) for f in factors],
                "exposure_time_s_per_frame": [float(params.exposure_time * f)
                                              for f in factors]}
               if factors is not None else {}),
        }
    if params.hot_pixels:
        out["defects"] = {
            "model": "photosites fixed over the capture (raw/ and dark/): hot ones add a "
                     "constant (clipped at the white level), stuck ones read a constant",
            "count": int(params.hot_pixels),
            **({"hot_xy_dn": [[int(x), int(y), float(v)] for (y, x), v
                              in zip(defects.hot_yx, defects.hot_dn, strict=True)],
                "stuck_xy_dn": [[int(x), int(y), float(v)] for (y, x), v
                                in zip(defects.stuck_yx, defects.stuck_dn, strict=True)]}
               if defects is not None else {}),
        }
    return out


def simulate_scene(name: str, out_dir, width: int = 480, height: int = 270,
                   n_frames: int = 24, seed: int = 0, overwrite: bool = False,
                   light: float = 1.0) -> Path:
    """Write scene `name` (one of ALL_SCENES) into out_dir; returns out_dir.

    light: the photon budget as a fraction of the scene's own (its mean green electrons
    and nominal lux times `light`), camera settings (ISO, exposure time, read noise, black
    level offsets) unchanged: a physically darker capture, where shot noise shrinks as
    sqrt(light) against a fixed read noise, unlike a raw scaled after capture
    (`data.exposure_ratio`), where signal and every noise shrink alike. Same seed, same
    random draws: the frames of two light levels differ by the photon count alone.

    If out_dir already holds a complete scene written with the same parameters
    (checked against the `sim.json` manifest, written last), it is reused and
    returned at once; `overwrite=True` rebuilds it anyway. The same scene written by
    an older SIM_VERSION is rebuilt. A folder holding anything else is only replaced
    with `overwrite=True`. The scene is built in
    `<out_dir>.tmp-<pid>` and renamed at the end. Deterministic for a seed.
    """
    out = Path(out_dir)
    if name not in ALL_SCENES:
        raise SceneError(out, f"unknown simulated scene {name!r}",
                         f"choose one of {', '.join(ALL_SCENES)}")
    if min(width, height) < MIN_SIZE or n_frames < 1:
        raise SceneError(out, f"cannot simulate {width}x{height} with {n_frames} frames",
                         f"use width and height of at least {MIN_SIZE} pixels (LibRaw's "
                         "minimum) and at least 1 frame")
    if not (np.isfinite(light) and 0.0 < light <= 1e3):
        raise SceneError(out, f"cannot simulate at light {light!r}",
                         "use a photon budget fraction in (0, 1000], e.g. 0.25")
    key = _key(name, width, height, n_frames, seed, light)
    if out.exists():
        if not out.is_dir():
            raise SceneError(out, "exists and is not a folder", "choose another output folder")
        if not overwrite and _is_complete(out, key):
            return out
        if not overwrite and not _is_stale(out, key) and any(out.iterdir()):
            raise SceneError(out, "already holds files that are not this simulated scene "
                             f"({name}, {width}x{height}, {n_frames} frames, seed {seed}"
                             + (f", light {light:g}" if light != 1.0 else "") + ")",
                             "choose another output folder, delete this one, or pass "
                             "overwrite=True to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f"{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _build(tmp, name, width, height, n_frames, seed, light)
        # If another process finished the same scene meanwhile, keep its copy (tmp is removed).
        finished_elsewhere = out.exists() and not overwrite and _is_complete(out, key)
        if finished_elsewhere:
            return out
        if out.exists():
            old = out.with_name(f"{out.name}.old-{os.getpid()}")
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out
