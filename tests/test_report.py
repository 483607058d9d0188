"""The report: findings generated from the paired intervals, Table 1 / ReDAM tables from the metrics, a self-contained
HTML page, and the stage end to end on the repository's committed reports."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from weatheralign.data.errors import DataFormatError
from weatheralign.report import (
    PAPER_TABLE1,
    StageCost,
    StageSource,
    cost_table,
    earlier_stages,
    findings,
    markdown_to_html,
    outdated_inputs,
    redam_table,
    reprojection_table,
    source_line,
    summary_markdown,
)

REPO = Path(__file__).resolve().parents[1]
REPORTS = REPO / "reports"


def _diff(a: str, b: str, metric: str, d: float, lo: float, hi: float) -> dict:
    return {"a": a, "b": b, "metric": metric, "difference": d, "ci": [lo, hi], "exceeds_noise": lo > 0 or hi < 0}


def test_findings_are_generated_from_the_intervals_noise_exceeding_first():
    detect = {"differences": {
        "pretrained:snow:unaligned-aligned:map": _diff("pretrained/snow-unaligned", "pretrained/snow-aligned", "map",
                                                       0.001, -0.002, 0.004),
        "pretrained:clean:fused-lidar:map": _diff("pretrained/clean", "pretrained/clean-lidar", "map",
                                                  0.049, 0.032, 0.067),
        "finetuned-rain-mix-vs-pretrained:clean:nds": _diff("finetuned-rain-mix/clean", "pretrained/clean", "nds",
                                                            -0.03, -0.05, -0.01),
        "something:new": _diff("m/x", "m/y", "map", 0.5, 0.4, 0.6)}}
    out = findings(detect)
    assert out[0] == ("The camera adds to the LiDAR-only detector's clean mAP +0.049 [+0.032, +0.067] "
                      "(exceeds the noise)")
    assert out[1] == "Finetuning on the rain mix changes the clean NDS by -0.030 [-0.050, -0.010] (exceeds the noise)"
    assert out[2] == "Map of m/x minus m/y: +0.500 [+0.400, +0.600] (exceeds the noise)"  # unknown key: generic
    assert out[3].startswith("Evaluating the pretrained detector on unaligned instead of aligned snow changes its mAP "
                             "by +0.001") and out[3].endswith("(within the noise)")
    assert findings({}) == []


def test_redam_table_reports_the_error_against_the_hidden_truth():
    level = {"alpha": 0.011, "beta": 1e-4, "ks": 0.02, "ks_ci_low": 0.01, "ks_ci_high": 0.05, "kid": 0.03,
             "camera_visibility_ratio": 0.9}
    table = redam_table({"light": level, "kid_backbone": "x"}, {"light": {"alpha": 0.010, "beta": 2e-4}})
    row = table.splitlines()[2]
    assert row.startswith("| light | 0.011 | 0.01 | +10.0% |") and "0.0200 [0.0100, 0.0500]" in row
    assert len(table.splitlines()) == 3  # the non-level entry is skipped
    assert "| — |" in redam_table({"light": level}, None)  # real data: no hidden truth
    with_interval = redam_table({"light": {**level, "alpha_ci_low": 0.0095, "alpha_ci_high": 0.0121,
                                           "airlight_gain_median": 1.04}}, None).splitlines()[2]
    assert with_interval.startswith("| light | 0.011 [0.0095, 0.0121] | — |") and with_interval.endswith("| 1.040 |")


def test_rate_table_reports_the_error_against_the_hidden_rate():
    from weatheralign.report import rate_table

    cal = {"kinds": ["snow", "rain"],
           "snow": {"rate_mm_h": 2.89, "rate_ci_low": 2.02, "rate_ci_high": 4.07, "beyond_grid": False,
                    "open_path_echo_rate_reference": 0.2215},
           "rain": {"rate_mm_h": 53.2, "rate_ci_low": 42.6, "rate_ci_high": 67.3, "beyond_grid": True,
                    "open_path_echo_rate_reference": 0.0065}}
    table = rate_table(cal, {"snow": {"rate_mm_h": 2.958}, "rain": {"rate_mm_h": 78.19}})
    assert "| snow | 2.89 [2.02, 4.07] | 2.958 | -2.3% | yes | 0.2215 | no |" in table
    assert "| rain | 53.2 [42.6, 67.3] | 78.19 | -32.0% | no | 0.0065 | yes |" in table
    assert "| snow | 2.89 [2.02, 4.07] | — | — | — |" in rate_table(cal, None)  # real data: no hidden truth


def test_reprojection_table_shows_the_papers_figures_beside_aligned_snow_and_rain():
    m = {"points_unchanged": 10, "points_attenuated": 80, "points_scattered": 8, "points_lost": 2,
         "reprojection_mean_px": 0.0003, "reprojection_max_px": 0.009, "reprojection_pairs": 5}
    table = reprojection_table({"snow-aligned": m, "snow-unaligned": m, "fog_light-aligned": {**m,
                                                                                              "reprojection_pairs": 0}})
    rows = table.splitlines()[2:]
    assert rows[0] == (f"| snow-aligned | 0.0003 | 0.0090 | 5 | 2.00% | 8.00% | "
                       f"{PAPER_TABLE1['reprojection_mean_px']['snow']} / "
                       f"{PAPER_TABLE1['reprojection_max_px']['snow']} |")
    assert rows[1].endswith("| — |") and rows[2].startswith("| fog_light-aligned | — | — | 0 |")


def test_every_table_names_its_mlflow_run_and_dvc_experiment():
    """The summary names under each table the stage run it came from (a link to its MLflow page) and the DVC
    experiment it ran in; without tracking no such line."""
    sources = {"detect": StageSource("detect", "detect", "http://127.0.0.1:5000/#/experiments/1/runs/abc",
                                     "exp-snow-5"),
               "calibrate_fog": StageSource("calibrate_fog", "calibrate_fog", "http://x/runs/def", "workspace")}
    assert source_line(sources, "detect") == ("*From `detect`: MLflow run [detect](http://127.0.0.1:5000/#/experiments/"
                                              "1/runs/abc), DVC experiment `exp-snow-5`.*")
    assert source_line(sources, "simulate", "verify") == ""
    text = summary_markdown({"calibrate_fog": {}}, None, ["## Table 2\n\n| a |\n| --- |\n| 1 |"], {}, [], sources)
    assert text.count("DVC experiment `exp-snow-5`") == 1 and text.count("[calibrate_fog](http://x/runs/def)") == 1
    assert "MLflow run" not in summary_markdown({"calibrate_fog": {}}, None, ["## Table 2"], {}, [])
    assert "computed by this run;" in text


def test_figures_of_a_stage_this_tracking_store_never_ran_are_labelled_an_earlier_runs():
    """Reports of a stage that did not rerun (its figures present, no run of it in the tracking store) are said to
    come from an earlier run, in the opening line and under its tables; without tracking nothing is claimed."""
    sources = {"calibrate_fog": StageSource("calibrate_fog", "calibrate_fog", "http://x/runs/def", "workspace")}
    metrics = {"calibrate_fog": {}, "detect": {}}
    assert earlier_stages(metrics, sources) == {"detect"} and earlier_stages(metrics, {}) == frozenset()
    line = source_line(sources, "detect", earlier=frozenset({"detect"}))
    assert line.startswith("*From `detect`: an earlier run, not in this MLflow store") and "dvc status" in line
    text = summary_markdown(metrics, None, ["## Table 2\n\n| a |\n| --- |\n| 1 |"], {}, [], sources)
    assert "computed by this run;" not in text and "those of `detect` come from an earlier run" in text
    assert text.count("`detect`: an earlier run") == 1  # under Table 2
    assert "computed by this run;" in summary_markdown(metrics, None, ["## Table 2"], {}, [])  # tracking off


def test_figures_computed_from_datasets_simulated_again_since_are_labelled():
    """A stage whose recorded input digests differ from the manifests' current ones is named with the changed datasets,
    in the opening line and under its tables, even when its run is in the tracking store; current inputs claim
    nothing."""
    sources = {s: StageSource(s, s, f"http://x/runs/{s}", "workspace") for s in ("detect", "verify")}
    recorded = {"world": "aa", "simulate-snow-aligned": "bb", "simulate-rain-aligned": "cc"}
    metrics = {"detect": {"input_digests": recorded}, "verify": {}}
    current = {**recorded, "simulate-snow-aligned": "b2", "simulate-fog_light-aligned": "dd"}
    assert outdated_inputs(metrics, current) == {"detect": ("simulate-snow-aligned",)}
    assert outdated_inputs(metrics, {"world": "aa"}) == {"detect": ("simulate-rain-aligned", "simulate-snow-aligned")}
    assert outdated_inputs(metrics, recorded) == {}
    tables = ["## Table 2\n\n| a |\n| --- |\n| 1 |"]
    text = summary_markdown(metrics, None, tables, {}, [], sources, current)
    assert "computed by this run;" not in text
    assert "**the figures of `detect` are computed from an earlier version of `simulate-snow-aligned`**" in text
    assert text.count("`detect`: computed from an earlier version of `simulate-snow-aligned`") == 1  # under Table 2
    assert "computed by this run;" in summary_markdown(metrics, None, tables, {}, [], sources, recorded)
    assert "computed by this run;" in summary_markdown(metrics, None, tables, {}, [], sources)  # not checked


def test_cost_table_totals():
    table = cost_table([StageCost("world", 360.0, 11_000_000_000), StageCost("media", None, None)])
    assert "| world | 6.0 min | 11.00 GB |" in table and "| media | — | — |" in table
    assert table.splitlines()[-1] == "| **total** | 6.0 min | 11.00 GB |"


def test_cost_table_lists_every_stage_in_dvc_order():
    """The cost table has a row for every stage of dvc.yaml (simulate_summary counted in simulate; the report
    itself aside), in the pipeline's order."""
    import yaml

    from flows.report import COST_STAGES

    stages = [s for s in yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
              if s not in ("simulate_summary", "report")]
    assert [stage for stage, _ in COST_STAGES] == stages


def test_html_page_is_self_contained(tmp_path: Path):
    png = REPORTS / "detect" / "learning_curve.png"
    if not png.is_file():
        pytest.skip("no committed figure")
    shutil.copy(png, tmp_path / "curve.png")
    text = "# T\n\n| a | b |\n| --- | ---: |\n| x | 1 |\n\n![curve](curve.png)\n\n![gone](missing.png)\n"
    page = markdown_to_html(text, tmp_path, "t")
    assert "<table>" in page and "<td>x</td>" in page
    assert page.count("data:image/png;base64,") == 1 and "[figure missing: missing.png]" in page
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", page)  # nothing from the network
    assert "<script" not in page


@pytest.mark.skipif(not (REPORTS / "detect" / "details.json").is_file(), reason="no committed reports")
def test_report_stage_on_the_committed_reports(tmp_path: Path):
    from flows.report import report_flow
    from tests.conftest import tiny_params

    reports = tmp_path / "reports"
    for stage in ("world", "calibrate_fog", "simulate", "simulate_summary", "detect"):
        shutil.copytree(REPORTS / stage, reports / stage)
    data = tmp_path / "data"
    (data / "reference").mkdir(parents=True)
    (data / "reference" / "sealed_truth.json").write_text(json.dumps({"dense": {"alpha": 0.05, "beta": 5e-4}}))
    (data / "world").mkdir()
    (data / "world" / "a.bin").write_bytes(b"x" * 1000)
    (data / "simulate").mkdir()
    (data / "simulate" / "a.bin").hardlink_to(data / "world" / "a.bin")  # a hard link costs nothing twice
    params = tiny_params(data).model_copy(update={"paths": tiny_params(data).paths.model_copy(
        update={"reports": reports})})
    (reports / "severity").mkdir()
    shutil.copy(REPORTS / "world" / "sample_bev.png", reports / "severity" / "snow.png")  # a drawn severity curve
    out = report_flow.fn(params)
    text = (reports / "summary.md").read_text()
    assert "Severity curve: snow (experiments from dvc exp show)" in text
    for heading in ("## Findings", "## Table 1", "## ReDAM", "Table 2", "Table 3", "## What the run cost"):
        assert heading in text
    assert out["findings_total"] == len(json.loads((REPORTS / "detect" / "details.json").read_text())["differences"])
    assert "| world | — | 0.00 GB |" in text and "| simulate | — | 0.00 GB |" in text  # 1000 bytes, counted once
    dense = json.loads((REPORTS / "calibrate_fog" / "details.json").read_text())["dense"]["alpha"]
    assert f"{dense / 0.05 - 1:+.1%}" in text
    page = (reports / "summary.html").read_text()
    assert page.count("data:image/png;base64,") == out["figures"] >= 4
    assert json.loads((reports / "report" / "details.json").read_text())["findings"] == out["findings"]
    assert json.loads((reports / "report" / "metrics.json").read_text())["findings_total"] == out["findings_total"]
    assert "needs the `verify` stage, which did not run" in text
    (reports / "verify").mkdir()
    (reports / "verify" / "details.json").write_text(json.dumps({"conditions": {}}))
    (reports / "verify" / "table.md").write_text("# Table 1 regenerated\n\n## Ours\n\n| | snow |\n|---|---|\n")
    report_flow.fn(params)
    text = (reports / "summary.md").read_text()
    assert "### Table 1 regenerated" in text and "#### Ours" in text and "did not run" not in text
    shutil.rmtree(reports / "detect")
    with pytest.raises(DataFormatError, match=r"detect/details.json: missing; run the stage detect first"):
        report_flow.fn(params)


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (make test installs Debian's chromium)")
def test_a_real_browser_renders_the_page_with_everything_embedded(tmp_path: Path):
    """Headless Chromium with every network request sent to a dead proxy: the page it parsed has the tables and
    every figure as an embedded image, and its screenshot shows them (not a blank page)."""
    import subprocess

    import numpy as np
    from PIL import Image

    figures = [p for p in (REPORTS / "detect" / "learning_curve.png", REPORTS / "simulate_summary" / "summary.png")
               if p.is_file()]
    if not figures:
        pytest.skip("no committed figures")
    for p in figures:
        shutil.copy(p, tmp_path / p.name)
    text = "# Summary\n\n| a | b |\n| --- | ---: |\n| x | 1 |\n\n" + "".join(f"![{p.stem}]({p.name})\n\n"
                                                                       for p in figures)
    page = tmp_path / "summary.html"
    page.write_text(markdown_to_html(text, tmp_path, "t"))
    base = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--proxy-server=http://127.0.0.1:9",
            "--user-data-dir=" + str(tmp_path / "profile")]
    dom = subprocess.run([*base, "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120).stdout
    srcs = re.findall(r'<img[^>]*src="([^"]{0,30})', dom)
    assert len(srcs) == len(figures) and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert "<table>" in dom and "<td>x</td>" in dom
    shot = tmp_path / "shot.png"
    subprocess.run([*base, "--window-size=1000,1600", f"--screenshot={shot}", page.as_uri()], capture_output=True,
                   timeout=120, check=True)
    pixels = np.asarray(Image.open(shot).convert("L"), dtype=np.float64)
    assert (pixels < 128).mean() > 0.02  # text, table lines and the figures are drawn
