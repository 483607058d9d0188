"""What a stage leaves in the Prefect UI: a named, tagged flow run, its INFO logs and prints, a table artifact of its
headline figures, a link artifact to its MLflow run and a progress artifact, read back through the Prefect API."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from flows.common import RunLabel
from tasks.tracking import HEADLINE_LIMIT, artifact_key, check_headline, headline_rows, mlflow_run_url

from .conftest import REPO

STAGE_SCRIPT = textwrap.dedent('''
    import sys
    from prefect import flow, task
    from prefect.cache_policies import NO_CACHE
    from flows.common import RunLabel, gather, parse_stage_args, run_stage
    from tasks.tracking import StageTracker

    @task(name="square", cache_policy=NO_CACHE)
    def square(x):
        return x * x

    @flow(name="viewcheck", log_prints=True)
    def viewcheck(params):
        with StageTracker(params, "viewcheck", name="viewcheck/snow-aligned") as tracker:
            values = gather([square.submit(i) for i in range(5)], "viewcheck: squares", False)
            print(f"squares {values}")
            tracker.finish({"total": sum(values), "detail": {"first": values[0], "list": values}},
                           {"total": sum(values)})
        return values

    run_stage(viewcheck, parse_stage_args("viewcheck", sys.argv[1:]), runner="threads",
              label=RunLabel.of_stage("viewcheck", condition="snow", alignment="aligned"))
''')


def test_run_label_names_and_tags_a_stage_run():
    label = RunLabel.of_stage("simulate", condition="snow", alignment="unaligned")
    assert label.name == "simulate/snow-unaligned"
    assert label.tags == ("stage:simulate", "condition:snow", "alignment:unaligned")
    assert RunLabel.of_stage("detect") == RunLabel("detect", ("stage:detect",))


def test_headline_rows_shallowest_first_scalars_only_and_capped():
    metrics = {"deep": {"map": 0.123456, "list": [1, 2]}, "samples": 400, "name": "snow", "flag": True,
               "missing": None}
    rows = headline_rows(metrics)
    assert rows == [{"figure": "samples", "value": "400"}, {"figure": "name", "value": "snow"},
                    {"figure": "flag", "value": "True"}, {"figure": "deep.map", "value": "0.1235"}]
    assert len(headline_rows({f"k{i}": i for i in range(100)}, limit=40)) == 40


def test_headline_metrics_are_few_scalars():
    """A stage's metrics.json (one ``dvc exp show`` column per leaf) holds at most `HEADLINE_LIMIT` scalars."""
    check_headline({"clean": {"map": 0.3, "ok": True, "name": "x", "missing": None}}, "detect")
    check_headline({f"k{i}": i for i in range(HEADLINE_LIMIT)}, "detect")
    with pytest.raises(ValueError, match=r"detect: 41 headline metrics, at most 40"):
        check_headline({f"k{i}": i for i in range(HEADLINE_LIMIT + 1)}, "detect")
    with pytest.raises(ValueError, match=r"world: headline metrics must be scalars; \['a.list'\]"):
        check_headline({"a": {"list": [1, 2]}}, "world")


def test_artifact_keys_and_mlflow_links(monkeypatch):
    assert artifact_key("simulate snow-aligned: samples") == "simulate-snow-aligned-samples"
    assert artifact_key("detect/Finetuned_Snow") == "detect-finetuned-snow"
    monkeypatch.setenv("MLFLOW_UI_URL", "http://mlflow.example:5000/")
    assert mlflow_run_url("3", "abc") == ("http://mlflow.example:5000/#/experiments/3/runs/abc"
                                          "?workflowType=machine_learning")


@pytest.mark.flow
def test_a_stage_run_shows_its_name_logs_figures_and_links_in_prefect(tmp_path: Path):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId, LogFilter, LogFilterFlowRunId
    from prefect.server.api.server import SubprocessASGIServer
    from prefect.settings import PREFECT_API_DATABASE_CONNECTION_URL, PREFECT_API_URL, temporary_settings

    # the server's own database: with the project's (make test sets PREFECT_HOME to .prefect) the flow runs of an
    # earlier test run, or of the user's pipeline runs, would be read back too
    server = SubprocessASGIServer()
    with temporary_settings(updates={PREFECT_API_DATABASE_CONNECTION_URL:
                                     f"sqlite+aiosqlite:///{tmp_path / 'prefect.db'}"}):
        server.start(timeout=120)
    try:
        script = tmp_path / "viewcheck.py"
        script.write_text(STAGE_SCRIPT)
        env = {**os.environ, "PYTHONPATH": f"{REPO / 'src'}:{REPO}", "PREFECT_API_URL": server.api_url,
               "PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL": "WARNING"}  # as the Makefile sets it
        env.pop("PREFECT_LOGGING_LEVEL", None)
        proc = subprocess.run([sys.executable, str(script), "--params", str(REPO / "params.yaml"),
                               "--set", f"paths.reports={tmp_path / 'reports'}",
                               "--set", f"tracking.mlflow_uri=sqlite:///{tmp_path / 'mlflow.db'}"],
                              cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "squares" not in proc.stdout + proc.stderr  # the console stays quiet
        with temporary_settings(updates={PREFECT_API_URL: server.api_url}), get_client(sync_client=True) as client:
            runs = [r for r in client.read_flow_runs() if r.name == "viewcheck/snow-aligned"]
            assert len(runs) == 1 and runs[0].state.is_completed()
            run = runs[0]
            assert {"stage:viewcheck", "condition:snow", "alignment:aligned"} <= set(run.tags)
            logs = client.read_logs(LogFilter(flow_run_id=LogFilterFlowRunId(any_=[run.id])))
            artifacts = client.read_artifacts(artifact_filter=ArtifactFilter(
                flow_run_id=ArtifactFilterFlowRunId(any_=[run.id])))
    finally:
        server.stop()
    assert any(log.level == 20 and "squares [0, 1, 4, 9, 16]" in log.message for log in logs)  # a print, at INFO
    by_type = {a.type: a for a in artifacts}
    assert set(by_type) >= {"table", "markdown", "progress"}  # a link artifact is markdown
    table = by_type["table"]
    assert table.key == "viewcheck-snow-aligned-figures"
    assert '"figure": "total"' in str(table.data).replace("'", '"') and "30" in str(table.data)
    link = by_type["markdown"]
    assert link.key == "viewcheck-snow-aligned-mlflow" and "/#/experiments/" in link.data
    assert by_type["progress"].data == 100.0
