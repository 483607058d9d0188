"""World generation benchmark: seconds per keyframe sample of the synthetic world (LiDAR keyframe + sweeps, six
1600 x 900 cameras, annotations, files written) with the pipeline's concurrency, and where one sample's time goes.

Run from the repository root: ``.venv/bin/python -m benchmarks.bench_world [--samples 8] [--workers 2]``. After one
warm-up sample (the first job; numba kernels compile or load from their cache), renders the next ``--samples``
default-config jobs (`sample_jobs`) into a temporary dataroot with a thread pool of ``--workers``, each task with
`threads_per_task` native threads as in the `world` flow. Then renders the first job once more sequentially, and
again part by part by calling the functions `render_sample` calls (checked: the same bytes). Writes
``reports/benchmarks/world.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import numba
import numpy as np
import open3d

from flows.common import threads_per_task
from weatheralign.atomic import write_json
from weatheralign.config import WorldConfig, params_from_dict
from weatheralign.world.build import (SWEEP_PERIOD_US, SceneSpec, sensor_rng, annotate, keyframe_time_us, render_sample,
                                      sensor_filename, write_camera, write_sweep)
from weatheralign.world.dataset import sample_jobs
from weatheralign.world.raycast import WorldRaycaster
from weatheralign.world.render import CameraFrame, pixel_directions, render_lidar_sweep, sun_lit
from weatheralign.sensors import lidar_model_from_params
from weatheralign.world.rig import camera_time_offset, make_cameras
from weatheralign.world.shading import camera_pixels

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "world.json"
TARGET_SECONDS = 3.0  # per sample, throughput of the pipeline's thread pool on 2 cores

T = TypeVar("T")


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far [MiB] (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    return {"cpu_count": os.cpu_count(), "platform": platform.platform(), "processor": platform.processor(),
            "python": platform.python_version(), "numpy": np.__version__, "numba": numba.__version__,
            "open3d": open3d.__version__}


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def throughput(jobs: list[tuple[SceneSpec, int]], cfg: WorldConfig, dataroot: Path, workers: int,
               nthreads: int) -> tuple[float, float]:
    """Wall and CPU seconds to render ``jobs`` with ``workers`` concurrent tasks of ``nthreads`` native threads
    each."""
    t0, cpu0 = time.perf_counter(), cpu_seconds()
    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(lambda job: render_sample(job[0], job[1], cfg, dataroot, nthreads), jobs))
    return time.perf_counter() - t0, cpu_seconds() - cpu0


class Stopwatch:
    """Accumulates wall seconds per named part."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def __call__(self, part: str, fn: Callable[[], T]) -> T:
        t0 = time.perf_counter()
        out = fn()
        self.seconds[part] = self.seconds.get(part, 0.0) + time.perf_counter() - t0
        return out


def breakdown(spec: SceneSpec, k: int, cfg: WorldConfig, dataroot: Path, nthreads: int) -> dict[str, float]:
    """Seconds per part of rendering sample ``k`` of ``spec``, the steps of `render_sample` and `render_camera` in
    their order (same functions, arguments and random streams)."""
    watch = Stopwatch()
    layout = watch("scene (layout, BVHs)", lambda: spec.layout(cfg))
    caster = watch("scene (layout, BVHs)", lambda: WorldRaycaster(layout, nthreads=nthreads))
    pattern = lidar_model_from_params(cfg.lidar).firing_pattern()
    t_key = keyframe_time_us(spec, cfg, k)
    key_sweep = None
    for j in range(cfg.sweeps_per_sample, -1, -1):
        t_us = t_key - j * SWEEP_PERIOD_US
        sweep = watch("lidar sweeps", lambda: render_lidar_sweep(caster, pattern, cfg.lidar, t_us * 1e-6,
                                                                  sensor_rng(spec.seed, t_us % 2**31, 1)))
        fname = sensor_filename("samples" if j == 0 else "sweeps", spec.log_name, "LIDAR_TOP", t_us, "pcd.bin")
        watch("file writing", lambda: write_sweep(dataroot, fname, sweep))
        key_sweep = sweep
    period_us = int(round(1e6 / cfg.lidar.frequency_hz))
    frames = []
    for c, cam in enumerate(make_cameras(cfg.camera.image_scale)):
        t_us = t_key + int(round(camera_time_offset(cam, period_us * 1e-6) * 1e6))
        t = t_us * 1e-6
        rng = sensor_rng(spec.seed, t_us % 2**31, 2 + c)
        T_global_cam = layout.T_global_ego(t) @ cam.T_ego_cam
        origin = T_global_cam[:3, 3]
        dirs = watch("camera ray casting", lambda: pixel_directions(cam, T_global_cam))
        hits = watch("camera ray casting", lambda: caster.cast_camera(cam.K, T_global_cam, cam.width, cam.height, t,
                                                                      dirs))
        lit = watch("camera shadows", lambda: sun_lit(caster, origin, dirs, hits, t, cfg.camera.shadows))
        noise = watch("camera noise (numpy RNG)", lambda: rng.standard_normal(dirs.shape, dtype=np.float32)
                      if cfg.camera.noise_std else None)
        pixels = watch("camera shading + sRGB", lambda: camera_pixels(
            layout, origin, dirs, hits.range, hits.normal, hits.material, hits.albedo, hits.reflectivity, lit, noise,
            cfg.camera.noise_std))
        image = pixels.reshape(cam.height, cam.width, 3)
        frame = CameraFrame(t, image, hits.range.astype(np.float32).reshape(cam.height, cam.width),
                            hits.instance.reshape(cam.height, cam.width))
        fname = sensor_filename("samples", spec.log_name, cam.channel, t_us, "jpg")
        watch("file writing", lambda: write_camera(dataroot, fname, frame, cfg.camera.jpeg_quality))
        frames.append((cam, frame))
    assert key_sweep is not None
    watch("annotations (visibility)", lambda: annotate(layout, key_sweep, frames, t_key * 1e-6, nthreads))
    return watch.seconds


def same_files(a: Path, b: Path) -> bool:
    """Whether the two dataroots hold the same files with the same bytes."""
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    return files_a == files_b and all((a / f).read_bytes() == (b / f).read_bytes() for f in files_a)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=8, help="samples rendered for the throughput (default 8)")
    parser.add_argument("--workers", type=int, default=2, help="concurrent samples (default 2, as the pipeline)")
    parser.add_argument("--out", type=Path, default=REPORT)
    args = parser.parse_args(argv)
    params = params_from_dict({"run": {"max_workers": args.workers}, "tracking": {"enabled": False}})
    cfg = params.world
    nthreads = threads_per_task(params)
    jobs = sample_jobs(cfg)
    timed = [jobs[i % len(jobs)] for i in range(1, args.samples + 1)]
    with tempfile.TemporaryDirectory(prefix="bench_world_") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        render_sample(*jobs[0], cfg, root / "warmup", nthreads)
        warmup = time.perf_counter() - t0
        load = os.getloadavg()[0]
        wall, cpu = throughput(timed, cfg, root / "pool", args.workers, nthreads)
        t0 = time.perf_counter()
        render_sample(*jobs[0], cfg, root / "sequential", nthreads)
        sequential = time.perf_counter() - t0
        parts = breakdown(*jobs[0], cfg, root / "parts", nthreads)
        reproduced = same_files(root / "sequential", root / "parts")
    per_sample = wall / len(timed)
    cameras = make_cameras(cfg.camera.image_scale)
    report = {
        "benchmark": "world generation per keyframe sample",
        "samples": len(timed),
        "workers": args.workers,
        "threads_per_worker": nthreads,
        "seconds_per_sample": per_sample,
        "wall_seconds": wall,
        "cpu_seconds_per_sample": cpu / len(timed),
        "load_average_before": load,  # > 0 when other processes compete for the cores
        "target_seconds_per_sample": TARGET_SECONDS,
        "pass": per_sample <= TARGET_SECONDS,
        "sequential_seconds_one_sample": sequential,
        "warmup_seconds": warmup,
        "breakdown_seconds": parts,
        "breakdown_total_seconds": sum(parts.values()),
        "breakdown_reproduces_render_sample": reproduced,
        "peak_rss_mib": peak_rss_mib(),
        "workload": {"lidar_sweeps": cfg.sweeps_per_sample + 1, "lidar_beams_per_sweep": len(lidar_model_from_params(
            cfg.lidar).ring), "cameras": len(cameras), "image_width_height": [cameras[0].width, cameras[0].height]},
        "machine": machine(),
    }
    print(f"world generation: {per_sample:.2f} s/sample over {len(timed)} samples, {args.workers} workers x "
          f"{nthreads} thread(s)  (target {TARGET_SECONDS:.1f} s: {'PASS' if report['pass'] else 'FAIL'})")
    print(f"one sample sequentially: {sequential:.2f} s; CPU {cpu / len(timed):.2f} s/sample; warm-up {warmup:.1f} s; "
          f"peak RSS {report['peak_rss_mib']:.0f} MiB; {report['machine']['cpu_count']} CPUs, load {load:.2f} before")
    print(f"{'part (one sample, sequential)':32s} {'seconds':>8s} {'share':>6s}")
    total = report["breakdown_total_seconds"]
    for part, sec in parts.items():
        print(f"{part:32s} {sec:8.3f} {sec / total:6.1%}")
    print(f"{'total':32s} {total:8.3f}   (reproduces render_sample bytes: {reproduced})")
    write_json(args.out, report, indent=2)
    print(f"wrote {args.out}")
    return report


if __name__ == "__main__":
    main()
