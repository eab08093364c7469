"""Physical darkness sweep: the same scene captured with fewer photons, not a scaled raw.

The paper's sweep (experiments.sweep) scales the raw after capture: signal and every
noise shrink alike, so the data term sees the same fit at another scale. A darker scene
shot with the same camera settings is another fit: the mean green signal drops by
`light`, shot noise by sqrt(light), and the read noise, row noise and the hidden per-CFA
black-level offsets stay as they are in DN, so they grow against the signal (at light
0.1 the simulator's scenes hold 0.7-3 electrons per pixel, where a read noise of
3.5 DN / K ~ 0.6-0.9 e- is no longer small beside the shot noise).

Each scene is simulated at every `light` (`gridnerf simulate <scene> --light f`, folder
data/sim/<scene>_light<f>; light 1 is the scene itself) and trained by the default preset
with the binned raw in every stage and no chroma prior (common.FACTOR_BASE) and the file's
black level (`binned`), where asked with the lens-cap black level (`dark_black`,
`data.black_offset=dark`) or as the default trains, its last stage on the mosaic and the
chroma prior on (`default`); every run estimates its own
bounds. Scored as
`gridnerf eval` scores a run, on the test views: ours, one grey-world gain on the same
field, the paper's 2D row (one frame, non-local means) and the generous per-frame
pipeline (2x2 binning, exposure matched to the reference). The training summary's noise
sigma and data eps (data_term.data_noise, data_term.capped_eps: the 2-sigma cap) are shown where
the run folder is here. Held-out scenes choose nothing; they are reported apart.

    python -m experiments.photons [--scenes bucket,held_deep_hall,held_mixed_toys]
                                  [--lights 0.1,0.25,0.5,1] [--variants binned,dark_black,default]

Writes reports/photons.md, .json and .png.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from experiments import common
from gridnerf.sim import HELDOUT, HELDOUT_MIXED

LIGHTS = (0.1, 0.25, 0.5, 1.0)
# run folder -> overrides of the default preset: the binned data term with the file's
# black level, with the lens-cap one; the default (its last stage on the mosaic, the chroma
# prior on)
VARIANTS = {"binned": common.FACTOR_BASE,
            "dark_black": ["data.black_offset=dark", *common.FACTOR_BASE], "default": []}
# (label, eval summary key) of the outputs compared at each light level
OUTPUTS = (("ours", "gridnerf"), ("global_gw", "global_grey_world"),
           ("denoised_2d", "baseline_denoised"), ("per_frame", "baseline_binned_matched"))
DEFAULT_OUT = "reports/photons"


def measure(scenes: list[str], lights: list[float], variants: list[str], runs: Path,
            quick: bool) -> dict:
    """{scene: {light: {"electrons", variant: {output: {psnr, ssim, delta_e},
    "data_noise", "data_eps"}}}} on the test views, training what is missing."""
    record: dict = {}
    for scene in scenes:
        for light in lights:
            folder = common.scene_dir(scene, quick, light)
            sim = json.loads((folder / "sim.json").read_text())
            cell = {"electrons": float(sim["electrons_mean_green"])}
            for variant in variants:
                m = common.run_variant(str(folder), variant, "default", VARIANTS[variant],
                                       runs, quick)
                got = {out: {k: float(m["summary"][key][k]) for k in ("psnr", "ssim", "delta_e")}
                       for out, key in OUTPUTS}
                path = Path(runs) / folder.name / variant / "summary.json"
                train = json.loads(path.read_text()) if path.is_file() else {}
                got |= {k: train.get(k) for k in ("data_noise", "data_eps")}
                cell[variant] = got
            record.setdefault(scene, {})[f"{light:g}"] = cell
    return record


def _pair(m: dict) -> str:
    return f"{common.fmt(m['psnr'])} / {common.fmt(m['delta_e'])}"


def markdown(record: dict, lights: list[float], variants: list[str], command: str) -> str:
    heads = [f"light {g:g}" for g in lights]
    parts = ["# Physical darkness sweep\n",
             "Each scene simulated with `light` x its photon budget, camera settings "
             "unchanged (read noise and black-level offsets fixed in DN); trained by the "
             "default preset (`binned`: the binned raw in every stage) from its own "
             "estimated bounds. Cells: test-view PSNR / "
             "CIEDE2000. Held-out scenes chose nothing.\n",
             f"Command: `{command}`\n"]
    groups = (("tuned on", [s for s in record if s not in HELDOUT + HELDOUT_MIXED]),
              ("held out", [s for s in record if s in HELDOUT + HELDOUT_MIXED]))
    rows = []
    for label, scenes in groups:
        for scene in scenes:
            by = record[scene]
            get = [by.get(f"{g:g}") for g in lights]
            rows.append([f"{scene} ({label})", "mean green electrons",
                         *[common.fmt(c["electrons"], 1) if c else "-" for c in get]])
            for variant in variants:
                for out, _ in OUTPUTS:
                    if variant != variants[0] and out in ("denoised_2d", "per_frame"):
                        continue  # the 2D rows do not depend on the run's black level
                    rows.append(["", f"{variant}: {out}",
                                 *[_pair(c[variant][out]) if c else "-" for c in get]])
    parts.append(common.markdown_table(["scene", "row", *heads], rows) + "\n")
    lines = []
    for scene, by in record.items():
        for variant in variants:
            cells = []
            for g in lights:
                c = by.get(f"{g:g}", {}).get(variant)
                if not c:
                    cells.append("-")
                    continue
                diff = (f"{c['ours']['psnr'] - c['denoised_2d']['psnr']:+.2f} / "
                        f"{c['ours']['psnr'] - c['global_gw']['psnr']:+.2f}")
                noise = c.get("data_noise")
                eps = c.get("data_eps")
                sig = (f"; eps {eps:.2g} = {eps / noise:.1f} sigma" if noise and eps else "")
                cells.append(diff + sig)
            lines.append([scene, variant, *cells])
    parts.append("Ours minus the 2D row / minus one grey-world gain on the same field (PSNR, "
                 "dB); the data term's eps against the training frames' noise where the run "
                 "folder is here:\n")
    parts.append(common.markdown_table(["scene", "variant", *heads], lines) + "\n")
    return "\n".join(parts)


def plot(record: dict, lights: list[float], variants: list[str], path: Path) -> None:
    plt = common.pyplot()
    fig, axes = plt.subplots(1, len(record), figsize=(3.6 * len(record), 3.2), squeeze=False)
    for ax, (scene, by) in zip(axes[0], record.items(), strict=True):
        got = [(by[f"{g:g}"]["electrons"], by[f"{g:g}"]) for g in lights if f"{g:g}" in by]
        x = [e for e, _ in got]
        for variant in variants:
            ax.plot(x, [c[variant]["ours"]["psnr"] for _, c in got], marker="o",
                    label=f"ours ({variant})")
        ax.plot(x, [c[variants[0]]["denoised_2d"]["psnr"] for _, c in got], marker="s",
                linestyle="--", label="2D: one frame + NLM")
        ax.plot(x, [c[variants[0]]["global_gw"]["psnr"] for _, c in got], marker="^",
                linestyle=":", label="one grey-world gain")
        ax.set_xscale("log")
        ax.minorticks_off()
        ax.set_xticks(x, [f"{e:g}" for e in x])
        ax.set_title(scene, fontsize=9)
        ax.set_xlabel("mean green electrons per pixel")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("test PSNR (dB)")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    common.save_figure(fig, path)


def main() -> None:
    ap = common.study_parser(__doc__, DEFAULT_OUT, scenes="bucket,held_deep_hall,held_mixed_toys",
                             runs=True, quick=True)
    ap.add_argument("--lights", default=",".join(f"{g:g}" for g in LIGHTS))
    ap.add_argument("--variants", default="binned",
                    help="comma-separated, of: " + ", ".join(VARIANTS))
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        raise SystemExit(f"--variants: choose from {', '.join(VARIANTS)}")
    try:
        lights = sorted(float(g) for g in args.lights.split(","))
    except ValueError:
        lights = []
    if not lights or not all(np.isfinite(g) and g > 0 for g in lights):
        raise SystemExit("--lights: positive numbers, e.g. 0.1,0.25,1")
    scenes = common.scene_names(args.scenes)
    record = measure(scenes, lights, variants, Path(args.runs), args.quick)
    command = (f"python -m experiments.photons --scenes {','.join(scenes)} --lights "
               f"{','.join(f'{g:g}' for g in lights)} --variants {','.join(variants)}"
               + (" --quick" if args.quick else "")
               + ("" if Path(args.out) == Path(DEFAULT_OUT) else f" --out {args.out}"))
    text = markdown(record, lights, variants, command)
    common.write_report(args.out, text, {"lights": lights, "variants": variants,
                                         "quick": args.quick, "results": record})
    plot(record, lights, variants, Path(args.out).with_suffix(".png"))
    print(text)


if __name__ == "__main__":
    main()
