"""Procedural LMRAW-like scenes: analytic props, a dark-scene sensor and a scene writer.

`simulate_scene(name, out_dir, ...)` writes one scene folder (see `writer`);
`SCENES` lists the nine scene names; `HELDOUT` the held-out scenes (other camera rigs,
a wide depth range, high-frequency textures), on which no default is tuned; `DEV` tuning
scenes with rigs of those kinds (an arc, a slide) but other content; `MIXED` the
mixed-light scenes (a warm lamp and daylight lighting different parts of the scene);
`HELDOUT_MIXED` mixed-light scenes held out from the mixed-light path's choices;
`HELDOUT_COLOUR` captures that break the colour path's assumptions (a ColorMatrix that does
not describe the sensor, lights off the Planckian locus), held out; `HELDOUT_QUIRK` held-out
scenes re-shot by a camera with a real camera's quirks (another CFA layout, 12 or 10 bits,
lens falloff, auto-exposure jitter, hot pixels), held out; `HELDOUT_UNIT` a sensor unlike
its camera model's reference matrix, held out.
"""

from gridnerf.sim.scenes import (
    ALL_SCENES,
    DEV,
    HELDOUT,
    HELDOUT_COLOUR,
    HELDOUT_MIXED,
    HELDOUT_QUIRK,
    HELDOUT_UNIT,
    MIXED,
    SCENES,
)
from gridnerf.sim.writer import folder_name, simulate_scene

__all__ = ["ALL_SCENES", "DEV", "HELDOUT", "HELDOUT_COLOUR", "HELDOUT_MIXED", "HELDOUT_QUIRK",
           "HELDOUT_UNIT", "MIXED", "SCENES", "folder_name", "simulate_scene"]
