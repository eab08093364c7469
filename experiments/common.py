"""Shared helpers for experiment scripts: train-and-evaluate one variant, table formatting."""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

from gridnerf import atomic
from gridnerf import config as cfgmod
from gridnerf.eval_run import evaluate_run
from gridnerf.sim import (
    ALL_SCENES,
    DEV,
    HELDOUT,
    HELDOUT_COLOUR,
    HELDOUT_MIXED,
    HELDOUT_QUIRK,
    HELDOUT_UNIT,
    MIXED,
    SCENES,
    folder_name,
    simulate_scene,
)
from gridnerf.sim.cycles import CYCLES, simulate_cycles
from gridnerf.train import train

# The default as the studies measured it (cfgmod.FOOTING: no chroma prior, the grid priors
# on a quarter of the rows, 1200 last-stage steps), on top of a preset and before a
# variant's own overrides: their kept runs stay the runs their configs name.
FOOTING = list(cfgmod.FOOTING)
# ... and before the mosaic stage (data.mosaic_stages=0: the 2x2-binned raw in every
# stage). The studies that measure a factor against the default (the ablations, the
# darkness and photon sweeps, the camera-quirk runs) were measured on it and keep their
# runs there, in folders of their own ("binned", ...); the data-term study (ablate --study
# data_term) measures the mosaic stage against it, and the chroma study (ablate --study
# chroma) the prior.
FACTOR_BASE = ["data.mosaic_stages=0", *FOOTING]
# the detail rule (grid.detail_width, off by default) at the width it was measured with
DETAIL_ON = ("grid.detail_width=288",)

# Quick mode (`make report QUICK=1`): every study on 160x90, 12-frame versions of its
# scenes (data/quick/<scene>) with each preset shrunk by quick_sets, in its own run root
# (runs_quick/) and report folder: minutes instead of hours, to check that every figure
# comes out. Its numbers say nothing about the method.
QUICK_SIZE = {"width": 160, "height": 90, "n_frames": 12}


def scene_dir(scene: str, quick: bool = False, light: float = 1.0) -> Path:
    """A built-in, held-out, tuning or mixed-light scene name (simulated on first use; the small
    version under data/quick with `quick`; at `light` times its photon budget in its own
    folder, sim.folder_name) or a folder."""
    if scene in ALL_SCENES:
        root, size = (Path("data/quick"), QUICK_SIZE) if quick else (Path("data/sim"), {})
        return simulate_scene(scene, root / folder_name(scene, light), light=light, **size)
    if scene in CYCLES:  # path-traced by Blender (gridnerf.sim.cycles)
        return simulate_cycles(scene, Path("data/cycles") / scene)
    return Path(scene)


def quick_sets(cfg: cfgmod.Config) -> list[str]:
    """Overrides that shrink a preset for quick mode and keep its shape: every stage's
    resolution / 4 (at least 8; y stays from the aspect), steps / 20 (at least 10), 8
    patches a batch, up to 24 samples a ray, carving at 1 % (a few coarse steps leave fog,
    which the default threshold would cut into the content), no appended stage (the
    shrunk grid's vertices span many of the frames' pixels)."""
    res = [[max(8, r[0] // 4), 0 if r[1] == 0 else max(8, r[1] // 4), max(8, r[2] // 4)]
           for r in cfg.grid.resolutions]
    steps = [max(10, s // 20) for s in cfg.train.steps_per_stage]
    return [f"grid.resolutions={json.dumps(res).replace(' ', '')}",
            f"train.steps_per_stage={json.dumps(steps).replace(' ', '')}",
            "train.batch_patches=8", "render.max_samples=24", "grid.prune_threshold=0.01",
            "train.log_every=10", "grid.voxel_pixels=0"]


def preset_config(preset: str, quick: bool = False) -> cfgmod.Config:
    """What `preset` trains today (quick_sets on top in quick mode)."""
    want = cfgmod.preset(preset)
    return cfgmod.override(want, quick_sets(want)) if quick else want


def fingerprint(cfg: cfgmod.Config) -> str:
    """A short hash of the config a run trains (every field, cfgmod.to_dict, but those of
    cfgmod.ADDED_FIELDS at their old behaviour's value): two runs with the same fingerprint
    were trained alike. RESULTS stores it beside each run's numbers."""
    fields = cfgmod.to_dict(cfg)
    for (section, name), old in cfgmod.ADDED_FIELDS.items():
        if fields[section].get(name) == old:
            del fields[section][name]
    blob = json.dumps(fields, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def stale_run(run: Path, preset: str, quick: bool = False) -> bool:
    """Whether the run's saved config differs from what `preset` trains today
    (quick_sets on top in quick mode): an old default's run is not this default's row. A
    run without config.json is taken as it is."""
    path = Path(run) / "config.json"
    if not path.is_file():
        return False
    return cfgmod.load(path) != preset_config(preset, quick)


# the scene groups a study's --scenes may name
GROUPS = {"nine": SCENES, "heldout": HELDOUT, "dev": DEV, "mixed": MIXED,
          "heldmixed": HELDOUT_MIXED, "heldcolour": HELDOUT_COLOUR, "cycles": tuple(CYCLES),
          "heldquirk": HELDOUT_QUIRK, "heldunit": HELDOUT_UNIT}
# (label, scenes) of the groups a colour study reports its means over, each apart
REPORT_GROUPS = tuple((label, GROUPS[key]) for key, label in (
    ("nine", "nine"), ("dev", "tuning"), ("heldout", "held out"), ("mixed", "mixed light"),
    ("heldmixed", "held-out mixed light"), ("heldcolour", "held-out colour"),
    ("heldquirk", "held-out quirky camera"), ("cycles", "path-traced")))


def scene_names(spec: str, all_groups: tuple[str, ...] = ("nine", "heldout")) -> list[str]:
    """Scene names from a study's --scenes: comma-separated names and GROUPS, `all` being
    the groups of `all_groups` (by default the report's: nine + held out); in order, each
    once."""
    out: list[str] = []
    for item in (s for s in spec.split(",") if s):
        group = ([n for g in all_groups for n in GROUPS[g]] if item == "all"
                 else GROUPS.get(item, (item,)))
        out += [n for n in group if n not in out]
    return out


def study_parser(doc: str, out: str | None, scenes: str = "all", runs: bool = False,
                 quick: bool = False) -> argparse.ArgumentParser:
    """A study's command line with the options the studies share: --scenes (scene_names'
    spec; `all` as the study's docstring says), --out (the reports' path without its
    suffix) and, for a study that trains or reads run folders, --runs (their root) and
    --quick (small scenes, shrunk presets). doc: the study's docstring (its first line
    describes the command). The caller adds its own options."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--scenes", default=scenes, help="comma-separated scene names and groups ("
                    + ", ".join(GROUPS) + ", all)")
    ap.add_argument("--out", default=out, help="reports path without its suffix")
    if runs:
        ap.add_argument("--runs", default="runs", help="root of the run folders")
    if quick:
        ap.add_argument("--quick", action="store_true", help="small scenes, shrunk presets")
    return ap


def simulated_folders(spec: str):
    """(name, folder) of the simulated scenes named by `spec` (scene_names; 'all': every
    group) that exist under data/sim (data/cycles for the path-traced ones); says which are
    skipped."""
    for name in scene_names(spec, tuple(GROUPS)):
        folder = Path("data/cycles" if name in CYCLES else "data/sim") / name
        if not (folder / "sim.json").exists():
            print(f"skipping {name}: simulate it first (gridnerf simulate {name})")
            continue
        yield name, folder


# Run folders are not kept in git and a fresh machine has none, so each evaluated run's
# summary is also kept here (committed beside the reports), keyed by <scene>/<run> with the
# fingerprint of the config that trained it: a study that finds a run's numbers here under
# its config of today reuses them instead of training again. Keyed by config only: a change
# of the simulator, of the metrics or of what training does under the same config calls for
# deleting the entries it touches (or retraining them), else old runs are read as new.
RESULTS = Path("reports/results.json")
# where the studies' tables are shown (update_doc): the report's in the README, the
# reconstruction, ablation and consistency tables in docs/results.md, the benchmark's in
# docs/speed.md
README = Path("README.md")
RESULTS_DOC = Path("docs/results.md")
SPEED_DOC = Path("docs/speed.md")


def load_results(path: Path = RESULTS) -> dict:
    """The kept results ({"<scene>/<run>": {"fingerprint", "summary"}}), {} when none."""
    return json.loads(Path(path).read_text()) if Path(path).is_file() else {}


def cached_result(scene: str, name: str, cfg: cfgmod.Config,
                  results: dict | None = None) -> dict | None:
    """{"summary": ..., "facts": ...} of <scene>/<name> from `results` (default: RESULTS
    read now) when its fingerprint is cfg's; facts ({} for results kept before them):
    run_facts of the run folder it was evaluated in."""
    entry = (load_results() if results is None else results).get(f"{scene}/{name}")
    if entry and entry.get("fingerprint") == fingerprint(cfg):
        return {"summary": entry["summary"], "facts": entry.get("facts", {}), "cached": True}
    return None


# what the tables read from a run folder besides its scores: (file, keys)
RUN_FACTS = (("summary.json", ("resolution", "occupied_fraction", "train_seconds", "colour")),
             ("plan.json", ("black_level",)))


def run_facts(run: Path) -> dict:
    """The run folder's facts the tables show beside its scores (RUN_FACTS: the final grid,
    its occupancy, the training seconds, the colour it shipped, the black level its plan
    took; bounds.json whole under "bounds"), kept with its scores so that a machine without
    the folder shows them too. Files or keys the folder lacks are left out."""
    facts: dict = {}
    for name, keys in RUN_FACTS:
        path = Path(run) / name
        if path.is_file():
            record = json.loads(path.read_text())
            facts |= {k: record[k] for k in keys if k in record}
    if (Path(run) / "bounds.json").is_file():
        facts["bounds"] = json.loads((Path(run) / "bounds.json").read_text())
    return facts


def record_result(scene: str, name: str, cfg: cfgmod.Config, metrics: dict,
                  path: Path = RESULTS) -> None:
    """Keep an evaluated run's summary in `path` under its config's fingerprint, with its
    folder's facts where `metrics` carries them (run_variant's "facts"; the file is
    rewritten only when that changes it)."""
    results = load_results(path)
    entry = {"fingerprint": fingerprint(cfg), "summary": metrics["summary"]}
    if metrics.get("facts"):
        entry["facts"] = metrics["facts"]
    if results.get(f"{scene}/{name}") != entry:
        results[f"{scene}/{name}"] = entry
        atomic.write_text(path, json.dumps(results, indent=1, sort_keys=True) + "\n")


def run_variant(scene: str, name: str, preset: str, overrides: list[str],
                runs: Path = Path("runs"), quick: bool = False,
                need_run: bool = False, white_ref: str | None = None,
                keep: bool = True) -> dict:
    """Train (resuming if possible) and evaluate <runs>/<scene>/<name>; returns eval metrics.
    quick: the small scene and quick_sets on top of the preset and overrides. Without the
    run folder, a result of the same config in RESULTS is returned instead of training
    ({"summary", "cached": True}), unless the caller needs the run itself (`need_run`:
    its renders or files); every result evaluated here is kept there (not in quick mode).
    white_ref: train's --white-ref; its runs are not kept in RESULTS (keep=False: the
    fingerprint is the config's alone), the caller keeps their numbers. "facts" in the
    result: run_facts of the folder, or those kept with the result."""
    scene_name = Path(scene).name  # scene_dir's folder name, without simulating it yet
    run = Path(runs) / scene_name / name
    cfg = cfgmod.override(cfgmod.preset(preset), overrides)
    if quick:
        cfg = cfgmod.override(cfg, quick_sets(cfg))
    if (run / "config.json").exists() and cfgmod.load(run / "config.json") != cfg:
        raise SystemExit(f"{run} holds a different config; delete it to re-run this variant")
    if not (run / "summary.json").exists():
        hit = None if quick or need_run or not keep else cached_result(scene_name, name, cfg)
        if hit:
            return hit
        train(scene_dir(scene, quick), run, cfg, white_ref=white_ref)
    metrics_path = run / "eval" / "metrics.json"
    metrics = (json.loads(metrics_path.read_text()) if metrics_path.exists()
               else evaluate_run(run))
    metrics["facts"] = run_facts(run)
    if keep and not quick:
        record_result(scene_name, name, cfg, metrics)
    return metrics


def write_report(out, markdown: str, record) -> None:
    """<out>.md (the table) and <out>.json (the numbers behind it), written atomically."""
    out = Path(out)
    atomic.write_text(out.with_suffix(".md"), markdown)
    atomic.write_text(out.with_suffix(".json"), json.dumps(record, indent=2) + "\n")


def update_doc(name: str, text: str, path: Path) -> None:
    """Replace the section of the markdown file `path` between `<!-- NAME:begin ... -->` and
    `<!-- NAME:end -->` by `text` (the tables a study writes; the file is kept as it is when
    it or the markers are absent)."""
    path = Path(path)
    if not path.is_file():
        return
    doc = path.read_text()
    begin, end = f"<!-- {name}:begin", f"<!-- {name}:end -->"
    if begin not in doc or end not in doc:
        return
    head, rest = doc.split(begin, 1)
    marker, rest = rest.split("-->", 1)
    atomic.write_text(path, f"{head}{begin}{marker}-->\n{text}\n{end}{rest.split(end, 1)[1]}")


def update_readme(text: str, path: Path = README) -> None:
    """The report's table in README.md (update_doc's `report` section)."""
    update_doc("report", text, path)


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int = 90) -> None:
    """Write a matplotlib figure as a PNG atomically (its folder made) and close it."""
    atomic.write(Path(path), lambda tmp: fig.savefig(tmp, format="png", dpi=dpi))
    pyplot().close(fig)


def fmt(x, nd=2) -> str:
    return "n/a" if x is None or isinstance(x, str) else f"{x:.{nd}f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)
