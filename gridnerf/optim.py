"""One optimisation step: the loss of a batch of ray patches, the optimiser, the jitted step.

The spine's middle: rays (gridnerf.dataset.batch) -> grid render (gridnerf.render) ->
losses (gridnerf.losses, gridnerf.llnerf) -> an optax update. gridnerf.train runs these
steps stage by stage; the benchmark and the tests build the same step here.
"""

from __future__ import annotations

import dataclasses

import jax
import optax

from gridnerf import data_term, dataset, devices, illuminant, llnerf, losses, render
from gridnerf.config import Config


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
    loss.method = "llnerf": the LLNeRF-style terms (llnerf.batch_terms) replace the data term,
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
        terms = llnerf.batch_terms(structure, params, flat, out, shape, k1, cfg)
    else:
        terms = {"data": losses.data_loss(out["rgb_low"], flat["target"], flat["mask"],
                                          data_term.data_eps(cfg, structure.color_scale))}
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
