"""Scale-out benchmark: the `simulate` stage on a `distributed.LocalCluster` of 1, 2, ... worker processes.

Run from the repository root after ``dvc repro media`` (world, fields, fog calibration, media):
``.venv/bin/python -m benchmarks.bench_scaling [--workers 1 2] [--samples 48] [--conditions fog_dense-aligned
snow-aligned]``. Each point runs ``python -m flows.simulate`` (`benchmarks.bench_simulate.run_condition`) with
``run.max_workers = n`` on the first ``--samples`` samples into a scratch copy, and reports samples per minute of the
whole command (Prefect, cluster start-up and completion of the copy included), the stage's own rate (its tasks only)
and the scaling efficiency ``rate(n) / (n rate(1))``. On a machine with more cores (the device machine: 16), pass
``--workers 1 2 4 8 16``.

``--engine core`` measures the per-sample work alone on the same engine, for machines where the stage cannot run
(the device machine has no Prefect, open3d or package registry): the stage's per-chunk function
(`weatheralign.simulate.weather_copy.run_chunk`, what each Prefect task runs) mapped with ``distributed.Client.submit``
onto a `distributed.LocalCluster` of n single-thread worker processes (distributed's pre-spawn environment without
``MALLOC_TRIM_THRESHOLD_``, as the stage's cluster), over ``--samples`` jobs tiled from the dataset's first samples
(each chunk into a scratch copy of its own, so that no job resumes another's), after one warm-up task per worker
(imports and numba caches). ``--data`` names the folder holding ``manifests/world.json`` and ``media/``.

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


def core_point(name: str, workers: int, samples: int, data: Path, scratch: Path, source_samples: int = 2
               ) -> dict[str, Any]:
    """One point of ``--engine core``: ``samples`` jobs of variant ``name`` (the dataset's first ``source_samples``
    samples, repeated) on a LocalCluster of ``workers``."""
    import shutil
    import time

    import dask
    from distributed import Client, LocalCluster

    from weatheralign.conditions import condition_named
    from weatheralign.config import load_params
    from weatheralign.data.nuscenes import open_nuscenes
    from weatheralign.manifest import manifest_path, read_manifest
    from weatheralign.provenance import stage_fingerprint
    from weatheralign.simulate.media import media_path, read_media
    from weatheralign.simulate.observe import ObserveOptions
    from weatheralign.simulate.plan import plan_jobs
    from weatheralign.simulate.weather_copy import DatasetRef, run_chunk

    condition, _, alignment = name.rpartition("-")
    condition_named(condition)
    params = load_params(REPO / "params.yaml")
    cfg = params.simulate
    world = read_manifest(manifest_path(data, "world"))
    nusc = open_nuscenes(world.dataroot, world.version)
    source = plan_jobs(nusc, read_media(media_path(data, condition)), alignment == "aligned", cfg.rain_appearance,
                       max_samples=source_samples)
    chunk = min(params.run.samples_per_task, len(source))  # distinct samples per chunk: none resumes another
    jobs = [source[i % len(source)] for i in range(samples)]
    chunks = [jobs[i:i + chunk] for i in range(0, len(jobs), chunk)]
    dataset = DatasetRef(str(world.dataroot), world.version, world.content_digest)
    options = ObserveOptions(cfg.near_clip_m, cfg.refine_transmission, 1)
    digest = stage_fingerprint("simulate", params, world.content_digest)
    root = scratch / f"{name}-{workers}"
    shutil.rmtree(root, ignore_errors=True)

    def submit(client: Client, k: int, jobs_k: list) -> Any:
        return client.submit(run_chunk, dataset, root / f"chunk{k}", jobs_k, world.sensors, options, digest,
                             cfg.jpeg_quality, cfg.sweeps, pure=False)

    environ = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
    with dask.config.set(environ), LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                dashboard_address=None) as cluster, Client(cluster) as client:
        client.gather([submit(client, -1 - w, source[:1]) for w in range(workers)])  # imports, numba caches
        t0 = time.perf_counter()
        records = [r for out in client.gather([submit(client, k, c) for k, c in enumerate(chunks)]) for r, _ in out]
        wall = time.perf_counter() - t0
    shutil.rmtree(root, ignore_errors=True)
    cpu = sum(r["cpu_seconds"] for r in records) / len(records)
    return {"workers": workers, "samples_per_minute": 60.0 * len(records) / wall, "wall_seconds": wall,
            "cpu_seconds_per_sample": round(cpu, 3)}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--samples", type=int, default=48)
    parser.add_argument("--conditions", nargs="+", default=["fog_dense-aligned", "snow-aligned"])
    parser.add_argument("--engine", choices=["stage", "core"], default="stage")
    parser.add_argument("--data", type=Path, default=REPO / "data", help="--engine core: manifests/ and media/")
    parser.add_argument("--source-samples", type=int, default=2, help="--engine core: distinct samples to tile")
    parser.add_argument("--scratch", type=Path, default=Path("/tmp/weatheralign-bench-scaling"))
    parser.add_argument("--out", type=Path, default=REPORT)
    args = parser.parse_args(argv)
    results: dict[str, Any] = {"machine": machine(), "samples": args.samples, "engine": args.engine,
                               "conditions": {}}
    for name in args.conditions:
        points = []
        for n in args.workers:
            if args.engine == "core":
                points.append(core_point(name, n, args.samples, args.data, args.scratch, args.source_samples))
                e = points[-1]
                print(f"{name:20s} {n:2d} workers: {e['samples_per_minute']:6.1f} samples/min "
                      f"({e['wall_seconds']:.1f} s, {e['cpu_seconds_per_sample']} CPU-s/sample)", flush=True)
                continue
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
