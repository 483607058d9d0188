"""Per-sample task of the `world` stage."""

from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.config import WorldConfig
from weatheralign.world.build import SampleResult, SceneSpec
from weatheralign.world.dataset import render_or_resume


@task(name="render-sample", cache_policy=NO_CACHE, retries=0)
def render_sample_task(spec: SceneSpec, sample_index: int, cfg: WorldConfig, dataroot: Path,
                       nthreads: int) -> tuple[SampleResult, bool]:
    """Render (or pick up from an interrupted run) one keyframe sample with its sweeps and six cameras."""
    return render_or_resume(spec, sample_index, cfg, dataroot, nthreads=nthreads)
