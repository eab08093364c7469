"""Run configuration: frozen, validated dataclasses, named presets and `a.b=value` overrides.

Every section checks its fields when it is built (types from the annotations, `Literal`
modes, ranges in `__post_init__`), so a bad preset, `--set` or config.json fails at once
with a `ConfigError` naming the field, the bad value and what is allowed.

The resolved config is saved as `config.json` in every run folder; `load`
reads it back, so a run can always be resumed or re-evaluated as trained.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import typing
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

from gridnerf import atomic
from gridnerf.errors import ConfigError

MAX_SH_DEGREE = 3  # gridnerf.grid.MAX_SH_DEGREE (not imported: config stays jax-free)


@functools.cache
def _hints(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _bad(section: str, name: str, value: Any, want: str) -> ConfigError:
    return ConfigError(None, f"{section}.{name} = {_dump(value)} is not allowed",
                       f"set {section}.{name} to {want}")


def _typed(section: str, name: str, value: Any, hint: Any, top: Any = None) -> Any:
    """`value` checked against the annotation `hint` (ints become floats for float fields,
    lists become tuples); ConfigError naming the field (and its whole value `top`)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    top = value if top is None else top
    if origin is Literal:
        if isinstance(value, str) and value in args:
            return value
        raise _bad(section, name, top, "one of " + ", ".join(repr(a) for a in args))
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise _bad(section, name, top, "true or false")
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise _bad(section, name, top, "a whole number")
    if hint is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        raise _bad(section, name, top, "a number")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise _bad(section, name, top, f"a list, e.g. {_example(hint)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_typed(section, name, v, args[0], top) for v in value)
        if len(value) != len(args):
            raise _bad(section, name, top, f"{len(args)} values, e.g. {_example(hint)}")
        return tuple(_typed(section, name, v, a, top)
                     for v, a in zip(value, args, strict=True))
    return value


def _example(hint: Any) -> str:
    args = typing.get_args(hint)
    if typing.get_origin(hint) is tuple:
        inner = [_example(args[0])] * 2 if args[-1] is Ellipsis else [_example(a) for a in args]
        return "[" + ",".join(inner) + "]"
    return "1" if hint is int else "1.0"


class _Section:
    """Validation shared by the config sections: types from the annotations, then `_check`."""

    _SECTION = ""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = _typed(self._SECTION, f.name, getattr(self, f.name), _hints(type(self))[f.name])
            object.__setattr__(self, f.name, value)
        self._check()

    def _check(self) -> None:
        pass

    def _require(self, name: str, ok: bool, want: str) -> None:
        if not ok:
            raise _bad(self._SECTION, name, getattr(self, name), want)

    def _range(self, name: str, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False, hi_open: bool = False) -> None:
        v = getattr(self, name)
        ok = math.isfinite(v)
        if lo is not None:
            ok = ok and (v > lo if lo_open else v >= lo)
        if hi is not None:
            ok = ok and (v < hi if hi_open else v <= hi)
        lo_s = "" if lo is None else f"{'>' if lo_open else '>='} {lo}"
        hi_s = "" if hi is None else f"{'<' if hi_open else '<='} {hi}"
        self._require(name, ok, "a finite number " + " and ".join(s for s in (lo_s, hi_s) if s))


# the data.target values in camera raw: shown through the colour matrix, trained with the
# gains, and the only ones with a Bayer mosaic (DataConfig.mosaic_from)
CAMERA_RAW = ("raw", "clean")


@dataclass(frozen=True)
class DataConfig(_Section):
    _SECTION = "data"
    # train on 2x2-binned camera RGB (true; but see mosaic_stages) or on the Bayer mosaic in
    # every stage (false)
    binning: bool = True
    # the last this many stages fit the raw Bayer mosaic photosite by photosite, the earlier
    # (coarse) ones the binned raw (0: binned throughout; target raw or clean, downscale 1;
    # none where the frames hold too few photons: gridnerf.data_term.MOSAIC_MIN_ELECTRONS)
    mosaic_stages: int = 1
    downscale: int = 1  # extra box downscale of the training frames (1 = binned/raw size)
    eval_downscale: int = 1  # downscale of eval renders relative to the full frame and gt/
    # training frames: "raw" (the capture), "reference" (gt/, clean: the oracle),
    # "processed" (each frame through the 2D pipeline with a denoiser: 2D + NeRF) or "clean"
    # (a simulated capture's noise-free raw: the error budget)
    target: Literal["raw", "reference", "processed", "clean"] = "raw"
    # black level: the file's tags, checked against the lens-cap frames of <scene>/dark/
    # where there are some (they replace the tags where they show them off), or "dark": the
    # lens-cap frames required
    black_offset: Literal["file", "dark"] = "file"
    exposure_ratio: float = 1.0  # raw targets times this after black-level removal (darkness)

    def _check(self) -> None:
        self._range("exposure_ratio", 0.0, lo_open=True)
        self._require("downscale", self.downscale >= 1, "a whole number >= 1")
        self._require("eval_downscale", self.eval_downscale >= 1, "a whole number >= 1")
        self._require("mosaic_stages", self.mosaic_stages >= 0, "a whole number >= 0")

    def mosaic_from(self, n_stages: int, mosaic_stages: int | None = None) -> int:
        """The first stage (0-based) that fits the Bayer mosaic: n_stages where none does.
        Only the camera's raw at its own size has a mosaic (CAMERA_RAW: the capture or its
        noise-free twin, downscale 1); every other target is a binned image, fitted binned
        throughout. mosaic_stages: the run plan's count (the photons may turn the mosaic
        stages off), None: the config's."""
        if self.target not in CAMERA_RAW or self.downscale != 1:
            return n_stages
        count = self.mosaic_stages if mosaic_stages is None else mosaic_stages
        return 0 if not self.binning else max(n_stages - count, 0)


@dataclass(frozen=True)
class GridConfig(_Section):
    _SECTION = "grid"
    # vertex counts (x, y, z) of each coarse-to-fine stage; y = 0: from the image aspect
    resolutions: tuple[tuple[int, int, int], ...] = ((48, 0, 24), (96, 0, 48), (192, 0, 64))
    sh_degree: int = 0  # spherical-harmonic degree of the low-light colour (0: no view dependence)
    prune_threshold: float = 0.05  # carve vertices no training ray weighs by more (weight, 0-1)
    fit_box: bool = True  # after the first stage, shrink the box to the visible content
    background: Literal["black", "mean"] = "mean"  # behind the grid: the capture's mean or black
    # the last stage's width (vertices across) where the stage before it leaves more detail
    # in its frames than the views' average leaves noise and the frames' photosites hold
    # it (gridnerf.residual; 288: the measured rule); 0 or no wider than the last: never
    detail_width: int = 0
    # capture pixels a vertex of the last stage may span across at most: where the capture
    # is wider, a stage twice as wide is appended (plan.appended_width; 0: never)
    voxel_pixels: float = 5.0

    def _check(self) -> None:
        self._range("voxel_pixels", 0.0)
        self._require("resolutions", len(self.resolutions) >= 1
                      and all(min(r[0], r[2]) >= 2 and (r[1] >= 2 or r[1] == 0)
                              for r in self.resolutions),
                      "one [x,y,z] per stage, each vertex count >= 2 (y may be 0: from the "
                      "image aspect), e.g. [[48,0,24],[64,0,32]]")
        self._require("detail_width", self.detail_width >= 0,
                      "0 (off) or a width, in vertices across, for the last stage")
        self._require("sh_degree", 0 <= self.sh_degree <= MAX_SH_DEGREE,
                      f"a whole number from 0 to {MAX_SH_DEGREE}")
        self._range("prune_threshold", 0.0, 1.0)


@dataclass(frozen=True)
class RenderConfig(_Section):
    _SECTION = "render"
    samples_per_voxel: float = 1.5  # candidate samples per voxel along a ray
    max_samples: int = 64  # occupied samples kept per ray after empty-space skipping (at most)
    # share of a stage's training rays whose occupied samples beyond the slots may be cut
    # off: each stage fits its slots to its rays (stages.fitted_samples; 0: max_samples)
    truncated_share: float = 0.005
    chunk: int = 8192  # rays per chunk when rendering whole images
    skip_empty: bool = True  # false: every candidate sample is shaded (tests, benchmarks)

    def _check(self) -> None:
        self._range("samples_per_voxel", 0.0, lo_open=True)
        self._require("max_samples", self.max_samples >= 1, "a whole number >= 1")
        self._range("truncated_share", 0.0, 1.0, hi_open=True)
        self._require("chunk", self.chunk >= 1, "a whole number >= 1")


@dataclass(frozen=True)
class LossConfig(_Section):
    _SECTION = "loss"
    method: Literal["brightnerf", "llnerf"] = "brightnerf"  # gridnerf.methods: the method trained
    w_data: float = 1.0  # lambda_1: RawNeRF's relative L2 on the raw (weight)
    data_eps: float = 1e-3  # eps of that term, (C - y)^2 / (sg(C) + eps)^2 (normalised raw)
    data_eps_sigmas: float = 2.0  # cap of data_eps in noise sigmas of the frames (0: no cap)
    w_ca: float = 0.1  # lambda_2: chromatic adaptation loss L_ca (eq. 14; weight)
    w_smooth: float = 0.1  # lambda_3: smoothness of the gains (weight)
    smooth_mode: Literal["patch", "tv"] = "tv"  # "tv": edge-aware grid TV; "patch": eq. 15
    tv_density: float = 1e-2  # TV weight on the density
    tv_rgb: float = 1e-2  # TV weight on the low-light colour
    tv_chroma: float = 1e-2  # TV weight on its chroma (log-like R - G, B - G) on top of tv_rgb
    sparsity: float = 1e-3  # weight of the Cauchy sparsity prior on the density
    opacity: float = 0.1  # weight of mean (1 - acc)^2: every ray ends on a surface
    opacity_stages: int = 1  # the opacity prior acts in this many first stages (0: all)
    tv_fraction: float = 0.1  # share of the grid's rows the grid priors sample per step
    # width (vertices across x) the TV weights are set for: a wider stage scales them by its
    # width over this (optim.tv_scale; 0: unset: a refined stage's are scaled against the
    # configured last width, an appended stage's by its footprint, plan.appended_tv_ref, and
    # the configured stages' then by theirs, plan.configured_tv; set: neither footprint rule)
    tv_ref_width: int = 0
    # what restores the colour: "field" (per-voxel von Kries gains), "global" (one gain for
    # the capture), "auto" (one gain under one light, the field where lights mix), "none"
    gain_model: Literal["field", "auto", "global", "none"] = "field"
    # the L_ca illuminant estimator; "consistent": picked per capture from the frames
    ca_illuminant: Literal["grey_world", "shades_of_grey", "grey_edge", "weighted_grey",
                           "consensus", "consistent"] = "consistent"
    ca_locus: bool = True  # project the illuminant estimate onto the camera's Planckian locus
    # where L_ca's illuminant comes from: each "batch", the whole "scene", or a per-frame "map"
    ca_target: Literal["batch", "scene", "map"] = "map"

    @property
    def use_gains(self) -> bool:
        """Whether the run has a colour restoration (gain_model is not "none")."""
        return self.gain_model != "none"

    def _check(self) -> None:
        for name in ("w_data", "w_ca", "w_smooth", "tv_density", "tv_rgb", "tv_chroma", "sparsity",
                     "opacity"):
            self._range(name, 0.0)
        self._range("tv_fraction", 0.0, 1.0, lo_open=True)
        self._require("tv_ref_width", self.tv_ref_width >= 0,
                      "a whole number >= 0 (0: the TV weights are never scaled)")
        self._range("data_eps", 0.0, lo_open=True)
        self._range("data_eps_sigmas", 0.0)
        self._require("opacity_stages", self.opacity_stages >= 0,
                      "a whole number >= 0 (0: the opacity prior in every stage)")
        self._require("ca_illuminant", self.ca_illuminant not in ("consensus", "consistent")
                      or self.ca_target != "batch", "one of 'grey_world', 'shades_of_grey', "
                      "'grey_edge', 'weighted_grey' with loss.ca_target=batch ('consensus' "
                      "and 'consistent' need loss.ca_target=scene or map)")
        self._require("gain_model", self.gain_model in ("field", "none")
                      or self.ca_target != "batch",
                      "'field' or 'none' with loss.ca_target=batch (one gain is the capture's "
                      "L_ca target: loss.ca_target=scene or map)")


@dataclass(frozen=True)
class TrainConfig(_Section):
    _SECTION = "train"
    steps_per_stage: tuple[int, ...] = (600, 600, 2100)  # optimisation steps of each stage
    batch_patches: int = 4096  # ray patches per step
    # patch side in pixels (rays per step = batch_patches * patch_size^2); 1: every ray
    # drawn on its own (patches only for loss.smooth_mode=patch or a batch grey edge)
    patch_size: int = 1
    lr_density: float = 0.3  # Adam learning rate of the raw density
    lr_rgb: float = 0.1  # Adam learning rate of the low-light colour
    lr_gain: float = 0.02  # Adam learning rate of the log gains
    lr_decay: float = 0.01  # final / initial learning rate over each stage (exponential)
    # steps over which each stage after the first ramps its rates up from 0 (linear): the
    # upsampled grid starts near its optimum, and Adam's first steps move every parameter
    warmup_steps: int = 0
    # L-BFGS iterations of the colour solve after the last stage (gridnerf.colour_solve: the
    # vertex colours fitted to every training ray with the geometry fixed); 0: none
    colour_solve_iters: int = 0
    seed: int = 0  # PRNG seed of the init and the batches
    log_every: int = 50  # steps between metrics.jsonl lines
    checkpoint_every: int = 300  # steps between checkpoints (also every CHECKPOINT_SECONDS)

    def _check(self) -> None:
        self._require("steps_per_stage", len(self.steps_per_stage) >= 1
                      and all(s >= 1 for s in self.steps_per_stage),
                      "one step count >= 1 per grid.resolutions stage, e.g. [600,600,1200]")
        self._require("batch_patches", self.batch_patches >= 1, "a whole number >= 1")
        self._require("patch_size", self.patch_size >= 1, "a whole number >= 1")
        for name in ("lr_density", "lr_rgb", "lr_gain"):
            self._range(name, 0.0)
        self._range("lr_decay", 0.0, lo_open=True)
        self._require("warmup_steps", self.warmup_steps >= 0, "a whole number >= 0")
        self._require("colour_solve_iters", self.colour_solve_iters >= 0,
                      "a whole number >= 0 (0: no colour solve)")
        self._require("seed", self.seed >= 0, "a whole number >= 0")
        self._require("log_every", self.log_every >= 1, "a whole number >= 1")
        self._require("checkpoint_every", self.checkpoint_every >= 1, "a whole number >= 1")


@dataclass(frozen=True)
class OutputConfig(_Section):
    _SECTION = "output"
    use_color_matrix: bool = True  # camera RGB -> sRGB by the sensor's ColorMatrix (false: none)
    target_luminance: float = 0.18  # auto exposure: mean luminance of the training renders

    def _check(self) -> None:
        self._range("target_luminance", 0.0, 1.0, lo_open=True)


@dataclass(frozen=True)
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def __post_init__(self) -> None:
        for f in fields(self):
            sub = getattr(self, f.name)
            if type(sub) is not _SECTIONS[f.name]:
                raise ConfigError(None, f"config section {f.name} is a {type(sub).__name__}",
                                  f"build it as a {_SECTIONS[f.name].__name__}")
        n_res, n_steps = len(self.grid.resolutions), len(self.train.steps_per_stage)
        if n_res != n_steps:
            raise ConfigError(
                None, f"train.steps_per_stage = {list(self.train.steps_per_stage)} has "
                f"{n_steps} stage(s) but grid.resolutions has {n_res}",
                "give one step count per resolution stage (set both together)")


_SECTIONS = {"data": DataConfig, "grid": GridConfig, "render": RenderConfig,
             "loss": LossConfig, "train": TrainConfig, "output": OutputConfig}


# The footing the presets other than the default and the studies were measured on
# (docs/results.md, "A tenth of the rows buys the steps"): the default without the chroma
# prior, its grid priors on a quarter of the rows, 1200 last-stage steps, max_samples slots
# per ray in every stage (none fitted to the rays), 64 ray patches of 8x8 a step. Each later
# change of the default joins it only where it was measured, so every kept result stays the
# run its config names; `--set` trains a preset on today's default footing instead.
FOOTING: tuple[str, ...] = ("loss.tv_chroma=0", "loss.tv_fraction=0.25",
                            "train.steps_per_stage=[600,600,1200]",
                            "render.truncated_share=0", "train.patch_size=8",
                            "train.batch_patches=64")


def _measured_footing(c: Config) -> Config:
    """c on FOOTING: where the presets other than the default were measured."""
    return override(c, list(FOOTING))


def _preset_tiny() -> Config:
    """Seconds-long runs for tests."""
    c = _measured_footing(Config())
    return replace(
        c,
        data=replace(c.data, mosaic_stages=0),  # binned throughout: the fastest
        # 40 coarse steps leave fog, not surfaces: carving at the default 0.05 would cut
        # the content (stage-1 loss x8), so carve only what no ray weighs by 1%
        # and no appended stage: tests train tiny grids on frames many pixels a vertex wide
        grid=replace(c.grid, resolutions=((24, 24, 16), (40, 40, 24)), prune_threshold=0.01,
                     voxel_pixels=0.0),
        render=replace(c.render, max_samples=24),
        train=replace(
            c.train, steps_per_stage=(40, 40), batch_patches=8, log_every=10, checkpoint_every=40
        ),
    )


def _preset_oracle() -> Config:
    """The representational ceiling: the default grid trained (supervised) on the clean
    normal-light references of the training views, no gains, no colour matrix."""
    c = _measured_footing(Config())
    return replace(c, data=replace(c.data, target="reference", mosaic_stages=0),
                   loss=replace(c.loss, gain_model="none"),
                   output=replace(c.output, use_color_matrix=False))


def _preset_processed() -> Config:
    """2D + NeRF (the paper's baseline family): the default grid trained, supervised, on
    the training frames each processed by the 2D pipeline (demosaic, grey world, colour
    matrix, auto exposure, non-local means), no gains, shown as it is."""
    o = _preset_oracle()
    return replace(o, data=replace(o.data, target="processed"))


def _preset_fast() -> Config:
    """Speed end of the speed-vs-error study: the default's first two stages only
    (48x27x24 -> 96x54x48, 600 + 600 steps)."""
    c = _measured_footing(Config())
    return replace(c, grid=replace(c.grid, resolutions=((48, 0, 24), (96, 0, 48))),
                   train=replace(c.train, steps_per_stage=(600, 600)))


def _preset_fine() -> Config:
    """Accuracy end of the speed-vs-error study: the three stages of FOOTING, then a fourth
    at 288x162x96 (~1.6 binned training pixels per voxel across x) for 600 steps, up to 96
    occupied samples per ray."""
    c = _measured_footing(Config())
    return replace(c, grid=replace(c.grid, resolutions=(*c.grid.resolutions, (288, 0, 96))),
                   render=replace(c.render, max_samples=96),
                   train=replace(c.train, steps_per_stage=(*c.train.steps_per_stage, 600)))


def _preset_llnerf() -> Config:
    """The LLNeRF-style row (Wang et al., ICCV 2023) on the default grid: trained on the
    dark sRGB frames made from the raw, colour = reflectance x lighting, the lighting
    enhanced per voxel (alpha v^gamma in the gain field) under LLNeRF's enhancement losses
    (gridnerf.methods.llnerf); shown as enhanced, with no auto exposure."""
    c = _measured_footing(Config())
    return replace(c, data=replace(c.data, mosaic_stages=0),
                   loss=replace(c.loss, method="llnerf"))


def _preset_nogain() -> Config:
    """No colour restoration (no gains, no L_ca, no smoothness): RawNeRF's fit on the grid,
    the report's RawNeRF + ISP row and the ablation's first. It fits the binned raw in
    every stage, as it was measured; the default's mosaic stage is measured on its own
    (`python -m experiments.ablate --study data_term`)."""
    c = _measured_footing(Config())
    return replace(c, data=replace(c.data, mosaic_stages=0),
                   loss=replace(c.loss, gain_model="none"))


def _preset_patch() -> Config:
    """The gains' smoothness as eq. 15 on ray patches instead of the grid TV (ablation)."""
    c = _measured_footing(Config())
    return replace(c, loss=replace(c.loss, smooth_mode="patch"))


PRESETS: dict[str, Any] = {
    "llnerf": _preset_llnerf,
    "fast": _preset_fast,
    "fine": _preset_fine,
    "oracle": _preset_oracle,
    "processed": _preset_processed,
    "default": Config,
    "tiny": _preset_tiny,
    "nogain": _preset_nogain,
    "patch": _preset_patch,
}


def preset(name: str) -> Config:
    """The named preset (`default`, `tiny`, `nogain`, `patch`, `oracle`, `processed`,
    `llnerf`, `fast`, `fine`)."""
    if name not in PRESETS:
        raise ConfigError(None, f"unknown preset {name!r}",
                          f"use --preset with one of {', '.join(sorted(PRESETS))}")
    return PRESETS[name]()


def _parse(section: str, name: str, text: str, current: Any) -> Any:
    """The typed value of `--set section.name=text` (validated later by the section)."""
    try:
        if text[:1] in "[{(" or text in ("true", "false"):
            return _tupleize(json.loads(text))
        if isinstance(current, bool):
            return text  # not true/false: the section names the field and the allowed values
        if isinstance(current, int):
            return int(text)
        if isinstance(current, float):
            return float(text)
    except ValueError:
        kind = "a whole number" if isinstance(current, int) else "a number"
        if isinstance(current, tuple):
            kind = "a JSON list"
        raise _bad(section, name, text, f"{kind} (now {_dump(current)})") from None
    return text


def _dump(value: Any) -> str:
    try:
        return json.dumps(value).replace(", ", ",")
    except (TypeError, ValueError):
        return repr(value)


def _tupleize(x: Any) -> Any:
    return tuple(_tupleize(v) for v in x) if isinstance(x, list | tuple) else x


def override(cfg: Config, items: list[str]) -> Config:
    """Apply `section.field=value` overrides, e.g. `train.steps_per_stage=[100,100]`.

    Every field is checked as it is set; the stage counts of grid.resolutions and
    train.steps_per_stage are compared once all items are applied. ConfigError otherwise.
    """
    sections = {f.name: getattr(cfg, f.name) for f in fields(Config)}
    for item in items:
        key, sep, value = item.partition("=")
        section, _, name = key.strip().partition(".")
        if not sep:
            raise ConfigError(None, f"bad override {item!r}",
                              "use section.field=value, e.g. train.batch_patches=32")
        if section not in sections:
            raise ConfigError(None, f"bad override {item!r}: no config section {section!r}",
                              f"use one of {', '.join(sections)}")
        known = [f.name for f in fields(sections[section])]
        if name not in known:
            raise ConfigError(None, f"bad override {item!r}: {section} has no field {name!r}",
                              f"use one of {', '.join(section + '.' + k for k in known)}")
        sub = sections[section]
        sections[section] = replace(sub, **{name: _parse(section, name, value.strip(),
                                                         getattr(sub, name))})
    return Config(**sections)


def to_dict(cfg: Config) -> dict:
    return dataclasses.asdict(cfg)


def diff(a: Config, b: Config) -> list[str]:
    """`section.field` names whose values differ between a and b."""
    da, db = to_dict(a), to_dict(b)
    return [f"{s}.{k}" for s in da for k in da[s] if da[s][k] != db[s][k]]


def get(cfg: Config, dotted: str) -> Any:
    section, name = dotted.split(".")
    return getattr(getattr(cfg, section), name)


# fields added after configs were saved, each with the value that trains as the code did
# before it: a saved config without the field is read with that value (from_dict), and
# experiments.common.fingerprint leaves the field out at that value, so the kept results
# of configs that do not use it stay valid
ADDED_FIELDS = {("data", "mosaic_stages"): 0, ("train", "warmup_steps"): 0,
                ("loss", "tv_chroma"): 0.0, ("render", "truncated_share"): 0.0,
                ("loss", "tv_ref_width"): 0, ("train", "colour_solve_iters"): 0,
                ("grid", "detail_width"): 0,
                # 5 trains as the code did before on every capture up to 960 pixels across,
                # which every kept result is; a run's appended stage is read from its plan
                ("grid", "voxel_pixels"): 5.0}


def from_dict(d: dict, source: Path | None = None) -> Config:
    """Config from `to_dict` output; unknown keys are ignored, missing ones take defaults
    (a field of ADDED_FIELDS its old behaviour's value). ConfigError (naming `source`) for
    a value that does not validate."""
    if not isinstance(d, dict):
        raise ConfigError(source, "the config is not a JSON object",
                          "delete it (train writes it again) or restore it")
    try:
        kwargs = {}
        for f in fields(Config):
            sub_cls = _SECTIONS[f.name]
            known = {sf.name for sf in fields(sub_cls)}
            vals = d.get(f.name) or {}
            if not isinstance(vals, dict):
                raise ConfigError(None, f"section {f.name} is not an object", "restore it")
            old = {k: v for (sec, k), v in ADDED_FIELDS.items() if sec == f.name}
            kwargs[f.name] = sub_cls(**{**old, **{k: _tupleize(v) for k, v in vals.items()
                                                  if k in known}})
        return Config(**kwargs)
    except ConfigError as e:
        if source is None:
            raise
        raise ConfigError(source, e.problem, e.fix) from None


def save(cfg: Config, path: Path) -> None:
    atomic.write_text(Path(path), json.dumps(to_dict(cfg), indent=2))


def load(path: Path) -> Config:
    """The config saved at `path`; ConfigError naming the file if it cannot be used."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError(path, f"cannot read the run's config ({exc})",
                          "restore it, or delete the run folder to train again") from None
    return from_dict(d, source=path)
