"""The black level measured from dark frames (lens-cap exposures) of the capture.

A RAW file records its black level (BlackLevel), but the dark signal of a real sensor sits
a few DN off it, differently per CFA position (the ELD noise model: Wei et al., "A
Physics-based Noise Formation Model for Extreme Low-light Raw Denoising", CVPR 2020;
gridnerf.sim hides such a bias of -2 to +4 DN, about +20 % of a blue signal of ~18 DN).
A field trained on the frames as they are learns mu + offset per colour: a colour cast
of the dark parts once the exposure is raised, and a shift of every illuminant estimate
made from the frames. Astrophotographers measure it the standard way, with a few frames
shot with the lens cap on at the capture's ISO and exposure time: their mean per CFA
position, less the file's black level, is the offset (2 frames of 480x270 photosites with
~7 DN of read noise and row noise: within 0.13 DN of the simulator's offsets on all 21
simulated scenes; docs/results.md).

Where `<scene>/dark/` holds such frames (any RAW format `raw/` takes), training checks the
file's black level against them (`data.black_offset = "file"`, the default: they replace it
where their offsets matter, data_term.black_level; "dark" requires them):
measures the offsets once (`measure`), keeps them in `<run>/black_level.json` and every
later load of the run's scene under that config (training, resume, evaluation:
runfolder.open_scene) adds them to the scene's black level (`apply`), so the data term,
the illuminant estimates and the noise fit all see the corrected frames. Without dark frames
the offsets could only be fitted from the noise against a render, which takes model error
for shot noise (a rejected alternative; docs/results.md).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from gridnerf import atomic, raw
from gridnerf.errors import SceneError

DARK_DIR = "dark"
BLACK_LEVEL = "black_level.json"  # in the run folder
# a lens-cap frame's mean may sit this far above the file's black level (fraction of
# white - black, ~160 DN at 14 bits): the offsets are a few DN, a light leak is more
NOT_DARK = 0.01
# How far off its file's black level a sensor's dark signal may sit per CFA position: -2 to
# +4 DN on the sensors the ELD noise model calibrated (Wei et al., CVPR 2020)
OFFSET_DN = 4.0
_FIX = ("shoot 1-4 frames with the lens cap on at the capture's ISO and exposure time into "
        "<scene>/dark/, or use data.black_offset=file")


def _raw_files(folder: Path) -> list[Path]:
    """RAW files in a folder, sorted ([] when it does not exist)."""
    from gridnerf.scene import RAW_EXTENSIONS

    return (sorted(p for p in folder.iterdir() if p.is_file()
                   and p.suffix.lower() in RAW_EXTENSIONS) if folder.is_dir() else [])


def has_dark_frames(scene_dir) -> bool:
    """Whether <scene>/dark holds RAW files (training checks the file's black level against
    them where it does; captures such as the paper's have none)."""
    return bool(_raw_files(Path(scene_dir) / DARK_DIR))


def dark_files(scene_dir) -> list[Path]:
    """RAW files in <scene>/dark, sorted (SceneError naming the folder when there are none)."""
    folder = Path(scene_dir) / DARK_DIR
    files = _raw_files(folder)
    if not files:
        raise SceneError(folder, "data.black_offset=dark needs dark frames and there are none",
                         _FIX)
    return files


def measure(scene_dir) -> dict:
    """Per-CFA black offsets from a scene folder's dark frames: {"offset_dn": (2, 2) list,
    DN above the file's black level per CFA position [row % 2][col % 2], "files": names,
    "read_sigma_dn": the frames' spread (row noise included)}.

    The first file of raw/ gives the size, CFA, black and white levels, ISO and exposure
    time the dark frames must share. SceneError (one line naming the dark frame or folder)
    when a dark frame cannot serve.
    """
    from gridnerf.scene import raw_files

    files = dark_files(scene_dir)
    first = raw.read_raw(next(iter(raw_files(Path(scene_dir)).values())))
    values, names = [], []  # per frame: (4, n) DN above the file's black, by CFA position
    for path in files:
        frame = raw.read_raw(path)
        _check(frame, first, path)
        blocks = _by_position(frame.raw_bayer, frame.black_level)
        mean = blocks.mean(axis=1).reshape(2, 2)  # per CFA position
        if np.any(mean > NOT_DARK * (frame.white_level - frame.black_level.max())):
            raise SceneError(path, f"is not dark: {float(mean.max()):.0f} DN above the black "
                             "level (a lens-cap frame sees no light)", _FIX)
        values.append(blocks)
        names.append(path.name)
    offset, sigma = _robust_mean(np.concatenate(values, axis=1))
    return {"offset_dn": offset.reshape(2, 2).tolist(), "files": names,
            "read_sigma_dn": float(sigma.mean())}


def _by_position(raw_bayer: np.ndarray, black_level) -> np.ndarray:
    """(H, W) mosaic and (2, 2) black level -> (4, n) DN above it, one row per CFA position
    (row-major: [0, 0], [0, 1], [1, 0], [1, 1]); an odd last row or column is cropped."""
    h, w = raw_bayer.shape
    blocks = raw_bayer[: h // 2 * 2, : w // 2 * 2].astype(np.float64).reshape(
        h // 2, 2, w // 2, 2) - np.asarray(black_level, np.float64)[None, :, None, :]
    return blocks.transpose(1, 3, 0, 2).reshape(4, -1)


def signal_dn(scene) -> np.ndarray:
    """(3,) mean signal of the scene's training frames per colour (R, G, B), in DN above the
    black level the scene carries (the file's, or with measured offsets applied)."""
    colour = np.asarray(scene.cfa).ravel()
    sums, counts = np.zeros(3), np.zeros(3)
    for i in scene.train_idx:
        blocks = _by_position(scene.raw_bayer[i], scene.black_level[i])
        np.add.at(sums, colour, blocks.sum(axis=1))
        np.add.at(counts, colour, blocks.shape[1])
    return sums / np.maximum(counts, 1)


def offset_shift(offset_dn, cfa, signal) -> float:
    """The largest share of a colour's mean signal that measured offsets move it by:
    max_c |mean offset over c's CFA positions| / signal_c (offset_dn: (2, 2) of measure;
    cfa: (2, 2) colour index per position; signal: (3,) of signal_dn, the file's level;
    inf where a colour's mean is <= 0)."""
    colour = np.asarray(cfa).ravel()
    sums, counts = np.zeros(3), np.zeros(3)
    np.add.at(sums, colour, np.ravel(offset_dn))
    np.add.at(counts, colour, 1)
    shift = np.abs(sums / np.maximum(counts, 1))
    signal = np.asarray(signal, np.float64)
    return float(np.max(np.where(signal > 0, shift / np.maximum(signal, 1e-12), np.inf)))


def offset_share(signal) -> float:
    """OFFSET_DN over the weakest colour's mean signal (signal: (3,) of signal_dn): how large
    a share of that colour an unknown black offset may be (inf where a colour's mean is
    <= 0)."""
    weakest = float(np.min(signal))
    return OFFSET_DN / weakest if weakest > 0 else float("inf")


def too_weak(signal, share_max: float) -> bool:
    """Whether the file's black level cannot be trusted for this signal ((3,) of
    signal_dn): its offset_share is above share_max (data_term.LENS_CAP_SHARE; 0: never)."""
    return share_max > 0 and offset_share(signal) > share_max


def _robust_mean(values: np.ndarray, cut: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """(4, n) dark values -> per row (mean, std) of the values within `cut` robust sigmas
    (1.4826 MAD) of the median: hot and dead photosites left out; the read noise is
    symmetric, so the cut does not bias the mean."""
    med = np.median(values, axis=1, keepdims=True)
    mad = 1.4826 * np.median(np.abs(values - med), axis=1, keepdims=True)
    keep = np.abs(values - med) <= cut * np.maximum(mad, 1.0)
    n = keep.sum(axis=1)
    mean = (values * keep).sum(axis=1) / n
    var = ((values - mean[:, None]) ** 2 * keep).sum(axis=1) / n
    return mean, np.sqrt(var)


def _check(frame: raw.RawFrame, first: raw.RawFrame, path: Path) -> None:
    """SceneError unless `frame` was shot by the capture's sensor at its settings."""
    problem = None
    if frame.raw_bayer.shape != first.raw_bayer.shape:
        problem = (f"is {frame.raw_bayer.shape[1]}x{frame.raw_bayer.shape[0]} but the frames "
                   f"are {first.raw_bayer.shape[1]}x{first.raw_bayer.shape[0]}")
    elif not np.array_equal(frame.cfa, first.cfa):
        problem = f"has CFA {frame.cfa.tolist()}, the frames {first.cfa.tolist()}"
    elif (not np.allclose(frame.black_level, first.black_level)
          or frame.white_level != first.white_level):
        problem = (f"has black {frame.black_level.ravel().tolist()} / white "
                   f"{frame.white_level:g}, the frames {first.black_level.ravel().tolist()} / "
                   f"{first.white_level:g}")
    else:
        for what, a, b in (("ISO", frame.iso, first.iso),
                           ("exposure time", frame.exposure_time, first.exposure_time)):
            if a and b and abs(a - b) > 0.01 * b:
                problem = f"has {what} {a:g}, the frames {b:g}"
                break
    if problem:
        raise SceneError(path, problem, _FIX)


def save(run, record: dict) -> None:
    """<run>/black_level.json: the measured offsets (measure's record)."""
    atomic.write_text(Path(run) / BLACK_LEVEL, json.dumps(record, indent=2) + "\n")


def load(run) -> np.ndarray | None:
    """(2, 2) offsets in DN kept by the run, or None (no file: the file's black level)."""
    path = Path(run) / BLACK_LEVEL
    if not path.is_file():
        return None
    try:
        offset = np.asarray(json.loads(path.read_text())["offset_dn"], np.float64)
    except (ValueError, KeyError, TypeError):
        offset = None
    if offset is None or offset.shape != (2, 2) or not np.isfinite(offset).all():
        raise SceneError(path, "cannot read the run's measured black level",
                         "delete it to measure it again from the dark frames")
    return offset


def apply(scene, offset_dn):
    """The scene with (2, 2) offsets in DN added to every frame's per-CFA black level."""
    black = scene.black_level + np.asarray(offset_dn, np.float32)[None]
    return dataclasses.replace(scene, black_level=black.astype(np.float32))
