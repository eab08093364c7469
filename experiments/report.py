"""Per-scene metric tables like the paper's Table 1, from every evaluated run.

Reads runs/<scene>/<preset>/eval/metrics.json and writes runs/report.md with
one table per preset: PSNR / SSIM / LPIPS / CIEDE2000 per scene for our
output, the paper's matrix-free output and the dark-frame baseline, plus the
mean over scenes, training time and speed. LPIPS is n/a (no offline weights).

    python experiments/report.py [--preset default] [--scenes all]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from common import fmt, markdown_table, run_variant

from gridnerf.sim import SCENES

METHODS = [
    ("gridnerf", "gridnerf (colour matrix)"),
    ("gridnerf_matrix_free", "gridnerf (paper's matrix-free output)"),
    ("baseline_dark_frame", "dark frame: demosaic + grey-world + gamma"),
]


def table_for(preset: str, metrics: dict[str, dict]) -> str:
    out = [f"## preset `{preset}`\n"]
    for key, label in METHODS:
        trained = key != "baseline_dark_frame"
        rows, cols = [], {k: [] for k in ("psnr", "ssim", "delta_e", "psnr_aligned")}
        for scene, m in sorted(metrics.items()):
            s = m["summary"].get(key)
            if not s:
                continue
            for k in cols:
                cols[k].append(s[k])
            rows.append(
                [
                    scene,
                    fmt(s["psnr"]),
                    fmt(s["ssim"], 3),
                    m.get("lpips", "n/a"),
                    fmt(s["delta_e"]),
                    fmt(s["psnr_aligned"]),
                    fmt(m["train_seconds"], 0) if trained else "-",
                    fmt(m["rays_per_second"], 0) if trained else "-",
                ]
            )
        if rows:
            rows.append(
                [
                    "**mean**",
                    fmt(np.mean(cols["psnr"])),
                    fmt(np.mean(cols["ssim"]), 3),
                    "n/a",
                    fmt(np.mean(cols["delta_e"])),
                    fmt(np.mean(cols["psnr_aligned"])),
                    "",
                    "",
                ]
            )
            header = [
                "scene",
                "PSNR",
                "SSIM",
                "LPIPS",
                "CIEDE2000",
                "PSNR al.",
                "train s",
                "rays/s",
            ]
            out.append(f"### {label}\n\n{markdown_table(header, rows)}\n")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default=None, help="only this preset (default: all found)")
    ap.add_argument(
        "--run-missing",
        default="",
        help="scenes to train first: a,b,c or all",
    )
    args = ap.parse_args()
    names = [s for s in args.run_missing.split(",") if s]
    todo = SCENES if args.run_missing == "all" else names
    for scene in todo:
        run_variant(scene, args.preset or "default", args.preset or "default", [])
    found: dict[str, dict[str, dict]] = {}
    for path in sorted(Path("runs").glob("*/*/eval/metrics.json")):
        preset, scene = path.parts[-3], path.parts[-4]
        if args.preset and preset != args.preset:
            continue
        found.setdefault(preset, {})[scene] = json.loads(path.read_text())
    if not found:
        raise SystemExit("no evaluated runs under runs/: run `make train SCENE=<name>` first")
    text = "# gridnerf report\n\n" + "\n".join(table_for(p, m) for p, m in sorted(found.items()))
    Path("runs/report.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
