"""Scene folder -> `Scene`: uint16 frame cache, cameras in a normalised world, split, gt paths.

Layouts, in priority order for the poses:
1. `transforms.json` (nerfstudio; gridnerf's own format, see pose_files.load_transforms),
2. `sparse/0` (COLMAP, the RawNeRF layout; frames = sorted raw files),
3. `poses_bounds.npy` (LLFF; one row per sorted raw file).
near/far: an explicit `near_far` argument, else transforms.json `near_far`, else the
poses_bounds bounds, else the depths of the COLMAP points, else BoundsMissing (carrying the
cameras, so gridnerf.bounds can estimate them). Without a split, every 8th frame
(0, 8, 16, ...) is a test frame. Exposure: exposure time x ISO from the raw metadata or an
exiftool `raw/<name>.json`, relative to the median; a factor unknown for some frame is
left out for all frames (1.0 when nothing is known). Frames are read as displayed (the raw
files' gain opcodes, DefaultCrop and Orientation applied: gridnerf.raw_layout, each decision
printed once), the size transforms.json must describe.
"""

from __future__ import annotations

import json
import pathlib
import warnings
from dataclasses import dataclass

import numpy as np

from gridnerf import cameras as cam_mod
from gridnerf import defects, pose_files, raw, raw_layout, rays, white_reference
from gridnerf.cameras import Cameras
from gridnerf.errors import PoseError, SceneError
from gridnerf.frame_checks import metadata_outliers, unusable_frames
from gridnerf.white_reference import WhiteRef

RAW_EXTENSIONS = (".dng", ".arw", ".cr2", ".cr3", ".nef", ".nrw", ".raf", ".orf", ".rw2",
                  ".pef", ".srw", ".3fr", ".iiq", ".erf", ".kdc", ".dcr", ".mrw", ".raw")
_POSES_FIX = "run `gridnerf poses <scene>` to estimate poses from images/"


@dataclass(frozen=True, eq=False)
class Scene:
    """A loaded scene. Arrays are indexed like `names`.

    raw_bayer: (N, H, W) uint16 mosaics as displayed, black NOT removed (any gain opcode of
    the files applied: lens_correction); black_level: (N, 2, 2) float32
    per CFA position; white_level: (N,) float32; cfa: (2, 2) int; xyz_to_cam: (3, 3) of
    frame 0; as_shot_neutral: (N, 3); exposure: (N,) relative exposure; cameras and
    near/far live in the normalised world (rays.normalize_world), which maps back to the
    input world by world_from_normalized (4, 4).
    """

    path: pathlib.Path
    names: tuple[str, ...]
    cameras: Cameras
    raw_bayer: np.ndarray
    black_level: np.ndarray
    white_level: np.ndarray
    cfa: np.ndarray
    xyz_to_cam: np.ndarray
    as_shot_neutral: np.ndarray
    exposure: np.ndarray
    train_idx: np.ndarray
    test_idx: np.ndarray
    near: float
    far: float
    forward_facing: bool
    gt_srgb_paths: dict[str, pathlib.Path]
    gt_linear_paths: dict[str, pathlib.Path]
    world_from_normalized: np.ndarray | None = None
    camera_model: str | None = None  # frame 0's UniqueCameraModel / Model tag
    # a grey card that sets the light (transforms.json's white_reference, or --white-ref)
    white_reference: WhiteRef | None = None
    # (H, W) bool: defective sensor positions (gridnerf.defects), None where none is found
    defects: np.ndarray | None = None
    # the gain opcodes the files carried, applied on loading (the files' own lens falloff
    # correction, e.g. "FixVignetteRadial (OpcodeList3)"), None where none: gridnerf.raw_layout
    lens_correction: str | None = None
    # (N,) the files' BaselineExposure tags (EV), recorded, not applied; None where absent
    baseline_exposure: np.ndarray | None = None

    def raw_normalized(self, i: int) -> np.ndarray:
        """raw_bayer (H, W) float32: (raw - black) / (white - black), negatives kept."""
        return raw.normalize_mosaic(self.raw_bayer[i], self.black_level[i], self.white_level[i])

    def saturated(self, i: int) -> np.ndarray:
        """(H, W) bool: pixels at or above the white level."""
        return self.raw_bayer[i] >= self.white_level[i]

    def valid_mask(self, i: int) -> np.ndarray:
        """(H, W) bool: the pixels of frame i a fit may use: not saturated, not defective."""
        saturated = self.saturated(i)
        return ~saturated if self.defects is None else ~(saturated | self.defects)

    def rgb_cam_binned(self, i: int, downscale: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """2x2-binned then box-downscaled frame i: rgb_cam (H/2/d, W/2/d, 3) float32 and a
        valid mask of the same shape (False where any source pixel is saturated or
        defective)."""
        rgb_cam = raw.bin2x2(self.raw_normalized(i), self.cfa)
        valid = raw.bin2x2_mask(self.valid_mask(i), self.cfa)
        if downscale > 1:
            rgb_cam = raw.downscale(rgb_cam, downscale)
            valid = raw.downscale(valid, downscale) >= 1.0
        return rgb_cam, valid


def raw_files(scene: pathlib.Path) -> dict[str, pathlib.Path]:
    raw_dir = scene / "raw"
    if not raw_dir.is_dir():
        raise SceneError(raw_dir, "raw/ folder is missing",
                         "put the RAW frames (.dng or camera raw) into <scene>/raw/")
    files: dict[str, pathlib.Path] = {}
    for p in sorted(raw_dir.iterdir()):
        if p.is_file() and p.suffix.lower() in RAW_EXTENSIONS:
            if p.stem not in files or p.suffix.lower() == ".dng":
                files[p.stem] = p
    if not files:
        raise SceneError(raw_dir, "raw/ holds no RAW frames",
                         f"put the RAW frames ({', '.join(RAW_EXTENSIONS[:5])}, ...) into it")
    return files


def _exiftool_exposure(path: pathlib.Path) -> tuple[float | None, float | None]:
    """(ExposureTime, ISO) from an exiftool JSON sidecar; (None, None) when absent."""
    if not path.is_file():
        return None, None
    try:
        meta = json.loads(path.read_text())
        meta = meta[0] if isinstance(meta, list) else meta
    except (OSError, ValueError, IndexError, KeyError) as exc:
        raise SceneError(path, f"cannot read the exiftool JSON ({exc})",
                         "re-create it with `exiftool -json` or delete it") from None

    def number(x):
        if x is None:
            return None
        if isinstance(x, str) and "/" in x:
            num, den = x.split("/", 1)
            return float(num) / float(den)
        value = float(x)
        return value if value > 0 else None

    try:
        return number(meta.get("ExposureTime")), number(meta.get("ISO"))
    except (TypeError, ValueError, ZeroDivisionError, AttributeError):
        raise SceneError(path, "ExposureTime/ISO are not numbers",
                         "re-create it with `exiftool -json` or delete it") from None


def _relative_exposure(times, isos, names=None) -> np.ndarray:
    """(N,) exposure time x ISO of each frame over the median frame's; a quantity that some
    frames lack is left out for all of them (with a warning naming those frames)."""
    exposure = np.ones(len(times))
    for what, values in (("exposure time", times), ("ISO", isos)):
        known = [v is not None and v > 0 for v in values]
        if all(known):
            exposure *= np.asarray(values, dtype=np.float64)
        elif any(known):
            lacking = [str(names[k]) if names is not None else str(k)
                       for k, ok in enumerate(known) if not ok]
            warnings.warn(f"{len(lacking)} of {len(values)} frames have no {what} "
                          f"({', '.join(lacking[:5])}): {what} differences between the "
                          "frames are ignored (add it to the files or a .json sidecar)",
                          stacklevel=3)
    return exposure / np.median(exposure)


def _read_frames(names, files: dict[str, pathlib.Path]):
    """Read every frame into one (N, H, W) uint16 array plus per-frame metadata."""
    first = None
    meta = {"black": [], "white": [], "neutral": [], "time": [], "iso": [], "matrix": [],
            "converted": []}
    raw_bayer = None
    for k, name in enumerate(names):
        frame = raw.read_raw(files[name])
        if first is None:
            first = frame
            if sorted(frame.cfa.ravel().tolist()) != [0, 1, 1, 2]:
                raise SceneError(frame.path, f"unsupported CFA {frame.cfa.tolist()}",
                                 "use a 2x2 RGB Bayer sensor")
            raw_bayer = np.empty((len(names), *frame.raw_bayer.shape), np.uint16)
        elif frame.raw_bayer.shape != first.raw_bayer.shape:
            odd, other = frame, first
            if k == 1 and len(names) > 2:  # frame 0 may be the odd one: a third frame decides
                third = raw.read_raw(files[names[2]])
                if third.raw_bayer.shape == frame.raw_bayer.shape:
                    odd, other = first, frame
            (h, w), (oh, ow) = odd.raw_bayer.shape, other.raw_bayer.shape
            raise SceneError(odd.path, f"frame is {w}x{h} but {pathlib.Path(other.path).name} "
                             f"is {ow}x{oh}",
                             "all frames must have one size: remove or re-export this frame")
        elif not np.array_equal(frame.cfa, first.cfa):
            turned = (f" (Orientation {frame.converted.orientation}, that frame's "
                      f"{first.converted.orientation})" if frame.converted.orientation
                      != first.converted.orientation else "")
            raise SceneError(frame.path, f"CFA pattern {frame.cfa.tolist()} differs from "
                             f"{first.cfa.tolist()} of {pathlib.Path(first.path).name}{turned}",
                             "use frames from one camera (one CFA layout) held one way up")
        raw_bayer[k] = frame.raw_bayer
        sidecar_time, sidecar_iso = _exiftool_exposure(files[name].with_suffix(".json"))
        meta["black"].append(frame.black_level)
        meta["white"].append(frame.white_level)
        meta["matrix"].append(frame.xyz_to_cam)
        meta["neutral"].append(frame.as_shot_neutral)
        meta["time"].append(sidecar_time or frame.exposure_time)
        meta["iso"].append(sidecar_iso or frame.iso)
        meta["converted"].append(frame.converted)
    return first, raw_bayer, meta


def _check_displayed_size(source: pathlib.Path, cams: Cameras, width: int, height: int):
    """SceneError naming transforms.json unless its w x h is the frames' size as displayed
    (the files' DefaultCrop and Orientation applied), or that size uniformly scaled to
    within a pixel (intrinsics given for previews)."""
    if (cams.width, cams.height) == (width, height):
        return
    if abs(cams.height * width / cams.width - height) > 1.0:
        raise SceneError(source, f"it describes {cams.width}x{cams.height} images but the raw "
                         f"frames are {width}x{height} as displayed (after their DefaultCrop "
                         "and Orientation tags)", "give w, h and the intrinsics of the image "
                         "as displayed, or re-run `gridnerf poses`")


def _poses(scene: pathlib.Path, files):
    """(names, cameras or None, split, near_far, source, colmap points or None)."""
    transforms, sparse, llff = (scene / "transforms.json", scene / "sparse" / "0",
                                scene / "poses_bounds.npy")
    if transforms.is_file():
        cams, split, near_far = pose_files.load_transforms(transforms)
        missing = [n for n in cams.names if n not in files]
        if missing:
            raise SceneError(transforms, f"frames {missing[:5]} have no raw file in raw/",
                             "add the raw files or remove those frames from transforms.json")
        unused = sorted(set(files) - set(cams.names))
        if unused:
            warnings.warn(f"{transforms}: {len(unused)} raw file(s) in raw/ have no frame "
                          f"entry ({', '.join(unused[:5])}{', ...' if len(unused) > 5 else ''})"
                          "; they are not used (add them to `frames` to train on them)",
                          stacklevel=3)
        return cams.names, cams, split, near_far, transforms, None
    names = tuple(sorted(files))
    if sparse.is_dir():
        cams, points = pose_files.load_colmap(sparse, names)
        return names, cams, None, None, sparse, points
    if llff.is_file():
        return names, None, None, None, llff, None
    raise PoseError(scene, "no camera poses (transforms.json, sparse/0 or poses_bounds.npy)",
                    _POSES_FIX)


class BoundsMissing(PoseError):
    """The scene's files give no near/far; `cameras` (the given poses) let gridnerf.bounds
    estimate them (train.py does, and stores them in the run folder)."""

    def __init__(self, scene: pathlib.Path, cameras: Cameras):
        super().__init__(scene, "no near/far scene bounds (no near_far in transforms.json, no "
                         "poses_bounds.npy, no COLMAP points)",
                         "`gridnerf train` estimates them; elsewhere pass near_far")
        self.cameras = cameras


def _near_far(scene: pathlib.Path, near_far, colmap_points, colmap_cams) -> tuple[float, float]:
    if near_far is not None:
        return near_far
    llff = scene / "poses_bounds.npy"
    if llff.is_file():
        arr = np.load(llff)
        if arr.ndim == 2 and arr.shape[1] == 17:
            near, far = float(arr[:, 15].min()), float(arr[:, 16].max())
            if 0 < near < far and np.isfinite(far):
                return near, far
        raise SceneError(llff, "bounds are not positive, finite near < far",
                         "fix poses_bounds.npy or add near_far to transforms.json")
    sparse = scene / "sparse" / "0"
    if colmap_points is None and sparse.is_dir():
        colmap_cams, colmap_points = pose_files.load_colmap(sparse)
    if colmap_points is not None and len(colmap_points):
        bounds = cam_mod.bounds_from_points(colmap_cams, colmap_points)
        if bounds is not None and 0 < bounds[0] < bounds[1]:
            return bounds
    raise BoundsMissing(scene, colmap_cams)


def load_scene(path, near_far: tuple[float, float] | None = None) -> Scene:
    """Load a scene folder (module docstring). Raises SceneError/PoseError/RawError.

    near_far: (near, far) in the input world's units, used instead of the files' bounds
    (e.g. estimated by gridnerf.bounds); without it and without bounds in the files the
    scene raises BoundsMissing before any frame is read.
    """
    scene = pathlib.Path(path)
    if not scene.is_dir():
        raise SceneError(scene, "scene folder does not exist",
                         "check the path, or create one with `gridnerf simulate`")
    files = raw_files(scene)
    names, cams, split, file_near_far, source, points = _poses(scene, files)
    if cams is not None:
        near, far = near_far or _near_far(scene, file_near_far, points, cams)
    first, raw_bayer, meta = _read_frames(names, files)
    tag_lines, lens_correction = raw_layout.describe(meta["converted"], first.cfa,
                                                     scene / "raw")
    for line in tag_lines:
        print(line)
    height, width = raw_bayer.shape[1:]
    if cams is None:
        cams, _ = pose_files.load_llff(source, names, width, height)
        near, far = near_far or _near_far(scene, file_near_far, points, cams)
    if source.name == "transforms.json":
        _check_displayed_size(source, cams, width, height)
    cams = cam_mod.resize_to(cams, width, height, source)
    cam_mod.validate(cams, source)

    c2w, near_n, far_n, world_from_norm = rays.normalize_world(cams.c2w, near, far)
    if split is None:
        test = np.arange(0, len(names), 8)
        train = np.setdiff1d(np.arange(len(names)), test)
    else:
        index = {n: k for k, n in enumerate(names)}
        train = np.array([index[n] for n in split["train"]], dtype=int)
        test = np.array([index[n] for n in split["test"]], dtype=int)
    if not first.has_color_matrix:
        warnings.warn(f"{first.path}: the RAW file has no colour matrix; sRGB primaries are "
                      "assumed, so colours may be off (use files with a ColorMatrix tag)",
                      stacklevel=2)
    bad = metadata_outliers(meta, float(meta["white"][0] - np.max(meta["black"][0])))
    bad.update({k: why for k, why in unusable_frames(
        raw_bayer, np.stack(meta["black"]), np.asarray(meta["white"]),
        where=scene / "raw").items() if k not in bad})
    for k, why in bad.items():
        warnings.warn(f"{files[names[k]]}: {why}; the frame is left out", stacklevel=2)
    train = np.array([k for k in train if k not in bad], dtype=int)
    test = np.array([k for k in test if k not in bad], dtype=int)
    if train.size == 0:
        raise SceneError(source, "the training split is empty" + (
            f" ({len(bad)} of {len(names)} frames are unusable: dark, clipped or corrupt)"
            if bad else ""), "list some usable frames in train_filenames (or remove the split)")
    black, white = np.stack(meta["black"]).astype(np.float32), np.asarray(meta["white"])
    usable = [k for k in range(len(names)) if k not in bad]
    defect_mask, why = defects.defective_pixels(
        raw.normalize_mosaic(raw_bayer[k], black[k], white[k]) for k in usable)
    if why:
        print(f"sensor: {why}")
    levels = [c.baseline_exposure for c in meta["converted"]]
    gt = scene / "gt"
    return Scene(
        path=scene,
        names=tuple(names),
        cameras=cams.with_c2w(c2w),
        raw_bayer=raw_bayer,
        black_level=black,
        white_level=np.asarray(meta["white"], np.float32),
        cfa=np.asarray(first.cfa, int),
        xyz_to_cam=np.asarray(first.xyz_to_cam, np.float64),
        as_shot_neutral=np.stack(meta["neutral"]).astype(np.float64),
        exposure=_relative_exposure(meta["time"], meta["iso"], names),
        train_idx=train,
        test_idx=test,
        near=float(near_n),
        far=float(far_n),
        forward_facing=rays.forward_facing(c2w),
        gt_srgb_paths={n: gt / f"{n}.png" for n in names if (gt / f"{n}.png").is_file()},
        gt_linear_paths={n: gt / f"{n}.exr" for n in names if (gt / f"{n}.exr").is_file()},
        world_from_normalized=world_from_norm,
        camera_model=first.camera_model,
        white_reference=(white_reference.from_transforms(scene / "transforms.json")
                         if (scene / "transforms.json").is_file() else None),
        defects=defect_mask,
        lens_correction=lens_correction,
        baseline_exposure=(np.asarray(levels, np.float64)
                           if all(v is not None for v in levels) else None),
    )
