"""Where the dB go: an error budget per simulated scene, and its noise-limited bound.

Four fits of the same default grid, test views, PSNR (dB):

- oracle: trained on the clean normal-light references (the `oracle` preset): what the
  grid holds;
- clean raw, true white: trained on the capture's exact noise-free raw
  (data.target=clean: binned, then the mosaic in the last stage, as the default fits
  the capture) through the method's own colour path, the L_ca anchor the simulator's
  light (`--white-ref rgb:...`): representation and colour pipeline;
- noisy raw, true white: the capture itself (the default's data term: the mosaic in the
  last stage), the same anchor: what the noise costs, the same data path as the clean;
- default: the capture, the light estimated from the frames.

The gaps telescope, so every dB between the oracle and the default is assigned:
pipeline = oracle - clean, noise = clean - noisy, white = noisy - default.

The noise-limited bound: the oracle's squared error plus the variance an ideal average
of the training views would leave in each test pixel (sim.json's noise model: K and the
read variance in DN, per raw pixel K x signal + read; the binned block's variance (the
greens averaged) of the clean raw, divided by the number of training views (every view
taken to see every pixel: an optimistic bound), carried to the reference's display
space by the 3x3 map fitted from the clean binned raw to the reference, and to sRGB by
the encoding's slope; the same crop as the metrics). Single-light scenes only, procedural
or path-traced (their clean raw is rebuilt from the reference: truth.clean_cam).

The colour path's own ceiling, no reconstruction at all: the clean binned raw of each
test view against its binned reference, through the best 3x3 map any raw pipeline could
apply (least squares per view: what the camera's response allows) and through the
method's own output path (the true white's von Kries gains, the file's colour matrix,
exposure matched to the reference); and the same output path on the clean camera RGB at
every photosite (truth.clean_cam: no colour filter array, no binning), the colour path's
ceiling at the capture's own resolution.

Two columns split the default's own gap with no further training (its test renders in
<runs>/<scene>/default/eval, best_map_psnr): "default, best white" is its render with the
white and exposure that fit the reference best (a von Kries diagonal in balanced camera
RGB, before the output matrix), "default, best 3x3" with the best 3x3 map of its camera
RGB. The gaps telescope: fit = oracle - best 3x3 (noise, footprint, representation),
output matrix = best 3x3 - best white (what the file's matrix after von Kries gains cannot
show), white & exposure = best white - default. The clean fit's renders re-shown the same
way ("clean raw, best 3x3") split the fit: representation = oracle - the clean fit's best
3x3, noise = the clean fit's best 3x3 - the default's.

A fifth fit splits the representation: the clean raw with the true white and the data
term's eps at 1e-5 (loss.data_eps; the default's 1e-3 is about one noise sigma of the
frames, data_term.capped_eps, and the relative loss (C - y)^2 / (sg(C) + eps)^2 weighs a
pixel darker than eps as if it were eps bright: a floor the noise sets, since the fit needs
it on noisy frames). 1e-5 is about the share of the clean raw's level that the oracle's
1e-3 is of the references' (mean luminance 0.18). Re-shown by its best 3x3: "representation:
eps" = its best 3x3 - the clean fit's, what the noise's floor costs the noise-free fit;
"representation: grid" = oracle - its best 3x3, what is left to the grid and the camera's
data path.

A last table sets the default against the noise in the raw itself (raw_discrepancy): its
error per photosite in units of one frame's noise variance, beside 1 / the number of
training views (what an ideal average leaves), and its residual on the training and the
test frames (under 1 on the training frames: noise taken for detail). It needs the run
folders; the rows of other scenes stay as recorded in <out>.json.

    python -m experiments.error_budget [--scenes nine,dev,heldout] [--runs runs]
    python -m experiments.error_budget --no-train   # no training: the fits already there
    python -m experiments.error_budget --train clean   # train only the missing clean fits
    python -m experiments.error_budget --train clean_eps --scenes nine
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.optimize import least_squares

from experiments.common import (
    GROUPS,
    RESULTS_DOC,
    cached_result,
    fingerprint,
    markdown_table,
    run_variant,
    scene_dir,
    scene_names,
    study_parser,
    update_doc,
    write_report,
)
from gridnerf import atomic, dataset, exposure, illuminant, image_io, plan, raw
from gridnerf import config as cfgmod
from gridnerf.color import srgb_encode
from gridnerf.eval_run import load_run, render_view
from gridnerf.evaluate import effective_crop, image_metrics
from gridnerf.scene import load_scene
from gridnerf.sim import sensor, truth

CROP = 16  # the metrics' border crop (evaluate.image_metrics)
# the ceilings (no reconstruction) and the fits: (record key, column heading)
CEILINGS = (("noise_only", "noise alone"), ("bound", "noise bound"),
            ("best_3x3", "colour: best 3x3"), ("path", "colour: output path"),
            ("best_3x3_full", "colour: best 3x3, full res"),
            ("path_full", "colour: output path, full res"), ("one_frame_nlm", "one frame + NLM"))
COLUMNS = (("oracle", "oracle"), ("clean", "clean raw, true white"),
           ("clean_best_map", "clean raw, best 3x3"),
           ("clean_eps_best_map", "clean raw, eps 1e-5, best 3x3"),
           ("noisy", "noisy raw, true white"),
           ("default", "default"), ("best_white", "default, best white"),
           ("best_map", "default, best 3x3"))


def srgb_slope(x: np.ndarray) -> np.ndarray:
    """d srgb_encode / dx of linear values (clipped to [0, 1] as the metrics clip)."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92, 1.055 / 2.4 * np.maximum(x, 1e-6) ** (1 / 2.4 - 1))


def per_view(folder: Path, scene) -> dict[str, list[float]]:
    """Per test view (module docstring): "noise_mse", the sRGB mean squared error an ideal
    average of the training views' noise would leave; "best_3x3" and "path", the PSNR of
    the clean binned raw through the best 3x3 map and through the output path;
    "path_full" and "best_3x3_full", the clean camera RGB at every photosite through the
    output path and through the best 3x3 map (what the camera's colours allow at all).
    scene: the folder's loaded scene."""
    sim = json.loads((folder / "sim.json").read_text())
    nt = truth.noise_truth(sim)
    mean, cam_full = truth.clean_mean(folder), truth.clean_cam(folder)
    views = len(scene.train_idx)
    light = np.asarray(sim["illuminant_neutral_cam"], np.float64)
    gains = np.asarray(illuminant.gains_from_illuminant(light / np.linalg.norm(light)))
    matrix = exposure.display_matrix(scene.xyz_to_cam, True)
    out = {"noise_mse": [], "best_3x3": [], "path": [], "path_full": [], "best_3x3_full": []}
    for i in scene.test_idx:
        name = scene.names[i]
        clean = mean(name)  # (H, W) normalised raw
        cam = raw.bin2x2(clean, scene.cfa, np.float64)
        var = truth.binned_noise_var(nt, clean, scene.cfa)
        gt = image_io.read_exr(scene.gt_linear_paths[name]).astype(np.float64)
        h2, w2 = cam.shape[:2]
        gt_b = raw.downscale(gt[: 2 * h2, : 2 * w2], 2)
        t, *_ = np.linalg.lstsq(cam.reshape(-1, 3), gt_b.reshape(-1, 3), rcond=None)
        var_disp = (var.reshape(-1, 3) @ (t**2)).reshape(h2, w2, 3) / views
        var_full = np.repeat(np.repeat(var_disp, 2, 0), 2, 1)
        g = gt[: 2 * h2, : 2 * w2]
        c = effective_crop(*g.shape[:2], CROP)
        sl = (slice(c, g.shape[0] - c), slice(c, g.shape[1] - c))
        out["noise_mse"].append(float(np.mean(srgb_slope(g[sl]) ** 2 * var_full[sl])))
        crop = CROP // 2  # the binned frame's
        out["best_3x3"].append(image_metrics(cam @ t, gt_b, crop)["psnr"])
        out["path"].append(image_metrics(exposed((cam * gains) @ matrix.T, gt_b), gt_b,
                                         crop)["psnr"])
        full_cam = cam_full(name).astype(np.float64)
        full = (full_cam * gains) @ matrix.T
        out["path_full"].append(image_metrics(exposed(full, gt), gt, CROP)["psnr"])
        out["best_3x3_full"].append(best_map_psnr(full_cam, gt, matrix, full=True))
    return out


def exposed(rgb_linear: np.ndarray, ref_linear: np.ndarray) -> np.ndarray:
    """rgb_linear times the one scale that fits ref_linear best (least squares)."""
    return rgb_linear * (np.sum(rgb_linear * ref_linear) / np.sum(rgb_linear * rgb_linear))


def best_map_psnr(pred_linear: np.ndarray, gt_linear: np.ndarray, matrix: np.ndarray,
                  full: bool = False) -> float:
    """PSNR of a rendered view (linear sRGB, shown through `matrix` (3, 3) from balanced
    camera RGB) re-shown by the map that fits the reference best, the metric's own error
    minimised (sRGB, clipped, on its crop; scipy's least_squares from the linear
    least-squares map and from the render as it is):

    full=False: a von Kries diagonal d (3,) on the balanced camera RGB (pred @
      inv(matrix).T) before `matrix`: the best white and exposure for this output path;
    full=True: any 3x3 map of the camera RGB (the output matrix's error removed too).
    The render as it is lies in both families, so neither is below its PSNR.
    """
    c = effective_crop(*gt_linear.shape[:2], CROP)
    crop = (slice(c, gt_linear.shape[0] - c), slice(c, gt_linear.shape[1] - c))
    gt = gt_linear[crop].reshape(-1, 3)
    gt_srgb = srgb_encode(np.clip(gt, 0.0, 1.0))
    if full:
        x = pred_linear[crop].reshape(-1, 3)

        def shown(p):
            return x @ p.reshape(3, 3).T
        start = np.eye(3).reshape(-1)
        linear = np.linalg.lstsq(x, gt, rcond=None)[0].T.reshape(-1)
    else:
        bal = pred_linear[crop].reshape(-1, 3) @ np.linalg.inv(matrix).T
        design = np.stack([np.outer(bal[:, k], matrix[:, k]).reshape(-1) for k in range(3)], 1)

        def shown(p):
            return (bal * p) @ matrix.T
        start = np.ones(3)
        linear, *_ = np.linalg.lstsq(design, gt.reshape(-1), rcond=None)

    def residual(p):
        return (srgb_encode(np.clip(shown(p), 0.0, 1.0)) - gt_srgb).reshape(-1)

    best = min([least_squares(residual, p0).x for p0 in (linear, start)] + [start],
               key=lambda p: float(np.sum(residual(p) ** 2)))
    return image_metrics(shown(best).reshape(gt_linear[crop].shape), gt_linear[crop],
                         0)["psnr"]


DETAIL_SIGMA = 1.0  # px: the Gaussian that leaves out the detail finer than about 2 pixels
LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luma weights: an error's grey part


def by_scale(pred_linear: np.ndarray, gt_linear: np.ndarray) -> dict[str, float]:
    """A render's error split by scale, in sRGB (srgb_encode of the clipped linear images,
    as the metrics compare), on the metrics' crop:

    "coarse": the PSNR after render and reference are both blurred by a Gaussian of
      DETAIL_SIGMA pixels (the error at scales above about two pixels: colour, exposure,
      low-frequency noise, misplaced geometry);
    "detail_kept": the render's detail (its image minus its blur) as a share of the
      reference's, in RMS amplitude: 1 where the render holds the reference's fine
      detail, near 0 where it is blurred (noise adds to it too: read it with the PSNR);
    "chroma_share": the share of the squared error that is colour, not grey: the error
      less its Rec. 709 luma-weighted grey (LUMA) at each pixel.
    pred_linear, gt_linear: (H, W, 3) linear sRGB."""
    c = effective_crop(*gt_linear.shape[:2], CROP)
    crop = (slice(c, gt_linear.shape[0] - c), slice(c, gt_linear.shape[1] - c))
    pred, gt = (srgb_encode(np.clip(np.asarray(x, np.float64), 0.0, 1.0))
                for x in (pred_linear, gt_linear))
    blur_pred, blur_gt = (gaussian_filter(x, (DETAIL_SIGMA, DETAIL_SIGMA, 0)) for x in (pred, gt))
    mse = float(np.mean((blur_pred[crop] - blur_gt[crop]) ** 2))
    detail_gt = float(np.mean((gt - blur_gt)[crop] ** 2))
    detail_pred = float(np.mean((pred - blur_pred)[crop] ** 2))
    err = (pred - gt)[crop]
    grey = err @ LUMA  # the error's grey part; the rest is its colour
    total = float(np.mean(err**2))
    return {"coarse": -10.0 * np.log10(max(mse, 1e-20)),
            "detail_kept": float(np.sqrt(detail_pred / max(detail_gt, 1e-20))),
            "chroma_share": float(np.mean((err - grey[..., None]) ** 2)) / max(total, 1e-20)}


def best_maps(scene, run: Path) -> dict[str, float]:
    """Means over the test views of a loaded scene of best_map_psnr on a run's
    renders (<run>/eval/<view>_pred.exr, the shipped "gridnerf" output: the colour matrix
    the run took as the sensor's, ColourPlan.sensor_matrix): "best_white" (the diagonal)
    and "best_map" (any 3x3), and of by_scale ("coarse", "detail_kept", "chroma_share");
    empty where a render is missing."""
    matrix = exposure.display_matrix(plan.load(run).colour.sensor_matrix(scene.xyz_to_cam),
                                     True)
    out = {"best_white": [], "best_map": [], "coarse": [], "detail_kept": [], "chroma_share": []}
    for i in scene.test_idx:
        pred = run / "eval" / f"{scene.names[i]}_pred.exr"
        if not pred.is_file():
            return {}
        gt = image_io.read_exr(scene.gt_linear_paths[scene.names[i]]).astype(np.float64)
        pred = image_io.read_exr(pred).astype(np.float64)
        out["best_white"].append(best_map_psnr(pred, gt, matrix))
        out["best_map"].append(best_map_psnr(pred, gt, matrix, full=True))
        for k, v in by_scale(pred, gt).items():
            out[k].append(v)
    return {k: float(np.mean(v)) for k, v in out.items()}


def raw_discrepancy(run: Path, every: int = 4) -> dict[str, float]:
    """A fit against the noise in the raw, photosite by photosite, in units of one frame's
    noise variance there (sim.json's noise model at the clean mean: truth.noise_truth,
    truth.clean_mean): "train", the mean of (render - frame)^2 / variance over every
    `every`-th training view; "test", the same over the test views; "error", (render -
    clean)^2 / variance over the test views, the fit's own error. A train value under 1 is
    a fit of the noise (the discrepancy principle: a fit that explains its frames better
    than their noise allows has taken noise for detail). Empty where the run folder is
    missing or the capture has lens falloff or exposure jitter (the render is not then the
    frame's mean photosite for photosite)."""
    if not (run / "summary.json").is_file():
        return {}
    cfg, _, scene, structure, params, _ = load_run(run)
    sim = json.loads((scene.path / "sim.json").read_text())
    if sim.get("vignetting") or sim.get("exposure_jitter"):
        return {}
    nt, mean = truth.noise_truth(sim), truth.clean_mean(scene.path)
    cams = scene.cameras
    h, w = cams.height, cams.width
    sl = (slice(CROP, h - CROP), slice(CROP, w - CROP))
    out: dict[str, list[float]] = {"train": [], "test": [], "error": []}
    for split, views in (("train", list(scene.train_idx)[::every]), ("test", scene.test_idx)):
        for i in views:
            rgb_low = render_view(structure, params, scene, cfg, cams.c2w[i],
                                  cams.intrinsics(i), h, w)["rgb_low"]
            pred = sensor.mosaic(np.asarray(rgb_low, np.float64), scene.cfa)
            clean = mean(scene.names[i])
            var = truth.raw_noise_var(nt, clean)
            frame = np.asarray(scene.raw_normalized(i), np.float64)
            out[split].append(float(np.mean(((pred - frame) ** 2 / var)[sl])))
            if split == "test":
                out["error"].append(float(np.mean(((pred - clean) ** 2 / var)[sl])))
    return {k: float(np.mean(v)) for k, v in out.items()}


def kept_summary(name: str, variant: str, cfg: cfgmod.Config, runs: Path) -> dict | None:
    """The eval summary of <runs>/<name>/<variant>, else its kept result (common RESULTS,
    same config), else None: nothing is trained."""
    metrics = runs / name / variant / "eval" / "metrics.json"
    if metrics.is_file():
        return json.loads(metrics.read_text())["summary"]
    hit = cached_result(name, variant, cfg)
    return None if hit is None else hit["summary"]


def save_npy(path: Path, array: np.ndarray) -> None:
    with open(path, "wb") as f:  # np.save on a name would append .npy to the temporary
        np.save(f, np.asarray(array, np.float32))


def write_clean(folder: Path) -> None:
    """<scene>/clean/<frame>.npy: every frame's exact noise-free raw (truth.clean_mean),
    what data.target=clean trains on; written once."""
    mean = truth.clean_mean(folder)
    out = folder / dataset.CLEAN_DIR
    for path in sorted((folder / "raw").glob("*.dng")):
        target = out / f"{path.stem}.npy"
        if not target.is_file():
            frame = mean(path.stem)
            atomic.write(target, lambda tmp, frame=frame: save_npy(tmp, frame))


def truth_white(folder: Path) -> str:
    """--white-ref of the simulator's light (camera RGB)."""
    rgb = json.loads((folder / "sim.json").read_text())["illuminant_neutral_cam"]
    return "rgb:" + ",".join(repr(float(v)) for v in rgb)


CLEAN_EPS = 1e-5  # the data term's eps of the fifth fit (module docstring)
# fit -> (run folder name, preset, overrides): the four fits (budget). The clean raw goes
# the default's own way (binned stages, then the mosaic), so clean - noisy is the noise alone
FITS = {"oracle": ("oracle", "oracle", []),
        "clean": ("clean_truewhite_mosaic", "default", ["data.target=clean"]),
        "clean_eps": ("clean_truewhite_eps", "default", ["data.target=clean",
                                                         f"loss.data_eps={CLEAN_EPS:g}"]),
        "noisy": ("truewhite", "default", []),
        "default": ("default", "default", [])}
# their light is not in the config: kept here, not in RESULTS
TRUE_WHITE = ("clean", "clean_eps", "noisy")


def fit_config(fit: str) -> cfgmod.Config:
    _, preset, sets = FITS[fit]
    return cfgmod.override(cfgmod.preset(preset), sets)


def kept(name: str, fit: str, runs: Path, earlier: dict) -> float | None:
    """PSNR of a fit, nothing trained: a true-white fit from this study's own earlier
    record `earlier` where the config that trained it (its fingerprint there) is the fit's
    today; another fit from kept_summary; else None."""
    cfg = fit_config(fit)
    if fit in TRUE_WHITE:
        old = earlier.get(name, {})
        same = old.get("fingerprints", {}).get(fit) == fingerprint(cfg)
        return old.get(fit) if same else None
    summary = kept_summary(name, FITS[fit][0], cfg, runs)
    return None if summary is None else float(summary["gridnerf"]["psnr"])


def budget(name: str, runs: Path, train=tuple(FITS), earlier: dict | None = None) -> dict:
    """One scene's row: the fits (kept, or trained where missing and named in `train`), the
    ceilings and the default's (and the clean fit's) renders re-shown."""
    folder = scene_dir(name)
    row = {k: v for k in FITS if (v := kept(name, k, runs, earlier or {})) is not None}
    if train:
        write_clean(folder)
        white = truth_white(folder)
        for k, (variant, preset, sets) in FITS.items():
            if k not in row and k in train:
                summary = run_variant(name, variant, preset, sets, runs,
                                      white_ref=white if k in TRUE_WHITE else None,
                                      keep=k not in TRUE_WHITE)["summary"]
                row[k] = float(summary["gridnerf"]["psnr"])
    row["fingerprints"] = {k: fingerprint(fit_config(k)) for k in TRUE_WHITE if k in row}
    default = kept_summary(name, "default", cfgmod.preset("default"), runs)
    if default is not None:  # the one-frame non-local-means row, beside the default
        row["one_frame_nlm"] = float(default["baseline_denoised"]["psnr"])
    mse_oracle = 10.0 ** (-row.get("oracle", np.inf) / 10.0)
    sim = json.loads((folder / "sim.json").read_text())
    scene = load_scene(folder, near_far=tuple(sim["near_far"]))
    views = per_view(folder, scene)
    row["bound"] = float(np.mean([-10.0 * np.log10(mse_oracle + m)
                                  for m in views["noise_mse"]]))
    row["noise_only"] = float(np.mean([-10.0 * np.log10(m) for m in views["noise_mse"]]))
    row["best_3x3"] = float(np.mean(views["best_3x3"]))
    row["path"] = float(np.mean(views["path"]))
    row["path_full"] = float(np.mean(views["path_full"]))
    row["best_3x3_full"] = float(np.mean(views["best_3x3_full"]))
    if default is not None:
        row.update(best_maps(scene, runs / name / "default"))
    old = (earlier or {}).get(name, {})

    def measured(fit: str, key: str, value: float | None) -> None:
        """row[key] = value, measured on the fit's run folder; without it, the study's
        earlier record of key where that record has the same fit (its PSNR unchanged)."""
        if value is None and fit in row and old.get(fit) == row[fit]:
            value = old.get(key)
        if value is not None:
            row[key] = value

    # the clean fits re-shown by their best 3x3: from their renders, else this study's record
    for fit in ("clean", "clean_eps"):
        maps = best_maps(scene, runs / name / FITS[fit][0])
        for k in ("best_map", "chroma_share"):
            measured(fit, f"{fit}_{k}", maps.get(k))
    # the default and the clean fit against the noise, in the raw (raw_discrepancy)
    row["raw_ideal"] = 1.0 / len(scene.train_idx)
    for fit, keys in (("default", ("train", "test", "error")), ("clean", ("error",))):
        got = raw_discrepancy(runs / name / FITS[fit][0])
        for k in keys:
            measured(fit, f"raw_{fit}_{k}", got.get(k))
    return row


# trained: pipeline, noise, white; from the renders: fit (= representation + noise, the
# clean and the default fit each re-shown by its best 3x3), output matrix, white & exposure
GAPS = ((("oracle", "clean"), "pipeline"), (("clean", "noisy"), "noise"),
        (("noisy", "default"), "white"), (("oracle", "best_map"), "fit"),
        (("oracle", "clean_best_map"), "fit: representation"),
        (("clean_eps_best_map", "clean_best_map"), "representation: eps"),
        (("oracle", "clean_eps_best_map"), "representation: grid"),
        (("clean_best_map", "best_map"), "fit: noise"),
        (("best_map", "best_white"), "output matrix"),
        (("best_white", "default"), "white & exposure"))


# the default's error by scale (by_scale): (record key, column heading), and its gap
SCALE_COLUMNS = (("default", "default"), ("coarse", f"default, both blurred {DETAIL_SIGMA:g} px"),
                 ("detail_kept", "detail kept"), ("chroma_share", "colour share of the error"),
                 ("clean_chroma_share", "clean fit: colour share"))
SCALE_GAPS = ((("coarse", "default"), "detail (dB)"),)


BUDGET_GROUPS = ("nine", "dev", "heldout", "cycles")  # the groups the tables show, in order
# the fits against the noise in the raw (raw_discrepancy), one frame's noise variance = 1
RAW_COLUMNS = (("raw_ideal", "ideal average of the training views"),
               ("raw_clean_error", "clean fit: error"), ("raw_default_error", "default: error"),
               ("raw_default_train", "default: training frames"),
               ("raw_default_test", "default: test frames"))


def table_row(label: str, r: dict, columns=COLUMNS, gaps=GAPS, fmt: str = ".2f") -> list[str]:
    """A row's cells ("n/a" where a fit is missing) and its gaps."""
    cells = [label, *(f"{r[k]:{fmt}}" if k in r else "n/a" for k, _ in columns)]
    return cells + [f"{r[a] - r[b]:+.2f}" if a in r and b in r else "n/a"
                    for (a, b), _ in gaps]


def main() -> None:
    ap = study_parser(__doc__, "reports/error_budget", scenes="nine,dev,heldout", runs=True)
    ap.add_argument("--train", default=",".join(FITS),
                    help="the fits to train where missing (comma-separated, of "
                    f"{', '.join(FITS)})")
    ap.add_argument("--no-train", action="store_true",
                    help="train nothing: the fits whose runs or kept results are here")
    args = ap.parse_args()
    names = scene_names(args.scenes, BUDGET_GROUPS)
    train = () if args.no_train else tuple(args.train.split(","))
    if unknown := set(train) - set(FITS):
        ap.error(f"--train: unknown fit(s) {sorted(unknown)}; the fits are {', '.join(FITS)}")
    record = {}
    earlier_path = Path(args.out).with_suffix(".json")
    earlier = json.loads(earlier_path.read_text()) if earlier_path.is_file() else {}
    for name in names:
        record[name] = budget(name, Path(args.runs), train, earlier)
        print(name, table_row(name, record[name]), flush=True)
    # the table shows every scene on record, by group: a run on some keeps the others' rows
    record = {**earlier, **record}
    order = [n for g in BUDGET_GROUPS for n in GROUPS[g] if n in record]
    record = {n: record[n] for n in order + sorted(set(record) - set(order))}
    rows = dict(record)
    for g in BUDGET_GROUPS:
        group = [r for n, r in record.items() if n in GROUPS[g]]
        if len(group) > 1:
            keys = set.intersection(*(set(r) for r in group)) - {"fingerprints"}
            rows[f"**mean, {g}** ({len(group)})"] = {k: float(np.mean([r[k] for r in group]))
                                                     for k in keys}
    ceilings = markdown_table(["scene", *(h for _, h in CEILINGS)],
                              [table_row(n, r, CEILINGS, ()) for n, r in rows.items()])
    fits = markdown_table(["scene", *(h for _, h in COLUMNS), *(h for _, h in GAPS)],
                          [table_row(n, r) for n, r in rows.items()])
    scales = markdown_table(["scene", *(h for _, h in SCALE_COLUMNS), *(h for _, h in SCALE_GAPS)],
                            [table_row(n, r, SCALE_COLUMNS, SCALE_GAPS) for n, r in rows.items()
                             if any(k in r for k, _ in SCALE_COLUMNS[1:])])
    raws = markdown_table(["scene", *(h for _, h in RAW_COLUMNS)],
                          [table_row(n, r, RAW_COLUMNS, (), ".3f") for n, r in rows.items()
                           if any(k in r for k, _ in RAW_COLUMNS[1:])])
    table = ("What no reconstruction can beat (nothing trained):\n\n" + ceilings
             + "\nThe fits and where their dB go:\n\n" + fits
             + "\nThe default's error by scale (render and reference both blurred by a "
             f"Gaussian of {DETAIL_SIGMA:g} px in sRGB: the error above about two pixels; "
             "detail = that PSNR - the PSNR; detail kept: the render's fine detail, its "
             "image minus its blur, as a share of the reference's in RMS; colour share: "
             "the share of the squared sRGB error that is colour rather than grey, the error "
             "less its luma-weighted grey, for the default and the clean fit):\n\n" + scales
             + "\nThe fits against the noise in the raw, photosite by photosite, in units of "
             "one frame's noise variance (the simulator's noise model at the clean mean): the "
             "ideal average, 1 / the training views; error, (render - clean raw)^2 on the "
             "test views; training and test frames, (render - frame)^2, where under 1 the fit "
             "has taken noise for detail (scenes whose run folders were measured):\n\n" + raws)
    md = ("# Error budget\n\n"
          f"`python -m experiments.error_budget --scenes {args.scenes}"
          f"{' --no-train' if args.no_train else ''}`"
          + (f" (the rows of {', '.join(n for n in record if n not in names)} as recorded "
             "by earlier runs)" if any(n not in names for n in record) else "")
          + ": test-view PSNR (dB). Ceilings: "
          "noise alone, the PSNR the ideal average of the training views' noise would leave on "
          "a perfect image; noise bound, the oracle's error plus that noise; colour, the clean "
          "raw with no reconstruction, binned and at every photosite (full res), through the "
          "best 3x3 map and through the output path. Fits: the same grid fitted four ways "
          "(pipeline = oracle - clean, noise = clean - noisy, white = noisy - default); the "
          "clean and the default fit re-shown with the best 3x3 map of their camera RGB, the "
          "default with the best white and exposure (fit = oracle - default's best 3x3 = "
          "representation (oracle - clean's best 3x3) + noise (clean's - default's best 3x3); "
          "the representation split by a fifth fit, the clean raw with the data term's eps "
          "at 1e-5 rather than the 1e-3 the noise needs: eps = its best 3x3 - the clean "
          "fit's, grid = oracle - its best 3x3; "
          "output matrix = best 3x3 - best white; white & exposure = best white - "
          "default).\n\n" + table + "\n")
    write_report(args.out, md, record)
    update_doc("error_budget", table, RESULTS_DOC)
    print(md)


if __name__ == "__main__":
    main()
