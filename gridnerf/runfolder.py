"""The run folder: what a training run keeps beside its checkpoint, shared by train and eval.

    <run>/config.json     resolved config (gridnerf.config)
    <run>/bounds.json     scene bounds estimated by gridnerf.bounds when the scene's files
                          give none (written once, reused by resume and eval)
    <run>/checkpoint.npz  grid + optimiser state (train.py)
    <run>/summary.json    written when training finishes
"""

from __future__ import annotations

import json
from pathlib import Path

from gridnerf import bounds
from gridnerf.checkpoint import atomic_write_text
from gridnerf.errors import SceneError
from gridnerf.scene import BoundsMissing, Scene, load_scene

BOUNDS = "bounds.json"


def open_scene(scene_dir, run: Path, estimate: bool = True) -> Scene:
    """Load the run's scene with the bounds the run uses.

    The run's bounds.json wins; otherwise the scene's own bounds; otherwise (estimate=True)
    gridnerf.bounds estimates them from the given poses and they are saved in bounds.json.
    """
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
        atomic_write_text(saved, json.dumps(found.to_dict(), indent=2))
        return load_scene(scene_dir, near_far=(found.near, found.far))
