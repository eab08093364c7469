"""Camera poses with pycolmap (SIFT, exhaustive matching, incremental mapping) on the CPU,
from the JPEG previews in images/ or (source="raw") from previews made from the RAW frames.

Writes `sparse/0` (the largest model, COLMAP binary) and a gridnerf `transforms.json` with
the registered frames, intrinsics in raw-frame pixels, the previous train/test split (if
any) and `near_far` from the sparse points. An existing `transforms.json` is first moved
to `transforms.prev.json`, an existing `sparse/0` to `sparse/0.prev`; the previous poses
are compared with the new ones (rotation error after the best global rotation, camera
centre error after a similarity alignment).

Intrinsics: a transforms.json that already gives one shared camera is trusted and kept
fixed (calibrated SfM). Otherwise COLMAP estimates one shared camera, SIMPLE_PINHOLE by
default (one focal length: pixels are square): gridnerf renders pinhole rays; on simulated
dark previews (forward-facing, small baselines) SIMPLE_RADIAL registered only 4-5 frames
where PINHOLE registered all, and on the quirky-camera captures from their RAW frames
alone SIMPLE_PINHOLE erred less than PINHOLE (held_quirk_brick: 0.40 deg mean rotation
error against 0.59, focal 446 against fx 446 / fy 456 for a true 461 px; held_quirk_table:
0.17 against 0.18 deg; held_quirk_shelf, a slide: all 24 frames registered against 12).
A capture that only translates (a slide rig) does not determine the focal length: there
SfM's is arbitrary (held_quirk_shelf: 1165 px for a true 461), which views along the slide
do not reveal; give the intrinsics in transforms.json where they are known.
Strongly denoised previews lose texture and can leave mostly planar structure (a back
wall), where SfM may settle in a wrong solution; source="raw" (bilinear demosaic and a
light blur) avoids that on the simulated scenes.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from gridnerf import baseline, color, pose_files, raw
from gridnerf import cameras as cam_mod
from gridnerf.errors import PoseError, SceneError
from gridnerf.scene import raw_files

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png")
_FIX = ("brighten the previews (more gain, stronger denoising), build them from the RAW "
        "frames (source='raw'), or capture with more overlap between neighbouring views, "
        "then re-run `gridnerf poses`")


def _previews(images_dir: Path) -> dict[str, str]:
    """stem -> file name of the preview images."""
    if not images_dir.is_dir():
        raise PoseError(images_dir, "images/ folder is missing",
                        "put JPEG previews named like the raw files (images/<name>.jpg) there")
    return {p.stem: p.name for p in sorted(images_dir.iterdir())
            if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS}


def run_colmap(images_dir: Path, image_names: list[str], work: Path, camera_model: str,
                known: tuple[float, float, float, float] | None,
                max_image_size: int | None = None):
    """SIFT + exhaustive matching + incremental mapping -> the largest Reconstruction.

    known: (fx, fy, cx, cy) in preview pixels, kept fixed (PINHOLE); None lets COLMAP
    estimate a shared `camera_model` (EXIF focal or 1.2 x image size as the start).
    max_image_size: SIFT runs on the previews scaled to at most this many pixels on the long
    side (keypoints in preview pixels again); None: COLMAP's default (3200).
    Inlier thresholds scale with the size SIFT sees (2 px at 320 px, COLMAP's 4 px from
    640 px up): on small noisy previews COLMAP's defaults admit enough outliers to bend
    forward-facing reconstructions by degrees.
    """
    import pycolmap

    # COLMAP logs every registration step at INFO (hundreds of lines per capture); its
    # warnings and errors still show
    pycolmap.logging.minloglevel = max(int(pycolmap.logging.minloglevel), 1)
    max_error = inlier_threshold(max(preview_size(images_dir, image_names[0])), max_image_size)

    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE" if known else camera_model
    if known:
        reader.camera_params = ",".join(f"{x:.6f}" for x in known)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.peak_threshold = 0.002  # dark, denoised previews have low contrast
    # one thread everywhere: with COLMAP's threads the features, matches and mapping order
    # change from run to run, and with them the estimated bounds (near 0.37-1.52 m on one
    # scene in four runs); seeds alone do not fix that
    extraction.num_threads = 1
    if max_image_size:
        extraction.max_image_size = int(max_image_size)
    pycolmap.extract_features(db, images_dir, image_names=image_names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = 0
    verification.ransac.max_error = max_error
    pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                              device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = 2
    options.num_threads = 1
    options.random_seed = 0
    options.mapper.random_seed = 0
    options.triangulation.random_seed = 0
    # Small dark previews give few features: accept smaller initial pairs and registrations.
    options.mapper.init_min_num_inliers = 50
    options.mapper.abs_pose_min_num_inliers = 15
    options.mapper.init_max_error = max_error
    options.mapper.abs_pose_max_error = 3.0 * max_error
    options.mapper.filter_max_reproj_error = max_error
    if known:
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_focal_length = False
        options.mapper.abs_pose_refine_extra_params = False
    (work / "models").mkdir()
    models = pycolmap.incremental_mapping(db, images_dir, work / "models", options=options)
    if not models:
        return None
    return max(models.values(), key=lambda rec: rec.num_reg_images())


def inlier_threshold(long_side: int, max_image_size: int | None = None) -> float:
    """COLMAP's inlier threshold in preview pixels for previews `long_side` pixels long that
    SIFT sees at most `max_image_size` long: long_side / 160 pixels of the image SIFT saw,
    within 2-4 (run_colmap), scaled back to preview pixels."""
    sift_side = min(long_side, max_image_size) if max_image_size else long_side
    return float(np.clip(sift_side / 160.0, 2.0, 4.0)) * long_side / sift_side


def preview_size(images_dir: Path, name: str) -> tuple[int, int]:
    """(width, height) of a preview image, read from its header."""
    shape = iio.improps(images_dir / name).shape
    return int(shape[1]), int(shape[0])


def _rotation_fit(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R (3, 3) minimising sum ||a_i - R b_i||^2 for stacked matrices a, b (N, 3, k)."""
    u, _, vt = np.linalg.svd(np.einsum("nik,njk->ij", a, b))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum ||dst_i - (s R src_i + t)||^2; src, dst: (N, 3)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(xd.T @ xs / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    var = (xs**2).sum() / len(src)
    scale = float(np.trace(np.diag(sig) @ d) / var) if var > 0 else 1.0
    return scale, rot, mu_d - scale * rot @ mu_s


def pose_agreement(prev: cam_mod.Cameras, new: cam_mod.Cameras) -> dict:
    """Compare new poses with previous ones (frames in both, in any world frame).

    Rotation error: angle of R_prev^T (R_align R_new) per frame, R_align the best global
    rotation between the two frames' orientations. Position error: camera-centre distance
    after a similarity (Umeyama) alignment, in previous world units and relative to the
    mean distance of the previous centres from their centroid.
    """
    common = [n for n in new.names if n in prev.names]
    if len(common) < 3:
        return {"compared_frames": len(common)}
    p = prev.take([prev.names.index(n) for n in common]).c2w
    q = new.take([new.names.index(n) for n in common]).c2w
    r_align = _rotation_fit(p[:, :, :3], q[:, :, :3])
    rel = np.einsum("nji,jk,nkl->nil", p[:, :, :3], r_align, q[:, :, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot_err = np.degrees(np.arccos(cos))
    s, rot, t = umeyama(q[:, :, 3], p[:, :, 3])
    pos_err = np.linalg.norm(p[:, :, 3] - (s * q[:, :, 3] @ rot.T + t), axis=1)
    extent = np.linalg.norm(p[:, :, 3] - p[:, :, 3].mean(0), axis=1).mean()
    return {
        "compared_frames": len(common),
        "rotation_error_deg": float(rot_err.mean()),
        "rotation_error_deg_max": float(rot_err.max()),
        "position_error": float(pos_err.mean()),
        "position_error_relative": float(pos_err.mean() / extent) if extent > 0 else None,
    }


def _previous(transforms: Path):
    """(cameras, split) of an existing transforms.json, or (None, None) if unreadable."""
    if not transforms.is_file():
        return None, None
    try:
        cams, split, _ = pose_files.load_transforms(transforms)
    except SceneError:
        return None, None
    return cams, split


def known_intrinsics(prev: cam_mod.Cameras | None, images_dir: Path, preview: str):
    """Shared (fx, fy, cx, cy) of the previous transforms.json in preview pixels, or None."""
    if prev is None or not all(np.allclose(a, a[0]) for a in (prev.fx, prev.fy, prev.cx, prev.cy)):
        return None
    width, height = preview_size(images_dir, preview)
    sx, sy = width / prev.width, height / prev.height
    if abs(sx / sy - 1.0) > 0.02:
        return None
    return prev.fx[0] * sx, prev.fy[0] * sy, prev.cx[0] * sx, prev.cy[0] * sy


def raw_preview(path, defects: np.ndarray | None = None) -> np.ndarray:
    """An SfM preview straight from a RAW frame: rgb_srgb (H, W, 3) uint8.

    Defective photosites (`defects`, (H, W) bool of the mosaic: defects.defective_pixels)
    take the median of their same-colour neighbours first, as a camera's own JPEG engine
    conceals them: a hot pixel sits at the same image position in every frame, and its
    blurred dot is a feature that matches across all views with no motion (on a capture
    with 12 of them, COLMAP registered 9 of 24 frames; concealed, all 24). Then a bilinear
    demosaic (baseline.demosaic_bilinear), white balance by AsShotNeutral, a 1-pixel
    Gaussian denoise, a gain to mean 0.25 and the sRGB curve. On simulated dark scenes it
    keeps more texture than a camera JPEG with strong noise reduction.
    """
    from scipy import ndimage

    from gridnerf.defects import neighbour_deviation

    frame = raw.read_raw(path)
    raw_norm = raw.normalize(frame)
    if defects is not None and defects.shape == raw_norm.shape:
        raw_norm = np.where(defects, neighbour_deviation(raw_norm)[1], raw_norm)
    rgb_cam = baseline.demosaic_bilinear(raw_norm, frame.cfa)
    rgb_cam = ndimage.gaussian_filter(rgb_cam / frame.as_shot_neutral, (1.0, 1.0, 0.0))
    rgb_cam *= 0.25 / max(float(rgb_cam.mean()), 1e-8)
    rgb_srgb = color.srgb_encode(rgb_cam)
    return np.round(rgb_srgb * 255.0).astype(np.uint8)


def raw_defects(files: list[Path]) -> np.ndarray | None:
    """(H, W) bool: the capture's defective photosites (defects.defective_pixels over its
    RAW frames; its line printed), None where none is found."""
    from gridnerf.defects import defective_pixels

    mask, why = defective_pixels(raw.normalize(raw.read_raw(f)) for f in files)
    if mask is not None:
        print(f"previews: {int(mask.sum())} defective pixels (at the same sensor position in "
              "most frames) concealed by their same-colour neighbours")
    elif why:
        print(f"previews: {why}")
    return mask


def sfm_images(scene: Path, files: dict, names: list[str], source: str, work: Path):
    """(folder, {stem: file name}, folder to name in errors) of the images COLMAP sees."""
    if source == "images":
        images_dir = scene / "images"
        return images_dir, _previews(images_dir), images_dir
    if source != "raw":
        raise ValueError(f"source must be 'images' or 'raw', got {source!r}")
    folder = work / "raw_previews"
    folder.mkdir()
    defects = raw_defects([files[n] for n in names])
    for name in names:
        iio.imwrite(folder / f"{name}.png", raw_preview(files[name], defects))
    return folder, {n: f"{n}.png" for n in names}, scene / "raw"


def _unreadable(path: Path) -> str | None:
    """Why COLMAP could not read this preview image (None when it decodes)."""
    try:
        iio.imread(path)
    except Exception as exc:  # noqa: BLE001 - any decoder failure means COLMAP skips it
        return f"its preview image cannot be decoded ({type(exc).__name__})"
    return None


def _install(rec, scene: Path) -> Path:
    """Write rec as scene/sparse/0, moving an existing model to sparse/0.prev."""
    sparse = scene / "sparse" / "0"
    sparse.parent.mkdir(exist_ok=True)
    staging = scene / "sparse" / "0.tmp"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    rec.write(staging)
    if sparse.exists():
        shutil.rmtree(scene / "sparse" / "0.prev", ignore_errors=True)
        os.replace(sparse, scene / "sparse" / "0.prev")
    os.replace(staging, sparse)
    return sparse


def estimate_poses(scene_dir, min_registered_fraction: float = 0.5,
                   camera_model: str = "SIMPLE_PINHOLE", use_known_intrinsics: bool = True,
                   source: str = "images") -> dict:
    """Estimate poses and write sparse/0 and transforms.json (module docstring).

    source: "images" (the previews in images/) or "raw" (previews made from the RAW
    frames by raw_preview). use_known_intrinsics: when a transforms.json already gives one
    shared camera, keep its intrinsics fixed (calibrated SfM; small forward-facing
    baselines constrain the focal length poorly); otherwise COLMAP estimates a shared
    `camera_model`. Returns {"registered": k, "total": n, "dropped": {stem: why} (no
    preview, unreadable preview, not registered; each also a warning), "seconds": t,
    "intrinsics": "known" | "estimated", model statistics, "near_far": ...} plus the pose
    agreement with a previous transforms.json. Raises PoseError naming the image folder
    when fewer than 2 or fewer than min_registered_fraction of the frames register.
    """
    start = time.perf_counter()
    scene = Path(scene_dir)
    if not scene.is_dir():
        raise SceneError(scene, "scene folder does not exist", "check the path")
    files = raw_files(scene)
    names = sorted(files)
    transforms = scene / "transforms.json"
    prev_cams, prev_split = _previous(transforms)
    with tempfile.TemporaryDirectory(prefix="gridnerf-colmap-") as tmp:
        work = Path(tmp)
        image_dir, previews, where = sfm_images(scene, files, names, source, work)
        dropped = {n: "it has no preview image" for n in names if n not in previews}
        dropped.update({n: why for n in names if n in previews
                        and (why := _unreadable(image_dir / previews[n]))})
        usable = [n for n in names if n not in dropped]
        if len(usable) < 2:
            raise PoseError(where, f"{len(usable)} of {len(names)} raw frames have a readable "
                            "preview image", "put JPEG previews named like the raw files there")
        known = None
        if use_known_intrinsics:
            known = known_intrinsics(prev_cams, image_dir, previews[usable[0]])
        rec = run_colmap(image_dir, [previews[n] for n in usable], work, camera_model, known)
        registered = set() if rec is None else {
            Path(im.name).stem for im in rec.images.values() if im.has_pose}
        registered_names = [n for n in names if n in registered]
        dropped.update({n: "COLMAP could not register it (too few feature matches with the "
                        "other frames)" for n in usable if n not in registered})
        for name, why in dropped.items():
            named = files[name] if source == "raw" else where / previews.get(name, name)
            warnings.warn(f"{named}: {why}; the frame is left out "
                          "of the poses", stacklevel=2)
        k, n = len(registered_names), len(names)
        if k < 2 or k < min_registered_fraction * n:
            raise PoseError(where, f"COLMAP registered only {k} of {n} frames", _FIX)
        stats = {
            "points": rec.num_points3D(),
            "reprojection_error_px": round(float(rec.compute_mean_reprojection_error()), 3),
            "mean_track_length": round(float(rec.compute_mean_track_length()), 2),
        }
        sparse = _install(rec, scene)

    cams_colmap, points = pose_files.load_colmap(sparse, registered_names)
    height, width = raw.read_raw(files[registered_names[0]]).raw_bayer.shape
    cams = cam_mod.resize_to(cams_colmap, width, height, where)
    near_far = cam_mod.bounds_from_points(cams_colmap, points, margin=0.1)
    train = test = None
    if prev_split is not None:
        train = [x for x in prev_split["train"] if x in registered]
        test = [x for x in prev_split["test"] if x in registered]
    if transforms.exists():
        os.replace(transforms, scene / "transforms.prev.json")
    pose_files.write_transforms(transforms, cams, train, test, near_far)
    report = {
        "registered": k,
        "total": n,
        "dropped": dropped,
        "seconds": round(time.perf_counter() - start, 2),
        "source": source,
        "intrinsics": "known" if known else "estimated",
        **stats,
        "near_far": None if near_far is None else [round(v, 4) for v in near_far],
    }
    if prev_cams is not None:
        report.update(pose_agreement(prev_cams, cams))
    return report
