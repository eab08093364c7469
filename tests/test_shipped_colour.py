"""The end-of-training safety net: a gain field whose white no estimate of the frames
supports is not shipped; one grey-world gain on the same field is, and the run says so.
And gain_distance, the measure every colour check uses."""

from __future__ import annotations

import numpy as np
import pytest

from gridnerf import illuminant, outputs, shipped_colour
from gridnerf import plan as planmod
from gridnerf.plan import ColourPlan


def test_gain_distance_measures_what_the_gains_do():
    a = np.array([0.6, 0.8, 0.05])
    assert illuminant.gain_distance(a, a) == 0.0
    assert illuminant.gain_distance(a, 7.0 * a) == pytest.approx(0.0, abs=1e-12)  # scale-free
    b = a * np.array([1.0, 1.0, 3.0])  # one channel three times as strong
    d = illuminant.gain_distance(a, b)
    assert d == pytest.approx(np.sqrt(2.0 / 3.0) * np.log(3.0))
    assert illuminant.gain_distance(b, a) == pytest.approx(d)
    # the angle hides the weak channel's error that the gains carry in full
    assert float(illuminant.angular_error_deg(a, b)) < 10.0 and d > 0.85
    assert np.isfinite(illuminant.gain_distance(a, np.array([1.0, 0.0, 0.0])))


def _render(light, gains, n=500, seed=0):
    """A training render: paint under `light` (rgb_low) and the field's gains on it."""
    rng = np.random.default_rng(seed)
    low = rng.uniform(0.1, 1.0, (n, 1)) * rng.uniform(0.5, 1.0, (n, 3)) * np.asarray(light)
    return {"rgb_low": low.astype(np.float32),
            "rgb_restored": (low * np.asarray(gains)).astype(np.float32)}


def test_shipped_white_is_the_light_the_gains_undo():
    light = np.array([0.7, 0.65, 0.3])
    out = _render(light, illuminant.gains_from_illuminant(light))
    assert float(illuminant.angular_error_deg(shipped_colour.shipped_white(out), light)) < 1e-3


def _colour(light):
    light = np.asarray(light, np.float64)
    evidence = {"grey_world": tuple(light * [1.02, 1.0, 0.97]),
                "shades_of_grey": tuple(light * [0.95, 1.0, 1.1]), "as_shot": tuple(light)}
    return ColourPlan(model="field", estimator="grey_world", anchor=tuple(light),
                      gains=tuple(illuminant.gains_from_illuminant(light)), evidence=evidence)


def test_a_field_near_the_frames_estimates_is_shipped(capsys):
    light = np.array([0.7, 0.65, 0.3])
    colour, record = shipped_colour.check(
        _render(light, illuminant.gains_from_illuminant(light * [1.05, 1.0, 0.95])),
        _colour(light))
    assert colour == _colour(light) and record["shipped"] == "field"
    assert record["distance"] <= shipped_colour.SHIP_TRUST
    assert "the field is shipped" in capsys.readouterr().out


def test_under_one_light_the_fields_white_is_shipped_as_one_gain(capsys):
    """Model only what the scene needs: where the maps show one light, a supported field's
    white becomes one gain (the white the field undoes on average); under lights that mix,
    or a spread in the doubt band, the field is shipped."""
    from dataclasses import replace

    from gridnerf import colour_target

    light = np.array([0.7, 0.65, 0.3])
    out = _render(light, illuminant.gains_from_illuminant(light * [1.05, 1.0, 0.95]))
    one = colour_target.LIGHT_DOUBT_DEG[0] - 0.1
    colour, record = shipped_colour.check(out, replace(_colour(light), light_spread_deg=one))
    assert record["shipped"] == "one_gain" and "one light" in capsys.readouterr().out
    white = shipped_colour.shipped_white(out)
    assert colour.shipped_gains == pytest.approx(tuple(illuminant.gains_from_illuminant(white)))
    for spread in (colour_target.LIGHT_DOUBT_DEG[0], colour_target.LIGHT_DOUBT_DEG[1] + 1.0):
        colour, record = shipped_colour.check(out, replace(_colour(light),
                                                           light_spread_deg=spread))
        assert record["shipped"] == "field" and colour.shipped_gains is None


def test_a_field_no_estimate_supports_falls_back_to_one_grey_world_gain(capsys, tmp_path):
    light = np.array([0.7, 0.65, 0.3])
    drifted = light * np.array([1.0, 1.0, 3.0])  # the field's white: three times the blue
    out = _render(light, illuminant.gains_from_illuminant(drifted))
    colour, record = shipped_colour.check(out, _colour(light))
    said = capsys.readouterr().out
    assert said.count("colour check:") == 1 and "one grey-world gain" in said
    assert record["shipped"] == "one_gain" and record["distance"] > shipped_colour.SHIP_TRUST
    assert colour.shipped_gains == pytest.approx(tuple(outputs.global_gains(out)))
    assert colour.model == "field"  # what was trained stays recorded
    # the run plan shows the shipped gain, and keeps it through plan.json
    plan = planmod.RunPlan(method="brightnerf", black_level="file", data_noise=0.01,
                           data_eps=0.001, colour=colour, opacity=(0.0,), n_candidates=(8,))
    assert plan.one_gain == colour.shipped_gains
    planmod.save(tmp_path, plan)
    back = planmod.load(tmp_path)
    assert back == plan and back.colour.shipped_why == colour.shipped_why
    assert back.colour.evidence["as_shot"] == pytest.approx(tuple(light))


def test_non_finite_whites_fall_back_and_plans_without_a_field_pass():
    light = np.array([0.7, 0.65, 0.3])
    out = _render(light, illuminant.gains_from_illuminant(light))
    out["rgb_restored"][:] = np.nan
    colour, record = shipped_colour.check(out, _colour(light))
    assert record["shipped"] == "one_gain"
    for model in ("one_gain", "none"):
        c = ColourPlan(model=model)
        assert shipped_colour.check(out, c) == (c, {"shipped": model})
