"""Does a partial white balance beat the true white? Mostly where the black level is off.

Under one light the gain field scores 0.1-0.4 dB above one gain at its own L_ca target
(`python experiments/ablate.py --study gain_model`), although that target is nearer the
simulator's white than the field's. The field ends between its target and no correction,
and this study asks why that pays: each run's low-light colour is shown with gains
g^alpha (alpha = 1: full von Kries correction; 0.9, 0.8: shrunk towards no correction in
log space) for two whites, the run's own (its one gain, or for a field run the white its
gains balance on average, eval_run.field_neutral) and the true white of the view (the
simulator's, for scoring only), every row at the run's own mean luminance per view
(experiments/colour_ceiling.py's convention). Runs in pairs: the file's black level
(`gain_auto`) and the lens-cap one (`gain_auto_dark`): if the shrunk true white wins with
the file's black level and loses with the exact one, the partial correction pays by
hiding the cast of the unknown black offsets (a positive offset in a weak channel,
amplified by its gain), not by a better white.

    python experiments/offset_cast.py [--scenes nine,heldout,dev] [--runs runs]
        [--variants gain_auto,gain_auto_dark]

Writes reports/offset_cast.md and reports/offset_cast.json.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from colour_ceiling import gains, shown_at, test_views
from common import fmt, markdown_table, scene_names, study_parser, write_report
from gridnerf import color, colour_target, eval_run, evaluate

ALPHAS = (1.0, 0.9, 0.8)


def run_rows(run: Path, folder: Path) -> dict:
    """{"own": [psnr per alpha], "true": [...]}: test-view mean PSNR of the run's
    low-light colour times g^alpha for its own white and for the true white of each view."""
    cfg, _, train_out, shown, views = test_views(run, folder)
    own = colour_target.load_one_gain(run, cfg)
    if own is None:
        own = gains(eval_run.field_neutral(train_out))
    matrix = shown["gridnerf"].matrix
    scores = {"own": [[] for _ in ALPHAS], "true": [[] for _ in ALPHAS]}
    for _, out, gt_linear, truth in views:
        ours, _ = shown["gridnerf"].show(out)
        target = float(np.mean(color.luminance(ours)))
        low = np.asarray(out["rgb_low"], np.float64)
        whites = {"own": own, "true": gains(truth.reshape(-1, 3).mean(0))}
        for key, g in whites.items():
            for k, a in enumerate(ALPHAS):
                rgb = shown_at(low * np.exp(a * np.log(g)), matrix, target)
                scores[key][k].append(evaluate.image_metrics(rgb, gt_linear)["psnr"])
    return {key: [float(np.mean(v)) for v in per] for key, per in scores.items()}


def main() -> None:
    ap = study_parser(__doc__, "reports/offset_cast", "nine,heldout,dev", runs=True)
    ap.add_argument("--variants", default="gain_auto,gain_auto_dark",
                    help="two run folders per scene: the file's and the lens-cap black level")
    args = ap.parse_args()
    variants = args.variants.split(",")
    record, rows = {}, []
    for scene in scene_names(args.scenes):
        folder = Path("data/sim") / scene
        got = {}
        for v in variants:
            run = Path(args.runs) / scene / v
            if (run / "summary.json").exists():
                got[v] = run_rows(run, folder)
                print(scene, v, got[v], flush=True)
        if len(got) < len(variants):
            print(f"{scene}: skipped (missing {', '.join(set(variants) - set(got))})")
            continue
        record[scene] = got
        rows.append([scene] + [" / ".join(fmt(x) for x in got[v][w])
                               for v in variants for w in ("own", "true")])
    means = {v: {w: [float(np.mean([record[s][v][w][k] for s in record]))
                     for k in range(len(ALPHAS))] for w in ("own", "true")}
             for v in variants} if record else {}
    if record:
        rows.append([f"**mean** ({len(record)})"] + [
            " / ".join(fmt(x) for x in means[v][w]) for v in variants for w in ("own", "true")])
    head = ["scene"] + [f"{v}: {w} white" for v in variants for w in ("own", "true")]
    command = (f"python experiments/offset_cast.py --scenes {args.scenes} --variants "
               f"{args.variants}"
               + ("" if args.out == "reports/offset_cast" else f" --out {args.out}"))
    text = ("# A partial white balance against the black level\n\n"
            f"`{command}`. Test-view PSNR of each run's low-light colour times g^alpha, "
            f"alpha = {' / '.join(str(a) for a in ALPHAS)} (1: full von Kries correction), "
            "for the run's own white and the true white of the view, at the run's own mean "
            "luminance per view. The first of each pair of run folders has the file's black "
            "level, the second the lens-cap one.\n\n" + markdown_table(head, rows) + "\n")
    write_report(args.out, text, {"alphas": list(ALPHAS), "scenes": record, "means": means})
    print(text)


if __name__ == "__main__":
    main()
