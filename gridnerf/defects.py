"""Sensor defects: hot, stuck and dead pixels found from their recurrence across frames.

A defective photosite reads wrong at the same sensor position in every frame, whatever the
camera looks at; a scene's own bright or dark detail moves across the sensor as the camera
moves between views. So a pixel that stands out from its same-colour neighbours in most
frames of a capture is the sensor's, not the scene's: it is left out of the data term and
of the colour estimates (Scene.valid_mask), where a radiance field would otherwise try to
explain a fixed bright dot in 21 views as floating geometry.

The test per frame k: the pixel's deviation from the median of its 8 nearest neighbours
of the same CFA colour (two pixels away in the mosaic), over the noise sigma expected at
that level (robust_z: a + b * level fitted per CFA position to median absolute
deviations, which the scene's texture and the defects themselves barely move). A pixel is
defective where that z-score exceeds Z_DEFECT with the same sign (always too bright, or
always too dark) in at least RECUR_SHARE of the frames and at least MIN_FRAMES of them,
standing alone in each of those frames: fewer than NEIGHBOURS_MAX of the other pixels
within ISOLATION pixels (any CFA colour) stand out the same way by over half as much. A defect
is one photosite (or a pair); the scene's edges and lines, which a camera that barely
moves keeps at the same sensor positions, light up several neighbours at once. Without
that test, 64x36 simulated captures of 4 frames (bucket, box, scoreboard and dora at 40,
160 and 640 electrons) read 2-25 edge pixels as defects; with it, none below 640 electrons
and one at 640, while the simulated hot and stuck pixels of the quirky-camera captures are
found as before (20, 12 and 29 on held_quirk_brick, _shelf and _table).
Under Gaussian noise a |z| above 6 has a probability of 2e-9 per pixel and frame, so
noise alone does not recur in three quarters of the frames; the heavier tails of read noise at high
gain are checked on simulated frames (tests/test_defects.py: none found on a clean
sensor; none on any of the simulated scenes either).
"""

from __future__ import annotations

import itertools
from concurrent.futures import ThreadPoolExecutor

import numpy as np

# a pixel is an outlier in a frame where its |deviation| from its same-colour neighbours'
# median is above this many robust noise sigmas
Z_DEFECT = 6.0
# ... and defective where it is an outlier in at least this share of the frames
RECUR_SHARE = 0.75
# and in at least this many frames (a capture of one or two frames cannot tell)
MIN_FRAMES = 3
# more recurring outliers than this share of the sensor are the scene's, not defects (a
# sensor with a thousandth of its pixels defective would be mapped by its maker)
MAX_SHARE = 1e-3
# ... though a few dozen are believed whatever the sensor's size (a small frame of a few
# thousand pixels may hold a few dozen defects)
MAX_ALWAYS = 64
# an outlier counts in a frame only where fewer than this many other pixels within
# ISOLATION pixels (Chebyshev distance) stand out the same way by over Z_DEFECT / 2
NEIGHBOURS_MAX = 2
ISOLATION = 2
# the noise variance against the level is fitted to this many bins of equal count
LEVEL_BINS = 16
# frames read at once, each on its own thread
WORKERS = 2
# the 8 same-colour neighbours of a Bayer mosaic pixel: two pixels away
_OFFSETS = tuple((dy, dx) for dy in (-2, 0, 2) for dx in (-2, 0, 2) if (dy, dx) != (0, 0))


def neighbour_deviation(raw_norm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dev, level), each (H, W) float32: each pixel minus the median of its 8 same-colour
    neighbours, and that median.

    raw_norm: (H, W) the normalised mosaic ((raw - black) / (white - black)); the border
    is reflected by two pixels, which keeps each neighbour on the pixel's CFA colour."""
    x = np.asarray(raw_norm, np.float32)
    h, w = x.shape
    padded = np.pad(x, 2, mode="reflect")
    shifted = np.stack([padded[2 + dy:2 + dy + h, 2 + dx:2 + dx + w] for dy, dx in _OFFSETS])
    level = np.median(shifted, axis=0)
    return x - level, level


def _mad_var(d: np.ndarray) -> float:
    """The variance of Gaussian noise with the median absolute deviation of d."""
    return float((1.4826 * np.median(np.abs(d - np.median(d)))) ** 2)


def robust_z(dev: np.ndarray, level: np.ndarray) -> np.ndarray:
    """(H, W) dev over the noise sigma expected at its level, per CFA position (y % 2,
    x % 2): the variance is fitted as a + b * level (shot noise grows with the signal,
    read noise does not) to the robust variances (_mad_var) of LEVEL_BINS bins of equal
    count; a bright region's noise is then not read as defects. Zero where the fitted
    variance is not positive."""
    z = np.zeros_like(dev, np.float32)
    for py in (0, 1):
        for px in (0, 1):
            d, lv = dev[py::2, px::2].ravel(), level[py::2, px::2].ravel()
            order = np.argsort(lv)
            bins = np.array_split(order, LEVEL_BINS)
            x = np.array([np.median(lv[b]) for b in bins if b.size])
            v = np.array([_mad_var(d[b]) for b in bins if b.size])
            if x.size >= 2 and np.ptp(x) > 0:
                slope, intercept = np.polyfit(x, v, 1)
                slope = max(slope, 0.0)
                intercept = max(float(np.median(v - slope * x)), 0.0)
            else:
                slope, intercept = 0.0, _mad_var(d)
            var = intercept + slope * np.maximum(level[py::2, px::2], 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                z[py::2, px::2] = np.where(var > 0, dev[py::2, px::2] / np.sqrt(var), 0.0)
    return z


def _lone(z: np.ndarray, sign: float) -> np.ndarray:
    """(H, W) bool: sign * z > Z_DEFECT where fewer than NEIGHBOURS_MAX other pixels within
    ISOLATION pixels stand out the same way by over half as much (and over Z_DEFECT / 2):
    module docstring, a defect stands alone, the scene's edges do not. Only the outliers'
    windows are read (a few per frame)."""
    s = sign * z
    out = s > Z_DEFECT
    ys, xs = np.nonzero(out)
    if ys.size:
        r = ISOLATION
        window = np.pad(s, r)[ys[:, None, None] + np.arange(2 * r + 1)[:, None],
                              xs[:, None, None] + np.arange(2 * r + 1)]
        # the outlier itself stands out by more than half its own deviation: not counted
        count = (window > s[ys, xs, None, None] / 2).sum(axis=(1, 2)) - 1
        out[ys, xs] = count < NEIGHBOURS_MAX
    return out


def _outliers(raw_norm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(too bright, too dark): (H, W) bool each, the frame's lone outliers (_lone)."""
    z = robust_z(*neighbour_deviation(raw_norm))
    return _lone(z, 1.0), _lone(z, -1.0)


def defective_pixels(raw_norm_frames) -> tuple[np.ndarray | None, str]:
    """(mask, why): the sensor positions that are outliers (|robust_z| > Z_DEFECT) in at
    least RECUR_SHARE and MIN_FRAMES of the frames, each time standing alone (_lone), and
    one line saying what was decided.

    raw_norm_frames: an iterable of (H, W) normalised mosaics of one capture (one frame in
    memory at a time). mask: (H, W) bool, None where nothing is left out: no recurring
    outlier, fewer than MIN_FRAMES frames, or more than MAX_SHARE of the sensor (and more
    than MAX_ALWAYS pixels) recurring
    (frames that barely move keep the scene's own detail at the same pixels: they cannot
    tell a defect from a star or a lamp, so none is taken). why: "" where there is no
    recurring outlier at all."""
    high, low, n = None, None, 0
    frames = iter(raw_norm_frames)
    # two frames at a time on two threads (numpy's sorts and medians release the GIL: a
    # 1920x1080 capture's 24 frames took 14 s on one); the counts are the same either way
    with ThreadPoolExecutor(WORKERS) as pool:
        while chunk := list(itertools.islice(frames, WORKERS)):
            for hi, lo in pool.map(_outliers, chunk):
                high = hi.astype(np.int32) + (0 if high is None else high)
                low = lo.astype(np.int32) + (0 if low is None else low)
                n += 1
    if high is None or n < MIN_FRAMES:
        return None, ""
    mask = np.maximum(high, low) >= max(MIN_FRAMES, int(np.ceil(RECUR_SHARE * n)))
    found = int(mask.sum())
    if found == 0:
        return None, ""
    if found > max(MAX_SHARE * mask.size, MAX_ALWAYS):
        return None, (f"{found} pixels stand out from their neighbours at the same sensor "
                      f"position in over {RECUR_SHARE:.0%} of the {n} frames, more than "
                      f"{MAX_SHARE:g} of the sensor: the frames move too little to tell "
                      "defects from the scene's detail, so none is left out")
    return mask, (f"{found} defective pixels (hot, stuck or dead: outliers against their "
                  f"same-colour neighbours at the same sensor position in at least "
                  f"{RECUR_SHARE:.0%} of the {n} frames) are left out of the data term and "
                  "the colour estimates")
