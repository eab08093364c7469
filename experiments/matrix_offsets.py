"""What the output matrix and the hidden black offsets do to a run's colour, white for white.

For each run (runs/<scene>/<variant>) the test views are rendered once and the field's
low-light colour (`rgb_low`, camera RGB) is balanced per pixel by a white and shown
through one of three output matrices, each at the run's own mean luminance per view (as in
colour_ceiling.py, so only colour differs from `ours`):

- whites: `true` (the simulator's white of each pixel, illuminant_maps.true_map) or
  `field` (the gain field's own white per pixel, opacity / composited gain);
- matrices: `d65` (the default: the raw file's ColorMatrix for D65, row-normalised;
  exposure.display_matrix), `none` (balanced camera RGB shown as sRGB: the paper's output)
  and `adapted` (the DNG pipeline for each pixel's own white: its nearest blackbody on the
  camera's locus, camera -> XYZ, Bradford to D65; exposure.display_matrix with `neutral`);
- `-off`: the same with the simulator's per-CFA black offsets taken off the low-light
  colour (offset_effect.offset_rgb x opacity). With the `field` white this is not what
  fitting the offsets would give: the field's white was estimated on frames that still
  held them.

The truth is read for scoring only; no trainer sees it.

    python experiments/matrix_offsets.py [--scenes mixed_lamp_window,rabbit] [--variant default]

Writes reports/matrix_offsets.md and reports/matrix_offsets.json.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from colour_ceiling import test_views
from common import REPORT_GROUPS, fmt, markdown_table, simulated_folders, study_parser, write_report
from gridnerf import color, evaluate, exposure, illuminant
from gridnerf.sim import HELDOUT_MIXED, MIXED
from offset_effect import offset_rgb

MATRICES = ("d65", "none", "adapted")


def shown_through(rgb_low, white, matrix: str, xyz_to_cam) -> np.ndarray:
    """rgb_linear (H, W, 3): rgb_low (H, W, 3) balanced by each pixel's white (H, W, 3) and
    shown through `matrix` (MATRICES); `adapted` groups the pixels by the locus entry
    nearest their white (one DNG matrix per entry)."""
    balanced = rgb_low * np.asarray(illuminant.gains_from_illuminant(white))
    if matrix != "adapted":
        return balanced @ exposure.display_matrix(xyz_to_cam, matrix == "d65").T
    locus = illuminant.planckian_locus(xyz_to_cam)
    nearest = np.argmax(illuminant.unit(white) @ locus.T, axis=-1)
    out = np.zeros_like(balanced)
    for k in np.unique(nearest):
        sel = nearest == k
        out[sel] = balanced[sel] @ exposure.display_matrix(xyz_to_cam, True, locus[k]).T
    return out


def run_rows(run: Path, folder: Path) -> dict:
    """{row: {"psnr", "delta_e"}} means over the run's test views."""
    _, scene, _, shown, views = test_views(run, folder)
    off = offset_rgb(scene)
    per_view = {}
    for _, out, gt, truth in views:
        ours, _ = shown["gridnerf"].show(out)
        target = float(np.mean(color.luminance(ours)))
        acc = np.asarray(out["acc"], np.float64)[..., None]
        field = acc / np.maximum(np.asarray(out["gain"], np.float64), 1e-12)
        field = np.where(acc > 1e-3, field, truth)  # empty rays: any white, nothing to show
        rows = {"ours": ours}
        low = np.asarray(out["rgb_low"], np.float64)
        for tag, rgb_low in (("", low), ("-off", low - off * acc)):
            for wname, white in (("true", truth), ("field", field)):
                for m in MATRICES:
                    rgb = shown_through(rgb_low, white, m, scene.xyz_to_cam)
                    rows[f"{wname} {m}{tag}"] = exposure.alpha_for_luminance(rgb, target) * rgb
        for name, rgb in rows.items():
            per_view.setdefault(name, []).append(
                evaluate.image_metrics(np.asarray(rgb, np.float32), gt))
    return {name: {k: float(np.mean([m[k] for m in scores])) for k in ("psnr", "delta_e")}
            for name, scores in per_view.items()}


def main() -> None:
    ap = study_parser(__doc__, "reports/matrix_offsets",
                      scenes="mixed,heldmixed,rabbit,bucket,box,dora,head,held_deep_hall,"
                      "held_arc_table")
    ap.add_argument("--variant", default="default")
    args = ap.parse_args()
    record = {}
    for name, folder in simulated_folders(args.scenes):
        run = Path("runs") / name / args.variant
        if not (run / "summary.json").exists():
            print(f"skipping {name}: no finished run at {run}")
            continue
        record[name] = run_rows(run, folder)
        print(name, {k: round(v["psnr"], 2) for k, v in record[name].items()}, flush=True)
    write_report(args.out, "# The output matrix and the black offsets, white for white\n\n"
                 f"`python experiments/matrix_offsets.py --scenes {args.scenes} --variant "
                 f"{args.variant}`. PSNR / CIEDE2000 on the test views, every row at the "
                 "run's own mean luminance per view; `-off`: the simulator's black offsets "
                 "taken off the field's low-light colour.\n\n" + table(record) + "\n", record)


def table(record: dict) -> str:
    """Markdown: each scene's rows, then the means per scene group, over all the mixed-light
    and all the single-light scenes shown, and over every scene shown."""
    columns = list(next(iter(record.values()))) if record else []
    lines = [[n, *(f"{fmt(r[c]['psnr'])} / {fmt(r[c]['delta_e'])}" for c in columns)]
             for n, r in record.items()]
    mixed = MIXED + HELDOUT_MIXED
    for label, group in (*REPORT_GROUPS, ("all mixed light", mixed),
                         ("all single light", tuple(n for n in record if n not in mixed)),
                         ("all shown", tuple(record))):
        got = [record[n] for n in group if n in record]
        if got:
            lines.append([f"**mean, {label}** ({len(got)})",
                          *(f"{fmt(np.mean([g[c]['psnr'] for g in got]))} / "
                            f"{fmt(np.mean([g[c]['delta_e'] for g in got]))}"
                            for c in columns)])
    return markdown_table(["scene", *columns], lines)

if __name__ == "__main__":
    main()
