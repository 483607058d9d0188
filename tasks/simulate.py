"""Per-sample task of the `simulate` stage."""

from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.sensors import SensorRig
from weatheralign.simulate.observe import ObserveOptions
from weatheralign.simulate.plan import SampleJob
from weatheralign.simulate.weather_copy import run_sample


@task(name="simulate-sample", cache_policy=NO_CACHE, retries=0)
def simulate_sample_task(nusc, src_root: Path, out_root: Path, job: SampleJob, sensors: SensorRig,
                         options: ObserveOptions, run_digest: str, jpeg_quality: int, sweeps: bool) -> tuple[dict, bool]:
    """Simulate one keyframe sample (LiDAR + six cameras) of the weather copy, or pick up a finished one."""
    return run_sample(nusc, src_root, out_root, job, sensors, options, run_digest, jpeg_quality, sweeps)
