"""The whole pipeline as one Prefect flow: every dvc.yaml stage as a subflow, in dvc.yaml's dependency order.

dvc.yaml is the one list of stages: `stage_runs` reads each stage's command (``python -m flows.<stage> --set ...``),
expands the ``matrix`` stages (``simulate@<condition>-<alignment>``) and `pipeline_flow` calls each stage module's
``main`` with those arguments, the run's ``params_file`` and ``overrides`` added. Each stage thus runs exactly as
`dvc repro` runs it (its own task runner, its own MLflow run, its resume records), as a subflow that the Prefect UI
shows under the pipeline's run. ``stages`` picks some of them (a stage name selects all its matrix entries). With
the repository's ``params.yaml`` and no overrides, a stage that ``dvc status`` finds up to date when its turn comes
(after the stages before it have run) is skipped, as `dvc repro` skips it, unless ``force``.

A run with the repository's ``params.yaml`` and no overrides records what it made in DVC (``dvc commit`` of the stages
it ran: their code, params and outputs are exactly what `dvc repro` would have produced), so ``dvc status`` stays
clean; a run with other params does not (its outputs no longer match dvc.yaml's params: the next ``dvc repro`` redoes
those stages, and each stage's own fingerprints make it recompute rather than reuse).

``python -m flows.pipeline [--stages world reference ...] [--params FILE] [--set key=value ...]`` runs it from a
shell with one Prefect API server for every stage (`flows.prefect_server`); `flows.serve` serves it for the UI.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import itertools
import json
import os
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from prefect import flow
from prefect.artifacts import create_markdown_artifact

REPO = Path(__file__).resolve().parents[1]
DVC_YAML = REPO / "dvc.yaml"
DEFAULT_PARAMS = "params.yaml"


@dataclass(frozen=True)
class StageRun:
    """One stage as `dvc repro` runs it: its DVC name (``simulate@snow-aligned``), the flow module and its
    arguments (``--set`` pairs from dvc.yaml's command)."""

    name: str
    module: str
    argv: tuple[str, ...]

    @property
    def base(self) -> str:
        """The stage's name without its matrix entry (``simulate``)."""
        return self.name.split("@", 1)[0]


def _command(stage: str, cmd: str, item: dict[str, Any]) -> tuple[str, tuple[str, ...]]:
    """(module, arguments) of ``cmd`` (``python -m <module> ...``) with ``${item.<key>}`` filled in from ``item``."""
    text = re.sub(r"\$\{item\.(\w+)\}", lambda m: str(item[m.group(1)]), cmd)
    words = shlex.split(text)
    if len(words) < 3 or words[:2] != ["python", "-m"]:
        raise ValueError(f"{DVC_YAML.name}: stage {stage!r}: cmd {cmd!r}; expected 'python -m flows.<stage> ...'")
    return words[2], tuple(words[3:])


def stage_runs(dvc_yaml: Path = DVC_YAML) -> list[StageRun]:
    """Every stage of ``dvc_yaml`` in its order (matrix stages expanded in the order of their matrix, first key
    outermost, named as DVC names them)."""
    stages = yaml.safe_load(dvc_yaml.read_text())["stages"]
    runs: list[StageRun] = []
    for stage, spec in stages.items():
        matrix = spec.get("matrix")
        if not matrix:
            runs.append(StageRun(stage, *_command(stage, spec["cmd"], {})))
            continue
        keys = list(matrix)
        for values in itertools.product(*(matrix[k] for k in keys)):
            item = dict(zip(keys, values))
            name = f"{stage}@{'-'.join(str(v) for v in values)}"
            runs.append(StageRun(name, *_command(name, spec["cmd"], item)))
    return runs


def select(runs: list[StageRun], stages: list[str] | None) -> list[StageRun]:
    """The ``runs`` named in ``stages`` (a stage name selects every matrix entry of it), in pipeline order; all when
    ``stages`` is None or empty.

    Raises:
        ValueError: a name that is no stage of the pipeline (the message lists them).
    """
    if not stages:
        return list(runs)
    known = {r.name for r in runs} | {r.base for r in runs}
    unknown = [s for s in stages if s not in known]
    if unknown:
        raise ValueError(f"unknown stage(s) {unknown}; the pipeline's stages are "
                         f"{sorted({r.base for r in runs})} and the matrix entries "
                         f"{[r.name for r in runs if '@' in r.name]}")
    wanted = set(stages)
    return [r for r in runs if r.name in wanted or r.base in wanted]


def _scalars(metrics: Any, limit: int = 6) -> str:
    """A few top-level numbers of a stage's metrics, for the run's artifact table."""
    if not isinstance(metrics, dict):
        return ""
    items = [(k, v) for k, v in metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in items[:limit])


def _dvc() -> str:
    """The dvc command of this interpreter's environment (else the one on PATH)."""
    dvc = Path(sys.executable).parent / "dvc"
    return str(dvc) if dvc.exists() else "dvc"


def up_to_date(name: str, repo: Path = REPO) -> bool:
    """Whether ``dvc status`` in ``repo`` finds the stage ``name`` itself (not its upstream stages) up to date: its
    code, params, inputs and outputs as dvc.lock records them. False when dvc cannot tell (the stage then runs)."""
    proc = subprocess.run([_dvc(), "status", "--json", name], cwd=repo, capture_output=True, text=True)
    if proc.returncode != 0:
        return False
    try:
        return not json.loads(proc.stdout or "{}")
    except json.JSONDecodeError:
        return False


def _record_in_dvc(names: list[str]) -> str:
    """``dvc commit`` the stages ``names``; returns what happened (for the artifact)."""
    if not names:
        return "nothing run: nothing to record in DVC"
    proc = subprocess.run([_dvc(), "commit", "-f", "-q", *names], cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        return f"dvc commit failed ({proc.returncode}): {proc.stderr.strip()[-500:]}"
    return f"recorded in DVC: {len(names)} stage(s)"


@flow(name="pipeline", log_prints=True)
def pipeline_flow(stages: list[str] | None = None, params_file: str = DEFAULT_PARAMS,
                  overrides: list[str] | None = None, record_in_dvc: bool = True, force: bool = False
                  ) -> dict[str, Any]:
    """Run the pipeline's stages (all, or those named in ``stages``: ``world``, ``simulate``,
    ``simulate@snow-aligned``, ...) in dvc.yaml's order, each as a subflow, with ``params_file`` (relative to the
    repository) and ``overrides`` (``key=value``, as ``--set``); with the repository's params and no overrides,
    those `up_to_date` are skipped unless ``force``. Returns the metrics of each stage run.

    Raises:
        ValueError: an unknown stage name.
        RuntimeError: a stage failed (its own subflow run has the log); later stages do not run.
    """
    runs = select(stage_runs(), stages)
    overrides = list(overrides or [])
    params_path = Path(params_file) if Path(params_file).is_absolute() else REPO / params_file
    default = params_path.resolve() == (REPO / DEFAULT_PARAMS).resolve() and not overrides
    results: dict[str, Any] = {}
    rows = ["| stage | seconds | metrics |", "| --- | ---: | --- |"]
    for run in runs:
        if default and not force and up_to_date(run.name):
            print(f"pipeline: {run.name} is up to date (dvc status): skipped")
            rows.append(f"| {run.name} | — | up to date (dvc status), not run |")
            continue
        argv = ["--params", str(params_path), *run.argv, *(a for o in overrides for a in ("--set", o))]
        print(f"pipeline: {run.name}")
        t0 = time.perf_counter()
        try:
            results[run.name] = importlib.import_module(run.module).main(argv)
        except SystemExit as exit_:
            raise RuntimeError(f"stage {run.name} failed (exit code {exit_.code}); "
                               "its subflow run has the log") from None
        rows.append(f"| {run.name} | {time.perf_counter() - t0:.1f} | {_scalars(results[run.name])} |")
    recorded = _record_in_dvc(list(results)) if record_in_dvc and default else \
        "not recorded in DVC (other params than params.yaml, or record_in_dvc off)"
    create_markdown_artifact(key="pipeline-stages", markdown="\n".join(
        [f"# weatheralign pipeline: {len(runs)} stage(s)", "", f"params: `{params_file}`" +
         (f", overrides: `{' '.join(overrides)}`" if overrides else ""), "", *rows, "", recorded]),
        description="Stages run, their time and headline metrics")
    return results


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """``python -m flows.pipeline``: the pipeline with one Prefect API server for every stage."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from flows.prefect_server import install_signal_handlers, prefect_api

    parser = argparse.ArgumentParser(prog="python -m flows.pipeline", description=__doc__.split("\n\n")[0])
    parser.add_argument("--stages", nargs="*", default=None, help="stages to run (default: all), e.g. world simulate")
    parser.add_argument("--params", default=DEFAULT_PARAMS, help="params YAML file (default: params.yaml)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override any params key (repeatable)")
    parser.add_argument("--no-dvc-record", action="store_true", help="do not dvc-commit the stages run")
    parser.add_argument("--force", action="store_true", help="run the stages even where dvc status finds them up "
                        "to date")
    args = parser.parse_args(argv)
    install_signal_handlers()
    with prefect_api() as url:
        if url:
            os.environ["PREFECT_API_URL"] = url  # the stages' own run_stage reuses it
        with temporary_settings(updates={PREFECT_API_URL: url}) if url else contextlib.nullcontext():
            try:
                return pipeline_flow(args.stages, args.params, args.overrides, not args.no_dvc_record, args.force)
            except (ValueError, RuntimeError) as err:
                print(f"error: {err}", file=sys.stderr)
                raise SystemExit(2) from None


if __name__ == "__main__":
    main()
