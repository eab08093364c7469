"""Render controls a photographer expects: exposure, white balance, size, a path of views.

`gridnerf render <run>` shows the run's main output (outputs.Output, exposed once per run
on the training render) along a camera path. These controls change how it is shown, never
the trained field:

- exposure compensation in stops: the auto exposure's alpha times 2**stops;
- white balance (`parse_white`), all von Kries gains in camera RGB, then the run's display
  matrix (exposure.display_matrix):
  - `learned`: the field's own gains (the default; one gain where the run shipped one),
  - `one_gain`: one grey-world gain for the whole scene (the field's low-light colour's
    grey world on the training render, outputs.global_gains),
  - `as_shot`: the files' AsShotNeutral (the camera's own white balance; mean over frames),
  - `temp:K[,DUV]`: a light at K kelvin on the Planckian locus, DUV off it (ANSI C78.377
    Duv: positive greener, negative more magenta; color.tinted_xyz_white), taken to camera
    RGB with the ColorMatrix the run took as the sensor's (ColourPlan.sensor_matrix),
  - `neutral:VIEW:X,Y[,W,H]`: the field's low-light colour of a picked neutral patch
    (pixel box in the render of frame VIEW at the render's size; 5x5 around X,Y unless
    W,H are given), the "click on something grey" of a raw converter;
  every white but `learned` is exposed again on the training render (the same auto
  exposure target), so a change of white does not change the brightness;
- size: `scale` times the capture's size (intrinsics scaled with it);
- camera paths: the spiral and ellipse around the capture (eval_run.camera_path), the test
  views, or a path through chosen frames (`views_path`: positions interpolated by
  Catmull-Rom splines, orientations by spherical linear interpolation).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from gridnerf import color, illuminant
from gridnerf.errors import ConfigError, SceneError

FORMATS = ("png", "exr", "mp4")  # what render writes: sRGB PNG, linear EXR, the path's video
WHITE_HELP = ("learned, one_gain, as_shot, temp:K[,DUV] (e.g. temp:3200,0.005) or "
              "neutral:VIEW:X,Y[,W,H] (e.g. neutral:frame_003:120,80)")
NEUTRAL_BOX = 5  # pixels on a side of a picked neutral point without W,H


@dataclass(frozen=True)
class White:
    """A white balance: mode in learned | one_gain | as_shot | temperature | neutral;
    kelvin, duv for temperature; view, box (x, y, w, h) for neutral."""

    mode: str = "learned"
    kelvin: float = 0.0
    duv: float = 0.0
    view: str = ""
    box: tuple[int, int, int, int] = (0, 0, 0, 0)


def _numbers(text: str, kind, what: str, spec: str) -> list:
    try:
        values = [kind(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(np.isfinite(values)):
        raise ConfigError(None, f"--white {spec!r}: {what} is not a list of numbers",
                          f"give --white as {WHITE_HELP}")
    return values


def parse_white(spec: str) -> White:
    """White from the command line's --white (module docstring); ConfigError (one line)
    for anything else."""
    spec = spec.strip()
    if spec in ("learned", "one_gain", "as_shot"):
        return White(spec)
    kind, _, rest = spec.partition(":")
    if kind == "temp" and rest:
        values = _numbers(rest, float, "the temperature", spec)
        if len(values) > 2 or not 1000.0 <= values[0] <= 25000.0 or (
                len(values) == 2 and abs(values[1]) > 0.05):
            raise ConfigError(None, f"--white {spec!r}: not a light 1000-25000 K with |Duv| "
                              "<= 0.05", "give temp:K or temp:K,DUV, e.g. temp:3200,0.005")
        return White("temperature", kelvin=values[0], duv=values[1] if len(values) == 2 else 0.0)
    if kind == "neutral" and ":" in rest:
        view, _, box = rest.rpartition(":")
        values = _numbers(box, int, "the pixel", spec)
        if len(values) == 2:
            values = [values[0] - NEUTRAL_BOX // 2, values[1] - NEUTRAL_BOX // 2,
                      NEUTRAL_BOX, NEUTRAL_BOX]
        if len(values) != 4 or values[2] <= 0 or values[3] <= 0:
            raise ConfigError(None, f"--white {spec!r}: not a pixel X,Y or a box X,Y,W,H",
                              "give neutral:VIEW:X,Y or neutral:VIEW:X,Y,W,H")
        return White("neutral", view=view, box=tuple(max(v, 0) for v in values[:2]) +
                     tuple(values[2:]))
    raise ConfigError(None, f"--white {spec!r} is not a white balance", f"give {WHITE_HELP}")


def view_index(scene, name: str) -> int:
    """Index of frame `name` in the scene (SceneError naming the known frames)."""
    if name not in scene.names:
        raise SceneError(scene.path, f"no frame named {name!r} (frames: "
                         f"{', '.join(scene.names[:4])}, ...)",
                         "name a frame as in transforms.json, without the extension")
    return scene.names.index(name)


def neutral_rgb(white: White, scene, render_frame, xyz_to_cam=None) -> np.ndarray | None:
    """(3,) unit camera RGB of the light the white balance undoes; None for learned and
    one_gain (their gains come from the run). render_frame(i) -> the render dict
    (H, W, ...) of frame i at the render's size, for a picked neutral point; xyz_to_cam:
    (3, 3) the sensor's matrix a temperature is taken through (the run's
    ColourPlan.sensor_matrix; None: the file's)."""
    if white.mode == "as_shot":
        per_frame = np.asarray(scene.as_shot_neutral, np.float64)
        per_frame /= np.linalg.norm(per_frame, axis=-1, keepdims=True)
        return np.asarray(illuminant.unit(per_frame.mean(0)))
    if white.mode == "temperature":
        xyz = color.tinted_xyz_white(white.kelvin, white.duv)
        matrix = scene.xyz_to_cam if xyz_to_cam is None else xyz_to_cam
        return np.asarray(illuminant.unit(np.asarray(matrix, np.float64) @ xyz))
    if white.mode == "neutral":
        out = render_frame(view_index(scene, white.view))
        rgb_low = np.asarray(out["rgb_low"], np.float64)
        x, y, w, h = white.box
        if x + w > rgb_low.shape[1] or y + h > rgb_low.shape[0]:
            raise SceneError(scene.path, f"neutral box {white.box} reaches outside the render "
                             f"({rgb_low.shape[1]}x{rgb_low.shape[0]} pixels)",
                             "pick a point inside the rendered view")
        patch = rgb_low[y:y + h, x:x + w].reshape(-1, 3).mean(0)
        if not np.all(np.isfinite(patch)) or patch.min() <= 0.0:
            raise SceneError(scene.path, f"neutral box {white.box} of {white.view!r} is "
                             "black in some colour: it cannot be a neutral",
                             "pick a grey or white surface")
        return np.asarray(illuminant.unit(patch))
    return None


def shown_output(shown: dict, main: str, white: White, neutral, stops: float,
                 training_out: dict, target: float):
    """The Output to render with: the run's `main` output with the white balance and
    exposure compensation applied. shown: the run's outputs (eval_run.run_outputs);
    neutral: neutral_rgb's light (None for learned / one_gain); training_out: the training
    render the auto exposure is set on; target: the run's output.target_luminance."""
    from gridnerf import outputs  # jax: not at import (the command line's help reads this)

    base = shown[main]
    if not isinstance(base, outputs.Output):
        if white.mode != "learned" or stops != 0.0:
            raise ConfigError(None, f"this run's output ({main}) is not exposed by gains",
                              "leave --white and --exposure out for this method")
        return base
    if white.mode == "one_gain":
        base = shown["global_grey_world"]
    elif neutral is not None:
        gains = np.asarray(illuminant.gains_from_illuminant(neutral), np.float64)
        candidate = outputs.Output("rgb_low", gains, shown["global_grey_world"].matrix)
        base = outputs.exposed({"w": candidate}, training_out, target)["w"]
    return replace(base, alpha=float(base.alpha * 2.0 ** stops))


def _catmull_rom(points: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n, 3) points on the uniform Catmull-Rom spline through (K, 3) `points` at
    parameters t in [0, K-1] (ends repeated, so the path passes through every point)."""
    p = np.concatenate([points[:1], points, points[-1:]])
    seg = np.minimum(np.floor(t).astype(int), len(points) - 2)
    s = (t - seg)[:, None]
    p0, p1, p2, p3 = p[seg], p[seg + 1], p[seg + 2], p[seg + 3]
    return 0.5 * (2 * p1 + (p2 - p0) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s ** 2
                  + (3 * p1 - p0 - 3 * p2 + p3) * s ** 3)


def views_path(c2w: np.ndarray, n_frames: int) -> np.ndarray:
    """(n_frames, 3, 4) camera-to-world poses through the (K >= 2, 3, 4) poses c2w in order:
    the first and last frames are the first and last poses."""
    c2w = np.asarray(c2w, np.float64)
    t = np.linspace(0.0, len(c2w) - 1, n_frames)
    slerp = Slerp(np.arange(len(c2w)), Rotation.from_matrix(c2w[:, :, :3]))
    rot = slerp(t).as_matrix()
    return np.concatenate([rot, _catmull_rom(c2w[:, :, 3], t)[:, :, None]], 2)


def parse_views(text: str, scene) -> list[int]:
    """Frame indices of a comma-separated list of at least two frame names."""
    names = [v.strip() for v in text.split(",") if v.strip()]
    if len(names) < 2:
        raise ConfigError(None, f"--views {text!r} names {len(names)} frame(s)",
                          "name at least two frames, e.g. --views frame_000,frame_008")
    return [view_index(scene, n) for n in names]
