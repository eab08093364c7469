"""Each camera quirk alone: its cost, before and after the trainer handles it.

The held-out quirky-camera scenes carry every quirk at once. Here one clean capture (by
default held_arc_brick, held_quirk_brick's twin) is shot again with one quirk at a time
(the clean camera changed by SensorParams fields; geometry, light, photon budget and every
random draw the twin's) and trained with the default preset on the binned raw in every
stage (common.FACTOR_BASE, as the runs measured) twice:

- after: the trainer as it is;
- before: its handling of that quirk switched off for the run (hot pixels: no defect map,
  so they stay in the data term and the colour estimates; lens falloff: no estimate from
  the frames; exposure jitter: every frame taken at the median exposure; a converter's
  falloff opcode: not applied, and no estimate either; its crop and orientation stay, as
  the frames must match transforms.json). A CFA layout and a bit depth are read from the
  files: they have no "before".

Rows: test-view PSNR / CIEDE2000 of the default output, the twin's kept result beside
them. Writes reports/quirk_effects.md/.json; each run is kept under
runs/<scene>+<quirk>/{after,before}, its numbers in reports/quirk_runs.json (both share the
default config, so they are kept apart from reports/results.json, whose entries are one per
config).

    python -m experiments.quirk_effects [--scenes held_arc_brick] [--quirks vignette,hot]
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import replace
from pathlib import Path
from unittest import mock

import numpy as np

from experiments import common
from gridnerf import config as cfgmod
from gridnerf.eval_run import evaluate_run
from gridnerf.sim import converter, simulate_scene, writer
from gridnerf.sim import scenes as sc
from gridnerf.train import train

# quirk: (SensorParams changes, what "before" switches off or None); the strengths are the
# quirky-camera group's
QUIRKS = {
    "cfa": ({"cfa_pattern": "BGGR"}, None),
    "bits": ({"bits": 12}, None),
    "vignette": ({"vignette_stops": 1.2}, "falloff"),
    "jitter": ({"exposure_jitter_stops": 1.0 / 3.0}, "exposure"),
    "hot": ({"hot_pixels": 20}, "defects"),
    # a converter's file: the falloff's FixVignetteRadial opcode, a default crop and the
    # frames stored upside down (Orientation 3)
    "converter": ({"vignette_stops": 1.2, "converter": converter.ConverterTags(
        crop_margin=(8, 6, 8, 6), orientation=3, vignette_opcode=True)}, "opcode"),
}


def shoot(scene: str, quirk: str) -> Path:
    """data/quirks/<scene>+<quirk>: the scene shot with that quirk alone."""
    spec = sc.build_scene(scene)
    spec = replace(spec, sensor=replace(spec.sensor, **QUIRKS[quirk][0]))
    with mock.patch.object(writer, "build_scene", lambda name, spec=spec: spec):
        return simulate_scene(scene, Path("data/quirks") / f"{scene}+{quirk}")


@contextlib.contextmanager
def handling_off(what: str | None):
    """The trainer with its handling of one quirk switched off (module docstring)."""
    from gridnerf import defects, raw_layout
    from gridnerf import scene as scene_mod
    from gridnerf import train as train_mod

    with contextlib.ExitStack() as stack:
        if what == "defects":
            stack.enter_context(mock.patch.object(
                defects, "defective_pixels", lambda frames: (None, "")))
        if what in ("falloff", "opcode"):
            stack.enter_context(mock.patch.object(
                train_mod, "_vignetting", lambda run, plan, *a, **k: (a[3], plan)))
        if what == "opcode":
            original = raw_layout.display

            def no_opcode(path, raw_bayer, cfa, black_level, white_level, tags, orientation):
                tags = {k: v for k, v in tags.items() if k != "opcodes"}
                return original(path, raw_bayer, cfa, black_level, white_level, tags,
                                orientation)
            stack.enter_context(mock.patch.object(raw_layout, "display", no_opcode))
        if what == "exposure":
            stack.enter_context(mock.patch.object(
                scene_mod, "_relative_exposure", lambda times, isos, names=None:
                np.ones(len(times))))
        yield


# the evaluated runs' numbers, under their config's fingerprint
RUNS = Path("reports/quirk_runs.json")


def run(scene: str, quirk: str, when: str) -> dict:
    """{psnr, delta_e} of the default output on runs/<scene>+<quirk>/<when>."""
    folder = shoot(scene, quirk)
    out = Path("runs") / f"{scene}+{quirk}" / when
    cfg = cfgmod.override(cfgmod.preset("default"), common.FACTOR_BASE)
    key = f"{scene}+{quirk}"
    hit = common.cached_result(key, when, cfg, common.load_results(RUNS))
    if hit is None:
        with handling_off(QUIRKS[quirk][1] if when == "before" else None):
            if not (out / "summary.json").exists():
                train(folder, out, cfg)
            metrics = evaluate_run(out)
        common.record_result(key, when, cfg, metrics, RUNS)
        hit = {"summary": metrics["summary"]}
    m = hit["summary"]["gridnerf"]
    return {"psnr": m["psnr"], "delta_e": m["delta_e"],
            "per_frame": hit["summary"]["baseline_binned_matched"]["psnr"]}


def main() -> None:
    ap = common.study_parser(__doc__, "reports/quirk_effects", scenes="held_arc_brick")
    ap.add_argument("--quirks", default=",".join(QUIRKS), help="comma-separated: "
                    + ", ".join(QUIRKS))
    args = ap.parse_args()
    rows, record = [], {}
    for scene in common.scene_names(args.scenes):
        twin = common.run_variant(scene, "binned", "default",
                                  common.FACTOR_BASE)["summary"]["gridnerf"]
        for quirk in args.quirks.split(","):
            after = run(scene, quirk, "after")
            before = run(scene, quirk, "before") if QUIRKS[quirk][1] else None
            record[f"{scene}+{quirk}"] = {"twin": twin, "after": after, "before": before}
            rows.append([scene, quirk,
                         f"{common.fmt(twin['psnr'])} / {common.fmt(twin['delta_e'])}",
                         "-" if before is None else
                         f"{common.fmt(before['psnr'])} / {common.fmt(before['delta_e'])}",
                         f"{common.fmt(after['psnr'])} / {common.fmt(after['delta_e'])}",
                         common.fmt(after["psnr"] - twin["psnr"]),
                         common.fmt(after["per_frame"])])
            print(" | ".join(rows[-1]), flush=True)
    table = common.markdown_table(
        ["scene", "quirk", "clean twin", "quirk, handling off", "quirk, default",
         "default - twin (dB)", "per-frame pipeline"], rows)
    common.write_report(args.out, "# Camera quirks one at a time\n\n`python -m "
                        "experiments.quirk_effects`; PSNR dB / CIEDE2000 of the test views.\n\n"
                        + table + "\n", json.loads(json.dumps(record, default=float)))


if __name__ == "__main__":
    main()
