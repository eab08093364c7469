"""What the data term is fitted against: the black level, the frames' noise, the eps.

Decided once per run by gridnerf.train, before the first step, and kept in the run plan
(gridnerf.plan):
- `black_level`: the file's black level, or the lens-cap frames' where the capture has
  them and they show the file's off (or data.black_offset = "dark");
- `data_noise`, `capped_eps`, `data_eps_note`: the training frames' noise sigma and the
  data term's eps (RawNeRF's relative MSE, (C - y)^2 / (sg(C) + eps)^2), capped at a few
  sigmas;
- `data_statistics`: the mean level and grey-world gains a grid starts from;
- `photosite_snr`, `planned_mosaic_stages`: the frames' photons per green photosite and
  whether the last stages fit the raw mosaic (data.mosaic_stages) or stay binned;
- `planned_downscale`, `fitted_config`: how far the binned frames are box-downscaled, from
  the capture's pixels per voxel of the final grid.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import jax
import numpy as np

from gridnerf import darkframes, dataset, illuminant, noisefit
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


# The absolute eps starts to cost where it passes this many noise sigmas of the frames
# (data_noise): chosen on bucket's darkness sweep alone (gamma 0.4: eps 3.2 sigma, -0.18 dB
# against gamma 1; 0.6: 2.2 sigma, +0.02), docs/results.md.
EPS_NOTE_SIGMAS = 2.5


# where an unknown black offset of darkframes.OFFSET_DN (4 DN, the ELD model's largest)
# would be more than this share of the weakest colour's mean signal and the capture has no
# lens-cap frames, training warns that the colour will follow the offset. At their own
# light the simulated scenes sit at 0.08-0.45 (held_deep_hall the highest)
LENS_CAP_SHARE = 0.5
# the lens-cap frames replace the file's black level where the offset they measure is more
# than this share of some colour's mean signal (darkframes.offset_shift): a 1 % shift of a
# colour's mean moves the gains by about 0.01 in log chromaticity, a ninth of the
# estimate's mean error from the light (0.086 on the 32 simulated scenes), so below it the
# correction cannot matter; in the dark parts of a frame the same offset is a larger share.
# The simulated captures: 0.2-0.4 % on the three path-traced ones, 1.4-23 % on the others
OFFSET_MATTERS = 0.01


def black_level(scene_dir, run: Path, cfg: Config, scene) -> str:
    """The black level a fresh run's frames take: "lens_cap" (the file's plus the offsets
    measured from <scene>/dark/, kept in <run>/black_level.json: darkframes.measure/save)
    or "file".

    data.black_offset = "file" (the default): the file's, checked against the lens-cap
    frames wherever the capture has them. A sensor's dark signal sits a few DN off the
    file's tag per CFA position: a cast of the dark parts and a shift of every illuminant
    estimate. Where the offsets the frames measure are more than OFFSET_MATTERS of some
    colour's mean signal (darkframes.offset_shift), the tag contradicts the pixels and the
    lens-cap level is taken (on every simulated scene; held_deep_hall 19.22 -> 21.22 dB,
    docs/results.md, "Black level"). Lens-cap frames that cannot serve (another size,
    lit): one warning naming the frame, and the file's. Without lens-cap frames, where an
    unknown offset of darkframes.OFFSET_DN would be more than LENS_CAP_SHARE of the
    weakest colour's mean signal (darkframes.offset_share), training warns: the colour
    follows the offset there (held_deep_hall at a tenth of its light: its illuminant
    estimate came out red > green, no light's colour). "dark": the lens-cap frames,
    SceneError where they cannot serve. One line whenever lens-cap frames are there or
    wanted. scene: the scene with the file's black level (not read under "dark", which
    measures before the scene loads).
    """
    if cfg.data.black_offset == "dark":
        measured = darkframes.measure(scene_dir)
        darkframes.save(run, measured)
        print("black level from the lens-cap frames: offsets (DN, CFA order) "
              f"{np.round(np.ravel(measured['offset_dn']), 2).tolist()}")
        return "lens_cap"
    where = Path(scene_dir) / darkframes.DARK_DIR
    if not darkframes.has_dark_frames(scene_dir):
        signal = darkframes.signal_dn(scene)
        if darkframes.too_weak(signal, LENS_CAP_SHARE):
            print(f"warning: the weakest colour's mean signal is {float(np.min(signal)):.1f} "
                  f"DN above the file's black level: an unknown black offset of "
                  f"{darkframes.OFFSET_DN:g} DN would be {darkframes.offset_share(signal):.0%} "
                  "of it, and the colour would follow it; shoot 1-4 frames with the lens cap "
                  f"on at the capture's ISO and exposure time into {where} (used automatically)")
        return "file"
    try:
        measured = darkframes.measure(scene_dir)
    except GridNerfError as err:  # e.g. a frame in dark/ of another size or lit
        print(f"warning: the lens-cap frames cannot serve ({err}); training with the file's "
              "black level")
        return "file"
    matters, shift = offsets_matter(measured["offset_dn"], scene)
    offsets = np.round(np.ravel(measured["offset_dn"]), 2).tolist()
    if not matters:
        print(f"black level: the file's (the lens-cap frames in {where} measure offsets "
              f"{offsets} DN, at most {shift:.1%} of a colour's mean signal)")
        return "file"
    darkframes.save(run, measured)
    print(f"black level from the lens-cap frames in {where}: offsets (DN, CFA order) "
          f"{offsets}, up to {shift:.0%} of a colour's mean signal off the file's")
    return "lens_cap"


def offsets_matter(offset_dn, scene) -> tuple[bool, float]:
    """(whether offsets measured by lens-cap frames replace the file's black level, the
    share of a colour's mean signal they move it by: darkframes.offset_shift against the
    scene's signal above the file's level). offset_dn: (2, 2) of darkframes.measure."""
    shift = darkframes.offset_shift(offset_dn, scene.cfa, darkframes.signal_dn(scene))
    return shift > OFFSET_MATTERS, shift


def data_noise(data: dataset.RayData, key, n_patches: int = 256) -> float:
    """Noise sigma of the training targets (noisefit.neighbour_sigma of n_patches random
    8x8 patches), nan where no two neighbours share a valid channel."""
    return noisefit.neighbour_sigma(*_sample_targets(data, key, n_patches))


def photosite_snr(data: dataset.RayData, key, n_patches: int = 256) -> float:
    """The training frames' effective photo-electrons per green photosite: mean^2 / variance
    of the green targets in n_patches random 8x8 patches (variance: noisefit.neighbour_sigma
    squared), nan where it cannot be measured.

    For a Poisson count of n electrons this is n; read noise lowers it (bucket: 10 electrons
    a green photosite in the simulator's truth, 9.5 measured; scoreboard 6.0 and 5.4; a
    tenth of bucket's light 1.0 and 0.34, the read noise a larger share of fewer photons).
    A binned target averages two green photosites (gridnerf.raw.bin2x2), so its mean^2 /
    variance is halved; a mosaic's green targets are one photosite each. Texture counts as
    noise where the median of neighbour differences sees it, so a textured scene reads
    lower than its photons.
    """
    y, m = _sample_targets(data, key, n_patches)
    g, mg = y[..., 1:2], m[..., 1:2]
    sigma = noisefit.neighbour_sigma(g, mg)
    mean = max(float((g * mg).sum() / max(mg.sum(), 1.0)), 0.0)
    if sigma == 0:
        return float("inf")
    if not sigma > 0:
        return float("nan")
    return (mean / sigma) ** 2 / (1.0 if data.mosaic else 2.0)


# The mosaic stages (data.mosaic_stages) are fitted only where the frames hold at least this
# many effective photo-electrons per green photosite (photosite_snr): planned_mosaic_stages.
MOSAIC_MIN_ELECTRONS = 3.0


def planned_mosaic_stages(cfg: Config, snr: float) -> int:
    """How many last stages fit the raw mosaic: data.mosaic_stages, or 0 (binned throughout)
    where the frames hold fewer than MOSAIC_MIN_ELECTRONS effective photo-electrons per
    green photosite (photosite_snr). Unmeasured (nan): the config's count. One line where
    the photons turn the mosaic stages off (data.binning=false fits the mosaic in every
    stage whatever the photons; data.mosaic_stages=0 never).

    A photosite's own noise is twice the binned green's variance; where the photons are few
    the fit is noise-limited and the binned raw's halved noise is worth more than the
    mosaic's resolution. Both ways on bucket and scoreboard (docs/results.md, "The mosaic
    data term"): the mosaic stage cost 0.11-0.50 dB at 0.21-1.55 effective electrons (a
    tenth and a quarter of their light) and gained 0.39-0.52 at 5.4-9.5 (their own light).
    The threshold, 3, lies between; every simulated and path-traced scene at its own light
    measures 5.0 or more. Checked on six other scene-light pairs (1.70-4.69): it picked the
    better data term on all six, by 0.08-0.33 dB.
    """
    want = cfg.data.mosaic_stages
    if want == 0 or not snr < MOSAIC_MIN_ELECTRONS:  # nan: not <
        return want
    print(f"the raw mosaic is not fitted: the frames hold {snr:.2g} effective "
          f"photo-electrons per green photosite, under {MOSAIC_MIN_ELECTRONS:g}; every stage "
          "fits the 2x2-binned raw, whose noise is half a photosite's (data.binning=false "
          "fits the mosaic anyway)")
    return 0


# A training pixel is at most this share of a final voxel's width (planned_downscale).
PIXEL_PER_VOXEL = 0.5


def planned_downscale(cfg: Config, image_width: int) -> int:
    """The box downscale of the 2x2-binned training frames (data.downscale, at least the
    config's): the largest power of 2 at which a training pixel, 2 x downscale capture
    pixels wide, spans at most PIXEL_PER_VOXEL of a voxel of the final grid. A voxel spans
    image_width / (the last stage's x vertex count) capture pixels: the box taken to fill
    the view's width, as the grid's resolutions are given. The config's own where the data
    is not binned (data.binning=false) or already coarser.

    Why: a step fits a fixed number of rays (train.batch_patches x patch_size^2), so a
    stage's photons are rays x photosites per training pixel. At 480x270 a final voxel
    spans 2.5 capture pixels, the last stage's 4.9M rays see every photosite of the 2.7M
    about twice, and the raw mosaic is the finest data the photons allow (planned_mosaic_
    stages). At 1920x1080 it spans 10: the same rays on the mosaic see 11% of the 44M
    photosites, on the binned raw 45%; downscaled by 2 (16 photosites a pixel, 4 capture
    pixels wide, still under half a voxel) all of them. On bucket at 1920x1080 (evaluated
    at 1920x1080, docs/results.md) the mosaic last stage scored 21.47 dB (colour-aligned
    24.66), binned throughout 21.90 (25.91), downscaled by 2 21.96 (26.92).
    """
    d = cfg.data.downscale
    if not cfg.data.binning:
        return d
    voxel_px = image_width / max(cfg.grid.resolutions[-1][0], 1)
    while 2 * (2 * d) <= PIXEL_PER_VOXEL * voxel_px:
        d *= 2
    return d


def fitted_config(cfg: Config, downscale: int | None) -> Config:
    """cfg with the run plan's training downscale (planned_downscale; None: cfg's own): the
    config the training data is built from and trained by. The saved config.json stays the
    user's.

    Where the plan raises the downscale by a factor f, the last stage trains f times its
    steps: a capture that large has f^2 times the photosites a voxel, and its time target
    more room (`make bench`: 480x270 within 3 min, 1920x1080 within 15). At 1920x1080
    (f = 2) twice the last stage's steps lifted bucket by 0.27 dB (colour-aligned 0.65)
    and the held-out held_arc_table by 0.51 (0.61); docs/results.md, "At the capture's own
    resolution"."""
    if downscale is None or downscale == cfg.data.downscale:
        return cfg
    factor = max(int(downscale) // cfg.data.downscale, 1)
    steps = cfg.train.steps_per_stage
    return replace(cfg, data=replace(cfg.data, downscale=int(downscale)),
                   train=replace(cfg.train, steps_per_stage=(*steps[:-1], steps[-1] * factor)))


def capped_eps(cfg: Config, sigma: float, raw: bool = True) -> float:
    """The data term's eps: loss.data_eps, lowered to loss.data_eps_sigmas x sigma (the
    training frames' noise, data_noise) where it is above that and the data term weighs
    raw frames with it (`raw`: the method's fits_raw, the runs whose fit depends on the
    raw's scale); unchanged where sigma is 0 or nan, or data_eps_sigmas is 0.

    The data term (C - y)^2 / (sg(C) + eps)^2 depends on eps / sigma alone: a raw scaled by
    gamma (data.exposure_ratio) scales C, y and sigma alike, so at a fixed ratio it is the
    same fit. RawNeRF's 1e-3 is 0.86-1.44 sigma on every simulated scene at gamma 1; at
    gamma 0.1 it is 13 sigma on bucket (-5.4 dB), where the cap trains it as at 2 sigma.
    Chosen on bucket's darkness sweep alone: best at 1.6-2.2 sigma (gamma 0.8 / 0.6:
    21.50 / 21.48 dB), worse past it (3.2 sigma: -0.18 dB, 4.3: -0.49, 13: -5.4).
    """
    lc = cfg.loss
    cap = lc.data_eps_sigmas * sigma
    if not (raw and cap > 0 and lc.data_eps > cap):  # nan: False
        return lc.data_eps
    return float(cap)


def data_eps_note(eps: float, sigma: float, raw: bool = True) -> str | None:
    """A note where the eps the steps use (capped_eps) is above EPS_NOTE_SIGMAS x the
    training frames' noise sigma (data_noise), else None (also where sigma is 0 or nan).
    With the default cap (2 sigmas) it is silent; it speaks where loss.data_eps_sigmas is
    0 or above EPS_NOTE_SIGMAS.

    There the data term stops weighing pixels by their own noise and the fit depends on the
    raw's scale. The darkness sweeps lose, at the same absolute eps, alike on scenes whose
    mean levels differ 2.3x but whose noise is alike: gamma 0.4 (eps 2.7-3.2 sigma) -0.18 /
    -0.47 / -0.39 dB on bucket / held_deep_hall / held_mixed_toys, gamma 0.1 4.0-5.4 dB.
    """
    if (not raw or not sigma > 0  # noiseless or unmeasured: no note
            or not eps > EPS_NOTE_SIGMAS * sigma):
        return None
    return (f"note: the data eps {eps:g} is {eps / sigma:.1f}x the noise sigma "
            f"{sigma:.2g} of the training frames (a very dark or low-gain capture): the fit "
            "depends on the raw's scale here; --set loss.data_eps_sigmas=2 (the default) caps "
            "it at 2 sigmas")
