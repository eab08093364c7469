"""What the finished grid misses that the views agree on: the multi-view detail reading.

For each scene's finished run (`<runs>/<scene>/<run>`, trained by `gridnerf train`),
`gridnerf.residual.read_views` carries each fourth training frame's residual (frame -
render, on the binned lattice) to the next training frame along the points the grid
renders, and reads the residual the two share over what they do not, times the views: the
missed detail that a grid of the same geometry could still fit, in units of the noise an
ideal average of the views leaves. --gaps reads it again with each frame paired with the
one that many later (views further apart: what changes with the view is shared less).
Beside it, where reports/results.json keeps both, the test-view PSNR of the run and of the
same scene trained with the detail rule
(`<scene>/detail288`: a 288-wide last stage where the rule refines; n/a where the rule
left the scene at the run's width) and their difference.
Nothing is trained: a scene without its run folder is skipped, and said so.

    python -m experiments.detail_views --scenes bucket,deer,... [--run default] [--gaps 1,2,3]

Writes reports/detail_views.md and .json.
"""

from __future__ import annotations

import time
from pathlib import Path

from experiments import common
from gridnerf import dataset, methods, residual
from gridnerf.eval_run import load_run

DEFAULT_OUT = "reports/detail_views"


def reading(run: Path, gaps=(1,)) -> dict:
    """{"reading", "error", "seconds", "width"} of a finished run folder (read_views on
    its training data as it trained its last stage; consecutive frames), and
    "by_gap": {gap: (reading, error)} for every gap in `gaps`."""
    cfg, _, scene, structure, params, _ = load_run(run)
    data = methods.get(cfg.loss.method).training_data(scene, cfg)
    near_t, far_t = dataset.grid_box(scene)[2:]
    t0 = time.perf_counter()
    by_gap = residual.read_views_at(structure, params, data, near_t, far_t, cfg.render,
                                    gaps=sorted(set(gaps) | {1}))
    value, error = by_gap[1]
    return {"reading": value, "error": error, "seconds": time.perf_counter() - t0,
            "width": int(structure.resolution[0]),
            "by_gap": {str(g): list(v) for g, v in by_gap.items()}}


def psnr(results: dict, key: str, finer_than: int = 0) -> float | None:
    """The kept test-view PSNR of `key`; None where it is not kept or its last stage is no
    wider than finer_than (the detail rule left it as it was)."""
    entry = results.get(key)
    if not entry or entry.get("facts", {}).get("resolution", [finer_than + 1])[0] <= finer_than:
        return None
    return entry["summary"]["gridnerf"]["psnr"]


def main() -> None:
    ap = common.study_parser(__doc__, DEFAULT_OUT, scenes="nine", runs=True)
    ap.add_argument("--run", default="default", help="the run folder's name under each scene")
    ap.add_argument("--gaps", default="1",
                    help="comma-separated frame gaps to read at (1: consecutive frames)")
    args = ap.parse_args()
    parts = [g.strip() for g in args.gaps.split(",") if g.strip()]
    if not all(g.isdigit() and int(g) >= 1 for g in parts):
        ap.error(f"--gaps {args.gaps}: give whole numbers >= 1, e.g. 1,2,3")
    gaps = sorted({int(g) for g in parts} | {1})
    results = common.load_results()
    record, rows = {}, []
    for name in common.scene_names(args.scenes):
        run = Path(args.runs) / name / args.run
        if not (run / "summary.json").is_file():
            print(f"skipping {name}: no finished run in {run}")
            continue
        r = reading(run, gaps)
        base = psnr(results, f"{name}/default")
        refined = psnr(results, f"{name}/detail288", finer_than=r["width"])
        r |= {"psnr": base, "psnr_detail288": refined,
              "gain": None if base is None or refined is None else refined - base}
        record[name] = r
        print(f"{name}: {r['reading']:.2f} +- {r['error']:.2f} ({r['seconds']:.0f} s)",
              flush=True)
        rows.append([name, str(r["width"]),
                     *(f"{r['by_gap'][str(g)][0]:.2f} +- {r['by_gap'][str(g)][1]:.2f}"
                       for g in gaps),
                     common.fmt(base), common.fmt(refined),
                     "n/a" if r["gain"] is None else f"{r['gain']:+.2f}"])
    table = common.markdown_table(
        ["scene", "last stage (vertices across)",
         *(f"views agree on, x averaged noise ({g} apart)" if g > 1 else
           "views agree on, x averaged noise" for g in gaps),
         "PSNR", "detail rule", "change"], rows)
    common.write_report(args.out, f"# Multi-view detail reading\n\n`python -m "
                        f"experiments.detail_views --scenes {args.scenes} --run "
                        f"{args.run} --gaps {','.join(map(str, gaps))}`\n\n{table}\n",
                        record)


if __name__ == "__main__":
    main()
