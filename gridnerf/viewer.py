"""`gridnerf view <run>`: one self-contained HTML file that ray-marches a trained run in WebGL2.

The file (default <run>/viewer.html) is gridnerf/viewer_template.html with one JSON payload
put in its place; it loads nothing else (no server, no CDN). The payload:

  grid     resolution (Rx, Ry, Rz), bbox_min / bbox_max (3,), color_scale, sh_degree,
           n_rows M, n_channels C = 4 + 3 n_sh;
           kept_bits: base64 of np.packbits((Rx, Ry, Rz) bool kept vertices, C order,
             bitorder "little"): row r of the features is the r-th kept vertex;
           features_f16: base64 of (M, C) float16 raw rows [density | rgb | log_gain]
             (grid.feature_table less its empty row); empty_row: (C,) the empty vertex's;
           occ_shape (Bx, By, Bz), occ_factor, occ_bits: base64 of the packed occupancy
             bitmask (the one the renderer skips empty space with);
           background: (2, 3) low-light RGB and gains of the backdrop.
  render   samples_per_voxel, max_samples K, n_candidates (the box diagonal's count,
           render.n_candidates), ndc, ndc_intrinsics (4,), near_t, far_t.
  camera   the first test view (or first training view): c2w (3, 4), intrinsics (4,) fx,
           fy, cx, cy at the eval size width x height, and the orbit centre (3,) on its
           optical axis (orbit_centre).
  outputs  the run's shown outputs (eval_run.run_outputs, main output first): restored
           (source rgb_restored, else rgb_low), gains (3,), matrix (3, 3) column-major,
           alpha (the auto exposure on the training render).
  white    (n_kelvin, n_duv, 3) linear-sRGB whites of lights on and off the Planckian
           locus (color.tinted_xyz_white), for the temperature / tint sliders.

The page scatters the rows into one dense RGBA16F 3D texture (channel groups of 4 side by
side along z) and a R8UI occupancy texture, and its fragment shader repeats
render.render_rays and outputs.Output.show per pixel: pixel rays, the NDC warp, the box
clip, candidates at (i + 0.5) / samples_per_voxel voxels, the first K occupied ones kept,
trilinear raw features (texelFetch, the renderer's corner weights), softplus density and
colour, exp(clip(log_gain)) gains, alpha compositing over the backdrop, then
alpha * 2^stops * matrix @ (source * gains), the white diagonal and the sRGB curve.
Approximations, none of which matter at 8 bits: raw features are float16 (relative error
<= 2^-11); the march stops once transmittance falls below 1e-4; transmittance is a running
product (render: exp of a cumulative sum). The renderer fits its candidate count to each
image, the shader loops to the box diagonal's count: both give every ray the step
1 / samples_per_voxel voxels, so the samples are the same. Other window sizes keep the
initial view's vertical field of view. The white-balance sliders are a diagonal in the
output's linear sRGB (6500 K, duv 0: none); a picked neutral replaces them by the diagonal
that turns the drawn 5x5 patch grey at its luminance (read back from the 8-bit canvas).
Runs whose shown output is not a matrix of gained colour (loss.method = "llnerf": a per-ray
enhancement in sRGB) are refused.
"""

from __future__ import annotations

import base64
import json
from importlib import resources
from pathlib import Path

import numpy as np

from gridnerf import atomic, color, consistency, dataset, eval_run, render
from gridnerf import grid as gridlib
from gridnerf.errors import CheckpointError, GridNerfError
from gridnerf.outputs import Output
from gridnerf.runfolder import CHECKPOINT

TEMPLATE = "viewer_template.html"
PLACEHOLDER = "/*GRIDNERF_PAYLOAD*/null"
DEFAULT_NAME = "viewer.html"
LABELS = {
    "gridnerf": "learned gains (per voxel)",
    "global_grey_world": "one global gain (grey world)",
    "gridnerf_matrix_free": "learned gains, no colour matrix",
}
WHITE_KELVIN = (2000.0, 12000.0)  # range of the temperature slider, sampled evenly in mired
WHITE_DUV = (-0.02, 0.02)  # range of the tint slider
REFERENCE_WHITE = (6500.0, 0.0)  # (kelvin, duv) where the sliders change nothing


def b64(array: np.ndarray) -> str:
    """Base64 of an array's bytes (little-endian, C order)."""
    a = np.ascontiguousarray(array)
    return base64.b64encode(a.astype(a.dtype.newbyteorder("<")).tobytes()).decode("ascii")


def packed_bits(mask: np.ndarray) -> str:
    """Base64 of a bool array of any shape (C order), 8 per byte, first in the lowest bit."""
    return b64(np.packbits(np.asarray(mask, bool).reshape(-1), bitorder="little"))


def grid_payload(structure: gridlib.GridStructure, params) -> dict:
    """The sparse grid as the page needs it (module docstring, `grid`): raw rows in
    float16, the kept vertices and the occupancy as bitmasks. GridNerfError where a raw
    value does not fit float16."""
    table = np.asarray(gridlib.feature_table(structure, params), np.float32)  # (M + 1, C)
    rows = table[:-1].astype(np.float16)
    if not np.all(np.isfinite(rows)):
        raise GridNerfError(None, "the grid holds raw values beyond float16's range (65504)",
                            "the run is unusable for the viewer; retrain it")
    kept = np.zeros(structure.resolution, bool)
    kept[tuple(np.asarray(structure.coords).T)] = True
    occupancy = np.asarray(structure.occupancy, bool)
    return {
        "resolution": list(structure.resolution), "n_rows": structure.n_rows,
        "n_channels": structure.n_channels, "sh_degree": structure.sh_degree,
        "color_scale": structure.color_scale,
        "bbox_min": np.asarray(structure.bbox_min, float).tolist(),
        "bbox_max": np.asarray(structure.bbox_max, float).tolist(),
        "kept_bits": packed_bits(kept), "features_f16": b64(rows),
        "empty_row": table[-1].tolist(),
        "occ_shape": list(occupancy.shape), "occ_factor": structure.occ_factor,
        "occ_bits": packed_bits(occupancy),
        "background": np.asarray(structure.background, float).tolist(),
    }


def render_payload(structure, scene, cfg) -> dict:
    """How rays are placed (module docstring, `render`)."""
    near_t, far_t = dataset.grid_box(scene)[2:]
    return {
        "samples_per_voxel": float(cfg.render.samples_per_voxel),
        "max_samples": int(cfg.render.max_samples),
        "n_candidates": render.n_candidates(structure, cfg.render),
        "ndc": bool(scene.forward_facing),
        "ndc_intrinsics": dataset.ndc_intrinsics(scene).astype(float).tolist(),
        "near_t": float(near_t), "far_t": float(far_t),
    }


def initial_view(scene, cfg) -> dict:
    """The first test view (or, with no test split, the first training view) at the eval
    size: name, index, c2w (3, 4), intrinsics (4,) fx, fy, cx, cy, width, height."""
    i = int(scene.test_idx[0] if len(scene.test_idx) else scene.train_idx[0])
    cams, ds = scene.cameras, cfg.data.eval_downscale
    intrinsics = cams.intrinsics(i) / ds
    return {"name": scene.names[i], "index": i, "c2w": cams.c2w[i].tolist(),
            "intrinsics": intrinsics.tolist(), "width": cams.width // ds,
            "height": cams.height // ds}


def orbit_centre(out: dict, c2w: np.ndarray, scene) -> np.ndarray:
    """(3,) world point the mouse orbits: on the view's optical axis at the median depth of
    the rendered surface in the middle third of the view (consistency.world_points of
    eval_run.render_view(points=True)'s `out`: points (H, W, 3), points_valid (H, W)), else
    of the whole view, else halfway between near and far. c2w: (3, 4)."""
    points, valid = out["points"], out["points_valid"]
    h, w = valid.shape
    middle = np.zeros_like(valid)
    middle[h // 3:h - h // 3, w // 3:w - w // 3] = True
    d = 0.5 * (scene.near + min(scene.far, 1e3))
    for mask in (valid & middle, valid):
        depth = consistency.camera_depth(c2w, points[mask])
        depth = depth[np.isfinite(depth) & (depth > 0)]
        if depth.size:
            d = float(np.median(depth))
            break
    return np.asarray(c2w[:, 3], float) - d * np.asarray(c2w[:, 2], float)


def output_payload(shown: dict, main: str) -> list[dict]:
    """The run's shown outputs as the page applies them, main output first. GridNerfError
    where the main output is not an outputs.Output (a matrix of gained colour)."""
    if not isinstance(shown.get(main), Output):
        raise GridNerfError(None, f"the run's output {main!r} is not a colour matrix on the "
                            "grid's colour, which the viewer's shader reproduces",
                            "view a run of loss.method = brightnerf")
    names = [main] + [k for k, o in shown.items() if k != main and isinstance(o, Output)]
    return [{"name": k, "label": label(k, shown[k]), "restored": shown[k].source == "rgb_restored",
             "gains": np.asarray(shown[k].gains, float).tolist(),
             "matrix": np.asarray(shown[k].matrix, float).T.reshape(-1).tolist(),
             "alpha": float(shown[k].alpha)} for k in names]


def label(name: str, output: Output) -> str:
    """What the white-balance menu calls an output: LABELS, except where the run's main
    output shows its low-light colour (one gain for the capture, or no gains)."""
    if name == "gridnerf" and output.source == "rgb_low":
        gained = not np.allclose(output.gains, 1.0)
        return "the run's one gain for the capture" if gained else "no gains (low-light colour)"
    return LABELS.get(name, name)


def white_table(n_kelvin: int = 41, n_duv: int = 9) -> dict:
    """Linear-sRGB whites (luminance 1) of lights at kelvin (evenly in mired over
    WHITE_KELVIN, ascending mired) and duv (WHITE_DUV): mired (n_kelvin,), duv (n_duv,),
    rgb (n_kelvin * n_duv * 3,) row-major (kelvin, duv, channel)."""
    mired = np.linspace(1e6 / WHITE_KELVIN[1], 1e6 / WHITE_KELVIN[0], n_kelvin)
    duv = np.linspace(*WHITE_DUV, n_duv)
    rgb = np.array([[color.SRGB_FROM_XYZ @ color.tinted_xyz_white(1e6 / m, float(d))
                     for d in duv] for m in mired])
    rgb /= (rgb @ color.LUMA)[..., None]
    return {"mired": mired.tolist(), "duv": duv.tolist(), "rgb": rgb.reshape(-1).tolist(),
            "reference_kelvin": REFERENCE_WHITE[0], "reference_duv": REFERENCE_WHITE[1]}


def check_run(run: Path) -> None:
    """CheckpointError naming <run>/checkpoint.npz where it is missing (the rest of a run
    folder is eval_run.load_run's to check)."""
    path = Path(run) / CHECKPOINT
    if not path.is_file():
        raise CheckpointError(path, "the run has no checkpoint to view",
                              f"train it first: gridnerf train <scene> --out {run}")


def payload(run: Path) -> dict:
    """Everything the page needs (module docstring) from a finished run."""
    check_run(run)
    cfg, plan, scene, structure, params, _ = eval_run.load_run(run)
    shown = eval_run.run_outputs(cfg, plan, scene, structure, params)
    outputs = output_payload(shown, eval_run.main_output(cfg))
    view = initial_view(scene, cfg)
    c2w = np.asarray(view["c2w"])
    out = eval_run.render_view(structure, params, scene, cfg, c2w,
                               np.asarray(view["intrinsics"]), view["height"], view["width"],
                               points=True)
    view["centre"] = orbit_centre(out, c2w, scene).tolist()
    return {"version": 1, "title": f"{scene.path.name} ({Path(run).resolve().name})",
            "grid": grid_payload(structure, params),
            "render": render_payload(structure, scene, cfg), "camera": view,
            "outputs": outputs, "white": white_table()}


def html(data: dict) -> str:
    """The page: the template with `data` as its JSON payload."""
    template = resources.files("gridnerf").joinpath(TEMPLATE).read_text()
    if template.count(PLACEHOLDER) != 1:
        raise ValueError(f"{TEMPLATE} must hold {PLACEHOLDER} once")
    text = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    return template.replace(PLACEHOLDER, text)


def write_viewer(run: Path, out: Path | None = None) -> Path:
    """Write the viewer of `run` to `out` (default <run>/viewer.html); returns its path."""
    run = Path(run)
    out = run / DEFAULT_NAME if out is None else Path(out)
    atomic.write_text(out, html(payload(run)))
    return out
