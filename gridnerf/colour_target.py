"""The L_ca inputs, estimated from the training frames before training starts.

The chromatic adaptation loss (the paper's eq. 14) pulls each ray's integrated gains S_k
towards a target; in the paper K_avg / C_k, with C_k the batch's mean of channel k and
K_avg their mean: the batch's grey world. Here the config chooses the target
(loss.ca_target, loss.ca_illuminant, loss.ca_map_anchor; docs/colour.md):

- "batch": each batch's own estimate (nothing to prepare here, but the Planckian locus
  when loss.ca_locus);
- "scene": one illuminant (3,) for the capture, from all training frames at once
  (scene_illuminant);
- "map": one illuminant per block of each training frame (gridnerf.illum_map's Retinex
  maps), anchored to the capture's light or to the lights of its warm and cool halves
  (with_illuminant_map).

loss.ca_illuminant = "consistent" (the default) picks the estimator per capture
(consistent_estimator). colour_inputs is the one entry point training (and the
benchmarks, carry_runs) call; it runs once per training, on the host (NumPy).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from gridnerf import atomic, dataset, illum_map, illuminant, noisefit, raw
from gridnerf.config import Config

ONE_GAIN = "one_gain.json"  # in a run folder: the capture's one gain (loss.gain_model)


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


def scene_illuminant(data: dataset.RayData, scene, cfg: Config, frames=None,
                     downscale: int = 1) -> np.ndarray:
    """The capture's illuminant (3,) unit camera RGB, estimated once from all training frames.

    loss.ca_illuminant on the 2x2-binned frames divided by their exposure, saturated blocks
    left out (illuminant.frames_estimate: pooled pixels; grey edge per frame), then projected
    onto the camera's Planckian locus when loss.ca_locus; "consensus" is the per-channel
    median of illuminant.CONSENSUS's estimates (illuminant.consensus). The mosaic mode bins
    the frames for this estimate only. frames: (images, masks) of estimate_frames when the
    caller has them already. loss.ca_illuminant = "consistent" is resolved on these frames
    (resolve_estimator). downscale: the estimate runs on the frames box-downscaled by it
    (downscaled; estimate_downscale chooses it for the capture).
    """
    frames = estimate_frames(data, scene) if frames is None else frames
    lc = resolve_estimator(scene, cfg, frames, downscale).loss
    locus = illuminant.planckian_locus(scene.xyz_to_cam) if lc.ca_locus else None
    images, masks = downscaled(frames, downscale)
    return illuminant.capture_estimate(lc.ca_illuminant, images, masks, locus,
                                       lc.ca_illuminant_p)


def with_illuminant_map(data: dataset.RayData, scene, cfg: Config,
                        anchor: np.ndarray | None = None, frames=None, downscale: int = 1
                        ) -> tuple[dataset.RayData, np.ndarray]:
    """(data with its per-frame L_ca illuminant map, the maps' anchor (3,)) for
    loss.ca_target = "map": each training frame's Retinex map (gridnerf.illum_map, blocks
    of loss.ca_map_block binned pixels) anchored, with loss.ca_map_anchor = "regions", to
    the lights of the maps' warm and cool halves (illum_map.regional_anchor, each by
    loss.ca_illuminant; `anchor` is not used) or, with "capture", to `anchor` (3,) (default:
    scene_illuminant); on the locus when loss.ca_locus; frames as in scene_illuminant (the
    whole capture's: "consistent" is resolved on them, resolve_estimator). The maps use the
    frames at full size (their blocks average the noise); the estimates, the frames
    downscaled by `downscale` (scene_illuminant)."""
    images, masks = estimate_frames(data, scene) if frames is None else frames
    cfg = resolve_estimator(scene, cfg, (images, masks), downscale)
    lc = cfg.loss
    locus = illuminant.planckian_locus(scene.xyz_to_cam) if lc.ca_locus else None
    rel, weight = illum_map.relative_maps(images, masks, lc.ca_map_block, lc.ca_map_tau)
    if lc.ca_map_anchor == "regions":
        anchor = illum_map.regional_anchor(
            images, masks, rel, weight,
            lambda ims, mks: scene_illuminant(data, scene, cfg, (ims, mks), downscale), locus,
            lc.ca_map_block)
    elif anchor is None:
        anchor = scene_illuminant(data, scene, cfg, (images, masks), downscale)
    maps = illum_map.frame_maps(images, masks, anchor, locus, lc.ca_map_block, lc.ca_map_tau,
                                rel=rel)
    return dataclasses.replace(data, illuminant_map=jnp.asarray(maps, jnp.float32)), anchor


def light_spread(scene, cfg: Config, frames, downscale: int = 1) -> tuple[float, dict]:
    """(spread, estimates): how far the capture's illuminant maps, anchored to the
    consensus, stray from it (illum_map.map_spread_deg, deg; under one light less than
    loss.ca_one_light_deg), and the consensus's three estimates {name: (3,)} of the whole
    capture. frames: (images, masks) of estimate_frames; the estimates run on them
    downscaled by `downscale` (scene_illuminant), the maps at full size."""
    images, masks = frames
    small, small_masks = downscaled(frames, downscale)
    lc = cfg.loss
    locus = illuminant.planckian_locus(scene.xyz_to_cam) if lc.ca_locus else None
    wholes = {n: illuminant.capture_estimate(n, small, small_masks, locus, lc.ca_illuminant_p)
              for n in illuminant.CONSENSUS}
    cons = illuminant.consensus(list(wholes.values()), locus)
    maps = illum_map.frame_maps(images, masks, cons, locus, lc.ca_map_block, lc.ca_map_tau)
    return illum_map.map_spread_deg(maps, cons), wholes


def consistent_estimator(scene, cfg: Config, frames, downscale: int = 1,
                         spread: tuple[float, dict] | None = None) -> str:
    """The estimator loss.ca_illuminant = "consistent" stands for on this capture: under one
    light (light_spread below loss.ca_one_light_deg) the one of the consensus's three
    whose quadrant estimates agree best (illuminant.quadrant_spreads), else "consensus"
    (under two lights the quadrants see different lights, and the spread would measure
    them). frames: (images, masks) of estimate_frames; the estimates run on them
    downscaled by `downscale` (scene_illuminant), the maps at full size; spread:
    light_spread's result when the caller has it. Prints the choice."""
    small, small_masks = downscaled(frames, downscale)
    lc = cfg.loss
    locus = illuminant.planckian_locus(scene.xyz_to_cam) if lc.ca_locus else None
    spread, wholes = light_spread(scene, cfg, frames, downscale) if spread is None else spread
    if spread >= lc.ca_one_light_deg:
        print(f"L_ca estimator: consensus (the maps stray {spread:.2f} deg: lights mix)")
        return "consensus"
    spreads = illuminant.quadrant_spreads(small, small_masks, locus, lc.ca_illuminant_p,
                                          wholes)
    name = illuminant.least_spread(spreads)
    print(f"L_ca estimator: {name} (one light: the maps stray {spread:.2f} deg; quadrant "
          "spreads " + ", ".join(f"{n} {s:.2f}" for n, (_, s) in spreads.items()) + " deg)")
    return name


def resolve_estimator(scene, cfg: Config, frames, downscale: int = 1,
                      spread: tuple[float, dict] | None = None) -> Config:
    """cfg with loss.ca_illuminant = "consistent" replaced by the estimator it stands for on
    this capture (consistent_estimator; frames: the whole capture's (images, masks) of
    estimate_frames, downscale and spread as there), any other cfg as it is."""
    if cfg.loss.ca_illuminant != "consistent":
        return cfg
    name = consistent_estimator(scene, cfg, frames, downscale, spread)
    return dataclasses.replace(cfg, loss=dataclasses.replace(cfg.loss, ca_illuminant=name))


def estimates_from_frames(cfg: Config) -> bool:
    """Whether training estimates the L_ca illuminant from the training frames before it
    starts (gains on, not loss.method = "llnerf", the "scene" or "map" target): the runs
    whose training loss.ca_illuminant can change, through colour_inputs alone."""
    lc = cfg.loss
    return lc.use_gains and lc.method != "llnerf" and lc.ca_target in ("scene", "map")


def one_gain(cfg: Config, spread: float | None) -> bool:
    """Whether the colour is one gain for the capture rather than the gain field:
    loss.gain_model "global", or "auto" with the capture lit by one light (light_spread's
    spread below loss.ca_one_light_deg)."""
    model = cfg.loss.gain_model
    return model == "global" or (model == "auto" and spread is not None
                                 and spread < cfg.loss.ca_one_light_deg)


def colour_inputs(data: dataset.RayData, scene, cfg: Config) -> tuple[dataset.RayData, dict]:
    """The L_ca inputs, as the config chooses them: (data, make_step keyword arguments).

    data gains its illuminant map for loss.ca_target = "map" (with_illuminant_map);
    kwargs: {"scene_ill": (3,)} for the "scene" and "map" targets (the map's anchor, and
    where the gains start), with "one_gain": True where the colour is that one gain
    (one_gain: loss.gain_model), {"locus": (n, 3)} for the batch target with
    loss.ca_locus, {} otherwise (no gains, loss.method = "llnerf", or the batch's own
    estimate).
    """
    if not cfg.loss.use_gains or cfg.loss.method == "llnerf":
        return data, {}
    if estimates_from_frames(cfg):
        frames = estimate_frames(data, scene)  # binned once for every estimate
        d = estimate_downscale(frames, cfg.loss.ca_noise_ratio)
        if d > 1:
            print(f"L_ca estimates on the frames downscaled {d}x: their noise is above "
                  f"{cfg.loss.ca_noise_ratio:g} x their level (loss.ca_noise_ratio)")
        spread = None
        if cfg.loss.ca_illuminant == "consistent" or cfg.loss.gain_model == "auto":
            spread = light_spread(scene, cfg, frames, d)
        cfg = resolve_estimator(scene, cfg, frames, d, spread)  # "consistent" picked once
        if cfg.loss.ca_target == "map":  # its own anchor: of the whole capture or by region
            data, anchor = with_illuminant_map(data, scene, cfg, frames=frames, downscale=d)
        else:
            anchor = scene_illuminant(data, scene, cfg, frames, d)
        kwargs = {"scene_ill": jnp.asarray(anchor, jnp.float32)}
        if one_gain(cfg, None if spread is None else spread[0]):
            kwargs["one_gain"] = True
            why = ("loss.gain_model=global" if cfg.loss.gain_model == "global" else
                   f"one light: the maps stray {spread[0]:.2f} deg, under "
                   f"loss.ca_one_light_deg {cfg.loss.ca_one_light_deg:g}")
            print(f"colour: one gain for the capture, the L_ca target's ({why}); no gain "
                  "field is trained")
        elif cfg.loss.gain_model == "auto":
            print(f"colour: the gain field (lights mix: the maps stray {spread[0]:.2f} deg)")
        return data, kwargs
    if cfg.loss.ca_locus:
        return data, {"locus": jnp.asarray(illuminant.planckian_locus(scene.xyz_to_cam),
                                           jnp.float32)}
    return data, {}


def save_one_gain(run: Path, scene_ill) -> None:
    """<run>/one_gain.json: the capture's one gain, the von Kries gains of the L_ca
    target's anchor scene_ill (3,) (illuminant.gains_from_illuminant), with that
    illuminant (unit camera RGB)."""
    ill = np.asarray(illuminant.unit(np.asarray(scene_ill, np.float64)))
    record = {"illuminant": ill.tolist(),
              "gains": np.asarray(illuminant.gains_from_illuminant(ill), np.float64).tolist()}
    atomic.write_text(Path(run) / ONE_GAIN, json.dumps(record, indent=2) + "\n")


def load_one_gain(run: Path, cfg: Config) -> np.ndarray | None:
    """(3,) the run's one gain (save_one_gain) where its colour is one gain, None where it
    is the gain field (loss.gain_model "field", or "auto" that found lights mixing: no
    file) or a file that is not three positive finite numbers."""
    path = Path(run) / ONE_GAIN
    if cfg.loss.gain_model == "field" or not path.exists():
        return None
    try:
        gains = np.asarray(json.loads(path.read_text())["gains"], np.float64)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return gains if gains.shape == (3,) and np.all(np.isfinite(gains) & (gains > 0)) else None
