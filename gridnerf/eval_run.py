"""Evaluate and render a trained run: test views vs gt/, baselines, camera paths.

eval/metrics.json holds per-view and mean PSNR / SSIM / CIEDE2000 on sRGB,
raw and after a per-channel affine alignment in linear space, for
- `gridnerf`: our bright render with the colour matrix (or without, if the
  run's config says so),
- `gridnerf_matrix_free`: the same radiance field shown the paper's way,
- `global_grey_world`: the field's low-light colour times one grey-world gain for the
  whole scene (global_gains), shown like `gridnerf`: what a single white balance gives,
  the reference a gain field must beat (for a run without gains: RawNeRF + a generic ISP),
- `baseline_dark_frame`: the plain demosaic + grey-world + gamma of the dark test frame,
- `baseline_denoised`: the same with non-local-means denoising (the paper's 2D row),
- `baseline_binned_matched`: 2x2 binning, grey world, exposure matched to the reference
  (the generous per-frame pipeline of the reconstruction table),
plus train_seconds, rays_per_second and peak memory. A run of loss.method = "llnerf" shows
one output in place of the first three, `llnerf`: its enhanced render (gridnerf.llnerf),
decoded from sRGB to linear, no auto exposure.
"""

from __future__ import annotations

import json
import resource
import time
from dataclasses import dataclass, replace
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from gridnerf import (
    atomic,
    baseline,
    color,
    colour_target,
    consistency,
    dataset,
    evaluate,
    exposure,
    illuminant,
    image_io,
    llnerf,
    raw,
    rays,
    render,
)
from gridnerf import config as cfgmod
from gridnerf.errors import SceneError
from gridnerf.runfolder import CHECKPOINT, lens_cap_black, load_state, open_scene


def load_run(run: Path):
    """(cfg, scene, structure, params, summary) of a finished run."""
    if not (run / "summary.json").exists() or not (run / CHECKPOINT).exists():
        raise SceneError(
            run, "no finished training run here", f"run `gridnerf train <scene> --out {run}`"
        )
    cfg = cfgmod.load(run / "config.json")
    summary = json.loads((run / "summary.json").read_text())
    scene = open_scene(Path(summary["scene"]), run, estimate=False,
                       dark=lens_cap_black(cfg, run))
    structure, params, _, _ = load_state(run)
    return cfg, scene, structure, params, summary


def render_view(structure, params, scene, cfg, c2w, intrinsics, height, width,
                points: bool = False) -> dict:
    """Render one camera: dict of (H, W, ...) host arrays (rgb_low, gain, rgb_restored, ...);
    with `points`, also the rendered surface's world points (H, W, 3) and their validity
    (H, W) (consistency.world_points)."""
    near_t, far_t = dataset.grid_box(scene)[2:]
    o, d = dataset.image_rays(c2w, intrinsics, height, width)
    ndc = jnp.asarray(dataset.ndc_intrinsics(scene))
    o, d = dataset.to_grid_space(scene.forward_facing, ndc, o, d)
    out = render.render_image(structure, params, o, d, near_t, far_t, cfg.render)
    if points:
        out["points"], out["points_valid"] = consistency.world_points(
            out["depth"], out["acc"], o, d, scene.forward_facing, ndc)
    return out


# rays of the training render that auto exposure and the global grey world are taken on
TRAINING_RENDER_RAYS = 65536


def training_render(structure, params, scene, cfg) -> dict:
    """The field rendered on an even, fixed sample of every training frame (about
    TRAINING_RENDER_RAYS pixels on a regular grid, dataset.strided_pixels): (N, hs, ws, ...).

    Not a random sample: 128 random 8x8 patches (the sample before) set the auto exposure
    of box 28 % apart between two training seeds (0.6 dB) where a bright coloured wall
    filled some patches and not others; an even grid over all frames does not depend on
    the seed."""
    data = dataset.training_data(scene, cfg.data)
    rays = dataset.rays_at(data, *dataset.strided_pixels(data, TRAINING_RENDER_RAYS))
    near_t, far_t = dataset.grid_box(scene)[2:]
    return render.render_image(
        structure, params, rays["origins"], rays["directions"], near_t, far_t, cfg.render
    )


def global_gains(out: dict) -> np.ndarray:
    """(3,) one grey-world von Kries gain for the whole scene: the gains of the grey world of
    the field's low-light colour on the training rays (training_render), no gain field.

    The "global white balance" reference of the colour issue: a field that only learned
    one white balance scores the same as rgb_low times these gains.
    """
    return np.asarray(illuminant.gains_from_illuminant(_grey_world(out)))


def _grey_world(out: dict) -> np.ndarray:
    """(3,) grey world of the field's low-light colour on the training render."""
    return np.asarray(illuminant.grey_world(np.asarray(out["rgb_low"], np.float64)))


def field_neutral(out: dict) -> np.ndarray:
    """(3,) the camera-RGB white the field's gains balance: 1 / their mean per unit opacity
    over the training render (the composited gain divided by the opacity, pooled)."""
    gain = np.asarray(out["gain"], np.float64).reshape(-1, 3).sum(0)
    acc = float(np.asarray(out["acc"], np.float64).sum())
    return np.asarray(illuminant.unit(acc / np.maximum(gain, 1e-12)))


@dataclass(frozen=True)
class Output:
    """How one output shows a render: rgb_linear = alpha * matrix @ (out[source] * gains)."""

    source: str  # "rgb_restored" (the field's own gains) or "rgb_low"
    gains: np.ndarray  # (3,) von Kries gains applied on top (ones: none)
    matrix: np.ndarray  # (3, 3) display matrix (exposure.display_matrix)
    alpha: float = 1.0

    def show(self, out: dict) -> tuple[np.ndarray, np.ndarray]:
        """(rgb_linear, rgb_srgb) of a render (render_view / training_render output)."""
        return exposure.to_display(np.asarray(out[self.source]) * self.gains, self.alpha,
                                   self.matrix)


@dataclass(frozen=True)
class EnhancedOutput:
    """The LLNeRF-style output: the dark sRGB render enhanced per ray
    (llnerf.enhanced_render), decoded to linear sRGB; no exposure (alpha stays 1)."""

    alpha: float = 1.0

    def show(self, out: dict) -> tuple[np.ndarray, np.ndarray]:
        """(rgb_linear, rgb_srgb) of a render (render_view / training_render output)."""
        rgb_srgb = np.asarray(llnerf.enhanced_render(out["rgb_low"], out["gain"], out["acc"]),
                              np.float32)
        return color.srgb_decode(rgb_srgb).astype(np.float32), rgb_srgb


def main_output(cfg) -> str:
    """The name of a run's shown output: "llnerf" for loss.method = "llnerf", else
    "gridnerf" (the one written as <view>_pred.png and rendered along camera paths)."""
    return "llnerf" if cfg.loss.method == "llnerf" else "gridnerf"


def outputs(structure, params, scene, cfg, out: dict | None = None,
            one_gain: np.ndarray | None = None) -> dict[str, Output | EnhancedOutput]:
    """The shown outputs of a run, each exposed on the training render (training_render,
    or `out`): "gridnerf" (the colour matrix, or matrix-free when output.use_color_matrix
    is off), "gridnerf_matrix_free", and "global_grey_world" (the field's low-light colour
    times one grey-world gain for the scene, global_gains). output.color_matrix =
    "adapted" takes the matrix for the white the gains balanced (field_neutral; the grey
    world's for the global row), exposure.display_matrix. one_gain: (3,) the run's one
    gain (colour_target.load_one_gain) where its colour is one gain: the first two show the
    low-light colour times it instead of the field's gains. loss.method = "llnerf": only
    "llnerf" (EnhancedOutput), nothing exposed."""
    if cfg.loss.method == "llnerf":
        return {"llnerf": EnhancedOutput()}
    out = training_render(structure, params, scene, cfg) if out is None else out
    raw_target = cfg.data.target == "raw"
    ones = np.ones(3) if one_gain is None else np.asarray(one_gain, np.float64)
    source = "rgb_restored" if cfg.loss.use_gains and one_gain is None else "rgb_low"
    adapted = cfg.output.color_matrix == "adapted"
    neutral = None
    if cfg.loss.use_gains and adapted:
        neutral = field_neutral(out) if one_gain is None else illuminant.unit(1.0 / ones)
    grey = _grey_world(out) if adapted else None
    free = Output(source, ones, np.eye(3))
    shown = {
        "gridnerf": (Output(source, ones, exposure.display_matrix(scene.xyz_to_cam, raw_target,
                                                                  neutral))
                     if cfg.output.use_color_matrix else free),
        "gridnerf_matrix_free": free,
        "global_grey_world": Output("rgb_low", global_gains(out), exposure.display_matrix(
            scene.xyz_to_cam, raw_target and cfg.output.use_color_matrix, grey)),
    }
    target = cfg.output.target_luminance
    return {k: replace(o, alpha=exposure.alpha_for_luminance(o.show(out)[0], target))
            for k, o in shown.items()}


def run_outputs(run: Path, structure, params, scene, cfg, out: dict | None = None
                ) -> dict[str, Output | EnhancedOutput]:
    """outputs() of the run in folder `run`: with its one gain where its colour is one
    gain (colour_target.load_one_gain), else the field's."""
    return outputs(structure, params, scene, cfg, out,
                   one_gain=colour_target.load_one_gain(run, cfg))


def evaluate_run(run: Path) -> dict:
    """Render the test views, compare with gt/, write eval/ images and eval/metrics.json."""
    t0 = time.perf_counter()
    cfg, scene, structure, params, summary = load_run(run)
    if len(scene.test_idx) == 0:
        raise SceneError(scene.path, "the scene's test split is empty: there is nothing to "
                         "score", "list frames in test_filenames of transforms.json (or "
                         "remove the split lists: every 8th frame is then a test frame)")
    out_dir = run / "eval"
    out_dir.mkdir(parents=True, exist_ok=True)
    one_gain = colour_target.load_one_gain(run, cfg)  # read once: shown and recorded
    shown = outputs(structure, params, scene, cfg, one_gain=one_gain)
    main = main_output(cfg)
    adapted = cfg.output.color_matrix == "adapted"  # the baselines take the same matrix
    per_view: dict[str, dict[str, dict]] = {
        m: {} for m in [*shown, "baseline_dark_frame", "baseline_denoised",
                        "baseline_binned_matched"]}
    cams = scene.cameras
    ds = cfg.data.eval_downscale
    h, w = cams.height // ds, cams.width // ds
    for i in scene.test_idx:
        name = scene.names[i]
        intr = np.array([cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]]) / ds
        out = render_view(structure, params, scene, cfg, cams.c2w[i], intr, h, w)
        gt_linear = reference_linear(scene, name, h, w)
        for method, output in shown.items():
            pred_linear, pred_srgb = output.show(out)
            if method == main:
                image_io.write_png(out_dir / f"{name}_pred.png", pred_srgb)
                image_io.write_exr(out_dir / f"{name}_pred.exr", pred_linear)
                depth = out["depth"] / max(float(np.percentile(out["depth"], 99)), 1e-6)
                image_io.write_png(
                    out_dir / f"{name}_depth.png", np.repeat(depth[..., None], 3, -1)
                )
            if gt_linear is not None:
                per_view[method][name] = evaluate.image_metrics(pred_linear, gt_linear)
                if method == main:
                    gt_srgb = color.srgb_encode(gt_linear)
                    image_io.write_png(out_dir / f"{name}_gt.png", gt_srgb)
                    image_io.write_png(
                        out_dir / f"{name}_error.png", evaluate.error_image(pred_srgb, gt_srgb)
                    )
        if gt_linear is not None:
            dark_linear = baseline.process_dark_frame(
                scene.raw_normalized(i), scene.cfa, scene.xyz_to_cam, adapted=adapted)
            dark_linear = raw.downscale(dark_linear, ds) if ds > 1 else dark_linear
            image_io.write_png(out_dir / f"{name}_baseline.png", color.srgb_encode(dark_linear))
            per_view["baseline_dark_frame"][name] = evaluate.image_metrics(dark_linear, gt_linear)
            denoised_linear = baseline.process_denoised_frame(
                scene.raw_normalized(i), scene.cfa, scene.xyz_to_cam, adapted=adapted)
            denoised_linear = raw.downscale(denoised_linear, ds) if ds > 1 else denoised_linear
            per_view["baseline_denoised"][name] = evaluate.image_metrics(denoised_linear,
                                                                         gt_linear)
            binned_linear = baseline.process_binned_frame(
                scene.raw_normalized(i), scene.cfa, scene.xyz_to_cam,
                gt_linear if ds == 1 else reference_linear(scene, name, cams.height, cams.width),
                adapted=adapted)
            binned_linear = raw.downscale(binned_linear, ds) if ds > 1 else binned_linear
            per_view["baseline_binned_matched"][name] = evaluate.image_metrics(
                binned_linear, gt_linear)
    result = {
        "scene": str(scene.path),
        "run": str(run),
        "test_views": [scene.names[i] for i in scene.test_idx],
        "alpha": {k: o.alpha for k, o in shown.items()},
        # what carried the colour: the gain field, or one gain for the capture (its gains)
        "colour": "field" if one_gain is None else {"one_gain": one_gain.tolist()},
        "train_seconds": summary["train_seconds"],
        "rays_per_second": summary["rays_per_second"],
        "train_peak_rss_mb": summary.get("peak_rss_mb"),
        "eval_seconds": time.perf_counter() - t0,
        "eval_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "lpips": evaluate.lpips_status(),
        "liqe": evaluate.lpips_status(),
        "per_view": per_view,
        "summary": {m: evaluate.summarize(v) for m, v in per_view.items() if v},
    }
    atomic.write_text(out_dir / "metrics.json", json.dumps(result, indent=2))
    return result


def reference_linear(scene, name: str, h: int, w: int):
    """(h, w, 3) float32 linear-sRGB reference of view `name` (gt/<name>.exr, box-downscaled
    to the render size), or None where the scene has none; SceneError for a size that is
    not a whole multiple of (h, w)."""
    path = scene.gt_linear_paths.get(name)
    if path is None:
        return None
    gt_linear = image_io.read_exr(path)
    if gt_linear.shape[0] != h or gt_linear.shape[1] != w:
        factor = gt_linear.shape[0] // h
        if factor < 1 or gt_linear.shape[1] // factor != w:
            raise SceneError(
                path,
                f"reference is {gt_linear.shape[:2]}, renders are {(h, w)}",
                "write gt/ at the raw frames' size",
            )
        gt_linear = raw.downscale(gt_linear, factor)
    return gt_linear


def camera_path(scene, kind: str, n_frames: int) -> np.ndarray:
    """(n, 3, 4) camera-to-world poses around the capture (normalised world).

    spiral: LLFF-style spiral around the mean camera, looking at the focus point
    (the mean of near and far along the mean view); ellipse: a flat ellipse in
    the mean camera's image plane; radii from the 90th percentile of camera offsets.
    """
    c2w = scene.cameras.c2w
    avg = rays.average_pose(c2w)
    centre, rot = avg[:, 3], avg[:, :3]
    focus = centre - rot[:, 2] * 0.5 * (scene.near + scene.far) * 0.5
    offsets = (c2w[:, :, 3] - centre) @ rot
    radii = np.percentile(np.abs(offsets), 90, axis=0) + 1e-3
    t = np.linspace(0.0, 2 * np.pi, n_frames, endpoint=False)
    if kind == "spiral":
        local = np.stack(
            [np.cos(t) * radii[0], -np.sin(t) * radii[1], np.sin(0.5 * t) * radii[2]], 1
        )
    else:
        local = np.stack([np.cos(t) * radii[0], np.sin(t) * radii[1], np.zeros_like(t)], 1)
    poses = []
    for p in centre + local @ rot.T:
        poses.append(np.concatenate([rays.look_at(p, focus, rot[:, 1]), p[:, None]], 1))
    return np.stack(poses)


def render_run(run: Path, path: str = "spiral", n_frames: int = 60) -> Path:
    """Render test views (`path='test'`) or a camera path to run/render/: PNG, EXR, mp4."""
    cfg, scene, structure, params, _ = load_run(run)
    main = run_outputs(run, structure, params, scene, cfg)[main_output(cfg)]
    cams = scene.cameras
    ds = cfg.data.eval_downscale
    h, w = cams.height // ds, cams.width // ds
    intr0 = np.array([cams.fx[0], cams.fy[0], cams.cx[0], cams.cy[0]]) / ds
    if path == "test":
        views = [(scene.names[i], cams.c2w[i]) for i in scene.test_idx]
    else:
        views = [(f"{path}_{k:03d}", p) for k, p in enumerate(camera_path(scene, path, n_frames))]
    out_dir = run / "render"
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for name, c2w in views:
        out = render_view(structure, params, scene, cfg, c2w, intr0, h, w)
        rgb_linear, rgb_srgb = main.show(out)
        image_io.write_png(out_dir / f"{name}.png", rgb_srgb)
        image_io.write_exr(out_dir / f"{name}.exr", rgb_linear)
        frames.append(rgb_srgb)
    video = out_dir / f"{path}.mp4"
    image_io.write_mp4(video, frames, fps=30)
    return video
