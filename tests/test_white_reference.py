"""A white reference (a grey card in one frame) sets the capture's light: recovered from a
noisy dark card to under a degree, refused with one line where the box is not usable, and
taken by the colour plan in place of the estimators and the locus prior."""

from __future__ import annotations

import json
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from gridnerf import illuminant, white_reference
from gridnerf.errors import SceneError
from gridnerf.white_reference import WhiteRef


def _card_scene(light, electrons=30.0, seed=0, shape=(90, 160)):
    """A fake scene whose frames show a grey card lit by `light` (camera RGB) in the box
    x 40-119, y 20-69 (raw pixels) on a coloured backdrop, with shot noise at `electrons`
    photo-electrons per binned channel on the card."""
    rng = np.random.default_rng(seed)
    h, w = shape[0] // 2, shape[1] // 2
    light = np.asarray(light, np.float64) / np.max(light)
    clean = np.tile(np.array([0.9, 0.3, 0.1]) * light, (h, w, 1))
    clean[10:35, 20:60] = 0.5 * light
    noisy = rng.poisson(clean * electrons) / electrons - 0.0
    saturated = np.zeros((h, w, 3), bool)
    saturated[0:4, 0:4] = True

    def rgb_cam_binned(i, downscale=1):
        return noisy.astype(np.float32), ~saturated

    return SimpleNamespace(names=("a", "b"), rgb_cam_binned=rgb_cam_binned)


def test_a_noisy_dark_grey_card_gives_the_light_within_a_degree():
    for light in ([0.9, 1.0, 0.35], [0.6, 1.0, 0.9], [1.0, 0.8, 0.06]):  # warm, cool, sodium
        scene = _card_scene(light)
        est = white_reference.estimate(scene, WhiteRef("b", (40, 20, 80, 50)))
        assert float(illuminant.angular_error_deg(est, light)) < 1.0
        assert illuminant.gain_distance(est, light) < 0.1


def test_parse_and_transforms(tmp_path):
    assert white_reference.parse("frame_003:10,20,30,40") == WhiteRef("frame_003",
                                                                      (10, 20, 30, 40))
    for bad in ("frame_003", "f:1,2,3", "f:1,2,0,4", "f:a,b,c,d", "f:-1,0,4,4"):
        with pytest.raises(SceneError):
            white_reference.parse(bad)
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"frames": []}))
    assert white_reference.from_transforms(path) is None
    path.write_text(json.dumps({"white_reference": {"frame": "raw/x.dng", "box": [1, 2, 3, 4]}}))
    ref = white_reference.from_transforms(path)
    assert ref.frame == "x" and ref.box == (1, 2, 3, 4) and ref.source == str(path)
    path.write_text(json.dumps({"white_reference": [1, 2]}))
    with pytest.raises(SceneError, match="white_reference"):
        white_reference.from_transforms(path)


@pytest.mark.parametrize("ref, says", [
    (WhiteRef("zz", (40, 20, 80, 50)), "not one of the scene's frames"),
    (WhiteRef("a", (150, 20, 80, 50)), "outside"),
    (WhiteRef("a", (0, 0, 8, 8)), "unclipped"),  # clipped corner
    (WhiteRef("a", (40, 20, 6, 6)), "unclipped"),  # too small
])
def test_unusable_boxes_are_refused(ref, says):
    with pytest.raises(SceneError, match=says):
        white_reference.estimate(_card_scene([1.0, 1.0, 1.0]), ref)


def test_a_black_box_is_refused():
    scene = _card_scene([1.0, 1.0, 1e-4], electrons=0.5)
    with pytest.raises(SceneError, match="too dark"):
        white_reference.estimate(scene, WhiteRef("a", (40, 20, 80, 50)))


def test_the_colour_plan_takes_the_reference(small_scene, capsys):
    from dataclasses import replace

    from conftest import sim_near_far

    from gridnerf import colour_target, dataset
    from gridnerf import config as cfgmod
    from gridnerf.scene import load_scene

    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    ref = WhiteRef(scene.names[int(scene.train_idx[0])], (40, 30, 60, 40))
    scene = replace(scene, white_reference=ref)
    data = dataset.build(scene, scene.train_idx, True)
    _, colour = colour_target.plan_colour(data, scene, cfgmod.preset("tiny"))
    said = capsys.readouterr().out
    assert "white reference" in said and "L_ca estimator" not in said
    expect = white_reference.estimate(scene, ref)
    assert colour.estimator == "white_reference" and not colour.locus
    assert float(illuminant.angular_error_deg(np.asarray(colour.anchor), expect)) < 1e-6
    assert colour.evidence["white_reference"] == pytest.approx(tuple(expect))


def test_the_cli_refuses_a_bad_reference_in_one_line(small_scene, tmp_path):
    run = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "gridnerf.cli", "train", str(small_scene),
                           "--out", str(run), "--preset", "tiny", "--white-ref",
                           "nosuch:0,0,40,40"], capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if "nosuch" in ln]
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert not (run / "config.json").exists() and not (run / "checkpoint.npz").exists()


def test_measured_light_in_camera_rgb(tmp_path):
    """A light measured elsewhere, given as camera RGB on the command line or in
    transforms.json, is the light (unit); a malformed one is refused naming the field."""
    ref = white_reference.parse("rgb:0.6,1,0.3")
    assert ref.camera_rgb == (0.6, 1.0, 0.3) and ref.spec() == "rgb:0.6,1,0.3"
    est = white_reference.estimate(None, ref)
    assert est == pytest.approx(np.array([0.6, 1.0, 0.3]) / np.linalg.norm([0.6, 1.0, 0.3]))
    for bad in ("rgb:1,2", "rgb:1,0,1", "rgb:a,b,c", "rgb:1,nan,1"):
        with pytest.raises(SceneError, match="camera RGB"):
            white_reference.parse(bad)
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"white_reference": {"camera_rgb": [2, 4, 1]}}))
    assert white_reference.from_transforms(path).camera_rgb == (2.0, 4.0, 1.0)
    path.write_text(json.dumps({"white_reference": {"camera_rgb": [2, -4, 1]}}))
    with pytest.raises(SceneError, match="camera_rgb"):
        white_reference.from_transforms(path)
