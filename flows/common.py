"""What every stage flow shares: the command line, the task runner, progress over mapped tasks."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from prefect.futures import PrefectFuture, as_completed
from prefect.task_runners import TaskRunner, ThreadPoolTaskRunner
from tqdm import tqdm

from weatheralign.config import ConfigError, Params, load_params


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


def task_runner(params: Params) -> TaskRunner:
    """A bounded thread pool on this machine, or a Dask cluster when ``run.dask_address`` is set."""
    if params.run.dask_address:
        from prefect_dask import DaskTaskRunner

        return DaskTaskRunner(address=params.run.dask_address)
    return ThreadPoolTaskRunner(max_workers=params.run.max_workers)


def threads_per_task(params: Params) -> int:
    """Native threads each concurrent task may use so that workers x threads ~ the machine's cores."""
    return max(1, (os.cpu_count() or 2) // params.run.max_workers)


def gather(futures: Iterable[PrefectFuture], desc: str, show: bool, on_result: Callable[[Any], None] | None = None,
           ) -> list[Any]:
    """Results of mapped task futures in submission order, with a progress bar as they complete."""
    futures = list(futures)
    order = {id(f): i for i, f in enumerate(futures)}
    results: list[Any] = [None] * len(futures)
    with tqdm(total=len(futures), desc=desc, disable=not show, unit="task") as bar:
        for fut in as_completed(futures):
            value = fut.result()
            results[order[id(fut)]] = value
            if on_result is not None:
                on_result(value)
            bar.update(1)
    return results
