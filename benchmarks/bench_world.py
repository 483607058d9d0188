"""World generation benchmark: CPU seconds per keyframe sample of the synthetic world (ten LiDAR sweeps, six
1600 x 900 cameras, annotations, files written) with the pipeline's concurrency, and where one sample's time goes.

Run from the repository root: ``.venv/bin/python -m benchmarks.bench_world [--samples 32] [--workers 2]
[--chunk 8] [--set world.key=value ...]``. The world config is the repository's ``params.yaml`` (``--set`` overrides
keys). After one warm-up sample in this process (numba kernels compile or load from their cache), renders
``--samples`` jobs of `sample_jobs` (`timed_jobs`: runs of ``--chunk`` consecutive samples of a scene, as the `world`
flow's tasks take them, from scenes spread over the dataset) into a temporary dataroot with ``--workers`` worker
processes of one thread each (as the flow's Dask workers, each warmed up first), one task per run; a worker process
keeps its scenes (`build.scene_caster`), so a scene is set up once per worker. Reports wall seconds and CPU seconds:
the tasks' own process CPU, and all of the workers' (``RUSAGE_CHILDREN``: start-up and warm-up included); the
projection for the whole world (``num_samples x task CPU / cores``); and a breakdown of one mid-scene sample rendered
part by part in this process by the functions `render_sample` calls (CPU seconds per part, the scene set-up amortised
over its samples; checked: the same bytes as `render_sample`). Writes ``reports/benchmarks/world.json`` and prints a
table.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import platform
import resource
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import numba
import numpy as np
import open3d

from weatheralign.atomic import write_json
from weatheralign.config import WorldConfig, load_params
from weatheralign.world import build
from weatheralign.world.build import (
    SWEEP_PERIOD_US,
    SceneSpec,
    annotate,
    firing_pattern,
    keyframe_time_us,
    render_sample,
    scene_caster,
    sensor_filename,
    sensor_rng,
    write_camera,
    write_sweep,
)
from weatheralign.world.dataset import sample_jobs
from weatheralign.world.raycast import WorldRaycaster
from weatheralign.world.render import CameraFrame, render_lidar_sweep
from weatheralign.world.rig import camera_time_offset, make_cameras
from weatheralign.world.shading import camera_frame, noise_key

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "world.json"
TARGET_CPU_SECONDS = 1.0  # per sample: the mini-scale world (~400 samples) in <= 8 min on 2 cores incl. overheads

T = TypeVar("T")


def peak_rss_mib(who: int = resource.RUSAGE_SELF) -> float:
    """Peak resident set size [MiB] of this process (or its largest waited-for child) (``ru_maxrss`` is in KiB)."""
    return resource.getrusage(who).ru_maxrss / 1024.0


def cpu_seconds(who: int = resource.RUSAGE_SELF) -> float:
    """User + system CPU seconds of this process (or of its terminated, waited-for children) so far."""
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    return {"cpu_count": os.cpu_count(), "platform": platform.platform(), "processor": platform.processor(),
            "python": platform.python_version(), "numpy": np.__version__, "numba": numba.__version__,
            "open3d": open3d.__version__}


def _warm_worker(job: tuple[SceneSpec, int], cfg: WorldConfig, dataroot: Path) -> None:
    """Worker start-up: the job rendered once at a tenth of the image size without sweeps (numba kernels load from
    their cache), so the timed tasks see a worker as the flow's after its first sample."""
    small = cfg.model_copy(update={"sweeps_per_sample": 0,
                                   "camera": cfg.camera.model_copy(update={"image_scale": 0.1})})
    render_sample(*job, small, dataroot / f"warm-{os.getpid()}", 1)
    build._scene_cache.clear()  # the timed tasks set their scenes up themselves


def _render_chunk(jobs: list[tuple[SceneSpec, int]], cfg: WorldConfig, dataroot: Path) -> float:
    """Render ``jobs`` in this worker process (one native thread); returns its process CPU seconds for them."""
    cpu0 = time.process_time()
    for spec, k in jobs:
        render_sample(spec, k, cfg, dataroot, 1)
    return time.process_time() - cpu0


def throughput(jobs: list[tuple[SceneSpec, int]], cfg: WorldConfig, dataroot: Path, workers: int,
               chunk: int) -> dict[str, float]:
    """Render ``jobs`` in tasks of ``chunk`` consecutive samples on ``workers`` fresh worker processes (each warmed up
    by `_warm_worker`): wall seconds of the tasks, the workers' whole CPU seconds (start-up and warm-up included) and
    the tasks' own CPU seconds."""
    chunks = [jobs[i:i + chunk] for i in range(0, len(jobs), chunk)]
    children0 = cpu_seconds(resource.RUSAGE_CHILDREN)
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_warm_worker, initargs=(jobs[0], cfg, dataroot.parent)) as pool:
        list(pool.map(time.sleep, [0.5] * workers))  # every worker started and warm before the clock starts
        t0 = time.perf_counter()
        task_cpu = sum(pool.map(_render_chunk, chunks, [cfg] * len(chunks), [dataroot] * len(chunks)))
        wall = time.perf_counter() - t0
    return {"wall": wall, "cpu": cpu_seconds(resource.RUSAGE_CHILDREN) - children0, "task_cpu": task_cpu}


class Stopwatch:
    """Accumulates CPU seconds (this process: open3d's native threads count too) and wall seconds per part."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {}
        self.wall: dict[str, float] = {}

    def __call__(self, part: str, fn: Callable[[], T]) -> T:
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        self.cpu[part] = self.cpu.get(part, 0.0) + time.process_time() - c0
        self.wall[part] = self.wall.get(part, 0.0) + time.perf_counter() - t0
        return out


def scene_setup(spec: SceneSpec, cfg: WorldConfig) -> tuple[WorldRaycaster, float]:
    """A fresh caster of ``spec`` with its static sun grid built, and the CPU seconds that took."""
    c0 = time.process_time()
    caster = WorldRaycaster(spec.layout(cfg), nthreads=1)
    if cfg.camera.shadows:
        caster.static_sun_grid  # noqa: B018 (built on first use)
    return caster, time.process_time() - c0


def breakdown(spec: SceneSpec, k: int, cfg: WorldConfig, dataroot: Path) -> tuple[dict[str, float], dict[str, float],
                                                                                 dict[str, float]]:
    """CPU and wall seconds per part of rendering sample ``k`` of ``spec``: the steps of `render_sample` and
    `render_camera` in their order (same functions, arguments and random streams) with the scene from
    `scene_caster`; and estimates of what the camera pass spends on shadow rays and noise (the pass again without)."""
    watch = Stopwatch()
    caster = scene_caster(spec, cfg, 1)
    layout = caster.layout
    pattern = firing_pattern(cfg)
    t_key = keyframe_time_us(spec, cfg, k)
    key_sweep = None
    for j in range(cfg.sweeps_per_sample, -1, -1):
        t_us = t_key - j * SWEEP_PERIOD_US
        sweep = watch("lidar sweeps", lambda: render_lidar_sweep(caster, pattern, cfg.lidar, t_us * 1e-6,
                                                                  sensor_rng(spec.seed, t_us % 2**31, 1)))
        fname = sensor_filename("samples" if j == 0 else "sweeps", spec.log_name, "LIDAR_TOP", t_us, "pcd.bin")
        watch("lidar files", lambda: write_sweep(dataroot, fname, sweep))
        key_sweep = sweep
    period_us = int(round(1e6 / cfg.lidar.frequency_hz))
    frames = []
    estimates = {"camera pass without shadow rays": 0.0, "camera pass without noise": 0.0}
    for c, cam in enumerate(make_cameras(cfg.camera.image_scale)):
        t_us = t_key + int(round(camera_time_offset(cam, period_us * 1e-6) * 1e6))
        t = t_us * 1e-6
        rng = sensor_rng(spec.seed, t_us % 2**31, 2 + c)
        T_global_cam = layout.T_global_ego(t) @ cam.T_ego_cam
        inv_depth, gid, tris = watch("camera rasterisation", lambda: caster.camera_depth(
            cam.K, T_global_cam, cam.width, cam.height, t))
        key = noise_key(rng)
        static_grid = caster.static_sun_grid
        moving_grid = watch("camera moving-actor sun grid", lambda: caster.moving_sun_grid(t)
                            if cfg.camera.shadows else None)

        def shade(shadows: bool, noise_std: float) -> tuple:
            return camera_frame(layout, T_global_cam[:3, 3], T_global_cam[:3, :3], cam.K, inv_depth, gid, tris,
                                static_grid, moving_grid, shadows=shadows, key=key, noise_std=noise_std,
                                height=cam.height, width=cam.width)

        image, rng_map, inst = watch("camera pass (shading, shadows, noise, sRGB)",
                                     lambda: shade(cfg.camera.shadows, cfg.camera.noise_std))
        for name, args in (("camera pass without shadow rays", (False, cfg.camera.noise_std)),
                           ("camera pass without noise", (cfg.camera.shadows, 0.0))):
            c0 = time.process_time()
            shade(*args)
            estimates[name] += time.process_time() - c0
        frame = CameraFrame(t, image, rng_map, inst)
        fname = sensor_filename("samples", spec.log_name, cam.channel, t_us, "jpg")
        watch("camera files (JPEG, range map)", lambda: write_camera(dataroot, fname, frame, cfg.camera.jpeg_quality))
        frames.append((cam, frame))
    assert key_sweep is not None
    watch("annotations (visibility)", lambda: annotate(caster, key_sweep, frames, t_key * 1e-6))
    return watch.cpu, watch.wall, estimates


def timed_jobs(jobs: list[tuple[SceneSpec, int]], cfg: WorldConfig, samples: int,
               chunk: int) -> list[tuple[SceneSpec, int]]:
    """``samples`` jobs in runs of ``chunk`` consecutive samples from mid-scene (sample 10 on), the runs taken from
    scenes spread evenly over the dataset (light and heavy streets alike)."""
    per_scene = cfg.samples_per_scene
    scenes = len(jobs) // per_scene
    runs = -(-samples // chunk)
    picked = []
    for r in range(runs):
        scene = int(round(r * (scenes - 1) / max(runs - 1, 1)))
        first = scene * per_scene + min(10, max(per_scene - chunk, 0))
        picked += [jobs[(first + i) % len(jobs)] for i in range(chunk)]
    return picked[:samples]


def same_files(a: Path, b: Path) -> bool:
    """Whether the two dataroots hold the same files with the same bytes."""
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    return files_a == files_b and all((a / f).read_bytes() == (b / f).read_bytes() for f in files_a)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=32, help="samples rendered for the throughput (default 32)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2, as the pipeline)")
    parser.add_argument("--chunk", type=int, default=8, help="consecutive samples per task (default 8)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", type=Path, default=REPORT)
    args = parser.parse_args(argv)
    params = load_params(REPO / "params.yaml", ["tracking.enabled=false", *args.overrides])
    cfg = params.world
    jobs = sample_jobs(cfg)
    timed = timed_jobs(jobs, cfg, args.samples, args.chunk)
    part_job = jobs[min(cfg.samples_per_scene // 2, len(jobs) - 1)]  # mid-scene
    with tempfile.TemporaryDirectory(prefix="bench_world_") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        render_sample(*jobs[0], cfg, root / "warmup", 1)
        warmup = time.perf_counter() - t0
        load = os.getloadavg()[0]
        pool = throughput(timed, cfg, root / "pool", args.workers, args.chunk)
        _, setup_cpu = scene_setup(part_job[0], cfg)
        c0 = time.process_time()
        render_sample(*part_job, cfg, root / "sequential", 1)
        sequential_cpu = time.process_time() - c0
        cpu_parts, wall_parts, estimates = breakdown(*part_job, cfg, root / "parts")
        reproduced = same_files(root / "sequential", root / "parts")
    n = len(timed)
    amortised = setup_cpu / cfg.samples_per_scene
    parts = {"scene setup (layout, BVHs, sun grid) / samples per scene": amortised, **cpu_parts}
    num_samples = len(jobs)
    cores = min(args.workers, os.cpu_count() or 1)
    cameras = make_cameras(cfg.camera.image_scale)
    report = {
        "benchmark": "world generation per keyframe sample",
        "samples": n,
        "workers": args.workers,
        "threads_per_worker": 1,
        "samples_per_task": args.chunk,
        "wall_seconds": pool["wall"],
        "seconds_per_sample": pool["wall"] / n,
        "cpu_seconds_per_sample": pool["cpu"] / n,  # worker processes: start-up, warm-up and scene set-up included
        "task_cpu_seconds_per_sample": pool["task_cpu"] / n,
        "load_average_before": load,  # > 0 when other processes compete for the cores
        "target_cpu_seconds_per_sample": TARGET_CPU_SECONDS,
        "pass": pool["task_cpu"] / n <= TARGET_CPU_SECONDS,
        "projected_world_minutes": num_samples * (pool["task_cpu"] / n) / cores / 60.0,
        "world_samples": num_samples,
        "sequential_cpu_seconds_one_sample": sequential_cpu,
        "scene_setup_cpu_seconds": setup_cpu,
        "warmup_seconds": warmup,
        "breakdown_cpu_seconds": parts,
        "breakdown_wall_seconds": wall_parts,
        "breakdown_total_cpu_seconds": sum(parts.values()),
        "camera_pass_estimates_cpu_seconds": {
            "shadow rays": parts["camera pass (shading, shadows, noise, sRGB)"]
            - estimates["camera pass without shadow rays"],
            "noise": parts["camera pass (shading, shadows, noise, sRGB)"] - estimates["camera pass without noise"]},
        "breakdown_reproduces_render_sample": reproduced,
        "peak_rss_mib": peak_rss_mib(),
        "peak_rss_mib_worker": peak_rss_mib(resource.RUSAGE_CHILDREN),
        "workload": {"samples_per_scene": cfg.samples_per_scene, "lidar_sweeps": cfg.sweeps_per_sample + 1,
                     "lidar_beams_per_sweep": len(firing_pattern(cfg).ring), "cameras": len(cameras),
                     "image_width_height": [cameras[0].width, cameras[0].height]},
        "machine": machine(),
    }
    print(f"world generation: {report['task_cpu_seconds_per_sample']:.2f} CPU-s/sample in the tasks "
          f"({report['cpu_seconds_per_sample']:.2f} with worker start-up and warm-up), "
          f"{report['seconds_per_sample']:.2f} s/sample "
          f"wall over {n} samples, {args.workers} worker processes, {args.chunk} samples per task  (target "
          f"{TARGET_CPU_SECONDS:.1f} CPU-s: {'PASS' if report['pass'] else 'FAIL'}); the {num_samples}-sample world: "
          f"~{report['projected_world_minutes']:.1f} min on {cores} cores")
    print(f"one sample sequentially: {sequential_cpu:.2f} CPU-s; scene set-up {setup_cpu:.2f} CPU-s once per scene "
          f"and worker; warm-up {warmup:.1f} s; peak RSS {report['peak_rss_mib']:.0f} MiB (worker "
          f"{report['peak_rss_mib_worker']:.0f}); {report['machine']['cpu_count']} CPUs, load {load:.2f} before")
    print(f"{'part (one sample, sequential)':58s} {'CPU s':>7s} {'share':>6s}")
    total = report["breakdown_total_cpu_seconds"]
    for part, sec in parts.items():
        print(f"{part:58s} {sec:7.3f} {sec / total:6.1%}")
    print(f"{'total':58s} {total:7.3f}   (reproduces render_sample bytes: {reproduced})")
    for part, sec in report["camera_pass_estimates_cpu_seconds"].items():
        print(f"  of the camera pass, about {sec:.3f} CPU-s for {part}")
    write_json(args.out, report, indent=2)
    print(f"wrote {args.out}")
    return report


if __name__ == "__main__":
    main()
