"""What the data term is fitted against: the black level, the frames' noise, the eps.

Decided once per run by gridnerf.train, before the first step (the fitted offsets: before
the last stage, against the previous stage's field):
- `with_weak_signal_black_level`: the file's black level, or the lens-cap frames' where an
  unknown offset would be a large share of the weakest colour's signal;
- `with_fitted_offsets`: per-CFA black offsets fitted against the field (data.black_offset
  = "fit");
- `data_noise`, `with_data_eps_cap`, `data_eps`, `data_eps_note`: the training frames' noise
  sigma and the data term's eps (RawNeRF's relative MSE, (C - y)^2 / (sg(C) + eps)^2),
  capped at a few sigmas;
- `data_statistics`: the mean level and grey-world gains a grid starts from.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from gridnerf import config as cfgmod
from gridnerf import darkframes, dataset, illuminant, noisefit, runfolder, sensorfit
from gridnerf.config import Config
from gridnerf.errors import GridNerfError

_batch_jit = jax.jit(dataset.batch, static_argnames=("n_patches", "patch"))


def _sample_targets(data: dataset.RayData, key, n_patches: int) -> tuple[np.ndarray, np.ndarray]:
    """Targets and masks (n_patches, 8, 8, 3) of random 8x8 training patches (float64); one
    compile serves data_statistics and data_noise."""
    sample = _batch_jit(data, key, n_patches=n_patches, patch=8)
    return np.asarray(sample["target"], np.float64), np.asarray(sample["mask"], np.float64)


def data_statistics(data: dataset.RayData, key, n_patches: int = 256
                    ) -> tuple[float, np.ndarray, np.ndarray]:
    """Mean target level, grey-world log gains (3,) and mean colour (3,) of the training
    data (masked means over n_patches random 8x8 patches)."""
    y, m = (a.reshape(-1, 3) for a in _sample_targets(data, key, n_patches))
    means = (y * m).sum(0) / np.maximum(m.sum(0), 1.0)
    gains = illuminant.gains_from_illuminant(illuminant.grey_world(y, m), floor=1e-6)
    return float(max(means.mean(), 1e-12)), np.log(gains), means


def with_fitted_offsets(run: Path, data: dataset.RayData, structure, params, scene,
                        cfg: Config) -> dataset.RayData:
    """data with the per-CFA black offsets fitted against the field (sensorfit.fit_field),
    fitted once and kept in <run>/sensor_fit.json (a resumed run reads them back)."""
    b = sensorfit.load_offsets(run)
    if b is None:
        fit = sensorfit.fit_field(structure, params, scene, cfg)
        scale = float(np.mean(scene.white_level - scene.black_level.mean(axis=(1, 2))))
        sensorfit.save(run, fit, scale)
        b = np.asarray(fit.black_offset, np.float64)
        print("black offsets fitted from the noise (DN, CFA order): "
              f"{np.round(b.ravel() * scale, 2).tolist()}")
    return dataclasses.replace(data, black_offset=jnp.asarray(b, jnp.float32))


# The absolute eps starts to cost where it passes this many noise sigmas of the frames
# (data_noise): chosen on bucket's darkness sweep alone (gamma 0.4: eps 3.2 sigma, -0.18 dB
# against gamma 1; 0.6: 2.2 sigma, +0.02), docs/report.md.
EPS_NOTE_SIGMAS = 2.5


def with_weak_signal_black_level(scene, scene_dir, run: Path, cfg: Config):
    """The scene with the black level training uses under data.black_offset = "file".

    The file's black level, except where an unknown black offset of darkframes.OFFSET_DN
    (4 DN) would be more than data.lens_cap_share of the weakest colour's mean signal
    (darkframes.offset_share): there the colour follows the offset (the capture's
    illuminant estimate on held_deep_hall at a tenth of its light came out red > green, no
    light's colour) and, where the scene has lens-cap frames, their offsets are measured,
    kept in <run>/black_level.json (as under "dark": resume and eval read them,
    runfolder.lens_cap_black) and applied; without lens-cap frames, or with frames that
    cannot serve (darkframes.measure's SceneError), training warns and keeps the file's
    black level. One line either way; a note naming data.black_offset=dark where the gate
    does not bind but the scene has lens-cap frames. Decided on a fresh start only: a run
    that keeps its offsets, or has a checkpoint without them, is returned as loaded.
    """
    if (cfg.data.black_offset != "file" or darkframes.load(run) is not None
            or (run / runfolder.CHECKPOINT).exists()):
        return scene
    signal = darkframes.signal_dn(scene)
    has_dark = darkframes.has_dark_frames(scene_dir)
    if not darkframes.too_weak(signal, cfg.data.lens_cap_share):
        if has_dark:
            print(f"note: {Path(scene_dir) / darkframes.DARK_DIR} has lens-cap frames; "
                  "--set data.black_offset=dark uses them for the black level (docs/colour.md)")
        return scene
    what = (f"the weakest colour's mean signal is {float(np.min(signal)):.1f} DN above the "
            f"file's black level: an unknown black offset of {darkframes.OFFSET_DN:g} DN "
            f"would be {darkframes.offset_share(signal):.0%} of it (data.lens_cap_share "
            f"{cfg.data.lens_cap_share:g})")
    if not has_dark:
        print(f"warning: {what}, and the colour would follow it; shoot 1-4 frames with the "
              f"lens cap on at the capture's ISO and exposure time into "
              f"{Path(scene_dir) / darkframes.DARK_DIR} (used automatically), or try "
              "--set data.black_offset=fit")
        return scene
    try:
        measured = darkframes.measure(scene_dir)
    except GridNerfError as err:  # e.g. a frame in dark/ of another size or lit
        print(f"warning: {what}, but the lens-cap frames cannot serve ({err}); training "
              "with the file's black level")
        return scene
    darkframes.save(run, measured)
    print(f"black level from the lens-cap frames, since {what}: offsets (DN, CFA order) "
          f"{np.round(np.ravel(measured['offset_dn']), 2).tolist()}")
    return darkframes.apply(scene, measured["offset_dn"])


def data_noise(data: dataset.RayData, key, n_patches: int = 256) -> float:
    """Noise sigma of the training targets (noisefit.neighbour_sigma of n_patches random
    8x8 patches), nan where no two neighbours share a valid channel."""
    return noisefit.neighbour_sigma(*_sample_targets(data, key, n_patches))


def data_eps(cfg: Config, color_scale: float) -> float:
    """The data term's eps in normalised raw: loss.data_eps, times the training data's mean
    level (color_scale) with loss.data_eps_mode = "level"."""
    lc = cfg.loss
    return lc.data_eps * (color_scale if lc.data_eps_mode == "level" else 1.0)


def with_data_eps_cap(cfg: Config, sigma: float) -> Config:
    """The config the steps train with: loss.data_eps lowered to loss.data_eps_sigmas x
    sigma (the training frames' noise, data_noise) where it is above that, the eps is
    absolute and the targets are raw; else cfg itself (also where sigma is 0 or nan, or
    data_eps_sigmas is 0).

    The data term (C - y)^2 / (sg(C) + eps)^2 depends on eps / sigma alone: a raw scaled by
    gamma (data.exposure_ratio) scales C, y and sigma alike, so at a fixed ratio it is the
    same fit. RawNeRF's 1e-3 is 0.86-1.44 sigma on every simulated scene at gamma 1; at
    gamma 0.1 it is 13 sigma on bucket (-5.4 dB), where the cap trains it as at 2 sigma.
    """
    lc = cfg.loss
    cap = lc.data_eps_sigmas * sigma
    if not (cfgmod.eps_follows_noise(cfg) and cap > 0 and lc.data_eps > cap):  # nan: False
        return cfg
    return dataclasses.replace(cfg, loss=dataclasses.replace(lc, data_eps=float(cap)))


def data_eps_note(cfg: Config, sigma: float) -> str | None:
    """A note where the absolute loss.data_eps the steps use is above EPS_NOTE_SIGMAS x the
    training frames' noise sigma (data_noise), else None (also where sigma is 0 or nan).
    cfg: the steps' config (with_data_eps_cap's), so with the default cap (2 sigmas) it
    is silent; it speaks where loss.data_eps_sigmas is 0 or above EPS_NOTE_SIGMAS.

    There the data term stops weighing pixels by their own noise and the fit depends on the
    raw's scale. The darkness sweeps (docs/report.md) lose, at the same absolute eps, alike
    on scenes whose mean levels differ 2.3x but whose noise is alike: gamma 0.4 (eps 2.7-3.2
    sigma) -0.18 / -0.47 / -0.39 dB on bucket / held_deep_hall / held_mixed_toys, gamma 0.1
    4.0-5.4 dB.
    """
    lc = cfg.loss
    if (not cfgmod.eps_follows_noise(cfg) or not sigma > 0  # noiseless or unmeasured: no note
            or not lc.data_eps > EPS_NOTE_SIGMAS * sigma):
        return None
    return (f"note: the data eps {lc.data_eps:g} is {lc.data_eps / sigma:.1f}x the noise sigma "
            f"{sigma:.2g} of the training frames (a very dark or low-gain capture): the fit "
            "depends on the raw's scale here; --set loss.data_eps_sigmas=2 (the default) caps "
            "it at 2 sigmas (docs/report.md, darkness sweep)")
