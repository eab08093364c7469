"""Noise-model fit (eq. 7): recovery of known parameters, hard cases, a simulated scene."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gridnerf import noisefit
from gridnerf.sim import sensor
from gridnerf.sim.truth import clean_mean, noise_truth

SCALE = sensor.WHITE_LEVEL - sensor.BLACK_LEVEL
BIAS = ((3.0, -1.5), (0.5, 2.2))


def _frames(h, w, n, k_gain=5.0, bias=BIAS, max_e=30.0, seed=0):
    """Simulated ELD frames of a blocky scene: (clean mean (h, w), frames (n, h, w)),
    normalised raw, and the true figures in DN."""
    rng = np.random.default_rng(seed)
    e = np.kron(rng.uniform(0.0, max_e, (h // 8, w // 8)), np.ones((8, 8)))
    params = sensor.SensorParams(k_gain=k_gain, bias=bias)
    raw = np.stack([sensor.expose(e, params, rng) for _ in range(n)])
    y = (raw.astype(np.float64) - sensor.BLACK_LEVEL) / SCALE
    truth = noise_truth({
        "K_dn_per_electron": k_gain, "white_level": sensor.WHITE_LEVEL,
        "black_level": sensor.BLACK_LEVEL,
        "noise": {"read_tukey_sigma_dn": params.read_sigma, "read_tukey_lambda":
                  params.tl_lambda, "row_sigma_dn": params.row_sigma,
                  "black_bias_dn_per_cfa_position": [list(r) for r in bias]}})
    return e * k_gain / SCALE, y, truth


def test_tukey_lambda_variance_matches_samples():
    x = sensor.tukey_lambda(np.random.default_rng(0), (400_000,), -0.075, 3.5)
    assert noisefit.tukey_lambda_variance(3.5, -0.075) == pytest.approx(x.var(), rel=0.01)
    assert noisefit.tukey_lambda_variance(1.0, 0.0) == pytest.approx(math.pi**2 / 3)


def test_recovers_known_parameters_from_a_clean_mean():
    mean, y, truth = _frames(128, 160, 8)
    fit = noisefit.fit_noise(mean, y)
    got = fit.in_dn(SCALE)
    assert fit.converged and fit.k_identified
    assert got["K_dn_per_electron"] == pytest.approx(truth["K_dn_per_electron"], rel=0.03)
    assert got["read_var_dn2"] == pytest.approx(truth["read_var_dn2"], rel=0.08)
    np.testing.assert_allclose(got["black_offset_dn"], truth["black_offset_dn"], atol=0.3)
    assert fit.counts.sum() == y.size


def test_offsets_from_a_mean_that_absorbed_them():
    """A field trained on the frames renders mu + b per colour (the two greens averaged):
    the residual keeps only the green difference; the offsets come from the variance and
    the third moment (Poisson skew), less precisely."""
    mean, y, truth = _frames(256, 320, 6, seed=1)
    b = np.asarray(BIAS) / SCALE
    g = 0.5 * (b[0, 1] + b[1, 0])
    absorbed = mean + np.tile([[b[0, 0], g], [g, b[1, 1]]], (128, 160))
    fit = noisefit.fit_noise(absorbed, y, mean_includes_offset=True)
    got = fit.in_dn(SCALE)
    assert fit.converged
    np.testing.assert_allclose(got["mean_offset_dn"], (b - [[b[0, 0], g], [g, b[1, 1]]])
                               * SCALE, atol=0.3)
    assert got["K_dn_per_electron"] == pytest.approx(truth["K_dn_per_electron"], rel=0.05)
    # offsets relative to their mean: from the per-position variance intercepts (precise);
    # their common part: from the third moment (~1 DN at 0.5 M photosites, ~0.2 at 2 M)
    fb, tb = np.asarray(got["black_offset_dn"]), np.asarray(truth["black_offset_dn"])
    np.testing.assert_allclose(fb - fb.mean(), tb - tb.mean(), atol=0.4)
    assert abs(fb.mean() - tb.mean()) < 1.5


def test_all_dark_frames_give_finite_read_noise_and_offsets():
    mean, y, truth = _frames(96, 128, 6, max_e=0.0, seed=2)
    fit = noisefit.fit_noise(mean, y)
    got = fit.in_dn(SCALE)
    assert not fit.k_identified  # no signal range: K is not measurable
    assert all(np.isfinite(v).all() for v in (fit.k, fit.read_var, fit.black_offset))
    assert got["read_var_dn2"] == pytest.approx(truth["read_var_dn2"], rel=0.08)
    np.testing.assert_allclose(got["black_offset_dn"], truth["black_offset_dn"], atol=0.3)
    # constant zero frames and a zero mean: nothing to measure, still finite
    zero = noisefit.fit_noise(np.zeros((8, 8)), np.zeros((2, 8, 8)))
    assert np.isfinite([zero.k, zero.read_var]).all() and np.all(zero.black_offset == 0.0)


def test_a_missing_cfa_position_keeps_the_others():
    mean, y, truth = _frames(128, 160, 6, seed=3)
    mask = np.ones(y.shape, bool)
    mask[:, 1::2, 1::2] = False  # position (1, 1) never measured
    y[:, 1::2, 1::2] = np.nan  # and unreadable, too
    fit = noisefit.fit_noise(mean, y, mask)
    got = fit.in_dn(SCALE)
    assert fit.counts[1, 1] == 0 and fit.black_offset[1, 1] == 0.0
    assert np.isfinite(fit.black_offset).all() and np.isfinite([fit.k, fit.read_var]).all()
    np.testing.assert_allclose(np.asarray(got["black_offset_dn"]).ravel()[:3],
                               np.asarray(truth["black_offset_dn"]).ravel()[:3], atol=0.35)
    assert got["K_dn_per_electron"] == pytest.approx(truth["K_dn_per_electron"], rel=0.05)


def test_fit_on_a_simulated_scene_folder(small_scene):
    fit, scale = noisefit.fit_scene(small_scene, clean_mean(small_scene))
    truth = noise_truth(small_scene)
    got = fit.in_dn(scale)
    assert scale == truth["scale"] and fit.converged
    assert got["K_dn_per_electron"] == pytest.approx(truth["K_dn_per_electron"], rel=0.1)
    assert got["read_var_dn2"] == pytest.approx(truth["read_var_dn2"], rel=0.15)
    np.testing.assert_allclose(got["black_offset_dn"], truth["black_offset_dn"], atol=0.5)


def test_neighbour_sigma_on_binned_and_mosaic_targets():
    """neighbour_sigma: Gaussian noise of known sigma on a flat level, within 5 % for
    binned targets (every channel at every pixel) and for a mosaic's one-hot targets
    (same-colour pixels two columns apart); no valid pair gives nan."""
    rng = np.random.default_rng(1)
    sigma = 5e-4
    y = 0.002 + sigma * rng.standard_normal((400, 8, 8, 3))
    assert abs(noisefit.neighbour_sigma(y) / sigma - 1.0) < 0.05
    cfa = np.array([[0, 1], [1, 2]])  # RGGB
    v, u = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    onehot = np.eye(3)[cfa[v % 2, u % 2]]  # (8, 8, 3)
    mask = np.broadcast_to(onehot, y.shape)
    assert abs(noisefit.neighbour_sigma(y * mask, mask) / sigma - 1.0) < 0.05
    assert math.isnan(noisefit.neighbour_sigma(y, np.zeros_like(y)))
