"""load_scene: the simulated scene, the three pose layouts, and every bad input."""

from __future__ import annotations

import json
import pathlib
import shutil

import numpy as np
import pytest
from conftest import sim_near_far
from scipy.spatial.transform import Rotation

from gridnerf import cameras as cam_mod
from gridnerf import pose_files, raw
from gridnerf.dng import write_dng
from gridnerf.errors import PoseError, RawError, SceneError
from gridnerf.scene import BoundsMissing, load_scene

W, H, N = 40, 32, 10
GRBG = np.array([[1, 0], [2, 1]])
BLACK = np.array([[60.0, 62.0], [64.0, 66.0]])
WHITE = 1023


def _cameras(n=N) -> cam_mod.Cameras:
    """Forward-facing cameras on a small grid, all looking down -z (slightly rotated)."""
    rots = Rotation.from_euler("xy", np.linspace(-0.1, 0.1, 2 * n).reshape(n, 2)).as_matrix()
    pos = np.stack([np.linspace(-0.5, 0.5, n), np.cos(np.arange(n)) * 0.2, np.zeros(n)], 1)
    c2w = np.concatenate([rots, pos[:, :, None]], axis=2)
    return cam_mod.make_cameras([f"f{k:02d}" for k in range(n)], c2w, 36.0, 36.0, 20.0, 16.0, W, H)


def _write_frame(path, k, shape=(H, W), cfa=GRBG):
    rng = np.random.default_rng(k)
    raw_bayer = rng.integers(40, 400, size=shape).astype(np.uint16)
    raw_bayer[3, 5] = WHITE  # one saturated pixel
    write_dng(path, raw_bayer, cfa, BLACK, WHITE, np.eye(3), np.array([0.5, 1.0, 0.7]),
              exposure_time=0.01 * (k + 1), iso=800)


def _make_scene(root, split=True, near_far=(2.0, 10.0)):
    """A tiny scene folder with transforms.json (written by gridnerf itself)."""
    (root / "raw").mkdir(parents=True)
    cams = _cameras()
    for k, name in enumerate(cams.names):
        _write_frame(root / "raw" / f"{name}.dng", k)
    test = [n for k, n in enumerate(cams.names) if k % 3 == 0] if split else None
    train = [n for n in cams.names if n not in test] if split else None
    pose_files.write_transforms(root / "transforms.json", cams, train, test, near_far)
    return root, cams


def _edit_transforms(root, edit):
    meta = json.loads((root / "transforms.json").read_text())
    edit(meta)
    (root / "transforms.json").write_text(json.dumps(meta))


def test_simulated_scene(small_scene):
    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    n = len(scene.names)
    assert n == 12 and scene.raw_bayer.dtype == np.uint16 and scene.raw_bayer.shape == (12, 90, 160)
    np.testing.assert_array_equal(scene.test_idx, [0, 8])
    np.testing.assert_array_equal(scene.train_idx, [k for k in range(12) if k not in (0, 8)])
    frame = raw.read_raw(small_scene / "raw" / f"{scene.names[3]}.dng")
    np.testing.assert_array_equal(scene.raw_normalized(3), raw.normalize(frame))
    assert scene.raw_normalized(3).min() < 0  # dark noise below black stays negative
    rgb_cam, valid = scene.rgb_cam_binned(3)
    assert rgb_cam.shape == valid.shape == (45, 80, 3) and valid.dtype == bool
    np.testing.assert_allclose(rgb_cam, raw.bin2x2(raw.normalize(frame), frame.cfa))
    rgb_small, valid_small = scene.rgb_cam_binned(3, downscale=2)
    assert rgb_small.shape == valid_small.shape == (22, 40, 3)
    assert scene.cameras.c2w.shape == (12, 3, 4) and len(scene.cameras) == 12
    assert scene.near == pytest.approx(1 / 0.75) and scene.far > scene.near
    assert set(scene.gt_linear_paths) == set(scene.names) == set(scene.gt_srgb_paths)
    np.testing.assert_allclose(np.median(scene.exposure), 1.0)


def test_tiny_scene_contents(tmp_path):
    root, cams = _make_scene(tmp_path / "s")
    scene = load_scene(root)
    assert scene.names == cams.names
    np.testing.assert_array_equal(scene.test_idx, [0, 3, 6, 9])
    np.testing.assert_array_equal(scene.cfa, GRBG)
    np.testing.assert_allclose(scene.black_level[4], BLACK)
    assert scene.forward_facing and scene.saturated(2)[3, 5] and scene.saturated(2).sum() == 1
    _, valid = scene.rgb_cam_binned(2)
    # Pixel (row 3, col 5) is a green of block (1, 2) in GRBG: only that block's G is invalid.
    assert not valid[1, 2, 1] and valid[1, 2, 0] and valid.sum() == valid.size - 1
    times = 0.01 * (np.arange(N) + 1)
    np.testing.assert_allclose(scene.exposure, times / np.median(times), rtol=1e-6)
    mosaic = raw.read_raw(root / "raw" / "f02.dng").raw_bayer
    manual = (mosaic - BLACK[0, 1]) / (WHITE - BLACK[0, 1])
    np.testing.assert_allclose(scene.raw_normalized(2)[0, 1::2], manual[0, 1::2], rtol=1e-6)
    # Normalised poses map back to the input poses.
    np.testing.assert_allclose(_world_positions(scene), cams.c2w[:, :, 3], atol=1e-9)
    assert scene.near == pytest.approx(1 / 0.75) and scene.far == pytest.approx(10 / 1.5)


def _world_positions(scene) -> np.ndarray:
    c = np.concatenate([scene.cameras.c2w[:, :, 3], np.ones((len(scene.names), 1))], axis=1)
    return (scene.world_from_normalized @ c.T)[:3].T


def test_colmap_and_llff_layouts_match_transforms(tmp_path):
    root, cams = _make_scene(tmp_path / "s", split=False)
    ref = load_scene(root)
    np.testing.assert_array_equal(ref.test_idx, [0, 8])
    (root / "transforms.json").unlink()

    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"1 SIMPLE_RADIAL {W * 2} {H * 2} 72 40 32 0.01\n")
    lines = []
    for i, name in enumerate(cams.names):
        r_cv = cams.c2w[i, :, :3] @ np.diag([1.0, -1.0, -1.0])
        t = -r_cv.T @ cams.c2w[i, :, 3]
        qx, qy, qz, qw = Rotation.from_matrix(r_cv.T).as_quat()
        lines += [f"{i + 1} {qw} {qx} {qy} {qz} {t[0]} {t[1]} {t[2]} 1 {name}.jpg", ""]
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    depths = np.linspace(2.0, 10.0, 200)  # points along camera 0's optical axis
    pts = cams.c2w[0, :, 3] - depths[:, None] * cams.c2w[0, :, 2]
    (sparse / "points3D.txt").write_text(
        "".join(f"{k + 1} {p[0]} {p[1]} {p[2]} 1 2 3 0.1\n" for k, p in enumerate(pts)))
    (root / "raw" / "f01.json").write_text(json.dumps([{"ExposureTime": "1/10", "ISO": 800}]))
    colmap = load_scene(root)
    np.testing.assert_allclose(colmap.cameras.c2w[:, :, :3], ref.cameras.c2w[:, :, :3], atol=1e-6)
    np.testing.assert_allclose(_world_positions(colmap), cams.c2w[:, :, 3], atol=1e-6)
    np.testing.assert_allclose(colmap.cameras.fx, 36.0)  # rescaled from 2x previews
    # near/far from the points' depths (2..10 along camera 0's axis), with a 10% margin.
    near_w = np.linalg.norm(colmap.world_from_normalized[:3, 0]) / 0.75  # T scales by 1 / s
    assert 1.7 < near_w < 2.0 and colmap.far * near_w * 0.75 == pytest.approx(
        np.percentile(depths, 99) * 1.1, rel=0.02)
    assert colmap.exposure[1] / colmap.exposure[0] == pytest.approx(10.0)  # sidecar wins

    shutil.rmtree(root / "sparse")
    c2w = cams.c2w
    poses = np.stack([-c2w[:, :, 1], c2w[:, :, 0], c2w[:, :, 2], c2w[:, :, 3]], axis=2)
    hwf = np.tile([[H, W, 36.0]], (N, 1))[:, :, None]
    arr = np.concatenate([np.concatenate([poses, hwf], 2).reshape(N, 15),
                          np.tile([[2.0, 10.0]], (N, 1))], axis=1)
    np.save(root / "poses_bounds.npy", arr)
    llff = load_scene(root)
    np.testing.assert_allclose(llff.cameras.c2w, ref.cameras.c2w, atol=1e-9)
    assert (llff.near, llff.far) == pytest.approx((ref.near, ref.far))
    np.save(root / "poses_bounds.npy", arr[:-1])
    with pytest.raises(SceneError, match="9 poses for 10 raw frames"):
        load_scene(root)


def _drop_matrix(meta):
    del meta["frames"][4]["transform_matrix"]


def _nan_pose(meta):
    meta["frames"][4]["transform_matrix"][0][3] = float("nan")


def _scale_pose(meta):
    m = np.array(meta["frames"][4]["transform_matrix"])
    m[:3, :3] *= 1.01
    meta["frames"][4]["transform_matrix"] = m.tolist()


def _bad_split(meta):
    meta["test_filenames"] = ["raw/f00.dng", "nope"]


def _no_near_far(meta):
    del meta["near_far"]


@pytest.mark.parametrize(
    "edit, error, words",
    [(_drop_matrix, PoseError, ["'f04'", "gridnerf poses", "remove the frame"]),
     (_nan_pose, PoseError, ["'f04'", "NaN"]),
     (_scale_pose, PoseError, ["'f04'", "not rigid"]),
     (_bad_split, SceneError, ["nope", "not frames"]),
     (_no_near_far, BoundsMissing, ["near/far", "gridnerf train"])],
)
def test_bad_transforms(tmp_path, edit, error, words):
    root, _ = _make_scene(tmp_path / "s")
    _edit_transforms(root, edit)
    with pytest.raises(error) as info:
        load_scene(root)
    assert "transforms.json" in str(info.value) or str(root) in str(info.value)
    for w in words:
        assert w in str(info.value)


def test_bad_folders_and_frames(tmp_path, monkeypatch):
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match="raw/ folder is missing"):
        load_scene(tmp_path / "empty")
    (tmp_path / "empty" / "raw").mkdir()
    with pytest.raises(SceneError, match="no RAW frames"):
        load_scene(tmp_path / "empty")

    root, _ = _make_scene(tmp_path / "s")
    (root / "transforms.json").rename(root / "t.json")
    with pytest.raises(PoseError, match="gridnerf poses"):
        load_scene(root)
    (root / "t.json").rename(root / "transforms.json")

    (root / "raw" / "f07.dng").rename(root / "f07.dng")
    with pytest.raises(SceneError, match=r"\['f07'\] have no raw file"):
        load_scene(root)
    (root / "raw" / "f07.dng").write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(RawError, match="f07.dng"):
        load_scene(root)
    _write_frame(root / "raw" / "f07.dng", 7, shape=(H, W + 2))
    with pytest.raises(SceneError, match="f07.dng: frame is 42x32") as info:
        load_scene(root)
    assert "remove or re-export" in str(info.value)
    _write_frame(root / "raw" / "f07.dng", 7, cfa=np.array([[0, 1], [1, 2]]))
    with pytest.raises(SceneError, match="f07.dng: CFA pattern"):
        load_scene(root)

    real = raw.read_raw

    def odd_cfa(path):  # a reader that lets a non-Bayer pattern through
        frame = real(path)
        return type(frame)(**{**frame.__dict__, "cfa": np.array([[0, 0], [1, 2]])})

    monkeypatch.setattr(raw, "read_raw", odd_cfa)
    with pytest.raises(SceneError, match="unsupported CFA"):
        load_scene(root)


def _rewrite(path, fn):
    """Rewrite one DNG with fn(raw_bayer, frame) as its mosaic, keeping its metadata."""
    from gridnerf import dng

    frame = raw.read_raw(path)
    dng.write_dng(path, fn(frame.raw_bayer.copy(), frame), frame.cfa, frame.black_level,
                  int(frame.white_level), frame.xyz_to_cam, frame.as_shot_neutral)


def _black(mosaic, frame):
    return np.full_like(mosaic, int(frame.black_level.mean()))


def test_black_and_clipped_frames_are_named_and_left_out(small_scene, tmp_path):
    import shutil

    root = tmp_path / "s"
    shutil.copytree(small_scene, root)
    names = sorted(p.stem for p in (root / "raw").glob("*.dng"))
    _rewrite(root / "raw" / f"{names[3]}.dng", _black)
    _rewrite(root / "raw" / f"{names[5]}.dng",
             lambda m, f: np.full_like(m, int(f.white_level)))
    with pytest.warns(UserWarning) as record:
        scene = load_scene(root, near_far=sim_near_far(root))
    text = " ".join(str(w.message) for w in record)
    assert f"{names[3]}.dng" in text and "below" in text
    assert f"{names[5]}.dng" in text and "clipped" in text
    assert 3 not in scene.train_idx and 5 not in scene.train_idx
    for name in names:
        _rewrite(root / "raw" / f"{name}.dng", _black)
    with pytest.raises(SceneError, match="every frame is at the black level") as info:
        load_scene(root, near_far=sim_near_far(root))
    assert info.value.path == str(root / "raw")  # the one error line names the folder


def test_simulated_frames_are_all_usable(small_scene):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no frame may be flagged
        scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    assert len(scene.train_idx) + len(scene.test_idx) == len(scene.names)


def test_corrupt_pixel_data_is_named_and_left_out():
    from gridnerf.scene import unusable_frames

    rng = np.random.default_rng(0)
    n, h, w = 6, 64, 96
    black, white = np.full((n, 2, 2), 512.0), np.full(n, 16383.0)
    raw_bayer = (512 + rng.poisson(40.0, (n, h, w))).astype(np.uint16)
    # 1250 overwritten values (2500 random bytes) in frame 2: random 16-bit numbers
    flat = raw_bayer[2].reshape(-1)
    flat[rng.choice(flat.size, 1250, replace=False)] = rng.integers(0, 65536, 1250)
    bad = unusable_frames(raw_bayer, black, white)
    assert list(bad) == [2] and "corrupt" in bad[2]
    # read noise that takes values a few DN below black is not corruption
    noisy = np.clip(512 + rng.poisson(2.0, (n, h, w)) + rng.normal(0.0, 6.0, (n, h, w)),
                    0, 16383).astype(np.uint16)
    assert (noisy < 512).any() and unusable_frames(noisy, black, white) == {}


def _edit_transforms(root, fn):
    path = root / "transforms.json"
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize("edit, needle", [
    (lambda m: m.update(train_filenames=[m["frames"][1]["file_path"]] * 2), "more than once"),
    (lambda m: m.update(train_filenames=[f["file_path"] for f in m["frames"]],
                        test_filenames=[m["frames"][0]["file_path"]]), "both the train"),
])
def test_bad_splits_are_refused(small_scene, tmp_path, edit, needle):
    root = tmp_path / "s"
    shutil.copytree(small_scene, root)
    _edit_transforms(root, edit)
    with pytest.raises(SceneError, match=needle):
        load_scene(root, near_far=sim_near_far(root))


def test_raw_files_without_a_frame_entry_are_named(small_scene, tmp_path):
    root = tmp_path / "s"
    shutil.copytree(small_scene, root)
    dropped = {}

    def drop_last(meta):
        dropped["name"] = pathlib.Path(meta["frames"][-1]["file_path"]).stem
        meta["frames"] = meta["frames"][:-1]
        for key in ("train_filenames", "test_filenames"):
            if key in meta:
                meta[key] = [f for f in meta[key] if dropped["name"] not in f]

    _edit_transforms(root, drop_last)
    with pytest.warns(UserWarning, match=f"no frame entry.*{dropped.get('name', '')}"):
        load_scene(root, near_far=sim_near_far(root))


@pytest.mark.parametrize("odd", [0, 4])
def test_odd_sized_frame_is_the_one_named(small_scene, tmp_path, odd):
    root = tmp_path / "s"
    shutil.copytree(small_scene, root)
    names = sorted(p.stem for p in (root / "raw").glob("*.dng"))
    _rewrite(root / "raw" / f"{names[odd]}.dng", lambda m, f: m[:-2, :-2])
    with pytest.raises(SceneError) as info:
        load_scene(root, near_far=sim_near_far(root))
    assert info.value.path.endswith(f"{names[odd]}.dng"), str(info.value)


def _rewrite_header(path, **changes):
    """Rewrite one DNG with some header fields changed (mosaic and exposure kept)."""
    from gridnerf import dng

    f = raw.read_raw(path)
    fields = dict(cfa=f.cfa, black_level=f.black_level, white_level=int(f.white_level),
                  xyz_to_cam=f.xyz_to_cam, as_shot_neutral=f.as_shot_neutral,
                  exposure_time=f.exposure_time, iso=f.iso)
    fields.update(changes)
    dng.write_dng(path, f.raw_bayer, **fields)


def test_frames_whose_header_disagrees_are_named_and_left_out(small_scene, tmp_path):
    root = tmp_path / "s"
    shutil.copytree(small_scene, root)
    names = sorted(p.stem for p in (root / "raw").glob("*.dng"))
    first = raw.read_raw(root / "raw" / f"{names[0]}.dng")
    _rewrite_header(root / "raw" / f"{names[2]}.dng", white_level=4095 + 512)
    _rewrite_header(root / "raw" / f"{names[6]}.dng", xyz_to_cam=first.xyz_to_cam[::-1])
    with pytest.warns(UserWarning) as record:
        scene = load_scene(root, near_far=sim_near_far(root))
    text = " ".join(str(w.message) for w in record)
    assert f"{names[2]}.dng" in text and "white level" in text
    assert f"{names[6]}.dng" in text and "colour matrix" in text
    left = set(scene.train_idx) | set(scene.test_idx)
    assert 2 not in left and 6 not in left and len(left) == len(names) - 2


def test_missing_exposure_metadata_is_named(small_scene, tmp_path):
    root = tmp_path / "s"
    shutil.copytree(small_scene, root)
    names = sorted(p.stem for p in (root / "raw").glob("*.dng"))
    _rewrite_header(root / "raw" / f"{names[1]}.dng", exposure_time=None)
    with pytest.warns(UserWarning, match=f"no exposure time \\({names[1]}\\)"):
        scene = load_scene(root, near_far=sim_near_far(root))
    assert np.all(np.isfinite(scene.exposure))


def test_missing_colour_matrix_is_named(small_scene, monkeypatch):
    import dataclasses

    from gridnerf import scene as scene_mod

    real = raw.read_raw
    monkeypatch.setattr(scene_mod.raw, "read_raw",
                        lambda p: dataclasses.replace(real(p), has_color_matrix=False))
    with pytest.warns(UserWarning, match="no colour matrix; sRGB primaries"):
        load_scene(small_scene, near_far=sim_near_far(small_scene))


def test_dng_with_overwritten_pixel_bytes_is_named(small_scene, tmp_path):
    """2000 random bytes written into a frame's pixel data (the hostile probe of issue 7)."""
    root = tmp_path / "s"
    shutil.copytree(small_scene, root)
    names = sorted(p.stem for p in (root / "raw").glob("*.dng"))
    path = root / "raw" / f"{names[4]}.dng"
    data = bytearray(path.read_bytes())
    at = len(data) // 2  # the uncompressed mosaic fills all but the header
    data[at:at + 2000] = np.random.default_rng(0).integers(0, 256, 2000, np.uint8).tobytes()
    path.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match=f"{names[4]}.dng: .*corrupt pixel data"):
        scene = load_scene(root, near_far=sim_near_far(root))
    assert 4 not in scene.train_idx and 4 not in scene.test_idx
