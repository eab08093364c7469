"""One optimisation step: the loss of a batch of ray patches, the optimiser, the jitted step.

The spine's middle: rays (gridnerf.dataset.batch) -> grid render (gridnerf.render) ->
losses (the method's terms, gridnerf.methods, and the grid priors shared by every method,
gridnerf.losses) -> an optax update. gridnerf.train runs these steps stage by stage; the
benchmark and the tests build the same step here.
"""

from __future__ import annotations

from dataclasses import replace

import jax
import numpy as np
import optax

from gridnerf import dataset, devices, illuminant, losses, methods, render
from gridnerf.config import Config
from gridnerf.plan import RunPlan, StepPlan


def make_optimizer(cfg: Config, steps: int, stage: int = 0) -> optax.GradientTransformation:
    """Adam per field with an exponential decay to lr * lr_decay over the stage's `steps`;
    in a stage after the first the rates first ramp up from 0 over train.warmup_steps. The
    gains are not trained without a gain model (loss.gain_model "none").

    Why the ramp: Adam's first update is lr * sign(gradient) on every parameter a batch
    touches, whatever the gradient's size. A stage starts from the previous grid upsampled,
    near its optimum, so that first update is noise: on bucket (480x270) the test PSNR fell
    from 23.51 to 21.65 dB in the last stage's first 100 steps without it (docs/speed.md)."""
    warm = min(cfg.train.warmup_steps, steps - 1) if stage > 0 else 0

    def adam(lr):
        if warm > 0:
            sched = optax.warmup_exponential_decay_schedule(
                0.0, lr, warmup_steps=warm, transition_steps=max(steps - warm, 1),
                decay_rate=cfg.train.lr_decay)
        else:
            sched = optax.exponential_decay(
                lr, transition_steps=max(steps, 1), decay_rate=cfg.train.lr_decay
            )
        return optax.adam(sched, b1=0.9, b2=0.99, eps=1e-8)

    gain_tx = adam(cfg.train.lr_gain) if cfg.loss.use_gains else optax.set_to_zero()
    return optax.multi_transform(
        {"density": adam(cfg.train.lr_density), "rgb": adam(cfg.train.lr_rgb),
         "log_gain": gain_tx},
        {"density": "density", "rgb": "rgb", "log_gain": "log_gain"},
    )


def tv_scale(cfg: Config, stage: int) -> float:
    """The factor on the TVs of density, colour and chroma in `stage`: the stage's width
    (vertices across x) over loss.tv_ref_width where the stage is wider, else 1.

    Why: the TV is a mean over vertices of |forward difference|, and a field that varies
    smoothly changes by h |grad| between vertices h apart, so a fixed weight w asks for
    w h |grad| per unit volume: a finer grid is smoothed less for the same field, while
    each of its vertices sees fewer rays and more noise. w / h keeps the prior's strength in
    the scene's units where a stage is finer than the one the weights were set on."""
    ref = cfg.loss.tv_ref_width
    width = cfg.grid.resolutions[stage][0]
    return float(width) / ref if ref > 0 and width > ref else 1.0


def stage_tv_scale(cfg: Config, plan: RunPlan, stage: int) -> float:
    """The factor on the TVs in `stage` of a run: tv_scale, times the plan's configured_tv
    on the stages the config gave (every stage but the one the run appended;
    plan.configured_tv None: 1)."""
    scale = tv_scale(cfg, stage)
    appended = (plan.appended_width is not None
                and stage == len(cfg.grid.resolutions) - 1)
    if plan.configured_tv is not None and not appended:
        scale *= plan.configured_tv
    return scale


def step_plan(cfg: Config, plan: RunPlan, stage: int, scene) -> StepPlan:
    """The StepPlan of stage `stage` of a run: its plan's eps, opacity weight, candidate
    count and occupied-sample slots; the gain terms where the colour is the gain field; the
    capture's illuminant (float32) where the plan has one; the camera's Planckian locus for
    the batch target where the plan trusts it."""
    anchor = None if plan.colour.anchor is None else np.asarray(plan.colour.anchor, np.float32)
    locus = None
    if cfg.loss.ca_target == "batch" and plan.colour.locus and plan.colour.model == "field":
        matrix = plan.colour.sensor_matrix(scene.xyz_to_cam)
        locus = np.asarray(illuminant.planckian_locus(matrix), np.float32)
    return StepPlan(data_eps=plan.data_eps, opacity=plan.opacity[stage],
                    n_candidates=plan.n_candidates[stage],
                    max_samples=plan.samples(stage, cfg),
                    train_gains=plan.colour.model == "field", anchor=anchor, locus=locus,
                    tv_scale=stage_tv_scale(cfg, plan, stage))


def loss_fn(params, structure, rays: dict, key, cfg: Config, step: StepPlan, near_t: float,
            far_t: float):
    """Total loss and its terms for one batch of (P, p, p) ray patches: the method's terms
    (methods.get(loss.method).batch_terms) and the grid priors every method shares (the
    opacity prior where step.opacity > 0, TV of density, colour and chroma, sparsity),
    the grid terms on one sample of loss.tv_fraction of the rows (losses.grid_sample)."""
    shape = rays["target"].shape  # (P, p, p, 3)
    flat = {k: v.reshape(-1, 3) for k, v in rays.items()}
    k0, key = jax.random.split(key)
    render_cfg = (replace(cfg.render, max_samples=step.max_samples) if step.max_samples
                  else cfg.render)
    out = render.render_rays(structure, params, flat["origins"], flat["directions"], near_t,
                             far_t, render_cfg, key=k0, n_cand=step.n_candidates)
    lc = cfg.loss
    # one sample of the grid's rows (one gather) for the shared priors and the method's
    sample = losses.grid_sample(structure, params, sample_key=key, fraction=lc.tv_fraction)
    terms, weights = methods.get(lc.method).batch_terms(structure, params, flat, out, shape,
                                                        sample, cfg, step)
    if step.opacity > 0:
        terms["opacity"] = losses.opacity_loss(out["acc"])
    priors = losses.grid_priors(sample)
    if lc.tv_chroma <= 0:
        del priors["tv_chroma"]
    terms.update(priors)
    weights = {**weights, "opacity": step.opacity, "tv_density": lc.tv_density * step.tv_scale,
               "tv_rgb": lc.tv_rgb * step.tv_scale, "tv_chroma": lc.tv_chroma * step.tv_scale,
               "sparsity": lc.sparsity}
    total = sum(weights[k] * v for k, v in terms.items())
    return total, terms


def make_step(cfg: Config, step: StepPlan, tx, near_t: float, far_t: float):
    """Jitted step: (params, opt_state, structure, data, key) -> (params, opt_state, loss, aux).

    step: the stage's StepPlan (step_plan). The batch's patches are split over all local
    devices (gridnerf.devices); parameters are replicated. train.batch_patches must be a
    multiple of the device count.
    """
    devices.check_divisible(cfg.train.batch_patches, "train.batch_patches")
    if step.train_gains and cfg.loss.ca_target == "scene" and step.anchor is None:
        raise ValueError("loss.ca_target = 'scene' needs the capture's illuminant: build the "
                         "step from the run plan (optim.step_plan)")

    @jax.jit
    def step_fn(params, opt_state, structure, data, key):
        kb, kl = jax.random.split(key)
        rays = devices.shard_rays(
            dataset.batch(data, kb, cfg.train.batch_patches, cfg.train.patch_size))
        (total, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, structure, rays, kl, cfg, step, near_t, far_t
        )
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        return params, opt_state, total, terms

    return step_fn
