"""A white reference: a grey card or white patch in one frame that sets the capture's light.

For users who need exact colour. Named in transforms.json,

    "white_reference": {"frame": "frame_003", "box": [x, y, w, h]}

(the frame's name as in its file_path, the box in that frame's raw pixels), or given on
the command line, `gridnerf train <scene> --white-ref frame_003:x,y,w,h`, which wins. The
light is the box's mean colour in camera RGB (2x2-binned frame, black level removed, no
clipped pixel: estimate), so a neutral card under the light reads as the light itself.
A light measured elsewhere (a grey card shot with the same camera under the same light,
its camera RGB after the black level: what a custom white balance records as
AsShotNeutral) is given as {"camera_rgb": [r, g, b]} or `--white-ref rgb:r,g,b`. It
replaces the illuminant estimators and the Planckian-locus prior: the L_ca target's
anchor (colour_target.plan_colour). A box that is not a usable reference (outside the
frame, clipped, too dark or too small for its mean to stand above the noise) is refused
with one line naming it and the fix.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gridnerf.errors import SceneError

KEY = "white_reference"
# every channel's box mean must stand this many standard errors above zero
MIN_SNR = 20.0
MIN_BINNED_PIXELS = 16


@dataclass(frozen=True)
class WhiteRef:
    """frame: a frame's name; box: (x, y, w, h) in that frame's raw pixels; source: where
    it was given (for messages); camera_rgb: (3,) a light measured elsewhere, in camera RGB
    (frame and box then empty)."""

    frame: str
    box: tuple[int, ...]
    source: str = "--white-ref"
    camera_rgb: tuple[float, float, float] | None = None

    def spec(self) -> str:
        if self.camera_rgb is not None:
            return "rgb:" + ",".join(f"{v:.6g}" for v in self.camera_rgb)
        return f"{self.frame}:{','.join(str(v) for v in self.box)}"


def _light(values, where: str | None, field: str) -> WhiteRef:
    try:
        rgb = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        rgb = ()
    if len(rgb) != 3 or not all(np.isfinite(rgb)) or min(rgb) <= 0.0:
        raise SceneError(where, f"{field} is {values!r}, not a light's camera RGB",
                         "give three positive numbers r,g,b (a grey card's camera RGB "
                         "after the black level, any scale)")
    return WhiteRef("", (), where or "--white-ref", rgb)


def _box(values, where: str, field: str) -> tuple[int, int, int, int]:
    try:
        box = tuple(int(v) for v in values)
    except (TypeError, ValueError):
        box = ()
    if len(box) != 4 or box[0] < 0 or box[1] < 0 or box[2] <= 0 or box[3] <= 0:
        raise SceneError(where, f"{field} is {values!r}, not a pixel box x,y,w,h",
                         "give four whole numbers: left, top, width, height (width and "
                         "height > 0)")
    return box


def parse(spec: str) -> WhiteRef:
    """WhiteRef from "frame:x,y,w,h" or "rgb:r,g,b" (the command line's --white-ref)."""
    if ":" not in spec:
        raise SceneError(None, f"--white-ref {spec!r} has no frame name",
                         "give it as <frame>:<x>,<y>,<w>,<h>, e.g. frame_003:120,80,24,24")
    frame, box = spec.rsplit(":", 1)
    if frame.strip() == "rgb":
        return _light(box.split(","), None, f"--white-ref {spec!r}")
    return WhiteRef(frame.strip(), _box(box.split(","), None, f"--white-ref box {box!r}"))


def from_transforms(path: Path) -> WhiteRef | None:
    """The white_reference of a transforms.json, None where it has none."""
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # pose_files.load_transforms reports an unreadable file
    ref = meta.get(KEY) if isinstance(meta, dict) else None
    if ref is None:
        return None
    if isinstance(ref, dict) and "camera_rgb" in ref:
        return _light(ref["camera_rgb"], str(path), f"{KEY}.camera_rgb")
    if not isinstance(ref, dict) or not isinstance(ref.get("frame"), str) or "box" not in ref:
        raise SceneError(path, f"{KEY} is {ref!r}",
                         'give {"frame": "<name>", "box": [x, y, w, h]} or '
                         '{"camera_rgb": [r, g, b]}, or remove it')
    frame = Path(ref["frame"]).stem
    return WhiteRef(frame, _box(ref["box"], str(path), f"{KEY}.box"), str(path))


def estimate(scene, ref: WhiteRef) -> np.ndarray:
    """(3,) unit camera RGB: the light as the reference's box reads it (module docstring).
    SceneError where the frame is unknown or the box is not usable."""
    if ref.camera_rgb is not None:
        rgb = np.asarray(ref.camera_rgb, np.float64)
        return rgb / np.linalg.norm(rgb)
    where = ref.source
    if ref.frame not in scene.names:
        raise SceneError(where, f"white reference frame {ref.frame!r} is not one of the "
                         f"scene's frames ({', '.join(scene.names[:4])}, ...)",
                         "name a frame as in its file_path, without the extension")
    i = scene.names.index(ref.frame)
    rgb_cam, valid = scene.rgb_cam_binned(i)
    h, w = rgb_cam.shape[0] * 2, rgb_cam.shape[1] * 2
    x, y, bw, bh = ref.box
    if x + bw > w or y + bh > h:
        raise SceneError(where, f"white reference box {ref.box} reaches outside frame "
                         f"{ref.frame!r} ({w}x{h} pixels)", "give a box inside the frame")
    rows, cols = slice(y // 2, (y + bh + 1) // 2), slice(x // 2, (x + bw + 1) // 2)
    pix = np.asarray(rgb_cam[rows, cols], np.float64).reshape(-1, 3)
    ok = np.asarray(valid[rows, cols]).reshape(pix.shape[0], -1).all(-1)
    if ok.sum() < MIN_BINNED_PIXELS:
        raise SceneError(where, f"white reference box {ref.box} of {ref.frame!r} has "
                         f"{int(ok.sum())} unclipped 2x2 blocks, under {MIN_BINNED_PIXELS}",
                         "give a larger box on the card, away from clipped highlights")
    pix = pix[ok]
    mean = pix.mean(0)
    stderr = pix.std(0) / np.sqrt(len(pix))
    if np.any(mean <= MIN_SNR * np.maximum(stderr, 1e-12)):
        weak = "RGB"[int(np.argmin(mean / np.maximum(stderr, 1e-12)))]
        raise SceneError(where, f"white reference box {ref.box} of {ref.frame!r} is too dark "
                         f"or too small: its {weak} mean is within {MIN_SNR:g} standard "
                         "errors of zero", "give a larger box, on a brighter grey or white "
                         "surface")
    return mean / np.linalg.norm(mean)
