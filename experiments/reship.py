"""Re-apply today's end-of-training colour check to finished runs, then evaluate them.

The check (gridnerf.shipped_colour) decides what a finished field is shown with; it never
changes the field. A run trained before the check changed therefore ships what training it
again would ship once its plan's decision is made anew: this resets the plan's shipped
colour, runs the check on the run's training render, rewrites plan.json and summary.json's
"colour", evaluates the run and keeps its numbers in reports/results.json (under the run's
config fingerprint, as experiments.common.run_variant does).

    python -m experiments.reship --scenes cycles,heldcolour [--name default]
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from experiments import common
from gridnerf import atomic, eval_run, outputs, shipped_colour
from gridnerf import config as cfgmod
from gridnerf import plan as planmod


def reship(run: Path) -> dict:
    """The run's colour record after the check (its plan and summary rewritten)."""
    cfg, plan, scene, structure, params, summary = eval_run.load_run(run)
    if plan.colour.model != "field" or not plan.colour.evidence:
        return summary.get("colour", {"shipped": plan.colour.model})
    before = replace(plan.colour, shipped_gains=None, shipped_why=None)
    colour, record = shipped_colour.check(
        outputs.training_render(structure, params, scene, cfg), before)
    planmod.save(run, replace(plan, colour=colour))
    atomic.write_text(run / "summary.json", json.dumps({**summary, "colour": record}, indent=2))
    return record


def main() -> None:
    parser = common.study_parser(__doc__, None)
    parser.add_argument("--name", default="default", help="the run under runs/<scene>/")
    args = parser.parse_args()
    for scene in common.scene_names(args.scenes):
        run = Path("runs") / scene / args.name
        if not (run / "checkpoint.npz").exists():
            print(f"{scene}: no finished run at {run}; skipped")
            continue
        record = reship(run)
        metrics = eval_run.evaluate_run(run)
        common.record_result(scene, args.name, cfgmod.load(run / "config.json"), metrics)
        m = metrics["summary"]
        print(f"{scene}: shipped {record['shipped']}; PSNR / CIEDE2000 "
              f"{m['gridnerf']['psnr']:.2f} / {m['gridnerf']['delta_e']:.2f}, one grey-world "
              f"gain {m['global_grey_world']['psnr']:.2f} / "
              f"{m['global_grey_world']['delta_e']:.2f}", flush=True)


if __name__ == "__main__":
    main()
