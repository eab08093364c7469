"""The report's studies (experiments/ablate.py, sweep.py, speed.py, colour_ceiling.py,
consistency.py):
their tables, means and plots from given results, and how the report picks them up. No
training here."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gridnerf import color, eval_run
from gridnerf import config as cfgmod
from gridnerf.sim import DEV, HELDOUT, MIXED, SCENES

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "experiments"))

import ablate  # noqa: E402
import black_level  # noqa: E402
import carry_runs  # noqa: E402
import colour_ceiling  # noqa: E402
import common  # noqa: E402
import consistency  # noqa: E402
import dark_gates  # noqa: E402
import illuminant_maps  # noqa: E402
import matrix_offsets  # noqa: E402
import photons  # noqa: E402
import retinex_edges  # noqa: E402
import speed  # noqa: E402
import sweep  # noqa: E402


def _m(psnr: float) -> dict:
    return {"psnr": psnr, "ssim": 0.5, "delta_e": 10.0, "psnr_aligned": psnr + 1.0}


def test_ablation_means_keep_nine_and_held_out_apart():
    record = {
        "bucket": {"no_cr": {"matrix": _m(12.0), "global_gain": _m(18.0)},
                   "full_tv": {"matrix": _m(20.0)}},
        "deer": {"no_cr": {"matrix": _m(14.0)}, "full_tv": {"matrix": _m(22.0)}},
        "held_arc_brick": {"full_tv": {"matrix": _m(15.0)}},
    }
    nine = ablate.means(record, SCENES)
    held = ablate.means(record, HELDOUT)
    assert nine["full_tv"]["matrix"]["psnr"] == 21.0 and nine["full_tv"]["matrix"]["n"] == 2
    assert nine["no_cr"]["global_gain"]["n"] == 1  # only where the output exists
    assert held["full_tv"]["matrix"]["psnr"] == 15.0 and "no_cr" not in held
    text = ablate.markdown(record, {"nine": nine, "held out": held})
    assert "**mean, held out** (n=1)" in text and "global_gain" in text
    assert "**mean, nine** (n=2)" in text


def test_sweep_table_and_plot(tmp_path):
    record = {"default": {"bucket": {"0.3": _m(16.0) | {"delta_e": 14.0},
                                     "1": _m(19.0) | {"delta_e": 11.0}}}}
    text = sweep.markdown(record, [0.1, 0.3, 1.0])
    assert "| default | bucket | - | 16.00 / 14.00 | 19.00 / 11.00 |" in text
    sweep.plot(record, [0.1, 0.3, 1.0], tmp_path / "sweep.png")
    assert (tmp_path / "sweep.png").stat().st_size > 1000
    assert sweep.variant("default", 1.0) == "default"
    # the level-eps method's gamma-1 run is the eps study's (same folder, same config)
    preset, _, sets = sweep.METHODS["eps_level0.5"]
    study = {folder: (p, s) for _, _, folder, p, s in ablate.EPS_VARIANTS}
    assert study[sweep.variant("eps_level0.5", 1.0)] == (preset, sets)
    assert sweep.variant("llnerf", 0.3) == "llnerf_gamma0.3"


def test_photon_sweep_table_differences_and_plot(tmp_path):
    def cell(electrons, ours, noise):
        outs = {"ours": ours, "global_gw": 20.0, "denoised_2d": 19.0, "binned": 15.0}
        run = {k: {"psnr": v, "ssim": 0.5, "delta_e": 10.0} for k, v in outs.items()}
        eps = noise and min(1e-3, 2 * noise)
        return {"electrons": electrons, "default": run | {"data_noise": noise, "data_eps": eps}}

    record = {"bucket": {"0.1": cell(1.0, 18.5, 4e-4), "1": cell(10.0, 21.5, 8e-4)},
              "held_deep_hall": {"1": cell(7.0, 19.0, None)}}
    md = photons.markdown(record, [0.1, 1.0], ["default"], "cmd")
    assert "| bucket (tuned on) | mean green electrons | 1.0 | 10.0 |" in md
    assert "| held_deep_hall (held out) | mean green electrons | - | 7.0 |" in md
    assert "|  | default: ours | 18.50 / 10.00 | 21.50 / 10.00 |" in md
    # ours - 2D / ours - one grey-world gain; the eps in sigmas where the noise is known
    assert "| bucket | default | -0.50 / -1.50; eps 0.0008 = 2.0 sigma | " \
        "+2.50 / +1.50; eps 0.001 = 1.2 sigma |" in md
    assert "| held_deep_hall | default | - | +0.00 / -1.00 |" in md
    photons.plot(record, [0.1, 1.0], ["default"], tmp_path / "photons.png")
    assert (tmp_path / "photons.png").stat().st_size > 1000


def test_dark_gates_table_and_the_own_light_summary():
    def row(light, share, ratios, d):
        return {"light": light, "electrons": 10.0 * light, "weakest_dn": 4.0 / share,
                "offset_share": share, "lens_cap": share > 0.5,
                "noise_ratio": dict(zip(("file", "dark"), ratios, strict=True)),
                "downscale": d}

    record = {"bucket": row(1.0, 0.15, (0.33, 0.35), 1),
              "scoreboard": row(1.0, 0.35, (0.45, 0.52), 1),
              "bucket_light0.1": row(0.1, 1.64, (1.41, 2.04), 4)}
    md = dark_gates.markdown(record, "cmd")
    assert "At their own light (2 scenes): offset share at most 0.35 (gate 0.5), noise " \
        "ratio at most 0.52 with either black level (gate 0.6)." in md
    assert "| bucket_light0.1 | 0.1 | 1.0 | 2.4 | 1.64 | yes | 1.41 | 2.04 | 4 |" in md


def test_consistency_table_marks_missing_runs_and_partial_means():
    def rows(ours, llnerf=None):
        r = {"gridnerf": {"mae": ours / 255, "coverage": 0.9},
             "reference": {"mae": 3.0 / 255, "coverage": 0.9}}
        return r | ({"llnerf": {"mae": llnerf / 255, "coverage": 0.9}} if llnerf else {})

    record = {name: {"rows": r, "command": "cmd"} for name, r in (
        ("bucket", rows(2.0, llnerf=9.0)), ("deer", rows(4.0)), ("held_arc_brick", rows(5.0)))}
    text = consistency.markdown(record)
    line = {ln.split(" | ")[0]: ln for ln in text.splitlines() if ln.startswith("| ")}
    cols = text.splitlines()[[i for i, ln in enumerate(text.splitlines())
                              if ln.startswith("| scene")][0]].split(" | ")
    deer = line["| deer"].split(" | ")
    assert deer[cols.index("llnerf (x255)")] == "n/a"
    nine = line["| **mean, nine** (2 of 9)"].split(" | ")
    assert nine[cols.index("gridnerf (x255)")] == "3.00"
    assert nine[cols.index("llnerf (x255)")] == "9.00 (n=1)"
    held = line["| **mean, held out** (1 of 4)"].split(" | ")
    assert held[cols.index("llnerf (x255)")] == "n/a"
    table = consistency.means_table(record)  # the README's: every row, its scene count
    assert "| ours | 3.00 (n=2) | 5.00 (n=1) |" in table
    assert "| LLNeRF-style | 9.00 (n=1) | - |" in table
    assert len(table.splitlines()) == 2 + len(consistency.ROWS)


def test_speed_time_to_quality():
    points = [{"wall_s": 10.0, "psnr": 15.0}, {"wall_s": 20.0, "psnr": 18.6},
              {"wall_s": 30.0, "psnr": 19.0}]
    assert speed.time_to(points, 18.5) == 20.0
    assert speed.time_to(points, 19.5) is None
    curve = {"points": points, "train_wall_s": 31.0, "final_resolution": [96, 54, 48],
             "occupied_fraction": 0.25}
    text = speed.markdown({"bucket": {"fast": curve,
                                      "fine": {**curve, "points": [*points, {
                                          "wall_s": 60.0, "psnr": 21.0}]}}})
    # fast: within 0.5 dB of its own 19.0 at 20 s; never within 1 dB of the best (21.0)
    assert "| bucket | fast | 96x54x48 | 19.00 | 31 | 20 | n/a | 25.0 |" in text
    assert "| bucket | fine | 96x54x48 | 21.00 | 31 | 60 | 60 | 25.0 |" in text


@pytest.mark.parametrize("with_png", [False, True])
def test_report_appends_the_studies_it_finds(tmp_path, with_png):
    run = tmp_path / "runs" / "bucket" / "default" / "eval"
    run.mkdir(parents=True)
    m = {"psnr": 20.0, "ssim": 0.5, "delta_e": 10.0, "psnr_aligned": 21.0,
         "ssim_aligned": 0.6, "delta_e_aligned": 9.0}
    (run / "metrics.json").write_text(json.dumps({"summary": {"gridnerf": m}}))
    out = tmp_path / "out"
    out.mkdir()
    (out / "sweep.md").write_text("# Darkness sweep\n\nthe sweep table\n\n## Extreme\n\nx\n")
    (out / "noise.md").write_text("Sensor noise fitted from the frames\n\n| a table |\n")
    if with_png:
        (out / "sweep.png").write_bytes(b"not checked")
    proc = subprocess.run([sys.executable, str(REPO / "experiments" / "report.py"),
                           "--runs", "runs", "--out", "out/report"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    text = (out / "report.md").read_text()
    assert "## Darkness sweep\n\nthe sweep table" in text
    assert "\n### Extreme\n" in text  # the study's own headings one level down
    assert ("![Darkness sweep](sweep.png)" in text) == with_png
    assert "## Ablation\n\nNot built yet: `python experiments/ablation.py`" not in text
    assert "Not built yet: `python experiments/ablate.py`" in text
    # a study without a title line (the colour tables) still sits under its heading
    assert "## Sensor fit (fitted against true)\n\nSensor noise fitted" in text
    assert "Not built yet: `python experiments/colour_ceiling.py`" in text


def test_ablation_scene_groups_and_colour_study():
    assert common.scene_names("nine,mixed") == [*SCENES, *MIXED]
    assert common.scene_names("all") == [*SCENES, *HELDOUT]
    assert common.scene_names("box,deer,nine") == ["box", "deer", *[s for s in SCENES
                                                                   if s not in ("box", "deer")]]
    assert common.scene_names("all", ("nine", "dev")) == [*SCENES, *DEV]
    record = {"bucket": {"no_cr": {"matrix": _m(12.0), "global_gain": _m(20.0)},
                         "full_tv": {"matrix": _m(22.0)}},
              "deer": {"full_tv": {"matrix": _m(20.0)}}}
    table = ablate.means_table(ablate.means(record, SCENES), {})  # the README's
    assert "| the same grid, one grey-world gain (RawNeRF + ISP) | 20.00 / 0.500 / 10.00 " \
        "(n=1) | - |" in table
    assert "| full, smoothness as grid TV (default) | 21.00 / 0.500 / 10.00 (n=2) | - |" in table
    record = {"bucket": {"grey_world": {"matrix": _m(18.0)},
                         "map_regions": {"matrix": _m(19.0)}}}
    nine = ablate.means(record, SCENES, ablate.COLOUR_VARIANTS)
    assert set(nine) == {"grey_world", "map_regions"}
    assert "illuminant map anchored by region (default)" in ablate.markdown(
        record, {"nine": nine}, ablate.COLOUR_VARIANTS)
    mixed = {"mixed_lamp_window": {"map_regions": {"matrix": _m(25.0)}}}
    text = ablate.markdown(mixed, ablate.group_means(mixed, ablate.COLOUR_VARIANTS),
                           ablate.COLOUR_VARIANTS)
    assert "| **mean, mixed light** (n=1) | field, illuminant map anchored by region " \
        "(default) | matrix | 25.00 |" in text
    assert "mean, nine" not in text


def test_eps_study_levels_table_reads_the_level_runs(tmp_path):
    """The eps study's level column comes from the level run's summary.json (data_level),
    with the absolute eps's ratio to it; a scene whose run is only cached shows "-"."""
    run = tmp_path / "bucket" / "eps_level0.5"
    run.mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps({"data_level": 0.0025}))
    table = ablate.levels_table(["bucket", "deer"], tmp_path)
    assert "| bucket | 0.00250 | 0.40 |" in table
    assert "| deer | - | - |" in table
    level = dict(ablate.EPS_VARIANTS[1][4][i].split("=") for i in range(2))
    assert level == {"loss.data_eps_mode": "level", "loss.data_eps": "0.5"}


def test_every_study_variant_is_a_valid_config_and_shared_folders_agree():
    """A run folder shared by studies (e.g. `default`) must mean one config everywhere,
    else run_variant refuses it in the second study; every override must validate."""
    seen: dict = {}
    for variants in ablate.STUDIES.values():
        for _key, _label, folder, preset, sets in variants:
            cfg = cfgmod.override(cfgmod.preset(preset), sets)
            assert seen.setdefault(folder, cfg) == cfg, folder
    for folder, sets in photons.VARIANTS.items():  # the photon sweep's, on the default
        cfg = cfgmod.override(cfgmod.preset("default"), sets)
        assert seen.setdefault(folder, cfg) == cfg, folder
    assert seen["ws0.01"].loss.w_smooth == 0.01
    assert seen["default"] == cfgmod.preset("default")
    gates_off = seen["no_gates"]
    assert (gates_off.data.lens_cap_share, gates_off.loss.ca_noise_ratio) == (0.0, 0.0)


def test_colour_ceiling_rows_share_luminance_and_undo_the_true_white():
    """experiments/colour_ceiling.view_rows: every row at ours' mean luminance; a grey scene
    lit by a different white in each half comes out neutral with the per-pixel truth, and
    one gain (the truth's mean) leaves a cast in both halves."""
    warm, cool = np.array([0.6, 1.0, 0.35]), np.array([0.37, 1.0, 0.72])
    truth = np.empty((8, 10, 3))
    truth[:, :5], truth[:, 5:] = warm, cool
    out = {"rgb_low": 0.05 * truth}  # a grey wall (albedo 0.05) under the two lights
    shown = {"gridnerf": eval_run.Output("rgb_low", np.ones(3), np.eye(3), alpha=3.0),
             "global_grey_world": eval_run.Output("rgb_low", np.ones(3), np.eye(3))}
    rows = colour_ceiling.view_rows(out, shown, np.eye(3), truth, warm)
    target = color.luminance(rows["ours"]).mean()
    for name, rgb_linear in rows.items():
        assert color.luminance(rgb_linear).mean() == pytest.approx(target, rel=1e-5), name
    local = rows["true_local"]
    assert np.allclose(local, local[..., 1:2], rtol=1e-5)  # neutral everywhere
    one = rows["true_global"]
    assert abs(one[0, 0, 0] - one[0, 0, 2]) > 0.1 * one[0, 0, 1]  # a cast remains
    field = rows["field_global"]  # the field's mean white, here the warm light: that half
    assert np.allclose(field[:, :5], field[:, :5, 1:2], rtol=1e-5)  # neutral, the other not
    assert abs(field[0, 9, 0] - field[0, 9, 2]) > 0.1 * field[0, 9, 1]
    uniform = np.broadcast_to(warm, truth.shape)
    same = colour_ceiling.view_rows({"rgb_low": 0.05 * uniform}, shown, np.eye(3), uniform,
                                    warm)
    assert np.allclose(same["true_local"], same["true_global"], rtol=1e-5)


def test_colour_ceiling_splits_the_white_into_level_and_shape():
    """view_rows' split rows: a field with the true white's shape but a cast (every pixel's
    white times one colour) shows neutral once its level is the truth's
    (field_true_level), and the true shape at the field's level is the field's own white
    (true_shape equals the field shown per pixel)."""
    from gridnerf import illuminant

    warm, cool = np.array([0.6, 1.0, 0.35]), np.array([0.37, 1.0, 0.72])
    truth = np.empty((8, 10, 3))
    truth[:, :5], truth[:, 5:] = warm, cool
    cast = np.array([1.3, 1.0, 0.8])
    acc = np.full((8, 10), 0.9)
    gain = acc[..., None] * np.asarray(illuminant.gains_from_illuminant(truth * cast))
    out = {"rgb_low": 0.05 * truth, "acc": acc, "gain": gain}
    shown = {"gridnerf": eval_run.Output("rgb_low", np.ones(3), np.eye(3), alpha=3.0),
             "global_grey_world": eval_run.Output("rgb_low", np.ones(3), np.eye(3))}
    rows = colour_ceiling.view_rows(out, shown, np.eye(3), truth, warm)
    assert np.allclose(rows["field_true_level"], rows["true_local"], rtol=1e-5)
    shown_field = out["rgb_low"] * np.asarray(illuminant.gains_from_illuminant(truth * cast))
    ratio = rows["true_shape"] / shown_field
    assert np.allclose(ratio, ratio[0, 0, 0], rtol=1e-5)  # the field's colours, one scale
    assert not np.allclose(rows["true_shape"], rows["true_local"], rtol=1e-2)
    assert "true_shape" not in colour_ceiling.view_rows({"rgb_low": out["rgb_low"]}, shown,
                                                        np.eye(3), truth, warm)


def test_white_errors_score_the_field_and_single_whites_against_the_truth():
    """colour_ceiling.white_errors: a gain field that undoes the per-pixel truth scores 0
    deg, one white scores its angle from each pixel's truth; transparent pixels (opacity
    <= 0.5) do not count."""
    from gridnerf import illuminant

    warm, cool = np.array([0.6, 1.0, 0.35]), np.array([0.37, 1.0, 0.72])
    truth = np.empty((6, 8, 3))
    truth[:, :4], truth[:, 4:] = warm, cool
    acc = np.full((6, 8), 0.9)
    acc[0] = 0.1  # transparent: its (wrong) gain must not count
    gain = acc[..., None] * np.asarray(illuminant.gains_from_illuminant(truth))
    gain[0] = 5.0
    out = {"acc": acc, "gain": gain, "rgb_low": 0.05 * truth}
    errs = colour_ceiling.white_errors(out, truth, {"warm": warm})
    assert errs["field"] == pytest.approx(0.0, abs=1e-6)
    w = truth[1:, :, 1]  # the green signal of the opaque rows
    angle = float(illuminant.angular_error_deg(warm, cool))
    assert errs["warm"] == pytest.approx(angle * w[:, 4:].sum() / w.sum(), rel=1e-6)


def test_true_level_keeps_the_maps_shape_and_takes_the_truths_level():
    """illuminant_maps.with_true_level: a map that is the truth times one per-channel
    factor (right shape, wrong level) becomes the truth; a flat map stays flat."""
    warm, cool = np.array([0.6, 1.0, 0.35]), np.array([0.37, 1.0, 0.72])
    truth = np.empty((6, 8, 3))
    truth[:, :4], truth[:, 4:] = warm, cool
    rgb_cam = 0.05 * truth
    off = truth * np.array([1.3, 1.0, 0.8])
    np.testing.assert_allclose(illuminant_maps.with_true_level(off, truth, rgb_cam)
                               / truth, 1.0, rtol=1e-6)
    flat = illuminant_maps.with_true_level(np.broadcast_to(warm, truth.shape), truth, rgb_cam)
    np.testing.assert_allclose(flat / flat[0, 0], 1.0, rtol=1e-9)


def test_shape_split_of_a_frame_under_one_and_two_lights():
    """illuminant_maps.shape_split: under one light there is no illumination change to
    lose (errors 0, nothing on dropped edges); under a smooth blend of two lights over
    flat paint nothing is dropped and the true steps rebuild the truth within a degree."""
    warm, cool = np.array([0.6, 1.0, 0.35]), np.array([0.37, 1.0, 0.72])
    h, w = 64, 256  # 16 blocks: steps of ~0.055 in log chromaticity, under tau
    one = np.broadcast_to(warm, (h, w, 3))
    split = illuminant_maps.shape_split(0.2 * one, None, one, 16, 0.1)
    assert split["true_steps_kept_edges"] == pytest.approx(0.0, abs=1e-6)
    assert split["dropped_share"] == 0.0 and split["edges_dropped"] == 0.0
    t = np.linspace(0.0, 1.0, w)[None, :, None]
    two = np.broadcast_to((1 - t) * warm + t * cool, (h, w, 3))
    split = illuminant_maps.shape_split(0.2 * two, None, two, 16, 0.1)
    assert split["edges_dropped"] == 0.0 and split["dropped_share"] == 0.0
    assert split["true_steps_kept_edges"] < 1.0
    assert split["true_steps_kept_edges"] == pytest.approx(split["true_steps_all_edges"])


def test_edge_rules_keep_a_lights_shadow_and_drop_paint():
    """retinex_edges.edge_rules on three blocks of one grey paint in a row: the middle one
    lit by a warm and a cool light, the left one in the warm light's shadow, the right one
    painted another colour. Every rule drops the paint edge; the default drops the shadow
    edge too (a step of 0.23), the chord and shadow rules keep it. (Mixtures curve in log
    chromaticity: with lights twice as far apart the shadow's step leaves the chord by
    more than the rules allow.)"""
    warm, cool = np.array([0.8, 1.0, 0.55]), np.array([0.6, 1.0, 0.8])  # ~0.47 apart
    lit = 0.3 * warm + 0.3 * cool
    means = np.stack([0.3 * cool, lit, lit * np.array([0.9, 0.5, 0.3])])[None]  # (1, 3, 3)
    chroma = np.stack([np.log(means[..., 0] / means[..., 1]),
                       np.log(means[..., 2] / means[..., 1])], -1)
    c = np.log(warm[[0, 2]] / warm[1]) - np.log(cool[[0, 2]] / cool[1])
    along = c / np.linalg.norm(c)
    across = np.array([-along[1], along[0]])
    rules = retinex_edges.edge_rules(means, chroma, along, across, tau=0.1)
    # edges: (left, middle) = the shadow's, (middle, right) = the paint's
    assert not rules["retinex"][0] and rules["chord"][0] and rules["shadow"][0]
    assert not any(r[1] for r in rules.values()) and "crease" not in rules
    # the crease rule keeps the step between faces turned 90 deg apart, paint or not
    normals = np.array([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]])
    crease = retinex_edges.edge_rules(means, chroma, along, across, 0.1, normals)["crease"]
    assert list(crease) == [False, True]


def test_every_output_matrix_shows_a_grey_surface_grey_under_its_own_white():
    """matrix_offsets.shown_through: a grey surface under two lights (its low-light colour
    is the light's colour), balanced by each pixel's true white, comes out neutral through
    the D65 matrix, no matrix and the per-pixel DNG-adapted matrix; the adapted matrix of
    a white on the locus is display_matrix's for that white."""
    from gridnerf import exposure, illuminant

    xyz_to_cam = np.array([[0.7, -0.1, -0.05], [-0.4, 1.2, 0.2], [-0.08, 0.2, 0.6]])
    locus = illuminant.planckian_locus(xyz_to_cam)
    warm, cool = locus[200], locus[800]
    white = np.empty((4, 6, 3))
    white[:, :3], white[:, 3:] = warm, cool
    rgb_low = 0.02 * white
    for m in matrix_offsets.MATRICES:
        rgb = matrix_offsets.shown_through(rgb_low, white, m, xyz_to_cam)
        np.testing.assert_allclose(rgb / rgb[..., 1:2], 1.0, atol=1e-6, err_msg=m)
    tint = rgb_low * np.array([1.5, 1.0, 0.5])  # a coloured surface: matrices differ
    got = matrix_offsets.shown_through(tint, white, "adapted", xyz_to_cam)
    for part, w in ((slice(0, 3), warm), (slice(3, 6), cool)):
        want = (tint[:, part] * np.asarray(illuminant.gains_from_illuminant(w))
                @ exposure.display_matrix(xyz_to_cam, True, w).T)
        np.testing.assert_allclose(got[:, part], want, rtol=1e-9)


def test_black_level_table_differences_and_group_means():
    def per(ours_file, gw_file, ours_dark, gw_dark):
        return {"file": {"ours": {"psnr": ours_file, "delta_e": 9.0},
                         "global_gw": {"psnr": gw_file, "delta_e": 10.0}},
                "dark": {"ours": {"psnr": ours_dark, "delta_e": 7.0},
                         "global_gw": {"psnr": gw_dark, "delta_e": 8.0}}}

    record = {"bucket": per(20.0, 19.0, 21.0, 19.5), "box": per(22.0, 21.0, 21.5, 21.0),
              MIXED[0]: per(24.0, 23.0, 26.0, 24.0)}
    md = black_level.table(record, "cmd")
    assert ("| bucket | 20.00 / 9.00 | 19.00 / 10.00 | 21.00 / 7.00 | 19.50 / 8.00 | 1.00 "
            "| 1.50 |") in md
    # the nine's mean holds bucket and box only; the mixed-light scene is its own group
    assert "| **mean, nine** (2) | 21.00 / 9.00 | 20.00 / 10.00 | 21.25 / 7.00 | 20.25 / 8.00 " \
        "| 0.25 | 1.00 |" in md
    assert "| **mean, mixed light** (1) | 24.00 / 9.00 |" in md
    assert "held out" not in md.split("|---|")[1]  # no group without scenes
    readme = black_level.readme_table(record, "cmd")  # the group means alone
    assert "| nine (2) | 21.00 / 9.00 |" in readme and "bucket" not in readme


def test_carry_runs_compares_the_l_ca_inputs(small_scene, tmp_path):
    """A run's L_ca inputs are identical under its own estimator and differ under one that
    moves the estimate; runs without gains do not read the estimator."""
    cfg = cfgmod.override(cfgmod.preset("default"), ["loss.ca_illuminant=consensus"])
    run = tmp_path / "run"
    run.mkdir()
    assert carry_runs.same_inputs(run, small_scene, cfg, "consensus")
    assert not carry_runs.same_inputs(run, small_scene, cfg, "grey_world")
    assert carry_runs.estimates_from_frames(cfg)
    for preset in ("nogain", "llnerf"):
        assert not carry_runs.estimates_from_frames(cfgmod.preset(preset))
    batch = ["loss.ca_illuminant=grey_world", "loss.ca_target=batch"]
    assert not carry_runs.estimates_from_frames(cfgmod.override(cfg, batch))


def test_bench_training_key_follows_the_config_not_the_preset_name(monkeypatch, tmp_path):
    """experiments/bench.train_spec: the same preset name training a different config (a
    changed default) gets a different cache key; the same config, the same key."""
    import bench

    scene, run = tmp_path / "scene", tmp_path / "run"
    before = bench.train_spec(scene, "default", [], run)
    assert before == bench.train_spec(scene, "default", [], run)
    assert before["config"] != bench.train_spec(scene, "fast", [], run)["config"]
    changed = dict(cfgmod.PRESETS)
    changed["default"] = lambda: cfgmod.override(cfgmod.Config(), ["loss.w_ca=0.5"])
    monkeypatch.setattr(cfgmod, "PRESETS", changed)
    after = bench.train_spec(scene, "default", [], run)
    assert after["preset"] == before["preset"] and after["config"] != before["config"]
