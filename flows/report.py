"""`report` stage: ``reports/summary.md`` and ``reports/summary.html`` (the same, one self-contained page).

``python -m flows.report`` reads the stages' ``details.json`` (world, calibrate_fog, simulate_summary,
detect), the detect stage's Tables 2 and 3, the reference's sealed truth where the reference is synthetic, the
figures the stages drew, what each stage cost (wall time of its latest tracked MLflow run, disk of its outputs) and
where each table came from (that MLflow run and its DVC experiment), and writes the summary (`weatheralign.report`).
``reports/report/details.json`` holds the findings with their intervals, ``metrics.json`` their counts. A stage
whose figures are missing is an error naming the stage to run.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from prefect import flow

from flows.common import parse_stage_args, run_stage
from tasks.tracking import StageTracker, mlflow_run_url, tracking_client
from weatheralign import atomic
from weatheralign.config import Params
from weatheralign.data.errors import read_json_file
from weatheralign.manifest import manifest_path, read_manifest
from weatheralign.report import StageCost, StageSource, findings, markdown_to_html, summary_markdown

STAGES_READ = {"world": "world", "calibrate_fog": "calibrate_fog", "simulate": "simulate_summary", "detect": "detect"}
"""Per stage whose figures the summary reads, the folder of its ``details.json`` under ``paths.reports`` (``simulate``:
the summary of its ten variants)."""

COST_STAGES: tuple[tuple[str, str | None], ...] = (
    ("world", "world"), ("reference", "reference"), ("calibrate_fog", None), ("calibrate_precipitation", None),
    ("particles", None), ("media", None), ("simulate", "simulate"), ("verify", None), ("detect", "detect"))
"""(stage, its folder under ``paths.data`` or None) in pipeline order, for the cost table: every stage of
``dvc.yaml`` but ``simulate_summary`` (counted in ``simulate``) and ``report`` itself."""

FIGURES: tuple[tuple[str, str], ...] = (
    ("A world sample: LiDAR BEV with boxes", "world/sample_bev.png"),
    ("LiDAR intensity ECDFs: reference vs tuned simulation (dense fog)", "calibrate_fog/ecdf_dense.png"),
    ("Every condition: LiDAR point labels and re-projection error", "simulate_summary/summary.png"),
    ("Snow, aligned: LiDAR BEV and CAM_FRONT", "simulate/snow-aligned/side_by_side.png"),
    ("Fog (dense), aligned: LiDAR BEV and CAM_FRONT", "simulate/fog_dense-aligned/side_by_side.png"),
    ("Fused features of real and simulated snow (verify)", "verify/embedding_snow.png"),
    ("MMD² permutation tests, dense fog (verify)", "verify/permutations_fog_dense.png"),
    ("LiDAR intensity ECDFs, reference vs simulation, every verified condition", "verify/ecdf.png"),
    ("Detector learning curve (clean val)", "detect/learning_curve.png"),
    ("Detector predictions in BEV", "detect/predictions_bev.png"),
)
"""(caption, path under ``paths.reports``) of the figures shown when present."""


def disk_bytes(folder: Path, seen: set[tuple[int, int]]) -> int:
    """Bytes of the regular files under ``folder`` not counted before (by device and inode, so hard links to files
    of an earlier stage cost nothing); 0 for a missing folder."""
    total = 0
    for root, _, files in os.walk(folder):
        for name in files:
            st = os.lstat(os.path.join(root, name))
            key = (st.st_dev, st.st_ino)
            if key not in seen:
                seen.add(key)
                total += st.st_size
    return total


def latest_stage_runs(params: Params) -> dict[tuple[str, str], Any]:
    """Per (``stage`` tag, run name) the latest finished MLflow stage run (the ten simulate variants are ten runs of
    the stage simulate); empty when tracking is off or nothing was tracked."""
    if not params.tracking.enabled:
        return {}
    client = tracking_client(params, Path.cwd())
    exp = client.get_experiment_by_name(params.tracking.experiment)
    if exp is None:
        return {}
    latest: dict[tuple[str, str], Any] = {}
    for run in client.search_runs([exp.experiment_id], "attributes.status = 'FINISHED' AND tags.kind = 'stage'",
                                  max_results=5000, order_by=["attributes.start_time ASC"]):
        stage, name = run.data.tags.get("stage"), run.data.tags.get("mlflow.runName", "")
        if stage:
            latest[(stage, name)] = run
    return latest


def summary_stage(stage: str) -> str:
    """The stage a run's ``stage`` tag counts under in the summary (``simulate_summary`` under ``simulate``)."""
    return "simulate" if stage == "simulate_summary" else stage


def stage_seconds(runs: dict[tuple[str, str], Any]) -> dict[str, float]:
    """Per stage the wall seconds of its latest runs (the simulate variants and their summary summed into
    ``simulate``)."""
    out: dict[str, float] = {}
    for (stage, _), run in runs.items():
        if "stage_seconds" in run.data.metrics:
            base = summary_stage(stage)
            out[base] = out.get(base, 0.0) + run.data.metrics["stage_seconds"]
    return out


def stage_sources(runs: dict[tuple[str, str], Any]) -> dict[str, StageSource]:
    """Per stage whose tables the summary shows (``simulate``: its summary run) the latest run's name, MLflow UI page
    and DVC experiment (``workspace`` outside ``dvc exp run``)."""
    out: dict[str, StageSource] = {}
    for (stage, name), run in runs.items():
        if stage == "simulate" or stage == "report":
            continue
        base = summary_stage(stage)
        experiment = run.data.tags.get("dvc_experiment", "none")
        out[base] = StageSource(base, name, mlflow_run_url(run.info.experiment_id, run.info.run_id),
                                "workspace" if experiment == "none" else experiment)
    return out


def run_costs(params: Params, runs: dict[tuple[str, str], Any]) -> list[StageCost]:
    """Wall time (of ``runs``, `latest_stage_runs`) and disk use per stage."""
    seconds = stage_seconds(runs)
    seen: set[tuple[int, int]] = set()
    costs = []
    for stage, folder in COST_STAGES:
        disk = disk_bytes(params.paths.data / folder, seen) if folder else None
        costs.append(StageCost(stage, seconds.get(stage), disk))
    return costs


def read_inputs(params: Params) -> tuple[dict[str, dict[str, Any]], dict[str, Any] | None, list[str]]:
    """The stages' figures, the sealed truth (None unless the reference is synthetic) and the detect tables."""
    reports = params.paths.reports
    metrics = {s: read_json_file(reports / folder / "details.json",
                                 f"run the stage {folder} first (dvc repro {folder})")
               for s, folder in STAGES_READ.items()}
    truth_path = params.paths.data / "reference" / "sealed_truth.json"
    truth = read_json_file(truth_path, "") if truth_path.is_file() else None
    tables = [(reports / "detect" / name).read_text() for name in ("table_alignment.md", "table_finetune.md")
              if (reports / "detect" / name).is_file()]
    rates = reports / "calibrate_precipitation" / "details.json"
    if rates.is_file():  # ReDAM for snow and rain
        metrics["calibrate_precipitation"] = read_json_file(rates, "")
    verify = reports / "verify" / "details.json"
    if verify.is_file():  # Table 1's MMD half (the verify stage)
        metrics["verify"] = read_json_file(verify, "run the stage verify first (dvc repro verify)")
        metrics["verify"]["table_markdown"] = (reports / "verify" / "table.md").read_text()
    return metrics, truth, tables


def dataset_digests(data: Path) -> dict[str, str]:
    """Manifest name -> content digest of every dataset the stages handed on (``data/manifests/*.json``)."""
    folder = manifest_path(data, "world").parent
    return {path.stem: read_manifest(path).content_digest for path in sorted(folder.glob("*.json"))}


def severity_figures(reports: Path) -> dict[str, str]:
    """The severity curves ``python -m flows.severity curve`` drew from ``dvc exp show`` (``reports/severity/*.png``),
    caption -> path under ``reports``. They are made outside the pipeline, so DVC does not track them as a dependency:
    ``dvc repro -f report`` after drawing one."""
    return {f"Severity curve: {p.stem} (experiments from dvc exp show)": f"severity/{p.name}"
            for p in sorted((reports / "severity").glob("*.png"))}


HEADLINE = ("findings_total", "findings_exceeding_noise")
"""The figures of reports/report/metrics.json (the figure count and the page's size in details.json and MLflow)."""


def headline(details: dict) -> dict:
    """The `HEADLINE` figures of the report's details."""
    return {k: details[k] for k in HEADLINE}


@flow(name="report", log_prints=True)
def report_flow(params: Params) -> dict:
    """Write reports/summary.md, reports/summary.html and reports/report/{details,metrics}.json; returns the
    details."""
    with StageTracker(params, "report") as tracker:
        metrics, truth, tables = read_inputs(params)
        reports = params.paths.reports
        figures = {caption: path for caption, path in FIGURES if (reports / path).is_file()}
        figures.update(severity_figures(reports))
        runs = latest_stage_runs(params)
        text = summary_markdown(metrics, truth, tables, figures, run_costs(params, runs), stage_sources(runs),
                                dataset_digests(params.paths.data))
        atomic.write_text(reports / "summary.md", text)
        page = markdown_to_html(text, reports, "weatheralign: run summary")
        atomic.write_text(reports / "summary.html", page)
        found = findings(metrics["detect"])
        out = {"findings": found, "findings_total": len(found),
               "findings_exceeding_noise": sum("(exceeds the noise)" in f for f in found),
               "figures": len(figures), "html_bytes": len(page.encode())}
        tracker.log_artifact(reports / "summary.md")
        tracker.log_artifact(reports / "summary.html")
        tracker.finish(out, headline(out), logged={k: v for k, v in out.items() if k != "findings"})
    return out


def main(argv: list[str] | None = None) -> dict:
    return run_stage(report_flow, parse_stage_args("report", argv), runner=None)


if __name__ == "__main__":
    main()
