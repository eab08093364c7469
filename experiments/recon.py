"""Reconstruction table: every scene trained from transforms.json without bounds.

For each scene: the default preset (ours), the oracle preset (the same grid trained on the
clean references: the representational ceiling) and the generous per-frame baseline (2x2
binning, grey world, colour matrix, exposure matched to the reference, bilinear upsampling;
gridnerf.baseline.process_binned_frame), scored on the test views. The nine built-in
scenes, the tuning scenes with an arc and a slide rig (gridnerf.sim.DEV: defaults may be
chosen on them) and the held-out scenes (gridnerf.sim.HELDOUT, which no default is tuned
on) are reported in separate tables. Runs are cached in runs/<scene>/<preset>/ (re-running
reuses finished runs); without the folder, a kept result of the same config
(reports/results.json) and the folder's facts kept beside it stand in for the run. Writes
reports/recon.md and reports/recon.json and, with --scenes all, the tables in
docs/results.md between the recon markers.

    python -m experiments.recon [--scenes all|nine|dev|heldout|name,name]
                                [--oracle all|heldout|none]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

from experiments.common import (
    RESULTS_DOC,
    cached_result,
    fmt,
    markdown_table,
    preset_config,
    run_variant,
    scene_names,
    update_doc,
    write_report,
)
from gridnerf.sim import DEV, HELDOUT


def row_for(scene: str, oracle: bool) -> dict:
    """One scene's row: the default's run folder where it is here (trained where neither
    it nor a kept result of today's default is), else its kept result and kept facts
    (common.run_facts; "n/a" for a result kept before them)."""
    ours = run_variant(scene, "default", "default", [])
    s = ours["summary"]
    summary = ours.get("facts", {})  # the folder's (run_variant), or kept with the result
    row = {
        "scene": scene,
        "held_out": scene in HELDOUT,
        "group": "heldout" if scene in HELDOUT else "dev" if scene in DEV else "nine",
        "psnr": s["gridnerf"]["psnr"],
        "ssim": s["gridnerf"]["ssim"],
        "delta_e": s["gridnerf"]["delta_e"],
        "baseline_psnr": s["baseline_binned_matched"]["psnr"],
        "baseline_ssim": s["baseline_binned_matched"]["ssim"],
        "resolution": summary.get("resolution"),
        "occupied_fraction": summary.get("occupied_fraction"),
        "train_seconds": summary.get("train_seconds"),
        "oracle_psnr": None,
    }
    for key, name in (("global", "global_grey_world"), ("denoised", "baseline_denoised")):
        if name in s:  # runs evaluated before these rows existed lack them
            row[f"{key}_psnr"], row[f"{key}_delta_e"] = s[name]["psnr"], s[name]["delta_e"]
    if "bounds" in summary:
        row["bounds"] = summary["bounds"]
    if oracle:
        o = run_variant(scene, "oracle", "oracle", [])  # its scores: a cached result will do
        row["oracle_psnr"] = o["summary"]["gridnerf"]["psnr"]
        row["oracle_ssim"] = o["summary"]["gridnerf"]["ssim"]
    return row


def table(rows: list[dict]) -> str:
    body = []
    for r in rows:
        body.append([r["scene"], fmt(r["psnr"]), fmt(r["ssim"], 3), fmt(r["delta_e"]),
                     fmt(r["oracle_psnr"]), fmt(r["baseline_psnr"]),
                     fmt(r["psnr"] - r["baseline_psnr"]),
                     "x".join(str(v) for v in r["resolution"] or []),
                     fmt(100 * r["occupied_fraction"], 1) if r["occupied_fraction"] else "n/a",
                     fmt(r["train_seconds"], 0) if r["train_seconds"] is not None else "n/a"])
    if rows:
        mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
        oracle = [r["oracle_psnr"] for r in rows if r["oracle_psnr"] is not None]
        secs = [r["train_seconds"] for r in rows if r["train_seconds"] is not None]
        body.append(["**mean**", fmt(mean("psnr")), fmt(mean("ssim"), 3), fmt(mean("delta_e")),
                     fmt(float(np.mean(oracle))) if oracle else "n/a",
                     fmt(mean("baseline_psnr")), fmt(mean("psnr") - mean("baseline_psnr")),
                     "", "", fmt(float(np.mean(secs)), 0) if secs else "n/a"])
    return markdown_table(["scene", "PSNR", "SSIM", "CIEDE2000", "oracle PSNR",
                           "per-frame PSNR", "ours - per-frame", "final grid", "occupied %",
                           "train s"], body)


def colour_table(rows: list[dict]) -> str:
    """Ours against the same field with one grey-world gain for the scene (no gain field)
    and against the paper's 2D row (one frame, non-local means): PSNR / CIEDE2000."""
    rows = [r for r in rows if "global_psnr" in r]
    pair = lambda p, d: f"{fmt(p)} / {fmt(d)}"  # noqa: E731
    body = [[r["scene"], pair(r["psnr"], r["delta_e"]), pair(r["global_psnr"],
                                                            r["global_delta_e"]),
             pair(r.get("denoised_psnr"), r.get("denoised_delta_e"))] for r in rows]
    if rows:
        mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
        body.append(["**mean**", pair(mean("psnr"), mean("delta_e")),
                     pair(mean("global_psnr"), mean("global_delta_e")),
                     pair(mean("denoised_psnr"), mean("denoised_delta_e"))])
    return markdown_table(["scene", "ours (gain field)", "one global grey-world gain",
                           "2D: one frame + non-local means"], body)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="all")
    ap.add_argument("--oracle", default="all", choices=["all", "heldout", "none"],
                    help="which scenes also train the oracle preset ('heldout': the held-out and "
                    "the tuning scenes; its run folders and kept results are read in any case)")
    args = ap.parse_args()
    rows = [row_for(s, args.oracle == "all" or (args.oracle == "heldout"
                                                 and s in HELDOUT + DEV)
                    or (Path("runs") / s / "oracle" / "eval" / "metrics.json").is_file()
                    or cached_result(s, "oracle", preset_config("oracle")) is not None)
            for s in scene_names(args.scenes, ("nine", "dev", "heldout"))]
    machine = f"{platform.machine()}, {os.cpu_count()} cores, python {sys.version.split()[0]}"
    text = ["# Reconstruction: trained from transforms.json without bounds\n",
            f"Command: `python -m experiments.recon --scenes {args.scenes} --oracle "
            f"{args.oracle}`; machine: "
            f"{machine}. Metrics on the test views (sRGB, 16-pixel border crop).\n",
            "## Built-in scenes\n", table([r for r in rows if r["group"] == "nine"]), "",
            "## Tuning scenes with an arc and a slide rig (defaults may be chosen on them)\n",
            table([r for r in rows if r["group"] == "dev"]), "",
            "## Held-out scenes (no default tuned on them)\n",
            table([r for r in rows if r["group"] == "heldout"]), ""]
    colour = ["## Colour: the gain field against one global grey-world gain (PSNR / "
              "CIEDE2000)\n", colour_table(rows), ""]
    write_report(Path("reports") / "recon", "\n".join(text + colour),
                 {"machine": machine, "rows": rows})
    if args.scenes == "all":
        update_doc("recon", "\n".join(text[2:]).replace("## ", "### ").rstrip("\n"),
                   RESULTS_DOC)
    print("\n".join(text + colour))


if __name__ == "__main__":
    main()
