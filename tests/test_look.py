"""Render controls (gridnerf.look): white balance parsing, paths through views, exposure."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gridnerf import color, illuminant, look
from gridnerf.errors import ConfigError


@pytest.mark.parametrize("spec, expected", [
    ("learned", look.White("learned")),
    ("as_shot", look.White("as_shot")),
    ("temp:3200", look.White("temperature", kelvin=3200.0)),
    ("temp:5000,-0.01", look.White("temperature", kelvin=5000.0, duv=-0.01)),
    ("neutral:frame_003:120,80", look.White("neutral", view="frame_003", box=(118, 78, 5, 5))),
    ("neutral:a:b:1,2,8,6", look.White("neutral", view="a:b", box=(1, 2, 8, 6))),
])
def test_white_balances_parse(spec, expected):
    assert look.parse_white(spec) == expected


@pytest.mark.parametrize("spec", ["", "daylight", "temp:", "temp:abc", "temp:500",
                                  "temp:4000,0.2", "neutral:frame_000", "neutral:f:1,2,0,3",
                                  "neutral:f:1,2,3", "temp:nan"])
def test_bad_white_balances_are_refused_with_the_forms(spec):
    with pytest.raises(ConfigError, match="learned, one_gain, as_shot|temp:K|neutral:VIEW"):
        look.parse_white(spec)


def _pose(angle_deg: float, position) -> np.ndarray:
    rot = Rotation.from_euler("y", angle_deg, degrees=True).as_matrix()
    return np.concatenate([rot, np.asarray(position, float)[:, None]], 1)


def test_views_path_passes_through_every_view_and_keeps_rotations_rigid():
    poses = np.stack([_pose(0, [0, 0, 0]), _pose(30, [1, 0, 0]), _pose(60, [2, 1, 0])])
    path = look.views_path(poses, 9)  # frames 0, 4, 8 fall on the views
    for k, i in enumerate([0, 4, 8]):
        np.testing.assert_allclose(path[i], poses[k], atol=1e-9)
    rot = path[:, :, :3]
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape),
                               atol=1e-9)
    angles = Rotation.from_matrix(rot).as_euler("yxz", degrees=True)[:, 0]
    assert np.all(np.diff(angles) > 0)  # turns one way, evenly
    np.testing.assert_allclose(np.diff(angles), 7.5, atol=1e-6)


class _Scene:
    as_shot_neutral = np.array([[0.5, 1.0, 0.25], [0.5, 1.0, 0.25]])
    xyz_to_cam = color.CAMERA_XYZ_TO_CAM[next(iter(color.CAMERA_XYZ_TO_CAM))]
    names = ["frame_000", "frame_001"]
    path = "scene"


def test_temperature_white_is_the_cameras_response_to_that_light():
    """temp:K gives the camera RGB of a blackbody at K through the file's matrix, or
    through the sensor's matrix the run took where it is given; a warmer light has a
    higher R/B; as_shot is the files' neutral."""
    scene = _Scene()
    warm = look.neutral_rgb(look.White("temperature", kelvin=2800.0), scene, None)
    cool = look.neutral_rgb(look.White("temperature", kelvin=8000.0), scene, None)
    expected = scene.xyz_to_cam @ color.blackbody_xyz_white(2800.0)
    assert illuminant.angular_error_deg(warm, expected) < 1e-6
    assert warm[0] / warm[2] > cool[0] / cool[2]
    sensor = np.diag([0.5, 1.0, 2.0]) @ scene.xyz_to_cam
    taken = look.neutral_rgb(look.White("temperature", kelvin=2800.0), scene, None, sensor)
    assert illuminant.angular_error_deg(taken, sensor @ color.blackbody_xyz_white(2800.0)) < 1e-6
    assert illuminant.angular_error_deg(taken, expected) > 1.0
    shot = look.neutral_rgb(look.White("as_shot"), scene, None)
    assert illuminant.angular_error_deg(shot, [0.5, 1.0, 0.25]) < 1e-6


def test_picked_neutral_reads_the_fields_low_light_colour_in_the_box():
    rgb_low = np.full((10, 12, 3), [0.1, 0.2, 0.05])
    rgb_low[2:5, 3:6] = [0.3, 0.2, 0.1]
    scene = _Scene()
    got = look.neutral_rgb(look.White("neutral", view="frame_001", box=(3, 2, 3, 3)), scene,
                           lambda i: {"rgb_low": rgb_low} if i == 1 else None)
    assert illuminant.angular_error_deg(got, [0.3, 0.2, 0.1]) < 1e-6
    with pytest.raises(Exception, match="outside the render"):
        look.neutral_rgb(look.White("neutral", view="frame_001", box=(10, 2, 5, 5)), scene,
                         lambda i: {"rgb_low": rgb_low})
    with pytest.raises(Exception, match="no frame named"):
        look.neutral_rgb(look.White("neutral", view="frame_9", box=(0, 0, 1, 1)), scene,
                         lambda i: {"rgb_low": rgb_low})
