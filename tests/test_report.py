"""make report's assembly (python -m experiments.report): rows from the evaluated runs, nine
and held-out means apart; the result cache (reports/results.json) and the tables the
studies write into README.md and docs/."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _metrics(psnr: float) -> dict:
    m = {"psnr": psnr, "ssim": 0.5, "delta_e": 10.0, "psnr_aligned": psnr + 1,
         "ssim_aligned": 0.6, "delta_e_aligned": 9.0}
    return {"summary": {"gridnerf": m, "global_grey_world": {**m, "psnr": psnr - 1},
                        "baseline_denoised": {**m, "psnr": psnr - 2}}}


def _write(runs: Path, scene: str, variant: str, metrics: dict) -> None:
    path = runs / scene / variant / "eval" / "metrics.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(metrics))


def _report(cwd: Path) -> subprocess.CompletedProcess:
    """python -m experiments.report in `cwd` (its runs/ and reports/ are cwd's)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "experiments.report",
                           "--runs", "runs", "--out", "out/report"],
                          cwd=cwd, capture_output=True, text=True, timeout=300, env=env)


def test_report_rows_and_separate_means(tmp_path):
    runs = tmp_path / "runs"
    _write(runs, "bucket", "default", _metrics(20.0))
    _write(runs, "deer", "default", _metrics(18.0))
    _write(runs, "held_arc_brick", "default", _metrics(15.0))
    _write(runs, "held_arc_brick", "oracle", _metrics(25.0))
    proc = _report(tmp_path)
    assert proc.returncode == 0, proc.stderr
    record = json.loads((tmp_path / "out" / "report.json").read_text())
    assert record["ours"]["mean_nine"]["psnr"] == 19.0 and record["ours"]["mean_nine"]["n"] == 2
    assert record["ours"]["mean_heldout"]["psnr"] == 15.0  # never mixed into the nine
    assert record["global_wb"]["scenes"]["bucket"]["psnr"] == 19.0
    assert record["2d_denoised"]["mean_nine"]["psnr"] == 17.0
    assert record["oracle"]["mean_nine"] is None and record["oracle"]["mean_heldout"]["n"] == 1
    text = (tmp_path / "out" / "report.md").read_text()
    assert "`rawnerf_isp`: no evaluated runs yet" in text
    assert "SID, RED, ABF, DNF" in text and "n/a" in text


def test_report_without_runs_says_what_to_do(tmp_path):
    proc = _report(tmp_path)
    assert proc.returncode != 0 and "make recon" in proc.stderr
    assert not (tmp_path / "out").exists()


def test_report_leaves_out_runs_of_another_config(tmp_path):
    from gridnerf import config as cfgmod

    runs = tmp_path / "runs"
    _write(runs, "bucket", "default", _metrics(20.0))
    _write(runs, "deer", "default", _metrics(18.0))
    old = cfgmod.override(cfgmod.preset("default"), ["grid.background=black"])
    cfgmod.save(old, runs / "bucket" / "default" / "config.json")
    cfgmod.save(cfgmod.preset("default"), runs / "deer" / "default" / "config.json")
    proc = _report(tmp_path)
    assert proc.returncode == 0, proc.stderr
    record = json.loads((tmp_path / "out" / "report.json").read_text())
    assert set(record["ours"]["scenes"]) == {"deer"} and record["ours"]["stale"] == ["bucket"]
    assert "another config than their preset's today: runs/bucket/default" in (
        tmp_path / "out" / "report.md").read_text()


def test_report_reuses_results_only_with_todays_fingerprint(tmp_path):
    """A fresh machine has no run folders: reports/results.json gives their numbers back
    when the config fingerprint beside them is the preset's today, and never otherwise."""
    from experiments.common import fingerprint, preset_config

    runs = tmp_path / "runs"
    _write(runs, "deer", "default", _metrics(18.0))
    today = fingerprint(preset_config("default"))
    other = fingerprint(preset_config("nogain"))
    assert today != other
    results = {f"{scene}/default": {"fingerprint": fp, "summary": _metrics(psnr)["summary"]}
               for scene, fp, psnr in (("bucket", today, 20.0), ("box", other, 21.0),
                                       ("deer", today, 1.0))}
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "results.json").write_text(json.dumps(results))
    proc = _report(tmp_path)
    assert proc.returncode == 0, proc.stderr
    ours = json.loads((tmp_path / "out" / "report.json").read_text())["ours"]
    assert ours["scenes"]["bucket"]["psnr"] == 20.0 and ours["cached"] == ["bucket"]
    assert "box" not in ours["scenes"]  # trained by another config: not reused
    assert ours["scenes"]["deer"]["psnr"] == 18.0  # a run on this machine wins
    assert "taken from reports/results.json" in (tmp_path / "out" / "report.md").read_text()


def test_run_variant_keeps_and_reuses_results(tmp_path, monkeypatch):
    """run_variant returns a result of the same config without training, and trains (not
    reuses) when the config differs or the caller needs the run folder."""
    from experiments import common

    monkeypatch.chdir(tmp_path)
    trained = []
    monkeypatch.setattr(common, "train",
                        lambda sdir, run, cfg, **kw: trained.append(run))
    monkeypatch.setattr(common, "scene_dir", lambda scene, quick=False: tmp_path / scene)
    monkeypatch.setattr(common, "evaluate_run", lambda run: _metrics(19.0))
    cfg = common.preset_config("default")
    common.record_result("bucket", "default", cfg, _metrics(20.0))
    got = common.run_variant("bucket", "default", "default", [], tmp_path / "runs")
    assert got["cached"] and got["summary"]["gridnerf"]["psnr"] == 20.0 and not trained
    got = common.run_variant("bucket", "default", "default", ["loss.w_smooth=0.0"],
                             tmp_path / "runs")
    assert len(trained) == 1 and got["summary"]["gridnerf"]["psnr"] == 19.0
    common.run_variant("bucket", "default", "default", [], tmp_path / "runs", need_run=True)
    assert len(trained) == 2
    kept = json.loads((tmp_path / "reports" / "results.json").read_text())
    assert kept["bucket/default"]["summary"]["gridnerf"]["psnr"] == 19.0  # the newest


def test_kept_results_carry_their_run_folders_facts(tmp_path, monkeypatch):
    """Beside an evaluated run's scores run_variant keeps the facts the tables read from its
    folder (common.run_facts); without the folder the kept result gives them back, and the
    colour-group and reconstruction rows show them as they would from the folder."""
    from experiments import colour_groups, common, recon

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(common, "train", lambda *a, **k: pytest.fail("nothing to train"))
    run = tmp_path / "runs" / "bucket" / "default"
    metrics = _metrics(20.0)
    metrics["summary"]["baseline_binned_matched"] = {"psnr": 16.0, "ssim": 0.3}
    _write(tmp_path / "runs", "bucket", "default", metrics)
    summary = {"resolution": [192, 113, 64], "occupied_fraction": 0.25, "train_seconds": 180.0,
               "colour": {"shipped": "one_gain", "distance": 0.04}, "rays_per_second": 9.0}
    (run / "summary.json").write_text(json.dumps(summary))
    (run / "plan.json").write_text(json.dumps({"black_level": "lens_cap", "downscale": 1}))
    (run / "bounds.json").write_text(json.dumps({"near": 1.5, "far": 15.0}))
    here = common.run_variant("bucket", "default", "default", [], tmp_path / "runs")["facts"]
    facts = common.load_results()["bucket/default"]["facts"]
    assert facts == {"resolution": [192, 113, 64], "occupied_fraction": 0.25,
                     "train_seconds": 180.0, "colour": summary["colour"],
                     "black_level": "lens_cap", "bounds": {"near": 1.5, "far": 15.0}}
    (tmp_path / "runs").rename(tmp_path / "elsewhere")  # a fresh machine: no run folders
    got = common.run_variant("bucket", "default", "default", [], tmp_path / "runs")
    assert got["cached"] and got["facts"] == facts
    kept = got["facts"]
    assert kept == here
    assert colour_groups.shipped(kept) == "one_gain (0.04)"
    assert colour_groups.black_level(kept) == "lens cap"
    assert colour_groups.shipped(None) == "kept result"  # a result kept before its facts
    row = recon.row_for("bucket", oracle=False)
    assert row["resolution"] == [192, 113, 64] and row["train_seconds"] == 180.0
    assert row["bounds"] == {"near": 1.5, "far": 15.0} and row["psnr"] == 20.0


def test_readme_means_table_names_every_row_and_count():
    from experiments import report

    m = {"psnr": 20.0, "ssim": 0.5, "delta_e": 10.0, "n": 3}
    record = {r: {"mean_nine": m if r == "ours" else None, "mean_heldout": None}
              for r in report.SHORT}
    table = report.means_table(record)
    assert "| ours | 20.00 / 0.500 / 10.00 (n=3) | - |" in table
    assert len(table.splitlines()) == 2 + len(report.ROWS)


def test_consistency_table_keeps_earlier_scenes_of_todays_runs(tmp_path, monkeypatch):
    """consistency.build scores the scenes it is given and keeps the earlier ones whose runs
    were trained by today's presets (and only those), saying each command."""
    from experiments import common, consistency

    row = {"mae": 2.0 / 255, "coverage": 0.9}
    monkeypatch.setattr(consistency, "scene_rows", lambda name, runs, quick: {
        "gridnerf": row, "reference": row})
    monkeypatch.setattr(consistency, "scene_dir", lambda scene, quick=False: tmp_path / scene)
    today = common.fingerprint(common.preset_config("default"))
    old = {"scenes": {
        "deer": {"rows": {"gridnerf": row}, "command": "old call",
                 "fingerprints": {"default": today}},
        "box": {"rows": {"gridnerf": row}, "command": "older call",
                "fingerprints": {"default": "0" * 16}}}}
    out = tmp_path / "consistency"
    out.with_suffix(".json").write_text(json.dumps(old))
    text = consistency.build(["bucket"], tmp_path / "runs", out, False, "new call")
    record = json.loads(out.with_suffix(".json").read_text())["scenes"]
    # in SCENES order; box's run was trained by another config: dropped
    assert list(record) == ["deer", "bucket"]
    assert "`old call`; `new call`" in text and "older call" not in text
    assert "**mean, nine** (2 of 9)" in text


def _cached_variants() -> dict:
    """{run folder: config} of every variant the studies keep in reports/results.json (the
    report's rows, the ablation studies, the darkness and photon sweeps, recon's oracle)."""
    from experiments import ablate, photons, report, sweep
    from gridnerf import config as cfgmod

    variants = {f: (p, []) for f, p in report.RUN_PRESETS.items()}
    variants |= {f: (p, s) for study in ablate.STUDIES.values() for _, _, f, p, s in study}
    variants |= {f: ("default", s) for f, s in photons.VARIANTS.items()}
    for method, (preset, _, sets) in sweep.METHODS.items():
        for g in (sweep.EXTREME, *sweep.GAMMAS):
            extra = [] if g == 1.0 else [f"data.exposure_ratio={g:g}"]
            variants[sweep.variant(method, g)] = (preset, sets + extra)
    return {f: cfgmod.override(cfgmod.preset(p), s) for f, (p, s) in variants.items()}


def test_committed_results_carry_todays_fingerprints():
    """Every kept result is a variant of a study today, under the fingerprint of the config
    that variant trains today: a result no study can look up (a removed study or config
    field) is dead weight, and a stale fingerprint means it is never reused."""
    from experiments.common import fingerprint, load_results

    results = load_results(REPO / "reports" / "results.json")
    variants = _cached_variants()
    today = {f: fingerprint(cfg) for f, cfg in variants.items()}
    assert len(set(today.values())) == len(today)  # one config, one fingerprint
    orphans = sorted(k for k in results if k.split("/", 1)[1] not in variants)
    assert not orphans, f"results of no study today: {orphans[:5]}"
    stale = sorted(k for k, e in results.items()
                   if e["fingerprint"] != today[k.split("/", 1)[1]])
    assert not stale, (f"{len(stale)} kept results no longer match their variant's config "
                       f"(e.g. {stale[:3]}): re-key them if the change trains alike, else "
                       "delete them")


def test_committed_report_rebuilds_from_the_kept_results():
    """Each cell of the committed report (reports/report.json) is in the kept results under
    its row's preset of today: a fresh machine without run folders rebuilds the report."""
    from experiments.common import cached_result, load_results, preset_config
    from experiments.report import RUN_PRESETS

    results = load_results(REPO / "reports" / "results.json")
    record = json.loads((REPO / "reports" / "report.json").read_text())
    missing = []
    for row, entry in record.items():
        cfg = preset_config(RUN_PRESETS[entry["variant"]])
        for scene, metrics in entry["scenes"].items():
            hit = cached_result(scene, entry["variant"], cfg, results)
            if hit is None or float(hit["summary"][entry["key"]]["psnr"]) != metrics["psnr"]:
                missing.append(f"{row}: {scene}")
    assert not missing, missing[:5]
    assert sum(len(e["scenes"]) for e in record.values()) > 50


def test_update_doc_replaces_only_its_section(tmp_path):
    """update_doc rewrites the text between one name's markers (keeping the marker's note)
    and leaves a file without them as it is; update_readme writes the report's section."""
    from experiments.common import update_doc, update_readme

    doc = tmp_path / "doc.md"
    doc.write_text("# Doc\n\n<!-- recon:begin (written by python -m experiments.recon) -->\n"
                   "old\n<!-- recon:end -->\n\ntail\n<!-- report:begin -->\nr\n"
                   "<!-- report:end -->\n")
    update_doc("recon", "| new |", doc)
    assert doc.read_text() == ("# Doc\n\n<!-- recon:begin (written by python -m "
                               "experiments.recon) -->\n| new |\n<!-- recon:end -->\n\ntail\n"
                               "<!-- report:begin -->\nr\n<!-- report:end -->\n")
    before = doc.read_text()
    update_doc("bench", "x", doc)  # no bench markers here
    update_doc("bench", "x", tmp_path / "missing.md")
    assert doc.read_text() == before and not (tmp_path / "missing.md").exists()
    update_readme("| means |", doc)
    assert "<!-- report:begin -->\n| means |\n<!-- report:end -->" in doc.read_text()
    assert "| new |" in doc.read_text()


@pytest.mark.parametrize("name, module, path", [
    ("report", "report", "README.md"), ("recon", "recon", "docs/results.md"),
    ("ablation", "ablate", "docs/results.md"), ("consistency", "consistency", "docs/results.md"),
    ("bench", "bench", "docs/speed.md")])
def test_every_generated_table_has_its_markers(name, module, path):
    """The files the studies write their tables into hold those tables' markers, naming the
    module that writes them (else update_doc keeps the file and the table goes stale)."""
    text = (REPO / path).read_text()
    assert f"<!-- {name}:begin (written by python -m experiments.{module}) -->" in text
    assert f"<!-- {name}:end -->" in text
    assert (REPO / "experiments" / f"{module}.py").is_file()


def test_a_colour_group_run_on_some_scenes_keeps_the_other_rows(tmp_path):
    """kept_rows reads the rows the colour-group report last wrote, which a run on some of
    the scenes keeps for the others; no report, no rows."""
    from experiments import colour_groups

    out = tmp_path / "colour_groups"
    assert colour_groups.kept_rows(out) == {}
    row = {"group": "nine", "gridnerf": [24.0, 6.0], "colour": "one_gain (0.04)",
           "black": "lens cap"}
    out.with_suffix(".json").write_text(json.dumps({"scenes": {"bucket": row}}))
    assert colour_groups.kept_rows(out) == {"bucket": row}
