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


@dataclass(frozen=True)
class DataConfig(_Section):
    _SECTION = "data"
    binning: bool = True  # train on 2x2-binned camera RGB (True) or on the Bayer mosaic (False)
    downscale: int = 1  # extra box downscale of training images (1 = binned/raw resolution)
    eval_downscale: int = 1  # downscale of eval renders relative to the full frame / gt
    # "raw" (the method), "reference" (the oracle, trained on gt/, clean), "processed"
    # (2D + NeRF: trained on each frame processed by the 2D pipeline with a denoiser) or
    # "dark_srgb" (the LLNeRF-style row: each frame as a camera saves a dark photo, binned,
    # grey world, colour matrix, no brightening, sRGB curve; needs loss.method=llnerf)
    target: Literal["raw", "reference", "processed", "dark_srgb"] = "raw"
    # black level: "file" (the frames' BlackLevel tags); "dark": the file's plus per-CFA
    # offsets measured from lens-cap frames in <scene>/dark/ (gridnerf.darkframes), for
    # every use of the frames; "fit": per-CFA offsets fitted from the noise against the
    # field before the last stage (gridnerf.sensorfit), taken off the targets of the last
    # stage. Experimental: against a render the fit takes model error for shot noise
    # (bucket: offsets 3-4 DN off, 17.95 dB against 19.68 with "file"; docs/colour.md)
    black_offset: Literal["file", "fit", "dark"] = "file"
    # "file" only: where a black offset of darkframes.OFFSET_DN (4 DN, the ELD model's
    # largest) would be more than this share of the weakest colour's mean signal
    # (darkframes.offset_share), the frames take the lens-cap black level as under "dark"
    # when the scene has lens-cap frames, and training warns when it has none; 0: never.
    # At their own light the 21 simulated scenes sit at 0.08-0.35: it binds on none
    lens_cap_share: float = 0.5
    # the paper's darkness sweep: raw targets times this ratio after black-level removal
    exposure_ratio: float = 1.0

    def _check(self) -> None:
        self._range("exposure_ratio", 0.0, lo_open=True)
        self._range("lens_cap_share", 0.0)
        self._require("downscale", self.downscale >= 1, "a whole number >= 1")
        self._require("eval_downscale", self.eval_downscale >= 1, "a whole number >= 1")


@dataclass(frozen=True)
class GridConfig(_Section):
    _SECTION = "grid"
    # Coarse-to-fine vertex resolutions (x, y, z); one stage per entry. y = 0: from the image
    # aspect and the stage's box, so y voxels have the pixel footprint of x voxels.
    # Three stages up to ~2.5 binned training pixels per voxel on a 480x270 capture: the
    # 64x64x32 grid was at the resolution ceiling (the oracle matched an 8x-downscaled
    # reference) and lost to a single binned frame on high-frequency scenes.
    resolutions: tuple[tuple[int, int, int], ...] = ((48, 0, 24), (96, 0, 48), (192, 0, 64))
    sh_degree: int = 0  # spherical-harmonic degree of the low-light colour (0 = no view dependence)
    init_density: float = -4.0  # raw density at init (softplus: sigma 0.018 per voxel)
    # "visibility": max ray weight over training rays; "density": the vertex's own alpha;
    # "ray_mass": vertices some training ray needs to keep grid.prune_mass of its weight;
    # "guarded": visibility, then the vertices that rays it would empty need (their opacity
    # falling below grid.prune_guard of what it was) are given back.
    # A weight threshold alone cuts dim walls out whole where their weight spreads over many
    # samples (mixed_desk_daylight: 0.7 % of the training rays black after the first carving,
    # the data loss 0.10 -> 2.0, 13.2 dB) and holes into bucket's table (7 % of its rays);
    # ray_mass keeps 92-100 % of the box where the coarse stage is fog (held_arc_table) and
    # rays then cross more occupied samples than render.max_samples (-3.3 dB there).
    prune_mode: Literal["visibility", "density", "ray_mass", "guarded"] = "visibility"
    prune_mass: float = 0.9  # "ray_mass", "guarded": share of a ray's weight that is kept
    # "guarded": a ray rendering at least prune_guard_acc opacity is emptied when carving
    # leaves it less than prune_guard of it (render.carving_rescue). At 0.1 the few thin
    # fog rays of deer (opacity 0.31-0.39) filled 70 % of its stage-1 box and became
    # floaters (19.15 -> 17.95 dB); at 0.5 deer is left as it was (19.01) while the
    # smeared walls of bucket and mixed_desk_daylight (opacity 0.3-0.8) are still rescued
    prune_guard: float = 0.2
    prune_guard_acc: float = 0.5
    # carve vertices whose weight (or alpha) is below this; 0.01 kept 96% of the coarse
    # box (thin fog reaches 1% somewhere), 0.05 keeps ~50% at the same PSNR but cuts holes
    # into dim surfaces (bucket's table, box's wooden floor render black there). 0.02 was
    # tried as the default: bucket and box gained, but deer kept 90% of the coarse box and
    # its fog turned into floaters (19.45 -> 18.43 dB, SSIM 0.655 -> 0.563)
    prune_threshold: float = 0.05
    prune_dilate: int = 1  # keep this many vertices around survivors when pruning
    # NDC box across x/y: "reference" +-1.25 (the mean camera's frustum and a margin) or
    # "frustums" (every training camera's frustum: arcs and slides see far beyond the mean)
    ndc_xy: Literal["reference", "frustums"] = "reference"
    fit_box: bool = True  # after the first stage, shrink the box to the visible content
    # refit x/y too (False: depth only; in a forward-facing capture every pixel sees
    # something, so the cameras, not the content, bound x/y: dim sky can fall below the
    # mass quantile and be cut off)
    fit_xy: bool = True
    fit_quantile: float = 0.005  # rendered mass left outside the fitted box at each end
    fit_margin: float = 2.0  # margin around the content, in voxels of the first stage
    # what a ray sees behind the grid: "mean" (the capture's mean colour: every ray of a
    # capture ends on something, so a dark texture is not rendered as transparency for
    # free; box: the table's dark wood grain was carved into black holes, 19.41 -> 19.94 dB;
    # the nine scenes' mean 20.74 -> 21.28, but SSIM lower on six of them: brick and print
    # soften, docs/reconstruction.md "Session 8") or "black" (nothing: the compositing of
    # NeRF without a background)
    background: Literal["black", "mean"] = "mean"
    occupancy_threshold: float = 0.005  # cells whose max alpha is below this are skipped
    occupancy_every: int = 100  # refresh the empty-space bitmask every this many steps

    def _check(self) -> None:
        self._require("resolutions", len(self.resolutions) >= 1
                      and all(min(r[0], r[2]) >= 2 and (r[1] >= 2 or r[1] == 0)
                              for r in self.resolutions),
                      "one [x,y,z] per stage, each vertex count >= 2 (y may be 0: from the "
                      "image aspect), e.g. [[48,0,24],[64,0,32]]")
        self._require("sh_degree", 0 <= self.sh_degree <= MAX_SH_DEGREE,
                      f"a whole number from 0 to {MAX_SH_DEGREE}")
        self._range("init_density")
        self._range("prune_threshold", 0.0, 1.0)
        self._range("prune_mass", 0.0, 1.0, lo_open=True)
        self._range("prune_guard", 0.0, 1.0)
        self._range("prune_guard_acc", 0.0, 1.0)
        self._require("prune_dilate", self.prune_dilate >= 0, "a whole number >= 0")
        self._range("fit_quantile", 0.0, 0.5, hi_open=True)
        self._range("fit_margin", 0.0)
        self._range("occupancy_threshold", 0.0, 1.0, hi_open=True)
        self._require("occupancy_every", self.occupancy_every >= 1, "a whole number >= 1")


@dataclass(frozen=True)
class RenderConfig(_Section):
    _SECTION = "render"
    samples_per_voxel: float = 1.5  # candidate samples per voxel along a ray (cheap bitmask test)
    # Kept (occupied) samples per ray after empty-space skipping. Uncarved coarse grids make
    # NDC rays cross ~50 occupied candidates: 48 truncated them before the back wall
    # (held_arc_brick: -1.3 dB, oracle too); the carved 192x108x64 stage has <= 49.
    max_samples: int = 64
    chunk: int = 8192  # rays per chunk when rendering whole images
    skip_empty: bool = True  # False: every candidate sample is shaded, K = N (tests, benchmarks)
    # static candidate count N per ray; 0: fitted to the rays (training: each stage's
    # training rays, stages.with_fitted_candidates; images: render.image_config), at most the
    # count that crosses the box diagonal
    n_candidates: int = 0

    def _check(self) -> None:
        self._range("samples_per_voxel", 0.0, lo_open=True)
        self._require("max_samples", self.max_samples >= 1, "a whole number >= 1")
        self._require("chunk", self.chunk >= 1, "a whole number >= 1")
        self._require("n_candidates", self.n_candidates >= 0, "a whole number >= 0 (0 = auto)")


@dataclass(frozen=True)
class LossConfig(_Section):
    _SECTION = "loss"
    w_data: float = 1.0  # lambda_1, RawNeRF linearised log-L2 on the raw
    # epsilon of that term, (C - y)^2 / (sg(C) + eps)^2: RawNeRF's 1e-3 in normalised raw
    # ("absolute"), or data_eps x the training data's mean level ("level": a raw scaled by
    # gamma trains alike at every gamma). Absolute, it makes the fit depend on the raw's
    # scale: on bucket (mean level 0.0022) gamma 0.1 scored 16.06 dB against gamma 1's 21.46;
    # "level" with data_eps 0.5 scored 21.48 at both (docs/report.md, darkness sweep). At the
    # simulator's levels the two are equal within the seed spread (ablate.py --study eps,
    # sessions 24-25, held-out scenes included), so "absolute" stays the default.
    data_eps: float = 1e-3
    data_eps_mode: Literal["absolute", "level"] = "absolute"
    # "absolute" on raw targets: the eps never exceeds this many noise sigmas of the
    # training frames (data_term.data_noise), so a darker or lower-gain raw is weighed alike
    # (0 = no cap). The loss depends on eps / sigma alone (a raw scaled by gamma is the same
    # fit at the same ratio); bucket's darkness sweep, the one scene chosen on, is best at
    # 1.6-2.2 sigma (gamma 0.8 / 0.6: 21.50 / 21.48 dB) and loses past it (3.2 sigma:
    # -0.18, 4.3: -0.49, 13: -5.4). At gamma 1 every simulated scene's 1e-3 is 0.86-1.44
    # sigma, so the cap binds only on darker captures (session 27, docs/report.md)
    data_eps_sigmas: float = 2.0
    w_ca: float = 0.1  # lambda_2, chromatic adaptation loss (eq. 14)
    w_smooth: float = 0.1  # lambda_3, local smoothness of the gains (eq. 15 or grid TV)
    # "patch" (eq. 15 on ray patches), "tv" (edge-aware gain TV), "both"
    smooth_mode: Literal["patch", "tv", "both"] = "tv"
    ca_stop_grad: bool = True  # stop gradients through the batch channel means Cbar_k
    tv_density: float = 1e-2  # TV weight on density
    tv_rgb: float = 1e-2  # TV weight on the low-light colour
    sparsity: float = 1e-3  # weight of the Cauchy sparsity prior on density (free space)
    # "cauchy": log(1 + 2 sigma^2); "l1": sigma (removes fog)
    sparsity_mode: Literal["cauchy", "l1"] = "cauchy"
    distortion: float = 0.0  # weight of the mip-NeRF 360 distortion loss (voxel units)
    # weight of mean (1 - acc)^2: every ray of a capture ends on a surface. With the grey
    # backdrop (grid.background) alone, deer's table was left transparent where its colour
    # is near the capture's mean (grey patches in novel views, 19.20 dB); 0.1 fills them
    # (19.51; box 19.94 either way). Over black, 0.1-0.5 cost box SSIM (0.67 -> 0.62)
    opacity: float = 0.1
    # the opacity prior acts in the first `opacity_stages` stages only (0: in every stage).
    # Holes are made in the coarse stage and carving keeps them; later stages left free of
    # the prior can sharpen texture that the prior would blur into an opaque mean. 1 (the
    # coarse stage): scoreboard SSIM 0.530 -> 0.576 (16.69 -> 16.76 dB), dev_slide_bench
    # 0.596 -> 0.604, box and dev_arc_shop within 0.02 dB (docs/reconstruction.md, session 9)
    opacity_stages: int = 1
    tv_fraction: float = 0.25  # fraction of voxels sampled per step for TV terms
    use_gains: bool = True  # False: ablation without the colour-restoration (gain) field
    # gain map of L_ca and the patch smoothness: "normalized" = S / acc composited with
    # stop-gradient weights (the colour prior never moves density); "raw" = S as rendered
    gain_map: Literal["normalized", "raw"] = "normalized"
    # The L_ca target K_avg / C_k comes from an illuminant estimate C. Default: once per
    # capture ("scene") from every training frame's binned raw, the per-channel median of
    # grey world, shades of grey (p = 6) and grey edge, each projected onto the camera's
    # Planckian locus ("consensus", illuminant.consensus; scene target only). Chosen on the
    # nine built-in scenes: raw-frame angular error mean / worst of the nine (all + locus):
    # grey world 5.27 / 9.32 deg, grey edge 3.48 / 8.97 (dora), shades of grey 3.10 / 6.67
    # (scoreboard), consensus 3.26 / 5.98. Trained: shades of grey alone took dora from
    # 19.52 to 22.90 dB but scoreboard from 18.77 to 14.52 (a blue cast, CIEDE2000 18.55:
    # its bright orange digits lead the p = 6 mean); grey world tints scenes whose mean is
    # not grey (doll 19.19 dB against 21.97 with grey edge).
    # "consistent" (the default since session 22): the consensus where the capture's
    # illuminant maps show lights mixing, and where they do not (one light: the maps stray
    # less than ca_one_light_deg from the consensus, illum_map.map_spread_deg) the one of
    # its three estimators whose estimates on the frames' four quadrants agree best
    # (illuminant.quadrant_spreads): on the raw frames, nine 3.33 -> 2.83 deg, held out
    # 3.29 -> 2.20 (experiments/estimator_choice.py). Trained (docs/colour.md, session
    # 20): nine 21.63 -> 21.89 dB / CIEDE2000 10.57 -> 10.05, held out 19.17 -> 19.56 /
    # 13.30 -> 12.34; scene and map targets only
    ca_illuminant: Literal["grey_world", "shades_of_grey", "grey_edge", "weighted_grey",
                           "consensus", "consistent"] = "consistent"
    # "consistent": the map spread (deg) below which a capture counts as lit by one light.
    # Chosen between the nine, tuning and tuned mixed-light scenes' spreads (single light
    # at most 2.42, head; mixed light at least 4.05, mixed_desk_daylight), before the
    # held-out scenes' were looked at for this use
    ca_one_light_deg: float = 3.0
    # what carries the colour restoration: "field" (the paper: per-voxel von Kries gains,
    # trained by L_ca and the smoothness), "global" (one gain for the capture: the gains of
    # the L_ca target's anchor, the capture's illuminant; no gain terms in the steps), or
    # "auto": one gain where the capture is lit by one light (its illuminant maps stray
    # less than ca_one_light_deg from the consensus, the "consistent" pick's own test) and
    # the field where lights mix. With one gain the steps train density and colour alone
    # (the data term gives the gains no gradient, and L_ca on the normalised gain map
    # none to the density or the colour), so the field is the same and the step cheaper;
    # the gain is kept in <run>/one_gain.json (colour_target.save_one_gain). Measured
    # (session 29, docs/colour.md): bucket's training 110 -> 92 s; under one light "auto"
    # is 0.2 dB below the field with the file's black level and level with it with the
    # lens-cap one (nine -0.08, held out -0.05 dB, CIEDE2000 lower); the one-light test
    # misreads two of four held-out mixed-light scenes (-0.6 to -0.7 dB): not the default
    gain_model: Literal["field", "auto", "global"] = "field"
    ca_illuminant_p: float = 6.0  # Minkowski p of shades_of_grey (grey_edge uses p = 1)
    # the capture's illuminant estimates (and the "consistent" pick) run on the binned
    # frames box-downscaled by the smallest power of 2 that brings their noise sigma under
    # this share of their mean level (colour_target.estimate_downscale): shades of grey's
    # p-norm and grey edge's gradients measure the noise where it rivals the signal (at a
    # tenth of the light the pick took the noise's own colour, 13-14 deg off). 0.6 sits
    # above every kept run's ratio (at most 0.52, scoreboard's lens-cap frames), so the
    # simulated scenes at their own light keep the full frames; 0: never
    ca_noise_ratio: float = 0.6
    # project the L_ca illuminant estimate onto the Planckian locus of the camera (from the
    # raw file's ColorMatrix): removes the green-magenta part of the estimator's error
    # (fluorescent/LED light lies up to |Duv| ~0.01 off the locus: set false for such light)
    ca_locus: bool = True
    # where the L_ca illuminant is estimated: "map" (default): the capture's illuminant,
    # varied over each training frame where smooth chromaticity gradients show lights of
    # different colour mixing (gridnerf.illum_map: Retinex; one light gives a flat map, so
    # the data, not a flag, decide between one gain and a field; docs/colour.md, session
    # 15: the mixed-light scenes +0.2 to +2.0 dB over "scene", the nine within 0.2 dB of
    # it); "scene": one estimate, once, before training, from every training frame's binned
    # raw (all pixels instead of one batch's 4096 rays, so the target does not wander from
    # step to step; reports/illuminants.md scores it on the raw frames); "batch" (the
    # paper): from each batch's rendered low-light colour
    ca_target: Literal["batch", "scene", "map"] = "map"
    ca_map_block: int = 16  # "map": block side in training pixels (noise averages down)
    ca_map_tau: float = 0.1  # "map": log-chromaticity step above which blocks differ in paint
    # "map": what the maps are anchored to. "regions" (default): ca_illuminant on the map's
    # warm and cool halves apart, each less its mean map value (illum_map.regional_anchor):
    # two lights no longer pull one estimate towards the brighter one (mixed_desk_daylight:
    # 8.1 -> 6.1 deg per pixel, 21.64 -> 23.26 dB); "capture": ca_illuminant on all pixels
    ca_map_anchor: Literal["capture", "regions"] = "regions"
    # "brightnerf" (the method: gains, L_ca and smoothness on the raw) or "llnerf" (the
    # LLNeRF-style comparison row, gridnerf.llnerf: the dark sRGB frames of
    # data.target=dark_srgb, the colour split into lighting max_k c_k and reflectance, the
    # lighting enhanced as alpha v^gamma with log alpha, log gamma in the gain field)
    method: Literal["brightnerf", "llnerf"] = "brightnerf"
    # llnerf's enhancement losses in Zero-DCE's form (gridnerf.llnerf). Weights and level
    # from LLNeRF's released training script (github.com/onpix/LLNeRF scripts/trian.sh:
    # exposure_loss_mult 0.1, fixed_exposure 0.55, gray_loss_mult 0.1, alpha_ltv and
    # gamma_ltv_loss_mult 0.1 each; Zero-DCE's own E is 0.6)
    w_exposure: float = 0.1  # exposure control: mean |pooled mean intensity - level|
    exposure_level: float = 0.55  # E, the sRGB intensity the enhanced render is pushed to
    exposure_pool: int = 4  # side of the pooled regions of a ray patch (divides patch_size)
    w_color_constancy: float = 0.1  # sum over channel pairs of (mean_p - mean_q)^2
    w_enhance_tv: float = 0.1  # grid TV of log alpha and log gamma (losses.tv_loss)
    # llnerf's data term on the dark sRGB: "rawnerf" (RawNeRF's weighted L2, losses.data_loss,
    # as LLNeRF's released script trains, data_loss_type 'rawnerf'; the grid's priors were
    # weighed against this term) or "mse" (plain MSE: 6e-4 on the 160x90 test bucket against
    # 0.6 weighted, so the TV, opacity and sparsity priors would dominate the fit)
    llnerf_data: Literal["rawnerf", "mse"] = "rawnerf"

    def _check(self) -> None:
        for name in ("w_data", "w_ca", "w_smooth", "tv_density", "tv_rgb", "sparsity",
                     "distortion", "opacity", "w_exposure", "w_color_constancy",
                     "w_enhance_tv"):
            self._range(name, 0.0)
        self._range("tv_fraction", 0.0, 1.0, lo_open=True)
        self._range("data_eps", 0.0, lo_open=True)
        self._range("data_eps_sigmas", 0.0)
        self._range("ca_noise_ratio", 0.0)
        self._require("opacity_stages", self.opacity_stages >= 0,
                      "a whole number >= 0 (0: the opacity prior in every stage)")
        self._range("ca_illuminant_p", 1.0)
        self._require("ca_illuminant", self.ca_illuminant not in ("consensus", "consistent")
                      or self.ca_target != "batch", "one of 'grey_world', 'shades_of_grey', "
                      "'grey_edge', 'weighted_grey' with loss.ca_target=batch ('consensus' "
                      "and 'consistent' need loss.ca_target=scene or map)")
        self._range("ca_one_light_deg", 0.0)
        self._require("gain_model", self.gain_model == "field" or (
            self.ca_target != "batch" and self.method == "brightnerf"),
            "'field' with loss.ca_target=batch or loss.method=llnerf (one gain is the "
            "capture's L_ca target: loss.ca_target=scene or map)")
        self._require("ca_map_block", self.ca_map_block >= 2, "a whole number >= 2")
        self._range("ca_map_tau", 0.0, lo_open=True)
        self._range("exposure_level", 0.0, 1.0, lo_open=True, hi_open=True)
        self._require("exposure_pool", self.exposure_pool >= 1, "a whole number >= 1")


@dataclass(frozen=True)
class TrainConfig(_Section):
    _SECTION = "train"
    # optimisation steps of each stage. The last stage's 1200 (was 800): box 19.67 -> 20.04
    # and 19.71 -> 20.10 dB (seeds 0 and 1), dev_arc_shop 20.16 -> 20.21, for ~65 s more
    steps_per_stage: tuple[int, ...] = (600, 600, 1200)
    batch_patches: int = 64  # ray patches per step (coherent batches are faster)
    patch_size: int = 8  # patch side in pixels (rays per step = batch_patches * patch_size^2)
    lr_density: float = 0.3  # Adam learning rate of raw density, decayed 100x over each stage
    # Adam learning rate of the colour params. 0.1 (was 0.05): the colour of a voxel gets a
    # gradient from few rays of a batch, each dominated by photon noise, so Adam's steps
    # stay well below the rate and the last stage had not converged (box 20.01 dB at 1200
    # steps, 20.37 at 2400); 0.1 gave box 20.62 at 1200 steps, 0.2 20.54
    # (docs/reconstruction.md, session 10)
    lr_rgb: float = 0.1
    lr_gain: float = 0.02  # Adam learning rate of the log gains
    fine_density_lr_scale: float = 1.0  # density learning rate after the first stage, relative
    lr_decay: float = 0.01  # final/initial learning-rate ratio per stage (exponential)
    seed: int = 0  # PRNG seed for init and batches
    log_every: int = 50  # steps between metrics.jsonl lines
    checkpoint_every: int = 300  # steps between checkpoints
    checkpoint_seconds: float = 30.0  # also checkpoint when this long has passed (0 = off)

    def _check(self) -> None:
        self._require("steps_per_stage", len(self.steps_per_stage) >= 1
                      and all(s >= 1 for s in self.steps_per_stage),
                      "one step count >= 1 per grid.resolutions stage, e.g. [600,600,1200]")
        self._require("batch_patches", self.batch_patches >= 1, "a whole number >= 1")
        self._require("patch_size", self.patch_size >= 1, "a whole number >= 1")
        for name in ("lr_density", "lr_rgb", "lr_gain", "fine_density_lr_scale"):
            self._range(name, 0.0)
        self._range("lr_decay", 0.0, lo_open=True)
        self._require("seed", self.seed >= 0, "a whole number >= 0")
        self._require("log_every", self.log_every >= 1, "a whole number >= 1")
        self._require("checkpoint_every", self.checkpoint_every >= 1, "a whole number >= 1")
        self._range("checkpoint_seconds", 0.0)


@dataclass(frozen=True)
class OutputConfig(_Section):
    _SECTION = "output"
    use_color_matrix: bool = True  # camera->sRGB via the file's ColorMatrix (False: paper's)
    # which matrix: "d65" (the ColorMatrix for D65, row-normalised so that balanced white
    # stays white; RawNeRF's convention) or "adapted" (the DNG pipeline for the white the
    # gains balanced: ColorMatrix inverse, Bradford adaptation to D65). "adapted" is exact
    # on clean simulated data but scored lower on the trained runs (nine built-in scenes:
    # 20.40 against 20.74 dB, CIEDE2000 10.94 against 10.87; docs/colour.md)
    color_matrix: Literal["d65", "adapted"] = "d65"
    target_luminance: float = 0.18  # auto exposure: mean luminance of the bright training renders

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
        llnerf = self.loss.method == "llnerf"
        if (llnerf != (self.data.target == "dark_srgb") or llnerf and not self.loss.use_gains
                or llnerf and not self.data.binning):
            raise ConfigError(
                None, f"loss.method = {self.loss.method!r} with data.target = "
                f"{self.data.target!r}, loss.use_gains = {_dump(self.loss.use_gains)} and "
                f"data.binning = {_dump(self.data.binning)}",
                "use loss.method=llnerf with data.target=dark_srgb, loss.use_gains=true and "
                "data.binning=true (the llnerf preset), or neither")
        if llnerf and self.train.patch_size % self.loss.exposure_pool:
            raise ConfigError(
                None, f"loss.exposure_pool = {self.loss.exposure_pool} does not divide "
                f"train.patch_size = {self.train.patch_size}",
                "set loss.exposure_pool to a divisor of train.patch_size, e.g. 4 for 8")
        if self.data.black_offset == "fit" and (n_res < 2 or self.data.target != "raw"):
            raise ConfigError(None, "data.black_offset = 'fit' needs a field to fit against "
                              "(two or more stages) and the raw frames (data.target = raw)",
                              "use data.black_offset=file, or add a coarse stage")


_SECTIONS = {"data": DataConfig, "grid": GridConfig, "render": RenderConfig,
             "loss": LossConfig, "train": TrainConfig, "output": OutputConfig}


def _preset_tiny() -> Config:
    """Seconds-long runs for tests."""
    c = Config()
    return replace(
        c,
        # 40 coarse steps leave fog, not surfaces: carving at the default 0.05 would cut
        # the content (stage-1 loss x8), so carve only what no ray weighs by 1%
        grid=replace(c.grid, resolutions=((24, 24, 16), (40, 40, 24)), prune_threshold=0.01),
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


def _preset_processed() -> Config:
    """2D + NeRF (the paper's baseline family): the default grid trained, supervised, on
    the training frames each processed by the 2D pipeline (demosaic, grey world, colour
    matrix, auto exposure, non-local means), no gains, shown as it is."""
    o = _preset_oracle()
    return replace(o, data=replace(o.data, target="processed"))


def _preset_fast() -> Config:
    """Speed end of the speed-vs-error study: the default's first two stages only
    (48x27x24 -> 96x54x48, 600 + 600 steps)."""
    c = Config()
    return replace(c, grid=replace(c.grid, resolutions=((48, 0, 24), (96, 0, 48))),
                   train=replace(c.train, steps_per_stage=(600, 600)))


def _preset_fine() -> Config:
    """Accuracy end of the speed-vs-error study: the default's three stages, then a fourth
    at 288x162x96 (~1.6 binned training pixels per voxel across x) for 600 steps, up to 96
    occupied samples per ray."""
    c = Config()
    return replace(c, grid=replace(c.grid, resolutions=(*c.grid.resolutions, (288, 0, 96))),
                   render=replace(c.render, max_samples=96),
                   train=replace(c.train, steps_per_stage=(*c.train.steps_per_stage, 600)))


def _preset_llnerf() -> Config:
    """The LLNeRF-style row (Wang et al., ICCV 2023) on the default grid: trained on the
    dark sRGB frames (data.target=dark_srgb), colour = reflectance x lighting, the lighting
    enhanced per voxel (alpha v^gamma in the gain field) under LLNeRF's enhancement losses
    (gridnerf.llnerf); shown as enhanced, with no auto exposure."""
    c = Config()
    return replace(c, data=replace(c.data, target="dark_srgb"),
                   loss=replace(c.loss, method="llnerf"))


PRESETS: dict[str, Any] = {
    "llnerf": _preset_llnerf,
    "fast": _preset_fast,
    "fine": _preset_fine,
    "oracle": _preset_oracle,
    "processed": _preset_processed,
    "default": Config,
    "tiny": _preset_tiny,
    "nogain": lambda: replace(Config(), loss=replace(Config().loss, use_gains=False)),
    "patch": lambda: replace(Config(), loss=replace(Config().loss, smooth_mode="patch")),
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


# loss fields that only act through the gains: inert when loss.use_gains is false
GAIN_FIELDS = ("w_ca", "w_smooth", "smooth_mode", "ca_stop_grad", "gain_map", "ca_illuminant",
               "ca_illuminant_p", "ca_locus", "ca_target", "ca_map_block", "ca_map_tau",
               "ca_map_anchor", "ca_one_light_deg", "ca_noise_ratio", "gain_model")
# loss fields of loss.method = "llnerf" alone: inert in the other runs
LLNERF_FIELDS = ("w_exposure", "exposure_level", "exposure_pool", "w_color_constancy",
                 "w_enhance_tv", "llnerf_data")


# loss fields read only with loss.ca_target = "map"
MAP_FIELDS = ("ca_map_block", "ca_map_tau", "ca_map_anchor")
# What `effective` resets inert fields to: fixed values (the defaults before the colour
# default became the anchored illuminant map), not today's defaults, so that changing a
# default does not change what a run that never reads the field compares equal to (the
# cached results of experiments are keyed by it).
INERT_REFERENCE = LossConfig(ca_target="scene", ca_map_anchor="capture",
                             ca_illuminant="consensus", data_eps_sigmas=2.0,
                             ca_noise_ratio=0.6)


def eps_follows_noise(cfg: Config) -> bool:
    """Whether the data term's eps is absolute and weighs raw frames: the runs whose fit
    depends on the raw's scale, where loss.data_eps_sigmas caps it (data_term.with_data_eps_cap)
    and is otherwise inert."""
    return (cfg.loss.method == "brightnerf" and cfg.loss.data_eps_mode == "absolute"
            and cfg.data.target == "raw")


def effective(cfg: Config) -> Config:
    """cfg with the fields that cannot change its training reset to INERT_REFERENCE's
    values: the GAIN_FIELDS of a run without gains, so that two configs that train alike
    compare equal (cached experiment runs, e.g. the oracle, survive a change of the colour
    defaults), the LLNERF_FIELDS of a run that is not loss.method = "llnerf" (a
    loss.method = "llnerf" run reads only gain_map of the GAIN_FIELDS: llnerf.batch_terms
    replace L_ca and the smoothness), and the MAP_FIELDS of a run whose L_ca target is not
    the illuminant map, loss.data_eps_sigmas where the eps is not absolute or the
    targets are not raw frames, and data.lens_cap_share where the black level is not
    data.black_offset = "file"."""
    base = INERT_REFERENCE
    llnerf = cfg.loss.method == "llnerf"
    gain_inert = (GAIN_FIELDS if not cfg.loss.use_gains
                  else tuple(f for f in GAIN_FIELDS if f != "gain_map") if llnerf else ())
    inert = gain_inert + (() if llnerf else LLNERF_FIELDS)
    if not gain_inert and cfg.loss.ca_target != "map":
        inert += MAP_FIELDS
    if not eps_follows_noise(cfg):
        inert += ("data_eps_sigmas",)
    share = LEGACY[("data", "lens_cap_share")]
    if cfg.data.black_offset != "file" and cfg.data.lens_cap_share != share:
        cfg = replace(cfg, data=replace(cfg.data, lens_cap_share=share))  # read by "file" only
    if not inert:
        return cfg
    return replace(cfg, loss=replace(cfg.loss, **{k: getattr(base, k) for k in inert}))


def get(cfg: Config, dotted: str) -> Any:
    section, name = dotted.split(".")
    return getattr(getattr(cfg, section), name)


# (section, field) -> the value a saved config that lacks the field was trained with, for
# fields added with a default that changes behaviour (a run's config.json must describe it)
LEGACY = {("grid", "background"): "black", ("loss", "opacity_stages"): 0,
          ("loss", "data_eps"): 1e-3, ("loss", "data_eps_mode"): "absolute",
          ("loss", "ca_map_anchor"): "capture", ("loss", "ca_one_light_deg"): 3.0,
          # trained uncapped, but the cap binds on none of the runs kept when it came (the
          # frames' noise puts 1e-3 at 0.86-1.44 sigma on all 21 simulated scenes, file and
          # lens-cap black level); the darkness-sweep runs where it binds were trained again
          ("loss", "data_eps_sigmas"): 2.0,
          # trained before the gate, which binds on none of those runs (offset shares
          # 0.08-0.35 on all 21 simulated scenes at their own light); a run where it bound
          # keeps the lens-cap offsets in its black_level.json
          ("data", "lens_cap_share"): 0.5,
          # likewise: the frames' noise is under 0.6 of their level on every kept run
          ("loss", "ca_noise_ratio"): 0.6,
          # every run before it trained the field
          ("loss", "gain_model"): "field"}
# (section, field) -> the one value of a removed field whose behaviour the code still has:
# a saved config with another value was trained by code that no longer exists, so it must
# not load as today's config (unknown keys are otherwise ignored)
REMOVED = {("loss", "ca_on"): "rays"}  # per-sample L_ca, dropped in session 16


def from_dict(d: dict, source: Path | None = None) -> Config:
    """Config from `to_dict` output; unknown keys are ignored, missing ones take defaults
    (or their LEGACY value). ConfigError (naming `source`) for a value that does not
    validate, or for a REMOVED field set to a behaviour the code no longer has."""
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
            legacy = {k: v for (sec, k), v in LEGACY.items() if sec == f.name and k not in vals}
            for (sec, k), kept in REMOVED.items():
                if sec == f.name and k in vals and vals[k] != kept:
                    raise ConfigError(None, f"trained with {sec}.{k}={vals[k]!r}, an option "
                                      "that has since been removed (only "
                                      f"{kept!r} remains)", "delete the run folder and "
                                      "train it again")
            kwargs[f.name] = sub_cls(**legacy, **{k: _tupleize(v) for k, v in vals.items()
                                                  if k in known})
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
