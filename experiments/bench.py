"""Speed against error: train a scene at several budgets, one process each.

For each setting: training seconds, rays/s, peak memory (RSS of the training
process), voxels, and the test-view PSNR / SSIM / CIEDE2000 (raw and aligned).
Also runs the renderer micro-benchmark (experiments/bench_render.py).
Writes runs/<scene>/bench.md and prints it.

    python experiments/bench.py --scene bucket [--quick]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from common import fmt, markdown_table, scene_dir

SETTINGS = {
    "bench_small": ["grid.resolutions=[[48,48,24],[96,96,48]]", "train.steps_per_stage=[300,450]"],
    "bench_default": [],
    "bench_large": [
        "grid.resolutions=[[64,64,32],[128,128,64],[192,192,96]]",
        "train.steps_per_stage=[600,900,900]",
    ],
}


def run_setting(sdir: Path, name: str, overrides: list[str]) -> dict:
    run = Path("runs") / sdir.name / name
    if not (run / "eval" / "metrics.json").exists():
        cmd = [sys.executable, "-m", "gridnerf.cli", "train", str(sdir), "--out", str(run)]
        subprocess.run(cmd + (["--set", *overrides] if overrides else []), check=True)
        subprocess.run([sys.executable, "-m", "gridnerf.cli", "eval", str(run)], check=True)
    summary = json.loads((run / "summary.json").read_text())
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    return {"summary": summary, "metrics": metrics["summary"]["gridnerf"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="bucket")
    ap.add_argument("--quick", action="store_true", help="only the small setting")
    args = ap.parse_args()
    sdir = scene_dir(args.scene)
    names = ["bench_small"] if args.quick else list(SETTINGS)
    rows = []
    for name in names:
        r = run_setting(sdir, name, SETTINGS[name])
        s, m = r["summary"], r["metrics"]
        rows.append(
            [
                name,
                fmt(s["train_seconds"], 0),
                fmt(s["rays_per_second"], 0),
                fmt(s["peak_rss_mb"], 0),
                str(s["voxels"]),
                fmt(m["psnr"]),
                fmt(m["ssim"], 3),
                fmt(m["delta_e"]),
                fmt(m["psnr_aligned"]),
            ]
        )
    table = markdown_table(
        [
            "setting",
            "train s",
            "rays/s",
            "peak RSS MB",
            "voxels",
            "PSNR",
            "SSIM",
            "CIEDE2000",
            "PSNR al.",
        ],
        rows,
    )
    render = subprocess.run(
        [sys.executable, str(Path(__file__).with_name("bench_render.py"))],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    out = Path("runs") / sdir.name / "bench.md"
    out.write_text(f"# Speed against error on {args.scene}\n\n{table}\n\n## Renderer\n\n{render}\n")
    print(out.read_text())


if __name__ == "__main__":
    main()
