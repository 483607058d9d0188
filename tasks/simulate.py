"""Per-sample task of the `simulate` stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.config import SimulateConfig
from weatheralign.simulate import Weather, simulate_or_resume


@task(name="simulate-sample", cache_policy=NO_CACHE, retries=0)
def simulate_sample_task(nusc, src_root: Path, out_root: Path, sample_token: str, weather: Weather,
                         cfg: SimulateConfig, airlight: np.ndarray, jpeg_quality: int,
                         nthreads: int) -> tuple[dict, bool]:
    """Simulate one keyframe sample (LiDAR + six cameras) of the weather copy, or pick up a finished one."""
    return simulate_or_resume(nusc, src_root, out_root, sample_token, weather, cfg, airlight, jpeg_quality, nthreads)
