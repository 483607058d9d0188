"""`dvc exp show` stays readable: its table has a column per params.yaml key, per leaf of every declared metrics file
and per dependency path of dvc.yaml, all of them shown with ``--only-changed`` off. These tests count them from
dvc.yaml, params.yaml and the committed metrics files (which the next run rewrites with the same keys: the flows'
tests check each ``metrics.json`` is its stage's `headline`), so the table cannot grow unnoticed; one test checks the
count against ``dvc exp show --json`` itself where DVC and the repository's git metadata are at hand."""

from __future__ import annotations

import itertools
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]

FIXED_COLUMNS = ("Experiment", "Created")
"""The table's own columns before the data ones (``--csv`` adds ``rev``, ``typ`` and ``parent``)."""

COLUMN_BUDGET = 200
"""Most columns of ``dvc exp show --no-pager`` for the default pipeline (fixed, metrics, params and deps): params.yaml
holds the knobs compared across experiments (the fixed setup in the configs/ files it names: one dep column each),
dvc.yaml each stage's code by package folder and its inputs by folder where a stage reads all of one."""

METRICS_BUDGET = 70
"""Most metrics columns: the headline figures a reader compares between experiments."""


def _leaves(node: Any, prefix: str = "", nulls: bool = True) -> list[str]:
    """Dotted keys of a nested mapping's leaves, as DVC names its columns (a list is one value; ``nulls`` False:
    None leaves left out, as DVC leaves them out of metrics)."""
    if isinstance(node, dict) and node:
        return [k for key, value in node.items() for k in _leaves(value, f"{prefix}{key}.", nulls)]
    return [prefix[:-1]] if prefix and (nulls or node is not None) else []


def _resolve(text: str, tree: dict[str, Any]) -> str:
    """``${a.b}`` of dvc.yaml's templating, from ``tree`` (params.yaml and a matrix entry's ``item``)."""
    def value(m: re.Match) -> str:
        node: Any = tree
        for part in m.group(1).split("."):
            node = node[part]
        return str(node)

    return re.sub(r"\$\{\s*([\w.]+)\s*\}", value, text)


def _entries(path: Any) -> list[str]:
    """The paths of a dvc.yaml list of deps / metrics (plain strings or one-key mappings with options)."""
    return [next(iter(p)) if isinstance(p, dict) else p for p in path or []]


def stage_instances() -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(stage definition, templating tree) for every stage of dvc.yaml, matrix entries expanded."""
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    out = []
    for stage in yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"].values():
        matrix = stage.get("matrix") or {}
        for combo in itertools.product(*matrix.values()):
            out.append((stage, {**params, "item": dict(zip(matrix, combo))}))
    return out


def columns() -> dict[str, list[str]]:
    """The data columns of ``dvc exp show`` for the workspace: params, metrics (``file:key``) and deps."""
    params = _leaves(yaml.safe_load((REPO / "params.yaml").read_text()))
    metrics, deps = [], []
    for stage, tree in stage_instances():
        for path in _entries(stage.get("metrics")):
            file = _resolve(path, tree)
            metrics += [f"{file}:{key}" for key in _leaves(json.loads((REPO / file).read_text()), nulls=False)]
        deps += [Path(_resolve(d, tree)).as_posix() for d in _entries(stage.get("deps"))]
    return {"metrics": list(dict.fromkeys(metrics)), "params": params, "deps": list(dict.fromkeys(deps))}


def test_exp_show_fits_its_budget() -> None:
    cols = columns()
    counts = {kind: len(names) for kind, names in cols.items()}
    total = len(FIXED_COLUMNS) + sum(counts.values())
    print(f"dvc exp show: {total} columns ({len(FIXED_COLUMNS)} fixed, {counts})")
    assert total <= COLUMN_BUDGET, (f"dvc exp show has {total} columns (budget {COLUMN_BUDGET}): {counts}; move "
                                    f"fixed setup out of params.yaml (configs/), figures out of metrics.json "
                                    f"(details.json)")
    assert counts["metrics"] <= METRICS_BUDGET, f"{counts['metrics']} metrics columns, at most {METRICS_BUDGET}"


def test_every_declared_metrics_file_is_small_and_scalar() -> None:
    """A metrics file is a handful of scalars: every leaf a number, a boolean, a string or None."""
    for stage, tree in stage_instances():
        for path in _entries(stage.get("metrics")):
            data = json.loads((REPO / _resolve(path, tree)).read_text())

            def scalars(node: Any) -> list[Any]:
                return [v for x in node.values() for v in scalars(x)] if isinstance(node, dict) else [node]

            bad = [v for v in scalars(data) if isinstance(v, (list, dict))]
            assert not bad, f"{path}: lists in a metrics file ({bad[:2]}): they belong in details.json"


def test_count_agrees_with_dvc_exp_show() -> None:
    """The count above is what ``dvc exp show --json`` reports for the workspace (run where DVC and git are)."""
    dvc = Path(sys.executable).parent / "dvc"
    if not dvc.exists() or shutil.which("git") is None or not (REPO / ".dvc").is_dir():
        pytest.skip("needs DVC beside the interpreter and the repository's .dvc and git metadata")
    run = subprocess.run([str(dvc), "exp", "show", "--no-pager", "--json"], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    if run.returncode != 0:
        pytest.skip(f"dvc exp show failed here: {run.stderr[-300:]}")
    workspace = next(row for row in json.loads(run.stdout) if row["rev"] == "workspace")["data"]
    shown = {"params": [k for f in workspace["params"].values() for k in _leaves(f.get("data", {}))],
             "metrics": [f"{file}:{k}" for file, f in workspace["metrics"].items() for k in _leaves(f.get("data", {}))],
             "deps": list(workspace["deps"])}
    ours = columns()
    for kind in ("params", "metrics", "deps"):
        assert sorted(shown[kind]) == sorted(ours[kind]), kind


def test_committed_metrics_are_the_headlines_of_the_committed_details() -> None:
    """Each committed ``metrics.json`` is what its stage's `headline` writes from the committed ``details.json`` (the
    count above is the count of a run's, and no stage's metrics drift from its details)."""
    import flows.calibrate_fog
    import flows.calibrate_precipitation
    import flows.detect
    import flows.media
    import flows.particles
    import flows.reference
    import flows.report
    import flows.simulate
    import flows.verify
    import flows.world
    from weatheralign.conditions import CONDITIONS

    reports = REPO / yaml.safe_load((REPO / "params.yaml").read_text())["paths"]["reports"]

    def read(path: str) -> Any:
        return json.loads((reports / path).read_text())

    for module in (flows.world, flows.reference, flows.calibrate_fog, flows.calibrate_precipitation, flows.particles,
                   flows.verify, flows.report):
        stage = module.__name__.split(".")[-1]
        assert read(f"{stage}/metrics.json") == module.headline(read(f"{stage}/details.json")), stage
    assert not (reports / "media" / "metrics.json").exists(), "media declares no metrics: a stale file"
    flows.media.headline(read("media/details.json"))  # still the Prefect table of the stage
    details = read("detect/details.json")
    finetuned = [c for c in CONDITIONS if f"finetuned-{c}" in details["models"]]
    assert read("detect/metrics.json") == flows.detect.headline(details, finetuned)
    variants = sorted(p.name for p in (reports / "simulate").iterdir() if (p / "details.json").is_file())
    assert len(variants) == 2 * len(CONDITIONS)
    for variant in variants:
        assert read(f"simulate/{variant}/metrics.json") == flows.simulate.headline(
            read(f"simulate/{variant}/details.json")), variant
