"""Round trips of the EXR/PNG/mp4 writers and their error messages."""

from __future__ import annotations

import imageio.v2 as iio2
import numpy as np
import pytest

from gridnerf.errors import SceneError
from gridnerf.image_io import read_exr, read_png, write_exr, write_mp4, write_png


def test_exr_round_trip_is_bit_exact(tmp_path):
    rng = np.random.default_rng(0)
    rgb_linear = (rng.standard_normal((13, 17, 3)) * 3.0).astype(np.float32)  # HDR, negatives
    rgb_linear[0, 0] = [1e-30, 65504.0 * 4, -7.5]
    path = tmp_path / "sub" / "view.exr"
    write_exr(path, rgb_linear)
    back = read_exr(path)
    assert back.dtype == np.float32 and back.shape == (13, 17, 3)
    np.testing.assert_array_equal(back, rgb_linear)
    assert sorted(p.name for p in path.parent.iterdir()) == ["view.exr"]  # no .tmp left


def test_exr_overwrite_replaces_content(tmp_path):
    path = tmp_path / "a.exr"
    write_exr(path, np.zeros((4, 4, 3), np.float32))
    write_exr(path, np.full((4, 4, 3), 2.5, np.float32))
    np.testing.assert_array_equal(read_exr(path), np.full((4, 4, 3), 2.5, np.float32))


def test_read_exr_missing_and_corrupt_name_the_file(tmp_path):
    missing = tmp_path / "nope.exr"
    with pytest.raises(SceneError, match="nope.exr.*not found"):
        read_exr(missing)
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr at all")
    with pytest.raises(SceneError, match="bad.exr.*cannot read EXR"):
        read_exr(bad)


def test_write_rejects_non_rgb(tmp_path):
    with pytest.raises(SceneError, match=r"\(H, W, 3\)"):
        write_exr(tmp_path / "x.exr", np.zeros((4, 4), np.float32))
    with pytest.raises(SceneError, match=r"\(H, W, 3\)"):
        write_png(tmp_path / "x.png", np.zeros((4, 4, 4), np.float32))
    assert list(tmp_path.iterdir()) == []


def test_png_round_trip_within_one_step(tmp_path):
    rng = np.random.default_rng(1)
    rgb_srgb = rng.uniform(0.0, 1.0, (9, 11, 3)).astype(np.float32)
    path = tmp_path / "view.png"
    write_png(path, rgb_srgb)
    back = read_png(path)
    assert back.dtype == np.float32 and back.shape == (9, 11, 3)
    assert np.max(np.abs(back - rgb_srgb)) <= 0.5 / 255 + 1e-6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["view.png"]


def test_png_clips_out_of_range_and_nan(tmp_path):
    rgb_srgb = np.array([[[-1.0, 2.0, np.nan], [0.5, 1.0, 0.0]]], np.float32)
    write_png(tmp_path / "c.png", rgb_srgb)
    back = read_png(tmp_path / "c.png")
    np.testing.assert_allclose(back, [[[0.0, 1.0, 0.0], [128 / 255, 1.0, 0.0]]], atol=1e-6)


def test_read_png_missing_names_the_file(tmp_path):
    with pytest.raises(SceneError, match="gone.png.*not found"):
        read_png(tmp_path / "gone.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG garbage")
    with pytest.raises(SceneError, match="bad.png.*cannot read PNG"):
        read_png(bad)


@pytest.mark.parametrize("size", [(16, 24), (15, 21)])
def test_mp4_has_right_frame_count_and_even_size(tmp_path, size):
    h, w = size
    ramp = np.linspace(0.0, 1.0, 5)
    frames = [np.full((h, w, 3), v, np.float32) for v in ramp]
    path = tmp_path / "path.mp4"
    write_mp4(path, frames, fps=10)
    assert path.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["path.mp4"]
    decoded = iio2.mimread(path, format="FFMPEG")
    assert len(decoded) == 5
    assert decoded[0].shape == (h + h % 2, w + w % 2, 3)
    means = [float(f.mean()) / 255 for f in decoded]
    np.testing.assert_allclose(means, ramp, atol=0.05)


def test_mp4_accepts_array_and_rejects_bad_frames(tmp_path):
    write_mp4(tmp_path / "a.mp4", np.zeros((3, 8, 8, 3), np.float32), fps=5)
    assert len(iio2.mimread(tmp_path / "a.mp4", format="FFMPEG")) == 3
    with pytest.raises(SceneError, match="no frames"):
        write_mp4(tmp_path / "b.mp4", [])
    with pytest.raises(SceneError, match="differ in size"):
        write_mp4(tmp_path / "b.mp4", [np.zeros((8, 8, 3)), np.zeros((8, 10, 3))])
    assert not (tmp_path / "b.mp4").exists()
