"""Where the two low-light gates bind: the lens-cap black level and the downscaled estimates.

For every simulated scene folder under data/sim (the 21 scenes at their own light and any
`<scene>_light<f>` of the physical darkness sweep, experiments/photons.py), as the default
preset's training would see it:
- the weakest colour's mean signal in DN above the file's black level and the share of it
  that an unknown black offset of darkframes.OFFSET_DN (4 DN) would be
  (darkframes.offset_share); above data.lens_cap_share the training takes the lens-cap
  black level (data_term.with_weak_signal_black_level);
- the binned frames' noise sigma over their mean level (colour_target.estimate_downscale's
  ratio) with the file's and with the lens-cap black level, and the downscale the capture's
  illuminant estimates run at on the frames the training uses (loss.ca_noise_ratio).

config.LEGACY keeps both fields at their defaults for runs trained before them, on the
claim that neither binds on a scene at its own light: this table is that claim's check.

    python experiments/dark_gates.py [--scenes all]

Writes reports/dark_gates.md and .json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import common
from gridnerf import colour_target, darkframes, dataset
from gridnerf import config as cfgmod
from gridnerf.scene import load_scene
from gridnerf.sim import ALL_SCENES


def training_frames(scene, cfg: cfgmod.Config):
    """The frames the capture's estimates see (colour_target.estimate_frames of the
    default's training data)."""
    return colour_target.estimate_frames(dataset.training_data(scene, cfg.data), scene)


def measure(folders) -> dict:
    cfg = cfgmod.preset("default")
    record = {}
    for name, folder in folders:
        sim = json.loads((folder / "sim.json").read_text())
        file_scene = load_scene(folder, near_far=tuple(sim["near_far"]))
        dark_scene = darkframes.apply(file_scene, darkframes.measure(folder)["offset_dn"])
        signal = darkframes.signal_dn(file_scene)
        share = darkframes.offset_share(signal)
        gated = darkframes.too_weak(signal, cfg.data.lens_cap_share)
        frames = {"file": training_frames(file_scene, cfg),
                  "dark": training_frames(dark_scene, cfg)}
        ratios = {k: colour_target.noise_ratio(f) for k, f in frames.items()}
        d = colour_target.estimate_downscale(frames["dark" if gated else "file"],
                                             cfg.loss.ca_noise_ratio)
        record[name] = {"light": float(sim.get("light", 1.0)),
                        "electrons": float(sim["electrons_mean_green"]),
                        "weakest_dn": float(np.min(signal)),
                        "offset_share": share, "lens_cap": bool(gated),
                        "noise_ratio": ratios, "downscale": d}
        print(name, record[name], flush=True)
    return record


def markdown(record: dict, command: str) -> str:
    cfg = cfgmod.preset("default")
    rows = [[name, f"{r['light']:g}", common.fmt(r["electrons"], 1),
             common.fmt(r["weakest_dn"], 1), common.fmt(r["offset_share"]),
             "yes" if r["lens_cap"] else "no", common.fmt(r["noise_ratio"]["file"]),
             common.fmt(r["noise_ratio"]["dark"]), str(r["downscale"])]
            for name, r in record.items()]
    own = [r for r in record.values() if r["light"] == 1.0]
    summary = ""
    if own:
        summary = (f"At their own light ({len(own)} scenes): offset share at most "
                   f"{max(r['offset_share'] for r in own):.2f} (gate "
                   f"{cfg.data.lens_cap_share:g}), noise ratio at most "
                   f"{max(max(r['noise_ratio'].values()) for r in own):.2f} with either black "
                   f"level (gate {cfg.loss.ca_noise_ratio:g}).\n\n")
    return ("# Low-light gates\n\nThe lens-cap black level (`data.lens_cap_share`) and the "
            "downscaled illuminant estimates (`loss.ca_noise_ratio`), scene by scene, as the "
            "default preset trains.\n\n" + f"Command: `{command}`\n\n" + summary
            + common.markdown_table(
                ["scene", "light", "mean green e-", "weakest colour (DN)", "offset share",
                 "lens-cap black", "noise / level (file)", "noise / level (lens cap)",
                 "estimate downscale"], rows) + "\n")


def main() -> None:
    ap = common.study_parser(__doc__, "reports/dark_gates")
    args = ap.parse_args()
    wanted = set(common.scene_names(args.scenes, tuple(common.GROUPS)))
    folders = [(p.name, p) for p in sorted(Path("data/sim").iterdir())
               if (p / "sim.json").is_file()
               and (p.name in wanted or p.name.split("_light")[0] in wanted)
               and p.name.split("_light")[0] in ALL_SCENES]
    missing = sorted(wanted - {name for name, _ in folders})
    if missing:
        print(f"skipping {', '.join(missing)}: simulate them first (gridnerf simulate NAME)")
    record = measure(folders)
    command = f"python experiments/dark_gates.py --scenes {args.scenes}"
    text = markdown(record, command)
    common.write_report(args.out, text, record)
    print(text)


if __name__ == "__main__":
    main()
