"""Lens falloff: the fit of paired observations recovers a known falloff from noisy pixels
and finds none where there is none; apply takes it off the binned pixels; the plan keeps
it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gridnerf import dataset, vignetting
from gridnerf import plan as planmod


def _data(n=3, h=30, w=40) -> dataset.RayData:
    import jax.numpy as jnp

    intr = np.tile(np.array([50.0, 50.0, w / 2, h / 2], np.float32), (n, 1))
    return dataset.RayData(
        c2w=jnp.zeros((n, 3, 4)), intrinsics=jnp.asarray(intr), ndc_intrinsics=jnp.zeros(4),
        pixels=jnp.ones((n, h, w, 3), jnp.float32), valid=jnp.ones((n, h, w, 3), bool),
        black=jnp.zeros((n, 2, 2)), white=jnp.ones(n), inv_exposure=jnp.ones(n),
        cfa=jnp.zeros((2, 2), jnp.int32))


def test_radius_is_zero_at_the_centre_and_one_at_the_corners():
    data = _data()
    h, w = data.image_hw
    r2 = vignetting.radius2(data, np.array([0, 0, 1]), np.array([h / 2 - 0.5, -0.5, h - 0.5]),
                            np.array([w / 2 - 0.5, -0.5, w - 0.5]))
    np.testing.assert_allclose(r2, [0.0, 1.0, 1.0], atol=1e-9)


@pytest.mark.parametrize("stops", [0.0, 0.5, 1.2])
def test_pairs_recover_a_radial_falloff_from_noisy_pixels(stops):
    """Surface points of random radiance, each seen twice at random radii through the
    simulator's cos^4 falloff with ~5 photo-electrons of shot noise: the fit gives the
    corner falloff to 0.05 stop."""
    rng = np.random.default_rng(0)
    n = 400_000
    radiance = rng.uniform(0.01, 0.05, n)
    r2_i, r2_j = rng.uniform(0.0, 1.0, n), rng.uniform(0.0, 1.0, n)
    c = 2.0 ** (stops / 2) - 1  # 1 / (1 + c r^2)^2: `stops` darker at r = 1

    def seen(r2):
        return rng.poisson(radiance / (1.0 + c * r2) ** 2 * 200.0) / 200.0

    k = vignetting.fit_pairs(r2_i, r2_j, seen(r2_i), seen(r2_j))
    assert vignetting.corner_stops(k) == pytest.approx(stops, abs=0.05)


def test_nothing_to_fit_gives_no_falloff():
    assert vignetting.fit_pairs(*(np.zeros(0),) * 4) == (0.0, 0.0)
    z = np.zeros(10)
    assert vignetting.fit_pairs(z, z, z, z) == (0.0, 0.0)


def test_apply_divides_the_binned_pixels_by_the_falloff():
    data = _data()
    k = (-0.6, -0.1)
    out = vignetting.apply(data, k)
    n, h, w = 3, *data.image_hw
    f, v, u = np.meshgrid(np.arange(n), np.arange(h), np.arange(w), indexing="ij")
    r2 = vignetting.radius2(data, f, v, u)
    np.testing.assert_allclose(np.asarray(out.pixels)[..., 1], np.exp(0.6 * r2 + 0.1 * r2**2),
                               rtol=1e-5)
    assert vignetting.apply(data, None) is data and vignetting.apply(data, (0.0, 0.0)) is data


def test_apply_divides_the_mosaic_targets_as_they_are_read():
    """A mosaic keeps its raw integers: its targets are divided by the falloff when a batch
    reads them, and a second estimate (what is left after the second stage) adds to it."""
    import jax.numpy as jnp

    n, h, w = 2, 30, 40
    raw_bayer = np.full((n, h, w), 500, np.uint16)
    data = replace(_data(n, h, w), pixels=jnp.asarray(raw_bayer), valid=jnp.ones(n, bool),
                   white=jnp.full(n, 1000.0), mosaic=True)
    f, v, u = np.meshgrid(np.arange(n), np.arange(h), np.arange(w), indexing="ij")
    r2 = vignetting.radius2(data, f, v, u)

    def level(d):  # the one measured channel of each target
        y, m = dataset.targets(d, jnp.asarray(f), jnp.asarray(v), jnp.asarray(u))
        return np.asarray(y).sum(-1)

    np.testing.assert_allclose(level(data), 0.5, rtol=1e-6)
    once = vignetting.apply(data, (-0.6, -0.1))
    assert once.pixels is data.pixels
    np.testing.assert_allclose(level(once), 0.5 * np.exp(0.6 * r2 + 0.1 * r2**2), rtol=1e-5)
    twice = vignetting.apply(once, (-0.2, 0.0))
    np.testing.assert_allclose(np.asarray(twice.falloff), [-0.8, -0.1], rtol=1e-6)
    np.testing.assert_allclose(level(twice), 0.5 * np.exp(0.8 * r2 + 0.1 * r2**2), rtol=1e-5)


def test_plan_round_trip_keeps_the_falloff():
    colour = planmod.ColourPlan(model="none")
    plan = planmod.RunPlan(method="brightnerf", black_level="file", data_noise=None,
                           data_eps=1e-3, colour=colour, opacity=(0.1,), n_candidates=(4,),
                           vignetting=(-0.5, -0.1))
    back = planmod.from_dict(planmod.to_dict(plan))
    assert back.vignetting == (-0.5, -0.1)
    old = planmod.to_dict(plan)
    del old["vignetting"]  # a plan written before the falloff was estimated
    assert planmod.from_dict(old).vignetting is None


def test_training_takes_a_lens_falloff_off_and_leaves_a_clean_lens_alone(small_scene,
                                                                           tmp_path):
    """bucket shot through a lens 1.5 stops down at the corners (the simulator's cos^4 law,
    otherwise the same capture as small_scene): a small training finds the falloff after
    its first stage and keeps it in the plan, fitting the binned raw or the mosaic; the
    clean capture keeps none."""
    from gridnerf import config as cfgmod
    from gridnerf.sim import scenes, simulate_scene, writer
    from gridnerf.train import train

    base = scenes.build_scene("bucket")
    spec = replace(base, sensor=replace(base.sensor, vignette_stops=1.5))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(writer, "build_scene", lambda name: spec)
        folder = simulate_scene("bucket", tmp_path / "vignetted", width=160, height=90,
                                n_frames=12, seed=0)
    # the tiny preset with a longer first stage: its depth must place the pixels (after 40
    # steps of a 24x24x16 grid nothing is opaque yet; after 400 the estimate reads 1.14)
    cfg = cfgmod.override(cfgmod.preset("tiny"), ["train.steps_per_stage=[400,20]"])
    train(folder, tmp_path / "run", cfg)
    k = planmod.load(tmp_path / "run").vignetting
    assert k is not None and vignetting.corner_stops(k) == pytest.approx(1.5, abs=0.5)
    train(folder, tmp_path / "mosaic", cfgmod.override(cfg, ["data.binning=false"]))
    k = planmod.load(tmp_path / "mosaic").vignetting
    assert k is not None and vignetting.corner_stops(k) == pytest.approx(1.5, abs=0.5)
    train(small_scene, tmp_path / "clean", cfg)
    assert planmod.load(tmp_path / "clean").vignetting is None


def test_parallax_is_the_angle_between_the_rays_at_the_point():
    """Two cameras 1 apart, a point 1 in front of the first: 45 deg; straight ahead of both
    (the same ray): 0; a camera behind the point: 180."""
    point = np.array([[0.0, 0.0, 1.0]])
    assert vignetting.parallax_deg(np.zeros(3) - point, np.array([1.0, 0.0, 0.0]) - point
                                   ) == pytest.approx([45.0])
    assert vignetting.parallax_deg(-point, -2 * point) == pytest.approx([0.0], abs=1e-6)
    assert vignetting.parallax_deg(-point, point) == pytest.approx([180.0])
