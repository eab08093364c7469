"""`gridnerf` command line: simulate | poses | train | eval | render | view.

Every user-fixable problem surfaces as one line on stderr naming the file
and the fix, with exit status 2 (see gridnerf.errors).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from pathlib import Path

from gridnerf.errors import GridNerfError


def _simulate(args) -> None:
    from gridnerf import sim
    from gridnerf.sim import cycles

    groups = {"all": sim.SCENES, "heldout": sim.HELDOUT, "dev": sim.DEV, "mixed": sim.MIXED,
              "heldmixed": sim.HELDOUT_MIXED, "heldcolour": sim.HELDOUT_COLOUR,
              "heldquirk": sim.HELDOUT_QUIRK, "heldunit": sim.HELDOUT_UNIT,
              "cycles": tuple(cycles.CYCLES)}
    names = groups.get(args.name, (args.name,))
    for name in names:
        if name in cycles.CYCLES:  # path-traced by Blender, at its own size
            out = Path(args.out) if args.out and len(names) == 1 else Path("data/cycles") / name
            path = cycles.simulate_cycles(name, out, n_frames=args.frames, seed=args.seed,
                                          overwrite=args.overwrite)
            print(f"scene {name}: {path}")
            continue
        if name not in sim.ALL_SCENES:
            fix = (f"choose one of {', '.join(sim.ALL_SCENES + tuple(cycles.CYCLES))}, 'all', "
                   "'heldout', 'dev', 'mixed', 'heldmixed', 'heldcolour', 'heldquirk', "
                   "'heldunit' or 'cycles'")
            raise GridNerfError(None, f"unknown scene {name!r}", fix)
        out = (Path(args.out) if args.out and len(names) == 1
               else Path("data/sim") / sim.folder_name(name, args.light))
        path = sim.simulate_scene(
            name,
            out,
            width=args.width,
            height=args.height,
            n_frames=args.frames,
            seed=args.seed,
            overwrite=args.overwrite,
            light=args.light,
        )
        print(f"scene {name}: {path}")


def _poses(args) -> None:
    from gridnerf.poses import estimate_poses

    report = estimate_poses(Path(args.scene), source=args.source)
    print(json.dumps(report, indent=2))


def _distributed(args) -> None:
    """jax.distributed for a run over several processes (hosts); see gridnerf.devices."""
    from gridnerf import devices

    devices.initialize_distributed(devices.distributed_settings(
        args.coordinator, args.num_processes, args.process_id))


def _train(args) -> None:
    from gridnerf import config as cfgmod
    from gridnerf.train import train

    _distributed(args)
    cfg = cfgmod.override(cfgmod.preset(args.preset), args.set or [])
    run = Path(args.out) if args.out else Path("runs") / Path(args.scene).name / args.preset
    summary = train(Path(args.scene), run, cfg, overwrite_config=args.overwrite_config,
                    white_ref=args.white_ref)
    print(json.dumps(summary, indent=2))


def _eval(args) -> None:
    from gridnerf.eval_run import evaluate_run

    metrics = evaluate_run(Path(args.run), refine_poses=args.refine_poses)
    print(json.dumps(metrics["summary"], indent=2))


def _render(args) -> None:
    from gridnerf.eval_run import RenderSettings, render_run
    from gridnerf.look import FORMATS

    formats = tuple(f.strip() for f in args.format.split(",") if f.strip())
    settings = RenderSettings(path=args.path, n_frames=args.frames, views=args.views or "",
                              exposure_stops=args.exposure, white=args.white,
                              scale=args.scale, formats=formats)
    if args.path == "views" and not args.views:
        raise _UsageError("gridnerf render: --path views needs --views FRAME,FRAME[,...]. "
                          "Fix: name at least two frames, e.g. --views frame_000,frame_008")
    bad = [f for f in formats if f not in FORMATS] or ([] if formats else [args.format])
    if bad:
        raise _UsageError(f"gridnerf render: --format {args.format!r} is not a list of "
                          f"{', '.join(FORMATS)}. Fix: e.g. --format png,exr")
    out = render_run(Path(args.run), settings)
    print(f"wrote {out}")


def _view(args) -> None:
    from gridnerf.viewer import write_viewer

    out = write_viewer(Path(args.run), Path(args.out) if args.out else None)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB)")


class _UsageError(Exception):
    """A command-line syntax error (argparse), reported like GridNerfError: one line, status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse would print the usage and exit
        raise _UsageError(f"{self.prog}: {message}. Fix: see `{self.prog} --help`")


def _whole(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not a positive whole number (>= 1)")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"{value} is not a positive finite number")
    return value


_TRAIN_EPILOG = """\
Resuming: a run folder that holds a checkpoint is resumed with the config saved in its
config.json; --preset and --set must give the same config (repeat the original command).
--overwrite-config continues the run with the new config instead, provided it keeps the
model's shapes (grid.resolutions, grid.sh_degree, loss.use_gains); otherwise delete the
run folder or choose another --out. config.json is written once training starts; a
failed start leaves no run folder behind. One training per run folder at a time."""


def build_parser() -> argparse.ArgumentParser:
    from gridnerf.config import PRESETS
    from gridnerf.look import FORMATS, WHITE_HELP

    p = _Parser(prog="gridnerf", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="write a simulated low-light RAW scene")
    s.add_argument("name", help="scene name (bucket, held_arc_brick, mixed_lamp_window, ...), "
                   "'all' (the nine scenes), 'heldout' (the held-out scenes), 'dev' (the tuning "
                   "scenes with an arc and a slide rig), 'mixed' (the mixed-light scenes), "
                   "'heldmixed' (the held-out mixed-light scenes), 'heldcolour' (held-out "
                   "files with a wrong ColorMatrix and lights off the Planckian locus), "
                   "'heldquirk' (held-out scenes re-shot by a quirky camera: another CFA, "
                   "12 or 10 bits, vignetting, exposure jitter, hot pixels) or 'heldunit' "
                   "(a sensor unlike its camera model's reference matrix)")
    s.add_argument("--out", help="scene folder (default data/sim/<name>)")
    s.add_argument("--width", type=_positive_int, default=480)
    s.add_argument("--height", type=_positive_int, default=270)
    s.add_argument("--frames", type=_positive_int, default=24)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--full-hd", action="store_true", help="1920x1080 frames")
    s.add_argument("--overwrite", action="store_true", help="replace an existing scene folder")
    s.add_argument("--light", type=_positive_float, default=1.0,
                   help="photon budget as a fraction of the scene's own, camera settings "
                        "unchanged (a physically darker capture; default folder "
                        "data/sim/<name>_light<f>)")
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

    s = sub.add_parser("train", help="train a grid on a scene folder (resumes automatically)",
                       epilog=_TRAIN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("scene")
    s.add_argument("--out", help="run folder (default runs/<scene>/<preset>)")
    s.add_argument("--preset", default="default",
                   help=f"named config: {', '.join(sorted(PRESETS))} (default: default)")
    s.add_argument("--white-ref", metavar="FRAME:X,Y,W,H",
                   help="a grey card or white patch in one frame (its name, a pixel box) that "
                   "sets the light instead of the estimators; or rgb:R,G,B, a light "
                   "measured elsewhere in camera RGB")
    # extend, not store: a repeated --set adds its overrides instead of replacing the
    # earlier ones (which argparse's default would drop without a word)
    s.add_argument("--set", nargs="*", action="extend", metavar="SECTION.FIELD=VALUE",
                   help="config overrides, e.g. train.steps_per_stage=[100,200]; may be "
                   "repeated (fields: see a run's config.json or gridnerf/config.py)")
    s.add_argument(
        "--overwrite-config", action="store_true",
        help="resume a run with this command's config instead of refusing a config that "
        "differs from the run's config.json (model shapes must stay the same)",
    )
    d = s.add_argument_group(
        "several hosts (jax.distributed; all three on every process, or the environment "
        "variables JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID)")
    d.add_argument("--coordinator", metavar="HOST:PORT",
                   help="address of process 0 and a free port, e.g. 10.0.0.1:12345")
    d.add_argument("--num-processes", type=_whole, metavar="N", help="number of processes")
    d.add_argument("--process-id", type=_whole, metavar="I",
                   help="this process, 0 .. N-1 (0 runs the coordinator)")
    s.set_defaults(func=_train)

    s = sub.add_parser("eval", help="render test views and compute metrics against gt/")
    s.add_argument("run")
    s.add_argument("--refine-poses", action="store_true",
                   help="render each test view at the pose that best explains its own raw "
                   "frame (for poses from `gridnerf poses`: a pose a fraction of a pixel off "
                   "costs dB that are not the field's)")
    s.set_defaults(func=_eval)

    s = sub.add_parser("render", help="render test views or a camera path (PNG, EXR, mp4)")
    s.add_argument("run")
    s.add_argument("--path", default="spiral", choices=["spiral", "ellipse", "test", "views"],
                   help="spiral or ellipse around the capture, the test views, or a path "
                   "through the frames given by --views")
    s.add_argument("--views", metavar="FRAME,FRAME[,...]",
                   help="frames the `views` path passes through, in order")
    s.add_argument("--frames", type=_positive_int, default=60, help="frames of the camera path")
    s.add_argument("--exposure", type=float, default=0.0, metavar="STOPS",
                   help="exposure compensation over the automatic exposure, in stops")
    s.add_argument("--white", default="learned", metavar="WB",
                   help=f"white balance: {WHITE_HELP}")
    s.add_argument("--scale", type=_positive_float, default=1.0,
                   help="output size as a multiple of the capture's (e.g. 0.5, 2)")
    s.add_argument("--format", default=",".join(FORMATS),
                   help="files to write, comma-separated: png (sRGB), exr (linear), "
                   "mp4 (the path as a video)")
    s.set_defaults(func=_render)

    s = sub.add_parser("view", help="write one self-contained HTML file that renders the run "
                       "in a browser (WebGL2: orbit, exposure, white balance)")
    s.add_argument("run")
    s.add_argument("--out", help="HTML file (default <run>/viewer.html)")
    s.set_defaults(func=_view)
    return p


def _one_line(message: str) -> str:
    return " ".join(str(message).split())


def _warning_line(message, category, filename, lineno, line=None) -> str:
    """A warning as the command line shows it: one line, "warning: <message>" (Python's
    default adds the file, line and source of the call that warned)."""
    return f"warning: {message}\n"


# Where Debian and Ubuntu install tcmalloc (libtcmalloc-minimal4), x86-64 and arm64.
TCMALLOC_PATHS = ("/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4",
                  "/usr/lib/aarch64-linux-gnu/libtcmalloc_minimal.so.4")
# set to "system" to keep glibc's malloc
MALLOC_ENV = "GRIDNERF_MALLOC"


def preload_tcmalloc(environ=os.environ, exists=os.path.exists, execve=os.execve) -> bool:
    """Restart this command with tcmalloc preloaded (LD_PRELOAD) where the system has it and
    the process was started without it; returns False where it does not restart.

    JAX's CPU runtime allocates and frees large buffers every step; under glibc's malloc
    that is kernel time (madvise and page faults). The whole `gridnerf train
    data/sim/bucket` took 300 s (182 s of it system time) with glibc's malloc against 187 s
    (5 s) with tcmalloc, one run each on an idle 2-core AMD EPYC machine (docs/speed.md).
    The Makefile preloads it for its own targets; this gives a user who calls `gridnerf`
    directly the same speed. GRIDNERF_MALLOC=system opts out. Only the console command
    restarts (main() without argv): a call of main(argv) from Python never does, and the
    restarted process, whose LD_PRELOAD names tcmalloc, never restarts again."""
    preload = environ.get("LD_PRELOAD", "")
    if environ.get(MALLOC_ENV) == "system" or "tcmalloc" in preload:
        return False
    lib = next((p for p in TCMALLOC_PATHS if exists(p)), None)
    if lib is None:
        return False
    env = {**environ, "LD_PRELOAD": " ".join(x for x in (lib, preload) if x)}
    argv = list(getattr(sys, "orig_argv", None) or [sys.executable, *sys.argv])
    try:
        execve(sys.executable, [sys.executable, *argv[1:]], env)
    except OSError:
        return False
    return True


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        preload_tcmalloc()
    warnings.formatwarning = _warning_line
    try:
        args = build_parser().parse_args(argv)
        if getattr(args, "full_hd", False):
            args.width, args.height = 1920, 1080
        args.func(args)
    except (GridNerfError, _UsageError) as e:
        print(f"error: {_one_line(e)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
