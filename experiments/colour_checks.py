"""The colour path's self-checks on every simulated scene, from the frames alone (no training).

For each scene (its training frames, 2x2-binned, as the default's training sees them: with
the lens-cap black level where the scene's lens-cap frames show the file's off): the file's
matrix against its camera's reference (colour_target.matrix_check), the frames' own estimate's
angle to the file's Planckian locus and its nearest temperature (colour_target.locus_check),
how far the three estimators disagree (colour_target.estimators_disagree), the decisions
(locus kept or given up, the estimator "consistent" takes), and the angular error against
the simulator's true light (sim.json's illuminant_neutral_cam) of the capture estimate the
default takes with the checks and of the one it took without them (the pick on the locus,
whatever the checks say), and of grey world unprojected, as angles and as
illuminant.gain_distance. Mixed-light scenes' truth is the lights' mix, so their errors say
less. Where a default run is trained (runs/<scene>/default), what the end-of-training check
(gridnerf.shipped_colour) says of it: its summary's record, or the check made on its
checkpoint for a run trained before the check existed.

    python -m experiments.colour_checks --scenes all [--out reports/colour_checks]
"""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from experiments.common import (
    GROUPS,
    fmt,
    markdown_table,
    simulated_folders,
    study_parser,
    write_report,
)
from gridnerf import colour_target, darkframes, data_term, dataset, illuminant
from gridnerf import config as cfgmod
from gridnerf.scene import load_scene


def scene_row(folder) -> dict:
    """The checks, decisions and errors of one simulated scene folder."""
    sim = json.loads((folder / "sim.json").read_text())
    truth = np.asarray(sim["illuminant_neutral_cam"], np.float64)
    scene = load_scene(folder, near_far=tuple(sim["near_far"]))
    if darkframes.has_dark_frames(folder):  # data_term.black_level's check
        offset = darkframes.measure(folder)["offset_dn"]
        if data_term.offsets_matter(offset, scene)[0]:
            scene = darkframes.apply(scene, offset)
    data = dataset.build(scene, scene.train_idx, True)
    frames = colour_target.estimate_frames(data, scene)
    d = colour_target.estimate_downscale(frames, colour_target.NOISE_RATIO)
    _, angle, kelvin, gap, free = colour_target.locus_check(scene, frames, d)
    locus = illuminant.planckian_locus(scene.xyz_to_cam)
    with contextlib.redirect_stdout(io.StringIO()) as said:
        matrix, given_up, disagreement, _ = colour_target.trusted_locus(
            scene, cfgmod.Config(), frames, d)
        used = None if matrix is None else illuminant.planckian_locus(matrix)
        picked = colour_target.consistent_estimator(frames, d, None, used, disagreement,
                                                    given_up)
        before = colour_target.consistent_estimator(frames, d, None, locus, 0.0)

    def error(name, loc) -> tuple[float, float]:
        est = colour_target.scene_illuminant(frames, name, d, loc)
        return (float(illuminant.angular_error_deg(est, truth)),
                illuminant.gain_distance(est, truth))

    (err, err_gain), (err0, err0_gain), (err_gw, err_gw_gain) = (
        error(picked, used), error(before, locus), error("grey_world", None))
    return {"matrix_ok": colour_target.matrix_check(scene) is None, "locus_deg": angle,
            "locus_kelvin": kelvin, "grey_gap": gap, "disagree": disagreement,
            "locus": ("file" if matrix is not None and np.array_equal(matrix, scene.xyz_to_cam)
                      else "reference" if matrix is not None else "given up"),
            "estimator": picked, "estimator_before": before,
            "error_deg": err, "error_gain": err_gain, "error_before_deg": err0,
            "error_before_gain": err0_gain, "error_grey_world_deg": err_gw,
            "error_grey_world_gain": err_gw_gain,
            "fallback": "given up" in said.getvalue() or "grey_world (" in said.getvalue()}


def shipped_row(run: Path) -> dict | None:
    """What the end-of-training check says of a trained default run: its summary's record,
    or (a run trained before the check) the check made now on its checkpoint, with the
    evidence taken from its frames. None where the run is not there."""
    summary_path = run / "summary.json"
    if not summary_path.is_file() or not (run / "checkpoint.npz").is_file():
        return None
    record = json.loads(summary_path.read_text()).get("colour")
    if record is not None and "distance" in record:
        return record
    from gridnerf import eval_run, outputs, shipped_colour

    cfg, plan, scene, structure, params, _ = eval_run.load_run(run)
    if plan.colour.model != "field":
        return {"shipped": plan.colour.model}
    colour = plan.colour
    if not colour.evidence:
        data = dataset.build(scene, scene.train_idx, True)
        frames = colour_target.estimate_frames(data, scene)
        *_, free = colour_target.locus_check(scene, frames, colour.estimate_downscale)
        colour = replace(colour, evidence=colour_target.frames_evidence(free, scene))
    with contextlib.redirect_stdout(io.StringIO()):
        _, record = shipped_colour.check(
            outputs.training_render(structure, params, scene, cfg), colour)
    return {**record, "checked_after": True}


def main() -> None:
    ap = study_parser(__doc__, "reports/colour_checks", scenes="all", runs=True)
    args = ap.parse_args()
    from gridnerf import shipped_colour

    rows, net_rows, record = [], [], {"scenes": {}, "thresholds": {
        "LOCUS_TRUST_DEG": colour_target.LOCUS_TRUST_DEG,
        "LOCUS_TRUST_GAIN": colour_target.LOCUS_TRUST_GAIN,
        "LOCUS_END_KELVIN": list(colour_target.LOCUS_END_KELVIN),
        "MATRIX_AGREE_DEG": colour_target.MATRIX_AGREE_DEG,
        "ESTIMATORS_AGREE": colour_target.ESTIMATORS_AGREE,
        "SHIP_TRUST": shipped_colour.SHIP_TRUST}}
    group_of = {n: g for g, names in GROUPS.items() for n in names}
    for name, folder in simulated_folders(args.scenes):
        r = scene_row(folder)
        r["shipped"] = shipped_row(Path(args.runs) / name / "default")
        record["scenes"][name] = r
        print(name, {k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()},
              flush=True)
        rows.append([name, group_of.get(name, ""), "yes" if r["matrix_ok"] else "NO",
                     f"{fmt(r['locus_deg'])} / {r['locus_kelvin']:.0f} K",
                     f"{r['grey_gap']:.3f}", f"{r['disagree']:.3f}",
                     r["locus"],
                     f"{r['estimator_before']} -> {r['estimator']}"
                     if r["estimator"] != r["estimator_before"] else r["estimator"],
                     f"{fmt(r['error_before_deg'])} / {r['error_before_gain']:.3f}",
                     f"{fmt(r['error_deg'])} / {r['error_gain']:.3f}",
                     f"{fmt(r['error_grey_world_deg'])} / {r['error_grey_world_gain']:.3f}"])
        if (s := r["shipped"]) is not None and "distance" in s:
            net_rows.append([name, group_of.get(name, ""), s["nearest"],
                             f"{s['distance']:.3f}", s["shipped"]])
    table = markdown_table(
        ["scene", "group", "matrix fits its camera", "frames to locus (deg / nearest)",
         "grey world to locus (gain)", "estimators disagree (gain)", "locus prior from",
         "estimator", "error without checks", "error with checks", "grey world, no locus"],
        rows)
    t = record["thresholds"]
    md = ("# Colour checks on the simulated scenes (frames only, no training)\n\n"
          f"`python -m experiments.colour_checks --scenes {args.scenes}`. Thresholds: locus "
          f"trusted within {t['LOCUS_TRUST_DEG']:g} deg (the consensus), "
          f"{t['LOCUS_TRUST_GAIN']:g} (grey world, illuminant.gain_distance) and "
          f"{t['LOCUS_END_KELVIN'][0]:.0f}-{t['LOCUS_END_KELVIN'][1]:.0f} K, matrix within "
          f"{t['MATRIX_AGREE_DEG']:g} deg of its camera's reference, estimators within "
          f"{t['ESTIMATORS_AGREE']:g} under one light. Errors of the capture estimate to the "
          "simulator's light: angle (deg) / gain distance. \"Without checks\": the pick on "
          "the file's locus whatever the checks say.\n\n" + table + "\n")
    if net_rows:
        md += ("\n## The end-of-training check (gridnerf.shipped_colour)\n\n"
               f"Trained default runs under {args.runs}/<scene>/default: the gain distance "
               "from the field's white on the training render to the nearest of the frames' "
               f"estimates; over {t['SHIP_TRUST']:g} one grey-world gain is shipped.\n\n"
               + markdown_table(["scene", "group", "nearest estimate", "distance",
                                 "shipped"], net_rows) + "\n")
    write_report(args.out, md, record)
    print(md)


if __name__ == "__main__":
    main()
