"""Bright-NeRF (the method): a raw data term, per-voxel von Kries gains, L_ca, smoothness.

Trains the grid's low-light colour on the raw frames (data.target "raw"; "clean", a
simulated capture's noise-free raw, is the error budget's; "reference" and "processed" are
the oracle and 2D + NeRF rows, without gains) under RawNeRF's relative
L2 (losses.data_loss) and the gain field under the chromatic adaptation loss (eq. 14,
losses.ca_loss, its target from gridnerf.colour_target's plan) and the local smoothness
(edge-aware grid TV, losses.edge_aware_gain_tv, or eq. 15 on ray patches,
losses.smooth_loss_patch). Shown as rgb_low x gains through the sensor's colour matrix with
one auto exposure per run (gridnerf.outputs), beside the matrix-free output and one
grey-world gain for the capture on the same field (the reference a gain field must beat).
"""

from __future__ import annotations

import numpy as np

from gridnerf import colour_target, dataset, exposure, illuminant, losses, render
from gridnerf.config import CAMERA_RAW, Config
from gridnerf.errors import ConfigError
from gridnerf.outputs import Output, exposed, global_gains, training_render

NAME = "brightnerf"
MAIN_OUTPUT = "gridnerf"


def check(cfg: Config) -> None:
    """The terms that read the batch's ray patches need patches: eq. 15
    (loss.smooth_mode "patch") and the batch's grey edge (loss.ca_target "batch" with
    loss.ca_illuminant "grey_edge") differentiate across adjacent rays, and one-ray patches
    (train.patch_size 1, the default) have no neighbours."""
    lc = cfg.loss
    needs = ("loss.smooth_mode = 'patch'" if lc.smooth_mode == "patch" else
             "loss.ca_illuminant = 'grey_edge' with loss.ca_target = 'batch'"
             if lc.ca_target == "batch" and lc.ca_illuminant == "grey_edge" else None)
    if needs and cfg.train.patch_size < 2:
        raise ConfigError(None, f"{needs} needs ray patches, and train.patch_size = "
                          f"{cfg.train.patch_size}",
                          "also set train.patch_size=8 train.batch_patches=64 (the `patch` "
                          "preset's)")
    if cfg.train.colour_solve_iters > 0 and cfg.grid.sh_degree != 0:
        raise ConfigError(None, "train.colour_solve_iters solves view-independent colours, "
                          f"and grid.sh_degree = {cfg.grid.sh_degree}",
                          "set train.colour_solve_iters=0 or grid.sh_degree=0")


def fits_raw(cfg: Config) -> bool:
    """Whether the data term weighs raw frames with the eps (its fit then depends on the
    raw's scale, and data_term.capped_eps caps the eps at a few noise sigmas)."""
    return cfg.data.target == "raw"


def training_data(scene, cfg: Config) -> dataset.RayData:
    return dataset.training_data(scene, cfg.data)


def plan_colour(data, scene, cfg: Config, saved=None):
    return colour_target.plan_colour(data, scene, cfg, saved)


def init_log_gain(cfg: Config, colour, color_scale: float, grey_log_gain) -> np.ndarray:
    """The gains start at the L_ca target (the capture's illuminant as the steps hold it,
    float32), else at the data's grey world; zeros without gains."""
    if not cfg.loss.use_gains:
        return np.zeros(3)
    if colour.anchor is not None:
        anchor = np.asarray(colour.anchor, np.float32)
        return np.log(illuminant.gains_from_illuminant(anchor, floor=1e-6))
    return grey_log_gain


def batch_terms(structure, params, flat: dict, out: dict, shape, sample: dict, cfg: Config,
                step):
    """(terms, weights) of one batch: "data" (the raw against the render's low-light
    colour, eps step.data_eps) and, where the gains train (step.train_gains), "ca" (L_ca
    towards the ray's illuminant: its block of the frame's map, the capture's anchor, or
    the batch's own estimate, on the locus when given) and "smooth" (on the step's
    grid_sample `sample`, or eq. 15 on the batch's patches)."""
    lc = cfg.loss
    terms = {"data": losses.data_loss(out["rgb_low"], flat["target"], flat["mask"],
                                      step.data_eps)}
    if step.train_gains:
        # divided by the opacity: half-transparent rays are not pushed to target / acc
        gain = losses.normalized_gain(*render.frozen_density_gain(out))
        if lc.ca_target == "map":
            if "illuminant" not in flat:
                raise ValueError("loss.ca_target = 'map' needs the data's illuminant map "
                                 "(colour_target.with_illuminant_map)")
            c_ill = flat["illuminant"]  # (n, 3): each ray's block of its frame's map
        elif step.anchor is not None:
            c_ill = step.anchor
        elif lc.ca_illuminant != "grey_world" or step.locus is not None:
            c_ill = losses.batch_illuminant(lc.ca_illuminant, out["rgb_low"], out["acc"],
                                            shape, colour_target.ESTIMATOR_P)
            if step.locus is not None:
                c_ill = illuminant.to_locus(c_ill, step.locus)
        else:
            c_ill = None  # ca_loss's grey world of the batch (the paper's target)
        terms["ca"] = losses.ca_loss(out["rgb_low"], gain, illuminant=c_ill)
        if lc.smooth_mode == "patch":
            terms["smooth"] = losses.smooth_loss_patch(gain.reshape(shape),
                                                       out["rgb_low"].reshape(shape))
        else:
            terms["smooth"] = losses.edge_aware_gain_tv(sample)
    return terms, {"data": lc.w_data, "ca": lc.w_ca, "smooth": lc.w_smooth}


def outputs(structure, params, scene, cfg: Config, plan, out: dict | None = None
            ) -> dict[str, Output]:
    """The shown outputs, each exposed on the training render (outputs.training_render, or
    `out`): "gridnerf" (the colour matrix, or matrix-free without output.use_color_matrix),
    "gridnerf_matrix_free", and "global_grey_world" (the field's low-light colour times one
    grey-world gain for the capture, global_gains). Where the run's colour is one
    gain (plan.one_gain) the first two show the low-light colour times it. The colour
    matrix is the one the run takes as the sensor's (ColourPlan.sensor_matrix: the file's,
    or its camera model's reference where the frames chose it over the file's)."""
    out = training_render(structure, params, scene, cfg) if out is None else out
    raw_target = cfg.data.target in CAMERA_RAW
    one_gain = plan.one_gain
    ones = np.ones(3) if one_gain is None else np.asarray(one_gain, np.float64)
    source = "rgb_restored" if cfg.loss.use_gains and one_gain is None else "rgb_low"
    free = Output(source, ones, np.eye(3))
    sensor = plan.colour.sensor_matrix(scene.xyz_to_cam)
    shown = {
        "gridnerf": (Output(source, ones, exposure.display_matrix(sensor, raw_target))
                     if cfg.output.use_color_matrix else free),
        "gridnerf_matrix_free": free,
        "global_grey_world": Output("rgb_low", global_gains(out), exposure.display_matrix(
            sensor, raw_target and cfg.output.use_color_matrix)),
    }
    return exposed(shown, out, cfg.output.target_luminance)
