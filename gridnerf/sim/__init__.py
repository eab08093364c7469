"""Procedural LMRAW-like scenes: analytic props, a dark-scene sensor and a scene writer.

`simulate_scene(name, out_dir, ...)` writes one scene folder (see `writer`);
`SCENES` lists the nine scene names.
"""

from gridnerf.sim.scenes import SCENES
from gridnerf.sim.writer import simulate_scene

__all__ = ["SCENES", "simulate_scene"]
