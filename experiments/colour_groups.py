"""The default against one grey-world gain on the same field, per scene group.

Every scene of every group trained by the default preset (or its kept result,
experiments.common.run_variant), test views, PSNR (dB) / CIEDE2000: the default; one
grey-world gain for the capture on the same trained field (the reference a gain field must
not fall below); the per-frame pipeline (2x2 binning, grey world, colour matrix, exposure
matched to the reference); one frame denoised by non-local means. "margin" is default - one
gain; "colour" what the run shipped (the end-of-training check of gridnerf.shipped_colour:
the field, or one grey-world gain, and the gain distance of the field's white from the
nearest of the frames' estimates), from its run folder or the facts kept with its result
(common.run_facts), "kept result" where only the numbers are kept (reports/results.json);
"black level" the one the run's plan took (the lens-cap frames' or the file's: a run
trained before the lens-cap frames became the default says "file").

    python -m experiments.colour_groups [--scenes all] [--runs runs]

A run on some of the scenes (`--scenes heldcolour`, a name) refreshes their rows and keeps
the other scenes' rows as <out>.json last had them, so the report and docs/results.md stay
whole; a kept result without its facts takes those the report last gave the same numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from experiments.common import (
    GROUPS,
    RESULTS_DOC,
    markdown_table,
    run_variant,
    scene_dir,
    scene_names,
    study_parser,
    update_doc,
    write_report,
)

LABELS = {"nine": "nine built-in", "dev": "tuning", "heldout": "held out",
          "mixed": "mixed light", "heldmixed": "held-out mixed light",
          "heldcolour": "held-out colour", "cycles": "path-traced (Blender Cycles)",
          "heldquirk": "held-out quirky camera", "heldunit": "held-out sensor unit"}


def shipped(facts: dict | None) -> str:
    """What the run's summary says was shipped, or "kept result" without its facts."""
    if facts is None:
        return "kept result"
    record = facts.get("colour")
    if not record or "distance" not in record:
        return record["shipped"] if record else "trained before the check"
    return f"{record['shipped']} ({record['distance']:.2f})"


def black_level(facts: dict | None) -> str:
    """The black level the run's plan took ("lens cap", "file"), or "kept result"."""
    if facts is None:
        return "kept result"
    return facts.get("black_level", "file").replace("_", " ")


def kept_rows(out) -> dict:
    """{scene: row} of the report <out>.json last written ({} without one)."""
    path = Path(out).with_suffix(".json")
    return json.loads(path.read_text()).get("scenes", {}) if path.is_file() else {}


def main() -> None:
    ap = study_parser(__doc__, "reports/colour_groups", scenes="all", runs=True)
    args = ap.parse_args()
    groups = [g for g in GROUPS if g in LABELS]
    wanted = scene_names(args.scenes, tuple(groups))
    everything = set(wanted) >= {n for g in groups for n in GROUPS[g]}
    last = kept_rows(args.out)
    kept = {} if everything else last
    record, sections, summary_rows = {"scenes": {}}, [], []
    for g in groups:
        rows, vals = [], []
        for name in (n for n in GROUPS[g] if n in wanted or n in kept):
            if name in wanted:
                m = run_variant(scene_dir(name), "default", "default", [], Path(args.runs))
                s = m["summary"]
                row = {k: (s[k]["psnr"], s[k]["delta_e"]) for k in
                       ("gridnerf", "global_grey_world", "baseline_binned_matched",
                        "baseline_denoised")}
                facts = m.get("facts") or None  # none: a result kept before its facts
                row["colour"], row["black"] = shipped(facts), black_level(facts)
                same = last.get(name, {})
                if facts is None and np.allclose(same.get("gridnerf", (0, 0)), row["gridnerf"]):
                    # the same result, reported before with its run folder's facts
                    row["colour"], row["black"] = same["colour"], same["black"]
            else:
                row = {k: v for k, v in kept[name].items() if k != "group"}
            record["scenes"][name] = {"group": g, **row}
            vals.append(row)
            margin = row["gridnerf"][0] - row["global_grey_world"][0]
            rows.append([name, *(f"{row[k][0]:.2f} / {row[k][1]:.2f}" for k in
                                 ("gridnerf", "global_grey_world")),
                         f"{margin:+.2f}", f"{row['baseline_binned_matched'][0]:.2f}",
                         f"{row['baseline_denoised'][0]:.2f}", row["colour"], row["black"]])
            print(name, rows[-1], flush=True)
        if not vals:
            continue

        def mean(k, i, vals=vals):
            return float(np.mean([v[k][i] for v in vals]))

        margins = [v["gridnerf"][0] - v["global_grey_world"][0] for v in vals]
        over_frame = [v["gridnerf"][0] - v["baseline_binned_matched"][0] for v in vals]
        rows.append([f"**mean** ({len(vals)})",
                     f"{mean('gridnerf', 0):.2f} / {mean('gridnerf', 1):.2f}",
                     f"{mean('global_grey_world', 0):.2f} / {mean('global_grey_world', 1):.2f}",
                     f"{np.mean(margins):+.2f}", f"{mean('baseline_binned_matched', 0):.2f}",
                     f"{mean('baseline_denoised', 0):.2f}", "", ""])
        summary_rows.append([LABELS[g], str(len(vals)),
                             f"{mean('gridnerf', 0):.2f} / {mean('gridnerf', 1):.2f}",
                             f"{mean('global_grey_world', 0):.2f} / "
                             f"{mean('global_grey_world', 1):.2f}",
                             f"{min(margins):+.2f}", f"{min(over_frame):+.2f}",
                             f"{sum(v['black'] == 'lens cap' for v in vals)}"])
        sections.append(f"### {LABELS[g]}\n\n" + markdown_table(
            ["scene", "default", "one grey-world gain", "margin", "per-frame PSNR",
             "one frame + NLM PSNR", "colour shipped (gain distance)", "black level"], rows))
    table = markdown_table(["group", "scenes", "default", "one grey-world gain",
                            "worst margin", "worst default - per-frame",
                            "lens-cap black level"], summary_rows)
    command = f"`python -m experiments.colour_groups --scenes {args.scenes}`" + (
        "" if everything else " (the other scenes' rows as the report last had them)")
    md = ("# The default against one grey-world gain, per group\n\n"
          f"{command}: PSNR (dB) / CIEDE2000 of the test views.\n\n" + table + "\n\n"
          + "\n\n".join(sections) + "\n")
    write_report(args.out, md, record)
    update_doc("colour_groups", table + "\n\n" + "\n\n".join(sections), RESULTS_DOC)
    print(md)


if __name__ == "__main__":
    main()
