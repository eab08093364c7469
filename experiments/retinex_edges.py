"""Which block edges a Retinex map may integrate: the default rule against two that keep
large steps that look like illumination.

Most of the mixed-light maps' shape error is illumination change on edges the default rule
drops (reports/illuminant_maps.md, second table: 58-72 % of the true change lies on edges
whose chromaticity step exceeds tau). Two rules that keep some larger steps are scored
here on the 2x2-binned raw training frames, each map at the truth's level (its shape
alone, not projected on the locus; green-weighted angular error against the simulator's
per-pixel white, as in experiments/illuminant_maps.py):

- `retinex` (the default, illum_map.log_chroma_map): a step is kept when its log
  chromaticity changes by at most tau.
- `chord`: also keep a larger step (up to 0.3 along the camera's Planckian locus) that
  runs along the locus (at most 0.02 across it): where two blackbody lights mix, the
  illumination moves along the chord between them, close to the locus.
- `shadow`: also keep a larger step that looks like one light's shadow or falloff: between
  a brighter block b and a darker block d of one paint, E_b = E_d + k L (one light L
  added), so b / d - 1 = k L / E_d is positive in every channel, and both its log
  chromaticity and the step's run along the locus (within 10 deg), the same way, the
  former the longer. Paint edges give any ratio.

- `crease` (an oracle of geometry): also keep a step between blocks whose surfaces face
  directions more than 20 deg apart (the simulator's true normals, averaged over each
  block): a face turned to another light. It tells whether geometry, were the grid's
  good enough, would point out the light's steps.

The first two mistake some paint for light (a white beside a warm paint reads as a cool
light added); the third keeps every paint edge that falls on a crease or an outline.
The table measures what each costs, under one light as under two.

    python experiments/retinex_edges.py [--scenes all] [--block 16] [--tau 0.1]

Writes reports/retinex_edges.md and reports/retinex_edges.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common import REPORT_GROUPS, fmt, markdown_table, write_report
from gridnerf import illum_map, raw
from gridnerf import illuminant as il
from gridnerf.sim import capture
from gridnerf.sim.scenes import build_scene
from illuminant_maps import map_arguments, shape_error, true_map
from illuminants import training_frames

RULES = ("retinex", "chord", "shadow", "crease")
ACROSS, ALONG = 0.02, 0.3  # the chord rule's limits (log chromaticity)
SHADOW_DEG, SHADOW_MIN_RATIO = 10.0, 0.05  # the shadow rule's angle; b / d - 1 floor
CREASE_DEG = 20.0  # the crease rule's angle between neighbouring blocks' normals


def true_normals(folder, sim: dict, frames: list[str], shape: tuple[int, int]
                 ) -> list[np.ndarray]:
    """(h, w, 3) per frame of `frames`: the simulator's mean surface normal of each binned
    pixel (shape: the binned frames'), from the frame's pose in transforms.json and the
    scene's spec (each read or built once)."""
    meta = json.loads((folder / "transforms.json").read_text())
    poses = {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"], np.float64)
             for f in meta["frames"]}
    intr = capture.Intrinsics(meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"],
                              meta["w"], meta["h"])
    spec = build_scene(sim["scene"])
    return [raw.downscale(capture.render_normals(spec, poses[f], intr).astype(np.float64),
                          2)[: shape[0], : shape[1]] for f in frames]


def locus_axes(xyz_to_cam) -> tuple[np.ndarray, np.ndarray]:
    """((2,), (2,)) unit directions along and across the camera's Planckian locus in log
    chromaticity (log R/G, log B/G): illum_map.locus_axis, and the normal to it."""
    along = illum_map.locus_axis(il.planckian_locus(xyz_to_cam))
    return along, np.array([-along[1], along[0]])


def edge_rules(means, chroma, along, across, tau: float, normals=None
               ) -> dict[str, np.ndarray]:
    """Each rule's kept edges (E,) bool (illum_map.neighbour_pairs order). means: (hb, wb,
    3) the blocks' mean camera RGB; chroma: (hb, wb, 2) their log chromaticity; normals:
    (hb, wb, 3) the blocks' mean surface normals, or None (no crease rule)."""
    a, b = illum_map.neighbour_pairs(*chroma.shape[:2])
    flat_c, flat_m = chroma.reshape(-1, 2), means.reshape(-1, 3)
    step = flat_c[b] - flat_c[a]
    small = np.hypot(step[:, 0], step[:, 1]) <= tau
    chord = (np.abs(step @ across) <= ACROSS) & (np.abs(step @ along) <= ALONG)
    lum = flat_m.sum(-1)
    hi, lo = np.where(lum[b] > lum[a], b, a), np.where(lum[b] > lum[a], a, b)
    ratio = flat_m[hi] / np.maximum(flat_m[lo], 1e-12) - 1.0  # k L / E_d for a shadow
    q = np.log(np.maximum(ratio, 1e-6))
    q = np.stack([q[:, 0] - q[:, 1], q[:, 2] - q[:, 1]], -1)
    s = flat_c[hi] - flat_c[lo]
    tan = np.tan(np.deg2rad(SHADOW_DEG))
    sa, qa = s @ along, q @ along
    shadow = ((ratio > SHADOW_MIN_RATIO).all(-1)
              & (np.abs(s @ across) <= tan * np.abs(sa))
              & (np.abs(q @ across) <= tan * np.abs(qa))
              & (np.sign(sa) == np.sign(qa))
              & (np.hypot(*q.T) >= np.hypot(*s.T)))
    rules = {"retinex": small, "chord": small | chord, "shadow": small | shadow}
    if normals is not None:
        n = np.asarray(normals, np.float64).reshape(-1, 3)
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        turned = np.sum(n[a] * n[b], -1) < np.cos(np.deg2rad(CREASE_DEG))
        rules["crease"] = small | turned
    return rules


def frame_errors(img, mask, truth, normals, along, across, block: int, tau: float) -> dict:
    """Each rule's map of one frame at the truth's level: green-weighted angular error
    (deg) against truth (hb * block, wb * block, 3), and the share of edges it keeps that
    the default rule drops ('<rule>_extra'); normals: (h, w, 3) true_normals."""
    chroma, weight = illum_map.block_chroma(img, mask, block)
    hb, wb = weight.shape
    means = illum_map.block_means(img, mask, block)[0]
    a, b = illum_map.neighbour_pairs(hb, wb)
    flat_c = chroma.reshape(-1, 2)
    crop = img[: hb * block, : wb * block]
    rules = edge_rules(means, chroma, along, across, tau,
                       illum_map.block_means(normals, None, block)[0])
    out = {}
    for name, keep in rules.items():
        out[name] = shape_error(illum_map.integrate_steps(flat_c[b] - flat_c[a], keep, weight),
                                truth, crop, block)
        out[f"{name}_extra"] = float(np.mean(keep & ~rules["retinex"]))
    return out


def main() -> None:
    args = map_arguments(__doc__.splitlines()[0], "reports/retinex_edges")
    record, rows = {}, []
    for name, folder, sim, images, masks, names in training_frames(args.scenes):
        along, across = locus_axes(sim["xyz_to_cam"])
        per = []
        normals = true_normals(folder, sim, names, images[0].shape[:2])
        for img, mask, frame, nrm in zip(images, masks, names, normals, strict=True):
            hb, wb = (s // args.block for s in img.shape[:2])
            truth = true_map(folder, sim, frame, (hb * args.block, wb * args.block))
            per.append(frame_errors(img, mask, truth, nrm, along, across, args.block,
                                    args.tau))
        record[name] = {k: float(np.mean([p[k] for p in per])) for k in per[0]}
        record[name]["mixed_light"] = bool(sim.get("mixed_light"))
        rows.append([name, *(fmt(record[name][r]) for r in RULES),
                     *(fmt(record[name][f"{r}_extra"]) for r in RULES[1:])])
        print(" | ".join(rows[-1]), flush=True)
    for label, group in REPORT_GROUPS:
        got = [record[n] for n in group if n in record]
        if got:
            rows.append([f"**mean, {label}** ({len(got)})",
                         *(fmt(float(np.mean([g[r] for g in got]))) for r in RULES),
                         *(fmt(float(np.mean([g[f"{r}_extra"] for g in got])))
                           for r in RULES[1:])])
    md = ("# Retinex edges: which steps a map may integrate\n\n"
          f"`python experiments/retinex_edges.py --scenes {args.scenes}`. Per-pixel angular "
          "error (deg, green-weighted) of each frame's map at the truth's level (its shape "
          "alone), 2x2-binned raw training frames, blocks of "
          f"{args.block}, tau {args.tau}; `extra`: the share of edges a rule keeps that "
          "the default (`retinex`) drops. Rules in the script's docstring.\n\n"
          + markdown_table(["scene", *(f"{r} (deg)" for r in RULES),
                            *(f"{r} extra" for r in RULES[1:])], rows) + "\n")
    write_report(args.out, md, record)


if __name__ == "__main__":
    main()
