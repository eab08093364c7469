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
plus train_seconds, rays_per_second and peak memory. The outputs are the method's
(gridnerf.methods): a run of loss.method = "llnerf" shows one in place of the first three,
`llnerf`: its enhanced render, decoded from sRGB to linear, no auto exposure.
"""

from __future__ import annotations

import json
import resource
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from gridnerf import (
    atomic,
    baseline,
    color,
    consistency,
    data_term,
    dataset,
    evaluate,
    image_io,
    look,
    losses,
    methods,
    outputs,
    pose_refine,
    raw,
    rays,
    render,
    vignetting,
)
from gridnerf import config as cfgmod
from gridnerf import plan as planmod
from gridnerf.errors import SceneError
from gridnerf.runfolder import CHECKPOINT, load_state, open_scene


def load_run(run: Path):
    """(cfg, plan, scene, structure, params, summary) of a finished run; cfg is its
    config.json with its plan's appended stage (plan.capture_config) and training
    downscale (data_term.fitted_config), the config
    its training data was built with, and its last stage's occupied-sample slots
    (plan.render_config), the samples its renders shade."""
    run = Path(run)
    if not (run / "summary.json").exists() or not (run / CHECKPOINT).exists():
        raise SceneError(
            run, "no finished training run here", f"run `gridnerf train <scene> --out {run}`"
        )
    plan = planmod.load(run)
    cfg = planmod.render_config(data_term.fitted_config(
        planmod.capture_config(cfgmod.load(run / "config.json"), plan.appended_width,
                               planmod.trained_appended_steps(plan), plan.appended_tv_ref),
        plan.downscale), plan)
    summary = json.loads((run / "summary.json").read_text())
    scene = open_scene(Path(summary["scene"]), run, estimate=False,
                       dark=plan.black_level == "lens_cap")
    structure, params, _, _ = load_state(run)
    return cfg, plan, scene, structure, params, summary


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


def run_outputs(cfg, plan, scene, structure, params, out: dict | None = None) -> dict:
    """The run's shown outputs {name: output with .show(render)}, as its method shows them
    (methods.get(loss.method).outputs), exposed on the training render (or `out`)."""
    return methods.get(cfg.loss.method).outputs(structure, params, scene, cfg, plan, out)


def main_output(cfg) -> str:
    """The name of a run's shown output (its method's MAIN_OUTPUT: "gridnerf" or
    "llnerf"), the one written as <view>_pred.png and rendered along camera paths."""
    return methods.get(cfg.loss.method).MAIN_OUTPUT


def own_raw_term(rgb_low: np.ndarray, scene, frame: int, cfg, plan) -> float | None:
    """The data term of a test view's render against its own dark raw frame, photosite by
    photosite: losses.data_loss (RawNeRF's relative squared error at the run's eps) of the
    render's low-light camera RGB rgb_low (H, W, 3), rendered at the capture's pixels, and
    the frame's raw mosaic (its lens falloff taken off as in training). None for a run that
    does not fit the raw, or a render at another size.

    A score with no reference: the test frames are part of the capture, left out of
    training. Their noise is the same for every field of one capture, so of two fields the
    one with the lower term explains the unseen views better (the noise adds the same
    expected amount to both); the term alone does not split noise from error."""
    if cfg.data.target != "raw" or rgb_low.shape[:2] != (scene.cameras.height,
                                                         scene.cameras.width):
        return None
    data = vignetting.apply(dataset.build(scene, np.array([frame]), False, 1, "raw",
                                          cfg.data.exposure_ratio), plan.vignetting)
    h, w = data.image_hw
    v, u = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    target, mask = dataset.targets(data, jnp.zeros_like(v), v, u)
    return float(losses.data_loss(jnp.asarray(rgb_low[:h, :w]), target, mask, plan.data_eps))


def evaluate_run(run: Path, refine_poses: bool = False) -> dict:
    """Render the test views, compare with gt/, write eval/ images and eval/metrics.json.

    refine_poses: each test view is rendered at the pose that best explains its own raw
    frame through the field (gridnerf.pose_refine), for poses estimated by structure from
    motion; metrics.json records how far each moved."""
    t0 = time.perf_counter()
    cfg, plan, scene, structure, params, summary = load_run(run)
    if refine_poses and not pose_refine.applies(cfg):
        raise SceneError(run / "config.json", "eval --refine-poses aligns each test view to "
                         "its own raw frame, and this run does not fit the raw "
                         f"(data.target={cfg.data.target})",
                         "evaluate it without --refine-poses")
    if len(scene.test_idx) == 0:
        raise SceneError(scene.path, "the scene's test split is empty: there is nothing to "
                         "score", "list frames in test_filenames of transforms.json (or "
                         "remove the split lists: every 8th frame is then a test frame)")
    out_dir = run / "eval"
    out_dir.mkdir(parents=True, exist_ok=True)
    one_gain = plan.one_gain
    shown = run_outputs(cfg, plan, scene, structure, params)
    main = main_output(cfg)
    per_view: dict[str, dict[str, dict]] = {
        m: {} for m in [*shown, "baseline_dark_frame", "baseline_denoised",
                        "baseline_binned_matched"]}
    cams = scene.cameras
    ds = cfg.data.eval_downscale
    h, w = cams.height // ds, cams.width // ds
    refined, own_raw = {}, {}
    for i in scene.test_idx:
        name = scene.names[i]
        intr = cams.intrinsics(i) / ds
        c2w = cams.c2w[i]
        if refine_poses:
            r = pose_refine.refine(structure, params, scene, cfg, plan, int(i))
            c2w = r.c2w
            refined[name] = {"rotation_deg": r.rotation_deg, "translation_near": r.translation,
                             "data_loss": [r.loss_before, r.loss_after]}
            print(f"eval: {name}'s pose refined against its raw frame: turned "
                  f"{r.rotation_deg:.3f} deg, moved {r.translation:.4f} x the near bound, "
                  f"data term {r.loss_before:.4g} -> {r.loss_after:.4g}")
        out = render_view(structure, params, scene, cfg, c2w, intr, h, w)
        own = own_raw_term(out["rgb_low"], scene, int(i), cfg, plan)
        if own is not None:
            own_raw[name] = own
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
                scene.raw_normalized(i), scene.cfa, scene.xyz_to_cam)
            dark_linear = raw.downscale(dark_linear, ds) if ds > 1 else dark_linear
            image_io.write_png(out_dir / f"{name}_baseline.png", color.srgb_encode(dark_linear))
            per_view["baseline_dark_frame"][name] = evaluate.image_metrics(dark_linear, gt_linear)
            denoised_linear = baseline.process_denoised_frame(
                scene.raw_normalized(i), scene.cfa, scene.xyz_to_cam)
            denoised_linear = raw.downscale(denoised_linear, ds) if ds > 1 else denoised_linear
            per_view["baseline_denoised"][name] = evaluate.image_metrics(denoised_linear,
                                                                         gt_linear)
            binned_linear = baseline.process_binned_frame(
                scene.raw_normalized(i), scene.cfa, scene.xyz_to_cam,
                gt_linear if ds == 1 else reference_linear(scene, name, cams.height, cams.width))
            binned_linear = raw.downscale(binned_linear, ds) if ds > 1 else binned_linear
            per_view["baseline_binned_matched"][name] = evaluate.image_metrics(
                binned_linear, gt_linear)
    result = {
        "scene": str(scene.path),
        "run": str(run),
        "test_views": [scene.names[i] for i in scene.test_idx],
        # the test views' poses: as the scene gives them, or refined (gridnerf.pose_refine)
        "test_poses": "refined" if refine_poses else "given",
        **({"pose_refined": refined} if refine_poses else {}),
        "alpha": {k: o.alpha for k, o in shown.items()},
        # what carried the colour: the gain field, or one gain for the capture (its gains)
        "colour": plan.colour.model if one_gain is None else {"one_gain": list(one_gain)},
        "train_seconds": summary["train_seconds"],
        "rays_per_second": summary["rays_per_second"],
        "train_peak_rss_mb": summary.get("peak_rss_mb"),
        "eval_seconds": time.perf_counter() - t0,
        "eval_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "lpips": evaluate.lpips_status(),
        "liqe": evaluate.lpips_status(),
        "per_view": per_view,
        "summary": {m: evaluate.summarize(v) for m, v in per_view.items() if v},
        # each test view's render against its own raw frame (own_raw_term), and their mean
        "own_raw": {"per_view": own_raw,
                    "mean": float(np.mean(list(own_raw.values()))) if own_raw else None},
    }
    if not result["summary"]:
        print("eval: the scene has no references (gt/) for its test views: nothing to score "
              f"against; the test renders are in {out_dir}")
    if own_raw:
        print(f"eval: the test views against their own raw frames: data term "
              f"{result['own_raw']['mean']:.4g} (lower explains the unseen views better; "
              "compare runs of this capture only)")
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


@dataclass(frozen=True)
class RenderSettings:
    """How `render_run` shows a run (gridnerf.look): a camera path (spiral, ellipse, test,
    views: through the frames named in `views`, comma-separated), its frame count,
    exposure compensation in stops, a white balance (look.parse_white's text), a size scale
    and the files written (a subset of FORMATS)."""

    path: str = "spiral"
    n_frames: int = 60
    views: str = ""
    exposure_stops: float = 0.0
    white: str = "learned"
    scale: float = 1.0
    formats: tuple[str, ...] = look.FORMATS


def _path_views(scene, settings: RenderSettings) -> list[tuple[str, np.ndarray]]:
    """[(file stem, (3, 4) camera-to-world)] of the settings' camera path."""
    cams = scene.cameras
    if settings.path == "test":
        return [(scene.names[i], cams.c2w[i]) for i in scene.test_idx]
    if settings.path == "views":
        poses = look.views_path(cams.c2w[look.parse_views(settings.views, scene)],
                                settings.n_frames)
    else:
        poses = camera_path(scene, settings.path, settings.n_frames)
    return [(f"{settings.path}_{k:03d}", p) for k, p in enumerate(poses)]


def render_run(run: Path, settings: RenderSettings | None = None) -> Path:
    """Render test views or a camera path to run/render/ (PNG, EXR, mp4 as asked) with the
    settings' exposure, white balance and size; render/<path>.json records what was shown
    (the gains, exposure alpha and matrix). Returns the video, or the folder without one."""
    settings = settings or RenderSettings()
    white = look.parse_white(settings.white)
    cfg, plan, scene, structure, params, _ = load_run(run)
    cams = scene.cameras
    size = settings.scale / cfg.data.eval_downscale
    h, w = max(int(round(cams.height * size)), 1), max(int(round(cams.width * size)), 1)

    def frame_intrinsics(i: int) -> np.ndarray:
        return cams.intrinsics(i) * size

    def render_frame(i: int) -> dict:
        return render_view(structure, params, scene, cfg, cams.c2w[i], frame_intrinsics(i),
                           h, w)

    views = _path_views(scene, settings)
    training_out = outputs.training_render(structure, params, scene, cfg)
    shown = run_outputs(cfg, plan, scene, structure, params, training_out)
    main = look.shown_output(shown, main_output(cfg), white,
                             look.neutral_rgb(white, scene, render_frame,
                                              plan.colour.sensor_matrix(scene.xyz_to_cam)),
                             settings.exposure_stops, training_out,
                             cfg.output.target_luminance)
    out_dir = run / "render"
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for name, c2w in views:
        out = render_view(structure, params, scene, cfg, c2w, frame_intrinsics(0), h, w)
        rgb_linear, rgb_srgb = main.show(out)
        if "png" in settings.formats:
            image_io.write_png(out_dir / f"{name}.png", rgb_srgb)
        if "exr" in settings.formats:
            image_io.write_exr(out_dir / f"{name}.exr", rgb_linear)
        frames.append(rgb_srgb)
    record = {"settings": asdict(settings), "size": [w, h], "views": [n for n, _ in views],
              "alpha": getattr(main, "alpha", 1.0)}
    if isinstance(main, outputs.Output):
        record.update(source=main.source, gains=[float(v) for v in main.gains],
                      matrix=np.asarray(main.matrix).tolist())
    atomic.write_text(out_dir / f"{settings.path}.json", json.dumps(record, indent=2))
    if "mp4" in settings.formats and len(frames) > 1:
        video = out_dir / f"{settings.path}.mp4"
        image_io.write_mp4(video, frames, fps=30)
        return video
    return out_dir
