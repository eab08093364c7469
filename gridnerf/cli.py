"""`gridnerf` command line: simulate | poses | train | eval | render.

Every user-fixable problem surfaces as one line on stderr naming the file
and the fix, with exit status 2 (see gridnerf.errors).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from gridnerf.errors import GridNerfError


def _simulate(args) -> None:
    from gridnerf.sim import HELDOUT, SCENES, simulate_scene

    names = {"all": SCENES, "heldout": HELDOUT}.get(args.name, (args.name,))
    for name in names:
        if name not in SCENES + HELDOUT:
            fix = f"choose one of {', '.join(SCENES + HELDOUT)}, 'all' or 'heldout'"
            raise GridNerfError(None, f"unknown scene {name!r}", fix)
        out = Path(args.out) if args.out and len(names) == 1 else Path("data/sim") / name
        path = simulate_scene(
            name,
            out,
            width=args.width,
            height=args.height,
            n_frames=args.frames,
            seed=args.seed,
            overwrite=args.overwrite,
        )
        print(f"scene {name}: {path}")


def _poses(args) -> None:
    from gridnerf.poses import estimate_poses

    report = estimate_poses(Path(args.scene), source=args.source)
    print(json.dumps(report, indent=2))


def _train(args) -> None:
    from gridnerf import config as cfgmod
    from gridnerf.train import train

    run = Path(args.out) if args.out else Path("runs") / Path(args.scene).name / args.preset
    if (run / "config.json").exists() and not args.overwrite_config:
        cfg = cfgmod.load(run / "config.json")
        if args.set:
            cfg = cfgmod.override(cfg, args.set)
        print(f"resuming run folder {run} with its saved config.json")
    else:
        cfg = cfgmod.override(cfgmod.preset(args.preset), args.set or [])
    summary = train(Path(args.scene), run, cfg)
    print(json.dumps(summary, indent=2))


def _eval(args) -> None:
    from gridnerf.eval_run import evaluate_run

    metrics = evaluate_run(Path(args.run))
    print(json.dumps(metrics["summary"], indent=2))


def _render(args) -> None:
    from gridnerf.eval_run import render_run

    out = render_run(Path(args.run), path=args.path, n_frames=args.frames)
    print(f"wrote {out}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="gridnerf", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="write a simulated low-light RAW scene")
    s.add_argument("name", help="scene name (bucket, held_arc_brick, ...), 'all' (the nine "
                   "scenes) or 'heldout' (the held-out scenes)")
    s.add_argument("--out", help="scene folder (default data/sim/<name>)")
    s.add_argument("--width", type=int, default=480)
    s.add_argument("--height", type=int, default=270)
    s.add_argument("--frames", type=int, default=24)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--full-hd", action="store_true", help="1920x1080 frames")
    s.add_argument("--overwrite", action="store_true", help="replace an existing scene folder")
    s.set_defaults(func=_simulate)

    s = sub.add_parser("poses", help="estimate camera poses with COLMAP (pycolmap)")
    s.add_argument("scene")
    s.add_argument(
        "--source",
        default="images",
        choices=["images", "raw"],
        help="images/ previews (default) or previews made from the raw frames",
    )
    s.set_defaults(func=_poses)

    s = sub.add_parser("train", help="train a grid on a scene folder (resumes automatically)")
    s.add_argument("scene")
    s.add_argument("--out", help="run folder (default runs/<scene>/<preset>)")
    s.add_argument("--preset", default="default")
    s.add_argument("--set", nargs="*", metavar="SECTION.FIELD=VALUE", help="config overrides")
    s.add_argument(
        "--overwrite-config", action="store_true", help="ignore an existing run's config.json"
    )
    s.set_defaults(func=_train)

    s = sub.add_parser("eval", help="render test views and compute metrics against gt/")
    s.add_argument("run")
    s.set_defaults(func=_eval)

    s = sub.add_parser("render", help="render test views or a camera path (PNG, EXR, mp4)")
    s.add_argument("run")
    s.add_argument("--path", default="spiral", choices=["spiral", "ellipse", "test"])
    s.add_argument("--frames", type=int, default=60)
    s.set_defaults(func=_render)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "full_hd", False):
        args.width, args.height = 1920, 1080
    try:
        args.func(args)
    except GridNerfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
