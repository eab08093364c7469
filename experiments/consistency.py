"""Multi-view consistency of each method's output, measured (issue 9).

For every test view i of a scene and its neighbouring frame j (i + 1, else i - 1), each
method's image of view i is moved into view j along the surface points the trained grid
renders (gridnerf.consistency) and compared with the same method's image of view j where
j sees the same point. The geometry is the grid's for every row, so a row's number is the
disagreement of its images alone: 2D methods process each frame on its own (their own
exposure and white balance per frame, their own noise), the grid renders one model. The
references' row (the clean renders of the simulator) is the floor of the metric: what
the grid's geometry error and view-dependent shading leave even for perfect images.

Reads (or trains, with the default preset) runs/<scene>/default.

    python experiments/consistency.py [--scenes all|nine|heldout|a,b] [--out PATH]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from common import markdown_table, run_variant, simulated_folders, write_report
from gridnerf import baseline, color, consistency, raw
from gridnerf.eval_run import load_run, outputs, reference_linear, render_view
from gridnerf.sim import HELDOUT, SCENES

ROWS = ("gridnerf", "baseline_denoised", "baseline_dark_frame", "reference")


def _views(scene, cfg, structure, params, shown, i: int) -> dict:
    """The shown images (sRGB) of frame i per row (ours through `shown`, the run's
    eval_run.Output), and the grid's render with points."""
    cams = scene.cameras
    ds = cfg.data.eval_downscale
    h, w = cams.height // ds, cams.width // ds
    intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]]) / ds
    out = render_view(structure, params, scene, cfg, cams.c2w[i], intr, h, w, points=True)
    raw_i = scene.raw_normalized(i)
    images = {"gridnerf": shown.show(out)[1]}
    for name, fn in (("baseline_denoised", baseline.process_denoised_frame),
                     ("baseline_dark_frame", baseline.process_dark_frame)):
        linear = fn(raw_i, scene.cfa, scene.xyz_to_cam)
        images[name] = color.srgb_encode(raw.downscale(linear, ds) if ds > 1 else linear)
    gt = reference_linear(scene, scene.names[i], h, w)
    if gt is not None:
        images["reference"] = color.srgb_encode(gt)
    return {"out": out, "images": images, "c2w": cams.c2w[i], "intr": intr}


def scene_rows(scene_name: str) -> dict:
    """{row: {"mae": mean over test views, "coverage": ...}} for one scene."""
    run_variant(scene_name, "default", "default", [])
    cfg, scene, structure, params, _ = load_run(Path("runs") / scene_name / "default")
    n = len(scene.names)
    shown = outputs(structure, params, scene, cfg)["gridnerf"]  # exposed once per run
    per_row: dict[str, list] = {r: [] for r in ROWS}
    for i in scene.test_idx:
        j = int(i) + 1 if int(i) + 1 < n else int(i) - 1
        a = _views(scene, cfg, structure, params, shown, int(i))
        b = _views(scene, cfg, structure, params, shown, j)
        for row in ROWS:
            if row in a["images"] and row in b["images"]:
                per_row[row].append(consistency.warp_disagreement(
                    a["images"][row], a["out"]["points"], a["out"]["points_valid"],
                    b["images"][row], b["out"]["points"], b["out"]["points_valid"],
                    b["c2w"], b["intr"]))
    return {row: {"mae": float(np.nanmean([m["mae"] for m in v])),
                  "coverage": float(np.mean([m["coverage"] for m in v]))}
            for row, v in per_row.items() if v}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="all")
    ap.add_argument("--out", default="reports/consistency")
    args = ap.parse_args()
    spec = {"all": ",".join([*SCENES, *HELDOUT]), "nine": ",".join(SCENES),
            "heldout": ",".join(HELDOUT)}.get(args.scenes, args.scenes)
    record = {name: scene_rows(name) for name, _ in simulated_folders(spec)}
    header = ["scene", *[f"{r} (x255)" for r in ROWS], "coverage"]
    lines = []
    for name, rows in record.items():
        lines.append([name, *[f"{255 * rows[r]['mae']:.2f}" if r in rows else "n/a"
                              for r in ROWS], f"{rows['gridnerf']['coverage']:.2f}"])
    for label, names in (("mean, nine", SCENES), ("mean, held out", HELDOUT)):
        got = [record[s] for s in names if s in record]
        if got:
            lines.append([label, *[f"{255 * np.mean([g[r]['mae'] for g in got if r in g]):.2f}"
                                   for r in ROWS], ""])
    md = ("# Multi-view consistency\n\nMean absolute sRGB difference (0-255) between a test "
          "view and its neighbouring frame at the same surface points (the grid's geometry "
          "for every row; occluded and transparent pixels left out; `coverage`: share of "
          "the test view compared). Lower is more consistent; `reference` is the floor "
          "the geometry leaves.\n\n"
          f"Command: `python experiments/consistency.py --scenes {args.scenes}`\n\n"
          + markdown_table(header, lines) + "\n")
    write_report(args.out, md, record)
    print(md)


if __name__ == "__main__":
    main()
