"""The Makefile: SCENE with spaces and '#' stays one quoted argument, a missing scene
folder is one error line with status 2, the first `make train` on a fresh machine installs
tcmalloc before it decides (when the recipe runs) to preload it, and the study targets run
the experiments package's modules."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TCMALLOC = "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4"

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


def _make(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """`make <args>` in `cwd` (the tests pass -n, or -o .venv/.installed: nothing is
    installed or trained)."""
    return subprocess.run(["make", "--no-print-directory", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=60)


def test_scene_with_spaces_and_hash_is_one_argument(tmp_path):
    scene = tmp_path / "my scenes" / "a #1"
    out = _make("-n", "-o", ".venv/.installed", "train", f"SCENE={scene}/", "PRESET=tiny")
    assert out.returncode == 0, out.stderr
    assert f'gridnerf train "{scene}/" --out "runs/a #1/tiny" --preset "tiny"' in out.stdout
    assert 'gridnerf eval "runs/a #1/tiny"' in out.stdout


def test_missing_scene_folder_is_one_error_line(tmp_path):
    scene = tmp_path / "my scenes" / "a #1"
    out = _make("-s", "-o", ".venv/.installed", "data", f"SCENE={scene}/")
    assert out.returncode == 2
    ours = [line for line in out.stderr.splitlines() if not line.startswith("make")]
    assert ours == [f"error: scene folder {scene}/ does not exist"], out.stderr
    scene.mkdir(parents=True)
    assert _make("-s", "-o", ".venv/.installed", "data", f"SCENE={scene}/").returncode == 0


def test_first_train_installs_then_preloads_tcmalloc(tmp_path):
    shutil.copy(ROOT / "Makefile", tmp_path)  # a fresh checkout: no .venv yet
    (tmp_path / "pyproject.toml").write_text("")
    out = _make("-n", "train", "SCENE=bucket", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    text = out.stdout
    install = text.index("libtcmalloc-minimal4")  # system-deps, run before the venv
    venv = text.index("-m venv .venv")
    train = text.index(".venv/bin/gridnerf train")
    preload = text.rindex(f"$(test -e {TCMALLOC} && echo LD_PRELOAD={TCMALLOC})", 0, train)
    assert install < venv < preload < train  # decided when the train recipe runs


@pytest.mark.parametrize("target, args, command", [
    ("ablate", [], '.venv/bin/python -m experiments.ablate --scenes "all"'),
    ("ablate", ["SCENE=bucket"], '.venv/bin/python -m experiments.ablate --scenes "bucket"'),
    ("report", [], ".venv/bin/python -m experiments.report"),
    ("report", ["QUICK=1"], ".venv/bin/python -m experiments.report --quick"),
    ("recon", [], ".venv/bin/python -m experiments.recon --scenes all --oracle heldout"),
    ("bench", ["BENCH_ARGS=--fresh"],
     '.venv/bin/python -m experiments.bench --scene "bucket" --fresh'),
])
def test_study_targets_run_the_experiments_modules(target, args, command):
    out = _make("-n", "-o", ".venv/.installed", target, *args)
    assert out.returncode == 0, out.stderr
    lines = [ln for ln in out.stdout.splitlines() if "experiments" in ln]
    assert len(lines) == 1 and lines[0].rstrip().endswith(command), out.stdout
    assert f"$(test -e {TCMALLOC} && echo LD_PRELOAD={TCMALLOC})" in lines[0]
    module = command.split("-m experiments.")[1].split()[0]
    assert (ROOT / "experiments" / f"{module}.py").is_file()
