"""The aligned-vs-unaligned comparison from MLflow: ``python -m flows.compare`` (what the MLflow UI shows).

The detect stage logs every evaluation as an MLflow run tagged ``kind=eval``, ``model``, ``weather``, ``alignment``
(``aligned`` / ``unaligned``; ``none`` for clean val) and ``modality``, with the same metric names in every run
(``map``, ``nds``, ...). This reads them back with ``mlflow.search_runs`` (the latest run of each model, weather,
alignment and modality) and prints, per model and weather, the metric on the aligned and the unaligned copy and their
difference, so the dashboard and the report (``reports/detect/table_alignment.md``) can be checked against each
other. In the MLflow UI: experiment ``weatheralign``, search ``tags.kind = 'eval' and tags.model = 'pretrained'``,
select the runs, Compare, and group by the ``weather`` and ``alignment`` tags.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def eval_runs(tracking_uri: str, experiment: str, modality: str = "fused") -> list[dict[str, Any]]:
    """The latest evaluation run per (model, weather, alignment, training seed) of ``modality``: dicts of their tags
    and metrics.

    Raises:
        LookupError: no such experiment, or no evaluation runs in it.
    """
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=tracking_uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise LookupError(f"{tracking_uri}: no MLflow experiment {experiment!r} (run the pipeline first)")
    runs = client.search_runs([exp.experiment_id], f"tags.kind = 'eval' AND tags.modality = '{modality}'",
                              max_results=50000, order_by=["attributes.start_time ASC"])
    latest: dict[tuple[str, str, str, str], dict[str, Any]] = {}
    for run in runs:
        tags = run.data.tags
        latest[(tags.get("model", ""), tags.get("weather", ""), tags.get("alignment", ""), tags.get("seed", ""))] = {
            **{k: tags.get(k) for k in ("model", "weather", "alignment", "seed")}, **run.data.metrics}
    if not latest:
        raise LookupError(f"{tracking_uri}: no evaluation runs (tags.kind = 'eval') in experiment {experiment!r}")
    return list(latest.values())


def comparison(runs: list[dict[str, Any]], metric: str = "map") -> list[tuple[str, str, float, float]]:
    """(model, weather, aligned, unaligned) ``metric`` for every model and weather evaluated both ways, averaged over
    the training seeds evaluated (as the detect stage's tables), sorted."""
    table: dict[tuple[str, str], dict[str, list[float]]] = {}
    for r in runs:
        if r["alignment"] in ("aligned", "unaligned") and metric in r:
            table.setdefault((r["model"], r["weather"]), {}).setdefault(r["alignment"], []).append(float(r[metric]))
    return sorted((m, w, sum(v["aligned"]) / len(v["aligned"]), sum(v["unaligned"]) / len(v["unaligned"]))
                  for (m, w), v in table.items() if "aligned" in v and "unaligned" in v)


def render(rows: list[tuple[str, str, float, float]], metric: str) -> str:
    """The comparison as a Markdown table."""
    lines = [f"| model | weather | aligned {metric} | unaligned {metric} | unaligned - aligned |",
             "| --- | --- | ---: | ---: | ---: |"]
    lines += [f"| {m} | {w} | {a:.3f} | {u:.3f} | {u - a:+.3f} |" for m, w, a, u in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flows.compare", description=__doc__.split("\n\n")[0])
    parser.add_argument("--tracking-uri", default=os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{REPO}/mlflow.db",
                        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI, else the repository's mlflow.db)")
    parser.add_argument("--experiment", default="weatheralign")
    parser.add_argument("--metric", default="map", help="metric name as logged (map, nds, map_present, ...)")
    parser.add_argument("--modality", default="fused", choices=["fused", "lidar", "camera"])
    args = parser.parse_args(argv)
    try:
        rows = comparison(eval_runs(args.tracking_uri, args.experiment, args.modality), args.metric)
    except LookupError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(render(rows, args.metric))
    return 0


if __name__ == "__main__":
    sys.exit(main())
