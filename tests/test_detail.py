"""The detail reading: a grid's missing detail told apart from the frames' noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from gridnerf import detail

RGGB = np.array([[0, 1], [1, 2]])


def _texture(rng, shape, scale: float, blur: float) -> np.ndarray:
    """(T, H, W) scene-fixed structure: white noise blurred by `blur` photosites."""
    t = ndimage.gaussian_filter(rng.normal(size=shape), sigma=(0, blur, blur))
    return scale * t / t.std()


def test_green_positions_of_every_bayer_layout():
    for cfa, want in (([[0, 1], [1, 2]], ((0, 1), (1, 0))), ([[2, 1], [1, 0]], ((0, 1), (1, 0))),
                      ([[1, 0], [2, 1]], ((0, 0), (1, 1))), ([[1, 2], [0, 1]], ((0, 0), (1, 1)))):
        assert detail.green_positions(np.array(cfa)) == want
    with pytest.raises(ValueError):
        detail.green_positions(np.array([[0, 1], [2, 3]]))


def test_the_white_gain_is_the_band_share_of_white_noise():
    rng = np.random.default_rng(0)
    h = detail.highpass(rng.normal(size=(4, 256, 256)))
    assert detail.white_gain() == pytest.approx(float((h**2).mean()), rel=0.02)
    assert 0.5 < detail.white_gain() < 1.0


def _heteroscedastic(rng, level):
    """Shot plus read noise of a photosite at `level` (normalised raw)."""
    return np.sqrt(2e-4 * level + 1e-5) * rng.normal(size=level.shape)


def test_noise_alone_reads_no_detail_at_any_level():
    rng = np.random.default_rng(0)
    shape = (40, detail.TILE, detail.TILE)
    level = 0.05 + 0.04 * np.abs(_texture(rng, shape, 1.0, 4.0))  # the render's shading
    resid = _heteroscedastic(rng, level)
    d, n, cells = detail.band_powers(resid, level, np.ones(shape, bool), RGGB)
    want = detail.white_gain() * float(np.mean(2e-4 * level + 1e-5))
    assert cells > 20000
    assert n == pytest.approx(want, rel=0.05)
    assert abs(d) < 0.03 * n


def test_missing_detail_is_read_under_the_noise_and_never_overstated():
    """Structure the render lacks, at a few % of one frame's noise, on a tenth of the
    frames' area, is read at every scale, the finest too (which the two greens half a plane
    pixel apart do not share); where it covers the whole frame the median takes part of it
    for noise, so the reading falls short of it but does not exceed it: a conservative
    reading."""
    rng = np.random.default_rng(1)
    shape = (40, detail.TILE, detail.TILE)
    level = np.full(shape, 0.05)
    ones = np.ones(shape, bool)
    noise = _heteroscedastic(rng, level)
    for every, blur in ((10, 0.7), (10, 1.5), (1, 0.7), (1, 1.5), (1, 2.5)):
        tex = _texture(rng, shape, 0.0026, blur) * (np.arange(shape[0]) % every == 0)[
            :, None, None]
        h = [detail.highpass(tex[:, a::2, b::2]) for a, b in ((0, 1), (1, 0))]
        d_true = 0.5 * float((h[0] ** 2).mean() + (h[1] ** 2).mean())
        d, n, _ = detail.band_powers(tex + noise, level, ones, RGGB)
        assert d < d_true + 0.02 * n, (every, blur)
        if every > 1:
            assert abs(d - d_true) < 0.02 * n, (every, blur)
        else:
            assert d > 0.25 * d_true, (every, blur)
    # the reading scales with the residual squared: its ratio does not depend on the units
    d3, n3, _ = detail.band_powers(3 * (tex + noise), 9 * level, ones, RGGB)
    assert d3 / n3 == pytest.approx(d / n, rel=1e-6)


def test_saturated_photosites_are_left_out():
    rng = np.random.default_rng(2)
    shape = (20, detail.TILE, detail.TILE)
    level = np.full(shape, 0.05)
    resid = _heteroscedastic(rng, level)
    valid = np.ones(shape, bool)
    ref = detail.band_powers(resid, level, valid, RGGB)
    spoiled = resid.copy()
    spoiled[:, 20:30, 20:30] = 5.0  # a clipped highlight: its residual means nothing
    valid[:, 20:30, 20:30] = False
    d, n, cells = detail.band_powers(spoiled, level, valid, RGGB)
    assert cells < ref[2]
    assert abs(d) < 0.05 * n and n == pytest.approx(ref[1], rel=0.1)


def test_tiles_are_whole_cells_inside_the_frame_and_thinned_to_the_budget():
    fr, v, u = detail.tiles((270, 480), 6)
    assert v.shape[1:] == (detail.TILE, detail.TILE)
    assert v.min() >= 0 and v.max() < 270 and u.min() >= 0 and u.max() < 480
    assert (v[:, 0, 0] % 2 == 0).all() and (u[:, 0, 0] % 2 == 0).all()
    assert set(np.unique(fr)) == set(range(6))
    fr, v, u = detail.tiles((1080, 1920), 6, max_rays=1 << 19)
    assert v.size <= 1 << 19 and len(np.unique(fr)) == 6
    with pytest.raises(ValueError):
        detail.tiles((40, 480), 2)


def _tiny(detail_ratio: float):
    from gridnerf import config as cfgmod

    return cfgmod.override(cfgmod.preset("tiny"), [
        f"grid.refine_detail={detail_ratio}", "grid.refine_resolution=[48,48,28]"])


def test_a_run_refines_only_where_its_frames_show_the_detail(small_scene, tmp_path, capsys):
    """Under the threshold the run trains exactly as one that never reads (the reading
    draws nothing from the run's key); over it the last stage trains at
    grid.refine_resolution, kept in the plan, checkpointed finite, resumed and rendered
    at it; a rerun of the finished run trains nothing."""
    from gridnerf import checkpoint, eval_run
    from gridnerf import plan as planmod
    from gridnerf.train import train

    never = train(small_scene, tmp_path / "never", _tiny(0.0))
    below = train(small_scene, tmp_path / "below", _tiny(1e9))
    assert "the last stage trains at [40, 40, 24]" in capsys.readouterr().out
    plan = planmod.load(tmp_path / "below")
    assert plan.refined is False and plan.detail_ratio is not None
    assert planmod.load(tmp_path / "never").refined is None
    assert below["resolution"] == never["resolution"] == [40, 40, 24]
    assert below["refined"] is False
    a = checkpoint.load(tmp_path / "never" / "checkpoint.npz")[0]
    b = checkpoint.load(tmp_path / "below" / "checkpoint.npz")[0]
    assert a.keys() == b.keys()
    for name in a:
        for x, y in zip(a[name], b[name], strict=True):
            np.testing.assert_array_equal(x, y)

    above = train(small_scene, tmp_path / "above", _tiny(1e-9))
    assert "trains at [48, 48, 28] in place of [40, 40, 24]" in capsys.readouterr().out
    plan = planmod.load(tmp_path / "above")
    assert plan.refined is True and plan.detail_ratio == below_ratio(tmp_path)
    assert above["refined"] is True and above["resolution"] == [48, 48, 28]
    groups = checkpoint.load(tmp_path / "above" / "checkpoint.npz")[0]
    assert all(np.isfinite(x).all() for arrays in groups.values() for x in arrays
               if x.dtype.kind == "f")
    assert train(small_scene, tmp_path / "above", _tiny(1e-9))["refined"] is True
    assert "already trained" in capsys.readouterr().out
    assert eval_run.load_run(tmp_path / "above")[3].resolution == (48, 48, 28)


def below_ratio(tmp_path) -> float:
    """The reading of the run under the threshold: the same first stage, the same frames."""
    from gridnerf import plan as planmod

    return planmod.load(tmp_path / "below").detail_ratio
