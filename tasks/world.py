"""Per-chunk task of the `world` stage."""

from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.config import WorldConfig
from weatheralign.world.build import SampleResult, SceneSpec
from weatheralign.world.dataset import render_or_resume


@task(name="render-samples", cache_policy=NO_CACHE, retries=0)
def render_samples_task(jobs: list[tuple[SceneSpec, int]], cfg: WorldConfig, dataroot: Path,
                        nthreads: int) -> list[tuple[SampleResult, bool]]:
    """Render (or pick up from an interrupted run) consecutive keyframe samples, each with its sweeps and six
    cameras; one (result, rendered_now) per job."""
    return [render_or_resume(spec, k, cfg, dataroot, nthreads=nthreads) for spec, k in jobs]
