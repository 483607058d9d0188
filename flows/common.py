"""What every stage flow shares: the command line, the task runner, the flow run's name and tags in the Prefect UI,
progress over mapped tasks (a console bar and a Prefect progress artifact)."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from prefect.futures import PrefectFuture, as_completed
from prefect.task_runners import TaskRunner, ThreadPoolTaskRunner
from tqdm import tqdm

from tasks.tracking import artifact_key
from weatheralign.atomic import DiskFullError
from weatheralign.config import ConfigError, Params, load_params
from weatheralign.data.errors import DataFormatError


def parse_stage_args(stage: str, argv: Sequence[str] | None = None) -> Params:
    """``--params FILE`` (default params.yaml) and repeatable ``--set key=value`` overrides -> validated `Params`."""
    parser = argparse.ArgumentParser(prog=f"python -m flows.{stage}", description=f"Run the '{stage}' stage.")
    parser.add_argument("--params", default="params.yaml", help="params YAML file (default: params.yaml)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override any params key, e.g. --set world.num_train_scenes=2 (repeatable)")
    args = parser.parse_args(argv)
    try:
        return load_params(args.params, args.overrides)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


EXPECTED_ERRORS = (DataFormatError, ConfigError, DiskFullError)
"""Errors about the user's data, params or disk: one clear line, no traceback (unless ``WEATHERALIGN_VERBOSE=1``)."""


class _NoTracebackForExpectedErrors(logging.Filter):
    """On the console, Prefect's records of an expected error (`EXPECTED_ERRORS`) are dropped: the stage prints the
    error itself, first and once. The run's log in the Prefect API keeps them, traceback included."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, EXPECTED_ERRORS):
            return False
        message = record.getMessage()
        return not any(f"{cls.__name__}(" in message or f"{cls.__name__}:" in message for cls in EXPECTED_ERRORS)


def _verbose() -> bool:
    return os.environ.get("WEATHERALIGN_VERBOSE") == "1"


def _quiet_console() -> None:
    from prefect.logging.configuration import setup_logging

    setup_logging()  # Prefect configures its handlers lazily: do it now so that the console handler exists
    for handler in logging.getLogger().handlers + logging.getLogger("prefect").handlers:
        if isinstance(handler, logging.StreamHandler) and not any(
                isinstance(f, _NoTracebackForExpectedErrors) for f in handler.filters):
            handler.addFilter(_NoTracebackForExpectedErrors())


@dataclass(frozen=True)
class RunLabel:
    """How a stage's flow run shows in the Prefect UI: its ``name`` (``simulate/snow-aligned``) and ``tags``
    (``stage:simulate``, ``condition:snow``, ``alignment:aligned``), by which the UI's run list filters."""

    name: str
    tags: tuple[str, ...] = ()

    @classmethod
    def of_stage(cls, stage: str, **labels: str) -> RunLabel:
        """``stage`` with ``labels`` (e.g. ``condition="snow", alignment="aligned"``): named ``stage/<values joined
        by '-'>`` (the stage alone without labels), tagged ``stage:<stage>`` and ``<key>:<value>`` per label."""
        name = f"{stage}/{'-'.join(labels.values())}" if labels else stage
        return cls(name, (f"stage:{stage}", *(f"{k}:{v}" for k, v in labels.items())))


def run_stage(flow: Any, params: Params, runner: Literal["processes", "threads"] | None = "processes",
              label: RunLabel | None = None) -> Any:
    """Run a stage's flow: SIGTERM / SIGHUP end it cleanly, and its Prefect API is ``PREFECT_API_URL`` or a server
    of its own that cannot outlive it (`flows.prefect_server`); ``runner``: its tasks on Dask worker processes
    (`task_runner`), on a thread pool of ``run.max_workers`` (tasks that share large in-memory inputs and release
    the interpreter lock), or None for the flow's default. The flow run is named and tagged by ``label`` (default:
    the flow's name and ``stage:<name>``).

    A `DataFormatError`, `ConfigError` or `DiskFullError` (`EXPECTED_ERRORS`), raised in the flow or in a task on a
    worker process, ends the stage with ``error: <message>`` on stderr and exit code 2, without Prefect's traceback
    on the console (set ``WEATHERALIGN_VERBOSE=1`` to see it; the Prefect UI has it anyway).
    """
    from prefect import tags
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from flows.prefect_server import install_signal_handlers, prefect_api

    label = label or RunLabel.of_stage(flow.name)
    # a run name is a template of the flow's parameters: braces in a label are literal
    flow = flow.with_options(flow_run_name=label.name.replace("{", "{{").replace("}", "}}"))
    verbose = _verbose()
    install_signal_handlers()
    if not verbose:
        _quiet_console()
    try:
        with prefect_api() as url:
            settings = temporary_settings(updates={PREFECT_API_URL: url}) if url else contextlib.nullcontext()
            with settings:
                if runner == "processes":
                    flow = flow.with_options(task_runner=task_runner(params))
                elif runner == "threads":
                    flow = flow.with_options(task_runner=ThreadPoolTaskRunner(max_workers=params.run.max_workers))
                with worker_environment(), tags(*label.tags):
                    return flow(params)
    except EXPECTED_ERRORS as err:
        if verbose:
            raise
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def worker_environment() -> contextlib.AbstractContextManager:
    """The environment of the local Dask cluster's worker processes while it is in force: distributed's defaults
    (one BLAS / OpenMP thread per worker) without its ``MALLOC_TRIM_THRESHOLD_=65536``. glibc freezes the mmap
    threshold at 128 KiB once any malloc threshold is set explicitly, so every image-sized array becomes a fresh
    mmap whose pages fault in zero-filled, for every such array of every sample (mostly system time). Each worker also
    preloads this module (`dask_setup`), so that its console follows the one-line-error rule."""
    import dask

    preload = [*dask.config.get("distributed.worker.preload", []), __name__]
    return dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                            "distributed.worker.preload": list(dict.fromkeys(preload))})


def dask_setup(worker: Any) -> None:
    """Dask's preload hook, run in each worker process as it starts (`worker_environment`): unless
    ``WEATHERALIGN_VERBOSE=1``, the worker's console drops Prefect's records of an expected error (`EXPECTED_ERRORS`)
    as the stage's own does, so that a task failing on bad data ends in the stage's one line, not in the worker's
    traceback (the Prefect API keeps it)."""
    if not _verbose():
        _quiet_console()


SHARED_DASK_ENV = "WEATHERALIGN_DASK_ADDRESS"
"""Environment variable holding the scheduler address of the cluster `flows.api_server --dask` starts for a whole run
(every stage's tasks go to its worker processes, which stay warm between stages)."""


def task_runner(params: Params) -> TaskRunner:
    """Dask: the scheduler at ``run.dask_address`` when set, else that of the run's shared cluster
    (``$WEATHERALIGN_DASK_ADDRESS``, `flows.api_server --dask`), else a `distributed.LocalCluster` of
    ``run.max_workers`` worker processes with one thread each (per-sample work is CPU-bound Python and numpy: threads
    of one process would share its interpreter lock), started with the flow and closed with it."""
    from prefect_dask import DaskTaskRunner

    address = params.run.dask_address or os.environ.get(SHARED_DASK_ENV)
    if address:
        return DaskTaskRunner(address=address)
    return DaskTaskRunner(cluster_class="distributed.LocalCluster", cluster_kwargs=local_cluster_kwargs(params))


def local_cluster_kwargs(params: Params) -> dict[str, Any]:
    """`distributed.LocalCluster` arguments: ``run.max_workers`` processes x 1 thread, no dashboard, memory limit
    shared out of the machine's, the cluster's own start-up chatter kept off the console (warnings still shown)."""
    return {"n_workers": params.run.max_workers, "threads_per_worker": 1, "processes": True,
            "dashboard_address": None, "memory_limit": "auto", "silence_logs": logging.WARNING}


def threads_per_task(params: Params) -> int:
    """Native threads each concurrent task may use so that workers x threads ~ the machine's cores."""
    return max(1, (os.cpu_count() or 2) // params.run.max_workers)


class ProgressArtifact:
    """A Prefect progress artifact of the current flow run (the run page's Artifacts tab shows its percentage),
    updated as work completes, at most every ``step_percent``; nothing outside a flow run. Artifacts are a view:
    an API error is ignored, never ends the stage."""

    def __init__(self, description: str, total: float, step_percent: float = 2.0) -> None:
        from prefect.context import FlowRunContext

        self.total, self.step, self.done, self.shown = max(float(total), 1.0), step_percent, 0.0, 0.0
        self.artifact_id = None
        if FlowRunContext.get() is None:
            return
        from prefect.artifacts import create_progress_artifact

        with contextlib.suppress(Exception):
            self.artifact_id = create_progress_artifact(0.0, key=artifact_key(description), description=description)

    def advance(self, amount: float) -> None:
        """``amount`` more of ``total`` done."""
        self.done += amount
        percent = min(100.0, 100.0 * self.done / self.total)
        if self.artifact_id is None or (percent - self.shown < self.step and percent < 100.0):
            return
        from prefect.artifacts import update_progress_artifact

        with contextlib.suppress(Exception):
            update_progress_artifact(self.artifact_id, percent)
            self.shown = percent


def gather(futures: Iterable[PrefectFuture], desc: str, show: bool,
           on_result: Callable[[int, Any], None] | None = None, weights: Sequence[int] | None = None) -> list[Any]:
    """Results of mapped task futures in submission order, with a progress bar as they complete (advancing by each
    task's ``weights`` entry, e.g. the samples of a chunk; 1 per task by default) and a `ProgressArtifact` named
    ``desc``; ``on_result(i, result)`` as the i-th future completes."""
    futures = list(futures)
    order = {id(f): i for i, f in enumerate(futures)}
    results: list[Any] = [None] * len(futures)
    steps = list(weights) if weights is not None else [1] * len(futures)
    progress = ProgressArtifact(desc, sum(steps))
    with tqdm(total=sum(steps), desc=desc, disable=not show, unit="sample" if weights is not None else "task") as bar:
        for fut in as_completed(futures):
            value = fut.result()
            i = order[id(fut)]
            results[i] = value
            if on_result is not None:
                on_result(i, value)
            bar.update(steps[i])
            progress.advance(steps[i])
    return results
