"""The run folder: what a training run keeps beside its checkpoint, shared by train and eval.

    <run>/config.json     resolved config (gridnerf.config), written once training starts
    <run>/plan.json       the run plan (gridnerf.plan): what training decided from the
                          frames (black level, data eps, colour, candidate counts)
    <run>/bounds.json     scene bounds estimated by gridnerf.bounds when the scene's files
                          give none (written once, reused by resume and eval)
    <run>/checkpoint.npz  grid + optimiser state (train.py)
    <run>/metrics.jsonl   one line per log step, trimmed to the checkpoint on resume
    <run>/summary.json    written when training finishes
    <run>/.lock           flock'ed by the one training process allowed in the folder
                          (the kernel drops the flock when its process dies, even by
                          kill -9: a killed training never blocks the next one)

`RunLock` holds the lock while a training runs, removes the `.tmp` files a killed
training left mid-write (gridnerf.atomic) and, if the start fails (bad scene,
corrupt checkpoint, refused config, Ctrl-C), removes what the start created, so a
failed start leaves no run folder (or no new file in an existing one) behind.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
from pathlib import Path

from gridnerf import atomic, bounds, checkpoint, darkframes, grid
from gridnerf import config as cfgmod
from gridnerf.errors import CheckpointError, ConfigError, RunLockedError, SceneError
from gridnerf.plan import PLAN
from gridnerf.scene import BoundsMissing, Scene, load_scene

BOUNDS = "bounds.json"
CONFIG = "config.json"
METRICS = "metrics.jsonl"
LOCK = ".lock"
CHECKPOINT = "checkpoint.npz"
SUMMARY = "summary.json"
# Fields a checkpoint's arrays or its run plan depend on: a resumed run can never change them.
SHAPE_FIELDS = ("grid.resolutions", "grid.sh_degree", "loss.gain_model", "loss.method")


class RunLock:
    """`with RunLock(run) as s:` one training in `run`: takes <run>/.lock (RunLockedError if
    another process holds it); call `s.started()` once training really starts. Leaving the
    block with an exception before that removes every file the start created in `run` (and
    `run` itself if it was created). The lock is released on exit."""

    def __init__(self, run: Path):
        self.run = Path(run)
        self._fd: int | None = None
        self._started = False

    def __enter__(self) -> RunLock:
        self._made_dir = not self.run.exists()
        try:
            self.run.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SceneError(self.run, f"cannot create the run folder ({exc.strerror or exc})",
                             "choose another --out") from None
        self._before = {p.name for p in self.run.iterdir()}
        try:
            self._fd = _lock(self.run / LOCK)
        except BaseException:
            self._rollback()
            raise
        _remove_stale_tmp(self.run)
        return self

    def started(self) -> None:
        self._started = True

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is not None and not self._started:
                self._rollback()
        finally:
            if self._fd is not None:
                os.close(self._fd)  # releases the flock
                self._fd = None

    def _rollback(self) -> None:
        if not self.run.is_dir():
            return
        for p in self.run.iterdir():
            if p.name not in self._before and (p.is_file() or p.is_symlink()):
                p.unlink(missing_ok=True)
        if self._made_dir:
            with contextlib.suppress(OSError):  # something else appeared in it: keep it
                self.run.rmdir()


def _remove_stale_tmp(run: Path) -> None:
    """Delete the `<file>.tmp` a killed training (kill -9, power loss) left mid-write of one
    of the run folder's files (gridnerf.atomic never moves a .tmp into place, so it is
    never read). Only called with the lock held: no other training is writing them."""
    for name in (CONFIG, PLAN, BOUNDS, CHECKPOINT, METRICS, SUMMARY):
        (run / f"{name}.tmp").unlink(missing_ok=True)


def _lock(path: Path) -> int:
    """An fd holding an exclusive flock on `path` (created); RunLockedError if taken."""
    for _ in range(5):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            try:
                holder = f" (pid {int(path.read_text().strip())})"
            except (OSError, ValueError):
                holder = ""
            raise RunLockedError(path.parent, f"another training is running in this run "
                                 f"folder{holder}", "wait for it to finish, stop it, or train "
                                 "into another --out") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:  # else a failed start removed the file between our open and flock: retry
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)
    raise RunLockedError(path.parent, "cannot take the run folder's lock", "try again")


def resolve_config(run: Path, cfg: cfgmod.Config, overwrite: bool) -> cfgmod.Config:
    """The config to train `run` with, given the requested `cfg`.

    A run with a checkpoint resumes with its saved config.json: a request that differs is
    refused (ConfigError naming the fields) unless `overwrite`, and even then fields the
    checkpoint's arrays depend on (SHAPE_FIELDS) cannot change. Without a checkpoint
    there is nothing to resume and `cfg` is used (config.json is rewritten on start).
    """
    run = Path(run)
    path = run / CONFIG
    if not (run / CHECKPOINT).exists() or not path.exists():
        return cfg
    saved = cfgmod.load(path)
    changed = cfgmod.diff(saved, cfg)
    if not changed:
        return saved
    shown = "; ".join(f"{k}: run {_show(cfgmod.get(saved, k))}, asked {_show(cfgmod.get(cfg, k))}"
                      for k in changed[:4]) + ("; ..." if len(changed) > 4 else "")
    if not overwrite:
        raise ConfigError(path, f"this run was trained with another config ({shown})",
                          "repeat the run's --preset/--set (see its config.json) to resume, "
                          "train into another --out, or pass --overwrite-config to continue "
                          "with the new values")
    fixed = [k for k in changed if k in SHAPE_FIELDS]
    if fixed:
        raise ConfigError(path, f"--overwrite-config cannot change {', '.join(fixed)} of a "
                          "run with a checkpoint (the saved model has other shapes)",
                          "train into another --out, or delete the run folder to start over")
    print(f"continuing {run} with a changed config: {shown}")
    return cfg


def _show(v) -> str:
    return json.dumps(v).replace(", ", ",") if isinstance(v, tuple | list) else repr(v)


def trim_metrics(run: Path, stage: int, step: int) -> None:
    """Keep the metrics.jsonl lines up to (stage, step), where training resumes; lines
    written after the last checkpoint (and torn lines) are dropped."""
    path = Path(run) / METRICS
    if not path.exists():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
            if (int(rec["stage"]), int(rec["step"])) <= (stage, step):
                kept.append(line)
        except (ValueError, KeyError, TypeError):
            continue
    atomic.write_text(path, "".join(f"{line}\n" for line in kept))


def open_scene(scene_dir, run: Path, estimate: bool = True, dark: bool = False) -> Scene:
    """Load the run's scene with the bounds and the black level the run uses.

    The run's bounds.json wins; otherwise the scene's own bounds; otherwise (estimate=True)
    gridnerf.bounds estimates them from the given poses and they are saved in bounds.json.
    dark (the run plan's black_level is "lens_cap"): the black level the run measured from
    lens-cap frames (black_level.json, gridnerf.darkframes) is added to the file's.
    """
    scene = _open_scene(scene_dir, run, estimate)
    offset = darkframes.load(run) if dark else None
    return scene if offset is None else darkframes.apply(scene, offset)


def _open_scene(scene_dir, run: Path, estimate: bool) -> Scene:
    saved = Path(run) / BOUNDS
    if saved.is_file():
        try:
            b = json.loads(saved.read_text())
            near_far = (float(b["near"]), float(b["far"]))
        except (ValueError, KeyError, TypeError):
            raise SceneError(saved, "cannot read the run's bounds",
                             "delete bounds.json to estimate them again") from None
        return load_scene(scene_dir, near_far=near_far)
    try:
        return load_scene(scene_dir)
    except BoundsMissing as missing:
        if not estimate:
            raise
        found = bounds.estimate(scene_dir, missing.cameras)
        print(f"scene bounds estimated ({found.source}): near {found.near:.4g}, "
              f"far {found.far:.4g}")
        Path(run).mkdir(parents=True, exist_ok=True)
        atomic.write_text(saved, json.dumps(found.to_dict(), indent=2))
        return load_scene(scene_dir, near_far=(found.near, found.far))


def save_state(run: Path, structure, params, opt_state, header: dict) -> None:
    """Atomic checkpoint: grid layout + params, optimiser state, progress header."""
    state = grid.to_state(structure, params)
    keys = sorted(state)
    checkpoint.save(
        run / CHECKPOINT,
        {"grid": [state[k] for k in keys], "opt_state": checkpoint.flatten(opt_state)},
        {**header, "grid_keys": keys},
    )


def load_state(run: Path):
    """(structure, params, opt_leaves, header) from the run's checkpoint (CheckpointError
    naming the file if it is unreadable)."""
    path = Path(run) / CHECKPOINT
    groups, header = checkpoint.load(path)
    try:
        state = dict(zip(header["grid_keys"], groups["grid"], strict=True))
        structure, params = grid.from_state(state)
        missing = [k for k in ("stage", "step", "train_seconds", "key") if k not in header]
        if missing:
            raise KeyError(f"header lacks {missing}")
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        raise CheckpointError(path, f"the checkpoint is incomplete ({type(exc).__name__}: "
                              f"{exc})", f"delete {CHECKPOINT} to train the run again from "
                              "the start") from None
    return structure, params, groups.get("opt_state", []), header
