"""Ablation of Bright-NeRF's parts (the paper's Table 2 analogue), scene by scene.

Variants (each the package's own preset plus overrides, cached in <runs>/<scene>/<run>;
runs that other studies share are reused, not trained twice):
- no colour restoration: no gains, no L_ca, no smoothness (the `nogain` preset, also the
  report's RawNeRF + ISP row);
- gains + L_ca, no smoothness (`loss.w_smooth=0`);
- full, smoothness as edge-aware grid TV (the default's colour path: the `binned` run);
- full, smoothness as eq. 15 on ray patches (the `patch` preset).
Every variant of these studies but the data-term and chroma ones fits the binned raw in
every stage without the chroma prior (common.FACTOR_BASE): the factors were measured before
the default gained its mosaic stage and that prior, which those two studies measure on
their own.
Each is scored with the colour matrix (the shown output) and without it (the paper's
matrix-free output); the no-gain variant is also shown with one grey-world gain for the
scene (its `global_grey_world` output), which is what "no gains" vs "gains" should compare.
Writes <out>.md and <out>.json: per scene, then the mean over each report group the scenes
cover (nine built-in, tuning, held out, mixed light, held-out mixed light), each apart.

Other studies (--study) compare the gains' smoothness weight, one gain against the field,
the grid regularisers' row sample, the data term's targets (binned raw or mosaic) and the
chroma TV prior on the same footing, and the density's Adam rate on today's default, each
in reports/ablation_<study>.
The parts' means (nine built-in, held out) written to reports/ablation also go into
docs/results.md between its ablation markers.

    python -m experiments.ablate [--scenes all|nine|heldout|a,b]
                                 [--study parts|smoothness|gain_model|tv_fraction|data_term|chroma
                                          |density_rate]
                                 [--quick]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments.common import (
    DETAIL_ON,
    FACTOR_BASE,
    FOOTING,
    REPORT_GROUPS,
    RESULTS_DOC,
    fmt,
    markdown_table,
    run_variant,
    scene_names,
    study_parser,
    update_doc,
    write_report,
)

# (key, label, run folder, preset, overrides)
VARIANTS = [
    ("no_cr", "no colour restoration (no gains, L_ca, smoothness)", "nogain", "nogain", []),
    ("cr_ca", "gains + L_ca", "ablate_cr_ca", "default",
     ["loss.w_smooth=0.0", *FACTOR_BASE]),
    ("full_tv", "full, smoothness as grid TV (default)", "binned", "default", FACTOR_BASE),
    ("full_patch", "full, smoothness as eq. 15 on ray patches", "patch", "patch",
     FACTOR_BASE),
]
# --study smoothness: the gains' grid TV weight loss.w_smooth at a tenth of the default's
# (does the field follow its illuminant map closer, and at what cost where one light?).
# Tuned on mixed_lamp_window and mixed_desk_daylight, tested on the rest
SMOOTHNESS_VARIANTS = [
    ("map_regions", "field, loss.w_smooth = 0.1 (default)", "binned", "default",
     FACTOR_BASE),
    ("smooth_0.01", "field, loss.w_smooth = 0.01", "ws0.01", "default",
     ["loss.w_smooth=0.01", *FACTOR_BASE]),
]
# --study gain_model: what carries the colour. The field (default) against
# loss.gain_model=auto: one gain for the capture (the L_ca target's anchor) where its
# illuminant maps show one light, the field where lights mix; with one gain the steps
# train no gains. Each with the file's black level and with the lens-cap one
GAIN_MODEL_VARIANTS = [
    ("field", "gain field (default)", "binned", "default", FACTOR_BASE),
    ("auto", "one gain where one light, the field where lights mix", "gain_auto", "default",
     ["loss.gain_model=auto", *FACTOR_BASE]),
    ("field_dark", "gain field, lens-cap black level", "dark_black", "default",
     ["data.black_offset=dark", *FACTOR_BASE]),
    ("auto_dark", "one gain where one light, lens-cap black level", "gain_auto_dark",
     "default", ["loss.gain_model=auto", "data.black_offset=dark", *FACTOR_BASE]),
]
# --study tv_fraction: the share of the grid's rows the four grid regularisers (TV of
# density, of colour, of the gains; sparsity) sample per step. Their backward scatters are
# about 30 % of the last stage's step (docs/speed.md); at a tenth of the rows the step is
# ~16 % faster. Is it free? Nothing was chosen on these runs; the default now samples a
# tenth and spends the time on last-stage steps (docs/results.md)
TV_FRACTION_VARIANTS = [
    ("tv_0.25", "grid regularisers on 25 % of the rows per step (the footing's)", "binned",
     "default", FACTOR_BASE),
    ("tv_0.1", "grid regularisers on 10 % of the rows per step", "tv0.1", "default",
     [*FACTOR_BASE, "loss.tv_fraction=0.1"]),
]
# --study data_term: what the data term compares. The 2x2-binned raw in every stage
# against the raw Bayer mosaic photosite by photosite, in every stage or in the last stage
# only (data.mosaic_stages=1, the default: the coarse stages binned place the geometry),
# each without the chroma prior. Chosen on the nine built-in scenes; nothing was chosen on
# the held-out ones
DATA_TERM_VARIANTS = [
    ("binned", "binned raw in every stage", "binned", "default", FACTOR_BASE),
    ("mosaic", "raw mosaic in every stage", "mosaic", "default",
     ["data.binning=false", *FACTOR_BASE]),
    ("mosaic_last", "raw mosaic in the last stage, binned before (default)", "mosaic_last",
     "default", FOOTING),
]
# --study chroma: a TV of the colour's chroma on top of the colour's TV (loss.tv_chroma,
# gridnerf.losses.chroma_tv_loss). Its weight, 0.01, was chosen on the nine built-in
# scenes; every other group is trained after that choice
CHROMA_VARIANTS = [
    ("off", "no chroma prior", "mosaic_last", "default", FOOTING),
    ("chroma", "chroma TV, loss.tv_chroma = 0.01 (the default's)", "chroma", "default",
     [*FOOTING, "loss.tv_chroma=0.01"]),
]
# --study density_rate: the raw density's Adam rate (train.lr_density) at twice the
# default's. Chosen on the four tuning scenes (bucket, scoreboard, dev_arc_shop,
# dev_slide_bench; docs/results.md "The density's learning rate"); every other group is
# trained after that choice, on today's default footing
DENSITY_RATE_VARIANTS = [
    ("rate_0.3", "density rate 0.3 (the default's)", "default", "default", []),
    ("rate_0.6", "density rate 0.6", "lrd0.6", "default", ["train.lr_density=0.6"]),
]
# --study last_width: the last stage 288 vertices across instead of 192 (the same 64 in
# depth; the slots' cap raised so the stage may fit more), its TVs scaled by the width
# over 192 (loss.tv_ref_width: the prior's strength per unit of the scene kept). Does a
# finer grid across the view hold detail the frames show, or their noise? The same stage
# without the scaling was measured first (`<scene>/w288` in RESULTS; docs/results.md,
# "A finer last stage")
LAST_WIDTH_VARIANTS = [
    ("w192", "last stage 192 wide (the default's)", "default", "default", []),
    ("w288_tv", "last stage 288 wide, its TVs x 1.5 (loss.tv_ref_width = 192)", "w288tv",
     "default", ["grid.resolutions=[[48,0,24],[96,0,48],[288,0,64]]",
                 "render.max_samples=96", "loss.tv_ref_width=192"]),
]
# --study colour_solve: after the last stage, the vertex colours fitted to every training
# ray at once with the geometry fixed (train.colour_solve_iters, gridnerf.colour_solve)
# against Adam's colour. Does Adam leave noise a converged fit would average away?
COLOUR_SOLVE_VARIANTS = [
    ("adam", "Adam's colour (the default's)", "default", "default", []),
    ("solve20", "colour solved, 20 L-BFGS iterations", "cs20", "default",
     ["train.colour_solve_iters=20"]),
]
# --study detail: the last stage 288 wide only where the 96-wide stage before it
# leaves more detail in its frames than the views' average leaves of their noise and the
# frames hold 5 photosites across per 3 vertices (gridnerf.residual, grid.detail_width; the
# threshold residual.ABOVE = 1 set from the reading's unit when only bucket had been read),
# against the default, which has the rule off
DETAIL_VARIANTS = [
    ("w192", "last stage 192 wide (the default's: grid.detail_width = 0)", "default",
     "default", []),
    ("detail", "last stage 288 wide where the 96-wide grid leaves detail over the averaged "
     "noise, as the photosites allow (grid.detail_width = 288)", "detail288", "default",
     list(DETAIL_ON)),
]
STUDIES = {"parts": VARIANTS, "smoothness": SMOOTHNESS_VARIANTS,
           "gain_model": GAIN_MODEL_VARIANTS, "tv_fraction": TV_FRACTION_VARIANTS,
           "data_term": DATA_TERM_VARIANTS, "chroma": CHROMA_VARIANTS,
           "density_rate": DENSITY_RATE_VARIANTS, "last_width": LAST_WIDTH_VARIANTS,
           "colour_solve": COLOUR_SOLVE_VARIANTS, "detail": DETAIL_VARIANTS}
# (column, eval summary key) shown for every variant; the no-gain run adds its global gain
OUTPUTS = [("matrix", "gridnerf"), ("matrix_free", "gridnerf_matrix_free"),
           ("global_gain", "global_grey_world")]
METRICS = ("psnr", "ssim", "delta_e", "psnr_aligned")


def ablate(scenes: list[str], runs: Path, quick: bool, variants=VARIANTS) -> dict:
    """{scene: {variant: {output: metrics}}}, training what is missing."""
    record: dict = {}
    for scene in scenes:
        for key, _, folder, preset, sets in variants:
            summary = run_variant(scene, folder, preset, sets, runs, quick)["summary"]
            shown = OUTPUTS if key.startswith("no_cr") else OUTPUTS[:2]
            record.setdefault(scene, {})[key] = {
                out: {m: float(summary[k][m]) for m in METRICS} for out, k in shown
                if k in summary}
    return record


def means(record: dict, group, variants=VARIANTS) -> dict:
    """{variant: {output: mean metrics}} over the scenes of `group` in the record."""
    got = [record[s] for s in group if s in record]
    out: dict = {}
    for key, *_ in variants:
        for name, _ in OUTPUTS:
            vals = [g[key][name] for g in got if name in g.get(key, {})]
            if vals:
                out.setdefault(key, {})[name] = {m: float(np.mean([v[m] for v in vals]))
                                                 for m in METRICS} | {"n": len(vals)}
    return out


def group_means(record: dict, variants=VARIANTS) -> dict:
    """{group label: means} for each of common.REPORT_GROUPS the record has a scene of
    (nine, tuning, held out, mixed light, held-out mixed light: each group apart)."""
    return {label: means(record, group, variants) for label, group in REPORT_GROUPS
            if any(s in record for s in group)}


def markdown(record: dict, groups: dict, variants=VARIANTS, command: str = "") -> str:
    """The per-scene rows, then the means of each group ({label: means}, group_means)."""
    labels = {key: label for key, label, *_ in variants}

    def rows(scene: str, per: dict) -> list[list[str]]:
        return [[scene, labels[key], name, fmt(m["psnr"]), fmt(m["ssim"], 3),
                 fmt(m["delta_e"]), fmt(m["psnr_aligned"])]
                for key, outs in per.items() for name, m in outs.items()]

    lines = [r for scene, per in record.items() for r in rows(scene, per)]
    for label, mean in groups.items():
        n = max((m["n"] for outs in mean.values() for m in outs.values()), default=0)
        lines += rows(f"**mean, {label}** (n={n})", mean)
    return ("# Ablation\n\nTest views, PSNR / SSIM / CIEDE2000 and aligned PSNR. Outputs: "
            "`matrix` (the colour matrix, shown by default), `matrix_free` (the paper's), "
            "`global_gain` (the no-gain grid with one grey-world gain for the scene).\n\n"
            + (f"Command: `{command}`\n\n" if command else "")
            + markdown_table(["scene", "variant", "output", "PSNR", "SSIM", "CIEDE2000",
                              "PSNR al."], lines) + "\n")


def means_table(mean_nine: dict, mean_held: dict, variants=VARIANTS) -> str:
    """The shown output's (`matrix`) mean per variant, nine and held out (the table in
    docs/results.md), each cell saying over how many scenes."""
    def cell(outs):
        m = outs.get("matrix") if outs else None
        return "-" if not m else (f"{fmt(m['psnr'])} / {fmt(m['ssim'], 3)} / "
                                  f"{fmt(m['delta_e'])} (n={m['n']})")
    rows = [[label, cell(mean_nine.get(key)), cell(mean_held.get(key))]
            for key, label, *_ in variants]
    if "no_cr" in mean_nine or "no_cr" in mean_held:  # the no-gain grid, one grey-world gain
        rows.insert(1, ["the same grid, one grey-world gain (RawNeRF + ISP)",
                        *[cell({"matrix": m["no_cr"]["global_gain"]}
                               if "global_gain" in m.get("no_cr", {}) else None)
                          for m in (mean_nine, mean_held)]])
    return markdown_table(["variant", "nine built-in", "held out"], rows)


def main() -> None:
    ap = study_parser(__doc__, None, runs=True, quick=True)
    ap.add_argument("--study", default="parts", choices=list(STUDIES),
                    help="parts: Bright-NeRF's parts; smoothness: the gains' TV weight; "
                    "gain_model: one gain where one light against the field; tv_fraction: the "
                    "grid regularisers' row sample; data_term: the binned raw against the "
                    "mosaic; chroma: the chroma TV prior; density_rate: the density's Adam "
                    "rate; last_width: a 288-wide last stage; colour_solve: the colours "
                    "solved to convergence after the last stage; detail: a 288-wide last stage "
                    "where the frames show detail over the averaged noise")
    args = ap.parse_args()
    out = args.out or ("reports/ablation" if args.study == "parts"
                       else f"reports/ablation_{args.study}")
    print(build(scene_names(args.scenes), Path(args.runs), out, args.quick,
                STUDIES[args.study]))


def build(scenes: list[str], runs: Path, out, quick: bool, variants=VARIANTS,
          command: str | None = None) -> str:
    """Train what is missing, write <out>.md and <out>.json; returns the markdown. The
    command shown defaults to this script's call for these scenes and variants."""
    study = next((k for k, v in STUDIES.items() if v is variants), "parts")
    command = command or (f"python -m experiments.ablate --scenes {','.join(scenes)}"
                          + (f" --study {study}" if study != "parts" else "")
                          + (" --quick" if quick else ""))
    record = ablate(scenes, runs, quick, variants)
    groups = group_means(record, variants)
    text = markdown(record, groups, variants, command)
    write_report(out, text, {"quick": quick, "scenes": record, "means": groups})
    if not quick and variants is VARIANTS and Path(out) == Path("reports/ablation"):
        update_doc("ablation", means_table(groups.get("nine", {}), groups.get("held out", {})),
                   RESULTS_DOC)
    return text


if __name__ == "__main__":
    main()
