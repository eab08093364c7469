"""python -m experiments.bench --quick writes every figure, finite and positive, with the
machine and the command, and a re-run reads its cache; the multi-host options of
`gridnerf train` are checked before anything starts (one line, status 2)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SUMMARY_FIELDS = {
    "train_rays_per_s", "train_samples_per_s", "train_slots_per_s", "train_step_s",
    "train_occupied_samples_per_ray", "dense_rays_per_s", "dense_samples_per_s",
    "dense_step_s", "sparsity_speedup", "compile_s", "dense_compile_s", "run_rays_per_s",
    "final_psnr", "time_to_psnr_window_s", "time_to_psnr_window_train_s",
    "train_small_wall_s", "train_small_train_s", "train_small_peak_rss_mb",
    "train_large_wall_s", "train_large_train_s", "train_large_peak_rss_mb",
    "train_large_peak_rss_gb", "render_small_s", "render_large_s", "render_compile_s",
    "train_refined_wall_s", "train_refined_train_s", "train_refined_peak_rss_mb",
}


def _bench(out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "experiments.bench", "--quick", "--out",
                           str(out)], cwd=REPO, capture_output=True, text=True, timeout=600,
                          env=dict(os.environ))


def _positive(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def test_quick_bench_writes_every_figure(tmp_path):
    out = tmp_path / "bench"
    proc = _bench(out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    speed_doc = (REPO / "docs" / "speed.md").read_text()
    record = json.loads((out / "results.json").read_text())
    md = (out / "results.md").read_text()
    assert md.startswith("# gridnerf benchmark")
    assert "\n## Targets (2-core CPU)\n" in md and "issue" not in md.lower()
    assert set(record["summary"]) == SUMMARY_FIELDS
    bad = {k: v for k, v in record["summary"].items() if not _positive(v)}
    assert not bad, bad
    assert len(record["scaling_grid"]) == 3 and len(record["scaling_image"]) == 2
    for row in record["scaling_grid"] + record["scaling_image"]:
        for key in ("rays_per_s", "samples_per_s"):
            assert _positive(row[key]), row
    assert [len(r["resolution"]) for r in record["scaling_grid"]] == [3, 3, 3]
    assert len({r["rows"] for r in record["scaling_grid"]}) == 3
    assert len(record["targets"]) == 7
    # the whole `gridnerf train` process at both image sizes, and of the scene the detail
    # rule would refine, each against its own goal
    assert {t["field"] for t in record["targets"]} >= {"train_small_wall_s",
                                                       "train_large_wall_s",
                                                       "train_refined_wall_s"}
    assert [t["image"] for t in record["trainings"]] == [[96, 54], [128, 72], [96, 54]]
    assert all(isinstance(t["met"], bool) and _positive(t["measured"])
               for t in record["targets"])
    assert len(record["psnr_curve"]) >= 2
    m = record["machine"]
    assert m["cores"] >= 1 and m["jax_version"] and m["platform"] and m["cpu_model"]
    assert record["command"].startswith("python -m experiments.bench --quick")
    # the training steps were rebuilt from the runs' plans: the dense reference shades every
    # candidate, the sparse grid no more than max_samples
    dense, base = record["items"]["step_dense"], record["items"]["step_grid_1x"]
    assert dense["skip_empty"] is False and dense["slots_per_ray"] == dense["candidates_per_ray"]
    assert base["skip_empty"] is True and base["slots_per_ray"] <= 24  # the tiny preset's
    for name, item in record["items"].items():
        assert item["command"], name
        assert item["machine"]["jax_version"] == m["jax_version"], name
        assert item["cached"] is False, name
    # a re-run measures nothing again: every item comes from bench/cache
    again = _bench(out)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "measuring" not in again.stdout
    record2 = json.loads((out / "results.json").read_text())
    assert all(item["cached"] for item in record2["items"].values())
    assert record2["summary"] == record["summary"]
    # a quick run writes no tables into the docs
    assert (REPO / "docs" / "speed.md").read_text() == speed_doc


@pytest.mark.parametrize("args, message", [
    (["--coordinator", "10.0.0.1", "--num-processes", "2", "--process-id", "0"],
     "is not host:port"),
    (["--coordinator", "h:99999", "--num-processes", "2", "--process-id", "0"],
     "is not host:port"),
    (["--coordinator", "h:1234", "--num-processes", "2"], "--process-id (or JAX_PROCESS_ID)"),
    (["--coordinator", "h:1234", "--num-processes", "0", "--process-id", "0"],
     "--num-processes = 0"),
    (["--coordinator", "h:1234", "--num-processes", "2", "--process-id", "2"],
     "--process-id = 2 is not in 0 .. 1"),
    (["--coordinator", "h:1234", "--num-processes", "two", "--process-id", "0"],
     "'two' is not a whole number"),
])
def test_multi_host_options_are_checked(tmp_path, capsys, monkeypatch, args, message):
    from gridnerf import cli

    for var in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        monkeypatch.delenv(var, raising=False)
    run = tmp_path / "run"
    assert cli.main(["train", str(tmp_path / "no_scene"), "--out", str(run), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err, err
    assert not run.exists()


def test_multi_host_settings_from_the_environment():
    from gridnerf import devices
    from gridnerf.errors import ConfigError

    assert devices.distributed_settings(None, None, None, environ={}) is None
    env = {"JAX_COORDINATOR_ADDRESS": "node0:1234", "JAX_NUM_PROCESSES": "4",
           "JAX_PROCESS_ID": "3"}
    assert devices.distributed_settings(None, None, None, environ=env) == {
        "coordinator_address": "node0:1234", "num_processes": 4, "process_id": 3}
    # the command line wins over the environment
    assert devices.distributed_settings(None, None, 0, environ=env)["process_id"] == 0
    with pytest.raises(ConfigError, match="JAX_NUM_PROCESSES='x' is not a whole number"):
        devices.distributed_settings(None, None, None, environ={**env, "JAX_NUM_PROCESSES": "x"})
    with pytest.raises(ConfigError, match="--coordinator"):
        devices.distributed_settings(None, 2, 0, environ={})


def test_a_training_item_measures_again_when_any_field_changes(monkeypatch):
    """The cache key holds every config field: grid.voxel_pixels at its ADDED_FIELDS value
    leaves the results fingerprint as it was, and still changes what a 1920x1080 capture
    trains, so the bench must not read the measurement of the old one."""
    from experiments.bench import train_spec
    from experiments.common import fingerprint
    from gridnerf import config as cfgmod
    from gridnerf import plan as planmod

    scene, run = Path("data/sim/bucket_1920x1080"), Path("bench/runs/large")
    on = train_spec(scene, "default", [], run)
    off = train_spec(scene, "default", ["grid.voxel_pixels=0"], run)
    assert on["config"] != off["config"]
    assert train_spec(scene, "default", [], run) == on
    monkeypatch.setattr(planmod, "APPENDED_STEPS", (1200, 1))
    steps = train_spec(scene, "default", [], run)["config"]
    assert steps != on["config"]
    monkeypatch.setattr(planmod, "TV_FOOTPRINT", 1.0)
    assert train_spec(scene, "default", [], run)["config"] not in (on["config"], steps)
    default = cfgmod.preset("default")
    assert fingerprint(default) == fingerprint(cfgmod.override(default, ["grid.voxel_pixels=5"]))
