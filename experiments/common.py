"""Shared helpers for experiment scripts: train-and-evaluate one variant, table formatting."""

from __future__ import annotations

import json
from pathlib import Path

from gridnerf import atomic
from gridnerf import config as cfgmod
from gridnerf.eval_run import evaluate_run
from gridnerf.sim import HELDOUT, MIXED, SCENES, simulate_scene
from gridnerf.train import train


def scene_dir(scene: str) -> Path:
    """A built-in, held-out or mixed-light scene name (simulated on first use) or a folder."""
    if scene in SCENES or scene in HELDOUT or scene in MIXED:
        return simulate_scene(scene, Path("data/sim") / scene)
    return Path(scene)


def simulated_folders(spec: str):
    """(name, folder) of the simulated scenes named by `spec` ('all': nine + held-out +
    mixed, or comma-separated names) that exist under data/sim; says which are skipped."""
    names = SCENES + HELDOUT + MIXED if spec == "all" else tuple(spec.split(","))
    for name in names:
        folder = Path("data/sim") / name
        if not (folder / "sim.json").exists():
            print(f"skipping {name}: simulate it first (gridnerf simulate {name})")
            continue
        yield name, folder


def run_variant(scene: str, name: str, preset: str, overrides: list[str]) -> dict:
    """Train (resuming if possible) and evaluate runs/<scene>/<name>; returns eval metrics."""
    sdir = scene_dir(scene)
    run = Path("runs") / sdir.name / name
    cfg = cfgmod.override(cfgmod.preset(preset), overrides)
    if (run / "config.json").exists() and (cfgmod.effective(cfgmod.load(run / "config.json"))
                                           != cfgmod.effective(cfg)):
        raise SystemExit(f"{run} holds a different config; delete it to re-run this variant")
    if not (run / "summary.json").exists():
        train(sdir, run, cfg)
    metrics_path = run / "eval" / "metrics.json"
    if metrics_path.exists():
        return json.loads(metrics_path.read_text())
    return evaluate_run(run)


def write_report(out, markdown: str, record) -> None:
    """<out>.md (the table) and <out>.json (the numbers behind it), written atomically."""
    out = Path(out)
    atomic.write_text(out.with_suffix(".md"), markdown)
    atomic.write_text(out.with_suffix(".json"), json.dumps(record, indent=2) + "\n")


def update_readme(name: str, text: str, path: Path = Path("README.md")) -> None:
    """Replace the README section between `<!-- NAME:begin ... -->` and `<!-- NAME:end -->`
    (the tables an experiment writes; kept as it is when the markers are absent)."""
    if not path.is_file():
        return
    readme = path.read_text()
    begin, end = f"<!-- {name}:begin", f"<!-- {name}:end -->"
    if begin not in readme or end not in readme:
        return
    head, rest = readme.split(begin, 1)
    marker, rest = rest.split("-->", 1)
    atomic.write_text(path, f"{head}{begin}{marker}-->\n{text}\n{end}{rest.split(end, 1)[1]}")


def fmt(x, nd=2) -> str:
    return "n/a" if x is None or isinstance(x, str) else f"{x:.{nd}f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)
