"""What the simulator knows and a capture does not: the true noise figures of a simulated
scene and the exact clean raw of its frames (for tests and studies of the noise fit,
gridnerf.noisefit; never for training)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gridnerf import raw
from gridnerf.color import XYZ_FROM_SRGB
from gridnerf.image_io import read_exr
from gridnerf.noisefit import tukey_lambda_variance
from gridnerf.sim import sensor


def noise_truth(sim: dict | str | Path) -> dict:
    """True noise figures of a simulated scene (its sim.json, or the dict), in DN as
    NoiseFit.in_dn gives them: K, read variance = Tukey-lambda + row^2 + 1/12 (rounding),
    read sigma, black offsets (2, 2); and "scale" = white - black."""
    if not isinstance(sim, dict):
        path = Path(sim)
        sim = json.loads((path / "sim.json" if path.is_dir() else path).read_text())
    noise = sim["noise"]
    var = (tukey_lambda_variance(noise["read_tukey_sigma_dn"], noise["read_tukey_lambda"])
           + noise["row_sigma_dn"] ** 2 + 1.0 / 12.0)
    return {"K_dn_per_electron": float(sim["K_dn_per_electron"]), "read_var_dn2": var,
            "read_sigma_dn": math.sqrt(var),
            "black_offset_dn": [list(map(float, r))
                                for r in noise["black_bias_dn_per_cfa_position"]],
            "scale": float(sim["white_level"] - sim["black_level"])}


def raw_noise_var(nt: dict, clean: np.ndarray) -> np.ndarray:
    """(H, W) noise variance of one frame's photosites in normalised raw: K x signal + read
    variance (noise_truth `nt`, in DN) at the clean mean `clean` (H, W; negatives as 0)."""
    return (nt["K_dn_per_electron"] * np.maximum(clean, 0.0) * nt["scale"]
            + nt["read_var_dn2"]) / nt["scale"] ** 2


def binned_noise_var(nt: dict, clean: np.ndarray, cfa: np.ndarray) -> np.ndarray:
    """(H/2, W/2, 3) noise variance of one 2x2-binned frame in normalised raw:
    raw_noise_var binned like the frame (raw.bin2x2), the two greens of a binned pixel
    averaged (half their variance)."""
    var = raw.bin2x2(raw_noise_var(nt, clean), cfa, np.float64)
    var[..., 1] *= 0.5
    return var


def clean_cam(scene_dir) -> Callable[[str], np.ndarray]:
    """For a simulated single-illuminant scene: name -> rgb_cam (H, W, 3), the exact clean
    camera RGB of that frame at every photosite before the colour filter array keeps one
    channel, in normalised raw (no offset), from its reference gt/<name>.exr and sim.json
    (the reference divided by gt_scale is the simulator's clean render; camera response
    under the scene's illuminant, electrons per unit signal, K, white - black; the lens
    falloff and the frame's exposure factor of a quirky camera, not its defects). A
    path-traced capture (gridnerf.sim.cycles: no illuminant_kelvin) lights its white
    render in linear sRGB: camera RGB = xyz_to_cam @ XYZ_FROM_SRGB @ (light_rgb * render)."""
    folder = Path(scene_dir)
    sim = json.loads((folder / "sim.json").read_text())
    if len(sim.get("illuminants", [None])) > 1:
        raise ValueError(f"{folder} is lit by several illuminants; its reference is white "
                         "balanced per light, so the raw signal cannot be rebuilt from it")
    if sim.get("illuminant_kelvin") is None:  # path-traced: the light applied in sRGB
        to_cam = (sensor.SensorParams(camera_model=sim["camera_model"],
                                      crosstalk=float(sim.get("sensor_crosstalk", 0.0))
                                      ).xyz_to_cam
                  @ XYZ_FROM_SRGB)  # as gridnerf.sim.cycles lights its white render
        light = np.asarray(sim["light_rgb"], np.float64)

        def scene_to_cam(rgb_linear: np.ndarray) -> np.ndarray:
            return (rgb_linear * light) @ to_cam.T
    else:
        params = sensor.SensorParams(camera_model=sim["camera_model"],
                                     cfa_pattern=sim["cfa_pattern"],
                                     kelvin=float(sim["illuminant_kelvin"]),
                                     tint_duv=float(sim.get("light_tint_duv", 0.0)),
                                     crosstalk=float(sim.get("sensor_crosstalk", 0.0)))

        def scene_to_cam(rgb_linear: np.ndarray) -> np.ndarray:
            return sensor.scene_to_cam(rgb_linear, params)
    gain = (sim["electrons_per_unit_signal"] * sim["K_dn_per_electron"]
            / (sim["white_level"] - sim["black_level"]) / sim["gt_scale"])

    stops = sim.get("vignetting", {}).get("stops_at_corners", 0.0)
    factor = dict(zip(sim["frames"], sim.get("exposure_jitter", {}).get("factor_per_frame", []),
                      strict=False))

    def cam(name: str) -> np.ndarray:
        rgb_cam = np.maximum(scene_to_cam(read_exr(folder / "gt" / f"{name}.exr")),
                             0.0) * gain
        if stops:
            rgb_cam = rgb_cam * sensor.vignette_gain(*rgb_cam.shape[:2], stops)[..., None]
        return rgb_cam * factor[name] if name in factor else rgb_cam

    return cam


def clean_mean(scene_dir) -> Callable[[str], np.ndarray]:
    """For a simulated single-illuminant scene: name -> the exact clean mean (H, W) of that
    frame in normalised raw (no offset): clean_cam's camera RGB through the colour filter
    array."""
    cam = clean_cam(scene_dir)
    cfa = sensor.SensorParams(
        cfa_pattern=json.loads((Path(scene_dir) / "sim.json").read_text())["cfa_pattern"]).cfa
    return lambda name: sensor.mosaic(cam(name), cfa)
