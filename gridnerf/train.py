"""Training: scene -> rays -> grid render -> losses -> optax step, coarse to fine.

The stage loop around gridnerf.optim's jitted step, one per resolution stage (shapes
change only between stages). What the run decides from the frames (the black level, the
data term's eps, the training frames' downscale and the mosaic stages, gridnerf.data_term;
the colour, the method's plan_colour; each stage's candidate count, gridnerf.stages) is
the run plan (gridnerf.plan), saved as plan.json and read back on resume; the config is
never changed (config.json keeps the user's; the data is built from it with the plan's
downscale, data_term.fitted_config).
The run folder (gridnerf.runfolder) holds config.json, plan.json, checkpoint.npz (atomic,
finite-only, written every train.checkpoint_every steps or CHECKPOINT_SECONDS, resumed
automatically) and metrics.jsonl. One
training per folder (a lock); a failed start leaves nothing behind. A
non-finite loss stops training with a clear message; the last good
checkpoint is kept. The loss stays on the device between host syncs: only log steps
(train.log_every), checkpoint steps and a stage's first and last steps wait for the step
and check the losses since the previous sync, always before a checkpoint is written.
"""

from __future__ import annotations

import json
import resource
import time
from dataclasses import replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from gridnerf import (
    atomic,
    checkpoint,
    colour_solve,
    darkframes,
    data_term,
    dataset,
    grid,
    illuminant,
    methods,
    optim,
    outputs,
    residual,
    runfolder,
    shipped_colour,
    stages,
    vignetting,
    white_reference,
)
from gridnerf import config as cfgmod
from gridnerf import plan as planmod
from gridnerf.config import Config
from gridnerf.errors import CheckpointError, NumericsError
from gridnerf.runfolder import load_state, save_state

CHECKPOINT = runfolder.CHECKPOINT
CHECKPOINT_SECONDS = 30.0  # a checkpoint also when this long has passed since the last


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
                template = optim.make_optimizer(cfg, schedule[stage][1], stage).init(params)
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


def _vignetting(run: Path, plan, stage: int, structure, params, data, scene, near_t, far_t,
                cfg: Config, fits_raw: bool):
    """(data, plan) at the start of `stage`: after the first stage the lens falloff of the
    frames is estimated from the coarse fit's correspondences (gridnerf.vignetting) and,
    over vignetting.MIN_STOPS at the corners, taken off the data and kept in the plan;
    after the second, where one was found, what is left of it (the finer depth matches
    fewer pixels wrongly) is added. Only for a method that fits the raw; a run that fits the
    mosaic estimates it on the frames' binned raw and divides the mosaic's targets by it.

    Skipped where the raw files carried their own falloff correction, applied on loading
    (plan.file_falloff: a FixVignetteRadial or GainMap opcode, gridnerf.raw_layout): that
    is the lens's calibration, which the pair estimate (scatter up to 0.4 stop on captures
    without falloff) could only blur, and taking a falloff off twice would brighten the
    corners; not running it also saves its renders."""
    if plan.file_falloff is not None:
        return data, plan
    first = stage == 1 and plan.vignetting is None
    refine = stage == 2 and plan.vignetting is not None
    if not fits_raw or not (first or refine):
        return data, plan
    # the pairs compare binned pixels: a mosaic run pairs its frames' binned raw
    binned = data if not data.mosaic else vignetting.apply(
        dataset.training_data(scene, replace(cfg.data, binning=True)), plan.vignetting)
    k = vignetting.estimate(structure, params, binned, near_t, far_t, cfg.render)
    stops = vignetting.corner_stops(k)
    if first and abs(stops) <= vignetting.MIN_STOPS:
        return data, plan
    total = k if first else (plan.vignetting[0] + k[0], plan.vignetting[1] + k[1])
    print(f"lens falloff: the frames' corners are {abs(stops):.2f} stops "
          f"{'darker' if stops > 0 else 'brighter'} than their centres after stage "
          f"{stage - 1} (the same surfaces seen at different radii; over "
          f"{vignetting.MIN_STOPS:g} where first found): taken off the training pixels, "
          f"{vignetting.corner_stops(total):.2f} stops in all")
    plan = replace(plan, vignetting=(float(total[0]), float(total[1])))
    planmod.save(run, plan)
    return vignetting.apply(data, k), plan


def _colour_solve(run: Path, cfg: Config, plan, scene, method, structure, params, data,
                  near_t, far_t, key, elapsed: float, done: dict | None):
    """(params, record) after the colour solve of the finished stages (gridnerf.colour_solve;
    train.colour_solve_iters > 0, the brightnerf data term), saved in the checkpoint with
    its record so a resumed run does not solve twice (done: the record a resumed
    checkpoint already holds, or None); (params, None) without one."""
    if cfg.train.colour_solve_iters <= 0:
        return params, None
    if method.NAME != "brightnerf":
        print(f"colour solve: skipped, the {method.NAME} method's data term is not the one "
              "it fits")
        return params, None
    if done is not None:
        return params, done
    last = len(cfg.grid.resolutions) - 1
    data = stage_data(data, scene, cfg, method, plan, last)
    params, record = colour_solve.solve(structure, params, data, near_t, far_t, cfg,
                                        plan.data_eps, plan.n_candidates[last],
                                        optim.stage_tv_scale(cfg, plan, last))
    print(f"colour solve: {record['iterations']} L-BFGS iterations over {record['rays']:,} "
          f"rays in {record['seconds']:.0f} s, data term {record['data_before']:.4g} -> "
          f"{record['data_after']:.4g} ({record['kept']} colour kept)")
    save_state(run, structure, params, [], {
        "stage": last + 1, "step": 0, "train_seconds": elapsed,
        "key": np.asarray(key).tolist(), "colour_solve": record})
    return params, record


def _read_detail(run: Path, cfg: Config, plan, structure, params, data, near_t, far_t):
    """The plan with the detail the last stage but one left in its frames
    (gridnerf.residual.read, on the last stage's data where it is the raw mosaic) and, where
    grid.detail_width is set and the reading exceeds residual.ABOVE, the last stage's
    width refined to it, no finer than the frames' photosites hold
    (residual.refined_width); saved. It draws no random numbers, so a run it leaves at the
    config's width trains as one without the option, which does not read (the reading
    renders each fourth frame's greens: 5-10 s at 480x270)."""
    stage = len(cfg.grid.resolutions) - 2
    render_cfg = planmod.render_config(cfg, plan, stage).render
    t0 = time.perf_counter()
    reading, error = residual.read(structure, params, data, near_t, far_t, render_cfg)
    seconds = time.perf_counter() - t0
    measured = bool(np.isfinite(reading))
    width = cfg.grid.resolutions[-1][0]
    across = int(data.image_hw[1])
    refined = residual.refined_width(reading, error, cfg.grid.detail_width, width, across)
    plan = replace(plan, detail=float(reading) if measured else None,
                   detail_error=float(error) if measured else None, last_width=refined)
    what = ("not measurable (the last stage fits the binned raw)" if not measured
            else f"{reading:.2f} +- {error:.2f} times the noise the views' average leaves "
            f"(read in {seconds:.1f} s)")
    # over the threshold and asked wider, yet kept: the frames' photosites are the cap
    capped = (refined is None and residual.exceeds(reading, error)
              and width < cfg.grid.detail_width)
    if refined:
        print(f"detail: the {cfg.grid.resolutions[stage][0]}-wide grid leaves {what}, over "
              f"{residual.ABOVE:g} by {residual.SIGMAS:g} "
              f"errors: the last stage is {refined} wide instead of {width}")
    elif capped:
        print(f"detail: the {cfg.grid.resolutions[stage][0]}-wide grid leaves {what}, but "
              f"{across} photosites across hold no last stage finer than "
              f"{residual.finest_width(across)} wide: the last stage is {width} wide")
    else:
        print(f"detail: the {cfg.grid.resolutions[stage][0]}-wide grid leaves {what}; the "
              f"last stage is {width} wide")
    planmod.save(run, plan)
    return plan


def stage_data(data, scene, cfg: Config, method, plan, stage: int):
    """The training data of `stage`: from the first of the plan's last mosaic stages on
    (DataConfig.mosaic_from), the raw Bayer mosaic, photosite by photosite, in place of
    the binned raw, with the binned data's illuminant map and the lens falloff (the plan's
    k1, k2, or None) carried over. The coarse stages fit the binned raw: a quarter of the
    rays, with half the green noise, place the geometry (on scoreboard, the scene with the
    fewest photons, the mosaic in every stage cost 0.14 dB against binning throughout,
    the mosaic in the last stage alone gained 0.39; docs/results.md)."""
    if data.mosaic or stage < cfg.data.mosaic_from(len(cfg.grid.resolutions),
                                                   plan.mosaic_stages):
        return data
    mosaic = method.training_data(scene, replace(cfg, data=replace(cfg.data, binning=False)))
    mosaic = replace(mosaic, illuminant_map=data.illuminant_map)
    print(f"stage {stage}: fitting the raw mosaic, {mosaic.image_hw[1]}x{mosaic.image_hw[0]} "
          "photosites a frame")
    return vignetting.apply(mosaic, plan.vignetting)


def train(scene_dir: Path, run: Path, cfg: Config, overwrite_config: bool = False,
          white_ref: str | None = None) -> dict:
    """Train (or resume) a run; returns the summary written to run/summary.json.

    white_ref: "frame:x,y,w,h", a grey card that sets the light (gridnerf.white_reference),
    in place of the scene's transforms.json white_reference; a resumed run keeps the light
    its plan saved.

    Holds the run folder's lock throughout (RunLockedError if another training has it).
    A run with a checkpoint resumes with its saved config; a different `cfg` is refused
    unless `overwrite_config` (runfolder.resolve_config). config.json is written only once
    the scene and the checkpoint have loaded; a failed start leaves no new file behind.
    """
    run = Path(run)
    with runfolder.RunLock(run) as lock:
        return _train(scene_dir, run, cfg, overwrite_config, lock, white_ref)



def _train(scene_dir: Path, run: Path, cfg: Config, overwrite_config: bool,
           lock: runfolder.RunLock, white_ref: str | None = None) -> dict:
    cfg = runfolder.resolve_config(run, cfg, overwrite_config)
    reference = None if white_ref is None else white_reference.parse(white_ref)
    method = methods.get(cfg.loss.method)
    method.check(cfg)
    resuming = (run / CHECKPOINT).exists()
    saved = planmod.load(run) if resuming else None
    black = None if saved is None else saved.black_level
    if black is None and cfg.data.black_offset == "dark":  # before the scene loads: a fast refusal
        black = data_term.black_level(scene_dir, run, cfg, None)
    scene = runfolder.open_scene(scene_dir, run)
    if reference is not None:
        scene = replace(scene, white_reference=reference)
    if scene.white_reference is not None and saved is None:
        white_reference.estimate(scene, scene.white_reference)  # refused before any write
    if black is None:
        black = data_term.black_level(scene_dir, run, cfg, scene)
    if black == "lens_cap":
        scene = darkframes.apply(scene, darkframes.load(run))
    # the training frames' downscale (the saved plan's, or from the final grid's footprint):
    # from here on `cfg` builds the data with it; config.json keeps the user's `asked`
    asked = cfg
    if saved is None:
        appended = planmod.appended_width(cfg, scene.cameras.width)
        appended_steps = planmod.APPENDED_STEPS
        appended_tv = (None if appended is None
                       else planmod.appended_tv_ref(cfg, appended, scene.cameras.width))
        configured_tv = planmod.configured_tv(cfg, appended, scene.cameras.width)
    else:  # a resume keeps the stage, steps and TVs its run began with
        appended, appended_tv = saved.appended_width, saved.appended_tv_ref
        configured_tv = saved.configured_tv
        appended_steps = planmod.trained_appended_steps(saved)
    cfg = planmod.capture_config(cfg, appended, appended_steps, appended_tv)
    if appended is not None and saved is None:
        print(f"last stage: {cfg.grid.resolutions[-2][0]} vertices across span "
              f"{scene.cameras.width / cfg.grid.resolutions[-2][0]:.3g} capture pixels, over "
              f"grid.voxel_pixels = {cfg.grid.voxel_pixels:g}: a stage {appended} wide is "
              f"appended, its TVs x{optim.tv_scale(cfg, len(cfg.grid.resolutions) - 1):.3g} "
              f"({scene.cameras.width / appended:.3g} pixels a vertex; plan.appended_tv_ref)"
              + ("" if configured_tv is None else
                 f"; the configured stages' TVs x{configured_tv:.3g} (plan.configured_tv)"))
    downscale = (data_term.planned_downscale(cfg, scene.cameras.width) if saved is None
                 else saved.downscale)
    cfg = data_term.fitted_config(cfg, downscale)
    if saved is not None:  # a resumed run trains the last stage its plan decided
        cfg = planmod.refined_config(cfg, saved)
    if downscale is not None and downscale != asked.data.downscale:
        print(f"training frames: binned and box-downscaled by {downscale} "
              f"({scene.cameras.width // (2 * downscale)} pixels wide): a voxel of the "
              f"{cfg.grid.resolutions[-1][0]}-wide final grid spans "
              f"{scene.cameras.width / cfg.grid.resolutions[-1][0]:.3g} capture pixels, and "
              "the steps see more photons in fewer, larger pixels; the last stage trains "
              f"{cfg.train.steps_per_stage[-1]} steps")
    # the first stage's data: the binned raw, or the mosaic where every stage fits it; and
    # how many last stages fit the mosaic: the saved plan's, or decided on these frames
    n_stages = len(cfg.grid.resolutions)
    mosaic_stages = None if saved is None else saved.mosaic_stages
    mosaic_first = cfg.data.mosaic_from(n_stages, mosaic_stages) == 0
    data = method.training_data(scene, replace(cfg, data=replace(cfg.data, binning=False))
                                if mosaic_first else cfg)
    snr = None if saved is None else saved.photosite_snr
    if saved is None and cfg.data.binning and cfg.data.mosaic_from(n_stages) < n_stages:
        measured = data_term.photosite_snr(
            data, jax.random.fold_in(jax.random.PRNGKey(cfg.train.seed), 11))
        mosaic_stages = data_term.planned_mosaic_stages(cfg, measured)
        snr = measured if np.isfinite(measured) else None
        if mosaic_first and cfg.data.mosaic_from(n_stages, mosaic_stages) > 0:
            data = method.training_data(scene, cfg)  # the photons turned the mosaic off
    near_t, far_t = dataset.grid_box(scene)[2:]
    data, colour = method.plan_colour(data, scene, cfg, None if saved is None else saved.colour)
    if colour.anchor is not None:
        anchor = np.asarray(colour.anchor, np.float32)
        print("L_ca target: the capture's illuminant (camera RGB) "
              f"{np.round(anchor / anchor.max(), 3).tolist()}")
        if data.illuminant_map is not None:
            spread = illuminant.angular_error_deg(np.asarray(data.illuminant_map), anchor)
            print(f"L_ca illuminant map: {spread.shape[1]}x{spread.shape[2]} blocks per "
                  f"frame, {np.percentile(spread, 90):.2f} deg from the capture's at the "
                  "90th percentile")
    key = jax.random.PRNGKey(cfg.train.seed)
    schedule = list(zip(cfg.grid.resolutions, cfg.train.steps_per_stage, strict=True))

    if resuming:
        structure, params, opt_leaves, header = load_state(run)
        stage, start, elapsed = header["stage"], header["step"], header["train_seconds"]
        solved_before = header.get("colour_solve")  # the colour solve's record, once done
        key = jnp.asarray(np.array(header["key"], np.uint32))
        _check_resume(run / CHECKPOINT, cfg, structure, params, opt_leaves, stage, schedule)
        if stage >= len(schedule) and (run / "summary.json").exists():
            print(f"{run} is already trained; delete its checkpoint.npz to train again")
            lock.started()
            return json.loads((run / "summary.json").read_text())
        print(f"resuming {run} at stage {stage}, step {start}")
        plan = saved
        data = vignetting.apply(data, plan.vignetting)
        if stage < len(schedule):
            data = stage_data(data, scene, cfg, method, plan, stage)
    else:
        structure, params = stages.initial_grid(
            data, scene, cfg, key,
            lambda scale, grey: method.init_log_gain(cfg, colour, scale, grey))
        stage, start, elapsed, opt_leaves = 0, 0, 0.0, []
        solved_before = None
        # the frames' noise (the seed's key) and the data term's eps capped against it
        sigma = data_term.data_noise(data,
                                     jax.random.fold_in(jax.random.PRNGKey(cfg.train.seed), 7))
        raw = method.fits_raw(cfg)
        eps = data_term.capped_eps(cfg, sigma, raw)
        if eps != cfg.loss.data_eps:
            print(f"data eps: {cfg.loss.data_eps:g} is {cfg.loss.data_eps / sigma:.1f}x the "
                  f"noise sigma {sigma:.2g} of the training frames, capped at "
                  f"{cfg.loss.data_eps_sigmas:g} sigma: {eps:.3g} (loss.data_eps_sigmas)")
        if note := data_term.data_eps_note(eps, sigma, raw):
            print(note)
        plan = planmod.RunPlan(
            method=method.NAME, black_level=black,
            data_noise=float(sigma) if np.isfinite(sigma) else None, data_eps=eps,
            colour=colour,
            opacity=planmod.opacity_schedule(cfg.loss.opacity, n_stages,
                                             cfg.loss.opacity_stages),
            n_candidates=(0,) * n_stages, file_falloff=scene.lens_correction,
            photosite_snr=snr, mosaic_stages=mosaic_stages, downscale=downscale,
            appended_width=appended,
            appended_steps=None if appended is None else tuple(appended_steps),
            appended_tv_ref=appended_tv, configured_tv=configured_tv)
        if scene.lens_correction and method.fits_raw(cfg):
            print(f"lens falloff: corrected on loading by the raw files' "
                  f"{scene.lens_correction}; the frame-based estimate is skipped")

    # Training really starts: save the config and the plan, drop metrics logged after the
    # checkpoint.
    cfgmod.save(asked, run / runfolder.CONFIG)
    planmod.save(run, plan)
    runfolder.trim_metrics(run, stage, start)
    lock.started()
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
        if stage > 0 and start == 0 and not opt_leaves:
            data, plan = _vignetting(run, plan, stage, structure, params, data, scene, near_t,
                                     far_t, cfg, method.fits_raw(cfg))
            data = stage_data(data, scene, cfg, method, plan, stage)
            if stage == n_stages - 1 and cfg.grid.detail_width > 0 and plan.detail is None:
                plan = _read_detail(run, cfg, plan, structure, params, data, near_t, far_t)
                cfg = planmod.refined_config(cfg, plan)
                schedule[stage] = (cfg.grid.resolutions[stage], steps)
                res = schedule[stage][0]
            structure, params, info = stages.next_stage_grid(
                structure, params, res, data, cfg, near_t, far_t,
                fit=cfg.grid.fit_box and stage == 1, forward_facing=scene.forward_facing)
            print(f"stage {stage}: {info['resolution']} grid, box "
                  f"{np.round(info['bbox_min'], 3).tolist()}.."
                  f"{np.round(info['bbox_max'], 3).tolist()}, "
                  f"{100 * info['occupied_fraction']:.1f}% of the box occupied"
                  )
        tx = optim.make_optimizer(cfg, steps, stage)
        opt_state = tx.init(params)
        if opt_leaves:
            opt_state = checkpoint.unflatten_like(opt_state, opt_leaves)
            opt_leaves = []
        structure = grid.update_occupancy(structure, params)
        # the stage's candidate count and sample slots: decided on its grid and its rays,
        # kept in the plan (one write)
        decided = plan
        if not plan.n_candidates[stage]:
            plan = plan.with_candidates(stage, stages.fitted_candidates(
                structure, data, near_t, far_t, cfg.render))
        if plan.max_samples is None or not plan.max_samples[stage]:
            plan = plan.with_samples(stage, stages.fitted_samples(
                structure, data, near_t, far_t, cfg.render, plan.n_candidates[stage]))
            print(f"stage {stage}: {plan.max_samples[stage]} occupied samples per ray "
                  f"(of {plan.n_candidates[stage]} candidates)")
        if plan is not decided:
            planmod.save(run, plan)
        step_fn = optim.make_step(cfg, optim.step_plan(cfg, plan, stage, scene), tx, near_t,
                                  far_t)
        t_stage = time.perf_counter()
        last_save = t_stage
        steps_timed = 0
        pending = []  # (loss of each step since the last host sync) device scalars
        for step in range(start, steps):
            key, sub = jax.random.split(key)
            params, opt_state, total, terms = step_fn(params, opt_state, structure, data, sub)
            pending.append(total)
            steps_timed += 1
            if (step + 1) % grid.OCCUPANCY_EVERY == 0:
                structure = grid.update_occupancy(structure, params)
            bar.update(1)
            last = step + 1 == steps
            logging = (step + 1) % cfg.train.log_every == 0 or last
            overdue = CHECKPOINT_SECONDS <= time.perf_counter() - last_save
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

    cfg = planmod.render_config(cfg, plan)  # renders shade the last stage's slots
    params, solved = _colour_solve(run, cfg, plan, scene, method, structure, params, data,
                                   near_t, far_t, key, elapsed, solved_before)
    # the safety net: the field's white checked against the frames before the run is done
    colour_record = {"shipped": plan.colour.model}
    if plan.colour.model == "field" and plan.colour.evidence:
        colour, colour_record = shipped_colour.check(
            outputs.training_render(structure, params, scene, cfg), plan.colour)
        if colour != plan.colour:
            plan = replace(plan, colour=colour)
            planmod.save(run, plan)
    summary = {
        "scene": str(Path(scene_dir).resolve()),
        "resolution": list(structure.resolution),
        "occupied_fraction": structure.n_rows / float(np.prod(structure.resolution)),
        "train_seconds": elapsed,
        "rays_per_second": rate,
        "voxels": int(structure.n_rows),
        # the training data's mean level (the grid's colour scale)
        "data_level": float(structure.color_scale),
        # the training frames' noise sigma (data_noise) and the absolute eps the data term used
        "data_noise": plan.data_noise,
        "data_eps": plan.data_eps,
        # the frames' photons per green photosite and the stages that fitted the raw mosaic
        "photosite_snr": plan.photosite_snr,
        "mosaic_stages": (n_stages - cfg.data.mosaic_from(n_stages, plan.mosaic_stages)),
        # the binned training frames' box downscale (data_term.planned_downscale)
        "downscale": cfg.data.downscale,
        # the detail the last stage but one left, in units of the views' averaged noise
        # (gridnerf.residual), and the last stage's width it decided
        "detail": plan.detail,
        "detail_error": plan.detail_error,
        "last_width": int(structure.resolution[0]),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    if solved is not None:
        summary["colour_solve"] = solved
    if plan.black_level == "lens_cap" and (offset := darkframes.load(run)) is not None:
        summary["black_offset_dn"] = offset.tolist()
    if plan.one_gain is not None:
        summary["one_gain"] = list(plan.one_gain)
    summary["colour"] = colour_record  # which colour was shipped, and why
    atomic.write_text(run / "summary.json", json.dumps(summary, indent=2))
    return summary
