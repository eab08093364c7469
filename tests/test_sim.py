"""Tests for the procedural scene simulator (gridnerf.sim)."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import OpenEXR
import pytest
import rawpy

from gridnerf import cli
from gridnerf.color import CAMERA_XYZ_TO_CAM, luminance, srgb_encode
from gridnerf.errors import SceneError
from gridnerf.raw import bin2x2
from gridnerf.sim import DEV, HELDOUT, HELDOUT_MIXED, MIXED, SCENES, simulate_scene, writer
from gridnerf.sim import scenes as sc
from gridnerf.sim import sensor as sn
from gridnerf.sim import textures as tx
from gridnerf.sim.capture import (
    camera_path,
    intrinsics,
    look_at,
    pixel_rays,
    render_normals,
    render_view,
)
from gridnerf.sim.geometry import Primitive, cast, occluded, rotation

WHITE = tx.solid((1.0, 1.0, 1.0))


def _read_raw(path):
    """(raw_bayer (H, W) uint16, cfa (2, 2) colour index, rawpy black levels, white level)."""
    with rawpy.imread(str(path)) as r:
        pattern = np.array(r.raw_pattern)
        desc = r.color_desc.decode()
        cfa = np.vectorize(lambda i: "RGB".index(desc[i]))(pattern)
        return (r.raw_image_visible.copy(), cfa, list(r.black_level_per_channel),
                r.white_level, np.array(r.camera_whitebalance[:3]))


def _read_exr(path):
    return OpenEXR.File(str(path)).channels()["RGB"].pixels


def _manifest(scene):
    return json.loads((scene / "sim.json").read_text())


# ---------------------------------------------------------------- geometry


def test_sphere_box_hits_are_analytic():
    prims = [Primitive("ellipsoid", np.zeros(3), np.ones(3), WHITE),
             Primitive("box", np.array([5.0, 0.0, 0.0]), np.array([1.0, 2.0, 3.0]), WHITE)]
    origins = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [10.0, 0.5, 0.0], [0.0, 5.0, 5.0]])
    dirs = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -2.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    hits = cast(prims, origins, dirs)
    np.testing.assert_allclose(hits.t[:3], [4.0, 2.0, 4.0], atol=1e-9)
    assert hits.prim.tolist() == [0, 0, 1, -1] and np.isinf(hits.t[3])
    np.testing.assert_allclose(hits.normal[0], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(hits.normal[2], [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(hits.point[2], [6.0, 0.5, 0.0], atol=1e-9)


def test_rotated_box_and_open_bucket():
    # A cube rotated 45 degrees about y shows an edge at distance sqrt(2) from its centre.
    cube = Primitive("box", np.zeros(3), np.ones(3), WHITE, rot=rotation(yaw=np.pi / 4))
    hits = cast([cube], np.array([[0.0, 0.0, 5.0]]), np.array([[0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(hits.t, [5.0 - np.sqrt(2.0)], atol=1e-9)
    # Open-topped bucket: a ray from above passes the opening and hits the floor inside,
    # whose normal faces up; a horizontal ray hits the outside wall, facing the ray.
    bucket = Primitive("frustum", np.zeros(3), np.array([0.5, 1.0, 0.8]), WHITE,
                       caps=(True, False))
    hits = cast([bucket], np.array([[0.0, 5.0, 0.0], [3.0, 0.0, 0.0]]),
                np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(hits.t, [6.0, 3.0 - 0.65], atol=1e-9)
    np.testing.assert_allclose(hits.normal[0], [0, 1, 0], atol=1e-9)
    assert hits.normal[1, 0] > 0.9
    blocked = occluded([bucket], np.array([[3.0, 0.0, 0.0], [3.0, 3.0, 0.0]]),
                       np.array([[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]))
    assert blocked.tolist() == [True, False]


def test_camera_rays_follow_opengl_convention():
    intr = intrinsics(64, 36)
    c2w = np.eye(4)
    c2w[:3, :3] = look_at(np.array([1.0, 2.0, 5.0]), np.array([0.0, 0.5, 0.0]))
    c2w[:3, 3] = [1.0, 2.0, 5.0]
    rot = c2w[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    forward = -rot[:, 2]
    aim = np.array([-1.0, -1.5, -5.0]) / np.linalg.norm([1.0, 1.5, 5.0])
    np.testing.assert_allclose(forward, aim, atol=1e-12)
    _, dirs = pixel_rays(c2w, intr, ssaa=1)
    d_cam = dirs[..., 0, :] @ rot  # back to camera frame
    np.testing.assert_allclose(d_cam[..., 2], -1.0, atol=1e-12)
    assert d_cam[0, -1, 0] > 0 and d_cam[0, -1, 1] > 0  # top-right pixel: +x, +y
    assert rot[1, 1] > 0.9  # camera up is world up (small roll only)


# ---------------------------------------------------------------- sensor


def test_true_normals_face_the_camera_and_shorten_on_creases():
    """render_normals: unit normals facing the camera where a pixel sees one flat face, 0
    where it sees nothing, shorter where its sub-rays straddle a crease or an outline."""
    spec = sc.build_scene("box")
    intr = intrinsics(48, 27)
    c2w = camera_path(spec, 1, np.random.default_rng(0))[0]
    normals = render_normals(spec, c2w, intr, ssaa=2)
    assert normals.shape == (27, 48, 3) and np.isfinite(normals).all()
    length = np.linalg.norm(normals, axis=-1)
    assert length.max() <= 1.0 + 1e-5 and (length > 0.999).mean() > 0.5
    assert (length < 0.99).any()  # some pixel straddles an edge
    _, dirs = pixel_rays(c2w, intr)
    facing = np.einsum("hwc,hwc->hw", normals, dirs[:, :, 0])
    assert (facing[length > 0.999] < 0).all()


def test_noise_variance_follows_gain_and_read_noise():
    params = sn.SensorParams(k_gain=5.0, bias=((1.0, -1.0), (2.0, 3.0)))
    rng = np.random.default_rng(0)
    levels = np.array([0.0, 2.0, 5.0, 10.0, 20.0, 40.0])
    means, variances = [], []
    for e in levels:
        dn = sn.expose(np.full((256, 256), e), params, rng).astype(np.float64)
        means.append(dn.mean())
        variances.append(dn.var())
    signal = np.array(means) - sn.BLACK_LEVEL - 1.25  # minus black and the mean bias
    np.testing.assert_allclose(signal, 5.0 * levels, atol=1.0)  # linear response K * e
    slope, read_var = np.polyfit(signal, variances, 1)
    assert slope == pytest.approx(params.k_gain, rel=0.15)
    # Tukey-lambda read noise (heavier tailed than a logistic) plus row noise and rounding.
    assert params.read_sigma**2 * 3.29 < read_var < params.read_sigma**2 * 6


def test_tukey_lambda_is_symmetric_heavy_tailed():
    x = sn.tukey_lambda(np.random.default_rng(1), 200_000, -0.075, 3.5)
    assert abs(np.median(x)) < 0.05
    kurtosis = np.mean((x - x.mean()) ** 4) / x.var() ** 2
    assert kurtosis > 4.2  # logistic (lambda = 0) has 4.2; negative lambda is heavier


def test_mosaic_and_cfa_patterns():
    rgb_cam = np.stack([np.full((4, 6), 1.0), np.full((4, 6), 2.0), np.full((4, 6), 3.0)], -1)
    raw = sn.mosaic(rgb_cam, np.array(sn.CFA_PATTERNS["GRBG"]))
    assert raw[0, :2].tolist() == [2.0, 1.0] and raw[1, :2].tolist() == [3.0, 2.0]
    warm = sn.illuminant_neutral(sn.SensorParams(kelvin=2500.0))
    assert warm[2] < 0.5 * warm[1]
    np.testing.assert_allclose(bin2x2(raw, np.array(sn.CFA_PATTERNS["GRBG"]), np.float64)[0, 0],
                               [1.0, 2.0, 3.0])


def test_preview_balances_a_warm_grey_frame():
    params = sn.SensorParams(kelvin=2600.0)
    grey = sn.scene_to_cam(np.full((32, 48, 3), 0.5), params)  # a grey card under warm light
    raw = sn.expose(sn.mosaic(grey, params.cfa) * 40.0, params, np.random.default_rng(0))
    rgb_srgb = sn.preview_srgb(raw, params.cfa, np.full((2, 2), 512.0), 16383,
                               params.xyz_to_cam)
    assert rgb_srgb.shape == (32, 48, 3)
    means = rgb_srgb.reshape(-1, 3).mean(axis=0)
    assert np.ptp(means) < 0.05 and 0.3 < means.mean() < 0.6  # neutral, normal brightness


# ---------------------------------------------------------------- scene folder


def test_scene_folder_reads_back(small_scene):
    tf = json.loads((small_scene / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "frames", "train_filenames",
                "test_filenames"):
        assert key in tf
    assert "near_far" not in tf  # no exact bounds for the trainer; they stay in sim.json
    assert (tf["w"], tf["h"]) == (160, 90) and len(tf["frames"]) == 12
    paths = [f["file_path"] for f in tf["frames"]]
    assert paths[0] == "raw/frame_000.dng"
    assert tf["test_filenames"] == ["raw/frame_000.dng", "raw/frame_008.dng"]
    assert sorted(tf["train_filenames"] + tf["test_filenames"]) == sorted(paths)
    hfov = 2 * np.degrees(np.arctan(0.5 * tf["w"] / tf["fl_x"]))
    assert 50.0 <= hfov <= 60.0
    poses = np.array([f["transform_matrix"] for f in tf["frames"]])
    np.testing.assert_allclose(poses[:, 3], np.tile([0, 0, 0, 1.0], (12, 1)))
    rots = poses[:, :3, :3]
    np.testing.assert_allclose(rots @ rots.transpose(0, 2, 1), np.tile(np.eye(3), (12, 1, 1)),
                               atol=1e-9)
    spread = np.ptp(poses[:, :3, 3], axis=0)
    assert spread[0] > 0.3 and spread[1] > 0.1  # the tripod really moves
    near, far = _manifest(small_scene)["near_far"]
    assert 0 < near < far and 1.5 <= far / near <= 4.5
    gt = _read_exr(small_scene / "gt" / "frame_003.exr")
    assert gt.shape == (90, 160, 3) and gt.dtype == np.float32
    png = iio.imread(small_scene / "gt" / "frame_003.png")
    assert png.shape == (90, 160, 3) and png.dtype == np.uint8
    np.testing.assert_allclose(png / 255.0, srgb_encode(gt), atol=0.51 / 255)
    jpg = iio.imread(small_scene / "images" / "frame_003.jpg")
    assert jpg.shape == (90, 160, 3) and 40 < jpg.mean() < 200
    raw, cfa, black, white, wb = _read_raw(small_scene / "raw" / "frame_003.dng")
    assert raw.shape == (90, 160) and raw.dtype == np.uint16
    assert cfa.tolist() == [[0, 1], [1, 2]] and black == [512] * 4 and white == 16383
    assert wb[2] > wb[1]  # camera WB boosts the weak blue channel of a warm scene
    manifest = _manifest(small_scene)
    assert manifest["scene"] == "bucket" and 2300 <= manifest["illuminant_kelvin"] <= 3200
    assert manifest["rig"] == "tripod" and manifest["held_out"] is False
    assert "0.18" in manifest["exposure_convention"]
    # lens-cap frames: same sensor and settings, no light; their mean is the hidden bias
    assert manifest["dark_frames"] == ["dark/dark_000.dng", "dark/dark_001.dng"]
    dark, dark_cfa, dark_black, _, _ = _read_raw(small_scene / "dark" / "dark_000.dng")
    assert dark.shape == raw.shape and dark_cfa.tolist() == cfa.tolist() and dark_black == black
    bias = np.array(manifest["noise"]["black_bias_dn_per_cfa_position"])
    per_position = (dark.astype(np.float64) - 512).reshape(45, 2, 80, 2).mean(axis=(0, 2))
    np.testing.assert_allclose(per_position, bias, atol=0.6)


def test_raw_is_dark_and_warm(small_scene):
    manifest = _manifest(small_scene)
    cfa = np.array(manifest["cfa"])
    sums, counts = np.zeros(3), np.zeros(3)
    for stem in manifest["frames"]:
        raw = _read_raw(small_scene / "raw" / f"{stem}.dng")[0].astype(np.float64) - 512
        colour = sn.cfa_index(*raw.shape, cfa)
        for c in range(3):
            sums[c] += raw[colour == c].sum()
            counts[c] += (colour == c).sum()
    mean = sums / counts
    assert mean[2] / mean[1] < 0.7  # warm light: blue well below green
    assert mean.mean() / (16383 - 512) < 0.05  # dark: a few percent of the range or less
    k, electrons = manifest["K_dn_per_electron"], manifest["electrons_mean_green"]
    assert mean[1] == pytest.approx(k * electrons, abs=5.0)  # photon budget as recorded


def test_references_are_colourful_and_normalised(small_scene):
    frames = np.stack([_read_exr(p) for p in sorted((small_scene / "gt").glob("*.exr"))])
    assert frames.shape == (12, 90, 160, 3)
    assert float(luminance(frames.astype(np.float64)).mean()) == pytest.approx(0.18, rel=1e-3)
    means = frames.reshape(-1, 3).mean(axis=0)
    assert (means.max() - means.min()) / means.mean() > 0.1  # not grey on average
    chroma = frames.max(axis=-1) - frames.min(axis=-1)
    assert chroma.mean() > 0.05


def test_deterministic_and_reused(small_scene, tmp_path):
    again = simulate_scene("bucket", tmp_path / "again", width=160, height=90, n_frames=12,
                           seed=0)
    for stem in ("frame_000", "frame_007"):
        a = _read_raw(small_scene / "raw" / f"{stem}.dng")[0]
        b = _read_raw(again / "raw" / f"{stem}.dng")[0]
        np.testing.assert_array_equal(a, b)
    stamps = {p: p.stat().st_mtime_ns for p in small_scene.rglob("*") if p.is_file()}
    assert simulate_scene("bucket", small_scene, width=160, height=90, n_frames=12,
                          seed=0) == small_scene
    assert {p: p.stat().st_mtime_ns for p in small_scene.rglob("*") if p.is_file()} == stamps
    assert not list(tmp_path.glob("again.tmp-*"))


def test_seed_changes_noise_and_cameras(tmp_path):
    a = simulate_scene("box", tmp_path / "a", width=64, height=36, n_frames=2, seed=1)
    b = simulate_scene("box", tmp_path / "b", width=64, height=36, n_frames=2, seed=2)
    assert not np.array_equal(_read_raw(a / "raw" / "frame_001.dng")[0],
                              _read_raw(b / "raw" / "frame_001.dng")[0])
    pose = [json.loads((d / "transforms.json").read_text())["frames"][1]["transform_matrix"]
            for d in (a, b)]
    assert not np.allclose(pose[0], pose[1])


def test_refuses_foreign_folder_and_bad_name(tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(SceneError, match="overwrite"):
        simulate_scene("doll", out, width=64, height=36, n_frames=1)
    simulate_scene("doll", out, width=64, height=36, n_frames=1, overwrite=True)
    assert not (out / "notes.txt").exists() and (out / "sim.json").is_file()
    with pytest.raises(SceneError, match="unknown simulated scene"):
        simulate_scene("teapot", tmp_path / "teapot")
    with pytest.raises(SceneError, match="at least"):
        simulate_scene("doll", tmp_path / "tiny", width=4, height=4)


@pytest.mark.parametrize("name", SCENES)
def test_every_scene_builds(name, tmp_path):
    out = simulate_scene(name, tmp_path / name, width=64, height=36, n_frames=3, seed=0)
    manifest = _manifest(out)
    raw, cfa, *_ = _read_raw(out / "raw" / "frame_002.dng")
    assert raw.shape == (36, 64)
    assert cfa.tolist() == np.array(sn.CFA_PATTERNS[manifest["cfa_pattern"]]).tolist()
    gt = _read_exr(out / "gt" / "frame_002.exr")
    assert np.isfinite(gt).all() and gt.min() >= 0.0 and gt.max() > 0.1
    assert len(list((out / "images").glob("*.jpg"))) == 3


# ---------------------------------------------------------------- rigs and held-out scenes


def _poses(name, n=24, seed=0):
    return camera_path(sc.build_scene(name), n, np.random.default_rng(seed))


def _yaw_deg(poses, target):
    """Yaw of each camera centre about the target, degrees (0 = straight in front, +z)."""
    off = poses[:, :3, 3] - np.asarray(target)
    return np.degrees(np.arctan2(off[:, 0], off[:, 2]))


def test_heldout_scenes_are_named_and_distinct():
    assert len(HELDOUT) >= 4 and not set(HELDOUT) & set(SCENES)
    assert all(name.startswith("held_") for name in HELDOUT)
    assert "held out" in sc.__doc__ and "no default" in sc.__doc__
    rigs = set()
    for name in HELDOUT:
        spec = sc.build_scene(name)
        assert spec.name == name and "Held out" in sc._HELD[name].__doc__
        rigs.add(spec.rig)
        s = spec.sensor
        assert 2300 <= s.kelvin <= 3200 and 5 <= s.electrons <= 35
        assert s.camera_model in CAMERA_XYZ_TO_CAM and s.cfa_pattern in ("RGGB", "GRBG")
    assert rigs == {"arc", "slide"}
    assert all(sc.build_scene(name).rig == "tripod" for name in SCENES)
    with pytest.raises(ValueError, match="unknown scene"):
        sc.build_scene("held_nothing")


def test_tuning_scenes_have_the_new_rigs_and_are_not_held_out(tmp_path):
    """DEV: one arc and one slide, distinct from the nine, the held-out and the mixed
    scenes, single-light, marked as not held out in the scene's manifest."""
    assert not set(DEV) & set(SCENES + HELDOUT + MIXED)
    assert {sc.build_scene(name).rig for name in DEV} == {"arc", "slide"}
    for name in DEV:
        spec = sc.build_scene(name)
        assert "Tuning" in sc._DEV[name].__doc__ and not spec.layered
        assert spec.sensor.camera_model in CAMERA_XYZ_TO_CAM
    out = simulate_scene(DEV[0], tmp_path / DEV[0], width=64, height=36, n_frames=2)
    assert json.loads((out / "sim.json").read_text())["held_out"] is False


@pytest.mark.parametrize("name", ["bucket", "held_arc_brick", "held_slide_shelf"])
def test_poses_are_rigid(name):
    poses = _poses(name)
    rots = poses[:, :3, :3]
    np.testing.assert_allclose(rots @ rots.transpose(0, 2, 1), np.tile(np.eye(3), (24, 1, 1)),
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rots), 1.0, atol=1e-9)
    np.testing.assert_allclose(poses[:, 3], np.tile([0, 0, 0, 1.0], (24, 1)))
    assert (rots[:, 1, 1] > 0.9).all()  # upright: camera up is close to world up


@pytest.mark.parametrize("name", ["held_arc_brick", "held_arc_table"])
def test_arc_cameras_converge_on_the_subject(name):
    spec = sc.build_scene(name)
    poses = _poses(name)
    target = np.asarray(spec.target)
    centres = poses[:, :3, 3]
    axes = -poses[:, :3, 2]  # optical axes (unit)
    to_target = target - centres
    along = np.einsum("ij,ij->i", to_target, axes)
    miss = np.linalg.norm(to_target - along[:, None] * axes, axis=1)
    assert (along > 0).all() and miss.max() < 0.1  # every axis passes by the subject
    assert miss.max() > 1e-3  # ... with some aim jitter, not exactly through it
    dist = np.linalg.norm(to_target, axis=1)
    assert 1.5 <= dist.min() and dist.max() <= 3.0
    yaw = _yaw_deg(poses, target)
    assert -20.0 <= yaw.min() <= -15.0 and 15.0 <= yaw.max() <= 20.0
    assert np.all(np.diff(yaw) > 0)  # one sweep, in capture order
    # Optical-axis yaw follows the positions (the cameras turn toward the subject).
    axis_yaw = np.degrees(np.arctan2(-axes[:, 0], -axes[:, 2]))
    assert np.ptp(axis_yaw) > 25.0
    assert 0.01 < np.ptp(centres[:, 1]) < 0.4  # slight height variation
    roll = np.degrees(np.arcsin(poses[:, 1, 0]))  # camera x axis tilts out of horizontal
    assert 0.1 < np.abs(roll).max() < 5.0


@pytest.mark.parametrize("name", ["held_slide_shelf", "held_deep_hall"])
def test_slide_cameras_share_one_orientation_on_a_line(name):
    spec = sc.build_scene(name)
    poses = _poses(name)
    rots = poses[:, :3, :3]
    rel = np.einsum("nji,mjk->nmik", rots, rots)  # R_n^T R_m for every pair
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=2, axis2=3) - 1) / 2, -1, 1)))
    assert angle.max() < 1.0  # parallel optical axes up to a tiny wobble
    centres = poses[:, :3, 3]
    centred = centres - centres.mean(axis=0)
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    rail = vt[0]
    assert sv[1] / np.sqrt(len(centres)) < 0.003  # on a line, to a few mm
    assert abs(rail[1]) < 0.01  # horizontal
    assert abs(rail @ rots[0][:, 0]) > 0.999  # along the cameras' x axis: a lateral slide
    baseline = np.ptp(centred @ rail)
    assert 0.3 <= baseline / spec.distance <= 0.5


def test_deep_scene_spans_a_wide_depth_range():
    spec = sc.build_scene("held_deep_hall")
    poses = _poses("held_deep_hall", n=12)
    intr = intrinsics(96, 54)
    depths = np.stack([render_view(spec, poses[i], intr)[1] for i in (0, 6, 11)])
    finite = depths[np.isfinite(depths)]
    assert finite.size == depths.size  # a closed hall: every ray hits something
    near, far = finite.min(), finite.max()
    assert 0.8 <= near <= 1.2 and 6.0 <= far <= 10.0
    assert 5.0 <= far / near <= 10.0


def test_high_frequency_textures():
    uv = np.stack(np.meshgrid(np.linspace(0, 1, 400, endpoint=False),
                              np.linspace(0, 1, 400, endpoint=False)), -1).reshape(-1, 2)
    p, face = np.zeros((len(uv), 3)), np.zeros(len(uv), np.int64)
    brick = tx.bricks([(0.7, 0.3, 0.2)], (0.9, 0.9, 0.9), rows=10, cols=4, joint=0.1,
                      aspect=0.4)(p, uv, face).reshape(400, 400, 3)
    mortar = np.all(brick == tx.solid((0.9, 0.9, 0.9))(p[:1], uv[:1], face[:1])[0], axis=-1)
    assert 0.1 <= mortar.mean() <= 0.2  # thin joints: 10% of courses, 4% of bricks
    assert mortar[:, 200].reshape(10, 40)[:, :4].all()  # a bed joint at the foot of each course
    ink = tx.text_bitmap(["AB 12"])
    assert ink.shape == (9, 30) and ink[1:8, 0:5].sum() == tx.glyph("A").sum()
    np.testing.assert_array_equal(ink[1:8, 18:23], tx.glyph("1"))
    assert not ink[:, 12:18].any()  # a space
    lines = tx.random_lines(4, 30, seed=3)
    assert len(lines) == 4 and all(len(line) == 30 for line in lines)
    page = tx.text((0, 0, 0), (1, 1, 1), rows=12, cols=32)(p, uv, face)
    assert 0.08 < (page[:, 0] < 0.5).mean() < 0.4
    grain = tx.wood((0.7, 0.5, 0.3), (0.4, 0.25, 0.1), planks=2)(p, uv, face)
    luma = luminance(grain.reshape(400, 400, 3))
    assert np.abs(np.diff(luma, axis=1)).mean() > 0.003  # fine streaks along the grain
    assert np.abs(np.diff(luma, axis=0)).mean() > np.abs(np.diff(luma, axis=1)).mean()


def test_heldout_scene_folder_has_no_bounds(tmp_path):
    out = simulate_scene("held_arc_table", tmp_path / "t", width=64, height=36, n_frames=3)
    tf = json.loads((out / "transforms.json").read_text())
    assert "near_far" not in tf and len(tf["frames"]) == 3
    manifest = _manifest(out)
    assert manifest["rig"] == "arc" and manifest["held_out"] is True
    near, far = manifest["near_far"]
    assert 0.8 < near < far
    gt = _read_exr(out / "gt" / "frame_001.exr")
    assert np.isfinite(gt).all() and gt.max() > 0.1


def test_older_format_is_rebuilt(tmp_path):
    out = simulate_scene("box", tmp_path / "box", width=64, height=36, n_frames=1)
    manifest = _manifest(out)
    manifest["version"] = writer.SIM_VERSION - 1
    (out / "sim.json").write_text(json.dumps(manifest))
    simulate_scene("box", out, width=64, height=36, n_frames=1)  # no error: rebuilt
    assert _manifest(out)["version"] == writer.SIM_VERSION
    manifest["n_frames"] = 5  # another scene's manifest, old or not, is not ours to replace
    (out / "sim.json").write_text(json.dumps(manifest))
    with pytest.raises(SceneError, match="overwrite"):
        simulate_scene("box", out, width=64, height=36, n_frames=1)


def test_darker_capture_has_fewer_photons_and_the_same_sensor(tmp_path):
    """light f: the expected signal scales by f, the read noise and black level do not;
    the manifest says so, and a folder of one light level is not taken for another's."""
    kw = {"width": 64, "height": 36, "n_frames": 2}
    full = simulate_scene("box", tmp_path / "full", **kw)
    dim = simulate_scene("box", tmp_path / "dim", light=0.25, **kw)
    m_full, m_dim = _manifest(full), _manifest(dim)
    assert m_dim["light"] == 0.25 and m_full["light"] == 1.0
    assert m_dim["electrons_mean_green"] == pytest.approx(0.25 * m_full["electrons_mean_green"])
    assert m_dim["lux"] == pytest.approx(0.25 * m_full["lux"])
    assert m_dim["noise"] == m_full["noise"] and m_dim["iso"] == m_full["iso"]
    signal = [np.mean([_read_raw(d / "raw" / f"frame_00{i}.dng")[0].astype(float) - 512
                       for i in range(2)]) for d in (full, dim)]
    assert signal[1] / signal[0] == pytest.approx(0.25, rel=0.05)
    # the lens-cap frames hold no photons: the same at every light level
    assert np.array_equal(_read_raw(full / "dark" / "dark_000.dng")[0],
                          _read_raw(dim / "dark" / "dark_000.dng")[0])
    assert simulate_scene("box", dim, light=0.25, **kw) == dim  # reused
    with pytest.raises(SceneError, match="light 0.5"):
        simulate_scene("box", dim, light=0.5, **kw)
    with pytest.raises(SceneError, match="overwrite"):
        simulate_scene("box", dim, **kw)  # light 1 is another scene too
    with pytest.raises(SceneError, match="photon budget"):
        simulate_scene("box", tmp_path / "none", light=0.0, **kw)


def test_manifest_without_light_was_written_at_light_one(tmp_path):
    out = simulate_scene("box", tmp_path / "box", width=64, height=36, n_frames=1)
    manifest = _manifest(out)
    del manifest["light"]  # a folder written before the option existed
    (out / "sim.json").write_text(json.dumps(manifest))
    assert simulate_scene("box", out, width=64, height=36, n_frames=1) == out
    assert "light" not in _manifest(out)  # reused as it is, not rebuilt


def test_cli_simulates_a_darker_capture_in_its_own_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    args = ["--width", "64", "--height", "36", "--frames", "1"]
    assert cli.main(["simulate", "box", "--light", "0.5", *args]) == 0
    assert _manifest(tmp_path / "data" / "sim" / "box_light0.5")["light"] == 0.5
    assert not (tmp_path / "data" / "sim" / "box").exists()
    capsys.readouterr()
    assert cli.main(["simulate", "box", "--light", "0", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert "--light" in err and len(err.splitlines()) == 1


def test_cli_simulates_heldout_group(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    args = ["--width", "64", "--height", "36", "--frames", "1"]
    assert cli.main(["simulate", "heldout", *args]) == 0
    for name in HELDOUT:
        assert (tmp_path / "data" / "sim" / name / "sim.json").is_file()
    assert cli.main(["simulate", "held_deep_hall", "--out", "one", *args]) == 0
    assert (tmp_path / "one" / "sim.json").is_file()
    assert cli.main(["simulate", "teapot", *args]) == 2
    assert "heldout" in capsys.readouterr().err


# ---------------------------------------------------------------- mixed-light scenes


def test_mixed_scenes_have_two_illuminants_and_the_others_one():
    assert len(MIXED) >= 2 and not set(MIXED) & set(SCENES + HELDOUT)
    for name in MIXED:
        spec = sc.build_scene(name)
        assert spec.name == name and spec.layered and len(spec.kelvins) == 2
        assert max(spec.kelvins) - min(spec.kelvins) >= 2500  # a warm lamp and daylight
        assert any(isinstance(light, sc.PointLight) for light in spec.lights)
    for name in SCENES + HELDOUT:  # the single-light path, unchanged (byte-identical files)
        spec = sc.build_scene(name)
        assert not spec.layered and spec.kelvins == (spec.sensor.kelvin,)


def test_held_out_mixed_scene_differs_from_the_mixed_ones(tmp_path):
    """HELDOUT_MIXED: two lights of different colour, another rig, sensor and lights than
    MIXED (nothing of the mixed-light path is chosen on it), marked held out."""
    assert len(HELDOUT_MIXED) >= 2 and not set(HELDOUT_MIXED) & set(SCENES + HELDOUT + DEV
                                                                  + MIXED)
    tuned = [sc.build_scene(name) for name in MIXED]
    for name in HELDOUT_MIXED:
        spec = sc.build_scene(name)
        assert spec.layered and len(spec.kelvins) == 2
        assert max(spec.kelvins) - min(spec.kelvins) >= 1500
        assert spec.rig not in {t.rig for t in tuned}
        assert spec.sensor.cfa_pattern not in {t.sensor.cfa_pattern for t in tuned}
        assert set(spec.kelvins).isdisjoint(k for t in tuned for k in t.kelvins)
    held = [sc.build_scene(name) for name in HELDOUT_MIXED]  # unlike each other, too
    assert len({s.kelvins for s in held}) == len(held)
    assert len({(s.rig, s.sensor.camera_model, s.sensor.cfa_pattern) for s in held}) == len(held)
    out = simulate_scene(HELDOUT_MIXED[0], tmp_path / "s", width=64, height=36, n_frames=2)
    record = _manifest(out)
    assert record["held_out"] is True and record["mixed_light"] is True


def test_layers_add_up_to_the_single_light_render():
    """A mixed scene's directional lights split over two layers render, summed, exactly
    what capture.shade gives with all of them in one colour."""
    from dataclasses import replace

    from gridnerf.sim.capture import render_view_layers

    spec = sc.build_scene("mixed_lamp_window")
    lights = tuple(replace(li, kelvin=None) for li in spec.lights if isinstance(li, sc.Light))
    one = replace(spec, lights=lights, ambient_kelvin=None)
    two = replace(one, lights=tuple(replace(li, kelvin=5000.0) for li in lights))
    pose = _poses("mixed_lamp_window", 1)[0]
    intr = intrinsics(48, 27)
    rgb, _ = render_view(one, pose, intr, ssaa=1)
    layers, irradiance, _ = render_view_layers(two, pose, intr, ssaa=1)
    assert layers.shape == (2, 27, 48, 3) and irradiance.shape == (27, 48, 2)
    np.testing.assert_allclose(layers.sum(0), rgb, rtol=1e-5, atol=1e-7)


def test_mixed_scene_folder_records_both_lights(tmp_path):
    out = simulate_scene("mixed_lamp_window", tmp_path / "m", width=96, height=54,
                         n_frames=4, seed=0)
    m = _manifest(out)
    assert m["mixed_light"] and len(m["illuminants"]) == 2
    kelvins = sorted(e["kelvin"] for e in m["illuminants"])
    assert kelvins == [2700.0, 6500.0]
    shares = [e["share_of_green_signal"] for e in m["illuminants"]]
    assert abs(sum(shares) - 1.0) < 1e-9 and min(shares) > 0.2
    lamp, day = (np.array(e["neutral_cam"]) for e in m["illuminants"])
    assert lamp[0] / lamp[2] > 2.5 * day[0] / day[2]  # warm vs cool in camera RGB
    mixed = np.array(m["illuminant_neutral_cam"])
    assert day[0] / day[2] < mixed[0] / mixed[2] < lamp[0] / lamp[2]
    # which light dominates where: both regimes cover a good part of the frames
    share = np.stack([iio.imread(out / "illuminant" / f"frame_{i:03d}.png") / 255.0
                      for i in range(4)])
    assert share.shape == (4, 54, 96)
    assert (share > 0.6).mean() > 0.1 and (share < 0.3).mean() > 0.1
    # the raw agrees: camera R/B is far higher where the lamp dominates
    rb = []
    for region in (share > 0.6, share < 0.3):
        sums = np.zeros(3)
        for i in range(4):
            raw, cfa, black, white, _ = _read_raw(out / "raw" / f"frame_{i:03d}.dng")
            y = (raw.astype(np.float64) - black[0]) / (white - black[0])
            colour = cfa[np.arange(54)[:, None] % 2, np.arange(96)[None, :] % 2]
            for c in (0, 2):
                sums[c] += y[region[i] & (colour == c)].sum()
        rb.append(sums[0] / sums[2])
    assert rb[0] > 1.8 * rb[1]
    gt = _read_exr(out / "gt" / "frame_001.exr")
    assert np.isfinite(gt).all() and gt.min() >= 0.0


def test_cli_simulates_mixed_group(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = ["--width", "48", "--height", "27", "--frames", "1"]
    assert cli.main(["simulate", "mixed", *args]) == 0
    for name in MIXED:
        assert _manifest(tmp_path / "data" / "sim" / name)["scene"] == name
    from gridnerf.sim.truth import clean_mean

    with pytest.raises(ValueError, match="several illuminants"):
        clean_mean(tmp_path / "data" / "sim" / MIXED[0])
