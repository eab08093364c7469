"""The colour priors check themselves against the frames: frames far off the Planckian
locus of the file's ColorMatrix, or a matrix that differs from its camera's reference, give
up the locus prior with one printed line and fall back to the frames' own estimate,
unprojected; estimators that disagree widely under one light fall back to grey world."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from gridnerf import colour_target, illuminant
from gridnerf import config as cfgmod
from gridnerf.color import CAMERA_XYZ_TO_CAM, _uv, blackbody_xyz_white, tinted_xyz_white

SONY = "Sony ILCE-7SM2"


def test_tinted_light_moves_off_the_locus_by_its_duv():
    np.testing.assert_array_equal(tinted_xyz_white(2800.0, 0.0), blackbody_xyz_white(2800.0))
    for kelvin in (2100.0, 3500.0, 6500.0):
        for duv in (-0.01, 0.02):
            shift = _uv(tinted_xyz_white(kelvin, duv)) - _uv(blackbody_xyz_white(kelvin))
            assert np.linalg.norm(shift) == pytest.approx(abs(duv), rel=1e-6)
            assert np.sign(shift[1]) == np.sign(duv)  # + above the locus: towards green
            assert tinted_xyz_white(kelvin, duv)[1] == pytest.approx(1.0)


def test_matrix_disagreement_sees_a_scaled_or_foreign_matrix():
    m = CAMERA_XYZ_TO_CAM[SONY]
    assert illuminant.matrix_disagreement_deg(m, m) == pytest.approx(0.0, abs=1e-6)
    assert illuminant.matrix_disagreement_deg(3.0 * m, m) == pytest.approx(0.0, abs=1e-6)
    scaled = np.diag([1.25, 1.0, 0.7]) @ m
    gap = illuminant.matrix_disagreement_deg(scaled, m)
    assert gap > colour_target.MATRIX_AGREE_DEG
    assert illuminant.matrix_disagreement_deg(m, scaled) == pytest.approx(gap)
    for other in CAMERA_XYZ_TO_CAM:
        if other != SONY:
            assert illuminant.matrix_disagreement_deg(CAMERA_XYZ_TO_CAM[other], m) > 0.1


def test_matrix_check_names_the_camera_only_where_the_file_disagrees():
    m = CAMERA_XYZ_TO_CAM[SONY]
    assert colour_target.matrix_check(SimpleNamespace(camera_model=SONY, xyz_to_cam=m)) is None
    assert colour_target.matrix_check(SimpleNamespace(camera_model="Unknown X1",
                                                      xyz_to_cam=np.eye(3))) is None
    why = colour_target.matrix_check(SimpleNamespace(
        camera_model=SONY, xyz_to_cam=np.diag([1.25, 1.0, 0.7]) @ m))
    assert why is not None and SONY in why


def _uniform_frames(neutral_cam, n=4, shape=(24, 32)):
    """Frames of a grey-and-coloured checker lit by `neutral_cam` (camera RGB of white)."""
    rng = np.random.default_rng(0)
    paint = rng.uniform(0.2, 0.8, (n, *shape, 1)) * np.array([1.0, 1.0, 1.0])
    images = [0.01 * p * np.asarray(neutral_cam) for p in paint]
    return images, [np.ones(shape, bool) for _ in images]


def test_locus_check_trusts_blackbody_light_and_refuses_far_or_end_points():
    m = CAMERA_XYZ_TO_CAM[SONY]
    scene = SimpleNamespace(xyz_to_cam=m, camera_model=SONY)
    on = m @ blackbody_xyz_white(2800.0)
    trusted, angle, kelvin, gap, free = colour_target.locus_check(scene, _uniform_frames(on))
    assert trusted and angle < 0.5 and gap < 0.05 and 2500 < kelvin < 3100
    assert set(free) == set(illuminant.CONSENSUS)
    green = on * np.array([1.0, 1.4, 1.0])  # a strong green cast: far off the locus
    trusted, angle, _, _, _ = colour_target.locus_check(scene, _uniform_frames(green))
    assert not trusted and angle > colour_target.LOCUS_TRUST_DEG
    red = m @ blackbody_xyz_white(1200.0)  # redder than the locus's first entry: its end
    trusted, _, kelvin, _, _ = colour_target.locus_check(scene, _uniform_frames(red))
    assert not trusted and kelvin <= colour_target.LOCUS_END_KELVIN[0]


def test_locus_check_sees_a_weak_channel_the_angle_hides():
    """A sodium-like lamp (2100 K, 0.02 Duv above the locus): its blue is a few per cent of
    its green, so its angle to the locus is small; its grey world's gains differ from the
    projection's by more than LOCUS_TRUST_GAIN, and the prior is given up."""
    m = CAMERA_XYZ_TO_CAM[SONY]
    scene = SimpleNamespace(xyz_to_cam=m, camera_model=SONY)
    sodium = m @ tinted_xyz_white(2100.0, 0.02)
    trusted, angle, _, gap, _ = colour_target.locus_check(scene, _uniform_frames(sodium))
    assert angle < colour_target.LOCUS_TRUST_DEG  # the angle alone would trust it
    assert gap > colour_target.LOCUS_TRUST_GAIN and not trusted



def test_the_locus_prior_yields_to_estimators_that_agree_off_it():
    """A light 0.01 Duv above the locus at 2800 K: 3 deg from the locus and grey world 0.13
    from it, inside the angle and gain bounds, but the three estimators agree exactly on
    it (uniform paint): the prior would pull the light further than the frames doubt it,
    and is given up. A light nearer the locus (0.004 Duv) keeps it: its pull is under
    LOCUS_GAP_FLOOR."""
    m = CAMERA_XYZ_TO_CAM[SONY]
    scene = SimpleNamespace(xyz_to_cam=m, camera_model=SONY)
    off = m @ tinted_xyz_white(2800.0, 0.01)
    trusted, angle, _, gap, free = colour_target.locus_check(scene, _uniform_frames(off))
    assert angle < colour_target.LOCUS_TRUST_DEG and gap < colour_target.LOCUS_TRUST_GAIN
    assert colour_target.estimators_disagree(free) < 0.01
    assert gap > colour_target.LOCUS_GAP_FLOOR and not trusted
    near = m @ tinted_xyz_white(2800.0, 0.004)
    trusted, _, _, gap, _ = colour_target.locus_check(scene, _uniform_frames(near))
    assert 0.0 < gap < colour_target.LOCUS_GAP_FLOOR and trusted


def test_consistent_takes_grey_world_where_one_light_or_several_cannot_be_told(capsys):
    """A light spread inside LIGHT_DOUBT_DEG: not the quadrant pick, grey world, with one
    printed line; above the band grey world for the lights' mix, below it the pick."""
    frames = _uniform_frames(np.ones(3))
    lo, hi = colour_target.LIGHT_DOUBT_DEG
    for spread in (lo, 0.5 * (lo + hi), hi - 1e-3):
        assert colour_target.consistent_estimator(frames, spread=(spread, {})) == "grey_world"
        assert "cannot be told" in capsys.readouterr().out
    assert colour_target.consistent_estimator(frames, spread=(hi, {})) == "grey_world"
    assert "lights mix" in capsys.readouterr().out
    wholes = {n: np.ones(3) for n in illuminant.CONSENSUS}
    name = colour_target.consistent_estimator(frames, spread=(lo - 0.1, wholes))
    assert name in illuminant.CONSENSUS and "one light" in capsys.readouterr().out

def test_consistent_takes_grey_world_where_the_estimators_disagree(capsys):
    frames = _uniform_frames(np.ones(3))
    name = colour_target.consistent_estimator(
        frames, disagreement=colour_target.ESTIMATORS_AGREE + 0.1)
    assert name == "grey_world" and "disagree" in capsys.readouterr().out
    for given_up in (False, True):  # disagreement wins over a given-up locus
        name = colour_target.consistent_estimator(
            frames, disagreement=colour_target.ESTIMATORS_AGREE + 0.1, given_up=given_up)
        assert name == "grey_world"
    name = colour_target.consistent_estimator(frames, given_up=True)
    assert name == "grey_world" and "given up" in capsys.readouterr().out
    # under mixed light grey world, for the lights' mix, whatever the disagreement
    for disagreement in (0.0, colour_target.ESTIMATORS_AGREE + 1):
        name = colour_target.consistent_estimator(
            frames, spread=(2 * colour_target.ONE_LIGHT_DEG, {}), disagreement=disagreement)
        assert name == "grey_world" and "lights mix" in capsys.readouterr().out


@pytest.fixture(scope="module")
def colour_scenes(tmp_path_factory):
    from gridnerf.sim import simulate_scene

    root = tmp_path_factory.mktemp("colour")
    return {n: simulate_scene(n, root / n, width=160, height=90, n_frames=12, seed=0)
            for n in ("held_colour_generic", "held_colour_other", "held_colour_sodium",
                      "held_unit_own")}


def _plan(scene_dir):
    from conftest import sim_near_far

    from gridnerf import dataset
    from gridnerf.scene import load_scene

    scene = load_scene(scene_dir, near_far=sim_near_far(scene_dir))
    data = dataset.build(scene, scene.train_idx, True)
    _, colour = colour_target.plan_colour(data, scene, cfgmod.preset("tiny"))
    frames = colour_target.estimate_frames(data, scene)
    free = colour_target.scene_illuminant(frames, "consensus", colour.estimate_downscale)
    return scene, colour, free


def test_an_off_locus_light_falls_back_near_grey_world(colour_scenes, capsys):
    """A sodium-like lamp, 0.02 Duv above the locus: the printed fallback, and the
    capture's light within 3 deg of the frames' grey world (unprojected), nearer the true
    light than the locus would have put it."""
    import json

    scene, colour, _ = _plan(colour_scenes["held_colour_sodium"])
    out = capsys.readouterr().out
    assert out.count("locus prior is given up") == 1 and not colour.locus
    grey = np.asarray(colour.evidence["grey_world"])
    anchor = np.asarray(colour.anchor)
    assert float(illuminant.angular_error_deg(anchor, grey)) < 3.0
    assert {"grey_world", "shades_of_grey", "grey_edge", "as_shot"} <= set(colour.evidence)
    truth = np.asarray(json.loads((colour_scenes["held_colour_sodium"] / "sim.json")
                                  .read_text())["illuminant_neutral_cam"])
    projected = illuminant.to_locus(grey, illuminant.planckian_locus(scene.xyz_to_cam))
    assert (illuminant.gain_distance(anchor, truth)
            < illuminant.gain_distance(projected, truth) - 0.3)


@pytest.mark.parametrize("name", ["held_colour_generic", "held_colour_other"])
def test_a_wrong_matrix_is_replaced_by_the_reference_the_frames_agree_with(
        colour_scenes, capsys, name):
    """A generic matrix and another camera's: one printed line naming the camera, the
    locus prior built from its reference matrix (recorded in the plan), the capture's light
    on that locus. (How near the truth it lands on the full-size captures:
    experiments.colour_checks.)"""
    scene, colour, _ = _plan(colour_scenes[name])
    out = capsys.readouterr().out
    assert out.count("reference matrix") == 1 and scene.camera_model in out
    assert colour.locus and colour.locus_matrix is not None
    reference = CAMERA_XYZ_TO_CAM[scene.camera_model]
    np.testing.assert_allclose(np.reshape(colour.locus_matrix, (3, 3)), reference)
    anchor = np.asarray(colour.anchor)
    on_reference = illuminant.to_locus(anchor, illuminant.planckian_locus(reference))
    assert float(illuminant.angular_error_deg(anchor, on_reference)) < 0.2


def test_a_units_own_matrix_is_kept_where_the_frames_agree_with_it_better(colour_scenes,
                                                                          capsys):
    """A unit whose channels leak into their neighbours (4.4 deg from its model's reference),
    its own matrix in the file: the matrix check fires, but the frames' grey world lies
    nearer the file's locus than the reference's, so the file's matrix stays the sensor's
    for the locus prior and the display (one printed line saying so)."""
    scene, colour, _ = _plan(colour_scenes["held_unit_own"])
    out = capsys.readouterr().out
    assert colour_target.matrix_check(scene) is not None
    assert out.count("is kept as the sensor's") == 1 and "reference matrix" not in out
    assert colour.locus and colour.locus_matrix is None
    np.testing.assert_array_equal(colour.sensor_matrix(scene.xyz_to_cam), scene.xyz_to_cam)


def test_the_simulated_unit_leaks_into_its_neighbours():
    """The simulator's crosstalk keeps a grey grey, and at 0.1 puts the sensor over the
    2 deg at which a file's matrix is called not its camera's."""
    from gridnerf.sim.sensor import SensorParams, crosstalk_matrix

    np.testing.assert_allclose(crosstalk_matrix(0.1) @ np.ones(3), np.ones(3))
    unit = SensorParams(camera_model=SONY, crosstalk=0.1)
    gap = illuminant.matrix_disagreement_deg(unit.xyz_to_cam, CAMERA_XYZ_TO_CAM[SONY])
    assert colour_target.MATRIX_AGREE_DEG < gap < 6.0
    np.testing.assert_array_equal(SensorParams(camera_model=SONY).xyz_to_cam,
                                  CAMERA_XYZ_TO_CAM[SONY])
    with pytest.raises(ValueError, match="crosstalk"):
        SensorParams(crosstalk=0.6)


def test_a_wrong_matrix_of_an_unknown_camera_is_checked_by_the_frames(colour_scenes, capsys):
    """The generic matrix in a file whose camera is not in the reference table: only the
    frames can tell, and they give the prior up (grey world, unprojected)."""
    from dataclasses import replace

    from conftest import sim_near_far

    from gridnerf import dataset
    from gridnerf.scene import load_scene

    folder = colour_scenes["held_colour_generic"]
    scene = replace(load_scene(folder, near_far=sim_near_far(folder)), camera_model="X1")
    data = dataset.build(scene, scene.train_idx, True)
    _, colour = colour_target.plan_colour(data, scene, cfgmod.preset("tiny"))
    out = capsys.readouterr().out
    assert out.count("locus prior is given up") == 1
    assert not colour.locus and colour.estimator == "grey_world"


def test_another_camera_s_matrix_is_named(colour_scenes, capsys):
    """held_colour_other: the file names one camera and carries another's matrix: the line
    that gives the prior up names that camera."""
    scene, colour, _ = _plan(colour_scenes["held_colour_other"])
    out = capsys.readouterr().out
    assert scene.camera_model in CAMERA_XYZ_TO_CAM  # the DNG names its camera
    assert out.count("differs from") == 1 and scene.camera_model in out


def test_a_right_matrix_keeps_the_prior(small_scene, capsys):
    _, colour, _ = _plan(small_scene)
    assert "locus prior is given up" not in capsys.readouterr().out
    assert colour.locus and colour.estimator in illuminant.CONSENSUS + ("consensus",)
