"""One helper that writes a stage's ``reports/<stage>/metrics.json`` (for DVC) and logs the same numbers, params and
figures to MLflow (one parent run per pipeline run, one child run per stage).

The parent run is found by the pipeline id: ``WEATHERALIGN_PIPELINE_ID`` (set by ``make reproduce``), else DVC's
``DVC_EXP_NAME``; a stage run on its own gets a fresh parent. MLflow is used through `MlflowClient` (no active-run
global state); the store is a sqlite file in the repository unless ``tracking.mlflow_uri`` or
``MLFLOW_TRACKING_URI`` say otherwise, artifacts go to ``mlartifacts/`` beside it.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from weatheralign import atomic
from weatheralign.config import Params

PIPELINE_TAG = "weatheralign.pipeline_id"
STAGE_TAG = "weatheralign.stage"


def flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


def log_params(client: Any, run_id: str | None, params: dict[str, Any]) -> None:
    """The leaves of ``params`` (nested dicts flattened with dots) as MLflow params of run ``run_id`` (nothing
    without a client)."""
    if client is None:
        return
    from mlflow.entities import Param

    items = [Param(k, str(v)[:6000]) for k, v in sorted(flatten(params).items())]
    for i in range(0, len(items), 100):
        client.log_batch(run_id, params=items[i:i + 100])


def tracking_uri(params: Params, repo: Path) -> str:
    return params.tracking.mlflow_uri or os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{repo / 'mlflow.db'}"


class StageTracker:
    """Context manager around one stage run. ``finish(metrics)`` writes metrics.json and logs to MLflow."""

    def __init__(self, params: Params, stage: str, repo: Path | None = None) -> None:
        self.params = params
        self.stage = stage
        self.repo = (repo or Path.cwd()).resolve()
        self.reports = params.paths.reports / stage
        self.client: Any = None
        self.run_id: str | None = None
        self.parent_id: str | None = None
        self._t0 = time.time()

    def __enter__(self) -> "StageTracker":
        self.reports.mkdir(parents=True, exist_ok=True)
        if not self.params.tracking.enabled:
            return self
        from mlflow.tracking import MlflowClient

        self.client = MlflowClient(tracking_uri=tracking_uri(self.params, self.repo))
        name = self.params.tracking.experiment
        exp = self.client.get_experiment_by_name(name)
        exp_id = exp.experiment_id if exp else self.client.create_experiment(
            name, artifact_location=(self.repo / "mlartifacts").as_uri())
        parent = self._parent_run(exp_id)
        self.parent_id = parent
        tags = {"mlflow.parentRunId": parent, STAGE_TAG: self.stage, "mlflow.runName": self.stage,
                "dvc.stage": os.environ.get("DVC_STAGE", ""), "prefect.flow_run_id": _prefect_flow_run_id()}
        self.run_id = self.client.create_run(exp_id, tags=tags).info.run_id
        return self

    def _parent_run(self, exp_id: str) -> str:
        pipeline = os.environ.get("WEATHERALIGN_PIPELINE_ID") or os.environ.get("DVC_EXP_NAME")
        if pipeline:
            found = self.client.search_runs([exp_id], filter_string=f"tags.`{PIPELINE_TAG}` = '{pipeline}'",
                                            max_results=1)
            if found:
                return found[0].info.run_id
        else:
            pipeline = f"standalone-{self.stage}-{time.strftime('%Y%m%d-%H%M%S')}"
        run = self.client.create_run(exp_id, tags={PIPELINE_TAG: pipeline, "mlflow.runName": f"pipeline {pipeline}"})
        return run.info.run_id

    def log_params(self, section: dict[str, Any]) -> None:
        log_params(self.client, self.run_id, section)

    def log_artifact(self, path: Path, folder: str | None = None) -> None:
        if self.client is not None:
            self.client.log_artifact(self.run_id, str(path), folder)

    def finish(self, metrics: dict[str, Any]) -> None:
        """Write ``reports/<stage>/metrics.json`` and log its numeric leaves as MLflow metrics."""
        atomic.write_json(self.reports / "metrics.json", metrics, indent=2)
        if self.client is None:
            return
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        numeric = {k: float(v) for k, v in flatten(metrics).items()
                   if isinstance(v, (int, float)) and not isinstance(v, bool)}
        numeric["stage_seconds"] = time.time() - self._t0
        items = [Metric(k, v, now, 0) for k, v in sorted(numeric.items())]
        for i in range(0, len(items), 500):
            self.client.log_batch(self.run_id, metrics=items[i:i + 500])
        self.client.log_artifact(self.run_id, str(self.reports / "metrics.json"))

    def child(self, name: str, tags: dict[str, str]) -> "ChildRun":
        """A nested MLflow run under this stage's run (one training or one evaluation), tagged with ``tags`` (e.g.
        ``model``, ``weather``, ``alignment``) so that the MLflow UI can group and compare them."""
        if self.client is None:
            return ChildRun(None, None)
        exp_id = self.client.get_run(self.run_id).info.experiment_id
        run_tags = {"mlflow.parentRunId": self.run_id, STAGE_TAG: self.stage, "mlflow.runName": name,
                    **{k: str(v) for k, v in tags.items()}}
        return ChildRun(self.client, self.client.create_run(exp_id, tags=run_tags).info.run_id)

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if self.client is not None and self.run_id is not None:
            status = "FAILED" if exc_type else "FINISHED"
            self.client.set_terminated(self.run_id, status)
            self.client.set_terminated(self.parent_id, status)  # reopened by the next stage's child if any


class ChildRun:
    """A nested MLflow run (`StageTracker.child`); every method does nothing when tracking is off."""

    def __init__(self, client: Any, run_id: str | None) -> None:
        self.client, self.run_id = client, run_id

    def log_params(self, params: dict[str, Any]) -> None:
        log_params(self.client, self.run_id, params)

    def log_metrics(self, metrics: dict[str, Any], step: int = 0) -> None:
        """Numeric leaves of ``metrics`` (nested dicts flattened with dots) at ``step``."""
        if self.client is None:
            return
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, step) for k, v in sorted(flatten(metrics).items())
                 if isinstance(v, (int, float)) and not isinstance(v, bool)]
        for i in range(0, len(items), 500):
            self.client.log_batch(self.run_id, metrics=items[i:i + 500])

    def log_artifact(self, path: Path, folder: str | None = None) -> None:
        if self.client is not None:
            self.client.log_artifact(self.run_id, str(path), folder)

    def close(self, failed: bool = False) -> None:
        if self.client is not None:
            self.client.set_terminated(self.run_id, "FAILED" if failed else "FINISHED")

    def __enter__(self) -> "ChildRun":
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self.close(failed=exc_type is not None)


def _prefect_flow_run_id() -> str:
    try:
        from prefect.runtime import flow_run

        return str(flow_run.id or "")
    except Exception:  # noqa: BLE001 - tracking must never break a stage
        return ""
