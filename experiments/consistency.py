"""Multi-view consistency of each method's output, measured.

For every test view i of a scene and its neighbouring frame j (i + 1, else i - 1), each
method's image of view i is moved into view j along the surface points the trained grid
renders (gridnerf.consistency) and compared with the same method's image of view j where
j sees the same point. The geometry is the grid's for every row, so a row's number is the
disagreement of its images alone: 2D methods process each frame on its own (their own
exposure and white balance per frame, their own noise), the grid renders one model. The
references' row (the clean renders of the simulator) is the floor of the metric: what
the grid's geometry error and view-dependent shading leave even for perfect images.
The other 3D rows of the report (RawNeRF + ISP: runs/<scene>/nogain with one grey-world
gain; 2D + NeRF: runs/<scene>/processed; LLNeRF-style: runs/<scene>/llnerf) render their
own images of both views, still compared through the default run's geometry; a row whose
run has not finished (or was trained by another preset than today's) is left out
(`n/a`), not trained.

Reads (or trains, with the default preset) runs/<scene>/default. The table can be built in
parts: a call scores the scenes it names and keeps the other scenes of <out>.json whose
runs were trained by today's presets (their config fingerprints), so scenes scored on an
earlier machine (run folders are not in git) stay in the table with the command that
scored them. Written to reports/consistency, the means also go into docs/results.md
between its consistency markers.

    python -m experiments.consistency [--scenes all|nine|heldout|a,b] [--out PATH]
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from experiments.common import (
    RESULTS_DOC,
    fingerprint,
    markdown_table,
    preset_config,
    run_variant,
    scene_dir,
    scene_names,
    stale_run,
    study_parser,
    update_doc,
    write_report,
)
from gridnerf import baseline, color, consistency, raw
from gridnerf.eval_run import load_run, reference_linear, render_view, run_outputs
from gridnerf.sim import HELDOUT, SCENES

# the report's other 3D rows: row -> (run folder, shown output of eval_run.run_outputs)
RUN_ROWS = {"rawnerf_isp": ("nogain", "global_grey_world"), "2d_nerf": ("processed", "gridnerf"),
            "llnerf": ("llnerf", "llnerf")}
ROWS = ("gridnerf", *RUN_ROWS, "baseline_denoised", "baseline_dark_frame", "reference")
ROW_LABELS = {"gridnerf": "ours", "rawnerf_isp": "RawNeRF + ISP", "2d_nerf": "2D + NeRF",
              "llnerf": "LLNeRF-style", "baseline_denoised": "2D per image (non-local means)",
              "baseline_dark_frame": "one dark frame",
              "reference": "clean references (the geometry's floor)"}


def _views(scene, cfg, structure, params, shown, others, i: int) -> dict:
    """The shown images (sRGB) of frame i per row (ours through `shown`, the run's shown
    output, gridnerf.outputs; `others`: {row: (cfg, structure, params, output)} of the
    other runs), and the grid's render with points."""
    cams = scene.cameras
    ds = cfg.data.eval_downscale
    h, w = cams.height // ds, cams.width // ds
    intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]]) / ds
    out = render_view(structure, params, scene, cfg, cams.c2w[i], intr, h, w, points=True)
    raw_i = scene.raw_normalized(i)
    images = {"gridnerf": shown.show(out)[1]}
    for row, (o_cfg, o_structure, o_params, o_shown) in others.items():
        o_out = render_view(o_structure, o_params, scene, o_cfg, cams.c2w[i], intr, h, w)
        images[row] = o_shown.show(o_out)[1]
    for name, fn in (("baseline_denoised", baseline.process_denoised_frame),
                     ("baseline_dark_frame", baseline.process_dark_frame)):
        linear = fn(raw_i, scene.cfa, scene.xyz_to_cam)
        images[name] = color.srgb_encode(raw.downscale(linear, ds) if ds > 1 else linear)
    gt = reference_linear(scene, scene.names[i], h, w)
    if gt is not None:
        images["reference"] = color.srgb_encode(gt)
    return {"out": out, "images": images, "c2w": cams.c2w[i], "intr": intr}


def scene_rows(scene_name: str, runs: Path = Path("runs"), quick: bool = False) -> dict:
    """{row: {"mae": mean over test views, "coverage": ...}} for one scene (quick: the
    small scene's runs, common.run_variant)."""
    run_variant(scene_name, "default", "default", [], runs, quick, need_run=True)
    folder = Path(runs) / scene_dir(scene_name, quick).name
    cfg, plan, scene, structure, params, _ = load_run(folder / "default")
    n = len(scene.names)
    shown = run_outputs(cfg, plan, scene, structure, params)["gridnerf"]
    others = {}
    for row, (run_folder, key) in RUN_ROWS.items():
        run = folder / run_folder
        if (run / "summary.json").is_file() and not stale_run(run, run_folder, quick):
            o_cfg, o_plan, o_scene, o_structure, o_params, _ = load_run(run)
            o_shown = run_outputs(o_cfg, o_plan, o_scene, o_structure, o_params)[key]
            others[row] = (o_cfg, o_structure, o_params, o_shown)
    per_row: dict[str, list] = {r: [] for r in ROWS}
    for i in scene.test_idx:
        j = int(i) + 1 if int(i) + 1 < n else int(i) - 1
        a = _views(scene, cfg, structure, params, shown, others, int(i))
        b = _views(scene, cfg, structure, params, shown, others, j)
        for row in ROWS:
            if row in a["images"] and row in b["images"]:
                per_row[row].append(consistency.warp_disagreement(
                    a["images"][row], a["out"]["points"], a["out"]["points_valid"],
                    b["images"][row], b["out"]["points"], b["out"]["points_valid"],
                    b["c2w"], b["intr"]))
    return {row: {"mae": float(np.nanmean([m["mae"] for m in v])),
                  "coverage": float(np.mean([m["coverage"] for m in v]))}
            for row, v in per_row.items() if v}


def group_means(record: dict) -> dict:
    """{row: {"nine": (mean x255, n) or None, "held out": ...}} over the scenes of each
    group in the record."""
    out: dict = {}
    for label, names in (("nine", SCENES), ("held out", HELDOUT)):
        got = [record[s]["rows"] for s in names if s in record]
        for r in ROWS:
            vals = [g[r]["mae"] for g in got if r in g]
            out.setdefault(r, {})[label] = (255 * float(np.mean(vals)), len(vals)) if vals \
                else None
    return out


def means_table(record: dict) -> str:
    """The table in docs/results.md: each row's mean disagreement (x255) over the nine and the
    held-out scenes, with the number of scenes."""
    def cell(v):
        return "-" if v is None else f"{v[0]:.2f} (n={v[1]})"
    return markdown_table(["row", "nine built-in", "held out"],
                          [[ROW_LABELS[r], cell(m["nine"]), cell(m["held out"])]
                           for r, m in group_means(record).items()])


def markdown(record: dict) -> str:
    """The table of build's record ({scene: {"rows", "command", ...}}): per scene, then the
    means over the nine and the held-out scenes, each saying how many of its group it
    covers (a row's mean over fewer scenes than the others says n=)."""
    header = ["scene", *[f"{r} (x255)" for r in ROWS], "coverage"]
    lines = []
    for name, entry in record.items():
        rows = entry["rows"]
        lines.append([name, *[f"{255 * rows[r]['mae']:.2f}" if r in rows else "n/a"
                              for r in ROWS], f"{rows['gridnerf']['coverage']:.2f}"])
    means = group_means(record)
    for label, key, names in (("mean, nine", "nine", SCENES),
                              ("mean, held out", "held out", HELDOUT)):
        n = sum(s in record for s in names)
        if n:
            lines.append([f"**{label}** ({n} of {len(names)})", *[
                "n/a" if means[r][key] is None else f"{means[r][key][0]:.2f}" + (
                    f" (n={means[r][key][1]})" if means[r][key][1] < n else "")
                for r in ROWS], ""])
    commands = list(dict.fromkeys(e["command"] for e in record.values()))
    return ("# Multi-view consistency\n\nMean absolute sRGB difference (0-255) between a test "
            "view and its neighbouring frame at the same surface points (the grid's geometry "
            "for every row; occluded and transparent pixels left out; `coverage`: share of "
            "the test view compared). Lower is more consistent; `reference` is the floor "
            "the geometry leaves. Rows as in the report's table (`gridnerf`: ours); `n/a`: "
            "that run has not finished.\n\n"
            + ("Command" + ("s (each scored its scenes; the table keeps them all)"
                            if len(commands) > 1 else "") + ": "
               + "; ".join(f"`{c}`" for c in commands) + "\n\n")
            + markdown_table(header, lines) + "\n")


def todays_fingerprints(quick: bool = False) -> dict:
    """{run folder: fingerprint of the preset of that name today} for the default run and
    the RUN_ROWS runs (each folder is named after its preset)."""
    return {f: fingerprint(preset_config(f, quick))
            for f in ("default", *[f for f, _ in RUN_ROWS.values()])}


def run_fingerprints(scene_name: str, runs: Path, quick: bool, today: dict) -> dict:
    """{run folder: config fingerprint} of the runs a scene's rows were rendered from
    (the default and those of RUN_ROWS that have finished); today: todays_fingerprints."""
    folder = Path(runs) / scene_dir(scene_name, quick).name
    return {f: fp for f, fp in today.items()
            if f == "default" or (folder / f / "summary.json").is_file()}


def kept(out, today: dict) -> dict:
    """The scenes of an earlier <out>.json whose runs were trained by today's presets
    (today: todays_fingerprints)."""
    path = Path(out).with_suffix(".json")
    if not path.is_file():
        return {}
    old = json.loads(path.read_text()).get("scenes", {})
    return {name: e for name, e in old.items()
            if all(today.get(f) == fp for f, fp in e["fingerprints"].items())}


def build(scenes: list[str], runs: Path, out, quick: bool, command: str) -> str:
    """Score every scene given (training its default run if missing), keep the others of
    <out>.json (`kept`), write <out>.md and <out>.json; returns the markdown."""
    today = todays_fingerprints(quick)
    record = ({} if quick else kept(out, today)) | {
        name: {"rows": scene_rows(name, runs, quick), "command": command,
               "fingerprints": run_fingerprints(name, runs, quick, today)} for name in scenes}
    order = [s for s in [*SCENES, *HELDOUT] if s in record]
    record = {s: record[s] for s in [*order, *[s for s in record if s not in order]]}
    text = markdown(record)
    write_report(out, text, {"quick": quick, "scenes": record})
    if not quick and Path(out) == Path("reports/consistency"):
        update_doc("consistency", means_table(record), RESULTS_DOC)
    return text


def main() -> None:
    ap = study_parser(__doc__, "reports/consistency")
    args = ap.parse_args()
    print(build(scene_names(args.scenes), Path("runs"), args.out, False,
                f"python -m experiments.consistency --scenes {args.scenes}"))


if __name__ == "__main__":
    main()
