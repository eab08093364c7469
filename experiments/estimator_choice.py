"""Choosing the illuminant estimator per capture by its consistency across the frames.

The L_ca target's level is the capture's colour constancy: the consensus (per-channel
median) of grey world, shades of grey and grey edge, each on the camera's Planckian locus
(illuminant.capture_estimate "consensus"). Each of the three fails on some content, and
the consensus outvotes one that fails. An alternative that looks at the capture: an
estimator that reacts to the light, not the content, gives the same answer on different
parts of the scene. Here each estimator runs on the four quadrants of the training frames
(pooled over the frames) and on the whole capture; its `spread` is the mean angle of the
quadrants' estimates from the whole's, and the `pick` is the estimator that spreads least.
The `safe pick` never takes the odd one out (the estimate furthest from the consensus):
the least spread of the other two.

Scored on the 2x2-binned raw training frames against the simulator's white:

- one estimate for the capture (single-light scenes): angular error of the consensus and
  of the pick;
- the L_ca map anchored by region (illum_map.regional_anchor, the default target) with the
  consensus or with the pick in both halves: green-weighted per-pixel angular error, as
  experiments/illuminant_maps.py scores it (every scene).

Under two lights the quadrants see different lights as well as different content, so
the spread measures both.

    python experiments/estimator_choice.py [--scenes all]

Writes reports/estimator_choice.md and reports/estimator_choice.json.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from common import REPORT_GROUPS, fmt, markdown_table, study_parser, write_report
from gridnerf import illum_map
from gridnerf import illuminant as il
from gridnerf.config import LossConfig
from illuminant_maps import to_pixels, true_map, weighted_error
from illuminants import training_frames

_LOSS = LossConfig()
BLOCK, TAU = _LOSS.ca_map_block, _LOSS.ca_map_tau  # the default map's


def regional_map_error(images, masks, rel, weight, truths, estimate, locus) -> float:
    """Mean over the frames of the per-pixel error of the regional-anchor map built with
    `estimate` (images, masks) -> (3,); rel, weight: the frames' illum_map.relative_maps;
    truths: each frame's true white per pixel over its whole blocks (true_map)."""
    anchor = illum_map.regional_anchor(images, masks, rel, weight, estimate, locus, BLOCK)
    maps = illum_map.frame_maps(images, masks, anchor, locus, BLOCK, TAU, rel=rel)
    errs = []
    for img, fmap, truth in zip(images, maps, truths, strict=True):
        crop = img[: truth.shape[0], : truth.shape[1]]
        errs.append(weighted_error(to_pixels(fmap, BLOCK), truth, crop))
    return float(np.mean(errs))


def main() -> None:
    ap = study_parser(__doc__, "reports/estimator_choice")
    args = ap.parse_args()
    record, rows = {}, []
    for name, folder, sim, images, masks, names in training_frames(args.scenes):
        locus = il.planckian_locus(sim["xyz_to_cam"])
        spread = il.quadrant_spreads(images, masks, locus)
        pick = il.least_spread(spread)
        cons = il.consensus([e for e, _ in spread.values()], locus)
        odd = max(spread, key=lambda n: il.angular_error_deg(spread[n][0], cons))
        safe = min((n for n in spread if n != odd), key=lambda n: spread[n][1])
        rec = {"pick": pick, "safe_pick": safe,
               "spread_deg": {n: s for n, (_, s) in spread.items()},
               "mixed_light": bool(sim.get("mixed_light"))}
        if not rec["mixed_light"]:
            true = np.asarray(sim["illuminant_neutral_cam"], np.float64)
            rec["capture_consensus"] = float(il.angular_error_deg(cons, true))
            rec["capture_pick"] = float(il.angular_error_deg(spread[pick][0], true))
        rel, weight = illum_map.relative_maps(images, masks, BLOCK, TAU)
        rec["map_spread"] = illum_map.map_spread_deg(
            illum_map.frame_maps(images, masks, cons, locus, BLOCK, TAU, rel=rel), cons)
        one_light = rec["map_spread"] < _LOSS.ca_one_light_deg
        truths = [true_map(folder, sim, frame, (r.shape[0] * BLOCK, r.shape[1] * BLOCK))
                  for r, frame in zip(rel, names, strict=True)]
        for key, est in (("map_consensus", "consensus"), ("map_pick", pick),
                         ("map_safe_pick", safe)):
            rec[key] = regional_map_error(images, masks, rel, weight, truths,
                                          partial(il.capture_estimate, est, locus=locus),
                                          locus)
        rec["map_consistent"] = rec["map_pick"] if one_light else rec["map_consensus"]
        record[name] = rec
        rows.append([name, pick, *(fmt(spread[n][1]) for n in il.CONSENSUS),
                     *(fmt(rec[k]) if k in rec else "" for k in ("capture_consensus",
                                                                  "capture_pick")),
                     fmt(rec["map_consensus"]), fmt(rec["map_pick"]), safe,
                     fmt(rec["map_safe_pick"]), fmt(rec["map_spread"]),
                     fmt(rec["map_consistent"])])
        print(" | ".join(rows[-1]), flush=True)
    keys = ("capture_consensus", "capture_pick", "map_consensus", "map_pick", "",
            "map_safe_pick", "", "map_consistent")
    for label, group in REPORT_GROUPS:
        got = [record[n] for n in group if n in record]
        if got:
            means = [fmt(float(np.mean([g[k] for g in got if k in g])))
                     if k and any(k in g for g in got) else "" for k in keys]
            rows.append([f"**mean, {label}** ({len(got)})", "", "", "", "", *means])
    md = ("# Choosing the illuminant estimator by its consistency\n\n"
          f"`python experiments/estimator_choice.py --scenes {args.scenes}`. Binned raw "
          "training frames; angular errors (deg) against the simulator's white. `spread`: "
          "mean angle of each estimator's quadrant estimates from its whole-capture "
          "estimate (on the locus); `pick`: the estimator that spreads least; `capture`: "
          "one estimate for the capture (single-light scenes); `map`: the default L_ca map "
          "(regional anchor) with the consensus, the pick or the safe pick (the least "
          "spread of the two estimates nearer the consensus) in both halves, "
          "green-weighted per pixel; `map spread`: how far the maps anchored to the "
          "consensus stray from it (illum_map.map_spread_deg); `consistent`: "
          "loss.ca_illuminant=consistent, the pick where the map spread is below "
          f"loss.ca_one_light_deg = {_LOSS.ca_one_light_deg} (one light), else the "
          "consensus.\n\n"
          + markdown_table(["scene", "pick", *(f"spread {n}" for n in il.CONSENSUS),
                            "capture: consensus", "capture: pick", "map: consensus",
                            "map: pick", "safe pick", "map: safe pick", "map spread",
                            "map: consistent"], rows) + "\n")
    write_report(args.out, md, record)


if __name__ == "__main__":
    main()
