"""Shared fixtures: one small simulated scene per test session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory):
    """A 12-frame 160x90 simulated `bucket` scene folder (Path). Built once per session."""
    from gridnerf.sim import simulate_scene

    out = tmp_path_factory.mktemp("scenes") / "bucket"
    return simulate_scene("bucket", out, width=160, height=90, n_frames=12, seed=0)


def sim_near_far(scene_dir) -> tuple[float, float]:
    """The simulator's true (near, far) from sim.json: tests that load a simulated scene
    without training pass it explicitly (transforms.json carries no bounds)."""
    import json
    from pathlib import Path

    near, far = json.loads((Path(scene_dir) / "sim.json").read_text())["near_far"]
    return float(near), float(far)
