"""Scale-out benchmark: the `simulate` stage on a `distributed.LocalCluster` of 1, 2, ... worker processes.

Run from the repository root after ``dvc repro media`` (world, fields, fog calibration, media):
``.venv/bin/python -m benchmarks.bench_scaling [--workers 1 2] [--samples 48] [--conditions fog_dense-aligned
snow-aligned]``. Each point runs ``python -m flows.simulate`` (`benchmarks.bench_simulate.run_condition`) with
``run.max_workers = n`` on the first ``--samples`` samples into a scratch copy, and reports samples per minute of the
whole command (Prefect, cluster start-up and completion of the copy included), the stage's own rate (its tasks only)
and the scaling efficiency ``rate(n) / (n rate(1))``. On a machine with more cores (the device machine: 16), pass
``--workers 1 2 4 8 16``.

A projection for nuScenes-trainval (34,149 keyframes, 6 cameras, the same sweeps through the weather) follows from the
measured CPU seconds per sample: CPU-hours per condition, next to MultiCorrupt's 12 h of LiDAR snow on 32 CPUs
(384 CPU-hours, LiDAR only). Results go to ``reports/benchmarks/scaling.json`` with the machine they were measured on.
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path
from typing import Any

from benchmarks.bench_simulate import run_condition
from weatheralign.atomic import write_json

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "scaling.json"
TRAINVAL_KEYFRAMES = 34_149
MULTICORRUPT_CPU_HOURS = 12.0 * 32


def machine() -> dict[str, Any]:
    """Where the figures were measured."""
    return {"cpu_count": os.cpu_count(), "platform": platform.platform(), "processor": platform.processor(),
            "python": platform.python_version(), "load_average": os.getloadavg()}


def projection(cpu_seconds_per_sample: float) -> dict[str, float]:
    """nuScenes-trainval at the measured CPU cost per sample: CPU-hours, and the ratio to MultiCorrupt's LiDAR snow."""
    hours = cpu_seconds_per_sample * TRAINVAL_KEYFRAMES / 3600.0
    return {"trainval_cpu_hours": hours, "trainval_hours_on_32_cpus": hours / 32.0,
            "multicorrupt_snow_cpu_hours": MULTICORRUPT_CPU_HOURS,
            "ratio_to_multicorrupt": MULTICORRUPT_CPU_HOURS / hours if hours > 0 else None}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--samples", type=int, default=48)
    parser.add_argument("--conditions", nargs="+", default=["fog_dense-aligned", "snow-aligned"])
    parser.add_argument("--scratch", type=Path, default=Path("/tmp/weatheralign-bench-scaling"))
    parser.add_argument("--out", type=Path, default=REPORT)
    args = parser.parse_args(argv)
    results: dict[str, Any] = {"machine": machine(), "samples": args.samples, "conditions": {}}
    for name in args.conditions:
        points = []
        for n in args.workers:
            e = run_condition(name, args.scratch, ["--set", f"run.max_workers={n}",
                                                   "--set", f"simulate.max_samples={args.samples}"])
            points.append({"workers": n, "samples_per_minute": e["samples_per_minute"],
                           "wall_seconds": e["wall_seconds"], "cpu_seconds_per_sample": e["cpu_seconds_per_sample"],
                           "cpu_seconds_command": e["cpu_seconds_command"]})
            print(f"{name:20s} {n:2d} workers: {e['samples_per_minute']:6.1f} samples/min "
                  f"({e['wall_seconds']:.1f} s, {e['cpu_seconds_per_sample']} CPU-s/sample)", flush=True)
        base = points[0]["samples_per_minute"] / points[0]["workers"]
        for p in points:
            p["efficiency"] = p["samples_per_minute"] / (p["workers"] * base)
        cpu = min(p["cpu_seconds_per_sample"] for p in points)
        results["conditions"][name] = {"points": points, "projection": projection(cpu)}
    write_json(args.out, results, indent=2)
    print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main()
