"""How much of a run's error is white balance: its render shown with the true white.

For each run (runs/<scene>/<variant>) the test views are rendered once and the field's
low-light colour (`rgb_low`, camera RGB) is shown four ways through the run's own display
matrix, each at the same mean luminance as the run's own output on that view (so only
colour differs from `ours`):

- `ours`: the run's output (its gain field; eval_run.outputs' "gridnerf"),
- `field_global`: the gain field collapsed to one gain, the white it balances on average
  over the training render (eval_run.field_neutral): the same estimate of the light
  without the spatial variation, so `ours - field_global` is what the field's variation
  adds,
- `global_gw`: one grey-world gain for the scene (eval_run.global_gains),
- `true_global`: one gain from the true white of the view (the mean of the per-pixel truth),
- `true_local`: per-pixel gains from the true white of each pixel: for mixed-light scenes
  the blend of the two lights by the first one's share of the camera green signal
  (illuminant/<frame>.png, written by the simulator), elsewhere the one light.

`true_local - true_global` is what a perfect gain *field* could add over a perfect single
gain on that reconstruction; `true_local - ours` is what colour still costs the run.

Two more rows split that cost between the white's level (its mean colour: colour
constancy) and its shape (how it varies over the view), for runs with gains:
`field_true_level`, the field's own white per pixel (opacity / composited gain) moved to
the truth's mean log chromaticity, and `true_shape`, the true white per pixel moved to the
field's mean log chromaticity (illuminant_maps.with_true_level, green-weighted over the
pixels the grid renders). `field_true_level - global_gw` is what the field would beat one
grey-world gain by with perfect colour constancy, `true_shape - global_gw` the same with a
perfect shape at the field's own level. The
truth is read for scoring only; no trainer sees it. Run folders whose config uses the
adapted matrix are shown with the D65 matrix here (the adapted one needs one white).

    python experiments/colour_ceiling.py [--scenes all] [--variant default]

Writes reports/colour_ceiling.md and reports/colour_ceiling.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common import REPORT_GROUPS, fmt, markdown_table, simulated_folders, study_parser, write_report
from gridnerf import color, eval_run, evaluate, exposure, illuminant
from gridnerf.sim import HELDOUT_MIXED, MIXED
from illuminant_maps import true_map, weighted_error, with_true_level

ROWS = ("ours", "field_global", "global_gw", "true_global", "true_local")
SPLIT = ("field_true_level", "true_shape")  # the level / shape split (runs with gains)


def test_views(run: Path, folder: Path):
    """The run loaded and scored the way `gridnerf eval` scores it: (cfg, scene, train_out,
    shown, views), train_out its training render, shown eval_run.outputs of it, views an
    iterator over the test views of (name, out: the render, gt_linear (H, W, 3), truth: the
    true white per pixel (H, W, 3), from the simulator's sim.json and illuminant maps)."""
    sim = json.loads((folder / "sim.json").read_text())
    cfg, scene, structure, params, _ = eval_run.load_run(run)
    train_out = eval_run.training_render(structure, params, scene, cfg)
    shown = eval_run.run_outputs(run, structure, params, scene, cfg, train_out)
    cams = scene.cameras
    hw = (cams.height, cams.width)

    def views():
        for i in scene.test_idx:
            intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]])
            out = eval_run.render_view(structure, params, scene, cfg, cams.c2w[i], intr, *hw)
            yield (scene.names[i], out, eval_run.reference_linear(scene, scene.names[i], *hw),
                   true_map(folder, sim, scene.names[i], hw))

    return cfg, scene, train_out, shown, views()


def view_rows(out: dict, shown: dict, matrix: np.ndarray, truth: np.ndarray,
              field_white: np.ndarray) -> dict:
    """rgb_linear (H, W, 3) of each row for one rendered view; truth: (H, W, 3) true white
    per pixel (green = 1); field_white: (3,) the white the run's gains balance on average
    (eval_run.field_neutral of its training render)."""
    ours, _ = shown["gridnerf"].show(out)
    target = float(np.mean(color.luminance(ours)))
    low = np.asarray(out["rgb_low"], np.float64)
    local, one = gains(truth), gains(truth.reshape(-1, 3).mean(0))
    rows = {"ours": ours}
    field_one = gains(field_white)
    shows = [("field_global", low * field_one),
             ("global_gw", low * shown["global_grey_world"].gains),
             ("true_global", low * one), ("true_local", low * local)]
    if "gain" in out:
        field, rendered = pixel_white(out, field_white)
        shows += [("field_true_level", low * gains(with_true_level(field, truth, rendered))),
                  ("true_shape", low * gains(with_true_level(truth, field, rendered)))]
    for name, rgb_cam in shows:
        rows[name] = shown_at(rgb_cam, matrix, target)
    return rows


def shown_at(rgb_cam: np.ndarray, matrix: np.ndarray, target: float) -> np.ndarray:
    """(H, W, 3) float32 linear sRGB: camera RGB through the display matrix, exposed to the
    mean luminance `target` (the run's own output's on that view: only colour differs)."""
    rgb = rgb_cam @ matrix.T
    return (exposure.alpha_for_luminance(rgb, target) * rgb).astype(np.float32)


def gains(white) -> np.ndarray:
    """Von Kries gains (..., 3) for a white (..., 3), as float64 host arrays."""
    return np.asarray(illuminant.gains_from_illuminant(np.asarray(white, np.float64)))


def pixel_white(out: dict, fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(field, rendered): the gain field's own white per pixel (H, W, 3), opacity /
    composited gain (`fallback`, the (3,) white of its mean gain, where the opacity is
    below 0.05 and the ratio means nothing), and the camera RGB of the pixels the grid
    renders (opacity > 0.5, else 0), the weights of every comparison of whites."""
    acc = np.asarray(out["acc"], np.float64)[..., None]
    gain = np.maximum(np.asarray(out["gain"], np.float64), 1e-12)
    field = np.where(acc > 0.05, acc / gain, np.asarray(fallback, np.float64))
    return field, np.asarray(out["rgb_low"], np.float64) * (acc > 0.5)


def white_errors(out: dict, truth: np.ndarray, whites: dict) -> dict:
    """Angular error (deg) of each white against the true white of the view's pixels:
    'field' the gain field's own (opacity / composited gain, per pixel), the others (3,)
    whites of one gain; over the pixels the grid renders (opacity > 0.5), weighted by
    their rendered green signal."""
    field, rgb_cam = pixel_white(out, np.ones(3))  # the fallback's pixels weigh nothing
    if not np.any(rgb_cam[..., 1] > 0):
        return {}
    return {name: weighted_error(np.broadcast_to(white, truth.shape), truth, rgb_cam)
            for name, white in {"field": field, **whites}.items()}


WHITES = ("field", "field_global", "global_gw")


def white_table(record: dict) -> str:
    """Markdown: white_error_deg of each scene and group mean ('' when no run has it)."""
    rows = [[n, *(fmt(r["white_error_deg"][k]) for k in WHITES)]
            for n, r in record.items() if "white_error_deg" in r]
    for label, group in REPORT_GROUPS:
        got = [record[n]["white_error_deg"] for n in group
               if "white_error_deg" in record.get(n, {})]
        if got:
            rows.append([f"**mean, {label}** ({len(got)})",
                         *(fmt(float(np.mean([g[k] for g in got]))) for k in WHITES)])
    if not rows:
        return ""
    return ("\n\n## The whites against the true white\n\nAngular error (deg) on the test "
            "views against the true white of each pixel, over the pixels the grid renders "
            "(opacity > 0.5) weighted by their green signal: `field` the gain field's own "
            "white per pixel (opacity / composited gain), `field_global` its mean over the "
            "training render, `global_gw` the white of one grey-world gain.\n\n"
            + markdown_table(["scene", *WHITES], rows))


def split_table(record: dict) -> str:
    """Markdown: each run's PSNR over one grey-world gain, as it is and with a perfect
    level or a perfect shape of its white ('' when no run has the split rows)."""
    cols = ("ours", *SPLIT, "true_local")

    def row(name: str, got: list[dict]) -> list[str]:
        return [name, *(fmt(float(np.mean([g[c]["psnr"] - g["global_gw"]["psnr"]
                                            for g in got]))) for c in cols)]

    rows = [row(n, [r]) for n, r in record.items() if SPLIT[0] in r]
    for label, group in REPORT_GROUPS:
        got = [record[n] for n in group if SPLIT[0] in record.get(n, {})]
        if got:
            rows.append(row(f"**mean, {label}** ({len(got)})", got))
    if not rows:
        return ""
    return ("\n\n## Level or shape: what a perfect one of each would add\n\nPSNR (dB) over "
            "one grey-world gain on the same render (issue 8's bar: +1.5 on mixed light): "
            "`ours` the run's output, `field_true_level` the field's white per pixel at the "
            "truth's mean colour (perfect colour constancy, the field's shape), `true_shape` "
            "the true white per pixel at the field's mean colour (a perfect shape, the "
            "field's level), `true_local` both (the ceiling).\n\n"
            + markdown_table(["scene", *cols], rows))


def table_row(name: str, summary: dict) -> list[str]:
    """One line of the table: PSNR / CIEDE2000 of each row, then the three differences."""
    return [name, *(f"{fmt(summary[r]['psnr'])} / {fmt(summary[r]['delta_e'])}" for r in ROWS),
            fmt(summary["true_local"]["psnr"] - summary["true_global"]["psnr"]),
            fmt(summary["true_local"]["psnr"] - summary["ours"]["psnr"]),
            fmt(summary["ours"]["psnr"] - summary["field_global"]["psnr"])]


def main() -> None:
    ap = study_parser(__doc__, "reports/colour_ceiling", runs=True)
    ap.add_argument("--variant", default="default")
    args = ap.parse_args()
    record, table = {}, []
    for name, folder in simulated_folders(args.scenes):
        run = Path(args.runs) / name / args.variant
        if not (run / "summary.json").exists():
            print(f"skipping {name}: no finished run at {run}")
            continue
        cfg, scene, train_out, shown, views = test_views(run, folder)
        field_white = (eval_run.field_neutral(train_out) if cfg.loss.use_gains
                       else np.asarray(illuminant.grey_world(np.asarray(train_out["rgb_low"]))))
        matrix = exposure.display_matrix(scene.xyz_to_cam, cfg.output.use_color_matrix)
        per_view = {r: [] for r in ROWS + (SPLIT if cfg.loss.use_gains else ())}
        whites = {"field_global": field_white,
                  "global_gw": 1.0 / shown["global_grey_world"].gains}
        white_err = []
        for _, out, gt_linear, truth in views:
            for r, rgb_linear in view_rows(out, shown, matrix, truth, field_white).items():
                per_view[r].append(evaluate.image_metrics(rgb_linear, gt_linear))
            if cfg.loss.use_gains:
                white_err.append(white_errors(out, truth, whites))
        summary = {r: evaluate.summarize(dict(enumerate(v))) for r, v in per_view.items()}
        record[name] = {"run": str(run), "mixed_light": name in MIXED + HELDOUT_MIXED,
                        **summary}
        if white_err and all(white_err):
            record[name]["white_error_deg"] = {k: float(np.mean([e[k] for e in white_err]))
                                               for k in white_err[0]}
        table.append(table_row(name, summary))
        print(name, table[-1][1:], flush=True)
    for label, group in REPORT_GROUPS:
        got = [record[n] for n in group if n in record]
        if got:
            mean = {r: {m: float(np.mean([g[r][m] for g in got])) for m in ("psnr", "delta_e")}
                    for r in ROWS}
            table.append(table_row(f"**mean, {label}** ({len(got)})", mean))
    md_white = white_table(record) + split_table(record)
    md = ("# Colour ceiling: the run's render shown with the true white\n\n"
          f"`python experiments/colour_ceiling.py --scenes {args.scenes} --variant "
          f"{args.variant}`. PSNR / CIEDE2000 on the test views, every row at the run's own "
          "mean luminance per view. `field room`: true_local - true_global (what a perfect "
          "gain field adds over a perfect single gain); `colour cost`: true_local - ours; "
          "`field variation`: ours - field_global (what the field adds over its own mean "
          "gain).\n\n"
          + markdown_table(["scene", *ROWS, "field room", "colour cost", "field variation"],
                         table)
          + md_white)
    write_report(args.out, md, record)


if __name__ == "__main__":
    main()
