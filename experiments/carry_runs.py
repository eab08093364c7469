"""Carry kept runs over a change of the L_ca estimator (`loss.ca_illuminant`) without
training them again where the change cannot touch them.

The estimator reaches training only through the L_ca inputs (colour_target.colour_inputs: the
capture's or each region's illuminant, and the per-frame illuminant maps). For every run
folder under --runs whose config reads the estimator with the value --from, this computes
those inputs on the run's own frames (its bounds and black level) under --from and under
--to and compares them bit for bit. Training is deterministic on CPU (session 22: bouquet
trained again gave checkpoint arrays and metrics identical to its kept run's), so a run
whose inputs are identical is the run --to would train. With --apply, such a run's
config.json says --to and its entry in reports/results.json takes the new config's
fingerprint; a run whose inputs differ is moved to runs_old/<scene>/<run>, so that every
study that reports it trains it again (nothing is deleted). Used when the default became
`consistent` (docs/colour.md, session 22).

    python experiments/carry_runs.py --from consensus --to consistent [--apply]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
from pathlib import Path

import numpy as np

from common import RESULTS, fingerprint, load_results
from gridnerf import atomic, dataset, runfolder
from gridnerf import config as cfgmod
from gridnerf.colour_target import colour_inputs, estimates_from_frames
from gridnerf.errors import ConfigError


def same_inputs(run: Path, scene_dir: Path, cfg: cfgmod.Config, other: str) -> bool:
    """Whether the run's L_ca inputs under `other` are bit-identical to its own."""
    scene = runfolder.open_scene(scene_dir, run, dark=runfolder.lens_cap_black(cfg, run))
    data = dataset.training_data(scene, cfg.data)
    with contextlib.redirect_stdout(io.StringIO()):  # the estimators' choice lines
        d1, k1 = colour_inputs(data, scene, cfg)
        d2, k2 = colour_inputs(data, scene, cfgmod.override(cfg, [f"loss.ca_illuminant={other}"]))
    m1, m2 = d1.illuminant_map, d2.illuminant_map
    maps = (m1 is None) == (m2 is None) and (m1 is None or np.array_equal(m1, m2))
    return maps and np.array_equal(k1["scene_ill"], k2["scene_ill"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from", dest="old", required=True,
                    help="the estimator the runs were trained with")
    ap.add_argument("--to", dest="new", required=True, help="the estimator to carry them to")
    ap.add_argument("--runs", default="runs")
    ap.add_argument("--scenes-root", default="data/sim", help="where <scene> folders are")
    ap.add_argument("--apply", action="store_true", help="relabel / move aside (else: report)")
    args = ap.parse_args()
    results = load_results()
    counts = {"same": 0, "differ": 0}
    for path in sorted(Path(args.runs).glob("*/*/config.json")):
        run = path.parent
        try:
            cfg = cfgmod.load(path)
        except ConfigError:  # a removed option's run: not today's config in either case
            continue
        if not estimates_from_frames(cfg) or cfg.loss.ca_illuminant != args.old:
            continue
        scene = run.parent.name
        same = same_inputs(run, Path(args.scenes_root) / scene, cfg, args.new)
        counts["same" if same else "differ"] += 1
        print(f"{run}: {'identical' if same else 'different'} L_ca inputs", flush=True)
        if not args.apply:
            continue
        if same:
            new = cfgmod.override(cfg, [f"loss.ca_illuminant={args.new}"])
            entry = results.get(f"{scene}/{run.name}")
            if entry and entry["fingerprint"] == fingerprint(cfg):
                entry["fingerprint"] = fingerprint(new)
            cfgmod.save(new, path)
        else:
            dest = Path("runs_old") / scene / run.name
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(run), str(dest))
    if args.apply:
        atomic.write_text(RESULTS, json.dumps(results, indent=1, sort_keys=True) + "\n")
    print(f"{counts['same']} runs identical, {counts['differ']} different")


if __name__ == "__main__":
    main()
