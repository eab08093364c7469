"""How much of the noise a trained field averages away, measured in raw space.

The error budget (experiments.error_budget) scores every fit through the output path, so its
"noise" column holds whatever the noisy raw adds to a fit on clean raw: the noise, but also
the sensor's hidden black offsets, which a field trained on the frames as they are learns as
signal and the output path then shows. Here the colour path is left out. Each frame of a
simulated single-light scene is rendered by the trained field (rgb_low, the low-light camera
RGB per unit exposure, at the 2x2-binned size the data term fits) and compared with the
simulator's exact clean raw of that frame, binned the same way (gridnerf.sim.truth.clean_mean),
the black offsets the field learned taken off with their true values (none under a lens-cap
black level, whose measured offsets the data already lost). The error is given in dB below
the noise variance of one binned frame (sim.json's K and read variance at the clean signal;
the two greens of a binned pixel averaged): 0 dB is no better than one frame, and an ideal
average of the V training views that all see every pixel would reach 10 log10(V) dB (13.2 for
21 views). A fit far short of that on its own training views is limited by what the grid can
represent (its resolution, the geometry, the sampling of the binned mosaic), not by the
photons; the same field fitted to the clean raw (the budget's clean_truewhite run, where
present) shows that floor directly.

Reads finished runs only (runs/<scene>/<variant>); no training. Scenes with several lights
(no single clean raw) and cameras with lens falloff (the field is fitted to the frames with
the falloff taken off) are skipped with a line.

    python -m experiments.raw_fit [--scenes all] [--variants default,clean_truewhite,fine]
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from experiments import common
from gridnerf import eval_run, raw
from gridnerf.sim import truth


def binned_offsets(nt: dict, cfa: np.ndarray) -> np.ndarray:
    """(3,) the true black offsets as the binned channels carry them, normalised raw."""
    b = np.asarray(nt["black_offset_dn"], np.float64) / nt["scale"]
    return raw.bin2x2(np.tile(b, (2, 2)), cfa, np.float64)[0, 0]


def fit_errors(run: Path) -> dict:
    """{split: {"fit": (3,), "noise": (3,), "signal": (3,)}, "views": V}: mean squared error
    of the field's binned render against the clean binned raw, one binned frame's noise
    variance and the clean signal's mean square, per colour, averaged over the split's
    views (train, test); V the training views."""
    cfg, plan, scene, structure, params, _ = eval_run.load_run(run)
    folder = Path(scene.path)
    sim = json.loads((folder / "sim.json").read_text())
    nt = truth.noise_truth(sim)
    mean = truth.clean_mean(folder)
    learned_offsets = cfg.data.target != "clean" and plan.black_level != "lens_cap"
    offset = binned_offsets(nt, scene.cfa) if learned_offsets else np.zeros(3)
    out = {}
    for split, idx in (("train", scene.train_idx), ("test", scene.test_idx)):
        fit, noise, signal = [], [], []
        for i in idx:
            clean = mean(scene.names[i])  # (H, W) normalised raw, this frame's exposure
            cam = raw.bin2x2(clean, scene.cfa, np.float64) / scene.exposure[i]
            var = truth.binned_noise_var(nt, clean, scene.cfa) / scene.exposure[i] ** 2
            h, w = cam.shape[:2]
            intr = np.asarray(scene.cameras.intrinsics(i), np.float64) * 0.5
            render = eval_run.render_view(structure, params, scene, cfg,
                                          np.asarray(scene.cameras.c2w[i]), intr, h, w)
            low = np.asarray(render["rgb_low"], np.float64) - offset
            fit.append(np.mean((low - cam) ** 2, axis=(0, 1)))
            noise.append(np.mean(var, axis=(0, 1)))
            signal.append(np.mean(cam ** 2, axis=(0, 1)))
        out[split] = {k: np.mean(v, axis=0).tolist() for k, v in
                      (("fit", fit), ("noise", noise), ("signal", signal))}
    out["views"] = len(scene.train_idx)
    return out


def below_one_frame(e: dict) -> float:
    """dB the fit's error lies below one binned frame's noise (all colours)."""
    return float(10 * np.log10(np.sum(e["noise"]) / np.sum(e["fit"])))


def main() -> None:
    ap = common.study_parser(__doc__, "reports/raw_fit")
    ap.add_argument("--variants", default="default,clean_truewhite,fine",
                    help="run folders under runs/<scene>/ to read, where present")
    args = ap.parse_args()
    variants = args.variants.split(",")
    rows, record = [], {}
    for scene in common.scene_names(args.scenes):
        folder = common.scene_dir(scene)
        sim = json.loads((folder / "sim.json").read_text())
        if len(sim.get("illuminants", [None])) > 1 or sim.get("vignetting"):
            print(f"{scene}: skipped (several lights or a lens falloff: no clean raw to "
                  "compare the field with)")
            continue
        found = {v: fit_errors(Path("runs") / scene / v) for v in variants
                 if (Path("runs") / scene / v / "summary.json").exists()}
        if not found:
            print(f"{scene}: no finished run of {', '.join(variants)}; skipped")
            continue
        record[scene] = found
        first = next(iter(found.values()))
        one = first["train"]
        snr = 10 * np.log10(np.sum(one["signal"]) / np.sum(one["noise"]))
        ideal = 10 * np.log10(first["views"])
        cells = [f"{below_one_frame(found[v]['train']):+.1f} / "
                 f"{below_one_frame(found[v]['test']):+.1f}" if v in found else "-"
                 for v in variants]
        rows.append([scene, f"{snr:.1f}", f"{ideal:.1f}", *cells])
        print(" | ".join(rows[-1]), flush=True)
    table = common.markdown_table(
        ["scene", "one frame's raw SNR (dB)", "ideal average of the views (dB)",
         *[f"{v}: train / test views (dB below one frame's noise)" for v in variants]], rows)
    common.write_report(args.out, "# The fit's raw error against one frame's noise\n\n"
                        "`python -m experiments.raw_fit`: the field's binned render against "
                        "the simulator's clean binned raw (module docstring).\n\n" + table
                        + "\n", record)


if __name__ == "__main__":
    main()
