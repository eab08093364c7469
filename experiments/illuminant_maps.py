"""Per-pixel illuminant error: one estimate for the capture against per-frame maps.

For every simulated scene, on the 2x2-binned raw training frames: the capture's illuminant
as `loss.ca_target=scene` estimates it (illuminant.consensus of grey world, shades of grey
and grey edge on the camera's Planckian locus) and the per-frame maps of
`loss.ca_target=map` anchored to it (gridnerf.illum_map.frame_maps, on the locus) or to
the lights of the maps' warm and cool halves (`loss.ca_map_anchor=regions`,
illum_map.regional_anchor, the same consensus on each half), each scored against the true
illuminant of every pixel: for mixed-light scenes the blend of the two lights by the first
one's share of the green signal (illuminant/<frame>.png, written by the simulator),
elsewhere the one light. Angular errors are weighted by the pixel's green signal and
averaged over the training frames. "spread" is the 90th percentile of the map's angle from
the capture estimate: near 0 where the map stays flat. "true level": the regional map with
each frame's level (its green-weighted mean log chromaticity) set to the truth's, which
splits the map's error into its level (the anchor: colour constancy) and its shape.

For the mixed-light scenes a second table splits the shape error further, integrating
the *true* illumination's block-to-block steps (illum_map.integrate_steps) at the level of
the truth: over the edges Retinex keeps (its choice of edges, with no noise and no paint in
the kept steps) and over every edge (what blocks of this size can show), with the share of
the true illumination change that lies on the edges Retinex drops (steps above tau).

    python experiments/illuminant_maps.py [--scenes all] [--block 16] [--tau 0.1]

Writes reports/illuminant_maps.md and reports/illuminant_maps.json.
"""

from __future__ import annotations

import argparse
from functools import partial
from pathlib import Path

import numpy as np
from PIL import Image

from common import markdown_table, study_parser, write_report
from gridnerf import illum_map, raw
from gridnerf import illuminant as il
from gridnerf.config import LossConfig
from gridnerf.sim import DEV, HELDOUT, HELDOUT_MIXED, MIXED, SCENES
from illuminants import training_frames

KEYS = ("capture", "map", "map_regions", "map_true_level", "spread_p90")
SHAPE_KEYS = ("map_true_level", "true_steps_kept_edges", "true_steps_all_edges",
              "dropped_share", "edges_dropped")


def true_map(folder: Path, sim: dict, name: str, hw: tuple[int, int]) -> np.ndarray:
    """(h, w, 3) true illuminant (green = 1) of each binned pixel of frame `name`."""
    if not sim.get("mixed_light"):
        return np.broadcast_to(np.asarray(sim["illuminant_neutral_cam"], np.float64), (*hw, 3))
    share = np.asarray(Image.open(folder / "illuminant" / f"{name}.png"), np.float64) / 255.0
    share = share[..., 0] if share.ndim == 3 else share
    if share.shape[0] >= 2 * hw[0]:
        share = raw.downscale(share, 2)
    share = share[: hw[0], : hw[1], None]
    first, second = (np.asarray(e["neutral_cam"], np.float64) for e in sim["illuminants"][:2])
    return share * first / first[1] + (1.0 - share) * second / second[1]


def _green_weight(rgb_cam) -> np.ndarray:
    """(h, w) each pixel's weight: its green signal (never 0)."""
    return np.clip(rgb_cam[..., 1], 0.0, None) + 1e-12


def with_true_level(estimate, truth, rgb_cam) -> np.ndarray:
    """estimate (h, w, 3) scaled per channel (R and B against G) so that its green-weighted
    mean log chromaticity is the truth's: its shape kept, its level made right."""
    w = _green_weight(rgb_cam)[..., None]
    est, tru = np.maximum(estimate, 1e-12), np.maximum(truth, 1e-12)
    shift = (np.log(tru / tru[..., 1:2] * est[..., 1:2] / est) * w).sum((0, 1)) / w.sum()
    return est * np.exp(shift)


def weighted_error(estimate, truth, rgb_cam) -> float:
    """Green-weighted mean angular error (deg) of estimate against truth (h, w, 3)."""
    w = _green_weight(rgb_cam)
    return float((il.angular_error_deg(estimate, truth) * w).sum() / w.sum())


def to_pixels(block_map, block: int) -> np.ndarray:
    """(hb, wb, ...) one value per block -> (hb * block, wb * block, ...) per pixel."""
    return np.repeat(np.repeat(block_map, block, 0), block, 1)


def shape_error(f, truth, crop, block: int) -> float:
    """Green-weighted angular error (deg) of a relative map f (hb, wb, 2) (log R/G, log
    B/G per block, as illum_map.integrate_steps gives it) against truth (h, w, 3) once its
    level is the truth's (with_true_level): the error of its shape alone. crop: the frame's
    camera RGB (h, w, 3) = (hb * block, wb * block, 3), for the weights."""
    rgb = np.stack([np.exp(f[..., 0]), np.ones(f.shape[:-1]), np.exp(f[..., 1])], -1)
    full = to_pixels(rgb, block)
    return weighted_error(with_true_level(full, truth, crop), truth, crop)


def shape_split(img, mask, truth, block: int, tau: float) -> dict:
    """One frame's shape error split (module docstring): green-weighted angular errors (deg)
    of the true steps integrated over Retinex's kept edges and over every edge, each at
    the truth's level, and the signal-weighted share of the true illumination change on
    the edges it drops and the share of edges it drops. img, mask: the binned frame;
    truth: (hb * block, wb * block, 3) its true white per pixel."""
    chroma, weight = illum_map.block_chroma(img, mask, block)
    hb, wb = weight.shape
    crop = img[: hb * block, : wb * block]
    a, b = illum_map.neighbour_pairs(hb, wb)
    seen = chroma.reshape(-1, 2)[b] - chroma.reshape(-1, 2)[a]
    keep = np.hypot(seen[:, 0], seen[:, 1]) <= tau
    true_c = illum_map.block_chroma(truth, None, block)[0].reshape(-1, 2)
    steps = true_c[b] - true_c[a]
    size = np.hypot(steps[:, 0], steps[:, 1]) * np.minimum(weight.ravel()[a], weight.ravel()[b])

    def error(kept):
        return shape_error(illum_map.integrate_steps(steps, kept, weight), truth, crop, block)

    return {"true_steps_kept_edges": error(keep),
            "true_steps_all_edges": error(np.ones_like(keep)),
            "dropped_share": float(size[~keep].sum() / max(size.sum(), 1e-12)),
            "edges_dropped": float(np.mean(~keep))}


def map_arguments(description: str, out: str) -> argparse.Namespace:
    """A raw-frame map study's command line: --scenes, --block and --tau (the default map's,
    loss.ca_map_block and loss.ca_map_tau), --out."""
    ap = study_parser(description, out)
    loss = LossConfig()
    ap.add_argument("--block", type=int, default=loss.ca_map_block)
    ap.add_argument("--tau", type=float, default=loss.ca_map_tau)
    return ap.parse_args()


def main() -> None:
    args = map_arguments(__doc__.splitlines()[0], "reports/illuminant_maps")
    record, rows = {}, []
    for name, folder, sim, images, masks, names in training_frames(args.scenes):
        locus = il.planckian_locus(sim["xyz_to_cam"])
        estimate = partial(il.capture_estimate, "consensus", locus=locus)
        capture = estimate(images, masks)
        rel, weight = illum_map.relative_maps(images, masks, args.block, args.tau)
        regional = illum_map.regional_anchor(images, masks, rel, weight, estimate, locus,
                                             args.block)
        maps, maps_r = (illum_map.frame_maps(images, masks, a, locus, args.block, args.tau,
                                             rel=rel) for a in (capture, regional))
        err_c, err_m, err_r, err_l, split = [], [], [], [], []
        for img, mask, fmap, fmap_r, frame in zip(images, masks, maps, maps_r, names,
                                                  strict=True):
            hb, wb = fmap.shape[:2]
            crop = img[: hb * args.block, : wb * args.block]
            truth = true_map(folder, sim, frame, crop.shape[:2])
            err_c.append(weighted_error(np.broadcast_to(capture, truth.shape), truth, crop))
            full, full_r = (to_pixels(m, args.block) for m in (fmap, fmap_r))
            err_m.append(weighted_error(full, truth, crop))
            err_r.append(weighted_error(full_r, truth, crop))
            err_l.append(weighted_error(with_true_level(full_r, truth, crop), truth, crop))
            if sim.get("mixed_light"):
                split.append(shape_split(img, mask, truth, args.block, args.tau))
        rec = {"capture": float(np.mean(err_c)), "map": float(np.mean(err_m)),
               "map_regions": float(np.mean(err_r)), "map_true_level": float(np.mean(err_l)),
               "spread_p90": illum_map.map_spread_deg(maps, capture),
               "mixed_light": bool(sim.get("mixed_light"))}
        if split:
            rec.update({k: float(np.mean([d[k] for d in split])) for k in split[0]})
        record[name] = rec
        rows.append([name, "yes" if rec["mixed_light"] else "no",
                     *(f"{rec[k]:.2f}" for k in KEYS)])
        print(" | ".join(rows[-1]), flush=True)
    for group, members in (("nine built-in", SCENES), ("tuning", DEV),
                           ("held-out", HELDOUT), ("mixed light", MIXED),
                           ("held-out mixed light", HELDOUT_MIXED)):
        vals = [record[n] for n in members if n in record]
        if vals:
            rows.append([f"**mean, {group}** ({len(vals)})", "",
                         *(f"{np.mean([v[k] for v in vals]):.2f}" for k in KEYS)])
    table = markdown_table(["scene", "mixed light", "capture estimate (deg)",
                            "map, anchored to it (deg)", "map, regional anchor (deg)",
                            "regional map, true level (deg)",
                            "map spread p90 (deg)"], rows)
    shape_rows = [[n, *(f"{r[k]:.2f}" for k in SHAPE_KEYS)] for n, r in record.items()
                  if "dropped_share" in r]
    shape = ("\n## The mixed-light maps' shape error, split\n\nDegrees as above, every column "
             "at the truth's level: the regional map; the true illumination's block-to-block "
             "steps integrated over the edges Retinex keeps (steps of the frame's chromaticity "
             f"up to tau = {args.tau}) and over every edge (the floor of {args.block}-pixel "
             "blocks); the share of the true illumination change (signal-weighted) on the "
             "edges Retinex drops, and the share of edges it drops.\n\n"
             + markdown_table(["scene", "regional map, true level (deg)",
                               "true steps, Retinex's edges (deg)",
                               "true steps, every edge (deg)",
                               "illumination change on dropped edges",
                               "edges dropped"], shape_rows) + "\n") if shape_rows else ""
    write_report(args.out,
                 "Per-pixel angular error of the L_ca illuminant (green-weighted, binned raw "
                 "training frames): one estimate for the capture (`loss.ca_target=scene`) "
                 "against per-frame Retinex maps (`loss.ca_target=map`, block "
                 f"{args.block}, tau {args.tau}) anchored to that estimate "
                 "(`loss.ca_map_anchor=capture`) or to the lights of the maps' warm and cool "
                 "halves (`regions`, illum_map.regional_anchor), the regional map with "
                 "each frame's level set to the truth's (its shape alone), `python "
                 "experiments/illuminant_maps.py`.\n\n"
                 + table + "\n" + shape, record)
    print(table)


if __name__ == "__main__":
    main()
