"""Sparse grid invariants: exact trilinear on linear fields, prune, upsample, occupancy."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gridnerf import grid
from gridnerf.errors import GridNerfError

interpolate = jax.jit(grid.interpolate)  # one compile per grid shape
LO = np.array([-1.0, -2.0, 0.5])
HI = np.array([2.0, 1.0, 3.0])


def vertex_positions(structure) -> np.ndarray:
    res = np.asarray(structure.resolution)
    return LO + np.asarray(structure.coords) / (res - 1) * (HI - LO)


def linear_params(structure, coef: np.ndarray) -> dict:
    """Every channel c holds coef[c, :3] . x + coef[c, 3] at its vertex. coef: (C, 4)."""
    x = vertex_positions(structure)
    feats = (x @ coef[:, :3].T + coef[:, 3]).astype(np.float32)
    n_rgb = 3 * structure.n_sh
    return {"density": jnp.asarray(feats[:, 0]), "rgb": jnp.asarray(feats[:, 1:1 + n_rgb]),
            "log_gain": jnp.asarray(feats[:, 1 + n_rgb:])}


def linear_truth(points: np.ndarray, coef: np.ndarray) -> np.ndarray:
    return points @ coef[:, :3].T + coef[:, 3]


def random_points(rng, n, lo=LO, hi=HI) -> np.ndarray:
    return rng.uniform(lo, hi, (n, 3)).astype(np.float32)


def make(resolution=(7, 6, 5), sh_degree=0, **kw):
    return grid.init_grid(resolution, LO, HI, sh_degree=sh_degree, **kw)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), sh_degree=st.integers(0, 1),
       res=st.tuples(st.integers(2, 6), st.integers(2, 6), st.integers(2, 6)))
def test_trilinear_exact_on_linear_fields(seed, sh_degree, res):
    rng = np.random.default_rng(seed)
    structure, _ = make(res, sh_degree)
    coef = rng.normal(size=(structure.n_channels, 4))
    params = linear_params(structure, coef)
    pts = random_points(rng, 64)
    got = np.asarray(interpolate(structure, params, jnp.asarray(pts)))
    np.testing.assert_allclose(got, linear_truth(pts, coef), atol=2e-5 * (1 + np.abs(coef).sum()))


def test_vertices_and_outside_points():
    structure, params = make()
    params = linear_params(structure, np.random.default_rng(0).normal(size=(7, 4)))
    got = interpolate(structure, params, jnp.asarray(vertex_positions(structure)))
    expect = grid.feature_table(structure, params)[:-1]
    np.testing.assert_allclose(got, expect, atol=1e-5)
    outside = jnp.asarray([[HI[0] + 0.1, 0.0, 1.0], [0.0, LO[1] - 1e-3, 1.0]])
    empty = np.zeros((2, 7), np.float32)
    empty[:, 0] = grid.EMPTY_DENSITY_RAW
    np.testing.assert_array_equal(interpolate(structure, params, outside), empty)


def test_structure_tables_are_consistent_after_prune():
    structure, params = make((6, 5, 4))
    keep = np.random.default_rng(1).random(structure.n_rows) < 0.5
    pruned, pp = grid.prune(structure, params, keep)
    m = pruned.n_rows
    assert m == keep.sum() and pp["density"].shape == (m,) and pp["rgb"].shape == (m, 3)
    coords, index = np.asarray(pruned.coords), np.asarray(pruned.index)
    np.testing.assert_array_equal(index[tuple(coords.T)], np.arange(m))
    assert (index == m).sum() == index.size - m
    nb = np.asarray(pruned.neighbors)
    for r in range(m):
        for a in range(3):
            v = coords[r].copy()
            v[a] += 1
            expect = index[tuple(v)] if v[a] < pruned.resolution[a] else m
            assert nb[r, a] == expect
    # a dense vertex mask gives the same result as the row mask
    dense = np.zeros(structure.resolution, bool)
    dense[tuple(np.asarray(structure.coords)[keep].T)] = True
    again, pp2 = grid.prune(structure, params, dense)
    np.testing.assert_array_equal(again.index, pruned.index)
    np.testing.assert_array_equal(pp2["density"], pp["density"])
    with pytest.raises(ValueError, match="keep mask"):
        grid.prune(structure, params, np.ones(3, bool))


def test_prune_keeps_linear_field_exact_and_empties_the_rest():
    rng = np.random.default_rng(2)
    structure, _ = make((9, 8, 7))
    coef = rng.normal(size=(7, 4))
    params = linear_params(structure, coef)
    x = vertex_positions(structure)
    pruned, pp = grid.prune(structure, params, x[:, 0] < 0.6)  # drop the far +x part
    assert pruned.n_rows < structure.n_rows
    near = random_points(rng, 64, hi=np.array([0.2, HI[1], HI[2]]))  # all corners kept
    np.testing.assert_allclose(interpolate(pruned, pp, jnp.asarray(near)),
                               linear_truth(near, coef), atol=1e-4)
    far = random_points(rng, 16, lo=np.array([1.2, LO[1], LO[2]]))  # no corner kept
    feats = np.asarray(interpolate(pruned, pp, jnp.asarray(far)))
    np.testing.assert_allclose(feats[:, 0], grid.EMPTY_DENSITY_RAW, atol=1e-5)
    np.testing.assert_array_equal(feats[:, 1:], 0.0)
    # empty everywhere: M = 0 rows still interpolates to the empty row
    none, pn = grid.prune(structure, params, np.zeros(structure.n_rows, bool))
    assert none.n_rows == 0 and not np.asarray(none.occupancy).any()
    np.testing.assert_allclose(interpolate(none, pn, jnp.asarray(near))[:, 0],
                               grid.EMPTY_DENSITY_RAW, atol=1e-5)


@pytest.mark.parametrize("sh_degree", [0, 1])
def test_upsample_reproduces_linear_fields(sh_degree):
    rng = np.random.default_rng(3)
    structure, _ = make((5, 4, 4), sh_degree)
    coef = rng.normal(size=(structure.n_channels, 4))
    params = linear_params(structure, coef)
    fine, fp = grid.upsample(structure, params, (9, 11, 6))
    assert fine.resolution == (9, 11, 6) and fine.n_rows == 9 * 11 * 6
    pts = random_points(rng, 64)
    np.testing.assert_allclose(interpolate(fine, fp, jnp.asarray(pts)),
                               linear_truth(pts, coef), atol=1e-4)


def test_upsample_after_prune_keeps_only_vertices_near_kept_parents():
    rng = np.random.default_rng(4)
    structure, _ = make((7, 7, 7))
    coef = rng.normal(size=(7, 4))
    params = linear_params(structure, coef)
    x = vertex_positions(structure)
    pruned, pp = grid.prune(structure, params, x[:, 2] < 1.2)
    fine, fp = grid.upsample(pruned, pp, (13, 13, 13))
    assert fine.n_rows < 13**3 and fp["density"].shape == (fine.n_rows,)
    # every fine vertex lies in a coarse cell with a kept corner: z at most one coarse cell
    # above the last kept coarse layer
    fine_z = LO[2] + np.asarray(fine.coords)[:, 2] / 12 * (HI[2] - LO[2])
    coarse_dz = (HI[2] - LO[2]) / 6
    assert fine_z.max() <= x[x[:, 2] < 1.2, 2].max() + coarse_dz + 1e-6
    pts = random_points(rng, 64, hi=np.array([HI[0], HI[1], 0.9]))
    np.testing.assert_allclose(interpolate(fine, fp, jnp.asarray(pts)),
                               linear_truth(pts, coef), atol=1e-4)


@pytest.mark.parametrize("occ_factor", [1, 2])
def test_update_occupancy_marks_cells_around_dense_vertices(occ_factor):
    structure, params = make((9, 9, 9), init_density=-20.0, occ_factor=occ_factor)
    assert np.asarray(structure.occupancy).all()  # dense grid: structural occupancy is full
    hot = int(np.asarray(structure.index)[4, 4, 4])
    params["density"] = params["density"].at[hot].set(5.0)
    occ = np.asarray(grid.update_occupancy(structure, params, threshold=0.01).occupancy)
    cells = np.zeros((8, 8, 8), bool)
    cells[3:5, 3:5, 3:5] = True
    expect = cells.reshape(8 // occ_factor, occ_factor, 8 // occ_factor, occ_factor,
                           8 // occ_factor, occ_factor).any(axis=(1, 3, 5))
    np.testing.assert_array_equal(occ, expect)
    none = grid.update_occupancy(structure, params, threshold=0.9999)
    assert not np.asarray(none.occupancy).any()
    # the default threshold is grid.OCCUPANCY_THRESHOLD: a vertex just below it marks
    # nothing, one just above marks its cells
    step_alpha = 1.0 - np.exp(-np.logaddexp(0.0, np.array([-6.0, -4.0])) * 0.5)
    assert step_alpha[0] < grid.OCCUPANCY_THRESHOLD < step_alpha[1]
    for raw, marked in ((-6.0, False), (-4.0, True)):
        p = {**params, "density": params["density"].at[hot].set(raw)}
        occ = np.asarray(grid.update_occupancy(structure, p).occupancy)
        assert occ.any() == marked
        if marked:
            np.testing.assert_array_equal(occ, expect)


def _occupancy_reference(structure, params, threshold, step_size=0.5) -> np.ndarray:
    """The host (numpy) occupancy update that grid.update_occupancy replaced: (B, B, B) bool."""
    coords = np.asarray(structure.coords)
    sigma = np.logaddexp(0.0, np.asarray(params["density"], np.float64))
    hot = coords[1.0 - np.exp(-sigma * step_size) > threshold]
    cells_shape = np.asarray(structure.resolution) - 1
    blocks = np.zeros(np.asarray(structure.occupancy).shape, bool)
    for off in np.ndindex(2, 2, 2):
        cell = hot - np.asarray(off)
        ok = np.all((cell >= 0) & (cell < cells_shape), axis=1)
        blocks[tuple((cell[ok] // structure.occ_factor).T)] = True
    return blocks


@pytest.mark.parametrize("occ_factor", [1, 2, 3])
def test_device_occupancy_matches_the_host_reference(occ_factor):
    rng = np.random.default_rng(occ_factor)
    structure, params = make((13, 9, 7), init_density=-20.0, occ_factor=occ_factor)
    structure, params = grid.prune(structure, params, rng.random(structure.n_rows) < 0.6)
    m = structure.n_rows
    for threshold in (0.0, 0.005, 0.3):
        floor = grid._density_floor(threshold, 0.5)
        # sparse hot rows, some exactly at the float32 boundary of the alpha test, NaN, +-inf
        density = np.where(rng.random(m) < 0.05, rng.normal(0.0, 3.0, m), -20.0)
        edge = rng.choice(m, 12, replace=False)
        density[edge[:4]] = floor
        density[edge[4:8]] = np.nextafter(floor, np.float32(-np.inf))
        density[edge[8:]] = [np.nan, np.inf, -np.inf, -800.0]
        p = {**params, "density": jnp.asarray(density, jnp.float32)}
        got = np.asarray(grid.update_occupancy(structure, p, threshold).occupancy)
        expect = _occupancy_reference(structure, p, threshold)
        assert got.shape == expect.shape and got.any()
        np.testing.assert_array_equal(got, expect)
    assert np.isnan(grid._density_floor(1.0, 0.5))  # alpha never exceeds 1: nothing is hot


def test_state_round_trip():
    structure, params = make((5, 4, 3), sh_degree=1, color_scale=0.004, occ_factor=2)
    structure, params = grid.prune(structure, params, np.arange(structure.n_rows) % 3 > 0)
    structure = dataclasses.replace(structure, background=jnp.asarray(
        [[0.01, 0.02, 0.005], [1.5, 1.0, 2.5]], jnp.float32))  # a grey backdrop
    back, bp = grid.from_state(grid.to_state(structure, params))
    assert (back.resolution, back.sh_degree, back.occ_factor, back.color_scale) == (
        structure.resolution, 1, 2, 0.004)
    for a, b in zip(jax.tree_util.tree_leaves((structure, params)),
                    jax.tree_util.tree_leaves((back, bp)), strict=True):
        np.testing.assert_array_equal(a, b)
    old = {k: v for k, v in grid.to_state(structure, params).items() if k != "background"}
    np.testing.assert_array_equal(grid.from_state(old)[0].background, grid.BLACK)  # old runs
    up, _ = grid.upsample(structure, params, (9, 7, 5))
    np.testing.assert_array_equal(up.background, structure.background)  # stages keep it


def test_decode_activations_and_ranges():
    structure, params = make((3, 3, 3), sh_degree=2, color_scale=0.01)
    feats = jnp.asarray(np.random.default_rng(5).normal(0, 20, (50, structure.n_channels)),
                        jnp.float32)
    dirs = jnp.asarray(np.random.default_rng(6).normal(size=(50, 3)), jnp.float32)
    dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    sigma, rgb, gain = (np.asarray(v) for v in grid.decode(structure, feats, dirs))
    assert (sigma >= 0).all() and (rgb >= 0).all() and (gain > 0).all()
    assert np.all(np.isfinite(sigma + rgb.sum(-1) + gain.sum(-1)))
    np.testing.assert_allclose(gain, np.exp(np.clip(np.asarray(feats[:, -3:]), -30, 30)),
                               rtol=1e-5)  # log gains are clipped to +-30
    # init: grey colour equal to color_scale, unit gains
    s0, p0 = make((3, 3, 3), color_scale=0.01)
    _, rgb0, gain0 = grid.decode(s0, grid.feature_table(s0, p0)[:-1])
    np.testing.assert_allclose(rgb0, 0.01, rtol=1e-5)
    np.testing.assert_allclose(gain0, 1.0)
    sigma_empty, _, _ = grid.decode(s0, grid.feature_table(s0, p0)[-1:])
    assert 0.0 <= float(sigma_empty[0]) < 1e-12


def test_sh_bands_are_orthonormal():
    n = 4000  # Fibonacci sphere: near-uniform quadrature
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z**2)
    dirs = jnp.asarray(np.stack([r * np.cos(phi), r * np.sin(phi), z], -1), jnp.float32)
    basis = np.asarray(grid.sh_basis(dirs, 3), np.float64)[:, 1:]  # bands 1..3
    gram = basis.T @ basis * (4 * np.pi / n)
    np.testing.assert_allclose(gram, np.eye(15), atol=5e-3)
    np.testing.assert_array_equal(np.asarray(grid.sh_basis(dirs, 0)), 1.0)


def test_bad_layouts_raise_clear_errors():
    with pytest.raises(GridNerfError, match="resolution"):
        grid.init_grid((1, 4, 4), LO, HI)
    with pytest.raises(GridNerfError, match="box"):
        grid.init_grid((4, 4, 4), HI, LO)
    with pytest.raises(GridNerfError, match="sh_degree"):
        grid.init_grid((4, 4, 4), LO, HI, sh_degree=7)


def test_resample_to_a_sub_box_keeps_linear_fields_and_drops_the_outside():
    rng = np.random.default_rng(5)
    structure, _ = make((6, 6, 6))
    coef = rng.normal(size=(structure.n_channels, 4))
    params = linear_params(structure, coef)
    lo, hi = LO + 0.25 * (HI - LO), HI + 0.5  # partly outside the old box
    new, new_params = grid.resample(structure, params, (9, 8, 7), lo, hi)
    res = np.asarray(new.resolution)
    pos = lo + np.asarray(new.coords) / (res - 1) * (hi - lo)
    assert np.all(pos <= HI + 1e-5) and new.n_rows < 9 * 8 * 7  # outside vertices dropped
    inner = HI - 1.01 * (hi - lo) / (res - 1)  # cells whose corners all lie in the old box
    pts = rng.uniform(lo, inner, (64, 3)).astype(np.float32)
    np.testing.assert_allclose(interpolate(new, new_params, jnp.asarray(pts)),
                               linear_truth(pts, coef), atol=1e-4)


def test_content_box_follows_the_mass_not_a_light_outlier():
    structure, _ = make((11, 11, 11))
    coords = np.asarray(structure.coords)
    mass = np.zeros(structure.n_rows)
    blob = np.all((coords >= 3) & (coords <= 5), axis=1)
    mass[blob] = 1.0
    mass[np.all(coords == 10, axis=1)] = 1e-4  # a faint floater in the far corner
    lo, hi = grid.content_box(structure, mass, quantile=0.005, margin=1.0)
    voxel = (HI - LO) / 10
    np.testing.assert_allclose(lo, LO + 2 * voxel, atol=1e-6)
    np.testing.assert_allclose(hi, LO + 6 * voxel, atol=1e-6)
    full_lo, full_hi = grid.content_box(structure, np.zeros(structure.n_rows))
    np.testing.assert_allclose(full_lo, LO) and np.testing.assert_allclose(full_hi, HI)
