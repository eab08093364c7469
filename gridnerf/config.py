"""Run configuration: frozen dataclasses, named presets and `a.b=value` overrides.

The resolved config is saved as `config.json` in every run folder; `load`
reads it back, so a run can always be resumed or re-evaluated as trained.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class DataConfig:
    binning: bool = True  # train on 2x2-binned camera RGB (True) or on the Bayer mosaic (False)
    downscale: int = 1  # extra box downscale of training images (1 = binned/raw resolution)
    eval_downscale: int = 1  # downscale of eval renders relative to the full frame / gt
    target: str = "raw"  # "raw" (the method) or "reference": the oracle, trained on gt/ (clean)


@dataclass(frozen=True)
class GridConfig:
    # Coarse-to-fine vertex resolutions (x, y, z); one stage per entry.
    resolutions: tuple[tuple[int, int, int], ...] = ((48, 48, 24), (64, 64, 32))
    sh_degree: int = 0  # spherical-harmonic degree of the low-light colour (0 = no view dependence)
    init_density: float = -4.0  # raw density at init (softplus: sigma 0.018 per voxel)
    prune_mode: str = "visibility"  # "visibility": max ray weight over training rays; "density"
    prune_threshold: float = 0.01  # carve vertices whose weight (or alpha) is below this
    prune_dilate: int = 1  # keep this many vertices around survivors when pruning
    fit_box: bool = True  # after the first stage, shrink the box to the visible content
    fit_quantile: float = 0.005  # rendered mass left outside the fitted box at each end
    fit_margin: float = 2.0  # margin around the content, in voxels of the first stage
    occupancy_threshold: float = 0.005  # cells whose max alpha is below this are skipped
    occupancy_every: int = 100  # refresh the empty-space bitmask every this many steps


@dataclass(frozen=True)
class RenderConfig:
    samples_per_voxel: float = 1.5  # candidate samples per voxel along a ray (cheap bitmask test)
    max_samples: int = 48  # kept (occupied) samples per ray after empty-space skipping
    chunk: int = 8192  # rays per chunk when rendering whole images


@dataclass(frozen=True)
class LossConfig:
    w_data: float = 1.0  # lambda_1, RawNeRF linearised log-L2 on the raw
    w_ca: float = 0.1  # lambda_2, chromatic adaptation loss (eq. 14)
    w_smooth: float = 0.1  # lambda_3, local smoothness of the gains (eq. 15 or grid TV)
    smooth_mode: str = "tv"  # "patch" (eq. 15 on ray patches), "tv" (edge-aware gain TV), "both"
    ca_stop_grad: bool = True  # stop gradients through the batch channel means Cbar_k
    tv_density: float = 1e-2  # TV weight on density
    tv_rgb: float = 1e-2  # TV weight on the low-light colour
    sparsity: float = 1e-3  # weight of the Cauchy sparsity prior on density (free space)
    sparsity_mode: str = "cauchy"  # "cauchy": log(1 + 2 sigma^2); "l1": sigma (removes fog)
    distortion: float = 0.0  # weight of the mip-NeRF 360 distortion loss (voxel units)
    tv_fraction: float = 0.25  # fraction of voxels sampled per step for TV terms
    use_gains: bool = True  # False: ablation without the colour-restoration (gain) field


@dataclass(frozen=True)
class TrainConfig:
    steps_per_stage: tuple[int, ...] = (600, 1400)  # optimisation steps of each resolution stage
    batch_patches: int = 64  # ray patches per step (coherent batches are faster)
    patch_size: int = 8  # patch side in pixels (rays per step = batch_patches * patch_size^2)
    lr_density: float = 0.3  # Adam learning rate of raw density, decayed 100x over each stage
    lr_rgb: float = 0.05  # Adam learning rate of the colour params
    lr_gain: float = 0.02  # Adam learning rate of the log gains
    fine_density_lr_scale: float = 1.0  # density learning rate after the first stage, relative
    lr_decay: float = 0.01  # final/initial learning-rate ratio per stage (exponential)
    seed: int = 0  # PRNG seed for init and batches
    log_every: int = 50  # steps between metrics.jsonl lines
    checkpoint_every: int = 300  # steps between checkpoints


@dataclass(frozen=True)
class OutputConfig:
    use_color_matrix: bool = True  # camera->sRGB via the file's ColorMatrix (False: paper's)
    target_luminance: float = 0.18  # auto exposure: mean luminance of the bright training renders


@dataclass(frozen=True)
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    output: OutputConfig = field(default_factory=OutputConfig)


def _preset_tiny() -> Config:
    """Seconds-long runs for tests."""
    c = Config()
    return replace(
        c,
        grid=replace(c.grid, resolutions=((24, 24, 16), (40, 40, 24))),
        render=replace(c.render, max_samples=24),
        train=replace(
            c.train, steps_per_stage=(40, 40), batch_patches=8, log_every=10, checkpoint_every=40
        ),
    )


def _preset_oracle() -> Config:
    """The representational ceiling: the default grid trained (supervised) on the clean
    normal-light references of the training views, no gains, no colour matrix."""
    c = Config()
    return replace(c, data=replace(c.data, target="reference"),
                   loss=replace(c.loss, use_gains=False),
                   output=replace(c.output, use_color_matrix=False))


PRESETS: dict[str, Any] = {
    "oracle": _preset_oracle,
    "default": Config,
    "tiny": _preset_tiny,
    "nogain": lambda: replace(Config(), loss=replace(Config().loss, use_gains=False)),
    "patch": lambda: replace(Config(), loss=replace(Config().loss, smooth_mode="patch")),
}


def preset(name: str) -> Config:
    """The named preset (`default`, `tiny`, `nogain`, `patch`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]()


def _coerce(value: str, current: Any) -> Any:
    parsed = json.loads(value) if value[:1] in "[{(" or value in ("true", "false") else value
    if isinstance(current, bool):
        if isinstance(parsed, bool):
            return parsed
        raise ValueError(f"expected true/false, got {value!r}")
    if isinstance(current, int):
        return int(parsed)
    if isinstance(current, float):
        return float(parsed)
    if isinstance(current, tuple):
        return _tupleize(parsed)
    return parsed


def _tupleize(x: Any) -> Any:
    return tuple(_tupleize(v) for v in x) if isinstance(x, list | tuple) else x


def override(cfg: Config, items: list[str]) -> Config:
    """Apply `section.field=value` overrides, e.g. `train.steps_per_stage=[100,100]`."""
    for item in items:
        key, sep, value = item.partition("=")
        section, _, name = key.partition(".")
        if not sep or not hasattr(cfg, section) or not hasattr(getattr(cfg, section), name):
            raise ValueError(f"bad override {item!r}; use section.field=value (see config.json)")
        sub = getattr(cfg, section)
        sub = replace(sub, **{name: _coerce(value.strip(), getattr(sub, name))})
        cfg = replace(cfg, **{section: sub})
    return cfg


def to_dict(cfg: Config) -> dict:
    return dataclasses.asdict(cfg)


def from_dict(d: dict) -> Config:
    kwargs = {}
    for f in fields(Config):
        sub_cls = type(getattr(Config(), f.name))
        known = {sf.name for sf in fields(sub_cls)}
        vals = {k: _tupleize(v) for k, v in d.get(f.name, {}).items() if k in known}
        kwargs[f.name] = sub_cls(**vals)
    return Config(**kwargs)


def save(cfg: Config, path: Path) -> None:
    from gridnerf.checkpoint import atomic_write_text

    atomic_write_text(Path(path), json.dumps(to_dict(cfg), indent=2))


def load(path: Path) -> Config:
    return from_dict(json.loads(Path(path).read_text()))
