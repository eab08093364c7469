"""The colour path's self-checks on every simulated scene, from the frames alone (no training).

For each scene (its training frames, 2x2-binned, as training sees them): the file's matrix
against its camera's reference (colour_target.matrix_check), the frames' own estimate's
angle to the file's Planckian locus and its nearest temperature (colour_target.locus_check),
how far the three estimators disagree (colour_target.estimators_disagree), the decisions
(locus kept or given up, the estimator "consistent" takes), and the angular error against
the simulator's true light (sim.json's illuminant_neutral_cam) of the capture estimate the
default takes with the checks and of the one it took without them (the pick on the locus,
whatever the checks say), and of grey world unprojected. Mixed-light scenes' truth is the
lights' mix, so their errors say less.

    python -m experiments.colour_checks --scenes all [--out reports/colour_checks]
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np

from experiments.common import (
    GROUPS,
    fmt,
    markdown_table,
    simulated_folders,
    study_parser,
    write_report,
)
from gridnerf import colour_target, dataset, illuminant
from gridnerf import config as cfgmod
from gridnerf.scene import load_scene


def scene_row(folder) -> dict:
    """The checks, decisions and errors of one simulated scene folder."""
    sim = json.loads((folder / "sim.json").read_text())
    truth = np.asarray(sim["illuminant_neutral_cam"], np.float64)
    scene = load_scene(folder, near_far=tuple(sim["near_far"]))
    data = dataset.build(scene, scene.train_idx, True)
    frames = colour_target.estimate_frames(data, scene)
    d = colour_target.estimate_downscale(frames, colour_target.NOISE_RATIO)
    _, angle, kelvin, free = colour_target.locus_check(scene, frames, d)
    locus = illuminant.planckian_locus(scene.xyz_to_cam)
    with contextlib.redirect_stdout(io.StringIO()) as said:
        use_locus, disagreement, _ = colour_target.trusted_locus(scene, cfgmod.Config(), frames,
                                                                 d)
        picked = colour_target.consistent_estimator(frames, d, None,
                                                    locus if use_locus else None, disagreement)
        before = colour_target.consistent_estimator(frames, d, None, locus, 0.0)

    def error(name, loc) -> float:
        est = colour_target.scene_illuminant(frames, name, d, loc)
        return float(illuminant.angular_error_deg(est, truth))

    return {"matrix_ok": colour_target.matrix_check(scene) is None, "locus_deg": angle,
            "locus_kelvin": kelvin, "disagree_deg": colour_target.estimators_disagree(free),
            "locus_kept": bool(use_locus), "estimator": picked, "estimator_before": before,
            "error_deg": error(picked, locus if use_locus else None),
            "error_before_deg": error(before, locus),
            "error_grey_world_deg": error("grey_world", None),
            "fallback": "given up" in said.getvalue() or "grey_world (" in said.getvalue()}


def main() -> None:
    ap = study_parser(__doc__, "reports/colour_checks", scenes="all")
    args = ap.parse_args()
    rows, record = [], {"scenes": {}, "thresholds": {
        "LOCUS_TRUST_DEG": colour_target.LOCUS_TRUST_DEG,
        "LOCUS_END_KELVIN": list(colour_target.LOCUS_END_KELVIN),
        "MATRIX_AGREE_DEG": colour_target.MATRIX_AGREE_DEG,
        "ESTIMATORS_AGREE_DEG": colour_target.ESTIMATORS_AGREE_DEG}}
    group_of = {n: g for g, names in GROUPS.items() for n in names}
    for name, folder in simulated_folders(args.scenes):
        r = scene_row(folder)
        record["scenes"][name] = r
        print(name, {k: round(v, 2) if isinstance(v, float) else v for k, v in r.items()},
              flush=True)
        rows.append([name, group_of.get(name, ""), "yes" if r["matrix_ok"] else "NO",
                     f"{fmt(r['locus_deg'])} / {r['locus_kelvin']:.0f} K",
                     fmt(r["disagree_deg"]), "kept" if r["locus_kept"] else "given up",
                     f"{r['estimator_before']} -> {r['estimator']}"
                     if r["estimator"] != r["estimator_before"] else r["estimator"],
                     fmt(r["error_before_deg"]), fmt(r["error_deg"]),
                     fmt(r["error_grey_world_deg"])])
    table = markdown_table(
        ["scene", "group", "matrix fits its camera", "frames to locus (deg / nearest)",
         "estimators disagree (deg)", "locus prior", "estimator", "error without checks",
         "error with checks", "grey world, no locus"], rows)
    t = record["thresholds"]
    md = ("# Colour checks on the simulated scenes (frames only, no training)\n\n"
          f"`python -m experiments.colour_checks --scenes {args.scenes}`. Thresholds: locus "
          f"trusted within {t['LOCUS_TRUST_DEG']:g} deg and {t['LOCUS_END_KELVIN'][0]:.0f}-"
          f"{t['LOCUS_END_KELVIN'][1]:.0f} K, matrix within {t['MATRIX_AGREE_DEG']:g} deg of "
          f"its camera's reference, estimators within {t['ESTIMATORS_AGREE_DEG']:g} deg. "
          "Errors: angle (deg) of the capture estimate to the simulator's light.\n\n"
          + table + "\n")
    write_report(args.out, md, record)
    print(md)


if __name__ == "__main__":
    main()
