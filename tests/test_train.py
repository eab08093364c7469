"""End-to-end: a tiny scene trains in seconds, lowers the loss, resumes, evaluates."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import numpy as np
import pytest

from gridnerf import checkpoint, data_term, optim, stages
from gridnerf import config as cfgmod
from gridnerf import plan as planmod
from gridnerf.errors import ConfigError, NumericsError


@pytest.fixture(scope="module")
def tiny_run(small_scene, tmp_path_factory):
    from gridnerf.train import train

    run = tmp_path_factory.mktemp("runs") / "tiny"
    cfg = cfgmod.preset("tiny")
    summary = train(small_scene, run, cfg)
    return run, cfg, summary


def _losses(run):
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_training_lowers_the_loss(tiny_run):
    """The data loss on one fixed batch of training rays, at the start (stages.initial_grid,
    composited over black: its fog renders at ~70 % of the data's level) and after
    training; and the opacity term falls in the coarse stage, the only one it acts in.
    (Over the mean-colour backdrop the start is the constant mean colour, which 80 steps of
    this 80x45 noisy scene do not beat on the raw loss: 0.234 at the start, 0.238 after.)"""
    import dataclasses

    import jax

    from gridnerf import dataset, eval_run, grid, losses, methods, render

    run, cfg, summary = tiny_run
    _, plan, scene, structure, params, _ = eval_run.load_run(run)
    method = methods.get(cfg.loss.method)
    data, colour = method.plan_colour(method.training_data(scene, cfg), scene, cfg, plan.colour)
    rays = dataset.batch(data, jax.random.PRNGKey(11), 128, 8)
    near_t, far_t = dataset.grid_box(scene)[2:]

    def data_loss(structure, params):
        out = render.render_image(structure, params, rays["origins"], rays["directions"],
                                  near_t, far_t, cfg.render)
        return float(losses.data_loss(out["rgb_low"].reshape(-1, 3),
                                      rays["target"].reshape(-1, 3),
                                      rays["mask"].reshape(-1, 3)))

    start, start_params = stages.initial_grid(
        data, scene, cfg, jax.random.PRNGKey(cfg.train.seed),
        lambda scale, grey: method.init_log_gain(cfg, colour, scale, grey))
    start = dataclasses.replace(start, background=jax.numpy.asarray(grid.BLACK))
    first, last = data_loss(start, start_params), data_loss(structure, params)
    assert last < 0.7 * first, (first, last)
    recs = _losses(run)
    coarse = [r for r in recs if r["stage"] == 0]  # loss.opacity_stages = 1: the prior's stage
    assert np.mean([r["opacity"] for r in coarse[-2:]]) < np.mean([r["opacity"]
                                                                  for r in coarse[:2]])
    assert cfg.loss.opacity_stages == 1 and not any("opacity" in r for r in recs
                                                    if r["stage"] > 0)
    assert summary["rays_per_second"] > 0 and summary["train_seconds"] > 0
    assert (run / "config.json").exists()
    assert cfgmod.load(run / "config.json") == cfg


def test_checkpoint_is_finite_and_loads(tiny_run):
    from gridnerf.train import load_state

    run, cfg, _ = tiny_run
    structure, params, _, header = load_state(run)
    assert tuple(structure.resolution) == cfg.grid.resolutions[-1]
    assert header["stage"] == len(cfg.grid.resolutions)
    for v in params.values():
        assert np.all(np.isfinite(np.asarray(v)))
    assert not list(run.glob("*.tmp"))


def _crash_after(monkeypatch, n_steps: int) -> None:
    """Make optim.make_step's steps raise KeyboardInterrupt after n_steps calls (a kill)."""

    real_make_step, calls = optim.make_step, {"n": 0}

    def crashing_make_step(*args, **kwargs):
        step = real_make_step(*args, **kwargs)

        def wrapped(*a):
            calls["n"] += 1
            if calls["n"] > n_steps:
                raise KeyboardInterrupt
            return step(*a)

        return wrapped

    monkeypatch.setattr(optim, "make_step", crashing_make_step)


@pytest.mark.parametrize("mosaic_stages", [0, 1])
def test_interrupted_training_resumes_from_checkpoint(small_scene, tmp_path, monkeypatch,
                                                      capsys, mosaic_stages):
    """Killed in its second stage, a run resumes there; with data.mosaic_stages=1 that
    stage fits the raw mosaic, before the crash and again on the resume."""
    from gridnerf import train as trainmod

    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", float("inf"))
    cfg = cfgmod.override(cfgmod.preset("tiny"), [
        "train.steps_per_stage=[20,20]", "train.checkpoint_every=10", "train.log_every=4",
        f"data.mosaic_stages={mosaic_stages}"])
    run = tmp_path / "run"
    real_make_step = optim.make_step
    _crash_after(monkeypatch, 33)  # dies at stage 1 step 14, after its step-10 checkpoint
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(small_scene, run, cfg)
    _, _, opt_leaves, header = trainmod.load_state(run)
    assert (header["stage"], header["step"]) == (1, 10)
    assert opt_leaves  # optimiser state is saved mid-stage
    assert capsys.readouterr().out.count("stage 1: fitting the raw mosaic") == mosaic_stages
    monkeypatch.setattr(optim, "make_step", real_make_step)
    trainmod.train(small_scene, run, cfg)
    assert capsys.readouterr().out.count("stage 1: fitting the raw mosaic") == mosaic_stages
    resumed = [r for r in _losses(run) if r["stage"] == 1]
    # 4, 8 and 12 were logged before the crash; 12 (after the checkpoint) is trimmed and redone
    assert [r["step"] for r in resumed] == [4, 8, 12, 16, 20]
    assert all(np.isfinite(r["loss"]) for r in resumed)
    assert trainmod.load_state(run)[3]["stage"] == 2


def test_the_mosaic_stages_are_the_last_ones_of_the_raw_capture(tmp_path):
    """DataConfig.mosaic_from: the last data.mosaic_stages stages of a raw run at its own
    size; none for a binned image target or a downscaled raw; all with binning off. A
    config saved before the added fields existed reads as binned throughout, without a
    warm-up, and the fingerprint of such a config is the one it had (its kept results stay
    valid)."""
    from experiments import common

    def first(*sets, n=3):
        return cfgmod.override(cfgmod.Config(), list(sets)).data.mosaic_from(n)

    assert first("data.mosaic_stages=1") == 2 and first("data.mosaic_stages=2") == 1
    assert first("data.mosaic_stages=5") == 0 and first("data.mosaic_stages=0") == 3
    assert first("data.binning=false") == 0
    for image in ("data.target=reference", "data.downscale=2"):
        assert first("data.mosaic_stages=1", image) == 3
    for name in ("oracle", "processed", "llnerf", "tiny", "nogain"):
        assert cfgmod.preset(name).data.mosaic_from(3) == 3
    for bad in ("mosaic_stages", "eval_downscale", "downscale"):
        with pytest.raises(ConfigError, match=bad):
            cfgmod.override(cfgmod.Config(), [f"data.{bad}=-1"])
    saved = cfgmod.to_dict(cfgmod.preset("oracle"))
    for section, name in cfgmod.ADDED_FIELDS:  # mosaic_stages, warmup_steps
        del saved[section][name]
    assert cfgmod.from_dict(saved) == cfgmod.preset("oracle")
    blob = json.dumps(saved, sort_keys=True, default=str)
    assert common.fingerprint(cfgmod.preset("oracle")) == hashlib.sha256(
        blob.encode()).hexdigest()[:16]
    assert common.fingerprint(cfgmod.Config()) != common.fingerprint(
        cfgmod.override(cfgmod.Config(), ["data.mosaic_stages=0"]))
    # the default: the last stage on the mosaic
    assert cfgmod.Config().data.mosaic_from(len(cfgmod.Config().grid.resolutions)) == 2


@pytest.fixture(scope="module")
def dark_scene(tmp_path_factory):
    """small_scene's capture at a fifth of its light (2 electrons a green photosite)."""
    from gridnerf.sim import simulate_scene

    out = tmp_path_factory.mktemp("scenes") / "bucket_dark"
    return simulate_scene("bucket", out, width=160, height=90, n_frames=12, seed=0, light=0.2)


def test_photosite_snr_counts_the_photons(small_scene, dark_scene):
    """data_term.photosite_snr on the binned and on the mosaic targets of one capture agree
    (a binned green averages two photosites), read the simulator's 10 electrons a green
    photosite within 15 %, and read a fifth of the light as fewer than the 2 electrons it
    holds (the read noise counts against it), under the threshold: the planned mosaic
    stages follow."""
    import jax

    from gridnerf import dataset
    from gridnerf import scene as scenemod
    from tests.conftest import sim_near_far

    cfg = cfgmod.Config()
    got = {}
    for name, folder in (("bright", small_scene), ("dark", dark_scene)):
        sc = scenemod.load_scene(folder, near_far=sim_near_far(folder))
        for binning in (True, False):
            data = dataset.training_data(sc, replace(cfg.data, binning=binning))
            got[name, binning] = data_term.photosite_snr(data, jax.random.PRNGKey(3))
        electrons = json.loads((folder / "sim.json").read_text())["electrons_mean_green"]
        assert abs(got[name, True] / got[name, False] - 1.0) < 0.2, got
        got[name] = electrons
    assert abs(got["bright", True] / got["bright"] - 1.0) < 0.15, got
    assert got["dark", True] < got["dark"] < data_term.MOSAIC_MIN_ELECTRONS, got
    assert data_term.planned_mosaic_stages(cfg, got["bright", True]) == 1
    assert data_term.planned_mosaic_stages(cfg, got["dark", True]) == 0


def test_planned_mosaic_stages_keep_the_config_unless_the_photons_are_few(capsys):
    """The config's count where the photons reach data_term.MOSAIC_MIN_ELECTRONS and where
    they could not be measured; 0 with one line below it, and always under
    data.mosaic_stages=0."""
    def planned(snr, *sets):
        return data_term.planned_mosaic_stages(cfgmod.override(cfgmod.Config(), list(sets)),
                                               snr)

    floor = data_term.MOSAIC_MIN_ELECTRONS
    assert planned(floor) == 1 and planned(50.0, "data.mosaic_stages=2") == 2
    assert planned(float("nan")) == 1 and planned(float("inf")) == 1
    assert planned(50.0, "data.mosaic_stages=0") == 0
    assert capsys.readouterr().out == ""
    assert planned(0.99 * floor) == 0
    assert "photo-electrons per green photosite" in capsys.readouterr().out


@pytest.mark.parametrize("sets", [["data.mosaic_stages=1"], ["data.mosaic_stages=5"]])
def test_a_dark_capture_trains_binned_and_the_plan_says_so(dark_scene, tmp_path, capsys,
                                                            monkeypatch, sets):
    """With too few photons a run asked for the mosaic (in the last stage, or in every
    stage through data.mosaic_stages) fits the binned raw throughout: its plan keeps the
    measured photons and the decision; killed in its second stage, it resumes there on the
    binned raw, without measuring again, and the summary says no stage fitted the mosaic."""
    from gridnerf import plan as planmod
    from gridnerf import train as trainmod

    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", float("inf"))
    cfg = cfgmod.override(cfgmod.preset("tiny"), [
        *sets, "train.steps_per_stage=[20,20]", "train.checkpoint_every=10"])
    run = tmp_path / "run"
    real_make_step = optim.make_step
    _crash_after(monkeypatch, 33)  # dies at stage 1 step 14, after its step-10 checkpoint
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(dark_scene, run, cfg)
    out = capsys.readouterr().out
    assert "fitting the raw mosaic" not in out and "photo-electrons per green" in out
    plan = planmod.load(run)
    assert plan.mosaic_stages == 0 and 0 < plan.photosite_snr < data_term.MOSAIC_MIN_ELECTRONS
    monkeypatch.setattr(optim, "make_step", real_make_step)
    summary = trainmod.train(dark_scene, run, cfg)
    out = capsys.readouterr().out
    assert "resuming" in out and "fitting the raw mosaic" not in out
    assert "photo-electrons per green" not in out  # the plan's decision, not a new one
    assert summary["mosaic_stages"] == 0 and summary["photosite_snr"] == plan.photosite_snr


def test_planned_downscale_follows_the_final_voxels_footprint():
    """A training pixel (2 x downscale capture pixels) stays within half a final voxel
    (capture width / last x vertex count): 480x270 under the default grid keeps the binned
    size (its mosaic stage), 1920x1080 is downscaled by 2, 3840 by 4; never below the
    config's downscale; a finer last stage or the mosaic in every stage (binning off) keep
    the config's."""
    def planned(width, *sets):
        return data_term.planned_downscale(cfgmod.override(cfgmod.Config(), list(sets)), width)

    assert planned(480) == 1 and planned(960) == 1 and planned(1536) == 2
    assert planned(1920) == 2 and planned(3840) == 4
    assert planned(480, "data.downscale=3") == 3 and planned(3840, "data.downscale=3") == 3
    assert planned(1920, "data.binning=false") == 1
    finer = "grid.resolutions=[[48,0,24],[96,0,48],[192,0,64],[480,0,96]]"
    assert planned(1920, finer, "train.steps_per_stage=[1,1,1,1]") == 1
    cfg = cfgmod.override(cfgmod.Config(), ["train.steps_per_stage=[600,600,1200]"])
    assert data_term.fitted_config(cfg, None) is cfg and data_term.fitted_config(cfg, 1) is cfg
    assert data_term.fitted_config(cfg, 2).data.downscale == 2
    # the last stage trains as many times its steps as the plan raised the downscale
    assert data_term.fitted_config(cfg, 2).train.steps_per_stage == (600, 600, 2400)
    asked = cfgmod.override(cfg, ["data.downscale=2"])
    assert data_term.fitted_config(asked, 2) is asked
    assert data_term.fitted_config(asked, 4).train.steps_per_stage == (600, 600, 2400)


def test_a_capture_wider_than_the_grid_trains_on_larger_pixels(small_scene, tmp_path, capsys,
                                                                 monkeypatch):
    """Ten capture pixels a final voxel: the run fits the binned frames downscaled by 2 and
    its plan says so; config.json keeps the user's downscale, load_run gives the fitted one;
    killed and resumed under a rule that would decide otherwise, it keeps its plan's."""
    from gridnerf import eval_run
    from gridnerf import plan as planmod
    from gridnerf import train as trainmod

    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", float("inf"))
    cfg = cfgmod.override(cfgmod.preset("tiny"), [
        "grid.resolutions=[[8,8,8],[16,16,8]]", "train.steps_per_stage=[20,20]",
        "train.checkpoint_every=10", "grid.voxel_pixels=0"])
    run = tmp_path / "run"
    real_make_step = optim.make_step
    _crash_after(monkeypatch, 33)
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(small_scene, run, cfg)
    assert "box-downscaled by 2 (40 pixels wide)" in capsys.readouterr().out
    assert planmod.load(run).downscale == 2
    assert cfgmod.load(run / "config.json").data.downscale == 1
    monkeypatch.setattr(optim, "make_step", real_make_step)
    monkeypatch.setattr(data_term, "PIXEL_PER_VOXEL", 0.25)  # would keep the binned size
    summary = trainmod.train(small_scene, run, cfg)
    assert "resuming" in capsys.readouterr().out
    assert summary["downscale"] == 2 and planmod.load(run).downscale == 2
    fitted = eval_run.load_run(run)[0]
    assert fitted.data.downscale == 2 and fitted == data_term.fitted_config(cfg, 2)
    last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    assert (last["stage"], last["step"]) == (1, 40)  # the last stage's 20 steps, twice


def test_appended_stage_follows_the_capture_width():
    """grid.voxel_pixels appends a stage twice as wide where a vertex of the last would span
    more capture pixels: 1920 under the default grid and 5 pixels (10 a vertex), not 960
    (5) nor 480; never where it is 0. The appended config: depth 1.5x, plan.APPENDED_STEPS
    on the last two stages, TVs against the configured width, slots by the ratio, binned."""
    def cfg(*sets):
        return cfgmod.override(cfgmod.Config(), ["grid.voxel_pixels=5", *sets])

    assert planmod.appended_width(cfg(), 1920) == 384
    assert planmod.appended_width(cfg(), 960) is None
    assert planmod.appended_width(cfg(), 480) is None
    assert planmod.appended_width(cfg("grid.voxel_pixels=0"), 3840) is None
    assert planmod.capture_config(cfg(), None) == cfg()
    c = planmod.capture_config(cfg("render.max_samples=64"), 384)
    assert c.grid.resolutions[-2:] == ((192, 0, 64), (384, 0, 96))
    assert c.train.steps_per_stage == (600, 600, *planmod.APPENDED_STEPS)
    assert c.loss.tv_ref_width == 192 and c.render.max_samples == 128
    assert c.data.mosaic_stages == 0
    assert optim.tv_scale(c, 3) == 2.0 and optim.tv_scale(c, 2) == 1.0
    # the TVs by the footprint too: 5 pixels a vertex at 1920 against TV_FOOTPRINT's 2.5 halve
    # the width's doubling; 3.3 at 1280 leave x1.5; at 3840 (10 pixels) the rule's x0.5
    # leaves the configured weights (optim.tv_scale never weakens them)
    assert planmod.appended_tv_ref(cfg(), 384, 1920) == 384
    assert planmod.appended_tv_ref(cfg(), 384, 1280) == 256
    assert planmod.appended_tv_ref(cfg("loss.tv_ref_width=96"), 384, 1920) == 96
    for capture, scale in ((1920, 1.0), (1280, 1.5), (3840, 1.0)):
        tv = planmod.appended_tv_ref(cfg(), 384, capture)
        fitted = planmod.capture_config(cfg(), 384, tv_ref=tv)
        assert optim.tv_scale(fitted, 3) == scale and optim.tv_scale(fitted, 2) == 1.0
    # the training frames then keep their binned size: a training pixel within half a vertex
    assert data_term.planned_downscale(c, 1920) == 1


def test_configured_stages_tvs_follow_the_capture_footprint():
    """Where a stage is appended, the configured stages' TVs scale by TV_FOOTPRINT over the
    capture pixels a vertex of the last configured stage spans (0.25 at 1920, 0.375 at
    1280), the appended stage's stay its own (appended_tv_ref); no factor where nothing is
    appended, where loss.tv_ref_width is set, or in a plan saved before the rule."""
    def cfg(*sets):
        return cfgmod.override(cfgmod.Config(), ["grid.voxel_pixels=5", *sets])

    assert planmod.configured_tv(cfg(), 384, 1920) == 0.25
    assert planmod.configured_tv(cfg(), 384, 1280) == 0.375
    assert planmod.configured_tv(cfg(), None, 480) is None
    assert planmod.configured_tv(cfg("loss.tv_ref_width=192"), 384, 1920) is None
    fitted = planmod.capture_config(cfg(), 384, tv_ref=planmod.appended_tv_ref(cfg(), 384, 1920))
    base = dict(method="brightnerf", black_level="file", data_noise=None, data_eps=1e-3,
                colour=planmod.ColourPlan(model="none"), opacity=(0.0,) * 4,
                n_candidates=(0,) * 4)
    ruled = planmod.RunPlan(**base, appended_width=384, configured_tv=0.25)
    assert [optim.stage_tv_scale(fitted, ruled, s) for s in range(4)] == [0.25] * 3 + [1.0]
    before = planmod.RunPlan(**base, appended_width=384)  # saved before the rule
    assert [optim.stage_tv_scale(fitted, before, s) for s in range(4)] == [1.0] * 4
    assert planmod.from_dict(planmod.to_dict(ruled)) == ruled


def test_a_wide_capture_trains_an_appended_stage_and_resumes(small_scene, tmp_path, capsys,
                                                               monkeypatch):
    """Ten capture pixels a vertex of the last stage over a limit of 2: the run appends a
    stage twice as wide, its plan says so, config.json keeps the user's stages, load_run
    gives the appended ones; killed and resumed with the limit off and other appended
    steps in the code, it keeps its plan's stage and steps."""
    from gridnerf import eval_run
    from gridnerf import train as trainmod

    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", float("inf"))
    cfg = cfgmod.override(cfgmod.preset("tiny"), [
        "grid.resolutions=[[8,8,8],[16,16,8]]", "train.steps_per_stage=[10,10]",
        "train.checkpoint_every=10", "grid.voxel_pixels=2"])
    monkeypatch.setattr(planmod, "APPENDED_STEPS", (10, 20))
    run = tmp_path / "run"
    real_make_step = optim.make_step
    _crash_after(monkeypatch, 25)
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(small_scene, run, cfg)
    assert "a stage 32 wide is appended" in capsys.readouterr().out
    assert planmod.load(run).appended_width == 32
    assert cfgmod.load(run / "config.json").grid.resolutions == ((8, 8, 8), (16, 16, 8))
    monkeypatch.setattr(optim, "make_step", real_make_step)
    assert planmod.load(run).appended_steps == (10, 20)
    tv_ref = planmod.load(run).appended_tv_ref
    assert tv_ref == planmod.appended_tv_ref(cfg, 32, 160) == 32  # the fixture is 160 wide
    configured = planmod.load(run).configured_tv
    assert configured == planmod.configured_tv(cfg, 32, 160) == 0.25
    # the code's steps and footprint changed since: the resume keeps what the run began with
    monkeypatch.setattr(planmod, "APPENDED_STEPS", (10, 30))
    monkeypatch.setattr(planmod, "TV_FOOTPRINT", 1.0)
    off = cfgmod.override(cfg, ["grid.voxel_pixels=0"])
    summary = trainmod.train(small_scene, run, off, overwrite_config=True)
    assert "resuming" in capsys.readouterr().out
    assert summary["resolution"][0] == 32 and planmod.load(run).appended_width == 32
    fitted = eval_run.load_run(run)[0]
    assert fitted.grid.resolutions[-1] == (32, 0, 12) and fitted.loss.tv_ref_width == tv_ref
    assert planmod.load(run).configured_tv == configured
    last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    assert (last["stage"], last["step"]) == (2, 20)


def test_checkpoint_refuses_non_finite(tmp_path):
    with pytest.raises(NumericsError, match="non-finite"):
        checkpoint.save(tmp_path / "c.npz", {"p": [np.array([1.0, np.nan])]}, {})
    assert not (tmp_path / "c.npz").exists()


def test_nan_loss_stops_training_without_checkpoint(small_scene, tmp_path, monkeypatch):
    from gridnerf import train as train_mod
    from gridnerf.train import train

    # a loaded machine may take over CHECKPOINT_SECONDS for the first (compiling) step: the
    # checkpoint's own refusal would then speak first
    monkeypatch.setattr(train_mod, "CHECKPOINT_SECONDS", 1e9)
    cfg = cfgmod.preset("tiny")
    object.__setattr__(cfg.train, "lr_rgb", float("nan"))  # the config refuses NaN itself
    # the loss is checked at the first log step (10), naming the step it first failed at
    with pytest.raises(NumericsError, match="loss became nan at stage 0 step 1;"):
        train(small_scene, tmp_path / "run", cfg)
    assert not (tmp_path / "run" / "checkpoint.npz").exists()


def test_eval_writes_metrics_and_images(tiny_run):
    from gridnerf.eval_run import evaluate_run

    run, _, _ = tiny_run
    result = evaluate_run(run)
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    assert metrics["summary"] == json.loads(json.dumps(result["summary"]))
    for method in ("gridnerf", "gridnerf_matrix_free", "global_grey_world",
                   "baseline_dark_frame", "baseline_denoised"):
        s = metrics["summary"][method]
        for key in ("psnr", "ssim", "delta_e", "psnr_aligned", "ssim_aligned", "delta_e_aligned"):
            assert np.isfinite(s[key]), (method, key)
    assert metrics["lpips"] == "n/a"
    for name in metrics["test_views"]:
        for suffix in ("pred.png", "pred.exr", "gt.png", "error.png"):
            assert (run / "eval" / f"{name}_{suffix}").exists()


def test_eval_scores_each_test_view_against_its_own_raw_frame(tiny_run):
    """eval's own_raw: one finite data term per test view against its own raw frame; a
    render that explains the frame worse (three times as bright) scores higher."""
    from gridnerf import eval_run

    run = tiny_run[0]
    metrics = eval_run.evaluate_run(run)
    own = metrics["own_raw"]
    assert sorted(own["per_view"]) == sorted(metrics["test_views"])
    assert all(np.isfinite(v) and v > 0 for v in own["per_view"].values())
    assert own["mean"] == pytest.approx(np.mean(list(own["per_view"].values())))
    cfg, plan, scene, structure, params, _ = eval_run.load_run(run)
    i = int(scene.test_idx[0])
    cams = scene.cameras
    out = eval_run.render_view(structure, params, scene, cfg, cams.c2w[i], cams.intrinsics(i),
                               cams.height, cams.width)
    term = eval_run.own_raw_term(out["rgb_low"], scene, i, cfg, plan)
    assert term == pytest.approx(own["per_view"][scene.names[i]], rel=1e-5)
    assert eval_run.own_raw_term(3.0 * out["rgb_low"], scene, i, cfg, plan) > 1.2 * term
    # a render at another size, or a run that does not fit the raw: no score
    assert eval_run.own_raw_term(out["rgb_low"][::2, ::2], scene, i, cfg, plan) is None
    ref = cfgmod.override(cfg, ["data.target=reference"])
    assert eval_run.own_raw_term(out["rgb_low"], scene, i, ref, plan) is None


def test_global_gains_equalise_the_render_means():
    from gridnerf.outputs import global_gains

    rgb_low = np.random.default_rng(0).uniform(size=(500, 3)) * [0.02, 0.04, 0.01]
    gains = global_gains({"rgb_low": rgb_low})
    means = (rgb_low * gains).mean(0)
    np.testing.assert_allclose(means, means.mean(), rtol=1e-9)
    np.testing.assert_allclose(global_gains({"rgb_low": 7.0 * rgb_low}), gains, rtol=1e-9)
    assert gains.mean() == pytest.approx(np.mean(rgb_low.mean(0)) * np.mean(1 / rgb_low.mean(0)))


def test_config_overrides_and_round_trip(tmp_path):
    cfg = cfgmod.override(
        cfgmod.preset("default"),
        ["train.steps_per_stage=[5,6,7]", "loss.gain_model=none", "grid.sh_degree=1"],
    )
    assert cfg.train.steps_per_stage == (5, 6, 7)
    assert cfg.loss.use_gains is False and cfg.grid.sh_degree == 1
    assert len([f for s in cfgmod.to_dict(cfg).values() for f in s]) <= 52  # the method's
    cfgmod.save(cfg, tmp_path / "c.json")
    assert cfgmod.load(tmp_path / "c.json") == cfg
    with pytest.raises(ValueError, match="bad override"):
        cfgmod.override(cfg, ["nosuch.field=1"])


def test_render_camera_path_writes_video(tiny_run):
    from gridnerf.eval_run import RenderSettings, render_run

    run, _, _ = tiny_run
    video = render_run(run, RenderSettings(path="spiral", n_frames=4))
    assert video.exists() and video.stat().st_size > 0
    assert len(list((run / "render").glob("spiral_*.png"))) == 4
    assert len(list((run / "render").glob("spiral_*.exr"))) == 4


def test_render_controls_change_only_what_they_name(tiny_run):
    """One stop more doubles the linear EXR; a white balance changes the colour but not the
    mean luminance (each white is exposed again); scale sets the size; a path through
    named views starts and ends on them; render/<path>.json records what was shown."""
    from gridnerf import color, image_io
    from gridnerf.eval_run import RenderSettings, render_run

    run, _, _ = tiny_run

    def rendered(**kw) -> tuple[np.ndarray, dict]:
        settings = RenderSettings(path="test", formats=("exr",), **kw)
        render_run(run, settings)
        record = json.loads((run / "render" / "test.json").read_text())
        return image_io.read_exr(run / "render" / f"{record['views'][0]}.exr"), record

    base, rec0 = rendered()
    brighter, rec1 = rendered(exposure_stops=1.0)
    np.testing.assert_allclose(brighter, 2.0 * base, rtol=1e-4, atol=1e-6)
    assert rec1["alpha"] == pytest.approx(2.0 * rec0["alpha"])
    warm, rec2 = rendered(white="temp:2500")
    cool, _ = rendered(white="temp:9000")
    assert rec2["source"] == "rgb_low"
    # a warmer assumed light takes more red out: the image is bluer than under a cooler one
    assert warm[..., 2].mean() / warm[..., 0].mean() > cool[..., 2].mean() / cool[..., 0].mean()
    assert color.luminance(warm).mean() == pytest.approx(color.luminance(cool).mean(), rel=0.1)
    half, rec3 = rendered(scale=0.5)
    assert half.shape[:2] == (base.shape[0] // 2, base.shape[1] // 2)
    assert rec3["size"] == [half.shape[1], half.shape[0]]

    first, last = rec0["views"][0], rec0["views"][-1]
    render_run(run, RenderSettings(path="views", views=f"{first},{last}", n_frames=3,
                                   formats=("exr",)))
    views = json.loads((run / "render" / "views.json").read_text())
    np.testing.assert_allclose(image_io.read_exr(run / "render" / "views_000.exr"), base,
                               atol=1e-5)
    assert views["views"] == ["views_000", "views_001", "views_002"]


def test_cli_reports_bad_input_with_exit_status_2(tmp_path, capsys):
    from gridnerf.cli import main

    assert main(["train", str(tmp_path / "missing"), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "missing" in err and "Fix:" in err
    assert main(["eval", str(tmp_path / "norun")]) == 2
    assert "gridnerf train" in capsys.readouterr().err


def test_checkpoints_by_time_as_well_as_steps(small_scene, tmp_path, monkeypatch):
    from gridnerf import train as trainmod

    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", 1e-9)
    cfg = cfgmod.override(cfgmod.preset("tiny"), [
        "train.steps_per_stage=[20,20]", "train.checkpoint_every=1000"])
    run = tmp_path / "run"
    _crash_after(monkeypatch, 7)
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(small_scene, run, cfg)
    header = trainmod.load_state(run)[3]
    assert (header["stage"], header["step"]) == (0, 7)  # saved after every step by time
    assert not list(run.glob("*.tmp"))


def test_resolve_resolution_follows_the_aspect():
    from gridnerf.stages import resolve_resolution

    lo, hi = np.array([-1.25, -1.25, -0.5]), np.array([1.25, 1.25, 0.9])
    # 16:9 frame on the square NDC box: y voxels get the pixel footprint of x voxels
    assert resolve_resolution((97, 0, 32), lo, hi, (270, 480), True) == (97, 55, 32)
    # given counts are kept; a world box uses the ratio of its extents
    assert resolve_resolution((64, 40, 32), lo, hi, (270, 480), True) == (64, 40, 32)
    assert resolve_resolution((65, 0, 8), np.zeros(3), np.array([2.0, 1.0, 1.0]),
                              (270, 480), False) == (65, 33, 8)


def test_forward_facing_box_starts_at_the_near_bound():
    from types import SimpleNamespace

    from gridnerf.dataset import grid_box

    # normalised world: near = 1 / 0.75 -> ndc z = 1 - 2 / near = -0.5, ray t = 0.25
    scene = SimpleNamespace(forward_facing=True, near=1.0 / 0.75, far=12.0)
    lo, hi, near_t, far_t = grid_box(scene)
    assert lo[2] == pytest.approx(-0.5) and near_t == pytest.approx(0.25) and far_t == 1.0
    assert hi[2] == pytest.approx(1.0 - 2.0 / (1.25 * 12.0))
    # a near bound at the NDC near plane keeps the whole z range
    lo, _, near_t, _ = grid_box(SimpleNamespace(forward_facing=True, near=1.0, far=12.0))
    assert lo[2] == -1.0 and near_t == 0.0


def test_aspect_resolution_trains_and_resumes(small_scene, tmp_path, monkeypatch):
    """y = 0 stages: the y count follows the frame aspect and the fitted box, and a run
    interrupted inside such a stage resumes (the checkpoint's y is not compared)."""
    from gridnerf import stages
    from gridnerf import train as trainmod

    cfg = cfgmod.override(cfgmod.preset("tiny"), [
        "grid.resolutions=[[16,0,8],[24,0,12]]", "train.steps_per_stage=[10,10]",
        "train.checkpoint_every=5"])
    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", float("inf"))
    run = tmp_path / "run"
    real_make_step = optim.make_step
    _crash_after(monkeypatch, 17)  # dies in stage 1 after its step-5 checkpoint
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(small_scene, run, cfg)
    structure, _, _, header = trainmod.load_state(run)
    assert (header["stage"], header["step"]) == (1, 5)
    lo, hi = np.asarray(structure.bbox_min), np.asarray(structure.bbox_max)

    from gridnerf.scene import load_scene
    bounds = json.loads((run / "bounds.json").read_text())  # the run's own, estimated
    scene = load_scene(small_scene, near_far=(bounds["near"], bounds["far"]))
    h, w = scene.cameras.height // 2, scene.cameras.width // 2
    assert structure.resolution == stages.resolve_resolution(
        (24, 0, 12), lo, hi, (h, w), scene.forward_facing)
    monkeypatch.setattr(optim, "make_step", real_make_step)
    summary = trainmod.train(small_scene, run, cfg)
    assert summary["resolution"] == list(structure.resolution)
    assert summary["data_level"] == structure.color_scale > 0
    assert summary["data_noise"] > 0  # measured on the resume as on a fresh start
    assert summary["data_eps"] == min(cfg.loss.data_eps,
                                      cfg.loss.data_eps_sigmas * summary["data_noise"])


def load_state_of(run):
    from gridnerf.train import load_state

    return load_state(run)[0]


def test_stopped_before_the_first_checkpoint_starts_over(small_scene, tmp_path, monkeypatch):
    """A training stopped before any checkpoint leaves config.json and metrics.jsonl but
    nothing to resume: the next train starts over with its own config (the stale
    config.json is replaced, not obeyed) and metrics.jsonl holds only the new run's
    lines. A scene given as a relative path is saved absolute, so the run loads for
    eval from any folder."""
    from gridnerf import train as trainmod
    from gridnerf.eval_run import load_run

    # data.downscale=2: the plan's own for this grid, so the steps stay 8
    base = ["grid.resolutions=[[16,16,8]]", "train.steps_per_stage=[8]", "train.log_every=2",
            "train.checkpoint_every=1000", "data.downscale=2"]
    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", float("inf"))
    first = cfgmod.override(cfgmod.preset("tiny"), [*base, "train.batch_patches=4"])
    second = cfgmod.override(cfgmod.preset("tiny"), base)
    run = tmp_path / "run"
    monkeypatch.chdir(small_scene.parent)
    relative = small_scene.relative_to(small_scene.parent)
    real_make_step = optim.make_step
    _crash_after(monkeypatch, 5)  # logged steps 2 and 4, no checkpoint
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(relative, run, first)
    assert not (run / "checkpoint.npz").exists()
    assert cfgmod.load(run / "config.json") == first
    assert [r["step"] for r in _losses(run)] == [2, 4]
    monkeypatch.setattr(optim, "make_step", real_make_step)
    summary = trainmod.train(relative, run, second)
    assert cfgmod.load(run / "config.json") == second
    assert [r["step"] for r in _losses(run)] == [2, 4, 6, 8]
    assert summary["scene"] == str(small_scene.resolve())
    monkeypatch.chdir(tmp_path)
    _, _, scene, _, _, _ = load_run(run)
    assert len(scene.train_idx) > 0


def test_scene_illuminant_from_the_training_frames(small_scene):
    """loss.ca_target = "scene": one estimate from the binned training frames, near the
    simulator's light for grey world, on the locus when ca_locus (binned and mosaic data
    give the same estimate)."""
    from gridnerf import colour_target, dataset, illuminant
    from gridnerf.scene import load_scene

    sim = json.loads((small_scene / "sim.json").read_text())
    truth = np.asarray(sim["illuminant_neutral_cam"])
    scene = load_scene(small_scene, near_far=(1.0, 10.0))
    cfg = cfgmod.override(cfgmod.preset("tiny"), ["loss.ca_target=scene",
                                                  "loss.ca_illuminant=grey_world",
                                                  "loss.ca_locus=false"])

    def estimate(data, c):
        locus = illuminant.planckian_locus(scene.xyz_to_cam) if c.loss.ca_locus else None
        return colour_target.scene_illuminant(colour_target.estimate_frames(data, scene),
                                              "grey_world", 1, locus)

    binned = dataset.build(scene, scene.train_idx, True)
    est = estimate(binned, cfg)
    assert np.isfinite(est).all() and abs(np.linalg.norm(est) - 1) < 1e-9
    assert float(illuminant.angular_error_deg(est, truth)) < 15.0
    mosaic = dataset.build(scene, scene.train_idx, False)
    np.testing.assert_allclose(estimate(mosaic, cfg), est, atol=1e-6)
    on = cfgmod.override(cfg, ["loss.ca_locus=true"])
    locus = illuminant.planckian_locus(scene.xyz_to_cam)
    assert np.min(illuminant.angular_error_deg(estimate(binned, on), locus)) < 1e-6
    # the plan of the scene target: the anchor is this estimate, the field trains
    _, colour = colour_target.plan_colour(binned, scene, cfg)
    assert colour.model == "field" and colour.estimator == "grey_world"
    np.testing.assert_allclose(colour.anchor, est)


def test_opacity_prior_only_in_its_stages():
    """loss.opacity_stages = n: stages < n train with the prior, later ones without; 0 keeps
    it everywhere; a negative count is refused."""
    from gridnerf.errors import ConfigError
    from gridnerf.plan import opacity_schedule

    assert opacity_schedule(0.1, 3, 1) == (0.1, 0.0, 0.0)
    assert opacity_schedule(0.1, 3, 2) == (0.1, 0.1, 0.0)
    assert opacity_schedule(0.1, 3, 0) == (0.1, 0.1, 0.1)
    assert opacity_schedule(0.0, 2, 1) == (0.0, 0.0)
    cfg = cfgmod.preset("default")
    with pytest.raises(ConfigError, match="loss.opacity_stages"):
        cfgmod.override(cfg, ["loss.opacity_stages=-1"])


def test_consensus_needs_the_scene_target():
    from gridnerf.errors import ConfigError

    cfg = cfgmod.preset("default")
    assert cfg.loss.ca_illuminant == "consistent" and cfg.loss.ca_target == "map"
    assert cfgmod.override(cfg, ["loss.ca_target=scene"]).loss.ca_target == "scene"
    with pytest.raises(ConfigError, match="loss.ca_illuminant"):
        cfgmod.override(cfg, ["loss.ca_target=batch"])
    with pytest.raises(ConfigError, match="loss.ca_illuminant"):
        cfgmod.override(cfg, ["loss.ca_illuminant=consensus", "loss.ca_target=batch"])
    batch = cfgmod.override(cfg, ["loss.ca_illuminant=grey_world", "loss.ca_target=batch"])
    assert batch.loss.ca_target == "batch"
    with pytest.raises(ConfigError, match="loss.gain_model"):
        cfgmod.override(batch, ["loss.gain_model=auto"])


def test_illuminant_map_target_trains(small_scene, tmp_path):
    """loss.ca_target = "map": the per-frame map rides in the data, every batch carries each
    ray's block of it, training runs and stays finite; the step refuses data without it."""
    import jax

    from gridnerf import colour_target, dataset, train
    from gridnerf.scene import load_scene

    cfg = cfgmod.override(cfgmod.preset("tiny"), ["loss.ca_target=map"])
    scene = load_scene(small_scene, near_far=(1.0, 10.0))
    data = dataset.build(scene, scene.train_idx, True)
    frames = colour_target.estimate_frames(data, scene)
    anchor = colour_target.scene_illuminant(frames, "grey_edge")
    mapped, kept = colour_target.with_illuminant_map(data, frames, "grey_edge", anchor=anchor)
    np.testing.assert_array_equal(kept, anchor)  # a resumed run's anchor is kept
    h, w = data.image_hw
    block = colour_target.MAP_BLOCK
    assert mapped.illuminant_map.shape == (len(scene.train_idx), h // block, w // block, 3)
    _, found = colour_target.with_illuminant_map(data, frames, "grey_edge")
    assert found.shape == (3,) and np.all(np.isfinite(found))
    rays = dataset.batch(mapped, jax.random.PRNGKey(0), 4, 8)
    assert rays["illuminant"].shape == (4, 8, 8, 3)
    summary = train.train(small_scene, tmp_path / "run", cfg)
    assert np.isfinite(summary["train_seconds"])
    recs = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["ca"]) for r in recs)
    with pytest.raises(ValueError, match="illuminant map"):
        optim.loss_fn(*_loss_args(cfg, data, scene))


def _loss_args(cfg, data, scene):
    import jax

    from gridnerf import dataset, grid

    lo, hi, near_t, far_t = dataset.grid_box(scene)
    structure, params = grid.init_grid((8, 8, 8), lo, hi)
    rays = dataset.batch(data, jax.random.PRNGKey(0), 2, 4)
    from gridnerf.plan import StepPlan

    step = StepPlan(data_eps=1e-3, opacity=0.1, n_candidates=0, train_gains=True,
                    anchor=np.ones(3, np.float32))
    return params, structure, rays, jax.random.PRNGKey(1), cfg, step, near_t, far_t


def test_dark_frame_black_level_trains_resumes_and_reaches_eval(small_scene, tmp_path,
                                                                monkeypatch):
    """data.black_offset = "dark": measured once before training (black_level.json, in the
    summary), not measured again on resume, and the evaluation's scene carries it."""
    from gridnerf import darkframes
    from gridnerf import train as trainmod
    from gridnerf.eval_run import load_run

    cfg = cfgmod.override(cfgmod.preset("tiny"), [
        "data.black_offset=dark", "train.steps_per_stage=[20,20]", "train.checkpoint_every=10"])
    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", float("inf"))
    run = tmp_path / "run"
    real_make_step = optim.make_step
    _crash_after(monkeypatch, 33)
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(small_scene, run, cfg)
    offset = darkframes.load(run)
    truth = json.loads((small_scene / "sim.json").read_text())["noise"][
        "black_bias_dn_per_cfa_position"]
    np.testing.assert_allclose(offset, truth, atol=0.4)
    monkeypatch.setattr(optim, "make_step", real_make_step)
    monkeypatch.setattr(darkframes, "measure", lambda *a, **k: pytest.fail("measured twice"))
    summary = trainmod.train(small_scene, run, cfg)
    np.testing.assert_array_equal(summary["black_offset_dn"], offset)
    plan, scene = load_run(run)[1:3]
    assert plan.black_level == "lens_cap"
    file_black = scene.black_level - offset.astype(np.float32)[None]
    np.testing.assert_allclose(file_black, 512.0, atol=1e-3)  # the DNG's tag, plus offset


def test_fitted_candidates_render_the_training_rays_unchanged(tiny_run):
    """stages.fitted_candidates: fewer candidates than the box diagonal on a forward-facing
    grid, and every training batch ray gets the very same samples and colour; the run plan
    keeps the count of its last stage."""
    import jax

    from gridnerf import dataset, eval_run, render
    from gridnerf.stages import fitted_candidates

    cfg, plan, scene, structure, params, _ = eval_run.load_run(tiny_run[0])
    data = dataset.training_data(scene, cfg.data)
    near_t, far_t = dataset.grid_box(scene)[2:]
    n_fit = fitted_candidates(structure, data, near_t, far_t, cfg.render)
    assert 0 < n_fit < render.n_candidates(structure, cfg.render)
    assert plan.n_candidates[-1] == n_fit and all(n > 0 for n in plan.n_candidates)
    rays = dataset.batch(data, jax.random.PRNGKey(3), 16, 8)
    key = jax.random.PRNGKey(4)
    o, d = (rays[k].reshape(-1, 3) for k in ("origins", "directions"))
    outs = [render.render_rays(structure, params, o, d, near_t, far_t, cfg.render, key=key,
                               n_cand=n) for n in (0, n_fit)]
    for name in ("rgb_low", "acc", "depth"):
        np.testing.assert_allclose(np.asarray(outs[0][name]), np.asarray(outs[1][name]),
                                   rtol=1e-5, atol=1e-7)


def test_data_eps_note_only_where_the_absolute_eps_exceeds_the_noise():
    """data_term.data_eps_note on the steps' config: silent at the simulator's noise (absolute
    eps 0.86-1.44 sigma at gamma 1), with the level eps and under the default cap; past 2.5
    sigma (the cap off) it names the ratio and the fix."""

    cfg = cfgmod.override(cfgmod.Config(), ["loss.data_eps_sigmas=0"])

    def note(c, sigma):
        raw = c.data.target == "raw"  # the method's fits_raw
        return data_term.data_eps_note(data_term.capped_eps(c, sigma, raw), sigma, raw)

    assert note(cfg, 0.00074) is None  # bucket at gamma 1: 1.35 sigma
    assert note(cfg, 0.6 * 0.00074) is None  # gamma 0.6: 2.25 sigma
    text = note(cfg, 0.4 * 0.00074)  # gamma 0.4: 3.4 sigma
    assert text is not None and "3.4x" in text and "loss.data_eps_sigmas=2" in text
    assert note(cfg, float("nan")) is None  # no neighbours to measure
    assert note(cfg, 0.0) is None  # noiseless frames: nothing to compare
    assert note(cfgmod.override(cfg, ["data.target=processed"]), 0.1 * 0.00074) is None
    # the cap: the steps' eps is 2 sigma, below the note's 2.5
    assert note(cfgmod.Config(), 0.1 * 0.00074) is None


def test_data_eps_cap_binds_only_on_darker_raw_frames():
    """data_term.capped_eps: RawNeRF's 1e-3 is kept where it is under 2 noise sigmas (the
    simulated scenes at gamma 1); below, the eps is 2 sigma; non-raw targets, the llnerf
    method, a cap of 0 and an unmeasured or zero sigma are left alone."""

    cfg = cfgmod.Config()
    assert data_term.capped_eps(cfg, 0.00074) == cfg.loss.data_eps  # 1.35 sigma
    assert data_term.capped_eps(cfg, 0.1 * 0.00074) == pytest.approx(2 * 0.1 * 0.00074)
    three = cfgmod.override(cfg, ["loss.data_eps_sigmas=3"])
    assert data_term.capped_eps(three, 1e-4) == pytest.approx(3e-4)
    from gridnerf import methods

    for sets in (["data.target=processed"], ["loss.data_eps_sigmas=0"], ["loss.method=llnerf"]):
        other = cfgmod.override(cfg, sets)
        raw = methods.get(other.loss.method).fits_raw(other)
        assert data_term.capped_eps(other, 1e-5, raw) == other.loss.data_eps, sets
    for sigma in (0.0, float("nan")):
        assert data_term.capped_eps(cfg, sigma) == cfg.loss.data_eps


def test_capped_data_term_is_the_same_at_every_gamma():
    """The data term with the capped eps depends on eps / sigma alone: frames, render and
    noise scaled by gamma (data.exposure_ratio's protocol) give the same loss wherever the
    cap binds, and the uncapped absolute eps does not."""
    import jax.numpy as jnp

    from gridnerf import losses

    rng = np.random.default_rng(1)
    render = jnp.asarray(0.002 + 0.002 * rng.random((256, 3)), jnp.float32)
    sigma = 8e-4
    target = render + sigma * jnp.asarray(rng.standard_normal((256, 3)), jnp.float32)
    mask = jnp.ones((256, 3), jnp.float32)
    cfg = cfgmod.Config()

    def loss(gamma, c):
        eps = data_term.capped_eps(c, gamma * sigma)
        return float(losses.data_loss(gamma * render, gamma * target, mask, eps))

    assert loss(0.1, cfg) == pytest.approx(loss(0.3, cfg), rel=1e-4)  # both capped
    off = cfgmod.override(cfg, ["loss.data_eps_sigmas=0"])
    assert abs(loss(0.1, off) / loss(0.3, off) - 1.0) > 0.1


def test_data_noise_measures_the_frames_noise_and_scales_with_them(small_scene):
    """data_term.data_noise on ray data whose frames are smooth shading plus Gaussian noise of
    known sigma: within 5 %; the frames scaled by gamma (data.exposure_ratio's protocol)
    give gamma x sigma; a saturated (masked) half changes nothing."""
    import jax
    from conftest import sim_near_far

    from gridnerf import dataset
    from gridnerf.scene import load_scene

    scene = load_scene(small_scene, near_far=sim_near_far(small_scene))
    data = dataset.build(scene, scene.train_idx[:3], binning=True)
    n, h, w, _ = data.pixels.shape
    yy, xx = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    shading = 0.003 * (1.0 + 0.5 * np.sin(3 * xx + 2 * yy))[None, :, :, None]
    sigma = 8e-4
    noisy = shading + sigma * np.random.default_rng(0).standard_normal((n, h, w, 3))

    def with_frames(frames, valid=None):
        return replace(data, pixels=jax.numpy.asarray(frames, np.float32),
                       valid=jax.numpy.ones((n, h, w, 3), bool) if valid is None else valid,
                       inv_exposure=jax.numpy.ones((n,), np.float32))

    key = jax.random.PRNGKey(0)
    got = data_term.data_noise(with_frames(noisy), key)
    assert abs(got / sigma - 1.0) < 0.05
    np.testing.assert_allclose(data_term.data_noise(with_frames(0.1 * noisy), key), 0.1 * got,
                               rtol=1e-4)
    clipped = noisy.copy()
    clipped[:, :, : w // 2] = 1.0  # saturated: masked out, and no noise to measure there
    valid = np.ones((n, h, w, 3), bool)
    valid[:, :, : w // 2] = False
    assert abs(data_term.data_noise(with_frames(clipped, valid), key) / sigma - 1.0) < 0.05


def test_the_summary_says_which_colour_was_shipped(tiny_run):
    """The end-of-training check ran: summary.json names the colour shipped and how far the
    field's white lay from the frames' nearest estimate."""
    run, cfg, summary = tiny_run
    record = summary["colour"]
    assert record["shipped"] in ("field", "one_gain")
    if cfg.loss.gain_model == "field":
        assert np.isfinite(record["distance"]) and record["nearest"]
    plan = json.loads((run / "plan.json").read_text())
    assert set(plan["colour"]["evidence"]) >= {"grey_world", "shades_of_grey", "grey_edge"}
    assert (plan["colour"]["shipped_gains"] is None) == (record["shipped"] == "field")


def test_eval_without_references_writes_the_renders_and_says_so(tiny_run, tmp_path, capsys):
    """A capture with no gt/ (raw files only): eval writes the test renders, scores nothing
    and says why instead of failing."""
    import shutil

    from gridnerf.eval_run import evaluate_run

    run, _, summary = tiny_run
    scene = tmp_path / "scene"
    shutil.copytree(summary["scene"], scene, ignore=shutil.ignore_patterns("gt"))
    copy = tmp_path / "run"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("eval", "render"))
    meta = json.loads((copy / "summary.json").read_text())
    (copy / "summary.json").write_text(json.dumps({**meta, "scene": str(scene)}))
    metrics = evaluate_run(copy)
    assert metrics["summary"] == {}
    assert "nothing to score against" in capsys.readouterr().out
    for name in metrics["test_views"]:
        assert (copy / "eval" / f"{name}_pred.png").exists()
        assert (copy / "eval" / f"{name}_pred.exr").exists()


def test_fitted_samples_follow_the_rays_occupied_samples(tiny_run):
    """stages.fitted_samples: truncated_share 0 gives max_samples (capped by the candidate
    count); a share keeps at most that share of the marched training rays above K, K a
    multiple of SAMPLE_QUANTUM that never exceeds max_samples, and a smaller share never a
    smaller K. The run plan and the finished run's render config carry the slots (the tiny
    preset fits none: its plan holds its own max_samples)."""
    import jax

    from gridnerf import dataset, eval_run, render, stages
    from gridnerf import plan as planmod

    cfg, plan, scene, structure, params, _ = eval_run.load_run(tiny_run[0])
    assert cfg.render.truncated_share == 0.0
    assert plan.max_samples == (cfg.render.max_samples,) * len(plan.n_candidates)
    data = dataset.training_data(scene, cfg.data)
    near_t, far_t = dataset.grid_box(scene)[2:]
    n_cand = plan.n_candidates[-1]
    assert stages.fitted_samples(structure, data, near_t, far_t, cfg.render,
                                 n_cand) == cfg.render.max_samples
    march = jax.jit(render.march, static_argnames=("cfg", "n_cand"))
    occupied = np.concatenate([
        np.asarray(march(structure, o, d, near_t, far_t, cfg.render, n_cand=n_cand)[3])[:n]
        for o, d, n in stages.training_rays(data, 4096, stride=stages.SAMPLE_STRIDE)])
    ks = []
    for share in (0.2, 0.05, 0.005):
        rc = cfgmod.override(cfg, ["render.max_samples=64",
                                   f"render.truncated_share={share}"]).render
        k = stages.fitted_samples(structure, data, near_t, far_t, rc, n_cand)
        assert k % stages.SAMPLE_QUANTUM == 0 and 1 <= k <= 64
        assert np.mean(occupied > k) <= share
        ks.append(k)
    assert ks == sorted(ks) and ks[0] < ks[-1]  # a smaller share, more slots
    fitted = plan.with_samples(len(plan.n_candidates) - 1, 8)
    assert planmod.render_config(cfg, fitted).render.max_samples == 8
    assert planmod.from_dict(planmod.to_dict(fitted)) == fitted
    old = planmod.from_dict({**planmod.to_dict(plan), "max_samples": None})  # an older plan
    assert old.samples(0, cfg) == cfg.render.max_samples
    assert planmod.render_config(cfg, old) == cfg


def test_a_run_keeps_its_fitted_slots_and_renders_with_them(small_scene, tmp_path, capsys):
    """With render.truncated_share > 0 every stage fits its slots (stages.fitted_samples),
    prints them and keeps them in plan.json; the finished run's config (eval_run.load_run)
    renders with its last stage's."""
    from gridnerf import eval_run
    from gridnerf import plan as planmod
    from gridnerf.train import train

    cfg = cfgmod.override(cfgmod.preset("tiny"), ["render.truncated_share=0.05",
                                                  "render.max_samples=32"])
    train(small_scene, tmp_path / "run", cfg)
    plan = planmod.load(tmp_path / "run")
    assert plan.max_samples is not None and len(plan.max_samples) == len(plan.n_candidates)
    assert all(1 <= k <= 32 and k % 8 == 0 for k in plan.max_samples)
    assert "occupied samples per ray" in capsys.readouterr().out
    loaded = eval_run.load_run(tmp_path / "run")[0]
    assert loaded.render.max_samples == plan.max_samples[-1]
    assert loaded.render.truncated_share == 0.05


def test_a_run_refines_its_last_stage_where_the_reading_asks_and_resumes_it(
        small_scene, tmp_path, capsys, monkeypatch):
    """With grid.detail_width set a run reads the detail before its last stage
    (gridnerf.residual), keeps it in the plan and the summary and, over residual.ABOVE,
    trains that stage wider; killed in that stage, it resumes it at the plan's width without
    reading again. Under the threshold it keeps the config's width, and its checkpoint is the
    one a run without the option trains (the reading draws no random numbers)."""
    from gridnerf import plan as planmod
    from gridnerf import train as trainmod

    monkeypatch.setattr(trainmod, "CHECKPOINT_SECONDS", float("inf"))
    sets = ["data.mosaic_stages=1", "train.steps_per_stage=[20,20]",
            "train.checkpoint_every=10"]
    from gridnerf import residual

    wide = cfgmod.override(cfgmod.preset("tiny"), [*sets, "grid.detail_width=56"])
    monkeypatch.setattr(residual, "ABOVE", -1e9)
    real_make_step = optim.make_step
    _crash_after(monkeypatch, 33)  # dies at stage 1 step 14, after its step-10 checkpoint
    with pytest.raises(KeyboardInterrupt):
        trainmod.train(small_scene, tmp_path / "wide", wide)
    assert "the last stage is 56 wide instead of 40" in capsys.readouterr().out
    plan = planmod.load(tmp_path / "wide")
    assert plan.last_width == 56 and plan.detail is not None and np.isfinite(plan.detail)
    assert 0 < plan.detail_error < plan.detail
    monkeypatch.setattr(optim, "make_step", real_make_step)
    summary = trainmod.train(small_scene, tmp_path / "wide", wide)
    out = capsys.readouterr().out
    assert "resuming" in out and "detail:" not in out
    assert summary["last_width"] == 56 and summary["detail"] == plan.detail
    assert load_state_of(tmp_path / "wide").resolution[0] == 56

    monkeypatch.setattr(residual, "ABOVE", 1e9)
    summary = trainmod.train(small_scene, tmp_path / "narrow", wide)
    assert summary["last_width"] == 40 and summary["detail"] == pytest.approx(plan.detail)
    assert planmod.load(tmp_path / "narrow").last_width is None
    trainmod.train(small_scene, tmp_path / "plain", cfgmod.override(cfgmod.preset("tiny"), sets))
    a, b = (np.load(tmp_path / name / "checkpoint.npz") for name in ("narrow", "plain"))
    assert sorted(a.files) == sorted(b.files)
    for name in a.files:
        if name != "header":
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_the_views_agree_on_no_detail_where_the_frames_are_the_render_and_noise(tiny_run):
    """residual.read_views on the tiny run: finite on its own frames; with each frame
    replaced by the field's own render plus independent noise the views share nothing, so
    the reading is 0 within a few of its errors (the noise a tenth of the signal), for
    consecutive views and for views two apart; with no pair at that gap it is nan."""
    import jax.numpy as jnp

    from gridnerf import dataset, eval_run, methods, render, residual

    run, _, _ = tiny_run
    cfg, _, scene, structure, params, _ = eval_run.load_run(run)
    data = methods.get(cfg.loss.method).training_data(scene, cfg)
    near_t, far_t = dataset.grid_box(scene)[2:]
    value, error = residual.read_views(structure, params, data, near_t, far_t, cfg.render,
                                       every=2)
    assert np.isfinite(value) and error > 0
    n, (h, w) = data.c2w.shape[0], data.image_hw
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    frames = []
    for f in range(n):
        rays = dataset.rays_at_jit(data, jnp.full((h, w), f), jnp.asarray(v), jnp.asarray(u))
        frames.append(render.render_image(structure, params, rays["origins"],
                                          rays["directions"], near_t, far_t,
                                          cfg.render)["rgb_low"])
    clean = np.stack(frames) / np.asarray(data.inv_exposure)[:, None, None, None]
    noisy = clean + np.random.default_rng(0).normal(0, 0.1 * clean.mean(), clean.shape)
    data = replace(data, pixels=jnp.asarray(noisy, jnp.float32),
                   valid=jnp.ones(noisy.shape, bool))
    value, error = residual.read_views(structure, params, data, near_t, far_t, cfg.render,
                                       every=2)
    assert abs(value) < 4 * error
    # views two apart share no noise either; a gap past the last frame pairs nothing
    value, error = residual.read_views(structure, params, data, near_t, far_t, cfg.render,
                                       every=2, gap=2)
    assert np.isfinite(value) and abs(value) < 4 * error
    assert np.isnan(residual.read_views(structure, params, data, near_t, far_t, cfg.render,
                                        gap=n)[0])
    with pytest.raises(ValueError, match="gap"):
        residual.read_views(structure, params, data, near_t, far_t, cfg.render, gap=0)


def test_carving_marches_as_many_rays_a_frame_on_any_capture():
    """The carving's stride is the one it was set with on a 480-pixel-wide capture, binned
    or on its mosaic, and grows with the frames, so that a 1920x1080 capture (or one
    downscaled) is carved by the same rays per frame."""
    assert stages.carving_stride(240, mosaic=False) == stages.CARVE_STRIDE == 2
    assert stages.carving_stride(480, mosaic=True) == 2
    assert stages.carving_stride(32, mosaic=False) == 2  # never below it
    assert stages.carving_stride(960, mosaic=False) == 8  # 1920x1080 binned
    assert stages.carving_stride(480, mosaic=False) == 4  # ... and downscaled by 2
    for width, mosaic in ((640, False), (1920, True), (3000, False)):
        rays = width / stages.carving_stride(width, mosaic)
        assert rays == pytest.approx((240 if mosaic else 120), rel=0.25)
