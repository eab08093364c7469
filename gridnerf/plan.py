"""The run plan: every decision a training makes from the frames, typed, frozen, saved.

The config (gridnerf.config) is what the user asked for; it is never rewritten. What
training decides at run time from the capture goes here instead, is saved as
<run>/plan.json beside config.json, and is what the step, a resume, eval and render read:

- the black level the frames take (the file's, or the lens-cap frames' offsets on top
  where they show the file's off, gridnerf.data_term.black_level, or under
  data.black_offset = "dark");
- the data term's eps (loss.data_eps capped at loss.data_eps_sigmas noise sigmas) and the
  noise sigma it was capped against;
- how far the binned frames are box-downscaled: data.downscale, or more where a final voxel
  spans many capture pixels (gridnerf.data_term.planned_downscale);
- how many last stages fit the raw mosaic: data.mosaic_stages, or none where the frames
  hold too few photons per photosite (gridnerf.data_term.planned_mosaic_stages);
- the colour (ColourPlan): which estimator "consistent" picked, the capture's illuminant
  (the L_ca target's anchor, where the gains start), one gain or the gain field;
- per stage: the opacity prior's weight and the fitted candidate count of the step;
- the lens falloff: estimated from the frames and taken off (gridnerf.vignetting), or
  corrected by the raw files' own opcodes on loading (gridnerf.raw_layout);
- the last stage's width: the config's, or grid.detail_width where the stage before it
  leaves more detail in its frames than the views average the noise to (gridnerf.residual);
- a stage appended after the config's last, twice as wide, where a vertex of the last
  would span more capture pixels than grid.voxel_pixels (appended_width).

The plan is built once before the first step (candidate counts are filled in as each
stage's grid is made: `with_candidates`); a resumed run reads it back and keeps it.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from gridnerf import atomic
from gridnerf.errors import CheckpointError

PLAN = "plan.json"
# steps of the last configured stage and of the stage grid.voxel_pixels appends after it
# (fixed in code, measured at 1920x1080: 3600 appended steps against 2400 gained 0.09 to
# 0.16 dB on four captures for about 140 s of a 2-core machine; docs/results.md)
APPENDED_STEPS = (1200, 3600)
# what a plan saved before it recorded them trained: (1200, 2400)
APPENDED_STEPS_BEFORE = (1200, 2400)
# capture pixels across a vertex of the last stage where the grid priors' weights were set:
# 480x270 captures and the 192-wide last stage (appended_tv_ref, configured_tv)
TV_FOOTPRINT = 2.5


@dataclass(frozen=True)
class ColourPlan:
    """What restores the colour and what L_ca pulls it towards.

    model: "field" (per-voxel gains trained by L_ca and the smoothness), "one_gain" (one
    gain for the capture, `gains`; the steps train no gains) or "none" (no gains, or a
    method with its own colour terms). estimator: the illuminant estimator used on the
    frames ("consistent" resolved to the one it picked), None where nothing was estimated
    from the frames (the batch target, no gains). anchor: (3,) unit camera RGB, the
    capture's illuminant (the "scene" target, the "map" target's anchor), or None.
    light_spread_deg: how far the capture's illuminant maps stray from the consensus (the
    one-light test), None where it was not measured. estimate_downscale: the box
    downscale the estimates ran at. locus: whether the estimates were projected onto the
    Planckian locus of the sensor's matrix (loss.ca_locus where the frames agree with it:
    colour_target.locus_check); locus_matrix: the XYZ -> camera matrix (9,) row-major
    that the run takes as the sensor's where it is not the file's (its camera model's
    reference, which the frames agreed with where the file's matrix did not:
    colour_target.trusted_locus): the locus prior and the display both use it
    (sensor_matrix); None for the file's. evidence: {name: (3,)} what the frames say the light
    is, without the locus (the three estimators, the files' as-shot neutral, a white
    reference where given): the end-of-training check (gridnerf.shipped_colour) compares
    the shipped white with it. shipped_gains / shipped_why: the one gain shown in place of
    the gain field and why, where that check found the field's white implausible; None
    where the field is shown.
    """

    model: Literal["field", "one_gain", "none"] = "none"
    estimator: str | None = None
    anchor: tuple[float, float, float] | None = None
    gains: tuple[float, float, float] | None = None
    light_spread_deg: float | None = None
    estimate_downscale: int = 1
    locus: bool = False
    locus_matrix: tuple[float, ...] | None = None
    evidence: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    shipped_gains: tuple[float, float, float] | None = None
    shipped_why: str | None = None

    def sensor_matrix(self, file_matrix) -> np.ndarray:
        """(3, 3) the XYZ -> camera matrix the run takes as the sensor's: locus_matrix
        where the frames chose the camera model's reference over the file's ColorMatrix,
        else the file's (`file_matrix`, Scene.xyz_to_cam)."""
        if self.locus_matrix is None:
            return np.asarray(file_matrix, np.float64)
        return np.reshape(np.asarray(self.locus_matrix, np.float64), (3, 3))


@dataclass(frozen=True)
class RunPlan:
    """The decisions of one training run (module docstring).

    black_level: "file" or "lens_cap" (<run>/black_level.json's offsets added to the
    file's); data_noise: the training frames' noise sigma (normalised raw; None where not
    measurable); data_eps: the data term's eps the steps use; opacity: the opacity prior's
    weight in each stage; n_candidates: each stage's static candidate count per ray (0:
    not decided yet); vignetting: (k1, k2) the lens falloff exp(k1 r^2 + k2 r^4) taken off
    the training pixels (gridnerf.vignetting), None where none was found; file_falloff: the
    raw files' own falloff correction the loader applied (Scene.lens_correction, e.g.
    "FixVignetteRadial (OpcodeList3)"), None where they carried none. Where set, the
    frame-based estimate is skipped (train._vignetting), so vignetting stays None.
    photosite_snr: the frames' effective photo-electrons per green photosite
    (data_term.photosite_snr; None where not measured or not measurable); mosaic_stages:
    how many last stages fit the raw mosaic (data_term.planned_mosaic_stages), None where
    nothing was decided (no stage could fit the mosaic, data.binning off, or a plan saved
    before the decision existed): the config's data.mosaic_stages. downscale: the box
    downscale of the binned training frames (data_term.planned_downscale), None (a plan
    saved before the decision existed): the config's data.downscale. max_samples: each
    stage's occupied-sample slots per ray (stages.fitted_samples; 0: not decided yet), None
    (a plan saved before the decision existed): the config's render.max_samples; the last
    stage's is the finished run's (render_config). detail: what the last stage but one left
    of its frames' detail in units of the noise the views' average leaves
    (residual.read; None: not read or not measurable) and its standard error
    (detail_error); last_width: the last stage's width where the reading refined it
    (refined_config), None: the config's. appended_width: the width of the stage appended
    after the config's last (capture_config), None: none; appended_steps: the steps of the
    last configured stage and of the appended one (APPENDED_STEPS when the plan was made;
    None: none appended, or a plan saved before they were recorded, see
    trained_appended_steps); appended_tv_ref: the loss.tv_ref_width the appended stage's
    TVs were scaled against (appended_tv_ref; None: none appended, or a plan saved before
    it was recorded: the config's, else its last configured width); configured_tv: the
    factor on the TVs of the configured stages where a stage is appended (configured_tv;
    None: none appended, loss.tv_ref_width set, or a plan saved before it was recorded:
    the weights as configured).
    """

    method: str
    black_level: Literal["file", "lens_cap"]
    data_noise: float | None
    data_eps: float
    colour: ColourPlan
    opacity: tuple[float, ...]
    n_candidates: tuple[int, ...]
    vignetting: tuple[float, float] | None = None
    file_falloff: str | None = None
    photosite_snr: float | None = None
    mosaic_stages: int | None = None
    downscale: int | None = None
    max_samples: tuple[int, ...] | None = None
    detail: float | None = None
    detail_error: float | None = None
    last_width: int | None = None
    appended_width: int | None = None
    appended_steps: tuple[int, int] | None = None
    appended_tv_ref: int | None = None
    configured_tv: float | None = None

    @property
    def one_gain(self) -> tuple[float, float, float] | None:
        """(3,) the capture's one gain where the colour is one gain (trained so, or shown so
        by the end-of-training check: colour.shipped_gains), else None."""
        if self.colour.model == "one_gain":
            return self.colour.gains
        return self.colour.shipped_gains

    def with_candidates(self, stage: int, n: int) -> RunPlan:
        """The plan with stage `stage`'s candidate count set to n."""
        counts = list(self.n_candidates)
        counts[stage] = int(n)
        return replace(self, n_candidates=tuple(counts))

    def with_samples(self, stage: int, k: int) -> RunPlan:
        """The plan with stage `stage`'s occupied-sample slots set to k."""
        slots = list(self.max_samples or (0,) * len(self.n_candidates))
        slots[stage] = int(k)
        return replace(self, max_samples=tuple(slots))

    def samples(self, stage: int, cfg) -> int:
        """Stage `stage`'s occupied-sample slots per ray: the plan's where decided, else
        cfg's render.max_samples."""
        k = 0 if self.max_samples is None else self.max_samples[stage]
        return int(k) if k else int(cfg.render.max_samples)


def render_config(cfg, plan: RunPlan, stage: int = -1):
    """cfg with the render.max_samples of `stage` (default: the last, the finished run's
    slots): the renders of a run shade the samples its stage trained."""
    k = plan.samples(stage % len(plan.n_candidates), cfg)
    if k == cfg.render.max_samples:
        return cfg
    return replace(cfg, render=replace(cfg.render, max_samples=k))


def refined_config(cfg, plan: RunPlan):
    """cfg as the run trains it where the plan refined the last stage (plan.last_width):
    that stage plan.last_width vertices across (its depth the config's), its TVs scaled by
    its width over the config's last (loss.tv_ref_width, unless set: optim.tv_scale keeps
    the priors' strength per unit of the scene) and its slots' cap by the same ratio (a
    finer grid holds more samples per ray). cfg unchanged where the plan did not refine."""
    if plan.last_width is None:
        return cfg
    res = [list(r) for r in cfg.grid.resolutions]
    width = res[-1][0]
    res[-1][0] = int(plan.last_width)
    cfg = _finer(cfg, width, plan.last_width / width)
    # detail_width 0: the width is decided
    return replace(cfg, grid=replace(cfg.grid, resolutions=tuple(tuple(r) for r in res),
                                     detail_width=0))


def _finer(cfg, width: int, ratio: float, tv_ref: int | None = None):
    """cfg with a last stage `ratio` times the configured last `width`: the TVs scaled
    against tv_ref (None: loss.tv_ref_width, unless set that width; optim.tv_scale) and the
    slots' cap by the ratio (a finer grid holds more samples per ray)."""
    ref = tv_ref or cfg.loss.tv_ref_width or width
    return replace(cfg, loss=replace(cfg.loss, tv_ref_width=int(ref)),
                   render=replace(cfg.render,
                                  max_samples=int(round(cfg.render.max_samples * ratio))))


def appended_width(cfg, capture_width: int) -> int | None:
    """The width (vertices across) of the stage appended after the config's last, twice
    its width, where a vertex of the last spans more than grid.voxel_pixels capture pixels
    across (the grid taken to fill the view's width, as the resolutions are given); None
    where it does not, or grid.voxel_pixels is 0.

    Why: the last stage's width is given in vertices, whatever the capture. At 480x270 a
    vertex of the default's 192-wide stage spans 2.5 capture pixels; at 1920x1080, 10, more
    than the texture of a scene allows even from clean frames. The held-out held_arc_table
    at 1920x1080 trained on its clean references: 22.47 dB with the 192-wide last stage,
    23.82 with a 384-wide stage appended; trained on its dark raw, +0.37 dB, held_deep_hall
    +0.49, bucket 0.00 (+0.31 colour-aligned), and a path-traced capture at 1280x720 +0.50
    (docs/results.md, "At the capture's own resolution"). At 5 pixels no 480x270 or
    320x180 capture is touched."""
    limit = cfg.grid.voxel_pixels
    width = cfg.grid.resolutions[-1][0]
    if limit <= 0 or capture_width <= limit * width:
        return None
    return 2 * int(width)


def trained_appended_steps(plan: RunPlan) -> tuple[int, int]:
    """The steps the run of `plan` trains its last configured and its appended stage: its
    own record, or APPENDED_STEPS_BEFORE where a plan with a stage appended predates it,
    so that a resume keeps the schedule the run began with."""
    return plan.appended_steps or APPENDED_STEPS_BEFORE


def appended_tv_ref(cfg, width: int, capture_width: int) -> int:
    """loss.tv_ref_width for a stage `width` vertices across appended after cfg's last on a
    capture `capture_width` pixels wide: the config's where set; else the width against
    which optim.tv_scale gives the appended stage's TVs its width over the last's (the
    prior's strength per unit of the scene, as refined_config keeps it) times TV_FOOTPRINT
    over the capture pixels a vertex of it spans (a scale under 1 leaves the weights as
    configured: optim.tv_scale).

    Why the footprint: a vertex's colour is the mean of the photons of the pixels around
    it, about footprint^2 per view, so the noise of that mean falls as the footprint grows,
    and a TV weight that holds the noise back where it was set (2.5 pixels a vertex) holds
    back detail where a vertex spans more. At 1920x1080 the appended 384-wide stage spans
    5 pixels a vertex: its TVs are the configured weights (scale 1) rather than twice them
    (its width over 192). Chosen on the tuning captures bucket and dev_arc_shop at
    1920x1080 (+0.06 and +0.16 dB, colour-aligned +0.51 and +0.21), then shown on the
    held-out held_arc_table and held_deep_hall (+0.24, +0.35) and on a path-traced capture
    at 1280x720 (x1.5 against x2: +0.16; docs/results.md, "At the capture's own
    resolution")."""
    if cfg.loss.tv_ref_width:
        return int(cfg.loss.tv_ref_width)
    last = int(cfg.grid.resolutions[-1][0])
    return max(1, int(round(last * capture_width / (TV_FOOTPRINT * int(width)))))


def configured_tv(cfg, appended: int | None, capture_width: int) -> float | None:
    """The factor on the TVs of cfg's own stages on a capture `capture_width` pixels wide
    where a stage `appended` wide is appended after them (appended_width): TV_FOOTPRINT
    over the capture pixels a vertex of the last configured stage spans, at most 1 (0.25 at
    1920x1080, 0.375 at 1280x720); None where none is appended (every capture at 960
    pixels across or fewer) or loss.tv_ref_width is set (the user's width rules the TVs).

    Why: the weights were set at 480x270, where a vertex of each stage spans 480 / its
    width capture pixels (2.5 for the 192-wide one). On a wider capture the same stage's
    vertex spans more pixels, whose mean holds less noise, and the same prior holds back
    texture rather than noise: each stage's weight falls as its vertex's footprint grows
    over the one it was set at, as appended_tv_ref has the appended stage's do. Chosen on
    the tuning captures bucket and dev_arc_shop at 1920x1080 (-0.01 and +0.20 dB; every TV
    halved instead: -0.04 and +0.16, with CIEDE2000 +0.23 and +0.35), then shown on the
    held-out held_arc_table and held_deep_hall at 1920x1080 (+0.24, +0.07) and a
    path-traced capture at 1280x720 (+0.07), CIEDE2000 lower on all three (docs/results.md,
    "At the capture's own resolution"). The detail rule's refined stage, where it acts on
    such a capture, is a configured stage and takes the factor too."""
    if appended is None or cfg.loss.tv_ref_width:
        return None
    last = int(cfg.grid.resolutions[-1][0])
    return min(1.0, TV_FOOTPRINT * last / int(capture_width))


def capture_config(cfg, width: int | None, steps: tuple[int, int] | None = None,
                   tv_ref: int | None = None):
    """cfg with the stage appended_width decided (width vertices across; None: cfg): its
    depth 1.5x the last's, the last configured stage and the new one trained `steps`
    (None: APPENDED_STEPS, a new run's), the TVs scaled against `tv_ref`
    (appended_tv_ref; None: loss.tv_ref_width, unless set the configured last width, what
    a plan saved before the footprint rule trained; optim.tv_scale) and the slots' cap by
    the width's ratio (a finer grid holds more samples per ray), as refined_config does; every stage
    on the binned frames (data.mosaic_stages 0): at 1920x1080 the appended stage's rays
    would see about a quarter of the mosaic's photosites, and there the mosaic's last
    stage had cost bucket 0.43 dB against binning throughout."""
    if width is None:
        return cfg
    res = [tuple(r) for r in cfg.grid.resolutions]
    last = res[-1]
    res.append((int(width), 0, int(round(last[2] * 1.5))))
    before, after = steps or APPENDED_STEPS
    per_stage = (*cfg.train.steps_per_stage[:-1], int(before), int(after))
    cfg = _finer(cfg, last[0], width / last[0], tv_ref)
    return replace(cfg, grid=replace(cfg.grid, resolutions=tuple(res)),
                   data=replace(cfg.data, mosaic_stages=0),
                   train=replace(cfg.train, steps_per_stage=per_stage))


def opacity_schedule(weight: float, stages: int, first: int) -> tuple[float, ...]:
    """The opacity prior's weight in each of `stages` stages: `weight` in the first `first`
    (loss.opacity_stages; 0: in every stage), 0 after."""
    return tuple(weight if first == 0 or s < first else 0.0 for s in range(stages))


def to_dict(plan: RunPlan) -> dict:
    return asdict(plan)


def from_dict(d: dict) -> RunPlan:
    """RunPlan from to_dict output (tuples restored); KeyError/TypeError/ValueError if not."""
    c = dict(d["colour"])
    for k in ("anchor", "gains", "shipped_gains", "locus_matrix"):
        c[k] = None if c.get(k) is None else tuple(float(v) for v in c[k])
    c["evidence"] = {str(k): tuple(float(x) for x in v)
                     for k, v in c.get("evidence", {}).items()}
    d = dict(d)
    d["colour"] = ColourPlan(**c)
    d["opacity"] = tuple(float(v) for v in d["opacity"])
    d["n_candidates"] = tuple(int(v) for v in d["n_candidates"])
    if d.get("max_samples") is not None:
        d["max_samples"] = tuple(int(v) for v in d["max_samples"])
    if d.get("vignetting") is not None:
        d["vignetting"] = tuple(float(v) for v in d["vignetting"])
    if d.get("appended_steps") is not None:
        d["appended_steps"] = tuple(int(v) for v in d["appended_steps"])
    plan = RunPlan(**d)
    if not math.isfinite(plan.data_eps) or plan.data_eps <= 0:
        raise ValueError(f"data_eps {plan.data_eps}")
    return plan


def save(run: Path, plan: RunPlan) -> None:
    """<run>/plan.json (atomic)."""
    atomic.write_text(Path(run) / PLAN, json.dumps(to_dict(plan), indent=2) + "\n")


def load(run: Path) -> RunPlan:
    """The plan saved in <run>/plan.json; CheckpointError naming the file if it is missing
    or unreadable (a run trained before plans were kept has none: train it again)."""
    path = Path(run) / PLAN
    try:
        return from_dict(json.loads(path.read_text()))
    except FileNotFoundError:
        raise CheckpointError(path, "the run has no plan.json (trained by an older version, "
                              "or its training never started)", "train the run again "
                              "into a new --out") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CheckpointError(path, f"cannot read the run plan ({type(exc).__name__}: {exc})",
                              "delete the run folder and train again") from None


@dataclass(frozen=True, eq=False)
class StepPlan:
    """What one stage's step is built with (optim.make_step), from the run plan.

    data_eps: the data term's eps; opacity: the opacity prior's weight this stage;
    n_candidates: the static candidate count per ray; max_samples: the occupied-sample slots
    per ray (0: the config's render.max_samples); train_gains: whether the gain terms
    (L_ca, smoothness) are in the loss (False with one gain or no gains); anchor: (3,)
    float32 the capture's illuminant (the "scene" and "map" targets) or None; locus: (n, 3)
    float32 the camera's Planckian locus for the "batch" target with loss.ca_locus, or None.
    tv_scale: the factor on the TVs of density, colour and chroma this stage (optim.tv_scale).
    """

    data_eps: float
    opacity: float
    n_candidates: int
    train_gains: bool
    anchor: object = None
    locus: object = None
    max_samples: int = 0
    tv_scale: float = 1.0
