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

from weatheralign.camera.depth import camera_range_map, consistent_sky
from weatheralign.camera.fog import estimate_airlight
from weatheralign.data.frame import Frame
from weatheralign.data.nuscenes import load_frame, load_lidar
from weatheralign.sensors import EgoBody
from weatheralign.simulate.media import ConditionMedia, SceneMedia

DEPTH_SWEEPS = 3
"""LiDAR scans aggregated for the cameras' dense depth where the dataset has no exact range maps (real data): the
keyframe and its 2 earlier sweeps (`load_lidar` counts the keyframe; nuScenes: 3 HDL-32E sweeps cover ~2 % of an
image). Not all the sweeps a keyframe has: on 8 x 6 cameras of the synthetic world (exact depth, ego body masked)
AbsRel is 0.029 with 1 scan, 0.028 with 2, 0.029 with 3, 0.035 with 5 and 0.047 with 10, since older sweeps add
moving objects' ghosts and parallax faster than they fill gaps (2 and 3 are equal within the sampling noise)."""


@dataclass(frozen=True)
class SampleJob:
    """One keyframe sample to simulate: its ``sample_token``, the scene's ``media`` and ``airlight`` (3,) sRGB."""

    sample_token: str
    media: SceneMedia
    airlight: tuple[float, float, float]


def sample_range_maps(nusc, frame: Frame, images: dict[str, NDArray[np.uint8]],
                      ego_body: EgoBody | None = None) -> dict[str, NDArray[np.float32]]:
    """Per camera of ``frame`` its (H, W) float32 ray length [m] (inf = sky): the exact range map where the dataset
    stores one (the synthetic world, whose cameras render ``ego_body`` already), else
    `weatheralign.camera.depth.camera_range_map` from `DEPTH_SWEEPS` scans, the keyframe and earlier sweeps (real data)
    with the sky neighbouring cameras agree on (`consistent_sky`), nearer where a pixel's ray meets the ego's own
    body (`EgoBody.camera_ranges`: the LiDAR never sees it, so the completion would give it the far scene's depth or
    sky, and fog or particles would be drawn on the car)."""
    exact = all(v.range_path is not None for v in frame.cameras.values())
    depth_lidar = frame.lidar if exact else load_lidar(nusc, nusc.get("sample", frame.token)["data"]["LIDAR_TOP"],
                                                       DEPTH_SWEEPS)
    ranges = {ch: camera_range_map(v, depth_lidar, images[ch]) for ch, v in frame.cameras.items()}
    if exact:
        return ranges
    ranges = consistent_sky(frame.cameras, ranges)
    if ego_body is None:
        return ranges
    return {ch: np.minimum(r, ego_body.camera_ranges(frame.cameras[ch].K, frame.cameras[ch].T_ego_cam, r.shape[1],
                                                     r.shape[0])) for ch, r in ranges.items()}


def scene_airlight(nusc, sample_token: str) -> NDArray[np.float64]:
    """One airlight for a scene from the cameras of ``sample_token`` (its first sample): `estimate_airlight` over the
    images and their sky pixels (the exact range maps where the dataset has them, else the dense depth from the
    LiDAR, `sample_range_maps`), a neutral grey."""
    frame = load_frame(nusc, sample_token)
    images = {ch: v.load_image() for ch, v in frame.cameras.items()}
    ranges = sample_range_maps(nusc, frame, images)
    return estimate_airlight(list(images.values()), [ranges[ch] for ch in images])


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
