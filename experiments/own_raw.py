"""Does the test views' own raw frame rank two fields of one capture as their references do?

`gridnerf eval` scores every test view's render against the view's own dark raw frame
(eval/metrics.json → own_raw: the data term, photosite by photosite; gridnerf.eval_run.
own_raw_term). The frame is part of the capture, left out of training, so the score needs
no reference, and its noise is the same for every field of the capture: of two fields the
one with the lower score should explain the unseen views better. If it ranks pairs of
fields as the clean references do, a run can choose between fields (a finer last stage, a
solved colour, a prior's weight) from its own frames.

For each scene and each pair "A:B" of run folders under runs/<scene>/ (both evaluated by
a gridnerf that writes own_raw), the change from A to B of the references' PSNR / SSIM /
CIEDE2000 and of the own-raw score, and whether the two agree (PSNR up where the score
goes down). Reads finished, evaluated runs only; no training.

    python -m experiments.own_raw --scenes bucket,held_arc_table --pairs default:cs20,default:w288
"""

from __future__ import annotations

import json
from pathlib import Path

from experiments import common


def scores(run: Path) -> dict | None:
    """{"psnr", "ssim", "delta_e", "own_raw"} of an evaluated run, or None."""
    path = run / "eval" / "metrics.json"
    if not path.is_file():
        return None
    m = json.loads(path.read_text())
    own = (m.get("own_raw") or {}).get("mean")
    main = m.get("summary", {}).get("gridnerf")
    if own is None or main is None:
        return None
    return {"psnr": main["psnr"], "ssim": main["ssim"], "delta_e": main["delta_e"],
            "own_raw": own}


def compare(sa: dict, sb: dict) -> dict:
    """The change from scores sa to sb (scores' keys), the own-raw score's relative change
    ("own_raw_rel") and whether the score agrees with the references' PSNR ("agree": PSNR
    up where the score goes down, or both the other way)."""
    d = {k: sb[k] - sa[k] for k in sa}
    d["own_raw_rel"] = d["own_raw"] / sa["own_raw"]
    d["agree"] = (d["psnr"] > 0) == (d["own_raw"] < 0)
    return d


def main() -> None:
    ap = common.study_parser(__doc__, "reports/own_raw", runs=True)
    ap.add_argument("--pairs", default="default:cs20,default:w288",
                    help="A:B run folders under runs/<scene>/, comma-separated")
    args = ap.parse_args()
    pairs = [tuple(p.split(":", 1)) for p in args.pairs.split(",")]
    if any(len(p) != 2 for p in pairs):
        raise SystemExit(f"--pairs: give A:B run folder pairs, got {args.pairs!r}")
    rows, record = [], {}
    for scene in common.scene_names(args.scenes):
        for a, b in pairs:
            sa, sb = (scores(Path(args.runs) / scene / v) for v in (a, b))
            if sa is None or sb is None:
                continue
            d = compare(sa, sb)
            rel, agree = d["own_raw_rel"], d["agree"]
            record.setdefault(scene, {})[f"{a}:{b}"] = {"a": sa, "b": sb, "agree": agree}
            rows.append([scene, f"{a} -> {b}", f"{d['psnr']:+.2f}", f"{d['ssim']:+.3f}",
                         f"{d['delta_e']:+.2f}", f"{sa['own_raw']:.4f} -> {sb['own_raw']:.4f}",
                         f"{100 * rel:+.1f} %", "yes" if agree else "no"])
            print(" | ".join(rows[-1]), flush=True)
    n_agree = sum(r[-1] == "yes" for r in rows)
    table = common.markdown_table(
        ["scene", "fields", "PSNR", "SSIM", "CIEDE2000", "own-raw score", "own-raw change",
         "agree"], rows)
    summary = (f"`python -m experiments.own_raw --scenes {args.scenes} --pairs {args.pairs}`: "
               "the change from the first field to the second (module docstring). The score "
               f"and the references agree on {n_agree} of {len(rows)} pairs.\n\n" + table)
    common.write_report(args.out, "# The test views' own raw frames as a score\n\n"
                        + summary + "\n", record)
    if Path(args.out) == Path("reports/own_raw"):
        common.update_doc("own_raw", summary, common.RESULTS_DOC)


if __name__ == "__main__":
    main()
