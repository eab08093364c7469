"""The methods a run can train, behind one small interface (loss.method picks one).

A method is a module with:

    NAME: str                  the loss.method value
    MAIN_OUTPUT: str           the output written as <view>_pred and along camera paths
    check(cfg)                 ConfigError where the config cannot train this method
    fits_raw(cfg) -> bool      whether its data term weighs raw frames with loss.data_eps
    training_data(scene, cfg) -> dataset.RayData
                               its training targets
    plan_colour(data, scene, cfg, saved) -> (RayData, plan.ColourPlan)
                               what it decides about colour before training (saved: a
                               resumed run's plan.ColourPlan, kept)
    init_log_gain(cfg, colour, color_scale, grey_log_gain) -> (3,)
                               the log gains the grid starts from
    batch_terms(structure, params, flat, out, shape, sample, cfg, step) -> (terms, weights)
                               its loss terms of one batch (the shared grid priors are
                               gridnerf.optim's), sample: the step's losses.grid_sample,
                               step: the stage's plan.StepPlan
    outputs(structure, params, scene, cfg, plan, out=None) -> {name: output}
                               how a trained run is shown (objects with .show(render) ->
                               (rgb_linear, rgb_srgb), gridnerf.outputs)

Bright-NeRF (gridnerf.methods.brightnerf) is the method; the LLNeRF-style comparison row
(gridnerf.methods.llnerf) trains on dark sRGB frames under its own enhancement losses.
The oracle and 2D + NeRF rows are Bright-NeRF without gains on other targets
(data.target).
"""

from __future__ import annotations

from types import ModuleType

from gridnerf.methods import brightnerf, llnerf

METHODS: dict[str, ModuleType] = {m.NAME: m for m in (brightnerf, llnerf)}


def get(name: str) -> ModuleType:
    """The method module of loss.method `name` (KeyError for an unknown one: the config's
    Literal has already refused it)."""
    return METHODS[name]
