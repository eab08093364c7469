"""Sensor defects are found from their recurrence at one sensor position across frames:
hot and stuck pixels on a moving camera are found exactly, a clean sensor gives none, and
frames that do not move give none (they cannot tell a defect from the scene's detail)."""

from __future__ import annotations

import numpy as np

from gridnerf import defects
from gridnerf.sim.sensor import tukey_lambda

H, W = 96, 128


def _scene(rng, h=H + 40, w=W + 40) -> np.ndarray:
    """A smooth textured radiance larger than the sensor, to be cropped per frame."""
    x = rng.uniform(0.0, 1.0, (h // 8, w // 8))
    x = np.kron(x, np.ones((8, 8)))
    k = np.ones(5) / 5.0  # blur: optics
    x = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 1, x)
    x = np.apply_along_axis(lambda c: np.convolve(c, k, mode="same"), 0, x)
    return 0.02 + 0.05 * x


def _frames(rng, n=12, move=True, electrons=40.0, k_gain=5.0, read=3.5, white=16383 - 512):
    """Normalised noisy mosaics of a camera that pans across _scene (or stays put)."""
    scene = _scene(rng)
    out = []
    for _ in range(n):
        dy, dx = ((rng.integers(0, 40), rng.integers(0, 40)) if move else (20, 20))
        signal = scene[dy:dy + H, dx:dx + W]
        e = rng.poisson(signal / signal.mean() * electrons)
        dn = k_gain * e + tukey_lambda(rng, (H, W), -0.075, read)
        out.append((dn / white).astype(np.float32))
    return out


def test_hot_and_stuck_pixels_are_found_where_they_recur():
    rng = np.random.default_rng(0)
    frames = _frames(rng)
    ys, xs = rng.integers(2, H - 2, 12), rng.integers(2, W - 2, 12)
    for f in frames:
        f[ys[:6], xs[:6]] += 0.3  # hot: a large excess in every frame
        f[ys[6:], xs[6:]] = 0.15  # stuck: one value whatever the light
    mask, why = defects.defective_pixels(frames)
    assert mask is not None and mask.shape == (H, W)
    expected = np.zeros((H, W), bool)
    expected[ys, xs] = True
    np.testing.assert_array_equal(mask, expected)
    assert f"{int(expected.sum())} defective pixels" in why


def test_a_clean_sensor_has_no_defects():
    """Shot noise and heavy-tailed read noise on a moving camera: nothing recurs."""
    for seed in range(3):
        mask, why = defects.defective_pixels(_frames(np.random.default_rng(seed), n=8,
                                                     electrons=5.0))
        assert mask is None and why == ""


def test_a_defect_seen_in_too_few_frames_is_kept():
    """An outlier in under RECUR_SHARE of the frames (a cosmic ray, a glint) stays."""
    rng = np.random.default_rng(1)
    frames = _frames(rng, n=10)
    for f in frames[:4]:
        f[40, 50] += 0.5
    mask, _ = defects.defective_pixels(frames)
    assert mask is None


def test_frames_that_do_not_move_cannot_tell_defects_from_detail():
    """A static camera over a sharp texture: the scene's own outliers recur at the same
    pixels; above MAX_SHARE of the sensor none is left out, and the line says why."""
    rng = np.random.default_rng(2)
    frames = _frames(rng, move=False, electrons=400.0)
    sharp = (rng.uniform(size=(H, W)) > 0.99) * 0.2  # point-like bright detail
    frames = [f + sharp.astype(np.float32) for f in frames]
    mask, why = defects.defective_pixels(frames)
    assert mask is None and "move too little" in why


def test_a_short_sharp_line_on_a_still_camera_is_not_a_row_of_defects():
    """Four frames of a camera that barely moves over a thin bright line: its pixels recur
    at the same sensor positions (fewer than MAX_ALWAYS of them, so the share guard does
    not act), but each has neighbours that stand out with it: none is a defect. A pair of
    adjacent hot pixels beside it is still found."""
    rng = np.random.default_rng(4)
    frames = _frames(rng, n=4, move=False, electrons=400.0)
    for f in frames:
        f[20:40, 50] += 0.2  # the line: 20 pixels, 10 of each CFA colour in its column
        f[70, 90:92] += 0.3  # a hot pair
    mask, _ = defects.defective_pixels(frames)
    assert mask is not None
    assert sorted(map(tuple, np.argwhere(mask).tolist())) == [(70, 90), (70, 91)]


def test_too_few_frames_decide_nothing():
    rng = np.random.default_rng(3)
    frames = _frames(rng, n=2)
    for f in frames:
        f[10, 10] += 0.5
    assert defects.defective_pixels(frames) == (None, "")
    assert defects.defective_pixels([]) == (None, "")


def test_the_neighbours_are_the_same_cfa_colour():
    """A mosaic whose CFA positions carry very different levels (a strong cast) has no
    outliers: each pixel is compared with its own colour only."""
    level = np.array([[0.5, 0.05], [0.05, 0.01]], np.float32)
    mosaic = np.tile(level, (H // 2, W // 2))
    dev, _ = defects.neighbour_deviation(mosaic)
    np.testing.assert_allclose(dev, 0.0, atol=1e-7)
