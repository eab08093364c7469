"""`gridnerf view`: one self-contained HTML file whose WebGL2 ray marcher, run by headless
Chromium (SwiftShader), draws what `gridnerf render` writes for the same camera."""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gridnerf.cli import main

# one short stage of a 20x20x12 grid, enough for a textured view (a flat colour would
# match any renderer's mean: the browser test checks the view is not flat)
TINY = ["grid.resolutions=[[20,20,12]]", "train.steps_per_stage=[40]", "train.batch_patches=32",
        "train.lr_rgb=0.3", "train.log_every=10", "train.checkpoint_every=40"]
# headless Chromium 156 with WebGL2 on the CPU (SwiftShader); the page puts its canvas as a
# PNG into the DOM (?snapshot=1), which --dump-dom prints: a --screenshot goes through the
# compositor, which dropped a row of a 480x270 canvas (the bucket lost 22 dB to it)
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--use-angle=swiftshader",
                  "--enable-unsafe-swiftshader"]


@pytest.fixture(scope="module")
def run(small_scene, tmp_path_factory):
    """A finished run of the `tiny` preset shrunk further (TINY), trained through the CLI."""
    run = tmp_path_factory.mktemp("viewer") / "run"
    argv = ["train", str(small_scene), "--out", str(run), "--preset", "tiny", "--set", *TINY]
    assert main(argv) == 0
    return run


def _payload(html: str) -> dict:
    m = re.search(r'<script id="payload" type="application/json">(.*?)</script>', html, re.S)
    return json.loads(m.group(1))


def test_view_writes_one_self_contained_file(run, tmp_path, capsys):
    from gridnerf import eval_run, grid

    out = tmp_path / "page" / "view.html"
    assert main(["view", str(run), "--out", str(out)]) == 0
    printed = capsys.readouterr().out.strip()
    assert re.fullmatch(rf"wrote {re.escape(str(out))} \(\d+\.\d MB\)", printed), printed
    assert sorted(p.name for p in out.parent.iterdir()) == ["view.html"]
    html = out.read_text()
    assert not re.search(r"https?://", html)  # no CDN, no server
    assert not re.search(r"""(src|href)\s*=\s*["'][^"'#]""", html)  # no other file
    data = _payload(html)
    cfg, _, scene, structure, params, _ = eval_run.load_run(run)
    g = data["grid"]
    rows = np.frombuffer(base64.b64decode(g["features_f16"]), "<f2").reshape(g["n_rows"], -1)
    table = np.asarray(grid.feature_table(structure, params))
    np.testing.assert_array_equal(rows, table[:-1].astype(np.float16))
    kept = np.unpackbits(np.frombuffer(base64.b64decode(g["kept_bits"]), np.uint8),
                         bitorder="little")[: int(np.prod(g["resolution"]))]
    assert kept.sum() == structure.n_rows
    assert data["camera"]["name"] == scene.names[scene.test_idx[0]]
    assert data["outputs"][0]["name"] == eval_run.main_output(cfg)


def test_view_of_a_run_without_checkpoint_is_one_error_line(run, tmp_path, capsys):
    broken = tmp_path / "run"
    shutil.copytree(run, broken)
    (broken / "checkpoint.npz").unlink()
    assert main(["view", str(broken)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(broken / "checkpoint.npz") in err, err
    assert not (broken / "viewer.html").exists()


@pytest.fixture(scope="module")
def chromium() -> str:
    """The Chromium binary, or a skip (before the run fixture trains anything)."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if path := shutil.which(name):
            return path
    pytest.skip("headless Chromium is not installed (Debian: apt-get install chromium, "
                "which `make system-deps` tries as root)")


def _browser_render(chromium: str, html: Path, width: int, height: int, tmp_path: Path,
                    status: bool = False, **controls):
    """(H, W, 3) rgb_srgb in [0, 1]: the page's canvas at width x height, controls as in its
    query string (output, stops, kelvin, tint, pick); with `status`, also the page's line
    on the picked neutral."""
    query = "&".join(f"{k}={v}" for k, v in
                     {"ui": 0, "w": width, "h": height, "snapshot": 1, **controls}.items())
    argv = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'chromium'}",
            f"--window-size={width},{height}", "--dump-dom", f"file://{html}?{query}"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=180)
    m = re.search(r'<pre id="snapshot"[^>]*>data:image/png;base64,([^<]+)</pre>', done.stdout)
    assert m, f"no canvas in the page (status {done.returncode}): {done.stderr[-2000:]}"
    import imageio.v3 as iio

    rgb_srgb = iio.imread(io.BytesIO(base64.b64decode(m.group(1))))[..., :3] / 255.0
    if not status:
        return rgb_srgb
    line = re.search(r'<div id="pickStatus">([^<]*)</div>', done.stdout)
    return rgb_srgb, line.group(1) if line else ""


def _box_means(rgb_linear: np.ndarray, box: int = 5) -> np.ndarray:
    """(H - box + 1, W - box + 1, 3) means of every box x box patch."""
    from numpy.lib.stride_tricks import sliding_window_view

    return sliding_window_view(rgb_linear, (box, box), axis=(0, 1)).mean(axis=(-2, -1))


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")
def test_a_picked_neutral_turns_its_patch_grey(chromium, run, tmp_path):
    """?pick=X,Y (a shift-click there): the 5x5 patch around (X, Y), the most coloured
    well-exposed patch of the view, is drawn grey at its luminance (8-bit sRGB and float16
    features: within 3 % per colour); a patch too dark to tell its hue is refused with a
    line saying so, and the view is left as it was."""
    from gridnerf import color, viewer

    html = viewer.write_viewer(run, tmp_path / "pick.html")
    cam = _payload(html.read_text())["camera"]
    w, h = cam["width"], cam["height"]
    before_srgb = _browser_render(chromium, html, w, h, tmp_path)
    lo, hi = [_box_means((before_srgb > t).astype(float)) for t in (0.15, 0.9)]
    usable = (lo.min(-1) == 1.0) & (hi.max(-1) == 0.0)  # every pixel exposed, none clipped
    assert usable.any()
    means = _box_means(color.srgb_decode(before_srgb))
    chroma = np.where(usable, np.ptp(means, -1) / means.mean(-1), -1.0)
    y0, x0 = np.unravel_index(np.argmax(chroma), chroma.shape)
    assert chroma[y0, x0] > 0.1  # the patch is coloured to begin with
    after_srgb, line = _browser_render(chromium, html, w, h, tmp_path, status=True,
                                       pick=f"{x0 + 2},{y0 + 2}")
    assert line.startswith(f"neutral picked at ({x0 + 2}, {y0 + 2})"), line
    patch = _box_means(color.srgb_decode(after_srgb))[y0, x0]
    np.testing.assert_allclose(patch / patch.mean(), 1.0, atol=0.03)
    assert color.luminance(patch) == pytest.approx(color.luminance(means[y0, x0]), rel=0.03)

    dark = _box_means(before_srgb).max(-1)
    yd, xd = np.unravel_index(np.argmin(dark), dark.shape)
    _, line = _browser_render(chromium, html, w, h, tmp_path, status=True, stops=-5,
                              pick=f"{xd + 2},{yd + 2}")
    assert line.startswith(f"not picked: the patch at ({xd + 2}, {yd + 2}) is too dark"), line


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # chromium's subprocess
def test_browser_draws_what_render_writes(chromium, run, tmp_path):
    """The page at the first test view matches `gridnerf render --path test`'s PNG (PSNR >
    30 dB; measured 75-78 dB, 1/255 at most), its exposure and one-gain controls match the
    outputs' own (eval_run.run_outputs: alpha x 2^stops, global_grey_world), and its
    temperature slider at 3000 K turns the view bluer."""
    from gridnerf import eval_run, evaluate, image_io

    t0 = time.perf_counter()
    html = run / "viewer.html"
    assert main(["view", str(run)]) == 0
    assert main(["render", str(run), "--path", "test"]) == 0
    data = _payload(html.read_text())
    cam = data["camera"]
    reference_srgb = image_io.read_png(run / "render" / f"{cam['name']}.png")
    h, w = reference_srgb.shape[:2]
    assert (w, h) == (cam["width"], cam["height"])
    flat_srgb = np.broadcast_to(reference_srgb.mean(axis=(0, 1)), reference_srgb.shape)
    assert evaluate.psnr(flat_srgb, reference_srgb) < 25.0  # the view has texture
    browser_srgb = _browser_render(chromium, html, w, h, tmp_path)
    psnr = evaluate.psnr(browser_srgb, reference_srgb)
    print(f"browser vs render: {psnr:.1f} dB at {w}x{h}")
    assert psnr > 30.0

    cfg, plan, scene, structure, params, _ = eval_run.load_run(run)
    shown = eval_run.run_outputs(cfg, plan, scene, structure, params)
    out = eval_run.render_view(structure, params, scene, cfg, np.asarray(cam["c2w"]),
                               np.asarray(cam["intrinsics"]), h, w)
    one_gain = shown["global_grey_world"]
    _, expected_srgb = replace(one_gain, alpha=one_gain.alpha * 0.5).show(out)
    browser_srgb = _browser_render(chromium, html, w, h, tmp_path,
                                   output="global_grey_world", stops=-1)
    psnr = evaluate.psnr(browser_srgb, expected_srgb)
    print(f"one gain, -1 stop: {psnr:.1f} dB; {time.perf_counter() - t0:.1f} s")
    assert psnr > 30.0
    # the temperature slider corrects for a warmer light: bluer, less red
    warm_srgb = _browser_render(chromium, html, w, h, tmp_path, kelvin=3000)
    shift = (warm_srgb - reference_srgb).mean(axis=(0, 1))
    assert shift[2] > 0.02 and shift[0] < -0.02, shift


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")
def test_browser_draws_world_rays_as_render_does(chromium, run, tmp_path, monkeypatch):
    """The page's world-ray branch (scenes that are not forward-facing: no NDC warp, the
    scene's near and far): the run loaded as such a scene, its grid box moved in front of
    the camera, drawn like eval_run.render_view."""
    import dataclasses

    import jax.numpy as jnp

    from gridnerf import eval_run, evaluate, viewer

    load_run = eval_run.load_run

    def as_world_scene(path):
        cfg, plan, scene, structure, params, summary = load_run(path)
        structure = dataclasses.replace(structure, bbox_min=jnp.asarray([-1.5, -1.0, -4.0]),
                                        bbox_max=jnp.asarray([1.5, 1.0, -1.6]))
        scene = dataclasses.replace(scene, forward_facing=False)
        return cfg, plan, scene, structure, params, summary

    monkeypatch.setattr(eval_run, "load_run", as_world_scene)
    html = viewer.write_viewer(run, tmp_path / "world.html")
    cfg, plan, scene, structure, params, _ = eval_run.load_run(run)
    main_output = eval_run.run_outputs(cfg, plan, scene, structure, params)[
        eval_run.main_output(cfg)]
    cam = _payload(html.read_text())["camera"]
    h, w = cam["height"], cam["width"]
    out = eval_run.render_view(structure, params, scene, cfg, np.asarray(cam["c2w"]),
                               np.asarray(cam["intrinsics"]), h, w)
    assert out["acc"].mean() > 0.1  # the rays cross the moved box
    _, expected_srgb = main_output.show(out)
    psnr = evaluate.psnr(_browser_render(chromium, html, w, h, tmp_path), expected_srgb)
    print(f"world rays: {psnr:.1f} dB")
    assert psnr > 30.0


def test_runs_shown_by_other_than_gains_are_refused():
    from gridnerf import viewer
    from gridnerf.errors import GridNerfError

    with pytest.raises(GridNerfError, match="brightnerf"):
        viewer.output_payload({"llnerf": object()}, "llnerf")


def test_menu_names_what_the_main_output_shows():
    from gridnerf import viewer
    from gridnerf.outputs import Output

    field = Output("rgb_restored", np.ones(3), np.eye(3))
    assert viewer.label("gridnerf", field) == viewer.LABELS["gridnerf"]
    one_gain = Output("rgb_low", np.array([1.2, 1.0, 1.7]), np.eye(3))
    assert viewer.label("gridnerf", one_gain) == "the run's one gain for the capture"
    assert viewer.label("gridnerf", replace(one_gain, gains=np.ones(3))).startswith("no gains")
