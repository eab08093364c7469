"""Training: scene -> rays -> grid render -> losses -> optax step, coarse to fine.

One jitted step per resolution stage (shapes change only between stages).
The run folder (gridnerf.runfolder) holds config.json, checkpoint.npz (atomic,
finite-only, written every train.checkpoint_every steps or
train.checkpoint_seconds, resumed automatically) and metrics.jsonl. One
training per folder (a lock); a failed start leaves nothing behind. A
non-finite loss stops training with a clear message; the last good
checkpoint is kept. The loss stays on the device between host syncs: only log steps
(train.log_every), checkpoint steps and a stage's first and last steps wait for the step
and check the losses since the previous sync, always before a checkpoint is written.
"""

from __future__ import annotations

import dataclasses
import json
import resource
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from gridnerf import (
    atomic,
    checkpoint,
    colour_target,
    darkframes,
    dataset,
    devices,
    grid,
    illuminant,
    llnerf,
    losses,
    noisefit,
    render,
    runfolder,
    sensorfit,
    stages,
)
from gridnerf import config as cfgmod
from gridnerf.config import Config
from gridnerf.errors import CheckpointError, GridNerfError, NumericsError
from gridnerf.runfolder import load_state, save_state

CHECKPOINT = runfolder.CHECKPOINT


def make_optimizer(cfg: Config, steps: int, stage: int = 0) -> optax.GradientTransformation:
    """Adam per field with an exponential decay to lr * lr_decay over the stage; after the
    first stage the density rate is scaled by train.fine_density_lr_scale (the geometry is
    refined, not re-learnt, so it cannot turn per-view noise into floaters)."""

    def adam(lr):
        sched = optax.exponential_decay(
            lr, transition_steps=max(steps, 1), decay_rate=cfg.train.lr_decay
        )
        return optax.adam(sched, b1=0.9, b2=0.99, eps=1e-8)

    lr_density = cfg.train.lr_density * (cfg.train.fine_density_lr_scale if stage else 1.0)
    gain_tx = adam(cfg.train.lr_gain) if cfg.loss.use_gains else optax.set_to_zero()
    return optax.multi_transform(
        {"density": adam(lr_density), "rgb": adam(cfg.train.lr_rgb), "log_gain": gain_tx},
        {"density": "density", "rgb": "rgb", "log_gain": "log_gain"},
    )


def loss_fn(params, structure, rays: dict, key, cfg: Config, near_t: float, far_t: float,
            locus=None, scene_ill=None):
    """Total loss and its terms for one batch of (P, p, p) ray patches.

    locus: (n, 3) camera-RGB Planckian locus (illuminant.planckian_locus) when
    loss.ca_locus, the L_ca illuminant estimate is projected onto it; else None.
    scene_ill: (3,) the capture's illuminant (colour_target.scene_illuminant) when loss.ca_target is
    "scene": the L_ca target for every batch, no per-batch estimate; else None.
    loss.method = "llnerf": the LLNeRF-style terms (llnerf_terms) replace the data term,
    L_ca and the smoothness; the terms after them are shared.
    """
    shape = rays["target"].shape  # (P, p, p, 3)
    flat = {k: v.reshape(-1, 3) for k, v in rays.items()}
    k0, key = jax.random.split(key)
    out = render.render_rays(
        structure, params, flat["origins"], flat["directions"], near_t, far_t, cfg.render, key=k0
    )
    lc = cfg.loss
    k1, k2 = jax.random.split(key)
    if lc.method == "llnerf":
        terms = llnerf_terms(structure, params, flat, out, shape, k1, cfg)
    else:
        terms = {"data": losses.data_loss(out["rgb_low"], flat["target"], flat["mask"],
                                          data_eps(cfg, structure.color_scale))}
    if lc.use_gains and lc.method == "brightnerf":
        gain = out["gain"]
        if lc.gain_map == "normalized":
            # divided by the opacity: half-transparent rays are not pushed to target / acc
            gain = losses.normalized_gain(*render.frozen_density_gain(out))
        c_ill = None  # None: ca_loss's grey world of the batch (the paper's target)
        if lc.ca_target == "map":
            if "illuminant" not in flat:
                raise ValueError("loss.ca_target = 'map' needs the data's illuminant map "
                                 "(colour_target.with_illuminant_map)")
            c_ill = flat["illuminant"]  # (n, 3): each ray's block of its frame's map
        elif scene_ill is not None:
            c_ill = scene_ill
        elif lc.ca_illuminant != "grey_world" or locus is not None:
            c_ill = losses.batch_illuminant(lc.ca_illuminant, out["rgb_low"], out["acc"],
                                            shape, lc.ca_illuminant_p)
            if locus is not None:
                c_ill = illuminant.to_locus(c_ill, locus)
        terms["ca"] = losses.ca_loss(out["rgb_low"], gain, stop_grad_mean=lc.ca_stop_grad,
                                     illuminant=c_ill)
        smooth = 0.0
        if lc.smooth_mode in ("patch", "both"):
            smooth = smooth + losses.smooth_loss_patch(
                gain.reshape(shape), out["rgb_low"].reshape(shape)
            )
        if lc.smooth_mode in ("tv", "both"):
            smooth = smooth + losses.edge_aware_gain_tv(
                structure, params, sample_key=k1, fraction=lc.tv_fraction
            )
        terms["smooth"] = smooth
    if lc.opacity > 0:
        terms["opacity"] = losses.opacity_loss(out["acc"])
    if lc.distortion > 0:
        terms["distortion"] = losses.distortion_loss(out["weights"], out["s_vox"],
                                                     out["step_vox"])
    terms["tv_density"] = losses.tv_loss(
        structure, params["density"][:, None], sample_key=k2, fraction=lc.tv_fraction
    )
    terms["tv_rgb"] = losses.tv_loss(
        structure, params["rgb"], sample_key=k2, fraction=lc.tv_fraction
    )
    terms["sparsity"] = losses.sparsity_loss(
        params["density"], sample_key=k2, fraction=lc.tv_fraction, mode=lc.sparsity_mode
    )
    weights = {
        "data": lc.w_data,
        "ca": lc.w_ca,
        "smooth": lc.w_smooth,
        "tv_density": lc.tv_density,
        "tv_rgb": lc.tv_rgb,
        "sparsity": lc.sparsity,
        "distortion": lc.distortion,
        "opacity": lc.opacity,
        "exposure": lc.w_exposure,
        "color_constancy": lc.w_color_constancy,
        "enhance_tv": lc.w_enhance_tv,
    }
    total = sum(weights[k] * v for k, v in terms.items())
    return total, terms


def llnerf_terms(structure, params, flat: dict, out: dict, shape, k1, cfg: Config) -> dict:
    """The LLNeRF-style terms of one batch (gridnerf.llnerf): "data" (the dark render against
    the dark sRGB, loss.llnerf_data), "exposure" and "color_constancy" (of the enhanced
    render), "enhance_tv" (grid TV of log alpha and log gamma, rows sampled with k1).

    flat: the batch's (n, 3) arrays; out: its render; shape: (P, p, p, 3). With
    loss.gain_map = "normalized" the enhancement parameters are composited with
    stop-gradient weights (render.frozen_density_gain, as for L_ca), so the enhancement
    losses train the enhancement field alone.
    """
    gain, acc = out["gain"], out["acc"]
    if cfg.loss.gain_map == "normalized":
        gain, acc = render.frozen_density_gain(out)
    terms = llnerf.loss_terms(out["rgb_low"], gain, acc, flat["target"],
                              flat["mask"], shape, cfg.loss.exposure_level,
                              cfg.loss.exposure_pool, cfg.loss.llnerf_data)
    terms["enhance_tv"] = llnerf.enhancement_tv(structure, params["log_gain"], sample_key=k1,
                                                fraction=cfg.loss.tv_fraction)
    return terms


def make_step(cfg: Config, tx, near_t: float, far_t: float, locus=None, scene_ill=None,
              one_gain: bool = False):
    """Jitted step: (params, opt_state, structure, data, key) -> (params, opt_state, loss, aux).

    locus: the camera's Planckian locus (n, 3) for loss.ca_locus; scene_ill: the capture's
    illuminant (3,) for loss.ca_target = "scene" (see loss_fn); else None. one_gain: the
    colour is one gain for the capture (colour_target.one_gain): the steps have no gain
    terms (L_ca, smoothness), so the gains get no gradient and stay where they started.

    The batch's patches are split over all local devices (gridnerf.devices); parameters are
    replicated. train.batch_patches must be a multiple of the device count.
    """
    devices.check_divisible(cfg.train.batch_patches, "train.batch_patches")
    if (cfg.loss.use_gains and cfg.loss.method == "brightnerf" and cfg.loss.ca_target != "batch"
            and scene_ill is None):
        raise ValueError("loss.ca_target = 'scene' needs the capture's illuminant: pass "
                         "make_step(..., **colour_target.colour_inputs(data, scene, cfg)[1])")

    loss_cfg = (dataclasses.replace(cfg, loss=dataclasses.replace(cfg.loss, use_gains=False))
                if one_gain else cfg)

    @jax.jit
    def step(params, opt_state, structure, data, key):
        kb, kl = jax.random.split(key)
        rays = devices.shard_rays(
            dataset.batch(data, kb, cfg.train.batch_patches, cfg.train.patch_size))
        (total, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, structure, rays, kl, loss_cfg, near_t, far_t, locus, scene_ill
        )
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        return params, opt_state, total, terms

    return step


def stage_config(cfg: Config, stage: int) -> Config:
    """The config one stage's step is built with: `cfg` with loss.opacity = 0 from stage
    loss.opacity_stages on (when that is > 0); otherwise `cfg` itself."""
    n = cfg.loss.opacity_stages
    if n == 0 or stage < n or cfg.loss.opacity == 0:
        return cfg
    return dataclasses.replace(cfg, loss=dataclasses.replace(cfg.loss, opacity=0.0))


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


def _check_resume(path: Path, cfg: Config, structure, params, opt_leaves, stage: int,
                  schedule: list) -> None:
    """CheckpointError unless the checkpoint's arrays fit `cfg` (shapes and stage count)."""
    problem = None
    if stage > len(schedule):
        problem = f"it is at stage {stage} but the config has {len(schedule)} stages"
    elif structure.sh_degree != cfg.grid.sh_degree:
        problem = f"its sh_degree is {structure.sh_degree}, the config's {cfg.grid.sh_degree}"
    elif opt_leaves and stage < len(schedule):
        want = tuple(schedule[stage][0])
        have = tuple(structure.resolution)
        if want[1] == 0:  # y from the aspect: compare x and z
            have, want = have[::2], want[::2]
        if have != want:
            problem = (f"its grid is {tuple(structure.resolution)}, the config's stage {stage} "
                       f"is {tuple(schedule[stage][0])}")
        else:
            try:
                template = make_optimizer(cfg, schedule[stage][1], stage).init(params)
                checkpoint.unflatten_like(template, opt_leaves)
            except ValueError as exc:
                problem = f"its optimiser state does not fit ({exc})"
    if problem:
        raise CheckpointError(path, f"the checkpoint does not match the run's config: {problem}",
                              "resume with the config it was trained with, or delete "
                              f"{CHECKPOINT} to train again from the start")


def _checked_loss(pending: list, run: Path, stage: int, step: int) -> float:
    """The last of the device losses (n,) of steps step - n + 1 .. step, brought to the host;
    NumericsError naming the first non-finite one (the caller has not checkpointed it)."""
    values = np.asarray(jax.device_get(pending), np.float64)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise NumericsError(
            run / CHECKPOINT,
            f"loss became {values[bad[0]]} at stage {stage} step "
            f"{step + 1 - values.size + bad[0]}; nothing was checkpointed",
            "lower train.lr_* or check the frames; rerun to resume from the last save",
        )
    return float(values[-1])


def train(scene_dir: Path, run: Path, cfg: Config, overwrite_config: bool = False) -> dict:
    """Train (or resume) a run; returns the summary written to run/summary.json.

    Holds the run folder's lock throughout (RunLockedError if another training has it).
    A run with a checkpoint resumes with its saved config; a different `cfg` is refused
    unless `overwrite_config` (runfolder.resolve_config). config.json is written only once
    the scene and the checkpoint have loaded; a failed start leaves no new file behind.
    """
    run = Path(run)
    with runfolder.Session(run) as session:
        return _train(scene_dir, run, cfg, overwrite_config, session)


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
            or (run / CHECKPOINT).exists()):
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


def initial_grid(data: dataset.RayData, scene, cfg: Config, key, scene_ill=None):
    """(structure, params) a run starts from: the dense first-stage grid on the scene's box,
    colour at the data's mean level, gains at the L_ca target (scene_ill (3,), else the
    data's grey world; ones without gains; loss.method = "llnerf": llnerf.init_log_gain),
    the backdrop of grid.background."""
    bbox_min, bbox_max, near_t, _ = dataset.grid_box(scene)
    if scene.forward_facing and cfg.grid.ndc_xy == "frustums":
        bbox_min[:2], bbox_max[:2] = dataset.frustum_xy(scene, scene.train_idx, bbox_min,
                                                        bbox_max, near_t)
    color_scale, log_gain, mean_colour = data_statistics(data, jax.random.fold_in(key, 1))
    if scene_ill is not None:  # start the gains at the target
        log_gain = np.log(illuminant.gains_from_illuminant(scene_ill, floor=1e-6))
    if cfg.loss.method == "llnerf":  # alpha brings the mean level to E, gamma 1
        log_gain = llnerf.init_log_gain(color_scale, cfg.loss.exposure_level)
    if not cfg.loss.use_gains:
        log_gain = np.zeros(3)
    background = grid.BLACK
    if cfg.grid.background == "mean":  # the capture's mean colour, at the gains' start
        background = np.stack([mean_colour, np.exp(log_gain)])
    return grid.init_grid(
        stages.resolve_resolution(cfg.grid.resolutions[0], bbox_min, bbox_max, data.image_hw,
                           scene.forward_facing),
        bbox_min, bbox_max, sh_degree=cfg.grid.sh_degree, init_density=cfg.grid.init_density,
        init_log_gain=log_gain, color_scale=color_scale, background=background,
        key=jax.random.fold_in(key, 2))


def _train(scene_dir: Path, run: Path, cfg: Config, overwrite_config: bool,
           session: runfolder.Session) -> dict:
    cfg = runfolder.resolve_config(run, cfg, overwrite_config)
    if cfg.data.black_offset == "dark" and darkframes.load(run) is None:
        measured = darkframes.measure(scene_dir)  # before the scene loads: a fast refusal
        darkframes.save(run, measured)  # open_scene adds it to the file's black level
        print("black level from the dark frames: offsets (DN, CFA order) "
              f"{np.round(np.ravel(measured['offset_dn']), 2).tolist()}")
    scene = runfolder.open_scene(scene_dir, run, dark=runfolder.lens_cap_black(cfg, run))
    scene = with_weak_signal_black_level(scene, scene_dir, run, cfg)
    data = dataset.training_data(scene, cfg.data)
    near_t, far_t = dataset.grid_box(scene)[2:]
    data, colour = colour_target.colour_inputs(data, scene, cfg)
    scene_ill = None if "scene_ill" not in colour else np.asarray(colour["scene_ill"])
    if scene_ill is not None:
        print("L_ca target: the capture's illuminant (camera RGB) "
              f"{np.round(scene_ill / scene_ill.max(), 3).tolist()}")
    if data.illuminant_map is not None:
        spread = illuminant.angular_error_deg(np.asarray(data.illuminant_map), scene_ill)
        print(f"L_ca illuminant map: {spread.shape[1]}x{spread.shape[2]} blocks per frame, "
              f"{np.percentile(spread, 90):.2f} deg from the capture's at the 90th percentile")
    key = jax.random.PRNGKey(cfg.train.seed)
    schedule = list(zip(cfg.grid.resolutions, cfg.train.steps_per_stage, strict=True))

    if (run / CHECKPOINT).exists():
        structure, params, opt_leaves, header = load_state(run)
        stage, start, elapsed = header["stage"], header["step"], header["train_seconds"]
        key = jnp.asarray(np.array(header["key"], np.uint32))
        _check_resume(run / CHECKPOINT, cfg, structure, params, opt_leaves, stage, schedule)
        if stage >= len(schedule) and (run / "summary.json").exists():
            print(f"{run} is already trained; delete its checkpoint.npz to train again")
            session.started()
            return json.loads((run / "summary.json").read_text())
        print(f"resuming {run} at stage {stage}, step {start}")
    else:
        structure, params = initial_grid(data, scene, cfg, key, scene_ill)
        stage, start, elapsed, opt_leaves = 0, 0, 0.0, []
    # the frames' noise, measured alike on a fresh start and on a resume (the seed's key)
    sigma = data_noise(data, jax.random.fold_in(jax.random.PRNGKey(cfg.train.seed), 7))
    step_cfg = with_data_eps_cap(cfg, sigma)
    if step_cfg is not cfg:
        print(f"data eps: {cfg.loss.data_eps:g} is {cfg.loss.data_eps / sigma:.1f}x the noise "
              f"sigma {sigma:.2g} of the training frames, capped at "
              f"{cfg.loss.data_eps_sigmas:g} sigma: {step_cfg.loss.data_eps:.3g} "
              "(loss.data_eps_sigmas)")
    if note := data_eps_note(step_cfg, sigma):
        print(note)

    # Training really starts: save the config, drop metrics logged after the checkpoint.
    cfgmod.save(cfg, run / runfolder.CONFIG)
    if colour.get("one_gain"):
        colour_target.save_one_gain(run, scene_ill)
    runfolder.trim_metrics(run, stage, start)
    session.started()
    log = open(run / runfolder.METRICS, "a")  # noqa: SIM115
    rays_per_step = cfg.train.batch_patches * cfg.train.patch_size**2
    total_steps = sum(s for _, s in schedule)
    done_before = sum(s for _, s in schedule[:stage]) + start
    bar = tqdm(
        total=total_steps, initial=done_before, unit="step", dynamic_ncols=True, mininterval=2.0
    )
    rate = 0.0
    while stage < len(schedule):
        res, steps = schedule[stage]
        if (cfg.data.black_offset == "fit" and stage == len(schedule) - 1
                and data.black_offset is None):  # against the previous stage's field
            data = with_fitted_offsets(run, data, structure, params, scene, cfg)
        if stage > 0 and start == 0 and not opt_leaves:
            structure, params, info = stages.next_stage_grid(
                structure, params, res, data, cfg, near_t, far_t,
                fit=cfg.grid.fit_box and stage == 1, forward_facing=scene.forward_facing)
            print(f"stage {stage}: {info['resolution']} grid, box "
                  f"{np.round(info['bbox_min'], 3).tolist()}.."
                  f"{np.round(info['bbox_max'], 3).tolist()}, "
                  f"{100 * info['occupied_fraction']:.1f}% of the box occupied"
                  + (f", {100 * info['emptied_ray_fraction']:.2f}% of the training rays "
                     "rescued from carving" if "emptied_ray_fraction" in info else ""))
        tx = make_optimizer(cfg, steps, stage)
        opt_state = tx.init(params)
        if opt_leaves:
            opt_state = checkpoint.unflatten_like(opt_state, opt_leaves)
            opt_leaves = []
        stage_cfg = stages.with_fitted_candidates(stage_config(step_cfg, stage), structure,
                                                  data, near_t, far_t)
        step_fn = make_step(stage_cfg, tx, near_t, far_t, **colour)
        structure = grid.update_occupancy(structure, params, cfg.grid.occupancy_threshold)
        t_stage = time.perf_counter()
        last_save = t_stage
        steps_timed = 0
        pending = []  # (loss of each step since the last host sync) device scalars
        for step in range(start, steps):
            key, sub = jax.random.split(key)
            params, opt_state, total, terms = step_fn(params, opt_state, structure, data, sub)
            pending.append(total)
            steps_timed += 1
            if (step + 1) % cfg.grid.occupancy_every == 0:
                structure = grid.update_occupancy(structure, params, cfg.grid.occupancy_threshold)
            bar.update(1)
            last = step + 1 == steps
            logging = (step + 1) % cfg.train.log_every == 0 or last
            overdue = 0 < cfg.train.checkpoint_seconds <= time.perf_counter() - last_save
            saving = (step + 1) % cfg.train.checkpoint_every == 0 or last or overdue
            if not (logging or saving or steps_timed == 1):
                continue  # the loss stays on the device: no host sync on this step
            # the first step of a stage includes compilation: the rate counts from its end
            jax.block_until_ready((params, opt_state, structure, total))
            now = time.perf_counter()
            loss = _checked_loss(pending, run, stage, step)
            pending = []
            if steps_timed == 1:
                t_rate = now
            else:
                rate = (steps_timed - 1) * rays_per_step / max(now - t_rate, 1e-9)
            bar.set_postfix(stage=stage, loss=f"{loss:.4g}", rays_s=f"{rate:,.0f}")
            if logging:
                rec = {
                    "stage": stage,
                    "step": step + 1,
                    "loss": loss,
                    "rays_per_second": rate,
                    "train_seconds": elapsed + now - t_stage,
                    "voxels": int(structure.n_rows),
                }
                rec.update({k: float(v) for k, v in terms.items()})
                log.write(json.dumps(rec) + "\n")
                log.flush()
            if saving:
                header = {
                    "stage": stage + 1 if last else stage,
                    "step": 0 if last else step + 1,
                    "train_seconds": elapsed + now - t_stage,
                    "key": np.asarray(key).tolist(),
                }
                save_state(run, structure, params, [] if last else opt_state, header)
                last_save = time.perf_counter()
        elapsed += time.perf_counter() - t_stage
        stage, start = stage + 1, 0
    bar.close()
    log.close()

    summary = {
        "scene": str(Path(scene_dir).resolve()),
        "resolution": list(structure.resolution),
        "occupied_fraction": structure.n_rows / float(np.prod(structure.resolution)),
        "train_seconds": elapsed,
        "rays_per_second": rate,
        "voxels": int(structure.n_rows),
        # the training data's mean level (grid colour scale; loss.data_eps_mode=level's unit)
        "data_level": float(structure.color_scale),
        # the training frames' noise sigma (data_noise) and the absolute eps the data term used
        "data_noise": sigma if np.isfinite(sigma) else None,
        "data_eps": data_eps(step_cfg, structure.color_scale),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    if runfolder.lens_cap_black(cfg, run) and (offset := darkframes.load(run)) is not None:
        summary["black_offset_dn"] = offset.tolist()
    if colour.get("one_gain"):
        summary["one_gain"] = json.loads((run / colour_target.ONE_GAIN).read_text())["gains"]
    if (run / sensorfit.SENSOR_FIT).exists():
        summary["sensor_fit_dn"] = json.loads((run / sensorfit.SENSOR_FIT).read_text())["dn"]
    atomic.write_text(run / "summary.json", json.dumps(summary, indent=2))
    return summary
