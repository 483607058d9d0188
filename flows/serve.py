"""Serve the pipeline for the Prefect UI: ``python -m flows.serve`` (``make serve``).

Deployments of `flows.pipeline.pipeline_flow`: ``pipeline/all`` (every stage) and one per stage of dvc.yaml
(``pipeline/world``, ``pipeline/simulate``, ...), each a "Run" form in the UI with typed parameters: the stages (a
stage name, or a matrix entry such as ``simulate@snow-aligned``), the params file, ``key=value`` overrides (e.g.
``simulate.condition=snow``, ``detect.seed=1``) and whether to record the run in DVC. Runs execute in subprocesses of
this process, in the repository, one at a time (``--limit``): the stages share two cores.

It serves against the API at ``PREFECT_API_URL``, by default the server of ``make prefect-ui``
(http://127.0.0.1:4200/api), and stops with a clear message when none answers.
"""

from __future__ import annotations

import argparse
import os
import sys

import httpx

from flows.pipeline import pipeline_flow, stage_runs

DEFAULT_API = "http://127.0.0.1:4200/api"


def deployments() -> list:
    """``all`` and one deployment per stage of dvc.yaml (in its order)."""
    bases = list(dict.fromkeys(r.base for r in stage_runs()))
    out = [pipeline_flow.to_deployment(name="all", description="every stage of dvc.yaml, in order",
                                       tags=["weatheralign", "pipeline"])]
    out += [pipeline_flow.to_deployment(name=b, parameters={"stages": [b]}, description=f"the {b} stage",
                                        tags=["weatheralign", "stage"]) for b in bases]
    return out


def api_answers(url: str) -> bool:
    """Whether a Prefect API at ``url`` answers its health check."""
    try:
        return httpx.get(f"{url.rstrip('/')}/health", timeout=3.0).status_code == 200
    except httpx.HTTPError:
        return False


def main(argv: list[str] | None = None) -> None:
    from prefect import serve

    parser = argparse.ArgumentParser(prog="python -m flows.serve", description=__doc__.split("\n\n")[0])
    parser.add_argument("--limit", type=int, default=1, help="flow runs at once (default 1: they share the cores)")
    args = parser.parse_args(argv)
    url = os.environ.setdefault("PREFECT_API_URL", DEFAULT_API)
    if not api_answers(url):
        print(f"error: no Prefect API answers at {url}: start the UI server first (make prefect-ui, in another "
              f"terminal) or set PREFECT_API_URL", file=sys.stderr)
        raise SystemExit(2)
    print(f"serving {len(deployments())} deployments against {url}; open the UI and press Run on "
          f"pipeline/<stage> (Ctrl-C stops)")
    serve(*deployments(), limit=args.limit)


if __name__ == "__main__":
    main()
