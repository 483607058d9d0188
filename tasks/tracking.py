"""One helper that writes a stage's figures (``reports/<name>/details.json``, every figure the stage measured, and
``reports/<name>/metrics.json``, its headline scalars: the DVC metrics that ``dvc exp show`` and ``dvc metrics diff``
compare) and logs the numbers, params, figures, input datasets and models to MLflow.

Runs. One parent run per pipeline run (``kind = pipeline``), found by the pipeline id: ``WEATHERALIGN_PIPELINE_ID``
(set by ``make reproduce``), else DVC's ``DVC_EXP_NAME``; a stage run on its own gets a fresh parent. Under it one run
per stage run (``kind = stage``; the ten simulate variants are ten of them) and, under those, one child per condition,
level, model, evaluation or comparison. Every run carries the tags of `TAG_KEYS` (``none`` where one does not apply),
so the MLflow UI groups and filters the ablations by tag; metric names never contain a condition (the same
``points_lost`` or ``map`` in every condition's run), so its compare view charts them across runs.

MLflow is used through `MlflowClient` (no active-run global state); the store is a sqlite file in the repository
unless ``tracking.mlflow_uri`` or ``MLFLOW_TRACKING_URI`` say otherwise, artifacts go to ``mlartifacts/`` beside it.
A sqlite store is checked when a stage starts (`check_tracking_store`): one that cannot be written or is not a
database ends the stage at once with one line naming the file and ``tracking.mlflow_uri``.
Detector checkpoints are saved as MLflow PyTorch models and registered in the model registry (`ChildRun.log_model`).

In the Prefect UI, ``finish`` leaves on the stage's flow run a table artifact of its headline figures and a link
artifact to its MLflow run (`publish_prefect_artifacts`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import sqlite3
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from weatheralign import atomic
from weatheralign.config import ConfigError, Params

TAG_KEYS = ("stage", "kind", "weather", "alignment", "severity", "model", "pipeline_id", "git_commit",
            "dvc_experiment")
"""Tags on every run (``none`` where one does not apply)."""
NOT_APPLICABLE = "none"
REGISTERED_MODEL_PREFIX = "weatheralign-detector-"
MLFLOW_UI_URL = "http://127.0.0.1:5000"
"""Where `make mlflow-ui` serves the MLflow UI (``MLFLOW_UI_URL`` in the environment overrides it): the Prefect link
artifacts point there."""
SYSTEM_METRICS_INTERVAL_S = 10.0
EXPERIMENT_KIND_TAG, EXPERIMENT_KIND = "mlflow.experimentKind", "custom_model_development"
HEADLINE_LIMIT = 40
"""Most scalars of a stage's ``metrics.json`` (its headline figures, one ``dvc exp show`` column each) and rows of its
Prefect table artifact."""
Scalar = int | float | str | bool | None


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


def numeric_leaves(tree: dict[str, Any]) -> dict[str, float]:
    """The int / float leaves of ``tree`` (flattened with dots; booleans and None left out) as floats."""
    return {k: float(v) for k, v in flatten(tree).items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def git_state(repo: Path) -> tuple[str, bool | None]:
    """(HEAD commit, whether tracked files differ from it) of the git work tree at ``repo``; ``("none", None)``
    outside one."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10)
        if sha.returncode != 0:
            return NOT_APPLICABLE, None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=repo,
                               capture_output=True, text=True, timeout=30)
        return sha.stdout.strip(), bool(dirty.stdout.strip()) if dirty.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return NOT_APPLICABLE, None


def log_params(client: Any, run_id: str | None, params: dict[str, Any]) -> None:
    """The leaves of ``params`` (nested dicts flattened with dots) as MLflow params of run ``run_id`` (nothing
    without a client)."""
    if client is None:
        return
    from mlflow.entities import Param

    items = [Param(k, str(v)[:6000]) for k, v in sorted(flatten(params).items())]
    for i in range(0, len(items), 100):
        client.log_batch(run_id, params=items[i:i + 100])


def log_metrics(client: Any, run_id: str | None, metrics: dict[str, float], step: int = 0,
                model_id: str | None = None, dataset: tuple[str, str] | None = None) -> None:
    """``metrics`` (name -> number) at ``step`` (nothing without a client), linked to the logged model
    ``model_id`` and the ``dataset`` (name, digest) they measure when given (MLflow's model page lists them)."""
    if client is None:
        return
    from mlflow.entities import Metric

    now = int(time.time() * 1000)
    name, digest = dataset or (None, None)
    items = [Metric(k, float(v), now, step, model_id=model_id, dataset_name=name, dataset_digest=digest)
             for k, v in sorted(metrics.items())]
    for i in range(0, len(items), 500):
        client.log_batch(run_id, metrics=items[i:i + 500])


def tracking_uri(params: Params, repo: Path) -> str:
    return params.tracking.mlflow_uri or os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{repo / 'mlflow.db'}"


STORE_LOCK_TIMEOUT_S = 60.0
"""How long [s] the store check waits for another process's write lock on the sqlite store (another stage's run
writing to it is no fault)."""
SQLITE_PREFIX = "sqlite:///"


def sqlite_store_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///<path>`` tracking URI (relative paths from the working directory, as
    SQLAlchemy reads them); None for any other store (a server, a file store, an in-memory database)."""
    if not uri.startswith(SQLITE_PREFIX):
        return None
    path = uri[len(SQLITE_PREFIX):].split("?", 1)[0]
    return Path(path).absolute() if path and path != ":memory:" else None


def _probe_sqlite_write(path: Path) -> None:
    """Open the existing sqlite database ``path`` for writing and write to it in a transaction that is rolled back
    (a real write: it needs the file and its folder, for the journal, to be writable, which a permission check cannot
    tell for root); raises `sqlite3.Error` when it cannot."""
    con = sqlite3.connect(f"{path.as_uri()}?mode=rw", uri=True, timeout=STORE_LOCK_TIMEOUT_S, isolation_level=None)
    try:
        con.execute("BEGIN IMMEDIATE")
        con.execute("CREATE TABLE weatheralign_write_probe (x INTEGER)")
        con.execute("ROLLBACK")
    finally:
        con.close()


def _probe_new_store(path: Path) -> None:
    """Make sure the store ``path`` (not there yet) can be created: its folder made if missing, a file written in it;
    raises OSError when it cannot (``ENOTDIR`` naming the file that stands where a folder should be)."""
    existing = next(folder for folder in path.parents if folder.exists())
    if not existing.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(existing))
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile(dir=path.parent):
        pass


def check_tracking_store(uri: str) -> None:
    """Fail fast, in one line, on a sqlite tracking store MLflow could not use: a file or folder that cannot be
    written (MLflow would retry, then end in a traceback of hundreds of lines) or a file that is not an SQLite
    database (an SQLAlchemy traceback); other stores are left to MLflow.

    Raises:
        ConfigError: naming the database file and the params key ``tracking.mlflow_uri``.
    """
    path = sqlite_store_path(uri)
    if path is None:
        return
    advice = (f"or point tracking.mlflow_uri (now {uri}) at another sqlite:///<file>, or set tracking.enabled: "
              f"false")
    try:
        if path.exists():
            _probe_sqlite_write(path)
        else:
            _probe_new_store(path)
    except sqlite3.OperationalError as exc:
        raise ConfigError(f"{path}: the MLflow tracking store cannot be written ({exc}); make the file and its "
                          f"folder writable, {advice}") from None
    except sqlite3.DatabaseError as exc:
        raise ConfigError(f"{path}: the MLflow tracking store is not a valid SQLite database ({exc}); move it away "
                          f"(MLflow starts a new one), {advice}") from None
    except OSError as exc:
        where = f": {exc.filename}" if exc.errno == errno.ENOTDIR and exc.filename else ""
        raise ConfigError(f"{path}: the MLflow tracking store cannot be created ({exc.strerror}{where}); its folder "
                          f"{path.parent} must be a writable folder, {advice}") from None


def tracking_client(params: Params, repo: Path) -> Any:
    """An `MlflowClient` of the store `tracking_uri` names, checked first (`check_tracking_store`)."""
    from mlflow.tracking import MlflowClient

    uri = tracking_uri(params, repo)
    check_tracking_store(uri)
    return MlflowClient(tracking_uri=uri)


class StageTracker:
    """Context manager around one stage run. ``finish(details, headline)`` writes details.json and metrics.json and logs
    to MLflow.

    Args:
        stage: the DVC stage (the ``stage`` tag); name: the run's name and its report folder under ``paths.reports``
            (default: ``stage``); tags: more tags of the stage run and its children (``weather``, ``alignment``, ...).
    """

    def __init__(self, params: Params, stage: str, repo: Path | None = None, name: str | None = None,
                 tags: dict[str, str] | None = None) -> None:
        self.params = params
        self.stage = stage
        self.name = name or stage
        self.repo = (repo or Path.cwd()).resolve()
        self.reports = params.paths.reports / self.name
        self.extra_tags = dict(tags or {})
        self.client: Any = None
        self.run_id: str | None = None
        self.parent_id: str | None = None
        self.experiment_id: str | None = None
        self.base_tags: dict[str, str] = {}
        self._system_metrics: Any = None
        self._t0 = time.time()

    def __enter__(self) -> StageTracker:
        self.reports.mkdir(parents=True, exist_ok=True)
        if not self.params.tracking.enabled:
            return self
        self.client = tracking_client(self.params, self.repo)
        exp_name = self.params.tracking.experiment
        exp = self.client.get_experiment_by_name(exp_name)
        self.experiment_id = exp.experiment_id if exp else self.client.create_experiment(
            exp_name, artifact_location=(self.repo / "mlartifacts").as_uri(),
            tags={EXPERIMENT_KIND_TAG: EXPERIMENT_KIND})
        if exp is not None and exp.tags.get(EXPERIMENT_KIND_TAG) != EXPERIMENT_KIND:
            # the UI opens a model-development experiment on its runs, not on the GenAI overview
            self.client.set_experiment_tag(self.experiment_id, EXPERIMENT_KIND_TAG, EXPERIMENT_KIND)
        commit, dirty = git_state(self.repo)
        pipeline = os.environ.get("WEATHERALIGN_PIPELINE_ID") or os.environ.get("DVC_EXP_NAME")
        pipeline = pipeline or f"standalone-{self.name.replace('/', '-')}-{time.strftime('%Y%m%d-%H%M%S')}"
        self.base_tags = {k: NOT_APPLICABLE for k in TAG_KEYS}
        self.base_tags.update({"stage": self.stage, "pipeline_id": pipeline, "git_commit": commit,
                               "dvc_experiment": os.environ.get("DVC_EXP_NAME") or NOT_APPLICABLE,
                               "mlflow.source.git.commit": commit, "git_dirty": str(dirty).lower()})
        self.parent_id = self._parent_run(pipeline)
        tags = {**self.base_tags, "kind": "stage", **self.extra_tags, "mlflow.parentRunId": self.parent_id,
                "mlflow.runName": self.name, "dvc.stage": os.environ.get("DVC_STAGE", NOT_APPLICABLE),
                "prefect.flow_run_id": _prefect_flow_run_id()}
        self.run_id = self.client.create_run(self.experiment_id, tags=tags).info.run_id
        self._system_metrics = start_system_metrics(self.run_id, self.client.tracking_uri)
        return self

    def _parent_run(self, pipeline: str) -> str:
        found = self.client.search_runs([self.experiment_id], filter_string=(
            f"tags.pipeline_id = '{pipeline}' AND tags.kind = 'pipeline'"), max_results=1)
        if found:
            return found[0].info.run_id
        tags = {**self.base_tags, "stage": "pipeline", "kind": "pipeline", "mlflow.runName": f"pipeline {pipeline}"}
        return self.client.create_run(self.experiment_id, tags=tags).info.run_id

    def log_params(self, section: dict[str, Any]) -> None:
        log_params(self.client, self.run_id, section)

    def log_artifact(self, path: Path, folder: str | None = None) -> None:
        if self.client is not None:
            self.client.log_artifact(self.run_id, str(path), folder)

    def log_dataset(self, name: str, digest: str, source: str, context: str) -> None:
        """Record a dataset this stage read as an MLflow dataset input of its run (``context``: e.g. ``source``,
        ``reference``, ``training``, ``evaluation``; ``digest``: the dataset's content digest)."""
        if self.client is None:
            return
        from mlflow.entities import Dataset, DatasetInput, InputTag

        dataset = Dataset(name=name, digest=digest, source_type="local", source=source)
        self.client.log_inputs(self.run_id, datasets=[DatasetInput(dataset, [InputTag("mlflow.data.context",
                                                                                      context)])])

    def tag_model_version(self, registered_name: str, version: str, tags: dict[str, str]) -> None:
        """Set ``tags`` (e.g. an evaluation's ``map.<dataroot>``) on a registered model version."""
        if self.client is not None:
            for key, value in tags.items():
                self.client.set_model_version_tag(registered_name, version, key, value)

    def finish(self, details: dict[str, Any], headline: dict[str, Any], logged: dict[str, float] | None = None,
               children: dict[str, tuple[dict[str, str], dict[str, Any]]] | None = None,
               metrics_file: bool = True) -> None:
        """Write ``reports/<name>/details.json`` = ``details`` and, with ``metrics_file`` (the stage declares DVC
        metrics), ``reports/<name>/metrics.json`` = ``headline`` (checked by `check_headline`; also the Prefect
        table artifact), and log to MLflow: ``logged`` (default: every numeric leaf of ``headline``) on the stage
        run, and per entry ``label: (tags, values)`` of ``children`` a child run ``<name>/<label>`` with those tags
        and the numeric leaves of ``values`` (so a per-condition or per-level figure keeps one name across runs)."""
        check_headline(headline, self.name)
        atomic.write_json(self.reports / "details.json", details, indent=2)
        if metrics_file:
            atomic.write_json(self.reports / "metrics.json", headline, indent=2)
        run_url = None if self.client is None else mlflow_run_url(self.experiment_id, self.run_id)
        publish_prefect_artifacts(self.name, headline, run_url)
        if self.client is None:
            return
        for label, (tags, values) in (children or {}).items():
            with self.child(f"{self.name}/{label}", {"kind": "condition", **tags}) as run:
                run.log_metrics(values)
        numeric = numeric_leaves(headline) if logged is None else dict(logged)
        numeric["stage_seconds"] = time.time() - self._t0
        log_metrics(self.client, self.run_id, numeric)
        for name in ("metrics.json", "details.json") if metrics_file else ("details.json",):
            self.client.log_artifact(self.run_id, str(self.reports / name))

    def child(self, name: str, tags: dict[str, str]) -> ChildRun:
        """A nested MLflow run under this stage's run (one condition, training, evaluation or comparison) with the
        stage run's tags overridden by ``tags`` (e.g. ``kind``, ``model``, ``weather``, ``alignment``)."""
        if self.client is None:
            return ChildRun(None, None)
        run_tags = {**self.base_tags, **self.extra_tags, **{k: str(v) for k, v in tags.items()},
                    "mlflow.parentRunId": self.run_id, "mlflow.runName": name}
        return ChildRun(self.client, self.client.create_run(self.experiment_id, tags=run_tags).info.run_id)

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if self._system_metrics is not None:
            with contextlib.suppress(Exception):
                self._system_metrics.finish()
        if self.client is not None and self.run_id is not None:
            status = "FAILED" if exc_type else "FINISHED"
            self.client.set_terminated(self.run_id, status)
            self.client.set_terminated(self.parent_id, status)  # reopened by the next stage's child if any


@dataclass(frozen=True)
class PyfuncModel:
    """An MLflow pyfunc model from code, as `ChildRun.log_model` logs it: the entry file ``code`` (it calls
    ``mlflow.models.set_model``), its ``artifacts`` (name -> local file), the folders shipped beside it
    (``code_paths``), its pinned ``requirements``, an input ``example`` with the model's ``output`` on it and the
    inference ``params`` (for the signature), the logged model's ``name`` and the registered model's
    ``description``."""

    name: str
    code: Path
    artifacts: dict[str, str]
    code_paths: tuple[str, ...]
    requirements: tuple[str, ...]
    example: Any
    output: Any
    params: dict[str, Any]
    description: str = ""


@dataclass(frozen=True)
class LoggedDetector:
    """A detector logged and registered by `ChildRun.log_model`: its registry version and MLflow logged-model id."""

    version: str
    model_id: str


class ChildRun:
    """A nested MLflow run (`StageTracker.child`); every method does nothing when tracking is off."""

    def __init__(self, client: Any, run_id: str | None) -> None:
        self.client, self.run_id = client, run_id

    def log_params(self, params: dict[str, Any]) -> None:
        log_params(self.client, self.run_id, params)

    def log_metrics(self, metrics: dict[str, Any], step: int = 0, model_id: str | None = None,
                    dataset: tuple[str, str] | None = None) -> None:
        """Numeric leaves of ``metrics`` (nested dicts flattened with dots) at ``step``, linked to a logged model and
        a dataset (name, digest) when given (`log_metrics`)."""
        log_metrics(self.client, self.run_id, numeric_leaves(metrics), step, model_id, dataset)

    def log_artifact(self, path: Path, folder: str | None = None) -> None:
        if self.client is not None:
            self.client.log_artifact(self.run_id, str(path), folder)

    def log_model(self, model: PyfuncModel, registered_name: str, aliases: tuple[str, ...] = ()
                  ) -> LoggedDetector | None:
        """Log ``model`` (a pyfunc from code, `PyfuncModel`) to this run as an MLflow logged model with a signature
        inferred from its input example and its output on it (the example is logged too), register it as a new
        version of ``registered_name`` (created if new) and point ``aliases`` (e.g. ``seed0``; ``@latest`` is
        MLflow's own: the newest version) at it. Returns its version and logged-model id (None when tracking is off).
        Load it with ``mlflow.pyfunc.load_model("models:/<name>@latest")``."""
        if self.client is None:
            return None
        import mlflow
        from mlflow.exceptions import MlflowException
        from mlflow.models import infer_signature

        mlflow.set_tracking_uri(self.client.tracking_uri)
        with mlflow.start_run(run_id=self.run_id):
            info = mlflow.pyfunc.log_model(
                name=model.name, python_model=str(model.code), artifacts=dict(model.artifacts),
                code_paths=list(model.code_paths), pip_requirements=list(model.requirements),
                signature=infer_signature(model.example, model.output, dict(model.params)),
                input_example=(model.example, dict(model.params)))
        try:
            self.client.create_registered_model(registered_name, description=model.description)
        except MlflowException as exc:
            if exc.error_code != "RESOURCE_ALREADY_EXISTS":
                raise
        version = self.client.create_model_version(registered_name, info.model_uri, run_id=self.run_id,
                                                   model_id=info.model_id)
        for alias in aliases:
            self.client.set_registered_model_alias(registered_name, alias, version.version)
        return LoggedDetector(str(version.version), info.model_id)

    def close(self, failed: bool = False) -> None:
        if self.client is not None:
            self.client.set_terminated(self.run_id, "FAILED" if failed else "FINISHED")

    def __enter__(self) -> ChildRun:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self.close(failed=exc_type is not None)


def check_headline(headline: dict[str, Any], stage: str) -> None:
    """A ValueError unless ``headline`` is a tree of scalars (numbers, strings, booleans, None) with at most
    `HEADLINE_LIMIT` leaves: a stage's DVC metrics stay one screen of ``dvc exp show`` columns."""
    leaves = flatten(headline)
    bad = [k for k, v in leaves.items() if not isinstance(v, Scalar)]
    if bad:
        raise ValueError(f"{stage}: headline metrics must be scalars; {bad[:3]} are not (put them in details.json)")
    if len(leaves) > HEADLINE_LIMIT:
        raise ValueError(f"{stage}: {len(leaves)} headline metrics, at most {HEADLINE_LIMIT} "
                         "(the rest belongs in details.json)")


def headline_rows(metrics: dict[str, Any], limit: int = HEADLINE_LIMIT) -> list[dict[str, str]]:
    """A stage's headline figures as table rows ``{"figure", "value"}``: the scalar leaves of ``metrics`` (numbers,
    strings, booleans; lists left out), shallowest first, at most ``limit``; numbers to 4 significant digits."""
    leaves = [(key, value) for key, value in flatten(metrics).items()
              if isinstance(value, (int, float, str, bool)) and value is not None]
    leaves.sort(key=lambda kv: kv[0].count("."))  # stable: the file's order within a depth
    return [{"figure": key, "value": f"{value:.4g}" if isinstance(value, float) else str(value)}
            for key, value in leaves[:limit]]


def start_system_metrics(run_id: str, tracking_uri: str, interval_s: float = SYSTEM_METRICS_INTERVAL_S) -> Any:
    """MLflow's system metrics (CPU, memory, disk, network; GPU where present) of this process's machine, logged to
    run ``run_id`` every ``interval_s`` until the returned monitor's ``finish()``; None when they cannot be had."""
    try:
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        monitor = SystemMetricsMonitor(run_id, sampling_interval=interval_s, tracking_uri=tracking_uri)
        monitor.start()
        return monitor
    except Exception:  # noqa: BLE001 - a view only: never break a stage
        return None


def artifact_key(text: str) -> str:
    """``text`` as a Prefect artifact key (lowercase letters, digits and dashes): ``simulate snow-aligned:
    samples`` -> ``simulate-snow-aligned-samples``."""
    return "-".join("".join(c if c.isalnum() else " " for c in text.lower()).split())


def mlflow_run_url(experiment_id: str | None, run_id: str | None) -> str:
    """The MLflow UI page of a run (`MLFLOW_UI_URL`), in the model-training workflow (without it MLflow 3's UI
    shows a browser that never chose one the GenAI sidebar; mlflow/mlflow#24498)."""
    base = os.environ.get("MLFLOW_UI_URL", MLFLOW_UI_URL).rstrip("/")
    return f"{base}/#/experiments/{experiment_id}/runs/{run_id}?workflowType=machine_learning"


def publish_prefect_artifacts(name: str, metrics: dict[str, Any], mlflow_url: str | None) -> None:
    """On the current Prefect flow run (none: nothing): a table artifact ``<name>-figures`` of `headline_rows` and,
    with ``mlflow_url``, a link artifact ``<name>-mlflow`` to the stage's MLflow run. A view only: an API error is
    ignored."""
    try:
        from prefect.artifacts import create_link_artifact, create_table_artifact
        from prefect.context import FlowRunContext

        if FlowRunContext.get() is None:
            return
        key = artifact_key(name)
        create_table_artifact(headline_rows(metrics), key=f"{key}-figures",
                              description=f"{name}: headline figures (all of them: reports/{name}/details.json)")
        if mlflow_url:
            create_link_artifact(mlflow_url, link_text=f"MLflow run of {name}", key=f"{key}-mlflow",
                                 description=f"{name}: params, metrics, figures and models in MLflow")
    except Exception:  # noqa: BLE001 - the Prefect views must never break a stage
        return


def _prefect_flow_run_id() -> str:
    try:
        from prefect.runtime import flow_run

        return str(flow_run.id or "")
    except Exception:  # noqa: BLE001 - tracking must never break a stage
        return ""
