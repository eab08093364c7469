"""Frames that load but are wrong, found against the scene's other frames: a header that
disagrees (metadata_outliers), pixel values no sensor can read (impossible_values), dark,
clipped or corrupt frames (unusable_frames). gridnerf.scene leaves them out with a warning.
"""

from __future__ import annotations

import pathlib

import numpy as np

from gridnerf.errors import SceneError


def metadata_outliers(meta: dict, first_range: float) -> dict[int, str]:
    """Frames whose header disagrees with the scene's other frames (a corrupted header
    reads as a different white level, black level or colour matrix): {index: reason}.

    meta: per-frame lists "white" (N,), "black" (N, 2, 2), "matrix" (N, 3, 3). The
    reference is the most common white level and matrix and the median black level; black
    levels may drift by 1 % of the white-black range (cameras that measure it per frame).
    """
    white = np.asarray(meta["white"], np.float64)
    black = np.asarray(meta["black"], np.float64)
    matrix = np.asarray(meta["matrix"], np.float64)
    values, counts = np.unique(white, return_counts=True)
    white_ref = values[np.argmax(counts)]
    keys = [m.round(4).tobytes() for m in matrix]
    matrix_ref = matrix[max(range(len(keys)), key=keys.count)]
    black_ref = np.median(black, axis=0)
    bad = {}
    for k in range(len(white)):
        if white[k] != white_ref:
            bad[k] = f"white level {white[k]:g} differs from the other frames' {white_ref:g}"
        elif np.abs(black[k] - black_ref).max() > 0.01 * first_range:
            bad[k] = (f"black level {black[k].ravel().tolist()} differs from the other "
                      f"frames' {black_ref.ravel().tolist()}")
        elif not np.allclose(matrix[k], matrix_ref, rtol=1e-3, atol=1e-4):
            bad[k] = "colour matrix differs from the other frames'"
    return {k: f"{why} (corrupt header?)" for k, why in bad.items()}


def impossible_values(raw_bayer: np.ndarray, black: np.ndarray, white: np.ndarray,
                      below: float = 0.05) -> np.ndarray:
    """(N,) count of pixel values no sensor reading can have: above the white level, or
    more than `below` x (white - black) under the black level (read noise is a few DN;
    14-bit frames have ~16k DN of range). Overwritten bytes in a frame's pixel data read
    as random 16-bit values, most of them above a 12- or 14-bit white level.
    raw_bayer: (N, H, W) uint16; black: (N, 2, 2); white: (N,)."""
    counts = np.zeros(len(raw_bayer), np.int64)
    for k, frame in enumerate(raw_bayer):
        low = float(black[k].min()) - below * float(white[k] - black[k].max())
        counts[k] = np.count_nonzero(frame > white[k]) + np.count_nonzero(frame < low)
    return counts


def unusable_frames(raw_bayer: np.ndarray, black: np.ndarray, white: np.ndarray,
                    dark_ratio: float = 0.25, bright_ratio: float = 4.0,
                    clipped_max: float = 0.2, corrupt_max: float = 1e-4,
                    where: str | pathlib.Path | None = None) -> dict[int, str]:
    """Frames that are readable but wrong, compared with the scene's other frames.

    raw_bayer: (N, H, W) uint16; black: (N, 2, 2); white: (N,). Per frame, on every 4th
    pixel: the mean normalised signal and the clipped fraction; on every pixel: the values
    outside what a sensor can read (impossible_values). A frame is unusable when more than
    corrupt_max of its pixels are impossible (corrupt data), its signal is below dark_ratio
    or above bright_ratio times the median frame's (a black frame, a frame from another
    exposure), or more than clipped_max of it is clipped.
    Returns {frame index: reason}. Raises SceneError naming `where` (the frames' folder)
    when every frame is at the black level (nothing to learn from).
    """
    sub = raw_bayer[:, ::4, ::4].astype(np.float32)
    level = (sub - black[:, :1, :1]) / (white - black[:, 0, 0])[:, None, None]
    mean = level.reshape(len(sub), -1).mean(axis=1)
    clipped = (sub >= white[:, None, None]).reshape(len(sub), -1).mean(axis=1)
    # one DN above black on average: below that there is no signal at all
    floor = 1.0 / float(np.max(white - black[:, 0, 0]))
    if np.all(mean < floor):
        raise SceneError(where, f"every frame is at the black level (mean signal "
                         f"{float(mean.max()):.2g} of the white level)",
                         "check the exposure, the lens cap and the black level in the RAW files")
    med = float(np.median(mean))
    impossible = impossible_values(raw_bayer, black, white)
    bad = {}
    for k in range(len(sub)):
        if impossible[k] > corrupt_max * raw_bayer[k].size:
            bad[k] = (f"{impossible[k]} pixel values lie outside the sensor's range "
                      "(above the white level or far below black): corrupt pixel data")
        elif clipped[k] > clipped_max:
            bad[k] = f"{100 * clipped[k]:.0f}% of the pixels are clipped"
        elif mean[k] < dark_ratio * med:
            bad[k] = f"signal {mean[k]:.3g} is below {dark_ratio} x the scene median {med:.3g}"
        elif mean[k] > bright_ratio * med:
            bad[k] = f"signal {mean[k]:.3g} is above {bright_ratio} x the scene median {med:.3g}"
    return bad
