"""Multi-view consistency metric: exact on a synthetic plane, sees colour disagreement."""

from __future__ import annotations

import numpy as np

from gridnerf import consistency, dataset, rays

H, W = 40, 60
INTR = np.array([50.0, 50.0, W / 2, H / 2])


def camera(x):
    c2w = np.zeros((3, 4))
    c2w[:, :3] = np.eye(3)
    c2w[0, 3] = x
    return c2w


def plane_view(x, depth=3.0):
    """Rays of a camera at (x, 0, 0) looking down -z at the plane z = -depth: world points,
    origins, directions and a smooth texture image of the plane (H, W, 3)."""
    o, d = (np.asarray(a, np.float64) for a in dataset.image_rays(camera(x), INTR, H, W))
    t = (-depth - o[..., 2]) / d[..., 2]
    p = o + t[..., None] * d
    image = np.stack([0.5 + 0.4 * np.sin(p[..., 0] * 2.0), 0.5 + 0.4 * np.cos(p[..., 1] * 3.0),
                      0.3 + 0.1 * p[..., 0]], -1)
    return p, o, d, t, image


def test_consistent_views_agree_and_a_colour_shift_is_measured():
    pa, oa, da, ta, img_a = plane_view(0.0)
    pb, ob, db, tb, img_b = plane_view(0.3)
    acc = np.ones((H, W))
    pts_a, ok_a = consistency.world_points(ta, acc, oa, da, ndc=False)
    pts_b, ok_b = consistency.world_points(tb, acc, ob, db, ndc=False)
    np.testing.assert_allclose(pts_a, pa, atol=1e-9)
    same = consistency.warp_disagreement(img_a, pts_a, ok_a, img_b, pts_b, ok_b, camera(0.3), INTR)
    shifted = consistency.warp_disagreement(img_a, pts_a, ok_a, img_b + 0.1, pts_b, ok_b,
                                            camera(0.3), INTR)
    # B is 0.3 to the side at 3 m with a 60-pixel-wide view of 50 px focal: ~5 px shift
    assert 0.8 < same["coverage"] < 1.0
    assert same["mae"] < 0.01  # nearest-pixel sampling of a smooth texture
    assert abs(shifted["mae"] - same["mae"] - 0.1) < 0.01


def test_occluded_and_transparent_pixels_are_left_out():
    pa, oa, da, ta, img_a = plane_view(0.0)
    pb, ob, db, tb, img_b = plane_view(0.3)
    acc = np.ones((H, W))
    pts_a, ok_a = consistency.world_points(ta, acc, oa, da, ndc=False)
    # B sees something nearer (1 m) in its left half: A's plane points there are occluded
    tb_occ = np.where(np.arange(W)[None, :] < W // 2, tb / 3.0, tb)
    pts_b, ok_b = consistency.world_points(tb_occ, acc, ob, db, ndc=False)
    full = consistency.warp_disagreement(img_a, pts_a, ok_a, img_b, *plane_world(tb, ob, db),
                                         camera(0.3), INTR)
    occ = consistency.warp_disagreement(img_a, pts_a, ok_a, img_b * 0.0, pts_b, ok_b,
                                        camera(0.3), INTR)
    assert occ["coverage"] < 0.6 * full["coverage"]
    assert occ["mae"] > 0.2  # what is left is compared with B's (black) right half
    # half-transparent rays of A have no surface: nothing counts
    _, ok_thin = consistency.world_points(ta * 0.3, acc * 0.3, oa, da, ndc=False)
    none = consistency.warp_disagreement(img_a, pts_a, ok_thin, img_b, pts_b, ok_b,
                                         camera(0.3), INTR)
    assert none["coverage"] == 0.0 and np.isnan(none["mae"])


def plane_world(t, o, d):
    return consistency.world_points(t, np.ones(t.shape), o, d, ndc=False)


def test_ndc_points_map_back_to_the_world():
    """The NDC ray parameter of a world point, turned back by world_points, is the point."""
    _, o, d, _, _ = plane_view(0.0)
    depth = np.linspace(1.5, 20.0, H * W).reshape(H, W)
    p = o + depth[..., None] * d  # camera at the origin looking down -z: z = -depth
    fx, fy = INTR[0], INTR[1]
    o_n, d_n = rays.ndc_rays(o, d, fx, fy, W, H, near=1.0, xp=np)
    t = (rays.ndc_points(p, fx, fy, W, H, near=1.0, xp=np)[..., 2] - o_n[..., 2]) / d_n[..., 2]
    back, ok = consistency.world_points(t, np.ones((H, W)), o_n, d_n, ndc=True,
                                        ndc_intrinsics=np.array([fx, fy, W, H]))
    assert ok.all()
    np.testing.assert_allclose(back, p, rtol=1e-6, atol=1e-6)
