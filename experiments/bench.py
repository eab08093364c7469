"""Speed and scale benchmark: writes <out>/results.json and <out>/results.md.

Every figure is measured on the package's own code, in its own process, and cached:

- training step throughput of a finished run of the preset at its final-stage grid
  (optim.make_step built as train.py builds it, lowered and compiled once, then the median
  of several timed steps after warm-up): rays/s, and occupied samples shaded per second
  (min(n_occupied, max_samples) per ray from render.render_rays on the same batches);
- the same step on a dense reference: every vertex of the same grid resolution and box kept
  (grid.init_grid), render.skip_empty = false (every candidate sample shaded), same gather;
  the sparsity gain is the ratio of the two, measured in the same benchmark;
- JIT compile time of the training step (jax's lower + compile of that step);
- time to reach within 0.5 dB of the preset's final test PSNR: one `gridnerf train` process
  checkpointing every `snapshot_every` steps (train.checkpoint_every; training is otherwise
  identical, so it also checkpoints every gridnerf.train.CHECKPOINT_SECONDS), each
  checkpoint hard-linked as it appears and scored afterwards on the test
  views exactly as `gridnerf eval` scores a run (eval_run.run_outputs, eval_run.render_view,
  exposure.to_display, evaluate.image_metrics PSNR); the time is the checkpoint file's
  mtime since the process started (imports, bounds estimation, compiles, carving and the
  extra checkpoint writes included);
- render time of one test view at the small and the large image size (render.render_image
  via eval_run.render_view, after a compiling first call, median of a few);
- peak resident memory (the child's ru_maxrss from os.wait4) of the whole training at the
  small (480x270) and the large (1920x1080) image size, one process each;
- the whole training of a second built-in scene at the small size with the detail rule on
  (grid.detail_width=288, off by default), one that it refines (a 288-wide last stage;
  FULL["refined"]): the option's time on such a scene;
- scaling: step throughput and the step process's peak memory at three grid resolutions
  (the final grid resampled by grid.resample to 0.5x, 1x and 1.5x per axis) and at the two
  image sizes (the large one from its own 1920x1080 training run).

Every record carries the machine (cores, CPU model, jax version, platform, load average)
and the command that produced it. Results are cached per item in <out>/cache/<item>-<key>.json,
keyed by the item and its configuration (a training's by a hash of every field of the config it
trains, so a changed preset or default measures again); a re-run reuses them (`--fresh`
measures again).
Timings taken while other processes use the CPU are not comparable: check load_average.
The full run (`--out bench`) also writes its tables into docs/speed.md between the bench
markers and its markdown as reports/bench.md (appended by experiments.report).

    LD_PRELOAD=/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4 \\
        .venv/bin/python -m experiments.bench [--quick] [--out bench] [--scene bucket]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import inspect
import json
import math
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from experiments.common import (
    DETAIL_ON,
    SPEED_DOC,
    fmt,
    markdown_table,
    update_doc,
    write_report,
)
from gridnerf import atomic
from gridnerf import config as cfgmod
from gridnerf import plan as planmod

HERE = Path(__file__).resolve()
REPO = HERE.parent.parent

# Sizes and settings of the full benchmark and of the quick smoke run (tests/test_bench.py).
FULL = {
    "preset": "default", "sets": [], "small": (480, 270), "large": (1920, 1080), "frames": 24,
    "grid_scales": (0.5, 1.0, 1.5), "warmup": 3, "steps": 10, "render_repeats": 3,
    "snapshot_every": 100, "psnr_window_db": 0.5, "jobs": 1,
    # a second built-in scene, trained whole at the small size with the detail rule on
    # (grid.detail_width=288, off by default), which refines it (its 96-wide stage reads
    # 6.0 +- 0.1 over 1 at 480x270: a 288-wide last stage; bucket, 0.84, would keep 192):
    # the option's cost on such a scene
    "refined": "deer",
}
# quick: one stage (one compile, no carving), two items at a time, XLA's CPU optimisation
# off (halves compile time; its timings mean nothing, it checks that every figure comes out)
QUICK_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
QUICK = {
    "preset": "tiny", "sets": ["grid.resolutions=[[16,16,8]]", "train.steps_per_stage=[8]"],
    "small": (96, 54), "large": (128, 72), "frames": 6, "grid_scales": (0.5, 1.0, 1.5),
    "warmup": 1, "steps": 2, "render_repeats": 1, "snapshot_every": 4, "psnr_window_db": 0.5,
    "jobs": 2, "refined": None,  # None: the quick scene again (the item's plumbing only)
}
# Targets on a 2-core CPU: (label, summary field, comparison, goal, unit)
TARGETS = [
    ("training throughput, default preset, final grid", "train_rays_per_s", ">=", 150_000,
     "rays/s"),
    ("within 0.5 dB of the final test PSNR (480x270, 24 frames)", "time_to_psnr_window_s",
     "<=", 180, "s"),
    # the whole `gridnerf train` process (loading, bounds, colour maps, training)
    ("480x270, 24 frames: whole training", "train_small_wall_s", "<=", 180, "s"),
    ("480x270, 24 frames, grid.detail_width=288 on a scene it refines: whole training",
     "train_refined_wall_s", "<=", 180, "s"),
    ("1920x1080, 24 frames: whole training", "train_large_wall_s", "<=", 900, "s"),
    ("1920x1080, 24 frames: peak memory of training", "train_large_peak_rss_gb", "<=", 8.0,
     "GB"),
    ("render of one 480x270 view", "render_small_s", "<=", 1.0, "s"),
]


# ---------------------------------------------------------------------------------------
# machine record and subprocesses


def machine() -> dict:
    """Where a measurement ran: cores, CPU model (/proc/cpuinfo), memory, jax version and
    backend, tcmalloc preload, XLA_FLAGS, load average and the git commit."""
    import jax

    model = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    try:
        kib = int(Path("/proc/meminfo").read_text().split("MemTotal:")[1].split()[0])
        mem_gb = round(kib * 1024 / 1e9, 1)
    except (OSError, IndexError, ValueError):
        pass
    git = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                         capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain",
                            "--untracked-files=no"], capture_output=True, text=True)
    return {
        "cores": os.cpu_count(), "usable_cores": len(os.sched_getaffinity(0)),
        "cpu_model": model, "memory_gb": mem_gb,
        "platform": f"{platform.system()} {platform.release()} {platform.machine()}",
        "python": platform.python_version(), "jax_version": jax.__version__,
        "jax_backend": jax.default_backend(), "device_count": jax.device_count(),
        "device_kind": jax.devices()[0].device_kind,
        "tcmalloc": "tcmalloc" in os.environ.get("LD_PRELOAD", ""),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "git_commit": git.stdout.strip() or None, "git_dirty": bool(dirty.stdout.strip()),
    }


def run_measured(cmd: list[str], log: Path, stdout=None, on_poll=None) -> dict:
    """Run `cmd` (cwd: the repository) to completion: wall seconds and the child's own peak
    RSS (os.wait4's ru_maxrss, KiB on Linux). on_poll() is called every 20 ms meanwhile.
    RuntimeError naming the log if the command fails."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "ab") as err:
        err.write(f"\n$ {' '.join(cmd)}\n".encode())
        err.flush()
        t0 = time.time()
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=stdout or err, stderr=err)
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if on_poll is not None:
                on_poll()
            time.sleep(0.02)
        wall = time.time() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
    if on_poll is not None:
        on_poll()
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:4])} ... failed with status {proc.returncode}; "
                           f"see {log}")
    return {"wall_s": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0, "t_start": t0,
            "cpu_s": usage.ru_utime + usage.ru_stime,
            "command": " ".join(cmd)}


def run_worker(kind: str, args: dict, log: Path) -> dict:
    """One measurement in a fresh process (this module with --worker, run from the
    repository): its JSON result, plus the process's wall time and peak RSS."""
    out = log.with_suffix(".out.json")
    cmd = [sys.executable, "-m", "experiments.bench", "--worker", kind, json.dumps(args),
           str(out)]
    proc = run_measured(cmd, log)
    result = json.loads(out.read_text())
    out.unlink()
    return {**result, "process_wall_s": proc["wall_s"], "process_cpu_s": proc["cpu_s"],
            "peak_rss_mb": proc["peak_rss_mb"],
            "command": proc["command"]}


# ---------------------------------------------------------------------------------------
# workers: each runs in its own process (python -m experiments.bench --worker KIND ...)


def _training_setup(run: str, scale: float, dense: bool, sets: list[str]):
    """The final stage of a finished run as train.py runs it: (cfg, step plan, structure,
    params, opt_state, step function, data, near_t, far_t). The step is rebuilt from the
    run's plan (plan.json: its eps, opacity, colour, candidate count and slots; the method's
    training data and L_ca inputs as training made them). scale != 1 resamples the grid
    (grid.resample) to round(scale * resolution) vertices per axis; dense replaces it by a
    full grid of that resolution and box (grid.init_grid) and turns off empty skipping;
    either way the step's candidate count and occupied-sample slots are fitted to the new grid
    (stages.fitted_candidates, stages.fitted_samples)."""

    from gridnerf import config as cfgmod
    from gridnerf import dataset, eval_run, grid, methods, optim, stages, train, vignetting

    cfg, plan, scene, structure, params, _ = eval_run.load_run(Path(run))
    cfg = cfgmod.override(cfg, sets)
    method = methods.get(cfg.loss.method)
    data = method.training_data(scene, cfg)
    data, _ = method.plan_colour(data, scene, cfg, plan.colour)  # the L_ca inputs
    stage = len(cfg.train.steps_per_stage) - 1
    # the last stage's data as training fits it: the raw mosaic where the plan says so
    data = train.stage_data(vignetting.apply(data, plan.vignetting), scene, cfg, method,
                            plan, stage)
    near_t, far_t = dataset.grid_box(scene)[2:]
    res = tuple(max(2, int(round(r * scale))) for r in structure.resolution)
    changed = dense or res != tuple(structure.resolution)
    if dense:
        structure, params = grid.init_grid(
            res, structure.bbox_min, structure.bbox_max, sh_degree=structure.sh_degree,
            color_scale=structure.color_scale)
        cfg = cfgmod.override(cfg, ["render.skip_empty=false"])
    elif changed:
        structure, params = grid.resample(structure, params, res)
    structure = grid.update_occupancy(structure, params)
    tx = optim.make_optimizer(cfg, cfg.train.steps_per_stage[-1], stage)
    step = optim.step_plan(cfg, plan, stage, scene)  # the last stage's
    if changed:  # the candidates and the slots fitted to the new grid, as a stage fits them
        n_cand = stages.fitted_candidates(structure, data, near_t, far_t, cfg.render)
        asked = cfgmod.override(cfgmod.load(Path(run) / "config.json"), sets).render
        step = dataclasses.replace(step, n_candidates=n_cand, max_samples=stages.fitted_samples(
            structure, data, near_t, far_t, asked, n_cand))
        cfg = dataclasses.replace(cfg, render=dataclasses.replace(
            cfg.render, max_samples=step.max_samples))
    step_fn = optim.make_step(cfg, step, tx, near_t, far_t)
    return cfg, step, structure, params, tx.init(params), step_fn, data, near_t, far_t


def worker_step(a: dict) -> dict:
    """Throughput of the training step: compile time, median step time, rays/s and the
    occupied samples shaded per ray (from render.render_rays on the timed batches)."""
    import jax
    import numpy as np

    from gridnerf import dataset, render

    cfg, step_plan, structure, params, opt_state, step, data, near_t, far_t = _training_setup(
        a["run"], a["scale"], a["dense"], a["sets"])
    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    lowered = step.lower(params, opt_state, structure, data, key)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    times, keys = [], []
    for i in range(a["warmup"] + a["steps"]):
        k = jax.random.PRNGKey(i + 1)
        s = time.perf_counter()
        params, opt_state, loss, _ = compiled(params, opt_state, structure, data, k)
        jax.block_until_ready((params, opt_state, loss))
        if i >= a["warmup"]:
            times.append(time.perf_counter() - s)
            keys.append(k)
    if not np.isfinite(float(loss)):
        raise SystemExit(f"the step's loss is {float(loss)}")
    # n_occupied of the step's own batches and sample offsets (optim.make_step: kb, kl =
    # split(key); loss_fn renders with k0 = split(kl)[0]; render.render_rays marches with
    # it), on the last parameters' occupancy: render.march alone, as render_rays calls it
    march = jax.jit(render.march, static_argnames=("cfg", "n_cand"))
    n_occ = []
    for k in keys:
        kb, kl = jax.random.split(k)
        rays = dataset.batch(data, kb, cfg.train.batch_patches, cfg.train.patch_size)
        out = march(structure, rays["origins"].reshape(-1, 3),
                    rays["directions"].reshape(-1, 3), near_t, far_t, cfg=cfg.render,
                    key=jax.random.split(kl)[0], n_cand=step_plan.n_candidates)
        n_occ.append(np.asarray(out[3]))
    n_occ = np.concatenate(n_occ)
    n_cand = render.n_candidates(structure, cfg.render, step_plan.n_candidates)
    slots = min(cfg.render.max_samples, n_cand) if cfg.render.skip_empty else n_cand
    shaded = np.minimum(n_occ, slots)
    sec = float(np.median(times))
    n_rays = cfg.train.batch_patches * cfg.train.patch_size**2
    return {
        "resolution": list(structure.resolution), "rows": int(structure.n_rows),
        "occupied_fraction": structure.n_rows / float(np.prod(structure.resolution)),
        "skip_empty": cfg.render.skip_empty, "candidates_per_ray": n_cand,
        "slots_per_ray": slots, "rays_per_step": n_rays,
        "trace_s": t1 - t0, "compile_s": t2 - t1, "step_s": times, "step_s_median": sec,
        "rays_per_s": n_rays / sec,
        "occupied_samples_per_ray": float(shaded.mean()),
        "samples_per_s": n_rays * float(shaded.mean()) / sec,
        "slots_per_s": n_rays * slots / sec,
        "truncated_ray_fraction": float(np.mean(n_occ > slots)),
        "loss": float(loss),
        "worker_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def worker_render(a: dict) -> dict:
    """Seconds to render one test view at each size (render.render_image through
    eval_run.render_view): the first call (compiles) and the median of the repeats."""
    import numpy as np

    from gridnerf import eval_run

    cfg, _, scene, structure, params, _ = eval_run.load_run(Path(a["run"]))
    cams, i = scene.cameras, int(scene.test_idx[0])
    out = {}
    for w, h in a["sizes"]:
        f = w / float(cams.width)
        intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]]) * f
        times = []
        for _ in range(1 + a["repeats"]):
            t0 = time.perf_counter()
            img = eval_run.render_view(structure, params, scene, cfg, cams.c2w[i], intr, h, w)
            times.append(time.perf_counter() - t0)
        if not np.all(np.isfinite(img["rgb_low"])):
            raise SystemExit("the render is not finite")
        out[f"{w}x{h}"] = {"first_s": times[0], "s": times[1:],
                           "median_s": float(np.median(times[1:])), "rays": w * h}
    return out


def worker_psnr(a: dict) -> dict:
    """Test-view PSNR of each checkpoint snapshot, scored as gridnerf eval scores a run."""
    import numpy as np

    from gridnerf import eval_run, evaluate, runfolder

    cfg, plan, scene, *_ = eval_run.load_run(Path(a["run"]))
    cams, ds = scene.cameras, cfg.data.eval_downscale
    h, w = cams.height // ds, cams.width // ds
    gts = {i: eval_run.reference_linear(scene, scene.names[i], h, w) for i in scene.test_idx}
    scores = []
    for snap in a["snapshots"]:
        structure, params, _, header = runfolder.load_state(Path(snap))
        main = eval_run.run_outputs(cfg, plan, scene, structure, params)[
            eval_run.main_output(cfg)]
        psnr = []
        for i, gt in gts.items():
            intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]]) / ds
            out = eval_run.render_view(structure, params, scene, cfg, cams.c2w[i], intr, h, w)
            pred_linear, _ = main.show(out)
            psnr.append(evaluate.image_metrics(pred_linear, gt)["psnr"])
        scores.append({"snapshot": snap, "stage": header["stage"], "step": header["step"],
                       "train_seconds": header["train_seconds"],
                       "psnr": float(np.mean(psnr))})
    return {"scores": scores}


WORKERS = {"step": worker_step, "render": worker_render, "psnr": worker_psnr}


# ---------------------------------------------------------------------------------------
# items: cached measurements


def train_spec(scene: Path, preset: str, sets: list[str], run: Path) -> dict:
    """The cache key's configuration of a training item: the scene, the preset and its
    --set overrides, and every field of the config they make, so a changed preset or
    default trains (and measures) again instead of reading a measurement of what it no
    longer trains. Not common.fingerprint: that leaves out a field of cfgmod.ADDED_FIELDS
    at the value that trains a kept result as before, and a new field may still change
    what a capture the kept results do not cover trains (grid.voxel_pixels at
    1920x1080). The steps of an appended stage are fixed in code (plan.APPENDED_STEPS),
    so they join the key too, as do the footprint its TVs are scaled by
    (plan.TV_FOOTPRINT) and the code of the rules that scale them (plan.appended_tv_ref,
    plan.configured_tv)."""
    trained = cfgmod.override(cfgmod.preset(preset), sets)
    blob = json.dumps({"config": cfgmod.to_dict(trained),
                       "appended_steps": list(planmod.APPENDED_STEPS),
                       "tv_footprint": planmod.TV_FOOTPRINT,
                       "tv_rules": [inspect.getsource(f) for f in (planmod.appended_tv_ref,
                                                                   planmod.configured_tv)]},
                      sort_keys=True, default=str)
    return {"scene": str(scene), "preset": preset, "sets": list(sets),
            "config": hashlib.sha256(blob.encode()).hexdigest()[:16], "run": str(run)}


class Bench:
    def __init__(self, out: Path, cfg: dict, fresh: bool, quick: bool, scene: str,
                 folder: Path | None = None):
        """folder: an existing scene folder to train on at any size (experiments.speed);
        None: the built-in `scene`, simulated at the sizes of cfg."""
        self.out, self.cfg, self.fresh, self.quick, self.scene = out, cfg, fresh, quick, scene
        self.folder = folder
        self.items: dict[str, dict] = {}

    def _path(self, name: str, spec: dict) -> Path:
        key = hashlib.sha1(json.dumps({"item": name, **spec}, sort_keys=True).encode())
        return self.out / "cache" / f"{name}-{key.hexdigest()[:12]}.json"

    def cached(self, name: str, spec: dict) -> dict | None:
        path = self._path(name, spec)
        if self.fresh or not path.is_file():
            return None
        return {**json.loads(path.read_text()), "cached": True}

    def item(self, name: str, spec: dict, measure, force: bool = False) -> dict:
        """The cached result of item `name` with configuration `spec`, or measure() it now
        (then stored with the machine record, the spec and the time); force: measure."""
        if name in self.items and not force:
            return self.items[name]
        result = None if force else self.cached(name, spec)
        if result is None:
            print(f"[bench] measuring {name} ...", flush=True)
            before = machine()
            t0 = time.time()
            result = measure()
            result.update(item=name, spec=spec, machine=before, cached=False,
                          load_average_after=[round(x, 2) for x in os.getloadavg()],
                          measured_at=time.strftime("%Y-%m-%dT%H:%M:%S"),
                          item_wall_s=time.time() - t0)
            path = self._path(name, spec)
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic.write_text(path, json.dumps(result, indent=2) + "\n")
            print(f"[bench] {name}: done in {result['item_wall_s']:.0f} s", flush=True)
        else:
            print(f"[bench] {name}: cached ({result['measured_at']})", flush=True)
        self.items[name] = result
        return result

    def log(self, name: str) -> Path:
        return self.out / "logs" / f"{name}.log"

    # -- scenes and training runs ------------------------------------------------------

    def scene_dir(self, size, name: str | None = None) -> Path:
        """The folder of built-in scene `name` (default: the bench's scene) at `size`."""
        if self.folder is not None:
            return self.folder
        w, h = size
        name = name or self.scene
        base = self.out / "scenes" if self.quick else REPO / "data" / "sim"
        return base / (name if (w, h) == (480, 270) and not self.quick else f"{name}_{w}x{h}")

    def simulate(self, tag: str, size, name: str | None = None) -> Path:
        name = name or self.scene
        folder = self.scene_dir(size, name)
        if self.folder is not None:
            return folder
        spec = {"scene": name, "size": list(size), "frames": self.cfg["frames"],
                "folder": str(folder)}

        def measure():
            existed = (folder / "sim.json").is_file()
            cmd = [sys.executable, "-m", "gridnerf.cli", "simulate", name, "--out",
                   str(folder), "--width", str(size[0]), "--height", str(size[1]),
                   "--frames", str(self.cfg["frames"])]
            r = run_measured(cmd, self.log(f"simulate_{tag}"))
            # an existing complete scene is reused by the simulator: no simulation time then
            return {"folder": str(folder), "already_simulated": existed,
                    "simulate_wall_s": None if existed else r["wall_s"],
                    "command": r["command"]}

        r = self.item(f"simulate_{tag}", spec, measure)
        if not (folder / "sim.json").is_file():  # cached, but the folder is gone
            r = self.item(f"simulate_{tag}", spec, measure, force=True)
        return Path(r["folder"])

    def train(self, tag: str, size, snapshots: bool, need_run: bool,
              name: str | None = None, extra: tuple[str, ...] = ()) -> dict:
        """A whole `gridnerf train` of the preset on built-in scene `name` (default: the
        bench's) at `size`, in its own process (wall time, peak RSS); with `snapshots`,
        every checkpoint is hard-linked to <run>/snapshots/NNN/checkpoint.npz as it appears.
        need_run: the run folder must exist (a cached result whose folder is gone is
        measured again); extra: --set overrides on top of the bench's. Runs other than
        "small" and "large" get the tag in their folder."""
        scene = self.simulate(tag, size, name)
        run = self.out / "runs" / (f"{name or self.scene}_{size[0]}x{size[1]}"
                                   + ("" if tag in ("small", "large") else f"_{tag}"))
        sets = [*self.cfg["sets"], *extra]
        if snapshots:
            sets += [f"train.checkpoint_every={self.cfg['snapshot_every']}"]
        spec = train_spec(scene, self.cfg["preset"], sets, run)

        def measure():
            shutil.rmtree(run, ignore_errors=True)  # never resume: time the whole training
            snap_dir, seen, snaps = run / "snapshots", set(), []

            def grab():
                ck = run / "checkpoint.npz"
                try:
                    if os.stat(ck).st_ino in seen:
                        return
                    d = snap_dir / f"{len(snaps):03d}"
                    d.mkdir(parents=True, exist_ok=True)
                    os.link(ck, d / "checkpoint.npz")  # the inode os.replace put there
                except FileNotFoundError:
                    return
                st = os.stat(d / "checkpoint.npz")
                if st.st_ino in seen:  # replaced between the stat and the link
                    shutil.rmtree(d)
                    return
                seen.add(st.st_ino)
                snaps.append({"dir": str(d), "mtime": st.st_mtime})

            cmd = [sys.executable, "-m", "gridnerf.cli", "train", str(scene), "--out", str(run),
                   "--preset", self.cfg["preset"], "--set", *sets]
            r = run_measured(cmd, self.log(f"train_{tag}"), on_poll=grab if snapshots else None)
            summary = json.loads((run / "summary.json").read_text())
            tc = json.loads((run / "config.json").read_text())["train"]
            rays = sum(tc["steps_per_stage"]) * tc["batch_patches"] * tc["patch_size"] ** 2
            for s in snaps:
                s["wall_s"] = s.pop("mtime") - r["t_start"]
            return {"run": str(run), "scene": str(scene), "image": list(size),
                    "wall_s": r["wall_s"], "cpu_s": r["cpu_s"], "peak_rss_mb": r["peak_rss_mb"],
                    "train_seconds": summary["train_seconds"],
                    "run_rays_per_s": rays / summary["train_seconds"],
                    "final_resolution": summary["resolution"],
                    "occupied_fraction": summary["occupied_fraction"],
                    "snapshots": snaps, "command": r["command"], "id": time.time()}

        name = f"train_{tag}"
        result = self.item(name, spec, measure)
        if need_run and not (run / "summary.json").is_file():  # cached, but the run is gone
            result = self.item(name, spec, measure, force=True)
        return result

    # -- measurements on a trained run -------------------------------------------------

    def step_spec(self, run: dict, scale: float, dense: bool) -> dict:
        return {"run": run["run"], "run_id": run["id"], "scale": scale, "dense": dense,
                "sets": self.cfg["sets"], "warmup": self.cfg["warmup"],
                "steps": self.cfg["steps"]}

    def step(self, name: str, run: dict, scale: float, dense: bool) -> dict:
        spec = self.step_spec(run, scale, dense)
        return self.item(name, spec, lambda: run_worker("step", spec, self.log(name)))

    def run_all(self) -> dict:
        """Every item; with cfg["jobs"] > 1 (quick only) independent items run side by side
        (their timings are then not comparable, which a smoke run does not need)."""
        c = self.cfg
        small, large = tuple(c["small"]), tuple(c["large"])
        # the run folder is needed only while some measurement on it is not cached yet
        small_run = self.train("small", small, snapshots=True,
                               need_run=self._pending_on_small())
        render_spec = {"run": small_run["run"], "run_id": small_run["id"],
                       "sizes": [list(small), list(large)], "repeats": c["render_repeats"]}
        psnr_spec = {"run": small_run["run"], "run_id": small_run["id"],
                     "snapshots": [s["dir"] for s in small_run["snapshots"]]}

        def large_items():
            run = self.train("large", large, snapshots=False, need_run=self._pending_on_large())
            return run, self.step("step_image_large", run, 1.0, False)

        tasks = {
            **{f"step_grid_{s:g}x": (lambda s=s: self.step(f"step_grid_{s:g}x", small_run, s,
                                                           False)) for s in c["grid_scales"]},
            "step_dense": lambda: self.step("step_dense", small_run, 1.0, True),
            "render": lambda: self.item("render", render_spec, lambda: run_worker(
                "render", render_spec, self.log("render"))),
            "psnr_curve": lambda: self.item("psnr_curve", psnr_spec, lambda: run_worker(
                "psnr", psnr_spec, self.log("psnr_curve"))),
            "large": large_items,
            "refined": lambda: self.train("refined", small, snapshots=False, need_run=False,
                                          name=c["refined"], extra=DETAIL_ON),
        }
        if c["jobs"] > 1:  # the longest chain first
            tasks = {"large": tasks.pop("large"), **tasks}
        with ThreadPoolExecutor(max_workers=c["jobs"]) as pool:
            futures = {name: pool.submit(fn) for name, fn in tasks.items()}
            done = {name: f.result() for name, f in futures.items()}
        steps = {s: done[f"step_grid_{s:g}x"] for s in c["grid_scales"]}
        large_run, step_large = done["large"]
        return summarize(c, small_run, large_run, steps, done["step_dense"], done["render"],
                         done["psnr_curve"], step_large, done["refined"])

    def _pending_on_small(self) -> bool:
        return True if self.fresh else self._any_missing("small")

    def _pending_on_large(self) -> bool:
        return True if self.fresh else self._any_missing("large")

    def _any_missing(self, tag: str) -> bool:
        """Whether a measurement on the cached `tag` training has no cache entry yet."""
        c = self.cfg
        size = tuple(c[tag])
        folder = self.scene_dir(size)
        run = self.out / "runs" / f"{self.scene}_{size[0]}x{size[1]}"
        sets = list(c["sets"])
        if tag == "small":
            sets += [f"train.checkpoint_every={c['snapshot_every']}"]
        r = self.cached(f"train_{tag}", {"scene": str(folder), "preset": c["preset"],
                                         "sets": sets, "run": str(run)})
        if r is None:
            return True
        if tag == "large":
            return self.cached("step_image_large", self.step_spec(r, 1.0, False)) is None
        specs = [("step_dense", self.step_spec(r, 1.0, True)),
                 ("render", {"run": r["run"], "run_id": r["id"],
                             "sizes": [list(c["small"]), list(c["large"])],
                             "repeats": c["render_repeats"]}),
                 ("psnr_curve", {"run": r["run"], "run_id": r["id"],
                                 "snapshots": [s["dir"] for s in r["snapshots"]]})]
        specs += [(f"step_grid_{s:g}x", self.step_spec(r, s, False)) for s in c["grid_scales"]]
        return any(self.cached(n, s) is None for n, s in specs)


# ---------------------------------------------------------------------------------------
# results


def summarize(c, small_run, large_run, steps, dense, renders, psnr, step_large,
              refined_run) -> dict:
    base = steps[1.0]
    scores = psnr["scores"]
    for s, snap in zip(scores, small_run["snapshots"], strict=True):
        s["wall_s"] = snap["wall_s"]
    final = scores[-1]["psnr"]
    hit = next(s for s in scores if s["psnr"] >= final - c["psnr_window_db"])
    w_s, h_s = c["small"]
    w_l, h_l = c["large"]
    summary = {
        "train_rays_per_s": base["rays_per_s"],
        "train_samples_per_s": base["samples_per_s"],
        "train_slots_per_s": base["slots_per_s"],
        "train_step_s": base["step_s_median"],
        "train_occupied_samples_per_ray": base["occupied_samples_per_ray"],
        "dense_rays_per_s": dense["rays_per_s"],
        "dense_samples_per_s": dense["samples_per_s"],
        "dense_step_s": dense["step_s_median"],
        "sparsity_speedup": base["rays_per_s"] / dense["rays_per_s"],
        "compile_s": base["compile_s"] + base["trace_s"],
        "dense_compile_s": dense["compile_s"] + dense["trace_s"],
        "run_rays_per_s": small_run["run_rays_per_s"],
        "final_psnr": final,
        "time_to_psnr_window_s": hit["wall_s"],
        "time_to_psnr_window_train_s": hit["train_seconds"],
        "train_small_wall_s": small_run["wall_s"],
        "train_small_train_s": small_run["train_seconds"],
        "train_small_peak_rss_mb": small_run["peak_rss_mb"],
        "train_large_wall_s": large_run["wall_s"],
        "train_large_train_s": large_run["train_seconds"],
        "train_large_peak_rss_mb": large_run["peak_rss_mb"],
        "train_large_peak_rss_gb": large_run["peak_rss_mb"] * 1024**2 / 1e9,
        "train_refined_wall_s": refined_run["wall_s"],
        "train_refined_train_s": refined_run["train_seconds"],
        "train_refined_peak_rss_mb": refined_run["peak_rss_mb"],
        "render_small_s": renders[f"{w_s}x{h_s}"]["median_s"],
        "render_large_s": renders[f"{w_l}x{h_l}"]["median_s"],
        "render_compile_s": renders[f"{w_s}x{h_s}"]["first_s"],
    }
    scaling_grid = [{"scale": s, "resolution": r["resolution"], "rows": r["rows"],
                     "rays_per_s": r["rays_per_s"], "samples_per_s": r["samples_per_s"],
                     "step_s": r["step_s_median"], "compile_s": r["compile_s"] + r["trace_s"],
                     "peak_rss_mb": r["peak_rss_mb"]}
                    for s, r in sorted(steps.items())]
    scaling_image = [{"image": list(run["image"]), "resolution": r["resolution"],
                      "rows": r["rows"], "rays_per_s": r["rays_per_s"],
                      "samples_per_s": r["samples_per_s"], "step_peak_rss_mb": r["peak_rss_mb"],
                      "train_peak_rss_mb": run["peak_rss_mb"], "train_wall_s": run["wall_s"]}
                     for run, r in ((small_run, base), (large_run, step_large))]
    targets = []
    for label, field, op, goal, unit in TARGETS:
        v = summary[field]
        met = v >= goal if op == ">=" else v <= goal
        targets.append({"target": label, "field": field, "goal": f"{op} {goal:,} {unit}",
                        "measured": v, "unit": unit, "met": bool(met),
                        "factor": v / goal if op == ">=" else goal / v})
    trainings = [{"scene": Path(run["scene"]).name, "image": list(run["image"]),
                  "final_resolution": run["final_resolution"], "wall_s": run["wall_s"],
                  "train_s": run["train_seconds"], "peak_rss_mb": run["peak_rss_mb"],
                  "rays_per_s": step["rays_per_s"] if step else None}
                 for run, step in ((small_run, base), (large_run, step_large),
                                   (refined_run, None))]
    return {"summary": summary, "scaling_grid": scaling_grid, "scaling_image": scaling_image,
            "trainings": trainings, "psnr_curve": scores, "targets": targets}


def _n(v, nd=0) -> str:
    return fmt(v, nd) if nd else f"{v:,.0f}"


def markdown(record: dict) -> str:
    s, m, c = record["summary"], record["machine"], record["config"]
    ws, hs = c["small"]
    wl, hl = c["large"]
    step_rows = [(f"{g:g}x", record["items"][f"step_grid_{g:g}x"]) for g in c["grid_scales"]]
    step_rows.append(("dense", record["items"]["step_dense"]))
    lines = [
        "# gridnerf benchmark" + (" (--quick: smoke sizes, XLA optimisation off; not the targets)"
                           if c["quick"] else ""),
        "",
        f"`{record['command']}` on {m['cpu_model']}, {m['cores']} cores, "
        f"{m['memory_gb']} GB, {m['platform']}, jax {m['jax_version']} "
        f"({m['jax_backend']}, {m['device_count']} device(s)), tcmalloc {m['tcmalloc']}, "
        f"git {m['git_commit']}{' (dirty)' if m['git_dirty'] else ''}; preset "
        f"`{c['preset']}` {' '.join(c['sets'])} on simulated `{c['scene']}`. Load average "
        "when each item was measured is in results.json (items[*].machine.load_average): "
        "timings taken beside other jobs are not comparable.",
        "",
        "## Targets (2-core CPU)",
        "",
        markdown_table(["target", "goal", "measured", "met", "x of goal"],
                       [[t["target"], t["goal"], f"{fmt(t['measured'], 2)} {t['unit']}",
                         "yes" if t["met"] else "no", fmt(t["factor"], 2)]
                        for t in record["targets"]]),
        "",
        f"## Training step ({ws}x{hs} scene, final-stage grid of the finished run)",
        "",
        "One jitted optim.make_step (batch + loss + Adam), median of "
        f"{c['steps']} steps after {c['warmup']} warm-up; occupied samples = "
        "min(n_occupied, K) per ray on the same batches; slots = K shaded slots per ray "
        "(fixed shapes) or every candidate for the dense reference.",
        "",
        markdown_table(
            ["grid", "vertices kept", "rays/s", "occupied samples/s", "slots/s",
             "ms/step", "compile s", "step process peak RSS MB"],
            [[("dense " if name == "dense" else "") + "x".join(map(str, r["resolution"])),
              f"{r['rows']:,} ({100 * r['occupied_fraction']:.0f}%)", _n(r["rays_per_s"]),
              _n(r["samples_per_s"]), _n(r["slots_per_s"]), fmt(1e3 * r["step_s_median"], 1),
              fmt(r["compile_s"] + r["trace_s"], 1), _n(r["peak_rss_mb"])]
             for name, r in step_rows]),
        "",
        f"Sparse over dense: {fmt(s['sparsity_speedup'], 1)}x rays/s. Whole training run: "
        f"{_n(s['run_rays_per_s'])} rays/s (all steps over the training-loop time).",
        "",
        "## Whole trainings (one process each; wall includes imports, bounds, compiles, "
        "carving, checkpoints)",
        "",
        markdown_table(
            ["scene", "image", "final grid", "wall s", "training loop s", "peak RSS MB",
             "step rays/s"],
            [[r["scene"], f"{r['image'][0]}x{r['image'][1]}",
              "x".join(map(str, r["final_resolution"])), fmt(r["wall_s"], 0),
              fmt(r["train_s"], 0), _n(r["peak_rss_mb"]),
              "-" if r["rays_per_s"] is None else _n(r["rays_per_s"])]
             for r in record["trainings"]]),
        "",
        f"## Render (one test view, median of {c['render_repeats']} after a compiling call)",
        "",
        markdown_table(["image", "seconds", "rays/s"],
                       [[f"{ws}x{hs}", fmt(s["render_small_s"], 2),
                         _n(ws * hs / s["render_small_s"])],
                        [f"{wl}x{hl}", fmt(s["render_large_s"], 2),
                         _n(wl * hl / s["render_large_s"])]]),
        "",
        f"## Time to within {c['psnr_window_db']} dB of the final test PSNR "
        f"({fmt(s['final_psnr'])} dB)",
        "",
        f"{fmt(s['time_to_psnr_window_s'], 0)} s since the training process started "
        f"({fmt(s['time_to_psnr_window_train_s'], 0)} s of training loop); checkpoints every "
        f"{c['snapshot_every']} steps (and every 30 s of training), so this is the first "
        "checkpoint inside the window.",
        "",
        markdown_table(["stage", "step", "wall s", "training loop s", "test PSNR"],
                       [[str(p["stage"]), str(p["step"]), fmt(p["wall_s"], 0),
                         fmt(p["train_seconds"], 0), fmt(p["psnr"])]
                        for p in record["psnr_curve"]]),
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench", help="output folder (default: bench)")
    ap.add_argument("--scene", default="bucket", help="built-in simulated scene")
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: tiny preset and images (under a minute)")
    ap.add_argument("--fresh", action="store_true", help="measure again, ignoring the cache")
    ap.add_argument("--worker", nargs=3, metavar=("KIND", "ARGS", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        kind, wargs, out = args.worker
        result = WORKERS[kind](json.loads(wargs))
        result["machine"] = machine()
        Path(out).write_text(json.dumps(result))
        return
    out = Path(args.out).resolve()
    if args.quick:  # inherited by every process it starts
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {QUICK_XLA_FLAGS}".strip()
    cfg = {**(QUICK if args.quick else FULL), "scene": args.scene, "quick": args.quick}
    bench = Bench(out, cfg, args.fresh, args.quick, args.scene)
    results = bench.run_all()
    record = {
        "command": " ".join(["python", "-m", "experiments.bench", *(argv or sys.argv[1:])]),
        "machine": machine(), "config": {k: list(v) if isinstance(v, tuple) else v
                                         for k, v in cfg.items()},
        **results, "items": bench.items,
    }
    record["markdown"] = markdown(record)
    write_report(out / "results", record["markdown"], record)
    if not args.quick and out == REPO / "bench":  # docs/speed.md shows the full run's tables
        md = record["markdown"]
        update_doc("bench", md[md.index("## Targets"):md.index("## Time to within")]
                   .replace("## ", "### ").rstrip("\n"), REPO / SPEED_DOC)
        atomic.write_text(REPO / "reports" / "bench.md", md)
    print(record["markdown"])
    bad = [k for k, v in record["summary"].items() if not (math.isfinite(v) and v > 0)]
    if bad:
        raise SystemExit(f"non-finite or non-positive figures: {', '.join(bad)}")


if __name__ == "__main__":
    main()
