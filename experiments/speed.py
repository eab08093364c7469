"""Speed against error: test PSNR against training wall time for presets fast -> fine.

For each scene and preset in PRESETS, one `gridnerf train` process checkpoints every
`--every` steps and each checkpoint is scored on the test views as `gridnerf eval` scores a
run: the benchmark's own machinery (experiments.bench: Bench.train with snapshots, the
"psnr" worker), so a point's time is the checkpoint file's time since the process started
(imports, bounds, compiles and carving included). The curves run alone on the machine only
when nothing else uses the CPU: the load average is kept with every item. Cached per item
in <runs>/speed/<preset>/cache. Writes <out>.md (time-to-quality table), <out>.json and
<out>.png (one curve per preset, one panel per scene).

    python -m experiments.speed [--scenes bucket] [--presets fast,default,fine] [--quick]

A preset may carry overrides after "+": `--presets default,default+loss.tv_fraction=0.1`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from experiments import bench
from experiments.common import (
    fmt,
    markdown_table,
    pyplot,
    quick_sets,
    save_figure,
    scene_dir,
    scene_names,
    study_parser,
    write_report,
)
from gridnerf import config as cfgmod

PRESETS = ("fast", "default", "fine")


def curve(scene: str, preset: str, runs: Path, every: int, quick: bool) -> dict:
    """{"points": [{"wall_s", "step", "stage", "psnr"}], "train": the training item}.

    preset: a preset's name, optionally with overrides after "+", e.g.
    "default+loss.tv_fraction=0.1" (each its own curve and cache folder)."""
    folder = scene_dir(scene, quick)
    name, *extra = preset.split("+")
    sets = (quick_sets(cfgmod.preset(name)) if quick else []) + extra
    meta = json.loads((folder / "sim.json").read_text()) if (folder / "sim.json").is_file() \
        else {"width": 0, "height": 0}
    cfg = {**bench.FULL, "preset": name, "sets": sets, "snapshot_every": every, "jobs": 1}
    b = bench.Bench(Path(runs).resolve() / "speed" / preset, cfg, fresh=False, quick=False,
                    scene=folder.name, folder=folder.resolve())
    run = b.train("small", (meta["width"], meta["height"]), snapshots=True, need_run=True)
    spec = {"run": run["run"], "run_id": run["id"],
            "snapshots": [s["dir"] for s in run["snapshots"]]}
    psnr = b.item("psnr_curve", spec, lambda: bench.run_worker("psnr", spec,
                                                               b.log("psnr_curve")))
    points = [{"wall_s": snap["wall_s"], "step": s["step"], "stage": s["stage"],
               "psnr": s["psnr"]} for s, snap in zip(psnr["scores"], run["snapshots"],
                                                     strict=True)]
    return {"points": points, "train_wall_s": run["wall_s"], "train_seconds":
            run["train_seconds"], "final_resolution": run["final_resolution"],
            "occupied_fraction": run["occupied_fraction"],
            "load_average": run["machine"].get("load_average")}


def time_to(points: list[dict], psnr: float) -> float | None:
    """Wall seconds of the first checkpoint at or above `psnr` (None: never)."""
    return next((p["wall_s"] for p in points if p["psnr"] >= psnr), None)


def markdown(record: dict) -> str:
    rows = []
    for scene, per_preset in record.items():
        best = max(c["points"][-1]["psnr"] for c in per_preset.values())
        for preset, c in per_preset.items():
            final = c["points"][-1]
            rows.append([scene, preset, "x".join(map(str, c["final_resolution"])),
                         fmt(final["psnr"]), fmt(c["train_wall_s"], 0),
                         fmt(time_to(c["points"], final["psnr"] - 0.5), 0),
                         fmt(time_to(c["points"], best - 1.0), 0),
                         fmt(100 * c["occupied_fraction"], 1)])
    return ("# Speed against error\n\nTest PSNR of checkpoints against the training "
            "process's wall time (2 cores). Time-to-quality: seconds to the first checkpoint "
            "within 0.5 dB of the preset's own final PSNR, and within 1 dB of the best "
            "preset's final PSNR on the scene ('n/a': never).\n\n"
            + markdown_table(["scene", "preset", "final grid", "final PSNR", "wall s",
                              "s to final - 0.5 dB", "s to best - 1 dB", "occupied %"], rows)
            + "\n")


def plot(record: dict, path: Path) -> None:
    """One panel per scene, one curve per preset; the presets share their first stages, so
    each curve has its own line style and the earlier ones are drawn wider, on top."""
    plt = pyplot()
    n = len(record)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.2), squeeze=False)
    for ax, (scene, per_preset) in zip(axes[0], record.items(), strict=True):
        styles = ("-", "--", ":", "-.")
        for k, (preset, c) in enumerate(per_preset.items()):
            ax.plot([p["wall_s"] for p in c["points"]], [p["psnr"] for p in c["points"]],
                    marker="o.x+"[k % 4], markersize=6 - k, linestyle=styles[k % 4],
                    linewidth=3.0 - 0.8 * k if k < 3 else 0.8, zorder=10 - k, label=preset)
        ax.set_title(scene)
        ax.set_xlabel("training wall time (s)")
        ax.set_ylabel("test PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def main() -> None:
    ap = study_parser(__doc__, "reports/speed", scenes="bucket", runs=True, quick=True)
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--every", type=int, default=200, help="steps between scored checkpoints")
    args = ap.parse_args()
    print(build(scene_names(args.scenes),
                [p for p in args.presets.split(",") if p], args.every, Path(args.runs),
                args.out, args.quick))


def build(scenes: list[str], presets: list[str], every: int, runs: Path, out,
          quick: bool) -> str:
    """Train and score what is missing, write <out>.md, .json and .png; returns the
    markdown. quick: checkpoints every every / 20 steps (at least 5)."""
    every = max(5, every // 20) if quick else every
    if quick:  # inherited by the training processes: compile fast, time nothing
        os.environ["XLA_FLAGS"] = (f"{os.environ.get('XLA_FLAGS', '')} "
                                   f"{bench.QUICK_XLA_FLAGS}").strip()
    record = {scene: {p: curve(scene, p, runs, every, quick) for p in presets}
              for scene in scenes}
    text = markdown(record)
    write_report(out, text, {"quick": quick, "every": every, "results": record})
    plot(record, Path(out).with_suffix(".png"))
    return text


if __name__ == "__main__":
    main()
