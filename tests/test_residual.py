"""The detail a stage leaves against the frames' noise (gridnerf.residual) and the last
stage it sets (plan.refined_config)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gridnerf import config as cfgmod
from gridnerf import plan as planmod
from gridnerf import residual
from gridnerf.errors import ConfigError


def _greens(rng, n, detail_var, level):
    """Two greens' residuals: a shared detail of variance detail_var, Poisson shot noise of
    `level` electrons (scaled to unit mean) plus heavy-tailed read noise."""
    d = rng.normal(0.0, np.sqrt(detail_var), n)
    def noise():
        shot = (rng.poisson(level) - level) / level
        read = 0.05 * rng.standard_t(4, n)
        return shot + read
    return d + noise(), d + noise()


@pytest.mark.parametrize("electrons", [3.0, 30.0])
def test_the_reading_is_the_missed_detail_over_the_noise_whatever_its_distribution(electrons):
    """Shot noise of a few electrons (skewed) and Student-t read noise (heavy tails): the
    reading is the shared detail's variance over one photosite's noise variance, 0 without
    detail, and it does not depend on the noise's scale per level."""
    rng = np.random.default_rng(0)
    n = 200_000
    level = np.full(n, electrons)
    noise_var = 1.0 / electrons + 0.05**2 * 2.0  # Poisson / level^2 * level; t(4): var 2
    for share in (0.0, 0.1, 0.5):
        r1, r2 = _greens(rng, n, share * noise_var, level)
        got, error = residual.detail_over_noise(r1, r2, rng.uniform(size=n))
        assert got == pytest.approx(share, abs=0.02)
        assert 0.5 / np.sqrt(n) < error < 0.02  # about 1 / sqrt(cells) for pure noise
        assert abs(got - share) < 4 * error
    # the noise twice as strong on half of the cells: the per-level ratio still reads it
    r1, r2 = _greens(rng, n, 0.2 * noise_var, level)
    bright = np.arange(n) >= n // 2
    r1[bright] *= 2.0
    r2[bright] *= 2.0
    assert residual.detail_over_noise(r1, r2, bright.astype(float))[0] == pytest.approx(
        0.2, abs=0.02)


def test_detail_that_differs_between_the_greens_counts_as_noise():
    """Conservative: detail at the photosite scale (independent at the two greens) reads as
    noise, not as detail a finer grid could hold."""
    rng = np.random.default_rng(1)
    n = 100_000
    r1, r2 = rng.normal(0, 1, n) + rng.normal(0, 1, n), rng.normal(0, 1, n) + rng.normal(0, 1, n)
    assert abs(residual.detail_over_noise(r1, r2, np.zeros(n))[0]) < 0.02
    assert np.isnan(residual.detail_over_noise(r1[:10], r2[:10], np.zeros(10))).all()


def test_the_read_cells_are_the_two_greens_of_each_cell():
    class Data:
        image_hw = (8, 12)
        c2w = np.zeros((9, 3, 4))
        cfa = np.array([[0, 1], [1, 2]])

    fr, v, u = residual.cell_pixels(Data(), every=4)
    assert sorted(set(fr[0].tolist())) == [0, 4, 8]
    assert fr.shape == v.shape == u.shape == (2, 3 * 4 * 6)
    assert np.all(Data.cfa[v % 2, u % 2] == 1)
    assert np.all((v[0] // 2 == v[1] // 2) & (u[0] // 2 == u[1] // 2))
    assert np.all(v[0] != v[1])  # different rows: row noise is not shared
    fr, v, u = residual.cell_pixels(Data(), every=1, max_cells=6)
    assert v.shape[1] <= 9 * 6 * 2


def test_the_refined_plan_trains_a_wider_last_stage_with_its_priors_per_unit_of_scene():
    cfg = cfgmod.Config()
    plan = planmod.RunPlan(method="brightnerf", black_level="file", data_noise=None,
                           data_eps=1e-3, colour=planmod.ColourPlan(), opacity=(0, 0, 0),
                           n_candidates=(0, 0, 0))
    assert planmod.refined_config(cfg, plan) is cfg
    wide = planmod.refined_config(cfg, planmod.from_dict(planmod.to_dict(
        replace(plan, detail=4.0, last_width=288))))
    assert wide.grid.resolutions[:-1] == cfg.grid.resolutions[:-1]
    assert wide.grid.resolutions[-1] == (288, 0, cfg.grid.resolutions[-1][2])
    assert wide.loss.tv_ref_width == cfg.grid.resolutions[-1][0]
    assert wide.render.max_samples == round(cfg.render.max_samples * 1.5)
    with pytest.raises(ConfigError, match="detail_width"):
        cfgmod.override(cfg, ["grid.detail_width=-1"])
    # a width no wider than the last stage never refines it (refined_width)
    assert cfgmod.override(cfg, ["grid.detail_width=100"]).grid.detail_width == 100



def test_the_refined_width_needs_the_reading_over_its_error_and_the_photosites_to_hold_it():
    """refined_width: None with the option off, a reading not measured or within SIGMAS
    errors of ABOVE; otherwise detail_width, but never finer than FOOTPRINT photosites per
    vertex, and None where that is no wider than the config's last stage."""
    assert residual.finest_width(480) == 288 and residual.finest_width(320) == 192
    over = residual.ABOVE + 3 * residual.SIGMAS * 0.05
    assert residual.refined_width(over, 0.05, 288, 192, 480) == 288
    assert residual.refined_width(over, 0.05, 288, 192, 1920) == 288
    assert residual.refined_width(over, 0.05, 288, 192, 400) == 240  # the frame's cap
    assert residual.refined_width(over, 0.05, 288, 192, 320) is None  # 192 already at it
    assert residual.refined_width(over, 0.05, 0, 192, 480) is None  # the option off
    assert residual.refined_width(residual.ABOVE + 0.05, 0.05, 288, 192, 480) is None
    assert residual.refined_width(float("nan"), float("nan"), 288, 192, 480) is None
    assert residual.exceeds(over, 0.05) and not residual.exceeds(residual.ABOVE + 0.05, 0.05)
    assert not residual.exceeds(float("nan"), float("nan"))


def test_the_views_share_the_detail_not_the_noise():
    """shared_over_rest: two views' residuals with a shared detail of variance s and
    independent unit noise read s (0 without detail), within a few of its errors."""
    rng = np.random.default_rng(2)
    n = 200_000
    for s in (0.0, 0.05, 0.5):
        d = rng.normal(0.0, np.sqrt(s), n)
        got, error = residual.shared_over_rest(d + rng.normal(size=n), d + rng.normal(size=n))
        assert abs(got - s) < max(4 * error, 0.01)
        assert 0 < error < 0.01
    assert np.isnan(residual.shared_over_rest(np.ones(4), np.ones(4))).all()  # no rest
