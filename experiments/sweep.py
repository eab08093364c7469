"""Darkness sweep (the paper's Fig. 6 protocol): train with the raw scaled by gamma.

Bright-NeRF scales the raw after black-level removal, I_gamma = gamma * I_raw, so noise and
signal shrink alike and only the photon budget seems to change; `data.exposure_ratio`
does exactly that (gridnerf.dataset.build). For each scene and gamma in GAMMAS (and the
extreme EXTREME) every method in METHODS is trained and scored on the test views; gamma
1 is the method's ordinary run. Runs are cached in <runs>/<scene>/<method>_gamma<g>
(gamma 1: <runs>/<scene>/<method>), so the sweep can be built in parts. Writes
<out>.md, <out>.json and <out>.png (PSNR and CIEDE2000 against gamma, one line per method
and scene).

Our method is swept as `binned` (the default preset with the binned raw in every stage,
common.FACTOR_BASE: the sweep was measured before the default gained its mosaic stage and
its chroma prior).

    python -m experiments.sweep [--scenes bucket] [--methods binned,llnerf] [--quick]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments.common import (
    FACTOR_BASE,
    fmt,
    markdown_table,
    pyplot,
    run_variant,
    save_figure,
    scene_names,
    study_parser,
    write_report,
)

GAMMAS = (0.3, 0.4, 0.6, 0.8, 1.0, 1.2, 1.5, 1.8)  # the paper's sweep
EXTREME = 0.1
# method -> (preset, eval summary key of its shown output, overrides); the method's name is
# its gamma-1 run folder (llnerf: the report's run; binned: the ablations')
METHODS = {"binned": ("default", "gridnerf", FACTOR_BASE), "llnerf": ("llnerf", "llnerf", [])}
SWEPT = ("binned", "llnerf")  # the report's sweep (--methods' default)
DEFAULT_OUT = "reports/sweep"


def variant(method: str, gamma: float) -> str:
    """The run folder name of a method at gamma (gamma 1: the method's own run)."""
    return method if gamma == 1.0 else f"{method}_gamma{gamma:g}"


def sweep(scenes: list[str], methods: list[str], gammas: list[float], runs: Path,
          quick: bool) -> dict:
    """{method: {scene: {gamma: metrics}}} of the test views, training what is missing."""
    record: dict = {}
    for method in methods:
        preset, key, method_sets = METHODS[method]
        for scene in scenes:
            for g in gammas:
                sets = method_sets + ([] if g == 1.0 else [f"data.exposure_ratio={g:g}"])
                m = run_variant(scene, variant(method, g), preset, sets, runs, quick)
                record.setdefault(method, {}).setdefault(scene, {})[f"{g:g}"] = {
                    k: float(m["summary"][key][k]) for k in ("psnr", "ssim", "delta_e")}
    return record


def markdown(record: dict, gammas: list[float], command: str = "") -> str:
    lines = []
    for method, per_scene in record.items():
        for scene, by_gamma in per_scene.items():
            lines.append([method, scene, *[
                f"{fmt(by_gamma[f'{g:g}']['psnr'])} / {fmt(by_gamma[f'{g:g}']['delta_e'])}"
                if f"{g:g}" in by_gamma else "-" for g in gammas]])
    return ("# Darkness sweep\n\nRaw scaled by gamma after black-level removal (the paper's "
            "protocol); each cell: test-view PSNR / CIEDE2000.\n\n"
            + (f"Command: `{command}`\n\n" if command else "")
            + markdown_table(["method", "scene", *[f"gamma {g:g}" for g in gammas]], lines)
            + "\n")


def plot(record: dict, gammas: list[float], path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for method, per_scene in record.items():
        for scene, by_gamma in per_scene.items():
            gs = [g for g in gammas if f"{g:g}" in by_gamma]
            for ax, metric in zip(axes, ("psnr", "delta_e"), strict=True):
                ax.plot(gs, [by_gamma[f"{g:g}"][metric] for g in gs], marker="o",
                        label=f"{method}, {scene}")
    for ax, label in zip(axes, ("PSNR (dB)", "CIEDE2000"), strict=True):
        ax.set_xscale("log")
        ax.set_xlabel("gamma (raw scale)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def main() -> None:
    ap = study_parser(__doc__, DEFAULT_OUT, scenes="bucket", runs=True, quick=True)
    ap.add_argument("--methods", default=",".join(SWEPT),
                    help="comma-separated, of: " + ", ".join(METHODS))
    ap.add_argument("--gammas", default=",".join(f"{g:g}" for g in (EXTREME, *GAMMAS)))
    args = ap.parse_args()
    methods = [m for m in args.methods.split(",") if m]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise SystemExit(f"unknown method {unknown[0]!r}: choose from {', '.join(METHODS)}")
    gammas = sorted(float(g) for g in args.gammas.split(","))
    if not all(np.isfinite(g) and g > 0 for g in gammas):
        raise SystemExit("--gammas: positive numbers, e.g. 0.1,0.3,1")
    print(build(scene_names(args.scenes), methods, gammas, Path(args.runs),
                args.out, args.quick))


def build(scenes: list[str], methods: list[str], gammas: list[float], runs: Path, out,
          quick: bool) -> str:
    """Train what is missing, write <out>.md, .json and .png; returns the markdown."""
    record = sweep(scenes, methods, gammas, runs, quick)
    command = (f"python -m experiments.sweep --scenes {','.join(scenes)} --methods "
               f"{','.join(methods)} --gammas {','.join(f'{g:g}' for g in gammas)}"
               + (" --quick" if quick else "")
               + ("" if Path(out) == Path(DEFAULT_OUT) else f" --out {out}"))
    text = markdown(record, gammas, command)
    write_report(out, text, {"gammas": gammas, "quick": quick, "results": record})
    plot(record, gammas, Path(out).with_suffix(".png"))
    return text


if __name__ == "__main__":
    main()
