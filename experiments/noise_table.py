"""Fitted vs true sensor noise (Bright-NeRF eq. 7) on every simulated scene.

Per scene, gridnerf.noisefit fits the shot gain K, the read variance and the per-CFA black
offsets from all RAW frames, with the clean mean taken from
- "oracle": the simulator's clean signal, rebuilt exactly from gt/*.exr (noisefit
  .sim_clean_mean; single-light scenes only), or
- "render" (--runs RUN): the trained field runs/<scene>/RUN rendered at every frame's pose
  at full resolution and mosaicked through the CFA (its low-light colour times the frame's
  exposure). Such a field absorbed the offsets into its colour, so the fit takes them from
  the variance and the third moment (mean_includes_offset=True).
- "dark frames": no fit, the scene's two lens-cap frames measured (gridnerf.darkframes:
  mean and spread per CFA position; no light, so no shot gain).
The truth comes from sim.json (noisefit.sim_truth). All figures in DN.

Run: LD_PRELOAD=/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4 \
     .venv/bin/python experiments/noise_table.py [--scenes all] [--runs default]
Writes reports/noise.md and reports/noise.json.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from common import simulated_folders, study_parser, write_report
from gridnerf import noisefit
from gridnerf.sim import HELDOUT_MIXED, MIXED


def render_mean(run: Path):
    """name -> (H, W) normalised-raw mean of that frame from the trained field
    (sensorfit.field_mosaic, as `data.black_offset=fit` training fits against)."""
    from gridnerf.eval_run import load_run
    from gridnerf.sensorfit import field_mosaic

    cfg, scene, structure, params, _ = load_run(run)
    index = {n: i for i, n in enumerate(scene.names)}

    def mean(name: str) -> np.ndarray:
        return field_mosaic(structure, params, scene, cfg, index[name])

    return mean, list(scene.names)


def dark_fit(folder: Path) -> dict:
    """The lens-cap frames' figures (gridnerf.darkframes.measure) as NoiseFit.in_dn gives
    them: black offsets and read variance; no shot gain (no light, no shot noise)."""
    from gridnerf import darkframes

    got = darkframes.measure(folder)
    return {"K_dn_per_electron": None, "read_var_dn2": got["read_sigma_dn"] ** 2,
            "black_offset_dn": got["offset_dn"]}


def _row(name: str, source: str, got: dict, truth: dict) -> str:
    b, tb = np.asarray(got["black_offset_dn"]), np.asarray(truth["black_offset_dn"])
    k = got["K_dn_per_electron"]
    return (f"| {name} | {source} | {'-' if k is None else f'{k:.3f}'} / "
            f"{truth['K_dn_per_electron']:.3f} | {got['read_var_dn2']:.1f} / "
            f"{truth['read_var_dn2']:.1f} | "
            + " ".join(f"{v:+.2f}" for v in b.ravel()) + " / "
            + " ".join(f"{v:+.2f}" for v in tb.ravel())
            + f" | {np.abs(b - tb).max():.2f} |")


def main() -> None:
    ap = study_parser(__doc__, "reports/noise")
    ap.add_argument("--runs", default=None, help="also fit with renders of runs/<scene>/RUN")
    args = ap.parse_args()
    rows, record = [], {}
    for name, folder in simulated_folders(args.scenes):
        truth = noisefit.sim_truth(folder)
        fits = {}
        if name not in MIXED + HELDOUT_MIXED:
            fits["oracle"] = noisefit.fit_scene(folder, noisefit.sim_clean_mean(folder))
        run = Path("runs") / name / (args.runs or "")
        if args.runs and (run / "summary.json").exists():
            mean, frames = render_mean(run)
            fits["render"] = noisefit.fit_scene(folder, mean, frames, mean_includes_offset=True)
        for source, (fit, scale) in fits.items():
            got = fit.in_dn(scale)
            record.setdefault(name, {})[source] = {**got, "converged": fit.converged,
                                                   "k_identified": fit.k_identified}
            rows.append(_row(name, source, got, truth))
            print(rows[-1], flush=True)
        if (folder / "dark").is_dir():
            record.setdefault(name, {})["dark"] = got = dark_fit(folder)
            rows.append(_row(name, "dark frames", got, truth))
            print(rows[-1], flush=True)
        record.setdefault(name, {})["truth"] = truth
    head = ("| scene | mean from | K DN/e- fit / true | read var DN^2 fit / true | "
            "black offsets DN (R G / G B positions) fit / true | max offset error |\n"
            "|---|---|---|---|---|---|")
    write_report(
        args.out,
        "Sensor noise fitted from the frames (eq. 7: Var = K mu + read variance, E = mu + "
        "per-CFA black offset) against the simulator's values, "
        f"`python experiments/noise_table.py{' --runs ' + args.runs if args.runs else ''}`. "
        "Read variance includes row noise and rounding; offsets in CFA order "
        "(0,0) (0,1) (1,0) (1,1).\n\n" + "\n".join([head, *rows]) + "\n", record)


if __name__ == "__main__":
    main()
