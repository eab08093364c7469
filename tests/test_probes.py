"""Hostile-user probes (issue 7) driven through `gridnerf.cli.main`, in process.

Each probe asserts exit status 2, exactly one line on stderr naming the file or field
(and the fix), and that nothing half-written is left: no run folder after a failed
start, no new or changed file in an existing run folder, no `.tmp` file.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from gridnerf.cli import main


def _fails(capsys, argv: list[str], *needles: str) -> str:
    """Run the CLI; assert status 2 and one stderr line containing every needle."""
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith("error: ") and "Traceback" not in err
    for needle in needles:
        assert needle in line, (needle, line)
    return line


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Size and mtime of the folder's files (the .lock file records the last locker's pid)."""
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(folder.iterdir()) if p.is_file() and p.name != ".lock"}


@pytest.fixture(scope="module")
def trained(small_scene, tmp_path_factory):
    """A finished `tiny` run trained through the CLI."""
    run = tmp_path_factory.mktemp("probes") / "run"
    assert main(["train", str(small_scene), "--out", str(run), "--preset", "tiny"]) == 0
    return run


@pytest.fixture
def run_copy(trained, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    return run


@pytest.fixture
def scene_copy(small_scene, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(small_scene, scene)
    return scene


# --- typed, validated config and arguments ------------------------------------------------

@pytest.mark.parametrize("args, needles", [
    (["--preset", "bogus"], ["bogus", "tiny", "--preset"]),
    (["--set", "bogus.field=1"], ["bogus.field", "train"]),
    (["--set", "train.steps_per_stage=[40]"], ["train.steps_per_stage", "grid.resolutions"]),
    (["--set", "train.batch_patches=abc"], ["train.batch_patches", "abc", "whole number"]),
    (["--set", "loss.smooth_mode=tvv"], ["loss.smooth_mode", "tvv", "'patch'", "'tv'"]),
    (["--set", "loss.gain_model=off"], ["loss.gain_model", "'field'", "'none'"]),
    (["--set", "data.target=gt"], ["data.target", "'raw'", "'reference'"]),
    (["--set", "grid.resolutions=[[1,8,8],[16,16,16]]"], ["grid.resolutions", ">= 2"]),
    (["--set", "grid.resolutions=[[8,1,8],[16,0,16]]"], ["grid.resolutions", "may be 0"]),
    (["--set", "grid.fit_box=maybe"], ["grid.fit_box", "true or false"]),
    # a read-only property, not a field: the message names the field that replaced it
    (["--set", "loss.use_gains=false"], ["loss.use_gains", "no field", "loss.gain_model"]),
    (["--set", "train.lr_decay=0"], ["train.lr_decay", "> 0"]),
    (["--set", "grid.prune_threshold=2"], ["grid.prune_threshold", "<= 1"]),
    # eq. 15 compares neighbouring rays: one-ray patches have none
    (["--set", "train.patch_size=1", "train.batch_patches=64", "loss.smooth_mode=patch"],
     ["loss.smooth_mode", "train.patch_size = 1", "train.patch_size=8"]),
])
def test_bad_config_is_one_line_and_leaves_no_run_folder(small_scene, tmp_path, capsys, args,
                                                         needles):
    run = tmp_path / "run"
    _fails(capsys, ["train", str(small_scene), "--out", str(run), "--preset", "tiny", *args],
           *needles)
    assert not run.exists()


def test_repeated_set_keeps_every_override(small_scene, tmp_path, capsys):
    """`--set a --set b` is `--set a b` (argparse's default kept only the last --set)."""
    from gridnerf.cli import build_parser

    args = build_parser().parse_args(["train", "s", "--set", "a.b=1", "c.d=2", "--set", "e.f=3"])
    assert args.set == ["a.b=1", "c.d=2", "e.f=3"]
    run = tmp_path / "run"
    _fails(capsys, ["train", str(small_scene), "--out", str(run), "--preset", "tiny",
                    "--set", "train.batch_patches=abc", "--set", "loss.smooth_mode=patch"],
           "train.batch_patches", "abc")
    assert not run.exists()


def test_stage_counts_are_checked_after_all_overrides():
    from gridnerf import config as cfgmod

    cfg = cfgmod.override(cfgmod.preset("tiny"), ["grid.resolutions=[[8,8,8],[9,9,9],[10,10,10]]",
                                                  "train.steps_per_stage=[1,2,3]"])
    assert cfg.train.steps_per_stage == (1, 2, 3)
    assert cfgmod.from_dict(cfgmod.to_dict(cfg)) == cfg


def test_a_saved_config_takes_defaults_for_missing_fields_and_ignores_unknown_ones():
    """A saved config.json without a field reads it at its default; fields the config no
    longer has (the run plan keeps what training decided) are ignored."""
    from gridnerf import config as cfgmod

    saved = cfgmod.to_dict(cfgmod.preset("default"))
    assert "use_gains" not in saved["loss"] and saved["loss"]["gain_model"] == "field"
    del saved["grid"]["background"]
    del saved["loss"]["opacity_stages"]
    saved["loss"]["ca_on"] = "samples"
    saved["grid"]["prune_mode"] = "guarded"
    assert cfgmod.from_dict(saved) == cfgmod.preset("default")
    saved["loss"]["gain_model"] = "none"
    got = cfgmod.from_dict(saved)
    assert got != cfgmod.preset("default") and not got.loss.use_gains


def test_bad_saved_config_names_the_file(tmp_path):
    from gridnerf import config as cfgmod
    from gridnerf.errors import ConfigError

    path = tmp_path / "config.json"
    path.write_text(json.dumps({"loss": {"smooth_mode": "tvv"}}))
    with pytest.raises(ConfigError, match="config.json: loss.smooth_mode"):
        cfgmod.load(path)


@pytest.mark.parametrize("frames", ["0", "-5", "x"])
def test_render_frames_must_be_positive(trained, capsys, frames):
    _fails(capsys, ["render", str(trained), "--frames", frames], "--frames")
    assert not (trained / "render").exists()


# --- stale config, lock ---------------------------------------------------------------------

def test_train_saves_the_config_it_ran_with(trained):
    from gridnerf import config as cfgmod
    from gridnerf import plan as planmod

    assert cfgmod.load(trained / "config.json") == cfgmod.preset("tiny")
    # what training decided from the frames is the run plan beside it
    plan = planmod.load(trained)
    # the simulated capture's lens-cap frames show its files' black level off
    assert plan.method == "brightnerf" and plan.black_level == "lens_cap"
    assert len(plan.n_candidates) == len(cfgmod.preset("tiny").grid.resolutions)
    assert all(n > 0 for n in plan.n_candidates)  # every stage's count was fitted
    assert not (trained / "one_gain.json").exists() and not (trained / "sensor_fit.json").exists()


@pytest.mark.parametrize("args, needles", [
    (["--preset", "default"], ["config.json", "grid.resolutions", "--overwrite-config"]),
    (["--preset", "tiny", "--set", "train.batch_patches=4"], ["train.batch_patches", "run 8",
                                                              "asked 4"]),
    (["--preset", "tiny", "--set", "grid.sh_degree=1", "--overwrite-config"],
     ["grid.sh_degree", "cannot change"]),
])
def test_resume_refuses_a_different_config(small_scene, run_copy, capsys, args, needles):
    before = _snapshot(run_copy)
    _fails(capsys, ["train", str(small_scene), "--out", str(run_copy), *args], *needles)
    assert _snapshot(run_copy) == before


def test_resume_with_the_same_config_is_accepted(small_scene, run_copy, capsys):
    assert main(["train", str(small_scene), "--out", str(run_copy), "--preset", "tiny"]) == 0
    assert "already trained" in capsys.readouterr().out


def test_failed_start_removes_what_it_created(small_scene, tmp_path, capsys, monkeypatch):
    from gridnerf import dataset
    from gridnerf.errors import SceneError

    def broken_build(*a, **k):
        raise SceneError(small_scene, "cannot build rays", "fix it")

    monkeypatch.setattr(dataset, "build", broken_build)
    run = tmp_path / "run"  # bounds.json is estimated (and written) before build fails
    _fails(capsys, ["train", str(small_scene), "--out", str(run), "--preset", "tiny"],
           "cannot build rays")
    assert not run.exists()
    run.mkdir()
    (run / "notes.txt").write_text("mine")
    _fails(capsys, ["train", str(small_scene), "--out", str(run), "--preset", "tiny"],
           "cannot build rays")
    assert sorted(p.name for p in run.iterdir()) == ["notes.txt"]


def test_second_training_in_a_run_folder_is_refused(small_scene, run_copy, capsys):
    with open(run_copy / ".lock", "a+") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        _fails(capsys, ["train", str(small_scene), "--out", str(run_copy), "--preset", "tiny"],
               str(run_copy), "another training")
    assert main(["train", str(small_scene), "--out", str(run_copy), "--preset", "tiny"]) == 0


# --- corrupt checkpoint, disk full ------------------------------------------------------------

@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty"])
def test_corrupt_checkpoint_in_eval_and_resume(small_scene, run_copy, capsys, damage):
    ckpt = run_copy / "checkpoint.npz"
    data = ckpt.read_bytes()
    ckpt.write_bytes({"truncate": data[: len(data) // 2], "garbage": b"\x00junk" * 100,
                      "empty": b""}[damage])
    before = _snapshot(run_copy)
    for argv in (["eval", str(run_copy)],
                 ["train", str(small_scene), "--out", str(run_copy), "--preset", "tiny"]):
        _fails(capsys, argv, str(ckpt), "delete checkpoint.npz")
        assert _snapshot(run_copy) == before
    assert not (run_copy / "eval").exists()


def test_disk_full_during_checkpoint(small_scene, tmp_path, capsys, monkeypatch):
    from tqdm import tqdm

    from gridnerf import train as trainmod

    def full_disk_savez(f, **arrays):
        f.write(b"PK\x03\x04 partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez", full_disk_savez)
    monkeypatch.setattr(trainmod, "tqdm", partial(tqdm, disable=True))
    run = tmp_path / "run"
    _fails(capsys, ["train", str(small_scene), "--out", str(run), "--preset", "tiny",
                    "--set", "train.checkpoint_every=1"],
           str(run / "checkpoint.npz"), "No space left", "free disk space")
    assert not list(run.glob("*.tmp")) and not (run / "checkpoint.npz").exists()


# --- transforms.json ---------------------------------------------------------------------------

def _edit_transforms(scene: Path, edit) -> None:
    path = scene / "transforms.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize("edit, needles", [
    (lambda m: m["frames"][1].update(transform_matrix=[[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0]]),
     ["transform_matrix"]),
    (lambda m: m["frames"][0].update(transform_matrix="identity"), ["transform_matrix"]),
    (lambda m: m["frames"][0].update(transform_matrix=[["1", "0", "0", "0"]] * 4),
     ["transform_matrix"]),
    (lambda m: m.update(w=0), ["w"]),
    (lambda m: m.update(h=-90), ["h"]),
    (lambda m: m.update(train_filenames=None), ["train_filenames"]),
    (lambda m: m.update(test_filenames="raw/x.dng"), ["test_filenames"]),
    (lambda m: m.update(frames={"a": 1}), ["frames"]),
    (lambda m: m["frames"].append(7), ["frame 12"]),
    (lambda m: m["frames"][0].update(file_path=None), ["file_path"]),
    (lambda m: m.update(train_filenames=[m["frames"][1]["file_path"]] * 2), ["more than once"]),
    (lambda m: m.update(train_filenames=[f["file_path"] for f in m["frames"]],
                        test_filenames=[m["frames"][0]["file_path"]]), ["both the train"]),
])
def test_bad_transforms_json_is_one_clear_error(scene_copy, tmp_path, capsys, edit, needles):
    _edit_transforms(scene_copy, edit)
    run = tmp_path / "run"
    _fails(capsys, ["train", str(scene_copy), "--out", str(run), "--preset", "tiny"],
           "transforms.json", *needles)
    assert not run.exists()


def test_eval_of_a_scene_without_test_views(run_copy, scene_copy, capsys):
    """An empty test split is named, not scored as `{}`."""
    path = scene_copy / "transforms.json"
    meta = json.loads(path.read_text())
    meta["train_filenames"] = [f["file_path"] for f in meta["frames"]]
    meta["test_filenames"] = []
    path.write_text(json.dumps(meta))
    summary = json.loads((run_copy / "summary.json").read_text())
    summary["scene"] = str(scene_copy)
    (run_copy / "summary.json").write_text(json.dumps(summary))
    before = _snapshot(run_copy)
    _fails(capsys, ["eval", str(run_copy)], str(scene_copy), "test split is empty",
           "test_filenames")
    assert _snapshot(run_copy) == before and not (run_copy / "eval").exists()


# --- kill -9 ------------------------------------------------------------------------------------

def _cli(args: list[str], jax_cache: Path, checkpoint_seconds: float | None = None,
         **kwargs) -> subprocess.Popen:
    """`gridnerf <args>` in a child process, importing this checkout's gridnerf. XLA's
    compilations go to the persistent cache `jax_cache`: a second process reuses them
    (a resume starts in ~3 s instead of ~10 s on 2 cores). checkpoint_seconds: training's
    time-based checkpoint interval (train.CHECKPOINT_SECONDS) in the child."""
    import gridnerf

    root = str(Path(gridnerf.__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (root, os.environ.get("PYTHONPATH")) if p),
        JAX_COMPILATION_CACHE_DIR=str(jax_cache), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1")
    if checkpoint_seconds is None:
        return subprocess.Popen([sys.executable, "-m", "gridnerf.cli", *args], env=env,
                                **kwargs)
    code = ("import sys\nimport gridnerf.train\n"
            f"gridnerf.train.CHECKPOINT_SECONDS = {float(checkpoint_seconds)!r}\n"
            "from gridnerf.cli import main\nsys.exit(main(sys.argv[1:]))\n")
    return subprocess.Popen([sys.executable, "-c", code, *args], env=env, **kwargs)


def _logged(run: Path) -> list[dict]:
    """metrics.jsonl records (a line torn by a kill is skipped)."""
    recs = []
    path = run / "metrics.jsonl"
    for line in (path.read_text().splitlines() if path.exists() else []):
        try:
            recs.append(json.loads(line))
        except ValueError:
            continue
    return recs


def test_kill_9_loses_at_most_checkpoint_seconds(small_scene, tmp_path):
    """SIGKILL a training mid-stage, after its first time-based checkpoint and one more
    interval (train.CHECKPOINT_SECONDS, shortened in the child): the checkpoint loads
    (finite), is at most that interval (+ one save's slack) behind the progress
    metrics.jsonl logged, the dead process's lock blocks nothing, no `.tmp` survives, and
    the same command resumes and finishes."""
    from gridnerf.runfolder import load_state

    # seconds between checkpoints; one stage of `steps`; a save's own time and one step
    every, steps, slack = 0.25, 400, 1.0
    run = tmp_path / "run"
    argv = ["train", str(small_scene), "--out", str(run), "--preset", "tiny", "--set",
            "grid.resolutions=[[16,16,8]]", f"train.steps_per_stage=[{steps}]",
            "train.batch_patches=4", "train.log_every=10", "train.checkpoint_every=100000",
            "data.downscale=2"]  # the plan's own for this grid: the steps stay `steps`
    with open(tmp_path / "first.log", "w") as log:
        proc = _cli(argv, tmp_path / "jax-cache", every, stdout=log, stderr=subprocess.STDOUT)
    ckpt, first_seen, first_inode = run / "checkpoint.npz", None, None
    deadline = time.monotonic() + 240
    try:
        while True:  # kill once a checkpoint was replaced and 1.5 intervals passed, or mid-run
            assert proc.poll() is None, (tmp_path / "first.log").read_text()[-2000:]
            assert time.monotonic() < deadline, "no checkpoint within 240 s"
            if first_seen is None and ckpt.exists():
                first_seen, first_inode = time.monotonic(), ckpt.stat().st_ino
            if first_seen is not None:
                replaced = ckpt.stat().st_ino != first_inode  # os.replace: a new inode
                waited = time.monotonic() - first_seen >= 1.5 * every
                halfway = max((r["step"] for r in _logged(run)), default=0) >= steps // 2
                if (replaced and waited) or halfway:
                    break
            time.sleep(0.01)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL

    # the kernel dropped the killed process's flock: the lock file names it but is free
    assert (run / ".lock").read_text().strip() == str(proc.pid)
    with open(run / ".lock", "a+") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(held, fcntl.LOCK_UN)
    # a kill inside gridnerf.atomic.write leaves its .tmp (never the file itself)
    assert {p.name for p in run.glob("*.tmp")} <= {"checkpoint.npz.tmp", "metrics.jsonl.tmp"}

    _, params, opt_leaves, header = load_state(run)
    assert all(np.all(np.isfinite(np.asarray(v))) for v in params.values())
    assert opt_leaves and header["stage"] == 0 and 0 < header["step"] < steps
    logged = _logged(run)  # lines up to the kill, past the checkpoint: trimmed on resume
    assert max((r["step"] for r in logged), default=0) > header["step"] - 10  # log_every
    lost = max((r["train_seconds"] for r in logged), default=0) - header["train_seconds"]
    assert lost <= every + slack, (lost, header, logged[-1])

    (run / "checkpoint.npz.tmp").write_bytes(b"PK\x03\x04 torn")  # as if killed mid-save
    with open(tmp_path / "second.log", "w") as log:
        resumed = _cli(argv, tmp_path / "jax-cache", every, stdout=subprocess.PIPE, stderr=log,
                       text=True)
        out, _ = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, (tmp_path / "second.log").read_text()[-2000:]
    assert f"resuming {run} at stage 0, step {header['step']}" in out
    assert not list(run.glob("*.tmp"))
    assert load_state(run)[3]["stage"] == 1 and (run / "summary.json").exists()
    done = [r["step"] for r in _logged(run)]  # trimmed to the checkpoint, then continued
    assert done == sorted(set(done)) and done[-1] == steps


def test_all_black_scene_is_refused(scene_copy, tmp_path, capsys):
    from gridnerf import dng, raw

    for path in sorted((scene_copy / "raw").glob("*.dng")):
        f = raw.read_raw(path)
        dng.write_dng(path, np.full_like(f.raw_bayer, int(f.black_level.mean())), f.cfa,
                      f.black_level, int(f.white_level), f.xyz_to_cam, f.as_shot_neutral)
    run = tmp_path / "run"
    with warnings.catch_warnings():  # the bounds estimate's warning comes first: not ours
        warnings.simplefilter("ignore", UserWarning)
        _fails(capsys, ["train", str(scene_copy), "--out", str(run), "--preset", "tiny"],
               str(scene_copy / "raw"), "every frame is at the black level", "Fix:")
    assert not run.exists()
