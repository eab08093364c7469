"""The colour plan: the L_ca inputs, estimated from the training frames before training.

The chromatic adaptation loss (the paper's eq. 14) pulls each ray's integrated gains S_k
towards a target; in the paper K_avg / C_k, with C_k the batch's mean of channel k and
K_avg their mean: the batch's grey world. Here the config chooses the target
(loss.ca_target, loss.ca_illuminant; docs/method.md):

- "batch": each batch's own estimate (on the Planckian locus with loss.ca_locus);
- "scene": one illuminant (3,) for the capture, from all training frames at once
  (scene_illuminant);
- "map": one illuminant per block of each training frame (gridnerf.illum_map's Retinex
  maps), anchored to the lights of the maps' warm and cool halves (with_illuminant_map).

loss.ca_illuminant = "consistent" (the default) picks the estimator per capture
(consistent_estimator); loss.gain_model = "auto" decides between one gain and the gain
field by the same one-light test (light_spread). plan_colour is the one entry point: it
runs once per training, on the host (NumPy), and returns the decisions as a typed
plan.ColourPlan that the run plan keeps (a resumed run passes its saved one back).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from gridnerf import dataset, illum_map, illuminant, noisefit, raw
from gridnerf.config import Config
from gridnerf.plan import ColourPlan

# Minkowski p of shades of grey (grey edge uses p = 1)
ESTIMATOR_P = 6.0
# the illuminant maps: blocks of MAP_BLOCK binned pixels (the noise averages down), and the
# log-chromaticity step above which neighbouring blocks differ in paint, not light
MAP_BLOCK = 16
MAP_TAU = 0.1
# the one-light test: a capture whose maps stray less than this (deg) from the consensus
# is lit by one light. Chosen between the single-light scenes' spreads (at most 2.42 deg)
# and the mixed-light ones' (at least 4.05) of the built-in and tuning scenes
ONE_LIGHT_DEG = 3.0
# the capture's estimates run on the frames box-downscaled until their noise sigma is under
# this share of their mean level (estimate_downscale): shades of grey's p-norm and grey
# edge's gradients measure the noise where it rivals the signal
NOISE_RATIO = 0.6


def estimate_frames(data: dataset.RayData, scene) -> tuple[list, list]:
    """The training frames as the capture-level estimators see them: (h, w, 3) camera RGB
    divided by the frame's exposure and (h, w[, 3]) validity, 2x2-binned in mosaic mode."""
    if data.mosaic:
        pairs = [scene.rgb_cam_binned(int(i)) for i in scene.train_idx]
        images = [p[0] / float(scene.exposure[i]) for p, i in zip(pairs, scene.train_idx,
                                                                   strict=True)]
        return images, [p[1] for p in pairs]
    inv = np.asarray(data.inv_exposure, np.float64)
    return (list(np.asarray(data.pixels, np.float64) * inv[:, None, None, None]),
            list(np.asarray(data.valid)))


def noise_ratio(frames) -> float:
    """The frames' noise sigma over their mean level: noisefit.neighbour_sigma of the valid
    pixels over their mean. frames: (images, masks) of estimate_frames. nan where the level
    is not positive or the noise is not measurable."""
    images, masks = frames
    stack = np.stack([np.asarray(im, np.float64) for im in images])
    valid = np.stack([np.broadcast_to(np.asarray(m, bool)[..., None] if np.ndim(m) == 2
                                      else np.asarray(m, bool), np.shape(im))
                      for im, m in zip(images, masks, strict=True)])
    level = float(stack[valid].mean()) if valid.any() else 0.0
    sigma = noisefit.neighbour_sigma(stack, valid)
    return sigma / level if level > 0 and np.isfinite(sigma) else float("nan")


def estimate_downscale(frames, ratio: float, largest: int = 16) -> int:
    """The box downscale the capture's illuminant estimates run at: the smallest power of 2
    (at most `largest`) at which the frames' noise_ratio, falling as 1 / d under a d x d box,
    is at most `ratio`. frames: (images, masks) of estimate_frames. 1 where ratio is 0 or
    the noise ratio is nan or already under `ratio`."""
    if ratio <= 0:
        return 1
    r = noise_ratio(frames)
    d = 1
    while d < largest and r / d > ratio:  # nan: False
        d *= 2
    return d


def downscaled(frames, d: int) -> tuple[list, list]:
    """(images, masks) box-downscaled by d (raw.downscale; a block is valid where every
    pixel of it is); the frames themselves at d = 1."""
    images, masks = frames
    if d == 1:
        return images, masks
    return ([raw.downscale(np.asarray(im), d) for im in images],
            [raw.downscale(np.asarray(m, np.float32), d) >= 1.0 for m in masks])


def _locus(scene, cfg: Config):
    return illuminant.planckian_locus(scene.xyz_to_cam) if cfg.loss.ca_locus else None


def scene_illuminant(scene, cfg: Config, frames, estimator: str, downscale: int = 1
                     ) -> np.ndarray:
    """The capture's illuminant (3,) unit camera RGB, estimated once from all training frames.

    `estimator` on the 2x2-binned frames divided by their exposure, saturated blocks left
    out (illuminant.frames_estimate: pooled pixels; grey edge per frame), then projected
    onto the camera's Planckian locus when loss.ca_locus; "consensus" is the per-channel
    median of illuminant.CONSENSUS's estimates (illuminant.consensus). frames: (images,
    masks) of estimate_frames; the estimate runs on them box-downscaled by `downscale`
    (estimate_downscale chooses it for the capture).
    """
    images, masks = downscaled(frames, downscale)
    return illuminant.capture_estimate(estimator, images, masks, _locus(scene, cfg),
                                       ESTIMATOR_P)


def with_illuminant_map(data: dataset.RayData, scene, cfg: Config, frames, estimator: str,
                        downscale: int = 1, anchor: np.ndarray | None = None
                        ) -> tuple[dataset.RayData, np.ndarray]:
    """(data with its per-frame L_ca illuminant map, the maps' anchor (3,)) for
    loss.ca_target = "map": each training frame's Retinex map (gridnerf.illum_map, blocks
    of MAP_BLOCK binned pixels) anchored to `anchor` (3,) where given (a resumed run's),
    else to the lights of the maps' warm and cool halves (illum_map.regional_anchor, each
    by `estimator`: two lights no longer pull one estimate towards the brighter one); on
    the locus when loss.ca_locus. The maps use the frames at full size (their blocks
    average the noise); the estimates, the frames downscaled by `downscale`."""
    images, masks = frames
    locus = _locus(scene, cfg)
    rel, weight = illum_map.relative_maps(images, masks, MAP_BLOCK, MAP_TAU)
    if anchor is None:
        anchor = illum_map.regional_anchor(
            images, masks, rel, weight,
            lambda ims, mks: scene_illuminant(scene, cfg, (ims, mks), estimator, downscale),
            locus, MAP_BLOCK)
    maps = illum_map.frame_maps(images, masks, anchor, locus, MAP_BLOCK, MAP_TAU, rel=rel)
    return dataclasses.replace(data, illuminant_map=jnp.asarray(maps, jnp.float32)), anchor


def light_spread(scene, cfg: Config, frames, downscale: int = 1) -> tuple[float, dict]:
    """(spread, estimates): how far the capture's illuminant maps, anchored to the
    consensus, stray from it (illum_map.map_spread_deg, deg; under one light less than
    ONE_LIGHT_DEG), and the consensus's three estimates {name: (3,)} of the whole
    capture. frames: (images, masks) of estimate_frames; the estimates run on them
    downscaled by `downscale` (scene_illuminant), the maps at full size."""
    images, masks = frames
    small, small_masks = downscaled(frames, downscale)
    locus = _locus(scene, cfg)
    wholes = {n: illuminant.capture_estimate(n, small, small_masks, locus, ESTIMATOR_P)
              for n in illuminant.CONSENSUS}
    cons = illuminant.consensus(list(wholes.values()), locus)
    maps = illum_map.frame_maps(images, masks, cons, locus, MAP_BLOCK, MAP_TAU)
    return illum_map.map_spread_deg(maps, cons), wholes


def consistent_estimator(scene, cfg: Config, frames, downscale: int = 1,
                         spread: tuple[float, dict] | None = None) -> str:
    """The estimator loss.ca_illuminant = "consistent" stands for on this capture: under one
    light (light_spread below ONE_LIGHT_DEG) the one of the consensus's three whose
    quadrant estimates agree best (illuminant.quadrant_spreads), else "consensus" (under
    two lights the quadrants see different lights, and the spread would measure them).
    frames: (images, masks) of estimate_frames; the estimates run on them downscaled by
    `downscale` (scene_illuminant), the maps at full size; spread: light_spread's result
    when the caller has it. Prints the choice."""
    small, small_masks = downscaled(frames, downscale)
    spread, wholes = light_spread(scene, cfg, frames, downscale) if spread is None else spread
    if spread >= ONE_LIGHT_DEG:
        print(f"L_ca estimator: consensus (the maps stray {spread:.2f} deg: lights mix)")
        return "consensus"
    spreads = illuminant.quadrant_spreads(small, small_masks, _locus(scene, cfg), ESTIMATOR_P,
                                          wholes)
    name = illuminant.least_spread(spreads)
    print(f"L_ca estimator: {name} (one light: the maps stray {spread:.2f} deg; quadrant "
          "spreads " + ", ".join(f"{n} {s:.2f}" for n, (_, s) in spreads.items()) + " deg)")
    return name


def one_gain(gain_model: str, spread: float | None) -> bool:
    """Whether the colour is one gain for the capture rather than the gain field:
    loss.gain_model "global", or "auto" with the capture lit by one light (light_spread's
    spread, deg, below ONE_LIGHT_DEG)."""
    return gain_model == "global" or (gain_model == "auto" and spread is not None
                                      and spread < ONE_LIGHT_DEG)


def plan_colour(data: dataset.RayData, scene, cfg: Config, saved: ColourPlan | None = None
                ) -> tuple[dataset.RayData, ColourPlan]:
    """The colour decisions of a Bright-NeRF run: (data, ColourPlan).

    No gains (loss.gain_model "none"): nothing to decide. The "batch" target: the gain
    field, each batch its own estimate. The "scene" and "map" targets: the frames are
    binned once (estimate_frames), the estimator picked ("consistent"), the capture's
    illuminant (the anchor) estimated and, for "map", data given its illuminant maps; the
    colour is one gain (the anchor's von Kries gains) for loss.gain_model "global", or
    "auto" under one light, else the gain field. saved: a resumed run's ColourPlan, whose
    estimator, downscale, anchor and light spread are kept (the maps are made again from
    the frames with its anchor).
    """
    lc = cfg.loss
    if not lc.use_gains:
        return data, ColourPlan(model="none")
    if lc.ca_target == "batch":
        return data, ColourPlan(model="field")
    frames = estimate_frames(data, scene)  # binned once for every estimate
    anchor = None
    if saved is not None:
        d, estimator, spread = saved.estimate_downscale, saved.estimator, saved.light_spread_deg
        anchor = None if saved.anchor is None else np.asarray(saved.anchor, np.float64)
    else:
        d = estimate_downscale(frames, NOISE_RATIO)
        if d > 1:
            print(f"L_ca estimates on the frames downscaled {d}x: their noise is above "
                  f"{NOISE_RATIO:g} x their level")
        measured = None
        if lc.ca_illuminant == "consistent" or lc.gain_model == "auto":
            measured = light_spread(scene, cfg, frames, d)
        estimator = (consistent_estimator(scene, cfg, frames, d, measured)
                     if lc.ca_illuminant == "consistent" else lc.ca_illuminant)
        spread = None if measured is None else float(measured[0])
    if lc.ca_target == "map":
        data, anchor = with_illuminant_map(data, scene, cfg, frames, estimator, d, anchor)
    elif anchor is None:
        anchor = scene_illuminant(scene, cfg, frames, estimator, d)
    anchor = np.asarray(anchor, np.float64)
    one = one_gain(lc.gain_model, spread)
    if saved is None and one:
        why = ("loss.gain_model=global" if lc.gain_model == "global" else
               f"one light: the maps stray {spread:.2f} deg, under {ONE_LIGHT_DEG:g}")
        print(f"colour: one gain for the capture, the L_ca target's ({why}); no gain "
              "field is trained")
    elif saved is None and lc.gain_model == "auto":
        print(f"colour: the gain field (lights mix: the maps stray {spread:.2f} deg)")
    # the gains of the anchor as the steps hold it (float32)
    unit = np.asarray(illuminant.unit(anchor.astype(np.float32).astype(np.float64)), np.float64)
    gains = np.asarray(illuminant.gains_from_illuminant(unit), np.float64)
    return data, ColourPlan(model="one_gain" if one else "field", estimator=estimator,
                            anchor=tuple(float(v) for v in anchor),
                            gains=tuple(float(v) for v in gains),
                            light_spread_deg=spread, estimate_downscale=int(d))
