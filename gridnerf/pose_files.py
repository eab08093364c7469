"""Pose files: nerfstudio `transforms.json`, COLMAP `sparse/0` and LLFF `poses_bounds.npy`.

Each reader returns a gridnerf.cameras.Cameras (camera-to-world in OpenGL axes, intrinsics
in pixels of the full-resolution frame, pixel centres at +0.5) and what else the file
holds; every problem in a file is one SceneError or PoseError naming the file and field.
COLMAP is read binary or text via pycolmap. Lens distortion (SIMPLE_RADIAL, RADIAL, OPENCV)
is ignored: the renderer is a pure pinhole model, which is accurate for the small
distortions of the previews COLMAP sees; undistort the images first if the lens distorts
strongly.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gridnerf import atomic, cameras
from gridnerf.errors import PoseError, SceneError

# OpenCV camera axes (x right, y down, z forward) <-> OpenGL (x right, y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0])
_COLMAP_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def _stem(file_path: str) -> str:
    return Path(str(file_path)).stem


def _is_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _kind(v) -> str:
    return {dict: "object", list: "list", str: "string", type(None): "null", bool: "boolean"
            }.get(type(v), "number" if _is_number(v) else type(v).__name__)


def _describe(v) -> str:
    text = json.dumps(v) if isinstance(v, str | type(None) | bool) else _kind(v)
    return text if len(text) <= 40 else text[:37] + "..."


def _matrix(v) -> np.ndarray | None:
    """A list of equal-length rows of numbers as a float64 array; None otherwise (ragged,
    strings, nesting)."""
    if not isinstance(v, list) or not v:
        return None
    if not all(isinstance(r, list) and len(r) == len(v[0]) and all(_is_number(x) for x in r)
               for r in v):
        return None
    return np.asarray(v, dtype=np.float64)


_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x")


def _intrinsics(frame: dict, base: dict, path, where: str):
    """(fx, fy, cx, cy, w, h) of one frame: its own keys override the top level's."""
    merged = {**base, **{k: frame[k] for k in _INTRINSIC_KEYS if k in frame}}
    for key in ("w", "h"):
        v = merged.get(key)
        if key in merged and not (_is_number(v) and v == int(v) and v > 0):
            src = "the frame" if key in frame else "the top level"
            raise SceneError(path, f"{where}: {key} is {v!r} (from {src})",
                             f"give {key} as the raw frame's {'width' if key == 'w' else 'height'}"
                             " in pixels (a whole number > 0)")
    try:
        w, h = int(merged["w"]), int(merged["h"])
        if "fl_x" in merged:
            fx = float(merged["fl_x"])
        else:
            fx = 0.5 * w / np.tan(0.5 * float(merged["camera_angle_x"]))
        fy = float(merged.get("fl_y", fx))
        cx = float(merged.get("cx", w / 2.0))
        cy = float(merged.get("cy", h / 2.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneError(
            path, f"{where}: missing or invalid intrinsics ({exc!r})",
            "add fl_x, fl_y, cx, cy, w, h (pixels of the raw frame) at the top level",
        ) from None
    return fx, fy, cx, cy, w, h


def load_transforms(path) -> tuple[cameras.Cameras, dict | None, tuple[float, float] | None]:
    """Read a nerfstudio transforms.json.

    Returns (cameras, split, near_far): split is {"train": [stems], "test": [stems]} or None,
    near_far is (near, far) in world units or None. Per-frame intrinsics override the top
    level; train/test entries may be file_path values or stems.
    """
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SceneError(path, f"cannot read transforms.json ({exc})",
                         "fix the JSON or delete it and run `gridnerf poses`") from None
    if not isinstance(meta, dict):
        raise SceneError(path, "transforms.json is not a JSON object",
                         "give an object with frames (or run `gridnerf poses`)")
    frames = meta.get("frames")
    if not frames:
        raise SceneError(path, "no frames listed", "add frames or run `gridnerf poses`")
    if not isinstance(frames, list):
        raise SceneError(path, f"frames is a {_kind(frames)}, not a list",
                         "give frames as a list of {file_path, transform_matrix} objects")
    base = {k: meta[k] for k in _INTRINSIC_KEYS if k in meta}
    names, c2ws, intr = [], [], []
    for k, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise SceneError(path, f"frame {k} is a {_kind(frame)}, not an object",
                             "give each frame as {file_path, transform_matrix}")
        if "file_path" not in frame:
            raise SceneError(path, f"frame {k} has no file_path", "add file_path: raw/<name>.dng")
        if not isinstance(frame["file_path"], str) or not frame["file_path"].strip():
            raise SceneError(path, f"frame {k}: file_path is {frame['file_path']!r}",
                             "give the raw file's path as a string, e.g. raw/<name>.dng")
        name = _stem(frame["file_path"])
        if "transform_matrix" not in frame:
            raise PoseError(path, f"frame {name!r} has no transform_matrix (no pose)",
                            "run `gridnerf poses` or remove the frame")
        m = _matrix(frame["transform_matrix"])
        if m is None or m.shape not in ((4, 4), (3, 4)):
            found = f"shape {m.shape}" if m is not None else _describe(frame["transform_matrix"])
            raise PoseError(path, f"frame {name!r}: transform_matrix is not a 4x4 matrix of "
                            f"numbers ({found})",
                            "give a 4x4 camera-to-world matrix as a list of 4 rows of 4 numbers")
        if name in names:
            raise SceneError(path, f"frame {name!r} is listed twice", "remove the duplicate")
        names.append(name)
        c2ws.append(m[:3])
        intr.append(_intrinsics(frame, base, path, f"frame {name!r}"))
    sizes = {(w, h) for *_, w, h in intr}
    if len(sizes) > 1:
        odd = next(n for n, i in zip(names, intr, strict=True) if i[4:] != intr[0][4:])
        raise SceneError(path, f"frame {odd!r} has size {intr[names.index(odd)][4:]} but "
                         f"frame {names[0]!r} has {intr[0][4:]}",
                         "all frames must have one size: remove or re-export the odd frame")
    fx, fy, cx, cy, w, h = (np.array(col) for col in zip(*intr, strict=True))
    cams = cameras.make_cameras(names, np.stack(c2ws), fx, fy, cx, cy, int(w[0]), int(h[0]))
    return cams, _read_split(meta, names, path), _read_near_far(meta, path)


def _read_split(meta: dict, names: list[str], path) -> dict | None:
    lists = {}
    choices = (("train", ("train_filenames",)), ("test", ("test_filenames", "val_filenames")))
    for key, keys in choices:
        for k in keys:
            if k in meta:
                v = meta[k]
                if not isinstance(v, list) or not all(isinstance(f, str) for f in v):
                    raise SceneError(path, f"{k} is {_describe(v)}, not a list of file paths",
                                     f"give {k} as a list like [\"raw/<name>.dng\", ...] or "
                                     "remove the key (every 8th frame is then a test frame)")
                lists[key] = [_stem(f) for f in v]
                break
    if not lists:
        return None
    for key, stems in lists.items():
        unknown = [s for s in stems if s not in names]
        if unknown:
            raise SceneError(path, f"{key} split names {unknown[:3]} that are not frames",
                             "list only frames present in `frames` (file_path or stem)")
        twice = sorted({s for s in stems if stems.count(s) > 1})
        if twice:
            raise SceneError(path, f"the {key} split lists {twice[:3]} more than once",
                             "list each frame once")
    if "train" in lists and "test" in lists:
        both = [s for s in lists["test"] if s in set(lists["train"])]
        if both:
            raise SceneError(path, f"frames {both[:3]} are in both the train and the test "
                             "split (a test view seen in training flatters every metric)",
                             "list each frame in one split only")
    if "train" not in lists:
        lists["train"] = [n for n in names if n not in set(lists["test"])]
    if "test" not in lists:
        lists["test"] = [n for n in names if n not in set(lists["train"])]
    return {"train": lists["train"], "test": lists["test"]}


def _read_near_far(meta: dict, path) -> tuple[float, float] | None:
    if "near_far" not in meta:
        return None
    try:
        near, far = (float(x) for x in meta["near_far"])
    except (TypeError, ValueError):
        near, far = np.nan, np.nan
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise SceneError(path, f"near_far {meta['near_far']!r} is not [near, far] with "
                         "0 < near < far", "fix near_far or remove it")
    return near, far


def write_transforms(path, cams: cameras.Cameras, train_names, test_names, near_far=None) -> None:
    """Write cams as a nerfstudio transforms.json (atomic). file_path is raw/<name>.dng.

    train_names/test_names: stems; both None writes no split (the loader then takes every
    8th frame as a test frame). near_far: (near, far) in world units or None.
    """
    path = Path(path)
    shared = all(np.allclose(a, a[0]) for a in (cams.fx, cams.fy, cams.cx, cams.cy))
    meta: dict = {"camera_model": "OPENCV", "w": cams.width, "h": cams.height}
    if shared:
        meta.update(fl_x=float(cams.fx[0]), fl_y=float(cams.fy[0]),
                    cx=float(cams.cx[0]), cy=float(cams.cy[0]))
    frames = []
    for i, name in enumerate(cams.names):
        m = np.eye(4)
        m[:3] = cams.c2w[i]
        frame = {"file_path": f"raw/{name}.dng", "transform_matrix": m.tolist()}
        if not shared:
            frame.update(fl_x=float(cams.fx[i]), fl_y=float(cams.fy[i]),
                         cx=float(cams.cx[i]), cy=float(cams.cy[i]))
        frames.append(frame)
    meta["frames"] = frames
    if train_names is not None or test_names is not None:
        meta["train_filenames"] = [f"raw/{n}.dng" for n in train_names or []]
        meta["test_filenames"] = [f"raw/{n}.dng" for n in test_names or []]
    if near_far is not None:
        meta["near_far"] = [float(near_far[0]), float(near_far[1])]
    atomic.write_text(path, json.dumps(meta, indent=2))


def load_colmap(sparse_dir, names=None) -> tuple[cameras.Cameras, np.ndarray]:
    """Read a COLMAP model (binary or text) -> (cameras, points3d (P, 3) float64).

    names: frame stems to return, in that order (PoseError if one is not registered);
    None returns every registered image sorted by name. OpenCV world-to-camera poses
    become OpenGL camera-to-world. Distortion parameters are ignored (module docstring).
    points3d keeps the points seen by 3+ images when the model has any.
    """
    import pycolmap

    sparse_dir = Path(sparse_dir)
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError
        raise SceneError(sparse_dir, f"cannot read the COLMAP model ({exc})",
                         "re-run `gridnerf poses`") from None
    by_stem = {_stem(im.name): im for im in rec.images.values() if im.has_pose}
    if names is None:
        names = sorted(by_stem)
    missing = [n for n in names if n not in by_stem]
    if missing:
        raise PoseError(sparse_dir, f"frames {missing[:5]} have no pose (COLMAP did not "
                        "register them)", "run `gridnerf poses` or remove the frame")
    if not names:
        raise PoseError(sparse_dir, "the model has no registered images", "run `gridnerf poses`")
    c2w, intr, sizes = [], [], set()
    for n in names:
        im = by_stem[n]
        w2c = im.cam_from_world().matrix()
        r_cv = w2c[:, :3].T
        c2w.append(np.concatenate([r_cv @ _CV_TO_GL, (-r_cv @ w2c[:, 3])[:, None]], axis=1))
        cam = rec.cameras[im.camera_id]
        model, p = cam.model.name, np.asarray(cam.params, dtype=np.float64)
        if model not in _COLMAP_MODELS:
            raise SceneError(sparse_dir, f"unsupported COLMAP camera model {model}",
                             f"use one of {', '.join(_COLMAP_MODELS)}")
        if model in ("PINHOLE", "OPENCV"):
            intr.append(p[:4])
        else:
            intr.append(np.array([p[0], p[0], p[1], p[2]]))
        sizes.add((int(cam.width), int(cam.height)))
    if len(sizes) > 1:
        raise SceneError(sparse_dir, f"COLMAP cameras have different image sizes {sorted(sizes)}",
                         "use previews of one size")
    (w, h), intr = sizes.pop(), np.stack(intr)
    points = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    track = np.array([p.track.length() for p in rec.points3D.values()], dtype=int)
    if np.any(track >= 3):  # two-view points of small-baseline captures are the noisiest
        points = points[track >= 3]
    cams = cameras.make_cameras(names, np.stack(c2w), intr[:, 0], intr[:, 1], intr[:, 2],
                                intr[:, 3], w, h)
    return cams, points


def load_llff(poses_bounds_path, names, width: int, height: int
              ) -> tuple[cameras.Cameras, np.ndarray]:
    """Read LLFF poses_bounds.npy (N, 17) for frames `names` (sorted raw stems).

    Rows are a flattened 3x5 [down, right, backwards, position, (H, W, focal)] plus
    (near, far). Returns (cameras at width x height, bounds (N, 2)); the principal point
    is the image centre (LLFF's assumption).
    """
    path = Path(poses_bounds_path)
    try:
        arr = np.load(path)
    except (OSError, ValueError) as exc:
        raise SceneError(path, f"cannot read poses_bounds.npy ({exc})",
                         "re-create it or run `gridnerf poses`") from None
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise SceneError(path, f"expected an (N, 17) array, found shape {arr.shape}",
                         "re-create it with LLFF's imgs2poses or run `gridnerf poses`")
    if arr.shape[0] != len(names):
        raise SceneError(path, f"{arr.shape[0]} poses for {len(names)} raw frames",
                         "one row per raw frame (sorted by name): re-run `gridnerf poses`")
    poses = arr[:, :15].reshape(-1, 3, 5).astype(np.float64)
    down, right, back, pos = (poses[:, :, k] for k in range(4))
    c2w = np.stack([right, -down, back, pos], axis=2)
    h_file, w_file, focal = poses[0, :, 4]
    cams = cameras.make_cameras(names, c2w, focal, focal, w_file / 2.0, h_file / 2.0,
                        int(round(w_file)), int(round(h_file)))
    if (w_file, h_file) != (width, height):
        cams = cameras.rescale(cams, width / w_file, height / h_file, width, height, path)
    return cams, arr[:, 15:17].astype(np.float64)
