"""Job planning of the simulate stage: which samples, with which media and airlight, in which order.

`plan_jobs` walks every scene of a nuScenes-format dataset in scene order and every sample of a scene through its
``next`` chain; each `SampleJob` carries the scene's `SceneMedia` and the scene's one airlight (`scene_airlight` of
its first sample's cameras). Flows map chunks of consecutive jobs of a scene (`chunk_jobs`) as tasks; tests call the
same functions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.fog import estimate_airlight
from weatheralign.data.nuscenes import load_frame
from weatheralign.simulate.media import ConditionMedia, SceneMedia


@dataclass(frozen=True)
class SampleJob:
    """One keyframe sample to simulate: its ``sample_token``, the scene's ``media`` and ``airlight`` (3,) sRGB."""

    sample_token: str
    media: SceneMedia
    airlight: tuple[float, float, float]


def scene_airlight(nusc, sample_token: str) -> NDArray[np.float64]:
    """One airlight for a scene from the cameras of ``sample_token`` (its first sample): `estimate_airlight` over the
    images and the exact range maps where the dataset has them (sky pixels), a neutral grey."""
    views = list(load_frame(nusc, sample_token).cameras.values())
    return estimate_airlight([v.load_image() for v in views], [v.load_range() if v.range_path else None for v in views])


def plan_jobs(nusc, media: ConditionMedia, aligned: bool, rain_appearance: str = "rain",
              max_samples: int = 0) -> list[SampleJob]:
    """Every keyframe sample of the dataset (scene order, then ``next``), at most ``max_samples`` (0 = all)."""
    jobs: list[SampleJob] = []
    for scene in nusc.scene:
        if max_samples and len(jobs) >= max_samples:
            break
        scene_media = media.for_scene(scene["name"], aligned, rain_appearance)
        airlight = tuple(float(a) for a in scene_airlight(nusc, scene["first_sample_token"]))
        token = scene["first_sample_token"]
        while token:
            jobs.append(SampleJob(token, scene_media, airlight))
            token = nusc.get("sample", token)["next"]
    return jobs[:max_samples] if max_samples else jobs


def chunk_jobs(jobs: list[SampleJob], size: int) -> list[list[SampleJob]]:
    """``jobs`` in order, cut into runs of at most ``size`` consecutive jobs of the same scene (one task each)."""
    if size < 1:
        raise ValueError(f"chunk size must be >= 1, got {size}")
    chunks: list[list[SampleJob]] = []
    for job in jobs:
        if chunks and len(chunks[-1]) < size and chunks[-1][-1].media is job.media:
            chunks[-1].append(job)
        else:
            chunks.append([job])
    return chunks


__all__ = ["SampleJob", "chunk_jobs", "plan_jobs", "scene_airlight"]
