"""The sensor model fitted against a trained field, and its black offsets in the data term.

Cameras record a black level in the file (BlackLevel), but the dark signal of a real sensor
sits a few DN off it, differently per CFA position (the ELD model: Wei et al., CVPR 2020;
gridnerf.sim hides such a bias of a few DN, about +20 % of a blue signal of ~18 DN). A
field trained on the frames as they are learns mu + b per colour: the offset becomes a
colour cast of the dark parts once the exposure is raised. Nothing in a capture shows b
in the mean; the noise does: Var = k (y - b) + r2 and the third moment k^2 (y - b)
(gridnerf.noisefit, eq. 7 of Bright-NeRF, mean_includes_offset=True).

`fit_field` renders the field at every used training frame's pose at full resolution,
mosaicks its low-light colour through the CFA at the frame's exposure (`field_mosaic`),
and fits the noise model on the frames' photosites against that mean (saturated ones left
out). With `data.black_offset = "fit"` training does this once, before its last stage,
keeps the result in <run>/sensor_fit.json, and the last stage trains on targets with the
fitted offsets taken off (dataset.RayData.black_offset).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gridnerf import atomic, eval_run, noisefit
from gridnerf.sim.sensor import mosaic

SENSOR_FIT = "sensor_fit.json"


def field_mosaic(structure, params, scene, cfg, i: int) -> np.ndarray:
    """(H, W) the field's mean of training frame i in normalised raw at its exposure."""
    cams = scene.cameras
    intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]], np.float32)
    out = eval_run.render_view(structure, params, scene, cfg, cams.c2w[i], intr,
                               int(cams.height), int(cams.width))
    return mosaic(np.asarray(out["rgb_low"], np.float64), scene.cfa) * float(scene.exposure[i])


def fit_field(structure, params, scene, cfg, max_frames: int = 8) -> noisefit.NoiseFit:
    """noisefit.fit_noise on up to `max_frames` training frames (evenly spaced) against
    the field's render (mean_includes_offset: the field absorbed the offsets)."""
    idx = np.asarray(scene.train_idx)
    idx = idx[np.unique(np.linspace(0, len(idx) - 1, min(max_frames, len(idx))).astype(int))]
    means = np.stack([field_mosaic(structure, params, scene, cfg, int(i)) for i in idx])
    frames = np.stack([scene.raw_normalized(int(i)) for i in idx])
    masks = np.stack([~scene.saturated(int(i)) for i in idx])
    return noisefit.fit_noise(means, frames, masks, mean_includes_offset=True)


def save(run: Path, fit: noisefit.NoiseFit, scale: float) -> None:
    """<run>/sensor_fit.json: the fit in normalised raw and in DN (scale = white - black)."""
    record = {"black_offset": np.asarray(fit.black_offset, np.float64).tolist(),
              "k": float(fit.k), "read_var": float(fit.read_var),
              "converged": bool(fit.converged), "k_identified": bool(fit.k_identified),
              "dn": fit.in_dn(scale), "scale": float(scale)}
    atomic.write_text(Path(run) / SENSOR_FIT, json.dumps(record, indent=2) + "\n")


def load_offsets(run: Path) -> np.ndarray | None:
    """(2, 2) fitted black offsets in normalised raw, or None before the fit."""
    path = Path(run) / SENSOR_FIT
    if not path.exists():
        return None
    b = np.asarray(json.loads(path.read_text())["black_offset"], np.float64)
    return b if b.shape == (2, 2) and np.isfinite(b).all() else None
