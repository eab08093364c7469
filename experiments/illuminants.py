"""Angular error of each illuminant estimator against the simulator's true illuminant.

For every simulated scene: the training frames' raw mosaics, 2x2-binned to camera RGB
(black level from the file, the unknown per-CFA bias left in, saturated blocks masked),
pooled over frames, go through each estimator of gridnerf.illuminant (grey edge per
frame, on a Gaussian-smoothed image: raw gradients are mostly noise). With --runs, the
same estimators also run on the trained field's low-light renders of the training views
(`runs/<scene>/<run>`, at 1/4 resolution; weighted_grey on the surface colour rgb_low / acc
weighted by acc, near-black rays left out; with --area also by the surface area each pixel
sees, depth^2 from the rendered NDC depth).
`consensus` is the per-channel median of grey world, shades of grey and grey edge
(illuminant.consensus; `+locus`: each projected first), the default L_ca target.
Each estimate is also scored after projection onto the camera's Planckian locus
(`+locus` columns: illuminant.to_locus on illuminant.planckian_locus of sim.json's
xyz_to_cam, the raw file's ColorMatrix).
The truth is sim.json's illuminant_neutral_cam (for mixed-light scenes the
signal-weighted mix of the two lights).

Run: LD_PRELOAD=/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4 \
     .venv/bin/python experiments/illuminants.py [--scenes all] [--runs default]
Writes reports/illuminants.md and reports/illuminants.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common import simulated_folders, study_parser, write_report
from gridnerf import illuminant as il
from gridnerf import raw
from gridnerf.scene import raw_files
from gridnerf.sim import HELDOUT, HELDOUT_MIXED, MIXED, SCENES

ORDER = ("grey_world", "shades_of_grey", "grey_edge", "weighted_grey")


def raw_images(scene_dir: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Binned camera RGB (h, w, 3) and validity (h, w) of the training frames."""
    sim = json.loads((scene_dir / "sim.json").read_text())
    test = set(sim.get("test_frames", []))
    images, masks = [], []
    for name, path in raw_files(scene_dir).items():
        if name in test:
            continue
        frame = raw.read_raw(path)
        images.append(raw.bin2x2(raw.normalize(frame), frame.cfa))
        masks.append(raw.bin2x2_mask(~raw.saturated_mask(frame), frame.cfa))
    return images, masks


def training_frames(spec: str):
    """Per simulated scene of `spec` (common.simulated_folders): (name, folder, sim: its
    sim.json, images, masks: raw_images, frames: the training frames' names in that
    order)."""
    for name, folder in simulated_folders(spec):
        sim = json.loads((folder / "sim.json").read_text())
        test = set(sim.get("test_frames", []))
        yield (name, folder, sim, *raw_images(folder),
               [n for n in raw_files(folder) if n not in test])


def estimates(images, masks) -> dict[str, np.ndarray]:
    """Each estimator on a list of (h, w, 3) images with (h, w) or (h, w, 3) masks, the way
    `loss.ca_target=scene` estimates a capture's illuminant (illuminant.frames_estimate)."""
    return {name: il.frames_estimate(name, images, masks) for name in ORDER}


def render_estimates(run: Path, area: bool = False) -> dict[str, np.ndarray]:
    """The estimators on the trained field's low-light renders of the training views
    (area: weighted_grey also weighs each pixel by the surface area it sees)."""
    from gridnerf.eval_run import load_run, render_view

    cfg, scene, structure, params, _ = load_run(run)
    cams = scene.cameras
    rgbs, accs, depths = [], [], []
    for i in scene.train_idx:
        h, w = int(cams.height) // 4, int(cams.width) // 4
        intr = np.array([cams.fx[i] / 4, cams.fy[i] / 4, cams.cx[i] / 4, cams.cy[i] / 4],
                        np.float32)
        out = render_view(structure, params, scene, cfg, cams.c2w[i], intr, h, w)
        rgbs.append(np.asarray(out["rgb_low"], np.float64))
        accs.append(np.asarray(out["acc"], np.float64))
        depths.append(np.asarray(out["depth"], np.float64))
    rgb, acc, t = np.stack(rgbs), np.stack(accs), np.stack(depths)
    res = {name: il.estimate(name, rgb) for name in ("grey_world", "shades_of_grey")}
    res["grey_edge"] = il.unit(np.mean([il.grey_edge(x, sigma=1.0) for x in rgbs], axis=0))
    weights = acc
    if area and scene.forward_facing:  # NDC: a ray's expected t maps to depth 1 / (1 - t)
        t_surface = np.clip(t / np.maximum(acc, 1e-3), 0.0, 0.999)
        weights = acc * il.footprint_weights(1.0 / (1.0 - t_surface))
    res["weighted_grey"] = il.weighted_grey(rgb / np.maximum(acc, 1e-3)[..., None],
                                            weights=weights)
    return res


def main() -> None:
    ap = study_parser(__doc__, "reports/illuminants")
    ap.add_argument("--runs", default=None, help="also estimate on renders of runs/<scene>/RUN")
    ap.add_argument("--area", action="store_true",
                    help="renders: weighted_grey weighs pixels by surface area (depth^2)")
    args = ap.parse_args()
    rows, record = [], {}
    columns = [*ORDER, "consensus", *(k + "+locus" for k in (*ORDER, "consensus"))]
    for name, folder in simulated_folders(args.scenes):
        sim = json.loads((folder / "sim.json").read_text())
        truth = np.array(sim["illuminant_neutral_cam"])
        locus = il.planckian_locus(sim["xyz_to_cam"])
        sources = {"raw": estimates(*raw_images(folder))}
        run = Path("runs") / name / (args.runs or "")
        if args.runs and (run / "summary.json").exists():
            sources["render"] = render_estimates(run, args.area)
        for source, est in sources.items():
            err = {k: float(il.angular_error_deg(v, truth)) for k, v in est.items()}
            err.update({k + "+locus": float(il.angular_error_deg(il.to_locus(v, locus), truth))
                        for k, v in est.items()})
            three = [est[k] for k in il.CONSENSUS]  # the default L_ca target (+locus)
            err["consensus"] = float(il.angular_error_deg(il.consensus(three), truth))
            err["consensus+locus"] = float(il.angular_error_deg(il.consensus(three, locus),
                                                                truth))
            record.setdefault(name, {})[source] = err
            rows.append(f"| {name} | {source} | "
                        + " | ".join(f"{err[k]:.2f}" for k in columns) + " |")
            print(rows[-1], flush=True)
    head = ("| scene | input | " + " | ".join(columns) + " |\n|---|---|"
            + "---|" * len(columns))
    means = []
    groups = {"nine built-in": SCENES, "held-out": HELDOUT, "mixed light": MIXED,
              "held-out mixed light": HELDOUT_MIXED,
              "all": tuple(record)}
    for source in ("raw", "render"):
        for group, names in groups.items():
            vals = [record[n][source] for n in names if source in record.get(n, {})]
            if vals:
                for stat, f in (("mean", np.mean), ("worst", np.max)):
                    means.append(f"| **{stat}, {group}** ({len(vals)}) | {source} | "
                                 + " | ".join(f"{f([v[k] for v in vals]):.2f}"
                                              for k in columns) + " |")
    write_report(
        args.out,
        "Angular error (degrees) of illuminant estimates against the simulator's true "
        "illuminant (camera RGB), `python experiments/illuminants.py"
        f"{' --runs ' + args.runs if args.runs else ''}{' --area' if args.area else ''}`.\n\n"
        + "\n".join([head, *rows, *means]) + "\n", record)
    print("\n".join(means))


if __name__ == "__main__":
    main()
