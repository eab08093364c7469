"""The per-scene report in the paper's layout, from every evaluated run (issue 9).

Reads runs/<scene>/<variant>/eval/metrics.json (nothing is trained unless --run-missing
asks) and writes reports/report.md and reports/report.json: for each method row and
each scene PSNR / SSIM / CIEDE2000, raw and aligned (per-channel affine fit in linear
space first), then the mean over the nine built-in scenes and, separately, over the
held-out ones (no default was tuned on those). Rows whose runs are missing say so; the
paper's CNN rows need pretrained weights that are not available offline and are n/a.
The multi-view consistency table (experiments/consistency.py) is appended when
reports/consistency.json exists.

    python experiments/report.py [--runs runs] [--out reports/report] [--run-missing a,b|all]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from common import fmt, markdown_table, run_variant, write_report

from gridnerf.sim import HELDOUT, SCENES

# (row, label, run variant, key in that run's eval summary)
ROWS = [
    ("ours", "ours (gains + L_ca + smoothness, auto exposure)", "default", "gridnerf"),
    ("rawnerf_isp", "RawNeRF + generic ISP (no gains; one grey-world gain)", "nogain",
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
    ("oracle", "oracle: the grid trained on the clean references (upper bound)", "oracle",
     "gridnerf"),
]
NOT_AVAILABLE = {
    "llnerf": "LLNeRF-style decomposition on the grid: not built yet",
    "cnn": "SID, RED, ABF, DNF: need pretrained weights, not available offline",
}
METRICS = ("psnr", "ssim", "delta_e", "psnr_aligned", "ssim_aligned", "delta_e_aligned")


def assemble(runs: Path, scenes: list[str]) -> dict:
    """{row: {"label", "scenes": {scene: metrics}, "mean_nine", "mean_heldout"}} from the
    evaluated runs under `runs`; a mean covers the scenes the row has (with their count)."""
    record = {}
    for row, label, variant, key in ROWS:
        per_scene = {}
        for scene in scenes:
            path = runs / scene / variant / "eval" / "metrics.json"
            if path.is_file():
                summary = json.loads(path.read_text())["summary"].get(key)
                if summary:
                    per_scene[scene] = {k: float(summary[k]) for k in METRICS}
        entry = {"label": label, "variant": variant, "key": key, "scenes": per_scene}
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


def markdown(record: dict, scenes: list[str], consistency: dict | None) -> str:
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
    text = ("# gridnerf report\n\nEach cell: PSNR / SSIM / CIEDE2000 (sRGB, 16-pixel border "
            "crop). Held-out scenes (no default tuned on them) are averaged separately.\n\n"
            f"{legend}\n"
            + "".join(f"- `{r}`: no evaluated runs yet\n" for r in missing)
            + "".join(f"- {k}: n/a ({v})\n" for k, v in NOT_AVAILABLE.items())
            + "\n## Test views\n\n" + markdown_table(header, lines)
            + "\n\n## Aligned (per-channel affine fit in linear space first)\n\n"
            + markdown_table(header, aligned) + "\n")
    if consistency:
        text += ("\n## Multi-view consistency\n\n(reports/consistency.md: mean absolute sRGB "
                 "difference, 0-255, between a test view and its neighbouring frame at the "
                 "grid's surface points)\n\n")
        cols = sorted({k for v in consistency.values() for k in v})
        text += markdown_table(["scene", *cols], [
            [s, *[fmt(255 * v[c]["mae"]) if c in v else "-" for c in cols]]
            for s, v in consistency.items()]) + "\n"
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="runs")
    ap.add_argument("--out", default="reports/report")
    ap.add_argument("--run-missing", default="",
                    help="scenes whose default run is trained first: a,b,c or all")
    args = ap.parse_args()
    scenes = [*SCENES, *HELDOUT]
    todo = scenes if args.run_missing == "all" else [s for s in args.run_missing.split(",") if s]
    for scene in todo:
        run_variant(scene, "default", "default", [])
    record = assemble(Path(args.runs), scenes)
    if not any(r["scenes"] for r in record.values()):
        raise SystemExit(f"no evaluated runs under {args.runs}/: run `make train SCENE=<name>` "
                         "or `make recon` first")
    cons_path = Path("reports/consistency.json")
    consistency = json.loads(cons_path.read_text()) if cons_path.is_file() else None
    text = markdown(record, scenes, consistency)
    write_report(args.out, text, record)
    print(text)


if __name__ == "__main__":
    main()
