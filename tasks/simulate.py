"""Per-chunk task of the `simulate` stage."""

from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.sensors import SensorRig
from weatheralign.simulate.observe import ObserveOptions
from weatheralign.simulate.plan import SampleJob
from weatheralign.simulate.weather_copy import DatasetRef, run_chunk


@task(name="simulate-samples", cache_policy=NO_CACHE, retries=0)
def simulate_chunk_task(dataset: DatasetRef, out_root: Path, jobs: list[SampleJob], sensors: SensorRig,
                        options: ObserveOptions, run_digest: str, jpeg_quality: int, sweeps: int,
                        lidar_twin: Path | None = None) -> list[tuple[dict, bool]]:
    """Simulate consecutive keyframe samples of one scene (LiDAR keyframe and sweeps, six cameras) of the weather
    copy, or pick up finished ones; the worker process opens the dataset itself (nothing large is shipped). An
    unaligned copy takes the LiDAR files of its aligned twin at ``lidar_twin`` where they match."""
    return run_chunk(dataset, out_root, jobs, sensors, options, run_digest, jpeg_quality, sweeps, lidar_twin)
