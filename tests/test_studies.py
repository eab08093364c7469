"""The studies of the experiments package (ablate, sweep, photons, speed, consistency,
report, bench): their tables, means and plots from given results, their variants' configs,
and how the report picks them up. No training here."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from gridnerf import config as cfgmod
from gridnerf.sim import DEV, HELDOUT, MIXED, SCENES

REPO = Path(__file__).resolve().parent.parent

from experiments import ablate, common, consistency, photons, report, speed, sweep  # noqa: E402

# the modules of the package: the studies make report, ablate, recon and bench run
STUDIES = ("ablate", "bench", "colour_checks", "colour_groups", "consistency",
           "detail_views", "error_budget", "own_raw", "photons", "quirk_effects", "raw_fit",
           "recon", "report", "reship", "speed", "sweep")


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
    assert sweep.variant("llnerf", 0.3) == "llnerf_gamma0.3"
    # each method's gamma-1 run is its own run: llnerf the report's, binned the ablations'
    for method in sweep.METHODS:
        assert sweep.variant(method, 1.0) == method
    assert report.RUN_PRESETS["llnerf"] == sweep.METHODS["llnerf"][0] == "llnerf"
    assert sweep.METHODS["llnerf"][2] == [] and sweep.METHODS["binned"][2] == common.FACTOR_BASE
    assert ("full_tv", "binned") in [(k, f) for k, _, f, *_ in ablate.VARIANTS]


def test_photon_sweep_table_differences_and_plot(tmp_path):
    def cell(electrons, ours, noise):
        outs = {"ours": ours, "global_gw": 20.0, "denoised_2d": 19.0, "per_frame": 15.0}
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
    (out / "ablation_gain_model.md").write_text("One gain against the field\n\n| a table |\n")
    (out / "noise.md").write_text("# Sensor fit\n\na study no longer shipped\n")
    if with_png:
        (out / "sweep.png").write_bytes(b"not checked")
    proc = subprocess.run([sys.executable, "-m", "experiments.report", "--runs", "runs",
                           "--out", "out/report"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr
    text = (out / "report.md").read_text()
    assert "## Darkness sweep\n\nthe sweep table" in text
    assert "\n### Extreme\n" in text  # the study's own headings one level down
    assert ("![Darkness sweep](sweep.png)" in text) == with_png
    assert "## Ablation\n\nNot built yet: `python -m experiments.ablate`.\n" in text
    assert "Not built yet: `python -m experiments.ablate --study tv_fraction`" in text
    assert "Not built yet: `python -m experiments.bench`" in text
    # a study without a title line still sits under its heading
    assert "## One gain where one light (loss.gain_model)\n\nOne gain against" in text
    assert "Sensor fit" not in text  # only the studies of STUDIES are appended


def test_report_studies_are_built_by_the_package():
    """Every study the report appends names a module of the package and a command its
    parser takes (the `Not built yet` hint must work as printed)."""
    assert {"ablation", "sweep", "photons", "speed", "consistency", "recon",
            "bench"} <= {stem for stem, _, _ in report.STUDIES}
    for stem, _, command in report.STUDIES:
        module, *args = command.split()
        assert module in STUDIES, stem
        if module == "ablate" and "--study" in args:
            study = args[args.index("--study") + 1]
            assert study in ablate.STUDIES and stem == f"ablation_{study}"


def test_experiments_is_a_package_of_the_studies():
    """experiments/ holds the studies and common only, each imported as experiments.<name>
    (no top-level `common` import, no sys.path edits)."""
    folder = REPO / "experiments"
    assert (folder / "__init__.py").is_file()
    assert {p.stem for p in folder.glob("*.py")} == {"__init__", "common", *STUDIES}
    bare = re.compile(r"^\s*(from|import) (" + "|".join(("common", *STUDIES)) + r")\b", re.M)
    for path in folder.glob("*.py"):
        text = path.read_text()
        assert not bare.search(text), (path, bare.search(text))
        assert "sys.path" not in text, path


@pytest.mark.parametrize("name", STUDIES)
def test_every_study_runs_as_a_module(name):
    """python -m experiments.<name> from the repository root: its command line parses."""
    proc = subprocess.run([sys.executable, "-m", f"experiments.{name}", "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith("usage:")


def test_ablation_scene_groups_and_gain_model_study():
    assert common.scene_names("nine,mixed") == [*SCENES, *MIXED]
    assert common.scene_names("all") == [*SCENES, *HELDOUT]
    assert common.scene_names("box,deer,nine") == ["box", "deer", *[s for s in SCENES
                                                                   if s not in ("box", "deer")]]
    assert common.scene_names("all", ("nine", "dev")) == [*SCENES, *DEV]
    record = {"bucket": {"no_cr": {"matrix": _m(12.0), "global_gain": _m(20.0)},
                         "full_tv": {"matrix": _m(22.0)}},
              "deer": {"full_tv": {"matrix": _m(20.0)}}}
    table = ablate.means_table(ablate.means(record, SCENES), {})  # docs/results.md's
    assert "| the same grid, one grey-world gain (RawNeRF + ISP) | 20.00 / 0.500 / 10.00 " \
        "(n=1) | - |" in table
    assert "| full, smoothness as grid TV (default) | 21.00 / 0.500 / 10.00 (n=2) | - |" in table
    record = {"bucket": {"field": {"matrix": _m(18.0)}, "auto": {"matrix": _m(19.0)}}}
    nine = ablate.means(record, SCENES, ablate.GAIN_MODEL_VARIANTS)
    assert set(nine) == {"field", "auto"}
    assert "one gain where one light, the field where lights mix" in ablate.markdown(
        record, {"nine": nine}, ablate.GAIN_MODEL_VARIANTS)
    mixed = {"mixed_lamp_window": {"field": {"matrix": _m(25.0)}}}
    text = ablate.markdown(mixed, ablate.group_means(mixed, ablate.GAIN_MODEL_VARIANTS),
                           ablate.GAIN_MODEL_VARIANTS)
    assert "| **mean, mixed light** (n=1) | gain field (default) | matrix | 25.00 |" in text
    assert "mean, nine" not in text
    # each held-out generator apart: a path-traced capture is not averaged into another group
    traced = {"cycles_cornell": {"field": {"matrix": _m(23.0)}}}
    text = ablate.markdown(traced, ablate.group_means(traced, ablate.GAIN_MODEL_VARIANTS),
                           ablate.GAIN_MODEL_VARIANTS)
    assert "| **mean, path-traced** (n=1) | gain field (default) | matrix | 23.00 |" in text
    assert "mean, held out" not in text and "mean, mixed light" not in text


def test_every_study_variant_is_a_valid_config_and_shared_folders_agree():
    """A run folder shared by studies (e.g. `default`) must mean one config everywhere,
    else run_variant refuses it in the second study; every override must validate."""
    seen: dict = {}
    for folder, preset in report.RUN_PRESETS.items():
        seen[folder] = cfgmod.preset(preset)
    for variants in ablate.STUDIES.values():
        for _key, _label, folder, preset, sets in variants:
            cfg = cfgmod.override(cfgmod.preset(preset), sets)
            assert seen.setdefault(folder, cfg) == cfg, folder
    for folder, sets in photons.VARIANTS.items():  # the photon sweep's, on the default
        cfg = cfgmod.override(cfgmod.preset("default"), sets)
        assert seen.setdefault(folder, cfg) == cfg, folder
    for method, (preset, _, sets) in sweep.METHODS.items():
        for g in (sweep.EXTREME, *sweep.GAMMAS):
            extra = [] if g == 1.0 else [f"data.exposure_ratio={g:g}"]
            cfg = cfgmod.override(cfgmod.preset(preset), sets + extra)
            assert seen.setdefault(sweep.variant(method, g), cfg) == cfg, method
    assert seen["ws0.01"].loss.w_smooth == 0.01
    assert seen["default"] == cfgmod.preset("default")
    assert seen["nogain"].loss.gain_model == "none" and not seen["nogain"].loss.use_gains
    assert seen["gain_auto_dark"].data.black_offset == "dark"
    assert seen["binned_gamma0.3"].data.exposure_ratio == 0.3
    # the factor studies' runs fit the binned raw throughout; the default, the data-term
    # study's mosaic run, the chroma study's two runs, the density-rate study's run and the
    # last-width, colour-solve and detail studies' are the only ones with a mosaic stage
    mosaic = sorted(f for f, c in seen.items()
                    if c.data.target == "raw" and c.data.mosaic_from(3) < 3)
    assert mosaic == ["chroma", "cs20", "default", "detail288", "lrd0.6", "mosaic",
                      "mosaic_last", "w288tv"], mosaic
    assert seen["detail288"].grid.detail_width == 288
    assert seen["cs20"].train.colour_solve_iters == 20
    assert seen["w288tv"].loss.tv_ref_width == 192
    assert seen["w288tv"].grid.resolutions[-1] == (288, 0, 64)
    # the chroma prior: the default's, and the chroma study's run of it on the measured
    # footing, which is the default's footing in all else (cfgmod.FOOTING); mosaic_last is
    # that run without the prior
    chroma = sorted(f for f, c in seen.items() if c.loss.tv_chroma > 0)
    assert chroma == ["chroma", "cs20", "default", "detail288", "lrd0.6", "w288tv"]
    assert seen["chroma"] == cfgmod.override(
        seen["default"], [*cfgmod.FOOTING, "loss.tv_chroma=0.01"])
    assert seen["mosaic_last"] == cfgmod.override(seen["chroma"], ["loss.tv_chroma=0"])
    # the density-rate study's run: today's default with the density's rate doubled
    assert seen["lrd0.6"] == cfgmod.override(seen["default"], ["train.lr_density=0.6"])
    assert seen["lrd0.6"] != seen["default"]
    # the last-width study's runs: today's default with a 288-wide last stage
    assert seen["w288tv"] == cfgmod.override(seen["default"], [
        "grid.resolutions=[[48,0,24],[96,0,48],[288,0,64]]", "render.max_samples=96",
        "loss.tv_ref_width=192"])
    # the detail study's run: today's default with the last stage refined where it reads
    assert seen["detail288"] == cfgmod.override(seen["default"], ["grid.detail_width=288"])
    # every preset but the default and every variant is on the measured footing
    for f, c in seen.items():
        if f not in ("default", "chroma", "tv0.1", "lrd0.6", "w288tv", "cs20", "detail288"):
            assert c.train.steps_per_stage[:3] == (600, 600, 1200), f
            assert c.loss.tv_fraction == 0.25 and c.loss.tv_chroma == 0, f
    assert set(ablate.STUDIES) == {"parts", "smoothness", "gain_model", "tv_fraction",
                                   "data_term", "chroma", "density_rate", "last_width",
                                   "colour_solve", "detail"}
    assert seen["default"].data.mosaic_from(3) == 2 and seen["mosaic"].data.mosaic_from(3) == 0
    assert seen["binned"].data.mosaic_from(3) == 3


def test_bench_training_key_follows_the_config_not_the_preset_name(monkeypatch, tmp_path):
    """experiments.bench.train_spec: the same preset name training a different config (a
    changed default) gets a different cache key; the same config, the same key."""
    from experiments import bench

    scene, run = tmp_path / "scene", tmp_path / "run"
    before = bench.train_spec(scene, "default", [], run)
    assert before == bench.train_spec(scene, "default", [], run)
    assert before["config"] != bench.train_spec(scene, "fast", [], run)["config"]
    changed = dict(cfgmod.PRESETS)
    changed["default"] = lambda: cfgmod.override(cfgmod.Config(), ["loss.w_ca=0.5"])
    monkeypatch.setattr(cfgmod, "PRESETS", changed)
    after = bench.train_spec(scene, "default", [], run)
    assert after["preset"] == before["preset"] and after["config"] != before["config"]


def test_error_budget_gaps_telescope_and_missing_fits_say_so():
    """Both sets of gaps of a full row add up to oracle - default (pipeline + noise + white
    from the trained fits; fit + output matrix + white & exposure from the renders), and
    the fit splits into representation + noise, the representation into eps + grid; the
    ceilings are the row's own numbers; a row without the trained fits says n/a rather than
    a number; the sRGB slope is the encoding's derivative."""
    from experiments import error_budget as eb
    from gridnerf.color import srgb_encode

    full = {"noise_only": 30.0, "bound": 25.0, "best_3x3": 26.0, "path": 24.0,
            "path_full": 28.0, "best_3x3_full": 28.5, "oracle": 29.0, "clean": 25.5,
            "clean_best_map": 26.5, "clean_eps_best_map": 27.5, "noisy": 23.0,
            "default": 21.0, "best_white": 22.5, "best_map": 23.5, "one_frame_nlm": 20.0}
    cells = eb.table_row("x", full)
    values = [float(c) for c in cells[len(eb.COLUMNS) + 1:]]
    gaps = dict(zip([h for _, h in eb.GAPS], values, strict=True))
    assert len(gaps) == len(eb.GAPS) == 10
    whole = full["oracle"] - full["default"]
    assert gaps["pipeline"] + gaps["noise"] + gaps["white"] == pytest.approx(whole)
    assert (gaps["fit"] + gaps["output matrix"] + gaps["white & exposure"]
            == pytest.approx(whole))
    assert gaps["fit: representation"] + gaps["fit: noise"] == pytest.approx(gaps["fit"])
    assert (gaps["representation: eps"] + gaps["representation: grid"]
            == pytest.approx(gaps["fit: representation"]))
    ceilings = eb.table_row("x", full, eb.CEILINGS, ())
    assert ceilings[1:] == [f"{full[k]:.2f}" for k, _ in eb.CEILINGS]
    part = {k: full[k] for k in ("noise_only", "bound", "oracle", "default", "best_map")}
    cells = eb.table_row("y", part)
    assert cells[1 + [k for k, _ in eb.COLUMNS].index("clean")] == "n/a"
    assert cells[-10:] == ["n/a"] * 3 + [f"{full['oracle'] - full['best_map']:+.2f}"] + [
        "n/a"] * 6
    import numpy as np

    x = np.array([0.001, 0.01, 0.18, 0.7])
    h = 1e-6
    numeric = (srgb_encode(x + h) - srgb_encode(x - h)) / (2 * h)
    np.testing.assert_allclose(eb.srgb_slope(x), numeric, rtol=1e-3)


def test_error_budget_best_white_undoes_a_wrong_diagonal_before_the_matrix():
    """A render whose balanced camera RGB is the reference's times a wrong white and
    exposure (a diagonal before the output matrix) scores as the reference itself with the
    best white; a twist of the colours (no diagonal in camera RGB undoes it exactly) does
    not, but the best 3x3 map does; neither map scores below the render as it is."""
    import numpy as np

    from experiments import error_budget as eb
    from gridnerf import color
    from gridnerf.evaluate import image_metrics

    rng = np.random.default_rng(0)
    gt = rng.uniform(0.02, 0.6, (48, 64, 3))
    matrix = color.srgb_from_cam(color.CAMERA_XYZ_TO_CAM["Sony ILCE-7SM2"])
    cam = gt.reshape(-1, 3) @ np.linalg.inv(matrix).T
    pred = ((cam * [1.6, 0.8, 1.3]) @ matrix.T).reshape(gt.shape)
    assert image_metrics(pred, gt, 16)["psnr"] < 20.0
    assert eb.best_map_psnr(pred, gt, matrix) > 60.0
    twist = np.array([[0.8, 0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.3, 0.7]])
    twisted = (gt.reshape(-1, 3) @ np.linalg.inv(twist).T).reshape(gt.shape)
    assert eb.best_map_psnr(twisted, gt, matrix) < 40.0
    assert eb.best_map_psnr(twisted, gt, matrix, full=True) > 60.0
    as_is = image_metrics(twisted, gt, 16)["psnr"]
    assert eb.best_map_psnr(twisted, gt, matrix) >= as_is - 1e-9


def test_error_budget_by_scale_tells_a_blurred_render_from_a_shifted_colour():
    """A render that is the reference blurred keeps little of its fine detail and is far
    closer to it at coarse scales than at full resolution; one that is the reference with a
    colour cast keeps all its detail and has the same error at both scales."""
    import numpy as np
    from scipy.ndimage import gaussian_filter

    from experiments import error_budget as eb
    from gridnerf.evaluate import image_metrics

    rng = np.random.default_rng(1)
    gt = gaussian_filter(rng.uniform(0.02, 0.6, (64, 96, 3)), (0.7, 0.7, 0))
    blurred = gaussian_filter(gt, (2.0, 2.0, 0))
    b = eb.by_scale(blurred, gt)
    assert b["detail_kept"] < 0.35
    assert b["coarse"] > image_metrics(blurred, gt, 16)["psnr"] + 6.0
    cast = gt * [1.15, 1.0, 0.9]
    c = eb.by_scale(cast, gt)
    assert 0.85 < c["detail_kept"] < 1.2
    assert abs(c["coarse"] - image_metrics(cast, gt, 16)["psnr"]) < 1.0
    same = eb.by_scale(gt, gt)
    assert same["detail_kept"] == 1.0 and same["coarse"] > 100.0
    # a cast is colour; a brighter render is grey where the reference is grey
    assert c["chroma_share"] > 0.5
    grey = np.repeat(gt[..., 1:2], 3, -1)
    assert eb.by_scale(grey * 1.1, grey)["chroma_share"] < 1e-9


def test_error_budget_reuses_a_true_white_fit_only_under_its_config(tmp_path):
    """A true-white fit (kept in the study's own record, not in RESULTS) is reused only
    where the record's fingerprint is the fit's config today: a fit trained by another
    config (the default before its mosaic stage, say) reads as missing, not as a number."""
    from experiments import error_budget as eb

    today = {k: common.fingerprint(eb.fit_config(k)) for k in eb.TRUE_WHITE}
    assert today["clean"] != today["noisy"]
    earlier = {"deer": {"clean": 25.0, "noisy": 24.0,
                        "fingerprints": {"clean": today["clean"], "noisy": "0" * 16}},
               "bucket": {"clean": 25.0, "noisy": 24.0}}  # a record without fingerprints
    assert eb.kept("deer", "clean", tmp_path, earlier) == 25.0
    assert eb.kept("deer", "noisy", tmp_path, earlier) is None
    assert eb.kept("bucket", "clean", tmp_path, earlier) is None
    # the clean raw goes the noisy raw's way: the mosaic in the last stage
    assert eb.fit_config("clean").data.mosaic_from(3) == 2
    assert eb.fit_config("noisy").data.mosaic_from(3) == 2
    # the fifth fit is the clean one with the data term's eps alone changed
    from dataclasses import replace

    clean = eb.fit_config("clean")
    assert eb.fit_config("clean_eps") == replace(clean, loss=replace(clean.loss,
                                                                     data_eps=eb.CLEAN_EPS))
    assert eb.CLEAN_EPS < clean.loss.data_eps


def test_own_raw_study_reads_pairs_of_evaluated_runs(tmp_path, monkeypatch):
    """experiments.own_raw: the change between two evaluated runs of a scene, and whether
    the own-raw score agrees with the references' PSNR; a pair with a run missing or
    evaluated without own_raw is left out."""
    from experiments import own_raw

    def run(name, psnr, own):
        folder = tmp_path / "runs" / "bucket" / name / "eval"
        folder.mkdir(parents=True)
        metrics = {"summary": {"gridnerf": {"psnr": psnr, "ssim": 0.8, "delta_e": 5.0}},
                   "own_raw": {"mean": own}}
        (folder / "metrics.json").write_text(json.dumps(metrics))

    run("a", 25.0, 0.100)
    run("b", 25.2, 0.098)  # better on both
    run("c", 24.8, 0.097)  # worse references, better score: disagree
    run("old", 25.0, None)
    d = own_raw.compare(own_raw.scores(tmp_path / "runs/bucket/a"),
                        own_raw.scores(tmp_path / "runs/bucket/b"))
    assert d["agree"] and d["psnr"] == pytest.approx(0.2)
    assert d["own_raw_rel"] == pytest.approx(-0.02)
    assert own_raw.scores(tmp_path / "runs/bucket/old") is None
    out = tmp_path / "own"
    monkeypatch.setattr(sys, "argv", ["own_raw", "--scenes", "bucket", "--runs",
                                      str(tmp_path / "runs"), "--out", str(out),
                                      "--pairs", "a:b,a:c,a:old,a:gone"])
    own_raw.main()
    record = json.loads(out.with_suffix(".json").read_text())
    assert sorted(record["bucket"]) == ["a:b", "a:c"]
    assert record["bucket"]["a:b"]["agree"] and not record["bucket"]["a:c"]["agree"]
    assert "agree on 1 of 2 pairs" in out.with_suffix(".md").read_text()


def test_error_budget_raw_discrepancy_reads_the_noise_in_units_of_its_variance(
        small_scene, tmp_path, monkeypatch):
    """A render that is the clean raw itself has no error, and its residual against the
    noisy frames is one frame's noise variance (chi^2 per photosite ~ 1) on training and test
    views alike; a render twice as bright errs; no run folder, nothing measured."""
    import numpy as np

    from experiments import error_budget as eb
    from gridnerf import config as cfgmod
    from gridnerf.sim import truth
    from gridnerf.train import train

    run = tmp_path / "run"
    cfg = cfgmod.override(cfgmod.preset("tiny"), ["train.steps_per_stage=[20]",
                                                  "grid.resolutions=[[12,0,8]]"])
    train(small_scene, run, cfg)
    cam = truth.clean_cam(small_scene)

    def clean_render(structure, params, scene, cfg, c2w, intr, h, w, scale=1.0):
        i = int(np.argmin([np.abs(c - c2w).sum() for c in scene.cameras.c2w]))
        return {"rgb_low": scale * cam(scene.names[i])}

    monkeypatch.setattr(eb, "render_view", clean_render)
    got = eb.raw_discrepancy(run, every=2)
    assert got["error"] == pytest.approx(0.0, abs=1e-9)
    assert got["train"] == pytest.approx(1.0, rel=0.05)
    assert got["test"] == pytest.approx(1.0, rel=0.08)
    monkeypatch.setattr(eb, "render_view", lambda *a: clean_render(*a, scale=2.0))
    assert eb.raw_discrepancy(run, every=2)["error"] > 1.0
    assert eb.raw_discrepancy(tmp_path / "missing") == {}
