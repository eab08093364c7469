"""Cameras, pose files (transforms.json, COLMAP text, LLFF) and rays (pixel rays, NDC)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gridnerf import cameras as cam_mod
from gridnerf import pose_files, rays
from gridnerf.errors import PoseError, SceneError

W, H, F = 64, 48, 60.0  # principal point at the centre so LLFF can describe the same camera
NAMES = ("a", "b", "c")


def _look_at(position, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """OpenGL camera-to-world (3, 4) at `position` looking at `target`."""
    back = np.asarray(position, float) - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(back, right), back, position], axis=1)


def _scene_cams() -> cam_mod.Cameras:
    target = np.array([0.2, -0.1, -4.0])
    c2w = np.stack([_look_at(p, target) for p in ([0, 0, 0], [0.5, 0.2, 0.1], [-0.4, -0.3, 0.2])])
    return cam_mod.make_cameras(NAMES, c2w, F, F, W / 2, H / 2, W, H)


def _write_colmap_text(folder, cams: cam_mod.Cameras, points) -> None:
    folder.mkdir(parents=True)
    fx, fy, cx, cy = cams.fx[0], cams.fy[0], cams.cx[0], cams.cy[0]
    (folder / "cameras.txt").write_text(f"1 PINHOLE {W} {H} {fx} {fy} {cx} {cy}\n")
    lines = []
    for i, name in enumerate(cams.names):
        r_cv = cams.c2w[i, :, :3] @ np.diag([1.0, -1.0, -1.0])  # camera-to-world, OpenCV axes
        r_w2c, t_w2c = r_cv.T, -r_cv.T @ cams.c2w[i, :, 3]
        qx, qy, qz, qw = Rotation.from_matrix(r_w2c).as_quat()
        lines += [f"{i + 1} {qw} {qx} {qy} {qz} {t_w2c[0]} {t_w2c[1]} {t_w2c[2]} 1 {name}.jpg", ""]
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text(
        "".join(f"{k + 1} {p[0]} {p[1]} {p[2]} 128 128 128 0.5\n" for k, p in enumerate(points))
    )


def _write_llff(path, cams: cam_mod.Cameras, scale: float) -> None:
    """poses_bounds.npy for previews `scale` times the raw size."""
    c2w = cams.c2w
    poses = np.stack([-c2w[:, :, 1], c2w[:, :, 0], c2w[:, :, 2], c2w[:, :, 3]], axis=2)
    hwf = np.broadcast_to(np.array([H * scale, W * scale, F * scale]), (len(cams), 3))
    arr = np.concatenate([poses, hwf[:, :, None]], axis=2).reshape(len(cams), 15)
    np.save(path, np.concatenate([arr, np.tile([[1.5, 9.0]], (len(cams), 1))], axis=1))


def _point_through(cams, i, u, v, depth) -> np.ndarray:
    origins, directions = rays.camera_rays(cams, i)
    return origins[v, u] + depth * directions[v, u]


def test_three_formats_agree_and_rays_hit_the_point(tmp_path):
    cams = _scene_cams()
    point = _point_through(cams, 0, 10, 7, 3.5)
    # Hand check of the convention: camera 0 sits at the origin, so the point is
    # depth * ((u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1) rotated into the world.
    d_cam = np.array([(10.5 - W / 2) / F, -(7.5 - H / 2) / F, -1.0])
    np.testing.assert_allclose(point, 3.5 * cams.c2w[0, :, :3] @ d_cam, atol=1e-12)

    pose_files.write_transforms(tmp_path / "transforms.json", cams, ["a", "b"], ["c"], (1.0, 9.0))
    from_json, split, near_far = pose_files.load_transforms(tmp_path / "transforms.json")
    _write_colmap_text(tmp_path / "sparse" / "0", cams, [point])
    from_colmap, points = pose_files.load_colmap(tmp_path / "sparse" / "0", names=list(NAMES))
    _write_llff(tmp_path / "poses_bounds.npy", cams, scale=0.5)
    from_llff, bounds = pose_files.load_llff(tmp_path / "poses_bounds.npy", NAMES, W, H)

    assert split == {"train": ["a", "b"], "test": ["c"]} and near_far == (1.0, 9.0)
    np.testing.assert_allclose(points, [point], atol=1e-9)
    np.testing.assert_allclose(bounds, [[1.5, 9.0]] * 3)
    assert (from_llff.width, from_llff.height, from_llff.fx[0]) == (W, H, F)
    uv0 = cam_mod.project(cams, 0, point[None])
    np.testing.assert_allclose(uv0, [[10.5, 7.5]], atol=1e-9)
    for loaded in (from_json, from_colmap, from_llff):
        assert loaded.names == NAMES
        cam_mod.validate(loaded, "x")
        for i in range(3):
            uv = cam_mod.project(loaded, i, point[None])[0]
            np.testing.assert_allclose(uv, cam_mod.project(cams, i, point[None])[0], atol=1e-6)
            # The ray through the (continuous) pixel of the point passes through the point.
            o, d = rays.pixel_rays(loaded.c2w[i], loaded.fx[i], loaded.fy[i], loaded.cx[i],
                                   loaded.cy[i], uv[0] - 0.5, uv[1] - 0.5)
            depth = -(loaded.c2w[i, :, :3].T @ (point - o))[2]
            np.testing.assert_allclose(o + depth * d, point, atol=1e-6)


def test_scaled_half_maps_pixel_centres():
    cams = _scene_cams()
    half = cams.scaled(0.5)
    assert (half.width, half.height) == (W // 2, H // 2)
    u, v = np.array([0, 5, 31]), np.array([0, 9, 23])
    _, d_half = rays.pixel_rays(half.c2w[1], half.fx[1], half.fy[1], half.cx[1], half.cy[1], u, v)
    # Binned pixel u covers full-res pixels 2u and 2u+1: its centre is full-res coordinate 2u+1.
    _, d_full = rays.pixel_rays(cams.c2w[1], cams.fx[1], cams.fy[1], cams.cx[1], cams.cy[1],
                                2 * u + 0.5, 2 * v + 0.5)
    np.testing.assert_allclose(d_half, d_full, atol=1e-12)
    point = _point_through(cams, 1, 20, 30, 2.0)[None]
    np.testing.assert_allclose(cam_mod.project(half, 1, point), cam_mod.project(cams, 1, point) / 2)


def test_camera_rays_shapes_and_unit_depth():
    cams = _scene_cams()
    origins, directions = rays.camera_rays(cams, 2)
    assert origins.shape == directions.shape == (H, W, 3)
    d_cam = directions @ cams.c2w[2, :, :3]  # back to the camera frame
    np.testing.assert_allclose(d_cam[..., 2], -1.0)
    np.testing.assert_allclose(origins, np.broadcast_to(cams.c2w[2, :, 3], (H, W, 3)))


def test_normalize_world_then_ndc():
    cams = _scene_cams()
    c2w_n, near_n, far_n, world_from_norm = rays.normalize_world(cams.c2w, 2.0, 12.0)
    assert near_n == pytest.approx(1 / 0.75) and far_n == pytest.approx(12.0 / 1.5)
    centres = world_from_norm @ np.concatenate([c2w_n[:, :, 3], np.ones((3, 1))], axis=1).T
    np.testing.assert_allclose(centres[:3].T, cams.c2w[:, :, 3], atol=1e-12)
    rot_back = world_from_norm[:3, :3] / 1.5  # T scales by 1 / s = 0.75 * near = 1.5
    np.testing.assert_allclose(np.einsum("ij,njk->nik", rot_back, c2w_n[:, :, :3]),
                               cams.c2w[:, :, :3], atol=1e-12)
    np.testing.assert_allclose(c2w_n[:, :, 3].mean(axis=0), 0.0, atol=1e-12)
    mean_view = -c2w_n[:, :, 2].mean(axis=0)
    np.testing.assert_allclose(mean_view / np.linalg.norm(mean_view), [0, 0, -1], atol=1e-12)
    assert rays.forward_facing(c2w_n)

    fx, fy = cams.fx[0], cams.fy[0]
    z_near, z_far = rays.ndc_points(np.array([[0.3, 0.2, -near_n], [0.3, 0.2, -far_n]]),
                                    fx, fy, W, H, near=near_n)[:, 2]
    assert z_near == pytest.approx(-1.0) and 0.6 < z_far < 1.0
    assert rays.ndc_depth_to_world(z_far, near_n) == pytest.approx(far_n)

    norm = cam_mod.make_cameras(NAMES, c2w_n, fx, fy, W / 2, H / 2, W, H)
    origins, directions = rays.camera_rays(norm, 1)
    o_ndc, d_ndc = rays.ndc_rays(origins, directions, fx, fy, W, H, near=1.0)
    for t in (near_n, 3.0, far_n):
        p_ndc = rays.ndc_points(origins + t * directions, fx, fy, W, H, near=1.0)
        s = (p_ndc[..., 2] - o_ndc[..., 2]) / d_ndc[..., 2]
        assert np.all((s > 0) & (s < 1))
        np.testing.assert_allclose(o_ndc + s[..., None] * d_ndc, p_ndc, atol=1e-9)
    np.testing.assert_allclose((o_ndc + d_ndc)[..., 2], 1.0)  # t = 1 is infinitely far

    import jax.numpy as jnp

    o_j, d_j = rays.ndc_rays(jnp.asarray(origins), jnp.asarray(directions), fx, fy, W, H)
    assert not isinstance(o_j, np.ndarray)
    np.testing.assert_allclose(np.asarray(o_j), o_ndc, atol=1e-4)
    np.testing.assert_allclose(np.asarray(d_j), d_ndc, atol=1e-4)


def test_forward_facing_false_for_a_ring():
    ring = np.stack([_look_at([4 * np.sin(a), 0.5, 4 * np.cos(a)], np.zeros(3))
                     for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
    assert not rays.forward_facing(ring)


def test_bounds_from_points():
    cams = _scene_cams()
    pts = np.stack([_point_through(cams, 0, 32, 24, d) for d in np.linspace(2.0, 6.0, 101)])
    near, far = cam_mod.bounds_from_points(cams.take([0]), pts, margin=0.0)
    assert near == pytest.approx(2.04) and far == pytest.approx(5.96)


@pytest.mark.parametrize(
    "bad, problem",
    [(lambda m: m.__setitem__(0, np.nan), "NaN"),
     (lambda m: m.__setitem__(slice(0, 3), m[:3] * 1.1), "not rigid"),
     (lambda m: m.__setitem__((slice(None), 0), -m[:, 0]), "not rigid")],
)
def test_validate_rejects_bad_poses(bad, problem):
    cams = _scene_cams()
    c2w = cams.c2w.copy()
    bad(c2w[1])
    with pytest.raises(PoseError, match=problem) as info:
        cam_mod.validate(cams.with_c2w(c2w), "scene/transforms.json")
    assert "scene/transforms.json" in str(info.value) and "'b'" in str(info.value)


def _meta():
    cams = _scene_cams()
    frames = [{"file_path": f"raw/{n}.dng", "transform_matrix": np.vstack(
        [cams.c2w[i], [0, 0, 0, 1]]).tolist()} for i, n in enumerate(NAMES)]
    return {"fl_x": F, "fl_y": F, "cx": W / 2, "cy": H / 2, "w": W, "h": H, "frames": frames}


def test_transforms_overrides_splits_and_errors(tmp_path):
    path = tmp_path / "transforms.json"
    meta = _meta()
    meta["frames"][2]["fl_x"] = 70.0
    meta["test_filenames"] = ["b"]  # a stem; train is the rest
    path.write_text(json.dumps(meta))
    cams, split, near_far = pose_files.load_transforms(path)
    np.testing.assert_allclose(cams.fx, [F, F, 70.0])
    assert split == {"train": ["a", "c"], "test": ["b"]} and near_far is None

    meta["test_filenames"] = ["raw/zzz.dng"]
    path.write_text(json.dumps(meta))
    with pytest.raises(SceneError, match="zzz"):
        pose_files.load_transforms(path)

    meta = _meta()
    del meta["frames"][1]["transform_matrix"]
    path.write_text(json.dumps(meta))
    with pytest.raises(PoseError, match="gridnerf poses") as info:
        pose_files.load_transforms(path)
    assert str(path) in str(info.value) and "'b'" in str(info.value)


def test_llff_and_colmap_errors(tmp_path):
    cams = _scene_cams()
    _write_llff(tmp_path / "poses_bounds.npy", cams, scale=1.0)
    with pytest.raises(SceneError, match="3 poses for 4 raw frames"):
        pose_files.load_llff(tmp_path / "poses_bounds.npy", ["a", "b", "c", "d"], W, H)
    np.save(tmp_path / "bad.npy", np.zeros((3, 15)))
    with pytest.raises(SceneError, match="17"):
        pose_files.load_llff(tmp_path / "bad.npy", NAMES, W, H)
    with pytest.raises(SceneError, match="aspect"):
        pose_files.load_llff(tmp_path / "poses_bounds.npy", NAMES, W, W)
    _write_colmap_text(tmp_path / "sparse", cams, np.zeros((1, 3)))
    with pytest.raises(PoseError, match="remove the frame"):
        pose_files.load_colmap(tmp_path / "sparse", names=["a", "d"])
