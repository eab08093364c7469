"""The per-scene report in the paper's layout, from every evaluated run.

Reads <runs>/<scene>/<variant>/eval/metrics.json and writes <out>.md and <out>.json: for
each method row and each scene PSNR / SSIM / CIEDE2000, raw and aligned (per-channel
affine fit in linear space first), then the mean over the nine built-in scenes and,
separately, over the held-out ones (no default was tuned on those). Rows whose runs are
missing say so; the paper's CNN rows need pretrained weights that are not available
offline and are n/a. The studies' tables are appended when their files exist beside the
report (ablation, sweep, photons, speed, consistency, recon, error budget, bench: STUDIES,
each from `python -m experiments.<study>`), with their plots, and a figure of one test view per
scene side by side (dark input, each method, reference) is written as <out>_views.png.
The rows' means go into README.md between its report markers.

Run folders are not in git: a cell whose run is not on this machine is taken from
reports/results.json (common.RESULTS: every evaluated run's summary under the fingerprint
of its config) when the fingerprint is its preset's today, so a fresh machine rebuilds the
report from what it trains plus what was measured before; the views figure is kept rather
than redrawn with grey tiles.

Nothing is trained unless asked: --run-missing a,b|all trains every row's run of those
scenes first. --quick builds the whole report small (160x90 scenes, presets shrunk by
common.quick_sets, runs under runs_quick/, report under reports/quick/): every run and
study it needs, in minutes, to check that every figure comes out.

    python -m experiments.report [--runs runs] [--out reports/report] [--run-missing a,b|all]
    python -m experiments.report --quick
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments.common import (
    cached_result,
    fmt,
    load_results,
    markdown_table,
    preset_config,
    pyplot,
    run_variant,
    save_figure,
    stale_run,
    update_readme,
    write_report,
)
from gridnerf.sim import HELDOUT, SCENES

# (row, label, run variant, key in that run's eval summary)
ROWS = [
    ("ours", "ours (gains + L_ca + smoothness, auto exposure)", "default", "gridnerf"),
    ("rawnerf_isp", "RawNeRF + generic ISP (no gains, binned raw; one grey-world gain)", "nogain",
     "global_grey_world"),
    ("global_wb", "global white balance (our field's low-light colour, one grey-world gain)",
     "default", "global_grey_world"),
    ("2d_denoised", "2D per image: one frame + grey world + non-local means", "default",
     "baseline_denoised"),
    ("2d_nerf", "2D + NeRF: the grid trained on the 2D-processed frames", "processed",
     "gridnerf"),
    ("per_frame_matched", "per-frame pipeline, exposure matched to the reference", "default",
     "baseline_binned_matched"),
    ("dark_frame", "one dark frame: demosaic + grey world + gamma", "default",
     "baseline_dark_frame"),
    ("llnerf", "LLNeRF-style: lighting / reflectance decomposition and its enhancement "
     "losses on the grid, trained on dark sRGB frames", "llnerf", "llnerf"),
    ("oracle", "oracle: the grid trained on the clean references (upper bound)", "oracle",
     "gridnerf"),
]
NOT_AVAILABLE = {
    "cnn": "SID, RED, ABF, DNF: need pretrained weights, not available offline",
}
# run folder -> preset of the rows' runs (--run-missing, --quick)
RUN_PRESETS = {"default": "default", "nogain": "nogain", "processed": "processed",
               "llnerf": "llnerf", "oracle": "oracle"}
# the studies appended to the report, in order: (file stem in the report's folder, title,
# the command that writes it: `python -m experiments.<command>`)
STUDIES = [("ablation", "Ablation", "ablate"),
           ("sweep", "Darkness sweep", "sweep"),
           ("sweep_heldout", "Darkness sweep, held-out scenes",
            "sweep --scenes held_deep_hall,held_mixed_toys --methods binned "
            "--out reports/sweep_heldout"),
           ("photons", "Physical darkness sweep (fewer photons)", "photons"),
           ("speed", "Speed against error", "speed"),
           ("consistency", "Multi-view consistency", "consistency"),
           ("recon", "Reconstruction against the per-frame pipeline and the oracle", "recon"),
           ("error_budget", "Error budget: where the dB between the oracle and the default go",
            "error_budget"),
           ("ablation_smoothness", "The gains' smoothness weight (loss.w_smooth)",
            "ablate --study smoothness"),
           ("ablation_gain_model", "One gain where one light (loss.gain_model)",
            "ablate --study gain_model"),
           ("ablation_tv_fraction", "The grid regularisers' row sample (loss.tv_fraction)",
            "ablate --study tv_fraction"),
           ("ablation_data_term", "The data term's targets: binned raw or mosaic "
            "(data.binning, data.mosaic_stages)", "ablate --study data_term"),
           ("bench", "Speed and memory benchmark", "bench")]
QUICK_SCENES = ["bucket", "held_arc_brick"]
METRICS = ("psnr", "ssim", "delta_e", "psnr_aligned", "ssim_aligned", "delta_e_aligned")


def stale(run: Path, variant: str, quick: bool = False) -> bool:
    """Whether a row's run was trained by another config than its variant's preset today
    (common.stale_run); a variant outside RUN_PRESETS is taken as it is."""
    return variant in RUN_PRESETS and stale_run(run, RUN_PRESETS[variant], quick)


def assemble(runs: Path, scenes: list[str], quick: bool = False) -> dict:
    """{row: {"label", "scenes": {scene: metrics}, "stale": [scene], "cached": [scene],
    "mean_nine", "mean_heldout"}} from the evaluated runs under `runs` whose config is
    their preset's today (others are listed as stale, not used); a mean covers the scenes
    the row has (with their count). A run not on this machine is taken from
    common.RESULTS when it holds the run under its preset's config of today (listed as
    cached): run folders are not in git, the results are."""
    record, results = {}, {} if quick else load_results()
    for row, label, variant, key in ROWS:
        per_scene, old, cached = {}, [], []
        today = preset_config(RUN_PRESETS[variant])
        for scene in scenes:
            run = runs / scene / variant
            path = run / "eval" / "metrics.json"
            if path.is_file() and stale(run, variant, quick):
                old.append(scene)
                continue
            if path.is_file():
                summary = json.loads(path.read_text())["summary"]
            else:
                hit = cached_result(scene, variant, today, results)
                summary = hit["summary"] if hit else {}
            if summary.get(key):
                per_scene[scene] = {k: float(summary[key][k]) for k in METRICS}
                if not path.is_file():
                    cached.append(scene)
        entry = {"label": label, "variant": variant, "key": key, "scenes": per_scene,
                 "stale": old, "cached": cached}
        for name, group in (("mean_nine", SCENES), ("mean_heldout", HELDOUT)):
            got = [per_scene[s] for s in group if s in per_scene]
            entry[name] = ({k: float(np.mean([g[k] for g in got])) for k in METRICS}
                           | {"n": len(got)}) if got else None
        record[row] = entry
    return record


def _cell(m: dict | None, suffix: str = "") -> str:
    """PSNR / SSIM / CIEDE2000 of metrics m (suffix "_aligned": the aligned ones)."""
    if not m:
        return "-"
    return (f"{fmt(m['psnr' + suffix])} / {fmt(m['ssim' + suffix], 3)} / "
            f"{fmt(m['delta_e' + suffix])}")


# the README's short names of the rows
SHORT = {"ours": "ours", "rawnerf_isp": "RawNeRF + generic ISP (binned raw, one grey-world "
         "gain)",
         "global_wb": "our field, one grey-world gain", "2d_denoised":
         "2D per image (one frame + non-local means)", "2d_nerf": "2D + NeRF",
         "per_frame_matched": "per-frame, exposure matched to the reference",
         "dark_frame": "one dark frame", "llnerf": "LLNeRF-style",
         "oracle": "oracle (clean references; a bound, not a competitor)"}


def means_table(record: dict) -> str:
    """The rows' means over the nine and the held-out scenes (the README's table)."""
    def cell(m):
        return _cell(m) + (f" (n={m['n']})" if m else "")
    return markdown_table(["row", "nine built-in", "held out"],
                          [[SHORT[r], cell(e["mean_nine"]), cell(e["mean_heldout"])]
                           for r, e in record.items()])


def markdown(record: dict, scenes: list[str], folder: Path, views: str | None) -> str:
    """The report: rows table, aligned table, then each study found in `folder` (its .md
    without its title, its .png linked) and the views figure (`views`, a file name)."""
    rows_done = [r for r in record if record[r]["scenes"]]
    header = ["scene", *rows_done]
    lines = [[s, *[_cell(record[r]["scenes"].get(s)) for r in rows_done]] for s in scenes
             if any(s in record[r]["scenes"] for r in rows_done)]
    for name, label in (("mean_nine", "**mean, nine**"), ("mean_heldout", "**mean, held out**")):
        lines.append([label, *[_cell(record[r][name]) + (
            f" (n={record[r][name]['n']})" if record[r][name] else "") for r in rows_done]])
    aligned = [[s, *[_cell(record[r]["scenes"].get(s), "_aligned") for r in rows_done]]
               for s in scenes if any(s in record[r]["scenes"] for r in rows_done)]
    legend = "\n".join(f"- `{r}`: {record[r]['label']} (runs/<scene>/{record[r]['variant']}, "
                       f"`{record[r]['key']}`)" for r in record)
    missing = [r for r in record if not record[r]["scenes"]]
    stale_runs = sorted({f"runs/{s}/{record[r]['variant']}" for r in record
                         for s in record[r]["stale"]})
    cached = "; ".join(f"{r}: {', '.join(record[r]['cached'])}" for r in record
                       if record[r].get("cached"))
    text = ("# gridnerf report\n\nEach cell: PSNR / SSIM / CIEDE2000 (sRGB, 16-pixel border "
            "crop). Held-out scenes (no default tuned on them) are averaged separately.\n\n"
            f"{legend}\n"
            + "".join(f"- `{r}`: no evaluated runs yet\n" for r in missing)
            + "".join(f"- {k}: n/a ({v})\n" for k, v in NOT_AVAILABLE.items())
            + (f"- left out, trained with another config than their preset's today: "
               f"{', '.join(stale_runs)}\n" if stale_runs else "")
            + (f"- taken from reports/results.json (trained by the preset of today, by "
               f"config fingerprint, on an earlier machine; run folders are not in git): "
               f"{cached}\n" if cached else "")
            + "\n## Test views\n\n" + markdown_table(header, lines)
            + "\n\n## Aligned (per-channel affine fit in linear space first)\n\n"
            + markdown_table(header, aligned) + "\n")
    if views:
        text += (f"\n## One test view per scene\n\n![test views]({views})\n\nColumns: "
                 + ", ".join(label for _, label in FIGURE_COLUMNS) + ".\n")
    for stem, title, command in STUDIES:
        md = folder / f"{stem}.md"
        if not md.is_file():
            text += f"\n## {title}\n\nNot built yet: `python -m experiments.{command}`.\n"
            continue
        body = md.read_text()
        body = body.split("\n", 1)[1] if body.startswith("# ") else body  # its own title
        # the study's own headings sit one level under its title
        body = "\n".join("#" + ln if ln.startswith("#") else ln for ln in body.split("\n"))
        text += f"\n## {title}\n\n" + body.strip("\n") + "\n"
        if (folder / f"{stem}.png").is_file():
            text += f"\n![{title}]({stem}.png)\n"
    return text


# (source, label) of the views figure's columns; source: an eval image of a run
# ("<variant>:<file suffix>"), "render:<variant>:<output>" rendered now, or the 2D rows
FIGURE_COLUMNS = [
    ("default:baseline", "dark frame + grey world + exposure"),
    ("denoised", "2D: + non-local means"),
    ("render:nogain:global_grey_world", "RawNeRF + ISP"),
    ("processed:pred", "2D + NeRF"),
    ("llnerf:pred", "LLNeRF-style"),
    ("default:pred", "ours"),
    ("oracle:pred", "oracle"),
    ("default:gt", "reference"),
]


def figure(runs: Path, scenes: list[str], path: Path, quick: bool = False,
           tile: tuple[int, int] = (160, 90)) -> bool:
    """One test view per scene (its middle test frame), FIGURE_COLUMNS side by side, tiles
    of `tile` (w, h) pixels; missing runs, and runs of another config than their preset's
    today (stale), leave a grey tile. An existing figure is kept rather than replaced by
    one with grey tiles (a fresh machine has no runs; the report reuses its numbers).
    False when there is no figure."""
    from skimage.transform import resize

    from gridnerf import baseline, color, eval_run, image_io

    rows, missing = [], 0
    for scene in scenes:
        ours = runs / scene / "default"
        if not (ours / "eval" / "metrics.json").is_file():
            missing += 1
            continue
        views = json.loads((ours / "eval" / "metrics.json").read_text()).get("test_views", [])
        if not views:
            continue
        name = views[len(views) // 2]
        tiles = []
        for source, _ in FIGURE_COLUMNS:
            img = None
            parts = source.split(":")
            if parts[0] == "denoised":
                sc = eval_run.load_run(ours)[2]
                i = sc.names.index(name)
                img = color.srgb_encode(np.clip(baseline.process_denoised_frame(
                    sc.raw_normalized(i), sc.cfa, sc.xyz_to_cam), 0, 1))
            elif parts[0] == "render":
                run = runs / scene / parts[1]
                if (run / "summary.json").is_file() and not stale(run, parts[1], quick):
                    cfg, plan, sc, structure, params, _ = eval_run.load_run(run)
                    i, cams = sc.names.index(name), sc.cameras
                    intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]])
                    out = eval_run.render_view(structure, params, sc, cfg, cams.c2w[i], intr,
                                               cams.height, cams.width)
                    shown = eval_run.run_outputs(cfg, plan, sc, structure, params)
                    img = shown[parts[2]].show(out)[1]
            else:
                png = runs / scene / parts[0] / "eval" / f"{name}_{parts[1]}.png"
                if png.is_file() and not stale(runs / scene / parts[0], parts[0], quick):
                    img = image_io.read_png(png)
            missing += img is None
            tiles.append(np.full((tile[1], tile[0], 3), 0.5) if img is None else
                         resize(np.clip(np.asarray(img, np.float64), 0, 1), (tile[1], tile[0]),
                                anti_aliasing=True))
        rows.append((scene, name, tiles))
    if missing and path.is_file():
        print(f"kept {path}: {missing} of its scenes or tiles have no run on this machine")
        return True
    if not rows:
        return False
    n_cols = len(FIGURE_COLUMNS)
    plt = pyplot()
    fig, axes = plt.subplots(len(rows), n_cols, figsize=(1.6 * n_cols, 1.0 * len(rows) + 0.4),
                             squeeze=False)
    for r, (scene, name, tiles) in enumerate(rows):
        for c, img in enumerate(tiles):
            ax = axes[r][c]
            ax.imshow(img)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(FIGURE_COLUMNS[c][1], fontsize=6)
            if c == 0:
                ax.set_ylabel(f"{scene}\n{name}", fontsize=6)
    fig.tight_layout(pad=0.2)
    save_figure(fig, path, dpi=100)
    return True


def build_quick(runs: Path, folder: Path) -> None:
    """Every run and study of the report, small (module docstring)."""
    from experiments import ablate, consistency, speed, sweep

    for scene in QUICK_SCENES:
        for variant, preset in RUN_PRESETS.items():
            run_variant(scene, variant, preset, [], runs, quick=True)
    ablate.build(QUICK_SCENES, runs, folder / "ablation", quick=True)
    sweep.build(QUICK_SCENES[:1], list(sweep.SWEPT), [0.3, 1.0], runs, folder / "sweep",
                quick=True)
    speed.build(QUICK_SCENES[:1], ["fast", "default"], 200, runs, folder / "speed",
                quick=True)
    consistency.build(QUICK_SCENES[:1], runs, folder / "consistency", True,
                      "python -m experiments.report --quick")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default=None, help="run root (default runs, quick: runs_quick)")
    ap.add_argument("--out", default=None,
                    help="report path stem (default reports/report, quick: reports/quick/report)")
    ap.add_argument("--run-missing", default="",
                    help="scenes whose row runs are trained first: a,b,c or all")
    ap.add_argument("--quick", action="store_true", help="the whole report, small, in minutes")
    ap.add_argument("--figure-scenes", default="bucket,box,held_arc_brick,held_deep_hall")
    args = ap.parse_args()
    runs = Path(args.runs or ("runs_quick" if args.quick else "runs"))
    out = Path(args.out or ("reports/quick/report" if args.quick else "reports/report"))
    scenes = [*SCENES, *HELDOUT]
    if args.quick:
        build_quick(runs, out.parent)
    todo = scenes if args.run_missing == "all" else [s for s in args.run_missing.split(",") if s]
    for scene in todo:
        for variant, preset in RUN_PRESETS.items():
            run_variant(scene, variant, preset, [], runs)
    record = assemble(runs, scenes, args.quick)
    if not any(r["scenes"] for r in record.values()):
        raise SystemExit(f"no evaluated runs under {runs}/: run `make train SCENE=<name>` "
                         "or `make recon` first")
    views = out.parent / f"{out.name}_views.png"
    fig_scenes = QUICK_SCENES if args.quick else args.figure_scenes.split(",")
    has_views = figure(runs, fig_scenes, views, args.quick)
    text = markdown(record, scenes, out.parent, views.name if has_views else None)
    write_report(out, text, record)
    if not args.quick and out == Path("reports/report"):
        update_readme(means_table(record))
    print(text)


if __name__ == "__main__":
    main()
