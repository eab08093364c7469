"""What the hidden black offsets cost a trained field: the true offsets taken off its colour.

For each run runs/<scene>/RUN of a simulated single-light scene: the simulator's per-CFA
black offsets (sim.json, noisefit.sim_truth) are binned like the training data (R, mean of
the greens, B), divided by the mean exposure of the training frames (the field learned
mu + b / exposure), and taken off the render: the low-light colour loses b x opacity, the
restored colour b x the composited gain. The test views are scored as `gridnerf eval`
scores them (eval_run.outputs, exposure re-derived from the corrected training render)
with and without the correction: an upper bound on what fitting the offsets can buy.

    python experiments/offset_effect.py [--scenes bucket,box,rabbit] [--run default]

Writes reports/offset_effect.md and reports/offset_effect.json.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from common import markdown_table, study_parser, write_report
from gridnerf import eval_run, evaluate, noisefit, raw


def corrected(out: dict, off_rgb: np.ndarray) -> dict:
    """The render with offsets off_rgb (3,) taken off the field's colour."""
    out = dict(out)
    out["rgb_restored"] = np.asarray(out["rgb_restored"]) - off_rgb * np.asarray(out["gain"])
    out["rgb_low"] = np.asarray(out["rgb_low"]) - off_rgb * np.asarray(out["acc"])[..., None]
    return out


def offset_rgb(scene) -> np.ndarray:
    """(3,) the simulator's per-CFA black offsets as the field learned them: binned like the
    training data (R, mean of the greens, B), normalised, divided by the training frames'
    mean exposure."""
    truth = noisefit.sim_truth(scene.path)
    b = np.asarray(truth["black_offset_dn"]) / truth["scale"]
    inv_e = float(np.mean(1.0 / scene.exposure[scene.train_idx]))
    return raw.bin2x2(b, scene.cfa, np.float64)[0, 0] * inv_e


def score(run: Path, fix) -> dict:
    cfg, scene, structure, params, _ = eval_run.load_run(run)
    main = eval_run.run_outputs(run, structure, params, scene, cfg,
                                fix(eval_run.training_render(structure, params, scene, cfg)))
    main = main["gridnerf"]
    cams, views = scene.cameras, []
    for i in scene.test_idx:
        intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]])
        out = fix(eval_run.render_view(structure, params, scene, cfg, cams.c2w[i], intr,
                                       cams.height, cams.width))
        gt = eval_run.reference_linear(scene, scene.names[i], cams.height, cams.width)
        views.append(evaluate.image_metrics(main.show(out)[0], gt))
    return {k: float(np.mean([v[k] for v in views])) for k in ("psnr", "ssim", "delta_e")}


def main() -> None:
    ap = study_parser(__doc__, "reports/offset_effect", scenes="bucket,box,rabbit")
    ap.add_argument("--run", default="default")
    args = ap.parse_args()
    rows, record = [], {}
    for name in args.scenes.split(","):
        run = Path("runs") / name / args.run
        _, scene, *_ = eval_run.load_run(run)
        truth = noisefit.sim_truth(scene.path)
        b = np.asarray(truth["black_offset_dn"]) / truth["scale"]
        off_rgb = offset_rgb(scene)
        rec = {"offsets_dn": b.ravel().tolist(), "as_is": score(run, lambda o: o),
               "offsets_off": score(run, lambda o, off=off_rgb: corrected(o, off))}
        record[name] = rec
        rows.append([name, " ".join(f"{v * truth['scale']:+.2f}" for v in b.ravel()),
                     *(f"{rec[k]['psnr']:.2f} / {rec[k]['delta_e']:.2f}"
                       for k in ("as_is", "offsets_off"))])
        print(" | ".join(rows[-1]), flush=True)
    table = markdown_table(["scene", "true offsets DN (CFA order)", "as trained: PSNR / "
                            "CIEDE2000", "true offsets taken off"], rows)
    write_report(args.out, "Black offsets: a trained field with the true offsets taken off "
                 f"its colour, `python experiments/offset_effect.py --scenes {args.scenes} "
                 f"--run {args.run}`.\n\n" + table + "\n", record)
    print(table)


if __name__ == "__main__":
    main()
