"""Per-frame task of the `reference` stage."""

from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.config import ReferenceConfig
from weatheralign.reference.synthetic import FrameRecord, FrameSpec, render_or_resume


@task(name="render-reference-frame", cache_policy=NO_CACHE, retries=0)
def render_reference_frame_task(spec: FrameSpec, cfg: ReferenceConfig, data: Path,
                                nthreads: int) -> tuple[FrameRecord, bool]:
    """Render (or pick up from an earlier run) one frame of the synthetic reference: HDL-64-like scan, stereo-left
    image and its exact range map, through the level's hidden fog."""
    return render_or_resume(spec, cfg, data, nthreads=nthreads)
